//! Tessera's farm worker. The wire types and the HTTP client it speaks live in the
//! `protocol` crate.
//!
//! - [`scenes`]: each job's scene fetched and built once, shared by in-process workers.
//! - [`run`]: the pull loop: lease, render with heartbeats, complete; back-off and hand-back.

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
