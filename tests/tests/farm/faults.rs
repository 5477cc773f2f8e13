//! Faults lose nothing: a worker killed mid-job, a coordinator killed mid-job and restarted,
//! a worker told to stop. The image stays identical to `tracer render`'s.

use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::JobState;

use crate::helpers::*;

async fn metric(url: &str, name: &str) -> f64 {
    let text = reqwest::get(format!("{url}/metrics"))
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    text.lines()
        .find_map(|l| l.strip_prefix(&format!("{name} ")))
        .unwrap_or_else(|| panic!("no metric {name}"))
        .parse()
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_killed_mid_job_loses_nothing() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--lease-timeout", "1", "--heartbeat", "0.25"],
        tmp.path().join("c.log"),
    );
    let mut doomed = start_worker(
        &coord.url,
        "doomed",
        &["--threads", "1"],
        tmp.path().join("w1.log"),
    );
    let survivor = start_worker(
        &coord.url,
        "survivor",
        &["--threads", "1"],
        tmp.path().join("w2.log"),
    );
    let client = Client::new(&coord.url, None).unwrap();
    let scene = course_scene("stacks.scene");
    let spec = small_spec(48, 16);
    let job = submit(&client, &scene, spec.clone()).await;
    // Kill it while it holds a tile, a few tiles in.
    wait_until(&client, job.id, Duration::from_secs(60), |j| {
        j.tiles_done >= 6
    })
    .await;
    let start = Instant::now();
    while !doomed.log_text().contains("rendered in") {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the doomed worker never rendered"
        );
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    doomed.kill9();
    let killed_at = wait_until(&client, job.id, Duration::from_secs(1), |_| true).await;
    assert!(
        killed_at.tiles_done < killed_at.tiles_total,
        "killed too late: {killed_at:?}"
    );
    let done = wait_finished(&client, job.id, Duration::from_secs(90)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    assert!(
        done.failures.is_empty(),
        "a lost worker is not a tile failure: {done:?}"
    );
    assert!(client.image(job.id).await.unwrap() == tracer_png(&scene, &spec, tmp.path()));
    let logs = [doomed.log_text(), survivor.log_text()];
    // The killed worker may have delivered its last tile without its log line reaching the
    // file (kill -9), so one tile may be missing from the logs; none may be extra.
    let logged = rendered_tiles(&logs, job.id).len() as u32;
    assert!(
        logged == done.tiles_total || logged + 1 == done.tiles_total,
        "{logged} tiles logged of {}",
        done.tiles_total
    );
    eprintln!(
        "leases expired: {}",
        metric(&coord.url, "tessera_leases_expired_total").await
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_coordinator_killed_mid_job_resumes_without_rendering_finished_tiles_again() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    // No straggler copies: every tile must be rendered exactly once.
    let args = [
        "--no-stragglers",
        "--heartbeat",
        "0.25",
        "--lease-timeout",
        "2",
    ];
    let mut coord = start_coordinator(&data, 0, &args, tmp.path().join("c1.log"));
    let workers = [
        start_worker(
            &coord.url,
            "w1",
            &["--threads", "1"],
            tmp.path().join("w1.log"),
        ),
        start_worker(
            &coord.url,
            "w2",
            &["--threads", "1"],
            tmp.path().join("w2.log"),
        ),
    ];
    let client = Client::new(&coord.url, None).unwrap();
    let scene = course_scene("stacks.scene");
    let spec = small_spec(48, 16);
    let job = submit(&client, &scene, spec.clone()).await;
    let before = wait_until(&client, job.id, Duration::from_secs(60), |j| {
        j.tiles_done >= 20
    })
    .await;
    coord.proc.kill9();
    assert!(
        before.tiles_done < before.tiles_total,
        "killed too late: {before:?}"
    );
    // Workers keep rendering and retrying while it is down.
    tokio::time::sleep(Duration::from_millis(700)).await;
    let restarted = start_coordinator(&data, coord.port, &args, tmp.path().join("c2.log"));
    assert_eq!(restarted.url, coord.url);
    let done = wait_finished(&client, job.id, Duration::from_secs(90)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    assert!(client.image(job.id).await.unwrap() == tracer_png(&scene, &spec, tmp.path()));
    let logs: Vec<String> = workers.iter().map(Proc::log_text).collect();
    let counts = rendered_tiles(&logs, job.id);
    assert_eq!(counts.len() as u32, done.tiles_total, "every tile rendered");
    let again: Vec<_> = counts.iter().filter(|(_, n)| **n > 1).collect();
    assert!(again.is_empty(), "tiles rendered more than once: {again:?}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stopping_worker_hands_its_tile_back() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(&tmp.path().join("data"), 0, &[], tmp.path().join("c.log"));
    let mut worker = start_worker(
        &coord.url,
        "w1",
        &["--threads", "1"],
        tmp.path().join("w.log"),
    );
    let client = Client::new(&coord.url, None).unwrap();
    let mut spec = small_spec(4096, 64);
    spec.render.width = 64;
    spec.render.height = 64;
    let job = submit(&client, &course_scene("stacks.scene"), spec).await;
    wait_until(&client, job.id, Duration::from_secs(20), |j| {
        j.tiles_running == 1
    })
    .await;
    worker.signal("TERM");
    let status = worker.wait_exit(Duration::from_secs(5));
    assert!(status.success(), "{}", worker.log_text());
    assert!(
        worker.log_text().contains("handed back"),
        "{}",
        worker.log_text()
    );
    // Requeued at once, not after a lease timeout, and not a failure.
    let info = client.job(job.id).await.unwrap();
    assert_eq!((info.tiles_running, info.tiles_done), (0, 0), "{info:?}");
    assert!(info.failures.is_empty());
    assert_eq!(
        metric(&coord.url, "tessera_tiles_handed_back_total").await,
        1.0
    );
}
