//! Results from workers: a finished tile's pixels (stored before the tile counts as done) and
//! reported failures. The state machine starts assembly itself when the last tile lands.

use std::sync::atomic::Ordering;

use protocol::{ApiError, Completion, FailureReport, JobInfo};

use super::state::FailureLimits;
use super::{Farm, FarmError, Result};

impl Farm {
    /// Stores a finished tile. The pixels are on disk before the tile counts as done; the
    /// first valid result wins, and the tile's other leases are revoked. The job's last tile
    /// starts its assembly.
    pub fn complete(&self, lease_id: u64, pixels: &[u8]) -> Result<Completion> {
        let (job_id, frame, tile, rect, tile_size) = {
            let state = self.lock();
            let lease = state.live(lease_id)?;
            let job = state.job(lease.job_id)?;
            if job.progress.is_some() {
                return Err(FarmError::BadRequest(ApiError::new(format!(
                    "lease {lease_id} is a pass of a progressive job: PUT its sums to \
                     /api/v1/leases/{lease_id}/sums"
                ))));
            }
            let grid = job.grid;
            (
                lease.job_id,
                grid.frame_at(grid.frame(lease.tile)),
                lease.tile,
                grid.rect(lease.tile),
                grid.tile_size(),
            )
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
        // Outside the lock. The lease may lapse meanwhile: then another worker owns the tile,
        // and the file (equal pixels, by determinism) is simply overwritten later.
        self.files
            .put_tile(job_id, frame, tile, tile_size, rect, pixels)?;
        self.tile_writes.fetch_add(1, Ordering::Relaxed);
        let now = self.now_ms();
        let done = self.lock().complete(lease_id, now)?;
        self.metrics.tiles_completed.fetch_add(1, Ordering::Relaxed);
        self.events.tile(job_id, tile);
        if done.last {
            self.start_assembly(job_id);
        }
        Ok(Completion {
            tiles_done: done.tiles_done,
            tiles_total: done.tiles_total,
        })
    }

    pub fn fail(&self, lease_id: u64, report: &FailureReport) -> Result<JobInfo> {
        let now = self.now_ms();
        let limits = FailureLimits {
            max_workers: self.config.max_tile_workers,
            max_attempts: self.config.max_tile_attempts,
        };
        let mut state = self.lock();
        let lease = state.live(lease_id)?.clone();
        let failed = state.fail(lease_id, &report.error, report.scene, now, limits)?;
        drop(state);
        tracing::warn!(
            "job {} tile {} failed on worker {}: {}",
            lease.job_id,
            lease.tile,
            lease.worker_id,
            report.error
        );
        self.metrics.tile_failed(lease.worker_id);
        if failed.requeued {
            self.work.notify_waiters();
        }
        self.events.tile(lease.job_id, lease.tile);
        Ok(failed.info)
    }
}
