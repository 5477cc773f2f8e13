//! `coordinator report`: error against run time through the embedded farm, one curve per
//! worker count (plus the in-process renderer as the baseline), so the farm's overhead and
//! scaling show on the same plot as the convergence.

use std::path::PathBuf;
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::Args;
use protocol::{JobSpec, JobState, DEFAULT_TILE_SIZE};
use tracer_core::cli_args::load_scene;
use tracer_core::convergence::Measurement;
use tracer_core::report::{
    measure, print_row, reference_image, timed_render, with_linear, write_report, ReportMeta,
};
use tracer_core::{Image, ImageFormat, RenderSettings};
use worker::available_cores;

use super::paired::{median_row, paired_markdown, runs_csv, Run};
use super::submit::{collect_submission, describe};
use super::Failure;
use crate::embedded::EmbeddedFarm;

#[derive(Args, Debug)]
pub struct ReportArgs {
    /// The scene file; its assets are found beside it (or in its parent folder).
    pub scene: PathBuf,
    /// Folder for report.csv, report.md and error_vs_time.png.
    #[arg(short, long, default_value = "report")]
    pub output: PathBuf,
    /// Use this PNG as the reference instead of rendering one.
    #[arg(long)]
    pub reference: Option<PathBuf>,
    /// Samples per pixel of the rendered reference.
    #[arg(long, default_value_t = 256)]
    pub reference_spp: u32,
    /// Sample counts to measure.
    #[arg(long, value_delimiter = ',', default_value = "1,2,4,8,16,32")]
    pub spp: Vec<u32>,
    /// Farm worker counts to measure, one curve each [default: 1 and every core].
    #[arg(long, value_delimiter = ',')]
    pub workers: Vec<usize>,
    /// Render threads in all, split between the workers [default: every core].
    #[arg(long)]
    pub threads: Option<usize>,
    /// Leave out the in-process baseline curve.
    #[arg(long)]
    pub no_baseline: bool,
    #[arg(long, default_value_t = 400)]
    pub width: u32,
    #[arg(long, default_value_t = 300)]
    pub height: u32,
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Tile edge in pixels.
    #[arg(long, default_value_t = DEFAULT_TILE_SIZE)]
    pub tile_size: u32,
    /// Also render progressive jobs with this noise threshold, one per uniform run, each with
    /// that run's wall time as its time limit: adaptive against uniform at equal time.
    #[arg(long, value_name = "X")]
    pub adaptive: Option<f64>,
    /// Runs per sample count and worker count (each uniform run followed by its adaptive
    /// one); the rows are the median of each column, and runs.csv holds every run.
    #[arg(long, default_value_t = 1)]
    pub repeats: u32,
}

pub fn run(args: ReportArgs) -> ExitCode {
    worker::init_logging("warn");
    super::finish("report", report(args))
}

fn plural(n: usize) -> &'static str {
    if n == 1 {
        ""
    } else {
        "s"
    }
}

/// Every image is compared as the 8-bit PNG a user gets, the reference included, so the
/// farm's PNGs and the in-process renders are measured alike.
fn as_delivered(image: &Image) -> Result<Image, Failure> {
    Image::from_png_bytes(&image.to_png()).map_err(Failure::failed)
}

fn report(args: ReportArgs) -> Result<(), Failure> {
    if args.spp.is_empty() || args.spp.contains(&0) {
        return Err(Failure::usage("--spp needs sample counts of at least 1"));
    }
    if args.repeats == 0 {
        return Err(Failure::usage("--repeats needs at least 1"));
    }
    let threads = args.threads.unwrap_or_else(available_cores).max(1);
    let mut workers = args.workers.clone();
    if workers.is_empty() {
        workers = vec![1, threads];
        workers.dedup();
    }
    if let Some(bad) = workers.iter().find(|&&w| w == 0 || w > threads) {
        return Err(Failure::usage(format!(
            "--workers {bad}: each count must be between 1 and the {threads} thread(s)"
        )));
    }
    let scene = load_scene(&args.scene).map_err(Failure::scene)?;
    let settings = RenderSettings {
        width: args.width,
        height: args.height,
        seed: args.seed,
        ..RenderSettings::default()
    };
    settings.validate().map_err(Failure::usage)?;
    let pool = rayon::ThreadPoolBuilder::new()
        .num_threads(threads)
        .build()
        .map_err(Failure::failed)?;

    let (reference, reference_note) = reference_image(
        &scene,
        &settings,
        args.reference.as_deref(),
        args.reference_spp,
        &pool,
    )
    .map_err(Failure::failed)?;
    // A rendered reference is linear f32: the linear columns measure against it (a PNG
    // given as the reference has no linear pixels to offer).
    let reference_linear = args.reference.is_none().then(|| reference.clone());
    // Compared as delivered, like every measured image.
    let reference = as_delivered(&reference)?;
    let measure_both = |config: &str, spp: u32, seconds: f64, delivered: &Image, linear: &Image| {
        let row = measure(config, spp, seconds, delivered, &reference)?;
        match &reference_linear {
            Some(lin) => with_linear(row, linear, lin),
            None => Ok(row),
        }
    };

    let mut rows: Vec<Measurement> = Vec::new();
    let mut record = |row: Measurement| {
        print_row(&row);
        rows.push(row);
    };

    if !args.no_baseline {
        let config = format!("in-process: {threads} thread{}", plural(threads));
        for &spp in &args.spp {
            let s = RenderSettings {
                spp,
                ..settings.clone()
            };
            let (image, seconds) = timed_render(&scene, &s, &pool).map_err(Failure::failed)?;
            record(
                measure_both(&config, spp, seconds, &as_delivered(&image)?, &image)
                    .map_err(Failure::failed)?,
            );
        }
    }

    let runtime = super::runtime()?;
    let mut runs: Vec<Run> = Vec::new();
    for &n in &workers {
        let config = format!("farm: {n} worker{}", plural(n));
        let adaptive_config = args
            .adaptive
            .map(|threshold| format!("{config}, adaptive {threshold}"));
        let largest = args.spp.iter().max().copied().unwrap_or(1).max(2);
        let rendered = runtime.block_on(async {
            let farm = EmbeddedFarm::start(None, n, threads, None).await?;
            let mut out = Vec::new();
            let result = async {
                // Each uniform run is followed at once by its adaptive run, so that a pair
                // sees the same load on the machine (the farm's times drift with it).
                for &spp in &args.spp {
                    for repeat in 0..args.repeats {
                        let spec = JobSpec {
                            name: None,
                            render: RenderSettings {
                                spp,
                                ..settings.clone()
                            },
                            frames: None,
                            tile_size: args.tile_size,
                            adaptive: None,
                        };
                        let (image, seconds, info) =
                            render_through(&farm, &args.scene, spec).await?;
                        // Its render time: first lease to image stored.
                        let rendering = info.elapsed_s.unwrap_or(seconds);
                        out.push((config.clone(), spp, repeat, image, seconds, None));
                        let Some(threshold) = args.adaptive else {
                            continue;
                        };
                        // The same time, spent where the error estimate says it is needed.
                        // The time limit counts from the job's first lease, so it is the
                        // uniform job's time from its first lease to its stored image:
                        // submission, upload and download then cost both jobs alike, and the
                        // two rows' seconds compare.
                        let spec = JobSpec {
                            name: None,
                            render: settings.clone(),
                            frames: None,
                            tile_size: args.tile_size,
                            adaptive: Some(protocol::AdaptiveSpec {
                                noise_threshold: threshold,
                                // The first pass straight to 8 spp: two passes fewer than
                                // from 2, and the plan decides nothing before 8 anyway.
                                spp_min: 8,
                                spp_max: 4 * largest,
                                time_limit_s: Some(rendering),
                            }),
                        };
                        let (image, seconds, info) =
                            render_through(&farm, &args.scene, spec).await?;
                        let mean = info.spp_mean.unwrap_or(0.0);
                        let label = adaptive_config.clone().unwrap_or_default();
                        out.push((label, spp, repeat, image, seconds, Some(mean)));
                    }
                }
                Ok::<(), Failure>(())
            }
            .await;
            farm.shutdown().await;
            result.map(|()| out)
        })?;
        for (config, spp, repeat, image, seconds, spp_mean) in rendered {
            // An adaptive row's spp is its mean, rounded.
            let shown = spp_mean.map_or(spp, |m| m.round() as u32);
            let row = measure_both(&config, shown, seconds, &image.png, &image.linear)
                .map_err(Failure::failed)?;
            print_row(&row);
            runs.push(Run {
                workers: n,
                budget: spp,
                repeat,
                adaptive: spp_mean.is_some(),
                spp_mean: spp_mean.unwrap_or(spp as f64),
                row,
            });
        }
    }
    // Uniform rows before adaptive ones, each the median of its runs.
    let mut labels: Vec<&str> = Vec::new();
    for run in &runs {
        if !labels.contains(&run.row.config.as_str()) {
            labels.push(&run.row.config);
        }
    }
    labels.sort_by_key(|l| l.contains("adaptive"));
    for label in labels {
        for &spp in &args.spp {
            let same: Vec<&Run> = runs
                .iter()
                .filter(|r| r.row.config == label && r.budget == spp)
                .collect();
            if let Some(row) = median_row(&same) {
                rows.push(row);
            }
        }
    }

    let meta = ReportMeta {
        scene: args.scene.clone(),
        width: args.width,
        height: args.height,
        reference: reference_note,
        notes: format!(
            "\"farm: N workers\" renders through the embedded farm (a loopback coordinator and \
             N in-process workers sharing {threads} render thread(s), {} px tiles): seconds run from \
             submitting the scene and its assets over HTTP to holding the finished PNG. \
             \"in-process\" is the tracer alone on the same threads. \"adaptive X\" rows are \
             progressive jobs (noise threshold X, 8..4x the largest spp) whose time limit is the \
             render time (first lease to stored image) of the uniform run just before it: \
             their spp is the mean. {} Every image, the reference included, is compared as the \
             8-bit PNG a user gets; a rendered reference also gives the f32 columns, each \
             image's linear pixels (the job's PFM, fetched after its time is taken).",
            args.tile_size,
            if args.repeats > 1 {
                format!(
                    "Farm rows: each column the median of {} runs (runs.csv lists them).",
                    args.repeats
                )
            } else {
                String::new()
            }
        ),
    };
    write_report(&args.output, &meta, &rows).map_err(Failure::failed)?;
    let write = |name: &str, text: String| {
        std::fs::write(args.output.join(name), text)
            .map_err(|e| Failure::failed(format!("writing {}/{name}: {e}", args.output.display())))
    };
    write("runs.csv", runs_csv(&runs))?;
    if args.adaptive.is_some() {
        let md = args.output.join("report.md");
        let mut text = std::fs::read_to_string(&md)
            .map_err(|e| Failure::failed(format!("reading {}: {e}", md.display())))?;
        text += &paired_markdown(&runs);
        write("report.md", text)?;
    }
    eprintln!(
        "wrote {}/report.csv, runs.csv, report.md and error_vs_time.png",
        args.output.display()
    );
    Ok(())
}

/// A farm job's image: the PNG a user gets, decoded, and the linear f32 pixels.
struct FarmImage {
    png: Image,
    linear: Image,
}

/// Submits one job to the farm, waits for it and returns the decoded image with the wall time
/// from submission to download of the PNG, and the finished job. The linear image is fetched
/// after the time is taken.
async fn render_through(
    farm: &EmbeddedFarm,
    scene: &std::path::Path,
    spec: JobSpec,
) -> Result<(FarmImage, f64, protocol::JobInfo), Failure> {
    let submission = collect_submission(scene, spec)?;
    let client = farm.client();
    let started = Instant::now();
    let job = client.submit(&submission).await.map_err(describe)?;
    let finished = loop {
        let info = client.job(job.id).await.map_err(describe)?;
        if info.state.is_finished() {
            break info;
        }
        tokio::time::sleep(Duration::from_millis(5)).await;
    };
    if finished.state != JobState::Done {
        return Err(Failure::failed(format!(
            "job {} ended {}: {}",
            job.id,
            finished.state.as_str(),
            finished.error.unwrap_or_default()
        )));
    }
    let png = client.image(job.id).await.map_err(describe)?;
    let seconds = started.elapsed().as_secs_f64();
    let png = Image::from_png_bytes(&png).map_err(Failure::failed)?;
    let pfm = client
        .image_in(job.id, None, ImageFormat::Pfm)
        .await
        .map_err(describe)?;
    let linear = Image::from_pfm_bytes(&pfm).map_err(Failure::failed)?;
    Ok((FarmImage { png, linear }, seconds, finished))
}
