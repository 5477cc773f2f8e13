//! A job in memory: what it renders, where it stands, and its tile book. Reading only; every
//! change goes through the transitions in [`super::state`].

use protocol::{BundleFile, JobInfo, JobSpec, JobState, TileFailure, TileInfo, TileState};

use super::progressive::Progress;
use super::tiles::{TileBook, TileGrid};

#[derive(Debug)]
pub struct Job {
    pub id: u64,
    pub name: String,
    pub scene_file: String,
    pub scene_hash: String,
    pub spec: JobSpec,
    pub state: JobState,
    pub error: Option<String>,
    pub created_ms: u64,
    pub started_ms: Option<u64>,
    pub finished_ms: Option<u64>,
    pub assets: Vec<BundleFile>,
    pub grid: TileGrid,
    pub tiles: TileBook,
    pub failures: Vec<TileFailure>,
    /// Sum and count of lease-to-completion times, for straggler detection.
    pub tile_ms_total: u64,
    pub tiles_timed: u64,
    /// Every tile is done and the image is being written (or, for a progressive job, the
    /// pass is ending).
    pub assembling: bool,
    /// A progressive job's passes.
    pub progress: Option<Box<Progress>>,
}

impl Job {
    pub fn is_active(&self) -> bool {
        matches!(self.state, JobState::Queued | JobState::Running)
    }

    pub fn total(&self) -> u32 {
        self.tiles.total()
    }

    pub fn info(&self, now: u64) -> JobInfo {
        let done = self.tiles.done_count();
        let elapsed_ms = self
            .started_ms
            .map(|s| self.finished_ms.unwrap_or(now).saturating_sub(s));
        let eta_s = match elapsed_ms {
            // A pass's tiles say nothing about how many passes remain.
            _ if self.progress.is_some() => None,
            Some(ms) if self.is_active() && done > 0 => {
                let per_tile = ms as f64 / 1000.0 / done as f64;
                Some(per_tile * (self.total() - done) as f64)
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
            tiles_done: done,
            tiles_running: self.tiles.leased_count(),
            elapsed_s: elapsed_ms.map(|ms| ms as f64 / 1000.0),
            eta_s,
            error: self.error.clone(),
            failures: self.failures.clone(),
            created_ms: self.created_ms,
            spp_mean: Some(match &self.progress {
                Some(p) => p.passes.last().map_or(0.0, |last| last.spp_mean),
                None => self.spec.render.spp as f64,
            }),
            passes: self.progress.as_ref().map(|p| p.pass()),
            error_estimate: self
                .progress
                .as_ref()
                .and_then(|p| p.passes.last())
                .map(|last| last.error)
                .filter(|e| e.is_finite()),
        }
    }

    /// The tile's state on the map; `workers` names its lease holders.
    pub fn tile_info(&self, tile: u32, workers: Vec<String>) -> TileInfo {
        let attempts = self.tiles.failures(tile).map_or(0, |f| f.attempts);
        let state = if self.tiles.is_done(tile) {
            TileState::Done
        } else if !self.tiles.leases(tile).is_empty() {
            TileState::Leased
        } else if attempts > 0 {
            TileState::Failed
        } else if self.is_active() {
            TileState::Queued
        } else {
            TileState::Idle
        };
        TileInfo {
            job_id: self.id,
            tile,
            frame: self.grid.frame(tile),
            rect: self.grid.rect(tile),
            state,
            workers,
            attempts,
        }
    }
}
