//! `/jobs`: submit (multipart, validated with tracer-core before it is accepted), list, show,
//! cancel, retry, image (one frame, or every frame as a tar) and bundle.

use std::collections::HashMap;

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::Duration;

use axum::body::{Body, Bytes};
use axum::extract::rejection::QueryRejection;
use axum::extract::{FromRequest, Multipart, Path, Query, Request, State};
use axum::http::{header, StatusCode};
use axum::response::{IntoResponse, Response};
use axum::Json;
use futures_util::StreamExt;
use protocol::{
    check_bundle_path, ApiError, Bundle, BundleFile, JobCamera, JobInfo, JobSpec, TilePage,
    CONTENT_TYPE_BLOB_REF, MAX_TILE_PAGE, PART_JOB, PART_SCENE,
};
use serde::Deserialize;
use tracer_core::scene::SceneDescription;
use tracer_core::{ImageFormat, MemoryAssets, Scene, SceneError};

use super::{blocking, parse_id, parse_json, ApiResult, AppState, Failure};
use crate::farm::{Farm, NewJob};

/// An asset part: its bytes, or a reference to content the coordinator already holds.
enum AssetPart {
    Bytes(Vec<u8>),
    Blob(String),
}

/// The `coordinator serve` flag that sets a scene budget named by [`SceneError::limit`].
fn limit_flag(limit: &str) -> &'static str {
    match limit {
        "max_texture_pixels" => "--max-texture-pixels",
        "max_primitives" => "--max-scene-primitives",
        _ => "a coordinator flag",
    }
}

fn scene_error(e: &SceneError) -> Failure {
    let error = match e.limit() {
        Some(limit) => format!("{e} (set by {} on this coordinator)", limit_flag(limit)),
        None => e.to_string(),
    };
    Failure(
        StatusCode::BAD_REQUEST,
        ApiError {
            error,
            file: Some(e.file.clone()),
            line: Some(e.line),
            column: Some(e.column),
        },
    )
}

fn multipart_error(e: axum::extract::multipart::MultipartError, limit: usize) -> Failure {
    let status = e.status();
    if status == StatusCode::PAYLOAD_TOO_LARGE {
        return Failure(
            status,
            ApiError::new(format!("the upload exceeds the limit of {limit} bytes")),
        );
    }
    Failure(
        status,
        ApiError::new(format!("malformed multipart body: {}", e.body_text())),
    )
}

/// The scene file's name as reported in errors: the last component of the part's file name.
fn scene_file_name(raw: Option<&str>) -> String {
    raw.and_then(|n| n.rsplit(['/', '\\']).next())
        .filter(|n| !n.is_empty() && n.len() <= 200)
        .unwrap_or("scene.scene")
        .to_string()
}

/// What the body pump saw that the multipart parser's error cannot say.
#[derive(Default)]
struct UploadState {
    too_large: AtomicBool,
    stalled: AtomicBool,
}

/// Feeds the request body to the multipart parser up to the upload limit, and keeps reading
/// (discarding) past it, or after the handler stopped reading, up to a hard cap. A client
/// still sending its body when the error answer goes out would otherwise see its connection
/// reset instead of the 4xx. A body that sends nothing for `stall` is abandoned, so a client
/// cannot hold a scene-build turn by pausing its upload.
fn pump_body(body: Body, limit: usize, stall: Duration, state: Arc<UploadState>) -> Body {
    let hard_cap = limit.saturating_mul(2).max(limit.saturating_add(64 << 20));
    let (tx, rx) = tokio::sync::mpsc::channel::<Result<Bytes, std::io::Error>>(8);
    tokio::spawn(async move {
        let mut stream = body.into_data_stream();
        let (mut seen, mut forwarding) = (0usize, true);
        loop {
            let chunk = match tokio::time::timeout(stall, stream.next()).await {
                Ok(Some(Ok(chunk))) => chunk,
                Ok(_) => break,
                Err(_) => {
                    if forwarding {
                        state.stalled.store(true, Ordering::SeqCst);
                        let err = std::io::Error::other("the upload stalled");
                        let _ = tx.send(Err(err)).await;
                    }
                    break;
                }
            };
            seen += chunk.len();
            if forwarding && seen > limit {
                state.too_large.store(true, Ordering::SeqCst);
                let err = std::io::Error::other("the upload exceeds the limit");
                let _ = tx.send(Err(err)).await;
                forwarding = false;
            } else if forwarding && tx.send(Ok(chunk)).await.is_err() {
                forwarding = false;
            }
            if seen > hard_cap {
                break;
            }
        }
    });
    Body::from_stream(futures_util::stream::unfold(rx, |mut rx| async move {
        rx.recv().await.map(|item| (item, rx))
    }))
}

pub async fn submit(State(app): AppState, req: Request) -> Response {
    let farm = app.farm.clone();
    let limit = farm.config().limits.max_upload_bytes;
    let stall = farm.config().connections.idle_timeout;
    // The upload is read, and the scene built, in turn with the other heavy requests.
    let _turn = app.scene_turn().await;
    let upload = Arc::new(UploadState::default());
    let (parts, body) = req.into_parts();
    let req = Request::from_parts(parts, pump_body(body, limit, stall, upload.clone()));
    let result = match Multipart::from_request(req, &()).await {
        Ok(multipart) => submit_inner(&app, multipart).await,
        Err(rejection) => Err(Failure(
            rejection.status(),
            ApiError::new(rejection.body_text()),
        )),
    };
    let result = result.map_err(|failure| {
        if upload.too_large.load(Ordering::SeqCst) {
            Failure(
                StatusCode::PAYLOAD_TOO_LARGE,
                ApiError::new(format!("the upload exceeds the limit of {limit} bytes")),
            )
        } else if upload.stalled.load(Ordering::SeqCst) {
            Failure(
                StatusCode::REQUEST_TIMEOUT,
                ApiError::new(format!(
                    "the upload sent nothing for {}s (the idle timeout); abandoned",
                    stall.as_secs_f64()
                )),
            )
        } else {
            failure
        }
    });
    match counted_submission(&farm, result) {
        Ok(info) => (StatusCode::CREATED, Json(info)).into_response(),
        Err(failure) => failure.into_response(),
    }
}

/// Counts a submission's outcome in the farm's metrics (and logs a refusal), for the route
/// and the in-process submission alike.
fn counted_submission(farm: &Farm, result: ApiResult<JobInfo>) -> ApiResult<JobInfo> {
    match &result {
        Ok(_) => farm.metrics.jobs_submitted.fetch_add(1, Ordering::Relaxed),
        Err(failure) => {
            tracing::info!("submission refused ({}): {}", failure.0, failure.1.error);
            farm.metrics
                .submissions_rejected
                .fetch_add(1, Ordering::Relaxed)
        }
    };
    result
}

async fn submit_inner(app: &super::App, mut multipart: Multipart) -> ApiResult<JobInfo> {
    let limit = app.farm.config().limits.max_upload_bytes;
    let mut spec: Option<JobSpec> = None;
    let mut scene: Option<(String, Vec<u8>)> = None;
    let mut parts: HashMap<String, AssetPart> = HashMap::new();
    // The first problem is reported once the whole body has been read.
    let mut problem: Option<Failure> = None;
    while let Some(field) = multipart
        .next_field()
        .await
        .map_err(|e| multipart_error(e, limit))?
    {
        let name = field.name().unwrap_or_default().to_string();
        let file_name = field.file_name().map(str::to_string);
        let is_ref = field.content_type() == Some(CONTENT_TYPE_BLOB_REF);
        let bytes = field.bytes().await.map_err(|e| multipart_error(e, limit))?;
        if problem.is_some() {
            continue;
        }
        tracing::debug!("submission part {name:?} ({file_name:?})");
        let outcome = match name.as_str() {
            PART_JOB if spec.is_none() => parse_json(&bytes).map(|s| spec = Some(s)),
            PART_SCENE if scene.is_none() => {
                scene = Some((scene_file_name(file_name.as_deref()), bytes.to_vec()));
                Ok(())
            }
            PART_JOB | PART_SCENE => Err(Failure::bad_request(format!(
                "the {name:?} part appears twice"
            ))),
            _ => check_bundle_path(&name)
                .map_err(Failure::bad_request)
                .and_then(|()| {
                    let part = if is_ref {
                        AssetPart::Blob(String::from_utf8_lossy(&bytes).trim().to_string())
                    } else {
                        AssetPart::Bytes(bytes.to_vec())
                    };
                    match parts.insert(name.clone(), part) {
                        Some(_) => Err(Failure::bad_request(format!(
                            "asset {name:?} appears twice"
                        ))),
                        None => Ok(()),
                    }
                }),
        };
        if let Err(failure) = outcome {
            problem = Some(failure);
        }
    }
    if let Some(failure) = problem {
        return Err(failure);
    }
    accept_submission(&app.farm, spec.unwrap_or_default(), scene, parts).await
}

/// Submits a job in this process, as `POST /jobs` would with the same parts (every asset sent
/// as bytes): the embedded farm's own submissions, which then skip hashing the assets to ask
/// which the farm holds, the multipart upload and its copies (on dragon.scene about 7 ms of
/// the farm's start). Refused with the route's status and message. Nothing is uploaded, so
/// `max_upload_bytes` does not apply: the bytes are already in this process, the user's own
/// (the embedded farm lifts the scene budgets for the same reason).
pub(crate) async fn submit_in_process(
    farm: &Arc<Farm>,
    submission: protocol::client::Submission,
) -> ApiResult<JobInfo> {
    let scene = Some((submission.scene_file, submission.scene));
    let result = match asset_parts(submission.assets) {
        Ok(parts) => accept_submission(farm, submission.spec, scene, parts).await,
        Err(failure) => Err(failure),
    };
    counted_submission(farm, result)
}

/// An in-process submission's assets as parts, refused as the route refuses their parts.
fn asset_parts(assets: Vec<(String, Vec<u8>)>) -> ApiResult<HashMap<String, AssetPart>> {
    let mut parts = HashMap::new();
    for (path, bytes) in assets {
        check_bundle_path(&path).map_err(Failure::bad_request)?;
        if parts
            .insert(path.clone(), AssetPart::Bytes(bytes))
            .is_some()
        {
            return Err(Failure::bad_request(format!(
                "asset {path:?} appears twice"
            )));
        }
    }
    Ok(parts)
}

/// The checks and storage a submission's parts go through once read: the job's budgets, the
/// scene parsed and built within the coordinator's limits from exactly the assets it
/// references, the blobs stored and the job queued.
async fn accept_submission(
    farm: &Arc<Farm>,
    spec: JobSpec,
    scene: Option<(String, Vec<u8>)>,
    mut parts: HashMap<String, AssetPart>,
) -> ApiResult<JobInfo> {
    farm.config()
        .limits
        .check(&spec)
        .map_err(Failure::bad_request)?;
    let (scene_file, scene_bytes) = scene.ok_or_else(|| {
        Failure::bad_request("the submission has no \"scene\" part with the scene file")
    })?;
    let text = String::from_utf8(scene_bytes)
        .map_err(|_| Failure::bad_request(format!("{scene_file} is not UTF-8 text")))?;

    let farm = farm.clone();
    blocking(move || {
        let load_limits = farm.config().limits.load_limits();
        let desc = SceneDescription::parse_with_limits(&text, &scene_file, &load_limits)
            .map_err(|e| scene_error(&e))?;
        // Only what the scene uses becomes part of the job; everything it uses must be here.
        let mut assets = MemoryAssets {
            files: HashMap::new(),
        };
        for path in desc.referenced_assets() {
            check_bundle_path(&path)
                .map_err(|e| Failure::bad_request(format!("{scene_file} references {e}")))?;
            let bytes = match parts.remove(&path) {
                Some(AssetPart::Bytes(bytes)) => bytes,
                Some(AssetPart::Blob(hash)) => farm.files().blob(&hash)?.ok_or_else(|| {
                    Failure::bad_request(format!(
                        "asset {path} refers to content {hash} that the coordinator does not \
                         hold; send its bytes"
                    ))
                })?,
                None => {
                    return Err(Failure(
                        StatusCode::BAD_REQUEST,
                        ApiError {
                            error: format!(
                                "missing asset {path}: {scene_file} references it but the \
                                 submission has no part named {path:?}"
                            ),
                            file: Some(path.clone()),
                            ..ApiError::default()
                        },
                    ))
                }
            };
            assets.files.insert(path, bytes);
        }
        drop(parts);
        // Load the scene as a worker would, within the coordinator's budgets, so a broken or
        // oversized mesh or texture is refused now rather than on every worker.
        let scene = farm
            .building_scenes(|| Scene::build_with_limits(&desc, &scene_file, &assets, &load_limits))
            .map_err(|e| scene_error(&e))?;
        check_frames(&spec, scene.frame_count()).map_err(Failure::bad_request)?;
        // Not needed to store the job: give their memory back before the blobs are written,
        // unless the scene goes to workers in this process (`Farm::share_built_scenes`).
        drop(desc);
        let scene = farm.wants_built_scenes().then_some(scene);
        let files = farm.files();
        let scene_hash = files.put_blob(text.as_bytes())?;
        let mut bundle = Vec::new();
        for (path, bytes) in &assets.files {
            bundle.push(BundleFile {
                path: path.clone(),
                hash: files.put_blob(bytes)?,
                size: bytes.len() as u64,
            });
        }
        bundle.sort_by(|a, b| a.path.cmp(&b.path));
        let name = spec.name.clone().unwrap_or_else(|| scene_file.clone());
        Ok(farm.submit_built(
            NewJob {
                name,
                scene_file,
                scene_hash,
                spec,
                assets: bundle,
            },
            scene,
        )?)
    })
    .await
}

/// Loads a stored job's scene from the blob store within the coordinator's current budgets.
/// Blocking.
fn load_stored_scene(farm: &Farm, bundle: &Bundle) -> ApiResult<Scene> {
    let missing = |what: &str| {
        Failure::not_found(format!(
            "{what} of job {} is missing from the store",
            bundle.job_id
        ))
    };
    let text = farm
        .files()
        .blob(&bundle.scene_hash)?
        .ok_or_else(|| missing("the scene file"))?;
    let text = String::from_utf8_lossy(&text);
    let mut assets = MemoryAssets::default();
    for file in &bundle.assets {
        let bytes = farm
            .files()
            .blob(&file.hash)?
            .ok_or_else(|| missing(&format!("asset {}", file.path)))?;
        assets.files.insert(file.path.clone(), bytes);
    }
    let limits = farm.config().limits.load_limits();
    let desc = SceneDescription::parse_with_limits(&text, &bundle.scene_file, &limits)
        .map_err(|e| scene_error(&e))?;
    farm.building_scenes(|| Scene::build_with_limits(&desc, &bundle.scene_file, &assets, &limits))
        .map_err(|e| scene_error(&e))
}

pub async fn list(State(app): AppState) -> Json<Vec<JobInfo>> {
    Json(app.farm.jobs())
}

pub async fn show(State(app): AppState, Path(id): Path<String>) -> ApiResult<Json<JobInfo>> {
    Ok(Json(app.farm.job(parse_id("job", &id)?)?))
}

pub async fn cancel(State(app): AppState, Path(id): Path<String>) -> ApiResult<Json<JobInfo>> {
    Ok(Json(app.farm.cancel(parse_id("job", &id)?)?))
}

pub async fn retry(State(app): AppState, Path(id): Path<String>) -> ApiResult<Json<JobInfo>> {
    Ok(Json(app.farm.retry(parse_id("job", &id)?)?))
}

pub async fn bundle(State(app): AppState, Path(id): Path<String>) -> ApiResult<Json<Bundle>> {
    Ok(Json(app.farm.bundle(parse_id("job", &id)?)?))
}

/// The frames a job asks for must exist in its scene.
fn check_frames(spec: &JobSpec, frame_count: u32) -> Result<(), String> {
    match spec.frames {
        Some(range) => range.validate(frame_count).map_err(|e| e.to_string()),
        None if spec.render.frame >= frame_count => Err(format!(
            "frame {} is out of range: the scene has {frame_count} frame(s), numbered from 0",
            spec.render.frame
        )),
        None => Ok(()),
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImageQuery {
    frame: Option<u32>,
    /// `png` (default), `exr` or `pfm`; anything else is a 400.
    #[serde(default)]
    format: ImageFormat,
}

pub async fn image(
    State(app): AppState,
    Path(id): Path<String>,
    query: Result<Query<ImageQuery>, QueryRejection>,
) -> ApiResult<Response> {
    let id = parse_id("job", &id)?;
    let Query(query) = query.map_err(|e| Failure::bad_request(e.body_text()))?;
    let farm = app.farm.clone();
    let format = query.format;
    let bytes = blocking(move || Ok(farm.image_in(id, query.frame, format)?)).await?;
    Ok((
        [(header::CONTENT_TYPE, protocol::image_media_type(format))],
        bytes,
    )
        .into_response())
}

/// A progressive job's finished passes.
pub async fn convergence(
    State(app): AppState,
    Path(id): Path<String>,
) -> ApiResult<Json<protocol::Convergence>> {
    let id = parse_id("job", &id)?;
    Ok(Json(app.farm.convergence(id)?))
}

/// Where a progressive job's samples went, as a grey PNG.
pub async fn samples(State(app): AppState, Path(id): Path<String>) -> ApiResult<Response> {
    let id = parse_id("job", &id)?;
    let farm = app.farm.clone();
    let png = blocking(move || Ok(farm.samples_png(id)?)).await?;
    Ok(([(header::CONTENT_TYPE, "image/png")], png).into_response())
}

/// Every frame of a finished job as a tar of numbered PNGs (`<name>_0003.png`).
pub async fn frames_tar(State(app): AppState, Path(id): Path<String>) -> ApiResult<Response> {
    let id = parse_id("job", &id)?;
    let farm = app.farm.clone();
    let (name, tar) = blocking(move || {
        let name = farm.job(id)?.name;
        let frames = farm.frame_images(id)?;
        let stem = archive_stem(&name);
        let mut archive = tar::Builder::new(Vec::new());
        for (frame, png) in frames {
            let mut header = tar::Header::new_ustar();
            header.set_size(png.len() as u64);
            header.set_mode(0o644);
            header.set_mtime(0);
            header.set_cksum();
            archive
                .append_data(
                    &mut header,
                    format!("{stem}_{frame:04}.png"),
                    png.as_slice(),
                )
                .map_err(|e| Failure::internal(format!("building the archive: {e}")))?;
        }
        let bytes = archive
            .into_inner()
            .map_err(|e| Failure::internal(format!("building the archive: {e}")))?;
        Ok((stem, bytes))
    })
    .await?;
    let disposition = format!("attachment; filename=\"{name}_frames.tar\"");
    Ok((
        [
            (header::CONTENT_TYPE, "application/x-tar".to_string()),
            (header::CONTENT_DISPOSITION, disposition),
        ],
        tar,
    )
        .into_response())
}

/// A job name made safe for file names in the archive: letters, digits, `-`, `_`, `.`.
fn archive_stem(name: &str) -> String {
    let stem = name.strip_suffix(".scene").unwrap_or(name);
    let safe: String = stem
        .chars()
        .map(|c| {
            if c.is_ascii_alphanumeric() || "-_.".contains(c) {
                c
            } else {
                '_'
            }
        })
        .collect();
    if safe.trim_matches('.').is_empty() {
        "frame".to_string()
    } else {
        safe
    }
}

#[derive(Debug, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TileQuery {
    #[serde(default)]
    offset: u32,
    limit: Option<u32>,
}

/// One page of the tile map: `?offset=&limit=`, at most [`MAX_TILE_PAGE`] tiles.
pub async fn tiles(
    State(app): AppState,
    Path(id): Path<String>,
    query: Result<Query<TileQuery>, QueryRejection>,
) -> ApiResult<Json<TilePage>> {
    let id = parse_id("job", &id)?;
    let Query(query) = query.map_err(|e| Failure::bad_request(e.body_text()))?;
    let limit = query.limit.unwrap_or(MAX_TILE_PAGE);
    if limit > MAX_TILE_PAGE {
        return Err(Failure::bad_request(format!(
            "limit {limit} is over the largest page of {MAX_TILE_PAGE} tiles"
        )));
    }
    Ok(Json(app.farm.tiles(id, query.offset, limit)?))
}

/// Where the job looks from: its camera override, or the scene's camera read from its file.
pub async fn camera(State(app): AppState, Path(id): Path<String>) -> ApiResult<Json<JobCamera>> {
    let id = parse_id("job", &id)?;
    let farm = app.farm.clone();
    let info = farm.job(id)?;
    let bundle = farm.bundle(id)?;
    let _turn = app.scene_turn().await;
    let camera = blocking(move || {
        let text = farm.files().blob(&bundle.scene_hash)?.ok_or_else(|| {
            Failure::not_found(format!(
                "the scene file of job {id} is missing from the store"
            ))
        })?;
        let text = String::from_utf8_lossy(&text);
        let limits = farm.config().limits.load_limits();
        let desc = SceneDescription::parse_with_limits(&text, &bundle.scene_file, &limits)
            .map_err(|e| scene_error(&e))?;
        Ok(job_camera(&desc, &info.spec))
    })
    .await?;
    Ok(Json(camera))
}

fn job_camera(desc: &SceneDescription, spec: &JobSpec) -> JobCamera {
    let cam = &desc.camera;
    let fov_deg = cam.fov.to_degrees();
    if let Some(o) = &spec.render.camera {
        return JobCamera {
            position: o.position,
            look_at: o.look_at,
            up: o.up,
            fov_deg,
            from_scene: false,
        };
    }
    let forward = cam.orientation * glam::DVec3::NEG_Z;
    let up = cam.orientation * glam::DVec3::Y;
    // The pivot: the point of the view axis nearest the origin, where course scenes sit.
    let distance = (-cam.position).dot(forward).max(1.0);
    JobCamera {
        position: cam.position.to_array(),
        look_at: (cam.position + forward * distance).to_array(),
        up: up.to_array(),
        fov_deg,
        from_scene: true,
    }
}

/// A new job of an existing job's scene and assets (nothing is uploaded again), with the
/// given settings or, for an empty body, the same ones.
pub async fn resubmit(
    State(app): AppState,
    Path(id): Path<String>,
    body: Bytes,
) -> ApiResult<Response> {
    let id = parse_id("job", &id)?;
    let farm = app.farm.clone();
    let original = farm.job(id)?;
    let spec: JobSpec = if body.iter().all(u8::is_ascii_whitespace) {
        original.spec.clone()
    } else {
        parse_json(&body)?
    };
    farm.config()
        .limits
        .check(&spec)
        .map_err(Failure::bad_request)?;
    let bundle = farm.bundle(id)?;
    // The scene is loaded again: the new settings may ask for frames it lacks, and the
    // budgets may have been lowered since the original was accepted.
    let _turn = app.scene_turn().await;
    let info = blocking(move || {
        let scene = load_stored_scene(&farm, &bundle)?;
        check_frames(&spec, scene.frame_count()).map_err(Failure::bad_request)?;
        drop(scene);
        Ok(farm.submit(NewJob {
            name: spec.name.clone().unwrap_or(original.name),
            scene_file: bundle.scene_file,
            scene_hash: bundle.scene_hash,
            spec,
            assets: bundle.assets,
        })?)
    })
    .await?;
    app.farm
        .metrics
        .jobs_submitted
        .fetch_add(1, Ordering::Relaxed);
    Ok((StatusCode::CREATED, Json(info)).into_response())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scene_camera_pivots_on_its_view_axis_and_an_override_wins() {
        let text = r#"<scene><camera><fov v="0.9"/><near_clip v="0.1"/><far_clip v="100"/>
            <position x="0" y="0" z="10"/><orientation a="0" x="0" y="1" z="0"/>
            </camera><background_color r="0" g="0" b="0"/><refractive_index v="1"/></scene>"#;
        let desc = SceneDescription::parse(text, "t.scene").unwrap();
        let mut spec = JobSpec::default();
        let cam = job_camera(&desc, &spec);
        assert!(cam.from_scene);
        assert_eq!(cam.position, [0.0, 0.0, 10.0]);
        assert!((cam.look_at[2]).abs() < 1e-12, "{cam:?}");
        assert!((cam.up[1] - 1.0).abs() < 1e-12);
        assert!((cam.fov_deg - 0.9f64.to_degrees()).abs() < 1e-9);
        spec.render.camera = Some(tracer_core::CameraOverride {
            position: [1.0, 2.0, 3.0],
            look_at: [0.0; 3],
            up: [0.0, 1.0, 0.0],
        });
        let cam = job_camera(&desc, &spec);
        assert!(!cam.from_scene);
        assert_eq!(cam.position, [1.0, 2.0, 3.0]);
    }

    #[test]
    fn scene_names_lose_their_folders() {
        assert_eq!(scene_file_name(Some("a/b/c.scene")), "c.scene");
        assert_eq!(scene_file_name(Some("..\\x.scene")), "x.scene");
        assert_eq!(scene_file_name(Some("")), "scene.scene");
        assert_eq!(scene_file_name(None), "scene.scene");
    }
}
