//! `/blobs`: content-addressed scene files and assets, for workers and for clients that skip
//! uploading what the coordinator already holds.

use axum::body::Bytes;
use axum::extract::{Path, State};
use axum::http::header;
use axum::response::{IntoResponse, Response};
use axum::Json;

use super::{blocking, parse_json, ApiResult, AppState, Failure};

/// How many hashes one `POST /blobs/missing` may ask about.
const MAX_QUERY: usize = 10_000;

pub async fn show(State(app): AppState, Path(hash): Path<String>) -> ApiResult<Response> {
    let farm = app.farm.clone();
    let bytes = blocking(move || {
        farm.files()
            .blob(&hash)?
            .ok_or_else(|| Failure::not_found(format!("no blob {hash}")))
    })
    .await?;
    Ok(([(header::CONTENT_TYPE, "application/octet-stream")], bytes).into_response())
}

pub async fn missing(State(app): AppState, body: Bytes) -> ApiResult<Json<Vec<String>>> {
    let hashes: Vec<String> = parse_json(&body)?;
    if hashes.len() > MAX_QUERY {
        return Err(Failure::bad_request(format!(
            "ask about at most {MAX_QUERY} hashes at once"
        )));
    }
    let files = app.farm.clone();
    Ok(Json(
        hashes
            .into_iter()
            .filter(|h| !files.files().has_blob(h))
            .collect(),
    ))
}
