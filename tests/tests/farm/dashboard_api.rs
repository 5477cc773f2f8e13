//! The read routes behind the dashboard: tile map, workers, camera, re-submission and the
//! event stream, with their 4xx answers; and the page itself, served without a token.

use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::{JobState, TilePage, TileState, WorkerInfo, WorkerState};
use reqwest::StatusCode;
use serde_json::{json, Value};

use crate::helpers::*;

const TOKEN: &str = "dash-token";

struct Api {
    http: reqwest::Client,
    url: String,
}

impl Api {
    async fn call(
        &self,
        method: reqwest::Method,
        path: &str,
        body: Option<&str>,
    ) -> (StatusCode, Value) {
        let mut req = self
            .http
            .request(method, format!("{}/api/v1{path}", self.url))
            .bearer_auth(TOKEN);
        if let Some(body) = body {
            req = req.body(body.to_string());
        }
        let resp = req.send().await.unwrap();
        let status = resp.status();
        (status, resp.json().await.unwrap_or(Value::Null))
    }

    async fn get(&self, path: &str) -> (StatusCode, Value) {
        self.call(reqwest::Method::GET, path, None).await
    }
}

/// Reads the event stream until `done` holds for what arrived so far, or `timeout` passes.
async fn read_events(
    resp: &mut reqwest::Response,
    text: &mut String,
    timeout: Duration,
    done: impl Fn(&str) -> bool,
) {
    let start = Instant::now();
    while !done(text) {
        let left = timeout.saturating_sub(start.elapsed());
        assert!(
            !left.is_zero(),
            "the expected events never came; got:\n{text}"
        );
        if let Ok(Ok(Some(chunk))) = tokio::time::timeout(left, resp.chunk()).await {
            text.push_str(&String::from_utf8_lossy(&chunk));
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn dashboard_routes_report_tiles_workers_and_events_and_resubmit() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", TOKEN],
        tmp.path().join("c.log"),
    );
    let api = Api {
        http: reqwest::Client::new(),
        url: coord.url.clone(),
    };
    let client = Client::new(&coord.url, Some(TOKEN.into())).unwrap();

    // The page and its files need no token; the data behind them does.
    for (path, kind) in [
        ("/", "text/html"),
        ("/dashboard.js", "text/javascript"),
        ("/dashboard.css", "text/css"),
    ] {
        let resp = reqwest::get(format!("{}{path}", coord.url)).await.unwrap();
        assert_eq!(resp.status(), StatusCode::OK, "{path}");
        let content_type = resp.headers()["content-type"].to_str().unwrap().to_string();
        assert!(content_type.starts_with(kind), "{path}: {content_type}");
        assert!(!resp.text().await.unwrap().is_empty());
    }
    for path in ["/api/v1/workers", "/api/v1/events", "/api/v1/jobs/1/tiles"] {
        let resp = reqwest::get(format!("{}{path}", coord.url)).await.unwrap();
        assert_eq!(resp.status(), StatusCode::UNAUTHORIZED, "{path}");
    }

    // 64x48 in 16-pixel tiles: 12 tiles, all queued before any worker shows up.
    let mut spec = small_spec(1, 16);
    spec.render.width = 64;
    spec.render.height = 48;
    let cube = course_scene("cube.scene");
    let job = submit(&client, &cube, spec.clone()).await;
    let (status, page) = api.get(&format!("/jobs/{}/tiles", job.id)).await;
    assert_eq!(status, StatusCode::OK);
    let page: TilePage = serde_json::from_value(page).unwrap();
    assert_eq!((page.tiles_total, page.offset), (12, 0));
    let tiles = page.tiles;
    assert_eq!(tiles.len(), 12);
    // Pages: a window of the map, and a limit over the largest page refused.
    let (status, page) = api
        .get(&format!("/jobs/{}/tiles?offset=10&limit=5", job.id))
        .await;
    assert_eq!(status, StatusCode::OK, "{page}");
    let page: TilePage = serde_json::from_value(page).unwrap();
    assert_eq!(
        page.tiles.iter().map(|t| t.tile).collect::<Vec<_>>(),
        [10, 11]
    );
    let (status, body) = api.get(&format!("/jobs/{}/tiles?limit=4097", job.id)).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(body["error"].as_str().unwrap().contains("4096"), "{body}");
    assert!(tiles
        .iter()
        .all(|t| t.state == TileState::Queued && t.workers.is_empty()));
    assert_eq!(
        (tiles[5].tile, tiles[5].rect.x, tiles[5].rect.y),
        (5, 16, 16)
    );
    assert_eq!(api.get("/workers").await, (StatusCode::OK, json!([])));

    // The scene's camera (cube.scene: at 0,6,11, tilted down 0.5 rad, fov 0.785).
    let (status, camera) = api.get(&format!("/jobs/{}/camera", job.id)).await;
    assert_eq!(status, StatusCode::OK, "{camera}");
    assert_eq!(camera["from_scene"], json!(true));
    assert_eq!(camera["position"], json!([0.0, 6.0, 11.0]));
    let fov = camera["fov_deg"].as_f64().unwrap();
    assert!((fov - 0.785f64.to_degrees()).abs() < 1e-9, "{camera}");
    let up_y = camera["up"][1].as_f64().unwrap();
    assert!((up_y - 0.5f64.cos()).abs() < 1e-9, "{camera}");

    // Bad ids and bodies: JSON 4xx.
    for path in ["/jobs/99/tiles", "/jobs/x/tiles", "/jobs/99/camera"] {
        let (status, body) = api.get(path).await;
        assert_eq!(status, StatusCode::NOT_FOUND, "{path}");
        assert!(body["error"].as_str().unwrap().contains("job"), "{body}");
    }
    let post = reqwest::Method::POST;
    let (status, body) = api.call(post.clone(), "/jobs/99/resubmit", None).await;
    assert_eq!(status, StatusCode::NOT_FOUND, "{body}");
    let resubmit = format!("/jobs/{}/resubmit", job.id);
    for (bad, needle) in [
        ("{not json", "invalid JSON"),
        (r#"{"colour": 1}"#, "unknown field"),
        (r#"{"render": {"width": 0}}"#, "image size 0x600"),
        (r#"{"tile_size": 2}"#, "tile_size"),
        (
            r#"{"render": {"camera": {"position": [0,0,0], "look_at": [0,0,0]}}}"#,
            "camera",
        ),
    ] {
        let (status, body) = api.call(post.clone(), &resubmit, Some(bad)).await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{bad}: {body}");
        let error = body["error"].as_str().unwrap();
        assert!(error.contains(needle), "{bad}: {error}");
    }

    // Follow the events while a worker renders the job.
    let mut events = api
        .http
        .get(format!("{}/api/v1/events", coord.url))
        .bearer_auth(TOKEN)
        .send()
        .await
        .unwrap();
    assert_eq!(events.status(), StatusCode::OK);
    assert!(events.headers()["content-type"]
        .to_str()
        .unwrap()
        .starts_with("text/event-stream"));
    let mut seen = String::new();
    let wait = Duration::from_secs(60);
    read_events(&mut events, &mut seen, wait, |t| {
        t.contains("event: workers")
    })
    .await;

    let _worker = start_worker(
        &coord.url,
        "dash-w1",
        &["--token", TOKEN, "--threads", "1"],
        tmp.path().join("w1.log"),
    );
    let done = wait_finished(&client, job.id, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done);
    read_events(&mut events, &mut seen, wait, |t| {
        t.contains("\"state\":\"done\",\"spec\"")
            && t.matches("\"state\":\"done\",\"workers\"").count() >= 12
    })
    .await;
    // Each event carries the state when it is written: every tile's last one says done.
    for tile in 0..12 {
        let needle = format!("\"tile\":{tile},");
        let last = seen
            .lines()
            .rfind(|l| l.starts_with("data:") && l.contains(&needle))
            .unwrap_or_else(|| panic!("no event for tile {tile}:\n{seen}"));
        assert!(last.contains("\"state\":\"done\""), "{last}");
    }

    let (_, page) = api.get(&format!("/jobs/{}/tiles", job.id)).await;
    let tiles = serde_json::from_value::<TilePage>(page).unwrap().tiles;
    assert!(tiles
        .iter()
        .all(|t| t.state == TileState::Done && t.attempts == 0));
    let (_, workers) = api.get("/workers").await;
    let workers: Vec<WorkerInfo> = serde_json::from_value(workers).unwrap();
    assert_eq!(workers.len(), 1, "{workers:?}");
    let w = &workers[0];
    assert_eq!(
        (w.name.as_str(), w.state, w.tiles_done),
        ("dash-w1", WorkerState::Idle, 12)
    );
    assert!(w.lease.is_none());
    assert!(
        w.address.as_deref().unwrap().starts_with("127.0.0.1:"),
        "{w:?}"
    );

    // The same scene from elsewhere: nothing uploaded, a new job with the override.
    let body = json!({
        "name": "cube from the side",
        "tile_size": 16,
        "render": {"width": 64, "height": 48, "spp": 1,
                   "camera": {"position": [11.0, 6.0, 0.0], "look_at": [0.0, 0.0, 0.0]}}
    });
    let (status, moved) = api
        .call(post.clone(), &resubmit, Some(&body.to_string()))
        .await;
    assert_eq!(status, StatusCode::CREATED, "{moved}");
    assert_eq!(moved["name"], json!("cube from the side"));
    let moved_id = moved["id"].as_u64().unwrap();
    let (_, camera) = api.get(&format!("/jobs/{moved_id}/camera")).await;
    assert_eq!(camera["from_scene"], json!(false));
    assert_eq!(camera["position"], json!([11.0, 6.0, 0.0]));
    // An empty body repeats the job's own settings.
    let (status, again) = api.call(post, &resubmit, None).await;
    assert_eq!(status, StatusCode::CREATED, "{again}");
    assert_eq!(again["spec"], serde_json::to_value(&job.spec).unwrap());
    assert_eq!(again["name"], json!(job.name));

    let moved = wait_finished(&client, moved_id, Duration::from_secs(60)).await;
    let again_id = again["id"].as_u64().unwrap();
    let again = wait_finished(&client, again_id, Duration::from_secs(60)).await;
    assert_eq!((moved.state, again.state), (JobState::Done, JobState::Done));
    let original = client.image(job.id).await.unwrap();
    assert_eq!(client.image(again_id).await.unwrap(), original);
    assert_ne!(client.image(moved_id).await.unwrap(), original);
}
