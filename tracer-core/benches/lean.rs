//! What loading only the referenced assets saves on the course scenes.
//!
//! `cargo bench -p tracer-core --bench lean`. For each course scene: the assets it references
//! (what the farm ships and a worker loads), its load time split into asset decoding and BVH
//! building, against the bytes and decode time of every asset in the course folder (what
//! shipping and loading the whole folder would cost).

use std::path::{Path, PathBuf};
use std::time::Instant;

use tracer_core::scene::{parse_obj, SceneDescription};
use tracer_core::texture::Texture;
use tracer_core::{FsAssets, Scene};

fn decode(path: &Path) {
    let bytes = std::fs::read(path).expect("course asset reads");
    if path.extension().is_some_and(|e| e == "png") {
        std::hint::black_box(Texture::decode_png(&bytes).expect("course texture decodes"));
    } else {
        let text = String::from_utf8_lossy(&bytes);
        std::hint::black_box(parse_obj(&text, "asset").expect("course mesh parses"));
    }
}

fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes/course");
    let mut folder: Vec<PathBuf> = ["images", "models"]
        .iter()
        .flat_map(|d| std::fs::read_dir(root.join(d)).expect("course folder"))
        .map(|e| e.expect("entry").path())
        .collect();
    folder.sort();
    let folder_bytes: u64 = folder.iter().map(|p| p.metadata().unwrap().len()).sum();
    let started = Instant::now();
    for p in &folder {
        decode(p);
    }
    let folder_ms = started.elapsed().as_secs_f64() * 1e3;
    println!(
        "whole course asset folder: {} files, {:.2} MB, {:.1} ms to decode\n",
        folder.len(),
        folder_bytes as f64 / 1e6,
        folder_ms
    );
    println!(
        "{:<12} {:>6} {:>10} {:>10} {:>10} {:>9} {:>10}",
        "scene", "assets", "MB", "assets ms", "BVH ms", "load ms", "saved MB"
    );
    let mut scenes: Vec<PathBuf> = std::fs::read_dir(&root)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "scene"))
        .collect();
    scenes.sort();
    for path in scenes {
        let text = std::fs::read_to_string(&path).unwrap();
        let desc = SceneDescription::parse(&text, "scene").unwrap();
        let fs = FsAssets::for_scene(&path);
        let referenced = desc.referenced_assets();
        let bytes: u64 = referenced
            .iter()
            .map(|a| fs.resolve(a).unwrap().metadata().unwrap().len())
            .sum();
        let started = Instant::now();
        let scene = Scene::load(&path).unwrap();
        let load_ms = started.elapsed().as_secs_f64() * 1e3;
        println!(
            "{:<12} {:>6} {:>10.3} {:>10.1} {:>10.1} {:>9.1} {:>10.2}",
            path.file_stem().unwrap().to_string_lossy(),
            referenced.len(),
            bytes as f64 / 1e6,
            scene.stats.asset_load.as_secs_f64() * 1e3,
            scene.stats.bvh_build.as_secs_f64() * 1e3,
            load_ms,
            (folder_bytes - bytes) as f64 / 1e6
        );
    }
}
