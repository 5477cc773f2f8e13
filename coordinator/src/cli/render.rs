//! `coordinator render`: the one-command farm. An [`EmbeddedFarm`], the scene submitted in
//! process through the checks of `POST /jobs` and rendered by workers that lease its tiles and
//! hand the pixels over in process (through the routes' code), a progress bar, the PNG written.
//!
//! The farm runs in this process, so the command learns of the job's progress from the farm's
//! change notifications and takes the finished image from it directly: polling the job and
//! downloading the image over HTTP cost up to a poll interval and a round trip with the
//! image's bytes, all after the render.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::sync::Arc;
use std::time::Instant;

use clap::Args;
use protocol::{JobInfo, JobState};
use tokio::sync::broadcast::error::RecvError;
use tracer_core::cli_args::OutputArgs;
use worker::available_cores;

use super::submit::{collect_submission, describe, progress_bar, show_progress};
use super::{Failure, SettingsArgs};
use crate::embedded::{local_tile_size, scratch_bytes, EmbeddedFarm};
use crate::farm::Farm;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// The scene file; its assets are found beside it (or in its parent folder).
    pub scene: PathBuf,
    #[command(flatten)]
    pub output: OutputArgs,
    /// Local workers [default: 1, rendering with every core].
    #[arg(long)]
    pub workers: Option<usize>,
    /// Render threads in all, split between the workers [default: every core].
    #[arg(long)]
    pub threads: Option<usize>,
    /// Keep the farm's data (jobs, tiles, image) here instead of a temporary folder.
    #[arg(long)]
    pub data_dir: Option<PathBuf>,
    #[command(flatten)]
    pub settings: SettingsArgs,
}

pub fn run(args: RenderArgs) -> ExitCode {
    worker::init_logging("warn");
    super::finish("render", render(args))
}

fn render(args: RenderArgs) -> Result<(), Failure> {
    let start = Instant::now();
    // Everything the flags can get wrong is refused before the scene is read.
    let output = args.output.path_for(&args.scene).map_err(Failure::usage)?;
    let threads = args.threads.unwrap_or_else(available_cores).max(1);
    let workers = args.workers.unwrap_or(1).clamp(1, threads);
    let mut spec = args.settings.to_spec()?;
    if args.settings.tile_size.is_none() {
        spec.tile_size = local_tile_size(&spec, workers);
    }
    let submission = collect_submission(&args.scene, spec)?;
    let quiet = args.output.quiet;
    let runtime = super::runtime()?;
    let (result, in_memory) = runtime.block_on(async move {
        let submitted = submission.scene.len() as u64
            + submission
                .assets
                .iter()
                .map(|(_, b)| b.len() as u64)
                .sum::<u64>();
        let scratch = scratch_bytes(&submission.spec, submitted);
        let farm = match EmbeddedFarm::start(args.data_dir.clone(), workers, threads, Some(scratch))
            .await
        {
            Ok(farm) => farm,
            Err(e) => return (Err(Failure::from(e)), false),
        };
        // The fragment hands the page the token without sending it anywhere.
        eprintln!(
            "dashboard (while it renders): {}/#token={}",
            farm.url(),
            farm.token()
        );
        let result = submit_and_wait(&farm, submission, &output, quiet, start).await;
        let in_memory = farm.in_memory();
        if in_memory {
            // Nothing of this farm outlives the process, which ends as soon as this returns:
            // stopping its workers and server cleanly (0.5 to 0.9 ms after every image) and
            // then the runtime would only delay the exit. Their threads end with the process.
            std::mem::forget(farm);
        } else {
            farm.shutdown().await;
        }
        (result, in_memory)
    });
    if in_memory {
        std::mem::forget(runtime);
    }
    result
}

/// Submits the scene to the in-process farm (no upload), waits for it with a progress bar and
/// writes the PNG. Ctrl-C cancels the job.
async fn submit_and_wait(
    farm: &EmbeddedFarm,
    submission: protocol::client::Submission,
    output: &std::path::Path,
    quiet: bool,
    start: Instant,
) -> Result<(), Failure> {
    let client = farm.client();
    let (workers, threads) = farm.size();
    // Subscribed before the job exists, so no change to it is missed.
    let mut events = farm.farm().subscribe();
    let job = farm.submit(submission).await.map_err(describe)?;
    let spp = match &job.spec.adaptive {
        Some(a) => format!("{}..{} spp progressive", a.spp_min, a.spp_max),
        None => format!("{} spp", job.spec.render.spp),
    };
    eprintln!(
        "rendering {} at {}x{}, {spp}: {} tiles on {workers} worker(s), {threads} thread(s)",
        job.scene_file, job.spec.render.width, job.spec.render.height, job.tiles_total
    );
    let finished = tokio::select! {
        done = wait_in_process(farm.farm(), &mut events, job.id, quiet) => {
            done.map_err(Failure::failed)?
        }
        _ = super::stop_signal() => {
            let _ = client.cancel(job.id).await;
            return Err(Failure::failed("interrupted; the job was cancelled"));
        }
    };
    match finished.state {
        JobState::Done => {
            let written = {
                let (farm, job, output) =
                    (farm.farm().clone(), finished.clone(), output.to_owned());
                tokio::task::spawn_blocking(move || write_output(&farm, &job, &output))
                    .await
                    .map_err(|e| e.to_string())??
            };
            eprintln!(
                "wrote {} in {:.2}s: {}",
                super::describe_written(&written),
                start.elapsed().as_secs_f64(),
                describe_samples(&finished)
            );
            Ok(())
        }
        JobState::Failed => Err(Failure::failed(format!(
            "the render failed: {}",
            finished.error.unwrap_or_default()
        ))),
        other => Err(Failure::failed(format!("the job ended {}", other.as_str()))),
    }
}

/// Waits for job `id` to finish, from the farm's change notifications (`events`, subscribed
/// before the job was submitted), with a progress bar. Returns the finished job.
async fn wait_in_process(
    farm: &Farm,
    events: &mut tokio::sync::broadcast::Receiver<crate::farm::FarmEvent>,
    id: u64,
    quiet: bool,
) -> Result<JobInfo, String> {
    let bar = progress_bar(quiet);
    loop {
        let info = farm.job(id).map_err(|e| e.to_string())?;
        show_progress(&bar, &info);
        if info.state.is_finished() {
            bar.finish_and_clear();
            return Ok(info);
        }
        // Any change may be this job's: the job is read again. Falling behind only means
        // some changes were merged into the next read.
        match events.recv().await {
            Ok(_) | Err(RecvError::Lagged(_)) => {}
            Err(RecvError::Closed) => return Err("the farm stopped".into()),
        }
    }
}

/// Writes a finished job's images (see [`super::download`]) taken from the farm itself.
fn write_output(farm: &Arc<Farm>, job: &JobInfo, output: &Path) -> Result<Vec<PathBuf>, String> {
    let format = tracer_core::cli_args::check_output(output).map_err(|e| e.to_string())?;
    let mut written = Vec::new();
    for (frame, path) in super::output_files(job, output) {
        let bytes = farm
            .image_in(job.id, frame, format)
            .map_err(|e| e.to_string())?;
        super::write_image(&path, &bytes)?;
        written.push(path);
    }
    Ok(written)
}

/// The final line's account of the samples: mean spp, and for a progressive job its passes
/// and estimated error.
fn describe_samples(job: &protocol::JobInfo) -> String {
    let spp = job.spp_mean.unwrap_or(job.spec.render.spp as f64);
    match (job.passes, job.error_estimate) {
        (Some(passes), Some(error)) => {
            format!("mean spp {spp:.2}, {passes} passes, estimated error {error:.4}")
        }
        (Some(passes), None) => format!("mean spp {spp:.2}, {passes} passes"),
        _ => format!("mean spp {spp:.2}"),
    }
}
