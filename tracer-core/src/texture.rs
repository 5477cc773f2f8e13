//! PNG textures: 8-bit RGB held bottom row first, sampled with repeat wrap (conventions §5),
//! and the latitude–longitude environment map built on one.

use glam::{DVec2, DVec3};
use serde::{Deserialize, Serialize};

/// How textures are sampled between texels.
#[cfg_attr(feature = "openapi", derive(utoipa::ToSchema))]
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum TextureFilter {
    /// Nearest texel: the handout's baseline, and the closer fit to the references.
    #[default]
    Nearest,
    /// GL-style bilinear with repeat wrap.
    Bilinear,
}

/// A texture file that cannot be used.
#[derive(Debug, thiserror::Error)]
pub enum TextureError {
    #[error("cannot decode PNG: {0}")]
    Decode(image::ImageError),
    #[error("the PNG has no pixels")]
    Empty,
}

#[derive(Clone, Debug)]
pub struct Texture {
    width: u32,
    height: u32,
    /// RGB texels, row 0 at the **bottom** of the image.
    texels: Vec<[u8; 3]>,
}

impl Texture {
    /// Decodes a PNG; alpha, gamma and colour-profile chunks are ignored, as in the course.
    pub fn decode_png(bytes: &[u8]) -> Result<Texture, TextureError> {
        let image = image::load_from_memory_with_format(bytes, image::ImageFormat::Png)
            .map_err(TextureError::Decode)?;
        let (width, height) = (image.width(), image.height());
        if width == 0 || height == 0 {
            return Err(TextureError::Empty);
        }
        // The decoder's 8-bit RGB and RGBA rows are read as they are (alpha dropped, as
        // `to_rgb8` drops it); every other layout goes through `to_rgb8`. Its generic
        // per-pixel conversion cost five times the decoding itself (about 90 instructions a
        // texel: toy.scene's two 1024×768 textures took 150 M before its first ray).
        let (raw, channels) = match image {
            image::DynamicImage::ImageRgb8(buffer) => (buffer.into_raw(), 3),
            image::DynamicImage::ImageRgba8(buffer) => (buffer.into_raw(), 4),
            other => (other.to_rgb8().into_raw(), 3),
        };
        let mut texels = Vec::with_capacity(width as usize * height as usize);
        // Bottom row first.
        for row in raw.chunks_exact(width as usize * channels).rev() {
            texels.extend(row.chunks_exact(channels).map(|p| [p[0], p[1], p[2]]));
        }
        Ok(Texture {
            width,
            height,
            texels,
        })
    }

    /// Builds a texture from bottom-first texels (tests and generated textures).
    pub fn from_texels(width: u32, height: u32, texels: Vec<[u8; 3]>) -> Texture {
        assert_eq!(texels.len(), width as usize * height as usize);
        Texture {
            width,
            height,
            texels,
        }
    }

    /// Width and height in texels.
    pub fn dimensions(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    #[inline(always)]
    fn texel(&self, x: u32, y: u32) -> DVec3 {
        let [r, g, b] = self.texels[y as usize * self.width as usize + x as usize];
        // The table holds v / 255 for every byte: the same values as dividing, without the
        // three divisions.
        DVec3::new(UNIT[r as usize], UNIT[g as usize], UNIT[b as usize])
    }

    /// The colour at `uv`, (0,0) at the bottom-left, repeating outside [0,1).
    #[inline]
    pub fn sample(&self, uv: DVec2, filter: TextureFilter) -> DVec3 {
        let u = wrap(uv.x);
        let v = wrap(uv.y);
        let (w, h) = (self.width as f64, self.height as f64);
        match filter {
            TextureFilter::Nearest => {
                // min() guards u == 1.0, which wrap() can produce after round-off.
                let x = ((u * w) as u32).min(self.width - 1);
                let y = ((v * h) as u32).min(self.height - 1);
                self.texel(x, y)
            }
            TextureFilter::Bilinear => {
                let sx = u * w - 0.5;
                let sy = v * h - 0.5;
                let (fx, fy) = (sx.floor(), sy.floor());
                let (tx, ty) = (sx - fx, sy - fy);
                let x0 = (fx as i64).rem_euclid(self.width as i64) as u32;
                let y0 = (fy as i64).rem_euclid(self.height as i64) as u32;
                let x1 = (x0 + 1) % self.width;
                let y1 = (y0 + 1) % self.height;
                let bottom = self.texel(x0, y0).lerp(self.texel(x1, y0), tx);
                let top = self.texel(x0, y1).lerp(self.texel(x1, y1), tx);
                bottom.lerp(top, ty)
            }
        }
    }
}

/// A latitude–longitude image seen by rays that leave the scene.
#[derive(Clone, Debug)]
pub struct Environment {
    pub image: Texture,
    pub intensity: f64,
    /// cos and sin of the turn about +Y.
    rotation: (f64, f64),
}

impl Environment {
    pub fn new(image: Texture, intensity: f64, rotation: f64) -> Self {
        Self {
            image,
            intensity,
            rotation: (rotation.cos(), rotation.sin()),
        }
    }

    /// The colour toward unit direction `d`: −Z (the default view) sees the image's centre,
    /// +Y its top row; u grows turning right, toward +X. Filtered bilinearly, wrapping
    /// around in u only.
    pub fn lookup(&self, d: DVec3) -> DVec3 {
        let (c, s) = self.rotation;
        // Turning the map by +θ about Y turns the direction by −θ.
        let x = c * d.x + s * d.z;
        let z = -s * d.x + c * d.z;
        let u = 0.5 + x.atan2(-z) / std::f64::consts::TAU;
        let v = 0.5 + d.y.clamp(-1.0, 1.0).asin() / std::f64::consts::PI;
        // Rows do not wrap over the poles: stay within the outer rows' centres.
        let half_row = 0.5 / self.image.dimensions().1 as f64;
        let v = v.clamp(half_row, 1.0 - half_row);
        self.intensity * self.image.sample(DVec2::new(u, v), TextureFilter::Bilinear)
    }
}

/// Byte value v as v / 255, for every byte.
const UNIT: [f64; 256] = {
    let mut table = [0.0; 256];
    let mut v = 0;
    while v < 256 {
        table[v] = v as f64 / 255.0;
        v += 1;
    }
    table
};

/// Repeat wrap into [0, 1]; non-finite coordinates map to 0 rather than poisoning the lookup.
#[inline(always)]
fn wrap(t: f64) -> f64 {
    if !t.is_finite() {
        return 0.0;
    }
    t - floor(t)
}

/// `t.floor()` for finite `t`, without the library call that x86-64's baseline instruction
/// set needs for it. Only the sign of a zero result can differ (−0 gives +0), and `wrap`'s
/// callers scale and truncate it, where the sign of zero does not matter.
#[inline(always)]
fn floor(t: f64) -> f64 {
    // From 2^52 on, every f64 is an integer.
    if t.abs() < 4_503_599_627_370_496.0 {
        let truncated = t as i64 as f64;
        if truncated > t {
            truncated - 1.0
        } else {
            truncated
        }
    } else {
        t
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// 2×2: bottom row red, green; top row blue, white.
    fn checker() -> Texture {
        Texture::from_texels(
            2,
            2,
            vec![[255, 0, 0], [0, 255, 0], [0, 0, 255], [255, 255, 255]],
        )
    }

    /// `image` encoded as a PNG.
    fn png(image: image::DynamicImage) -> Vec<u8> {
        let mut bytes = std::io::Cursor::new(Vec::new());
        image.write_to(&mut bytes, image::ImageFormat::Png).unwrap();
        bytes.into_inner()
    }

    #[test]
    fn every_png_layout_decodes_to_its_rgb_bottom_row_first() {
        // 3×2 texels, all different, with alpha that must be dropped (not blended).
        let rgba: Vec<u8> = (0..6u8)
            .flat_map(|i| [40 * i, 255 - 30 * i, 7 * i + 1, 50 * i])
            .collect();
        let rgba = image::RgbaImage::from_raw(3, 2, rgba).unwrap();
        let rgb = image::DynamicImage::ImageRgba8(rgba.clone()).to_rgb8();
        // What the decoder must give: the top row last.
        let expected: Vec<[u8; 3]> = (rgb.rows().rev())
            .flat_map(|row| row.map(|p| p.0))
            .collect();
        let layouts = [
            image::DynamicImage::ImageRgba8(rgba.clone()),
            image::DynamicImage::ImageRgb8(rgb.clone()),
            // Another layout, converted by `to_rgb8`.
            image::DynamicImage::ImageRgb16(image::DynamicImage::ImageRgb8(rgb.clone()).to_rgb16()),
        ];
        for layout in layouts {
            let texture = Texture::decode_png(&png(layout)).unwrap();
            assert_eq!(texture.dimensions(), (3, 2));
            assert_eq!(texture.texels, expected);
        }
        let grey = image::GrayImage::from_raw(2, 1, vec![10, 200]).unwrap();
        let texture = Texture::decode_png(&png(image::DynamicImage::ImageLuma8(grey))).unwrap();
        assert_eq!(texture.texels, vec![[10, 10, 10], [200, 200, 200]]);
    }

    #[test]
    fn origin_is_bottom_left() {
        let t = checker();
        assert_eq!(
            t.sample(DVec2::new(0.0, 0.0), TextureFilter::Nearest),
            DVec3::X
        );
        assert_eq!(
            t.sample(DVec2::new(0.75, 0.25), TextureFilter::Nearest),
            DVec3::Y
        );
        assert_eq!(
            t.sample(DVec2::new(0.25, 0.75), TextureFilter::Nearest),
            DVec3::Z
        );
    }

    #[test]
    fn coordinates_wrap_and_one_is_guarded() {
        let t = checker();
        let n = TextureFilter::Nearest;
        assert_eq!(
            t.sample(DVec2::new(1.25, -0.75), n),
            t.sample(DVec2::new(0.25, 0.25), n)
        );
        assert_eq!(t.sample(DVec2::new(500.0, 500.0), n), DVec3::X);
        // 1.0 wraps to 0.0; one ulp below it must clamp to the last texel, not index past it.
        let below_one = 1.0 - f64::EPSILON / 2.0;
        assert_eq!(t.sample(DVec2::new(below_one, below_one), n), DVec3::ONE);
        assert_eq!(t.sample(DVec2::new(f64::NAN, f64::INFINITY), n), DVec3::X);
    }

    #[test]
    fn floor_matches_the_library_floor() {
        let mut rng = crate::sampler::Rng::for_sample(9, 8, 7, 6);
        let specials = [
            0.0,
            -0.5,
            0.5,
            -1.0,
            1.0,
            -1e-300,
            1e-300,
            4_503_599_627_370_495.5,
            -4_503_599_627_370_495.5,
            4_503_599_627_370_497.0,
            -1e300,
            1e300,
            f64::MAX,
            f64::MIN,
        ];
        let random = (0..10_000).map(|i| {
            let scale = 10f64.powi(i % 20 - 6);
            (rng.next_f64() - 0.5) * scale
        });
        for t in specials.into_iter().chain(random) {
            assert_eq!(floor(t), t.floor(), "floor({t})");
            assert_eq!(wrap(t), t - t.floor(), "wrap({t})");
        }
        assert_eq!(UNIT.map(|v| v.to_bits()), {
            let mut direct = [0u64; 256];
            for (i, d) in direct.iter_mut().enumerate() {
                *d = (i as f64 / 255.0).to_bits();
            }
            direct
        });
    }

    #[test]
    fn bilinear_blends_neighbours_with_wrap() {
        let t = checker();
        let b = TextureFilter::Bilinear;
        // Texel centres give the texel itself.
        assert!((t.sample(DVec2::new(0.25, 0.25), b) - DVec3::X).length() < 1e-12);
        // Midway between red and green horizontally.
        let mid = t.sample(DVec2::new(0.5, 0.25), b);
        assert!((mid - DVec3::new(0.5, 0.5, 0.0)).length() < 1e-12);
        // At u = 0 the left neighbour wraps around to the right column.
        let edge = t.sample(DVec2::new(0.0, 0.25), b);
        assert!((edge - DVec3::new(0.5, 0.5, 0.0)).length() < 1e-12);
    }
}
