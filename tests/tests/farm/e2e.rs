//! The farm's image equals the local render's, bytes for bytes, for any worker count and tile
//! size, frame by frame for a frame-range job; cancelling reaches rendering workers within
//! about a second.

use std::path::Path;
use std::process::Command;
use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::JobState;
use tracer_core::ImageFormat;

use crate::helpers::*;

/// Waits until the coordinator has seen `n` workers ask for work.
async fn wait_for_workers(url: &str, n: usize) {
    let start = Instant::now();
    let needle = format!("tessera_workers_seen {n}\n");
    loop {
        let text = reqwest::get(format!("{url}/metrics"))
            .await
            .unwrap()
            .text()
            .await
            .unwrap();
        if text.contains(&needle) {
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "workers never showed up"
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

/// A coordinator and two one-thread worker processes, logging under `dir`, once both have
/// asked for work.
async fn two_worker_farm(dir: &std::path::Path) -> (Coordinator, [Proc; 2]) {
    let coord = start_coordinator(&dir.join("data"), 0, &[], dir.join("c.log"));
    let workers = ["w1", "w2"].map(|name| {
        start_worker(
            &coord.url,
            name,
            &["--threads", "1"],
            dir.join(format!("{name}.log")),
        )
    });
    wait_for_workers(&coord.url, 2).await;
    (coord, workers)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn two_workers_render_stacks_exactly_like_the_tracer() {
    let tmp = tempfile::tempdir().unwrap();
    let (coord, workers) = two_worker_farm(tmp.path()).await;
    let client = Client::new(&coord.url, None).unwrap();
    let scene = course_scene("stacks.scene");
    // An odd tile size leaves ragged tiles at the right and bottom edges.
    for (spp, tile) in [(4, 32), (8, 17)] {
        let spec = small_spec(spp, tile);
        let job = submit(&client, &scene, spec.clone()).await;
        let done = wait_finished(&client, job.id, Duration::from_secs(60)).await;
        assert_eq!(done.state, JobState::Done, "{done:?}");
        assert_eq!(done.tiles_done, done.tiles_total);
        let farm_png = client.image(job.id).await.unwrap();
        let tracer = tracer_png(&scene, &spec, tmp.path());
        assert!(
            farm_png == tracer,
            "the farm's PNG differs from tracer render's (tile {tile}, spp {spp})"
        );
        // The linear image too: EXR and PFM bytes equal the tracer's.
        for format in [ImageFormat::Exr, ImageFormat::Pfm] {
            let farm = client.image_in(job.id, None, format).await.unwrap();
            let tracer = tracer_image(&scene, &spec, tmp.path(), format.extension());
            assert!(
                farm == tracer,
                "the farm's {format:?} differs from tracer render's (tile {tile}, spp {spp})"
            );
        }
        let logs: Vec<String> = workers.iter().map(Proc::log_text).collect();
        let counts = rendered_tiles(&logs, job.id);
        assert_eq!(counts.len() as u32, done.tiles_total, "every tile rendered");
    }
    let bogus = reqwest::get(format!("{}/api/v1/jobs/1/image?format=bogus", coord.url))
        .await
        .unwrap();
    assert_eq!(bogus.status(), 400);
    let error: protocol::ApiError = bogus.json().await.unwrap();
    assert!(error.error.contains("bogus"), "{error:?}");
    let logs: Vec<String> = workers.iter().map(Proc::log_text).collect();
    for (i, log) in logs.iter().enumerate() {
        assert!(
            log.contains(": rendered in "),
            "worker {} rendered nothing:\n{log}",
            i + 1
        );
        // One scene load per job, however many tiles.
        assert!(log.matches("loaded stacks.scene").count() <= 2, "{log}");
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn cancelling_a_job_stops_its_rendering_tiles_within_a_second() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--heartbeat", "0.25"],
        tmp.path().join("c.log"),
    );
    let worker = start_worker(
        &coord.url,
        "w1",
        &["--threads", "2"],
        tmp.path().join("w.log"),
    );
    let client = Client::new(&coord.url, None).unwrap();
    // One tile that takes many seconds, in short rows: the worker checks for a cancel between
    // rows, so this measures how fast the cancel travels, not how long a row takes on a
    // loaded machine.
    let mut spec = small_spec(4096, 512);
    spec.render.width = 8;
    spec.render.height = 512;
    let job = submit(&client, &course_scene("stacks.scene"), spec).await;
    wait_until(&client, job.id, Duration::from_secs(20), |j| {
        j.tiles_running == 1
    })
    .await;
    tokio::time::sleep(Duration::from_millis(300)).await;
    let cancelled = client.cancel(job.id).await.unwrap();
    assert_eq!(cancelled.state, JobState::Cancelled);
    let start = Instant::now();
    while !worker.log_text().contains("dropped after") {
        assert!(
            start.elapsed() < Duration::from_millis(1500),
            "the worker kept rendering a cancelled tile:\n{}",
            worker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    // Cancelling twice is a conflict; the partial image is still served.
    assert!(client.cancel(job.id).await.is_err());
    let png = client.image(job.id).await.unwrap();
    let image = tracer_core::Image::from_png_bytes(&png).unwrap();
    assert_eq!((image.width, image.height), (8, 512));
}

/// The README's first command: the embedded farm renders the showcase scene, byte-identical
/// to `tracer render`, with any worker count.
#[test]
fn coordinator_render_matches_the_tracer_on_the_showcase_scene() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = workspace().join("scenes").join("showcase.scene");
    let spec = small_spec(4, 64);
    let tracer = tracer_png(&scene, &spec, tmp.path());
    for workers in ["1", "3"] {
        let png = coordinator_render(
            &scene,
            &tmp.path().join(format!("farm-{workers}.png")),
            &[
                "--width",
                "160",
                "--height",
                "120",
                "--spp",
                "4",
                "--workers",
                workers,
                "--tile-size",
                "24",
            ],
        );
        assert!(
            png == tracer,
            "coordinator render --workers {workers} differs from tracer render"
        );
    }
    // `-o out.exr` downloads the linear image, the tracer's bytes too.
    let exr = coordinator_render(
        &scene,
        &tmp.path().join("farm.exr"),
        &[
            "--width",
            "160",
            "--height",
            "120",
            "--spp",
            "4",
            "--workers",
            "3",
            "--tile-size",
            "24",
            "-q",
        ],
    );
    assert!(
        exr == tracer_image(&scene, &spec, tmp.path(), "exr"),
        "coordinator render -o farm.exr differs from tracer render -o x.exr"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_frame_range_job_yields_each_frame_exactly_like_the_tracer() {
    let tmp = tempfile::tempdir().unwrap();
    let (coord, _workers) = two_worker_farm(tmp.path()).await;
    let client = Client::new(&coord.url, None).unwrap();
    let scene = own_scene("motion_blur.scene");
    let mut spec = small_spec(2, 16);
    spec.render.width = 64;
    spec.render.height = 48;
    spec.frames = Some(tracer_core::FrameRange::new(2, 4).unwrap());
    let job = submit(&client, &scene, spec.clone()).await;
    assert_eq!(job.tiles_total, 3 * 4 * 3, "three frames of 4x3 tiles");
    let done = wait_finished(&client, job.id, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");

    let mut frames = Vec::new();
    for frame in 2..=4 {
        let farm_png = client.frame_image(job.id, frame).await.unwrap();
        let mut still = spec.clone();
        still.frames = None;
        still.render.frame = frame;
        let tracer = tracer_png(&scene, &still, tmp.path());
        assert!(
            farm_png == tracer,
            "frame {frame}: the farm's PNG differs from tracer render --frame {frame}"
        );
        frames.push(farm_png);
    }
    assert_ne!(frames[0], frames[2], "the frames show the animation");
    // A frame's linear image, stored beside its PNG after the tiles are gone.
    let farm_exr = client
        .image_in(job.id, Some(3), ImageFormat::Exr)
        .await
        .unwrap();
    let mut still = spec.clone();
    still.frames = None;
    still.render.frame = 3;
    assert!(
        farm_exr == tracer_image(&scene, &still, tmp.path(), "exr"),
        "frame 3: the farm's EXR differs from tracer render --frame 3 -o x.exr"
    );
    // The job's own image is its first frame; a frame it does not render is a 404.
    assert_eq!(client.image(job.id).await.unwrap(), frames[0]);
    let missing = reqwest::get(format!(
        "{}/api/v1/jobs/{}/image?frame=9",
        coord.url, job.id
    ))
    .await
    .unwrap();
    assert_eq!(missing.status(), 404);
    assert!(missing.text().await.unwrap().contains("no frame 9"));

    // The whole sequence as one download: numbered PNGs, in order, equal to the frames.
    let tar = reqwest::get(format!("{}/api/v1/jobs/{}/frames.tar", coord.url, job.id))
        .await
        .unwrap();
    assert_eq!(tar.status(), 200);
    let bytes = tar.bytes().await.unwrap();
    let mut archive = tar::Archive::new(bytes.as_ref());
    let mut entries = Vec::new();
    for entry in archive.entries().unwrap() {
        let mut entry = entry.unwrap();
        let name = entry.path().unwrap().display().to_string();
        let mut data = Vec::new();
        std::io::Read::read_to_end(&mut entry, &mut data).unwrap();
        entries.push((name, data));
    }
    let names: Vec<&str> = entries.iter().map(|(n, _)| n.as_str()).collect();
    assert_eq!(
        names,
        [
            "motion_blur_0002.png",
            "motion_blur_0003.png",
            "motion_blur_0004.png"
        ]
    );
    for ((_, data), frame) in entries.iter().zip(&frames) {
        assert!(data == frame);
    }
}

/// Caustics through the farm: every worker builds the same photon map, so the embedded farm
/// gives `tracer render`'s bytes with any worker count (issue #6's determinism contract).
#[test]
fn coordinator_render_matches_the_tracer_with_caustics() {
    let tmp = tempfile::tempdir().unwrap();
    let scene = workspace().join("scenes").join("caustics.scene");
    let size = ["--width", "160", "--height", "120", "--spp", "2"];
    // Fewer photons than the scene asks for keeps the test fast; --photons reaches the
    // workers through the job's settings.
    let caustics = ["--photons", "30000", "--photon-radius", "0.08"];
    let tracer = tmp.path().join("tracer.png");
    let status = std::process::Command::new(&bins().tracer)
        .arg("render")
        .arg(&scene)
        .arg("-o")
        .arg(&tracer)
        .arg("-q")
        .args(size)
        .args(caustics)
        .status()
        .unwrap();
    assert!(status.success());
    let tracer = std::fs::read(&tracer).unwrap();
    let off = tmp.path().join("off.png");
    let status = std::process::Command::new(&bins().tracer)
        .arg("render")
        .arg(&scene)
        .arg("-o")
        .arg(&off)
        .arg("-q")
        .args(size)
        .arg("--no-caustics")
        .status()
        .unwrap();
    assert!(status.success());
    assert!(
        std::fs::read(&off).unwrap() != tracer,
        "caustics changed nothing"
    );
    for workers in ["1", "3"] {
        let args = [
            &size[..],
            &caustics[..],
            &["--workers", workers, "--tile-size", "32"],
        ]
        .concat();
        let png = coordinator_render(
            &scene,
            &tmp.path().join(format!("farm-{workers}.png")),
            &args,
        );
        assert!(
            png == tracer,
            "coordinator render --workers {workers} differs from tracer render with caustics"
        );
    }
}

/// `coordinator render` and `tracer render` agree on flags, messages and exit codes: negative
/// camera coordinates parse, a missing scene is a scene error (3) without a position, an
/// output that is not a PNG is a usage error (2) before anything is read.
#[test]
fn both_command_lines_share_flags_and_exit_codes() {
    let tmp = tempfile::tempdir().unwrap();
    let run = |bin: &Path, args: &[&str]| {
        let out = Command::new(bin)
            .arg("render")
            .args(args)
            .current_dir(tmp.path())
            .output()
            .unwrap();
        (
            out.status.code(),
            String::from_utf8_lossy(&out.stderr).into_owned(),
        )
    };
    for bin in [&bins().tracer, &bins().coordinator] {
        let (code, err) = run(bin, &["nosuch.scene", "-o", "x.png"]);
        assert_eq!(code, Some(3), "{err}");
        assert!(
            err.trim_end()
                .ends_with("cannot read nosuch.scene: No such file or directory (os error 2)"),
            "{err}"
        );
        let (code, err) = run(bin, &["nosuch.scene", "-o", "x.jpg"]);
        assert_eq!(code, Some(2), "{err}");
        assert!(
            err.contains("the output must be a .png, .exr or .pfm file"),
            "{err}"
        );
        let (code, err) = run(
            bin,
            &[
                "nosuch.scene",
                "--camera-pos",
                "-10,4,10",
                "--look-at",
                "0,-1,0",
            ],
        );
        assert_eq!(
            code,
            Some(3),
            "negative coordinates parse, then the scene is missing: {err}"
        );
        let (code, err) = run(bin, &["nosuch.scene", "--spp", "0"]);
        assert_eq!(code, Some(2), "{err}");
    }
}
