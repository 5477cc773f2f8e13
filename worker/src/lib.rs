//! Tessera's farm worker. The wire types and the HTTP client it speaks live in the
//! `protocol` crate.
//!
//! - [`scenes`]: each job's scene fetched and built once, shared by in-process workers.
//! - [`run`]: the pull loop: lease, render with heartbeats, complete; back-off and hand-back.
//! - [`link`]: the coordinator as the pull loop reaches it: over HTTP, or in process.
//! - [`pass`]: what a lease renders and where it goes: pixels, or a progressive pass's sums.
//! - [`config_file`]: flags from a TOML file, below the command line and the environment.
//! - [`health`]: liveness and readiness probes over plain HTTP (`--health-listen`).

pub mod config_file;
pub mod health;
pub mod link;
pub mod pass;
pub mod run;
pub mod scenes;

pub use run::{Shutdown, Worker, WorkerConfig, WorkerStats};
pub use scenes::SceneCache;

/// The number of cores this process may use.
pub fn available_cores() -> usize {
    std::thread::available_parallelism()
        .map(|n| n.get())
        .unwrap_or(1)
}

/// Resolves on SIGINT or SIGTERM (on Ctrl-C where those cannot be watched): the one stop
/// signal the worker and the coordinator's commands wait for.
pub async fn stop_signal() {
    use tokio::signal::unix::{signal, SignalKind};
    match (
        signal(SignalKind::interrupt()),
        signal(SignalKind::terminate()),
    ) {
        (Ok(mut int), Ok(mut term)) => {
            tokio::select! {
                _ = int.recv() => {}
                _ = term.recv() => {}
            }
        }
        _ => {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

/// Logs to stderr (one line per tile for workers), `RUST_LOG` overriding `default` filter.
pub fn init_logging(default: &str) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new(default));
    let _ = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()))
        .with_target(false)
        .try_init();
}
