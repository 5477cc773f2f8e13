//! How much adaptive sampling could gain at most on a scene: the oracle bound of
//! docs/farm.md, "Progressive and adaptive rendering".
//!
//! Renders `--images` uniform images of `--spp` samples per pixel (independent seeds, the
//! progressive sample order a progressive job uses) and measures each pixel's squared error
//! against a high-sample reference and the rays its samples traced. For each block size it
//! then asks: if every B×B block got samples in proportion to the best allocation for its
//! true error (n_b ∝ σ_b / √κ_b, σ_b the per-sample standard deviation, κ_b its rays per
//! sample, for the same rays in all), by how much would the image's MSE fall? Two figures per
//! block size:
//! - `oracle`: the allocation from the measured errors themselves. With few images per pixel
//!   the measured error is itself noisy, which flatters small blocks (a lucky pixel looks
//!   quiet); that is why there is a second figure.
//! - `held out`: the allocation from half the images, its MSE evaluated on the other half (and
//!   the other way round): what an allocation made from that much noise really achieves.
//!
//! Errors are in linear RGB clamped to [0, 1] (the report's RMSE without its 8-bit
//! quantisation, a floor no allocation lowers: `delivered` gives its share).
//!
//! `--realize` renders each block size's allocation for real (a fresh seed, whole sample
//! counts, then the same rounded to powers of two), from the true errors and from the
//! half-buffer estimates (A − B)/2 the plan sees: the bound with stratification left in, and
//! how much of it the estimate keeps. `--simulate X` runs the farm's plan (`adaptive::plan`,
//! threshold X, `--spp-min`, `spp_max` 4× `--spp`) in-process on each uniform image's rays:
//! the allocation at equal cost with no farm in between.
//!
//! `cargo build --release -p tracer-core --example adaptive_oracle`, then
//! `$CARGO_TARGET_DIR/release/examples/adaptive_oracle SCENE [--width 240] [--height 180]
//!  [--spp 64] [--images 4] [--reference-spp 2048] [--reference ref.pfm] [--blocks 1,2,4,8,16]
//!  [--realize] [--simulate X [--spp-min 2]]`.
//! With `--reference FILE.pfm` the reference is read from FILE if it exists, else rendered and
//! written there.

use std::path::{Path, PathBuf};
use std::sync::atomic::AtomicBool;

use tracer_core::adaptive::{self, SumImage, SUMS};
use tracer_core::film::quantize;
use tracer_core::metrics::{rel_mse, rmse};
use tracer_core::report::REFERENCE_SEED_SALT;
use tracer_core::{Image, RenderSettings, Renderer, SampleOrder, Scene, TileRect};

struct Args {
    scene: PathBuf,
    width: u32,
    height: u32,
    spp: u32,
    images: u32,
    reference_spp: u32,
    reference: Option<PathBuf>,
    blocks: Vec<u32>,
    /// `spp_min` of the simulated progressive renders.
    spp_min: u32,
    /// Also render the oracle allocations (`--realize`).
    realize: bool,
    /// Noise threshold of the simulated progressive renders (`--simulate X`), if any.
    simulate: Option<f64>,
}

fn parse() -> Result<Args, String> {
    let mut argv = std::env::args().skip(1);
    let mut args = Args {
        scene: PathBuf::new(),
        width: 240,
        height: 180,
        spp: 64,
        images: 4,
        reference_spp: 2048,
        reference: None,
        blocks: vec![1, 2, 4, 8, 16],
        simulate: None,
        realize: false,
        spp_min: 2,
    };
    while let Some(a) = argv.next() {
        let mut value = || argv.next().ok_or(format!("{a} needs a value"));
        let number = |v: String| v.parse::<u32>().map_err(|e| format!("{a}: {e}"));
        match a.as_str() {
            "--width" => args.width = number(value()?)?,
            "--height" => args.height = number(value()?)?,
            "--spp" => args.spp = number(value()?)?,
            "--images" => args.images = number(value()?)?,
            "--reference-spp" => args.reference_spp = number(value()?)?,
            "--reference" => args.reference = Some(value()?.into()),
            "--blocks" => {
                args.blocks = value()?
                    .split(',')
                    .map(|b| b.parse::<u32>().map_err(|e| format!("--blocks: {e}")))
                    .collect::<Result<_, _>>()?
            }
            "--realize" => args.realize = true,
            "--spp-min" => args.spp_min = number(value()?)?,
            "--simulate" => {
                let v = value()?;
                args.simulate = Some(v.parse().map_err(|e| format!("--simulate: {e}"))?)
            }
            _ if a.starts_with("--") => return Err(format!("unknown option {a}")),
            _ => args.scene = a.into(),
        }
    }
    if args.scene.as_os_str().is_empty() || args.images < 2 || args.spp == 0 {
        return Err(
            "usage: adaptive_oracle SCENE [--spp N] [--images K>=2] [--width W] \
                    [--height H] [--reference-spp N] [--reference FILE.pfm] [--blocks 1,2,4]"
                .into(),
        );
    }
    Ok(args)
}

/// Reads a PFM as `Image::to_pfm` writes it.
fn read_pfm(path: &Path) -> Result<Image, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    Image::from_pfm_bytes(&bytes).map_err(|e| format!("{}: {e}", path.display()))
}

/// The strata every render here draws from: those of a progressive job whose `spp_max` is
/// 4× the uniform count (as `coordinator report --adaptive` sets it), so the uniform images
/// are the first samples of the same sequences the adaptive ones continue.
fn settings(args: &Args, seed: u64) -> RenderSettings {
    RenderSettings {
        width: args.width,
        height: args.height,
        spp: 4 * args.spp,
        seed,
        ..RenderSettings::default()
    }
}

/// Per pixel: the mean squared error over the channels (float and as delivered in 8 bits)
/// and the rays per sample, of one uniform image.
struct Measured {
    error: Vec<f64>,
    delivered: Vec<f64>,
    rays: Vec<f64>,
    /// The half-buffer estimate of the squared error, ((A − B) / 2)², as `adaptive` makes it.
    estimate: Vec<f64>,
    /// The image as a one-shot render divides it, and its rays in all.
    image: Image,
    total_rays: f64,
}

fn measure_image(scene: &Scene, args: &Args, seed: u64, reference: &Image) -> Measured {
    let renderer = Renderer::new(scene, &settings(args, seed))
        .expect("valid settings")
        .with_sample_order(SampleOrder::Progressive);
    let rect = TileRect::new(0, 0, args.width, args.height);
    let mut sums = vec![0.0; rect.pixel_count() * SUMS];
    let spp = args.spp;
    renderer.render_tile_samples(rect, &|_, _| 0..spp, &mut sums, &AtomicBool::new(false));
    let pixels = rect.pixel_count();
    let mut m = Measured {
        error: vec![0.0; pixels],
        delivered: vec![0.0; pixels],
        rays: vec![0.0; pixels],
        estimate: vec![0.0; pixels],
        image: Image::new(args.width, args.height),
        total_rays: sums.chunks_exact(SUMS).map(|p| p[5]).sum(),
    };
    let n = spp as f64;
    for p in 0..pixels {
        let s = &sums[p * SUMS..(p + 1) * SUMS];
        for (c, sum) in s[..3].iter().enumerate() {
            // As a one-shot render divides and stores it (f32).
            let v = (sum / n) as f32;
            m.image.pixels[p * 3 + c] = v;
            let r = reference.pixels[p * 3 + c];
            let d = v.clamp(0.0, 1.0) as f64 - r.clamp(0.0, 1.0) as f64;
            m.error[p] += d * d / 3.0;
            let q = (quantize(v) as f64 - quantize(r) as f64) / 255.0;
            m.delivered[p] += q * q / 3.0;
        }
        m.rays[p] = s[5] / n;
        let second = adaptive::second_half_count(spp) as f64;
        let d = ((s[3] - s[4]) / (n - second) - s[4] / second) / 2.0;
        m.estimate[p] = d * d;
    }
    m
}

/// The blocks of a `width`×`height` image at edge `b`: each block's pixel indices.
fn blocks(width: u32, height: u32, b: u32) -> Vec<Vec<usize>> {
    let cols = width.div_ceil(b);
    let mut out = vec![Vec::new(); (cols * height.div_ceil(b)) as usize];
    for y in 0..height {
        for x in 0..width {
            out[(x / b + y / b * cols) as usize].push((y * width + x) as usize);
        }
    }
    out
}

/// Per block: (pixel weight, mean squared error, rays per sample) of `error`.
fn per_block(groups: &[Vec<usize>], error: &[f64], rays: &[f64]) -> Vec<(f64, f64, f64)> {
    let total: usize = groups.iter().map(Vec::len).sum();
    groups
        .iter()
        .map(|g| {
            let n = g.len() as f64;
            let e = g.iter().map(|&p| error[p]).sum::<f64>() / n;
            let k = g.iter().map(|&p| rays[p]).sum::<f64>() / n;
            (n / total as f64, e, k)
        })
        .collect()
}

/// The MSE of the allocation made from `plan`'s errors, measured with `truth`'s, for the
/// rays of the uniform image: samples in block b ∝ √(v_b / κ_b) (v from `plan`), scaled to
/// the uniform image's rays; MSE = Σ w · v_truth · n / m_b.
fn allocated_mse(plan: &[(f64, f64, f64)], truth: &[(f64, f64, f64)]) -> f64 {
    let rays: f64 = plan.iter().map(|(w, _, k)| w * k).sum();
    // A block whose planning errors happen to be zero still gets a little (a hundredth of
    // the mean share), or the held-out figure would be infinite for any zero it meets.
    let mean_shape = plan.iter().map(|(w, v, k)| w * (v / k).sqrt()).sum::<f64>();
    let shape: Vec<f64> = plan
        .iter()
        .map(|(_, v, k)| (v / k).sqrt().max(0.01 * mean_shape))
        .collect();
    let shaped_rays: f64 = plan
        .iter()
        .zip(&shape)
        .map(|((w, _, k), s)| w * k * s)
        .sum();
    if shaped_rays <= 0.0 {
        return truth.iter().map(|(w, v, _)| w * v).sum();
    }
    // Relative samples m_b / n: the same rays as the uniform image.
    let scale = rays / shaped_rays;
    truth
        .iter()
        .zip(&shape)
        .map(|((w, v, _), s)| {
            let m = s * scale;
            if *v == 0.0 {
                0.0
            } else if m <= 0.0 {
                f64::INFINITY
            } else {
                w * v / m
            }
        })
        .sum()
}

fn mean(values: impl Iterator<Item = f64>, count: usize) -> f64 {
    values.sum::<f64>() / count as f64
}

/// A progressive render of `seed` as the farm plans it (`adaptive::plan`, threshold
/// `threshold`, `--spp-min`, `spp_max` 4× `--spp`), on a budget of `budget` rays: a pass
/// that would overspend keeps its blocks in index order while they fit (as a time limit keeps
/// the tiles that landed) and ends the render. Returns the image, its rays and mean spp.
fn simulate(
    scene: &Scene,
    args: &Args,
    seed: u64,
    threshold: f64,
    budget: f64,
) -> (Image, f64, f64) {
    let (w, h) = (args.width, args.height);
    let renderer = Renderer::new(scene, &settings(args, seed))
        .expect("valid settings")
        .with_sample_order(SampleOrder::Progressive);
    let rules = adaptive::Rules {
        noise_threshold: threshold,
        spp_min: args.spp_min,
        spp_max: 4 * args.spp,
    };
    let (cols, rows) = adaptive::blocks(w, h);
    let mut counts = vec![0u32; (cols * rows) as usize];
    let mut sums = SumImage::new(w, h);
    let rect = TileRect::new(0, 0, w, h);
    let rays_of = |s: &SumImage, b: usize| -> f64 {
        let r = adaptive::block_rect(w, h, b);
        s.tile(r).chunks_exact(SUMS).map(|p| p[5]).sum()
    };
    let mut spent = 0.0;
    loop {
        let targets = adaptive::plan(&sums, &counts, rules, None);
        if targets == counts {
            break;
        }
        let mut next = sums.clone();
        let range = |x: u32, y: u32| {
            let b = adaptive::block_of(w, x, y);
            counts[b]..targets[b]
        };
        renderer.render_tile_samples(rect, &range, &mut next.data, &AtomicBool::new(false));
        let mut cut = false;
        for b in 0..counts.len() {
            if targets[b] == counts[b] {
                continue;
            }
            let cost = rays_of(&next, b) - rays_of(&sums, b);
            // The first pass always finishes (before it there is no image).
            if spent + cost > budget && counts.iter().any(|&n| n > 0) {
                cut = true;
                continue;
            }
            spent += cost;
            sums.put_tile(
                adaptive::block_rect(w, h, b),
                &next.tile(adaptive::block_rect(w, h, b)),
            );
            counts[b] = targets[b];
        }
        if cut {
            break;
        }
    }
    let total: f64 = (0..counts.len())
        .map(|b| counts[b] as f64 * adaptive::block_rect(w, h, b).pixel_count() as f64)
        .sum();
    (sums.image(&counts), spent, total / (w * h) as f64)
}

/// Renders seed `seed` with each pixel's sample count from `count` (a function of the pixel):
/// the image and its rays.
fn render_counts(
    scene: &Scene,
    args: &Args,
    seed: u64,
    count: &(dyn Fn(u32, u32) -> u32 + Sync),
) -> (Image, f64) {
    let (w, h) = (args.width, args.height);
    let renderer = Renderer::new(scene, &settings(args, seed))
        .expect("valid settings")
        .with_sample_order(SampleOrder::Progressive);
    let rect = TileRect::new(0, 0, w, h);
    let mut sums = vec![0.0; rect.pixel_count() * SUMS];
    let range = |x: u32, y: u32| 0..count(x, y);
    renderer.render_tile_samples(rect, &range, &mut sums, &AtomicBool::new(false));
    let mut image = Image::new(w, h);
    let mut rays = 0.0;
    for y in 0..h {
        for x in 0..w {
            let p = (y * w + x) as usize;
            let n = count(x, y).max(1) as f64;
            for c in 0..3 {
                image.pixels[p * 3 + c] = (sums[p * SUMS + c] / n) as f32;
            }
            rays += sums[p * SUMS + 5];
        }
    }
    (image, rays)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse()?;
    let scene = Scene::load(&args.scene)?;
    let reference = match &args.reference {
        Some(path) if path.exists() => read_pfm(path)?,
        _ => {
            eprintln!("rendering the reference at {} spp…", args.reference_spp);
            let settings = RenderSettings {
                width: args.width,
                height: args.height,
                spp: args.reference_spp,
                seed: REFERENCE_SEED_SALT,
                ..RenderSettings::default()
            };
            let image = Renderer::new(&scene, &settings)?.render_image(&|_, _| {});
            if let Some(path) = &args.reference {
                image.save(path)?;
            }
            image
        }
    };
    if (reference.width, reference.height) != (args.width, args.height) {
        return Err("the reference has another size".into());
    }
    let measured: Vec<Measured> = (1..=args.images as u64)
        .map(|seed| {
            eprintln!("uniform image {seed} of {}…", args.images);
            measure_image(&scene, &args, seed, &reference)
        })
        .collect();
    let pixels = (args.width * args.height) as usize;
    let k = measured.len();
    let all = |f: fn(&Measured) -> &Vec<f64>, which: &mut dyn Iterator<Item = &Measured>| {
        let chosen: Vec<&Measured> = which.collect();
        (0..pixels)
            .map(|p| mean(chosen.iter().map(|m| f(m)[p]), chosen.len()))
            .collect::<Vec<f64>>()
    };
    let error = all(|m| &m.error, &mut measured.iter());
    let delivered = all(|m| &m.delivered, &mut measured.iter());
    let rays = all(|m| &m.rays, &mut measured.iter());
    let estimate = all(|m| &m.estimate, &mut measured.iter());
    let even = all(|m| &m.error, &mut measured.iter().step_by(2));
    let odd = all(|m| &m.error, &mut measured.iter().skip(1).step_by(2));
    let uniform = mean(error.iter().copied(), pixels);
    let uniform_delivered = mean(delivered.iter().copied(), pixels);
    println!(
        "{}: {}x{}, {} spp, {k} images; uniform RMSE {:.5} (as delivered in 8 bits {:.5}: \
         quantisation adds {:.0}% to the MSE)",
        args.scene.display(),
        args.width,
        args.height,
        args.spp,
        uniform.sqrt(),
        uniform_delivered.sqrt(),
        100.0 * (uniform_delivered / uniform - 1.0)
    );
    println!(
        "block  oracle MSE÷  RMSE    held out MSE÷  RMSE    delivered RMSE (oracle, held out)"
    );
    for &b in &args.blocks {
        let groups = blocks(args.width, args.height, b);
        let truth = per_block(&groups, &error, &rays);
        let oracle = allocated_mse(&truth, &truth);
        let (a, c) = (
            per_block(&groups, &even, &rays),
            per_block(&groups, &odd, &rays),
        );
        let uniform_of = |v: &[(f64, f64, f64)]| v.iter().map(|(w, e, _)| w * e).sum::<f64>();
        // Each half's allocation judged by the other half's errors, as a ratio to uniform.
        let held_out = uniform * (allocated_mse(&a, &c) + allocated_mse(&c, &a))
            / (uniform_of(&a) + uniform_of(&c));
        // Quantisation is a floor: the same absolute amount whatever the allocation.
        let floor = uniform_delivered - uniform;
        println!(
            "{b:>5}  {:>10.3}  {:>+5.1}%  {:>12.3}  {:>+5.1}%  {:+.1}%, {:+.1}%",
            uniform / oracle,
            100.0 * ((oracle / uniform).sqrt() - 1.0),
            uniform / held_out,
            100.0 * ((held_out / uniform).sqrt() - 1.0),
            100.0 * (((oracle + floor) / uniform_delivered).sqrt() - 1.0),
            100.0 * (((held_out + floor) / uniform_delivered).sqrt() - 1.0),
        );
    }
    if args.realize {
        // The oracle allocation rendered for real (a seed the errors did not come from):
        // what stratification and whole sample counts leave of the bound.
        println!(
            "block  realised RMSE ratio (whole counts, powers of two), relMSE ratio, rays ratio"
        );
        let seed = 1000;
        let uniform_count = |_: u32, _: u32| args.spp;
        let (uniform_image, uniform_rays) = render_counts(&scene, &args, seed, &uniform_count);
        let u = (
            rmse(&uniform_image, &reference)?,
            rel_mse(&uniform_image, &reference)?,
        );
        for (&b, source) in
            (args.blocks.iter()).flat_map(|b| [(b, "true errors"), (b, "estimates")])
        {
            let groups = blocks(args.width, args.height, b);
            let from = if source == "estimates" {
                &estimate
            } else {
                &error
            };
            let truth = per_block(&groups, from, &rays);
            let rays_mean: f64 = truth.iter().map(|(w, _, k)| w * k).sum();
            let mean_shape: f64 = truth.iter().map(|(w, v, k)| w * (v / k).sqrt()).sum();
            let shape: Vec<f64> = truth
                .iter()
                .map(|(_, v, k)| (v / k).sqrt().max(0.01 * mean_shape))
                .collect();
            let shaped: f64 = truth
                .iter()
                .zip(&shape)
                .map(|((w, _, k), s)| w * k * s)
                .sum();
            let scale = args.spp as f64 * rays_mean / shaped;
            let cols = args.width.div_ceil(b);
            let exact: Vec<u32> = shape
                .iter()
                .map(|s| ((s * scale).round() as u32).clamp(1, 4 * args.spp))
                .collect();
            let pow2: Vec<u32> = exact
                .iter()
                .map(|&n| {
                    let up = n.next_power_of_two();
                    if up > 1 && (up as f64 / n as f64) > (n as f64 / (up / 2) as f64) {
                        up / 2
                    } else {
                        up
                    }
                })
                .collect();
            let mut line = format!("{b:>5} {source:>11}");
            for counts in [&exact, &pow2] {
                let count = |x: u32, y: u32| counts[(x / b + y / b * cols) as usize];
                let (image, r) = render_counts(&scene, &args, seed, &count);
                line += &format!(
                    "  RMSE {:.3} relMSE {:.3} rays {:.3}",
                    rmse(&image, &reference)? / u.0,
                    rel_mse(&image, &reference)? / u.1,
                    r / uniform_rays
                );
            }
            println!("{line}");
        }
    }
    if let Some(threshold) = args.simulate {
        // Same seeds, same rays: adaptive against uniform with no farm in between.
        println!(
            "seed  uniform RMSE (8-bit) relMSE  adaptive RMSE (8-bit) relMSE  (rays ratio, mean spp)"
        );
        let delivered = |i: &Image| Image::from_png_bytes(&i.to_png());
        let reference8 = delivered(&reference)?;
        let mut ratio = (0.0, 0.0, 0.0);
        for (i, m) in measured.iter().enumerate() {
            let seed = i as u64 + 1;
            let (image, rays, spp) = simulate(&scene, &args, seed, threshold, m.total_rays);
            let measure = |i: &Image| -> Result<(f64, f64, f64), Box<dyn std::error::Error>> {
                Ok((
                    rmse(i, &reference)?,
                    rmse(&delivered(i)?, &reference8)?,
                    rel_mse(i, &reference)?,
                ))
            };
            let (u, a) = (measure(&m.image)?, measure(&image)?);
            ratio.0 += a.0 / u.0 / k as f64;
            ratio.1 += a.1 / u.1 / k as f64;
            ratio.2 += a.2 / u.2 / k as f64;
            println!(
                "{seed:>4}  {:.5} ({:.5}) {:.6}   {:.5} ({:.5}) {:.6}  ({:.3}, {spp:.1})",
                u.0,
                u.1,
                u.2,
                a.0,
                a.1,
                a.2,
                rays / m.total_rays
            );
        }
        println!(
            "mean ratio adaptive/uniform: RMSE {:.3} (8-bit {:.3}), relMSE {:.3}",
            ratio.0, ratio.1, ratio.2
        );
    }
    Ok(())
}
