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
