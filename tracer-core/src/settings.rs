//! Render settings and tile rectangles: the plain data a farm job carries.

use serde::{Deserialize, Serialize};

/// How textures are sampled between texels.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TextureFilter {
    /// Nearest texel: the handout's baseline, and the closer fit to the references.
    #[default]
    Nearest,
    /// GL-style bilinear with repeat wrap.
    Bilinear,
}

/// A camera placed by position, look-at point and up vector, replacing the scene's camera.
/// The scene's vertical field of view and clip planes are kept.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraOverride {
    pub position: [f64; 3],
    pub look_at: [f64; 3],
    #[serde(default = "default_up")]
    pub up: [f64; 3],
}

fn default_up() -> [f64; 3] {
    [0.0, 1.0, 0.0]
}

/// Caustic photon mapping requested by the render rather than the scene (see `photon.rs`).
/// The default follows the scene: caustics are on exactly when it has a `<caustics>` element.
#[derive(Clone, Copy, Debug, Default, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct CausticsSettings {
    /// Some(true) turns caustics on even without `<caustics>`, Some(false) turns them off;
    /// None follows the scene, or turns them on if `photons` or `radius` is given.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub enabled: Option<bool>,
    /// Photons emitted, replacing the scene's count.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub photons: Option<u32>,
    /// Gather radius in scene units, replacing the scene's.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub radius: Option<f64>,
}

impl CausticsSettings {
    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    pub fn validate(&self) -> Result<(), String> {
        if let Some(n) = self.photons {
            if n == 0 || n > crate::photon::MAX_PHOTONS {
                return Err(format!(
                    "caustic photons {n} must lie between 1 and {}",
                    crate::photon::MAX_PHOTONS
                ));
            }
        }
        if let Some(r) = self.radius {
            if !(r.is_finite() && r > 0.0) {
                return Err(format!(
                    "caustic gather radius {r} must be a positive number"
                ));
            }
        }
        Ok(())
    }
}

/// Everything besides the scene that decides a rendered pixel.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct RenderSettings {
    pub width: u32,
    pub height: u32,
    /// Samples per pixel, stratified over the pixel.
    pub spp: u32,
    /// Ray levels traced, the eye ray included (the course's 5 means at most 4 bounces).
    pub max_depth: u32,
    pub seed: u64,
    pub camera: Option<CameraOverride>,
    pub texture_filter: TextureFilter,
    /// Left out of the JSON when default, so that jobs without caustics serialise as before.
    #[serde(skip_serializing_if = "CausticsSettings::is_default")]
    pub caustics: CausticsSettings,
}

impl Default for RenderSettings {
    fn default() -> Self {
        Self {
            width: 800,
            height: 600,
            spp: 4,
            max_depth: 5,
            seed: 0,
            camera: None,
            texture_filter: TextureFilter::Nearest,
            caustics: CausticsSettings::default(),
        }
    }
}

impl RenderSettings {
    /// Rejects settings no render can honour (limits on size belong to the caller).
    pub fn validate(&self) -> Result<(), String> {
        if self.width == 0 || self.height == 0 {
            return Err(format!(
                "image size {}x{} must be at least 1x1",
                self.width, self.height
            ));
        }
        if self.spp == 0 {
            return Err("spp must be at least 1".into());
        }
        self.caustics.validate()?;
        if let Some(cam) = &self.camera {
            let all = cam.position.iter().chain(&cam.look_at).chain(&cam.up);
            if all.clone().any(|v| !v.is_finite()) {
                return Err("camera override has a non-finite coordinate".into());
            }
            let forward: Vec<f64> = (0..3).map(|i| cam.look_at[i] - cam.position[i]).collect();
            if forward.iter().all(|v| *v == 0.0) {
                return Err("camera override looks at its own position".into());
            }
            let up = cam.up;
            let cross = [
                forward[1] * up[2] - forward[2] * up[1],
                forward[2] * up[0] - forward[0] * up[2],
                forward[0] * up[1] - forward[1] * up[0],
            ];
            if cross.iter().all(|v| *v == 0.0) {
                return Err("camera override's up vector is parallel to its view direction".into());
            }
        }
        Ok(())
    }
}

/// A rectangle of pixels; (x, y) is its top-left corner with y counted from the image's top row.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TileRect {
    pub x: u32,
    pub y: u32,
    pub width: u32,
    pub height: u32,
}

impl TileRect {
    pub const fn new(x: u32, y: u32, width: u32, height: u32) -> Self {
        Self {
            x,
            y,
            width,
            height,
        }
    }

    pub fn pixel_count(&self) -> usize {
        self.width as usize * self.height as usize
    }

    /// Splits a `width`×`height` image into tiles of at most `tile`×`tile`, row by row from the top.
    pub fn grid(width: u32, height: u32, tile: u32) -> Vec<TileRect> {
        let tile = tile.max(1);
        let mut out = Vec::new();
        for y in (0..height).step_by(tile as usize) {
            for x in (0..width).step_by(tile as usize) {
                out.push(TileRect::new(
                    x,
                    y,
                    tile.min(width - x),
                    tile.min(height - y),
                ));
            }
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn grid_covers_the_image_once() {
        let tiles = TileRect::grid(130, 70, 64);
        assert_eq!(tiles.len(), 3 * 2);
        let area: usize = tiles.iter().map(|t| t.pixel_count()).sum();
        assert_eq!(area, 130 * 70);
        assert_eq!(tiles[2], TileRect::new(128, 0, 2, 64));
        assert_eq!(tiles[5], TileRect::new(128, 64, 2, 6));
    }

    #[test]
    fn settings_take_defaults_for_missing_json_fields() {
        let s: RenderSettings = serde_json::from_str(r#"{"spp": 16}"#).unwrap();
        assert_eq!(s.spp, 16);
        assert_eq!((s.width, s.height, s.max_depth), (800, 600, 5));
        assert!(serde_json::from_str::<RenderSettings>(r#"{"spq": 1}"#).is_err());
        let zero = RenderSettings {
            spp: 0,
            ..Default::default()
        };
        assert!(zero.validate().is_err());
    }
}
