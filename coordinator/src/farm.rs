//! The farm's state machine: one type owns every job, tile and lease transition, writes each
//! through to SQLite (and pixels to files) before answering, and wakes long-polling workers.
//!
//! Tile life: queued → leased (one lease, or two when an idle worker takes a straggler copy)
//! → done. A lapsed or handed-back lease requeues its tile without counting a failure; a
//! reported failure counts against the tile, which fails its job after failing on
//! [`FarmConfig::max_tile_workers`] different workers. Every lease has a fresh id; a message
//! with an id that is not live gets [`FarmError::Stale`] (HTTP 409).
//!
//! Locking: one std `Mutex` over the whole state and the database connection; nothing awaits
//! while it is held, and every critical section is a few map operations and at most one small
//! SQLite transaction. File I/O (tile pixels, images) happens outside it.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use tokio::sync::broadcast;
use tokio::sync::Notify;
use tracer_core::{RenderSettings, TileRect};
use worker::protocol::{
    ApiError, Bundle, BundleFile, Completion, FailureReport, JobInfo, JobSpec, JobState, Lease,
    LeaseStatus, TileFailure, TileInfo, TileState, WorkerInfo, WorkerLease, WorkerState,
};

use crate::clock::Clock;
use crate::config::FarmConfig;
use crate::metrics::Metrics;
use crate::store::{Db, Files, StoreError, StoredJob, StoredLease};

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

#[derive(Debug)]
struct Tile {
    /// The frame this tile belongs to: a frame-range job holds every frame's tiles in turn.
    frame: u32,
    rect: TileRect,
    done: bool,
    /// Live leases on this tile (two while a straggler copy runs).
    leases: Vec<u64>,
    /// Workers this tile has failed on, and its failures in all.
    failed_on: Vec<String>,
    attempts: usize,
}

#[derive(Debug)]
struct Job {
    id: u64,
    name: String,
    scene_file: String,
    scene_hash: String,
    spec: JobSpec,
    state: JobState,
    error: Option<String>,
    created_ms: u64,
    started_ms: Option<u64>,
    finished_ms: Option<u64>,
    assets: Vec<BundleFile>,
    tiles: Vec<Tile>,
    /// Tiles waiting for a worker, lowest index first.
    queued: BTreeSet<u32>,
    done: u32,
    failures: Vec<TileFailure>,
    /// Sum and count of lease-to-completion times, for straggler detection.
    tile_ms_total: u64,
    tiles_timed: u64,
    /// Every tile is done and the image is being written.
    assembling: bool,
}

impl Job {
    fn from_stored(stored: StoredJob) -> Job {
        let rects = TileRect::grid(
            stored.spec.render.width,
            stored.spec.render.height,
            stored.spec.tile_size,
        );
        let mut tiles: Vec<Tile> = stored
            .spec
            .frame_list()
            .into_iter()
            .flat_map(|frame| rects.iter().map(move |&rect| (frame, rect)))
            .map(|(frame, rect)| Tile {
                frame,
                rect,
                done: false,
                leases: Vec::new(),
                failed_on: Vec::new(),
                attempts: 0,
            })
            .collect();
        let mut done = 0;
        for &t in &stored.tiles_done {
            if let Some(tile) = tiles.get_mut(t as usize) {
                if !tile.done {
                    tile.done = true;
                    done += 1;
                }
            }
        }
        for f in &stored.failures {
            if let Some(tile) = tiles.get_mut(f.tile as usize) {
                tile.attempts += 1;
                if !tile.failed_on.contains(&f.worker) {
                    tile.failed_on.push(f.worker.clone());
                }
            }
        }
        Job {
            id: stored.id,
            name: stored.name,
            scene_file: stored.scene_file,
            scene_hash: stored.scene_hash,
            spec: stored.spec,
            state: stored.state,
            error: stored.error,
            created_ms: stored.created_ms,
            started_ms: stored.started_ms,
            finished_ms: stored.finished_ms,
            assets: stored.assets,
            tiles,
            queued: BTreeSet::new(),
            done,
            failures: stored.failures,
            tile_ms_total: 0,
            tiles_timed: 0,
            assembling: false,
        }
    }

    fn is_active(&self) -> bool {
        matches!(self.state, JobState::Queued | JobState::Running)
    }

    fn total(&self) -> u32 {
        self.tiles.len() as u32
    }

    /// Queues every tile that is neither done nor leased.
    fn queue_idle_tiles(&mut self) {
        for (i, tile) in self.tiles.iter().enumerate() {
            if !tile.done && tile.leases.is_empty() {
                self.queued.insert(i as u32);
            }
        }
    }

    fn info(&self, now: u64) -> JobInfo {
        let running = self.tiles.iter().filter(|t| !t.leases.is_empty()).count() as u32;
        let elapsed_ms = self
            .started_ms
            .map(|s| self.finished_ms.unwrap_or(now).saturating_sub(s));
        let eta_s = match elapsed_ms {
            Some(ms) if self.is_active() && self.done > 0 => {
                let per_tile = ms as f64 / 1000.0 / self.done as f64;
                Some(per_tile * (self.total() - self.done) as f64)
            }
            _ => None,
        };
        JobInfo {
            id: self.id,
            name: self.name.clone(),
            scene_file: self.scene_file.clone(),
            state: self.state,
            spec: self.spec.clone(),
            tiles_total: self.total(),
            tiles_done: self.done,
            tiles_running: running,
            elapsed_s: elapsed_ms.map(|ms| ms as f64 / 1000.0),
            eta_s,
            error: self.error.clone(),
            failures: self.failures.clone(),
            created_ms: self.created_ms,
        }
    }
}

/// Where a finished job's PNG of one frame is stored.
enum StoredImage {
    Job,
    Frame(u32),
}

/// What changed, for `GET /events`: readers look the current state up, so a burst of changes
/// to one job costs one message.
#[derive(Clone, Debug, PartialEq, Eq, Hash)]
pub enum FarmEvent {
    Job(u64),
    Tile(u64, u32),
    /// The farm is stopping: event streams end so the server can.
    Stopping,
}

/// How many events a slow reader may fall behind before it is told to resynchronise.
const EVENT_BACKLOG: usize = 4096;

/// What the farm knows of one worker since it started.
#[derive(Debug, Default)]
struct WorkerRecord {
    last_seen_ms: u64,
    address: Option<String>,
    tiles_done: u64,
    /// Its last lease lapsed without a heartbeat (cleared when it is heard from again).
    lapsed: bool,
}

#[derive(Clone, Debug)]
struct LiveLease {
    job_id: u64,
    tile: u32,
    worker: String,
    granted_ms: u64,
    deadline_ms: u64,
}

struct State {
    db: Db,
    jobs: BTreeMap<u64, Job>,
    leases: HashMap<u64, LiveLease>,
    by_worker: HashMap<String, u64>,
    next_lease: u64,
    /// Why recent leases ended, for clear 409 messages (bounded).
    ended: HashMap<u64, &'static str>,
    workers: HashMap<String, WorkerRecord>,
}

const ENDED_KEEP: usize = 100_000;

impl State {
    /// Records that `worker` was heard from.
    fn seen(&mut self, worker: &str, now: u64) -> &mut WorkerRecord {
        let record = self.workers.entry(worker.to_string()).or_default();
        record.last_seen_ms = now;
        record.lapsed = false;
        record
    }

    fn tile_info(&self, job: &Job, tile: u32) -> TileInfo {
        let t = &job.tiles[tile as usize];
        let state = if t.done {
            TileState::Done
        } else if !t.leases.is_empty() {
            TileState::Leased
        } else if t.attempts > 0 {
            TileState::Failed
        } else if job.is_active() {
            TileState::Queued
        } else {
            TileState::Idle
        };
        TileInfo {
            job_id: job.id,
            tile,
            frame: t.frame,
            rect: t.rect,
            state,
            workers: t
                .leases
                .iter()
                .filter_map(|l| self.leases.get(l).map(|l| l.worker.clone()))
                .collect(),
            attempts: t.attempts as u32,
        }
    }

    fn end_lease(&mut self, id: u64, why: &'static str) -> Option<LiveLease> {
        let lease = self.leases.remove(&id)?;
        if self.by_worker.get(&lease.worker) == Some(&id) {
            self.by_worker.remove(&lease.worker);
        }
        if let Some(tile) = self
            .jobs
            .get_mut(&lease.job_id)
            .and_then(|j| j.tiles.get_mut(lease.tile as usize))
        {
            tile.leases.retain(|l| *l != id);
        }
        if self.ended.len() >= ENDED_KEEP {
            self.ended.clear();
        }
        self.ended.insert(id, why);
        Some(lease)
    }

    fn stale(&self, id: u64) -> FarmError {
        let why = self.ended.get(&id).copied().unwrap_or("unknown or expired");
        FarmError::Stale(format!("lease {id} is no longer valid: {why}"))
    }

    fn live(&self, id: u64) -> Result<&LiveLease> {
        self.leases.get(&id).ok_or_else(|| self.stale(id))
    }

    fn job(&self, id: u64) -> Result<&Job> {
        self.jobs
            .get(&id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {id}")))
    }

    fn job_mut(&mut self, id: u64) -> Result<&mut Job> {
        self.jobs
            .get_mut(&id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {id}")))
    }

    /// Requeues a tile that has no live lease left.
    fn requeue_if_idle(&mut self, job_id: u64, tile: u32) -> bool {
        let Some(job) = self.jobs.get_mut(&job_id) else {
            return false;
        };
        if !job.is_active() {
            return false;
        }
        let t = &job.tiles[tile as usize];
        if !t.done && t.leases.is_empty() {
            job.queued.insert(tile);
            return true;
        }
        false
    }

    /// Ends a job (failed or cancelled): revokes its leases and drops its queue.
    fn finish_job(
        &mut self,
        job_id: u64,
        state: JobState,
        error: Option<String>,
        now: u64,
        why: &'static str,
    ) -> Result<()> {
        let ids: Vec<u64> = self
            .leases
            .iter()
            .filter(|(_, l)| l.job_id == job_id)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.end_lease(id, why);
        }
        self.db.delete_job_leases(job_id)?;
        let job = self.job_mut(job_id)?;
        job.queued.clear();
        job.state = state;
        job.error = error;
        job.finished_ms = Some(now);
        let (started, error) = (job.started_ms, job.error.clone());
        self.db
            .set_job_state(job_id, state, error.as_deref(), started, Some(now))?;
        Ok(())
    }
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
    events: broadcast::Sender<FarmEvent>,
}

impl Farm {
    /// Opens (or creates) the data dir and resumes every unfinished job in it.
    pub fn open(data_dir: &Path, config: FarmConfig, clock: Arc<dyn Clock>) -> Result<Arc<Farm>> {
        std::fs::create_dir_all(data_dir).map_err(|e| {
            StoreError::io(format!("creating the data dir {}", data_dir.display()), e)
        })?;
        let db = Db::open(&data_dir.join("tessera.db"))?;
        let files = Files::open(data_dir)?;
        Self::with_store(db, files, config, clock)
    }

    fn with_store(
        db: Db,
        files: Files,
        config: FarmConfig,
        clock: Arc<dyn Clock>,
    ) -> Result<Arc<Farm>> {
        let epoch = db.next_epoch()?;
        let now = clock.now_ms();
        let mut state = State {
            jobs: BTreeMap::new(),
            leases: HashMap::new(),
            by_worker: HashMap::new(),
            next_lease: epoch << 32,
            ended: HashMap::new(),
            workers: HashMap::new(),
            db,
        };
        for stored in state.db.load_jobs()? {
            let job = Job::from_stored(stored);
            state.jobs.insert(job.id, job);
        }
        // Leases granted before the restart stay valid for a grace period, so workers that
        // kept rendering through the outage can still deliver.
        let grace = config.restart_grace.as_millis() as u64;
        for stored in state.db.load_leases()? {
            let keep = state
                .jobs
                .get(&stored.job_id)
                .filter(|j| j.is_active())
                .and_then(|j| j.tiles.get(stored.tile as usize))
                .is_some_and(|t| !t.done)
                && !state.by_worker.contains_key(&stored.worker);
            if !keep {
                state.db.delete_lease(stored.id)?;
                continue;
            }
            let job = state.jobs.get_mut(&stored.job_id).expect("checked above");
            job.tiles[stored.tile as usize].leases.push(stored.id);
            state.by_worker.insert(stored.worker.clone(), stored.id);
            state.leases.insert(
                stored.id,
                LiveLease {
                    job_id: stored.job_id,
                    tile: stored.tile,
                    worker: stored.worker,
                    granted_ms: stored.granted_ms,
                    deadline_ms: now + grace,
                },
            );
        }
        let mut finished = Vec::new();
        for job in state.jobs.values_mut() {
            if job.is_active() {
                job.queue_idle_tiles();
                if job.done == job.total() {
                    job.assembling = true;
                    finished.push(job.id);
                }
            }
        }
        let farm = Arc::new(Farm {
            config,
            clock,
            files,
            state: Mutex::new(state),
            work: Notify::new(),
            stopping: AtomicBool::new(false),
            epoch,
            metrics: Metrics::default(),
            tile_writes: AtomicU64::new(0),
            events: broadcast::channel(EVENT_BACKLOG).0,
        });
        // Jobs whose last tile landed just before a crash.
        for id in finished {
            // A failure marks the job failed (and is logged); the farm still opens.
            let _ = farm.assemble(id);
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
        // A panic under the lock leaves maps consistent enough to keep serving.
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
        self.emit(FarmEvent::Stopping);
    }

    /// Subscribes to change notifications (`GET /events`).
    pub fn subscribe(&self) -> broadcast::Receiver<FarmEvent> {
        self.events.subscribe()
    }

    fn emit(&self, event: FarmEvent) {
        // An error only means nobody is listening.
        let _ = self.events.send(event);
    }

    fn emit_tile(&self, job_id: u64, tile: u32) {
        self.emit(FarmEvent::Tile(job_id, tile));
        self.emit(FarmEvent::Job(job_id));
    }

    /// Records the address a worker's lease request came from (for `GET /workers`).
    pub fn worker_address(&self, worker: &str, address: String) {
        let now = self.now_ms();
        self.lock().seen(worker, now).address = Some(address);
    }

    pub fn is_stopping(&self) -> bool {
        self.stopping.load(Ordering::SeqCst)
    }

    /// Waits until work may have been queued (or the farm stops).
    pub fn work_notified(&self) -> tokio::sync::futures::Notified<'_> {
        self.work.notified()
    }

    pub fn submit(&self, new: NewJob) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut stored = StoredJob {
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
        let mut state = self.lock();
        stored.id = state.db.insert_job(&stored)?;
        let mut job = Job::from_stored(stored);
        job.queue_idle_tiles();
        let info = job.info(now);
        tracing::info!(
            "job {}: {} queued, {} tiles of at most {}x{}",
            job.id,
            job.name,
            job.total(),
            job.spec.tile_size,
            job.spec.tile_size
        );
        state.jobs.insert(job.id, job);
        drop(state);
        self.work.notify_waiters();
        self.emit(FarmEvent::Job(info.id));
        Ok(info)
    }

    /// Grants `worker` a tile: the lease it already holds, else the lowest queued tile of the
    /// oldest job, else (with stragglers on) a copy of a slow running tile.
    pub fn lease(&self, worker: &str) -> Result<Option<Lease>> {
        let now = self.now_ms();
        let mut state = self.lock();
        state.seen(worker, now);
        if let Some(&id) = state.by_worker.get(worker) {
            let deadline = now + self.config.lease_timeout.as_millis() as u64;
            let lease = state.leases.get_mut(&id).expect("by_worker follows leases");
            lease.deadline_ms = deadline;
            let lease = lease.clone();
            return Ok(Some(self.describe(&state, id, &lease)));
        }
        let Some((job_id, tile)) = self
            .pick_queued(&mut state, worker)
            .or_else(|| self.pick_straggler(&state, worker, now))
        else {
            return Ok(None);
        };
        let id = state.next_lease;
        state.next_lease += 1;
        let lease = LiveLease {
            job_id,
            tile,
            worker: worker.to_string(),
            granted_ms: now,
            deadline_ms: now + self.config.lease_timeout.as_millis() as u64,
        };
        state.db.insert_lease(&StoredLease {
            id,
            job_id,
            tile,
            worker: worker.to_string(),
            granted_ms: now,
        })?;
        let job = state.jobs.get_mut(&job_id).expect("picked from the map");
        job.queued.remove(&tile);
        job.tiles[tile as usize].leases.push(id);
        if job.state == JobState::Queued {
            job.state = JobState::Running;
            job.started_ms = Some(now);
            state
                .db
                .set_job_state(job_id, JobState::Running, None, Some(now), None)?;
        }
        state.leases.insert(id, lease.clone());
        state.by_worker.insert(worker.to_string(), id);
        self.metrics.leases_granted.fetch_add(1, Ordering::Relaxed);
        let granted = self.describe(&state, id, &lease);
        drop(state);
        self.emit_tile(job_id, tile);
        Ok(Some(granted))
    }

    fn describe(&self, state: &State, id: u64, lease: &LiveLease) -> Lease {
        let job = &state.jobs[&lease.job_id];
        let now = self.now_ms();
        Lease {
            lease_id: id,
            job_id: lease.job_id,
            tile: lease.tile,
            rect: job.tiles[lease.tile as usize].rect,
            settings: RenderSettings {
                frame: job.tiles[lease.tile as usize].frame,
                ..job.spec.render.clone()
            },
            expires_in_ms: lease.deadline_ms.saturating_sub(now),
            heartbeat_ms: self.config.heartbeat.as_millis() as u64,
        }
    }

    /// The lowest queued tile of the oldest active job, preferring tiles that have not
    /// already failed on this worker.
    fn pick_queued(&self, state: &mut State, worker: &str) -> Option<(u64, u32)> {
        let mut fallback = None;
        for job in state.jobs.values().filter(|j| j.is_active()) {
            for &t in &job.queued {
                if !job.tiles[t as usize].failed_on.iter().any(|w| w == worker) {
                    return Some((job.id, t));
                }
                fallback.get_or_insert((job.id, t));
            }
        }
        fallback
    }

    /// With nothing queued: the running tile whose only lease is oldest, if that lease has
    /// run well past the job's typical tile time and `worker` does not hold it.
    fn pick_straggler(&self, state: &State, worker: &str, now: u64) -> Option<(u64, u32)> {
        if !self.config.stragglers {
            return None;
        }
        let mut best: Option<(u64, (u64, u32))> = None;
        for job in state.jobs.values().filter(|j| j.is_active()) {
            if job.tiles_timed == 0 {
                continue;
            }
            let typical = job.tile_ms_total / job.tiles_timed;
            let threshold = (2 * typical).max(1000);
            for (i, tile) in job.tiles.iter().enumerate() {
                let [only] = tile.leases.as_slice() else {
                    continue;
                };
                let lease = &state.leases[only];
                let age = now.saturating_sub(lease.granted_ms);
                if tile.done || lease.worker == worker || age < threshold {
                    continue;
                }
                if best.is_none_or(|(granted, _)| lease.granted_ms < granted) {
                    best = Some((lease.granted_ms, (job.id, i as u32)));
                }
            }
        }
        best.map(|(_, pick)| pick)
    }

    pub fn heartbeat(&self, lease_id: u64) -> Result<LeaseStatus> {
        let now = self.now_ms();
        let mut state = self.lock();
        let timeout = self.config.lease_timeout.as_millis() as u64;
        let worker = {
            let Some(lease) = state.leases.get_mut(&lease_id) else {
                return Err(state.stale(lease_id));
            };
            lease.deadline_ms = now + timeout;
            lease.worker.clone()
        };
        state.seen(&worker, now);
        Ok(LeaseStatus {
            expires_in_ms: timeout,
        })
    }

    /// Stores a finished tile. The pixels are on disk before the tile counts as done; the
    /// first valid result wins, and the tile's other leases are revoked.
    pub fn complete(&self, lease_id: u64, pixels: &[u8]) -> Result<(Completion, Option<u64>)> {
        let (job_id, tile, rect) = {
            let state = self.lock();
            let lease = state.live(lease_id)?;
            let rect = state.jobs[&lease.job_id].tiles[lease.tile as usize].rect;
            (lease.job_id, lease.tile, rect)
        };
        let expected = rect.pixel_count() * 12;
        if pixels.len() != expected {
            return Err(FarmError::BadRequest(ApiError::new(format!(
                "tile {tile} is {}x{}: its pixels are {expected} bytes of f32 RGB, got {}",
                rect.width,
                rect.height,
                pixels.len()
            ))));
        }
        self.files.put_tile(job_id, tile, pixels)?;
        self.tile_writes.fetch_add(1, Ordering::Relaxed);
        let now = self.now_ms();
        let mut state = self.lock();
        // The lease may have lapsed while the pixels were written: then another worker owns
        // the tile, and the file (equal pixels, by determinism) is simply overwritten later.
        let lease = state.live(lease_id)?.clone();
        state.db.complete_tile(job_id, tile)?;
        let others: Vec<u64> = state.jobs[&job_id].tiles[tile as usize]
            .leases
            .iter()
            .copied()
            .filter(|l| *l != lease_id)
            .collect();
        for other in others {
            state.end_lease(other, "another worker finished the tile first");
        }
        state.end_lease(lease_id, "the tile is finished");
        state.seen(&lease.worker, now).tiles_done += 1;
        let job = state.job_mut(job_id)?;
        job.tiles[tile as usize].done = true;
        job.queued.remove(&tile);
        job.done += 1;
        job.tile_ms_total += now.saturating_sub(lease.granted_ms);
        job.tiles_timed += 1;
        let complete = job.done == job.total() && !job.assembling;
        if complete {
            job.assembling = true;
        }
        let answer = Completion {
            tiles_done: job.done,
            tiles_total: job.total(),
        };
        self.metrics.tiles_completed.fetch_add(1, Ordering::Relaxed);
        drop(state);
        self.emit_tile(job_id, tile);
        Ok((answer, complete.then_some(job_id)))
    }

    /// Writes a finished job's PNG from its tiles and marks it done; if the image cannot be
    /// built (a tile file unreadable, the disk full) the job fails with that error rather than
    /// staying "running" forever. Blocking (file I/O and PNG encoding): call from a blocking
    /// thread.
    pub fn assemble(&self, job_id: u64) -> Result<()> {
        match self.write_image(job_id) {
            Ok(()) => self.mark_done(job_id),
            Err(FarmError::NotFound(e)) => Err(FarmError::NotFound(e)),
            Err(e) => {
                let error = format!("assembling the image failed: {e}");
                tracing::error!("job {job_id}: {error}");
                let now = self.now_ms();
                let mut state = self.lock();
                if !state.job(job_id)?.is_active() {
                    return Ok(());
                }
                state.job_mut(job_id)?.assembling = false;
                state.finish_job(job_id, JobState::Failed, Some(error), now, "the job failed")?;
                drop(state);
                self.emit(FarmEvent::Job(job_id));
                Err(e)
            }
        }
    }

    fn write_image(&self, job_id: u64) -> Result<()> {
        let (width, height, frames, tiles) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            let tiles: Vec<(u32, u32, TileRect)> = job
                .tiles
                .iter()
                .enumerate()
                .map(|(i, t)| (t.frame, i as u32, t.rect))
                .collect();
            (
                job.spec.render.width,
                job.spec.render.height,
                job.spec.frames.is_some(),
                tiles,
            )
        };
        let frame_list: BTreeSet<u32> = tiles.iter().map(|t| t.0).collect();
        let mut first = None;
        for &frame in &frame_list {
            let of_frame: Vec<(u32, TileRect)> = tiles
                .iter()
                .filter(|t| t.0 == frame)
                .map(|t| (t.1, t.2))
                .collect();
            let png = self
                .files
                .assemble(job_id, width, height, &of_frame)?
                .to_png();
            if frames {
                self.files.put_frame_image(job_id, frame, &png)?;
            }
            first.get_or_insert(png);
        }
        // The job's image is its (first) frame, so single-image clients keep working. Last,
        // because storing it drops the tiles.
        self.files.put_image(job_id, &first.unwrap_or_default())?;
        Ok(())
    }

    fn mark_done(&self, job_id: u64) -> Result<()> {
        let now = self.now_ms();
        let mut state = self.lock();
        let job = state.job_mut(job_id)?;
        if !job.is_active() {
            return Ok(());
        }
        job.state = JobState::Done;
        job.finished_ms = Some(now);
        job.assembling = false;
        let started = job.started_ms;
        let elapsed = started.map(|s| (now - s) as f64 / 1000.0).unwrap_or(0.0);
        state
            .db
            .set_job_state(job_id, JobState::Done, None, started, Some(now))?;
        tracing::info!("job {job_id}: done in {elapsed:.2}s");
        drop(state);
        self.emit(FarmEvent::Job(job_id));
        Ok(())
    }

    pub fn fail(&self, lease_id: u64, report: &FailureReport) -> Result<JobInfo> {
        let (job_id, tile) = {
            let state = self.lock();
            let lease = state.live(lease_id)?;
            (lease.job_id, lease.tile)
        };
        let info = self.record_failure(lease_id, report)?;
        self.emit_tile(job_id, tile);
        Ok(info)
    }

    fn record_failure(&self, lease_id: u64, report: &FailureReport) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut state = self.lock();
        let lease = state.live(lease_id)?.clone();
        state.end_lease(lease_id, "the worker reported a failure");
        state.db.delete_lease(lease_id)?;
        let failure = TileFailure {
            tile: lease.tile,
            worker: lease.worker.clone(),
            error: report.error.clone(),
        };
        state.db.insert_failure(lease.job_id, &failure, now)?;
        self.metrics.tile_failures.fetch_add(1, Ordering::Relaxed);
        let (max_workers, max_attempts) =
            (self.config.max_tile_workers, self.config.max_tile_attempts);
        let job = state.job_mut(lease.job_id)?;
        job.failures.push(failure);
        let tile = &mut job.tiles[lease.tile as usize];
        tile.attempts += 1;
        if !tile.failed_on.contains(&lease.worker) {
            tile.failed_on.push(lease.worker.clone());
        }
        let fatal = if report.scene {
            Some(format!("the scene could not be loaded: {}", report.error))
        } else if tile.failed_on.len() >= max_workers || tile.attempts >= max_attempts {
            Some(format!(
                "tile {} failed on {} workers ({} attempts): {}",
                lease.tile,
                tile.failed_on.len(),
                tile.attempts,
                report.error
            ))
        } else {
            None
        };
        tracing::warn!(
            "job {} tile {} failed on {}: {}",
            lease.job_id,
            lease.tile,
            lease.worker,
            report.error
        );
        if job.is_active() {
            if let Some(error) = fatal {
                tracing::error!("job {}: failed: {error}", lease.job_id);
                state.finish_job(
                    lease.job_id,
                    JobState::Failed,
                    Some(error),
                    now,
                    "the job failed",
                )?;
            } else if state.requeue_if_idle(lease.job_id, lease.tile) {
                drop(state);
                self.work.notify_waiters();
                return self.job(lease.job_id);
            }
        }
        Ok(state.job(lease.job_id)?.info(now))
    }

    /// A worker gives its tile back unfinished (it is stopping); not a failure.
    pub fn hand_back(&self, lease_id: u64) -> Result<()> {
        let mut state = self.lock();
        let lease = state.live(lease_id)?.clone();
        state.end_lease(lease_id, "handed back");
        state.db.delete_lease(lease_id)?;
        self.metrics.handed_back.fetch_add(1, Ordering::Relaxed);
        let requeued = state.requeue_if_idle(lease.job_id, lease.tile);
        drop(state);
        if requeued {
            self.work.notify_waiters();
        }
        self.emit_tile(lease.job_id, lease.tile);
        Ok(())
    }

    /// Ends every lease whose deadline has passed and requeues its tile. Returns how many.
    pub fn expire_leases(&self) -> Result<usize> {
        let now = self.now_ms();
        let mut state = self.lock();
        let expired: Vec<u64> = state
            .leases
            .iter()
            .filter(|(_, l)| l.deadline_ms < now)
            .map(|(id, _)| *id)
            .collect();
        let mut requeued = false;
        let mut changed = Vec::new();
        for &id in &expired {
            let lease = state
                .end_lease(id, "it expired without a heartbeat")
                .expect("live");
            state.db.delete_lease(id)?;
            if let Some(worker) = state.workers.get_mut(&lease.worker) {
                worker.lapsed = true;
            }
            changed.push((lease.job_id, lease.tile));
            tracing::warn!(
                "job {} tile {}: lease {id} of {} expired; requeued",
                lease.job_id,
                lease.tile,
                lease.worker
            );
            requeued |= state.requeue_if_idle(lease.job_id, lease.tile);
        }
        drop(state);
        self.metrics
            .leases_expired
            .fetch_add(expired.len() as u64, Ordering::Relaxed);
        if requeued {
            self.work.notify_waiters();
        }
        for (job_id, tile) in changed {
            self.emit_tile(job_id, tile);
        }
        Ok(expired.len())
    }

    pub fn cancel(&self, job_id: u64) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut state = self.lock();
        let job = state.job(job_id)?;
        if !job.is_active() {
            return Err(FarmError::Conflict(format!(
                "job {job_id} is already {}",
                job.state.as_str()
            )));
        }
        state.finish_job(
            job_id,
            JobState::Cancelled,
            None,
            now,
            "the job was cancelled",
        )?;
        tracing::info!("job {job_id}: cancelled");
        let info = state.job(job_id)?.info(now);
        drop(state);
        self.emit(FarmEvent::Job(job_id));
        Ok(info)
    }

    /// Requeues a failed job's unfinished tiles with fresh failure counts.
    pub fn retry(&self, job_id: u64) -> Result<JobInfo> {
        let now = self.now_ms();
        let mut state = self.lock();
        let job = state.job(job_id)?;
        if job.state != JobState::Failed {
            return Err(FarmError::Conflict(format!(
                "job {job_id} is {}; only failed jobs can be retried",
                job.state.as_str()
            )));
        }
        state.db.clear_failures(job_id)?;
        let job = state.job_mut(job_id)?;
        job.failures.clear();
        for tile in &mut job.tiles {
            tile.failed_on.clear();
            tile.attempts = 0;
        }
        job.state = if job.started_ms.is_some() {
            JobState::Running
        } else {
            JobState::Queued
        };
        job.error = None;
        job.finished_ms = None;
        job.queue_idle_tiles();
        let (state_now, started) = (job.state, job.started_ms);
        let info = job.info(now);
        state
            .db
            .set_job_state(job_id, state_now, None, started, None)?;
        drop(state);
        self.work.notify_waiters();
        self.emit(FarmEvent::Job(job_id));
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

    /// Every tile of a job with its state, lease holders and failed attempts.
    pub fn tiles(&self, job_id: u64) -> Result<Vec<TileInfo>> {
        let state = self.lock();
        let job = state.job(job_id)?;
        Ok((0..job.total()).map(|t| state.tile_info(job, t)).collect())
    }

    /// One tile, for the event stream.
    pub fn tile(&self, job_id: u64, tile: u32) -> Result<TileInfo> {
        let state = self.lock();
        let job = state.job(job_id)?;
        if tile >= job.total() {
            return Err(FarmError::NotFound(format!(
                "job {job_id} has no tile {tile}"
            )));
        }
        Ok(state.tile_info(job, tile))
    }

    /// Every worker heard from since start-up, by name. A worker is lost when its lease
    /// lapsed, or when it has been silent for longer than a long poll and a lease timeout
    /// (an idle worker re-asks at least once per long poll).
    pub fn workers(&self) -> Vec<WorkerInfo> {
        let now = self.now_ms();
        let silent_limit =
            (self.config.max_poll_wait + self.config.lease_timeout).as_millis() as u64;
        let state = self.lock();
        let mut list: Vec<WorkerInfo> = state
            .workers
            .iter()
            .map(|(name, record)| {
                let lease = state
                    .by_worker
                    .get(name)
                    .and_then(|id| state.leases.get(id));
                let worker_state = if lease.is_some() {
                    WorkerState::Rendering
                } else if record.lapsed || now.saturating_sub(record.last_seen_ms) > silent_limit {
                    WorkerState::Lost
                } else {
                    WorkerState::Idle
                };
                WorkerInfo {
                    name: name.clone(),
                    address: record.address.clone(),
                    state: worker_state,
                    lease: lease.map(|l| WorkerLease {
                        job_id: l.job_id,
                        tile: l.tile,
                    }),
                    tiles_done: record.tiles_done,
                    last_seen_ms: record.last_seen_ms,
                }
            })
            .collect();
        list.sort_by(|a, b| a.name.cmp(&b.name));
        list
    }

    /// The PNG of one frame of the job (its first frame when `frame` is None): the stored
    /// final image, or one assembled from the frame's finished tiles with the rest black.
    /// Blocking.
    pub fn image(&self, job_id: u64, frame: Option<u32>) -> Result<Vec<u8>> {
        let (width, height, tiles, state, stored) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            let frames = job.spec.frame_list();
            let frame = match frame {
                None => frames[0],
                Some(f) if frames.contains(&f) => f,
                Some(f) => {
                    return Err(FarmError::NotFound(format!(
                        "job {job_id} has no frame {f} (it renders {})",
                        match job.spec.frames {
                            Some(r) => format!("frames {}..{}", r.first, r.last),
                            None => format!("frame {}", frames[0]),
                        }
                    )))
                }
            };
            let tiles: Vec<(u32, TileRect)> = job
                .tiles
                .iter()
                .enumerate()
                .filter(|(_, t)| t.done && t.frame == frame)
                .map(|(i, t)| (i as u32, t.rect))
                .collect();
            // Only frame-range jobs store a PNG per frame; the job image is the first frame.
            let stored = if job.spec.frames.is_some() {
                StoredImage::Frame(frame)
            } else {
                StoredImage::Job
            };
            (
                job.spec.render.width,
                job.spec.render.height,
                tiles,
                job.state,
                stored,
            )
        };
        if state == JobState::Done {
            let png = match stored {
                StoredImage::Job => self.files.image(job_id)?,
                StoredImage::Frame(f) => self.files.frame_image(job_id, f)?,
            };
            if let Some(png) = png {
                return Ok(png);
            }
        }
        Ok(self.files.assemble(job_id, width, height, &tiles)?.to_png())
    }

    /// Every frame's PNG of a finished job, in frame order, as (frame, bytes). Blocking.
    pub fn frame_images(&self, job_id: u64) -> Result<Vec<(u32, Vec<u8>)>> {
        let (frames, state) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            (job.spec.frame_list(), job.state)
        };
        if state != JobState::Done {
            return Err(FarmError::Conflict(format!(
                "job {job_id} is {}: its frames are ready once it is done",
                state.as_str()
            )));
        }
        frames
            .into_iter()
            .map(|f| Ok((f, self.image(job_id, Some(f))?)))
            .collect()
    }

    /// Prometheus text: counters plus gauges computed from the current state.
    pub fn metrics_text(&self) -> String {
        let now = self.now_ms();
        let state = self.lock();
        let mut jobs_by_state: BTreeMap<&str, u64> = BTreeMap::new();
        let (mut queued, mut running, mut done) = (0u64, 0u64, 0u64);
        for job in state.jobs.values() {
            *jobs_by_state.entry(job.state.as_str()).or_default() += 1;
            done += job.done as u64;
            if job.is_active() {
                queued += job.queued.len() as u64;
                running += job.tiles.iter().filter(|t| !t.leases.is_empty()).count() as u64;
            }
        }
        let active = state
            .workers
            .values()
            .filter(|w| now.saturating_sub(w.last_seen_ms) < 60_000)
            .count();
        let gauges = crate::metrics::Gauges {
            jobs_by_state,
            tiles_queued: queued,
            tiles_running: running,
            tiles_done: done,
            leases: state.leases.len() as u64,
            workers_seen: state.workers.len() as u64,
            workers_active: active as u64,
        };
        drop(state);
        self.metrics.render(&gauges)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::clock::ManualClock;

    struct Fixture {
        _dir: tempfile::TempDir,
        clock: Arc<ManualClock>,
        farm: Arc<Farm>,
    }

    fn fixture(config: FarmConfig) -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let clock = Arc::new(ManualClock::new(1_000_000));
        let farm = Farm::for_tests(dir.path(), config, clock.clone());
        Fixture {
            _dir: dir,
            clock,
            farm,
        }
    }

    /// A 4-tile job (16x16 in 8x8 tiles).
    fn new_job(name: &str) -> NewJob {
        let mut spec = JobSpec::default();
        spec.render.width = 16;
        spec.render.height = 16;
        spec.tile_size = 8;
        NewJob {
            name: name.into(),
            scene_file: "s.scene".into(),
            scene_hash: "0".repeat(64),
            spec,
            assets: vec![],
        }
    }

    fn blank(rect: TileRect, value: f32) -> Vec<u8> {
        worker::protocol::pixels_to_bytes(&vec![value; rect.pixel_count() * 3])
    }

    fn finish(farm: &Farm, lease: &Lease) -> Option<u64> {
        farm.complete(lease.lease_id, &blank(lease.rect, 0.5))
            .unwrap()
            .1
    }

    #[test]
    fn leases_go_oldest_job_first_and_asking_again_returns_the_same_lease() {
        let f = fixture(FarmConfig::default());
        let a = f.farm.submit(new_job("a")).unwrap();
        let b = f.farm.submit(new_job("b")).unwrap();
        let l1 = f.farm.lease("w1").unwrap().unwrap();
        assert_eq!((l1.job_id, l1.tile), (a.id, 0));
        assert_eq!(f.farm.lease("w1").unwrap().unwrap(), l1);
        let l2 = f.farm.lease("w2").unwrap().unwrap();
        assert_eq!((l2.job_id, l2.tile), (a.id, 1));
        assert_ne!(l1.lease_id, l2.lease_id);
        assert_eq!(f.farm.job(a.id).unwrap().state, JobState::Running);
        assert_eq!(f.farm.job(b.id).unwrap().state, JobState::Queued);
    }

    #[test]
    fn tiles_and_workers_report_their_state_and_changes_are_announced() {
        let f = fixture(FarmConfig::default());
        let mut events = f.farm.subscribe();
        let job = f.farm.submit(new_job("a")).unwrap();
        assert_eq!(events.try_recv().unwrap(), FarmEvent::Job(job.id));
        let states = |farm: &Farm| -> Vec<TileState> {
            farm.tiles(job.id)
                .unwrap()
                .iter()
                .map(|t| t.state)
                .collect()
        };

        let l1 = f.farm.lease("w1").unwrap().unwrap();
        assert_eq!(events.try_recv().unwrap(), FarmEvent::Tile(job.id, 0));
        assert_eq!(events.try_recv().unwrap(), FarmEvent::Job(job.id));
        assert_eq!(f.farm.tile(job.id, 0).unwrap().workers, ["w1"]);
        assert_eq!(states(&f.farm)[..2], [TileState::Leased, TileState::Queued]);
        let w = &f.farm.workers()[0];
        assert_eq!(
            (w.state, w.lease.map(|l| l.tile)),
            (WorkerState::Rendering, Some(0))
        );
        finish(&f.farm, &l1);
        assert_eq!(events.try_recv().unwrap(), FarmEvent::Tile(job.id, 0));
        let w = &f.farm.workers()[0];
        assert_eq!((w.state, w.tiles_done), (WorkerState::Idle, 1));

        // A failed tile shows its attempts, leased again or not.
        let l2 = f.farm.lease("w2").unwrap().unwrap();
        let report = FailureReport {
            error: "boom".into(),
            scene: false,
        };
        f.farm.fail(l2.lease_id, &report).unwrap();
        let tile = f.farm.tile(job.id, l2.tile).unwrap();
        assert_eq!((tile.state, tile.attempts), (TileState::Failed, 1));

        // A worker whose lease lapses is lost; one silent past a long poll too.
        let l3 = f.farm.lease("w3").unwrap().unwrap();
        assert_eq!(l3.tile, l2.tile);
        f.clock.advance(5_001);
        f.farm.expire_leases().unwrap();
        let by_name = |name: &str| {
            let workers = f.farm.workers();
            workers.into_iter().find(|w| w.name == name).unwrap().state
        };
        assert_eq!(by_name("w3"), WorkerState::Lost);
        assert_eq!(by_name("w1"), WorkerState::Idle);
        f.clock.advance(31_000);
        assert_eq!(by_name("w1"), WorkerState::Lost);

        f.farm.cancel(job.id).unwrap();
        assert_eq!(
            states(&f.farm),
            [
                TileState::Done,
                TileState::Failed,
                TileState::Idle,
                TileState::Idle
            ]
        );
        assert!(matches!(
            f.farm.tile(job.id, 4),
            Err(FarmError::NotFound(_))
        ));
        assert!(matches!(f.farm.tiles(99), Err(FarmError::NotFound(_))));
    }

    #[test]
    fn a_silent_worker_loses_its_tile_without_a_failure() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let lease = f.farm.lease("dead").unwrap().unwrap();
        f.clock.advance(4_000);
        f.farm.heartbeat(lease.lease_id).unwrap();
        f.clock.advance(4_000);
        assert_eq!(
            f.farm.expire_leases().unwrap(),
            0,
            "the heartbeat extended it"
        );
        f.clock.advance(1_001);
        assert_eq!(f.farm.expire_leases().unwrap(), 1);
        let err = f.farm.heartbeat(lease.lease_id).unwrap_err();
        assert!(
            matches!(&err, FarmError::Stale(m) if m.contains("expired")),
            "{err}"
        );
        assert!(matches!(
            f.farm.complete(lease.lease_id, &blank(lease.rect, 0.0)),
            Err(FarmError::Stale(_))
        ));
        let again = f.farm.lease("alive").unwrap().unwrap();
        assert_eq!(again.tile, lease.tile, "the lapsed tile comes first");
        assert!(f.farm.job(job.id).unwrap().failures.is_empty());
    }

    #[test]
    fn a_frame_range_job_tiles_every_frame_and_assembles_each_on_its_own() {
        let f = fixture(FarmConfig::default());
        let mut new = new_job("anim");
        new.spec.frames = Some(tracer_core::FrameRange::new(3, 5).unwrap());
        let job = f.farm.submit(new).unwrap();
        assert_eq!(job.tiles_total, 3 * 4);
        assert!(matches!(
            f.farm.frame_images(job.id),
            Err(FarmError::Conflict(_))
        ));
        let mut last = None;
        for i in 0..12 {
            let lease = f.farm.lease(&format!("w{i}")).unwrap().unwrap();
            // Tiles go frame by frame, and the lease tells the worker which frame.
            let frame = 3 + lease.tile / 4;
            assert_eq!(lease.settings.frame, frame);
            let tiles = f.farm.tiles(job.id).unwrap();
            assert_eq!(tiles[lease.tile as usize].frame, frame);
            let done = f
                .farm
                .complete(lease.lease_id, &blank(lease.rect, frame as f32 / 10.0))
                .unwrap();
            last = done.1;
        }
        assert_eq!(last, Some(job.id));
        f.farm.assemble(job.id).unwrap();
        let frames = f.farm.frame_images(job.id).unwrap();
        assert_eq!(
            frames.iter().map(|(n, _)| *n).collect::<Vec<_>>(),
            [3, 4, 5]
        );
        for (frame, png) in &frames {
            let image = tracer_core::Image::from_png_bytes(png).unwrap();
            let expected = (*frame as f32 / 10.0 * 255.0 + 1e-4).floor() / 255.0;
            assert_eq!(image.pixel(9, 9), [expected; 3], "frame {frame}");
        }
        assert_eq!(f.farm.image(job.id, None).unwrap(), frames[0].1);
        assert_eq!(f.farm.image(job.id, Some(5)).unwrap(), frames[2].1);
        assert!(matches!(
            f.farm.image(job.id, Some(6)),
            Err(FarmError::NotFound(_))
        ));
    }

    #[test]
    fn a_job_whose_image_cannot_be_built_fails_instead_of_running_forever() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        for i in 0..4 {
            let lease = f.farm.lease(&format!("w{i}")).unwrap().unwrap();
            f.farm
                .complete(lease.lease_id, &blank(lease.rect, 0.5))
                .unwrap();
        }
        let tile = f._dir.path().join(format!("jobs/{}/tiles/2.f32", job.id));
        std::fs::remove_file(&tile).unwrap();
        assert!(f.farm.assemble(job.id).is_err());
        let info = f.farm.job(job.id).unwrap();
        assert_eq!(info.state, JobState::Failed);
        assert!(
            info.error
                .as_deref()
                .unwrap_or("")
                .contains("assembling the image failed"),
            "{:?}",
            info.error
        );
    }

    #[test]
    fn finished_tiles_are_on_disk_and_the_job_assembles() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let mut last = None;
        for i in 0..4 {
            let lease = f.farm.lease(&format!("w{i}")).unwrap().unwrap();
            let done = f
                .farm
                .complete(lease.lease_id, &blank(lease.rect, i as f32 / 4.0))
                .unwrap();
            assert_eq!((done.0.tiles_done, done.0.tiles_total), (i + 1, 4));
            last = done.1;
        }
        assert_eq!(last, Some(job.id));
        assert_eq!(f.farm.tile_writes(), 4);
        f.farm.assemble(job.id).unwrap();
        let info = f.farm.job(job.id).unwrap();
        assert_eq!((info.state, info.tiles_done), (JobState::Done, 4));
        let png = f.farm.image(job.id, None).unwrap();
        let image = tracer_core::Image::from_png_bytes(&png).unwrap();
        assert_eq!(image.pixel(0, 0), [0.0; 3]);
        assert_eq!(image.pixel(15, 15), [191.0 / 255.0; 3]);
        assert!(f.farm.lease("w9").unwrap().is_none());
    }

    #[test]
    fn pixels_of_the_wrong_size_are_refused() {
        let f = fixture(FarmConfig::default());
        f.farm.submit(new_job("a")).unwrap();
        let lease = f.farm.lease("w").unwrap().unwrap();
        let err = f.farm.complete(lease.lease_id, &[0u8; 10]).unwrap_err();
        assert!(
            matches!(&err, FarmError::BadRequest(e) if e.error.contains("768 bytes")),
            "{err}"
        );
        // The lease is still good for a correct upload.
        assert!(finish(&f.farm, &lease).is_none());
    }

    #[test]
    fn a_tile_failing_on_three_workers_fails_its_job() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let report = FailureReport {
            error: "out of memory".into(),
            scene: false,
        };
        for (i, w) in ["w1", "w2", "w3"].iter().enumerate() {
            let lease = f.farm.lease(w).unwrap().unwrap();
            assert_eq!(lease.tile, 0, "the failed tile is requeued first");
            let info = f.farm.fail(lease.lease_id, &report).unwrap();
            assert_eq!(info.failures.len(), i + 1);
            if i < 2 {
                assert_eq!(info.state, JobState::Running);
                // w1 is not handed the tile it failed on while others exist.
                let other = f.farm.lease("w1").unwrap().unwrap();
                assert_ne!(other.tile, 0);
                f.farm.hand_back(other.lease_id).unwrap();
            } else {
                assert_eq!(info.state, JobState::Failed);
                assert!(info.error.unwrap().contains("out of memory"));
            }
        }
        assert!(f.farm.lease("w4").unwrap().is_none());
        // One click requeues it.
        let retried = f.farm.retry(job.id).unwrap();
        assert_eq!(retried.state, JobState::Running);
        assert!(retried.failures.is_empty());
        assert_eq!(f.farm.lease("w4").unwrap().unwrap().tile, 0);
    }

    #[test]
    fn a_lone_worker_gives_up_after_the_attempt_limit() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let report = FailureReport {
            error: "boom".into(),
            scene: false,
        };
        // It tries the other tiles first, then comes back: 4 tiles × 5 attempts at most.
        let mut tries = 0;
        while let Some(lease) = f.farm.lease("only").unwrap() {
            f.farm.fail(lease.lease_id, &report).unwrap();
            tries += 1;
            assert!(tries <= 20);
        }
        let info = f.farm.job(job.id).unwrap();
        assert_eq!(info.state, JobState::Failed);
        assert!(info.error.unwrap().contains("5 attempts"));
    }

    #[test]
    fn a_scene_that_does_not_load_fails_the_job_at_once() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let l1 = f.farm.lease("w1").unwrap().unwrap();
        let l2 = f.farm.lease("w2").unwrap().unwrap();
        let report = FailureReport {
            error: "s.scene:3:4: unknown material".into(),
            scene: true,
        };
        let info = f.farm.fail(l1.lease_id, &report).unwrap();
        assert_eq!(info.state, JobState::Failed);
        assert!(info.error.unwrap().contains("s.scene:3:4"));
        assert!(matches!(
            f.farm.heartbeat(l2.lease_id),
            Err(FarmError::Stale(_))
        ));
        assert!(matches!(f.farm.cancel(job.id), Err(FarmError::Conflict(_))));
    }

    #[test]
    fn cancelling_revokes_running_tiles() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let lease = f.farm.lease("w").unwrap().unwrap();
        let info = f.farm.cancel(job.id).unwrap();
        assert_eq!(info.state, JobState::Cancelled);
        let err = f.farm.heartbeat(lease.lease_id).unwrap_err();
        assert!(err.to_string().contains("cancelled"), "{err}");
        assert!(f.farm.lease("w").unwrap().is_none());
        assert!(matches!(f.farm.job(99), Err(FarmError::NotFound(_))));
    }

    #[test]
    fn idle_workers_copy_stragglers_and_the_first_result_wins() {
        let f = fixture(FarmConfig::default());
        f.farm.submit(new_job("a")).unwrap();
        let slow = f.farm.lease("slow").unwrap().unwrap();
        for w in ["a", "b", "c"] {
            let l = f.farm.lease(w).unwrap().unwrap();
            f.clock.advance(100);
            finish(&f.farm, &l);
        }
        // Typical tile time is 100 ms; a copy needs the original to be 1 s old.
        assert!(f.farm.lease("idle").unwrap().is_none());
        f.clock.advance(1_000);
        let copy = f.farm.lease("idle").unwrap().unwrap();
        assert_eq!(copy.tile, slow.tile);
        assert_ne!(copy.lease_id, slow.lease_id);
        assert!(f.farm.lease("idle2").unwrap().is_none(), "one copy at most");
        assert!(finish(&f.farm, &copy).is_some());
        let err = f
            .farm
            .complete(slow.lease_id, &blank(slow.rect, 0.5))
            .unwrap_err();
        assert!(err.to_string().contains("finished the tile first"), "{err}");
    }

    #[test]
    fn no_stragglers_when_disabled() {
        let f = fixture(FarmConfig {
            stragglers: false,
            ..FarmConfig::default()
        });
        f.farm.submit(new_job("a")).unwrap();
        let _slow = f.farm.lease("slow").unwrap().unwrap();
        for w in ["a", "b", "c"] {
            let l = f.farm.lease(w).unwrap().unwrap();
            finish(&f.farm, &l);
        }
        f.clock.advance(60_000);
        f.farm.heartbeat(_slow.lease_id).unwrap();
        assert!(f.farm.lease("idle").unwrap().is_none());
    }

    #[test]
    fn handing_back_requeues_without_a_failure() {
        let f = fixture(FarmConfig::default());
        let job = f.farm.submit(new_job("a")).unwrap();
        let lease = f.farm.lease("w").unwrap().unwrap();
        f.farm.hand_back(lease.lease_id).unwrap();
        assert!(matches!(
            f.farm.hand_back(lease.lease_id),
            Err(FarmError::Stale(_))
        ));
        assert_eq!(f.farm.lease("v").unwrap().unwrap().tile, lease.tile);
        assert!(f.farm.job(job.id).unwrap().failures.is_empty());
    }

    #[test]
    fn a_restart_resumes_jobs_and_honours_old_leases() {
        let dir = tempfile::tempdir().unwrap();
        let clock = Arc::new(ManualClock::new(1_000_000));
        let (job, held) = {
            let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
            let job = farm.submit(new_job("a")).unwrap();
            let done = farm.lease("w1").unwrap().unwrap();
            finish(&farm, &done);
            let held = farm.lease("w2").unwrap().unwrap();
            (job, held)
            // Dropped without any shutdown, like a killed process.
        };
        clock.advance(60_000);
        let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
        assert_eq!(farm.epoch(), 2);
        let info = farm.job(job.id).unwrap();
        assert_eq!(
            (info.state, info.tiles_done, info.tiles_running),
            (JobState::Running, 1, 1)
        );
        // The lease from before the restart is honoured within the grace period...
        farm.heartbeat(held.lease_id).unwrap();
        // ...and asking again returns it, not a new tile.
        assert_eq!(farm.lease("w2").unwrap().unwrap().lease_id, held.lease_id);
        let next = farm.lease("w3").unwrap().unwrap();
        assert_eq!(next.tile, 2, "tile 0 is done and tile 1 is held");
        assert!(
            next.lease_id > held.lease_id,
            "lease ids never repeat across restarts"
        );
        finish(&farm, &held);
        finish(&farm, &next);
        let last = farm.lease("w3").unwrap().unwrap();
        assert_eq!(finish(&farm, &last), Some(job.id));
        assert_eq!(
            farm.tile_writes(),
            3,
            "the finished tile was not rendered again"
        );
        farm.assemble(job.id).unwrap();
        drop(farm);
        let farm = Farm::open(dir.path(), FarmConfig::default(), clock).unwrap();
        assert_eq!(farm.job(job.id).unwrap().state, JobState::Done);
        assert!(!farm.image(job.id, None).unwrap().is_empty());
    }

    #[test]
    fn a_job_whose_last_tile_landed_before_a_crash_is_assembled_on_start() {
        let dir = tempfile::tempdir().unwrap();
        let clock = Arc::new(ManualClock::new(5));
        let job = {
            let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
            let job = farm.submit(new_job("a")).unwrap();
            for w in ["a", "b", "c", "d"] {
                let l = farm.lease(w).unwrap().unwrap();
                finish(&farm, &l);
            }
            job
        };
        let farm = Farm::open(dir.path(), FarmConfig::default(), clock).unwrap();
        assert_eq!(farm.job(job.id).unwrap().state, JobState::Done);
    }
}
