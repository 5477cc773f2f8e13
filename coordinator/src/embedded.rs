//! An in-process farm: a coordinator on a loopback port and local workers sharing one scene
//! cache. `coordinator report` submits to it over HTTP as a user submits to a real farm;
//! `coordinator render` submits in process ([`EmbeddedFarm::submit`]) through the route's
//! checks. The workers register, lease, read pass sums and deliver their tiles in process
//! ([`InProcess`]), through the same code the routes run, so what the commands measure
//! includes the farm's own scheduling, storage and assembly; heartbeats, failures and
//! hand-backs go over HTTP like a remote worker's.

use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

use axum::http::StatusCode;
use protocol::client::{Bytes, Client, ClientError};
use protocol::{Completion, Lease, LeaseRequest, WorkerIdentity};
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use worker::link::{Answer, Link};
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

/// The local workers' link to the farm: registration, leases, pass sums and rendered tiles
/// handled in memory by the same code the routes run (validation, storage, the commit wait),
/// with the errors the routes' answers would give.
struct InProcess {
    farm: Arc<Farm>,
    /// Completions handed over, accepted or not.
    handed: AtomicU64,
}

impl Link for InProcess {
    fn register<'a>(&'a self, name: &'a str) -> Answer<'a, WorkerIdentity> {
        let registered = self.farm.register_worker(name);
        if let Ok(identity) = &registered {
            // Listed where a remote worker shows its peer address.
            self.farm
                .worker_address(identity.worker_id, "in process".into());
        }
        Box::pin(async move { registered.map_err(|e| answer(e.into())) })
    }

    fn lease(&self, req: LeaseRequest) -> Answer<'_, Option<Lease>> {
        Box::pin(async move {
            crate::api::wait_for_lease(&self.farm, &req)
                .await
                .map_err(|failure| match failure.0 {
                    // What the HTTP client makes of the route's 404: register again.
                    StatusCode::NOT_FOUND => ClientError::UnknownWorker(failure.1.error),
                    _ => answer(failure),
                })
        })
    }

    fn sums(&self, lease_id: u64) -> Answer<'_, Vec<u8>> {
        let sums = crate::api::read_sums(&self.farm, lease_id);
        Box::pin(async move { sums.map_err(answer) })
    }

    fn complete(&self, lease_id: u64, bytes: Bytes, pass: bool) -> Answer<'_, Completion> {
        self.handed.fetch_add(1, Ordering::Relaxed);
        Box::pin(async move {
            let stored = if pass {
                crate::api::store_sums(&self.farm, lease_id, bytes).await
            } else {
                crate::api::store_pixels(&self.farm, lease_id, bytes).await
            };
            stored.map_err(answer)
        })
    }
}

/// A route's refusal as the HTTP client would report its answer.
fn answer(crate::api::Failure(status, body): crate::api::Failure) -> ClientError {
    ClientError::from_answer(status.as_u16(), body)
}

/// A running in-process farm. Call [`EmbeddedFarm::shutdown`] to stop it cleanly.
pub struct EmbeddedFarm {
    farm: Arc<Farm>,
    link: Arc<InProcess>,
    client: Client,
    url: String,
    token: String,
    workers: usize,
    threads: usize,
    stop_workers: tokio::sync::watch::Sender<bool>,
    worker_tasks: Vec<JoinHandle<Result<WorkerStats, ClientError>>>,
    stop_server: oneshot::Sender<()>,
    server_task: JoinHandle<std::io::Result<()>>,
    // Held so a temporary data dir lives as long as the farm.
    _temp_dir: Option<tempfile::TempDir>,
    /// Neither a data dir nor a temporary folder: see [`EmbeddedFarm::in_memory`].
    in_memory: bool,
}

/// Where a farm without `--data-dir` keeps its files.
enum Scratch {
    /// In this process's memory ([`Farm::open_in_memory`]).
    Memory,
    /// In a temporary folder, removed when the farm stops.
    Folder(tempfile::TempDir),
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

/// Where a farm without a data dir keeps its files: in memory when the machine has room for
/// twice `need` bytes (the most the job stores, [`scratch_bytes`]), else — or when the
/// estimate is unknown — in a temporary folder in the system's temporary directory.
///
/// In memory, nothing is written to a file and read back: on this project's machine, storing
/// the tiles in a tmpfs folder, reading them back to assemble an 800×600 image and storing its
/// linear pixels and PNG took 15 to 18 ms after the last tile (the PNG's encoding aside), and
/// removing a folder on disk costs an `rmdir` per directory (3 to 4 ms each on its ext4).
fn scratch_store(need: Option<u64>) -> Result<Scratch, String> {
    if need.is_some_and(|need| available_memory().is_some_and(|free| free / 2 >= need)) {
        return Ok(Scratch::Memory);
    }
    tempfile::Builder::new()
        .prefix("tessera-farm-")
        .tempdir()
        .map(Scratch::Folder)
        .map_err(|e| format!("creating a temporary data dir: {e}"))
}

/// The memory the kernel estimates is available to start new work without swapping
/// (`MemAvailable`), in bytes; `None` where it does not say.
fn available_memory() -> Option<u64> {
    let meminfo = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = meminfo.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib.saturating_mul(1024))
}

/// The CPUs this process may run on, in order; empty where that cannot be read.
fn allowed_cpus() -> Vec<usize> {
    // SAFETY: `cpu_set_t` is plain data (all zeroes is the empty set), and the size passed is
    // the size of the set written.
    unsafe {
        let mut allowed: libc::cpu_set_t = std::mem::zeroed();
        if libc::sched_getaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &mut allowed) != 0 {
            return Vec::new();
        }
        (0..libc::CPU_SETSIZE as usize)
            .filter(|&cpu| libc::CPU_ISSET(cpu, &allowed))
            .collect()
    }
}

/// Keeps the calling thread on `cpu`. Best effort: where the kernel refuses, the thread stays
/// free to move, which renders the same bytes.
fn pin_current_thread(cpu: usize) {
    // SAFETY: as in `allowed_cpus`; `cpu` comes from the allowed set, below CPU_SETSIZE.
    unsafe {
        let mut one: libc::cpu_set_t = std::mem::zeroed();
        libc::CPU_SET(cpu, &mut one);
        if libc::sched_setaffinity(0, std::mem::size_of::<libc::cpu_set_t>(), &one) != 0 {
            tracing::debug!("could not pin a render thread to CPU {cpu}");
        }
    }
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
    /// `threads` render threads. Without `data_dir` the farm's data lives in memory, or in a
    /// temporary folder removed at shutdown; `scratch_bytes`, when known, is the most the farm
    /// will store (see [`scratch_bytes`]), and decides which.
    pub async fn start(
        data_dir: Option<PathBuf>,
        workers: usize,
        threads: usize,
        scratch_bytes: Option<u64>,
    ) -> Result<Self, String> {
        let threads = threads.max(1);
        let workers = workers.clamp(1, threads);
        let scratch = match data_dir {
            Some(_) => None,
            None => Some(scratch_store(scratch_bytes)?),
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
        let clock = Arc::new(SystemClock);
        let in_memory = matches!(scratch, Some(Scratch::Memory));
        let (farm, temp_dir) = match (&data_dir, scratch) {
            (Some(dir), _) => (Farm::open(dir, config, clock), None),
            (None, Some(Scratch::Memory)) => (Farm::open_in_memory(config, clock), None),
            (None, Some(Scratch::Folder(temp))) => {
                (Farm::open_scratch(temp.path(), config, clock), Some(temp))
            }
            (None, None) => unreachable!("a scratch store is chosen when no dir is given"),
        };
        let farm = farm.map_err(|e| e.to_string())?;
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
            farm.clone(),
            Some(token.clone()),
            async move {
                let _ = server_stop.await;
            },
        ));
        let client = Client::new(&url, Some(token.clone())).map_err(|e| e.to_string())?;

        let link = Arc::new(InProcess {
            farm: farm.clone(),
            handed: AtomicU64::new(0),
        });
        let (stop_workers, shutdown) = Shutdown::new();
        let mut worker_tasks = Vec::new();
        // With a render thread for every CPU this process may use, each thread keeps a CPU of
        // its own. Unpinned, a render thread woken for a new tile was at times placed on its
        // sibling's CPU, and the two shared it for 8 to 11 ms while the other CPU idled (perf
        // sched, 2 of 5 test.scene renders on the 2-vCPU machine); `tracer render`'s threads,
        // which never sleep mid-render, are not woken that often.
        let cpus = allowed_cpus();
        let pinned = cpus.len() == threads;
        let mut first_thread = 0;
        for i in 0..workers {
            // Spread the threads: the first `threads % workers` workers get one more.
            let n = threads / workers + usize::from(i < threads % workers);
            let name = format!("local-{i}");
            let own_cpus: Vec<usize> = match pinned {
                true => cpus[first_thread..first_thread + n].to_vec(),
                false => Vec::new(),
            };
            first_thread += n;
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(n)
                .thread_name(move |k| format!("local-{i}-render-{k}"))
                .start_handler(move |k| {
                    if let Some(&cpu) = own_cpus.get(k) {
                        pin_current_thread(cpu);
                    }
                })
                .build()
                .map_err(|e| e.to_string())?;
            let pool = Arc::new(pool);
            if i == 0 {
                farm.build_scenes_on(pool.clone());
            }
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
                    Worker::with_pool(client.clone(), config, scenes.clone(), pool.clone())
                        .with_link(link.clone() as Arc<dyn Link>);
                let shutdown = shutdown.clone();
                worker_tasks.push(tokio::spawn(async move { worker.run(shutdown).await }));
            }
        }
        Ok(Self {
            farm,
            link,
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
            in_memory,
        })
    }

    /// Submits a job without HTTP, with the checks and answers of `POST /jobs` (see
    /// `api::submit_in_process`): the farm is in this process, and so are the submission's
    /// bytes.
    pub async fn submit(
        &self,
        submission: protocol::client::Submission,
    ) -> Result<protocol::JobInfo, ClientError> {
        crate::api::submit_in_process(&self.farm, submission)
            .await
            .map_err(answer)
    }

    /// The farm itself, for what the process that runs it may read without a request: its
    /// change notifications and finished images (`coordinator render`).
    pub fn farm(&self) -> &Arc<Farm> {
        &self.farm
    }

    /// How many rendered tiles (or pass sums) the local workers handed to the farm in memory
    /// rather than over HTTP.
    pub fn handed_over(&self) -> u64 {
        self.link.handed.load(Ordering::Relaxed)
    }

    /// A client authorised on this farm.
    pub fn client(&self) -> &Client {
        &self.client
    }

    /// The coordinator's base URL (loopback).
    pub fn url(&self) -> &str {
        &self.url
    }

    /// Whether the farm keeps everything in this process's memory: no data dir, no
    /// temporary folder to remove, so a clean stop saves nothing.
    pub fn in_memory(&self) -> bool {
        self.in_memory
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

    /// The message of an answer that must be a 400.
    fn refused(answer: Result<Completion, ClientError>) -> String {
        match answer {
            Err(ClientError::Api {
                status: 400,
                message,
                ..
            }) => message,
            other => panic!("not refused with 400: {other:?}"),
        }
    }

    #[tokio::test]
    async fn the_in_process_handover_answers_as_the_routes_do() {
        let farm = Farm::open_in_memory(FarmConfig::default(), Arc::new(SystemClock)).unwrap();
        farm.submit(crate::farm::tests::new_job("handover"))
            .unwrap();
        let worker = farm.register_worker("w").unwrap().worker_id;
        let handover = InProcess {
            farm: farm.clone(),
            handed: AtomicU64::new(0),
        };
        let pixels = |value: f32, n: usize| protocol::client::pixels_body(vec![value; n]);

        let lease = farm.lease(worker).unwrap().unwrap();
        let n = lease.rect.pixel_count() * 3;
        let short = refused(
            handover
                .complete(lease.lease_id, pixels(0.5, 5), false)
                .await,
        );
        assert!(short.contains("768 bytes"), "{short}");
        let nan = refused(
            handover
                .complete(lease.lease_id, pixels(f32::NAN, n), false)
                .await,
        );
        assert!(nan.contains("non-finite"), "{nan}");
        // The NaN tile ended its lease as a failure: a late copy is stale (409).
        let late = handover
            .complete(lease.lease_id, pixels(0.5, n), false)
            .await;
        assert!(matches!(late, Err(ClientError::Stale(_))), "{late:?}");

        let lease = farm.lease(worker).unwrap().unwrap();
        let done = handover
            .complete(lease.lease_id, pixels(0.5, n), false)
            .await
            .unwrap();
        assert_eq!((done.tiles_done, done.tiles_total), (1, 4));
        assert_eq!(handover.handed.load(Ordering::Relaxed), 4);

        // Leases in process: the next tile, and an unknown worker told to register again as
        // the HTTP client tells it.
        let identity = handover.register("in-process").await.unwrap();
        let ask = |worker_id| LeaseRequest {
            worker_id,
            wait_ms: 0,
        };
        let lease = handover.lease(ask(identity.worker_id)).await.unwrap();
        let lease = lease.expect("three tiles are still queued");
        let unknown = handover.lease(ask(9999)).await;
        assert!(
            matches!(unknown, Err(ClientError::UnknownWorker(_))),
            "{unknown:?}"
        );
        // A plain tile has no pass sums: the sums route's refusal (409).
        let refusal = handover.sums(lease.lease_id).await;
        assert!(
            matches!(&refusal, Err(ClientError::Stale(why)) if why.contains("not a pass")),
            "{refusal:?}"
        );
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn local_workers_lease_and_hand_every_tile_over_in_process() {
        let scene = course("test.scene");
        let mut spec = protocol::JobSpec::default();
        (spec.render.width, spec.render.height, spec.tile_size) = (48, 32, 16);
        spec.render.spp = 1;
        let submission = crate::cli::collect_submission(&scene, spec).unwrap();
        let farm = EmbeddedFarm::start(None, 1, 2, None).await.unwrap();
        let mut events = farm.farm().subscribe();
        let job = farm.client().submit(&submission).await.unwrap();
        let info = loop {
            let info = farm.farm().job(job.id).unwrap();
            if info.state.is_finished() {
                break info;
            }
            let _ = events.recv().await;
        };
        assert_eq!(info.state, protocol::JobState::Done, "{:?}", info.error);
        assert_eq!(info.tiles_total, 6);
        assert_eq!(farm.handed_over(), 6, "every tile handed over, none posted");
        // A lease asked over HTTP would have recorded the worker's loopback address.
        let workers = farm.farm().workers();
        assert_eq!(workers.len(), SLOTS, "one identity per pull loop");
        for worker in workers {
            assert_eq!(worker.address.as_deref(), Some("in process"), "{worker:?}");
        }
        farm.shutdown().await;
    }

    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_in_process_submission_is_checked_as_the_route_checks_it() {
        let farm = EmbeddedFarm::start(None, 1, 1, None).await.unwrap();
        let mut spec = protocol::JobSpec::default();
        (spec.render.width, spec.render.height, spec.render.spp) = (16, 8, 1);
        let broken = protocol::client::Submission {
            spec: spec.clone(),
            scene_file: "broken.scene".into(),
            scene: b"<scene>\n  <camera>\n".to_vec(),
            assets: Vec::new(),
        };
        match farm.submit(broken).await {
            Err(ClientError::Api {
                status: 400, body, ..
            }) => assert_eq!(
                (body.file.as_deref(), body.line.is_some()),
                (Some("broken.scene"), true),
                "{body:?}"
            ),
            other => panic!("not refused with 400: {other:?}"),
        }
        // An asset outside the scene's folder is refused before anything is read.
        let mut outside =
            crate::cli::collect_submission(&course("test.scene"), spec.clone()).unwrap();
        outside.assets.push(("../secret".into(), b"x".to_vec()));
        assert!(matches!(
            farm.submit(outside).await,
            Err(ClientError::Api { status: 400, .. })
        ));

        let good = crate::cli::collect_submission(&course("test.scene"), spec).unwrap();
        let job = farm.submit(good).await.unwrap();
        assert_eq!(
            (job.scene_file.as_str(), job.tiles_total),
            ("test.scene", 1)
        );
        assert_eq!(farm.farm().job(job.id).unwrap().id, job.id);
        let metrics = &farm.farm().metrics;
        assert_eq!(
            (
                metrics.jobs_submitted.load(Ordering::Relaxed),
                metrics.submissions_rejected.load(Ordering::Relaxed)
            ),
            (1, 2)
        );
        farm.shutdown().await;
    }

    fn course(scene: &str) -> PathBuf {
        std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/scenes/course")
            .join(scene)
    }

    #[test]
    fn a_pinned_thread_runs_only_on_its_cpu() {
        let cpus = allowed_cpus();
        assert!(!cpus.is_empty(), "the process may run somewhere");
        let last = *cpus.last().unwrap();
        let seen = std::thread::spawn(move || {
            pin_current_thread(last);
            allowed_cpus()
        })
        .join()
        .unwrap();
        assert_eq!(seen, vec![last]);
        // The caller's own set is untouched.
        assert_eq!(allowed_cpus(), cpus);
    }

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
            match scratch_store(need).unwrap() {
                Scratch::Folder(dir) => assert!(dir.path().starts_with(&temp), "{:?}", dir.path()),
                Scratch::Memory => panic!("{need:?} bytes kept in memory"),
            }
        }
        if available_memory().is_some() {
            assert!(matches!(scratch_store(Some(1 << 20)), Ok(Scratch::Memory)));
        }
    }
}
