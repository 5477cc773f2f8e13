//! Bad submissions and bad credentials each get the right 4xx with a clear message, and the
//! coordinator keeps serving.

use reqwest::multipart::{Form, Part};
use reqwest::StatusCode;
use serde_json::{json, Value};

use crate::helpers::*;

const TOKEN: &str = "s3cret-token";

struct Api {
    http: reqwest::Client,
    url: String,
}

impl Api {
    fn authed(&self, req: reqwest::RequestBuilder) -> reqwest::RequestBuilder {
        req.bearer_auth(TOKEN)
    }

    async fn submit(&self, form: Form) -> (StatusCode, Value) {
        let resp = self
            .authed(self.http.post(format!("{}/api/v1/jobs", self.url)))
            .multipart(form)
            .send()
            .await
            .unwrap();
        let status = resp.status();
        (status, resp.json().await.unwrap_or(Value::Null))
    }

    async fn call(&self, method: reqwest::Method, path: &str) -> (StatusCode, Value) {
        let resp = self
            .authed(
                self.http
                    .request(method, format!("{}/api/v1{path}", self.url)),
            )
            .send()
            .await
            .unwrap();
        let status = resp.status();
        (status, resp.json().await.unwrap_or(Value::Null))
    }
}

fn job_part(spec: Value) -> Part {
    Part::text(spec.to_string())
        .mime_str("application/json")
        .unwrap()
}

/// A form with the scene and the given assets, named by path.
fn form(spec: Value, scene_name: &str, scene: &str, assets: &[(&str, Vec<u8>)]) -> Form {
    let mut form = Form::new()
        .percent_encode_noop()
        .part("job", job_part(spec))
        .part(
            "scene",
            Part::bytes(scene.as_bytes().to_vec()).file_name(scene_name.to_string()),
        );
    for (path, bytes) in assets {
        form = form.part(
            path.to_string(),
            Part::bytes(bytes.clone()).file_name(path.to_string()),
        );
    }
    form
}

fn small() -> Value {
    json!({"render": {"width": 32, "height": 24, "spp": 1}, "tile_size": 16})
}

fn cube_assets() -> Vec<(&'static str, Vec<u8>)> {
    let dir = course_scene("cube.scene").parent().unwrap().to_path_buf();
    ["images/cube.png", "images/tiles.png", "models/cube.obj"]
        .into_iter()
        .map(|p| (p, std::fs::read(dir.join(p)).unwrap()))
        .collect()
}

fn error_of(body: &Value) -> &str {
    body["error"].as_str().unwrap_or_default()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_submissions_get_clear_4xx_and_the_server_keeps_serving() {
    let tmp = tempfile::tempdir().unwrap();
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", TOKEN, "--max-upload-mib", "1"],
        tmp.path().join("c.log"),
    );
    let api = Api {
        http: reqwest::Client::new(),
        url: coord.url.clone(),
    };
    let cube = std::fs::read_to_string(course_scene("cube.scene")).unwrap();

    // Credentials: missing, wrong, right; the health check needs none.
    let resp = reqwest::get(format!("{}/api/v1/jobs", coord.url))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::UNAUTHORIZED);
    assert!(resp.text().await.unwrap().contains("Bearer"));
    let resp = api
        .http
        .get(format!("{}/api/v1/jobs", coord.url))
        .bearer_auth("wrong")
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::UNAUTHORIZED);
    let resp = api
        .http
        .get(format!("{}/metrics", coord.url))
        .send()
        .await
        .unwrap();
    assert_eq!(
        resp.status(),
        StatusCode::UNAUTHORIZED,
        "metrics need the token too"
    );
    let resp = reqwest::get(format!("{}/healthz", coord.url))
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let resp = api
        .http
        .post(format!("{}/api/v1/jobs", coord.url))
        .multipart(form(small(), "cube.scene", &cube, &cube_assets()))
        .send()
        .await
        .unwrap();
    assert_eq!(
        resp.status(),
        StatusCode::UNAUTHORIZED,
        "submitting needs the token"
    );

    // Malformed XML: 400 with the location.
    let (status, body) = api
        .submit(form(
            small(),
            "bad.scene",
            "<scene>\n  <camera>\n</scene>",
            &[],
        ))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert_eq!(body["file"], "bad.scene", "{body}");
    assert!(body["line"].as_u64().unwrap() >= 2, "{body}");
    assert!(body["column"].is_u64(), "{body}");

    // A missing asset names its path.
    let mut assets = cube_assets();
    assets.retain(|(p, _)| *p != "models/cube.obj");
    let (status, body) = api
        .submit(form(small(), "cube.scene", &cube, &assets))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("models/cube.obj"), "{body}");

    // Paths that leave the bundle: as a part name, absolute, or written in the scene.
    let mut escaping = cube_assets();
    escaping.push(("../../etc/passwd", b"x".to_vec()));
    let (status, body) = api
        .submit(form(small(), "cube.scene", &cube, &escaping))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains(".."), "{body}");
    let mut absolute = cube_assets();
    absolute.push(("/etc/passwd", b"x".to_vec()));
    let (status, body) = api
        .submit(form(small(), "cube.scene", &cube, &absolute))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("absolute"), "{body}");
    let sneaky = cube.replace("images/cube.png", "../cube.png");
    let (status, body) = api
        .submit(form(small(), "cube.scene", &sneaky, &cube_assets()))
        .await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("../cube.png"), "{body}");

    // An oversized body: 413.
    let mut huge = cube_assets();
    huge.push(("images/huge.png", vec![7u8; 2 << 20]));
    let (status, body) = api.submit(form(small(), "cube.scene", &cube, &huge)).await;
    assert_eq!(status, StatusCode::PAYLOAD_TOO_LARGE, "{body}");
    assert!(error_of(&body).contains("limit"), "{body}");

    // Absurd settings, each named.
    for (spec, needle) in [
        (json!({"render": {"spp": 1_000_000_000}}), "spp"),
        (
            json!({"render": {"width": 1_000_000, "height": 10}}),
            "per side",
        ),
        (json!({"render": {"width": 0}}), "size"),
        (json!({"render": {"max_depth": 100000}}), "max_depth"),
        (json!({"tile_size": 0}), "tile_size"),
        (json!({"render": {"sp": 3}}), "unknown field"),
    ] {
        let (status, body) = api
            .submit(form(spec.clone(), "cube.scene", &cube, &cube_assets()))
            .await;
        assert_eq!(status, StatusCode::BAD_REQUEST, "{spec}: {body}");
        assert!(error_of(&body).contains(needle), "{spec}: {body}");
    }

    // No scene at all.
    let (status, body) = api.submit(Form::new().part("job", job_part(small()))).await;
    assert_eq!(status, StatusCode::BAD_REQUEST, "{body}");
    assert!(error_of(&body).contains("scene"), "{body}");

    // Unknown resources and stale leases.
    let (status, _) = api.call(reqwest::Method::GET, "/jobs/999").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (status, _) = api.call(reqwest::Method::DELETE, "/jobs/abc").await;
    assert_eq!(status, StatusCode::NOT_FOUND);
    let (status, body) = api
        .call(reqwest::Method::POST, "/leases/12345/heartbeat")
        .await;
    assert_eq!(status, StatusCode::CONFLICT, "{body}");
    let (status, _) = api.call(reqwest::Method::DELETE, "/leases/12345").await;
    assert_eq!(status, StatusCode::CONFLICT);

    // Still serving: a good job is accepted, and its pixels are size-checked.
    let (status, body) = api
        .submit(form(small(), "cube.scene", &cube, &cube_assets()))
        .await;
    assert_eq!(status, StatusCode::CREATED, "{body}");
    assert_eq!(body["tiles_total"], 4);
    let identity: Value = api
        .authed(api.http.post(format!("{}/api/v1/workers", coord.url)))
        .json(&json!({"name": "manual"}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let worker_id = identity["worker_id"].as_u64().unwrap();
    let lease: Value = api
        .authed(api.http.post(format!("{}/api/v1/leases", coord.url)))
        .json(&json!({"worker_id": worker_id, "wait_ms": 0}))
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    let id = lease["lease_id"].as_u64().unwrap();
    let resp = api
        .authed(
            api.http
                .put(format!("{}/api/v1/leases/{id}/pixels", coord.url)),
        )
        .body(vec![0u8; 100])
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::BAD_REQUEST);
    assert!(resp.text().await.unwrap().contains("3072 bytes"));
    let resp = api
        .authed(
            api.http
                .put(format!("{}/api/v1/leases/{id}/pixels", coord.url)),
        )
        .body(vec![0u8; 16 * 16 * 12])
        .send()
        .await
        .unwrap();
    assert_eq!(resp.status(), StatusCode::OK);
    let resp = api
        .authed(
            api.http
                .put(format!("{}/api/v1/leases/{id}/pixels", coord.url)),
        )
        .body(vec![0u8; 16 * 16 * 12])
        .send()
        .await
        .unwrap();
    assert_eq!(
        resp.status(),
        StatusCode::CONFLICT,
        "a second result is refused"
    );
    let metrics = api
        .authed(api.http.get(format!("{}/metrics", coord.url)))
        .send()
        .await
        .unwrap()
        .text()
        .await
        .unwrap();
    assert!(
        metrics.contains("tessera_jobs_submitted_total 1\n"),
        "{metrics}"
    );
    assert!(
        metrics.contains("tessera_tiles{state=\"done\"} 1\n"),
        "{metrics}"
    );
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn unchanged_assets_are_stored_and_uploaded_once() {
    let tmp = tempfile::tempdir().unwrap();
    let data = tmp.path().join("data");
    let coord = start_coordinator(&data, 0, &[], tmp.path().join("c.log"));
    let client = protocol::client::Client::new(&coord.url, None).unwrap();
    let scene = course_scene("cube.scene");
    let mut spec = small_spec(1, 16);
    spec.render.width = 32;
    spec.render.height = 24;
    let first = submit(&client, &scene, spec.clone()).await;
    let second = submit(&client, &scene, spec).await;
    assert_ne!(first.id, second.id);
    let b1 = client.bundle(first.id).await.unwrap();
    let b2 = client.bundle(second.id).await.unwrap();
    assert_eq!(b1.assets, b2.assets);
    assert_eq!(
        b1.assets
            .iter()
            .map(|a| a.path.as_str())
            .collect::<Vec<_>>(),
        ["images/cube.png", "images/tiles.png", "models/cube.obj"],
        "exactly what the scene references"
    );
    // One file per distinct content: the scene and its three assets.
    let blobs: usize = std::fs::read_dir(data.join("blobs"))
        .unwrap()
        .map(|d| std::fs::read_dir(d.unwrap().path()).unwrap().count())
        .sum();
    assert_eq!(blobs, 4);
    // A client asking about them learns that it need not send them again.
    let hashes: Vec<String> = b1.assets.iter().map(|a| a.hash.clone()).collect();
    assert!(client.missing_blobs(&hashes).await.unwrap().is_empty());
}
