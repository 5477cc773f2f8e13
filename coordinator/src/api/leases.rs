//! `/leases`: the worker side. Lease requests long-poll; every other call names a lease id
//! and gets 409 when that lease is no longer live. A call that changed the farm is answered
//! once its change is committed (group commit, see `farm::commits`).

use std::net::SocketAddr;
use std::sync::atomic::Ordering;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{ConnectInfo, Path, State};
use axum::http::{Extensions, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use protocol::{Completion, FailureReport, JobInfo, Lease, LeaseRequest, LeaseStatus};

use super::{blocking, parse_id, parse_json, ApiResult, AppState, Failure};
use crate::farm::{Farm, FarmError};

/// Counts 409s for the metrics on the way out.
fn counted<T>(app: &super::App, result: Result<T, FarmError>) -> ApiResult<T> {
    stale_counted(&app.farm, result)
}

/// [`counted`], for a farm without the rest of the app (the embedded farm's handover).
fn stale_counted<T>(farm: &Farm, result: Result<T, FarmError>) -> ApiResult<T> {
    if let Err(FarmError::Stale(_)) = &result {
        farm.metrics.stale_requests.fetch_add(1, Ordering::Relaxed);
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
    // Present when the server was started with connection info (it always is but in tests
    // that build the router alone).
    if let Some(ConnectInfo(peer)) = extensions.get::<ConnectInfo<SocketAddr>>() {
        app.farm.worker_address(req.worker_id, peer.to_string());
    }
    Ok(match wait_for_lease(&app.farm, &req).await? {
        Some(lease) => Json(lease).into_response(),
        None => StatusCode::NO_CONTENT.into_response(),
    })
}

/// A tile for `req`'s worker, waiting up to its `wait_ms` (capped by the farm's
/// `max_poll_wait`) for one to turn up; None when none did. Answers once the lease is
/// committed: the lease route, and the embedded farm's workers asking in process.
pub(crate) async fn wait_for_lease(farm: &Farm, req: &LeaseRequest) -> ApiResult<Option<Lease>> {
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
            farm.durable(farm.written()).await?;
            farm.metrics.observe_lease_latency(start.elapsed());
            return Ok(Some(lease));
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
    Ok(None)
}

pub async fn heartbeat(
    State(app): AppState,
    Path(id): Path<String>,
) -> ApiResult<Json<LeaseStatus>> {
    let id = parse_id("lease", &id)?;
    Ok(Json(counted(&app, app.farm.heartbeat(id))?))
}

/// The longest failure message stored: it is repeated in every job listing and event.
pub const MAX_FAILURE_MESSAGE: usize = 4096;

/// Cuts `message` to at most `max` bytes on a character boundary, saying how long it was.
fn truncate_message(message: &mut String, max: usize) {
    if message.len() <= max {
        return;
    }
    let total = message.len();
    let note = format!("… ({total} bytes, truncated)");
    let mut end = max.saturating_sub(note.len());
    while !message.is_char_boundary(end) {
        end -= 1;
    }
    message.truncate(end);
    message.push_str(&note);
}

/// The index of the first value in `pixels` (f32 little-endian) that is NaN or infinite.
fn first_non_finite(pixels: &[u8]) -> Option<usize> {
    // Blocks are checked without an early exit, which compiles to vector code (every tile's
    // pixels pass here; searching value by value took ~0.1 ms per 256×256 tile); only a block
    // holding a non-finite value is searched for its index.
    const VALUES: usize = 64;
    let non_finite = |c: &[u8]| {
        let bits = u32::from_le_bytes([c[0], c[1], c[2], c[3]]);
        bits & 0x7f80_0000 == 0x7f80_0000
    };
    let whole = pixels.len() / 4 * 4;
    for (b, block) in pixels[..whole].chunks(4 * VALUES).enumerate() {
        let any = block
            .chunks_exact(4)
            .fold(false, |any, value| any | non_finite(value));
        if any {
            let at = block.chunks_exact(4).position(non_finite);
            return at.map(|i| b * VALUES + i);
        }
    }
    None
}

/// What a completion's blocking part decided.
enum Outcome {
    Stored(Completion),
    /// The pixels held a non-finite value: the lease ended as a failure and the tile went
    /// back to the queue.
    NonFinite(String),
}

/// Completions up to this size are stored on the async thread: a positioned write of a few
/// KiB costs less than handing the request to the blocking pool and back.
const INLINE_COMPLETION: usize = 64 << 10;

pub async fn complete(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Json<Completion>> {
    let id = parse_id("lease", &id)?;
    store_pixels(&app.farm, id, body).await.map(Json)
}

/// Stores lease `id`'s tile pixels (f32 little-endian) and answers once the change is
/// committed: the pixels route, and the embedded farm's workers handing tiles over in memory.
pub(crate) async fn store_pixels(farm: &Arc<Farm>, id: u64, body: Bytes) -> ApiResult<Completion> {
    let store_farm = farm.clone();
    let inline = body.len() <= INLINE_COMPLETION;
    let store = move || {
        Ok(match first_non_finite(&body) {
            // Recorded as the worker's failure rather than handed back: a tile that renders
            // NaN on every worker then fails its job after the usual attempts instead of
            // circulating for ever.
            Some(at) => {
                let error = format!(
                    "the tile's pixels hold a non-finite value (NaN or infinity) at value {at}"
                );
                let report = FailureReport {
                    error: error.clone(),
                    scene: false,
                };
                store_farm
                    .fail(id, &report)
                    .map(|_| Outcome::NonFinite(error))
            }
            None => store_farm.complete(id, &body).map(Outcome::Stored),
        })
    };
    let result = if inline {
        store()?
    } else {
        blocking(store).await?
    };
    let outcome = stale_counted(farm, result)?;
    farm.durable(farm.written()).await?;
    match outcome {
        Outcome::Stored(done) => Ok(done),
        Outcome::NonFinite(error) => Err(Failure::bad_request(format!(
            "{error}; refused, and the tile is queued again"
        ))),
    }
}

/// A pass lease's running sums so far (f64 little-endian).
pub async fn sums(State(app): AppState, Path(id): Path<String>) -> ApiResult<Response> {
    let id = parse_id("lease", &id)?;
    let bytes = read_sums(&app.farm, id)?;
    Ok((
        [(axum::http::header::CONTENT_TYPE, "application/octet-stream")],
        bytes,
    )
        .into_response())
}

/// A pass lease's running sums so far: the sums route, and the embedded farm's workers
/// asking in process.
pub(crate) fn read_sums(farm: &Farm, id: u64) -> ApiResult<Vec<u8>> {
    stale_counted(farm, farm.lease_sums(id))
}

/// A pass lease's new sums: the tile's part of the pass is done.
pub async fn complete_sums(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Json<Completion>> {
    let id = parse_id("lease", &id)?;
    store_sums(&app.farm, id, body).await.map(Json)
}

/// Stores a pass lease's new running sums (f64 little-endian) and answers once the change is
/// committed: the sums route, and the embedded farm's in-memory handover.
pub(crate) async fn store_sums(farm: &Arc<Farm>, id: u64, body: Bytes) -> ApiResult<Completion> {
    let store_farm = farm.clone();
    let done = stale_counted(
        farm,
        blocking(move || Ok(store_farm.complete_sums(id, &body))).await?,
    )?;
    farm.durable(farm.written()).await?;
    Ok(done)
}

pub async fn fail(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Json<JobInfo>> {
    let id = parse_id("lease", &id)?;
    let mut report: FailureReport = parse_json(&body)?;
    truncate_message(&mut report.error, MAX_FAILURE_MESSAGE);
    Ok(Json(counted(&app, app.farm.fail(id, &report))?))
}

pub async fn hand_back(State(app): AppState, Path(id): Path<String>) -> ApiResult<StatusCode> {
    let id = parse_id("lease", &id)?;
    counted(&app, app.farm.hand_back(id))?;
    app.farm.durable(app.farm.written()).await?;
    Ok(StatusCode::NO_CONTENT)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn long_messages_are_cut_on_a_character_boundary() {
        let mut short = "a short message".to_string();
        truncate_message(&mut short, 64);
        assert_eq!(short, "a short message");
        let mut long = "é".repeat(5000);
        truncate_message(&mut long, MAX_FAILURE_MESSAGE);
        assert!(long.len() <= MAX_FAILURE_MESSAGE, "{}", long.len());
        assert!(long.ends_with("(10000 bytes, truncated)"), "{long}");
        assert!(long.starts_with("éé"));
    }

    #[test]
    fn non_finite_pixels_are_found() {
        let mut pixels = protocol::pixels_to_bytes(&[0.0, 1.5, 1e30, -2.0]);
        assert_eq!(first_non_finite(&pixels), None);
        pixels.extend_from_slice(&f32::NAN.to_le_bytes());
        assert_eq!(first_non_finite(&pixels), Some(4));
        let inf = protocol::pixels_to_bytes(&[0.0, f32::INFINITY]);
        assert_eq!(first_non_finite(&inf), Some(1));
        // Across block boundaries, each kind of non-finite value, and the largest finite ones.
        let mut values = vec![f32::MAX; 1000];
        values[..10].fill(f32::MIN);
        values[500] = -0.0;
        assert_eq!(first_non_finite(&protocol::pixels_to_bytes(&values)), None);
        for (at, bad) in [
            (0, f32::NAN),
            (63, f32::INFINITY),
            (64, f32::NEG_INFINITY),
            (999, -f32::NAN),
        ] {
            let mut values = values.clone();
            values[at] = bad;
            assert_eq!(
                first_non_finite(&protocol::pixels_to_bytes(&values)),
                Some(at),
                "{bad} at {at}"
            );
        }
        // Two bad values: the first is named; a trailing partial value is not a value.
        values[700] = f32::NAN;
        values[130] = f32::NAN;
        let mut bytes = protocol::pixels_to_bytes(&values);
        assert_eq!(first_non_finite(&bytes), Some(130));
        bytes.truncate(4 * 100);
        bytes.extend_from_slice(&[0xff, 0xff, 0xff]);
        assert_eq!(first_non_finite(&bytes), None);
    }
}
