//! Render settings and tile rectangles: the plain data a farm job carries.

use std::path::{Path, PathBuf};
use std::str::FromStr;

use serde::{Deserialize, Serialize};

pub use crate::texture::TextureFilter;

/// Most caustic photons one map may emit (each stored photon takes 48 bytes).
pub const MAX_PHOTONS: u32 = 5_000_000;

/// Settings no render can honour.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum SettingsError {
    #[error("image size {width}x{height} must be at least 1x1")]
    EmptyImage { width: u32, height: u32 },
    #[error("spp must be at least 1")]
    NoSamples,
    #[error("caustic photons {0} must lie between 1 and {MAX_PHOTONS}")]
    Photons(u32),
    #[error("caustic gather radius {0} must be a positive number")]
    PhotonRadius(f64),
    #[error("camera override has a non-finite coordinate")]
    CameraNotFinite,
    #[error("camera override looks at its own position")]
    CameraLooksAtItself,
    #[error("camera override's up vector is parallel to its view direction")]
    CameraUpParallel,
    #[error("the frame range {first}..{last} is empty")]
    EmptyFrameRange { first: u32, last: u32 },
    #[error("frames {first}..{last}: the scene has {frame_count} frame(s), numbered from 0")]
    FramesOutOfRange {
        first: u32,
        last: u32,
        frame_count: u32,
    },
}

/// A command-line value that does not parse.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ParseError {
    #[error("expected A..B, got '{0}'")]
    FrameRange(String),
    #[error("'{0}' is not a frame number")]
    FrameNumber(String),
    #[error("expected x,y,z, got '{0}'")]
    Vec3(String),
    #[error("'{0}' is not a finite number")]
    NotFinite(String),
    #[error(transparent)]
    Settings(#[from] SettingsError),
}

/// A camera placed by position, look-at point and up vector, replacing the scene's camera.
/// The scene's vertical field of view and clip planes are kept.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
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
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
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
    /// The settings the command-line flags ask for: `--caustics`, `--no-caustics` (which
    /// wins), `--photons N` and `--photon-radius R`.
    pub fn from_flags(on: bool, off: bool, photons: Option<u32>, radius: Option<f64>) -> Self {
        Self {
            enabled: if off { Some(false) } else { on.then_some(true) },
            photons,
            radius,
        }
    }

    pub fn is_default(&self) -> bool {
        *self == Self::default()
    }

    pub fn validate(&self) -> Result<(), SettingsError> {
        if let Some(n) = self.photons {
            if n == 0 || n > MAX_PHOTONS {
                return Err(SettingsError::Photons(n));
            }
        }
        if let Some(r) = self.radius {
            if !(r.is_finite() && r > 0.0) {
                return Err(SettingsError::PhotonRadius(r));
            }
        }
        Ok(())
    }
}

/// Everything besides the scene that decides a rendered pixel.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
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
    /// Frame of an animated scene (time = frame); 0 for a still.
    pub frame: u32,
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
            frame: 0,
            caustics: CausticsSettings::default(),
        }
    }
}

impl RenderSettings {
    /// Rejects settings no render can honour (limits on size belong to the caller).
    pub fn validate(&self) -> Result<(), SettingsError> {
        if self.width == 0 || self.height == 0 {
            return Err(SettingsError::EmptyImage {
                width: self.width,
                height: self.height,
            });
        }
        if self.spp == 0 {
            return Err(SettingsError::NoSamples);
        }
        self.caustics.validate()?;
        if let Some(cam) = &self.camera {
            let all = cam.position.iter().chain(&cam.look_at).chain(&cam.up);
            if all.clone().any(|v| !v.is_finite()) {
                return Err(SettingsError::CameraNotFinite);
            }
            let forward: Vec<f64> = (0..3).map(|i| cam.look_at[i] - cam.position[i]).collect();
            if forward.iter().all(|v| *v == 0.0) {
                return Err(SettingsError::CameraLooksAtItself);
            }
            let up = cam.up;
            let cross = [
                forward[1] * up[2] - forward[2] * up[1],
                forward[2] * up[0] - forward[0] * up[2],
                forward[0] * up[1] - forward[1] * up[0],
            ];
            if cross.iter().all(|v| *v == 0.0) {
                return Err(SettingsError::CameraUpParallel);
            }
        }
        Ok(())
    }
}

/// A rectangle of pixels; (x, y) is its top-left corner with y counted from the image's top row.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
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

/// An inclusive range of frames of an animated scene, written `A..B` on command lines.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameRange {
    pub first: u32,
    pub last: u32,
}

impl FrameRange {
    /// A range from `first` through `last`; empty ranges are refused.
    pub fn new(first: u32, last: u32) -> Result<Self, SettingsError> {
        if first > last {
            return Err(SettingsError::EmptyFrameRange { first, last });
        }
        Ok(Self { first, last })
    }

    /// How many frames the range holds (at least one once validated).
    pub fn len(&self) -> u32 {
        self.last.saturating_sub(self.first).saturating_add(1)
    }

    /// Never true for a range made by [`FrameRange::new`]; a deserialised one is checked with
    /// [`FrameRange::validate`].
    pub fn is_empty(&self) -> bool {
        self.first > self.last
    }

    pub fn frames(&self) -> std::ops::RangeInclusive<u32> {
        self.first..=self.last
    }

    /// Checks the range against a scene with `frame_count` frames.
    pub fn validate(&self, frame_count: u32) -> Result<(), SettingsError> {
        if self.is_empty() {
            return Err(SettingsError::EmptyFrameRange {
                first: self.first,
                last: self.last,
            });
        }
        if self.last >= frame_count {
            return Err(SettingsError::FramesOutOfRange {
                first: self.first,
                last: self.last,
                frame_count,
            });
        }
        Ok(())
    }
}

impl FromStr for FrameRange {
    type Err = ParseError;

    /// `A..B`, inclusive.
    fn from_str(s: &str) -> Result<Self, ParseError> {
        let (a, b) = s
            .split_once("..")
            .ok_or_else(|| ParseError::FrameRange(s.to_string()))?;
        let num = |t: &str| {
            t.trim()
                .parse::<u32>()
                .map_err(|_| ParseError::FrameNumber(t.to_string()))
        };
        Ok(FrameRange::new(num(a)?, num(b)?)?)
    }
}

/// Where frame `frame` of a sequence goes: `out.png` → `out_0003.png`.
pub fn numbered_path(output: &Path, frame: u32) -> PathBuf {
    let stem = output
        .file_stem()
        .map(|s| s.to_string_lossy().into_owned())
        .unwrap_or_default();
    let name = match output.extension() {
        Some(ext) => format!("{stem}_{frame:04}.{}", ext.to_string_lossy()),
        None => format!("{stem}_{frame:04}"),
    };
    output.with_file_name(name)
}

/// `x,y,z` as three finite numbers (command-line vectors).
pub fn parse_vec3(s: &str) -> Result<[f64; 3], ParseError> {
    let parts: Vec<&str> = s.split(',').map(str::trim).collect();
    let [x, y, z] = parts.as_slice() else {
        return Err(ParseError::Vec3(s.to_string()));
    };
    let mut v = [0.0; 3];
    for (slot, part) in v.iter_mut().zip([x, y, z]) {
        *slot = part
            .parse::<f64>()
            .ok()
            .filter(|n| n.is_finite())
            .ok_or_else(|| ParseError::NotFinite(part.to_string()))?;
    }
    Ok(v)
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

    #[test]
    fn frame_ranges_parse_validate_and_number_paths() {
        let r: FrameRange = "2..5".parse().unwrap();
        assert_eq!((r.first, r.last, r.len()), (2, 5, 4));
        assert_eq!(r.frames().collect::<Vec<_>>(), [2, 3, 4, 5]);
        assert!("5..2".parse::<FrameRange>().is_err());
        assert!("5".parse::<FrameRange>().is_err());
        assert!("a..2".parse::<FrameRange>().is_err());
        assert!(r.validate(6).is_ok());
        assert!(r
            .validate(5)
            .unwrap_err()
            .to_string()
            .contains("5 frame(s)"));
        assert!(FrameRange { first: 3, last: 1 }.validate(9).is_err());
        assert_eq!(
            numbered_path(Path::new("out/a.png"), 3),
            Path::new("out/a_0003.png")
        );
        assert_eq!(numbered_path(Path::new("a"), 12), Path::new("a_0012"));
        assert_eq!(parse_vec3(" 1, -2,3e1").unwrap(), [1.0, -2.0, 30.0]);
        assert!(parse_vec3("1,2").is_err());
        assert!(parse_vec3("1,nan,2").is_err());
    }
}
