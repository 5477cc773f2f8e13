//! Every route of the coordinator with the status codes it answers. The coordinator builds its
//! router by walking [`ROUTES`] and asking for each [`RouteId`]'s handler in an exhaustive
//! `match`, so a route cannot be served without an entry here, and an entry cannot lack a
//! handler. Any route answers 401 without the right bearer token when the coordinator has one
//! (but `/healthz`).

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
    Failure,
    Healthz,
    Metrics,
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Route {
    pub id: RouteId,
    pub method: &'static str,
    /// The axum path pattern, under [`API_PREFIX`] when `prefixed`.
    pub path: &'static str,
    pub prefixed: bool,
    /// Status codes and bodies, for readers of this table and `docs/api.md`.
    pub answers: &'static str,
}

impl Route {
    /// The path as a client writes it: `/api/v1/jobs/{id}`.
    pub fn full_path(&self) -> String {
        if self.prefixed {
            format!("{API_PREFIX}{}", self.path)
        } else {
            self.path.to_string()
        }
    }
}

const fn api(
    id: RouteId,
    method: &'static str,
    path: &'static str,
    answers: &'static str,
) -> Route {
    Route {
        id,
        method,
        path,
        prefixed: true,
        answers,
    }
}

/// The whole API.
pub const ROUTES: &[Route] = &[
    api(
        RouteId::SubmitJob,
        "POST",
        "/jobs",
        "multipart: `job` JSON JobSpec, `scene`, one part per asset. 201 JobInfo; 400 ApiError \
         (bad scene, settings, path, or over a budget: the limit is named); 413 too large",
    ),
    api(
        RouteId::ListJobs,
        "GET",
        "/jobs",
        "200 Vec<JobInfo>, oldest first",
    ),
    api(RouteId::ShowJob, "GET", "/jobs/{id}", "200 JobInfo; 404"),
    api(
        RouteId::CancelJob,
        "DELETE",
        "/jobs/{id}",
        "200 JobInfo (cancelled); 404; 409 already finished",
    ),
    api(
        RouteId::RetryJob,
        "POST",
        "/jobs/{id}/retry",
        "200 JobInfo (failed tiles requeued); 404; 409 not failed",
    ),
    api(
        RouteId::JobImage,
        "GET",
        "/jobs/{id}/image",
        "?frame=N&format=png|exr|pfm. 200 image/png, image/x-exr or image/x-portable-floatmap \
         (partial while running); 400 unknown format; 404",
    ),
    api(
        RouteId::JobFramesTar,
        "GET",
        "/jobs/{id}/frames.tar",
        "200 application/x-tar of every frame's PNG; 404; 409 not done",
    ),
    api(
        RouteId::JobBundle,
        "GET",
        "/jobs/{id}/bundle",
        "200 Bundle; 404",
    ),
    api(
        RouteId::JobTiles,
        "GET",
        "/jobs/{id}/tiles",
        "?offset=&limit= (limit at most MAX_TILE_PAGE). 200 TilePage; 400 bad query; 404",
    ),
    api(
        RouteId::JobCamera,
        "GET",
        "/jobs/{id}/camera",
        "200 JobCamera; 404",
    ),
    api(
        RouteId::ResubmitJob,
        "POST",
        "/jobs/{id}/resubmit",
        "optional JobSpec. 201 JobInfo of a new job of the same scene; 400 (over a budget: the \
         limit is named); 404",
    ),
    api(
        RouteId::RegisterWorker,
        "POST",
        "/workers",
        "WorkerRegistration. 201 WorkerIdentity; 400 bad name",
    ),
    api(
        RouteId::ListWorkers,
        "GET",
        "/workers",
        "200 Vec<WorkerInfo>, by name then id",
    ),
    api(
        RouteId::Events,
        "GET",
        "/events",
        "200 text/event-stream: job, tile, workers, resync events",
    ),
    api(
        RouteId::MissingBlobs,
        "POST",
        "/blobs/missing",
        "Vec<String> of hashes. 200 Vec<String>: those the coordinator lacks",
    ),
    api(RouteId::Blob, "GET", "/blobs/{hash}", "200 bytes; 404"),
    api(
        RouteId::Lease,
        "POST",
        "/leases",
        "LeaseRequest. 200 Lease; 204 nothing to do within wait_ms; 404 unknown worker id \
         (register again)",
    ),
    api(
        RouteId::HandBack,
        "DELETE",
        "/leases/{id}",
        "204 handed back; 409 stale",
    ),
    api(
        RouteId::Heartbeat,
        "POST",
        "/leases/{id}/heartbeat",
        "200 LeaseStatus; 409 stale or unknown",
    ),
    api(
        RouteId::Pixels,
        "PUT",
        "/leases/{id}/pixels",
        "f32 LE RGB. 200 Completion; 400 wrong size; 409 stale",
    ),
    api(
        RouteId::Failure,
        "POST",
        "/leases/{id}/failure",
        "FailureReport. 200 JobInfo; 409 stale",
    ),
    Route {
        id: RouteId::Healthz,
        method: "GET",
        path: "/healthz",
        prefixed: false,
        answers: "200 `ok` (no token needed)",
    },
    Route {
        id: RouteId::Metrics,
        method: "GET",
        path: "/metrics",
        prefixed: false,
        answers: "200 Prometheus text",
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
