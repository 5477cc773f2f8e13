//! Ray-throughput measurements behind `tracer bench`: BVH build time, closest-hit rays
//! (coherent primary and incoherent), any-hit shadow rays and a full 1-spp render.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::Serialize;

use crate::accel::PACKET;
use crate::geometry::Ray;
use crate::render::{RenderError, Renderer};
use crate::sampler::{uniform_sphere, Rng};
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::shade::{spawn_ray, Surface};
use crate::world::{Mesh, World};

#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    pub build_ms: f64,
    pub primary_mrays: f64,
    pub incoherent_mrays: f64,
    pub shadow_mrays: f64,
    pub render_s: f64,
    /// Memory of the meshes' geometry and BVHs per mesh triangle ([`mesh_bytes`]); each
    /// mesh counted once however many models instance it. 0 without meshes.
    pub bytes_per_triangle: f64,
    #[serde(skip)]
    pub primary_rays: usize,
    #[serde(skip)]
    pub secondary_rays: usize,
}

/// Rays per parallel work item: large enough to amortise scheduling (a few µs against
/// ~0.1 ms of tracing), small enough that the last item leaves the other thread idle briefly.
/// Every chunk is its own item ([`time_rays`]): rayon's adaptive splitting would otherwise
/// stop at a quarter of the rays per thread, and the thread left with one such piece at the
/// end ran alone for up to a fifth of the measure.
const CHUNK: usize = 256;

/// Primary rays are traced as packets of `PACKET_SIDE`² pixels ([`World::intersect_packet`]),
/// [`TILE_PACKETS`] side by side per parallel work item (as many rays as [`CHUNK`]).
const PACKET_SIDE: usize = 8;
const TILE_PACKETS: usize = 4;
const _: () = assert!(PACKET_SIDE * PACKET_SIDE <= PACKET);

/// The rays of the bench's measures on a scene, as `tracer bench` traces them.
pub struct RaySets {
    /// One per pixel centre, row by row from the top, traced for hits with t in (`near`,
    /// `far`).
    pub primary: Vec<Ray>,
    /// Pixels per row of `primary`.
    pub width: usize,
    pub near: f64,
    pub far: f64,
    /// One uniformly random direction from every primary hit, offset as the shader would.
    pub incoherent: Vec<Ray>,
    /// From every primary hit to the first light, with the distance to it (empty without
    /// a light).
    pub shadow: Vec<(Ray, f64)>,
}

/// One of the ray measures of [`run`], for [`trace`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    /// Primary rays in packets of 8×8 pixels, as `tracer bench` traces them.
    Primary,
    /// The same rays one at a time ([`World::intersect`]), for comparison.
    PrimarySingle,
    Incoherent,
    Shadow,
}

impl RaySets {
    pub fn new(scene: &Scene, settings: &RenderSettings) -> Result<RaySets, RenderError> {
        let renderer = Renderer::new(scene, settings)?;
        let camera = renderer.camera();
        let (w, h) = (settings.width, settings.height);
        let primary: Vec<Ray> = (0..h)
            .flat_map(|y| (0..w).map(move |x| (x, y)))
            .map(|(x, y)| camera.ray(x as f64 + 0.5, y as f64 + 0.5, w as f64, h as f64))
            .collect();
        let (near, far) = (camera.near, camera.far);

        let stage = scene.stage(settings.texture_filter, None);
        let hits: Vec<(u32, Surface, f64)> = primary
            .par_iter()
            .enumerate()
            .filter_map(|(i, ray)| {
                let hit = scene.world.intersect(ray, near, far)?;
                let s = stage.surface(ray, &hit);
                Some((i as u32, s, s.position.abs().max_element() + hit.t))
            })
            .collect();
        let incoherent = hits
            .iter()
            .map(|(i, s, scale)| {
                let mut rng = Rng::for_sample(settings.seed, i % w, i / w, 0);
                let dir = uniform_sphere(rng.next_f64(), rng.next_f64());
                spawn_ray(s.position, s.geometric_normal, dir, *scale, 0.0)
            })
            .collect();
        let shadow = match scene.lights.first() {
            Some(light) => hits
                .iter()
                .filter_map(|(_, s, scale)| {
                    let to_light = light.position - s.position;
                    let d = to_light.length();
                    (d > 0.0).then(|| {
                        let ray =
                            spawn_ray(s.position, s.geometric_normal, to_light / d, *scale, 0.0);
                        let len = (light.position - ray.origin).length();
                        (ray, len)
                    })
                })
                .collect(),
            None => Vec::new(),
        };
        Ok(RaySets {
            primary,
            width: w as usize,
            near,
            far,
            incoherent,
            shadow,
        })
    }

    /// The number of rays of `measure`.
    pub fn len(&self, measure: Measure) -> usize {
        match measure {
            Measure::Primary | Measure::PrimarySingle => self.primary.len(),
            Measure::Incoherent => self.incoherent.len(),
            Measure::Shadow => self.shadow.len(),
        }
    }
}

/// Traces the rays of `measure` on the calling thread; returns how many hit (or, for shadow
/// rays, are blocked). For profiling one measure alone (`examples/bench_measure.rs`).
pub fn trace(scene: &Scene, rays: &RaySets, measure: Measure) -> usize {
    (0..work_items(rays, measure))
        .map(|item| trace_item(scene, rays, measure, item))
        .sum()
}

/// The parallel work items of `measure`: [`CHUNK`] rays each, or for packets of primary
/// rays a tile of [`TILE_PACKETS`] packets side by side.
fn work_items(rays: &RaySets, measure: Measure) -> usize {
    match measure {
        Measure::Primary => {
            let height = rays.primary.len().checked_div(rays.width).unwrap_or(0);
            rays.width.div_ceil(PACKET_SIDE * TILE_PACKETS) * height.div_ceil(PACKET_SIDE)
        }
        _ => rays.len(measure).div_ceil(CHUNK),
    }
}

/// [`trace`] over work item `item` of [`work_items`].
fn trace_item(scene: &Scene, rays: &RaySets, measure: Measure, item: usize) -> usize {
    let world = &scene.world;
    let n = rays.len(measure);
    let range = item * CHUNK..((item + 1) * CHUNK).min(n);
    match measure {
        Measure::Primary => {
            let width = rays.width;
            let height = n / width;
            let tiles_across = width.div_ceil(PACKET_SIDE * TILE_PACKETS);
            let (x0, y0) = (
                item % tiles_across * PACKET_SIDE * TILE_PACKETS,
                item / tiles_across * PACKET_SIDE,
            );
            let mut hit = 0;
            let mut packet = [rays.primary[0]; PACKET];
            let mut hits = [None; PACKET];
            for px in (x0..(x0 + PACKET_SIDE * TILE_PACKETS).min(width)).step_by(PACKET_SIDE) {
                let mut len = 0;
                for y in y0..(y0 + PACKET_SIDE).min(height) {
                    for x in px..(px + PACKET_SIDE).min(width) {
                        packet[len] = rays.primary[y * width + x];
                        len += 1;
                    }
                }
                world.intersect_packet(&packet[..len], rays.near, rays.far, None, &mut hits[..len]);
                hit += hits[..len].iter().filter(|h| h.is_some()).count();
            }
            hit
        }
        Measure::PrimarySingle => rays.primary[range]
            .iter()
            .filter(|r| world.intersect(r, rays.near, rays.far).is_some())
            .count(),
        Measure::Incoherent => rays.incoherent[range]
            .iter()
            .filter(|r| world.intersect(r, 0.0, f64::INFINITY).is_some())
            .count(),
        Measure::Shadow => rays.shadow[range]
            .iter()
            .filter(|(r, len)| world.occluded(r, *len))
            .count(),
    }
}

/// Runs every measurement `repeats` times and keeps the fastest (least disturbed) run.
pub fn run(
    scene: &Scene,
    settings: &RenderSettings,
    repeats: usize,
) -> Result<BenchReport, RenderError> {
    let repeats = repeats.max(1);
    let build = best_of(repeats, || {
        let started = Instant::now();
        let world = std::hint::black_box(scene.world.rebuilt());
        let elapsed = started.elapsed();
        // Freeing the world is not building it (`embree_rays.py` releases its old scene
        // before its timer starts, too).
        drop(world);
        elapsed
    });

    let rays = RaySets::new(scene, settings)?;
    let time = |measure| best_of(repeats, || time_rays(scene, &rays, measure));
    let primary_time = time(Measure::Primary);
    let incoherent_time = time(Measure::Incoherent);
    let shadow_time = (!rays.shadow.is_empty()).then(|| time(Measure::Shadow));

    let one_spp = RenderSettings {
        spp: 1,
        ..settings.clone()
    };
    let render = best_of(repeats, || {
        let r = Renderer::new(scene, &one_spp).expect("validated above");
        let started = Instant::now();
        std::hint::black_box(r.render_image(&|_, _| {}));
        started.elapsed()
    });

    let mrays = |n: usize, t: Duration| n as f64 / t.as_secs_f64() / 1e6;
    Ok(BenchReport {
        build_ms: build.as_secs_f64() * 1e3,
        primary_mrays: mrays(rays.primary.len(), primary_time),
        incoherent_mrays: mrays(rays.incoherent.len(), incoherent_time),
        shadow_mrays: shadow_time.map_or(0.0, |t| mrays(rays.shadow.len(), t)),
        render_s: render.as_secs_f64(),
        bytes_per_triangle: bytes_per_triangle(&scene.world),
        primary_rays: rays.primary.len(),
        secondary_rays: rays.incoherent.len(),
    })
}

/// Bytes the meshes of `world` hold, per mesh triangle (0 without meshes).
fn bytes_per_triangle(world: &World) -> f64 {
    // Padding slots (indices u32::MAX) fill leaf blocks; they are memory, not triangles.
    let triangles = world
        .meshes
        .iter()
        .flat_map(|m| &m.indices)
        .filter(|t| t[0] != u32::MAX)
        .count();
    if triangles == 0 {
        return 0.0;
    }
    world.meshes.iter().map(mesh_bytes).sum::<usize>() as f64 / triangles as f64
}

/// The heap bytes of one mesh: its triangles' corners, vertex indices, normals, texture
/// coordinates, f32 triangle blocks and BVH (nodes and leaf order), as stored.
pub fn mesh_bytes(mesh: &Mesh) -> usize {
    size_of_val(&mesh.corners[..])
        + size_of_val(&mesh.indices[..])
        + size_of_val(&mesh.normals[..])
        + size_of_val(&mesh.tex_coords[..])
        + size_of_val(&mesh.blocks[..])
        + size_of_val(&mesh.bvh.nodes[..])
        + size_of_val(&mesh.bvh.order[..])
}

/// Traces `measure`'s rays in parallel, one rayon job per work item ([`work_items`]).
fn time_rays(scene: &Scene, rays: &RaySets, measure: Measure) -> Duration {
    let started = Instant::now();
    let hits: usize = (0..work_items(rays, measure))
        .into_par_iter()
        .with_max_len(1)
        .map(|item| trace_item(scene, rays, measure, item))
        .sum();
    std::hint::black_box(hits);
    started.elapsed()
}

fn best_of(repeats: usize, mut run: impl FnMut() -> Duration) -> Duration {
    (0..repeats).map(|_| run()).min().unwrap_or_default()
}
