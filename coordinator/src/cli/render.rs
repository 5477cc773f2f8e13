//! `coordinator render`: the one-command farm. An [`EmbeddedFarm`], the scene submitted over
//! HTTP like any other job, a progress bar, the PNG written, everything torn down.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Args;
use protocol::JobState;
use tracer_core::cli_args::OutputArgs;
use worker::available_cores;

use super::submit::{collect_submission, describe, wait_for};
use super::{Failure, SettingsArgs};
use crate::embedded::{local_tile_size, scratch_bytes, EmbeddedFarm};

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
    runtime.block_on(async move {
        let submitted = submission.scene.len() as u64
            + submission
                .assets
                .iter()
                .map(|(_, b)| b.len() as u64)
                .sum::<u64>();
        let scratch = scratch_bytes(&submission.spec, submitted);
        let farm =
            EmbeddedFarm::start(args.data_dir.clone(), workers, threads, Some(scratch)).await?;
        // The fragment hands the page the token without sending it anywhere.
        eprintln!(
            "dashboard (while it renders): {}/#token={}",
            farm.url(),
            farm.token()
        );
        let result = submit_and_wait(&farm, &submission, &output, quiet, start).await;
        farm.shutdown().await;
        result
    })
}

/// Submits the scene to the in-process farm, waits for it with a progress bar and writes the
/// PNG. Ctrl-C cancels the job.
async fn submit_and_wait(
    farm: &EmbeddedFarm,
    submission: &protocol::client::Submission,
    output: &std::path::Path,
    quiet: bool,
    start: Instant,
) -> Result<(), Failure> {
    let client = farm.client();
    let (workers, threads) = farm.size();
    let job = client.submit(submission).await.map_err(describe)?;
    let spp = match &job.spec.adaptive {
        Some(a) => format!("{}..{} spp progressive", a.spp_min, a.spp_max),
        None => format!("{} spp", job.spec.render.spp),
    };
    eprintln!(
        "rendering {} at {}x{}, {spp}: {} tiles on {workers} worker(s), {threads} thread(s)",
        job.scene_file, job.spec.render.width, job.spec.render.height, job.tiles_total
    );
    let finished = tokio::select! {
        done = wait_for(client, job.id, Duration::from_millis(20), quiet) => {
            done.map_err(describe)?
        }
        _ = super::stop_signal() => {
            let _ = client.cancel(job.id).await;
            return Err(Failure::failed("interrupted; the job was cancelled"));
        }
    };
    match finished.state {
        JobState::Done => {
            let written = super::download(client, &finished, output).await?;
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
