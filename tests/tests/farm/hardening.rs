//! A hostile client against a real coordinator: slow and idle connections, scene budgets,
//! scenes that used to crash the loader, bad worker results, and error answers that are all
//! JSON. After each, the coordinator still answers.

use std::io::{Read, Write};
use std::net::TcpStream;
use std::time::{Duration, Instant};

use reqwest::multipart::{Form, Part};
use reqwest::StatusCode;
use serde_json::{json, Value};

use crate::helpers::*;

struct Api {
    http: reqwest::Client,
    url: String,
}

impl Api {
    fn new(coord: &Coordinator) -> Api {
        Api {
            http: reqwest::Client::new(),
            url: coord.url.clone(),
        }
    }

    async fn send(&self, req: reqwest::RequestBuilder) -> (StatusCode, String, Value) {
        let resp = req.send().await.unwrap();
        let status = resp.status();
        let content_type = resp
            .headers()
            .get("content-type")
            .map(|v| v.to_str().unwrap().to_string())
            .unwrap_or_default();
        (
            status,
            content_type,
            resp.json().await.unwrap_or(Value::Null),
        )
    }

    async fn submit(&self, spec: Value, scene_name: &str, scene: &[u8]) -> (StatusCode, Value) {
        self.submit_with(spec, scene_name, scene, &[]).await
    }

    async fn submit_with(
        &self,
        spec: Value,
        scene_name: &str,
        scene: &[u8],
        assets: &[(&str, Vec<u8>)],
    ) -> (StatusCode, Value) {
        let mut form = Form::new()
            .percent_encode_noop()
            .part(
                "job",
                Part::text(spec.to_string())
                    .mime_str("application/json")
                    .unwrap(),
            )
            .part(
                "scene",
                Part::bytes(scene.to_vec()).file_name(scene_name.to_string()),
            );
        for (path, bytes) in assets {
            form = form.part(
                path.to_string(),
                Part::bytes(bytes.clone()).file_name(path.to_string()),
            );
        }
        let req = self
            .http
            .post(format!("{}/api/v1/jobs", self.url))
            .multipart(form);
        let (status, _, body) = self.send(req).await;
        (status, body)
    }

    /// Whether `/healthz` answers on a new connection (a pooled one may have been closed by
    /// the server after an answer that left the request body unread).
    async fn healthy(&self) -> bool {
        let fresh = reqwest::Client::new();
        match fresh.get(format!("{}/healthz", self.url)).send().await {
            Ok(resp) => resp.status() == StatusCode::OK,
            Err(_) => false,
        }
    }

    async fn job_count(&self) -> usize {
        let req = self.http.get(format!("{}/api/v1/jobs", self.url));
        let (status, _, body) = self.send(req).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        body.as_array().unwrap().len()
    }

    /// `POST /jobs/{id}/resubmit` with `spec`, or an empty body.
    async fn resubmit(&self, id: u64, spec: Option<Value>) -> (StatusCode, Value) {
        let req = self
            .http
            .post(format!("{}/api/v1/jobs/{id}/resubmit", self.url))
            .body(spec.map(|s| s.to_string()).unwrap_or_default());
        let (status, _, body) = self.send(req).await;
        (status, body)
    }

    /// A lease for a new worker named `worker` (registered first), granted at once (the
    /// job's tiles are queued).
    async fn lease(&self, worker: &str) -> Value {
        let req = self
            .http
            .post(format!("{}/api/v1/workers", self.url))
            .json(&json!({ "name": worker }));
        let (status, _, identity) = self.send(req).await;
        assert_eq!(status, StatusCode::CREATED, "{identity}");
        let req = self
            .http
            .post(format!("{}/api/v1/leases", self.url))
            .json(&json!({"worker_id": identity["worker_id"], "wait_ms": 2000}));
        let (status, _, body) = self.send(req).await;
        assert_eq!(status, StatusCode::OK, "{body}");
        body
    }
}

fn error_of(body: &Value) -> &str {
    body["error"].as_str().unwrap_or_default()
}

fn spheres() -> Vec<u8> {
    std::fs::read(course_scene("spheres.scene")).unwrap()
}

/// One 16x16 tile, so a job is one lease.
fn one_tile() -> Value {
    json!({"render": {"width": 16, "height": 16, "spp": 1}, "tile_size": 16})
}

/// Opens a connection and sends part of a request head, never the blank line that ends it.
fn half_sent(port: u16) -> TcpStream {
    let mut conn = TcpStream::connect(("127.0.0.1", port)).unwrap();
    conn.write_all(b"GET /healthz HTTP/1.1\r\nHost: x\r\nX-Slow: ")
        .unwrap();
    conn
}

/// Whether the server closed `conn` (end of stream or reset) within `within`.
fn closed_by_server(conn: &mut TcpStream, within: Duration) -> bool {
    conn.set_read_timeout(Some(within)).unwrap();
    let mut buf = [0u8; 1024];
    loop {
        match conn.read(&mut buf) {
            Ok(0) => return true,
            // A server may answer before closing (hyper does not for a timed-out head).
            Ok(_) => continue,
            Err(e)
                if matches!(
                    e.kind(),
                    std::io::ErrorKind::WouldBlock | std::io::ErrorKind::TimedOut
                ) =>
            {
                return false
            }
            Err(_) => return true,
        }
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn half_sent_and_idle_connections_are_closed_and_healthz_keeps_answering() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--header-timeout", "1", "--idle-timeout", "3"],
        tmp.path().join("c.log"),
    );
    let api = Api::new(&coord);
    let port = coord.port;

    // Two hundred slow clients, and one that connects and sends nothing.
    let mut slow: Vec<TcpStream> = (0..200).map(|_| half_sent(port)).collect();
    slow.push(TcpStream::connect(("127.0.0.1", port)).unwrap());
    assert!(api.healthy().await, "/healthz answers beside them");
    let start = Instant::now();
    let closed = tokio::task::spawn_blocking(move || {
        slow.iter_mut()
            .map(|conn| closed_by_server(conn, Duration::from_secs(20)))
            .filter(|closed| *closed)
            .count()
    })
    .await
    .unwrap();
    assert_eq!(
        closed, 201,
        "every slow connection was closed by the server"
    );
    assert!(
        start.elapsed() < Duration::from_secs(20),
        "closed within the header timeout (plus scheduling)"
    );
    assert!(api.healthy().await);

    // A kept-alive connection outlives the header timeout between requests, and is closed
    // after the idle timeout.
    let mut conn = TcpStream::connect(("127.0.0.1", port)).unwrap();
    let request = b"GET /healthz HTTP/1.1\r\nHost: x\r\n\r\n";
    let mut answer = [0u8; 512];
    conn.write_all(request).unwrap();
    let n = conn.read(&mut answer).unwrap();
    assert!(answer[..n].starts_with(b"HTTP/1.1 200"));
    std::thread::sleep(Duration::from_millis(1500));
    conn.write_all(request).unwrap();
    let n = conn.read(&mut answer).unwrap();
    assert!(
        answer[..n].starts_with(b"HTTP/1.1 200"),
        "still open after 1.5 s idle"
    );
    assert!(
        closed_by_server(&mut conn, Duration::from_secs(20)),
        "an idle connection is closed"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn clients_beyond_the_connection_cap_wait_and_are_served() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--header-timeout", "1", "--max-connections", "8"],
        tmp.path().join("c.log"),
    );
    let api = Api::new(&coord);
    // Eight slow clients take every connection slot; the ninth (the health check) waits in
    // the backlog until the server drops one of them, then is answered.
    let mut slow: Vec<TcpStream> = (0..8).map(|_| half_sent(coord.port)).collect();
    assert!(api.healthy().await, "answered once a slot came free");
    let closed = tokio::task::spawn_blocking(move || {
        slow.iter_mut()
            .all(|conn| closed_by_server(conn, Duration::from_secs(20)))
    })
    .await
    .unwrap();
    assert!(closed);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn every_error_answer_is_json() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--max-upload-mib", "1"],
        tmp.path().join("c.log"),
    );
    let api = Api::new(&coord);
    let url = &coord.url;
    for (req, status, needle) in [
        (
            api.http.put(format!("{url}/api/v1/jobs")),
            StatusCode::METHOD_NOT_ALLOWED,
            "PUT is not allowed",
        ),
        (
            api.http.get(format!("{url}/api/v1/leases")),
            StatusCode::METHOD_NOT_ALLOWED,
            "GET is not allowed on /api/v1/leases",
        ),
        (
            api.http.post(format!("{url}/healthz")),
            StatusCode::METHOD_NOT_ALLOWED,
            "not allowed",
        ),
        (
            api.http.get(format!("{url}/api/v1/nothing-here")),
            StatusCode::NOT_FOUND,
            "no such route",
        ),
        (
            api.http
                .put(format!("{url}/api/v1/leases/1/pixels"))
                .body(vec![0u8; 2 << 20]),
            StatusCode::PAYLOAD_TOO_LARGE,
            "",
        ),
    ] {
        let (got, content_type, body) = api.send(req).await;
        assert_eq!(got, status, "{body}");
        assert_eq!(content_type, "application/json", "{status}: {body}");
        assert!(
            !error_of(&body).is_empty() && error_of(&body).contains(needle),
            "{status}: {body}"
        );
    }
    assert!(api.healthy().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scenes_that_crashed_the_loader_are_answered_and_the_coordinator_lives() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(&tmp.path().join("data"), 0, &[], tmp.path().join("c.log"));
    let api = Api::new(&coord);

    // 50,000 nested elements: this overflowed the handler's stack and aborted the process.
    let mut deep = String::from("<scene>");
    deep.push_str(&"<a>".repeat(50_000));
    deep.push_str(&"</a>".repeat(50_000));
    deep.push_str("</scene>");
    let (status, body) = api.submit(one_tile(), "deep.scene", deep.as_bytes()).await;
    assert!(status.is_client_error(), "{status}: {body}");
    assert_eq!(body["file"], "deep.scene", "{body}");
    assert!(api.healthy().await, "the coordinator survived");

    // A byte-order mark: a few bytes that panicked the loader, and a valid scene with one.
    let (status, body) = api
        .submit(one_tile(), "bom.scene", b"\xEF\xBB\xBF\n<")
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    let mut with_bom = b"\xEF\xBB\xBF".to_vec();
    with_bom.extend(spheres());
    let (status, body) = api.submit(one_tile(), "bom.scene", &with_bom).await;
    assert_eq!(status, StatusCode::CREATED, "a BOM is skipped: {body}");
    assert!(api.healthy().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn scene_budgets_refuse_submissions_and_resubmits_naming_their_flag() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let coord = start_coordinator(
        &data,
        0,
        &["--max-texture-pixels", "100"],
        tmp.path().join("c.log"),
    );
    let api = Api::new(&coord);

    // cube.scene's textures hold far more than 100 pixels.
    let cube = std::fs::read(course_scene("cube.scene")).unwrap();
    let dir = course_scene("cube.scene").parent().unwrap().to_path_buf();
    let assets: Vec<(&str, Vec<u8>)> = ["images/cube.png", "images/tiles.png", "models/cube.obj"]
        .into_iter()
        .map(|p| (p, std::fs::read(dir.join(p)).unwrap()))
        .collect();
    let (status, body) = api
        .submit_with(one_tile(), "cube.scene", &cube, &assets)
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("--max-texture-pixels"), "{body}");
    assert_eq!(api.job_count().await, 0, "nothing refused was stored");

    // spheres.scene has no texture; a resubmit may not ask for frames it lacks.
    let (status, body) = api.submit(one_tile(), "spheres.scene", &spheres()).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    let id = body["id"].as_u64().unwrap();
    let mut frames = one_tile();
    frames["frames"] = json!({"first": 0, "last": 9});
    let (status, body) = api.resubmit(id, Some(frames)).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("frame"), "{body}");
    let (status, body) = api.resubmit(id, None).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    drop(coord);

    // Restarted with a primitive budget that spheres.scene exceeds: a new submission and a
    // resubmit of the stored job are both refused, and nothing is added.
    let coord = start_coordinator(
        &data,
        0,
        &["--max-scene-primitives", "5"],
        tmp.path().join("c2.log"),
    );
    let api = Api::new(&coord);
    let (status, body) = api.submit(one_tile(), "spheres.scene", &spheres()).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("--max-scene-primitives"), "{body}");
    let (status, body) = api.resubmit(id, None).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("--max-scene-primitives"), "{body}");
    assert_eq!(api.job_count().await, 2);
    assert!(api.healthy().await);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn non_finite_pixels_are_refused_and_the_tile_is_queued_again() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(&tmp.path().join("data"), 0, &[], tmp.path().join("c.log"));
    let api = Api::new(&coord);
    let (status, body) = api.submit(one_tile(), "spheres.scene", &spheres()).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    let job = body["id"].as_u64().unwrap();

    let lease = api.lease("nan-maker").await;
    let lease_id = lease["lease_id"].as_u64().unwrap();
    let mut pixels = vec![0f32; 16 * 16 * 3];
    pixels[100] = f32::NAN;
    let req = api
        .http
        .put(format!("{}/api/v1/leases/{lease_id}/pixels", api.url))
        .body(protocol::pixels_to_bytes(&pixels));
    let (status, _, body) = api.send(req).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("non-finite"), "{body}");

    let info: Value = api
        .http
        .get(format!("{}/api/v1/jobs/{job}", api.url))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    assert_eq!(info["tiles_done"], 0, "{info}");
    assert_ne!(
        info["state"], "failed",
        "one bad result does not fail the job: {info}"
    );
    assert!(
        error_of(&info["failures"][0]).contains("non-finite"),
        "{info}"
    );

    // The tile is handed out again, and finite pixels complete it.
    let again = api.lease("honest").await;
    assert_eq!(again["tile"], lease["tile"], "{again}");
    let again_id = again["lease_id"].as_u64().unwrap();
    pixels[100] = f32::INFINITY;
    let req = api
        .http
        .put(format!("{}/api/v1/leases/{again_id}/pixels", api.url))
        .body(protocol::pixels_to_bytes(&pixels));
    let (status, _, body) = api.send(req).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "infinity too: {body}");
    let last = api.lease("honest-2").await;
    pixels[100] = 0.5;
    let req = api
        .http
        .put(format!(
            "{}/api/v1/leases/{}/pixels",
            api.url,
            last["lease_id"].as_u64().unwrap()
        ))
        .body(protocol::pixels_to_bytes(&pixels));
    let (status, _, body) = api.send(req).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    assert_eq!(body["tiles_done"], 1, "{body}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn long_failure_messages_are_truncated_before_they_are_stored() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(&tmp.path().join("data"), 0, &[], tmp.path().join("c.log"));
    let api = Api::new(&coord);
    let (status, body) = api.submit(one_tile(), "spheres.scene", &spheres()).await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    let job = body["id"].as_u64().unwrap();
    let lease = api.lease("verbose").await;
    let lease_id = lease["lease_id"].as_u64().unwrap();
    // 2 MB of two-byte characters.
    let message = "é".repeat(1 << 20);
    let req = api
        .http
        .post(format!("{}/api/v1/leases/{lease_id}/failure", api.url))
        .json(&json!({"error": message}));
    let (status, _, body) = api.send(req).await;
    assert_eq!(status, StatusCode::OK, "{body}");
    let jobs: Value = api
        .http
        .get(format!("{}/api/v1/jobs", api.url))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let stored = jobs
        .as_array()
        .unwrap()
        .iter()
        .find(|j| j["id"] == job)
        .unwrap()["failures"][0]["error"]
        .as_str()
        .unwrap()
        .to_string();
    assert!(stored.len() <= 4096, "{} bytes stored", stored.len());
    assert!(stored.starts_with("éé"), "{stored}");
    assert!(stored.contains("truncated"), "{stored}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_paused_upload_loses_its_turn_and_the_next_submission_goes_through() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--idle-timeout", "2", "--max-scene-builds", "1"],
        tmp.path().join("c.log"),
    );
    let api = Api::new(&coord);
    // Takes the only turn: headers and the start of a multipart body, then nothing.
    let mut paused = TcpStream::connect(("127.0.0.1", coord.port)).unwrap();
    let head = "POST /api/v1/jobs HTTP/1.1\r\nHost: x\r\n\
                Content-Type: multipart/form-data; boundary=XYZ\r\n\
                Content-Length: 100000\r\n\r\n\
                --XYZ\r\nContent-Disposition: form-data; name=\"scene\"; filename=\"a.scene\"\r\n\r\n<scene>";
    paused.write_all(head.as_bytes()).unwrap();
    std::thread::sleep(Duration::from_millis(200));

    // Waits for the turn, which the paused upload gives up after the idle timeout.
    let start = Instant::now();
    let (status, body) = tokio::time::timeout(
        Duration::from_secs(60),
        api.submit(one_tile(), "spheres.scene", &spheres()),
    )
    .await
    .expect("the turn was never given up");
    assert_eq!(status, StatusCode::CREATED, "{body}");
    assert!(
        start.elapsed() >= Duration::from_millis(1500),
        "the submission did not wait for the paused one's turn"
    );
    let answer = tokio::task::spawn_blocking(move || {
        paused
            .set_read_timeout(Some(Duration::from_secs(20)))
            .unwrap();
        let mut answer = Vec::new();
        let _ = paused.read_to_end(&mut answer);
        String::from_utf8_lossy(&answer).to_string()
    })
    .await
    .unwrap();
    assert!(answer.starts_with("HTTP/1.1 408"), "{answer}");
    assert!(answer.contains("idle timeout"), "{answer}");
}
