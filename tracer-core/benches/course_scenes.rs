//! Render time of every course scene at 800×600, at 1 and 16 samples per pixel.
//!
//! `cargo bench -p tracer-core --bench course_scenes [-- SCENE...]`; scene loading is timed
//! apart from rendering. Each render runs once after a 1-spp warm-up (a 16-spp render of a
//! whole frame is long enough that repeated runs differ by a few percent at most).

use std::path::PathBuf;
use std::time::Instant;

use tracer_core::{RenderSettings, Renderer, Scene};

const SCENES: [&str; 8] = [
    "cornell_box",
    "cube",
    "dragon",
    "spheres",
    "stacks",
    "test",
    "tetrahedron",
    "toy",
];

fn main() {
    let filter: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes/course");
    println!(
        "{:<12} {:>9} {:>10} {:>11} {:>12}",
        "scene", "load ms", "1 spp s", "16 spp s", "16spp Mray/s"
    );
    for name in SCENES
        .iter()
        .filter(|n| filter.is_empty() || filter.iter().any(|f| f == *n))
    {
        let started = Instant::now();
        let scene = Scene::load(&root.join(format!("{name}.scene"))).expect("course scene loads");
        let load_ms = started.elapsed().as_secs_f64() * 1e3;
        let time = |spp| {
            let settings = RenderSettings {
                spp,
                ..RenderSettings::default()
            };
            let renderer = Renderer::new(&scene, &settings).expect("valid settings");
            let started = Instant::now();
            std::hint::black_box(renderer.render_image(&|_, _| {}));
            let seconds = started.elapsed().as_secs_f64();
            (seconds, renderer.rays_traced() as f64 / seconds / 1e6)
        };
        time(1);
        let (one, _) = time(1);
        let (sixteen, mrays) = time(16);
        println!("{name:<12} {load_ms:>9.1} {one:>10.3} {sixteen:>11.2} {mrays:>12.1}");
    }
}
