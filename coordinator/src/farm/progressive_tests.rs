//! Progressive jobs through the farm's state machine, with in-process "workers" that render
//! pass leases with tracer-core exactly as the worker binary does (`worker::pass`).

use std::path::PathBuf;
use std::sync::atomic::AtomicBool;
use std::sync::Arc;

use protocol::{AdaptiveSpec, JobSpec, JobState, Lease};
use tracer_core::adaptive::{self, SumImage};
use tracer_core::{Image, ImageFormat, Renderer, SampleOrder, Scene};

use super::*;
use crate::clock::ManualClock;

fn cornell() -> Scene {
    let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/scenes/course/cornell_box.scene");
    Scene::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

fn adaptive_job(farm: &Farm, tile: u32, rules: AdaptiveSpec) -> NewJob {
    sized_job(farm, 24, 16, tile, rules)
}

fn sized_job(farm: &Farm, width: u32, height: u32, tile: u32, rules: AdaptiveSpec) -> NewJob {
    let mut spec = JobSpec::default();
    spec.render.width = width;
    spec.render.height = height;
    spec.tile_size = tile;
    spec.adaptive = Some(rules);
    NewJob {
        name: "cornell".into(),
        scene_file: "cornell_box.scene".into(),
        scene_hash: farm.files().put_blob(b"<scene/>").unwrap(),
        spec,
        assets: vec![],
    }
}

fn rules(threshold: f64, spp_min: u32, spp_max: u32) -> AdaptiveSpec {
    AdaptiveSpec {
        noise_threshold: threshold,
        spp_min,
        spp_max,
        time_limit_s: None,
    }
}

/// Renders one lease as the worker does and delivers it. False when nothing was leased.
fn work_once(farm: &Farm, scene: &Scene, worker: u64) -> bool {
    let Some(lease) = farm.lease(worker).unwrap() else {
        return false;
    };
    let sums = render(farm, scene, &lease);
    farm.complete_sums(lease.lease_id, &SumImage::to_bytes(&sums))
        .unwrap();
    true
}

fn render(farm: &Farm, scene: &Scene, lease: &Lease) -> Vec<f64> {
    let pass = lease.pass.as_ref().expect("a pass lease");
    let mut sums = if pass.samples_from == 0 {
        vec![0.0; lease.rect.pixel_count() * adaptive::SUMS]
    } else {
        let bytes = farm.lease_sums(lease.lease_id).unwrap();
        SumImage::from_bytes(&bytes, lease.rect.pixel_count(), "sums").unwrap()
    };
    let renderer = Renderer::new(scene, &lease.settings)
        .unwrap()
        .with_sample_order(SampleOrder::Progressive);
    let width = lease.settings.width;
    let samples = |x: u32, y: u32| pass.block_range(adaptive::block_of(width, x, y) as u32);
    assert!(renderer.render_tile_samples(lease.rect, &samples, &mut sums, &AtomicBool::new(false),));
    sums
}

/// Runs the job to its end with `workers` workers taking turns.
fn run(farm: &Farm, scene: &Scene, job: u64, workers: usize) {
    let ids: Vec<u64> = (0..workers)
        .map(|i| farm.register_worker(&format!("w{i}")).unwrap().worker_id)
        .collect();
    for _ in 0..10_000 {
        let mut any = false;
        for &w in &ids {
            any |= work_once(farm, scene, w);
        }
        if !any {
            farm.wait_for_assemblies();
            if farm.job(job).unwrap().state.is_finished() {
                return;
            }
        }
    }
    panic!("job {job} never finished");
}

/// The job's linear image (PFM: the f32 pixels, bit for bit).
fn linear(farm: &Farm, job: u64) -> Vec<u8> {
    farm.image_in(job, None, ImageFormat::Pfm).unwrap()
}

fn farm_at(dir: &std::path::Path, clock: Arc<ManualClock>) -> Arc<Farm> {
    Farm::open(dir, FarmConfig::default(), clock).unwrap()
}

#[test]
fn pass_by_pass_equals_the_one_shot_render_and_the_error_falls() {
    let scene = cornell();
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(1_000_000));
    let farm = Farm::for_tests(dir.path(), FarmConfig::default(), clock);
    // Threshold 0: every block goes to spp_max, the noisier ones first (each block continues
    // its own sample range, so passes leave blocks at different counts on the way).
    let job = farm
        .submit(sized_job(&farm, 64, 48, 7, rules(0.0, 2, 64)))
        .unwrap();
    assert_eq!(job.spec.render.spp, 64, "spp_max replaces spp");
    run(&farm, &scene, job.id, 1);
    let info = farm.job(job.id).unwrap();
    assert_eq!(info.state, JobState::Done);
    assert_eq!(info.spp_mean, Some(64.0));
    let settings = tracer_core::RenderSettings {
        spp: 64,
        ..job.spec.render.clone()
    };
    let one_shot = Renderer::new(&scene, &settings)
        .unwrap()
        .with_sample_order(SampleOrder::Progressive)
        .render_image(&|_, _| {});
    let pfm = farm.image_in(job.id, None, ImageFormat::Pfm).unwrap();
    assert_eq!(
        pfm,
        one_shot.to_pfm(),
        "the same bytes as the one-shot render"
    );
    let passes = farm.convergence(job.id).unwrap().passes;
    let spp: Vec<f64> = passes.iter().map(|p| p.spp_mean).collect();
    assert_eq!(spp[0], 2.0);
    assert!(
        spp.windows(2).all(|w| w[1] > w[0]) && passes.len() >= 4,
        "passes add samples: {spp:?}"
    );
    // Some pass left blocks at different counts: the allocation followed the noise.
    assert!(
        passes.iter().any(|p| p.spp_mean.fract() != 0.0),
        "uneven passes: {spp:?}"
    );
    let errors: Vec<f64> = passes.iter().map(|p| p.error).collect();
    // An estimate is itself noisy: it may wobble a little, but falls as samples add up.
    let last = errors.len() - 1;
    assert!(
        errors.windows(2).all(|w| w[1] < w[0] * 1.1) && errors[last] < errors[0] * 0.75,
        "the estimated error falls pass by pass: {errors:?}"
    );
}

#[test]
fn a_noise_threshold_stops_flat_blocks_and_keeps_sampling_noisy_ones() {
    let scene = cornell();
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::for_tests(
        dir.path(),
        FarmConfig::default(),
        Arc::new(ManualClock::new(0)),
    );
    let job = farm
        .submit(sized_job(&farm, 64, 48, 16, rules(0.02, 4, 64)))
        .unwrap();
    run(&farm, &scene, job.id, 1);
    let state = farm.lock();
    let progress = state.job(job.id).unwrap().progress.as_ref().unwrap();
    let counts = progress.counts.clone();
    drop(state);
    let (min, max) = (*counts.iter().min().unwrap(), *counts.iter().max().unwrap());
    assert_eq!(min, 4, "some block stopped at spp_min: {counts:?}");
    assert!(
        max >= 63,
        "some block kept sampling to (nearly) spp_max: {counts:?}"
    );
    // The sample map shows it: grey levels differ.
    let map = Image::from_png_bytes(&farm.samples_png(job.id).unwrap()).unwrap();
    let levels: std::collections::BTreeSet<u32> =
        map.pixels.iter().map(|v| (v * 255.0) as u32).collect();
    assert!(levels.len() > 1, "{levels:?}");
    let info = farm.job(job.id).unwrap();
    assert!(info.spp_mean.unwrap() < 64.0 && info.error_estimate.is_some());
}

#[test]
fn the_image_is_the_same_with_one_or_three_workers_and_any_tile_size() {
    let scene = cornell();
    let mut images = Vec::new();
    for (workers, tile) in [(1, 8), (3, 5), (3, 16)] {
        let dir = tempfile::tempdir().unwrap();
        let farm = Farm::for_tests(
            dir.path(),
            FarmConfig::default(),
            Arc::new(ManualClock::new(0)),
        );
        let job = farm
            .submit(adaptive_job(&farm, tile, rules(0.05, 2, 24)))
            .unwrap();
        run(&farm, &scene, job.id, workers);
        let passes = farm.convergence(job.id).unwrap().passes;
        images.push((linear(&farm, job.id), passes));
    }
    assert_eq!(images[0], images[1]);
    assert_eq!(images[0], images[2]);
}

#[test]
fn the_time_limit_ends_the_job_with_what_its_last_pass_finished() {
    let scene = cornell();
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(0));
    let farm = Farm::for_tests(dir.path(), FarmConfig::default(), clock.clone());
    let mut r = rules(0.0, 2, 64);
    r.time_limit_s = Some(5.0);
    let job = farm.submit(adaptive_job(&farm, 8, r)).unwrap();
    let w = farm.register_worker("w").unwrap().worker_id;
    // Pass 0 in full, then part of pass 1 when the time runs out.
    while farm.job(job.id).unwrap().passes == Some(0) {
        assert!(work_once(&farm, &scene, w));
        farm.wait_for_assemblies();
    }
    assert!(work_once(&farm, &scene, w));
    let held = farm.lease(w).unwrap().unwrap();
    clock.advance(4_999);
    farm.check_time_limits().unwrap();
    assert_eq!(farm.job(job.id).unwrap().state, JobState::Running);
    clock.advance(1);
    farm.check_time_limits().unwrap();
    farm.wait_for_assemblies();
    let info = farm.job(job.id).unwrap();
    assert_eq!(info.state, JobState::Done);
    // The tile that landed in pass 1 finished its block: the cut-short pass counts it, the
    // other blocks keep pass 0's two samples.
    assert_eq!(info.passes, Some(2));
    let (counts, targets) = {
        let state = farm.lock();
        let p = state.job(job.id).unwrap().progress.as_ref().unwrap();
        (p.counts.clone(), p.targets.clone())
    };
    assert_eq!(counts, targets, "nothing samples any more");
    assert!(counts.iter().any(|&n| n > 2), "{counts:?}");
    assert!(counts.contains(&2), "{counts:?}");
    assert!(info.spp_mean.unwrap() > 2.0 && info.spp_mean.unwrap() < 3.0);
    // The lease of the cut-short pass is revoked.
    assert!(matches!(
        farm.complete_sums(held.lease_id, &[]),
        Err(FarmError::Stale(_))
    ));
    let png = farm.image(job.id, None).unwrap();
    let image = Image::from_png_bytes(&png).unwrap();
    assert_eq!((image.width, image.height), (24, 16));
    assert!(image.pixels.iter().any(|v| *v > 0.0));
}

/// Runs job `job` to its end with one worker whose every tile takes the clock 1 ms per 20
/// rays it traced: a farm whose render rate is known. Returns each pass's wall seconds.
fn run_timed(farm: &Farm, clock: &ManualClock, scene: &Scene, job: u64) -> Vec<f64> {
    let w = farm.register_worker("timed").unwrap().worker_id;
    for _ in 0..10_000 {
        if farm.job(job).unwrap().state.is_finished() {
            return (farm.convergence(job).unwrap().passes)
                .iter()
                .map(|p| p.wall_s)
                .collect();
        }
        let Some(lease) = farm.lease(w).unwrap() else {
            farm.wait_for_assemblies();
            continue;
        };
        let before: f64 = match farm.lease_sums(lease.lease_id) {
            Ok(bytes) => SumImage::from_bytes(&bytes, lease.rect.pixel_count(), "sums")
                .unwrap()
                .iter()
                .skip(5)
                .step_by(adaptive::SUMS)
                .sum(),
            Err(_) => 0.0,
        };
        let sums = render(farm, scene, &lease);
        let rays: f64 = sums.iter().skip(5).step_by(adaptive::SUMS).sum::<f64>() - before;
        clock.advance((rays / 20.0).round() as u64);
        farm.complete_sums(lease.lease_id, &SumImage::to_bytes(&sums))
            .unwrap();
        farm.wait_for_assemblies();
    }
    panic!("job {job} never finished");
}

/// A farm on a manual clock that has run one job without a time limit (96×64, tiles of 16,
/// threshold 0, 8 to 64 spp) on the clock driven by its rays (`run_timed`).
struct TimedFarm {
    _dir: tempfile::TempDir,
    clock: Arc<ManualClock>,
    farm: Arc<Farm>,
    scene: Scene,
    free: u64,
    /// When each of the free job's passes ended, in seconds of the clock.
    free_walls: Vec<f64>,
}

impl TimedFarm {
    fn new() -> TimedFarm {
        let scene = cornell();
        let dir = tempfile::tempdir().unwrap();
        let clock = Arc::new(ManualClock::new(0));
        let farm = Farm::for_tests(dir.path(), FarmConfig::default(), clock.clone());
        let free = farm
            .submit(sized_job(&farm, 96, 64, 16, rules(0.0, 8, 64)))
            .unwrap()
            .id;
        let free_walls = run_timed(&farm, &clock, &scene, free);
        TimedFarm {
            _dir: dir,
            clock,
            farm,
            scene,
            free,
            free_walls,
        }
    }

    /// Runs the same job with a time limit of `limit_s`: its passes' end times, and the
    /// seconds of the clock from its submission to its end.
    fn run_limited(&self, limit_s: f64) -> (u64, Vec<f64>, f64) {
        let mut r = rules(0.0, 8, 64);
        r.time_limit_s = Some(limit_s);
        let job = self
            .farm
            .submit(sized_job(&self.farm, 96, 64, 16, r))
            .unwrap()
            .id;
        let start = self.clock.now_ms();
        let walls = run_timed(&self.farm, &self.clock, &self.scene, job);
        let used = (self.clock.now_ms() - start) as f64 / 1000.0;
        (job, walls, used)
    }
}

#[test]
fn the_pass_that_would_run_into_the_time_limit_is_sized_to_end_before_it() {
    let timed = TimedFarm::new();
    let farm = &timed.farm;
    // Without a limit, passes double: they end at about 1, 2, 4, 8… times the first's time.
    let walls = &timed.free_walls;
    let first = walls[0];
    assert!(first > 0.05 && walls[2] > 3.0 * first, "{walls:?}");
    // A limit of 6 first passes: doubling passes would be cut short in the fourth.
    let limit = 6.0 * first;
    let (limited, walls_limited, used) = timed.run_limited(limit);
    let info = farm.job(limited).unwrap();
    assert_eq!(info.state, JobState::Done);
    // With a limit passes may triple (the second ends at about 3 first passes), and the
    // last is sized to the time left: it ends before the limit (the clock never reached
    // it: no pass was cut short), and the job ends there rather than start a pass too
    // small to be worth its overhead.
    assert_eq!(walls_limited[0], first);
    assert!(walls_limited[1] > 2.5 * first, "{walls_limited:?}");
    let last = *walls_limited.last().unwrap();
    assert!(
        walls_limited.len() == 3 && last > 0.8 * limit && last < limit,
        "{walls_limited:?}, limit {limit}"
    );
    assert!(used < limit, "ended before the limit");
    // More samples by the limit than the doubling passes had when they passed it.
    let free_passes = farm.convergence(timed.free).unwrap().passes;
    let free_by_limit = free_passes.iter().rfind(|p| p.wall_s < limit).unwrap();
    assert!(
        info.spp_mean.unwrap() > free_by_limit.spp_mean,
        "{:?} against {free_by_limit:?}",
        info.spp_mean
    );
}

#[test]
fn the_last_pass_takes_the_whole_time_left_rather_than_end_early() {
    let timed = TimedFarm::new();
    let first = timed.free_walls[0];
    // 3.2 first passes: a full second pass (twice the image's rays, to about 3 first passes)
    // would leave too little for a third worth its overhead. The second pass takes the whole
    // time left instead of leaving it unused.
    let limit = 3.2 * first;
    let (_, walls, used) = timed.run_limited(limit);
    assert_eq!(walls.len(), 2, "{walls:?}, limit {limit}");
    assert!(
        used > 0.95 * limit && used < limit,
        "ended at {used} s of {limit}: {walls:?}"
    );
}

#[test]
fn a_coordinator_killed_between_passes_resumes_without_losing_a_finished_pass() {
    let scene = cornell();
    let reference = {
        let dir = tempfile::tempdir().unwrap();
        let farm = farm_at(dir.path(), Arc::new(ManualClock::new(0)));
        let job = farm
            .submit(adaptive_job(&farm, 8, rules(0.03, 2, 16)))
            .unwrap();
        run(&farm, &scene, job.id, 1);
        (
            linear(&farm, job.id),
            farm.convergence(job.id).unwrap().passes,
        )
    };
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(0));
    let (job, passes_before) = {
        let farm = farm_at(dir.path(), clock.clone());
        let job = farm
            .submit(adaptive_job(&farm, 8, rules(0.03, 2, 16)))
            .unwrap();
        let w = farm.register_worker("w").unwrap().worker_id;
        while farm.job(job.id).unwrap().passes.unwrap() < 2 {
            assert!(work_once(&farm, &scene, w));
            farm.wait_for_assemblies();
        }
        // Part of pass 2 is done when the coordinator dies.
        assert!(work_once(&farm, &scene, w));
        let before = farm.convergence(job.id).unwrap().passes;
        (job.id, before)
        // Dropped without a shutdown: only what was committed and written survives.
    };
    let farm = farm_at(dir.path(), clock);
    let info = farm.job(job).unwrap();
    assert_eq!(info.passes, Some(2), "both finished passes survived");
    assert_eq!(farm.convergence(job).unwrap().passes, passes_before);
    run(&farm, &scene, job, 1);
    assert_eq!(
        (
            linear(&farm, job),
            farm.convergence(job).unwrap().passes.len()
        ),
        (reference.0, reference.1.len())
    );
}

#[test]
fn a_lost_pass_row_is_rebuilt_from_the_sums_file() {
    let scene = cornell();
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(0));
    let (job, before) = {
        let farm = farm_at(dir.path(), clock.clone());
        let job = farm
            .submit(adaptive_job(&farm, 8, rules(0.0, 2, 16)))
            .unwrap();
        let w = farm.register_worker("w").unwrap().worker_id;
        while farm.job(job.id).unwrap().passes.unwrap() < 2 {
            assert!(work_once(&farm, &scene, w));
            farm.wait_for_assemblies();
        }
        let before = farm.convergence(job.id).unwrap().passes;
        // As if the crash came after the sums file but before the pass's row.
        farm.lock()
            .db
            .execute_for_tests("DELETE FROM passes WHERE pass = 1");
        farm.flush().unwrap();
        (job.id, before)
    };
    let farm = farm_at(dir.path(), clock);
    let passes = farm.convergence(job).unwrap().passes;
    assert_eq!(passes.len(), 2);
    assert_eq!(passes[..], before[..]);
}

#[test]
fn bad_rules_and_pixels_for_a_pass_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::for_tests(
        dir.path(),
        FarmConfig::default(),
        Arc::new(ManualClock::new(0)),
    );
    for bad in [rules(0.1, 1, 8), rules(0.1, 8, 4), rules(-1.0, 2, 8)] {
        let err = farm.submit(adaptive_job(&farm, 8, bad)).unwrap_err();
        assert!(matches!(err, FarmError::BadRequest(_)), "{err}");
    }
    let mut frames = adaptive_job(&farm, 8, rules(0.1, 2, 8));
    frames.spec.frames = Some(tracer_core::FrameRange::new(0, 1).unwrap());
    assert!(matches!(farm.submit(frames), Err(FarmError::BadRequest(_))));
    let job = farm
        .submit(adaptive_job(&farm, 8, rules(0.1, 2, 8)))
        .unwrap();
    let w = farm.register_worker("w").unwrap().worker_id;
    let lease = farm.lease(w).unwrap().unwrap();
    let pixels = protocol::pixels_to_bytes(&vec![0.5; lease.rect.pixel_count() * 3]);
    assert!(matches!(
        farm.complete(lease.lease_id, &pixels),
        Err(FarmError::BadRequest(_))
    ));
    let nan = SumImage::to_bytes(&vec![f64::NAN; lease.rect.pixel_count() * adaptive::SUMS]);
    assert!(matches!(
        farm.complete_sums(lease.lease_id, &nan),
        Err(FarmError::BadRequest(_))
    ));
    assert!(matches!(
        farm.samples_png(job.id),
        Err(FarmError::Conflict(_))
    ));
}

#[test]
fn a_version_1_sums_file_from_an_older_coordinator_still_resumes() {
    let mut spec = JobSpec::default();
    spec.render.width = 24;
    spec.render.height = 16;
    spec.adaptive = Some(rules(0.0, 2, 16));
    let mut progress = progressive::Progress::new(&spec).unwrap();
    for (i, v) in progress.sums.data.iter_mut().enumerate() {
        *v = i as f64 * 0.5;
    }
    progress.counts.iter_mut().for_each(|n| *n = 4);
    let current = progressive::Progress::encode(&progress);
    // The same state as version 1 wrote it: version byte 1, five sums a pixel (no ray count).
    let header = 8 + 4 + 8 + 4 + 4 + progress.counts.len() * 5;
    let mut old = current[..header].to_vec();
    old[7] = 1;
    for pixel in current[header..].chunks_exact(adaptive::SUMS * 8) {
        old.extend_from_slice(&pixel[..5 * 8]);
    }
    let restored = progressive::Progress::restore(&spec, Some(&old), vec![])
        .unwrap()
        .unwrap();
    assert_eq!(restored.counts, progress.counts);
    for (new, was) in restored
        .sums
        .data
        .chunks_exact(adaptive::SUMS)
        .zip(progress.sums.data.chunks_exact(adaptive::SUMS))
    {
        assert_eq!(new[..5], was[..5], "a version-1 pixel's sums are kept");
        assert_eq!(
            new[5], 4.0,
            "one ray per sample stands in for the missing count"
        );
    }
    // A file of neither version is still refused.
    let mut bad = old.clone();
    bad[7] = 9;
    assert!(progressive::Progress::restore(&spec, Some(&bad), vec![]).is_err());
}
