//! The HTTP API (`docs/api.md`): one file per resource, bearer-token authentication, and the
//! mapping from farm errors to status codes with JSON bodies. The router is built from
//! [`protocol::routes::ROUTES`]: every route there gets its handler here, and nothing else is
//! served but the dashboard's static files. Handlers only translate requests for the farm.

mod blobs;
mod dashboard;
mod events;
mod jobs;
mod leases;

pub(crate) use jobs::submit_in_process;
pub(crate) use leases::{read_sums, store_pixels, store_sums, wait_for_lease};
#[cfg(test)]
mod spec_tests;
mod workers;

use std::sync::Arc;

use axum::extract::{DefaultBodyLimit, Request, State};
use axum::http::{header, HeaderValue, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{delete, get, post, put, MethodRouter};
use axum::{Json, Router};
use protocol::routes::{Access, RouteId, ROUTES};
use protocol::{ApiError, API_PREFIX};
use sha2::{Digest, Sha256};
use subtle::ConstantTimeEq;
use tokio::sync::{OwnedSemaphorePermit, Semaphore};

use crate::farm::{Farm, FarmError};

/// Who may call what: the API's bearer token and the scrape-only metrics token. A coordinator
/// without either answers everyone (it is then bound to loopback, or `--insecure`).
#[derive(Clone, Debug, Default)]
pub struct Auth {
    /// `--token`: every route but the open ones.
    pub token: Option<String>,
    /// `--metrics-token`: `/metrics` only (the main token works there too).
    pub metrics_token: Option<String>,
}

impl From<Option<String>> for Auth {
    fn from(token: Option<String>) -> Self {
        Auth {
            token,
            metrics_token: None,
        }
    }
}

fn digest(token: &str) -> [u8; 32] {
    Sha256::digest(token.as_bytes()).into()
}

/// What every handler shares.
pub struct App {
    pub farm: Arc<Farm>,
    /// SHA-256 of the bearer token, when one is required. Comparing digests in constant time
    /// also hides the token's length.
    token_digest: Option<[u8; 32]>,
    /// SHA-256 of the metrics token, when there is one.
    metrics_digest: Option<[u8; 32]>,
    /// Turns at reading an upload or building a scene: each can take the memory of a whole
    /// scene, so only a few run at once and the rest wait (`ConnectionLimits::max_scene_builds`).
    scene_builds: Arc<Semaphore>,
    /// `GET /api/v1/openapi.json`, generated on first request: building the document took
    /// about 0.3 ms of every start, before the first connection was served.
    openapi: std::sync::OnceLock<axum::body::Bytes>,
}

impl App {
    /// Waits for a turn at scene work; the turn ends when the permit is dropped.
    pub async fn scene_turn(&self) -> OwnedSemaphorePermit {
        self.scene_builds
            .clone()
            .acquire_owned()
            .await
            .expect("the semaphore is never closed")
    }
}

pub type AppState = State<Arc<App>>;

/// An error answer: a status and a JSON [`ApiError`].
#[derive(Debug)]
pub struct Failure(pub StatusCode, pub ApiError);

impl Failure {
    pub fn bad_request(msg: impl Into<String>) -> Self {
        Failure(StatusCode::BAD_REQUEST, ApiError::new(msg))
    }

    pub fn not_found(msg: impl Into<String>) -> Self {
        Failure(StatusCode::NOT_FOUND, ApiError::new(msg))
    }

    pub fn internal(msg: impl Into<String>) -> Self {
        Failure(StatusCode::INTERNAL_SERVER_ERROR, ApiError::new(msg))
    }
}

impl IntoResponse for Failure {
    fn into_response(self) -> Response {
        let mut resp = (self.0, Json(self.1)).into_response();
        if self.0 == StatusCode::UNAUTHORIZED {
            resp.headers_mut()
                .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
        }
        resp
    }
}

impl From<FarmError> for Failure {
    fn from(e: FarmError) -> Self {
        match e {
            FarmError::NotFound(m) => Failure::not_found(m),
            FarmError::Stale(m) | FarmError::Conflict(m) => {
                Failure(StatusCode::CONFLICT, ApiError::new(m))
            }
            FarmError::BadRequest(body) => Failure(StatusCode::BAD_REQUEST, body),
            FarmError::Store(e) => {
                tracing::error!("storage error: {e}");
                Failure(
                    StatusCode::INTERNAL_SERVER_ERROR,
                    ApiError::new(format!("storage error: {e}")),
                )
            }
        }
    }
}

impl From<crate::store::StoreError> for Failure {
    fn from(e: crate::store::StoreError) -> Self {
        FarmError::Store(e).into()
    }
}

pub type ApiResult<T> = Result<T, Failure>;

/// Parses a numeric path id; anything else names no resource.
pub fn parse_id(what: &str, raw: &str) -> ApiResult<u64> {
    raw.parse()
        .map_err(|_| Failure::not_found(format!("no {what} {raw:?}")))
}

/// Parses a JSON body, answering 400 with serde's message when it does not fit.
pub fn parse_json<T: serde::de::DeserializeOwned>(body: &[u8]) -> ApiResult<T> {
    serde_json::from_slice(body)
        .map_err(|e| Failure::bad_request(format!("invalid JSON body: {e}")))
}

/// Runs blocking work (file I/O, scene building, PNG encoding) off the async threads.
pub async fn blocking<T: Send + 'static>(
    f: impl FnOnce() -> ApiResult<T> + Send + 'static,
) -> ApiResult<T> {
    tokio::task::spawn_blocking(f).await.map_err(|e| {
        Failure(
            StatusCode::INTERNAL_SERVER_ERROR,
            ApiError::new(format!("internal error: {e}")),
        )
    })?
}

/// Answers 401 after reading (and discarding) the request body, bounded by the upload limit,
/// so that a client still sending it sees the answer rather than a reset connection.
async fn unauthorized(req: Request, limit: usize, message: &str) -> Response {
    let _ = axum::body::to_bytes(req.into_body(), limit).await;
    Failure(StatusCode::UNAUTHORIZED, ApiError::new(message)).into_response()
}

/// Passes requests that carry one of `accepted` (digests of tokens) as their bearer token, or
/// any request when nothing is accepted because no token is set.
async fn check_token(app: &App, accepted: &[[u8; 32]], req: Request, next: Next) -> Response {
    if !accepted.is_empty() {
        let given = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.strip_prefix("Bearer "))
            .map(|t| digest(t.trim()));
        let problem = match given {
            None => Some("this coordinator needs an 'Authorization: Bearer <token>' header"),
            // Every candidate is compared, so the time taken does not say which one matched.
            Some(given)
                if !accepted
                    .iter()
                    .fold(false, |hit, d| hit | bool::from(given.ct_eq(d))) =>
            {
                Some("wrong bearer token")
            }
            Some(_) => None,
        };
        if let Some(message) = problem {
            let limit = app.farm.config().limits.max_upload_bytes;
            return unauthorized(req, limit, message).await;
        }
    }
    next.run(req).await
}

async fn authenticate(State(app): AppState, req: Request, next: Next) -> Response {
    let accepted: Vec<[u8; 32]> = app.token_digest.into_iter().collect();
    check_token(&app, &accepted, req, next).await
}

/// `/metrics`: the main token or the metrics token.
async fn authenticate_scrape(State(app): AppState, req: Request, next: Next) -> Response {
    let accepted: Vec<[u8; 32]> = app
        .token_digest
        .into_iter()
        .chain(app.metrics_digest)
        .collect();
    check_token(&app, &accepted, req, next).await
}

async fn healthz() -> &'static str {
    "ok\n"
}

async fn metrics(State(app): AppState) -> Response {
    (
        [(header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)],
        app.farm.metrics_text(),
    )
        .into_response()
}

async fn openapi(State(app): AppState) -> Response {
    (
        [(header::CONTENT_TYPE, "application/json")],
        app.openapi
            .get_or_init(|| protocol::openapi::json().into())
            .clone(),
    )
        .into_response()
}

async fn not_found() -> Failure {
    Failure::not_found("no such route; see docs/api.md")
}

/// The longest error text of a non-JSON answer that is carried into the JSON one.
const MAX_REWRAPPED_ERROR: usize = 4096;

/// Makes every error answer a JSON [`ApiError`], including those that axum makes itself (405
/// with an empty body, 413 and 400 from body extractors in plain text). Handlers' own errors
/// are JSON already and pass untouched.
async fn json_errors(req: Request, next: Next) -> Response {
    let (method, path) = (req.method().clone(), req.uri().path().to_string());
    let response = next.run(req).await;
    let status = response.status();
    let is_json = response
        .headers()
        .get(header::CONTENT_TYPE)
        .and_then(|v| v.to_str().ok())
        .is_some_and(|v| v.starts_with("application/json"));
    if !(status.is_client_error() || status.is_server_error()) || is_json {
        return response;
    }
    let (mut parts, body) = response.into_parts();
    let text = axum::body::to_bytes(body, MAX_REWRAPPED_ERROR)
        .await
        .map(|b| String::from_utf8_lossy(&b).trim().to_string())
        .unwrap_or_default();
    // (axum adds the `Allow` header after this layer has run.)
    let error = if status == StatusCode::METHOD_NOT_ALLOWED {
        format!("{method} is not allowed on {path}; its Allow header lists the methods it takes")
    } else if text.is_empty() {
        status.canonical_reason().unwrap_or("error").to_string()
    } else {
        text
    };
    parts.headers.remove(header::CONTENT_LENGTH);
    parts.headers.insert(
        header::CONTENT_TYPE,
        HeaderValue::from_static("application/json"),
    );
    let body = serde_json::to_vec(&ApiError::new(error)).unwrap_or_default();
    Response::from_parts(parts, axum::body::Body::from(body))
}

/// The handler of each route in the table; the match is exhaustive, so a route added to the
/// table without a handler does not compile.
fn handler(id: RouteId) -> MethodRouter<Arc<App>> {
    match id {
        // Submissions enforce the upload limit themselves, draining what lies beyond it.
        RouteId::SubmitJob => post(jobs::submit).layer(DefaultBodyLimit::disable()),
        RouteId::ListJobs => get(jobs::list),
        RouteId::ShowJob => get(jobs::show),
        RouteId::CancelJob => delete(jobs::cancel),
        RouteId::RetryJob => post(jobs::retry),
        RouteId::JobImage => get(jobs::image),
        RouteId::JobFramesTar => get(jobs::frames_tar),
        RouteId::JobBundle => get(jobs::bundle),
        RouteId::JobTiles => get(jobs::tiles),
        RouteId::JobCamera => get(jobs::camera),
        RouteId::JobConvergence => get(jobs::convergence),
        RouteId::JobSamples => get(jobs::samples),
        RouteId::ResubmitJob => post(jobs::resubmit),
        RouteId::RegisterWorker => post(workers::register),
        RouteId::ListWorkers => get(workers::list),
        RouteId::Events => get(events::stream),
        RouteId::MissingBlobs => post(blobs::missing),
        RouteId::Blob => get(blobs::show),
        RouteId::Lease => post(leases::lease),
        RouteId::HandBack => delete(leases::hand_back),
        RouteId::Heartbeat => post(leases::heartbeat),
        RouteId::Pixels => put(leases::complete),
        RouteId::LeaseSums => get(leases::sums),
        RouteId::PassSums => put(leases::complete_sums),
        RouteId::Failure => post(leases::fail),
        RouteId::OpenApi => get(openapi),
        RouteId::Healthz => get(healthz),
        RouteId::Metrics => get(metrics),
    }
}

/// The whole API. The routes the table marks [`Access::Open`] (`/healthz`, the OpenAPI document)
/// and the dashboard's static files answer without a token (probes carry none, the page asks for
/// it, and none reveals anything); `/metrics` takes the token or the metrics token; every other
/// route needs the token when one is set.
pub fn router(farm: Arc<Farm>, auth: &Auth) -> Router {
    let limit = farm.config().limits.max_upload_bytes;
    let app = app(farm, auth);
    let (mut api, mut guarded, mut scrape, mut open) =
        (Router::new(), Router::new(), Router::new(), Router::new());
    for route in ROUTES {
        let method_router = handler(route.id);
        match (route.access, route.prefixed) {
            (Access::Open, _) => open = open.route(&route.full_path(), method_router),
            (Access::MetricsToken, _) => scrape = scrape.route(&route.full_path(), method_router),
            (Access::Token, true) => api = api.route(route.path, method_router),
            (Access::Token, false) => guarded = guarded.route(route.path, method_router),
        }
    }
    let guarded = guarded
        .nest(API_PREFIX, api)
        .route_layer(middleware::from_fn_with_state(app.clone(), authenticate));
    let scrape = scrape.route_layer(middleware::from_fn_with_state(
        app.clone(),
        authenticate_scrape,
    ));
    open.merge(dashboard::routes())
        .merge(guarded)
        .merge(scrape)
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(limit))
        .layer(middleware::from_fn(json_errors))
        .with_state(app)
}

/// `/metrics` alone and without a token, for `--metrics-listen`: an address only scrapers reach.
pub fn metrics_router(farm: Arc<Farm>) -> Router {
    let limit = farm.config().limits.max_upload_bytes.min(1 << 16);
    let app = app(farm, &Auth::default());
    let path = ROUTES
        .iter()
        .find(|r| r.id == RouteId::Metrics)
        .expect("the table has /metrics")
        .full_path();
    Router::new()
        .route(&path, handler(RouteId::Metrics))
        .fallback(not_found)
        .layer(DefaultBodyLimit::max(limit))
        .layer(middleware::from_fn(json_errors))
        .with_state(app)
}

fn app(farm: Arc<Farm>, auth: &Auth) -> Arc<App> {
    let scene_builds = farm.config().connections.max_scene_builds.max(1);
    Arc::new(App {
        farm,
        token_digest: auth.token.as_deref().map(digest),
        metrics_digest: auth.metrics_token.as_deref().map(digest),
        scene_builds: Arc::new(Semaphore::new(scene_builds)),
        openapi: std::sync::OnceLock::new(),
    })
}

#[cfg(test)]
mod tests {
    use protocol::routes::ROUTES;

    /// docs/api.md documents every route of the table under its own heading.
    #[test]
    fn every_route_is_documented() {
        let docs = include_str!("../../../docs/api.md");
        for route in ROUTES {
            let heading = format!("### `{} {}`", route.method, route.full_path());
            assert!(docs.contains(&heading), "docs/api.md lacks {heading}");
        }
    }
}
