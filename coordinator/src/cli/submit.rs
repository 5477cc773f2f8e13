//! `coordinator submit`: collect a scene's referenced assets (and nothing else), upload them,
//! and optionally wait with a progress bar and download the image.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use protocol::client::{Client, ClientError, Submission};
use protocol::{JobInfo, JobSpec, JobState};
use tracer_core::cli_args::{exit, OutputArgs};
use tracer_core::scene::SceneDescription;
use tracer_core::{AssetSource, FsAssets};

use super::client::ServerArgs;
use super::{Failure, SettingsArgs};

#[derive(Args, Debug)]
pub struct SubmitArgs {
    #[command(flatten)]
    pub server: ServerArgs,
    /// The scene file; its assets are found beside it (or in its parent folder).
    pub scene: PathBuf,
    /// `-o`: download the finished image there (implies --wait).
    #[command(flatten)]
    pub output: OutputArgs,
    /// Wait for the job to finish, showing progress.
    #[arg(long)]
    pub wait: bool,
    #[command(flatten)]
    pub settings: SettingsArgs,
}

/// Reads a scene file and exactly the assets it references.
pub fn collect_submission(scene: &Path, spec: JobSpec) -> Result<Submission, Failure> {
    let text = std::fs::read_to_string(scene)
        .map_err(|e| Failure::scene(format!("cannot read {}: {e}", scene.display())))?;
    let scene_file = scene
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene.scene".into());
    let desc = SceneDescription::parse(&text, &scene_file).map_err(Failure::scene)?;
    let source = FsAssets::for_scene(scene);
    let mut assets = Vec::new();
    for path in desc.referenced_assets() {
        let bytes = source
            .read(&path)
            .map_err(|e| Failure::scene(format!("{scene_file}: asset {path}: {e}")))?;
        assets.push((path, bytes));
    }
    Ok(Submission {
        spec,
        scene_file,
        scene: text.into_bytes(),
        assets,
    })
}

/// An error from the coordinator, with a scene error's location when it has one: a scene
/// the farm refused exits as a scene error, other refused requests as usage errors.
pub fn describe(e: ClientError) -> Failure {
    let refused = match &e {
        // The client reads every 409 as a stale lease; to a user it is a refused request.
        ClientError::Stale(message) => return Failure::usage(format!("{message} (HTTP 409)")),
        ClientError::Api { body, status, .. } => {
            if let (Some(_), Some(_)) = (&body.file, body.line) {
                return Failure {
                    code: exit::SCENE,
                    message: format!("{} (HTTP {status})", body.error),
                };
            }
            (400..500).contains(status)
        }
        _ => false,
    };
    if refused {
        Failure::usage(e)
    } else {
        Failure::failed(e)
    }
}

/// A job's progress bar on stderr (hidden when it is not a terminal, or when `quiet`).
pub fn progress_bar(quiet: bool) -> ProgressBar {
    let bar = if quiet {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(0)
    };
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles {msg}",
        )
        .expect("a valid template"),
    );
    bar
}

/// Shows `info` on a bar from [`progress_bar`].
pub fn show_progress(bar: &ProgressBar, info: &JobInfo) {
    bar.set_length(info.tiles_total as u64);
    bar.set_position(info.tiles_done as u64);
    bar.set_message(match info.eta_s {
        Some(eta) => format!("ETA {eta:.0}s"),
        None => info.state.as_str().to_string(),
    });
}

/// Polls a job until it finishes, drawing a progress bar on stderr (hidden when it is not a
/// terminal). Returns the finished job.
pub async fn wait_for(
    client: &Client,
    id: u64,
    every: Duration,
    quiet: bool,
) -> Result<JobInfo, ClientError> {
    let bar = progress_bar(quiet);
    let mut unreachable_since: Option<std::time::Instant> = None;
    loop {
        let mut pause = every;
        match client.job(id).await {
            Ok(info) => {
                // Every tile is in: only the image's assembly is left, which takes a few
                // milliseconds, so a full pause would be most of the wait for the answer.
                if info.tiles_done == info.tiles_total {
                    pause = (every / 10).max(Duration::from_millis(1));
                }
                unreachable_since = None;
                show_progress(&bar, &info);
                if info.state.is_finished() {
                    bar.finish_and_clear();
                    return Ok(info);
                }
            }
            // Ride out a coordinator restart for a while.
            Err(e) if e.is_transient() => {
                let since = *unreachable_since.get_or_insert_with(std::time::Instant::now);
                if since.elapsed() > Duration::from_secs(120) {
                    bar.abandon();
                    return Err(e);
                }
            }
            Err(e) => {
                bar.abandon();
                return Err(e);
            }
        }
        tokio::time::sleep(pause).await;
    }
}

pub fn run(args: SubmitArgs) -> ExitCode {
    worker::init_logging("warn");
    super::finish("submit", submit(args))
}

fn submit(args: SubmitArgs) -> Result<(), Failure> {
    let output = match &args.output.output {
        Some(_) => Some(args.output.path_for(&args.scene).map_err(Failure::usage)?),
        None => None,
    };
    let spec = args.settings.to_spec()?;
    let submission = collect_submission(&args.scene, spec)?;
    let runtime = super::runtime()?;
    runtime.block_on(async move {
        let client = args.server.client()?;
        let job = client.submit(&submission).await.map_err(describe)?;
        eprintln!(
            "submitted job {} ({}, {} tiles)",
            job.id, job.name, job.tiles_total
        );
        // The job id alone on stdout, for scripts.
        println!("{}", job.id);
        if !args.wait && output.is_none() {
            return Ok(());
        }
        let every = Duration::from_millis(250);
        let done = wait_for(&client, job.id, every, args.output.quiet)
            .await
            .map_err(describe)?;
        match done.state {
            JobState::Done => {}
            JobState::Failed => {
                return Err(Failure::failed(format!(
                    "job {} failed: {}",
                    done.id,
                    done.error.unwrap_or_default()
                )))
            }
            other => {
                return Err(Failure::failed(format!(
                    "job {} ended {}",
                    done.id,
                    other.as_str()
                )))
            }
        }
        eprintln!(
            "job {} done in {:.2}s",
            done.id,
            done.elapsed_s.unwrap_or_default()
        );
        if let Some(out) = output {
            let written = super::download(&client, &done, &out).await?;
            eprintln!("wrote {}", super::describe_written(&written));
        }
        Ok(())
    })
}
