//! `coordinator render`: the one-command farm. An in-process coordinator on loopback, local
//! workers sharing one scene cache, the scene submitted over HTTP like any other job, a
//! progress bar, the PNG written, everything torn down.

use std::path::PathBuf;
use std::process::ExitCode;
use std::sync::Arc;
use std::time::{Duration, Instant};

use clap::Args;
use worker::protocol::JobState;
use worker::{available_cores, Client, SceneCache, Shutdown, Worker, WorkerConfig};

use super::submit::{collect_submission, describe, wait_for};
use super::SettingsArgs;
use crate::clock::SystemClock;
use crate::config::FarmConfig;
use crate::farm::Farm;

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

/// A token nobody else on the machine can guess, for the loopback coordinator.
fn local_token() -> String {
    let mut seed = format!("{:?}{}", std::time::SystemTime::now(), std::process::id());
    if let Ok(random) = std::fs::read("/proc/sys/kernel/random/uuid") {
        seed.push_str(&String::from_utf8_lossy(&random));
    }
    worker::hash_hex(seed.as_bytes())
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
    let workers = args.workers.unwrap_or(1).clamp(1, threads);
    let temp;
    let data_dir = match &args.data_dir {
        Some(dir) => dir.clone(),
        None => {
            temp = tempfile::Builder::new()
                .prefix("tessera-render-")
                .tempdir()
                .map_err(|e| format!("creating a temporary data dir: {e}"))?;
            temp.path().to_path_buf()
        }
    };
    // Every core is already busy with a worker: straggler copies would only compete.
    let config = FarmConfig {
        stragglers: false,
        ..FarmConfig::default()
    };
    let farm = Farm::open(&data_dir, config, Arc::new(SystemClock)).map_err(|e| e.to_string())?;
    let runtime = super::runtime()?;
    runtime.block_on(async move {
        let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
            .await
            .map_err(|e| format!("binding a loopback port: {e}"))?;
        let url = format!(
            "http://{}",
            listener.local_addr().map_err(|e| e.to_string())?
        );
        let token = local_token();
        let (stop_server, server_stop) = tokio::sync::oneshot::channel::<()>();
        let server = tokio::spawn(crate::server::serve(
            listener,
            farm,
            Some(token.clone()),
            async move {
                let _ = server_stop.await;
            },
        ));
        let client = Client::new(&url, Some(token.clone())).map_err(|e| e.to_string())?;

        let (stop_workers, shutdown) = Shutdown::new();
        let scenes = SceneCache::new();
        let mut handles = Vec::new();
        for i in 0..workers {
            // Spread the threads: the first `threads % workers` workers get one more.
            let n = threads / workers + usize::from(i < threads % workers);
            let config = WorkerConfig::new(format!("local-{i}"), n);
            let worker = Worker::new(client.clone(), config, scenes.clone())?;
            let shutdown = shutdown.clone();
            handles.push(tokio::spawn(async move { worker.run(shutdown).await }));
        }

        // The fragment hands the page the token without sending it anywhere.
        eprintln!("dashboard (while it renders): {url}/#token={token}");
        let result = submit_and_wait(&client, &submission, &output, workers, threads, start).await;
        let _ = stop_workers.send(true);
        for handle in handles {
            let _ = handle.await;
        }
        let _ = stop_server.send(());
        let _ = server.await;
        result
    })
}

/// Submits the scene to the in-process farm, waits for it with a progress bar and writes the
/// PNG. Ctrl-C cancels the job.
async fn submit_and_wait(
    client: &Client,
    submission: &worker::Submission,
    output: &std::path::Path,
    workers: usize,
    threads: usize,
    start: Instant,
) -> Result<(), String> {
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
            let png = client.image(job.id).await.map_err(|e| describe(&e))?;
            super::write_png(output, &png)?;
            eprintln!(
                "wrote {} in {:.2}s",
                output.display(),
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
