//! The farm's client commands: `jobs`, `show`, `cancel`, `retry`, `download` and `workers`.
//! Each prints a readable table or line, or with `--json` the API's JSON, and shares the
//! `--server`/`--token` handling of `submit` ([`ServerArgs`]).

use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use protocol::client::Client;
use protocol::{JobInfo, JobState, WorkerInfo, WorkerState};
use serde::Serialize;

use super::submit::describe;
use super::Failure;

/// Where the coordinator is and how to authenticate: shared by every client command.
#[derive(Args, Debug, Clone)]
pub struct ServerArgs {
    /// The coordinator's URL.
    #[arg(long, env = "TESSERA_COORDINATOR")]
    pub server: String,
    /// The coordinator's bearer token.
    #[arg(long, env = "TESSERA_TOKEN", hide_env_values = true)]
    pub token: Option<String>,
}

impl ServerArgs {
    pub fn client(&self) -> Result<Client, Failure> {
        Client::new(&self.server, self.token.clone()).map_err(Failure::usage)
    }
}

/// A command that only lists.
#[derive(Args, Debug)]
pub struct ListArgs {
    #[command(flatten)]
    pub server: ServerArgs,
    /// Print the API's JSON instead of a table.
    #[arg(long)]
    pub json: bool,
}

/// A command about one job.
#[derive(Args, Debug)]
pub struct JobArgs {
    #[command(flatten)]
    pub server: ServerArgs,
    /// The job's id.
    pub id: u64,
    /// Print the API's JSON instead of a line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Debug)]
pub struct DownloadArgs {
    #[command(flatten)]
    pub server: ServerArgs,
    /// The job's id.
    pub id: u64,
    /// Where to write the image (a frame-range job's first frame, or with --frames each frame
    /// numbered: out.png → out_0003.png).
    #[arg(short, long)]
    pub output: PathBuf,
    /// Every frame of a frame-range job, as numbered files.
    #[arg(long)]
    pub frames: bool,
    /// Print the written files as JSON (`{"job": ID, "files": [...]}`).
    #[arg(long)]
    pub json: bool,
}

/// Runs `body` on a runtime and turns its outcome into the exit code of `command`.
fn run_async<F>(command: &str, body: impl FnOnce() -> F) -> ExitCode
where
    F: std::future::Future<Output = Result<(), Failure>>,
{
    worker::init_logging("warn");
    let result = super::runtime()
        .map_err(Failure::from)
        .and_then(|rt| rt.block_on(body()));
    super::finish(command, result)
}

fn print_json(value: &impl Serialize) -> Result<(), Failure> {
    let text = serde_json::to_string_pretty(value).map_err(Failure::failed)?;
    println!("{text}");
    Ok(())
}

pub fn jobs(args: ListArgs) -> ExitCode {
    run_async("jobs", || async move {
        let jobs = args.server.client()?.jobs().await.map_err(describe)?;
        if args.json {
            return print_json(&jobs);
        }
        print!("{}", jobs_table(&jobs));
        Ok(())
    })
}

pub fn show(args: JobArgs) -> ExitCode {
    run_async("show", || async move {
        let job = args.server.client()?.job(args.id).await.map_err(describe)?;
        if args.json {
            return print_json(&job);
        }
        print!("{}", job_details(&job));
        Ok(())
    })
}

pub fn cancel(args: JobArgs) -> ExitCode {
    run_async("cancel", || async move {
        let job = args
            .server
            .client()?
            .cancel(args.id)
            .await
            .map_err(describe)?;
        if args.json {
            return print_json(&job);
        }
        println!("job {} {}", job.id, job.state.as_str());
        Ok(())
    })
}

pub fn retry(args: JobArgs) -> ExitCode {
    run_async("retry", || async move {
        let job = args
            .server
            .client()?
            .retry(args.id)
            .await
            .map_err(describe)?;
        if args.json {
            return print_json(&job);
        }
        println!(
            "job {} {}: {}/{} tiles done",
            job.id,
            job.state.as_str(),
            job.tiles_done,
            job.tiles_total
        );
        Ok(())
    })
}

pub fn workers(args: ListArgs) -> ExitCode {
    run_async("workers", || async move {
        let workers = args.server.client()?.workers().await.map_err(describe)?;
        if args.json {
            return print_json(&workers);
        }
        print!("{}", workers_table(&workers));
        Ok(())
    })
}

pub fn download(args: DownloadArgs) -> ExitCode {
    run_async("download", || async move {
        // The format comes from the output's extension, checked before anything is fetched.
        let format = tracer_core::cli_args::check_output(&args.output)
            .map_err(|e| Failure::usage(e.to_string()))?;
        let client = args.server.client()?;
        let job = client.job(args.id).await.map_err(describe)?;
        if job.state != JobState::Done {
            eprintln!(
                "note: job {} is {}: the image is what has been rendered so far",
                job.id,
                job.state.as_str()
            );
        }
        let written = if args.frames {
            if job.spec.frames.is_none() {
                return Err(Failure::usage(format!(
                    "--frames: job {} renders a single frame",
                    job.id
                )));
            }
            super::download(&client, &job, &args.output).await?
        } else {
            let bytes = client
                .image_in(job.id, None, format)
                .await
                .map_err(describe)?;
            super::write_image(&args.output, &bytes)?;
            vec![args.output.clone()]
        };
        if args.json {
            return print_json(&serde_json::json!({ "job": job.id, "files": written }));
        }
        println!("wrote {}", super::describe_written(&written));
        Ok(())
    })
}

/// Rows padded to each column's widest cell, the last column unpadded.
fn table(header: &[&str], rows: &[Vec<String>]) -> String {
    let mut widths: Vec<usize> = header.iter().map(|h| h.chars().count()).collect();
    for row in rows {
        for (w, cell) in widths.iter_mut().zip(row) {
            *w = (*w).max(cell.chars().count());
        }
    }
    let mut out = String::new();
    let header: Vec<String> = header.iter().map(|h| h.to_string()).collect();
    for row in std::iter::once(&header).chain(rows) {
        let last = row.len().saturating_sub(1);
        for (i, (cell, w)) in row.iter().zip(&widths).enumerate() {
            if i == last {
                out.push_str(cell);
            } else {
                out.push_str(&format!("{cell:<w$}  "));
            }
        }
        out.push('\n');
    }
    out
}

fn seconds(s: Option<f64>) -> String {
    s.map(|s| format!("{s:.1}s")).unwrap_or_else(|| "-".into())
}

fn jobs_table(jobs: &[JobInfo]) -> String {
    let rows: Vec<Vec<String>> = jobs
        .iter()
        .map(|j| {
            vec![
                j.id.to_string(),
                j.state.as_str().to_string(),
                format!("{}/{}", j.tiles_done, j.tiles_total),
                seconds(j.elapsed_s),
                seconds(j.eta_s),
                j.name.clone(),
            ]
        })
        .collect();
    table(&["ID", "STATE", "TILES", "ELAPSED", "ETA", "NAME"], &rows)
}

fn job_details(job: &JobInfo) -> String {
    let r = &job.spec.render;
    let mut lines = vec![
        ("id", job.id.to_string()),
        ("name", job.name.clone()),
        ("scene", job.scene_file.clone()),
        ("state", job.state.as_str().to_string()),
        (
            "tiles",
            format!(
                "{}/{} done, {} running",
                job.tiles_done, job.tiles_total, job.tiles_running
            ),
        ),
        (
            "settings",
            format!(
                "{}x{}, {} spp, depth {}, seed {}, tile {}",
                r.width, r.height, r.spp, r.max_depth, r.seed, job.spec.tile_size
            ),
        ),
    ];
    if let Some(range) = job.spec.frames {
        let frames: Vec<u32> = range.frames().collect();
        if let (Some(first), Some(last)) = (frames.first(), frames.last()) {
            lines.push(("frames", format!("{first}..{last}")));
        }
    }
    lines.push(("elapsed", seconds(job.elapsed_s)));
    lines.push(("eta", seconds(job.eta_s)));
    if let Some(error) = &job.error {
        lines.push(("error", error.clone()));
    }
    if !job.failures.is_empty() {
        lines.push(("failures", job.failures.len().to_string()));
    }
    let width = lines.iter().map(|(k, _)| k.len()).max().unwrap_or(0) + 1;
    lines
        .iter()
        .map(|(k, v)| format!("{:<width$} {v}\n", format!("{k}:")))
        .collect()
}

fn worker_state(state: WorkerState) -> &'static str {
    match state {
        WorkerState::Idle => "idle",
        WorkerState::Rendering => "rendering",
        WorkerState::Lost => "lost",
    }
}

fn workers_table(workers: &[WorkerInfo]) -> String {
    let rows: Vec<Vec<String>> = workers
        .iter()
        .map(|w| {
            vec![
                w.id.to_string(),
                worker_state(w.state).to_string(),
                w.lease
                    .map(|l| format!("job {} tile {}", l.job_id, l.tile))
                    .unwrap_or_else(|| "-".into()),
                w.tiles_done.to_string(),
                w.address.clone().unwrap_or_else(|| "-".into()),
                w.name.clone(),
            ]
        })
        .collect();
    table(&["ID", "STATE", "LEASE", "TILES", "ADDRESS", "NAME"], &rows)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn tables_pad_every_column_but_the_last() {
        let text = table(
            &["ID", "NAME"],
            &[
                vec!["7".into(), "a b".into()],
                vec!["12345".into(), "c".into()],
            ],
        );
        assert_eq!(text, "ID     NAME\n7      a b\n12345  c\n");
    }

    #[test]
    fn an_empty_list_is_just_the_header() {
        assert_eq!(jobs_table(&[]), "ID  STATE  TILES  ELAPSED  ETA  NAME\n");
    }
}
