//! The fuzz targets' bodies live in `harness.rs`, which the stable regression tests
//! (`tracer-core/tests/fuzz_regressions.rs`) include too, so a saved input replays exactly.

pub mod harness;
