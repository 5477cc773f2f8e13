//! The client commands (`submit`, `jobs`, `show`, `cancel`, `retry`, `workers`, `download`)
//! as a user runs them, against a real coordinator: their tables parse, their `--json` is the
//! API's, and a refused request prints the coordinator's message and exits 2.

use std::path::Path;
use std::process::{Command, Output, Stdio};
use std::time::Duration;

use protocol::client::Client;
use protocol::{FailureReport, JobInfo, JobState, LeaseRequest, WorkerInfo};
use serde_json::Value;

use crate::helpers::*;

const TOKEN: &str = "cli-token";

/// `coordinator ARGS` with the server and token from the environment, as a user sets them.
fn cli(url: &str, args: &[&str]) -> Output {
    Command::new(&bins().coordinator)
        .args(args)
        .env("TESSERA_COORDINATOR", url)
        .env("TESSERA_TOKEN", TOKEN)
        .stdin(Stdio::null())
        .output()
        .unwrap()
}

fn ok(url: &str, args: &[&str]) -> String {
    let out = cli(url, args);
    assert!(
        out.status.success(),
        "coordinator {args:?}: {}",
        String::from_utf8_lossy(&out.stderr)
    );
    String::from_utf8(out.stdout).unwrap()
}

fn json(url: &str, args: &[&str]) -> Value {
    let text = ok(url, args);
    serde_json::from_str(&text).unwrap_or_else(|e| panic!("{args:?}: {e}: {text}"))
}

/// The rows of a table whose first column is `id`.
fn row(table: &str, id: u64) -> Vec<&str> {
    table
        .lines()
        .skip(1)
        .map(|l| l.split_whitespace().collect::<Vec<_>>())
        .find(|cells| cells.first() == Some(&id.to_string().as_str()))
        .unwrap_or_else(|| panic!("no row {id} in\n{table}"))
}

fn submit_cli(url: &str, scene: &Path, extra: &[&str]) -> u64 {
    let scene = scene.to_str().unwrap();
    let mut args = vec!["submit", scene, "--width", "64", "--height", "48"];
    args.extend_from_slice(&["--spp", "1", "--tile-size", "16", "-q"]);
    args.extend_from_slice(extra);
    ok(url, &args).trim().parse().expect("submit prints the id")
}

/// Fails job `id`'s first tile as a worker whose scene does not load: the job fails at once.
async fn fail_job(client: &Client, id: u64) {
    let me = client.register("breaker").await.unwrap();
    let lease = client
        .lease(&LeaseRequest {
            worker_id: me.worker_id,
            wait_ms: 2000,
        })
        .await
        .unwrap()
        .expect("a queued tile");
    assert_eq!(lease.job_id, id);
    client
        .fail(
            lease.lease_id,
            &FailureReport {
                error: "broken on purpose".into(),
                scene: true,
            },
        )
        .await
        .unwrap();
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_client_commands_list_show_cancel_retry_and_download() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", TOKEN],
        tmp.path().join("coord.log"),
    );
    let url = coord.url.as_str();
    let client = Client::new(url, Some(TOKEN.into())).unwrap();
    let scene = course_scene("cube.scene");

    // No worker yet: jobs stay queued, so one can be cancelled and one failed on purpose.
    let cancelled = submit_cli(url, &scene, &[]);
    let failed = submit_cli(url, &scene, &[]);
    let table = ok(url, &["jobs"]);
    assert_eq!(
        table
            .lines()
            .next()
            .unwrap()
            .split_whitespace()
            .collect::<Vec<_>>(),
        ["ID", "STATE", "TILES", "ELAPSED", "ETA", "NAME"]
    );
    assert_eq!(row(&table, cancelled)[1], "queued");
    assert_eq!(row(&table, failed)[2], "0/12");
    let listed: Vec<JobInfo> = serde_json::from_value(json(url, &["jobs", "--json"])).unwrap();
    assert_eq!(listed, client.jobs().await.unwrap());

    assert_eq!(
        ok(url, &["cancel", &cancelled.to_string()]).trim(),
        format!("job {cancelled} cancelled")
    );
    let shown: JobInfo =
        serde_json::from_value(json(url, &["show", &cancelled.to_string(), "--json"])).unwrap();
    assert_eq!(shown.state, JobState::Cancelled);
    // Cancelling twice is refused with the coordinator's message.
    let again = cli(url, &["cancel", &cancelled.to_string()]);
    assert_eq!(again.status.code(), Some(2));
    let err = String::from_utf8_lossy(&again.stderr);
    assert!(err.contains("HTTP 409"), "{err}");

    // Retry: refused for a job that has not failed, then requeues a failed one.
    let refused = cli(url, &["retry", &failed.to_string()]);
    assert_eq!(refused.status.code(), Some(2), "{refused:?}");
    fail_job(&client, failed).await;
    let details = ok(url, &["show", &failed.to_string()]);
    assert!(details.contains("state:    failed"), "{details}");
    assert!(details.contains("broken on purpose"), "{details}");
    let retried: JobInfo =
        serde_json::from_value(json(url, &["retry", &failed.to_string(), "--json"])).unwrap();
    assert_eq!(retried.state, JobState::Running, "it had started");
    assert!(retried.error.is_none());

    // A worker renders the retried job; the download equals the API's image.
    let _worker = start_worker(url, "cli-w", &["--token", TOKEN], tmp.path().join("w.log"));
    let done = wait_finished(&client, failed, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    let out = tmp.path().join("out.png");
    let said = ok(
        url,
        &["download", &failed.to_string(), "-o", out.to_str().unwrap()],
    );
    assert_eq!(said.trim(), format!("wrote {}", out.display()));
    assert_eq!(
        std::fs::read(&out).unwrap(),
        client.image(failed).await.unwrap()
    );

    let workers: Vec<WorkerInfo> =
        serde_json::from_value(json(url, &["workers", "--json"])).unwrap();
    let cli_w = workers
        .iter()
        .find(|w| w.name == "cli-w")
        .expect("the worker is listed");
    let table = ok(url, &["workers"]);
    let cells = row(&table, cli_w.id);
    assert_eq!(cells.last(), Some(&"cli-w"));
    assert_eq!(cells[3], cli_w.tiles_done.to_string());

    // An unknown job is the coordinator's 404, exit 2.
    let missing = cli(url, &["show", "999"]);
    assert_eq!(missing.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&missing.stderr).contains("HTTP 404"));
    // A wrong token is refused too.
    let denied = Command::new(&bins().coordinator)
        .args(["jobs", "--server", url, "--token", "wrong"])
        .output()
        .unwrap();
    assert_eq!(denied.status.code(), Some(2));
    assert!(String::from_utf8_lossy(&denied.stderr).contains("HTTP 401"));
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn download_frames_writes_every_frame_numbered() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", TOKEN],
        tmp.path().join("coord.log"),
    );
    let url = coord.url.as_str();
    let client = Client::new(url, Some(TOKEN.into())).unwrap();
    let _worker = start_worker(url, "w", &["--token", TOKEN], tmp.path().join("w.log"));
    let id = submit_cli(url, &own_scene("motion_blur.scene"), &["--frames", "1..3"]);
    let done = wait_finished(&client, id, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");

    let out = tmp.path().join("anim").join("blur.png");
    let said = json(
        url,
        &[
            "download",
            &id.to_string(),
            "-o",
            out.to_str().unwrap(),
            "--frames",
            "--json",
        ],
    );
    let files: Vec<String> = serde_json::from_value(said["files"].clone()).unwrap();
    assert_eq!(files.len(), 3, "{said}");
    for (frame, file) in (1..=3).zip(&files) {
        assert!(file.ends_with(&format!("blur_{frame:04}.png")), "{file}");
        assert_eq!(
            std::fs::read(file).unwrap(),
            client.frame_image(id, frame).await.unwrap()
        );
    }
    // A still job has no frames to write.
    let still = submit_cli(url, &course_scene("cube.scene"), &[]);
    let refused = cli(
        url,
        &["download", &still.to_string(), "-o", "x.png", "--frames"],
    );
    assert_eq!(refused.status.code(), Some(2));
}
