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
use crate::farm::{Farm, TileGrid};
use tracer_core::LoadLimits;

/// Tiles each local worker has in hand at once, rendering on its one thread pool (see
/// `start`). Two were not enough: rayon runs a tile's rows in runs of several rows that cannot
/// be stolen, so when one tile ends while the other is in its last runs, an idle thread waits
/// for the first loop's round trip; with a third tile queued in the pool it seldom does
/// (cornell_box: the render threads slept 378 ms in all with two, 171 to 189 ms with three,
/// half of it before the first tile and after the last).
const SLOTS: usize = 3;

/// The largest tile edge [`local_tile_size`] chooses.
const LOCAL_TILE_MAX: u32 = 256;

/// The tile edge `coordinator render` uses when none is asked for: the largest of
/// [`LOCAL_TILE_MAX`] and its halves, down to the farm's default, that still gives every
/// pull loop (`workers` × [`SLOTS`]) at least four tiles of each frame. Each tile costs the
/// farm's threads a lease and a completion over HTTP with its pixels copied and checked
/// (perf on cornell_box at 800×600: the async threads took 70 to 87 ms of CPU for 130 tiles
/// of 64, 37 ms for 12 of 256), CPU taken from the render threads' cores. Larger tiles cost
/// no balance since rows are stolen one by one (`Renderer::render_tile`). Progressive jobs
/// keep the default: their passes, sums and sample maps are per tile.
pub fn local_tile_size(spec: &protocol::JobSpec, workers: usize) -> u32 {
    let default = protocol::DEFAULT_TILE_SIZE;
    if spec.adaptive.is_some() {
        return default;
    }
    let loops = workers.max(1) * SLOTS;
    let (width, height) = (spec.render.width, spec.render.height);
    let tiles = |size: u32| width.div_ceil(size) as usize * height.div_ceil(size) as usize;
    let mut size = LOCAL_TILE_MAX;
    while size > default && tiles(size) < 4 * loops {
        size /= 2;
    }
    size.max(default)
}

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

/// The most a farm stores for one job of `spec` submitted with `submitted` bytes of scene and
/// assets: the blobs, every frame's tiles (f32 RGB plus a header each), and each frame's
/// linear pixels and PNG (at most 4 bytes a pixel) plus the job's image again.
pub fn scratch_bytes(spec: &protocol::JobSpec, submitted: u64) -> u64 {
    let pixels = spec.render.width as u64 * spec.render.height as u64;
    let frames = spec.frame_list().len() as u64;
    let tiles = TileGrid::new(spec).total_u64();
    submitted + frames * pixels * 12 + tiles * 16 + (frames + 1) * pixels * (12 + 4) + (1 << 20)
}

/// A temporary data dir, removed when dropped. It goes in RAM-backed `/dev/shm` when that has
/// room for twice `need` bytes and `TMPDIR` names no other place: removing the folder costs an
/// `rmdir` per directory in it (jobs, tiles, one per blob prefix...), and on this project's
/// machine (ext4 mounted with `discard`) each takes 3 to 4 ms, about 1.5% of a 3 s render
/// in all. Elsewhere, or when the estimate is unknown, the system's temporary folder.
fn temporary_data_dir(need: Option<u64>) -> Result<tempfile::TempDir, String> {
    let mut builder = tempfile::Builder::new();
    builder.prefix("tessera-farm-");
    let shm = std::path::Path::new("/dev/shm");
    let in_ram = need.is_some_and(|need| {
        std::env::var_os("TMPDIR").is_none() && free_bytes(shm).is_some_and(|free| free / 2 >= need)
    });
    if in_ram {
        if let Ok(dir) = builder.tempdir_in(shm) {
            return Ok(dir);
        }
    }
    builder
        .tempdir()
        .map_err(|e| format!("creating a temporary data dir: {e}"))
}

/// Bytes an unprivileged process may still write on the file system holding `path`.
fn free_bytes(path: &std::path::Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let path = std::ffi::CString::new(path.as_os_str().as_bytes()).ok()?;
    // SAFETY: statvfs only writes the struct it is given; all-zero is a valid value of it.
    let mut stat: libc::statvfs = unsafe { std::mem::zeroed() };
    // SAFETY: `path` is NUL-terminated and `stat` is a live, writable statvfs.
    if unsafe { libc::statvfs(path.as_ptr(), &mut stat) } != 0 {
        return None;
    }
    // The fields' types vary between platforms.
    #[allow(clippy::unnecessary_cast)]
    Some((stat.f_bavail as u64).saturating_mul(stat.f_frsize as u64))
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
    /// removed at shutdown; `scratch_bytes`, when known, is the most the farm will store there
    /// (see [`scratch_bytes`]).
    pub async fn start(
        data_dir: Option<PathBuf>,
        workers: usize,
        threads: usize,
        scratch_bytes: Option<u64>,
    ) -> Result<Self, String> {
        let threads = threads.max(1);
        let workers = workers.clamp(1, threads);
        let temp_dir = match data_dir {
            Some(_) => None,
            None => Some(temporary_data_dir(scratch_bytes)?),
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
            // pool's other threads render the other loops' tiles instead of waiting.
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_scratch_estimate_covers_tiles_images_and_blobs() {
        let mut spec = protocol::JobSpec::default();
        spec.render.width = 100;
        spec.render.height = 50;
        spec.tile_size = 32;
        let one = scratch_bytes(&spec, 1000);
        // Tiles (12 bytes a pixel and a header each), the linear image and the PNG.
        assert!(one >= 1000 + 5000 * 12 + 8 * 16 + 5000 * (12 + 4));
        spec.frames = Some(tracer_core::FrameRange { first: 0, last: 3 });
        assert!(scratch_bytes(&spec, 1000) >= 1000 + 4 * 5000 * (12 + 12 + 4));
    }

    #[test]
    fn local_tiles_are_large_while_every_pull_loop_gets_four_per_frame() {
        let mut spec = protocol::JobSpec::default();
        (spec.render.width, spec.render.height) = (800, 600);
        // 4 × 3 tiles of 256 for one worker's three loops; 7 × 5 of 128 for two workers'.
        assert_eq!(local_tile_size(&spec, 1), 256);
        assert_eq!(local_tile_size(&spec, 2), 128);
        assert_eq!(local_tile_size(&spec, 3), protocol::DEFAULT_TILE_SIZE);
        (spec.render.width, spec.render.height) = (200, 150);
        assert_eq!(local_tile_size(&spec, 1), protocol::DEFAULT_TILE_SIZE);
        (spec.render.width, spec.render.height) = (800, 600);
        spec.adaptive = Some(protocol::AdaptiveSpec::default());
        assert_eq!(local_tile_size(&spec, 1), protocol::DEFAULT_TILE_SIZE);
    }

    #[test]
    fn without_an_estimate_or_room_in_memory_the_data_dir_is_the_systems_temporary_one() {
        let temp = std::env::temp_dir();
        for need in [None, Some(u64::MAX / 2)] {
            let dir = temporary_data_dir(need).unwrap();
            assert!(dir.path().starts_with(&temp), "{:?}", dir.path());
        }
    }
}
