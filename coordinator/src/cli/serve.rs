//! `coordinator serve`: a long-running coordinator for a farm of separate workers.

use std::io::{IsTerminal, Write};
use std::net::SocketAddr;
use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Duration;

use clap::builder::FalseyValueParser;
use clap::Args;

use crate::clock::SystemClock;
use crate::config::{ConnectionLimits, FarmConfig, Limits};
use crate::farm::Farm;

#[derive(Args, Debug)]
pub struct ServeArgs {
    /// Read flags from the `[serve]` table of this TOML file; a flag given on the command line
    /// or in its TESSERA_* variable wins over the file.
    #[arg(long, env = "TESSERA_CONFIG")]
    pub config: Option<PathBuf>,
    /// Address to listen on (port 0 picks a free port, printed on stdout).
    #[arg(long, default_value = "127.0.0.1:7878", env = "TESSERA_LISTEN")]
    pub listen: String,
    /// Where jobs, assets, tiles and images are kept; a restart on the same dir resumes.
    #[arg(long, default_value = "tessera-data", env = "TESSERA_DATA_DIR")]
    pub data_dir: PathBuf,
    /// Require `Authorization: Bearer <token>` on every API call.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// A second bearer token that `/metrics` accepts besides --token, and nothing else does: give
    /// it to scrapers (Prometheus, KEDA) instead of the token that submits jobs.
    #[arg(long, env = "TESSERA_METRICS_TOKEN", hide_env_values = true)]
    pub metrics_token: Option<String>,
    /// Also serve `/metrics`, without any token, on this address (e.g. 0.0.0.0:9464, reached
    /// only by the scrapers' network); its actual address is printed as `metrics on http://…`.
    #[arg(long, env = "TESSERA_METRICS_LISTEN")]
    pub metrics_listen: Option<String>,
    /// Allow a non-loopback listen address without a token.
    #[arg(long, env = "TESSERA_INSECURE", value_parser = FalseyValueParser::new())]
    pub insecure: bool,
    /// Seconds without a heartbeat before a worker's tile is requeued.
    #[arg(long, default_value_t = 5.0, env = "TESSERA_LEASE_TIMEOUT")]
    pub lease_timeout: f64,
    /// Seconds between worker heartbeats (and so how fast a cancel reaches them).
    #[arg(long, default_value_t = 1.0, env = "TESSERA_HEARTBEAT")]
    pub heartbeat: f64,
    /// Seconds that leases granted before a restart stay valid after it.
    #[arg(long, default_value_t = 15.0, env = "TESSERA_RESTART_GRACE")]
    pub restart_grace: f64,
    /// Never hand idle workers copies of slow tiles.
    #[arg(long, env = "TESSERA_NO_STRAGGLERS", value_parser = FalseyValueParser::new())]
    pub no_stragglers: bool,
    /// Largest submission, in MiB.
    #[arg(long, default_value_t = 256, env = "TESSERA_MAX_UPLOAD_MIB")]
    pub max_upload_mib: usize,
    /// Largest width or height.
    #[arg(long, default_value_t = Limits::default().max_dimension, env = "TESSERA_MAX_DIMENSION")]
    pub max_dimension: u32,
    /// Largest samples per pixel.
    #[arg(long, default_value_t = Limits::default().max_spp, env = "TESSERA_MAX_SPP")]
    pub max_spp: u32,
    /// Largest ray depth.
    #[arg(long, default_value_t = Limits::default().max_depth, env = "TESSERA_MAX_DEPTH")]
    pub max_depth: u32,
    /// Most tiles in one job, every frame counted (frames × tiles per frame).
    #[arg(long, default_value_t = Limits::default().max_job_tiles, env = "TESSERA_MAX_JOB_TILES")]
    pub max_job_tiles: u64,
    /// Most worker identities kept; registering beyond it forgets the longest-silent idle one.
    #[arg(long, default_value_t = FarmConfig::default().max_workers, env = "TESSERA_MAX_WORKERS")]
    pub max_workers: usize,
    /// Decoded pixels of all a scene's textures together (each PNG's header is read before
    /// it is decoded).
    #[arg(long, default_value_t = Limits::default().max_texture_pixels, env = "TESSERA_MAX_TEXTURE_PIXELS")]
    pub max_texture_pixels: u64,
    /// Primitives in one scene: spheres, triangles, and each distinct mesh's triangles (also
    /// bounds the XML elements a scene file may hold).
    #[arg(long, default_value_t = Limits::default().max_scene_primitives, env = "TESSERA_MAX_SCENE_PRIMITIVES")]
    pub max_scene_primitives: u64,
    /// Seconds a client has to send a complete request head, from connecting or from the
    /// first byte of a later request; slower connections are closed.
    #[arg(long, default_value_t = ConnectionLimits::default().header_timeout.as_secs_f64(), env = "TESSERA_HEADER_TIMEOUT")]
    pub header_timeout: f64,
    /// Seconds a kept-alive connection may sit idle between requests before it is closed;
    /// also the longest pause in a submission's upload (then 408).
    #[arg(long, default_value_t = ConnectionLimits::default().idle_timeout.as_secs_f64(), env = "TESSERA_IDLE_TIMEOUT")]
    pub idle_timeout: f64,
    /// Connections served at once (kept below three quarters of the descriptor limit);
    /// further clients wait to be accepted.
    #[arg(long, default_value_t = ConnectionLimits::default().max_connections, env = "TESSERA_MAX_CONNECTIONS")]
    pub max_connections: usize,
    /// Submissions, resubmits and camera reads that may load a scene at once; further ones
    /// wait their turn before their upload is read.
    #[arg(long, default_value_t = ConnectionLimits::default().max_scene_builds, env = "TESSERA_MAX_SCENE_BUILDS")]
    pub max_scene_builds: usize,
}

fn secs(v: f64, what: &str) -> Result<Duration, String> {
    if v.is_finite() && v > 0.0 {
        Ok(Duration::from_secs_f64(v))
    } else {
        Err(format!("--{what} must be a positive number of seconds"))
    }
}

fn positive(v: usize, what: &str) -> Result<usize, String> {
    if v > 0 {
        Ok(v)
    } else {
        Err(format!("--{what} must be at least 1"))
    }
}

impl ServeArgs {
    fn config(&self) -> Result<FarmConfig, String> {
        let config = FarmConfig {
            lease_timeout: secs(self.lease_timeout, "lease-timeout")?,
            heartbeat: secs(self.heartbeat, "heartbeat")?,
            restart_grace: secs(self.restart_grace, "restart-grace")?,
            stragglers: !self.no_stragglers,
            limits: Limits {
                max_upload_bytes: self.max_upload_mib.saturating_mul(1 << 20),
                max_dimension: self.max_dimension,
                max_spp: self.max_spp,
                max_depth: self.max_depth,
                max_job_tiles: self.max_job_tiles,
                max_texture_pixels: self.max_texture_pixels,
                max_scene_primitives: self.max_scene_primitives,
                ..Limits::default()
            },
            max_workers: self.max_workers.max(1),
            connections: ConnectionLimits {
                header_timeout: secs(self.header_timeout, "header-timeout")?,
                idle_timeout: secs(self.idle_timeout, "idle-timeout")?,
                max_connections: positive(self.max_connections, "max-connections")?,
                max_scene_builds: positive(self.max_scene_builds, "max-scene-builds")?,
            },
            ..FarmConfig::default()
        };
        if config.heartbeat * 2 > config.lease_timeout {
            return Err("--heartbeat must be at most half of --lease-timeout".into());
        }
        Ok(config)
    }
}

async fn resolve(listen: &str) -> Result<SocketAddr, String> {
    match tokio::net::lookup_host(listen).await.map(|mut a| a.next()) {
        Ok(Some(addr)) => Ok(addr),
        _ => Err(format!("cannot resolve the listen address {listen:?}")),
    }
}

/// `text` percent-encoded for a URL fragment (the dashboard decodes it).
fn fragment(text: &str) -> String {
    text.bytes()
        .map(|b| match b {
            b'A'..=b'Z' | b'a'..=b'z' | b'0'..=b'9' | b'-' | b'.' | b'_' | b'~' => {
                (b as char).to_string()
            }
            _ => format!("%{b:02X}"),
        })
        .collect()
}

/// Refuses to expose an unauthenticated coordinator beyond this machine.
pub fn check_exposure(addr: SocketAddr, token: Option<&str>, insecure: bool) -> Result<(), String> {
    if token.is_some_and(str::is_empty) {
        return Err("the token is empty".into());
    }
    if !addr.ip().is_loopback() && token.is_none() && !insecure {
        return Err(format!(
            "refusing to listen on {addr} without a token: a farm runs whatever it is sent. \
             Pass --token (or TESSERA_TOKEN), or --insecure on a trusted network"
        ));
    }
    Ok(())
}

pub fn run(args: ServeArgs) -> ExitCode {
    worker::init_logging("info");
    let fail = |msg: String| {
        eprintln!("coordinator: {msg}");
        ExitCode::from(2)
    };
    let config = match args.config() {
        Ok(c) => c,
        Err(e) => return fail(e),
    };
    // First: the connection cap is kept below the limit this leaves.
    let descriptors = crate::server::raise_descriptor_limit();
    let runtime = match super::runtime() {
        Ok(rt) => rt,
        Err(e) => return fail(e),
    };
    runtime.block_on(async move {
        let addr = match resolve(&args.listen).await {
            Ok(addr) => addr,
            Err(e) => return fail(e),
        };
        if let Err(e) = check_exposure(addr, args.token.as_deref(), args.insecure) {
            return fail(e);
        }
        if args.metrics_token.as_deref().is_some_and(str::is_empty) {
            return fail("the metrics token is empty".into());
        }
        let metrics_addr = match &args.metrics_listen {
            Some(listen) => match resolve(listen).await {
                Ok(addr) => Some(addr),
                Err(e) => return fail(e),
            },
            None => None,
        };
        let farm = match Farm::open(&args.data_dir, config, Arc::new(SystemClock)) {
            Ok(f) => f,
            Err(e) => return fail(format!("opening {}: {e}", args.data_dir.display())),
        };
        let listener = match tokio::net::TcpListener::bind(addr).await {
            Ok(l) => l,
            Err(e) => return fail(format!("cannot listen on {addr}: {e}")),
        };
        let metrics_listener = match metrics_addr {
            Some(addr) => match tokio::net::TcpListener::bind(addr).await {
                Ok(l) => Some(l),
                Err(e) => return fail(format!("cannot listen on {addr} for metrics: {e}")),
            },
            None => None,
        };
        let local = listener
            .local_addr()
            .map(|a| a.to_string())
            .unwrap_or_default();
        // Scripts and tests read the address (port 0 picks one) from the first line. A reader
        // may close the pipe after it: a failed write must not stop the server.
        let mut out = std::io::stdout().lock();
        let _ = writeln!(out, "listening on http://{local}");
        // The fragment hands the page the token without sending it to the server; only on a
        // terminal, so that service logs (journald, kubectl logs) never record the token.
        match args.token.as_deref().filter(|_| out.is_terminal()) {
            Some(t) => writeln!(out, "dashboard: http://{local}/#token={}", fragment(t)),
            None => writeln!(out, "dashboard: http://{local}/"),
        }
        .ok();
        if let Some(l) = &metrics_listener {
            if let Ok(a) = l.local_addr() {
                let _ = writeln!(out, "metrics on http://{a}/metrics (no token)");
            }
        }
        let _ = out.flush();
        drop(out);
        if let Some(n) = descriptors {
            tracing::debug!("descriptor limit {n}");
        }
        tracing::info!(
            "coordinator {} on http://{local}, data in {}{}",
            env!("CARGO_PKG_VERSION"),
            args.data_dir.display(),
            if args.token.is_some() {
                ", token required"
            } else {
                ""
            }
        );
        // One stop signal ends both listeners.
        let (stop_tx, mut stop_rx) = tokio::sync::watch::channel(false);
        let metrics_task = metrics_listener.map(|l| {
            let mut stop = stop_rx.clone();
            tokio::spawn(crate::server::serve_metrics(l, farm.clone(), async move {
                let _ = stop.wait_for(|s| *s).await;
            }))
        });
        tokio::spawn(async move {
            super::stop_signal().await;
            let _ = stop_tx.send(true);
        });
        let auth = crate::api::Auth {
            token: args.token,
            metrics_token: args.metrics_token,
        };
        let served = crate::server::serve_with(listener, farm, auth, async move {
            let _ = stop_rx.wait_for(|s| *s).await;
        })
        .await;
        if let Some(task) = metrics_task {
            let _ = task.await;
        }
        match served {
            Ok(()) => {
                tracing::info!("stopped");
                ExitCode::SUCCESS
            }
            Err(e) => fail(format!("serving: {e}")),
        }
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn only_loopback_may_go_without_a_token() {
        let lo: SocketAddr = "127.0.0.1:1".parse().unwrap();
        let any: SocketAddr = "0.0.0.0:1".parse().unwrap();
        let v6: SocketAddr = "[::1]:1".parse().unwrap();
        assert!(check_exposure(lo, None, false).is_ok());
        assert!(check_exposure(v6, None, false).is_ok());
        assert!(check_exposure(any, None, false)
            .unwrap_err()
            .contains("--token"));
        assert!(check_exposure(any, Some("t"), false).is_ok());
        assert!(check_exposure(any, None, true).is_ok());
        assert!(check_exposure(lo, Some(""), false).is_err());
    }

    /// Held by the tests that set a TESSERA_* variable or parse defaults that one could change.
    static ENV: std::sync::Mutex<()> = std::sync::Mutex::new(());

    /// `coordinator ARGV` with the `[serve]` flags of `file` (TOML text) joined, parsed.
    fn serve_with_file(argv: &[&str], file: &str) -> Result<ServeArgs, String> {
        use clap::{CommandFactory, Parser};
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("farm.toml");
        std::fs::write(&path, file).unwrap();
        let mut argv: Vec<std::ffi::OsString> = argv.iter().map(Into::into).collect();
        argv.extend(["--config".into(), path.into_os_string()]);
        let argv = worker::config_file::with_file_flags(
            &super::super::Cli::command(),
            argv,
            &["serve"],
            "serve",
        )?;
        match super::super::Cli::try_parse_from(argv)
            .map_err(|e| e.to_string())?
            .command
        {
            super::super::Command::Serve(args) => Ok(args),
            other => panic!("{other:?}"),
        }
    }

    #[test]
    fn flags_beat_the_environment_which_beats_the_file_which_beats_defaults() {
        let file =
            "[serve]\nmax-spp = 64\nmax_depth = 7\nno-stragglers = true\nlease-timeout = 8\n\
                    [worker]\ncoordinator = \"http://x:1\"\n";
        let _env = ENV.lock().unwrap_or_else(|e| e.into_inner());
        // The file alone, and the defaults under it.
        let args = serve_with_file(&["coordinator", "serve"], file).unwrap();
        assert_eq!((args.max_spp, args.max_depth), (64, 7));
        assert!(args.no_stragglers);
        assert_eq!(args.lease_timeout, 8.0);
        assert_eq!(args.max_dimension, Limits::default().max_dimension);
        assert_eq!(args.listen, "127.0.0.1:7878");
        // TESSERA_MAX_DEPTH is read by this test only.
        std::env::set_var("TESSERA_MAX_DEPTH", "9");
        let env = serve_with_file(&["coordinator", "serve"], file);
        let flag = serve_with_file(
            &["coordinator", "serve", "--max-depth", "3", "--max-spp", "2"],
            file,
        );
        std::env::remove_var("TESSERA_MAX_DEPTH");
        let env = env.unwrap();
        assert_eq!((env.max_spp, env.max_depth), (64, 9));
        let flag = flag.unwrap();
        assert_eq!((flag.max_spp, flag.max_depth), (2, 3));
    }

    #[test]
    fn an_unknown_key_is_refused_with_its_name_and_file() {
        let err =
            serve_with_file(&["coordinator", "serve"], "[serve]\nmax-spps = 4\n").unwrap_err();
        assert!(err.contains("unknown key `max-spps` in [serve]"), "{err}");
        assert!(err.contains("farm.toml"), "{err}");
        // A key of the other command is unknown here.
        let err = serve_with_file(&["coordinator", "serve"], "[serve]\nthreads = 4\n").unwrap_err();
        assert!(err.contains("`threads`"), "{err}");
        // A value of the wrong type is refused like the same flag would be.
        let err = serve_with_file(&["coordinator", "serve"], "[serve]\nmax-spp = \"many\"\n")
            .unwrap_err();
        assert!(err.contains("many"), "{err}");
    }

    #[test]
    fn the_example_file_holds_every_flag_at_its_default() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../deploy/farm.example.toml");
        let file = std::fs::read_to_string(path).unwrap();
        let _env = ENV.lock().unwrap_or_else(|e| e.into_inner());
        let args = serve_with_file(&["coordinator", "serve"], &file).unwrap();
        assert_eq!(args.listen, "0.0.0.0:7878");
        let defaults = serve_with_file(&["coordinator", "serve"], "").unwrap();
        assert_eq!(
            format!("{:?}", args.config().unwrap()),
            format!("{:?}", defaults.config().unwrap())
        );
        // Every serve flag but the config file itself and the token appears in the example.
        use clap::CommandFactory;
        let cli = super::super::Cli::command();
        let serve = cli.find_subcommand("serve").unwrap();
        for arg in serve.get_arguments().filter_map(|a| a.get_long()) {
            if !["config", "help", "token"].contains(&arg) {
                assert!(
                    file.lines().any(|l| l
                        .trim_start()
                        .trim_start_matches("# ")
                        .starts_with(&format!("{arg} ="))),
                    "{arg} is missing from {path}"
                );
            }
        }
    }

    #[test]
    fn the_dashboard_fragment_carries_any_token() {
        assert_eq!(fragment("Ab9-._~"), "Ab9-._~");
        assert_eq!(fragment("a+b/c= %#é"), "a%2Bb%2Fc%3D%20%25%23%C3%A9");
    }
}
