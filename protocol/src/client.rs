//! A typed HTTP client for the coordinator: each route's status codes become enum variants, so
//! callers decide between retrying (unreachable), dropping a tile (stale lease) and giving up.

use std::sync::{Arc, Mutex};
use std::time::Duration;

use reqwest::{header, Method, RequestBuilder, Response, StatusCode};
use serde::de::DeserializeOwned;

use crate::{
    ApiError, Bundle, Completion, FailureReport, JobInfo, JobSpec, Lease, LeaseRequest,
    LeaseStatus, TilePage, WorkerIdentity, WorkerInfo, WorkerRegistration, API_PREFIX,
    CONTENT_TYPE_BLOB_REF, PART_JOB, PART_SCENE,
};

#[derive(Debug, thiserror::Error)]
pub enum ClientError {
    /// The coordinator could not be reached or did not answer in time: try again later.
    #[error("coordinator unreachable: {0}")]
    Unreachable(String),
    /// 409: the lease is stale or unknown (or the job no longer wants the tile). Drop the tile.
    #[error("lease no longer valid: {0}")]
    Stale(String),
    /// 404 to a lease request: the coordinator does not know this worker id (its data dir
    /// was replaced). Register again.
    #[error("the coordinator does not know this worker: {0}")]
    UnknownWorker(String),
    /// Any other error status, with the coordinator's message.
    #[error("{message} (HTTP {status})")]
    Api {
        status: u16,
        message: String,
        body: ApiError,
    },
    /// An answer that does not follow the protocol.
    #[error("unexpected answer from the coordinator: {0}")]
    Protocol(String),
}

impl ClientError {
    /// The error an answer with error status `status` and body `body` means: what a worker
    /// gets from a route, or from the farm in its own process (the embedded farm's handover).
    pub fn from_answer(status: u16, body: ApiError) -> Self {
        let message = if body.error.is_empty() {
            StatusCode::from_u16(status)
                .map(|s| s.to_string())
                .unwrap_or_else(|_| format!("HTTP {status}"))
        } else {
            body.error.clone()
        };
        if status == StatusCode::CONFLICT.as_u16() {
            return ClientError::Stale(message);
        }
        ClientError::Api {
            status,
            message,
            body,
        }
    }

    /// Worth retrying after a pause: the network or a server-side (5xx) problem.
    pub fn is_transient(&self) -> bool {
        match self {
            ClientError::Unreachable(_) => true,
            ClientError::Api { status, .. } => *status >= 500,
            _ => false,
        }
    }
}

impl From<reqwest::Error> for ClientError {
    fn from(e: reqwest::Error) -> Self {
        if e.is_decode() {
            ClientError::Protocol(e.to_string())
        } else {
            // Connect, timeout, reset or body errors: all mean "try again".
            let mut msg = e.to_string();
            let mut source = std::error::Error::source(&e);
            while let Some(s) = source {
                msg.push_str(": ");
                msg.push_str(&s.to_string());
                source = s.source();
            }
            ClientError::Unreachable(msg)
        }
    }
}

pub type Result<T, E = ClientError> = std::result::Result<T, E>;

pub use bytes::Bytes;

/// A tile's pixels as the body [`Client::complete`] sends (f32 little-endian, as
/// [`crate::pixels_to_bytes`]): on a little-endian machine the renderer's own buffer, not a
/// copy. A worker sends a tile of 256×256 pixels as 786 KB; a copy into fresh memory cost
/// its page faults and a pass over it, and a retry after a network error another copy.
pub fn pixels_body(pixels: Vec<f32>) -> Bytes {
    little_endian_body(pixels, None)
}

fn little_endian_body(pixels: Vec<f32>, home: Option<TileBuffers>) -> Bytes {
    // Each value's bytes put in little-endian order, in place.
    #[cfg(target_endian = "big")]
    let pixels: Vec<f32> = pixels
        .into_iter()
        .map(|value| f32::from_ne_bytes(value.to_le_bytes()))
        .collect();
    Bytes::from_owner(LittleEndianPixels { pixels, home })
}

/// f32 values already in little-endian byte order, read as bytes; when the last copy of the
/// body is dropped, the buffer goes back to `home` if it has one.
struct LittleEndianPixels {
    pixels: Vec<f32>,
    home: Option<TileBuffers>,
}

impl AsRef<[u8]> for LittleEndianPixels {
    fn as_ref(&self) -> &[u8] {
        bytemuck::cast_slice(&self.pixels)
    }
}

impl Drop for LittleEndianPixels {
    fn drop(&mut self) {
        if let Some(home) = &self.home {
            home.put(std::mem::take(&mut self.pixels));
        }
    }
}

/// Tile buffers a worker renders into again once their pixels are sent (or handed over):
/// a 256×256 tile's 786 KB of fresh memory cost its render threads 192 page faults each
/// time, which on test.scene at 800×600 was about 1% of the render's CPU. Keeps at most
/// [`TileBuffers::KEPT`] buffers; the rest are freed.
#[derive(Clone, Default)]
pub struct TileBuffers(Arc<Mutex<Vec<Vec<f32>>>>);

impl TileBuffers {
    /// Enough for the tiles one worker has in flight (the embedded farm's pull loops share
    /// one pool per worker).
    pub const KEPT: usize = 4;

    /// A buffer to render into (empty when none is kept; its contents are to be overwritten).
    pub fn take(&self) -> Vec<f32> {
        self.0
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .pop()
            .unwrap_or_default()
    }

    fn put(&self, buffer: Vec<f32>) {
        let mut kept = self.0.lock().unwrap_or_else(|p| p.into_inner());
        if kept.len() < Self::KEPT && buffer.capacity() > 0 {
            kept.push(buffer);
        }
    }

    /// [`pixels_body`], with the buffer returned here when the body is dropped.
    pub fn body(&self, pixels: Vec<f32>) -> Bytes {
        little_endian_body(pixels, Some(self.clone()))
    }
}

/// One scene file and the assets it references, ready to submit.
#[derive(Clone, Debug, Default)]
pub struct Submission {
    pub spec: JobSpec,
    /// The scene's file name (reported in scene errors).
    pub scene_file: String,
    pub scene: Vec<u8>,
    /// (path as the scene writes it, content)
    pub assets: Vec<(String, Vec<u8>)>,
}

#[derive(Clone, Debug)]
pub struct Client {
    http: reqwest::Client,
    base: String,
    token: Option<String>,
}

impl Client {
    /// `base` is the coordinator's root URL, such as `http://10.0.0.5:7878`.
    pub fn new(base: &str, token: Option<String>) -> Result<Self> {
        let base = base.trim_end_matches('/').to_string();
        if !(base.starts_with("http://") || base.starts_with("https://")) {
            return Err(ClientError::Protocol(format!(
                "coordinator URL {base:?} must start with http:// or https://"
            )));
        }
        let http = reqwest::Client::builder()
            .connect_timeout(Duration::from_secs(5))
            .tcp_nodelay(true)
            .pool_max_idle_per_host(64)
            .build()
            .map_err(|e| ClientError::Protocol(e.to_string()))?;
        Ok(Self { http, base, token })
    }

    pub fn base_url(&self) -> &str {
        &self.base
    }

    /// A request to `path` under [`API_PREFIX`].
    fn request(&self, method: Method, path: &str) -> RequestBuilder {
        self.request_url(method, format!("{}{API_PREFIX}{path}", self.base))
    }

    fn request_url(&self, method: Method, url: String) -> RequestBuilder {
        let mut req = self
            .http
            .request(method, url)
            .timeout(Duration::from_secs(60));
        if let Some(token) = &self.token {
            req = req.header(header::AUTHORIZATION, format!("Bearer {token}"));
        }
        req
    }

    /// Turns a non-success status into the matching error.
    async fn check(resp: Response) -> Result<Response> {
        let status = resp.status();
        if status.is_success() {
            return Ok(resp);
        }
        let text = resp.text().await.unwrap_or_default();
        let body: ApiError =
            serde_json::from_str(&text).unwrap_or_else(|_| ApiError::new(text.trim()));
        Err(ClientError::from_answer(status.as_u16(), body))
    }

    async fn json<T: DeserializeOwned>(req: RequestBuilder) -> Result<T> {
        let resp = Self::check(req.send().await?).await?;
        let bytes = resp.bytes().await?;
        serde_json::from_slice(&bytes).map_err(|e| ClientError::Protocol(e.to_string()))
    }

    pub async fn healthz(&self) -> Result<()> {
        let req = self.request_url(Method::GET, format!("{}/healthz", self.base));
        Self::check(req.send().await?).await?;
        Ok(())
    }

    /// Registers a worker process under `name` (a label) and returns the id its lease
    /// requests carry.
    pub async fn register(&self, name: &str) -> Result<WorkerIdentity> {
        let body = WorkerRegistration {
            name: name.to_string(),
        };
        Self::json(self.request(Method::POST, "/workers").json(&body)).await
    }

    /// Asks for a tile, waiting up to `wait_ms` on the server for one to turn up.
    pub async fn lease(&self, req: &LeaseRequest) -> Result<Option<Lease>> {
        let resp = self
            .request(Method::POST, "/leases")
            .timeout(Duration::from_millis(req.wait_ms) + Duration::from_secs(30))
            .json(req)
            .send()
            .await?;
        let resp = match Self::check(resp).await {
            Err(ClientError::Api {
                status: 404,
                message,
                ..
            }) => return Err(ClientError::UnknownWorker(message)),
            other => other?,
        };
        if resp.status() == StatusCode::NO_CONTENT {
            return Ok(None);
        }
        let bytes = resp.bytes().await?;
        serde_json::from_slice(&bytes)
            .map(Some)
            .map_err(|e| ClientError::Protocol(e.to_string()))
    }

    pub async fn heartbeat(&self, lease_id: u64) -> Result<LeaseStatus> {
        Self::json(
            self.request(Method::POST, &format!("/leases/{lease_id}/heartbeat"))
                .timeout(Duration::from_secs(10)),
        )
        .await
    }

    /// Posts a finished tile's pixels: [`pixels_body`], or any f32 little-endian bytes (see
    /// [`crate::pixels_to_bytes`]).
    pub async fn complete(
        &self,
        lease_id: u64,
        pixels: impl Into<reqwest::Body>,
    ) -> Result<Completion> {
        Self::json(
            self.request(Method::PUT, &format!("/leases/{lease_id}/pixels"))
                .header(header::CONTENT_TYPE, "application/octet-stream")
                .body(pixels),
        )
        .await
    }

    /// The running sums a pass lease continues (`tracer_core::adaptive::SumImage::to_bytes`
    /// of the tile).
    pub async fn lease_sums(&self, lease_id: u64) -> Result<Vec<u8>> {
        self.bytes(&format!("/leases/{lease_id}/sums")).await
    }

    /// Posts a pass lease's new running sums.
    pub async fn complete_sums(
        &self,
        lease_id: u64,
        sums: impl Into<reqwest::Body>,
    ) -> Result<Completion> {
        Self::json(
            self.request(Method::PUT, &format!("/leases/{lease_id}/sums"))
                .header(header::CONTENT_TYPE, "application/octet-stream")
                .body(sums),
        )
        .await
    }

    /// Every finished pass of a progressive job.
    pub async fn convergence(&self, id: u64) -> Result<crate::Convergence> {
        Self::json(self.request(Method::GET, &format!("/jobs/{id}/convergence"))).await
    }

    /// The sample-count map of a progressive job, as PNG.
    pub async fn samples_png(&self, id: u64) -> Result<Vec<u8>> {
        self.bytes(&format!("/jobs/{id}/samples.png")).await
    }

    pub async fn fail(&self, lease_id: u64, report: &FailureReport) -> Result<JobInfo> {
        Self::json(
            self.request(Method::POST, &format!("/leases/{lease_id}/failure"))
                .json(report),
        )
        .await
    }

    /// Gives a tile back unfinished (the worker is stopping); it is requeued at once.
    pub async fn hand_back(&self, lease_id: u64) -> Result<()> {
        let req = self
            .request(Method::DELETE, &format!("/leases/{lease_id}"))
            .timeout(Duration::from_secs(5));
        Self::check(req.send().await?).await?;
        Ok(())
    }

    pub async fn bundle(&self, job_id: u64) -> Result<Bundle> {
        Self::json(self.request(Method::GET, &format!("/jobs/{job_id}/bundle"))).await
    }

    pub async fn blob(&self, hash: &str) -> Result<Vec<u8>> {
        let resp = self
            .request(Method::GET, &format!("/blobs/{hash}"))
            .send()
            .await?;
        Ok(Self::check(resp).await?.bytes().await?.to_vec())
    }

    /// Those of `hashes` whose content the coordinator does not hold.
    pub async fn missing_blobs(&self, hashes: &[String]) -> Result<Vec<String>> {
        Self::json(self.request(Method::POST, "/blobs/missing").json(hashes)).await
    }

    /// Submits a job. Assets the coordinator already holds are sent as references to their
    /// hash instead of their bytes.
    pub async fn submit(&self, sub: &Submission) -> Result<JobInfo> {
        let hashes: Vec<String> = sub
            .assets
            .iter()
            .map(|(_, bytes)| crate::hash_hex(bytes))
            .collect();
        let missing = if hashes.is_empty() {
            Vec::new()
        } else {
            self.missing_blobs(&hashes).await?
        };
        let spec =
            serde_json::to_vec(&sub.spec).map_err(|e| ClientError::Protocol(e.to_string()))?;
        // Part names are asset paths, sent as written (the default encoding mangles '/').
        let mut form = reqwest::multipart::Form::new()
            .percent_encode_noop()
            .part(
                PART_JOB,
                reqwest::multipart::Part::bytes(spec).mime_str("application/json")?,
            )
            .part(
                PART_SCENE,
                reqwest::multipart::Part::bytes(sub.scene.clone())
                    .file_name(sub.scene_file.clone()),
            );
        for ((path, bytes), hash) in sub.assets.iter().zip(hashes) {
            let part = if missing.contains(&hash) {
                reqwest::multipart::Part::bytes(bytes.clone()).file_name(path.clone())
            } else {
                reqwest::multipart::Part::bytes(hash.into_bytes())
                    .file_name(path.clone())
                    .mime_str(CONTENT_TYPE_BLOB_REF)?
            };
            form = form.part(path.clone(), part);
        }
        Self::json(self.request(Method::POST, "/jobs").multipart(form)).await
    }

    pub async fn job(&self, id: u64) -> Result<JobInfo> {
        Self::json(self.request(Method::GET, &format!("/jobs/{id}"))).await
    }

    pub async fn jobs(&self) -> Result<Vec<JobInfo>> {
        Self::json(self.request(Method::GET, "/jobs")).await
    }

    /// One page of a job's tile map: `limit` tiles from index `offset`.
    pub async fn tiles(&self, id: u64, offset: u32, limit: u32) -> Result<TilePage> {
        Self::json(self.request(
            Method::GET,
            &format!("/jobs/{id}/tiles?offset={offset}&limit={limit}"),
        ))
        .await
    }

    pub async fn cancel(&self, id: u64) -> Result<JobInfo> {
        Self::json(self.request(Method::DELETE, &format!("/jobs/{id}"))).await
    }

    /// Requeues a failed job's failed tiles (409 when the job has not failed).
    pub async fn retry(&self, id: u64) -> Result<JobInfo> {
        Self::json(self.request(Method::POST, &format!("/jobs/{id}/retry"))).await
    }

    /// Every worker the coordinator knows, by name then id.
    pub async fn workers(&self) -> Result<Vec<WorkerInfo>> {
        Self::json(self.request(Method::GET, "/workers")).await
    }

    /// The job's PNG (its first frame): final when it is done, partial while it runs.
    pub async fn image(&self, id: u64) -> Result<Vec<u8>> {
        self.bytes(&format!("/jobs/{id}/image")).await
    }

    /// One frame of a frame-range job, final or partial like [`Client::image`].
    pub async fn frame_image(&self, id: u64, frame: u32) -> Result<Vec<u8>> {
        self.bytes(&format!("/jobs/{id}/image?frame={frame}")).await
    }

    /// One frame of the job (its first when `frame` is None) in `format`: PNG, or the
    /// linear f32 pixels as EXR or PFM; final or partial like [`Client::image`].
    pub async fn image_in(
        &self,
        id: u64,
        frame: Option<u32>,
        format: tracer_core::ImageFormat,
    ) -> Result<Vec<u8>> {
        let frame = frame.map(|f| format!("&frame={f}")).unwrap_or_default();
        let format = format.extension();
        self.bytes(&format!("/jobs/{id}/image?format={format}{frame}"))
            .await
    }

    async fn bytes(&self, path: &str) -> Result<Vec<u8>> {
        let resp = self.request(Method::GET, path).send().await?;
        Ok(Self::check(resp).await?.bytes().await?.to_vec())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_pixel_body_is_the_wire_format() {
        let pixels = vec![0.0, 1.5, -2.25, f32::MAX, 1e-30, 0.1];
        let body = pixels_body(pixels.clone());
        assert_eq!(&body[..], &crate::pixels_to_bytes(&pixels)[..]);
        let rect = tracer_core::TileRect::new(0, 0, 2, 1);
        assert_eq!(crate::pixels_from_bytes(&body, rect).unwrap(), pixels);
    }

    #[test]
    fn a_tile_buffer_comes_back_when_the_last_copy_of_its_body_is_dropped() {
        let buffers = TileBuffers::default();
        assert!(buffers.take().is_empty(), "nothing kept at first");
        let pixels = vec![0.5f32; 3 * 64];
        let address = pixels.as_ptr();
        let body = buffers.body(pixels);
        assert_eq!(&body[..], &crate::pixels_to_bytes(&[0.5; 3 * 64])[..]);
        let retry = body.clone();
        drop(body);
        assert!(buffers.take().is_empty(), "a copy is still being sent");
        drop(retry);
        let back = buffers.take();
        assert_eq!((back.as_ptr(), back.capacity()), (address, 3 * 64));
        // Only so many are kept.
        let bodies: Vec<_> = (0..TileBuffers::KEPT + 2)
            .map(|_| buffers.body(vec![0.0; 3]))
            .collect();
        drop(bodies);
        let kept = std::iter::from_fn(|| Some(buffers.take()))
            .take_while(|b| b.capacity() > 0)
            .count();
        assert_eq!(kept, TileBuffers::KEPT);
    }
}
