//! One measure of `tracer bench` alone, on the calling thread, for profilers and instruction
//! counters (the full bench mixes the build, three ray sets and a render in one process):
//!
//! `cargo build --release --example bench_measure`, then e.g.
//! `perf stat -e cycles:u,instructions:u $CARGO_TARGET_DIR/release/examples/bench_measure
//!  ../shared/scenes/course/dragon.scene incoherent 10`
//! (measure: primary (in packets), primary-single (one ray at a time), incoherent, shadow (in
//! packets), shadow-single or build; the number of passes).

use std::path::Path;
use std::time::Instant;

use tracer_core::bench::{trace, Measure, RaySets};
use tracer_core::{RenderSettings, Scene};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let [_, scene, measure, passes] = args.as_slice() else {
        return Err("usage: bench_measure SCENE \
             primary|primary-single|incoherent|shadow|shadow-single|build PASSES"
            .into());
    };
    let passes: usize = passes.parse()?;
    let scene = Scene::load(Path::new(scene))?;
    let settings = RenderSettings {
        width: 800,
        height: 600,
        spp: 1,
        ..RenderSettings::default()
    };
    let measure = match measure.as_str() {
        "primary" => Some(Measure::Primary),
        "primary-single" => Some(Measure::PrimarySingle),
        "incoherent" => Some(Measure::Incoherent),
        "shadow" => Some(Measure::Shadow),
        "shadow-single" => Some(Measure::ShadowSingle),
        "build" => None,
        other => return Err(format!("unknown measure {other}").into()),
    };
    let rays = RaySets::new(&scene, &settings)?;
    let started = Instant::now();
    let mut count = 0;
    for _ in 0..passes {
        count += match measure {
            Some(m) => trace(&scene, &rays, m),
            None => {
                std::hint::black_box(scene.world().rebuilt());
                0
            }
        };
    }
    eprintln!("{count} hits in {:.3?}", started.elapsed());
    Ok(())
}
