//! What loading only the referenced assets saves on the course scenes.
//!
//! `cargo bench -p tracer-core --bench lean`. For each course scene: the assets it references
//! (what the farm ships and a worker loads), its load time split into asset decoding and BVH
//! building, against the bytes and decode time of every asset in the course folder (what
//! shipping and loading the whole folder would cost); the peak memory of a process that loads
//! the scene alone against one that also holds every course asset decoded; and what skipping
//! texture sampling saves on an untextured scene.

use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::Instant;

use tracer_core::scene::{parse_obj, SceneDescription};
use tracer_core::texture::Texture;
use tracer_core::{FsAssets, RenderSettings, Renderer, Scene};

fn decode(path: &Path) {
    let bytes = std::fs::read(path).expect("course asset reads");
    if path.extension().is_some_and(|e| e == "png") {
        std::hint::black_box(Texture::decode_png(&bytes).expect("course texture decodes"));
    } else {
        let text = String::from_utf8_lossy(&bytes);
        std::hint::black_box(parse_obj(&text, "asset").expect("course mesh parses"));
    }
}

/// Set in a child process: load this scene (and, with [`HOLD_FOLDER`], every course asset),
/// then print the process's peak resident memory.
const CHILD_SCENE: &str = "TESSERA_LEAN_CHILD_SCENE";
const HOLD_FOLDER: &str = "TESSERA_LEAN_HOLD_FOLDER";

fn course_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../shared/scenes/course")
}

fn course_assets(root: &Path) -> Vec<PathBuf> {
    let mut folder: Vec<PathBuf> = ["images", "models"]
        .iter()
        .flat_map(|d| std::fs::read_dir(root.join(d)).expect("course folder"))
        .map(|e| e.expect("entry").path())
        .collect();
    folder.sort();
    folder
}

/// Peak resident set size of this process in MB (Linux `VmHWM`).
fn peak_rss_mb() -> f64 {
    let status = std::fs::read_to_string("/proc/self/status").unwrap_or_default();
    status
        .lines()
        .find_map(|l| l.strip_prefix("VmHWM:"))
        .and_then(|v| v.trim().trim_end_matches("kB").trim().parse::<f64>().ok())
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

fn child(scene: &str) {
    let mut held = Vec::new();
    if std::env::var_os(HOLD_FOLDER).is_some() {
        for p in course_assets(&course_root()) {
            let bytes = std::fs::read(&p).expect("course asset reads");
            if p.extension().is_some_and(|e| e == "png") {
                held.push(Box::new(Texture::decode_png(&bytes).unwrap()) as Box<dyn std::any::Any>);
            } else {
                let text = String::from_utf8_lossy(&bytes);
                held.push(Box::new(parse_obj(&text, "asset").unwrap()));
            }
        }
    }
    let loaded = Scene::load(Path::new(scene)).expect("course scene loads");
    std::hint::black_box((&loaded, &held));
    println!("{}", peak_rss_mb());
}

/// Peak memory of a fresh process that loads `scene` (and holds every course asset too).
fn peak_mb_loading(scene: &Path, hold_folder: bool) -> f64 {
    let mut cmd = Command::new(std::env::current_exe().unwrap());
    cmd.env(CHILD_SCENE, scene);
    if hold_folder {
        cmd.env(HOLD_FOLDER, "1");
    }
    let out = cmd.output().expect("the bench re-runs itself");
    String::from_utf8_lossy(&out.stdout)
        .trim()
        .parse()
        .unwrap_or(f64::NAN)
}

fn main() {
    if let Ok(scene) = std::env::var(CHILD_SCENE) {
        child(&scene);
        return;
    }
    let root = course_root();
    let folder = course_assets(&root);
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
        "{:<12} {:>6} {:>10} {:>10} {:>10} {:>9} {:>10} {:>9} {:>12}",
        "scene",
        "assets",
        "MB",
        "assets ms",
        "BVH ms",
        "load ms",
        "saved MB",
        "peak MB",
        "+folder MB"
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
            "{:<12} {:>6} {:>10.3} {:>10.1} {:>10.1} {:>9.1} {:>10.2} {:>9.1} {:>12.1}",
            path.file_stem().unwrap().to_string_lossy(),
            referenced.len(),
            bytes as f64 / 1e6,
            scene.stats.asset_load.as_secs_f64() * 1e3,
            scene.stats.bvh_build.as_secs_f64() * 1e3,
            load_ms,
            (folder_bytes - bytes) as f64 / 1e6,
            peak_mb_loading(&path, false),
            peak_mb_loading(&path, true)
        );
    }
    texture_sampling_cost(&root);
}

/// Renders cornell_box as it is and with every material textured by a 1×1 white PNG: the
/// images are identical, so the difference is what a scene without textures saves by never
/// sampling one.
fn texture_sampling_cost(root: &Path) {
    let dir = std::env::temp_dir().join(format!("tessera-lean-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let white = tracer_core::Image::from_pixels(1, 1, vec![1.0; 3]).unwrap();
    std::fs::write(dir.join("white.png"), white.to_png()).unwrap();
    let text = std::fs::read_to_string(root.join("cornell_box.scene")).unwrap();
    let textured = text.replace(
        "<material name=\"",
        "<material texture=\"white.png\" name=\"",
    );
    std::fs::write(dir.join("textured.scene"), textured).unwrap();
    std::fs::write(dir.join("plain.scene"), &text).unwrap();
    let settings = RenderSettings {
        width: 400,
        height: 300,
        spp: 4,
        ..RenderSettings::default()
    };
    let mut images = Vec::new();
    println!("\ncornell_box 400x300 4 spp, fastest of 5:");
    for name in ["plain", "textured"] {
        let scene = Scene::load(&dir.join(format!("{name}.scene"))).unwrap();
        let renderer = Renderer::new(&scene, &settings).unwrap();
        let mut best = f64::INFINITY;
        let mut image = None;
        for _ in 0..5 {
            let started = Instant::now();
            image = Some(renderer.render_image(&|_, _| {}));
            best = best.min(started.elapsed().as_secs_f64());
        }
        println!("  {name:<9} {:.1} ms", best * 1e3);
        images.push(image.unwrap().to_png());
    }
    assert_eq!(
        images[0], images[1],
        "a white texture must not change the image"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}
