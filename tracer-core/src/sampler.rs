//! Deterministic random numbers: a generator seeded from (seed, pixel, sample) alone, so a
//! pixel's value never depends on threads, tiles or workers.

/// SplitMix64 finaliser: a strong 64-bit mix.
#[inline]
fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xbf58476d1ce4e5b9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94d049bb133111eb);
    z ^ (z >> 31)
}

/// A small, fast generator (SplitMix64 stream) for one pixel sample.
#[derive(Clone, Debug)]
pub struct Rng {
    state: u64,
}

impl Rng {
    pub fn for_sample(seed: u64, x: u32, y: u32, sample: u32) -> Rng {
        let pixel = ((y as u64) << 32) | x as u64;
        let state = mix(mix(seed ^ 0x9e3779b97f4a7c15) ^ mix(pixel).wrapping_add(sample as u64));
        Rng {
            state: mix(state.wrapping_add(sample as u64)),
        }
    }

    /// An independent stream of the same pixel sample for one effect. Effects draw only from
    /// their own stream, so turning one on never shifts the numbers the course's model uses
    /// (jitter, light samples): a scene without it renders the same bits as before.
    pub fn for_stream(seed: u64, x: u32, y: u32, sample: u32, stream: Stream) -> Rng {
        let base = Rng::for_sample(seed, x, y, sample).state;
        Rng {
            state: mix(base ^ mix(0xd1b54a32d192ed03u64.wrapping_mul(stream as u64))),
        }
    }

    /// A generator at `state` (a placeholder to be overwritten, in arrays of streams).
    pub const fn from_state(state: u64) -> Rng {
        Rng { state }
    }

    #[inline]
    pub fn next_u64(&mut self) -> u64 {
        self.state = self.state.wrapping_add(0x9e3779b97f4a7c15);
        mix(self.state)
    }

    /// Uniform in [0, 1).
    #[inline]
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 * (1.0 / (1u64 << 53) as f64)
    }
}

/// The random dimensions the effects add, each its own stream (see [`Rng::for_stream`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Stream {
    /// The thin lens's point on the aperture.
    Lens = 1,
    /// The time within the shutter interval.
    Time = 2,
    /// Glossy reflection lobes, drawn in tracing order.
    Gloss = 3,
}

/// A uniform point on the unit sphere from two uniform numbers.
#[inline]
pub fn uniform_sphere(u1: f64, u2: f64) -> glam::DVec3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let (cos, sin) = turn(u2);
    glam::DVec3::new(r * cos, r * sin, z)
}

/// (cos 2πu, sin 2πu) for u in [0, 1], without the library's `sincos` call (4–5% of a soft-shadow
/// render): the turn is split into the nearest quarter, which only swaps and negates, and a
/// remainder of at most an eighth of a turn, where fdlibm's kernel polynomials are accurate to
/// about an ulp. The results differ from `cos`/`sin` of 2πu by rounding only.
#[inline]
pub fn turn(u: f64) -> (f64, f64) {
    // Coefficients of fdlibm's __kernel_sin and __kernel_cos on [-π/4, π/4], digits as
    // published (more than f64 holds; they round to fdlibm's bit patterns).
    #[allow(clippy::excessive_precision)]
    const S: [f64; 6] = [
        -1.666_666_666_666_663_243_48e-1,
        8.333_333_333_322_489_461_24e-3,
        -1.984_126_982_985_794_931_34e-4,
        2.755_731_370_707_006_767_89e-6,
        -2.505_076_025_340_686_341_95e-8,
        1.589_690_995_211_550_102_21e-10,
    ];
    #[allow(clippy::excessive_precision)]
    const C: [f64; 6] = [
        4.166_666_666_666_660_190_37e-2,
        -1.388_888_888_887_410_957_49e-3,
        2.480_158_728_947_672_941_78e-5,
        -2.755_731_435_139_066_330_35e-7,
        2.087_572_321_298_174_827_90e-9,
        -1.135_964_755_778_819_482_65e-11,
    ];
    let quarters = 4.0 * u;
    // Nearest quarter turn (u ≥ 0, so adding a half and truncating rounds); the remainder
    // quarters − k is exact.
    let k = (quarters + 0.5) as i64;
    let a = (quarters - k as f64) * std::f64::consts::FRAC_PI_2;
    let z = a * a;
    let sin = a + a * z * (S[0] + z * (S[1] + z * (S[2] + z * (S[3] + z * (S[4] + z * S[5])))));
    let r = z * (C[0] + z * (C[1] + z * (C[2] + z * (C[3] + z * (C[4] + z * C[5])))));
    let cos = 1.0 - (0.5 * z - z * r);
    match k & 3 {
        0 => (cos, sin),
        1 => (-sin, cos),
        2 => (-cos, -sin),
        _ => (sin, -cos),
    }
}

/// A uniform point on the unit disk (Shirley–Chiu concentric map: strata stay compact).
pub fn concentric_disk(u1: f64, u2: f64) -> (f64, f64) {
    let a = 2.0 * u1 - 1.0;
    let b = 2.0 * u2 - 1.0;
    if a == 0.0 && b == 0.0 {
        return (0.0, 0.0);
    }
    let (r, phi) = if a.abs() > b.abs() {
        (a, std::f64::consts::FRAC_PI_4 * (b / a))
    } else {
        (
            b,
            std::f64::consts::FRAC_PI_2 - std::f64::consts::FRAC_PI_4 * (a / b),
        )
    };
    (r * phi.cos(), r * phi.sin())
}

/// The stratum grid for `spp` samples: `cols × rows == spp` with cols the largest divisor of
/// spp not above √spp (40 → 5×8; a prime count degrades to 1×spp stripes, still unbiased).
pub fn strata(spp: u32) -> (u32, u32) {
    let mut cols = (spp as f64).sqrt() as u32;
    while cols > 1 && !spp.is_multiple_of(cols) {
        cols -= 1;
    }
    let cols = cols.max(1);
    (cols, spp / cols)
}

/// The order in which a pixel's samples visit its `cols × rows` strata.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub enum SampleOrder {
    /// Sample k takes stratum k, row by row: the one-shot order every render has used.
    #[default]
    Grid,
    /// Every prefix of the samples is spread over the whole pixel, so a progressive render's
    /// early passes (and the error estimate made from them) see all of it, not its top rows.
    Progressive,
}

/// The progressive order of pixel (x, y)'s `cols × rows` strata, its first `limit` samples:
/// `out[k]` is the stratum (`cx + cy·cols`) of sample k. Costs O(limit), not O(strata): a
/// pass over the first samples of a large `spp_max` only orders what it renders.
///
/// Strata are numbered along a Morton curve of the enclosing power-of-two grid whose leading
/// bits are the coarsest cells; sample k takes the code `reverse(lk(k))`, with `lk` a
/// hash-based nested (Owen) scramble of k. A prefix of 2^j samples then puts exactly one
/// sample in each of the 2^j coarsest cells (`lk` permutes every set of low bits among
/// themselves, and the reversal makes k's low bits the code's leading ones), and the per-pixel
/// scramble puts each cell's sample at its own place in the cell. (A plain XOR mask would put
/// every sample of a prefix at the same place in its cell: a regular grid, measurably
/// noisier.) Codes outside a grid that is not a power of two in some direction are skipped;
/// its prefixes stay nearly as well spread.
pub fn progressive_strata(
    seed: u64,
    x: u32,
    y: u32,
    grid: (u32, u32),
    limit: u32,
    out: &mut Vec<u32>,
) {
    progressive_strata_from(seed, x, y, grid, 0, limit, out);
}

/// [`progressive_strata`] of samples `from..limit` only: `out[i]` is the stratum of sample
/// `from + i`. On a power-of-two grid (every code is a stratum) sample k's stratum follows
/// from k alone, so a later pass costs only its own samples, not the prefix before them.
pub fn progressive_strata_from(
    seed: u64,
    x: u32,
    y: u32,
    (cols, rows): (u32, u32),
    from: u32,
    limit: u32,
    out: &mut Vec<u32>,
) {
    out.clear();
    let limit = limit.min(cols * rows) as usize;
    let (bx, by) = (
        cols.next_power_of_two().trailing_zeros(),
        rows.next_power_of_two().trailing_zeros(),
    );
    let bits = bx + by;
    let pixel_seed = mix(mix(seed ^ 0x2545f4914f6cdd1d) ^ (((y as u64) << 32) | x as u64));
    let from = (from as usize).min(limit);
    if cols.is_power_of_two() && rows.is_power_of_two() {
        for k in from as u64..limit as u64 {
            let (cx, cy) = morton_decode(scrambled_code(k, bits, pixel_seed), bx, by);
            out.push(cx + cy * cols);
        }
        return;
    }
    for k in 0..1u64 << bits {
        let code = scrambled_code(k, bits, pixel_seed);
        let (cx, cy) = morton_decode(code, bx, by);
        if cx < cols && cy < rows {
            out.push(cx + cy * cols);
            if out.len() == limit {
                break;
            }
        }
    }
    out.drain(..from);
}

/// [`progressive_strata_from`] for one grid, with its Morton codes decoded once into a table
/// where the grid is a power of two both ways and small (a progressive job's `spp_max`). The
/// table is indexed by the scrambled index's low bits before their reversal, so a sample
/// costs the scramble's multiplications and one load. The decode's loop over the code's bits
/// was most of the order's cost: on a progressive stacks.scene render the order took 1.9 %
/// before the table and 0.4 % after it.
#[derive(Clone, Debug)]
pub struct StrataOrder {
    grid: (u32, u32),
    /// The stratum of each scrambled index's low bits, when decoded ahead.
    stratum_of_scrambled: Option<Vec<u32>>,
}

impl StrataOrder {
    /// Grids of up to this many strata get a decoded table (16 KiB).
    const TABLE_MAX: u32 = 4096;

    pub fn new((cols, rows): (u32, u32)) -> Self {
        let table = cols.is_power_of_two()
            && rows.is_power_of_two()
            && cols.saturating_mul(rows) <= Self::TABLE_MAX;
        let stratum_of_scrambled = table.then(|| {
            let (bx, by) = (cols.trailing_zeros(), rows.trailing_zeros());
            let bits = bx + by;
            (0..cols * rows)
                .map(|low| {
                    let code = (low as u64)
                        .reverse_bits()
                        .checked_shr(64 - bits)
                        .unwrap_or(0);
                    let (cx, cy) = morton_decode(code, bx, by);
                    cx + cy * cols
                })
                .collect()
        });
        Self {
            grid: (cols, rows),
            stratum_of_scrambled,
        }
    }

    /// Exactly [`progressive_strata_from`]`(seed, x, y, grid, from, limit, out)`.
    pub fn fill(&self, seed: u64, x: u32, y: u32, from: u32, limit: u32, out: &mut Vec<u32>) {
        let Some(table) = &self.stratum_of_scrambled else {
            return progressive_strata_from(seed, x, y, self.grid, from, limit, out);
        };
        out.clear();
        let limit = limit.min(table.len() as u32);
        let mask = table.len() as u64 - 1;
        let pixel_seed = mix(mix(seed ^ 0x2545f4914f6cdd1d) ^ (((y as u64) << 32) | x as u64));
        out.extend(
            (from.min(limit) as u64..limit as u64)
                .map(|k| table[(owen_scramble(k, pixel_seed) & mask) as usize]),
        );
    }
}

/// Sample k's `bits`-bit Morton code: k's bits reversed (the coarsest cells first) after a
/// nested scramble. A hash-based Owen scramble (Laine and Karras; Burley's constants,
/// "Practical Hash-based Owen Scrambling", JCGT 2020) of the reversed code is, before the
/// reversal, a map in which each bit depends on the bits below it only: a bijection on every
/// set of low bits, so on every prefix of the code's leading bits. It costs four
/// multiplications per sample where a hash per bit cost two hashes per bit (a progressive job
/// spent 5.7 % of its time there). In 64-bit words: the low 32 bits are Burley's hash
/// exactly, and grids past 2^32 codes still get a bijection.
#[inline]
fn scrambled_code(k: u64, bits: u32, seed: u64) -> u64 {
    if bits == 0 {
        return 0;
    }
    owen_scramble(k, seed).reverse_bits() >> (64 - bits)
}

/// The nested scramble of [`scrambled_code`], before the reversal.
#[inline]
fn owen_scramble(k: u64, seed: u64) -> u64 {
    let mut v = k.wrapping_add(seed);
    v ^= v.wrapping_mul(0x6c50_b47c);
    v ^= v.wrapping_mul(0xb82f_1e52);
    v ^= v.wrapping_mul(0xc7af_e638);
    v ^= v.wrapping_mul(0x8d22_f6e6);
    v
}

/// Splits a Morton code of a `2^bx × 2^by` grid whose most significant bits are the coarsest
/// (x and y bits alternate from the top while both last, then the longer one's follow).
fn morton_decode(code: u64, bx: u32, by: u32) -> (u32, u32) {
    let (mut cx, mut cy) = (0u32, 0u32);
    let (mut rx, mut ry) = (bx, by);
    let mut bit = bx + by;
    let mut take_x = true;
    while bit > 0 {
        bit -= 1;
        let v = ((code >> bit) & 1) as u32;
        let to_x = if rx == 0 {
            false
        } else if ry == 0 {
            true
        } else {
            take_x
        };
        if to_x {
            rx -= 1;
            cx |= v << rx;
        } else {
            ry -= 1;
            cy |= v << ry;
        }
        take_x = !take_x;
    }
    (cx, cy)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_samples_are_unit_and_unbiased() {
        let mut rng = Rng::for_sample(3, 1, 2, 0);
        let mut mean = glam::DVec3::ZERO;
        for _ in 0..20_000 {
            let p = uniform_sphere(rng.next_f64(), rng.next_f64());
            assert!((p.length() - 1.0).abs() < 1e-12);
            mean += p;
        }
        assert!((mean / 20_000.0).length() < 0.02);
    }

    #[test]
    fn turn_agrees_with_the_library_sin_and_cos() {
        let mut rng = Rng::for_sample(9, 8, 7, 6);
        let edges = [0.0, 0.125, 0.25, 0.375, 0.5, 0.625, 0.75, 0.875, 1.0];
        let values = edges
            .iter()
            .flat_map(|&e: &f64| [e, e.next_up(), e.next_down().max(0.0)])
            .chain((0..200_000).map(|_| rng.next_f64()));
        let mut worst = 0f64;
        for u in values {
            let (c, s) = turn(u);
            let phi = std::f64::consts::TAU * u;
            worst = worst.max((c - phi.cos()).abs()).max((s - phi.sin()).abs());
        }
        assert!(worst < 4.0 * f64::EPSILON, "worst difference {worst:e}");
    }

    #[test]
    fn streams_are_reproducible_and_distinct() {
        let a: Vec<u64> = (0..4)
            .map(|_| 0)
            .scan(Rng::for_sample(1, 2, 3, 4), |r, _| Some(r.next_u64()))
            .collect();
        let b: Vec<u64> = (0..4)
            .map(|_| 0)
            .scan(Rng::for_sample(1, 2, 3, 4), |r, _| Some(r.next_u64()))
            .collect();
        assert_eq!(a, b);
        let mut firsts = std::collections::HashSet::new();
        for s in 0..4 {
            for x in 0..50 {
                for y in 0..50 {
                    firsts.insert(Rng::for_sample(7, x, y, s).next_u64());
                }
            }
        }
        assert_eq!(firsts.len(), 4 * 50 * 50);
    }

    #[test]
    fn uniform_values_fill_the_unit_interval() {
        let mut rng = Rng::for_sample(0, 0, 0, 0);
        let mut buckets = [0u32; 10];
        for _ in 0..100_000 {
            let v = rng.next_f64();
            assert!((0.0..1.0).contains(&v));
            buckets[(v * 10.0) as usize] += 1;
        }
        assert!(
            buckets.iter().all(|&b| (9_500..10_500).contains(&b)),
            "{buckets:?}"
        );
    }

    #[test]
    fn streams_differ_from_the_main_stream_and_each_other() {
        let main = Rng::for_sample(5, 6, 7, 8).next_u64();
        let lens = Rng::for_stream(5, 6, 7, 8, Stream::Lens).next_u64();
        let time = Rng::for_stream(5, 6, 7, 8, Stream::Time).next_u64();
        let gloss = Rng::for_stream(5, 6, 7, 8, Stream::Gloss).next_u64();
        let all = [main, lens, time, gloss];
        for i in 0..4 {
            for j in i + 1..4 {
                assert_ne!(all[i], all[j]);
            }
        }
        assert_eq!(lens, Rng::for_stream(5, 6, 7, 8, Stream::Lens).next_u64());
    }

    #[test]
    fn concentric_disk_stays_inside_the_unit_disk() {
        let mut rng = Rng::for_sample(1, 1, 1, 1);
        for _ in 0..10_000 {
            let (x, y) = concentric_disk(rng.next_f64(), rng.next_f64());
            assert!(x * x + y * y <= 1.0 + 1e-12);
        }
        assert_eq!(concentric_disk(0.5, 0.5), (0.0, 0.0));
    }

    #[test]
    fn strata_multiply_to_spp() {
        assert_eq!(strata(1), (1, 1));
        assert_eq!(strata(16), (4, 4));
        assert_eq!(strata(40), (5, 8));
        assert_eq!(strata(7), (1, 7));
    }

    #[test]
    fn progressive_order_is_a_permutation_whose_prefixes_cover_the_pixel() {
        let mut order = Vec::new();
        for (spp, x) in [(16u32, 0u32), (64, 3), (40, 7), (7, 1), (1, 0), (32, 9)] {
            let grid = strata(spp);
            progressive_strata(11, x, 5, grid, spp, &mut order);
            let mut sorted = order.clone();
            sorted.sort();
            assert_eq!(sorted, (0..spp).collect::<Vec<_>>(), "spp {spp}");
        }
        // 64 strata (8×8): the first 4 samples land one in each quadrant, the first 16 one in
        // each 2×2 block.
        progressive_strata(3, 10, 20, (8, 8), 64, &mut order);
        let cell = |s: u32, size: u32| ((s % 8) / size, (s / 8) / size);
        let quads: std::collections::HashSet<_> = order[..4].iter().map(|&s| cell(s, 4)).collect();
        assert_eq!(quads.len(), 4);
        let blocks: std::collections::HashSet<_> =
            order[..16].iter().map(|&s| cell(s, 2)).collect();
        assert_eq!(blocks.len(), 16);
        // Pixels differ in their orders (the scramble), each reproducibly.
        let mut other = Vec::new();
        progressive_strata(3, 11, 20, (8, 8), 64, &mut other);
        assert_ne!(order, other);
        progressive_strata(3, 10, 20, (8, 8), 64, &mut other);
        assert_eq!(order, other);
        // A prefix is the start of the whole order.
        progressive_strata(3, 10, 20, (8, 8), 9, &mut other);
        assert_eq!(other, order[..9]);
        progressive_strata(5, 1, 2, (5, 8), 40, &mut order);
        progressive_strata(5, 1, 2, (5, 8), 17, &mut other);
        assert_eq!(other, order[..17]);
        // A later range is the same slice of the whole order, on either kind of grid.
        progressive_strata_from(5, 1, 2, (5, 8), 9, 17, &mut other);
        assert_eq!(other, order[9..17]);
        progressive_strata(3, 10, 20, (8, 8), 64, &mut order);
        progressive_strata_from(3, 10, 20, (8, 8), 13, 40, &mut other);
        assert_eq!(other, order[13..40]);
    }

    #[test]
    fn a_decoded_strata_order_is_the_order_itself() {
        // Table-driven (power-of-two grids up to 4096 strata) and not, every range of a few
        // pixels' samples equals `progressive_strata_from`'s.
        let (mut expected, mut got) = (Vec::new(), Vec::new());
        for grid in [
            (1, 1),
            (2, 1),
            (4, 4),
            (16, 8),
            (16, 32),
            (64, 64),
            (128, 64),
            (5, 8),
        ] {
            let order = StrataOrder::new(grid);
            let strata = grid.0 * grid.1;
            for (x, y) in [(0, 0), (3, 7), (799, 599)] {
                for (from, limit) in [(0, strata), (0, 1), (8, 16), (5, 23), (strata / 2, strata)] {
                    progressive_strata_from(11, x, y, grid, from, limit, &mut expected);
                    order.fill(11, x, y, from, limit, &mut got);
                    assert_eq!(got, expected, "grid {grid:?} pixel {x},{y} {from}..{limit}");
                }
            }
        }
        assert!(StrataOrder::new((16, 32)).stratum_of_scrambled.is_some());
        assert!(StrataOrder::new((128, 64)).stratum_of_scrambled.is_none());
    }

    #[test]
    fn every_power_of_two_prefix_is_stratified_in_every_pixel() {
        // On 16×32 strata (a progressive job's spp_max of 512), samples 0..2^j of any pixel
        // fall one in each of the 2^j coarsest Morton cells, and so does every aligned run
        // 2^j·m..2^j·(m+1): each doubling pass adds a stratified set of its own.
        let mut order = Vec::new();
        for (x, y) in (0..40).map(|i| (i * 7 % 23, i * 13 % 31)) {
            progressive_strata(9, x, y, (16, 32), 512, &mut order);
            let code = |s: u32| {
                let (cx, cy) = (s % 16, s / 16);
                // Morton code, coarsest bits first: x and y alternate for 4 levels, then y.
                let mut c = 0u32;
                for level in 0..4 {
                    c = c << 2 | ((cx >> (3 - level)) & 1) << 1 | ((cy >> (4 - level)) & 1);
                }
                c << 1 | (cy & 1)
            };
            for j in 0..=9 {
                for run in order.chunks(1 << j) {
                    let cells: std::collections::HashSet<_> =
                        run.iter().map(|&s| code(s) >> (9 - j)).collect();
                    assert_eq!(cells.len(), 1 << j, "pixel ({x}, {y}), 2^{j}");
                }
            }
        }
    }

    #[test]
    fn the_scramble_spreads_a_cells_sample_over_the_cell() {
        // Sample 0 of each pixel, on 8×8 strata: its stratum is uniform over all 64 across
        // pixels, not one place shared by all (which a plain XOR mask per level would give
        // within a prefix).
        let mut order = Vec::new();
        let mut counts = [0u32; 64];
        for y in 0..64 {
            for x in 0..100 {
                progressive_strata(4, x, y, (8, 8), 1, &mut order);
                counts[order[0] as usize] += 1;
            }
        }
        // 100 expected per stratum; a binomial's spread is 10.
        assert!(counts.iter().all(|&c| (50..150).contains(&c)), "{counts:?}");
    }
}
