//! The OpenAPI document against the router it describes, and its structure; the tokens of
//! `/metrics`.

use std::collections::{BTreeSet, HashSet};
use std::sync::Arc;

use axum::body::Body;
use axum::http::{header, Method, Request, StatusCode};
use protocol::routes::{Access, ROUTES};
use serde_json::Value;
use tower::ServiceExt;

use super::{metrics_router, router, Auth};
use crate::clock::ManualClock;
use crate::config::FarmConfig;
use crate::farm::Farm;

fn farm() -> (Arc<Farm>, tempfile::TempDir) {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(
        dir.path(),
        FarmConfig::default(),
        Arc::new(ManualClock::new(1_000_000)),
    )
    .unwrap();
    (farm, dir)
}

fn auth() -> Auth {
    Auth {
        token: Some("api-token".into()),
        metrics_token: Some("scrape-token".into()),
    }
}

fn spec() -> Value {
    serde_json::from_str(&protocol::openapi::json()).unwrap()
}

/// `path` with its `{parameters}` filled in.
fn concrete(path: &str) -> String {
    path.replace("{id}", "12345")
        .replace("{hash}", &"0".repeat(64))
}

async fn call(
    app: &axum::Router,
    method: &str,
    path: &str,
    token: Option<&str>,
) -> (StatusCode, String, Vec<u8>) {
    let mut req = Request::builder()
        .method(Method::from_bytes(method.as_bytes()).unwrap())
        .uri(path);
    if let Some(t) = token {
        req = req.header(header::AUTHORIZATION, format!("Bearer {t}"));
    }
    let resp = app
        .clone()
        .oneshot(req.body(Body::empty()).unwrap())
        .await
        .unwrap();
    let status = resp.status();
    let media = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .map(|v| v.to_str().unwrap().to_string())
        .unwrap_or_default();
    let body = axum::body::to_bytes(resp.into_body(), 1 << 24)
        .await
        .unwrap()
        .to_vec();
    (status, media, body)
}

/// Every route of the table is served (it answers its own way, not the router's 404 or 405)
/// and is in the document under its method with exactly the statuses the table lists.
#[tokio::test]
async fn every_served_route_is_in_the_spec_with_its_statuses() {
    let (farm, _dir) = farm();
    let app = router(farm, &auth());
    let spec = spec();
    let paths = spec["paths"].as_object().unwrap();
    for route in ROUTES {
        let path = route.full_path();
        let (status, _, body) = call(&app, route.method, &concrete(&path), None).await;
        let expected = match route.access {
            Access::Open => StatusCode::OK,
            Access::Token | Access::MetricsToken => StatusCode::UNAUTHORIZED,
        };
        assert_eq!(
            status,
            expected,
            "{} {path}: {}",
            route.method,
            String::from_utf8_lossy(&body)
        );
        let op = &paths
            .get(&path)
            .unwrap_or_else(|| panic!("{path} is not in the spec"))[route.method.to_lowercase()];
        assert!(op.is_object(), "{} {path} is not in the spec", route.method);
        let listed: BTreeSet<String> = op["responses"]
            .as_object()
            .unwrap()
            .keys()
            .cloned()
            .collect();
        let table: BTreeSet<String> = route
            .statuses()
            .iter()
            .map(|a| a.status.to_string())
            .collect();
        assert_eq!(listed, table, "{} {path}", route.method);
        for (status, response) in op["responses"].as_object().unwrap() {
            if status.starts_with('4') || status.starts_with('5') {
                assert_eq!(
                    response["content"]["application/json"]["schema"]["$ref"],
                    "#/components/schemas/ApiError",
                    "{} {path} {status}",
                    route.method
                );
            }
        }
    }
    // Nothing in the document that the router does not serve.
    let operations: usize = paths
        .values()
        .map(|item| {
            [
                "get", "put", "post", "delete", "patch", "head", "options", "trace",
            ]
            .iter()
            .filter(|m| item.get(**m).is_some())
            .count()
        })
        .sum();
    assert_eq!(operations, ROUTES.len());
}

#[test]
fn the_spec_names_query_parameters_and_security() {
    let spec = spec();
    let image = &spec["paths"]["/api/v1/jobs/{id}/image"]["get"];
    let format = image["parameters"]
        .as_array()
        .unwrap()
        .iter()
        .find(|p| p["name"] == "format")
        .expect("?format");
    assert_eq!(format["in"], "query");
    assert_eq!(
        format["schema"]["enum"],
        serde_json::json!(["png", "exr", "pfm"])
    );
    let tiles = &spec["paths"]["/api/v1/jobs/{id}/tiles"]["get"]["parameters"];
    let names: Vec<&str> = tiles
        .as_array()
        .unwrap()
        .iter()
        .map(|p| p["name"].as_str().unwrap())
        .collect();
    assert_eq!(names, ["id", "offset", "limit"]);
    let schemes = &spec["components"]["securitySchemes"];
    assert_eq!(schemes["token"]["scheme"], "bearer");
    assert_eq!(schemes["metricsToken"]["scheme"], "bearer");
    assert_eq!(
        spec["paths"]["/metrics"]["get"]["security"],
        serde_json::json!([{"token": []}, {"metricsToken": []}])
    );
    assert_eq!(
        spec["paths"]["/api/v1/jobs"]["get"]["security"],
        serde_json::json!([{"token": []}])
    );
    // An empty requirement: no credentials.
    assert_eq!(
        spec["paths"]["/api/v1/openapi.json"]["get"]["security"],
        serde_json::json!([{}])
    );
    // The wire types' fields, nested ones included.
    let schemas = &spec["components"]["schemas"];
    assert!(schemas["JobSpec"]["properties"]["render"].is_object());
    assert!(schemas["RenderSettings"]["properties"]["spp"].is_object());
    assert!(schemas["TileRect"]["properties"]["width"].is_object());
}

/// What is wrong with an OpenAPI 3.1 document beyond what deserialising it checks: references
/// that lead nowhere, path parameters not declared, responses without a description, duplicate
/// operation ids, security requirements naming no scheme.
fn problems(doc: &Value) -> Vec<String> {
    let mut out = Vec::new();
    if !doc["openapi"]
        .as_str()
        .is_some_and(|v| v.starts_with("3.1."))
    {
        out.push(format!("openapi is {}", doc["openapi"]));
    }
    fn refs<'a>(v: &'a Value, found: &mut Vec<&'a str>) {
        match v {
            Value::Object(map) => {
                if let Some(Value::String(r)) = map.get("$ref") {
                    found.push(r);
                }
                map.values().for_each(|v| refs(v, found));
            }
            Value::Array(items) => items.iter().for_each(|v| refs(v, found)),
            _ => {}
        }
    }
    let mut found = Vec::new();
    refs(doc, &mut found);
    for r in found {
        let target = r.strip_prefix('#').and_then(|pointer| doc.pointer(pointer));
        if target.is_none() {
            out.push(format!("$ref {r} resolves to nothing"));
        }
    }
    let schemes = &doc["components"]["securitySchemes"];
    let mut ids = HashSet::new();
    for (path, item) in doc["paths"].as_object().into_iter().flatten() {
        for (method, op) in item.as_object().into_iter().flatten() {
            let declared: HashSet<&str> = op["parameters"]
                .as_array()
                .into_iter()
                .flatten()
                .filter(|p| p["in"] == "path" && p["required"] == true)
                .filter_map(|p| p["name"].as_str())
                .collect();
            for part in path.split('/') {
                if let Some(name) = part.strip_prefix('{').and_then(|p| p.strip_suffix('}')) {
                    if !declared.contains(name) {
                        out.push(format!("{method} {path}: path parameter {name} undeclared"));
                    }
                }
            }
            match op["responses"].as_object() {
                Some(responses) if !responses.is_empty() => {
                    for (status, response) in responses {
                        if !response["description"].is_string() {
                            out.push(format!("{method} {path} {status}: no description"));
                        }
                    }
                }
                _ => out.push(format!("{method} {path}: no responses")),
            }
            match op["operationId"].as_str() {
                Some(id) if ids.insert(id.to_string()) => {}
                other => out.push(format!("{method} {path}: operationId {other:?}")),
            }
            for requirement in op["security"].as_array().into_iter().flatten() {
                for name in requirement
                    .as_object()
                    .into_iter()
                    .flatten()
                    .map(|(k, _)| k)
                {
                    if !schemes[name].is_object() {
                        out.push(format!("{method} {path}: no security scheme {name}"));
                    }
                }
            }
        }
    }
    out
}

#[test]
fn the_spec_validates() {
    let json = protocol::openapi::json();
    // oas3 deserialises OpenAPI 3.1 into its typed model: required fields, known types.
    let typed = oas3::from_json(&json).expect("an OpenAPI 3.1 document");
    assert!(typed.openapi.starts_with("3.1"), "{}", typed.openapi);
    assert_eq!(
        typed.paths.as_ref().map(|p| p.len()),
        Some(spec()["paths"].as_object().unwrap().len())
    );
    let doc = spec();
    assert_eq!(problems(&doc), Vec::<String>::new());

    // The checks catch what they are for.
    let mut broken = doc.clone();
    broken["components"]["schemas"]
        .as_object_mut()
        .unwrap()
        .remove("ApiError");
    assert!(problems(&broken)
        .iter()
        .any(|p| p.contains("#/components/schemas/ApiError")));
    let mut broken = doc.clone();
    broken["paths"]["/api/v1/jobs/{id}"]["get"]["parameters"] = Value::Array(vec![]);
    assert!(problems(&broken)
        .iter()
        .any(|p| p.contains("path parameter id")));
    let mut broken = doc.clone();
    broken["components"]["securitySchemes"]
        .as_object_mut()
        .unwrap()
        .remove("metricsToken");
    assert!(problems(&broken).iter().any(|p| p.contains("metricsToken")));
    let mut broken = doc.clone();
    broken.as_object_mut().unwrap().remove("info");
    assert!(oas3::from_json(broken.to_string()).is_err());
}

#[tokio::test]
async fn the_document_is_served_without_a_token() {
    let (farm, _dir) = farm();
    let app = router(farm, &auth());
    let (status, media, body) = call(&app, "GET", "/api/v1/openapi.json", None).await;
    assert_eq!(status, StatusCode::OK);
    assert_eq!(media, "application/json");
    assert_eq!(String::from_utf8(body).unwrap(), protocol::openapi::json());
}

#[tokio::test]
async fn metrics_take_either_token_and_nothing_else_does_the_metrics_token() {
    let (farm, _dir) = farm();
    let app = router(farm.clone(), &auth());
    for token in ["scrape-token", "api-token"] {
        let (status, media, body) = call(&app, "GET", "/metrics", Some(token)).await;
        assert_eq!(status, StatusCode::OK, "{token}");
        assert_eq!(media, crate::metrics::CONTENT_TYPE);
        let text = String::from_utf8(body).unwrap();
        assert!(
            text.contains("tessera_tiles{state=\"queued\"} 0\n"),
            "{text}"
        );
    }
    for token in [None, Some("wrong")] {
        let (status, media, body) = call(&app, "GET", "/metrics", token).await;
        assert_eq!(status, StatusCode::UNAUTHORIZED, "{token:?}");
        assert_eq!(media, "application/json");
        let error: protocol::ApiError = serde_json::from_slice(&body).unwrap();
        assert!(error.error.contains("token"), "{}", error.error);
    }
    // The scrape token opens nothing but the metrics.
    let (status, _, _) = call(&app, "GET", "/api/v1/jobs", Some("scrape-token")).await;
    assert_eq!(status, StatusCode::UNAUTHORIZED);
    let (status, _, _) = call(&app, "GET", "/api/v1/jobs", Some("api-token")).await;
    assert_eq!(status, StatusCode::OK);

    // The metrics listener's router: /metrics without a token, and nothing else.
    let scrape = metrics_router(farm);
    let (status, media, _) = call(&scrape, "GET", "/metrics", None).await;
    assert_eq!(
        (status, media.as_str()),
        (StatusCode::OK, crate::metrics::CONTENT_TYPE)
    );
    let (status, _, _) = call(&scrape, "GET", "/api/v1/jobs", None).await;
    assert_eq!(status, StatusCode::NOT_FOUND);
}
