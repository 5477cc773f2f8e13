//! Pixels: eye rays through stratified sub-pixel positions, averaged into linear f32 tiles.
//! A pixel's value depends only on (scene, settings, pixel), so any tiling gives the same bytes.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::Camera;
use crate::film::Image;
use crate::photon::{caustic_map, CausticMap};
use crate::sampler::{concentric_disk, strata, Rng, Stream};
use crate::scene::Scene;
use crate::settings::{RenderSettings, TileRect};
use crate::shade::{MediumStack, Tracer};

/// Largest recursion depth accepted; the ray budget bounds the work in any case.
pub const MAX_DEPTH_LIMIT: u32 = 64;

/// Renders pixels of one scene with one set of settings. Shared across threads.
pub struct Renderer<'a> {
    scene: &'a Scene,
    settings: RenderSettings,
    camera: Camera,
    /// Time of the shutter's opening for this frame, and how long it stays open.
    time_open: f64,
    shutter_length: f64,
    /// Whether samples draw a time (something moves while the shutter is open).
    sample_time: bool,
    /// Whether the camera itself moves while the shutter is open.
    camera_moves: bool,
    strata: (u32, u32),
    radiance_rays: AtomicU64,
    shadow_rays: AtomicU64,
    caustics: Option<Arc<CausticMap>>,
}

impl<'a> Renderer<'a> {
    pub fn new(scene: &'a Scene, settings: &RenderSettings) -> Result<Self, String> {
        settings.validate()?;
        if settings.max_depth == 0 || settings.max_depth > MAX_DEPTH_LIMIT {
            return Err(format!(
                "depth {} must lie between 1 and {MAX_DEPTH_LIMIT}",
                settings.max_depth
            ));
        }
        if settings.frame >= scene.frame_count() {
            return Err(format!(
                "frame {} is out of range: the scene has {} frame(s), numbered from 0",
                settings.frame,
                scene.frame_count()
            ));
        }
        let c = &scene.description.camera;
        let time_open = settings.frame as f64 + c.shutter[0];
        let shutter_length = c.shutter[1] - c.shutter[0];
        let moving = shutter_length > 0.0 && scene.description.has_motion();
        let mut camera = Self::camera_at(scene, settings, time_open);
        if let Some(o) = &settings.camera {
            camera = camera.with_override(o);
        }
        Ok(Self {
            scene,
            settings: settings.clone(),
            camera,
            time_open,
            shutter_length,
            sample_time: moving,
            camera_moves: moving && settings.camera.is_none() && !c.motion.is_static(),
            strata: strata(settings.spp),
            radiance_rays: AtomicU64::new(0),
            shadow_rays: AtomicU64::new(0),
            caustics: caustic_map(scene, settings),
        })
    }

    /// The scene's camera at `time`, before any override.
    fn camera_at(scene: &Scene, settings: &RenderSettings, time: f64) -> Camera {
        let c = &scene.description.camera;
        let (position, orientation) = c.at(time);
        Camera::from_orientation(
            position,
            orientation,
            c.fov,
            c.near_clip.max(0.0),
            c.far_clip,
            settings.width as f64 / settings.height as f64,
        )
        .with_lens(c.aperture, c.focus_at(time))
    }

    pub fn settings(&self) -> &RenderSettings {
        &self.settings
    }

    pub fn camera(&self) -> &Camera {
        &self.camera
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
        assert!(
            rect.x + rect.width <= self.settings.width
                && rect.y + rect.height <= self.settings.height,
            "tile {rect:?} lies outside the {}x{} image",
            self.settings.width,
            self.settings.height
        );
        let mut tile = Image::new(rect.width, rect.height);
        if rect.width == 0 {
            return Some(tile);
        }
        tile.pixels
            .par_chunks_mut(3 * rect.width as usize)
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
        image
            .pixels
            .par_chunks_mut(3 * w as usize)
            .enumerate()
            .for_each(|(row, out)| {
                self.render_row(0, row as u32, out);
                let now = done.fetch_add(w as u64, Ordering::Relaxed) + w as u64;
                progress(now, total);
            });
        image
    }

    /// Renders the pixels of image row `row` (counted from the top) starting at column `x0`
    /// into `out` (3 floats per pixel).
    fn render_row(&self, x0: u32, row: u32, out: &mut [f32]) {
        let mut tracer = Tracer::new(
            self.scene,
            self.settings.texture_filter,
            self.settings.max_depth,
        );
        tracer.caustics = self.caustics.as_deref();
        let mut radiance_rays = 0u64;
        let mut shadow_rays = 0u64;
        for (i, px) in out.chunks_exact_mut(3).enumerate() {
            let color = self.pixel(
                x0 + i as u32,
                row,
                &mut tracer,
                &mut radiance_rays,
                &mut shadow_rays,
            );
            px.copy_from_slice(&color);
        }
        self.radiance_rays
            .fetch_add(radiance_rays, Ordering::Relaxed);
        self.shadow_rays.fetch_add(shadow_rays, Ordering::Relaxed);
    }

    /// The average of the pixel's samples, before any clamping (conventions §3.2).
    fn pixel(
        &self,
        x: u32,
        row: u32,
        tracer: &mut Tracer<'_>,
        radiance_rays: &mut u64,
        shadow_rays: &mut u64,
    ) -> [f32; 3] {
        let s = &self.settings;
        // The course's pixel grid has y = 0 at the bottom.
        let y = s.height - 1 - row;
        let (cols, rows) = self.strata;
        let (w, h) = (s.width as f64, s.height as f64);
        let outer = MediumStack::new(self.scene.description.refractive_index);
        let mut sum = DVec3::ZERO;
        for sample in 0..s.spp {
            let mut rng = Rng::for_sample(s.seed, x, y, sample);
            // One sample goes through the pixel centre; more are jittered within strata.
            let (jx, jy) = if s.spp == 1 {
                (0.5, 0.5)
            } else {
                let (cx, cy) = (sample % cols, sample / cols);
                (
                    (cx as f64 + rng.next_f64()) / cols as f64,
                    (cy as f64 + rng.next_f64()) / rows as f64,
                )
            };
            // Effects draw from their own streams, so the numbers above stay the course's.
            let time = if self.sample_time {
                let mut r = Rng::for_stream(s.seed, x, y, sample, Stream::Time);
                self.time_open + self.shutter_length * r.next_f64()
            } else {
                self.time_open
            };
            let moved;
            let camera = if self.camera_moves {
                moved = Self::camera_at(self.scene, s, time);
                &moved
            } else {
                &self.camera
            };
            let (px, py) = (x as f64 + jx, y as f64 + jy);
            let ray = if camera.aperture > 0.0 {
                let mut r = Rng::for_stream(s.seed, x, y, sample, Stream::Lens);
                let lens = concentric_disk(r.next_f64(), r.next_f64());
                camera.lens_ray(px, py, w, h, lens)
            } else {
                camera.ray(px, py, w, h)
            }
            .at_time(time);
            if self.scene.has_gloss {
                tracer.gloss_rng = Rng::for_stream(s.seed, x, y, sample, Stream::Gloss);
            }
            tracer.radiance_rays = 0;
            tracer.shadow_rays = 0;
            let c = tracer.radiance(&ray, camera.near, camera.far, 0, outer, &mut rng);
            *radiance_rays += tracer.radiance_rays as u64;
            *shadow_rays += tracer.shadow_rays as u64;
            sum += sanitize(c);
        }
        let mean = sum / s.spp as f64;
        [mean.x as f32, mean.y as f32, mean.z as f32]
    }
}

/// Keeps one pathological sample from poisoning a pixel: NaN becomes 0, and values are capped
/// far above anything that survives the final clamp to [0, 1].
fn sanitize(c: DVec3) -> DVec3 {
    let f = |v: f64| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1e6) };
    DVec3::new(f(c.x), f(c.y), f(c.z))
}
