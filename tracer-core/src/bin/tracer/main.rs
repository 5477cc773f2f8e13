//! `tracer`: renders and benchmarks course scenes on this machine.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::Instant;

mod report;

use clap::{Args, Parser, Subcommand};
use indicatif::{ProgressBar, ProgressStyle};
use tracer_core::settings::{numbered_path, parse_vec3};
use tracer_core::{
    CameraOverride, CausticsSettings, FrameRange, RenderSettings, Renderer, Scene, TextureFilter,
};

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
        /// Output PNG.
        #[arg(short, long, default_value = "out.png")]
        output: PathBuf,
        #[command(flatten)]
        settings: SettingsArgs,
        /// Worker threads (default: every core).
        #[arg(long)]
        threads: Option<usize>,
        /// No progress bar.
        #[arg(long, short)]
        quiet: bool,
        /// Render this frame of an animated scene (0-based), to the output as named.
        #[arg(long, conflicts_with = "frames")]
        frame: Option<u32>,
        /// Render frames A through B inclusive (A..B), each to the output name with the
        /// frame number inserted: out.png → out_0003.png.
        #[arg(long)]
        frames: Option<FrameRange>,
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

/// Settings shared by every command that renders.
#[derive(Args, Clone, Debug)]
pub struct SettingsArgs {
    #[arg(long, default_value_t = 800)]
    width: u32,
    #[arg(long, default_value_t = 600)]
    height: u32,
    /// Samples per pixel (stratified); 1 traces through pixel centres.
    #[arg(long, default_value_t = 4)]
    spp: u32,
    /// Ray levels, the eye ray included (the course's 5 allows 4 bounces).
    #[arg(long, default_value_t = 5)]
    depth: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
    /// Camera position x,y,z (with --look-at).
    #[arg(long, value_parser = parse_vec3, requires = "look_at")]
    camera_pos: Option<[f64; 3]>,
    /// Point the camera looks at, x,y,z.
    #[arg(long, value_parser = parse_vec3, requires = "camera_pos")]
    look_at: Option<[f64; 3]>,
    /// Camera up vector x,y,z.
    #[arg(long, value_parser = parse_vec3, default_value = "0,1,0")]
    up: [f64; 3],
    /// Bilinear texture filtering instead of nearest texel.
    #[arg(long)]
    bilinear: bool,
    /// Caustics by photon mapping, even if the scene has no <caustics> element.
    #[arg(long, conflicts_with = "no_caustics")]
    caustics: bool,
    /// No caustics, even if the scene asks for them.
    #[arg(long)]
    no_caustics: bool,
    /// Caustic photons to emit (turns caustics on; overrides the scene's count).
    #[arg(long, conflicts_with = "no_caustics")]
    photons: Option<u32>,
    /// Caustic gather radius in scene units (turns caustics on; overrides the scene's).
    #[arg(long, conflicts_with = "no_caustics")]
    photon_radius: Option<f64>,
}

impl SettingsArgs {
    fn to_settings(&self) -> RenderSettings {
        RenderSettings {
            width: self.width,
            height: self.height,
            spp: self.spp,
            max_depth: self.depth,
            seed: self.seed,
            camera: self
                .camera_pos
                .zip(self.look_at)
                .map(|(position, look_at)| CameraOverride {
                    position,
                    look_at,
                    up: self.up,
                }),
            texture_filter: if self.bilinear {
                TextureFilter::Bilinear
            } else {
                TextureFilter::Nearest
            },
            frame: 0,
            caustics: CausticsSettings::from_flags(
                self.caustics,
                self.no_caustics,
                self.photons,
                self.photon_radius,
            ),
        }
    }
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    match run(cli) {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

fn thread_pool(threads: Option<usize>) -> Result<rayon::ThreadPool, String> {
    let mut builder = rayon::ThreadPoolBuilder::new();
    if let Some(n) = threads {
        if n == 0 {
            return Err("--threads must be at least 1".into());
        }
        builder = builder.num_threads(n);
    }
    builder.build().map_err(|e| e.to_string())
}

fn run(cli: Cli) -> Result<(), String> {
    match cli.command {
        Command::Render {
            scene,
            output,
            settings,
            threads,
            quiet,
            frame,
            frames,
        } => {
            let mut settings = settings.to_settings();
            let pool = thread_pool(threads)?;
            let started = Instant::now();
            let scene = pool
                .install(|| Scene::load(&scene))
                .map_err(|e| e.to_string())?;
            let Some(range) = frames else {
                settings.frame = frame.unwrap_or(0);
                return render_frame(&scene, &settings, &pool, &output, quiet, started);
            };
            range
                .validate(scene.frame_count())
                .map_err(|e| format!("--frames: {e}"))?;
            for f in range.frames() {
                settings.frame = f;
                render_frame(
                    &scene,
                    &settings,
                    &pool,
                    &numbered_path(&output, f),
                    quiet,
                    Instant::now(),
                )?;
            }
            Ok(())
        }
        Command::Report(args) => report::run(args),
        Command::Compare { image, reference } => {
            let read = |p: &PathBuf| {
                std::fs::read(p)
                    .map_err(|e| format!("cannot read {}: {e}", p.display()))
                    .and_then(|b| tracer_core::Image::from_png_bytes(&b))
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
            let scene = Scene::load(&scene).map_err(|e| e.to_string())?;
            let settings = RenderSettings {
                width,
                height,
                spp: 1,
                ..RenderSettings::default()
            };
            let report = pool.install(|| tracer_core::bench::run(&scene, &settings, repeats))?;
            if json {
                println!(
                    "{}",
                    serde_json::to_string(&report).map_err(|e| e.to_string())?
                );
            } else {
                println!("threads            {}", pool.current_num_threads());
                println!("triangles          {}", scene.stats.triangles);
                println!("BVH build          {:.2} ms", report.build_ms);
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
    output: &std::path::Path,
    quiet: bool,
    started: Instant,
) -> Result<(), String> {
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
    image
        .write_png(output)
        .map_err(|e| format!("cannot write {}: {e}", output.display()))?;
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
