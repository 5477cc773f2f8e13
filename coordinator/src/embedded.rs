//! An in-process farm: a coordinator on a loopback port and local workers sharing one scene
//! cache. `coordinator render` and `coordinator report` drive it over HTTP exactly as a user
//! drives a real farm, so what they measure includes the farm's own overhead.

use std::path::PathBuf;
use std::sync::Arc;

use protocol::client::{Client, ClientError};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use worker::{SceneCache, Shutdown, Worker, WorkerConfig, WorkerStats};

use crate::clock::SystemClock;
use crate::config::{FarmConfig, Limits};
use crate::farm::Farm;
use tracer_core::LoadLimits;

/// Tiles each local worker renders at once on its one thread pool (see `start`).
const SLOTS: usize = 2;

/// A running in-process farm. Call [`EmbeddedFarm::shutdown`] to stop it cleanly.
pub struct EmbeddedFarm {
    client: Client,
    url: String,
    token: String,
    workers: usize,
    threads: usize,
    stop_workers: tokio::sync::watch::Sender<bool>,
    worker_tasks: Vec<JoinHandle<Result<WorkerStats, ClientError>>>,
    stop_server: oneshot::Sender<()>,
    server_task: JoinHandle<std::io::Result<()>>,
    // Held so the temporary data dir lives as long as the farm.
    _temp_dir: Option<tempfile::TempDir>,
}

/// A token nobody else on the machine can guess, for the loopback coordinator.
fn local_token() -> String {
    let mut seed = format!("{:?}{}", std::time::SystemTime::now(), std::process::id());
    if let Ok(random) = std::fs::read("/proc/sys/kernel/random/uuid") {
        seed.push_str(&String::from_utf8_lossy(&random));
    }
    protocol::hash_hex(seed.as_bytes())
}

impl EmbeddedFarm {
    /// Starts a coordinator on 127.0.0.1 (any free port) with `workers` local workers sharing
    /// `threads` render threads. Without `data_dir` the farm's data lives in a temporary folder
    /// removed at shutdown.
    pub async fn start(
        data_dir: Option<PathBuf>,
        workers: usize,
        threads: usize,
    ) -> Result<Self, String> {
        let threads = threads.max(1);
        let workers = workers.clamp(1, threads);
        let temp_dir = match data_dir {
            Some(_) => None,
            None => Some(
                tempfile::Builder::new()
                    .prefix("tessera-farm-")
                    .tempdir()
                    .map_err(|e| format!("creating a temporary data dir: {e}"))?,
            ),
        };
        // Every core is already busy with a worker: straggler copies would only compete. The
        // scene is the user's own, on their own machine: it loads whatever `tracer render`
        // loads, so the scene budgets that protect a shared coordinator are lifted.
        let defaults = FarmConfig::default();
        let config = FarmConfig {
            stragglers: false,
            limits: Limits {
                max_texture_pixels: LoadLimits::UNLIMITED.max_texture_pixels,
                max_scene_primitives: LoadLimits::UNLIMITED.max_primitives,
                ..defaults.limits.clone()
            },
            ..defaults
        };
        // A farm kept in a temporary folder is deleted at exit, so its database stays in
        // memory: creating and committing a durable one cost fsyncs worth 1% of a short render.
        let farm = match (&data_dir, &temp_dir) {
            (Some(dir), _) => Farm::open(dir, config, Arc::new(SystemClock)),
            (None, Some(temp)) => Farm::open_scratch(temp.path(), config, Arc::new(SystemClock)),
            (None, None) => unreachable!("a temporary dir is made when none is given"),
        }
        .map_err(|e| e.to_string())?;
        // The workers render the scene the coordinator built to check the submission.
        let scenes = SceneCache::new();
        {
            let scenes = scenes.clone();
            farm.share_built_scenes(move |job_id, scene| scenes.insert(job_id, Arc::new(scene)));
        }
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| format!("binding a loopback port: {e}"))?;
        let url = format!(
            "http://{}",
            listener.local_addr().map_err(|e| e.to_string())?
        );
        let token = local_token();
        let (stop_server, server_stop) = oneshot::channel::<()>();
        let server_task = tokio::spawn(crate::server::serve(
            listener,
            farm,
            Some(token.clone()),
            async move {
                let _ = server_stop.await;
            },
        ));
        let client = Client::new(&url, Some(token.clone())).map_err(|e| e.to_string())?;

        let (stop_workers, shutdown) = Shutdown::new();
        let mut worker_tasks = Vec::new();
        for i in 0..workers {
            // Spread the threads: the first `threads % workers` workers get one more.
            let n = threads / workers + usize::from(i < threads % workers);
            let name = format!("local-{i}");
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .thread_name(move |k| format!("local-{i}-render-{k}"))
                .build()
                .map_err(|e| e.to_string())?;
            let pool = Arc::new(pool);
            // Each worker's pool is fed by SLOTS pull loops (each its own identity with the
            // coordinator, so each holds its own lease): while one loop sends its pixels and
            // asks for the next tile, or its tile's last rows occupy a thread or two, the
            // pool's other threads render the other loop's tile instead of waiting.
            for slot in 0..SLOTS {
                let label = match slot {
                    0 => name.clone(),
                    _ => format!("{name}.{slot}"),
                };
                let config = WorkerConfig::new(label, n);
                let worker =
                    Worker::with_pool(client.clone(), config, scenes.clone(), pool.clone());
                let shutdown = shutdown.clone();
                worker_tasks.push(tokio::spawn(async move { worker.run(shutdown).await }));
            }
        }
        Ok(Self {
            client,
            url,
            token,
            workers,
            threads,
            stop_workers,
            worker_tasks,
            stop_server,
            server_task,
            _temp_dir: temp_dir,
        })
    }

    /// A client authorised on this farm.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// The coordinator's base URL (loopback).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// The bearer token the farm demands (random per start).
    pub fn token(&self) -> &str {
        &self.token
    }

    /// How many workers run, and how many render threads they share.
    pub fn size(&self) -> (usize, usize) {
        (self.workers, self.threads)
    }

    /// Stops the workers (each finishes or hands back its tile), then the server.
    pub async fn shutdown(self) {
        let _ = self.stop_workers.send(true);
        for task in self.worker_tasks {
            let _ = task.await;
        }
        let _ = self.stop_server.send(());
        let _ = self.server_task.await;
    }
}
