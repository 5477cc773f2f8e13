//! Start-up: the state rebuilt from the data dir. Whatever a stored job holds, start-up goes
//! on: a job that cannot be loaded (settings that no longer parse, more tiles than the budget,
//! its scene or assets missing from the store) is marked failed with the reason, and every
//! other job resumes where it stopped.

use protocol::{JobSpec, JobState};

use super::job::Job;
use super::progressive::Progress;
use super::state::{LiveLease, State};
use super::tiles::{TileBook, TileGrid};
use super::workers::Registry;
use super::Result;
use crate::config::FarmConfig;
use crate::store::{Db, Files, JobRow, LoadedJob, StoredJob};

/// A stored job that will not run again, and why.
struct Unloadable {
    job: Job,
    /// Whether its row still has to be marked failed.
    mark_failed: bool,
}

/// The state of a data dir, and the jobs whose every tile was done before the restart (to be
/// assembled now).
pub fn resume(
    db: Db,
    files: &Files,
    config: &FarmConfig,
    epoch: u64,
    now: u64,
) -> Result<(State, Vec<u64>)> {
    let workers = Registry::load(db.load_workers()?);
    let loaded = db.load_jobs()?;
    let leases = db.load_leases()?;
    let mut state = State::new(db, epoch << 32, workers);
    for row in loaded {
        let job = match row {
            LoadedJob::Ok(stored) => match check(&stored, files, config) {
                Ok(grid) => match restore_progress(&state.db, files, &stored) {
                    Ok(progress) => Ok(with_progress(job_from_stored(*stored, grid), progress)),
                    Err(reason) => Err(unloadable(*stored, reason)),
                },
                Err(reason) => Err(unloadable(*stored, reason)),
            },
            LoadedJob::Unloadable(u) => {
                let spec = JobSpec::default();
                Err(Unloadable {
                    job: Job {
                        id: u.id,
                        name: u.name,
                        scene_file: u.scene_file,
                        scene_hash: String::new(),
                        grid: TileGrid::new(&spec),
                        spec,
                        state: JobState::Failed,
                        error: Some(format!("the job cannot be loaded: {}", u.reason)),
                        created_ms: u.created_ms,
                        started_ms: None,
                        finished_ms: Some(now),
                        assets: Vec::new(),
                        tiles: TileBook::new(0),
                        failures: Vec::new(),
                        tile_ms_total: 0,
                        tiles_timed: 0,
                        assembling: false,
                        progress: None,
                    },
                    mark_failed: true,
                })
            }
        };
        let job = match job {
            Ok(job) => job,
            Err(Unloadable { job, mark_failed }) => {
                if mark_failed {
                    tracing::error!("job {}: {}", job.id, job.error.as_deref().unwrap_or(""));
                    let row = JobRow {
                        state: job.state,
                        error: job.error.clone(),
                        started_ms: job.started_ms,
                        finished_ms: job.finished_ms,
                    };
                    // Not fatal either: the job is failed in memory, and on the next start
                    // it is found unloadable again.
                    if let Err(e) = state.db.set_job_state(job.id, &row) {
                        tracing::error!("job {}: recording its failure: {e}", job.id);
                    }
                }
                job
            }
        };
        state.jobs.insert(job.id, job);
    }
    restore_leases(&mut state, leases, config, now)?;
    let finished = state
        .jobs
        .values_mut()
        .filter(|job| job.is_active() && job.tiles.all_done())
        .map(|job| {
            job.assembling = true;
            job.id
        })
        .collect();
    Ok((state, finished))
}

/// Why a stored job cannot run, if it cannot: checked before its tile book is allocated.
fn check(stored: &StoredJob, files: &Files, config: &FarmConfig) -> Result<TileGrid, String> {
    let grid = TileGrid::new(&stored.spec);
    config.limits.check_tiles(&grid)?;
    if matches!(stored.state, JobState::Queued | JobState::Running) {
        if !files.has_blob(&stored.scene_hash) {
            return Err(format!(
                "its scene file {} ({}) is missing from the data dir",
                stored.scene_file, stored.scene_hash
            ));
        }
        if let Some(asset) = stored.assets.iter().find(|a| !files.has_blob(&a.hash)) {
            return Err(format!(
                "its asset {} ({}) is missing from the data dir",
                asset.path, asset.hash
            ));
        }
    }
    Ok(grid)
}

fn unloadable(stored: StoredJob, reason: String) -> Unloadable {
    let active = matches!(stored.state, JobState::Queued | JobState::Running);
    let spec = stored.spec;
    Unloadable {
        job: Job {
            id: stored.id,
            name: stored.name,
            scene_file: stored.scene_file,
            scene_hash: stored.scene_hash,
            grid: TileGrid::new(&spec),
            spec,
            // A finished job keeps its state; only its tile map is not rebuilt.
            state: if active {
                JobState::Failed
            } else {
                stored.state
            },
            error: if active {
                Some(format!("the job cannot be resumed: {reason}"))
            } else {
                stored.error
            },
            created_ms: stored.created_ms,
            started_ms: stored.started_ms,
            finished_ms: stored.finished_ms.or(Some(stored.created_ms)),
            assets: stored.assets,
            tiles: TileBook::new(0),
            failures: stored.failures,
            tile_ms_total: 0,
            tiles_timed: 0,
            assembling: false,
            progress: None,
        },
        mark_failed: active,
    }
}

/// A progressive job's passes from its sums file and `passes` rows (see `progressive`).
fn restore_progress(
    db: &Db,
    files: &Files,
    stored: &StoredJob,
) -> std::result::Result<Option<Progress>, String> {
    if stored.spec.adaptive.is_none() {
        return Ok(None);
    }
    let file = files.sums(stored.id).map_err(|e| e.to_string())?;
    let rows = db.load_passes(stored.id).map_err(|e| e.to_string())?;
    Progress::restore(&stored.spec, file.as_deref(), rows)
}

/// The job with its passes: an active one renders the tiles its current pass needs (the
/// tiles a pass in progress had finished render again); a finished one keeps only its
/// counts and history (its image is stored).
fn with_progress(mut job: Job, progress: Option<Progress>) -> Job {
    let Some(mut progress) = progress else {
        return job;
    };
    if job.is_active() {
        job.tiles = progress.book(&job.grid);
    } else {
        progress.sums.data = Vec::new();
    }
    job.progress = Some(Box::new(progress));
    job
}

fn job_from_stored(stored: StoredJob, grid: TileGrid) -> Job {
    let mut tiles = TileBook::new(grid.total_u64() as u32);
    for &t in &stored.tiles_done {
        tiles.mark_done(t);
    }
    for f in &stored.failures {
        if tiles.contains(f.tile) {
            tiles.record_failure(f.tile, f.worker_id);
        }
    }
    let mut job = Job {
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
        grid,
        tiles,
        failures: stored.failures,
        tile_ms_total: 0,
        tiles_timed: 0,
        assembling: false,
        progress: None,
    };
    if !job.is_active() {
        job.tiles.clear_queue();
    }
    job
}

/// Leases granted before the restart stay valid for a grace period, so workers that kept
/// rendering through the outage can still deliver. The others are dropped.
fn restore_leases(
    state: &mut State,
    leases: Vec<crate::store::StoredLease>,
    config: &FarmConfig,
    now: u64,
) -> Result<()> {
    let grace = config.restart_grace.as_millis() as u64;
    let mut dropped = Vec::new();
    for stored in leases {
        let keep = state.workers.contains(stored.worker_id)
            && !state.by_worker.contains_key(&stored.worker_id)
            && state.jobs.get(&stored.job_id).is_some_and(|j| {
                j.is_active() && j.tiles.contains(stored.tile) && !j.tiles.is_done(stored.tile)
            });
        if !keep {
            dropped.push(stored.id);
            continue;
        }
        let job = state.jobs.get_mut(&stored.job_id).expect("checked above");
        job.tiles.add_lease(stored.tile, stored.id);
        state.by_worker.insert(stored.worker_id, stored.id);
        state.leases.insert(
            stored.id,
            LiveLease {
                job_id: stored.job_id,
                tile: stored.tile,
                worker_id: stored.worker_id,
                granted_ms: stored.granted_ms,
                deadline_ms: now + grace,
            },
        );
    }
    if !dropped.is_empty() {
        state.db.end_leases(&dropped)?;
    }
    Ok(())
}
