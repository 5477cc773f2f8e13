//! `tracer report`: how fast a scene's image converges — error against run time, measured
//! against a high-sample reference, as a CSV, a Markdown table and a log–log plot.

use std::fmt::Write as _;
use std::path::{Path, PathBuf};
use std::time::Instant;

use clap::Args;
use plotters::prelude::*;
use tracer_core::convergence::{log_log_slope, Measurement};
use tracer_core::metrics::{mean_flip, rel_mse, rmse, REL_MSE_EPSILON};
use tracer_core::{Image, RenderSettings, Renderer, Scene};

#[derive(Args, Debug)]
pub struct ReportArgs {
    scene: PathBuf,
    /// Folder for report.csv, report.md and error_vs_time.png.
    #[arg(short, long, default_value = "report")]
    output: PathBuf,
    /// Use this PNG as the reference instead of rendering one.
    #[arg(long)]
    reference: Option<PathBuf>,
    /// Samples per pixel of the rendered reference.
    #[arg(long, default_value_t = 256)]
    reference_spp: u32,
    /// Sample counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16,32")]
    spp: Vec<u32>,
    /// Thread counts to measure, one curve each (default: every core).
    #[arg(long, value_delimiter = ',')]
    threads: Vec<usize>,
    #[arg(long, default_value_t = 400)]
    width: u32,
    #[arg(long, default_value_t = 300)]
    height: u32,
    #[arg(long, default_value_t = 0)]
    seed: u64,
}

/// The reference uses a seed no measured render uses, so its noise is independent of theirs.
const REFERENCE_SEED_SALT: u64 = 0x5eed_0000_0000_0001;

pub fn run(args: ReportArgs) -> Result<(), String> {
    if args.spp.is_empty() || args.spp.contains(&0) {
        return Err("--spp needs sample counts of at least 1".into());
    }
    let scene = Scene::load(&args.scene).map_err(|e| e.to_string())?;
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        seed: args.seed,
        ..RenderSettings::default()
    };
    let reference = match &args.reference {
        Some(path) => {
            let bytes =
                std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
            let image = Image::from_png_bytes(&bytes)?;
            if (image.width, image.height) != (args.width, args.height) {
                return Err(format!(
                    "the reference is {}x{}, but the report renders {}x{} (set --width/--height)",
                    image.width, image.height, args.width, args.height
                ));
            }
            image
        }
        None => {
            eprintln!("rendering the reference at {} spp…", args.reference_spp);
            let s = RenderSettings {
                spp: args.reference_spp,
                seed: args.seed ^ REFERENCE_SEED_SALT,
                ..settings.clone()
            };
            Renderer::new(&scene, &s)?.render_image(&|_, _| {})
        }
    };

    let threads = if args.threads.is_empty() {
        vec![rayon::current_num_threads()]
    } else {
        args.threads.clone()
    };
    let mut rows = Vec::new();
    for &n in &threads {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .map_err(|e| e.to_string())?;
        let config = format!("{n} thread{}", if n == 1 { "" } else { "s" });
        for &spp in &args.spp {
            let s = RenderSettings {
                spp,
                ..settings.clone()
            };
            let renderer = Renderer::new(&scene, &s)?;
            let started = Instant::now();
            let image = pool.install(|| renderer.render_image(&|_, _| {}));
            let seconds = started.elapsed().as_secs_f64();
            let row = Measurement {
                config: config.clone(),
                spp,
                seconds,
                rmse: rmse(&image, &reference)?,
                rel_mse: rel_mse(&image, &reference)?,
                mean_flip: mean_flip(&image, &reference)?,
            };
            eprintln!(
                "{config}, {spp} spp: {seconds:.3} s, RMSE {:.5}, relMSE {:.5}, FLIP {:.4}",
                row.rmse, row.rel_mse, row.mean_flip
            );
            rows.push(row);
        }
    }

    std::fs::create_dir_all(&args.output)
        .map_err(|e| format!("cannot create {}: {e}", args.output.display()))?;
    let write = |name: &str, bytes: &[u8]| {
        let path = args.output.join(name);
        std::fs::write(&path, bytes).map_err(|e| format!("cannot write {}: {e}", path.display()))
    };
    write("report.csv", csv(&rows).as_bytes())?;
    write("report.md", markdown(&args, &rows).as_bytes())?;
    write("error_vs_time.png", &plot(&args.scene, &rows)?)?;
    eprintln!(
        "wrote {}/report.csv, report.md and error_vs_time.png",
        args.output.display()
    );
    Ok(())
}

fn csv(rows: &[Measurement]) -> String {
    let mut out = String::from("config,spp,seconds,rmse,rel_mse,mean_flip\n");
    for r in rows {
        let _ = writeln!(
            out,
            "{},{},{:.6},{:.6},{:.6},{:.6}",
            r.config, r.spp, r.seconds, r.rmse, r.rel_mse, r.mean_flip
        );
    }
    out
}

fn configs(rows: &[Measurement]) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    for r in rows {
        if !out.contains(&r.config) {
            out.push(r.config.clone());
        }
    }
    out
}

fn markdown(args: &ReportArgs, rows: &[Measurement]) -> String {
    let mut out = format!(
        "# Error against time: {}\n\n{}×{}; reference: {}.\n\n\
         Metrics against the reference: RMSE over linear RGB clamped to [0,1]; relMSE = mean of \
         (x − ref)² / (ref² + ε) with ε = {REL_MSE_EPSILON}; mean FLIP (NVIDIA's perceptual \
         metric, 8-bit images, 67 pixels per degree).\n\n\
         | config | spp | seconds | RMSE | relMSE | mean FLIP |\n|---|---:|---:|---:|---:|---:|\n",
        args.scene.display(),
        args.width,
        args.height,
        match &args.reference {
            Some(p) => format!("`{}`", p.display()),
            None => format!(
                "rendered at {} spp with an independent seed",
                args.reference_spp
            ),
        }
    );
    for r in rows {
        let _ = writeln!(
            out,
            "| {} | {} | {:.3} | {:.5} | {:.5} | {:.4} |",
            r.config, r.spp, r.seconds, r.rmse, r.rel_mse, r.mean_flip
        );
    }
    out += "\nFitted slope of log RMSE against log time (Monte Carlo theory: about −0.5 once \
            noise dominates; aliasing and bias flatten it at low sample counts):\n\n";
    for config in configs(rows) {
        let points: Vec<(f64, f64)> = rows
            .iter()
            .filter(|r| r.config == config)
            .map(|r| (r.seconds, r.rmse))
            .collect();
        match log_log_slope(&points) {
            Some(slope) => {
                let _ = writeln!(out, "- {config}: **{slope:.3}**");
            }
            None => {
                let _ = writeln!(out, "- {config}: not enough points to fit");
            }
        }
    }
    out += "\n![error against time](error_vs_time.png)\n";
    out
}

/// Finds a TrueType font for the plot's labels (Debian's fonts-dejavu-core).
fn register_font() -> Result<(), String> {
    const CANDIDATES: [&str; 3] = [
        "/usr/share/fonts/truetype/dejavu/DejaVuSans.ttf",
        "/usr/share/fonts/TTF/DejaVuSans.ttf",
        "/usr/share/fonts/dejavu/DejaVuSans.ttf",
    ];
    let path = CANDIDATES
        .iter()
        .find(|p| Path::new(p).is_file())
        .ok_or("no DejaVuSans.ttf found for the plot's labels: install fonts-dejavu-core")?;
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {path}: {e}"))?;
    // Plotters keeps registered fonts for the life of the process.
    plotters::style::register_font(
        "sans-serif",
        FontStyle::Normal,
        Box::leak(bytes.into_boxed_slice()),
    )
    .map_err(|_| format!("{path} is not a usable font"))
}

fn plot(scene: &Path, rows: &[Measurement]) -> Result<Vec<u8>, String> {
    register_font()?;
    let (w, h) = (900u32, 600u32);
    let mut buffer = vec![255u8; (w * h * 3) as usize];
    let positive = |v: f64| v.is_finite() && v > 0.0;
    let xs: Vec<f64> = rows
        .iter()
        .map(|r| r.seconds)
        .filter(|v| positive(*v))
        .collect();
    let ys: Vec<f64> = rows
        .iter()
        .map(|r| r.rmse)
        .filter(|v| positive(*v))
        .collect();
    if xs.is_empty() || ys.is_empty() {
        return Err("no positive times and errors to plot".into());
    }
    let range = |v: &[f64]| {
        let lo = v.iter().cloned().fold(f64::INFINITY, f64::min);
        let hi = v.iter().cloned().fold(f64::NEG_INFINITY, f64::max);
        (lo / 1.5)..(hi * 1.5)
    };
    {
        let root = BitMapBackend::with_buffer(&mut buffer, (w, h)).into_drawing_area();
        let err = |e: DrawingAreaErrorKind<_>| e.to_string();
        root.fill(&WHITE).map_err(err)?;
        let title = format!(
            "RMSE against render time — {}",
            scene.file_name().map_or_else(
                || scene.display().to_string(),
                |n| n.to_string_lossy().into_owned()
            )
        );
        let mut chart = ChartBuilder::on(&root)
            .caption(title, ("sans-serif", 24))
            .margin(16)
            .x_label_area_size(48)
            .y_label_area_size(72)
            .build_cartesian_2d(range(&xs).log_scale(), range(&ys).log_scale())
            .map_err(err)?;
        chart
            .configure_mesh()
            .x_desc("wall time (s)")
            .y_desc("RMSE")
            .label_style(("sans-serif", 16))
            .draw()
            .map_err(err)?;
        for (i, config) in configs(rows).iter().enumerate() {
            let color = Palette99::pick(i).to_rgba();
            let points: Vec<(f64, f64)> = rows
                .iter()
                .filter(|r| &r.config == config && positive(r.seconds) && positive(r.rmse))
                .map(|r| (r.seconds, r.rmse))
                .collect();
            chart
                .draw_series(LineSeries::new(points.clone(), color.stroke_width(2)))
                .map_err(err)?
                .label(config.clone())
                .legend(move |(x, y)| {
                    PathElement::new([(x, y), (x + 20, y)], color.stroke_width(2))
                });
            chart
                .draw_series(points.iter().map(|&p| Circle::new(p, 4, color.filled())))
                .map_err(err)?;
        }
        chart
            .configure_series_labels()
            .background_style(WHITE.mix(0.8))
            .border_style(BLACK)
            .label_font(("sans-serif", 16))
            .draw()
            .map_err(err)?;
        root.present().map_err(err)?;
    }
    let image = Image::from_pixels(w, h, buffer.iter().map(|&b| b as f32 / 255.0).collect())?;
    Ok(image.to_png())
}
