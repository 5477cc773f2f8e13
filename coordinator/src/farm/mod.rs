//! The farm: jobs split into tiles, leased to workers, stored, assembled.
//!
//! - [`state`]: the one state type and every transition of a tile, job, lease and worker
//!   identity, each written to SQLite in one transaction before memory changes;
//! - [`tiles`]: per-job tile bookkeeping that costs memory for what is happening (leased,
//!   requeued, failed tiles) and one bit per tile otherwise;
//! - [`leasing`], [`completion`], [`assembly`]: handing tiles out, taking results in, and
//!   turning finished tiles into PNGs (started by the state machine on a job's last tile);
//! - [`resume`]: the state rebuilt from the data dir at start-up;
//! - [`workers`]: the worker registry; [`events`]: change notifications.
//!
//! - [`progressive`]: progressive jobs' passes, their stopping rules and sums file.
//! - [`commits`]: group commit of the hot transitions (one SQLite commit for many requests).
//!
//! [`Farm`] is the front: it owns the lock, the files and the clock, and wakes long-polling
//! workers. Locking: one std `Mutex` over the state and the database connection; nothing
//! awaits while it is held, no submission parses, hashes or allocates under it, and every
//! critical section is a few map operations and at most one small SQLite transaction (or a
//! savepoint in the open batch). File I/O (tile pixels, images) happens outside it.

mod assembly;
mod commits;
mod completion;
mod events;
mod job;
mod leasing;
mod progressive;
mod resume;
mod state;
mod tiles;
mod workers;

use std::collections::BTreeMap;
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard, OnceLock, Weak};
use std::thread::JoinHandle;

use tokio::sync::{broadcast, Notify};

use protocol::{
    ApiError, Bundle, BundleFile, JobInfo, JobSpec, JobState, TileInfo, TilePage, WorkerIdentity,
    WorkerInfo, MAX_TILE_PAGE, MAX_WORKER_NAME,
};

pub use events::FarmEvent;
pub use tiles::TileGrid;

use crate::clock::Clock;
use crate::config::FarmConfig;
use crate::metrics::Metrics;
use crate::store::{Db, Files, StoreError, StoredJob};
use events::Events;
use job::Job;
use state::State;
use tiles::TileBook;
use tracer_core::Scene;

#[derive(Debug, thiserror::Error)]
pub enum FarmError {
    #[error("{0}")]
    NotFound(String),
    /// The lease is not live: expired, handed back, revoked or never granted.
    #[error("{0}")]
    Stale(String),
    /// The request conflicts with the job's state (cancelling a finished job...).
    #[error("{0}")]
    Conflict(String),
    #[error("{}", .0.error)]
    BadRequest(ApiError),
    #[error(transparent)]
    Store(#[from] StoreError),
}

pub type Result<T, E = FarmError> = std::result::Result<T, E>;

/// A validated submission, its files already stored.
#[derive(Clone, Debug)]
pub struct NewJob {
    pub name: String,
    pub scene_file: String,
    pub scene_hash: String,
    pub spec: JobSpec,
    pub assets: Vec<BundleFile>,
}

pub struct Farm {
    config: FarmConfig,
    clock: Arc<dyn Clock>,
    files: Files,
    state: Mutex<State>,
    /// Woken whenever a tile is queued.
    work: Notify,
    stopping: AtomicBool,
    epoch: u64,
    pub metrics: Metrics,
    tile_writes: AtomicU64,
    events: Events,
    commits: commits::Commits,
    /// This farm, for the assembly threads it starts.
    me: Weak<Farm>,
    assemblies: Mutex<Vec<JoinHandle<()>>>,
    /// Takes the scenes submissions build to check them ([`Farm::share_built_scenes`]).
    scene_sink: OnceLock<SceneSink>,
    /// Where submissions build their scenes ([`Farm::build_scenes_on`]).
    scene_pool: OnceLock<Arc<rayon::ThreadPool>>,
}

/// Where a submission's checked scene goes instead of being dropped: (job id, scene).
type SceneSink = Box<dyn Fn(u64, Scene) + Send + Sync>;

impl Farm {
    /// Opens (or creates) the data dir and resumes every unfinished job in it. Stored data
    /// never stops the start: a job that cannot be loaded is marked failed.
    pub fn open(data_dir: &Path, config: FarmConfig, clock: Arc<dyn Clock>) -> Result<Arc<Farm>> {
        std::fs::create_dir_all(data_dir).map_err(|e| {
            StoreError::io(format!("creating the data dir {}", data_dir.display()), e)
        })?;
        let db = Db::open(&data_dir.join("tessera.db"))?;
        let files = Files::open(data_dir)?;
        Self::with_store(db, files, config, clock)
    }

    /// A farm that lives as long as its process: the database in memory, the files in `dir`
    /// (the embedded farm's temporary folder, removed when it stops). Nothing outlives the
    /// process, so no commit waits for the disk.
    pub fn open_scratch(
        dir: &Path,
        config: FarmConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Arc<Farm>> {
        Self::with_store(Db::open_in_memory()?, Files::open(dir)?, config, clock)
    }

    /// [`Farm::open_scratch`] with its files in memory too ([`Files::in_memory`]): no folder,
    /// and nothing written or read back around the render, for a job known to fit in memory.
    pub fn open_in_memory(config: FarmConfig, clock: Arc<dyn Clock>) -> Result<Arc<Farm>> {
        Self::with_store(Db::open_in_memory()?, Files::in_memory(), config, clock)
    }

    fn with_store(
        db: Db,
        files: Files,
        config: FarmConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Arc<Farm>> {
        let epoch = db.next_epoch()?;
        let (state, finished) = resume::resume(db, &files, &config, epoch, clock.now_ms())?;
        let farm = Arc::new_cyclic(|me| Farm {
            config,
            clock,
            files,
            state: Mutex::new(state),
            work: Notify::new(),
            stopping: AtomicBool::new(false),
            epoch,
            metrics: Metrics::default(),
            tile_writes: AtomicU64::new(0),
            events: Events::default(),
            commits: commits::Commits::default(),
            me: me.clone(),
            assemblies: Mutex::new(Vec::new()),
            scene_sink: OnceLock::new(),
            scene_pool: OnceLock::new(),
        });
        // What resuming changed is stored before anything is served.
        farm.flush()?;
        // Jobs whose last tile landed just before a crash.
        for id in finished {
            farm.start_assembly(id);
        }
        Ok(farm)
    }

    /// A farm on an in-memory database and the given folder, for tests.
    pub fn for_tests(dir: &Path, config: FarmConfig, clock: Arc<dyn Clock>) -> Arc<Farm> {
        Self::with_store(
            Db::open_in_memory().unwrap(),
            Files::open(dir).unwrap(),
            config,
            clock,
        )
        .unwrap()
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // Transitions change memory only after their write succeeded, so a panic elsewhere
        // under the lock leaves nothing half-done.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    pub fn config(&self) -> &FarmConfig {
        &self.config
    }

    pub fn files(&self) -> &Files {
        &self.files
    }

    pub fn now_ms(&self) -> u64 {
        self.clock.now_ms()
    }

    /// The start-up count of this data dir (it prefixes lease ids).
    pub fn epoch(&self) -> u64 {
        self.epoch
    }

    /// How many tile pixel files this process has written (tests use it to prove that a
    /// restart did not render finished tiles again).
    pub fn tile_writes(&self) -> u64 {
        self.tile_writes.load(Ordering::Relaxed)
    }

    /// Wakes every long poll and makes them answer "no work" (server shutdown).
    pub fn stop(&self) {
        self.stopping.store(true, Ordering::SeqCst);
        self.work.notify_waiters();
        self.events.send(FarmEvent::Stopping);
    }

    pub fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::SeqCst)
    }

    /// Subscribes to change notifications (`GET /events`).
    pub fn subscribe(&self) -> broadcast::Receiver<FarmEvent> {
        self.events.subscribe()
    }

    /// Waits until work may have been queued (or the farm stops).
    pub fn work_notified(&self) -> tokio::sync::futures::Notified<'_> {
        self.work.notified()
    }

    /// Issues a worker identity; `name` is only a label.
    pub fn register_worker(&self, name: &str) -> Result<WorkerIdentity> {
        if name.is_empty() || name.len() > MAX_WORKER_NAME {
            return Err(FarmError::BadRequest(ApiError::new(format!(
                "a worker name is 1 to {MAX_WORKER_NAME} bytes"
            ))));
        }
        let now = self.now_ms();
        let identity = self.lock().register(name, now, self.config.max_workers)?;
        self.flush()?;
        tracing::info!("worker {} registered as {name}", identity.worker_id);
        Ok(identity)
    }

    /// Records the address a worker's lease request came from (for `GET /workers`).
    pub fn worker_address(&self, worker_id: u64, address: String) {
        let now = self.now_ms();
        if let Some(worker) = self.lock().workers.seen(worker_id, now) {
            worker.address = Some(address);
        }
    }

    /// Hands every scene that a submission builds to check it to `sink`, with its job id,
    /// instead of dropping it: the embedded farm's workers, in this process, then render that
    /// scene rather than fetch the bundle and build it a second time. Set once.
    pub fn share_built_scenes(&self, sink: impl Fn(u64, Scene) + Send + Sync + 'static) {
        let _ = self.scene_sink.set(Box::new(sink));
    }

    /// Builds the scenes of submissions (their BVHs are built in parallel) on `pool` rather
    /// than on rayon's global pool. The embedded farm passes its workers' render pool: a
    /// submission then starts no second set of threads, which spun for milliseconds after
    /// the build beside the render threads (1% of a 0.25 s render's CPU). Set once.
    pub fn build_scenes_on(&self, pool: Arc<rayon::ThreadPool>) {
        let _ = self.scene_pool.set(pool);
    }

    /// Runs `build` on the pool set by [`Farm::build_scenes_on`], or on this thread.
    pub fn building_scenes<T: Send>(&self, build: impl FnOnce() -> T + Send) -> T {
        match self.scene_pool.get() {
            Some(pool) => pool.install(build),
            None => build(),
        }
    }

    /// Whether a submission should keep the scene it built for [`Farm::submit_built`].
    pub fn wants_built_scenes(&self) -> bool {
        self.scene_sink.get().is_some()
    }

    /// Accepts a job. Its tile count is checked against the budget and its tile book built
    /// before the lock is taken; under the lock it is only written and inserted.
    pub fn submit(&self, new: NewJob) -> Result<JobInfo> {
        self.submit_built(new, None)
    }

    /// [`Farm::submit`], handing `scene` (the job's scene, already built) to the sink set by
    /// [`Farm::share_built_scenes`] before any worker can lease a tile of the job.
    pub fn submit_built(&self, mut new: NewJob, scene: Option<Scene>) -> Result<JobInfo> {
        progressive::normalize(&mut new.spec)?;
        let grid = TileGrid::new(&new.spec);
        self.config
            .limits
            .check_tiles(&grid)
            .map_err(|e| FarmError::BadRequest(ApiError::new(e)))?;
        let now = self.now_ms();
        let stored = StoredJob {
            id: 0,
            name: new.name,
            scene_file: new.scene_file,
            scene_hash: new.scene_hash,
            spec: new.spec,
            state: JobState::Queued,
            error: None,
            created_ms: now,
            started_ms: None,
            finished_ms: None,
            assets: new.assets,
            tiles_done: Vec::new(),
            failures: Vec::new(),
        };
        let job = Job {
            id: 0,
            name: stored.name.clone(),
            scene_file: stored.scene_file.clone(),
            scene_hash: stored.scene_hash.clone(),
            spec: stored.spec.clone(),
            state: JobState::Queued,
            error: None,
            created_ms: now,
            started_ms: None,
            finished_ms: None,
            assets: stored.assets.clone(),
            grid,
            tiles: TileBook::new(grid.total_u64() as u32),
            failures: Vec::new(),
            tile_ms_total: 0,
            tiles_timed: 0,
            assembling: false,
            progress: progressive::Progress::new(&stored.spec).map(Box::new),
        };
        let mut state = self.lock();
        let id = state.add_job(&stored, job)?;
        let info = state.job(id)?.info(now);
        // Under the lock, so no lease of the job is granted before its scene is shared (the
        // sink only stores it).
        if let (Some(scene), Some(sink)) = (scene, self.scene_sink.get()) {
            sink(id, scene);
        }
        drop(state);
        self.flush()?;
        tracing::info!(
            "job {id}: {} queued, {} tiles of at most {}x{}",
            info.name,
            info.tiles_total,
            info.spec.tile_size,
            info.spec.tile_size
        );
        self.work.notify_waiters();
        self.events.send(FarmEvent::Job(id));
        Ok(info)
    }

    pub fn cancel(&self, job_id: u64) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut state = self.lock();
        state.end_job(
            job_id,
            JobState::Cancelled,
            None,
            now,
            "the job was cancelled",
        )?;
        let info = state.job(job_id)?.info(now);
        drop(state);
        self.flush()?;
        tracing::info!("job {job_id}: cancelled");
        self.events.send(FarmEvent::Job(job_id));
        Ok(info)
    }

    /// Requeues a failed job's unfinished tiles with fresh failure counts.
    pub fn retry(&self, job_id: u64) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut state = self.lock();
        state.retry(job_id)?;
        let info = state.job(job_id)?.info(now);
        drop(state);
        self.flush()?;
        self.work.notify_waiters();
        self.events.send(FarmEvent::Job(job_id));
        Ok(info)
    }

    pub fn job(&self, job_id: u64) -> Result<JobInfo> {
        let now = self.now_ms();
        Ok(self.lock().job(job_id)?.info(now))
    }

    pub fn jobs(&self) -> Vec<JobInfo> {
        let now = self.now_ms();
        self.lock().jobs.values().map(|j| j.info(now)).collect()
    }

    pub fn bundle(&self, job_id: u64) -> Result<Bundle> {
        let state = self.lock();
        let job = state.job(job_id)?;
        Ok(Bundle {
            job_id,
            scene_file: job.scene_file.clone(),
            scene_hash: job.scene_hash.clone(),
            assets: job.assets.clone(),
        })
    }

    /// A page of a job's tiles: at most `limit` (and [`MAX_TILE_PAGE`]) from `offset`.
    pub fn tiles(&self, job_id: u64, offset: u32, limit: u32) -> Result<TilePage> {
        let state = self.lock();
        let job = state.job(job_id)?;
        let total = job.total();
        let end = offset.saturating_add(limit.min(MAX_TILE_PAGE)).min(total);
        let tiles = (offset.min(total)..end)
            .map(|t| job.tile_info(t, state.holders(job, t)))
            .collect();
        Ok(TilePage {
            tiles_total: total,
            offset,
            tiles,
        })
    }

    /// One tile, for the event stream.
    pub fn tile(&self, job_id: u64, tile: u32) -> Result<TileInfo> {
        let state = self.lock();
        let job = state.job(job_id)?;
        if !job.tiles.contains(tile) {
            return Err(FarmError::NotFound(format!(
                "job {job_id} has no tile {tile}"
            )));
        }
        Ok(job.tile_info(tile, state.holders(job, tile)))
    }

    /// Every worker heard from since start-up, by name then id. A worker is lost when its
    /// lease lapsed, or when it has been silent for longer than a long poll and a lease
    /// timeout (an idle worker re-asks at least once per long poll).
    pub fn workers(&self) -> Vec<WorkerInfo> {
        let now = self.now_ms();
        let silent_limit =
            (self.config.max_poll_wait + self.config.lease_timeout).as_millis() as u64;
        let state = self.lock();
        state
            .workers
            .list(now, silent_limit, |id| state.worker_lease(id))
    }

    /// OpenMetrics text: counters plus gauges computed from the current state.
    pub fn metrics_text(&self) -> String {
        let now = self.now_ms();
        let state = self.lock();
        let mut jobs_by_state: BTreeMap<&str, u64> = BTreeMap::new();
        let (mut queued, mut running, mut done) = (0u64, 0u64, 0u64);
        for job in state.jobs.values() {
            *jobs_by_state.entry(job.state.as_str()).or_default() += 1;
            done += job.tiles.done_count() as u64;
            if job.is_active() {
                queued += job.tiles.queued_count();
                running += job.tiles.leased_count() as u64;
            }
        }
        let (workers_seen, workers_active) = state.workers.counts(now, 60_000);
        let gauges = crate::metrics::Gauges {
            jobs_by_state,
            tiles_queued: queued,
            tiles_running: running,
            tiles_done: done,
            leases: state.leases.len() as u64,
            workers_seen,
            workers_active,
        };
        drop(state);
        self.metrics.render(&gauges, &self.workers())
    }
}

#[cfg(test)]
mod progressive_tests;
#[cfg(test)]
pub(crate) mod tests;
