//! Progressive jobs (`"adaptive"` in the job spec): the job renders in passes. A pass leases
//! every tile that still has a sampling block; each lease continues the tile's running sums
//! over the pass's sample range (`GET`/`PUT /leases/{id}/sums`), and the sums land in
//! `pending`. When the pass's last tile lands, the pass ends (on a thread of its own, like an
//! assembly): the pending sums are merged, every block's error is estimated and the stopping
//! rules decide which blocks sample in the next pass (tracer-core's `adaptive` module does
//! the arithmetic). The job ends when no block samples any more or its time limit has passed;
//! its image is then that of the last finished pass.
//!
//! Persistence: at each pass end the job's sums file (sums, per-block counts and decisions,
//! written whole and renamed into place) is written first, then the pass's row in the
//! `passes` table. The file is the truth on restart: a pass whose row is missing (a crash in
//! between) is rebuilt from it, and a pass in progress starts again from the last finished
//! pass. Nothing of a finished pass is lost.

use std::collections::HashMap;

use protocol::{AdaptiveSpec, JobSpec, PassInfo, PassLease};
use tracer_core::adaptive::{self, SumImage};
use tracer_core::TileRect;

use super::tiles::{TileBook, TileGrid};
use super::{Farm, FarmError, FarmEvent, Result};
use protocol::{ApiError, JobState};

/// A progressive job's passes.
#[derive(Debug)]
pub struct Progress {
    pub rules: AdaptiveSpec,
    /// The running sums after the last finished pass (emptied once the job is done and its
    /// image stored).
    pub sums: SumImage,
    /// Samples per pixel of each block after the last finished pass.
    pub counts: Vec<u32>,
    /// Samples per pixel of each block after the current pass (`adaptive::plan`): a block
    /// samples in it when its target is above its count.
    pub targets: Vec<u32>,
    /// Every finished pass, in order.
    pub passes: Vec<PassInfo>,
    /// The current pass's finished tiles: their new sums, merged when the pass ends.
    pub pending: HashMap<u32, Vec<f64>>,
    /// How fast the passes render, for sizing the pass that would run into a time limit.
    pub timing: PassTiming,
}

/// The passes' render time and rays since this coordinator took the job over. Render time
/// runs from a pass's first lease to its end: the job's start-up (the workers loading the
/// scene before their first lease) and the gaps between passes are left out of the rate, so
/// it does not err low as a rate over the job's whole wall time did (that ended time-limited
/// jobs early); the gaps are counted on their own.
#[derive(Debug, Default, Clone)]
pub struct PassTiming {
    /// When the current pass's first tile was leased.
    pub pass_started_ms: Option<u64>,
    /// When the last pass ended.
    pub last_end_ms: Option<u64>,
    /// Finished passes' render time and the rays they traced.
    pub render_ms: u64,
    pub rays: f64,
    /// Time from one pass's end to the next one's first lease, summed, and how many.
    pub gap_ms: u64,
    pub gaps: u32,
}

/// The share of the time left that the pass sized to it may plan for: the rate is measured
/// on earlier passes and the tiles of a pass finish unevenly at its end. At 0.9 the last
/// pass left 5-6 % of a stacks job's time unused (its passes' durations came within
/// -3.5..+1.6 % of plan); a pass that runs into the limit is cut and loses only its tiles in
/// flight.
const TIME_MARGIN: f64 = 0.96;

/// A time-limited job's pass may add up to this multiple of the image's rays (passes
/// triple instead of doubling): each pass costs leases, sums up and down and a pass end
/// (at equal samples six doubling passes took 1.46 s where one took 1.2, cornell_box), and
/// the pass that would run into the limit is sized to the time left, so a large pass is
/// no longer cut short at the limit.
const TIMED_GROWTH: f64 = 2.0;

/// A pass smaller than this fraction of the image's rays so far is not worth its overhead
/// (leases, sums up and down, the pass end): a pass that would leave less than this after
/// it takes the whole time left instead, and a job whose time left cannot make this much
/// ends with the image it has.
const MIN_PASS: f64 = 0.125;

/// Magic and version of the sums file.
const MAGIC: &[u8; 8] = b"TSUMS\0\0\x02";
/// Version 1 (before the per-pixel ray count): still read, so a job left mid-run by an older
/// coordinator resumes instead of failing.
const MAGIC_V1: &[u8; 8] = b"TSUMS\0\0\x01";
/// f64 sums per pixel in a version-1 file: r, g, b, luminance, odd-parity luminance.
const SUMS_V1: usize = 5;

impl Progress {
    /// The passes of a job whose spec asks for them; None for a one-shot job.
    pub fn new(spec: &JobSpec) -> Option<Progress> {
        let rules = spec.adaptive.clone()?;
        let (w, h) = (spec.render.width, spec.render.height);
        let (cols, rows) = adaptive::blocks(w, h);
        let blocks = cols as usize * rows as usize;
        let mut progress = Progress {
            rules,
            sums: SumImage::new(w, h),
            counts: vec![0; blocks],
            targets: Vec::new(),
            passes: Vec::new(),
            pending: HashMap::new(),
            timing: PassTiming::default(),
        };
        progress.plan(None);
        Some(progress)
    }

    /// The stopping rules as `adaptive::plan` takes them.
    fn plan_rules(&self) -> adaptive::Rules {
        adaptive::Rules {
            noise_threshold: self.rules.noise_threshold,
            spp_min: self.rules.spp_min,
            spp_max: self.rules.spp_max,
        }
    }

    /// Plans the next pass from the sums and `max_rays` (a pure function of them: every farm
    /// plans alike; without a time limit there is no cap).
    fn plan(&mut self, max_rays: Option<f64>) {
        self.targets = adaptive::plan(&self.sums, &self.counts, self.plan_rules(), max_rays);
    }

    /// A tile of the current pass was leased at `now_ms`: the pass's render time starts
    /// with its first.
    pub fn leased(&mut self, now_ms: u64) {
        let t = &mut self.timing;
        if t.pass_started_ms.is_none() {
            t.pass_started_ms = Some(now_ms);
            if let Some(end) = t.last_end_ms {
                t.gap_ms += now_ms.saturating_sub(end);
                t.gaps += 1;
            }
        }
    }

    /// The most rays the next pass may plan when the job has a time limit and `wall_ms` of
    /// it are gone. `fits`, what the time left can trace: the passes' rate × the time left
    /// (less the mean gap before a pass's first lease) × [`TIME_MARGIN`]. The pass adds
    /// [`TIMED_GROWTH`] × the image's rays, unless what that leaves of `fits` would make too
    /// small a pass after it (under [`MIN_PASS`] of the image then): then it is the last
    /// and takes all of `fits`, so the job uses its whole time instead of ending up to a
    /// pass of 1/8 of its rays early. Zero (no pass) when `fits` is under [`MIN_PASS`] of
    /// the image. None without a limit or before a pass was timed: the doubling budget.
    /// `image_rays`: what the image's samples have traced so far (`SumImage::rays`).
    fn pass_cap(&self, wall_ms: u64, image_rays: f64) -> Option<f64> {
        let limit_ms = self.rules.time_limit_s? * 1000.0;
        let t = &self.timing;
        if t.render_ms == 0 || t.rays <= 0.0 {
            return None;
        }
        let rate = t.rays / t.render_ms as f64;
        let gap = if t.gaps > 0 {
            t.gap_ms as f64 / t.gaps as f64
        } else {
            0.0
        };
        let left = limit_ms - wall_ms as f64 - gap;
        let image = image_rays;
        let fits = rate * left * TIME_MARGIN;
        let full = TIMED_GROWTH * image;
        let cap = if fits - full < MIN_PASS * (image + full) {
            fits
        } else {
            full
        };
        Some(if cap < MIN_PASS * image { 0.0 } else { cap })
    }

    /// Whether block `b` samples in the current pass.
    pub fn active(&self, b: usize) -> bool {
        self.targets[b] > self.counts[b]
    }

    /// The blocks that sample in the current pass.
    pub fn active_count(&self) -> u32 {
        (0..self.counts.len()).filter(|&b| self.active(b)).count() as u32
    }

    /// No block samples any more (the job ended, or its time ran out).
    pub fn stop(&mut self) {
        self.targets.clone_from(&self.counts);
    }

    /// The pass being rendered now (the count of finished ones).
    pub fn pass(&self) -> u32 {
        self.passes.len() as u32
    }

    /// What the current pass asks of the tile at `rect`: each sampling block's range.
    pub fn lease(&self, rect: TileRect) -> PassLease {
        let active_blocks: Vec<u32> = adaptive::blocks_in(self.sums.width, rect)
            .into_iter()
            .filter(|&b| self.active(b as usize))
            .collect();
        let block_samples: Vec<[u32; 2]> = active_blocks
            .iter()
            .map(|&b| [self.counts[b as usize], self.targets[b as usize]])
            .collect();
        PassLease {
            pass: self.pass(),
            samples_from: block_samples.iter().map(|r| r[0]).min().unwrap_or(0),
            samples_to: block_samples.iter().map(|r| r[1]).max().unwrap_or(0),
            active_blocks,
            block_samples,
        }
    }

    /// The current pass's tile book: tiles without a sampling block are done already.
    pub fn book(&self, grid: &TileGrid) -> TileBook {
        let mut book = TileBook::new(grid.total_u64() as u32);
        for tile in 0..book.total() {
            let rect = grid.rect(tile);
            let sampling = adaptive::blocks_in(self.sums.width, rect)
                .iter()
                .any(|&b| self.active(b as usize));
            if !sampling {
                book.mark_done(tile);
            }
        }
        book
    }

    /// Mean samples per pixel after the last finished pass.
    pub fn spp_mean(&self) -> f64 {
        let (w, h) = (self.sums.width, self.sums.height);
        let total: f64 = (self.counts.iter().enumerate())
            .map(|(b, &n)| n as f64 * adaptive::block_rect(w, h, b).pixel_count() as f64)
            .sum();
        total / (w as f64 * h as f64)
    }

    /// Ends the current pass: merges its tiles' sums, counts its samples, plans the next
    /// pass and records this one. Returns true when the job ends here (no block samples any
    /// more, or `time_up`).
    ///
    /// A pass cut short by the time limit keeps what it finished: every sampling block whose
    /// pixels all lie in tiles that landed takes its new sums and count; the others keep those
    /// of the last pass (a block's pixels always share one count). Which tiles landed in time
    /// depends on the clock, so a time-limited image is not reproducible; without a time
    /// limit every tile lands and the image depends on the sums alone. Returns None when a
    /// cut-short pass finished no block (nothing to record).
    ///
    /// `now_ms` (the pass's end) closes the pass's render time; with a time limit, the next
    /// pass is sized to the time left after `wall_ms` (see `pass_cap`).
    pub fn finish_pass(
        &mut self,
        grid: &TileGrid,
        now_ms: u64,
        wall_ms: u64,
        time_up: bool,
    ) -> Option<bool> {
        let (w, h) = (self.sums.width, self.sums.height);
        let rays_before = self.sums.rays();
        let mut landed = vec![false; w as usize * h as usize];
        let mut merged = self.sums.clone();
        for (tile, sums) in self.pending.drain() {
            let rect = grid.rect(tile);
            merged.put_tile(rect, &sums);
            for y in rect.y..rect.y + rect.height {
                let row = (y * w) as usize;
                landed[row + rect.x as usize..row + (rect.x + rect.width) as usize].fill(true);
            }
        }
        let mut finished = 0;
        for b in 0..self.counts.len() {
            if !self.active(b) {
                continue;
            }
            let rect = adaptive::block_rect(w, h, b);
            let whole = (rect.y..rect.y + rect.height).all(|y| {
                let row = (y * w) as usize;
                landed[row + rect.x as usize..row + (rect.x + rect.width) as usize]
                    .iter()
                    .all(|l| *l)
            });
            if whole {
                self.sums.put_tile(rect, &merged.tile(rect));
                self.counts[b] = self.targets[b];
                finished += 1;
            }
        }
        if finished == 0 && time_up {
            self.stop();
            return None;
        }
        // One scan of the sums for the pass's rays and the next pass's cap.
        let rays_after = self.sums.rays();
        let t = &mut self.timing;
        if let Some(started) = t.pass_started_ms.take() {
            t.render_ms += now_ms.saturating_sub(started);
            t.rays += rays_after - rays_before;
        }
        t.last_end_ms = Some(now_ms);
        let cap = if time_up {
            None
        } else {
            self.pass_cap(wall_ms, rays_after)
        };
        self.plan(cap);
        let active_blocks = self.active_count();
        let ends = active_blocks == 0 || time_up;
        if ends {
            self.stop();
        }
        self.passes.push(PassInfo {
            pass: self.pass(),
            wall_s: wall_ms as f64 / 1000.0,
            spp_mean: self.spp_mean(),
            error: self.sums.error(&self.counts),
            active_blocks: self.active_count(),
        });
        Some(ends)
    }

    /// The sums file: magic, finished passes, the last pass's wall time, the image size, the
    /// per-block counts and decisions, then the sums (all little-endian).
    pub fn encode(&self) -> Vec<u8> {
        let mut out = Vec::with_capacity(48 + self.counts.len() * 5 + self.sums.data.len() * 8);
        out.extend_from_slice(MAGIC);
        out.extend_from_slice(&self.pass().to_le_bytes());
        let wall = self.passes.last().map_or(0.0, |p| p.wall_s);
        out.extend_from_slice(&wall.to_le_bytes());
        out.extend_from_slice(&self.sums.width.to_le_bytes());
        out.extend_from_slice(&self.sums.height.to_le_bytes());
        for n in &self.counts {
            out.extend_from_slice(&n.to_le_bytes());
        }
        out.extend((0..self.counts.len()).map(|b| self.active(b) as u8));
        out.extend_from_slice(&SumImage::to_bytes(&self.sums.data));
        out
    }

    /// Restores the passes of `spec`'s job from its sums file and its `passes` rows (see the
    /// module notes). Without a file (no pass finished) the job starts from its first pass.
    pub fn restore(
        spec: &JobSpec,
        file: Option<&[u8]>,
        mut rows: Vec<PassInfo>,
    ) -> std::result::Result<Option<Progress>, String> {
        let Some(mut progress) = Progress::new(spec) else {
            return Ok(None);
        };
        let Some(bytes) = file else {
            return Ok(Some(progress));
        };
        let blocks = progress.counts.len();
        let (w, h) = (progress.sums.width, progress.sums.height);
        let header = MAGIC.len() + 4 + 8 + 4 + 4;
        let v1 = bytes.len() >= MAGIC_V1.len() && &bytes[..MAGIC_V1.len()] == MAGIC_V1;
        let per_pixel = if v1 { SUMS_V1 } else { adaptive::SUMS };
        let expected = header + blocks * 5 + w as usize * h as usize * per_pixel * 8;
        if bytes.len() != expected || !(v1 || &bytes[..MAGIC.len()] == MAGIC) {
            return Err(format!(
                "its sums file is not a {w}x{h} progressive state ({} bytes, expected {expected})",
                bytes.len()
            ));
        }
        let u32_at = |at: usize| u32::from_le_bytes(bytes[at..at + 4].try_into().expect("4"));
        let passes = u32_at(MAGIC.len());
        let wall = f64::from_le_bytes(
            bytes[MAGIC.len() + 4..MAGIC.len() + 12]
                .try_into()
                .expect("8"),
        );
        if (u32_at(MAGIC.len() + 12), u32_at(MAGIC.len() + 16)) != (w, h) {
            return Err("its sums file is for another image size".into());
        }
        for (b, n) in progress.counts.iter_mut().enumerate() {
            *n = u32_at(header + 4 * b);
        }
        let sampling = bytes[header + 4 * blocks..header + 5 * blocks]
            .iter()
            .any(|&a| a != 0);
        let body = &bytes[header + 5 * blocks..];
        progress.sums.data = if v1 {
            upgrade_v1_sums(body, w, &progress.counts)
        } else {
            SumImage::from_bytes(body, w as usize * h as usize, "the sums file")
                .map_err(|e| e.to_string())?
        };
        // The plan is a function of the sums: planned again, it is the pass the file's
        // decisions were made for (the flags only say whether there is one).
        if sampling {
            // No pass was timed by this coordinator: the doubling budget (a time-limited
            // job sizes its passes again once one has run).
            progress.plan(None);
        } else {
            progress.stop();
        }
        rows.retain(|r| r.pass < passes);
        if rows.len() as u32 + 1 == passes {
            // Its file was written but the crash came before its row: rebuilt from the file.
            rows.push(PassInfo {
                pass: passes - 1,
                wall_s: wall,
                spp_mean: progress.spp_mean(),
                error: progress.sums.error(&progress.counts),
                active_blocks: progress.active_count(),
            });
        }
        if rows.len() as u32 != passes {
            return Err(format!(
                "its sums file has {passes} passes but the database {}",
                rows.len()
            ));
        }
        progress.passes = rows;
        Ok(Some(progress))
    }
}

/// A version-1 file's sums with the ray count added. Version 1 did not count rays; one ray
/// per sample (the block's sample count) stands in for it: the count only weighs what a sample
/// costs when later passes are planned, never a pixel's value.
fn upgrade_v1_sums(body: &[u8], width: u32, counts: &[u32]) -> Vec<f64> {
    let mut out = Vec::with_capacity(body.len() / SUMS_V1 * adaptive::SUMS);
    for (pixel, old) in body.chunks_exact(SUMS_V1 * 8).enumerate() {
        out.extend(
            old.chunks_exact(8)
                .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes"))),
        );
        let (x, y) = (pixel as u32 % width, pixel as u32 / width);
        out.push(counts[adaptive::block_of(width, x, y)] as f64);
    }
    out
}

/// Checks a progressive submission and makes its spec say what it renders: the strata of
/// `spp_max` (a pass renders a range of them).
pub fn normalize(spec: &mut JobSpec) -> Result<()> {
    let Some(rules) = &spec.adaptive else {
        return Ok(());
    };
    let bad = |e: String| FarmError::BadRequest(ApiError::new(format!("adaptive: {e}")));
    rules.validate().map_err(bad)?;
    if spec.frames.is_some() {
        return Err(bad(
            "a progressive job renders one frame, not a frame range".into(),
        ));
    }
    spec.render.spp = rules.spp_max;
    Ok(())
}

impl Farm {
    /// Ends a progressive job's pass whose last tile just landed (or, `time_up`, whose time
    /// ran out), off the caller's thread.
    pub(super) fn start_pass_end(&self, job_id: u64, time_up: bool) {
        let Some(farm) = self.me.upgrade() else {
            return;
        };
        let spawned = std::thread::Builder::new()
            .name(format!("pass-{job_id}"))
            .spawn(move || farm.end_pass_or_fail(job_id, time_up));
        match spawned {
            Ok(handle) => {
                let mut running = self.assemblies.lock().unwrap_or_else(|p| p.into_inner());
                running.retain(|h| !h.is_finished());
                running.push(handle);
            }
            Err(_) => self.end_pass_or_fail(job_id, time_up),
        }
    }

    fn end_pass_or_fail(&self, job_id: u64, time_up: bool) {
        if let Err(e) = self.end_pass(job_id, time_up) {
            let error = format!("ending a pass failed: {e}");
            tracing::error!("job {job_id}: {error}");
            let now = self.now_ms();
            let ended =
                self.lock()
                    .end_job(job_id, JobState::Failed, Some(error), now, "the job failed");
            if ended.is_ok() && self.flush().is_ok() {
                self.events.send(FarmEvent::Job(job_id));
            }
        }
    }

    /// See the module notes: merge, decide, store the file, then the row; then the next pass
    /// is queued, or the job's image assembled. `time_up`: the pass was cut short by the
    /// time limit (its leases revoked), and the job ends with what it finished.
    fn end_pass(&self, job_id: u64, time_up: bool) -> Result<()> {
        let now = self.now_ms();
        let (file, info, ends) = {
            let mut state = self.lock();
            let job = state
                .jobs
                .get_mut(&job_id)
                .ok_or_else(|| FarmError::NotFound(format!("no job {job_id}")))?;
            if !job.is_active() {
                return Ok(());
            }
            let wall_ms = now.saturating_sub(job.started_ms.unwrap_or(now));
            let grid = job.grid;
            let Some(progress) = job.progress.as_mut() else {
                return Ok(());
            };
            let time_up = time_up
                || progress
                    .rules
                    .time_limit_s
                    .is_some_and(|limit| wall_ms as f64 >= limit * 1000.0);
            let Some(ends) = progress.finish_pass(&grid, now, wall_ms, time_up) else {
                // Cut short before any block finished: the last pass's image stands.
                drop(state);
                self.assemble_now(job_id);
                return Ok(());
            };
            let info = progress.passes.last().cloned().expect("a pass was pushed");
            let rays = progress.timing.rays;
            (progress.encode(), (info, rays), ends)
        };
        let (info, rays) = info;
        self.files.put_sums(job_id, &file)?;
        drop(file);
        {
            let mut state = self.lock();
            state.db.record_pass(job_id, &info)?;
            let job = state
                .jobs
                .get_mut(&job_id)
                .ok_or_else(|| FarmError::NotFound(format!("no job {job_id}")))?;
            if !ends {
                if let Some(progress) = &job.progress {
                    job.tiles = progress.book(&job.grid);
                    job.assembling = false;
                }
            }
        }
        self.flush()?;
        tracing::info!(
            "job {job_id}: pass {} done at {:.3}s: mean spp {:.2}, error {:.4}, {} blocks sampling, {:.0} rays traced by the passes",
            info.pass,
            info.wall_s,
            info.spp_mean,
            info.error,
            info.active_blocks,
            rays
        );
        self.events.send(FarmEvent::Job(job_id));
        if ends {
            self.assemble_now(job_id);
        } else {
            self.work.notify_waiters();
        }
        Ok(())
    }

    /// Ends every progressive job whose time limit has passed: the current pass's leases are
    /// revoked and the job ends with the blocks that pass finished on top of the last
    /// finished pass. A job still in its first pass finishes that pass first: it has no
    /// image yet. Called by the reaper (and after each landed tile, see `complete_sums`).
    pub fn check_time_limits(&self) -> Result<()> {
        let now = self.now_ms();
        let due: Vec<u64> = {
            let state = self.lock();
            state
                .jobs
                .values()
                .filter(|j| j.is_active() && !j.assembling)
                .filter(|j| {
                    let (Some(progress), Some(started)) = (&j.progress, j.started_ms) else {
                        return false;
                    };
                    progress.pass() > 0
                        && progress.rules.time_limit_s.is_some_and(|limit| {
                            now.saturating_sub(started) as f64 >= limit * 1000.0
                        })
                })
                .map(|j| j.id)
                .collect()
        };
        for job_id in due {
            self.end_for_time_limit(job_id)?;
        }
        Ok(())
    }

    /// Cuts job `job_id`'s current pass short (see `check_time_limits`).
    fn end_for_time_limit(&self, job_id: u64) -> Result<()> {
        let stopped = self.lock().stop_passes(job_id)?;
        self.flush()?;
        if stopped {
            tracing::info!("job {job_id}: time limit reached; ending with what its pass finished");
            for tile in 0..self.lock().job(job_id)?.total() {
                self.events.tile(job_id, tile);
            }
            self.start_pass_end(job_id, true);
        }
        Ok(())
    }

    /// A running tile's sums so far, for its pass lease (`GET /leases/{id}/sums`).
    pub fn lease_sums(&self, lease_id: u64) -> Result<Vec<u8>> {
        let state = self.lock();
        let lease = state.live(lease_id)?;
        let job = state.job(lease.job_id)?;
        let Some(progress) = &job.progress else {
            return Err(FarmError::Conflict(format!(
                "lease {lease_id} is not a pass of a progressive job"
            )));
        };
        let tile = progress.sums.tile(job.grid.rect(lease.tile));
        drop(state);
        Ok(SumImage::to_bytes(&tile))
    }

    /// A pass lease's new sums (`PUT /leases/{id}/sums`): kept until the pass ends. The
    /// pass's last tile ends it.
    pub fn complete_sums(&self, lease_id: u64, bytes: &[u8]) -> Result<protocol::Completion> {
        let (rect, progressive) = {
            let state = self.lock();
            let lease = state.live(lease_id)?;
            let job = state.job(lease.job_id)?;
            (job.grid.rect(lease.tile), job.progress.is_some())
        };
        if !progressive {
            return Err(FarmError::Conflict(format!(
                "lease {lease_id} is not a pass of a progressive job: PUT its pixels"
            )));
        }
        let bad = |e: String| FarmError::BadRequest(ApiError::new(e));
        let sums = SumImage::from_bytes(bytes, rect.pixel_count(), "the tile's sums")
            .map_err(|e| bad(e.to_string()))?;
        if let Some(at) = sums.iter().position(|v| !v.is_finite()) {
            return Err(bad(format!(
                "the tile's sums hold a non-finite value at value {at}"
            )));
        }
        let now = self.now_ms();
        let mut state = self.lock();
        let lease = state.live(lease_id)?.clone();
        let done = state.complete(lease_id, now)?;
        let mut time_up = false;
        if let Some(job) = state.jobs.get_mut(&lease.job_id) {
            if let (Some(progress), Some(started)) = (job.progress.as_mut(), job.started_ms) {
                progress.pending.insert(lease.tile, sums);
                // Checked here too, not only by the reaper (every 250 ms, a large part of a
                // sub-second render): a landed tile past the limit ends the job at once.
                time_up = progress.pass() > 0
                    && progress
                        .rules
                        .time_limit_s
                        .is_some_and(|limit| now.saturating_sub(started) as f64 >= limit * 1000.0);
            }
        }
        drop(state);
        self.metrics
            .tiles_completed
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        self.events.tile(lease.job_id, lease.tile);
        if done.last {
            self.start_pass_end(lease.job_id, false);
        } else if time_up {
            self.end_for_time_limit(lease.job_id)?;
        }
        Ok(protocol::Completion {
            tiles_done: done.tiles_done,
            tiles_total: done.tiles_total,
        })
    }

    /// Every finished pass of a job (none for a one-shot job).
    pub fn convergence(&self, job_id: u64) -> Result<protocol::Convergence> {
        let state = self.lock();
        let job = state.job(job_id)?;
        Ok(protocol::Convergence {
            job_id,
            passes: job
                .progress
                .as_ref()
                .map(|p| p.passes.clone())
                .unwrap_or_default(),
        })
    }

    /// Where a progressive job's samples went, as PNG (each pixel's count over spp_max).
    pub fn samples_png(&self, job_id: u64) -> Result<Vec<u8>> {
        let (w, h, counts, max) = {
            let state = self.lock();
            let job = state.job(job_id)?;
            match &job.progress {
                Some(p) if p.pass() > 0 => (
                    job.spec.render.width,
                    job.spec.render.height,
                    p.counts.clone(),
                    p.rules.spp_max,
                ),
                Some(_) => {
                    return Err(FarmError::Conflict(format!(
                        "job {job_id} has not finished a pass yet"
                    )))
                }
                None => {
                    return Err(FarmError::Conflict(format!(
                        "job {job_id} is not progressive: every pixel has its {} samples",
                        job.spec.render.spp
                    )))
                }
            }
        };
        Ok(adaptive::sample_map(w, h, &counts, max).to_png())
    }

    /// The image of a progressive job's last finished pass (black before the first), or None
    /// for a one-shot job or one whose sums are already dropped (done: its image is stored).
    pub(super) fn progressive_image(&self, job_id: u64) -> Result<Option<tracer_core::Image>> {
        let state = self.lock();
        let job = state.job(job_id)?;
        Ok(match &job.progress {
            Some(p) if !p.sums.data.is_empty() => Some(p.sums.image(&p.counts)),
            _ => None,
        })
    }
}
