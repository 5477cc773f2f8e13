//! Progressive jobs across processes: `coordinator render` with stopping rules gives the same
//! bytes with one or three workers and any tile size, and says where its samples went; a
//! `coordinator serve` farm with worker processes serves the passes, the convergence route and
//! the sample map.

use std::process::Command;
use std::time::Duration;

use protocol::client::Client;
use protocol::{AdaptiveSpec, JobState};

use crate::helpers::*;

/// `coordinator render` with `args`; its PNG and its last line on stderr.
fn render(out: &std::path::Path, args: &[&str]) -> (Vec<u8>, String) {
    let output = Command::new(&bins().coordinator)
        .arg("render")
        .arg(course_scene("cornell_box.scene"))
        .arg("-o")
        .arg(out)
        .args(["--width", "64", "--height", "48", "--quiet"])
        .args(args)
        .output()
        .unwrap();
    let stderr = String::from_utf8_lossy(&output.stderr).to_string();
    assert!(
        output.status.success(),
        "coordinator render {args:?}: {stderr}"
    );
    let last = stderr.lines().last().unwrap_or_default().to_string();
    (std::fs::read(out).unwrap(), last)
}

#[test]
fn coordinator_render_is_the_same_with_one_or_three_workers_and_reports_mean_spp() {
    let tmp = tempfile::tempdir().unwrap();
    let rules = [
        "--noise-threshold",
        "0.03",
        "--spp-min",
        "4",
        "--spp-max",
        "32",
    ];
    let (one, line) = render(
        &tmp.path().join("one.png"),
        &[
            &rules[..],
            &["--workers", "1", "--threads", "2", "--tile-size", "16"],
        ]
        .concat(),
    );
    let (three, _) = render(
        &tmp.path().join("three.png"),
        &[
            &rules[..],
            &["--workers", "3", "--threads", "3", "--tile-size", "13"],
        ]
        .concat(),
    );
    assert!(one == three, "1 and 3 workers gave different images");
    assert!(line.contains("mean spp "), "{line}");
    assert!(line.contains("estimated error "), "{line}");
    let spp: f64 = line
        .split("mean spp ")
        .nth(1)
        .and_then(|s| s.split(',').next())
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| panic!("no mean spp in {line:?}"));
    assert!((4.0..32.0).contains(&spp), "{line}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_served_progressive_job_converges_through_worker_processes() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(&tmp.path().join("data"), 0, &[], tmp.path().join("c.log"));
    let _worker = start_worker(
        &coord.url,
        "w1",
        &["--threads", "2"],
        tmp.path().join("w.log"),
    );
    let client = Client::new(&coord.url, None).unwrap();
    let mut spec = small_spec(1, 32);
    spec.adaptive = Some(AdaptiveSpec {
        noise_threshold: 0.0,
        spp_min: 2,
        spp_max: 8,
        time_limit_s: None,
    });
    let job = submit(&client, &course_scene("cornell_box.scene"), spec).await;
    let done = wait_finished(&client, job.id, Duration::from_secs(120)).await;
    assert_eq!(done.state, JobState::Done, "{:?}", done.error);
    assert_eq!(done.spp_mean, Some(8.0));
    let passes = client.convergence(job.id).await.unwrap().passes;
    let spp: Vec<f64> = passes.iter().map(|p| p.spp_mean).collect();
    // Each pass adds about half the image's samples, where the noise is, up to spp_max.
    assert!(
        spp[0] == 2.0 && spp.windows(2).all(|w| w[1] > w[0]) && spp.len() >= 3,
        "{spp:?}"
    );
    assert!(passes.last().unwrap().error < passes[0].error, "{passes:?}");
    let map = client.samples_png(job.id).await.unwrap();
    assert!(map.starts_with(b"\x89PNG"));
    // Threshold 0 sends every pixel to spp_max: the one-shot render of 8 spp in the
    // progressive order, whatever the passes were.
    let png = client.image(job.id).await.unwrap();
    assert_eq!(tracer_core::Image::from_png_bytes(&png).unwrap().width, 160);
}
