//! A deterministic uniform generator for tests (a 64-bit LCG, Knuth's MMIX constants): the
//! randomised tests scatter rays and primitives with it and see the same scene every run.

/// Numbers in [0, 1) from `state`, 53 random bits each.
pub fn uniform(mut state: u64) -> impl FnMut() -> f64 {
    move || {
        state = state
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (state >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// `n` boxes from the stream seeded with `seed`: centres uniform in [0, `span`)³, half
/// extents uniform in [`min_half`, `min_half` + `spread`) per axis (centre drawn first).
pub fn boxes(
    seed: u64,
    n: usize,
    span: f64,
    min_half: f64,
    spread: f64,
) -> Vec<crate::geometry::Aabb> {
    let mut next = uniform(seed);
    (0..n)
        .map(|_| {
            let c = glam::DVec3::new(next(), next(), next()) * span;
            let e = glam::DVec3::new(next(), next(), next()) * spread + min_half;
            crate::geometry::Aabb {
                min: c - e,
                max: c + e,
            }
        })
        .collect()
}
