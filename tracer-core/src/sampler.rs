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

#[cfg(test)]
mod tests {
    use super::*;

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
    fn strata_multiply_to_spp() {
        assert_eq!(strata(1), (1, 1));
        assert_eq!(strata(16), (4, 4));
        assert_eq!(strata(40), (5, 8));
        assert_eq!(strata(7), (1, 7));
    }
}
