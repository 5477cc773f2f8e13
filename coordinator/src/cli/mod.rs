//! The `coordinator` command line: `serve`, `render` (the embedded one-command farm),
//! `submit`, `report`, and the client commands (`jobs`, `show`, `cancel`, `retry`, `download`,
//! `workers`). Flags are parsed into plain structs here; the commands build everything else.

mod client;
mod paired;
mod render;
mod report;
mod serve;
mod submit;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use protocol::{JobSpec, DEFAULT_TILE_SIZE};
use tracer_core::cli_args::{error_chain, exit, RenderArgs};
pub use worker::stop_signal;

pub use submit::collect_submission;

#[derive(Parser, Debug)]
#[command(
    name = "coordinator",
    version,
    about = "Tessera render farm: serve a farm, render through an embedded one, or submit and manage jobs"
)]
pub struct Cli {
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand, Debug)]
pub enum Command {
    /// Run a coordinator that workers pull tiles from.
    Serve(serve::ServeArgs),
    /// Render a scene through an in-process farm with local workers, and write the PNG.
    Render(render::RenderArgs),
    /// Submit a scene and its assets to a coordinator; optionally wait and download the image.
    Submit(submit::SubmitArgs),
    /// Measure error against run time through the embedded farm at several worker counts:
    /// report.csv, report.md and error_vs_time.png.
    Report(report::ReportArgs),
    /// List the coordinator's jobs.
    Jobs(client::ListArgs),
    /// Show one job: state, progress, settings, errors.
    Show(client::JobArgs),
    /// Cancel a queued or running job.
    Cancel(client::JobArgs),
    /// Requeue a failed job's failed tiles.
    Retry(client::JobArgs),
    /// Download a job's image (or with --frames every frame, numbered).
    Download(client::DownloadArgs),
    /// List the workers the coordinator knows.
    Workers(client::ListArgs),
}

/// Render settings, declared once in tracer-core and shared with `tracer render`, plus the
/// farm's tile size and a job name.
#[derive(Args, Debug, Clone)]
pub struct SettingsArgs {
    #[command(flatten)]
    pub render: RenderArgs,
    /// Tile edge in pixels [default: 64; `coordinator render` chooses up to 256 for a
    /// one-shot job, as long as every local pull loop gets at least four tiles a frame].
    #[arg(long)]
    pub tile_size: Option<u32>,
    /// A name for job listings [default: the scene's file name].
    #[arg(long)]
    pub name: Option<String>,
    #[command(flatten)]
    pub adaptive: AdaptiveArgs,
}

/// Progressive rendering: any of these flags renders in passes until the image is good enough
/// (`--spp` is then ignored: `--spp-max` bounds the samples).
#[derive(Args, Debug, Clone, Default)]
pub struct AdaptiveArgs {
    /// Stop sampling an 8x8 block once its estimated relative error is at most this (0: only
    /// spp-max stops it) [default: 0.01 when progressive].
    #[arg(long, value_name = "X")]
    pub noise_threshold: Option<f64>,
    /// Samples every pixel gets, at least 2 [default: 4 when progressive].
    #[arg(long, value_name = "N")]
    pub spp_min: Option<u32>,
    /// Samples no pixel goes beyond [default: 256 when progressive].
    #[arg(long, value_name = "N")]
    pub spp_max: Option<u32>,
    /// End with the last finished pass after this many seconds of rendering.
    #[arg(long, value_name = "SECONDS")]
    pub time_limit: Option<f64>,
}

impl AdaptiveArgs {
    /// The stopping rules the flags ask for; None when no flag is given (a one-shot job).
    pub fn to_spec(&self) -> Result<Option<protocol::AdaptiveSpec>, Failure> {
        if self.noise_threshold.is_none()
            && self.spp_min.is_none()
            && self.spp_max.is_none()
            && self.time_limit.is_none()
        {
            return Ok(None);
        }
        let defaults = protocol::AdaptiveSpec::default();
        let spp_min = self.spp_min.unwrap_or(defaults.spp_min);
        let spec = protocol::AdaptiveSpec {
            noise_threshold: self.noise_threshold.unwrap_or(defaults.noise_threshold),
            spp_min,
            spp_max: self.spp_max.unwrap_or(defaults.spp_max.max(spp_min)),
            time_limit_s: self.time_limit,
        };
        spec.validate().map_err(Failure::usage)?;
        Ok(Some(spec))
    }
}

impl SettingsArgs {
    /// The job the flags ask for, its settings checked before anything is read or sent.
    pub fn to_spec(&self) -> Result<JobSpec, Failure> {
        let render = self.render.to_settings();
        render.validate().map_err(Failure::usage)?;
        Ok(JobSpec {
            name: self.name.clone(),
            render,
            frames: self.render.frames,
            tile_size: self.tile_size.unwrap_or(DEFAULT_TILE_SIZE),
            adaptive: self.adaptive.to_spec()?,
        })
    }
}

/// Why a command failed: the message printed (every cause in the chain) and the exit code
/// ([`exit`]: usage, scene, anything else).
#[derive(Debug)]
pub struct Failure {
    pub code: u8,
    pub message: String,
}

impl Failure {
    fn with(code: u8, error: impl Into<Box<dyn std::error::Error>>) -> Self {
        Failure {
            code,
            message: error_chain(error.into().as_ref()),
        }
    }

    /// Bad flags or settings.
    pub fn usage(error: impl Into<Box<dyn std::error::Error>>) -> Self {
        Self::with(exit::USAGE, error)
    }

    /// A scene that cannot be read or loaded.
    pub fn scene(error: impl Into<Box<dyn std::error::Error>>) -> Self {
        Self::with(exit::SCENE, error)
    }

    /// Anything else: the farm, the network, the disk.
    pub fn failed(error: impl Into<Box<dyn std::error::Error>>) -> Self {
        Self::with(exit::FAILURE, error)
    }

    /// Prints the failure for `command` and gives its exit code.
    fn report(&self, command: &str) -> ExitCode {
        eprintln!("coordinator {command}: {}", self.message);
        ExitCode::from(self.code)
    }
}

impl From<String> for Failure {
    fn from(message: String) -> Self {
        Failure {
            code: exit::FAILURE,
            message,
        }
    }
}

/// The exit code of a command that returned `result`.
fn finish(command: &str, result: Result<(), Failure>) -> ExitCode {
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(failure) => failure.report(command),
    }
}

/// Runs the parsed command line.
pub fn main(cli: Cli) -> ExitCode {
    match cli.command {
        Command::Serve(args) => serve::run(args),
        Command::Render(args) => render::run(args),
        Command::Submit(args) => submit::run(args),
        Command::Report(args) => report::run(args),
        Command::Jobs(args) => client::jobs(args),
        Command::Show(args) => client::show(args),
        Command::Cancel(args) => client::cancel(args),
        Command::Retry(args) => client::retry(args),
        Command::Download(args) => client::download(args),
        Command::Workers(args) => client::workers(args),
    }
}

fn runtime() -> Result<tokio::runtime::Runtime, String> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the async runtime: {e}"))
}

fn write_image(path: &Path, bytes: &[u8]) -> Result<(), String> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| format!("creating {}: {e}", parent.display()))?;
    }
    std::fs::write(path, bytes).map_err(|e| format!("writing {}: {e}", path.display()))
}

/// Downloads a finished job's image to `output` in the format its extension names (PNG, EXR
/// or PFM), or each frame of a frame-range job to `output` numbered (out.exr →
/// out_0003.exr). Returns the files written.
async fn download(
    client: &protocol::client::Client,
    job: &protocol::JobInfo,
    output: &Path,
) -> Result<Vec<PathBuf>, String> {
    let format = tracer_core::cli_args::check_output(output).map_err(|e| e.to_string())?;
    let mut written = Vec::new();
    for (frame, path) in output_files(job, output) {
        let bytes = client
            .image_in(job.id, frame, format)
            .await
            .map_err(|e| e.to_string())?;
        write_image(&path, &bytes)?;
        written.push(path);
    }
    Ok(written)
}

/// Where a finished job's images go for `-o output`: the job's one image to `output`, or each
/// frame of a frame-range job to `output` numbered, with the frame to ask for.
fn output_files(job: &protocol::JobInfo, output: &Path) -> Vec<(Option<u32>, PathBuf)> {
    match job.spec.frames {
        None => vec![(None, output.to_path_buf())],
        Some(range) => range
            .frames()
            .map(|frame| {
                let path = tracer_core::settings::numbered_path(output, frame);
                (Some(frame), path)
            })
            .collect(),
    }
}

/// Names what [`download`] wrote, briefly.
fn describe_written(written: &[PathBuf]) -> String {
    match written {
        [one] => one.display().to_string(),
        [first, .., last] => format!(
            "{} frames, {} … {}",
            written.len(),
            first.display(),
            last.display()
        ),
        [] => "nothing".to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tracer_core::RenderSettings;

    #[test]
    fn settings_default_like_the_tracer() {
        let cli = Cli::parse_from(["coordinator", "submit", "--server", "http://x", "a.scene"]);
        let Command::Submit(args) = cli.command else {
            panic!()
        };
        let spec = args.settings.to_spec().unwrap();
        assert_eq!(spec.render, RenderSettings::default());
        assert_eq!(spec.tile_size, DEFAULT_TILE_SIZE);
    }

    #[test]
    fn negative_camera_coordinates_parse_and_camera_flags_go_together() {
        let cli = Cli::parse_from([
            "coordinator",
            "render",
            "a.scene",
            "--camera-pos",
            "-10,4,10",
            "--look-at",
            "0,0,0",
            "--spp",
            "2",
            "--tile-size",
            "16",
        ]);
        let Command::Render(args) = cli.command else {
            panic!()
        };
        let spec = args.settings.to_spec().unwrap();
        let cam = spec.render.camera.unwrap();
        assert_eq!(cam.position, [-10.0, 4.0, 10.0]);
        assert_eq!(cam.up, [0.0, 1.0, 0.0]);
        assert_eq!((spec.render.spp, spec.tile_size), (2, 16));
        let submit = Cli::parse_from([
            "coordinator",
            "submit",
            "--server",
            "http://x",
            "a.scene",
            "--camera-pos",
            "-1,-2,-3",
            "--look-at",
            "0,0,0",
        ]);
        let Command::Submit(args) = submit.command else {
            panic!()
        };
        let cam = args.settings.to_spec().unwrap().render.camera.unwrap();
        assert_eq!(cam.position, [-1.0, -2.0, -3.0]);
        let half = Cli::try_parse_from(["coordinator", "render", "a.scene", "--look-at", "0,0,0"]);
        assert!(half.is_err());
    }

    #[test]
    fn a_missing_scene_file_is_a_scene_error_without_a_position() {
        let spec = JobSpec {
            name: None,
            render: RenderSettings::default(),
            frames: None,
            tile_size: DEFAULT_TILE_SIZE,
            adaptive: None,
        };
        let failure = collect_submission(Path::new("nosuch.scene"), spec).unwrap_err();
        assert_eq!(failure.code, exit::SCENE);
        assert_eq!(
            failure.message,
            "cannot read nosuch.scene: No such file or directory (os error 2)"
        );
    }

    #[test]
    fn bad_settings_and_outputs_are_usage_errors() {
        let cli = Cli::parse_from(["coordinator", "render", "a.scene", "--spp", "0"]);
        let Command::Render(args) = cli.command else {
            panic!()
        };
        let failure = args.settings.to_spec().unwrap_err();
        assert_eq!(failure.code, exit::USAGE);
        assert!(failure.message.contains("spp"), "{}", failure.message);
        let cli = Cli::parse_from(["coordinator", "render", "a.scene", "-o", "x.jpg", "-q"]);
        let Command::Render(args) = cli.command else {
            panic!()
        };
        assert!(args.output.quiet);
        let refused = args.output.path_for(&args.scene).unwrap_err();
        assert!(
            refused.to_string().contains(".png, .exr or .pfm"),
            "{refused}"
        );
    }
}
