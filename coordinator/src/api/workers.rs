//! `/workers`: registration (the coordinator issues each worker process its identity) and the
//! listing.

use axum::body::Bytes;
use axum::extract::State;
use axum::http::StatusCode;
use axum::Json;
use protocol::{WorkerIdentity, WorkerInfo, WorkerRegistration};

use super::{parse_json, ApiResult, AppState};

pub async fn register(
    State(app): AppState,
    body: Bytes,
) -> ApiResult<(StatusCode, Json<WorkerIdentity>)> {
    let req: WorkerRegistration = parse_json(&body)?;
    let identity = app.farm.register_worker(&req.name)?;
    Ok((StatusCode::CREATED, Json(identity)))
}

pub async fn list(State(app): AppState) -> Json<Vec<WorkerInfo>> {
    Json(app.farm.workers())
}
