//! `--config farm.toml` on the real binaries: the coordinator takes its limits and token from
//! the file's `[serve]` table, a worker finds the coordinator from `[worker]`, and a key that is
//! no flag stops the coordinator before it listens.

use std::process::{Command, Stdio};
use std::time::Duration;

use protocol::client::{Client, ClientError};

use crate::helpers::*;

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serve_and_worker_read_their_tables_of_one_file() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("farm.toml");
    std::fs::write(&file, "[serve]\nmax-spp = 2\ntoken = \"file-token\"\n").unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--config", file.to_str().unwrap()],
        tmp.path().join("coord.log"),
    );
    // The file's token is required...
    let anonymous = Client::new(&coord.url, None).unwrap();
    match anonymous.jobs().await {
        Err(ClientError::Api { status: 401, .. }) => {}
        other => panic!("expected 401, got {other:?}"),
    }
    // ...and its limit applies, flags it does not name keep their defaults.
    let client = Client::new(&coord.url, Some("file-token".into())).unwrap();
    let scene = course_scene("cube.scene");
    let sub = coordinator::cli::collect_submission(&scene, small_spec(4, 64)).unwrap();
    match client.submit(&sub).await {
        Err(ClientError::Api {
            status: 400,
            message,
            ..
        }) => {
            assert!(message.contains("spp"), "{message}")
        }
        other => panic!("expected the spp limit, got {other:?}"),
    }

    // The worker takes everything from the same file's [worker] table.
    let text = format!(
        "[serve]\nmax-spp = 2\n[worker]\ncoordinator = \"{}\"\ntoken = \"file-token\"\nname = \"from-file\"\n",
        coord.url
    );
    std::fs::write(&file, text).unwrap();
    let mut cmd = Command::new(&bins().worker);
    cmd.args(["--config", file.to_str().unwrap()])
        .stdout(Stdio::null());
    let _worker = Proc::spawn(cmd, tmp.path().join("w.log"));
    let start = std::time::Instant::now();
    loop {
        let workers = client.workers().await.unwrap();
        if workers.iter().any(|w| w.name == "from-file") {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "the worker did not register: {}",
            std::fs::read_to_string(tmp.path().join("w.log")).unwrap_or_default()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[test]
fn an_unknown_key_stops_serve_with_its_name_and_file() {
    let tmp = tempfile::tempdir().unwrap();
    let file = tmp.path().join("bad.toml");
    std::fs::write(&file, "[serve]\nmax-sp = 2\n").unwrap();
    let out = Command::new(&bins().coordinator)
        .args(["serve", "--listen", "127.0.0.1:0", "--config"])
        .arg(&file)
        .arg("--data-dir")
        .arg(tmp.path().join("data"))
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(2));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("unknown key `max-sp`"), "{err}");
    assert!(err.contains("bad.toml"), "{err}");
    assert!(out.stdout.is_empty(), "it never listened");
}
