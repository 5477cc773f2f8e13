//! Writing an error-against-time report: `report.csv`, `report.md` (the table and the fitted
//! log–log slope per configuration) and `error_vs_time.png` (one curve per configuration).
//! Shared by `tracer report` (thread counts) and `coordinator report` (farm worker counts).

use std::fmt::Write as _;
use std::path::{Path, PathBuf};

use plotters::prelude::*;

use crate::convergence::{log_log_slope, Measurement};
use crate::film::ImageError;
use crate::metrics::{mean_flip, rel_mse, rmse, MetricsError, REL_MSE_EPSILON};
use crate::render::RenderError;
use crate::{Image, RenderSettings, Renderer, Scene};

/// Why a report could not be made.
#[derive(Debug, thiserror::Error)]
pub enum ReportError {
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
    #[error("the reference {path}")]
    Reference { path: PathBuf, source: ImageError },
    #[error(
        "the reference is {got_width}x{got_height}, but the report renders {width}x{height} \
         (set --width/--height)"
    )]
    ReferenceSize {
        got_width: u32,
        got_height: u32,
        width: u32,
        height: u32,
    },
    #[error(transparent)]
    Render(#[from] RenderError),
    #[error(transparent)]
    Metrics(#[from] MetricsError),
    #[error("cannot plot: {0}")]
    Plot(String),
}

/// Seeds the rendered reference apart from every measured render, so its noise is
/// independent of theirs.
pub const REFERENCE_SEED_SALT: u64 = 0x5eed_0000_0000_0001;

/// What the report's header says about how it was made.
#[derive(Clone, Debug)]
pub struct ReportMeta {
    pub scene: PathBuf,
    pub width: u32,
    pub height: u32,
    /// How the reference was obtained, e.g. "rendered at 256 spp with an independent seed".
    pub reference: String,
    /// A sentence on what the configurations are (threads, farm workers…).
    pub notes: String,
}

/// The reference a report measures against: the PNG at `path` (which must have the report's
/// size), or else the scene rendered at `reference_spp` with a seed no measured render uses.
/// Returns the image and a phrase saying where it came from.
pub fn reference_image(
    scene: &Scene,
    settings: &RenderSettings,
    path: Option<&Path>,
    reference_spp: u32,
    pool: &rayon::ThreadPool,
) -> Result<(Image, String), ReportError> {
    if let Some(path) = path {
        let bytes = std::fs::read(path).map_err(|source| ReportError::Read {
            path: path.to_path_buf(),
            source,
        })?;
        let image = Image::from_png_bytes(&bytes).map_err(|source| ReportError::Reference {
            path: path.to_path_buf(),
            source,
        })?;
        if (image.width, image.height) != (settings.width, settings.height) {
            return Err(ReportError::ReferenceSize {
                got_width: image.width,
                got_height: image.height,
                width: settings.width,
                height: settings.height,
            });
        }
        return Ok((image, format!("`{}`", path.display())));
    }
    eprintln!("rendering the reference at {reference_spp} spp…");
    let s = RenderSettings {
        spp: reference_spp,
        seed: settings.seed ^ REFERENCE_SEED_SALT,
        ..settings.clone()
    };
    let (image, _) = timed_render(scene, &s, pool)?;
    Ok((
        image,
        format!("rendered in-process at {reference_spp} spp with an independent seed"),
    ))
}

/// Renders the whole image on `pool`; returns it with the wall time of the render alone.
pub fn timed_render(
    scene: &Scene,
    settings: &RenderSettings,
    pool: &rayon::ThreadPool,
) -> Result<(Image, f64), ReportError> {
    let renderer = Renderer::new(scene, settings)?;
    let started = std::time::Instant::now();
    let image = pool.install(|| renderer.render_image(&|_, _| {}));
    Ok((image, started.elapsed().as_secs_f64()))
}

/// Prints one measurement as a progress line.
pub fn print_row(row: &Measurement) {
    let linear = match (row.rmse_linear, row.rel_mse_linear) {
        (Some(r), Some(m)) => format!("; linear f32: RMSE {r:.5}, relMSE {m:.5}"),
        _ => String::new(),
    };
    eprintln!(
        "{}, {} spp: {:.3} s, RMSE {:.5}, relMSE {:.5}, FLIP {:.4}{linear}",
        row.config, row.spp, row.seconds, row.rmse, row.rel_mse, row.mean_flip
    );
}

/// Measures one render against the reference.
pub fn measure(
    config: &str,
    spp: u32,
    seconds: f64,
    image: &Image,
    reference: &Image,
) -> Result<Measurement, ReportError> {
    Ok(Measurement {
        config: config.to_string(),
        spp,
        seconds,
        rmse: rmse(image, reference)?,
        rel_mse: rel_mse(image, reference)?,
        mean_flip: mean_flip(image, reference)?,
        rmse_linear: None,
        rel_mse_linear: None,
    })
}

/// Adds to `row` the error of the linear f32 `image` against the linear `reference`.
pub fn with_linear(
    row: Measurement,
    image: &Image,
    reference: &Image,
) -> Result<Measurement, ReportError> {
    Ok(Measurement {
        rmse_linear: Some(rmse(image, reference)?),
        rel_mse_linear: Some(rel_mse(image, reference)?),
        ..row
    })
}

/// Whether any row has the linear columns (a report prints them only then).
fn has_linear(rows: &[Measurement]) -> bool {
    rows.iter().any(|r| r.rmse_linear.is_some())
}

/// A linear column's value, empty where the row has none.
fn linear_field(value: Option<f64>, digits: usize) -> String {
    value.map_or(String::new(), |v| format!("{v:.digits$}"))
}

/// Writes the three report files into `dir`, creating it.
pub fn write_report(
    dir: &Path,
    meta: &ReportMeta,
    rows: &[Measurement],
) -> Result<(), ReportError> {
    std::fs::create_dir_all(dir).map_err(|source| ReportError::Write {
        path: dir.to_path_buf(),
        source,
    })?;
    let write = |name: &str, bytes: &[u8]| {
        let path = dir.join(name);
        std::fs::write(&path, bytes).map_err(|source| ReportError::Write { path, source })
    };
    write("report.csv", csv(rows).as_bytes())?;
    write("report.md", markdown(meta, rows).as_bytes())?;
    let png = plot(&meta.scene, rows).map_err(ReportError::Plot)?;
    write("error_vs_time.png", &png)?;
    Ok(())
}

/// A CSV field, quoted (RFC 4180) when it holds a comma, quote or line break.
fn csv_field(text: &str) -> String {
    if text.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", text.replace('"', "\"\""))
    } else {
        text.to_string()
    }
}

fn csv(rows: &[Measurement]) -> String {
    let linear = has_linear(rows);
    let mut out = String::from("config,spp,seconds,rmse,rel_mse,mean_flip");
    out += if linear {
        ",rmse_linear,rel_mse_linear\n"
    } else {
        "\n"
    };
    for r in rows {
        let _ = write!(
            out,
            "{},{},{:.6},{:.6},{:.6},{:.6}",
            csv_field(&r.config),
            r.spp,
            r.seconds,
            r.rmse,
            r.rel_mse,
            r.mean_flip
        );
        if linear {
            let _ = write!(
                out,
                ",{},{}",
                linear_field(r.rmse_linear, 6),
                linear_field(r.rel_mse_linear, 6)
            );
        }
        out.push('\n');
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

fn markdown(meta: &ReportMeta, rows: &[Measurement]) -> String {
    let linear = has_linear(rows);
    let mut out = format!(
        "# Error against time: {}\n\n{}×{}; reference: {}.\n\n{}\n\n\
         Metrics against the reference: RMSE over linear RGB clamped to [0,1]; relMSE = mean of \
         (x − ref)² / (ref² + ε) with ε = {REL_MSE_EPSILON}; mean FLIP (NVIDIA's perceptual \
         metric, 8-bit images, 67 pixels per degree).",
        meta.scene.display(),
        meta.width,
        meta.height,
        meta.reference,
        meta.notes
    );
    if linear {
        out += " \"f32\" columns: the same RMSE and relMSE of the linear f32 image against the \
                linear f32 reference, without the 8-bit quantisation (which adds an error floor \
                no sampling lowers).";
    }
    out += "\n\n| config | spp | seconds | RMSE | relMSE | mean FLIP |";
    out += if linear {
        " RMSE (f32) | relMSE (f32) |\n|---|---:|---:|---:|---:|---:|---:|---:|\n"
    } else {
        "\n|---|---:|---:|---:|---:|---:|\n"
    };
    for r in rows {
        let _ = write!(
            out,
            "| {} | {} | {:.3} | {:.5} | {:.5} | {:.4} |",
            r.config, r.spp, r.seconds, r.rmse, r.rel_mse, r.mean_flip
        );
        if linear {
            let _ = write!(
                out,
                " {} | {} |",
                linear_field(r.rmse_linear, 5),
                linear_field(r.rel_mse_linear, 5)
            );
        }
        out.push('\n');
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

/// A short axis label: log-scale ticks are arbitrary floats (0.30000000000000004…), so they
/// are rounded to two significant digits.
fn tick_label(v: f64) -> String {
    if !v.is_finite() || v <= 0.0 {
        return format!("{v}");
    }
    let digits = (1 - v.log10().floor() as i32).max(0) as usize;
    format!("{v:.digits$}")
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
            .x_label_formatter(&|v| tick_label(*v))
            .y_label_formatter(&|v| tick_label(*v))
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
    let image = Image::from_pixels(w, h, buffer.iter().map(|&b| b as f32 / 255.0).collect())
        .map_err(|e| e.to_string())?;
    Ok(image.to_png())
}

#[cfg(test)]
mod tests {
    use super::csv_field;

    #[test]
    fn tick_labels_keep_two_significant_digits() {
        assert_eq!(super::tick_label(0.30000000000000004), "0.30");
        assert_eq!(super::tick_label(0.0123), "0.012");
        assert_eq!(super::tick_label(2.0), "2.0");
        assert_eq!(super::tick_label(40.0), "40");
    }

    #[test]
    fn linear_columns_appear_only_when_a_row_has_them() {
        let row = crate::convergence::Measurement {
            config: "farm".into(),
            spp: 4,
            seconds: 0.5,
            rmse: 0.02,
            rel_mse: 0.001,
            mean_flip: 0.1,
            rmse_linear: None,
            rel_mse_linear: None,
        };
        let plain = super::csv(std::slice::from_ref(&row));
        assert_eq!(
            plain,
            "config,spp,seconds,rmse,rel_mse,mean_flip\nfarm,4,0.500000,0.020000,0.001000,0.100000\n"
        );
        let linear = crate::convergence::Measurement {
            rmse_linear: Some(0.015),
            rel_mse_linear: Some(0.0008),
            ..row.clone()
        };
        let both = super::csv(&[row.clone(), linear.clone()]);
        let lines: Vec<&str> = both.lines().collect();
        assert!(lines[0].ends_with(",rmse_linear,rel_mse_linear"), "{both}");
        assert!(lines[1].ends_with(",0.100000,,"), "{both}");
        assert!(lines[2].ends_with(",0.015000,0.000800"), "{both}");
        let meta = super::ReportMeta {
            scene: "s.scene".into(),
            width: 2,
            height: 2,
            reference: "r".into(),
            notes: "n".into(),
        };
        let md = super::markdown(&meta, &[linear]);
        assert!(md.contains("| RMSE (f32) | relMSE (f32) |"), "{md}");
        assert!(md.contains("| 0.1000 | 0.01500 | 0.00080 |"), "{md}");
        assert!(!super::markdown(&meta, &[row]).contains("(f32)"));
    }

    #[test]
    fn csv_fields_with_commas_or_quotes_are_quoted() {
        assert_eq!(csv_field("2 threads"), "2 threads");
        assert_eq!(csv_field("farm, 2"), "\"farm, 2\"");
        assert_eq!(csv_field("a \"b\""), "\"a \"\"b\"\"\"");
    }
}
