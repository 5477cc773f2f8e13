//! `/leases`: the worker side. Lease requests long-poll; every other call names a lease id
//! and gets 409 when that lease is no longer live.

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{ConnectInfo, Path, State};
use axum::http::{Extensions, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use protocol::{Completion, FailureReport, JobInfo, LeaseRequest, LeaseStatus};

use super::{blocking, parse_id, parse_json, ApiResult, AppState};
use crate::farm::FarmError;

/// Counts 409s for the metrics on the way out.
fn counted<T>(app: &super::App, result: Result<T, FarmError>) -> ApiResult<T> {
    if let Err(FarmError::Stale(_)) = &result {
        app.farm
            .metrics
            .stale_requests
            .fetch_add(1, Ordering::Relaxed);
    }
    Ok(result?)
}

/// How often a waiting lease request looks for straggler tiles (which appear with time, not
/// with a notification).
const STRAGGLER_RECHECK: Duration = Duration::from_secs(1);

pub async fn lease(
    State(app): AppState,
    extensions: Extensions,
    body: Bytes,
) -> ApiResult<Response> {
    let req: LeaseRequest = parse_json(&body)?;
    let farm = &app.farm;
    // Present when the server was started with connection info (it always is but in tests
    // that build the router alone).
    if let Some(ConnectInfo(peer)) = extensions.get::<ConnectInfo<SocketAddr>>() {
        farm.worker_address(req.worker_id, peer.to_string());
    }
    let start = Instant::now();
    let wait = Duration::from_millis(req.wait_ms).min(farm.config().max_poll_wait);
    let deadline = start + wait;
    loop {
        // Register for wake-ups before looking, so a tile queued in between is not missed.
        let notified = farm.work_notified();
        tokio::pin!(notified);
        notified.as_mut().enable();
        if farm.is_stopping() {
            break;
        }
        if let Some(lease) = farm.lease(req.worker_id)? {
            farm.metrics.observe_lease_latency(start.elapsed());
            return Ok(Json(lease).into_response());
        }
        let now = Instant::now();
        if now >= deadline {
            break;
        }
        let mut step = deadline - now;
        if farm.config().stragglers {
            step = step.min(STRAGGLER_RECHECK);
        }
        let _ = tokio::time::timeout(step, notified).await;
    }
    farm.metrics
        .lease_polls_empty
        .fetch_add(1, Ordering::Relaxed);
    Ok(StatusCode::NO_CONTENT.into_response())
}

pub async fn heartbeat(
    State(app): AppState,
    Path(id): Path<String>,
) -> ApiResult<Json<LeaseStatus>> {
    let id = parse_id("lease", &id)?;
    Ok(Json(counted(&app, app.farm.heartbeat(id))?))
}

pub async fn complete(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Json<Completion>> {
    let id = parse_id("lease", &id)?;
    let farm = app.farm.clone();
    let result = blocking(move || Ok(farm.complete(id, &body))).await?;
    Ok(Json(counted(&app, result)?))
}

pub async fn fail(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Json<JobInfo>> {
    let id = parse_id("lease", &id)?;
    let report: FailureReport = parse_json(&body)?;
    Ok(Json(counted(&app, app.farm.fail(id, &report))?))
}

pub async fn hand_back(State(app): AppState, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let id = parse_id("lease", &id)?;
    counted(&app, app.farm.hand_back(id))?;
    Ok(StatusCode::NO_CONTENT)
}
