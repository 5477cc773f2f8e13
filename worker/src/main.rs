//! `worker --coordinator URL [--token T] [--threads N] [--name NAME] [--config farm.toml]`:
//! pulls tiles until told to stop (SIGINT or SIGTERM), then hands its tile back and exits.
//! Every flag may also come from its TESSERA_* variable or the file's `[worker]` table.

use std::process::ExitCode;
use std::time::Duration;

use clap::{CommandFactory, Parser};
use protocol::client::Client;
use worker::{available_cores, SceneCache, Shutdown, Worker, WorkerConfig};

/// Every allocation on cache lines of its own: no false sharing between render threads
/// (see [`tracer_core::alloc`]).
#[global_allocator]
static ALLOC: tracer_core::alloc::OwnLines = tracer_core::alloc::OwnLines;

#[derive(Parser, Debug)]
#[command(
    name = "worker",
    version,
    about = "Tessera farm worker: renders tiles for a coordinator"
)]
struct Args {
    /// Read flags from the `[worker]` table of this TOML file; a flag given on the command
    /// line or in its TESSERA_* variable wins over the file.
    #[arg(long, env = "TESSERA_CONFIG")]
    config: Option<std::path::PathBuf>,
    /// The coordinator's URL, such as http://10.0.0.5:7878.
    #[arg(long, env = "TESSERA_COORDINATOR")]
    coordinator: String,
    /// The coordinator's bearer token.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true)]
    token: Option<String>,
    /// Render threads [default: every core].
    #[arg(long, env = "TESSERA_THREADS")]
    threads: Option<usize>,
    /// A label for listings and logs [default: host-pid]; the coordinator issues the identity.
    #[arg(long, env = "TESSERA_WORKER_NAME")]
    name: Option<String>,
    /// Longest pause between retries while the coordinator is unreachable, in seconds.
    #[arg(long, default_value_t = 5.0, env = "TESSERA_MAX_BACKOFF")]
    max_backoff: f64,
    /// Serve liveness (GET /livez) and readiness (GET /readyz) probes on this address.
    #[arg(long, env = "TESSERA_HEALTH_LISTEN")]
    health_listen: Option<String>,
}

fn main() -> ExitCode {
    let argv = std::env::args_os().collect();
    let argv = match worker::config_file::with_file_flags(&Args::command(), argv, &[], "worker") {
        Ok(argv) => argv,
        Err(e) => {
            eprintln!("worker: {e}");
            return ExitCode::from(2);
        }
    };
    let args = Args::parse_from(argv);
    worker::init_logging("info");
    let threads = args.threads.unwrap_or_else(available_cores).max(1);
    let name = args.name.unwrap_or_else(worker::run::default_name);
    let runtime = match tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
    {
        Ok(rt) => rt,
        Err(e) => {
            eprintln!("worker: cannot start the async runtime: {e}");
            return ExitCode::from(2);
        }
    };
    runtime.block_on(async move {
        let client = match Client::new(&args.coordinator, args.token) {
            Ok(c) => c,
            Err(e) => {
                eprintln!("worker: {e}");
                return ExitCode::from(2);
            }
        };
        if let Some(addr) = &args.health_listen {
            match tokio::net::TcpListener::bind(addr).await {
                Ok(listener) => {
                    tokio::spawn(worker::health::serve(listener, client.clone()));
                }
                Err(e) => {
                    eprintln!("worker: cannot listen on {addr} for health probes: {e}");
                    return ExitCode::from(2);
                }
            }
        }
        let mut config = WorkerConfig::new(name.clone(), threads);
        config.max_backoff = Duration::from_secs_f64(args.max_backoff.max(0.1));
        let worker = match Worker::new(client, config, SceneCache::new()) {
            Ok(w) => w,
            Err(e) => {
                eprintln!("worker: {e}");
                return ExitCode::from(2);
            }
        };
        let (stop, shutdown) = Shutdown::new();
        tokio::spawn(async move {
            worker::stop_signal().await;
            tracing::info!("stopping: handing back the current tile");
            let _ = stop.send(true);
            // A second signal means "now".
            worker::stop_signal().await;
            std::process::exit(130);
        });
        tracing::info!(
            "worker {name} with {threads} threads, coordinator {}",
            args.coordinator
        );
        match worker.run(shutdown).await {
            Ok(stats) => {
                tracing::info!(
                    "stopped: {} tiles rendered, {} failed, {} dropped, {} handed back",
                    stats.rendered,
                    stats.failed,
                    stats.dropped,
                    stats.handed_back
                );
                ExitCode::SUCCESS
            }
            Err(e) => {
                eprintln!("worker: {e}");
                ExitCode::from(1)
            }
        }
    })
}
