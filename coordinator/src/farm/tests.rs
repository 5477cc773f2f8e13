use super::*;
use crate::clock::ManualClock;
use crate::store::files::Frame;
use protocol::{FailureReport, Lease, TileState, WorkerState};
use tracer_core::TileRect;

impl Farm {
    /// Leases as the worker registered under `name`, registering it on first use (names are
    /// unique in these tests, so they stand for identities).
    fn lease_named(&self, name: &str) -> Result<Option<Lease>> {
        let known = self.lock().workers.id_of(name);
        let id = match known {
            Some(id) => id,
            None => self.register_worker(name)?.worker_id,
        };
        self.lease(id)
    }

    fn all_tiles(&self, job_id: u64) -> Result<Vec<TileInfo>> {
        Ok(self.tiles(job_id, 0, MAX_TILE_PAGE)?.tiles)
    }
}

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
pub(crate) fn new_job(name: &str) -> NewJob {
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

/// [`new_job`] with its scene stored, so a restart finds everything it needs.
fn stored_job(farm: &Farm, name: &str) -> NewJob {
    let mut new = new_job(name);
    new.scene_hash = farm.files().put_blob(b"<scene/>").unwrap();
    new
}

fn blank(rect: TileRect, value: f32) -> Vec<u8> {
    protocol::pixels_to_bytes(&vec![value; rect.pixel_count() * 3])
}

/// Completes a lease; the job's id when that was its last tile.
fn finish(farm: &Farm, lease: &Lease) -> Option<u64> {
    let done = farm
        .complete(lease.lease_id, &blank(lease.rect, 0.5))
        .unwrap();
    (done.tiles_done == done.tiles_total).then_some(lease.job_id)
}

#[test]
fn leases_go_oldest_job_first_and_asking_again_returns_the_same_lease() {
    let f = fixture(FarmConfig::default());
    let a = f.farm.submit(new_job("a")).unwrap();
    let b = f.farm.submit(new_job("b")).unwrap();
    let l1 = f.farm.lease_named("w1").unwrap().unwrap();
    assert_eq!((l1.job_id, l1.tile), (a.id, 0));
    assert_eq!(f.farm.lease_named("w1").unwrap().unwrap(), l1);
    let l2 = f.farm.lease_named("w2").unwrap().unwrap();
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
        farm.all_tiles(job.id)
            .unwrap()
            .iter()
            .map(|t| t.state)
            .collect()
    };

    let l1 = f.farm.lease_named("w1").unwrap().unwrap();
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
    let l2 = f.farm.lease_named("w2").unwrap().unwrap();
    let report = FailureReport {
        error: "boom".into(),
        scene: false,
    };
    f.farm.fail(l2.lease_id, &report).unwrap();
    let tile = f.farm.tile(job.id, l2.tile).unwrap();
    assert_eq!((tile.state, tile.attempts), (TileState::Failed, 1));

    // A worker whose lease lapses is lost; one silent past a long poll too.
    let l3 = f.farm.lease_named("w3").unwrap().unwrap();
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
    assert!(matches!(f.farm.all_tiles(99), Err(FarmError::NotFound(_))));
}

#[test]
fn a_silent_worker_loses_its_tile_without_a_failure() {
    let f = fixture(FarmConfig::default());
    let job = f.farm.submit(new_job("a")).unwrap();
    let lease = f.farm.lease_named("dead").unwrap().unwrap();
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
    let again = f.farm.lease_named("alive").unwrap().unwrap();
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
        let lease = f.farm.lease_named(&format!("w{i}")).unwrap().unwrap();
        // Tiles go frame by frame, and the lease tells the worker which frame.
        let frame = 3 + lease.tile / 4;
        assert_eq!(lease.settings.frame, frame);
        let tiles = f.farm.all_tiles(job.id).unwrap();
        assert_eq!(tiles[lease.tile as usize].frame, frame);
        let done = f
            .farm
            .complete(lease.lease_id, &blank(lease.rect, frame as f32 / 10.0))
            .unwrap();
        last = Some(done.tiles_done);
    }
    assert_eq!(last, Some(12));
    f.farm.wait_for_assemblies();
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
    // The tiles are gone, yet each frame's linear pixels are served exactly.
    for (frame, value) in [(None, 0.3f32), (Some(4), 0.4), (Some(5), 0.5)] {
        let pfm = f
            .farm
            .image_in(job.id, frame, tracer_core::ImageFormat::Pfm)
            .unwrap();
        let linear = tracer_core::Image::from_pixels(16, 16, vec![value; 3 * 16 * 16]).unwrap();
        assert_eq!(pfm, linear.to_pfm(), "frame {frame:?}");
        let exr = f
            .farm
            .image_in(job.id, frame, tracer_core::ImageFormat::Exr)
            .unwrap();
        assert_eq!(exr, linear.to_exr(), "frame {frame:?}");
    }
}

#[test]
fn a_job_whose_image_cannot_be_built_fails_instead_of_running_forever() {
    let f = fixture(FarmConfig::default());
    let job = f.farm.submit(new_job("a")).unwrap();
    for i in 0..4 {
        let lease = f.farm.lease_named(&format!("w{i}")).unwrap().unwrap();
        f.farm
            .complete(lease.lease_id, &blank(lease.rect, 0.5))
            .unwrap();
        if i == 2 {
            // Lost before the last tile lands and assembly starts (the last tile's write
            // makes the file again, with a hole where the others were).
            let tiles = f
                ._dir
                .path()
                .join(format!("jobs/{}/tiles/pixels.f32", job.id));
            std::fs::remove_file(&tiles).unwrap();
        }
    }
    f.farm.wait_for_assemblies();
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
        let lease = f.farm.lease_named(&format!("w{i}")).unwrap().unwrap();
        let done = f
            .farm
            .complete(lease.lease_id, &blank(lease.rect, i as f32 / 4.0))
            .unwrap();
        assert_eq!((done.tiles_done, done.tiles_total), (i + 1, 4));
        last = Some(done);
    }
    assert!(last.is_some());
    assert_eq!(f.farm.tile_writes(), 4);
    // The last tile started the assembly by itself.
    f.farm.wait_for_assemblies();
    let info = f.farm.job(job.id).unwrap();
    assert_eq!((info.state, info.tiles_done), (JobState::Done, 4));
    let png = f.farm.image(job.id, None).unwrap();
    let image = tracer_core::Image::from_png_bytes(&png).unwrap();
    assert_eq!(image.pixel(0, 0), [0.0; 3]);
    assert_eq!(image.pixel(15, 15), [191.0 / 255.0; 3]);
    assert!(f.farm.lease_named("w9").unwrap().is_none());
}

#[test]
fn pixels_of_the_wrong_size_are_refused() {
    let f = fixture(FarmConfig::default());
    f.farm.submit(new_job("a")).unwrap();
    let lease = f.farm.lease_named("w").unwrap().unwrap();
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
        let lease = f.farm.lease_named(w).unwrap().unwrap();
        assert_eq!(lease.tile, 0, "the failed tile is requeued first");
        let info = f.farm.fail(lease.lease_id, &report).unwrap();
        assert_eq!(info.failures.len(), i + 1);
        if i < 2 {
            assert_eq!(info.state, JobState::Running);
            // w1 is not handed the tile it failed on while others exist.
            let other = f.farm.lease_named("w1").unwrap().unwrap();
            assert_ne!(other.tile, 0);
            f.farm.hand_back(other.lease_id).unwrap();
        } else {
            assert_eq!(info.state, JobState::Failed);
            assert!(info.error.unwrap().contains("out of memory"));
        }
    }
    assert!(f.farm.lease_named("w4").unwrap().is_none());
    // One click requeues it.
    let retried = f.farm.retry(job.id).unwrap();
    assert_eq!(retried.state, JobState::Running);
    assert!(retried.failures.is_empty());
    assert_eq!(f.farm.lease_named("w4").unwrap().unwrap().tile, 0);
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
    while let Some(lease) = f.farm.lease_named("only").unwrap() {
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
    let l1 = f.farm.lease_named("w1").unwrap().unwrap();
    let l2 = f.farm.lease_named("w2").unwrap().unwrap();
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
    let lease = f.farm.lease_named("w").unwrap().unwrap();
    let info = f.farm.cancel(job.id).unwrap();
    assert_eq!(info.state, JobState::Cancelled);
    let err = f.farm.heartbeat(lease.lease_id).unwrap_err();
    assert!(err.to_string().contains("cancelled"), "{err}");
    assert!(f.farm.lease_named("w").unwrap().is_none());
    assert!(matches!(f.farm.job(99), Err(FarmError::NotFound(_))));
}

#[test]
fn idle_workers_copy_stragglers_and_the_first_result_wins() {
    let f = fixture(FarmConfig::default());
    f.farm.submit(new_job("a")).unwrap();
    let slow = f.farm.lease_named("slow").unwrap().unwrap();
    for w in ["a", "b", "c"] {
        let l = f.farm.lease_named(w).unwrap().unwrap();
        f.clock.advance(100);
        finish(&f.farm, &l);
    }
    // Typical tile time is 100 ms; a copy needs the original to be 1 s old.
    assert!(f.farm.lease_named("idle").unwrap().is_none());
    f.clock.advance(1_000);
    let copy = f.farm.lease_named("idle").unwrap().unwrap();
    assert_eq!(copy.tile, slow.tile);
    assert_ne!(copy.lease_id, slow.lease_id);
    assert!(
        f.farm.lease_named("idle2").unwrap().is_none(),
        "one copy at most"
    );
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
    let _slow = f.farm.lease_named("slow").unwrap().unwrap();
    for w in ["a", "b", "c"] {
        let l = f.farm.lease_named(w).unwrap().unwrap();
        finish(&f.farm, &l);
    }
    f.clock.advance(60_000);
    f.farm.heartbeat(_slow.lease_id).unwrap();
    assert!(f.farm.lease_named("idle").unwrap().is_none());
}

#[test]
fn handing_back_requeues_without_a_failure() {
    let f = fixture(FarmConfig::default());
    let job = f.farm.submit(new_job("a")).unwrap();
    let lease = f.farm.lease_named("w").unwrap().unwrap();
    f.farm.hand_back(lease.lease_id).unwrap();
    assert!(matches!(
        f.farm.hand_back(lease.lease_id),
        Err(FarmError::Stale(_))
    ));
    assert_eq!(f.farm.lease_named("v").unwrap().unwrap().tile, lease.tile);
    assert!(f.farm.job(job.id).unwrap().failures.is_empty());
}

#[test]
fn a_restart_resumes_jobs_and_honours_old_leases() {
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(1_000_000));
    let (job, held) = {
        let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
        let job = farm.submit(stored_job(&farm, "a")).unwrap();
        let done = farm.lease_named("w1").unwrap().unwrap();
        finish(&farm, &done);
        let held = farm.lease_named("w2").unwrap().unwrap();
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
    assert_eq!(
        farm.lease_named("w2").unwrap().unwrap().lease_id,
        held.lease_id
    );
    let next = farm.lease_named("w3").unwrap().unwrap();
    assert_eq!(next.tile, 2, "tile 0 is done and tile 1 is held");
    assert!(
        next.lease_id > held.lease_id,
        "lease ids never repeat across restarts"
    );
    finish(&farm, &held);
    finish(&farm, &next);
    let last = farm.lease_named("w3").unwrap().unwrap();
    assert_eq!(finish(&farm, &last), Some(job.id));
    assert_eq!(
        farm.tile_writes(),
        3,
        "the finished tile was not rendered again"
    );
    farm.wait_for_assemblies();
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
        let job = farm.submit(stored_job(&farm, "a")).unwrap();
        for w in ["a", "b", "c"] {
            let l = farm.lease_named(w).unwrap().unwrap();
            finish(&farm, &l);
        }
        job
    };
    // The crash came after the last tile's pixels and row were stored, before assembly.
    let files = Files::open(dir.path()).unwrap();
    files
        .put_tile(
            job.id,
            Frame {
                number: 0,
                width: 16,
                height: 16,
            },
            3,
            8,
            TileRect::new(8, 8, 8, 8),
            &blank(TileRect::new(8, 8, 8, 8), 0.5),
        )
        .unwrap();
    Db::open(&dir.path().join("tessera.db"))
        .unwrap()
        .complete_tile(job.id, 3)
        .unwrap();
    let farm = Farm::open(dir.path(), FarmConfig::default(), clock).unwrap();
    farm.wait_for_assemblies();
    assert_eq!(farm.job(job.id).unwrap().state, JobState::Done);
}

#[test]
fn two_workers_sharing_a_name_never_hold_one_lease() {
    let f = fixture(FarmConfig::default());
    f.farm.submit(new_job("a")).unwrap();
    let a = f.farm.register_worker("host-1").unwrap();
    let b = f.farm.register_worker("host-1").unwrap();
    assert_ne!(a.worker_id, b.worker_id);
    let la = f.farm.lease(a.worker_id).unwrap().unwrap();
    let lb = f.farm.lease(b.worker_id).unwrap().unwrap();
    assert_ne!(la.lease_id, lb.lease_id);
    assert_ne!(la.tile, lb.tile);
    // Each asking again gets its own lease back.
    assert_eq!(
        f.farm.lease(a.worker_id).unwrap().unwrap().lease_id,
        la.lease_id
    );
    assert_eq!(
        f.farm.lease(b.worker_id).unwrap().unwrap().lease_id,
        lb.lease_id
    );
    let listed: Vec<(u64, String)> = f
        .farm
        .workers()
        .into_iter()
        .map(|w| (w.id, w.name))
        .collect();
    assert_eq!(
        listed,
        [
            (a.worker_id, "host-1".to_string()),
            (b.worker_id, "host-1".to_string())
        ]
    );
    assert!(matches!(f.farm.lease(999), Err(FarmError::NotFound(_))));
    assert!(matches!(
        f.farm.register_worker(""),
        Err(FarmError::BadRequest(_))
    ));
}

#[test]
fn a_job_over_the_tile_budget_is_refused_before_it_is_stored() {
    let mut config = FarmConfig::default();
    config.limits.max_job_tiles = 3;
    let f = fixture(config);
    let err = f.farm.submit(new_job("a")).unwrap_err();
    assert!(
        matches!(&err, FarmError::BadRequest(e) if e.error.contains("--max-job-tiles")),
        "{err}"
    );
    assert!(f.farm.jobs().is_empty());
}

#[test]
fn tile_pages_are_bounded() {
    let f = fixture(FarmConfig::default());
    let mut new = new_job("big");
    new.spec.render.width = 1024;
    new.spec.render.height = 1024;
    new.spec.tile_size = 4;
    let job = f.farm.submit(new).unwrap();
    assert_eq!(job.tiles_total, 65_536);
    let page = f.farm.tiles(job.id, 0, u32::MAX).unwrap();
    assert_eq!(page.tiles.len() as u32, MAX_TILE_PAGE);
    assert_eq!(page.tiles_total, 65_536);
    let page = f.farm.tiles(job.id, 65_530, 100).unwrap();
    assert_eq!(
        page.tiles.iter().map(|t| t.tile).collect::<Vec<_>>(),
        (65_530..65_536).collect::<Vec<_>>()
    );
    assert!(f.farm.tiles(job.id, 70_000, 10).unwrap().tiles.is_empty());
}

#[test]
fn a_restart_fails_jobs_it_cannot_load_and_serves_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let clock = Arc::new(ManualClock::new(5));
    let (good, bad_spec, too_big, no_scene) = {
        let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
        // The scene blob exists for the jobs that should resume.
        let hash = farm.files().put_blob(b"<scene/>").unwrap();
        let mut ids = Vec::new();
        for name in ["good", "bad-spec", "too-big", "no-scene"] {
            let mut new = new_job(name);
            if name != "no-scene" {
                new.scene_hash = hash.clone();
            }
            ids.push(farm.submit(new).unwrap().id);
        }
        (ids[0], ids[1], ids[2], ids[3])
    };
    {
        let db = Db::open(&dir.path().join("tessera.db")).unwrap();
        db.execute_for_tests(&format!(
            "UPDATE jobs SET spec = '{{\"render\": 7' WHERE id = {bad_spec};
             UPDATE jobs SET spec = '{{\"render\": {{\"width\": 16384, \"height\": 16384}}, \"tile_size\": 4}}'
                 WHERE id = {too_big};"
        ));
    }
    let farm = Farm::open(dir.path(), FarmConfig::default(), clock.clone()).unwrap();
    let state_of = |id| farm.job(id).unwrap();
    assert_eq!(state_of(good).state, JobState::Queued);
    for (id, why) in [
        (bad_spec, "settings do not parse"),
        (too_big, "--max-job-tiles"),
        (no_scene, "missing from the data dir"),
    ] {
        let info = state_of(id);
        assert_eq!(info.state, JobState::Failed, "job {id}");
        assert!(
            info.error.as_deref().unwrap_or("").contains(why),
            "{:?}",
            info.error
        );
    }
    // The good job is served as before.
    let lease = farm.lease_named("w").unwrap().unwrap();
    assert_eq!(lease.job_id, good);
    drop(farm);
    // The failures were stored: the next start sees the same.
    let farm = Farm::open(dir.path(), FarmConfig::default(), clock).unwrap();
    assert_eq!(farm.job(too_big).unwrap().state, JobState::Failed);
    assert_eq!(farm.job(good).unwrap().state, JobState::Running);
}

#[test]
fn a_failed_lease_write_leaves_no_phantom_lease_for_the_straggler_search() {
    let f = fixture(FarmConfig::default());
    f.farm.submit(new_job("a")).unwrap();
    let slow = f.farm.lease_named("slow").unwrap().unwrap();
    for w in ["a", "b", "c"] {
        let l = f.farm.lease_named(w).unwrap().unwrap();
        f.clock.advance(100);
        finish(&f.farm, &l);
    }
    f.clock.advance(1_000);
    let idle = f.farm.register_worker("idle").unwrap().worker_id;
    f.farm.lock().db.fail_writes(true);
    // The straggler copy cannot be stored: an error, and nothing half-granted.
    assert!(matches!(f.farm.lease(idle), Err(FarmError::Store(_))));
    assert_eq!(
        f.farm.tile(slow.job_id, slow.tile).unwrap().workers,
        ["slow"]
    );
    f.farm.lock().db.fail_writes(false);
    // The search runs again over a consistent state, and hands out the copy.
    let copy = f.farm.lease(idle).unwrap().unwrap();
    assert_eq!(copy.tile, slow.tile);
    assert_ne!(copy.lease_id, slow.lease_id);
}

/// A scene that builds: a camera and nothing else.
fn empty_scene() -> Scene {
    let text = r#"<scene><camera><fov v="0.9"/><near_clip v="0.1"/><far_clip v="100"/>
        <position x="0" y="0" z="10"/><orientation a="0" x="0" y="1" z="0"/>
        </camera><background_color r="0" g="0" b="0"/><refractive_index v="1"/></scene>"#;
    let desc = tracer_core::scene::SceneDescription::parse(text, "t.scene").unwrap();
    let assets = tracer_core::MemoryAssets {
        files: Default::default(),
    };
    Scene::build(&desc, "t.scene", &assets).unwrap()
}

#[test]
fn a_built_scene_reaches_the_sink_with_its_job_id_before_any_lease() {
    let f = fixture(FarmConfig::default());
    assert!(!f.farm.wants_built_scenes());
    // Without a sink a scene handed in is only dropped.
    let a = f
        .farm
        .submit_built(new_job("a"), Some(empty_scene()))
        .unwrap();
    let got: Arc<Mutex<Vec<(u64, u32)>>> = Arc::default();
    {
        let (got, farm) = (got.clone(), Arc::downgrade(&f.farm));
        f.farm.share_built_scenes(move |id, scene| {
            // Called under the farm's lock: no lease of the job can have been granted.
            let farm = farm.upgrade().unwrap();
            assert!(farm.state.try_lock().is_err(), "the farm's lock is held");
            got.lock().unwrap().push((id, scene.frame_count()));
        });
    }
    assert!(f.farm.wants_built_scenes());
    let b = f
        .farm
        .submit_built(new_job("b"), Some(empty_scene()))
        .unwrap();
    f.farm.submit(new_job("c")).unwrap();
    assert_eq!(*got.lock().unwrap(), [(b.id, 1)]);
    assert_ne!(a.id, b.id);
}
