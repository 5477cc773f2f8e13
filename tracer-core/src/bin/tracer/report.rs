//! `tracer report`: how fast a scene's image converges — error against run time, measured
//! against a high-sample reference, as a CSV, a Markdown table and a log–log plot.

use std::path::PathBuf;

use clap::Args;
use tracer_core::cli_args::load_scene;
use tracer_core::report::{
    measure, print_row, reference_image, timed_render, write_report, ReportMeta,
};
use tracer_core::RenderSettings;

use crate::Failure;

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

pub fn run(args: ReportArgs) -> Result<(), Failure> {
    if args.spp.is_empty() || args.spp.contains(&0) {
        return Err(Failure::Usage(
            "--spp needs sample counts of at least 1".into(),
        ));
    }
    if args.threads.contains(&0) {
        return Err(Failure::Usage("--threads must be at least 1".into()));
    }
    let scene = load_scene(&args.scene)?;
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        seed: args.seed,
        ..RenderSettings::default()
    };
    let all_cores = rayon::ThreadPoolBuilder::new().build()?;
    let (reference, reference_note) = reference_image(
        &scene,
        &settings,
        args.reference.as_deref(),
        args.reference_spp,
        &all_cores,
    )?;

    let threads = if args.threads.is_empty() {
        vec![rayon::current_num_threads()]
    } else {
        args.threads.clone()
    };
    let mut rows = Vec::new();
    for &n in &threads {
        let pool = rayon::ThreadPoolBuilder::new().num_threads(n).build()?;
        let config = format!("{n} thread{}", if n == 1 { "" } else { "s" });
        for &spp in &args.spp {
            let s = RenderSettings {
                spp,
                ..settings.clone()
            };
            let (image, seconds) = timed_render(&scene, &s, &pool)?;
            let row = measure(&config, spp, seconds, &image, &reference)?;
            print_row(&row);
            rows.push(row);
        }
    }

    let meta = ReportMeta {
        scene: args.scene.clone(),
        width: args.width,
        height: args.height,
        reference: reference_note,
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
