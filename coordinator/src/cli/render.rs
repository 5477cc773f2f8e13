//! `coordinator render`: the one-command farm. An [`EmbeddedFarm`], the scene submitted over
//! HTTP like any other job, a progress bar, the PNG written, everything torn down.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Args;
use protocol::JobState;
use worker::available_cores;

use super::submit::{collect_submission, describe, wait_for};
use super::SettingsArgs;
use crate::embedded::EmbeddedFarm;

#[derive(Args, Debug)]
pub struct RenderArgs {
    /// The scene file; its assets are found beside it (or in its parent folder).
    pub scene: PathBuf,
    /// Where to write the PNG [default: <scene name>.png].
    #[arg(short, long)]
    pub output: Option<PathBuf>,
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
    match render(args) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("coordinator render: {e}");
            ExitCode::from(1)
        }
    }
}

fn render(args: RenderArgs) -> Result<(), String> {
    let start = Instant::now();
    let spec = args.settings.to_spec()?;
    let submission = collect_submission(&args.scene, spec)?;
    let output = args
        .output
        .clone()
        .unwrap_or_else(|| super::default_output(&args.scene));
    let threads = args.threads.unwrap_or_else(available_cores).max(1);
    let workers = args.workers.unwrap_or(1);
    let runtime = super::runtime()?;
    runtime.block_on(async move {
        let farm = EmbeddedFarm::start(args.data_dir.clone(), workers, threads).await?;
        // The fragment hands the page the token without sending it anywhere.
        eprintln!(
            "dashboard (while it renders): {}/#token={}",
            farm.url(),
            farm.token()
        );
        let result = submit_and_wait(&farm, &submission, &output, start).await;
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
    start: Instant,
) -> Result<(), String> {
    let client = farm.client();
    let (workers, threads) = farm.size();
    let job = client.submit(submission).await.map_err(|e| describe(&e))?;
    eprintln!(
        "rendering {} at {}x{}, {} spp: {} tiles on {workers} worker(s), {threads} thread(s)",
        job.scene_file,
        job.spec.render.width,
        job.spec.render.height,
        job.spec.render.spp,
        job.tiles_total
    );
    let finished = tokio::select! {
        done = wait_for(client, job.id, Duration::from_millis(20)) => {
            done.map_err(|e| describe(&e))?
        }
        _ = super::stop_signal() => {
            let _ = client.cancel(job.id).await;
            return Err("interrupted; the job was cancelled".to_string());
        }
    };
    match finished.state {
        JobState::Done => {
            let written = super::download(client, &finished, output).await?;
            eprintln!(
                "wrote {} in {:.2}s",
                super::describe_written(&written),
                start.elapsed().as_secs_f64()
            );
            Ok(())
        }
        JobState::Failed => Err(format!(
            "the render failed: {}",
            finished.error.unwrap_or_default()
        )),
        other => Err(format!("the job ended {}", other.as_str())),
    }
}
