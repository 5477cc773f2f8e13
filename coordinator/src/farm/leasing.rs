//! Handing tiles to workers: which tile a worker gets, heartbeats, hand-backs and lapsed
//! leases.

use std::sync::atomic::Ordering;

use protocol::{Lease, LeaseStatus};
use tracer_core::RenderSettings;

use super::state::{LiveLease, State};
use super::{Farm, FarmError, Result};

impl Farm {
    /// Grants worker `worker_id` a tile: the lease it already holds, else the lowest queued
    /// tile of the oldest job, else (with stragglers on) a copy of a slow running tile.
    pub fn lease(&self, worker_id: u64) -> Result<Option<Lease>> {
        let now = self.now_ms();
        let timeout = self.config.lease_timeout.as_millis() as u64;
        let mut state = self.lock();
        if state.workers.seen(worker_id, now).is_none() {
            return Err(unknown_worker(worker_id));
        }
        if let Some(&id) = state.by_worker.get(&worker_id) {
            if let Some(lease) = state.leases.get_mut(&id) {
                lease.deadline_ms = now + timeout;
                let lease = lease.clone();
                return Ok(Some(self.describe(&state, id, &lease)));
            }
        }
        let Some((job_id, tile)) =
            pick_queued(&state, worker_id).or_else(|| self.pick_straggler(&state, worker_id, now))
        else {
            return Ok(None);
        };
        let id = state.grant(job_id, tile, worker_id, now, timeout)?;
        if let Some(progress) = state
            .jobs
            .get_mut(&job_id)
            .and_then(|j| j.progress.as_mut())
        {
            progress.leased(now);
        }
        self.metrics.leases_granted.fetch_add(1, Ordering::Relaxed);
        // For timelines of a job's passes (RUST_LOG=coordinator=debug).
        tracing::debug!("job {job_id}: leased tile {tile} to worker {worker_id}");
        let granted = self.describe(&state, id, &state.leases[&id]);
        drop(state);
        self.events.tile(job_id, tile);
        Ok(Some(granted))
    }

    fn describe(&self, state: &State, id: u64, lease: &LiveLease) -> Lease {
        let job = &state.jobs[&lease.job_id];
        let rect = job.grid.rect(lease.tile);
        Lease {
            lease_id: id,
            job_id: lease.job_id,
            tile: lease.tile,
            rect,
            settings: RenderSettings {
                frame: job.grid.frame(lease.tile),
                ..job.spec.render.clone()
            },
            expires_in_ms: lease.deadline_ms.saturating_sub(self.now_ms()),
            heartbeat_ms: self.config.heartbeat.as_millis() as u64,
            pass: job.progress.as_ref().map(|p| p.lease(rect)),
        }
    }

    /// With nothing queued: the running tile whose only lease is oldest, if that lease has
    /// run well past the job's typical tile time and `worker_id` does not hold it.
    fn pick_straggler(&self, state: &State, worker_id: u64, now: u64) -> Option<(u64, u32)> {
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
            for (tile, ids) in job.tiles.leased() {
                let [only] = ids else {
                    continue;
                };
                // Every id in the tile book has its lease: both are changed together after
                // the write commits. A miss is skipped, never indexed.
                let Some(lease) = state.leases.get(only) else {
                    continue;
                };
                let age = now.saturating_sub(lease.granted_ms);
                if lease.worker_id == worker_id || age < threshold {
                    continue;
                }
                if best.is_none_or(|(granted, _)| lease.granted_ms < granted) {
                    best = Some((lease.granted_ms, (job.id, tile)));
                }
            }
        }
        best.map(|(_, pick)| pick)
    }

    pub fn heartbeat(&self, lease_id: u64) -> Result<LeaseStatus> {
        let now = self.now_ms();
        let timeout = self.config.lease_timeout.as_millis() as u64;
        let mut state = self.lock();
        let worker_id = match state.leases.get_mut(&lease_id) {
            Some(lease) => {
                lease.deadline_ms = now + timeout;
                lease.worker_id
            }
            None => return Err(state.stale(lease_id)),
        };
        state.workers.seen(worker_id, now);
        Ok(LeaseStatus {
            expires_in_ms: timeout,
        })
    }

    /// A worker gives its tile back unfinished (it is stopping); not a failure.
    pub fn hand_back(&self, lease_id: u64) -> Result<()> {
        let released = self.lock().release(&[lease_id], "handed back")?;
        self.metrics.handed_back.fetch_add(1, Ordering::Relaxed);
        self.after_release(&released);
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
        if expired.is_empty() {
            return Ok(0);
        }
        let released = state.release(&expired, "it expired without a heartbeat")?;
        for (lease, _) in &released {
            if let Some(worker) = state.workers.get_mut(lease.worker_id) {
                worker.lapsed = true;
            }
            tracing::warn!(
                "job {} tile {}: lease of worker {} expired; requeued",
                lease.job_id,
                lease.tile,
                lease.worker_id
            );
        }
        drop(state);
        self.metrics
            .leases_expired
            .fetch_add(released.len() as u64, Ordering::Relaxed);
        self.after_release(&released);
        Ok(released.len())
    }

    fn after_release(&self, released: &[(LiveLease, bool)]) {
        if released.iter().any(|(_, requeued)| *requeued) {
            self.work.notify_waiters();
        }
        for (lease, _) in released {
            self.events.tile(lease.job_id, lease.tile);
        }
    }
}

pub fn unknown_worker(worker_id: u64) -> FarmError {
    FarmError::NotFound(format!(
        "unknown worker id {worker_id}: register with POST /api/v1/workers"
    ))
}

/// The lowest queued tile of the oldest active job, preferring tiles that have not already
/// failed on this worker. Walks past at most as many tiles as have failed on it.
fn pick_queued(state: &State, worker_id: u64) -> Option<(u64, u32)> {
    let mut fallback = None;
    for job in state.jobs.values().filter(|j| j.is_active()) {
        for tile in job.tiles.queued() {
            let failed_here = job
                .tiles
                .failures(tile)
                .is_some_and(|f| f.workers.contains(&worker_id));
            if !failed_here {
                return Some((job.id, tile));
            }
            fallback.get_or_insert((job.id, tile));
        }
    }
    fallback
}
