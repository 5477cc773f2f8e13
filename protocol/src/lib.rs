//! The farm's wire protocol, shared by the coordinator, the worker and every client:
//!
//! - the JSON bodies of every route (this file);
//! - [`routes`]: every route with the status codes it answers — the coordinator builds its
//!   router from this table, so a route cannot exist without an entry here;
//! - the tile pixel wire format ([`pixels_to_bytes`], [`pixels_from_bytes`]), which is also the
//!   coordinator's tile file format;
//! - content hashes ([`hash_hex`]) that address scenes and assets;
//! - with the `client` feature, [`client`]: a typed HTTP client;
//! - with the `openapi` feature, [`openapi`]: the API as an OpenAPI 3.1 document, generated
//!   from the route table and these types.
//!
//! `docs/api.md` is the prose version. The crate compiles neither axum nor SQLite, so a worker
//! links only what it needs.

#[cfg(feature = "client")]
pub mod client;
#[cfg(feature = "openapi")]
pub mod openapi;
pub mod routes;

use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use tracer_core::{FrameRange, ImageFormat, RenderSettings, TileRect};

/// Lower-case hex SHA-256: the content address of scene files and assets.
pub fn hash_hex(bytes: &[u8]) -> String {
    let digest = Sha256::digest(bytes);
    let mut out = String::with_capacity(64);
    for b in digest {
        out.push_str(&format!("{b:02x}"));
    }
    out
}

/// Every JSON route sits under this prefix.
pub const API_PREFIX: &str = "/api/v1";

/// The default tile edge in pixels.
pub const DEFAULT_TILE_SIZE: u32 = 64;

/// Multipart part names of a job submission. Every other part is an asset, named by the path
/// the scene file writes.
pub const PART_JOB: &str = "job";
pub const PART_SCENE: &str = "scene";
/// An asset part with this content type carries only the hex hash of content the coordinator
/// already holds (see `POST /blobs/missing`), so an unchanged asset is never uploaded twice.
pub const CONTENT_TYPE_BLOB_REF: &str = "application/vnd.tessera.blob-ref";

/// What a job renders besides its scene: the JSON of the `job` part.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct JobSpec {
    /// A label for listings; defaults to the scene's file name.
    pub name: Option<String>,
    pub render: RenderSettings,
    /// Render these frames of an animated scene as one job (`render.frame` is then ignored):
    /// every frame is split into tiles, and each frame's PNG is assembled on its own.
    pub frames: Option<FrameRange>,
    /// Tiles are at most `tile_size`×`tile_size` pixels.
    pub tile_size: u32,
    /// Render in passes until the stopping rules say the image is good enough (one frame
    /// only). Left out of the JSON when absent, so other jobs serialise as before.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub adaptive: Option<AdaptiveSpec>,
}

/// The stopping rules of a progressive job (`"adaptive": {...}` in a [`JobSpec`]). The job
/// renders in passes over the samples of `spp_max` (which replaces `render.spp`); each 8×8
/// block of pixels stops once it has `spp_min` samples and its estimated relative error is at
/// most `noise_threshold`, or when it reaches `spp_max`; the job ends when every block has
/// stopped or `time_limit_s` has passed (with the image of the last finished pass).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AdaptiveSpec {
    /// Relative error of a block's mean at which it stops; 0 never stops a block early.
    pub noise_threshold: f64,
    /// Samples every pixel gets (the first pass), at least 2: the error needs two halves.
    pub spp_min: u32,
    /// Samples no pixel goes beyond.
    pub spp_max: u32,
    /// Seconds after the first lease at which the job ends with its last finished pass
    /// (the first pass always finishes).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub time_limit_s: Option<f64>,
}

impl Default for AdaptiveSpec {
    fn default() -> Self {
        Self {
            noise_threshold: 0.01,
            spp_min: 4,
            spp_max: 256,
            time_limit_s: None,
        }
    }
}

/// The largest `spp_max` a progressive job may ask for.
pub const MAX_ADAPTIVE_SPP: u32 = 1 << 16;

impl AdaptiveSpec {
    /// Rules no progressive render can follow.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.noise_threshold.is_finite() && self.noise_threshold >= 0.0) {
            return Err(format!(
                "noise_threshold {} must be a finite number >= 0",
                self.noise_threshold
            ));
        }
        if self.spp_min < 2 {
            return Err(format!(
                "spp_min {} must be at least 2 (the error estimate compares two halves)",
                self.spp_min
            ));
        }
        if self.spp_max < self.spp_min || self.spp_max > MAX_ADAPTIVE_SPP {
            return Err(format!(
                "spp_max {} must lie between spp_min {} and {MAX_ADAPTIVE_SPP}",
                self.spp_max, self.spp_min
            ));
        }
        if let Some(t) = self.time_limit_s {
            if !(t.is_finite() && t > 0.0) {
                return Err(format!("time_limit_s {t} must be a positive number"));
            }
        }
        Ok(())
    }
}

impl JobSpec {
    /// The frames the job renders, in order.
    pub fn frame_list(&self) -> Vec<u32> {
        match self.frames {
            Some(range) => range.frames().collect(),
            None => vec![self.render.frame],
        }
    }
}

impl Default for JobSpec {
    fn default() -> Self {
        Self {
            name: None,
            render: RenderSettings::default(),
            frames: None,
            tile_size: DEFAULT_TILE_SIZE,
            adaptive: None,
        }
    }
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum JobState {
    /// No tile has been leased yet.
    Queued,
    Running,
    Done,
    Failed,
    Cancelled,
}

impl JobState {
    pub fn is_finished(self) -> bool {
        matches!(
            self,
            JobState::Done | JobState::Failed | JobState::Cancelled
        )
    }

    pub fn as_str(self) -> &'static str {
        match self {
            JobState::Queued => "queued",
            JobState::Running => "running",
            JobState::Done => "done",
            JobState::Failed => "failed",
            JobState::Cancelled => "cancelled",
        }
    }

    pub fn parse(s: &str) -> Option<JobState> {
        [
            JobState::Queued,
            JobState::Running,
            JobState::Done,
            JobState::Failed,
            JobState::Cancelled,
        ]
        .into_iter()
        .find(|state| state.as_str() == s)
    }
}

/// One tile's failure on one worker.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileFailure {
    pub tile: u32,
    /// The worker's name (a label: two workers may share one).
    pub worker: String,
    /// The worker's coordinator-issued id (0 for failures stored before ids existed).
    #[serde(default)]
    pub worker_id: u64,
    pub error: String,
}

/// A job's progress, as `GET /jobs/{id}` reports it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobInfo {
    pub id: u64,
    pub name: String,
    pub scene_file: String,
    pub state: JobState,
    pub spec: JobSpec,
    pub tiles_total: u32,
    pub tiles_done: u32,
    /// Tiles some worker holds a lease on right now.
    pub tiles_running: u32,
    /// Seconds since the first tile was leased (until the job finished).
    pub elapsed_s: Option<f64>,
    /// Remaining seconds at the rate tiles have finished so far.
    pub eta_s: Option<f64>,
    /// Why the job failed, when it did.
    pub error: Option<String>,
    /// Every tile failure so far, oldest first.
    pub failures: Vec<TileFailure>,
    /// Unix milliseconds.
    pub created_ms: u64,
    /// Mean samples per pixel of the image so far (the job's spp for a one-shot job once
    /// it is done).
    #[serde(default)]
    pub spp_mean: Option<f64>,
    /// Progressive jobs: passes finished so far.
    #[serde(default)]
    pub passes: Option<u32>,
    /// Progressive jobs: the estimated relative error of the image after the last pass.
    #[serde(default)]
    pub error_estimate: Option<f64>,
}

/// One finished pass of a progressive job.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct PassInfo {
    /// Counted from 0.
    pub pass: u32,
    /// Seconds from the job's first lease to the end of the pass.
    pub wall_s: f64,
    /// Mean samples per pixel after the pass.
    pub spp_mean: f64,
    /// The image's estimated relative error after the pass.
    pub error: f64,
    /// 8×8 blocks still sampling after the pass.
    pub active_blocks: u32,
}

/// `GET /jobs/{id}/convergence`: every finished pass, oldest first (empty for a one-shot job).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Convergence {
    pub job_id: u64,
    pub passes: Vec<PassInfo>,
}

/// A tile's state on a job's tile map.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TileState {
    /// Waiting for a worker.
    Queued,
    /// Some worker holds a lease on it (two while a straggler copy runs).
    Leased,
    Done,
    /// It failed at least once and is not leased now: it waits for a retry, or failed its job.
    Failed,
    /// Not done and never will be: its job was cancelled or failed.
    Idle,
}

/// `GET /jobs/{id}/tiles` answers at most this many tiles per request.
pub const MAX_TILE_PAGE: u32 = 4096;

/// One page of a job's tile map, `GET /jobs/{id}/tiles?offset=&limit=`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TilePage {
    /// Every tile of the job (all frames), so a reader knows when it has seen them all.
    pub tiles_total: u32,
    /// The index of the first tile in `tiles`.
    pub offset: u32,
    /// Tiles `offset`, `offset + 1`, … in index order; at most the requested `limit` and at
    /// most [`MAX_TILE_PAGE`].
    pub tiles: Vec<TileInfo>,
}

/// One tile of a job, as `GET /jobs/{id}/tiles` and the `tile` event report it.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileInfo {
    pub job_id: u64,
    pub tile: u32,
    /// The frame the tile belongs to (0 for a still).
    pub frame: u32,
    pub rect: TileRect,
    pub state: TileState,
    /// The workers holding a lease on it right now.
    pub workers: Vec<String>,
    /// Failed attempts so far.
    pub attempts: u32,
}

/// Where a job's camera stands: its override, or the scene's own camera. The look-at point
/// of a scene camera is the point of its view axis nearest the origin (at least one unit
/// ahead), the pivot a viewer orbits around.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct JobCamera {
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    pub up: [f64; 3],
    /// Vertical field of view in degrees (always the scene's).
    pub fov_deg: f64,
    /// True when the job renders the scene's camera, not an override.
    pub from_scene: bool,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum WorkerState {
    /// Seen recently, holding no lease.
    Idle,
    Rendering,
    /// Its last lease lapsed without a heartbeat, or it has not been heard from for longer
    /// than a long poll plus a lease timeout.
    Lost,
}

/// The lease a worker holds.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkerLease {
    pub job_id: u64,
    pub tile: u32,
}

/// One worker as the coordinator knows it (since the coordinator started).
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct WorkerInfo {
    /// The id the coordinator issued when the worker registered.
    pub id: u64,
    /// The worker's label, as it registered (not necessarily unique).
    pub name: String,
    /// The address its last lease request came from.
    pub address: Option<String>,
    pub state: WorkerState,
    pub lease: Option<WorkerLease>,
    /// Tiles it finished (first result) since the coordinator started.
    pub tiles_done: u64,
    /// Unix milliseconds of its last lease request or heartbeat.
    pub last_seen_ms: u64,
}

/// `GET /events` event names. Each `data` is JSON: a [`JobInfo`] (a job was submitted or
/// changed), a [`TileInfo`] (a tile changed state), every [`WorkerInfo`] (after tile changes and every two seconds),
/// or `null` (events were dropped for a slow reader: fetch everything again).
pub const EVENT_JOB: &str = "job";
pub const EVENT_TILE: &str = "tile";
pub const EVENT_WORKERS: &str = "workers";
pub const EVENT_RESYNC: &str = "resync";

/// `POST /workers`: a worker process introduces itself before asking for tiles.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct WorkerRegistration {
    /// A label for listings and logs (1 to [`MAX_WORKER_NAME`] bytes); it need not be unique.
    pub name: String,
}

/// The longest worker name the coordinator accepts, in bytes.
pub const MAX_WORKER_NAME: usize = 200;

/// The answer to a registration: the identity every lease request carries.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct WorkerIdentity {
    /// Issued by the coordinator and never issued twice, so two processes sharing a name
    /// are still two workers.
    pub worker_id: u64,
    pub name: String,
}

/// `POST /leases`: ask for a tile. Asking again while holding a lease answers the same lease.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LeaseRequest {
    /// The id from `POST /workers`: leases, failures and metrics are keyed by it.
    pub worker_id: u64,
    /// How long the coordinator may hold the request open waiting for work (long poll);
    /// capped by the coordinator.
    #[serde(default)]
    pub wait_ms: u64,
}

/// A tile assignment. Every later message about it carries `lease_id`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Lease {
    pub lease_id: u64,
    pub job_id: u64,
    pub tile: u32,
    pub rect: TileRect,
    pub settings: RenderSettings,
    /// The lease lapses this long after it was granted or last extended.
    pub expires_in_ms: u64,
    /// How often the worker should heartbeat (well inside `expires_in_ms`).
    pub heartbeat_ms: u64,
    /// A pass of a progressive job: the worker continues the tile's running sums
    /// (`GET /leases/{id}/sums`) and answers with `PUT /leases/{id}/sums` instead of pixels.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pass: Option<PassLease>,
}

/// What one pass of a progressive job asks of a tile.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PassLease {
    pub pass: u32,
    /// Sample indices `samples_from..samples_to` in the progressive order over `settings.spp`
    /// strata; the sums so far hold samples `0..samples_from`. With `block_samples`, the
    /// smallest start and largest end of its ranges.
    pub samples_from: u32,
    pub samples_to: u32,
    /// The 8×8 blocks of the image (`tracer_core::adaptive::block_of` indices) of this tile
    /// that still sample, ascending; pixels of the others keep their sums.
    pub active_blocks: Vec<u32>,
    /// Each active block's own sample range `[from, to)` (same order as `active_blocks`):
    /// blocks of one pass may sample different ranges. Empty: every active block samples
    /// `samples_from..samples_to`.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub block_samples: Vec<[u32; 2]>,
}

impl PassLease {
    /// The sample range of block `block` in this pass (empty for a block that does not
    /// sample).
    pub fn block_range(&self, block: u32) -> std::ops::Range<u32> {
        match self.active_blocks.binary_search(&block) {
            Ok(i) => match self.block_samples.get(i) {
                Some(&[from, to]) => from..to,
                None => self.samples_from..self.samples_to,
            },
            Err(_) => 0..0,
        }
    }
}

/// The answer to a heartbeat: the lease's new expiry.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct LeaseStatus {
    pub expires_in_ms: u64,
}

/// The answer to a tile's accepted pixels: the job's progress. (A result for a tile that
/// another worker finished first gets 409 like any stale lease: the first result wins.)
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Completion {
    pub tiles_done: u32,
    pub tiles_total: u32,
}

/// `POST /leases/{id}/failure`.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FailureReport {
    pub error: String,
    /// The scene itself could not be loaded: no other worker will do better, so the job fails
    /// at once instead of after three workers.
    #[serde(default)]
    pub scene: bool,
}

/// What a worker needs to load a job's scene: every file by content hash.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Bundle {
    pub job_id: u64,
    pub scene_file: String,
    pub scene_hash: String,
    pub assets: Vec<BundleFile>,
}

#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct BundleFile {
    /// The path exactly as the scene writes it.
    pub path: String,
    /// Lower-case hex SHA-256 of the content.
    pub hash: String,
    pub size: u64,
}

/// Every 4xx/5xx JSON body. Scene errors carry their location.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ApiError {
    pub error: String,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub file: Option<String>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub line: Option<u32>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub column: Option<u32>,
}

impl ApiError {
    pub fn new(error: impl Into<String>) -> Self {
        Self {
            error: error.into(),
            ..Self::default()
        }
    }
}

/// The `Content-Type` of a job image served as `format` (`GET /jobs/{id}/image?format=`).
/// EXR's is the one OpenEXR registers informally; PFM has none, so it is named likewise.
pub fn image_media_type(format: ImageFormat) -> &'static str {
    match format {
        ImageFormat::Png => "image/png",
        ImageFormat::Exr => "image/x-exr",
        ImageFormat::Pfm => "image/x-portable-floatmap",
    }
}

/// Encodes a tile's linear pixels for `PUT /leases/{id}/pixels`: f32 little-endian, r g b per
/// pixel, top row first.
pub fn pixels_to_bytes(pixels: &[f32]) -> Vec<u8> {
    let mut out = Vec::with_capacity(pixels.len() * 4);
    for p in pixels {
        out.extend_from_slice(&p.to_le_bytes());
    }
    out
}

/// Decodes [`pixels_to_bytes`], checking the size against a `width`×`height` tile.
pub fn pixels_from_bytes(bytes: &[u8], rect: TileRect) -> Result<Vec<f32>, String> {
    let expected = rect.pixel_count() * 3 * 4;
    if bytes.len() != expected {
        return Err(format!(
            "a {}x{} tile is {expected} bytes of f32 RGB, got {}",
            rect.width,
            rect.height,
            bytes.len()
        ));
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

/// Checks a path a scene uses for an asset: relative, `/`-separated, with no `..`, `.` or empty
/// components, so it can never name anything outside the bundle.
pub fn check_bundle_path(path: &str) -> Result<(), String> {
    if path.is_empty() {
        return Err("an asset path is empty".into());
    }
    if path.starts_with('/') || path.starts_with('\\') || path.contains(':') {
        return Err(format!(
            "asset path {path:?} is absolute; bundle paths must be relative"
        ));
    }
    if path.contains('\\') || path.contains('\0') {
        return Err(format!("asset path {path:?} must use '/' separators"));
    }
    for part in path.split('/') {
        match part {
            ".." => return Err(format!("asset path {path:?} leaves the bundle ('..')")),
            "" | "." => return Err(format!("asset path {path:?} has an empty or '.' component")),
            _ => {}
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pixels_round_trip_and_sizes_are_checked() {
        let rect = TileRect::new(0, 0, 2, 1);
        let px = vec![0.0, 0.5, 1.0, f32::MAX, -0.0, 1e-30];
        let bytes = pixels_to_bytes(&px);
        assert_eq!(bytes.len(), 24);
        let back = pixels_from_bytes(&bytes, rect).unwrap();
        assert_eq!(
            back.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
            px.iter().map(|v| v.to_bits()).collect::<Vec<_>>()
        );
        let err = pixels_from_bytes(&bytes[..20], rect).unwrap_err();
        assert!(err.contains("24 bytes"), "{err}");
    }

    #[test]
    fn bundle_paths_stay_inside_the_bundle() {
        for ok in ["images/a.png", "a.obj", "models/x/y.obj", "..a/b"] {
            assert!(check_bundle_path(ok).is_ok(), "{ok}");
        }
        for bad in [
            "/etc/passwd",
            "../x.png",
            "images/../../x",
            "a//b",
            "./a",
            "",
            "C:/x",
            "a\\b",
        ] {
            assert!(check_bundle_path(bad).is_err(), "{bad}");
        }
    }

    #[test]
    fn job_spec_defaults_and_rejects_unknown_fields() {
        let spec: JobSpec = serde_json::from_str(r#"{"render": {"width": 16}}"#).unwrap();
        assert_eq!(spec.tile_size, DEFAULT_TILE_SIZE);
        assert_eq!(spec.render.width, 16);
        assert_eq!(spec.render.height, 600);
        assert!(serde_json::from_str::<JobSpec>(r#"{"tile": 3}"#).is_err());
    }

    #[test]
    fn job_states_round_trip_through_their_names() {
        for s in ["queued", "running", "done", "failed", "cancelled"] {
            assert_eq!(JobState::parse(s).unwrap().as_str(), s);
        }
        assert_eq!(JobState::parse("nope"), None);
    }
}
