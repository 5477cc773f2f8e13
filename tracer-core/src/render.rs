//! Pixels: each sample's eye ray from [`EyeRays`], traced by the shading model, averaged into
//! linear f32 tiles. A pixel's value depends only on (scene, settings, pixel), so any tiling
//! gives the same bytes.

use std::ops::Range;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

use crate::accel::{Spread, PACKET};
use crate::adaptive::{in_second_half, luminance, SUMS};
use crate::camera::{Camera, EyeRays, EyeSample};
use crate::film::Image;
use crate::geometry::Ray;
use crate::photon::{caustic_map, CausticMap};
use crate::sampler::SampleOrder;
use crate::scene::Scene;
use crate::settings::{RenderSettings, SettingsError, TileRect};
use crate::shade::{Eye, RayCounts, Tracer};
use crate::world::{BlockSlots, Hit, World, LANES};

/// Largest recursion depth accepted; the ray budget bounds the work in any case.
pub const MAX_DEPTH_LIMIT: u32 = 64;

/// Settings a render of a given scene cannot honour.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RenderError {
    #[error(transparent)]
    Settings(#[from] SettingsError),
    #[error("depth {0} must lie between 1 and {MAX_DEPTH_LIMIT}")]
    Depth(u32),
    #[error("frame {frame} is out of range: the scene has {frames} frame(s), numbered from 0")]
    Frame { frame: u32, frames: u32 },
}

/// Renders pixels of one scene with one set of settings. Shared across threads.
pub struct Renderer<'a> {
    scene: &'a Scene,
    settings: RenderSettings,
    eye: EyeRays<'a>,
    radiance_rays: AtomicU64,
    shadow_rays: AtomicU64,
    caustics: Option<Arc<CausticMap>>,
    order: SampleOrder,
    /// Whether a progressive pixel's samples are traced in stratum order (always, but for
    /// the test that checks it changes no bit).
    trace_by_stratum: bool,
    /// Whether a pixel whose eye-ray frustum meets no object takes the miss colour for every
    /// sample without making its rays (always, but for the test that checks it changes no
    /// bit).
    skip_empty_pixels: bool,
    /// Whether an eye ray's mirror ray off an axis-aligned plane is intersected among its
    /// pixel's mirror slots ([`crate::world::World::mirror_slots`]) instead of walking
    /// (always, but for the test that checks it changes no bit).
    mirror_slots: bool,
}

/// One pixel's running sums: what a one-shot render accumulates, plus (when `ESTIMATE`) the
/// half-buffer luminance sums of [`crate::adaptive`].
#[derive(Clone, Copy, Default)]
struct PixelSums {
    rgb: DVec3,
    lum: f64,
    lum_odd: f64,
    /// Rays traced (radiance and shadow): what the pixel's samples cost.
    rays: f64,
}

impl<'a> Renderer<'a> {
    pub fn new(scene: &'a Scene, settings: &RenderSettings) -> Result<Self, RenderError> {
        settings.validate()?;
        if settings.max_depth == 0 || settings.max_depth > MAX_DEPTH_LIMIT {
            return Err(RenderError::Depth(settings.max_depth));
        }
        if settings.frame >= scene.frame_count() {
            return Err(RenderError::Frame {
                frame: settings.frame,
                frames: scene.frame_count(),
            });
        }
        Ok(Self {
            scene,
            settings: settings.clone(),
            eye: EyeRays::new(scene, settings),
            radiance_rays: AtomicU64::new(0),
            shadow_rays: AtomicU64::new(0),
            caustics: caustic_map(scene, settings),
            order: SampleOrder::Grid,
            trace_by_stratum: true,
            skip_empty_pixels: true,
            mirror_slots: true,
        })
    }

    /// The same renderer visiting each pixel's strata in `order` (progressive renders use
    /// [`SampleOrder::Progressive`] over the strata of their largest sample count).
    pub fn with_sample_order(self, order: SampleOrder) -> Self {
        Self { order, ..self }
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    pub fn camera(&self) -> &Camera {
        self.eye.camera()
    }

    /// The caustic photon map this render gathers from, if caustics are on.
    pub fn caustics(&self) -> Option<&CausticMap> {
        self.caustics.as_deref()
    }

    /// Rays traced so far by this renderer (radiance and shadow rays).
    pub fn rays_traced(&self) -> u64 {
        self.radiance_rays.load(Ordering::Relaxed) + self.shadow_rays.load(Ordering::Relaxed)
    }

    /// Renders `rect` (rows in parallel on the current rayon pool). Returns None if `cancel`
    /// was set before it finished.
    pub fn render_tile(&self, rect: TileRect, cancel: &AtomicBool) -> Option<Image> {
        self.render_tile_in(rect, cancel, Vec::new())
    }

    /// [`Renderer::render_tile`] into `buffer`'s memory, whatever it holds. A worker passes
    /// the buffer of a tile it has sent: fresh memory is mapped page by page as the rows
    /// are written, 192 page faults for a 256×256 tile, on the render threads.
    pub fn render_tile_in(
        &self,
        rect: TileRect,
        cancel: &AtomicBool,
        mut buffer: Vec<f32>,
    ) -> Option<Image> {
        assert!(
            rect.x + rect.width <= self.settings.width
                && rect.y + rect.height <= self.settings.height,
            "tile {rect:?} lies outside the {}x{} image",
            self.settings.width,
            self.settings.height
        );
        // Every value is written below (a cancelled tile is dropped), so what the buffer
        // holds can stay: only values past its length are set first.
        let len = 3 * rect.pixel_count();
        buffer.truncate(len);
        buffer.resize(len, 0.0);
        let mut tile = Image {
            width: rect.width,
            height: rect.height,
            pixels: buffer,
        };
        if rect.width == 0 {
            return Some(tile);
        }
        // One row per rayon job: a thread that runs out of work can steal any row that has
        // not started, so a tile's end does not leave threads idle while one finishes a run of
        // several rows (the embedded farm keeps several tiles on one pool and relies on it).
        // A row is far more work than a job's overhead; the bytes are the same either way.
        tile.pixels
            .par_chunks_mut(3 * rect.width as usize)
            .with_max_len(1)
            .enumerate()
            .for_each(|(row, out)| {
                if !cancel.load(Ordering::Relaxed) {
                    self.render_row(rect.x, rect.y + row as u32, out);
                }
            });
        (!cancel.load(Ordering::Relaxed)).then_some(tile)
    }

    /// Renders the whole image, calling `progress(pixels_done, pixels_total)` after each row.
    pub fn render_image(&self, progress: &(dyn Fn(u64, u64) + Sync)) -> Image {
        let (w, h) = (self.settings.width, self.settings.height);
        let mut image = Image::new(w, h);
        let total = w as u64 * h as u64;
        let done = AtomicU64::new(0);
        // One row per rayon job, as in `render_tile`: rows cost unevenly (glass, meshes), and
        // runs of several rows left a thread idle at the end while another finished its run.
        image
            .pixels
            .par_chunks_mut(3 * w as usize)
            .with_max_len(1)
            .enumerate()
            .for_each(|(row, out)| {
                self.render_row(0, row as u32, out);
                let now = done.fetch_add(w as u64, Ordering::Relaxed) + w as u64;
                progress(now, total);
            });
        image
    }

    /// Continues the running sums of each of `rect`'s pixels with the samples `samples(x, y)`
    /// (indices into the settings' `spp`, in the renderer's sample order; x, y in image pixels
    /// from the top): a pixel's range starts where its sums stopped, and a pixel with an empty
    /// range keeps its sums (each 8×8 block of a pass has its own range). `sums` holds
    /// [`SUMS`] f64 per pixel of the tile, row-major from its top row ([`crate::adaptive`]):
    /// zeros before the first pass. A pixel's sum after samples 0..n is bit-identical to what
    /// a one-shot render of n samples divides. Returns false if `cancel` was set first.
    pub fn render_tile_samples(
        &self,
        rect: TileRect,
        samples: &(dyn Fn(u32, u32) -> Range<u32> + Sync),
        sums: &mut [f64],
        cancel: &AtomicBool,
    ) -> bool {
        assert!(
            rect.x + rect.width <= self.settings.width
                && rect.y + rect.height <= self.settings.height,
            "tile {rect:?} lies outside the {}x{} image",
            self.settings.width,
            self.settings.height
        );
        assert_eq!(sums.len(), rect.pixel_count() * SUMS, "tile sums size");
        if rect.width == 0 {
            return true;
        }
        // One row per rayon job, as in `render_tile`, so that a pass's last tile is shared row
        // by row at the pass's end (no wall-time change was measurable at load 7-8).
        sums.par_chunks_mut(SUMS * rect.width as usize)
            .with_max_len(1)
            .enumerate()
            .for_each(|(row, out)| {
                if cancel.load(Ordering::Relaxed) {
                    return;
                }
                let row = rect.y + row as u32;
                self.pixels(rect.x, row, out.len() / SUMS, |i, x, shade| {
                    let px = &mut out[i * SUMS..(i + 1) * SUMS];
                    let range = samples(x, row);
                    if range.is_empty() {
                        return;
                    }
                    assert!(
                        range.end <= self.settings.spp,
                        "samples {range:?} go beyond spp {}",
                        self.settings.spp
                    );
                    let mut acc = PixelSums {
                        rgb: DVec3::new(px[0], px[1], px[2]),
                        lum: px[3],
                        lum_odd: px[4],
                        rays: px[5],
                    };
                    shade.accumulate::<true>(x, range, &mut acc);
                    px.copy_from_slice(&[
                        acc.rgb.x,
                        acc.rgb.y,
                        acc.rgb.z,
                        acc.lum,
                        acc.lum_odd,
                        acc.rays,
                    ]);
                });
            });
        !cancel.load(Ordering::Relaxed)
    }

    /// Renders the pixels of image row `row` (counted from the top) starting at column `x0`
    /// into `out` (3 floats per pixel).
    fn render_row(&self, x0: u32, row: u32, out: &mut [f32]) {
        let spp = self.settings.spp;
        self.pixels(x0, row, out.len() / 3, |i, x, shade| {
            let mut acc = PixelSums::default();
            shade.accumulate::<false>(x, 0..spp, &mut acc);
            // The average before any clamping (conventions §3.2).
            let mean = acc.rgb / spp as f64;
            out[i * 3..i * 3 + 3].copy_from_slice(&[mean.x as f32, mean.y as f32, mean.z as f32]);
        });
    }

    /// Calls `pixel(i, x, shader)` for the `count` pixels of image row `row` (from the top)
    /// starting at column `x0`, with a shader for that row; counts its rays.
    fn pixels(
        &self,
        x0: u32,
        row: u32,
        count: usize,
        mut pixel: impl FnMut(usize, u32, &mut RowShader),
    ) {
        let stage = self
            .scene
            .stage(self.settings.texture_filter, self.caustics.as_deref());
        let mut tracer = Tracer::new(stage, self.settings.max_depth);
        let miss = tracer.uniform_miss().filter(|_| self.skip_empty_pixels);
        let mut shade = RowShader {
            renderer: self,
            world: stage.world,
            tracer,
            miss,
            // The course's pixel grid has y = 0 at the bottom.
            y: self.settings.height - 1 - row,
            order: Vec::new(),
            slots: Vec::new(),
            block: None,
            block_slots: BlockSlots::default(),
            eyes: Vec::new(),
            picks: Vec::new(),
            rays: Vec::new(),
            hits: Vec::new(),
            visit: Vec::new(),
            marks: Vec::new(),
            position_of: Vec::new(),
            traced: Vec::new(),
            radiance_rays: 0,
            shadow_rays: 0,
        };
        for i in 0..count {
            pixel(i, x0 + i as u32, &mut shade);
        }
        self.radiance_rays
            .fetch_add(shade.radiance_rays, Ordering::Relaxed);
        self.shadow_rays
            .fetch_add(shade.shadow_rays, Ordering::Relaxed);
    }
}

/// What tracing the samples of one image row needs, reused across its pixels.
struct RowShader<'r> {
    renderer: &'r Renderer<'r>,
    tracer: Tracer<'r>,
    /// What a sample whose eye ray meets nothing adds ([`Tracer::uniform_miss`]); None where
    /// that depends on the ray.
    miss: Option<(DVec3, RayCounts)>,
    /// The row, counted from the bottom.
    y: u32,
    world: &'r World,
    /// The current pixel's stratum order (empty: the grid order).
    order: Vec<u32>,
    /// The top-level slots the current pixel's eye-ray frustum meets (see
    /// [`World::frustum_slots`]); kept for the row, so no allocation per pixel.
    slots: Vec<u32>,
    /// The first column of the block of [`FRUSTUM_BLOCK`] pixels whose candidate slots
    /// `block_slots` holds ([`World::block_candidates`]).
    block: Option<u32>,
    block_slots: BlockSlots,
    /// The eye samples of the current packet, and their (sample, stratum) pairs.
    eyes: Vec<EyeSample>,
    picks: Vec<(u32, u32)>,
    /// Their rays and hits (kept for the row, so no allocation per pixel).
    rays: Vec<Ray>,
    hits: Vec<Option<Hit>>,
    /// A progressive pixel's samples in the order they are traced (positions in its range),
    /// sorted by stratum through a bitmap of the strata (`marks`, left all clear) and each
    /// stratum's position.
    visit: Vec<u32>,
    marks: Vec<u64>,
    position_of: Vec<u32>,
    /// Their colours and rays by position, until they are summed in sample order.
    traced: Vec<(DVec3, RayCounts)>,
    radiance_rays: u64,
    shadow_rays: u64,
}

impl RowShader<'_> {
    /// Adds samples `samples` of pixel `x` of this row to `acc`, in sample order.
    #[inline]
    fn accumulate<const ESTIMATE: bool>(
        &mut self,
        x: u32,
        samples: Range<u32>,
        acc: &mut PixelSums,
    ) {
        let eye = &self.renderer.eye;
        // A pixel's eye rays share an origin and stay within its frustum, whatever their
        // strata: the top-level slots the frustum meets are found once per pixel, and each eye
        // ray tests just those instead of traversing.
        let pixel_frustum = eye.pixel_frustum(x, self.y);
        self.tracer
            .start_pixel(pixel_frustum.filter(|_| self.renderer.mirror_slots));
        let frustum = match pixel_frustum {
            Some((origin, planes)) => {
                // The candidates of the block of pixels holding this one, found once for it.
                let start = x - x % FRUSTUM_BLOCK;
                if self.block != Some(start) {
                    let end = (start + FRUSTUM_BLOCK).min(self.renderer.settings.width);
                    self.block = eye
                        .span_frustum(start..end, self.y)
                        .map(|(_, block_planes)| {
                            self.world.block_candidates(
                                origin,
                                &block_planes,
                                &mut self.block_slots,
                            );
                            start
                        });
                }
                if self.block.is_some() {
                    self.world.frustum_slots_among(
                        origin,
                        &planes,
                        &mut self.block_slots,
                        &mut self.slots,
                    );
                } else {
                    // No frustum for the block (none arises where the pixel has one, but the
                    // candidates must never be another block's): the pixel's own walk.
                    self.world.frustum_slots(origin, &planes, &mut self.slots);
                }
                Some(&self.slots[..])
            }
            None => None,
        };
        // Where the frustum meets nothing, every eye ray misses and each sample adds the same
        // miss colour: added in sample order as tracing would, without making the rays (most
        // of test.scene's and dragon.scene's pixels).
        if let (Some([]), Some((color, counts))) = (frustum, self.miss) {
            for sample in samples {
                self.radiance_rays += counts.radiance as u64;
                self.shadow_rays += counts.shadow as u64;
                add_sample::<ESTIMATE>(acc, sample, color, counts);
            }
            return;
        }
        eye.strata_order(
            self.renderer.order,
            x,
            self.y,
            samples.clone(),
            &mut self.order,
        );
        let first = samples.start;
        let stratum = |order: &[u32], sample: u32| {
            if order.is_empty() {
                sample
            } else {
                order[(sample - first) as usize]
            }
        };
        // Only a mesh model shares work among a packet's rays; other objects take them one by
        // one, so a pixel whose frustum meets no model gains nothing from a packet and pays
        // its set-up (test and cornell_box rendered 10-15% slower with packets everywhere).
        let packet_slots = frustum
            .filter(|slots| samples.len() >= MIN_PACKET && self.world.any_model_among(slots));
        // A pixel that sees scene triangles and no mesh model: its eye rays' hits found four
        // at a time ([`World::intersect_among_lanes`]), a group ahead of the samples being
        // shaded, so that finding them overlaps the shading as finding each one in turn did.
        let lane_slots =
            frustum.filter(|slots| packet_slots.is_none() && self.world.lanes_among(slots));
        // Traces one eye sample, its first hit found as `first` says (captures only the
        // tracer and the ray counters, so the row's buffers stay free).
        let mut trace = |ray: &mut EyeSample, first: Eye| {
            let (color, counts) = self.tracer.sample(
                &ray.ray,
                ray.near,
                ray.far,
                &mut ray.rng,
                ray.gloss.take(),
                first,
            );
            self.radiance_rays += counts.radiance as u64;
            self.shadow_rays += counts.shadow as u64;
            (color, counts)
        };
        // A progressive order scatters consecutive samples over the pixel; traced that way,
        // neighbouring rays no longer follow each other through the caches (texture lookups
        // on stacks.scene took 27 % longer than in the grid order). So its samples are traced
        // in stratum order, each one's colour kept, and summed in sample order afterwards: a
        // sample's rays depend on its index alone, so the sums are the same bits.
        let reordered = self.renderer.trace_by_stratum && !self.order.is_empty();
        if reordered {
            // A pixel's strata are distinct numbers below spp (its grid is cols × rows = spp):
            // a bitmap sorts them in O(spp / 64 + samples), where a comparison sort cost as
            // much as it saved.
            let order = &self.order;
            let strata = self.renderer.settings.spp as usize;
            self.marks.resize(strata.div_ceil(64), 0);
            self.position_of.resize(strata, 0);
            for (i, &stratum) in order.iter().enumerate() {
                self.position_of[stratum as usize] = i as u32;
                self.marks[stratum as usize / 64] |= 1 << (stratum % 64);
            }
            self.visit.clear();
            for (w, word) in self.marks.iter_mut().enumerate() {
                let mut bits = std::mem::take(word);
                while bits != 0 {
                    let stratum = w * 64 + bits.trailing_zeros() as usize;
                    self.visit.push(self.position_of[stratum]);
                    bits &= bits - 1;
                }
            }
            self.traced.clear();
            self.traced
                .resize(order.len(), (DVec3::ZERO, RayCounts::default()));
        }
        // The sample at position `j` of the tracing order.
        let visit = &self.visit;
        let sample_at = |j: u32| {
            if reordered {
                first + visit[j as usize]
            } else {
                first + j
            }
        };
        // The eye rays are made a batch at a time before any is shaded: each one's square root
        // and divisions then overlap the next one's, where between two shaded samples they
        // would wait on each other's latency. Where the pixel's rays are coherent enough for
        // a packet, the batch's hits are found together too (the same hits as one at a time).
        let one_by_one = frustum.map_or(Eye::Walk, Eye::Among);
        let count = samples.len() as u32;
        let mut start = 0;
        while start < count {
            let end = count.min(start + PACKET as u32);
            self.eyes.clear();
            self.picks.clear();
            self.picks.extend((start..end).map(|j| {
                let s = sample_at(j);
                (s, stratum(&self.order, s))
            }));
            eye.samples_in(x, self.y, &self.picks, &mut self.eyes);
            // Whether the batch's rays share their range of hits, as the packet and lane
            // tests take them.
            let (near, far) = (self.eyes[0].near, self.eyes[0].far);
            let shared_range = self.eyes.iter().all(|e| e.near == near && e.far == far);
            let lanes = lane_slots.filter(|_| shared_range);
            if let Some(slots) = packet_slots {
                self.rays.clear();
                self.rays.extend(self.eyes.iter().map(|e| e.ray));
                self.hits.resize(self.eyes.len(), None);
                let hits = &mut self.hits[..];
                if shared_range {
                    self.world.intersect_packet(
                        &self.rays,
                        near,
                        far,
                        Some(slots),
                        Spread::Pixel,
                        hits,
                    );
                } else {
                    for (h, e) in hits.iter_mut().zip(&self.eyes) {
                        *h = self.world.intersect_among(&e.ray, e.near, e.far, slots);
                    }
                }
            }
            if let Some(slots) = lanes {
                self.hits.resize(self.eyes.len(), None);
                lane_hits(self.world, &self.eyes, &mut self.hits, slots, 0);
            }
            for k in 0..self.eyes.len() {
                let first_hit = match (packet_slots, lanes) {
                    (Some(_), _) => Eye::Found(self.hits[k]),
                    (None, Some(slots)) => {
                        if k % LANES == 0 {
                            let next = k + LANES;
                            lane_hits(self.world, &self.eyes, &mut self.hits, slots, next);
                        }
                        Eye::Found(self.hits[k])
                    }
                    (None, None) => one_by_one,
                };
                let ray = &mut self.eyes[k];
                let sample = sample_at(start + k as u32);
                let (color, counts) = trace(ray, first_hit);
                if reordered {
                    self.traced[(sample - first) as usize] = (color, counts);
                } else {
                    add_sample::<ESTIMATE>(acc, sample, color, counts);
                }
            }
            start = end;
        }
        if reordered {
            for (i, &(color, counts)) in self.traced.iter().enumerate() {
                add_sample::<ESTIMATE>(acc, first + i as u32, color, counts);
            }
        }
    }
}

/// The hits of eye rays `eyes[start..start + LANES]` (those there are; all with the same
/// near and far planes) among `slots`, into `hits` ([`World::intersect_among_lanes`]).
fn lane_hits(
    world: &World,
    eyes: &[EyeSample],
    hits: &mut [Option<Hit>],
    slots: &[u32],
    start: usize,
) {
    let end = eyes.len().min(start + LANES);
    if start >= end {
        return;
    }
    let rays: [&Ray; LANES] = std::array::from_fn(|k| &eyes[(start + k).min(end - 1)].ray);
    let (near, far) = (eyes[start].near, eyes[start].far);
    world.intersect_among_lanes(
        &rays[..end - start],
        near,
        far,
        slots,
        &mut hits[start..end],
    );
}

/// Pixels of a row whose frustum slots are found among one block's candidates
/// ([`World::frustum_slots_among`]): a block's walk and triangle tests then serve them all.
const FRUSTUM_BLOCK: u32 = 16;

/// Fewer eye rays than this per pixel are traced one at a time: a packet's set-up costs
/// more than it shares among so few.
const MIN_PACKET: usize = 4;

/// Adds one sample's colour (and, when `ESTIMATE`, its luminance and ray count) to `acc`.
#[inline(always)]
fn add_sample<const ESTIMATE: bool>(
    acc: &mut PixelSums,
    sample: u32,
    color: DVec3,
    counts: RayCounts,
) {
    let color = sanitize(color);
    acc.rgb += color;
    if ESTIMATE {
        let lum = luminance(color.x, color.y, color.z);
        acc.lum += lum;
        if in_second_half(sample) {
            acc.lum_odd += lum;
        }
        acc.rays += (counts.radiance + counts.shadow) as f64;
    }
}

/// Keeps one pathological sample from poisoning a pixel: NaN becomes 0, and values are capped
/// far above anything that survives the final clamp to [0, 1].
fn sanitize(c: DVec3) -> DVec3 {
    let f = |v: f64| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1e6) };
    DVec3::new(f(c.x), f(c.y), f(c.z))
}

#[cfg(test)]
mod tests {
    use std::path::PathBuf;

    use super::*;

    #[test]
    fn mirror_rays_among_their_pixels_slots_render_the_same_bits_as_walked() {
        // A reflective floor, left wall and back wall meeting in a corner (pixels along the
        // seams see two mirror planes, so the per-pixel slots must follow the plane), with
        // spheres and a tilted triangle in front and in the reflections.
        let vertex = |name: &str, material: &str, p: [f64; 3], n: [f64; 3]| {
            format!(
                r#"<vertex name="{name}" material="{material}"><position x="{}" y="{}" z="{}"/>
                <normal x="{}" y="{}" z="{}"/><tex_coord u="0" v="0"/></vertex>"#,
                p[0], p[1], p[2], n[0], n[1], n[2]
            )
        };
        let quad = |name: &str, corners: [[f64; 3]; 4], n: [f64; 3]| {
            let mut xml = String::new();
            for (k, c) in corners.iter().enumerate() {
                xml += &vertex(&format!("{name}{k}"), "mirror", *c, n);
            }
            for tri in [[0, 1, 2], [0, 2, 3]] {
                xml += r#"<triangle material="mirror"><position x="0" y="0" z="0"/>"#;
                for k in tri {
                    xml += &format!(r#"<vertex name="{name}{k}"/>"#);
                }
                xml += "</triangle>";
            }
            xml
        };
        let floor = [
            [-2.0, -1.0, 1.0],
            [2.0, -1.0, 1.0],
            [2.0, -1.0, -3.0],
            [-2.0, -1.0, -3.0],
        ];
        let left = [
            [-2.0, -1.0, 1.0],
            [-2.0, -1.0, -3.0],
            [-2.0, 2.0, -3.0],
            [-2.0, 2.0, 1.0],
        ];
        let back = [
            [-2.0, -1.0, -3.0],
            [2.0, -1.0, -3.0],
            [2.0, 2.0, -3.0],
            [-2.0, 2.0, -3.0],
        ];
        let xml = format!(
            r#"<scene>
    <camera><fov v="1.0"/><near_clip v=".01"/><far_clip v="100"/>
        <position x="1.2" y="0.6" z="3"/><orientation a="-0.35" x="0.3" y="1" z="0"/></camera>
    <background_color r="0.2" g="0.3" b="0.5"/>
    <refractive_index v="1"/>
    <ambient_light r="0.2" g="0.2" b="0.2"/>
    <point_light><position x="1" y="1.8" z="0"/><color r="1" g="1" b="1"/></point_light>
    <material name="mirror"><diffuse r="0.5" g="0.4" b="0.3"/><specular r="0.6" g="0.6" b="0.6"/>
        <refractive_index v="0"/></material>
    <material name="red"><diffuse r="0.9" g="0.1" b="0.1"/><specular r="0.3" g="0.3" b="0.3"/>
        <refractive_index v="0"/></material>
    {}{}{}
    <sphere material="red"><position x="-1" y="-0.4" z="-1.5"/><radius v="0.6"/></sphere>
    <sphere material="red"><position x="0.6" y="0.5" z="-2.2"/><radius v="0.4"/></sphere>
    {}{}{}
    <triangle material="red"><position x="0" y="0" z="0"/>
        <vertex name="t0"/><vertex name="t1"/><vertex name="t2"/></triangle>
</scene>"#,
            quad("f", floor, [0.0, 1.0, 0.0]),
            quad("l", left, [1.0, 0.0, 0.0]),
            quad("b", back, [0.0, 0.0, 1.0]),
            vertex("t0", "red", [0.2, -0.9, -0.5], [0.0, 1.0, 0.0]),
            vertex("t1", "red", [1.2, -0.9, -1.0], [0.0, 1.0, 0.0]),
            vertex("t2", "red", [0.7, 0.3, -1.2], [0.0, 1.0, 0.0]),
        );
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("corner.scene");
        std::fs::write(&path, xml).unwrap();
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let settings = RenderSettings {
            width: 48,
            height: 36,
            spp: 9,
            ..RenderSettings::default()
        };
        let rect = TileRect::new(0, 0, 48, 36);
        let never = AtomicBool::new(false);
        let render = |mirror_slots: bool| {
            let renderer = Renderer {
                mirror_slots,
                ..Renderer::new(&scene, &settings).unwrap()
            };
            let image = renderer.render_tile(rect, &never).unwrap();
            (bits(&image.pixels), renderer.rays_traced())
        };
        // The seams are in view: some pixels' eye rays meet two of the mirror planes.
        let renderer = Renderer::new(&scene, &settings).unwrap();
        let world = scene.world();
        let seam_pixels = (0..36u32)
            .flat_map(|y| (0..48u32).map(move |x| (x, y)))
            .filter(|&(x, y)| {
                let mut planes = Vec::new();
                for sample in 0..9 {
                    let eye = renderer.eye.sample(x, y, sample);
                    let hit = world.intersect(&eye.ray, eye.near, eye.far);
                    if let Some(plane) = hit.and_then(|h| world.mirror_plane(&h)) {
                        if !planes.contains(&plane) {
                            planes.push(plane);
                        }
                    }
                }
                planes.len() >= 2
            })
            .count();
        assert!(
            seam_pixels > 10,
            "{seam_pixels} pixels see two mirror planes"
        );
        assert!(
            render(true) == render(false),
            "mirror slots changed the render"
        );
    }

    #[test]
    fn pixels_whose_frustum_meets_nothing_sum_the_same_bits_without_their_rays() {
        // The course scenes with background pixels: coloured backgrounds (a wrong miss colour
        // changes bits), mirrors and a mesh; a skipped pixel that shifted another's random
        // numbers, ray counts or sums would show.
        for name in ["test", "tetrahedron", "dragon"] {
            let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
                .join(format!("../../shared/scenes/course/{name}.scene"));
            let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
            let settings = RenderSettings {
                width: 40,
                height: 30,
                spp: 9,
                ..RenderSettings::default()
            };
            let rect = TileRect::new(0, 0, 40, 30);
            let never = AtomicBool::new(false);
            let render = |skip: bool, order: SampleOrder| {
                let renderer = Renderer {
                    skip_empty_pixels: skip,
                    ..Renderer::new(&scene, &settings).unwrap()
                }
                .with_sample_order(order);
                let image = renderer.render_tile(rect, &never).unwrap();
                let mut sums = vec![0.0; rect.pixel_count() * crate::adaptive::SUMS];
                for samples in [0..4, 4..9] {
                    assert!(renderer.render_tile_samples(
                        rect,
                        &|_, _| samples.clone(),
                        &mut sums,
                        &never,
                    ));
                }
                (bits(&image.pixels), bits(&sums), renderer.rays_traced())
            };
            // Some pixels' frustums meet nothing, or the skip is never taken.
            let renderer = Renderer::new(&scene, &settings).unwrap();
            let mut slots = Vec::new();
            let empty = (0..30)
                .flat_map(|y| (0..40).map(move |x| (x, y)))
                .filter(|&(x, y)| {
                    let (origin, planes) = renderer.eye.pixel_frustum(x, y).unwrap();
                    scene.world().frustum_slots(origin, &planes, &mut slots);
                    slots.is_empty()
                })
                .count();
            assert!(empty > 0 && empty < 40 * 30, "{name}: {empty} empty pixels");
            for order in [SampleOrder::Grid, SampleOrder::Progressive] {
                assert!(
                    render(true, order) == render(false, order),
                    "{name}, {order:?}: skipping empty pixels changed the render"
                );
            }
        }
    }

    #[test]
    fn tracing_by_stratum_sums_the_same_bits_as_tracing_in_sample_order() {
        // Textures, glass, a mirror and soft shadows: every sample's rays differ, so a sample
        // summed out of order or traced with another's random numbers changes bits.
        let path = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
            .join("../../shared/scenes/course/stacks.scene");
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        let settings = RenderSettings {
            width: 20,
            height: 15,
            spp: 64,
            ..RenderSettings::default()
        };
        let rect = TileRect::new(4, 3, 12, 9);
        let never = AtomicBool::new(false);
        let render = |by_stratum: bool| {
            let renderer = Renderer {
                trace_by_stratum: by_stratum,
                ..Renderer::new(&scene, &settings).unwrap()
            }
            .with_sample_order(SampleOrder::Progressive);
            let mut sums = vec![0.0; rect.pixel_count() * crate::adaptive::SUMS];
            // Passes as a progressive job makes them, and an uneven one.
            for samples in [0..8, 8..16, 16..37, 37..64] {
                assert!(renderer.render_tile_samples(
                    rect,
                    &|x, _| if x % 3 == 0 { 0..0 } else { samples.clone() },
                    &mut sums,
                    &never,
                ));
            }
            (bits(&sums), renderer.rays_traced())
        };
        let (by_stratum, rays) = render(true);
        assert!(rays > 0 && by_stratum.iter().any(|&b| b != 0));
        assert_eq!(by_stratum, render(false).0);
        assert_eq!(rays, render(false).1);
    }

    /// The bits of rendered values (pixels in f32, sums in f64; widening f32 is exact), to
    /// compare renders exactly.
    fn bits<T: Copy + Into<f64>>(values: &[T]) -> Vec<u64> {
        values.iter().map(|&v| v.into().to_bits()).collect()
    }
}
