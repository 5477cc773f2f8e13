//! `tracer`: renders and benchmarks course scenes on this machine.

use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::Instant;

mod report;

use clap::{Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use tracer_core::cli_args::{
    error_chain, exit, load_scene, LoadError, OutputArgs, OutputError, RenderArgs,
};
use tracer_core::metrics::MetricsError;
use tracer_core::report::ReportError;
use tracer_core::settings::numbered_path;
use tracer_core::{Image, RenderError, RenderSettings, Renderer, Scene};

/// Every allocation on cache lines of its own: no false sharing between render threads
/// (see [`tracer_core::alloc`]).
#[global_allocator]
static ALLOC: tracer_core::alloc::OwnLines = tracer_core::alloc::OwnLines;

#[derive(Parser)]
#[command(
    name = "tracer",
    version,
    about = "Tessera's ray tracer: render CMU 15-462 scenes locally"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Render a scene to a PNG.
    Render {
        scene: PathBuf,
        #[command(flatten)]
        output: OutputArgs,
        #[command(flatten)]
        settings: RenderArgs,
        /// Worker threads (default: every core).
        #[arg(long)]
        threads: Option<usize>,
    },
    /// Measure error against run time over sample counts and thread counts, against a
    /// high-sample reference: report.csv, report.md and error_vs_time.png.
    Report(report::ReportArgs),
    /// Compare two PNGs: RMSE, PSNR and mean FLIP.
    Compare { image: PathBuf, reference: PathBuf },
    /// Measure BVH build time, ray throughput and a 1-spp render on the scene's camera.
    Bench {
        scene: PathBuf,
        #[arg(long, default_value_t = 800)]
        width: u32,
        #[arg(long, default_value_t = 600)]
        height: u32,
        #[arg(long)]
        threads: Option<usize>,
        /// Repetitions of each measurement; the fastest is reported.
        #[arg(long, default_value_t = 3)]
        repeats: usize,
        /// Print one JSON object instead of a table.
        #[arg(long)]
        json: bool,
    },
}

/// Why a command failed, which decides the exit code.
#[derive(Debug, thiserror::Error)]
pub enum Failure {
    #[error("{0}")]
    Usage(String),
    #[error(transparent)]
    Output(#[from] OutputError),
    #[error(transparent)]
    Load(#[from] LoadError),
    #[error(transparent)]
    Settings(#[from] RenderError),
    #[error("cannot read {path}")]
    Read {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("cannot write {path}")]
    Write {
        path: PathBuf,
        source: std::io::Error,
    },
    #[error("{path} is not an image")]
    NotAnImage {
        path: PathBuf,
        source: tracer_core::film::ImageError,
    },
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error(transparent)]
    Report(#[from] ReportError),
    #[error("cannot start the render threads")]
    Threads(#[from] rayon::ThreadPoolBuildError),
    #[error("cannot print JSON")]
    Json(#[from] serde_json::Error),
}

impl Failure {
    fn exit_code(&self) -> u8 {
        match self {
            Failure::Usage(_) | Failure::Output(_) | Failure::Settings(_) => exit::USAGE,
            Failure::Report(ReportError::Render(_)) => exit::USAGE,
            Failure::Load(_) => exit::SCENE,
            _ => exit::FAILURE,
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(failure) => {
            eprintln!("error: {}", error_chain(&failure));
            ExitCode::from(failure.exit_code())
        }
    }
}

fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool, Failure> {
    let mut builder = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        if n == 0 {
            return Err(Failure::Usage("--threads must be at least 1".into()));
        }
        builder = builder.num_threads(n);
    }
    Ok(builder.build()?)
}

fn run(cli: Cli) -> Result<(), Failure> {
    match cli.command {
        Command::Render {
            scene,
            output,
            settings,
            threads,
        } => {
            // Everything the flags can get wrong is refused before the scene is read.
            let path = output.path_for(&scene)?;
            let mut render = settings.to_settings();
            render.validate().map_err(RenderError::from)?;
            let pool = thread_pool(threads)?;
            let started = Instant::now();
            let scene = pool.install(|| load_scene(&scene))?;
            let Some(range) = settings.frames else {
                return render_frame(&scene, &render, &pool, &path, output.quiet, started);
            };
            range
                .validate(scene.frame_count())
                .map_err(|e| Failure::Usage(format!("--frames: {e}")))?;
            for f in range.frames() {
                render.frame = f;
                render_frame(
                    &scene,
                    &render,
                    &pool,
                    &numbered_path(&path, f),
                    output.quiet,
                    Instant::now(),
                )?;
            }
            Ok(())
        }
        Command::Report(args) => report::run(args),
        Command::Compare { image, reference } => {
            let read = |path: &PathBuf| {
                let bytes = std::fs::read(path).map_err(|source| Failure::Read {
                    path: path.clone(),
                    source,
                })?;
                Image::from_png_bytes(&bytes).map_err(|source| Failure::NotAnImage {
                    path: path.clone(),
                    source,
                })
            };
            let (a, b) = (read(&image)?, read(&reference)?);
            let m = tracer_core::metrics::Comparison::of(&a, &b)?;
            println!(
                "rmse {:.5}  psnr {:.2} dB  mean_flip {:.4}",
                m.rmse, m.psnr, m.mean_flip
            );
            Ok(())
        }
        Command::Bench {
            scene,
            width,
            height,
            threads,
            repeats,
            json,
        } => {
            let pool = thread_pool(threads)?;
            let scene = load_scene(&scene)?;
            let settings = RenderSettings {
                width,
                height,
                spp: 1,
                ..RenderSettings::default()
            };
            let report = pool.install(|| tracer_core::bench::run(&scene, &settings, repeats))?;
            if json {
                println!("{}", serde_json::to_string(&report)?);
            } else {
                println!("threads            {}", pool.current_num_threads());
                println!("triangles          {}", scene.stats.triangles);
                println!("bytes/triangle     {:.1}", report.bytes_per_triangle);
                println!(
                    "BVH build          {:.2} ms (median {:.2} ms)",
                    report.build_ms, report.build_ms_median
                );
                println!(
                    "primary rays       {:.2} Mrays/s ({} rays)",
                    report.primary_mrays, report.primary_rays
                );
                println!(
                    "incoherent rays    {:.2} Mrays/s ({} rays)",
                    report.incoherent_mrays, report.secondary_rays
                );
                println!("shadow rays        {:.2} Mrays/s", report.shadow_mrays);
                println!("1-spp render       {:.3} s", report.render_s);
            }
            Ok(())
        }
    }
}

/// Renders one frame of `scene` to `output`, reporting time and ray rate on stderr.
fn render_frame(
    scene: &Scene,
    settings: &RenderSettings,
    pool: &rayon::ThreadPool,
    output: &Path,
    quiet: bool,
    started: Instant,
) -> Result<(), Failure> {
    // Inside the pool: building a caustic map uses the same threads as rendering.
    let prepared = Instant::now();
    let renderer = pool.install(|| Renderer::new(scene, settings))?;
    if let Some(map) = renderer.caustics() {
        eprintln!(
            "caustics: {} photons emitted, {} stored, gather radius {}, built in {:.2} s",
            map.emitted(),
            map.len(),
            map.radius(),
            prepared.elapsed().as_secs_f64()
        );
    }
    let total = settings.width as u64 * settings.height as u64;
    let bar = if quiet || !std::io::IsTerminal::is_terminal(&std::io::stderr()) {
        ProgressBar::hidden()
    } else {
        ProgressBar::new(total).with_style(
            ProgressStyle::with_template("{bar:40} {percent:>3}% {elapsed_precise} ETA {eta}")
                .expect("static template"),
        )
    };
    let image = pool.install(|| renderer.render_image(&|done, _| bar.set_position(done)));
    bar.finish_and_clear();
    image.save(output).map_err(|source| Failure::Write {
        path: output.to_path_buf(),
        source,
    })?;
    let seconds = started.elapsed().as_secs_f64();
    let rays = renderer.rays_traced();
    eprintln!(
        "{}: {}x{} at {} spp in {seconds:.2} s, {rays} rays, {:.1} Mrays/s",
        output.display(),
        settings.width,
        settings.height,
        settings.spp,
        rays as f64 / seconds / 1e6
    );
    Ok(())
}
