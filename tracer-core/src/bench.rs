//! Ray-throughput measurements behind `tracer bench`: BVH build time, closest-hit rays
//! (coherent primary and incoherent), any-hit shadow rays and a full 1-spp render.

use std::time::{Duration, Instant};

use rayon::prelude::*;
use serde::Serialize;

use crate::accel::{Spread, PACKET};
use crate::geometry::Ray;
use crate::render::{RenderError, Renderer};
use crate::sampler::{uniform_sphere, Rng};
use crate::scene::Scene;
use crate::settings::RenderSettings;
use crate::shade::{spawn_ray, Surface};
use crate::world::{Hit, Leaving, Mesh, World};

#[derive(Clone, Debug, Serialize)]
pub struct BenchReport {
    /// The fastest of the repeats' builds, like every figure here.
    pub build_ms: f64,
    /// The median of the repeats' builds, the figure `embree_rays.py` records for Embree's.
    pub build_ms_median: f64,
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
    /// One uniformly random direction from every primary hit, offset as the shader would,
    /// and what it leaves there (traced as the shader traces its rays:
    /// [`World::intersect_leaving`]).
    pub incoherent: Vec<(Ray, Leaving)>,
    /// From every primary hit to the first light, with the distance to it and what the ray
    /// leaves (empty without a light).
    pub shadow: Vec<(Ray, f64, Leaving)>,
    /// The pixel (index into `primary`) each shadow ray starts from, ascending.
    pub shadow_pixel: Vec<u32>,
    /// The parallel work items of [`Measure::Shadow`]: runs of 8×8-pixel blocks along one
    /// row of blocks, about [`CHUNK`] shadow rays each.
    shadow_items: Vec<ShadowItem>,
}

/// Blocks `first..end` (in units of `PACKET_SIDE` pixels across) of block row `row`.
#[derive(Clone, Copy, Debug)]
struct ShadowItem {
    row: u32,
    first: u32,
    end: u32,
}

/// One of the ray measures of [`run`], for [`trace`].
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Measure {
    /// Primary rays in packets of 8×8 pixels, as `tracer bench` traces them.
    Primary,
    /// The same rays one at a time ([`World::intersect`]), for comparison.
    PrimarySingle,
    Incoherent,
    /// Shadow rays in packets of the 8×8 pixel blocks they start from
    /// ([`World::occluded_packet`]), as `tracer bench` traces them.
    Shadow,
    /// The same rays one at a time ([`World::occluded`]), for comparison.
    ShadowSingle,
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
        let hits: Vec<(u32, Surface, f64, Hit)> = primary
            .par_iter()
            .enumerate()
            .filter_map(|(i, ray)| {
                let hit = scene.world.intersect(ray, near, far)?;
                let s = stage.surface(ray, &hit);
                Some((i as u32, s, s.position.abs().max_element() + hit.t, hit))
            })
            .collect();
        let incoherent = hits
            .iter()
            .map(|(i, s, scale, hit)| {
                let mut rng = Rng::for_sample(settings.seed, i % w, i / w, 0);
                let dir = uniform_sphere(rng.next_f64(), rng.next_f64());
                let leaving = scene.world.leaving(hit, dir.dot(s.geometric_normal) > 0.0);
                let ray = spawn_ray(s.position, s.geometric_normal, dir, *scale, 0.0);
                (ray, leaving)
            })
            .collect();
        let (shadow, shadow_pixel): (Vec<(Ray, f64, Leaving)>, Vec<u32>) = match scene
            .lights
            .first()
        {
            Some(light) => hits
                .iter()
                .filter_map(|(i, s, scale, hit)| {
                    let to_light = light.position - s.position;
                    let d = to_light.length();
                    (d > 0.0).then(|| {
                        let ray =
                            spawn_ray(s.position, s.geometric_normal, to_light / d, *scale, 0.0);
                        let len = (light.position - ray.origin).length();
                        let leaving = scene
                            .world
                            .leaving(hit, to_light.dot(s.geometric_normal) > 0.0);
                        ((ray, len, leaving), *i)
                    })
                })
                .unzip(),
            None => (Vec::new(), Vec::new()),
        };
        let shadow_items = shadow_items(&shadow_pixel, w as usize, h as usize);
        Ok(RaySets {
            primary,
            width: w as usize,
            near,
            far,
            incoherent,
            shadow,
            shadow_pixel,
            shadow_items,
        })
    }

    /// The first shadow ray from pixel `pixel` or a later one (shadow rays are in pixel
    /// order).
    fn shadow_from(&self, pixel: usize) -> usize {
        self.shadow_pixel.partition_point(|&q| (q as usize) < pixel)
    }

    /// The number of rays of `measure`.
    pub fn len(&self, measure: Measure) -> usize {
        match measure {
            Measure::Primary | Measure::PrimarySingle => self.primary.len(),
            Measure::Incoherent => self.incoherent.len(),
            Measure::Shadow | Measure::ShadowSingle => self.shadow.len(),
        }
    }
}

/// Splits the rows of 8×8-pixel blocks of a `width`×`height` image into runs of blocks
/// holding about [`CHUNK`] shadow rays each (blocks without any are left out), so that a
/// work item of packets costs about what one of [`CHUNK`] single rays does.
fn shadow_items(shadow_pixel: &[u32], width: usize, height: usize) -> Vec<ShadowItem> {
    let across = width.div_ceil(PACKET_SIDE);
    let mut per_block = vec![0u32; across * height.div_ceil(PACKET_SIDE)];
    for &p in shadow_pixel {
        let (x, y) = (p as usize % width, p as usize / width);
        per_block[y / PACKET_SIDE * across + x / PACKET_SIDE] += 1;
    }
    let mut items = Vec::new();
    for (row, blocks) in per_block.chunks(across).enumerate() {
        let (mut first, mut rays) = (None, 0);
        for (b, &count) in blocks.iter().enumerate() {
            if count > 0 {
                first.get_or_insert(b);
                rays += count as usize;
            }
            if let Some(f) = first.filter(|_| rays >= CHUNK || b + 1 == across) {
                items.push(ShadowItem {
                    row: row as u32,
                    first: f as u32,
                    end: b as u32 + 1,
                });
                (first, rays) = (None, 0);
            }
        }
    }
    items
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
        Measure::Shadow => rays.shadow_items.len(),
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
                world.intersect_packet(
                    &packet[..len],
                    rays.near,
                    rays.far,
                    None,
                    Spread::Wide,
                    &mut hits[..len],
                );
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
            .filter(|(r, leaving)| {
                world
                    .intersect_leaving(r, 0.0, f64::INFINITY, *leaving)
                    .is_some()
            })
            .count(),
        Measure::Shadow => {
            let mut blocked = 0;
            let mut found = [false; PACKET];
            shadow_packets(rays, item, |packet, limits, leaving| {
                let found = &mut found[..packet.len()];
                world.occluded_packet(packet, limits, leaving, found);
                blocked += found.iter().filter(|&&b| b).count();
            });
            blocked
        }
        Measure::ShadowSingle => rays.shadow[range]
            .iter()
            .filter(|(r, len, leaving)| world.occluded_leaving(r, *len, *leaving))
            .count(),
    }
}

/// Hands `packet(rays, t_max, leaving)` the shadow rays of each 8×8-pixel block of work item `item`
/// of [`Measure::Shadow`], block by block (an empty slice for a block without any).
fn shadow_packets(rays: &RaySets, item: usize, mut packet: impl FnMut(&[Ray], &[f64], &[Leaving])) {
    let width = rays.width;
    let height = rays.primary.len() / width;
    let item = rays.shadow_items[item];
    let y0 = item.row as usize * PACKET_SIDE;
    let ys = y0..(y0 + PACKET_SIDE).min(height);
    // Per pixel row of the block row, the next shadow ray of the item there (the rays are in
    // pixel order, so a block's part of a row is a run).
    let mut next = [0usize; PACKET_SIDE];
    for (n, y) in next.iter_mut().zip(ys.clone()) {
        *n = rays.shadow_from(y * width + item.first as usize * PACKET_SIDE);
    }
    let mut shadow = [Ray::new(glam::DVec3::ZERO, glam::DVec3::Z); PACKET];
    let mut limits = [0.0; PACKET];
    let mut leaving = [Leaving::NOTHING; PACKET];
    for block in item.first as usize..item.end as usize {
        let x_end = ((block + 1) * PACKET_SIDE).min(width);
        let mut len = 0;
        for (n, y) in next.iter_mut().zip(ys.clone()) {
            let end = (y * width + x_end) as u32;
            while *n < rays.shadow.len() && rays.shadow_pixel[*n] < end {
                (shadow[len], limits[len], leaving[len]) = rays.shadow[*n];
                len += 1;
                *n += 1;
            }
        }
        packet(&shadow[..len], &limits[..len], &leaving[..len]);
    }
}

/// Runs every measurement `repeats` times and keeps the fastest (least disturbed) run.
pub fn run(
    scene: &Scene,
    settings: &RenderSettings,
    repeats: usize,
) -> Result<BenchReport, RenderError> {
    let repeats = repeats.max(1);
    let builds: Vec<Duration> = (0..repeats)
        .map(|_| {
            let started = Instant::now();
            let world = std::hint::black_box(scene.world.rebuilt());
            let elapsed = started.elapsed();
            // Freeing the world is not building it (`embree_rays.py` releases its old scene
            // before its timer starts, too).
            drop(world);
            elapsed
        })
        .collect();
    let build = builds.iter().min().copied().unwrap_or_default();

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
        build_ms_median: median(&builds).as_secs_f64() * 1e3,
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
/// coordinates, f32 triangle blocks and BVH (nodes, leaf order and spans), as stored.
pub fn mesh_bytes(mesh: &Mesh) -> usize {
    mesh.corner_bytes()
        + size_of_val(&mesh.indices[..])
        + size_of_val(&mesh.normals[..])
        + size_of_val(&mesh.tex_coords[..])
        + size_of_val(&mesh.blocks[..])
        + size_of_val(&mesh.bvh.nodes[..])
        + size_of_val(&mesh.bvh.order[..])
        + size_of_val(&mesh.bvh.spans[..])
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

/// The middle time, or the mean of the two middle ones for an even count (as Python's
/// `statistics.median`, which `embree_rays.py` uses); zero for none.
fn median(times: &[Duration]) -> Duration {
    let mut sorted = times.to_vec();
    sorted.sort();
    match sorted.len() {
        0 => Duration::ZERO,
        n if n % 2 == 1 => sorted[n / 2],
        n => (sorted[n / 2 - 1] + sorted[n / 2]) / 2,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::DVec3;

    #[test]
    fn the_median_is_the_middle_time_or_the_mean_of_the_two_middle_ones() {
        let ms = Duration::from_millis;
        assert_eq!(median(&[]), Duration::ZERO);
        assert_eq!(median(&[ms(7)]), ms(7));
        assert_eq!(median(&[ms(9), ms(1), ms(5), ms(30), ms(2)]), ms(5));
        assert_eq!(median(&[ms(9), ms(1), ms(5), ms(30)]), ms(7));
    }

    #[test]
    fn shadow_packets_hold_each_shadow_ray_once_with_its_blocks_neighbours() {
        let mut next = crate::test_rng::uniform(8);
        for (w, h, density) in [(100, 37, 0.3), (64, 64, 1.0), (13, 5, 0.5), (40, 16, 0.0)] {
            // Shadow rays from some pixels, each marked by its pixel in the origin's x.
            let shadow_pixel: Vec<u32> = (0..w * h)
                .filter(|_| next() < density)
                .map(|p| p as u32)
                .collect();
            let shadow = shadow_pixel
                .iter()
                .map(|&p| {
                    let ray = Ray::new(DVec3::new(p as f64, 0.0, 0.0), DVec3::Z);
                    (ray, p as f64, Leaving::NOTHING)
                })
                .collect();
            let rays = RaySets {
                primary: vec![Ray::new(DVec3::ZERO, DVec3::Z); w * h],
                width: w,
                near: 0.0,
                far: 1.0,
                incoherent: Vec::new(),
                shadow,
                shadow_items: shadow_items(&shadow_pixel, w, h),
                shadow_pixel,
            };
            let mut seen = vec![0; w * h];
            for item in 0..work_items(&rays, Measure::Shadow) {
                shadow_packets(&rays, item, |packet, limits, _| {
                    assert!(packet.len() <= PACKET);
                    let block = |p: usize| (p % w / PACKET_SIDE, p / w / PACKET_SIDE);
                    for (ray, &t) in packet.iter().zip(limits) {
                        let p = ray.origin.x as usize;
                        assert_eq!(t, p as f64);
                        assert_eq!(block(p), block(packet[0].origin.x as usize));
                        seen[p] += 1;
                    }
                });
            }
            for &p in &rays.shadow_pixel {
                assert_eq!(seen[p as usize], 1, "{w}x{h}: pixel {p}");
            }
            assert_eq!(seen.iter().sum::<usize>(), rays.shadow.len());
            let per_item = rays.shadow.len() / work_items(&rays, Measure::Shadow).max(1);
            assert!(
                rays.shadow.len() < 2 * CHUNK || per_item >= CHUNK / 2,
                "{per_item}"
            );
        }
    }
}
