//! Pixels: each sample's eye ray from [`EyeRays`], traced by the shading model, averaged into
//! linear f32 tiles. A pixel's value depends only on (scene, settings, pixel), so any tiling
//! gives the same bytes.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

use crate::camera::{Camera, EyeRays};
use crate::film::Image;
use crate::photon::{caustic_map, CausticMap};
use crate::scene::Scene;
use crate::settings::{RenderSettings, SettingsError, TileRect};
use crate::shade::Tracer;

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
        })
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
        let stage = self
            .scene
            .stage(self.settings.texture_filter, self.caustics.as_deref());
        let mut tracer = Tracer::new(stage, self.settings.max_depth);
        // The course's pixel grid has y = 0 at the bottom.
        let y = self.settings.height - 1 - row;
        let (mut radiance_rays, mut shadow_rays) = (0u64, 0u64);
        // A pixel's eye rays share an origin and stay within its frustum: the top-level slots
        // the frustum meets are found once per pixel, and each eye ray tests just those
        // instead of traversing (kept for the row, so no allocation per pixel).
        let mut slots = Vec::new();
        for (i, px) in out.chunks_exact_mut(3).enumerate() {
            let x = x0 + i as u32;
            let mut sum = DVec3::ZERO;
            let frustum = self.eye.pixel_frustum(x, y).map(|(origin, planes)| {
                stage.world.frustum_slots(origin, &planes, &mut slots);
                &slots[..]
            });
            for sample in 0..self.settings.spp {
                let mut eye = self.eye.sample(x, y, sample);
                let (color, counts) = tracer.sample(
                    &eye.ray,
                    eye.near,
                    eye.far,
                    &mut eye.rng,
                    eye.gloss,
                    frustum,
                );
                radiance_rays += counts.radiance as u64;
                shadow_rays += counts.shadow as u64;
                sum += sanitize(color);
            }
            // The average before any clamping (conventions §3.2).
            let mean = sum / self.settings.spp as f64;
            px.copy_from_slice(&[mean.x as f32, mean.y as f32, mean.z as f32]);
        }
        self.radiance_rays
            .fetch_add(radiance_rays, Ordering::Relaxed);
        self.shadow_rays.fetch_add(shadow_rays, Ordering::Relaxed);
    }
}

/// Keeps one pathological sample from poisoning a pixel: NaN becomes 0, and values are capped
/// far above anything that survives the final clamp to [0, 1].
fn sanitize(c: DVec3) -> DVec3 {
    let f = |v: f64| if v.is_nan() { 0.0 } else { v.clamp(0.0, 1e6) };
    DVec3::new(f(c.x), f(c.y), f(c.z))
}
