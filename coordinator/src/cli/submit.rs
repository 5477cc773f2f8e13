//! `coordinator submit`: collect a scene's referenced assets (and nothing else), upload them,
//! and optionally wait with a progress bar and download the image.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Duration;

use clap::Args;
use indicatif::{ProgressBar, ProgressStyle};
use protocol::client::{Client, ClientError, Submission};
use protocol::{JobInfo, JobSpec, JobState};
use tracer_core::scene::SceneDescription;
use tracer_core::{AssetSource, FsAssets};

use super::SettingsArgs;

#[derive(Args, Debug)]
pub struct SubmitArgs {
    /// The coordinator's URL.
    #[arg(long, env = "TESSERA_COORDINATOR")]
    pub server: String,
    /// The coordinator's bearer token.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
    /// The scene file; its assets are found beside it (or in its parent folder).
    pub scene: PathBuf,
    /// Download the finished image here (implies --wait).
    #[arg(short, long)]
    pub output: Option<PathBuf>,
    /// Wait for the job to finish, showing progress.
    #[arg(long)]
    pub wait: bool,
    #[command(flatten)]
    pub settings: SettingsArgs,
}

/// Reads a scene file and exactly the assets it references.
pub fn collect_submission(scene: &Path, spec: JobSpec) -> Result<Submission, String> {
    let text =
        std::fs::read_to_string(scene).map_err(|e| format!("reading {}: {e}", scene.display()))?;
    let scene_file = scene
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_else(|| "scene.scene".into());
    let desc = SceneDescription::parse(&text, &scene_file).map_err(|e| e.to_string())?;
    let source = FsAssets::for_scene(scene);
    let mut assets = Vec::new();
    for path in desc.referenced_assets() {
        let bytes = source
            .read(&path)
            .map_err(|e| format!("{scene_file}: asset {path}: {e}"))?;
        assets.push((path, bytes));
    }
    Ok(Submission {
        spec,
        scene_file,
        scene: text.into_bytes(),
        assets,
    })
}

/// An error from the coordinator, with a scene error's location when it has one.
pub fn describe(e: &ClientError) -> String {
    match e {
        ClientError::Api { body, status, .. } => match (&body.file, body.line) {
            (Some(_), Some(_)) => format!("{} (HTTP {status})", body.error),
            _ => e.to_string(),
        },
        _ => e.to_string(),
    }
}

/// Polls a job until it finishes, drawing a progress bar on stderr (hidden when it is not a
/// terminal). Returns the finished job.
pub async fn wait_for(client: &Client, id: u64, every: Duration) -> Result<JobInfo, ClientError> {
    let bar = ProgressBar::new(0);
    bar.set_style(
        ProgressStyle::with_template(
            "{spinner} [{elapsed_precise}] {wide_bar} {pos}/{len} tiles {msg}",
        )
        .expect("a valid template"),
    );
    let mut unreachable_since: Option<std::time::Instant> = None;
    loop {
        match client.job(id).await {
            Ok(info) => {
                unreachable_since = None;
                bar.set_length(info.tiles_total as u64);
                bar.set_position(info.tiles_done as u64);
                bar.set_message(match info.eta_s {
                    Some(eta) => format!("ETA {eta:.0}s"),
                    None => info.state.as_str().to_string(),
                });
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
        tokio::time::sleep(every).await;
    }
}

pub fn run(args: SubmitArgs) -> ExitCode {
    worker::init_logging("warn");
    let fail = |msg: String| {
        eprintln!("coordinator submit: {msg}");
        ExitCode::from(1)
    };
    let spec = match args.settings.to_spec() {
        Ok(s) => s,
        Err(e) => return fail(e),
    };
    let submission = match collect_submission(&args.scene, spec) {
        Ok(s) => s,
        Err(e) => return fail(e),
    };
    let runtime = match super::runtime() {
        Ok(rt) => rt,
        Err(e) => return fail(e),
    };
    runtime.block_on(async move {
        let client = match Client::new(&args.server, args.token.clone()) {
            Ok(c) => c,
            Err(e) => return fail(e.to_string()),
        };
        let job = match client.submit(&submission).await {
            Ok(job) => job,
            Err(e) => return fail(describe(&e)),
        };
        eprintln!(
            "submitted job {} ({}, {} tiles)",
            job.id, job.name, job.tiles_total
        );
        // The job id alone on stdout, for scripts.
        println!("{}", job.id);
        if !args.wait && args.output.is_none() {
            return ExitCode::SUCCESS;
        }
        let done = match wait_for(&client, job.id, Duration::from_millis(250)).await {
            Ok(done) => done,
            Err(e) => return fail(describe(&e)),
        };
        match done.state {
            JobState::Done => {}
            JobState::Failed => {
                return fail(format!(
                    "job {} failed: {}",
                    done.id,
                    done.error.unwrap_or_default()
                ))
            }
            other => return fail(format!("job {} ended {}", done.id, other.as_str())),
        }
        eprintln!(
            "job {} done in {:.2}s",
            done.id,
            done.elapsed_s.unwrap_or_default()
        );
        if let Some(out) = args.output {
            match super::download(&client, &done, &out).await {
                Ok(written) => eprintln!("wrote {}", super::describe_written(&written)),
                Err(e) => return fail(e),
            }
        }
        ExitCode::SUCCESS
    })
}
