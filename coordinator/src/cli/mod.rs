//! The `coordinator` command line: `serve`, `render` (the embedded one-command farm) and
//! `submit`. Flags are parsed into plain structs here; the commands build everything else.

mod render;
mod report;
mod serve;
mod submit;

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use clap::{Args, Parser, Subcommand};
use protocol::{JobSpec, DEFAULT_TILE_SIZE};
use tracer_core::settings::parse_vec3;
use tracer_core::{CameraOverride, CausticsSettings, FrameRange, RenderSettings, TextureFilter};

pub use submit::collect_submission;

#[derive(Parser, Debug)]
#[command(
    name = "coordinator",
    version,
    about = "Tessera render farm: serve a farm, render through an embedded one, or submit jobs"
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
}

/// Render settings, as `tracer render` takes them, plus the farm's tile size.
#[derive(Args, Debug, Clone)]
pub struct SettingsArgs {
    /// Image width in pixels [default: 800].
    #[arg(long)]
    pub width: Option<u32>,
    /// Image height in pixels [default: 600].
    #[arg(long)]
    pub height: Option<u32>,
    /// Samples per pixel [default: 4].
    #[arg(long)]
    pub spp: Option<u32>,
    /// Ray depth, the eye ray included [default: 5].
    #[arg(long)]
    pub depth: Option<u32>,
    /// Random seed [default: 0].
    #[arg(long)]
    pub seed: Option<u64>,
    /// Camera position x,y,z (with --look-at), replacing the scene's camera.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub camera_pos: Option<[f64; 3]>,
    /// Point the camera looks at, x,y,z.
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub look_at: Option<[f64; 3]>,
    /// Camera up vector x,y,z [default: 0,1,0].
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub up: Option<[f64; 3]>,
    /// Bilinear texture filtering instead of nearest texel.
    #[arg(long)]
    pub bilinear: bool,
    /// Render frames A through B (inclusive) of an animated scene as one job; the PNGs are
    /// written with the frame number inserted: out.png → out_0003.png.
    #[arg(long, conflicts_with = "frame")]
    pub frames: Option<FrameRange>,
    /// Render this frame of an animated scene (0-based) [default: 0].
    #[arg(long)]
    pub frame: Option<u32>,
    /// Caustics by photon mapping, even if the scene has no <caustics> element.
    #[arg(long, conflicts_with = "no_caustics")]
    pub caustics: bool,
    /// No caustics, even if the scene asks for them.
    #[arg(long)]
    pub no_caustics: bool,
    /// Caustic photons to emit (turns caustics on; overrides the scene's count).
    #[arg(long, conflicts_with = "no_caustics")]
    pub photons: Option<u32>,
    /// Caustic gather radius in scene units (turns caustics on; overrides the scene's).
    #[arg(long, conflicts_with = "no_caustics")]
    pub photon_radius: Option<f64>,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = DEFAULT_TILE_SIZE)]
    pub tile_size: u32,
    /// A name for job listings [default: the scene's file name].
    #[arg(long)]
    pub name: Option<String>,
}

impl SettingsArgs {
    pub fn to_spec(&self) -> Result<JobSpec, String> {
        let d = RenderSettings::default();
        let camera = match (self.camera_pos, self.look_at) {
            (Some(position), Some(look_at)) => Some(CameraOverride {
                position,
                look_at,
                up: self.up.unwrap_or([0.0, 1.0, 0.0]),
            }),
            (None, None) if self.up.is_none() => None,
            _ => return Err("--camera-pos and --look-at go together (--up needs both)".into()),
        };
        Ok(JobSpec {
            name: self.name.clone(),
            render: RenderSettings {
                width: self.width.unwrap_or(d.width),
                height: self.height.unwrap_or(d.height),
                spp: self.spp.unwrap_or(d.spp),
                max_depth: self.depth.unwrap_or(d.max_depth),
                seed: self.seed.unwrap_or(d.seed),
                camera,
                texture_filter: if self.bilinear {
                    TextureFilter::Bilinear
                } else {
                    d.texture_filter
                },
                frame: self.frame.unwrap_or(d.frame),
                caustics: CausticsSettings::from_flags(
                    self.caustics,
                    self.no_caustics,
                    self.photons,
                    self.photon_radius,
                ),
            },
            frames: self.frames,
            tile_size: self.tile_size,
        })
    }
}

/// Runs the parsed command line.
pub fn main(cli: Cli) -> ExitCode {
    match cli.command {
        Command::Serve(args) => serve::run(args),
        Command::Render(args) => render::run(args),
        Command::Submit(args) => submit::run(args),
        Command::Report(args) => report::run(args),
    }
}

fn runtime() -> Result<tokio::runtime::Runtime, String> {
    tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start the async runtime: {e}"))
}

fn write_png(path: &Path, png: &[u8]) -> Result<(), String> {
    if let Some(parent) = path.parent().filter(|p| !p.as_os_str().is_empty()) {
        std::fs::create_dir_all(parent)
            .map_err(|e| format!("creating {}: {e}", parent.display()))?;
    }
    std::fs::write(path, png).map_err(|e| format!("writing {}: {e}", path.display()))
}

/// Downloads a finished job's image to `output`, or each frame of a frame-range job to
/// `output` numbered (out.png → out_0003.png). Returns the files written.
async fn download(
    client: &protocol::client::Client,
    job: &protocol::JobInfo,
    output: &Path,
) -> Result<Vec<PathBuf>, String> {
    let Some(range) = job.spec.frames else {
        let png = client
            .image(job.id)
            .await
            .map_err(|e| submit::describe(&e))?;
        write_png(output, &png)?;
        return Ok(vec![output.to_path_buf()]);
    };
    let mut written = Vec::new();
    for frame in range.frames() {
        let png = client
            .frame_image(job.id, frame)
            .await
            .map_err(|e| submit::describe(&e))?;
        let path = tracer_core::settings::numbered_path(output, frame);
        write_png(&path, &png)?;
        written.push(path);
    }
    Ok(written)
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

/// Where the PNG goes when `-o` is not given: the scene's name with `.png`, here.
fn default_output(scene: &Path) -> PathBuf {
    let stem = scene
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_else(|| "render".into());
    PathBuf::from(format!("{stem}.png"))
}

/// Resolves on SIGINT or SIGTERM.
pub async fn stop_signal() {
    use tokio::signal::unix::{signal, SignalKind};
    match (
        signal(SignalKind::interrupt()),
        signal(SignalKind::terminate()),
    ) {
        (Ok(mut int), Ok(mut term)) => {
            tokio::select! {
                _ = int.recv() => {}
                _ = term.recv() => {}
            }
        }
        _ => {
            let _ = tokio::signal::ctrl_c().await;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

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
    fn camera_flags_go_together() {
        let cli = Cli::parse_from([
            "coordinator",
            "render",
            "a.scene",
            "--camera-pos",
            "-1,2,3",
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
        assert_eq!(cam.position, [-1.0, 2.0, 3.0]);
        assert_eq!(cam.up, [0.0, 1.0, 0.0]);
        assert_eq!((spec.render.spp, spec.tile_size), (2, 16));
        let half = Cli::parse_from(["coordinator", "render", "a.scene", "--look-at", "0,0,0"]);
        let Command::Render(args) = half.command else {
            panic!()
        };
        assert!(args.settings.to_spec().is_err());
        assert!(parse_vec3("1,2").is_err());
        assert!(parse_vec3("1,b,2").is_err());
    }
}
