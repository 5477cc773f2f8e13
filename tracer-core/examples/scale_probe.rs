//! Where a scene's primary rays spend their time: `tracer bench`'s primary rays split into
//! those that hit and those that miss, each set traced alone on the calling thread, so scenes
//! whose views are mostly background (dragon.scene: 83% of its pixels) can be compared per
//! hit with scenes that fill the view (docs/performance.md, "Scale"). With `hash` instead, it
//! prints a hash of every mesh's BVH nodes and triangle order: a faster builder must leave it
//! unchanged.
//!
//! `cargo build --release --example scale_probe`, then
//! `RAYON_NUM_THREADS=1 $CARGO_TARGET_DIR/release/examples/scale_probe SCENE PASSES [hash]`.

use std::hash::{Hash, Hasher};
use std::path::Path;
use std::time::Instant;

use tracer_core::bench::RaySets;
use tracer_core::world::World;
use tracer_core::{RenderSettings, Scene};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let (Some(scene), Some(passes)) = (args.get(1), args.get(2)) else {
        return Err("usage: scale_probe SCENE PASSES [hash]".into());
    };
    let passes: usize = passes.parse()?;
    let scene = Scene::load(Path::new(scene))?;
    let world = scene.world();
    if args.get(3).is_some_and(|a| a == "hash") {
        print_hashes(world);
        return Ok(());
    }
    let settings = RenderSettings {
        width: 800,
        height: 600,
        spp: 1,
        ..RenderSettings::default()
    };
    let rays = RaySets::new(&scene, &settings)?;
    let hits = |r: &tracer_core::geometry::Ray| world.intersect(r, rays.near, rays.far).is_some();
    let (hit, miss): (Vec<_>, Vec<_>) = rays.primary.iter().partition(|r| hits(r));
    let all: Vec<_> = rays.primary.iter().collect();
    for (name, set) in [("hit", &hit), ("miss", &miss), ("all", &all)] {
        let started = Instant::now();
        let mut found = 0;
        for _ in 0..passes {
            found += set.iter().filter(|r| hits(r)).count();
        }
        let seconds = started.elapsed().as_secs_f64();
        let traced = (set.len() * passes).max(1) as f64;
        println!(
            "{name}: {} rays, {found} hits, {:.1} ns/ray, {:.2} Mrays/s",
            set.len(),
            seconds * 1e9 / traced,
            traced / seconds / 1e6
        );
    }
    Ok(())
}

fn print_hashes(world: &World) {
    for (i, mesh) in world.meshes.iter().enumerate() {
        let mut h = std::collections::hash_map::DefaultHasher::new();
        for node in &mesh.bvh.nodes {
            for v in node.bounds.iter().flatten() {
                v.to_bits().hash(&mut h);
            }
            node.index.hash(&mut h);
            node.count.hash(&mut h);
        }
        for v in (0..mesh.slots()).flat_map(|s| mesh.corners(s)) {
            for x in v.to_array() {
                x.to_bits().hash(&mut h);
            }
        }
        mesh.indices.hash(&mut h);
        println!(
            "mesh {i}: {} nodes, {} slots, depth {}, hash {:016x}",
            mesh.bvh.nodes.len(),
            mesh.slots(),
            mesh.bvh.depth(),
            h.finish()
        );
    }
}
