//! Every route of the coordinator with the status codes it answers. The coordinator builds its
//! router by walking [`ROUTES`] and asking for each [`RouteId`]'s handler in an exhaustive
//! `match`, so a route cannot be served without an entry here, and an entry cannot lack a
//! handler. The table is also the source of the OpenAPI document (`openapi` feature,
//! [`crate::openapi`]): each route lists every status it answers with its body, its query
//! parameters and who may call it.

use crate::API_PREFIX;

/// Names a route independently of its method and path.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum RouteId {
    SubmitJob,
    ListJobs,
    ShowJob,
    CancelJob,
    RetryJob,
    JobImage,
    JobFramesTar,
    JobBundle,
    JobTiles,
    JobCamera,
    JobConvergence,
    JobSamples,
    ResubmitJob,
    RegisterWorker,
    ListWorkers,
    Events,
    MissingBlobs,
    Blob,
    Lease,
    HandBack,
    Heartbeat,
    Pixels,
    LeaseSums,
    PassSums,
    Failure,
    OpenApi,
    Healthz,
    Metrics,
}

/// Who may call a route when the coordinator has a token.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Access {
    /// Anyone: liveness probes and the API description.
    Open,
    /// The bearer token (`--token`).
    Token,
    /// The bearer token or the scrape-only metrics token (`--metrics-token`).
    MetricsToken,
}

/// What a request or an answer carries.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Body {
    Empty,
    /// JSON of the named wire type of this crate (the OpenAPI component of that name).
    Json(&'static str),
    /// A JSON array of the named wire type.
    JsonList(&'static str),
    /// A JSON array of strings.
    Strings,
    /// Bytes of this media type.
    Bytes(&'static str),
    /// The `multipart/form-data` of a job submission ([`crate::PART_JOB`], [`crate::PART_SCENE`],
    /// assets).
    Submission,
}

/// One status a route answers. Every 4xx/5xx carries an [`crate::ApiError`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Answer {
    pub status: u16,
    pub body: Body,
    pub meaning: &'static str,
}

/// A success answer.
pub const fn ok(status: u16, body: Body, meaning: &'static str) -> Answer {
    Answer {
        status,
        body,
        meaning,
    }
}

/// An error answer (its body is an [`crate::ApiError`]).
pub const fn err(status: u16, meaning: &'static str) -> Answer {
    Answer {
        status,
        body: Body::Json("ApiError"),
        meaning,
    }
}

/// The values a query parameter takes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum QueryValue {
    /// An unsigned integer.
    Integer,
    /// One of these words.
    OneOf(&'static [&'static str]),
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct QueryParam {
    pub name: &'static str,
    pub value: QueryValue,
    pub meaning: &'static str,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Route {
    pub id: RouteId,
    pub method: &'static str,
    /// The axum path pattern, under [`API_PREFIX`] when `prefixed`.
    pub path: &'static str,
    pub prefixed: bool,
    /// One line for listings (`docs/api.md` has the prose).
    pub summary: &'static str,
    pub access: Access,
    pub request: Body,
    /// Whether a request body must be sent (when `request` is not [`Body::Empty`]).
    pub request_required: bool,
    pub query: &'static [QueryParam],
    /// Every status the route answers but 401 (see [`Route::statuses`]).
    pub answers: &'static [Answer],
}

/// The 401 every route but an [`Access::Open`] one answers when the coordinator has a token.
pub const UNAUTHORIZED: Answer = err(401, "no bearer token, or the wrong one");

/// Answered by every route whose handler reads the store.
const STORAGE: Answer = err(500, "storage failure");

impl Route {
    /// The path as a client writes it: `/api/v1/jobs/{id}`.
    pub fn full_path(&self) -> String {
        if self.prefixed {
            format!("{API_PREFIX}{}", self.path)
        } else {
            self.path.to_string()
        }
    }

    /// Every answer of the route, 401 included when it needs a token, by status.
    pub fn statuses(&self) -> Vec<Answer> {
        let mut all = self.answers.to_vec();
        if self.access != Access::Open {
            all.push(UNAUTHORIZED);
        }
        all.sort_by_key(|a| a.status);
        all
    }

    /// The names of the path's `{parameters}`.
    pub fn path_params(&self) -> Vec<&'static str> {
        self.path
            .split('/')
            .filter_map(|part| part.strip_prefix('{')?.strip_suffix('}'))
            .collect()
    }

    const fn query(mut self, query: &'static [QueryParam]) -> Route {
        self.query = query;
        self
    }

    const fn takes(mut self, request: Body, required: bool) -> Route {
        self.request = request;
        self.request_required = required;
        self
    }
}

/// A route under [`API_PREFIX`] that needs the token and takes no body: the others are built
/// from it with [`Route::takes`] and [`Route::query`].
const fn api(
    id: RouteId,
    method: &'static str,
    path: &'static str,
    summary: &'static str,
    answers: &'static [Answer],
) -> Route {
    Route {
        id,
        method,
        path,
        prefixed: true,
        summary,
        access: Access::Token,
        request: Body::Empty,
        request_required: false,
        query: &[],
        answers,
    }
}

const NO_JOB: Answer = err(404, "no such job");
const STALE: Answer = err(409, "the lease is stale or unknown");
const BAD_JSON: Answer = err(400, "the body is not the expected JSON");
const OVER_BUDGET: &str =
    "bad scene, settings or asset path, or over a budget (the limit is named)";

/// The whole API.
pub const ROUTES: &[Route] = &[
    api(
        RouteId::SubmitJob,
        "POST",
        "/jobs",
        "submit a job",
        &[
            ok(201, Body::Json("JobInfo"), "the job was accepted"),
            err(400, OVER_BUDGET),
            err(408, "the upload stalled for longer than the idle timeout"),
            err(413, "the submission is over --max-upload-mib"),
            STORAGE,
        ],
    )
    .takes(Body::Submission, true),
    api(
        RouteId::ListJobs,
        "GET",
        "/jobs",
        "list jobs, oldest first",
        &[ok(200, Body::JsonList("JobInfo"), "every job")],
    ),
    api(
        RouteId::ShowJob,
        "GET",
        "/jobs/{id}",
        "one job",
        &[ok(200, Body::Json("JobInfo"), "the job"), NO_JOB],
    ),
    api(
        RouteId::CancelJob,
        "DELETE",
        "/jobs/{id}",
        "cancel",
        &[
            ok(200, Body::Json("JobInfo"), "the job, cancelled"),
            NO_JOB,
            err(409, "the job has finished already"),
            STORAGE,
        ],
    ),
    api(
        RouteId::RetryJob,
        "POST",
        "/jobs/{id}/retry",
        "requeue a failed job",
        &[
            ok(
                200,
                Body::Json("JobInfo"),
                "the job, its failed tiles queued again",
            ),
            NO_JOB,
            err(409, "the job has not failed"),
            STORAGE,
        ],
    ),
    api(
        RouteId::JobImage,
        "GET",
        "/jobs/{id}/image",
        "the picture (partial while the job runs)",
        &[
            ok(
                200,
                Body::Bytes("image/png"),
                "the image; image/x-exr or image/x-portable-floatmap for ?format=exr|pfm",
            ),
            err(400, "a bad query (an unknown format or frame)"),
            NO_JOB,
            STORAGE,
        ],
    )
    .query(&[
        QueryParam {
            name: "frame",
            value: QueryValue::Integer,
            meaning: "the frame of a frame-range job (default: its first)",
        },
        QueryParam {
            name: "format",
            value: QueryValue::OneOf(&["png", "exr", "pfm"]),
            meaning: "png (8-bit sRGB, the default), or linear f32 exr or pfm",
        },
    ]),
    api(
        RouteId::JobFramesTar,
        "GET",
        "/jobs/{id}/frames.tar",
        "every frame of a finished job",
        &[
            ok(200, Body::Bytes("application/x-tar"), "every frame's PNG"),
            NO_JOB,
            err(409, "the job is not done"),
            STORAGE,
        ],
    ),
    api(
        RouteId::JobBundle,
        "GET",
        "/jobs/{id}/bundle",
        "what a worker needs to load the scene",
        &[
            ok(200, Body::Json("Bundle"), "the scene's files by hash"),
            NO_JOB,
            STORAGE,
        ],
    ),
    api(
        RouteId::JobTiles,
        "GET",
        "/jobs/{id}/tiles",
        "the tile map, one page",
        &[
            ok(200, Body::Json("TilePage"), "tiles offset, offset + 1, …"),
            err(400, "a bad query, or a limit over MAX_TILE_PAGE (4096)"),
            NO_JOB,
        ],
    )
    .query(&[
        QueryParam {
            name: "offset",
            value: QueryValue::Integer,
            meaning: "the first tile (default 0)",
        },
        QueryParam {
            name: "limit",
            value: QueryValue::Integer,
            meaning: "tiles in the page, at most 4096 (the default)",
        },
    ]),
    api(
        RouteId::JobCamera,
        "GET",
        "/jobs/{id}/camera",
        "where the job looks from",
        &[
            ok(200, Body::Json("JobCamera"), "the camera"),
            NO_JOB,
            STORAGE,
        ],
    ),
    api(
        RouteId::JobConvergence,
        "GET",
        "/jobs/{id}/convergence",
        "a progressive job's passes: wall time, mean spp, estimated error",
        &[
            ok(200, Body::Json("Convergence"), "every finished pass"),
            NO_JOB,
        ],
    ),
    api(
        RouteId::JobSamples,
        "GET",
        "/jobs/{id}/samples.png",
        "where a progressive job's samples went",
        &[
            ok(
                200,
                Body::Bytes("image/png"),
                "each pixel's spp over spp_max, as grey",
            ),
            NO_JOB,
            err(409, "the job is not progressive, or has no finished pass"),
        ],
    ),
    api(
        RouteId::ResubmitJob,
        "POST",
        "/jobs/{id}/resubmit",
        "render the same scene again",
        &[
            ok(201, Body::Json("JobInfo"), "the new job"),
            err(400, OVER_BUDGET),
            NO_JOB,
            STORAGE,
        ],
    )
    .takes(Body::Json("JobSpec"), false),
    api(
        RouteId::RegisterWorker,
        "POST",
        "/workers",
        "register a worker process",
        &[
            ok(201, Body::Json("WorkerIdentity"), "the worker's identity"),
            err(400, "bad JSON or a bad name"),
            STORAGE,
        ],
    )
    .takes(Body::Json("WorkerRegistration"), true),
    api(
        RouteId::ListWorkers,
        "GET",
        "/workers",
        "every worker heard from, by name then id",
        &[ok(200, Body::JsonList("WorkerInfo"), "the workers")],
    ),
    api(
        RouteId::Events,
        "GET",
        "/events",
        "what changes, as it happens",
        &[ok(
            200,
            Body::Bytes("text/event-stream"),
            "job, tile, workers and resync events",
        )],
    ),
    api(
        RouteId::MissingBlobs,
        "POST",
        "/blobs/missing",
        "which of these hashes the coordinator lacks",
        &[
            ok(200, Body::Strings, "the hashes it lacks"),
            err(400, "bad JSON, or more than 10000 hashes"),
        ],
    )
    .takes(Body::Strings, true),
    api(
        RouteId::Blob,
        "GET",
        "/blobs/{hash}",
        "a scene file or asset by hash",
        &[
            ok(200, Body::Bytes("application/octet-stream"), "its bytes"),
            err(404, "no such blob"),
            STORAGE,
        ],
    ),
    api(
        RouteId::Lease,
        "POST",
        "/leases",
        "ask for a tile (long poll)",
        &[
            ok(200, Body::Json("Lease"), "a tile to render"),
            ok(204, Body::Empty, "nothing to do within wait_ms"),
            BAD_JSON,
            err(404, "unknown worker id (register again)"),
            STORAGE,
        ],
    )
    .takes(Body::Json("LeaseRequest"), true),
    api(
        RouteId::HandBack,
        "DELETE",
        "/leases/{id}",
        "hand a tile back",
        &[ok(204, Body::Empty, "handed back"), STALE, STORAGE],
    ),
    api(
        RouteId::Heartbeat,
        "POST",
        "/leases/{id}/heartbeat",
        "extend a lease",
        &[
            ok(200, Body::Json("LeaseStatus"), "the lease's new expiry"),
            STALE,
        ],
    ),
    api(
        RouteId::Pixels,
        "PUT",
        "/leases/{id}/pixels",
        "complete a tile",
        &[
            ok(200, Body::Json("Completion"), "the job's progress"),
            err(
                400,
                "the wrong size, or a non-finite value (the tile is queued again)",
            ),
            STALE,
            STORAGE,
        ],
    )
    .takes(Body::Bytes("application/octet-stream"), true),
    api(
        RouteId::LeaseSums,
        "GET",
        "/leases/{id}/sums",
        "a pass lease's running sums so far",
        &[
            ok(
                200,
                Body::Bytes("application/octet-stream"),
                "f64 little-endian, 5 per pixel, row-major from the tile's top row",
            ),
            err(409, "the lease is stale, unknown or not a pass"),
        ],
    ),
    api(
        RouteId::PassSums,
        "PUT",
        "/leases/{id}/sums",
        "complete a pass of a tile",
        &[
            ok(200, Body::Json("Completion"), "the pass's progress"),
            err(400, "the wrong size, or a non-finite value"),
            err(409, "the lease is stale, unknown or not a pass"),
            STORAGE,
        ],
    )
    .takes(Body::Bytes("application/octet-stream"), true),
    api(
        RouteId::Failure,
        "POST",
        "/leases/{id}/failure",
        "report a tile's failure",
        &[
            ok(200, Body::Json("JobInfo"), "the job"),
            BAD_JSON,
            STALE,
            STORAGE,
        ],
    )
    .takes(Body::Json("FailureReport"), true),
    Route {
        id: RouteId::OpenApi,
        method: "GET",
        path: "/openapi.json",
        prefixed: true,
        summary: "this API as an OpenAPI 3.1 document",
        access: Access::Open,
        request: Body::Empty,
        request_required: false,
        query: &[],
        answers: &[ok(200, Body::Bytes("application/json"), "the document")],
    },
    Route {
        id: RouteId::Healthz,
        method: "GET",
        path: "/healthz",
        prefixed: false,
        summary: "liveness",
        access: Access::Open,
        request: Body::Empty,
        request_required: false,
        query: &[],
        answers: &[ok(200, Body::Bytes("text/plain"), "`ok`")],
    },
    Route {
        id: RouteId::Metrics,
        method: "GET",
        path: "/metrics",
        prefixed: false,
        summary: "Prometheus metrics",
        access: Access::MetricsToken,
        request: Body::Empty,
        request_required: false,
        query: &[],
        answers: &[ok(
            200,
            Body::Bytes("application/openmetrics-text"),
            "OpenMetrics text",
        )],
    },
];

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_route_is_listed_once() {
        let mut seen = std::collections::HashSet::new();
        for route in ROUTES {
            assert!(seen.insert(route.id), "{:?} twice", route.id);
            assert!(
                seen.len() <= ROUTES.len()
                    && ROUTES
                        .iter()
                        .filter(|r| r.method == route.method && r.path == route.path)
                        .count()
                        == 1,
                "{} {} twice",
                route.method,
                route.path
            );
        }
        assert!(ROUTES
            .iter()
            .any(|r| r.full_path() == "/api/v1/jobs/{id}/frames.tar"));
    }
}
