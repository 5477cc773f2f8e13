//! `tracer report`: how fast a scene's image converges — error against run time, measured
//! against a high-sample reference, as a CSV, a Markdown table and a log–log plot.

use std::path::PathBuf;
use std::time::Instant;

use clap::Args;
use tracer_core::report::{measure, write_report, ReportMeta, REFERENCE_SEED_SALT};
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
            let row = measure(&config, spp, seconds, &image, &reference)?;
            eprintln!(
                "{config}, {spp} spp: {seconds:.3} s, RMSE {:.5}, relMSE {:.5}, FLIP {:.4}",
                row.rmse, row.rel_mse, row.mean_flip
            );
            rows.push(row);
        }
    }

    let meta = ReportMeta {
        scene: args.scene.clone(),
        width: args.width,
        height: args.height,
        reference: match &args.reference {
            Some(p) => format!("`{}`", p.display()),
            None => format!(
                "rendered at {} spp with an independent seed",
                args.reference_spp
            ),
        },
        notes: "Each configuration renders in-process with the given number of threads; \
                seconds are wall time of the render alone (scene loaded once)."
            .into(),
    };
    write_report(&args.output, &meta, &rows)?;
    eprintln!(
        "wrote {}/report.csv, report.md and error_vs_time.png",
        args.output.display()
    );
    Ok(())
}
