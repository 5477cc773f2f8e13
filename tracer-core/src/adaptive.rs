//! Progressive, adaptive rendering: a render in passes, each adding samples to the pixels that
//! still need them, and the arithmetic that decides which do.
//!
//! A pass continues each pixel's running sums at the sample index the previous pass stopped
//! at ([`crate::Renderer::render_tile_samples`]), so after n samples a pixel holds exactly the
//! f64 sum a one-shot n-sample render accumulates: the same bytes.
//!
//! Decisions are made per [`BLOCK`]×[`BLOCK`] block of the image (blocks are fixed to the image,
//! not to tiles, so any tile size gives the same decisions). A block's error estimate comes
//! from two interleaved half-buffers: the mean luminance of each pixel's samples of even bit
//! parity (A) and of odd bit parity (B) ([`in_second_half`]). |A − B| / 2 estimates the standard error of the pixel's mean;
//! the block's relative error is Σ|A − B|/2 over its pixels divided by Σ max(I, [`DARK_FLOOR`])
//! (I the pixel's mean luminance), so dark blocks are not sampled forever for noise nobody
//! can see. A block stops once it has at least `spp_min` samples and its error is at most the
//! noise threshold; no block goes beyond `spp_max`. Everything here is a pure function of the
//! sums, so the same samples give the same decisions on any farm.

use crate::film::Image;
use crate::settings::TileRect;

/// f64 values kept per pixel: the sum of the samples' r, g, b (the one-shot render's sum),
/// then the sum of every sample's luminance and the sum of the luminance of the samples in the
/// second half-buffer ([`in_second_half`]): the two half-buffers of the error estimate; then
/// the rays the samples traced (what they cost: a deterministic stand-in for time).
pub const SUMS: usize = 6;

/// The edge of a decision block, in pixels.
pub const BLOCK: u32 = 8;

/// Luminance below this counts as this much when an error is made relative: the noise of a
/// near-black pixel is invisible, however large relative to its value.
pub const DARK_FLOOR: f64 = 0.05;

/// Whether sample `k` belongs to the second half-buffer (B): odd bit parity (the Thue–Morse
/// sequence). The progressive order bit-reverses the sample index into the pixel's Morton
/// code, so splitting by k's lowest bit would put the halves in opposite halves of the pixel
/// (A − B would measure an edge, not noise); splitting by parity gives each half one sample
/// of every diagonal pair, so both cover the whole pixel in every prefix of 2^j samples.
#[inline]
pub fn in_second_half(k: u32) -> bool {
    k.count_ones() % 2 == 1
}

/// How many of samples 0..n are in the second half-buffer.
pub fn second_half_count(n: u32) -> u32 {
    // Each pair (2m, 2m + 1) has one sample in each half.
    let pairs = n / 2;
    pairs + (n % 2 == 1 && in_second_half(n - 1)) as u32
}

/// A sample's contribution to the error estimate: its mean channel, each channel clamped to
/// the displayable [0, 1] (an out-of-range sample is no noisier on screen than a white one).
#[inline]
pub fn luminance(r: f64, g: f64, b: f64) -> f64 {
    (r.min(1.0) + g.min(1.0) + b.min(1.0)) / 3.0
}

/// The stopping rules a plan follows (the job spec's `adaptive`, less its time limit).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Rules {
    /// Relative error at which a block stops; 0 never stops a block on noise.
    pub noise_threshold: f64,
    pub spp_min: u32,
    pub spp_max: u32,
}

/// Each pass adds this fraction of the samples the image already has (at least one per
/// pixel): passes double, so there are few of them (each costs a round of leases and a pass
/// end, and on a sub-second image that weighs), and a pass cut short by a time limit keeps
/// the blocks it finished.
const PASS_GROWTH: f64 = 1.0;

/// Below this many samples a block's estimate is rough (two to seven samples per pixel
/// compared in halves): a pass may at most double its samples; from here on, quadruple them.
const TRUSTED_SPP: u32 = 8;

/// How a block's share divides by its mean luminance: L^-w (0: absolute error, RMSE; 1:
/// relative error). A quarter keeps the allocation close to the RMSE-optimal one while
/// dark blocks still get a little more (in-process at equal rays, `adaptive_oracle
/// --simulate`: 0.5 cost stacks 3 % of RMSE against 0.25 for a relMSE 3 % lower; 0 left the
/// RMSE level and relMSE 10 % higher).
const LUMINANCE_WEIGHT: f64 = 0.25;

/// A block's share of a pass never falls below this fraction of the mean share, so a block
/// whose few samples happened to agree is still looked at again.
const SHARE_FLOOR: f64 = 0.1;

/// The samples per pixel each block has after the next pass (`counts` is what each has now;
/// a block with `target == count` does not sample in it). A pure function of the sums, so
/// every farm plans alike.
///
/// The first pass brings every block to `spp_min`. A block is done (keeps its count) at
/// `spp_max`, or once it has `spp_min` samples and its relative error is at most the noise
/// threshold. The other blocks share the pass's samples (as many as the image has, at least
/// one per pixel; counted in rays, the deterministic stand-in for time): a block's total
/// goes towards c · σ_b / (L_b^w √κ_b), where σ_b is its per-sample standard deviation (the
/// root mean square of its pixels' (A − B)/2, × √n), L_b its mean luminance (floored at
/// [`DARK_FLOOR`]), w = [`LUMINANCE_WEIGHT`] and κ_b its rays per sample (glass and many
/// bounces cost more). Samples ∝ σ / √κ minimise the absolute squared error (RMSE) for a
/// given cost, samples ∝ σ / (L √κ) the relative one. σ is a root mean square, not the mean
/// |A − B| the stopping rule uses: a block's squared error is the mean of its pixels'
/// squared errors, so a block with a few very noisy pixels (an edge, a caustic) needs more
/// than its mean |A − B| says. c is the smallest that spends the pass's samples
/// (water-filling: blocks already beyond their share get nothing). Counts step in powers of
/// two ([`level_above`]): a block's total grows one level per pass below [`TRUSTED_SPP`]
/// (×2) and at most two from there (×4; its estimate is noisy before), never beyond
/// `spp_max`, and with a threshold never beyond the first level that reaches what its
/// estimate says it needs (n · (error / threshold)²).
///
/// `max_rays`, when given, replaces the doubling budget by a limit the pass stays within (a
/// time-limited job passes the rays its time left allows): the pass spends as much of it as
/// whole levels allow, possibly nothing (a cap of zero or less plans no pass at all). The
/// first pass (every block to `spp_min`) ignores it. Still a pure function of its
/// arguments: without a cap the plan is exactly the doubling one.
pub fn plan(sums: &SumImage, counts: &[u32], rules: Rules, max_rays: Option<f64>) -> Vec<u32> {
    let spp_max = rules.spp_max.max(1);
    let spp_min = rules.spp_min.clamp(1, spp_max);
    let pixels = |b: usize| block_rect(sums.width, sums.height, b).pixel_count() as f64;
    // (count, cap, share) of each block still sampling; None for a done one.
    let mut open: Vec<Option<(u32, u32, f64)>> = Vec::with_capacity(counts.len());
    // Each block's cost of one more sample per pixel (its rays per sample × its pixels).
    let cost = sample_costs(sums, counts);
    let (mut total, mut one_each) = (0.0, 0.0);
    for (b, &n) in counts.iter().enumerate() {
        let p = pixels(b);
        total += cost[b] * n as f64;
        one_each += cost[b];
        if n < spp_min {
            // Not sampled yet (the first pass): to spp_min, whatever the rest get.
            open.push(Some((n, spp_min, f64::INFINITY)));
            continue;
        }
        let (num, den, squares) = sums.block_error_parts(b, n);
        let relative = if den > 0.0 { num / den } else { 0.0 };
        let quiet = rules.noise_threshold > 0.0 && relative <= rules.noise_threshold;
        if n >= spp_max || quiet {
            open.push(None);
            continue;
        }
        let mut cap = level_above(n, spp_max);
        if n >= TRUSTED_SPP {
            cap = level_above(cap, spp_max);
        }
        if rules.noise_threshold > 0.0 {
            // The first level that reaches what the estimate says the block needs.
            let need = n as f64 * (relative / rules.noise_threshold).powi(2);
            let mut enough = level_above(n, spp_max);
            while (enough as f64) < need && enough < cap {
                enough = level_above(enough, spp_max);
            }
            cap = cap.min(enough);
        }
        let sigma = (squares / p * n as f64).sqrt();
        let rays_per_sample = cost[b] / p;
        open.push(Some((
            n,
            cap,
            sigma / rays_per_sample.sqrt() / (den / p).powf(LUMINANCE_WEIGHT),
        )));
    }
    if open.iter().flatten().any(|o| o.2.is_infinite()) {
        // The first pass (or blocks never sampled): everyone to at least spp_min.
        return counts
            .iter()
            .zip(&open)
            .map(|(&n, o)| match o {
                Some((_, cap, share)) if share.is_infinite() => *cap,
                _ => n,
            })
            .collect();
    }
    let (mut weighted, mut weight) = (0.0, 0.0);
    for (b, o) in open.iter().enumerate() {
        if let Some((_, _, share)) = o {
            weighted += share * pixels(b);
            weight += pixels(b);
        }
    }
    let floor = if weight > 0.0 && weighted > 0.0 {
        weighted / weight * SHARE_FLOOR
    } else {
        // Every open block looks flat: share alike.
        1.0
    };
    let doubling = (total * PASS_GROWTH).max(one_each);
    // A cap is a limit the pass must stay within (the time left), not a target to reach:
    // the pass ends at or below it.
    let (budget, within) = match max_rays {
        Some(cap) if cap <= 0.0 => return counts.to_vec(),
        Some(cap) => (cap, true),
        None => (doubling, false),
    };
    let targets = |c: f64| -> Vec<u32> {
        counts
            .iter()
            .zip(&open)
            .map(|(&n, o)| match o {
                Some((n, cap, share)) => {
                    // The highest level up to the block's share of c.
                    let want = c * share.max(floor);
                    let mut t = *n;
                    while t < *cap && level_above(t, *cap) as f64 <= want {
                        t = level_above(t, *cap);
                    }
                    t
                }
                None => n,
            })
            .collect()
    };
    let spent = |t: &[u32]| -> f64 {
        t.iter()
            .zip(counts)
            .enumerate()
            .map(|(b, (&t, &n))| (t - n) as f64 * cost[b])
            .sum()
    };
    // The smallest c that spends the budget, by bisection (a fixed number of steps on f64:
    // the same c on every machine); if even every cap does not, every open block to its cap.
    // Within a limit: the largest c that does not exceed it (possibly nothing at all).
    let capped = targets(f64::INFINITY);
    if spent(&capped) <= budget {
        return capped;
    }
    let mut hi = 1.0;
    while spent(&targets(hi)) < budget {
        hi *= 2.0;
    }
    let mut lo = 0.0;
    for _ in 0..60 {
        let mid = (lo + hi) / 2.0;
        if spent(&targets(mid)) >= budget {
            hi = mid;
        } else {
            lo = mid;
        }
    }
    let planned = targets(hi);
    if within && spent(&planned) > budget {
        targets(lo)
    } else {
        planned
    }
}

/// Each block's cost of one more sample per pixel, in rays: its rays per sample so far (at
/// least one; one before it has samples) × its pixels.
fn sample_costs(sums: &SumImage, counts: &[u32]) -> Vec<f64> {
    (counts.iter().enumerate())
        .map(|(b, &n)| {
            let p = block_rect(sums.width, sums.height, b).pixel_count() as f64;
            p * if n > 0 {
                (sums.block_rays(b) / (n as f64 * p)).max(1.0)
            } else {
                1.0
            }
        })
        .collect()
}

/// The rays a pass from `counts` to `targets` is expected to trace, priced as [`plan`]
/// prices samples (each block at its rays per sample so far).
pub fn pass_rays(sums: &SumImage, counts: &[u32], targets: &[u32]) -> f64 {
    let cost = sample_costs(sums, counts);
    (targets.iter().zip(counts).zip(&cost))
        .map(|((&t, &n), c)| t.saturating_sub(n) as f64 * c)
        .sum()
}

/// The sample count a block steps up to from `n`: the next power of two (capped at
/// `spp_max`). The progressive order puts a prefix of 2^j samples one in each of the pixel's
/// 2^j coarsest cells, so power-of-two counts are perfectly stratified; counts in between
/// visit some cells twice and others not at all, and on edges and soft shadows that costs
/// more error than their extra samples save.
fn level_above(n: u32, spp_max: u32) -> u32 {
    let next = if n.is_power_of_two() {
        n.saturating_mul(2)
    } else {
        n.next_power_of_two()
    };
    next.min(spp_max).max(n.saturating_add(1).min(spp_max))
}

/// The decision blocks of a `width`×`height` image: (columns, rows).
pub fn blocks(width: u32, height: u32) -> (u32, u32) {
    (width.div_ceil(BLOCK), height.div_ceil(BLOCK))
}

/// The index of the block holding pixel (x, y) (y from the top) of a `width`-wide image.
#[inline]
pub fn block_of(width: u32, x: u32, y: u32) -> usize {
    (x / BLOCK + (y / BLOCK) * width.div_ceil(BLOCK)) as usize
}

/// The pixels of block `block` of a `width`×`height` image (blocks at the right and bottom
/// edges are cut to the image).
pub fn block_rect(width: u32, height: u32, block: usize) -> TileRect {
    let cols = width.div_ceil(BLOCK) as usize;
    let (x, y) = ((block % cols) as u32 * BLOCK, (block / cols) as u32 * BLOCK);
    TileRect::new(x, y, BLOCK.min(width - x), BLOCK.min(height - y))
}

/// Every decision block that intersects `rect`, as block indices.
pub fn blocks_in(width: u32, rect: TileRect) -> Vec<u32> {
    let mut out = Vec::new();
    if rect.width == 0 || rect.height == 0 {
        return out;
    }
    let cols = width.div_ceil(BLOCK);
    for by in rect.y / BLOCK..=(rect.y + rect.height - 1) / BLOCK {
        for bx in rect.x / BLOCK..=(rect.x + rect.width - 1) / BLOCK {
            out.push(bx + by * cols);
        }
    }
    out
}

/// The running sums of every pixel of an image ([`SUMS`] f64 per pixel, row-major from the
/// top), as a progressive render keeps them between passes.
#[derive(Clone, Debug, PartialEq)]
pub struct SumImage {
    pub width: u32,
    pub height: u32,
    pub data: Vec<f64>,
}

/// Sums whose size does not match their image.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{what}: expected {expected} bytes of f64 sums, got {got}")]
pub struct SumsSize {
    pub what: String,
    pub expected: usize,
    pub got: usize,
}

impl SumImage {
    pub fn new(width: u32, height: u32) -> SumImage {
        SumImage {
            width,
            height,
            data: vec![0.0; width as usize * height as usize * SUMS],
        }
    }

    /// The sums of the pixels of `rect`, row-major from its top row.
    pub fn tile(&self, rect: TileRect) -> Vec<f64> {
        let mut out = Vec::with_capacity(rect.pixel_count() * SUMS);
        for y in rect.y..rect.y + rect.height {
            let start = (y as usize * self.width as usize + rect.x as usize) * SUMS;
            out.extend_from_slice(&self.data[start..start + rect.width as usize * SUMS]);
        }
        out
    }

    /// Replaces the sums of `rect` (laid out as [`SumImage::tile`] returns them).
    pub fn put_tile(&mut self, rect: TileRect, sums: &[f64]) {
        assert_eq!(sums.len(), rect.pixel_count() * SUMS, "tile sums size");
        let row = rect.width as usize * SUMS;
        for (i, y) in (rect.y..rect.y + rect.height).enumerate() {
            let start = (y as usize * self.width as usize + rect.x as usize) * SUMS;
            self.data[start..start + row].copy_from_slice(&sums[i * row..(i + 1) * row]);
        }
    }

    /// The relative error estimate of block `block` after `n` samples per pixel (see the
    /// module notes); infinite below two samples, where there are no two halves to compare.
    pub fn block_error(&self, block: usize, n: u32) -> f64 {
        let (num, den, _) = self.block_error_parts(block, n);
        if n < 2 {
            f64::INFINITY
        } else {
            num / den
        }
    }

    /// The rays every pixel's samples traced so far.
    pub fn rays(&self) -> f64 {
        self.data.iter().skip(5).step_by(SUMS).sum()
    }

    /// The rays block `block`'s samples traced so far.
    fn block_rays(&self, block: usize) -> f64 {
        let r = block_rect(self.width, self.height, block);
        let mut rays = 0.0;
        for y in r.y..r.y + r.height {
            for x in r.x..r.x + r.width {
                rays += self.data[(y as usize * self.width as usize + x as usize) * SUMS + 5];
            }
        }
        rays
    }

    /// Σ|A − B|/2, Σ max(I, floor) and Σ((A − B)/2)² over the block's pixels.
    fn block_error_parts(&self, block: usize, n: u32) -> (f64, f64, f64) {
        let r = block_rect(self.width, self.height, block);
        let second = second_half_count(n);
        let (first_n, second_n) = ((n - second.min(n)) as f64, second as f64);
        let (mut num, mut den, mut squares) = (0.0, 0.0, 0.0);
        for y in r.y..r.y + r.height {
            for x in r.x..r.x + r.width {
                let p = (y as usize * self.width as usize + x as usize) * SUMS;
                let (all, second) = (self.data[p + 3], self.data[p + 4]);
                if n >= 2 {
                    let half = ((all - second) / first_n - second / second_n) / 2.0;
                    num += half.abs();
                    squares += half * half;
                }
                den += (all / n.max(1) as f64).max(DARK_FLOOR);
            }
        }
        (num, den, squares)
    }

    /// The image's relative error estimate, with each block at its own sample count
    /// (`counts[block]`): the same ratio as a block's, over every pixel.
    pub fn error(&self, counts: &[u32]) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for (block, &n) in counts.iter().enumerate() {
            if n < 2 {
                return f64::INFINITY;
            }
            let (a, b, _) = self.block_error_parts(block, n);
            num += a;
            den += b;
        }
        if den > 0.0 {
            num / den
        } else {
            0.0
        }
    }

    /// The image: each pixel's sum divided by its block's count, exactly as a one-shot render
    /// of that many samples divides it (same operations, same bytes).
    pub fn image(&self, counts: &[u32]) -> Image {
        let mut image = Image::new(self.width, self.height);
        for y in 0..self.height {
            for x in 0..self.width {
                let i = y as usize * self.width as usize + x as usize;
                let n = counts[block_of(self.width, x, y)].max(1) as f64;
                let s = &self.data[i * SUMS..i * SUMS + 3];
                image.pixels[i * 3..i * 3 + 3].copy_from_slice(&[
                    (s[0] / n) as f32,
                    (s[1] / n) as f32,
                    (s[2] / n) as f32,
                ]);
            }
        }
        image
    }

    /// f64 little-endian, the layout of [`SumImage::data`] (also the wire format of a tile's
    /// sums).
    pub fn to_bytes(values: &[f64]) -> Vec<u8> {
        let mut out = Vec::with_capacity(values.len() * 8);
        for v in values {
            out.extend_from_slice(&v.to_le_bytes());
        }
        out
    }

    /// Decodes [`SumImage::to_bytes`] of `pixels` pixels; `what` names the data in the error.
    pub fn from_bytes(bytes: &[u8], pixels: usize, what: &str) -> Result<Vec<f64>, SumsSize> {
        let expected = pixels * SUMS * 8;
        if bytes.len() != expected {
            return Err(SumsSize {
                what: what.to_string(),
                expected,
                got: bytes.len(),
            });
        }
        Ok(bytes
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes(c.try_into().expect("8 bytes")))
            .collect())
    }
}

/// Where the samples went: each pixel's block count over `spp_max`, as grey.
pub fn sample_map(width: u32, height: u32, counts: &[u32], spp_max: u32) -> Image {
    let mut image = Image::new(width, height);
    for y in 0..height {
        for x in 0..width {
            let v = counts[block_of(width, x, y)] as f32 / spp_max.max(1) as f32;
            let i = (y as usize * width as usize + x as usize) * 3;
            image.pixels[i..i + 3].copy_from_slice(&[v, v, v]);
        }
    }
    image
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 32×8 image (four blocks) after `n` samples per pixel whose per-sample luminance
    /// spread in block b is `spread[b]` around 0.5: each pixel's halves differ by the spread
    /// over √n (the standard error of a mean of n samples).
    fn spread_sums(n: u32, spread: [f64; 4]) -> SumImage {
        let mut sums = SumImage::new(32, 8);
        let second = second_half_count(n) as f64;
        let first = n as f64 - second;
        for y in 0..8 {
            for x in 0..32 {
                let d = spread[(x / 8) as usize] / (n as f64).sqrt();
                // Half A's mean 0.5 + d, half B's 0.5 - d: |A - B| / 2 = d.
                let (a, b) = ((0.5 + d) * first, (0.5 - d) * second);
                let p = ((y * 32 + x) * SUMS as u32) as usize;
                sums.data[p..p + SUMS].copy_from_slice(&[
                    a + b,
                    a + b,
                    a + b,
                    a + b,
                    b,
                    2.0 * n as f64,
                ]);
            }
        }
        sums
    }

    const RULES: Rules = Rules {
        noise_threshold: 0.0,
        spp_min: 4,
        spp_max: 256,
    };

    #[test]
    fn the_first_pass_brings_every_block_to_spp_min() {
        let sums = SumImage::new(20, 9);
        assert_eq!(plan(&sums, &[0; 6], RULES, None), [4; 6]);
    }

    #[test]
    fn a_pass_doubles_the_image_s_samples_where_the_noise_is() {
        // Block 0 noisiest, block 3 flat.
        let sums = spread_sums(16, [0.4, 0.2, 0.1, 0.0]);
        let targets = plan(&sums, &[16; 4], RULES, None);
        let added: u32 = targets.iter().map(|t| t - 16).sum();
        // As many samples as the image has (4 × 16 per pixel), give or take one block's step.
        assert!((64..=66).contains(&added), "{targets:?}");
        assert!(
            targets[0] > targets[1] && targets[1] > targets[2],
            "{targets:?}"
        );
        // A flat block keeps a small floor share, so it is looked at again later, but here it
        // lies below its count already.
        assert_eq!(targets[3], 16, "{targets:?}");
        assert!(
            targets.iter().all(|&t| t <= 64),
            "at most x4 per pass: {targets:?}"
        );
        // Rough estimates (below 8 samples) at most double.
        let early = plan(&spread_sums(4, [0.4, 0.0, 0.0, 0.0]), &[4; 4], RULES, None);
        assert_eq!(early[0], 8, "{early:?}");
    }

    #[test]
    fn a_ray_cap_shrinks_the_pass_and_keeps_it_where_the_noise_is() {
        let sums = spread_sums(16, [0.4, 0.2, 0.1, 0.0]);
        let counts = [16; 4];
        let doubling = plan(&sums, &counts, RULES, None);
        let full = pass_rays(&sums, &counts, &doubling);
        // The image has 32 × 8 pixels × 16 samples × 2 rays: the pass doubles that.
        assert!(
            (8192.0..=8192.0 + 2.0 * 64.0 * 48.0).contains(&full),
            "{full}"
        );
        // A cap above the doubling budget is spent too (within it).
        let more = plan(&sums, &counts, RULES, Some(2.0 * full));
        let spent = pass_rays(&sums, &counts, &more);
        assert!(spent > full && spent <= 2.0 * full, "{spent} {more:?}");
        // Half of it: the pass stays within that, still on the noisiest block first.
        let capped = plan(&sums, &counts, RULES, Some(full / 2.0));
        let spent = pass_rays(&sums, &counts, &capped);
        assert!(spent > 0.0 && spent <= full / 2.0, "{spent} {capped:?}");
        assert!(capped[0] > 16 && capped[0] >= capped[1], "{capped:?}");
        assert!(
            capped.iter().zip(&doubling).all(|(c, d)| c <= d),
            "{capped:?}"
        );
        // Nothing left to spend: no pass.
        assert_eq!(plan(&sums, &counts, RULES, Some(0.0)), counts);
        // The first pass goes to spp_min whatever the cap.
        assert_eq!(
            plan(&SumImage::new(20, 9), &[0; 6], RULES, Some(0.0)),
            [4; 6]
        );
    }

    #[test]
    fn a_few_very_noisy_pixels_weigh_more_than_the_same_mean_noise_spread_out() {
        // Block 0: four pixels with spread 0.8, the rest flat; block 1: every pixel 0.05.
        // Their mean |A − B| is the same, but block 0's squared error is 16 times block 1's.
        let mut sums = spread_sums(16, [0.05, 0.05, 0.0, 0.0]);
        let (sparse, flat) = (
            spread_sums(16, [0.8, 0.0, 0.0, 0.0]),
            spread_sums(16, [0.0; 4]),
        );
        for y in 0..8 {
            for x in 0..8 {
                let from = if x < 2 && y < 2 { &sparse } else { &flat };
                let p = (y * 32 + x) * SUMS;
                sums.data[p..p + SUMS].copy_from_slice(&from.data[p..p + SUMS]);
            }
        }
        let (a, b) = (sums.block_error(0, 16), sums.block_error(1, 16));
        assert!((a - b).abs() < 1e-12, "same mean |A - B|: {a} {b}");
        let targets = plan(&sums, &[16; 4], RULES, None);
        assert!(targets[0] > targets[1], "{targets:?}");
    }

    #[test]
    fn done_blocks_keep_their_count_and_a_threshold_caps_what_a_block_needs() {
        let sums = spread_sums(16, [0.4, 0.2, 0.1, 0.0]);
        let rules = Rules {
            noise_threshold: 0.15,
            ..RULES
        };
        // Relative errors 0.2, 0.1, 0.05 and 0 after 16 samples: blocks 1 to 3 are quiet;
        // block 0 needs 16 · (0.2 / 0.15)² = 28.4 samples to reach the threshold: the first
        // level past that is 32, less than the 64 the pass would give it.
        assert_eq!(plan(&sums, &[16; 4], rules, None), [32, 16, 16, 16]);
        // At spp_max a block is done whatever its noise.
        let capped = Rules {
            spp_max: 16,
            ..RULES
        };
        assert_eq!(plan(&sums, &[16; 4], capped, None), [16; 4]);
    }

    #[test]
    fn the_halves_split_every_pair_and_are_counted() {
        let second: Vec<u32> = (0..8).filter(|&k| in_second_half(k)).collect();
        assert_eq!(second, [1, 2, 4, 7]);
        for n in 0..40 {
            let counted = (0..n).filter(|&k| in_second_half(k)).count() as u32;
            assert_eq!(second_half_count(n), counted, "n {n}");
        }
    }

    #[test]
    fn blocks_follow_the_image_not_the_tile() {
        assert_eq!(blocks(20, 9), (3, 2));
        assert_eq!(block_of(20, 17, 8), 5);
        assert_eq!(blocks_in(20, TileRect::new(6, 0, 4, 9)), [0, 1, 3, 4]);
    }

    #[test]
    fn tiles_round_trip_and_the_error_separates_flat_from_noisy() {
        let mut sums = SumImage::new(16, 8);
        let n = 4u32;
        // Block 0 flat (every sample 0.5), block 1 noisy (samples alternate 0 and 1).
        for y in 0..8 {
            for x in 0..16 {
                let p = (y * 16 + x) * SUMS;
                let (all, odd) = if x < 8 { (2.0, 1.0) } else { (2.0, 2.0) };
                sums.data[p..p + SUMS].copy_from_slice(&[all, all, all, all, odd, 8.0]);
            }
        }
        assert_eq!(sums.block_error(0, n), 0.0);
        assert!((sums.block_error(1, n) - 1.0).abs() < 1e-12);
        assert!(sums.block_error(0, 1).is_infinite());
        let rect = TileRect::new(3, 2, 9, 4);
        let tile = sums.tile(rect);
        let mut copy = SumImage::new(16, 8);
        copy.put_tile(rect, &tile);
        assert_eq!(copy.tile(rect), tile);
        let bytes = SumImage::to_bytes(&tile);
        assert_eq!(SumImage::from_bytes(&bytes, 36, "t").unwrap(), tile);
        assert!(SumImage::from_bytes(&bytes[1..], 36, "t").is_err());
        let image = sums.image(&[4, 2]);
        assert_eq!(image.pixel(0, 0), [0.5; 3]);
        assert_eq!(image.pixel(9, 0), [1.0; 3]);
    }
}
