//! The farm's state and every transition of a tile, a job, a lease and a worker identity.
//!
//! Tile life: queued → leased (one lease, or two while a straggler copy runs) → done; a lapsed
//! or handed-back lease puts its tile back in the queue without counting a failure; a reported
//! failure counts against the tile (shown as failed while it waits) and may fail its job; a job
//! that ends (failed, cancelled) leaves its unfinished tiles idle. Job life: queued → running
//! (first lease) → done (assembled) | failed | cancelled; failed → running again on retry.
//!
//! Every transition writes its whole change to SQLite in ONE transaction first and touches
//! memory only once that commit succeeded: a failed write answers an error and leaves the
//! state exactly as it was.

use std::collections::{BTreeMap, HashMap};

use protocol::{JobInfo, JobState, TileFailure, WorkerIdentity, WorkerLease};

use super::job::Job;
use super::workers::Registry;
use super::{FarmError, Result};
use crate::store::{Db, JobRow, StoredJob, StoredLease};

#[derive(Clone, Debug)]
pub struct LiveLease {
    pub job_id: u64,
    pub tile: u32,
    pub worker_id: u64,
    pub granted_ms: u64,
    pub deadline_ms: u64,
}

/// Why recent leases ended, kept for clear 409 messages (bounded).
const ENDED_KEEP: usize = 100_000;

pub struct State {
    pub db: Db,
    pub jobs: BTreeMap<u64, Job>,
    pub leases: HashMap<u64, LiveLease>,
    pub by_worker: HashMap<u64, u64>,
    pub next_lease: u64,
    pub ended: HashMap<u64, &'static str>,
    pub workers: Registry,
}

/// What a completed tile changed.
#[derive(Debug, PartialEq, Eq)]
pub struct Completed {
    pub tiles_done: u32,
    pub tiles_total: u32,
    /// This was the job's last tile: its image is to be assembled now.
    pub last: bool,
}

/// What a reported failure changed.
#[derive(Debug)]
pub struct Failed {
    pub info: JobInfo,
    pub requeued: bool,
}

/// How many failures a tile survives.
#[derive(Clone, Copy, Debug)]
pub struct FailureLimits {
    pub max_workers: usize,
    pub max_attempts: usize,
}

impl State {
    pub fn new(db: Db, next_lease: u64, workers: Registry) -> State {
        State {
            db,
            jobs: BTreeMap::new(),
            leases: HashMap::new(),
            by_worker: HashMap::new(),
            next_lease,
            ended: HashMap::new(),
            workers,
        }
    }

    pub fn job(&self, id: u64) -> Result<&Job> {
        self.jobs
            .get(&id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {id}")))
    }

    /// The job, if it can still change state; a finished one is a conflict.
    fn active_job(&self, id: u64) -> Result<&Job> {
        let job = self.job(id)?;
        if !job.is_active() {
            return Err(FarmError::Conflict(format!(
                "job {id} is already {}",
                job.state.as_str()
            )));
        }
        Ok(job)
    }

    fn job_mut(&mut self, id: u64) -> Result<&mut Job> {
        self.jobs
            .get_mut(&id)
            .ok_or_else(|| FarmError::NotFound(format!("no job {id}")))
    }

    pub fn stale(&self, id: u64) -> FarmError {
        let why = self.ended.get(&id).copied().unwrap_or("unknown or expired");
        FarmError::Stale(format!("lease {id} is no longer valid: {why}"))
    }

    pub fn live(&self, id: u64) -> Result<&LiveLease> {
        self.leases.get(&id).ok_or_else(|| self.stale(id))
    }

    /// The names of the workers holding leases on a tile.
    pub fn holders(&self, job: &Job, tile: u32) -> Vec<String> {
        job.tiles
            .leases(tile)
            .iter()
            .filter_map(|l| self.leases.get(l))
            .map(|l| self.workers.name(l.worker_id))
            .collect()
    }

    pub fn worker_lease(&self, worker_id: u64) -> Option<WorkerLease> {
        let lease = self.leases.get(self.by_worker.get(&worker_id)?)?;
        Some(WorkerLease {
            job_id: lease.job_id,
            tile: lease.tile,
        })
    }

    /// Drops a lease from memory (its row is already gone) and remembers why.
    fn forget_lease(&mut self, id: u64, why: &'static str) -> Option<LiveLease> {
        let lease = self.leases.remove(&id)?;
        if self.by_worker.get(&lease.worker_id) == Some(&id) {
            self.by_worker.remove(&lease.worker_id);
        }
        if let Some(job) = self.jobs.get_mut(&lease.job_id) {
            job.tiles.remove_lease(lease.tile, id);
        }
        if self.ended.len() >= ENDED_KEEP {
            self.ended.clear();
        }
        self.ended.insert(id, why);
        Some(lease)
    }

    /// Requeues a tile of an active job that has no live lease left.
    fn requeue(&mut self, job_id: u64, tile: u32) -> bool {
        match self.jobs.get_mut(&job_id) {
            Some(job) if job.is_active() => {
                job.tiles.requeue(tile);
                job.tiles.is_queued(tile)
            }
            _ => false,
        }
    }

    /// A new job, its tiles all queued. `job` was built (tile book allocated) before the
    /// caller took the lock; its id is the one SQLite gives it.
    pub fn add_job(&mut self, stored: &StoredJob, mut job: Job) -> Result<u64> {
        let id = self.db.insert_job(stored)?;
        job.id = id;
        self.jobs.insert(id, job);
        Ok(id)
    }

    /// Leased: a tile of an active job goes to a worker (queued → leased, or leased →
    /// leased twice for a straggler copy). The job starts with its first lease.
    pub fn grant(
        &mut self,
        job_id: u64,
        tile: u32,
        worker_id: u64,
        now: u64,
        timeout_ms: u64,
    ) -> Result<u64> {
        let job = self.job(job_id)?;
        if !job.is_active() || !job.tiles.contains(tile) || job.tiles.is_done(tile) {
            return Err(FarmError::Conflict(format!(
                "job {job_id} tile {tile} cannot be leased"
            )));
        }
        let starts = job.state == JobState::Queued;
        let id = self.next_lease;
        let row = StoredLease {
            id,
            job_id,
            tile,
            worker: self.workers.name(worker_id),
            worker_id,
            granted_ms: now,
        };
        let started = starts.then_some(JobRow {
            state: JobState::Running,
            error: None,
            started_ms: Some(now),
            finished_ms: None,
        });
        self.db.grant_lease(&row, started.as_ref())?;
        // Committed: now memory follows.
        self.next_lease += 1;
        let job = self.job_mut(job_id)?;
        job.tiles.add_lease(tile, id);
        if starts {
            job.state = JobState::Running;
            job.started_ms = Some(now);
        }
        self.leases.insert(
            id,
            LiveLease {
                job_id,
                tile,
                worker_id,
                granted_ms: now,
                deadline_ms: now + timeout_ms,
            },
        );
        self.by_worker.insert(worker_id, id);
        Ok(id)
    }

    /// Done: the lease's tile is finished (its pixels are on disk); every other lease on it is
    /// revoked. The job's last tile says so, for assembly to start.
    pub fn complete(&mut self, lease_id: u64, now: u64) -> Result<Completed> {
        let lease = self.live(lease_id)?.clone();
        self.db.complete_tile(lease.job_id, lease.tile)?;
        let others: Vec<u64> = self
            .job(lease.job_id)?
            .tiles
            .leases(lease.tile)
            .iter()
            .copied()
            .filter(|l| *l != lease_id)
            .collect();
        for other in others {
            self.forget_lease(other, "another worker finished the tile first");
        }
        self.forget_lease(lease_id, "the tile is finished");
        if let Some(worker) = self.workers.seen(lease.worker_id, now) {
            worker.tiles_done += 1;
        }
        let job = self.job_mut(lease.job_id)?;
        job.tiles.mark_done(lease.tile);
        job.tile_ms_total += now.saturating_sub(lease.granted_ms);
        job.tiles_timed += 1;
        let last = job.tiles.all_done() && job.is_active() && !job.assembling;
        if last {
            job.assembling = true;
        }
        Ok(Completed {
            tiles_done: job.tiles.done_count(),
            tiles_total: job.total(),
            last,
        })
    }

    /// Failed: the worker reports the tile failed. The tile waits in the queue again, unless
    /// the failure is fatal to the job (a scene that does not load, or the tile's failure
    /// limits reached): then the job fails.
    pub fn fail(
        &mut self,
        lease_id: u64,
        error: &str,
        scene: bool,
        now: u64,
        limits: FailureLimits,
    ) -> Result<Failed> {
        let lease = self.live(lease_id)?.clone();
        let job = self.job(lease.job_id)?;
        // The tile's counts as they will be, computed before anything changes.
        let mut counts = job.tiles.failures(lease.tile).cloned().unwrap_or_default();
        counts.attempts += 1;
        if !counts.workers.contains(&lease.worker_id) {
            counts.workers.push(lease.worker_id);
        }
        let fatal = if !job.is_active() {
            None
        } else if scene {
            Some(format!("the scene could not be loaded: {error}"))
        } else if counts.workers.len() >= limits.max_workers
            || counts.attempts as usize >= limits.max_attempts
        {
            Some(format!(
                "tile {} failed on {} workers ({} attempts): {error}",
                lease.tile,
                counts.workers.len(),
                counts.attempts
            ))
        } else {
            None
        };
        let failure = TileFailure {
            tile: lease.tile,
            worker: self.workers.name(lease.worker_id),
            worker_id: lease.worker_id,
            error: error.to_string(),
        };
        let end = fatal.map(|error| JobRow {
            state: JobState::Failed,
            error: Some(error),
            started_ms: job.started_ms,
            finished_ms: Some(now),
        });
        self.db
            .record_failure(lease_id, lease.job_id, &failure, now, end.as_ref())?;
        self.forget_lease(lease_id, "the worker reported a failure");
        let job = self.job_mut(lease.job_id)?;
        job.tiles.record_failure(lease.tile, lease.worker_id);
        job.failures.push(failure);
        let requeued = match end {
            Some(row) => {
                tracing::error!(
                    "job {}: failed: {}",
                    lease.job_id,
                    row.error.as_deref().unwrap_or("")
                );
                self.end_job_in_memory(lease.job_id, row, "the job failed");
                false
            }
            None => self.requeue(lease.job_id, lease.tile),
        };
        Ok(Failed {
            info: self.job(lease.job_id)?.info(now),
            requeued,
        })
    }

    /// Queued again: leases end without a result (handed back by a stopping worker, or
    /// lapsed without a heartbeat). Returns each lease with whether its tile was requeued.
    pub fn release(&mut self, ids: &[u64], why: &'static str) -> Result<Vec<(LiveLease, bool)>> {
        for id in ids {
            self.live(*id)?;
        }
        self.db.end_leases(ids)?;
        let mut released = Vec::with_capacity(ids.len());
        for id in ids {
            if let Some(lease) = self.forget_lease(*id, why) {
                let requeued = self.requeue(lease.job_id, lease.tile);
                released.push((lease, requeued));
            }
        }
        Ok(released)
    }

    fn end_job_in_memory(&mut self, job_id: u64, row: JobRow, why: &'static str) {
        let ids: Vec<u64> = self
            .leases
            .iter()
            .filter(|(_, l)| l.job_id == job_id)
            .map(|(id, _)| *id)
            .collect();
        for id in ids {
            self.forget_lease(id, why);
        }
        if let Some(job) = self.jobs.get_mut(&job_id) {
            job.tiles.clear_queue();
            job.state = row.state;
            job.error = row.error;
            job.finished_ms = row.finished_ms;
            job.assembling = false;
        }
    }

    /// Cancelled or failed: an active job ends, its leases revoked and its queue dropped.
    pub fn end_job(
        &mut self,
        job_id: u64,
        state: JobState,
        error: Option<String>,
        now: u64,
        why: &'static str,
    ) -> Result<()> {
        let job = self.active_job(job_id)?;
        let row = JobRow {
            state,
            error,
            started_ms: job.started_ms,
            finished_ms: Some(now),
        };
        self.db.finish_job(job_id, &row)?;
        self.end_job_in_memory(job_id, row, why);
        Ok(())
    }

    /// A progressive job's current pass is cut short (its time is up): its leases are
    /// revoked and its queue dropped; the pass end then keeps the blocks its landed tiles
    /// finished and the job's image is assembled. False if the job is not a progressive one
    /// that is still rendering passes.
    pub fn stop_passes(&mut self, job_id: u64) -> Result<bool> {
        let job = self.job(job_id)?;
        if !job.is_active() || job.assembling || job.progress.is_none() {
            return Ok(false);
        }
        let ids: Vec<u64> = self
            .leases
            .iter()
            .filter(|(_, l)| l.job_id == job_id)
            .map(|(id, _)| *id)
            .collect();
        if !ids.is_empty() {
            self.db.end_leases(&ids)?;
        }
        for id in ids {
            self.forget_lease(id, "the job's time limit passed");
        }
        let job = self.job_mut(job_id)?;
        job.tiles.clear_queue();
        // The tiles that landed stay pending: the pass end keeps the blocks they finished.
        job.assembling = true;
        Ok(true)
    }

    /// Done: the job's image is written.
    pub fn mark_done(&mut self, job_id: u64, now: u64) -> Result<()> {
        let job = self.active_job(job_id)?;
        let row = JobRow {
            state: JobState::Done,
            error: None,
            started_ms: job.started_ms,
            finished_ms: Some(now),
        };
        self.db.set_job_state(job_id, &row)?;
        self.end_job_in_memory(job_id, row, "the job is done");
        // A progressive job's image is stored: its sums are not needed in memory any more.
        if let Some(progress) = self.job_mut(job_id)?.progress.as_mut() {
            progress.sums.data = Vec::new();
        }
        Ok(())
    }

    /// Running again: a failed job's unfinished tiles are requeued with fresh failure counts.
    pub fn retry(&mut self, job_id: u64) -> Result<()> {
        let job = self.job(job_id)?;
        if job.state != JobState::Failed {
            return Err(FarmError::Conflict(format!(
                "job {job_id} is {}; only failed jobs can be retried",
                job.state.as_str()
            )));
        }
        let state = if job.started_ms.is_some() {
            JobState::Running
        } else {
            JobState::Queued
        };
        let row = JobRow {
            state,
            error: None,
            started_ms: job.started_ms,
            finished_ms: None,
        };
        self.db.retry_job(job_id, &row)?;
        let job = self.job_mut(job_id)?;
        job.failures.clear();
        job.tiles.clear_failures();
        job.state = state;
        job.error = None;
        job.finished_ms = None;
        job.tiles.requeue_all();
        Ok(())
    }

    /// A new worker identity. A full registry first forgets its longest-silent worker that
    /// holds no lease.
    pub fn register(&mut self, name: &str, now: u64, max_workers: usize) -> Result<WorkerIdentity> {
        if self.workers.len() >= max_workers {
            let by_worker = &self.by_worker;
            let Some(evict) = self
                .workers
                .eviction_candidate(|id| by_worker.contains_key(&id))
            else {
                return Err(FarmError::Conflict(format!(
                    "the coordinator already knows {max_workers} workers, all rendering \
                     (--max-workers)"
                )));
            };
            self.db.forget_worker(evict)?;
            self.workers.remove(evict);
        }
        let id = self.db.register_worker(name, now)?;
        self.workers.insert(id, name.to_string(), now);
        Ok(WorkerIdentity {
            worker_id: id,
            name: name.to_string(),
        })
    }
}

#[cfg(test)]
mod tests {
    use super::super::tiles::{TileBook, TileGrid};
    use super::*;
    use protocol::{JobSpec, TileState};

    const TIMEOUT: u64 = 5_000;
    const LIMITS: FailureLimits = FailureLimits {
        max_workers: 3,
        max_attempts: 5,
    };

    /// A new job as a submission stores it: queued, nothing rendered.
    fn queued_stored_job(name: &str, spec: JobSpec) -> StoredJob {
        StoredJob {
            id: 0,
            name: name.into(),
            scene_file: format!("{name}.scene"),
            scene_hash: "0".repeat(64),
            spec,
            state: JobState::Queued,
            error: None,
            created_ms: 0,
            started_ms: None,
            finished_ms: None,
            assets: vec![],
            tiles_done: vec![],
            failures: vec![],
        }
    }

    /// A state with one queued 4-tile job and two registered workers (ids 1 and 2).
    fn state() -> (State, u64) {
        let mut state = State::new(Db::open_in_memory().unwrap(), 1 << 32, Registry::default());
        state.register("w", 0, 100).unwrap();
        state.register("w", 0, 100).unwrap();
        let mut spec = JobSpec::default();
        spec.render.width = 16;
        spec.render.height = 16;
        spec.tile_size = 8;
        let stored = queued_stored_job("a", spec.clone());
        let grid = TileGrid::new(&spec);
        let job = Job {
            id: 0,
            name: stored.name.clone(),
            scene_file: stored.scene_file.clone(),
            scene_hash: stored.scene_hash.clone(),
            spec,
            state: JobState::Queued,
            error: None,
            created_ms: 0,
            started_ms: None,
            finished_ms: None,
            assets: vec![],
            grid,
            tiles: TileBook::new(grid.total_u64() as u32),
            failures: vec![],
            tile_ms_total: 0,
            tiles_timed: 0,
            assembling: false,
            progress: None,
        };
        let id = state.add_job(&stored, job).unwrap();
        (state, id)
    }

    fn tile_state(state: &State, job: u64, tile: u32) -> TileState {
        state.jobs[&job].tile_info(tile, vec![]).state
    }

    /// Everything observable about the state, to show a failed transition changed nothing.
    fn snapshot(state: &State) -> String {
        let job = &state.jobs.values().next().unwrap();
        format!(
            "{:?} {:?} {:?} {:?} {} {:?} {:?}",
            job.info(0),
            (0..4)
                .map(|t| job.tile_info(t, state.holders(job, t)))
                .collect::<Vec<_>>(),
            job.tiles.queued().collect::<Vec<_>>(),
            {
                let mut l: Vec<_> = state.leases.keys().collect();
                l.sort();
                l
            },
            state.next_lease,
            {
                let mut w: Vec<_> = state.by_worker.iter().collect();
                w.sort();
                w
            },
            state.db.load_leases().unwrap()
        )
    }

    #[test]
    fn queued_to_leased_starts_the_job_in_one_write() {
        let (mut s, job) = state();
        assert_eq!(tile_state(&s, job, 0), TileState::Queued);
        let lease = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        assert_eq!(tile_state(&s, job, 0), TileState::Leased);
        assert_eq!(s.jobs[&job].state, JobState::Running);
        assert_eq!(s.jobs[&job].tiles.queued().next(), Some(1));
        assert_eq!(s.by_worker[&1], lease);
        assert_eq!(s.db.load_leases().unwrap()[0].id, lease);
    }

    #[test]
    fn queued_to_leased_with_a_failed_write_changes_nothing_and_does_not_panic() {
        let (mut s, job) = state();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(matches!(
            s.grant(job, 0, 1, 10, TIMEOUT),
            Err(FarmError::Store(_))
        ));
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
        assert_eq!(s.jobs[&job].state, JobState::Queued);
        // The state is still whole: the tile is handed out normally afterwards.
        let lease = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        assert_eq!(lease, 1 << 32, "the failed grant used no id");
    }

    #[test]
    fn leased_to_leased_straggler_copy_keeps_both_leases() {
        let (mut s, job) = state();
        let first = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let copy = s.grant(job, 0, 2, 20, TIMEOUT).unwrap();
        assert_eq!(s.jobs[&job].tiles.leases(0), [first, copy]);
        assert_eq!(s.holders(&s.jobs[&job], 0).len(), 2);
    }

    #[test]
    fn leased_to_done_revokes_the_other_copy() {
        let (mut s, job) = state();
        let first = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let copy = s.grant(job, 0, 2, 20, TIMEOUT).unwrap();
        let done = s.complete(copy, 30).unwrap();
        assert_eq!(
            (done.tiles_done, done.tiles_total, done.last),
            (1, 4, false)
        );
        assert_eq!(tile_state(&s, job, 0), TileState::Done);
        let err = s.complete(first, 40).unwrap_err();
        assert!(err.to_string().contains("finished the tile first"), "{err}");
        assert!(s.db.load_leases().unwrap().is_empty());
    }

    #[test]
    fn leased_to_done_for_the_last_tile_asks_for_assembly_once() {
        let (mut s, job) = state();
        for tile in 0..4 {
            let lease = s.grant(job, tile, 1, 10, TIMEOUT).unwrap();
            let done = s.complete(lease, 20).unwrap();
            assert_eq!(done.last, tile == 3);
        }
        assert!(s.jobs[&job].assembling);
        s.mark_done(job, 30).unwrap();
        assert_eq!(s.jobs[&job].state, JobState::Done);
        assert!(!s.jobs[&job].assembling);
    }

    #[test]
    fn leased_to_done_with_a_failed_write_changes_nothing() {
        let (mut s, job) = state();
        let lease = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(s.complete(lease, 20).is_err());
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
        assert_eq!(tile_state(&s, job, 0), TileState::Leased);
    }

    #[test]
    fn leased_to_queued_when_handed_back_or_lapsed_without_a_failure() {
        let (mut s, job) = state();
        let a = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let b = s.grant(job, 1, 2, 10, TIMEOUT).unwrap();
        let released = s.release(&[a, b], "handed back").unwrap();
        assert!(released.iter().all(|(_, requeued)| *requeued));
        assert_eq!(tile_state(&s, job, 0), TileState::Queued);
        assert_eq!(
            s.jobs[&job].tiles.queued().collect::<Vec<_>>(),
            [0, 1, 2, 3]
        );
        assert!(s.jobs[&job].failures.is_empty());
        assert!(matches!(s.release(&[a], "again"), Err(FarmError::Stale(_))));
    }

    #[test]
    fn leased_to_queued_with_a_failed_write_changes_nothing() {
        let (mut s, _) = state();
        let a = s.grant(1, 0, 1, 10, TIMEOUT).unwrap();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(s.release(&[a], "lapsed").is_err());
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
    }

    #[test]
    fn leased_to_failed_counts_the_failure_and_requeues() {
        let (mut s, job) = state();
        let a = s.grant(job, 2, 1, 10, TIMEOUT).unwrap();
        let failed = s.fail(a, "boom", false, 20, LIMITS).unwrap();
        assert!(failed.requeued);
        assert_eq!(failed.info.state, JobState::Running);
        assert_eq!(tile_state(&s, job, 2), TileState::Failed);
        assert!(s.jobs[&job].tiles.is_queued(2));
        assert_eq!(failed.info.failures[0].worker_id, 1);
    }

    #[test]
    fn failed_to_leased_on_another_worker() {
        let (mut s, job) = state();
        let a = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        s.fail(a, "boom", false, 20, LIMITS).unwrap();
        s.grant(job, 0, 2, 30, TIMEOUT).unwrap();
        assert_eq!(tile_state(&s, job, 0), TileState::Leased);
        assert_eq!(s.jobs[&job].tile_info(0, vec![]).attempts, 1);
    }

    #[test]
    fn leased_to_failed_fails_the_job_after_the_limits_and_leaves_tiles_idle() {
        let (mut s, job) = state();
        let other = s.grant(job, 3, 2, 10, TIMEOUT).unwrap();
        for attempt in 1..=5 {
            let lease = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
            let failed = s.fail(lease, "boom", false, 20, LIMITS).unwrap();
            assert_eq!(failed.info.state == JobState::Failed, attempt == 5);
        }
        let info = s.jobs[&job].info(30);
        assert!(info.error.unwrap().contains("5 attempts"));
        assert_eq!(tile_state(&s, job, 1), TileState::Idle);
        assert!(
            matches!(s.complete(other, 40), Err(FarmError::Stale(_))),
            "its leases are revoked"
        );
        assert!(s.db.load_leases().unwrap().is_empty());
    }

    #[test]
    fn leased_to_failed_with_a_failed_write_changes_nothing() {
        let (mut s, _) = state();
        let a = s.grant(1, 0, 1, 10, TIMEOUT).unwrap();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(s.fail(a, "boom", true, 20, LIMITS).is_err());
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
    }

    #[test]
    fn running_to_cancelled_leaves_unfinished_tiles_idle() {
        let (mut s, job) = state();
        let a = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        s.end_job(job, JobState::Cancelled, None, 20, "the job was cancelled")
            .unwrap();
        assert_eq!(tile_state(&s, job, 0), TileState::Idle);
        assert_eq!(s.jobs[&job].tiles.queued().next(), None);
        let err = s.complete(a, 30).unwrap_err();
        assert!(err.to_string().contains("cancelled"), "{err}");
        assert!(matches!(
            s.end_job(job, JobState::Cancelled, None, 20, "again"),
            Err(FarmError::Conflict(_))
        ));
    }

    #[test]
    fn running_to_cancelled_with_a_failed_write_changes_nothing() {
        let (mut s, job) = state();
        s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(s.end_job(job, JobState::Cancelled, None, 20, "x").is_err());
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
    }

    #[test]
    fn failed_to_running_on_retry_requeues_with_fresh_counts() {
        let (mut s, job) = state();
        let a = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        s.complete(a, 20).unwrap();
        let b = s.grant(job, 1, 1, 10, TIMEOUT).unwrap();
        s.fail(b, "scene", true, 30, LIMITS).unwrap();
        assert_eq!(s.jobs[&job].state, JobState::Failed);
        s.retry(job).unwrap();
        let j = &s.jobs[&job];
        assert_eq!((j.state, j.failures.len()), (JobState::Running, 0));
        assert_eq!(j.tiles.queued().collect::<Vec<_>>(), [1, 2, 3]);
        assert!(matches!(s.retry(job), Err(FarmError::Conflict(_))));
    }

    #[test]
    fn registering_issues_distinct_ids_for_one_name_and_evicts_when_full() {
        let (mut s, job) = state();
        let lease = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        let c = s.register("w", 5, 2).unwrap();
        assert!(c.worker_id > 2);
        // Worker 1 holds a lease, so worker 2 (silent the longest) was forgotten.
        assert!(s.workers.contains(1) && !s.workers.contains(2));
        assert_eq!(s.live(lease).unwrap().worker_id, 1);
    }

    #[test]
    fn new_to_queued_stores_the_job_before_it_is_listed() {
        let (mut s, first) = state();
        let stored = queued_stored_job("b", s.jobs[&first].spec.clone());
        let job = || Job {
            tiles: TileBook::new(4),
            ..job_like(&s.jobs[&first])
        };
        let (attempt, retry) = (job(), job());
        s.db.fail_writes(true);
        assert!(s.add_job(&stored, attempt).is_err());
        s.db.fail_writes(false);
        assert_eq!(s.jobs.len(), 1, "a job that was not stored is not listed");
        let id = s.add_job(&stored, retry).unwrap();
        assert_eq!(s.jobs[&id].tiles.queued().collect::<Vec<_>>(), [0, 1, 2, 3]);
        assert_eq!(tile_state(&s, id, 3), TileState::Queued);
    }

    /// A copy of a job's description with an empty tile book.
    fn job_like(job: &Job) -> Job {
        Job {
            id: 0,
            name: job.name.clone(),
            scene_file: job.scene_file.clone(),
            scene_hash: job.scene_hash.clone(),
            spec: job.spec.clone(),
            state: job.state,
            error: None,
            created_ms: 0,
            started_ms: None,
            finished_ms: None,
            assets: vec![],
            grid: job.grid,
            tiles: TileBook::new(0),
            failures: vec![],
            tile_ms_total: 0,
            tiles_timed: 0,
            assembling: false,
            progress: None,
        }
    }

    #[test]
    fn running_to_done_with_a_failed_write_stays_running() {
        let (mut s, job) = state();
        for tile in 0..4 {
            let lease = s.grant(job, tile, 1, 10, TIMEOUT).unwrap();
            s.complete(lease, 20).unwrap();
        }
        s.db.fail_writes(true);
        assert!(s.mark_done(job, 30).is_err());
        s.db.fail_writes(false);
        assert_eq!(s.jobs[&job].state, JobState::Running);
        s.mark_done(job, 30).unwrap();
        assert_eq!(s.jobs[&job].state, JobState::Done);
        assert!(matches!(s.mark_done(job, 40), Err(FarmError::Conflict(_))));
    }

    #[test]
    fn failed_to_running_with_a_failed_write_changes_nothing() {
        let (mut s, job) = state();
        let a = s.grant(job, 0, 1, 10, TIMEOUT).unwrap();
        s.fail(a, "scene", true, 20, LIMITS).unwrap();
        let before = snapshot(&s);
        s.db.fail_writes(true);
        assert!(s.retry(job).is_err());
        s.db.fail_writes(false);
        assert_eq!(snapshot(&s), before);
        assert_eq!(s.jobs[&job].state, JobState::Failed);
    }

    #[test]
    fn registering_with_a_failed_write_issues_nothing() {
        let (mut s, _) = state();
        s.db.fail_writes(true);
        assert!(s.register("w", 5, 100).is_err());
        s.db.fail_writes(false);
        assert_eq!(s.workers.len(), 2);
        assert_eq!(s.register("w", 5, 100).unwrap().worker_id, 3);
    }
}
