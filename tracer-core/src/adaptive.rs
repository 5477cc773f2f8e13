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
/// second half-buffer ([`in_second_half`]): the two half-buffers of the error estimate.
pub const SUMS: usize = 5;

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

/// Cumulative samples per pixel after pass `pass` (counted from 0) of a render that starts
/// with `spp_min` and stops at `spp_max`: each pass adds half of what was there (at least one
/// sample), so passes grow geometrically and a time limit loses at most a third of the work.
pub fn pass_target(pass: u32, spp_min: u32, spp_max: u32) -> u32 {
    let mut n = spp_min.clamp(1, spp_max.max(1));
    for _ in 0..pass {
        if n >= spp_max {
            break;
        }
        n = (n + (n / 2).max(1)).min(spp_max);
    }
    n
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
        let (num, den) = self.block_error_parts(block, n);
        if n < 2 {
            f64::INFINITY
        } else {
            num / den
        }
    }

    /// Σ|A − B|/2 and Σ max(I, floor) over the block's pixels.
    fn block_error_parts(&self, block: usize, n: u32) -> (f64, f64) {
        let cols = self.width.div_ceil(BLOCK) as usize;
        let (bx, by) = ((block % cols) as u32 * BLOCK, (block / cols) as u32 * BLOCK);
        let second = second_half_count(n);
        let (first_n, second_n) = ((n - second.min(n)) as f64, second as f64);
        let (mut num, mut den) = (0.0, 0.0);
        for y in by..(by + BLOCK).min(self.height) {
            for x in bx..(bx + BLOCK).min(self.width) {
                let p = (y as usize * self.width as usize + x as usize) * SUMS;
                let (all, second) = (self.data[p + 3], self.data[p + 4]);
                if n >= 2 {
                    num += ((all - second) / first_n - second / second_n).abs() / 2.0;
                }
                den += (all / n.max(1) as f64).max(DARK_FLOOR);
            }
        }
        (num, den)
    }

    /// The image's relative error estimate, with each block at its own sample count
    /// (`counts[block]`): the same ratio as a block's, over every pixel.
    pub fn error(&self, counts: &[u32]) -> f64 {
        let (mut num, mut den) = (0.0, 0.0);
        for (block, &n) in counts.iter().enumerate() {
            if n < 2 {
                return f64::INFINITY;
            }
            let (a, b) = self.block_error_parts(block, n);
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

    #[test]
    fn passes_grow_from_spp_min_to_spp_max() {
        let targets: Vec<u32> = (0..12).map(|p| pass_target(p, 4, 64)).collect();
        assert_eq!(targets, [4, 6, 9, 13, 19, 28, 42, 63, 64, 64, 64, 64]);
        assert_eq!(pass_target(0, 1, 3), 1);
        assert_eq!(pass_target(1, 1, 3), 2);
        assert_eq!(pass_target(0, 10, 4), 4);
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
                sums.data[p..p + SUMS].copy_from_slice(&[all, all, all, all, odd]);
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
