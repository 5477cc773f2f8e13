//! Where rendered pixels are written: linear f32 RGB images (whole frames and tiles), tiles
//! assembled into a frame ([`assemble`], the one path the tracer and the farm share), and the
//! file formats: 8-bit PNG with the course's quantisation, linear f32 OpenEXR and PFM.

use std::io::Cursor;
use std::path::Path;

use crate::settings::TileRect;

/// Pixels that do not make the image they are meant to.
#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("a {width}x{height} image needs {expected} floats, got {got}")]
    PixelCount {
        width: u32,
        height: u32,
        expected: usize,
        got: usize,
    },
    #[error("a {got_width}x{got_height} tile does not fill {rect:?}")]
    TileSize {
        rect: TileRect,
        got_width: u32,
        got_height: u32,
    },
    #[error("tile {rect:?} lies outside the {width}x{height} image")]
    TileOutside {
        rect: TileRect,
        width: u32,
        height: u32,
    },
    #[error("cannot decode the image: {0}")]
    Decode(image::ImageError),
    #[error("not a PFM as Tessera writes it: {0}")]
    Pfm(&'static str),
}

/// The file formats an [`Image`] is written in, named by their usual extension (lower case
/// in `serde`, so `?format=exr` parses to [`ImageFormat::Exr`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ImageFormat {
    /// 8-bit RGB with the course's quantisation (clamp, ×255, truncate).
    #[default]
    Png,
    /// OpenEXR: the linear f32 RGB pixels as rendered, losslessly compressed.
    Exr,
    /// Portable float map: the linear f32 RGB pixels, uncompressed.
    Pfm,
}

impl ImageFormat {
    pub const ALL: [ImageFormat; 3] = [ImageFormat::Png, ImageFormat::Exr, ImageFormat::Pfm];

    pub fn extension(self) -> &'static str {
        match self {
            ImageFormat::Png => "png",
            ImageFormat::Exr => "exr",
            ImageFormat::Pfm => "pfm",
        }
    }

    /// The format a file name's extension (in any case) names, if one is supported.
    pub fn from_path(path: &Path) -> Option<ImageFormat> {
        let ext = path.extension()?;
        Self::ALL
            .into_iter()
            .find(|f| ext.eq_ignore_ascii_case(f.extension()))
    }
}

/// The `width`×`height` image made of `tiles` (each placed at its rectangle; pixels no tile
/// covers stay black). A tile that does not fit is an error, never a panic: the farm gets
/// its tiles from the network.
pub fn assemble<E: From<ImageError>>(
    width: u32,
    height: u32,
    tiles: impl IntoIterator<Item = Result<(TileRect, Image), E>>,
) -> Result<Image, E> {
    let mut image = Image::new(width, height);
    for tile in tiles {
        let (rect, tile) = tile?;
        image.try_insert(rect, &tile)?;
    }
    Ok(image)
}

/// A linear RGB image, row-major with the **top** row first (PNG order).
#[derive(Clone, Debug, PartialEq)]
pub struct Image {
    pub width: u32,
    pub height: u32,
    /// `3 * width * height` floats: r, g, b for each pixel.
    pub pixels: Vec<f32>,
}

impl Image {
    pub fn new(width: u32, height: u32) -> Self {
        Self {
            width,
            height,
            pixels: vec![0.0; 3 * width as usize * height as usize],
        }
    }

    /// Wraps raw pixels, checking the length (the farm receives them over the wire).
    pub fn from_pixels(width: u32, height: u32, pixels: Vec<f32>) -> Result<Self, ImageError> {
        let expected = 3 * width as usize * height as usize;
        if pixels.len() != expected {
            return Err(ImageError::PixelCount {
                width,
                height,
                expected,
                got: pixels.len(),
            });
        }
        Ok(Self {
            width,
            height,
            pixels,
        })
    }

    pub fn pixel(&self, x: u32, y: u32) -> [f32; 3] {
        let i = 3 * (y as usize * self.width as usize + x as usize);
        [self.pixels[i], self.pixels[i + 1], self.pixels[i + 2]]
    }

    /// Copies `tile` into this image with its top-left corner at `(rect.x, rect.y)`; panics
    /// if it does not fit (see [`Image::try_insert`]).
    pub fn insert(&mut self, rect: TileRect, tile: &Image) {
        if let Err(e) = self.try_insert(rect, tile) {
            panic!("{e}");
        }
    }

    /// Copies `tile` into this image at `rect`, if it is `rect`'s size and lies inside.
    pub fn try_insert(&mut self, rect: TileRect, tile: &Image) -> Result<(), ImageError> {
        if (rect.width, rect.height) != (tile.width, tile.height) {
            return Err(ImageError::TileSize {
                rect,
                got_width: tile.width,
                got_height: tile.height,
            });
        }
        let inside =
            |start: u32, len: u32, size: u32| start.checked_add(len).is_some_and(|end| end <= size);
        if !inside(rect.x, rect.width, self.width) || !inside(rect.y, rect.height, self.height) {
            return Err(ImageError::TileOutside {
                rect,
                width: self.width,
                height: self.height,
            });
        }
        let row_len = 3 * rect.width as usize;
        for row in 0..rect.height as usize {
            let dst = 3 * ((rect.y as usize + row) * self.width as usize + rect.x as usize);
            let src = row * row_len;
            self.pixels[dst..dst + row_len].copy_from_slice(&tile.pixels[src..src + row_len]);
        }
        Ok(())
    }

    /// Copies out the pixels of `rect`.
    pub fn crop(&self, rect: TileRect) -> Image {
        let mut out = Image::new(rect.width, rect.height);
        let row_len = 3 * rect.width as usize;
        for row in 0..rect.height as usize {
            let src = 3 * ((rect.y as usize + row) * self.width as usize + rect.x as usize);
            out.pixels[row * row_len..(row + 1) * row_len]
                .copy_from_slice(&self.pixels[src..src + row_len]);
        }
        out
    }

    /// 8-bit RGB bytes with the course's quantisation.
    pub fn to_rgb8(&self) -> Vec<u8> {
        self.pixels.iter().map(|&v| quantize(v)).collect()
    }

    /// Encodes as an 8-bit RGB PNG. Pure function of the pixels, so equal images give equal bytes.
    pub fn to_png(&self) -> Vec<u8> {
        let mut out = Vec::new();
        let encoder = image::codecs::png::PngEncoder::new(Cursor::new(&mut out));
        image::ImageEncoder::write_image(
            encoder,
            &self.to_rgb8(),
            self.width,
            self.height,
            image::ExtendedColorType::Rgb8,
        )
        .expect("encoding a PNG into memory cannot fail");
        out
    }

    pub fn write_png(&self, path: &Path) -> std::io::Result<()> {
        std::fs::write(path, self.to_png())
    }

    /// Encodes as an OpenEXR file of f32 R, G, B channels holding the pixels bit for bit
    /// (ZIP-compressed scan lines, top row first). Single-threaded, so equal images give
    /// equal bytes. Rendered images are at least 1×1 (the settings refuse less); OpenEXR has
    /// no empty image, so encoding a 0-pixel one panics.
    pub fn to_exr(&self) -> Vec<u8> {
        use exr::prelude::{Encoding, Layer, LayerAttributes, SpecificChannels, WritableImage};
        let channels = SpecificChannels::rgb(|pos: exr::math::Vec2<usize>| {
            let [r, g, b] = self.pixel(pos.x() as u32, pos.y() as u32);
            (r, g, b)
        });
        let layer = Layer::new(
            (self.width as usize, self.height as usize),
            LayerAttributes::default(),
            Encoding::SMALL_LOSSLESS,
            channels,
        );
        let mut out = Cursor::new(Vec::new());
        exr::prelude::Image::from_layer(layer)
            .write()
            .non_parallel()
            .to_buffered(&mut out)
            .expect("encoding an EXR into memory cannot fail");
        out.into_inner()
    }

    /// Encodes as a little-endian colour PFM (`PF`, scale -1), whose rows run bottom to top.
    pub fn to_pfm(&self) -> Vec<u8> {
        let header = format!("PF\n{} {}\n-1.0\n", self.width, self.height);
        let mut out = Vec::with_capacity(header.len() + 4 * self.pixels.len());
        out.extend_from_slice(header.as_bytes());
        let row_len = 3 * self.width as usize;
        if row_len > 0 {
            for row in self.pixels.chunks_exact(row_len).rev() {
                out.extend(row.iter().flat_map(|v| v.to_le_bytes()));
            }
        }
        out
    }

    /// Writes the image in the format `path`'s extension names (see [`ImageFormat::from_path`]);
    /// an unsupported extension is an `InvalidInput` error, not a PNG under a wrong name.
    pub fn save(&self, path: &Path) -> std::io::Result<()> {
        let format = ImageFormat::from_path(path).ok_or_else(|| {
            std::io::Error::new(
                std::io::ErrorKind::InvalidInput,
                "the name must end in .png, .exr or .pfm",
            )
        })?;
        std::fs::write(path, self.encode(format))
    }

    /// The image's bytes in `format`.
    pub fn encode(&self, format: ImageFormat) -> Vec<u8> {
        match format {
            ImageFormat::Png => self.to_png(),
            ImageFormat::Exr => self.to_exr(),
            ImageFormat::Pfm => self.to_pfm(),
        }
    }

    /// Decodes a little-endian colour PFM as [`Image::to_pfm`] writes it (`PF`, a negative
    /// scale, rows bottom to top): the linear f32 pixels, bit for bit.
    pub fn from_pfm_bytes(bytes: &[u8]) -> Result<Image, ImageError> {
        let mut lines = Vec::with_capacity(3);
        let mut at = 0;
        // Three header lines: "PF", "W H", the scale.
        for _ in 0..3 {
            let end = (bytes.get(at..).unwrap_or_default().iter())
                .position(|&b| b == b'\n')
                .ok_or(ImageError::Pfm("its header is cut short"))?;
            lines.push(std::str::from_utf8(&bytes[at..at + end]).unwrap_or(""));
            at += end + 1;
        }
        if lines[0] != "PF" {
            return Err(ImageError::Pfm("it does not start with PF (colour)"));
        }
        if !lines[2].parse::<f32>().is_ok_and(|scale| scale < 0.0) {
            return Err(ImageError::Pfm("its scale is not negative (little-endian)"));
        }
        let size: Vec<u32> = lines[1]
            .split_whitespace()
            .map(|v| {
                v.parse()
                    .map_err(|_| ImageError::Pfm("its size is not two numbers"))
            })
            .collect::<Result<_, _>>()?;
        let [width, height] = size[..] else {
            return Err(ImageError::Pfm("its size is not two numbers"));
        };
        let row = 3 * width as usize;
        let body = &bytes[at..];
        let floats_needed = row.checked_mul(height as usize);
        if floats_needed.and_then(|n| n.checked_mul(4)) != Some(body.len()) {
            return Err(ImageError::Pfm("its pixels do not fill its size"));
        }
        let floats: Vec<f32> = body
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes(c.try_into().expect("4 bytes")))
            .collect();
        let pixels = if row == 0 {
            Vec::new()
        } else {
            floats.chunks_exact(row).rev().flatten().copied().collect()
        };
        Image::from_pixels(width, height, pixels)
    }

    /// Decodes an 8-bit image (PNG) into linear floats value/255, as the course's loader does.
    pub fn from_png_bytes(bytes: &[u8]) -> Result<Image, ImageError> {
        let decoded = image::load_from_memory(bytes).map_err(ImageError::Decode)?;
        let rgb = decoded.to_rgb8();
        let (width, height) = rgb.dimensions();
        let pixels = rgb.as_raw().iter().map(|&b| b as f32 / 255.0).collect();
        Ok(Image {
            width,
            height,
            pixels,
        })
    }
}

/// Clamps to [0,1], scales by 255 and truncates (conventions §7.1, no gamma).
///
/// The small guard keeps an average of identical samples of, say, 0.8 at 204 even when
/// floating-point summation leaves it a hair below (conventions §0.4). NaN maps to 0.
pub fn quantize(v: f32) -> u8 {
    let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
    // The value is in [0, 255.0001], where truncation is the floor: an integer conversion
    // instead of a call to libm's `floor` per channel (x86-64's baseline has no rounding
    // instruction), which took a quarter of an 800×600 PNG's encoding.
    ((v as f64) * 255.0 + 1e-4).min(255.0) as u8
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantisation_is_the_floor_of_the_scaled_value_for_every_input() {
        let reference = |v: f32| -> u8 {
            let v = if v.is_nan() { 0.0 } else { v.clamp(0.0, 1.0) };
            ((v as f64) * 255.0 + 1e-4).floor().min(255.0) as u8
        };
        // Every 61st float from 0 to 1, every float next to a step, and the odd ones out.
        let mut inputs: Vec<f32> = (0..=1.0f32.to_bits())
            .step_by(61)
            .map(f32::from_bits)
            .collect();
        for k in 0..=255u32 {
            let step = ((k as f64 - 1e-4) / 255.0) as f32;
            let bits = step.max(0.0).to_bits();
            inputs.extend((bits.saturating_sub(4)..bits + 4).map(f32::from_bits));
        }
        inputs.extend([
            -0.0,
            -1.0,
            1.0,
            1.5,
            f32::INFINITY,
            f32::NEG_INFINITY,
            f32::NAN,
        ]);
        for v in inputs {
            assert_eq!(quantize(v), reference(v), "{v:e}");
        }
    }

    #[test]
    fn quantisation_truncates_without_gamma() {
        assert_eq!(quantize(0.7), 178);
        assert_eq!(quantize(0.8), 204);
        assert_eq!(quantize(0.043), 10);
        assert_eq!(quantize(0.349), 88);
        assert_eq!(quantize(0.1), 25);
        assert_eq!(quantize(1.5), 255);
        assert_eq!(quantize(-1.0), 0);
        assert_eq!(quantize(f32::NAN), 0);
        // An average that lands one ulp below 0.8 still gives the reference's 204.
        let avg = (0..40).map(|_| 0.8f64).sum::<f64>() / 40.0;
        assert_eq!(quantize(avg as f32), 204);
    }

    #[test]
    fn insert_and_crop_round_trip() {
        let mut img = Image::new(5, 4);
        let mut tile = Image::new(2, 3);
        for (i, p) in tile.pixels.iter_mut().enumerate() {
            *p = i as f32;
        }
        let rect = TileRect::new(3, 1, 2, 3);
        img.insert(rect, &tile);
        assert_eq!(img.crop(rect), tile);
        assert_eq!(img.pixel(0, 0), [0.0; 3]);
        assert_eq!(img.pixel(3, 1), [0.0, 1.0, 2.0]);
    }

    #[test]
    fn tiles_assemble_and_misfits_are_errors() {
        let rects = TileRect::grid(3, 2, 2);
        let tiles = rects.iter().enumerate().map(|(i, r)| {
            let mut tile = Image::new(r.width, r.height);
            tile.pixels.iter_mut().for_each(|p| *p = i as f32);
            Ok::<_, ImageError>((*r, tile))
        });
        let image = assemble(3, 2, tiles).unwrap();
        assert_eq!(image.pixel(0, 0), [0.0; 3]);
        assert_eq!(image.pixel(2, 1), [1.0; 3]);
        let outside = [Ok::<_, ImageError>((
            TileRect::new(2, 0, 2, 2),
            Image::new(2, 2),
        ))];
        assert!(matches!(
            assemble(3, 2, outside),
            Err(ImageError::TileOutside { .. })
        ));
        let wrong = [Ok::<_, ImageError>((
            TileRect::new(0, 0, 2, 2),
            Image::new(1, 2),
        ))];
        assert!(matches!(
            assemble(3, 2, wrong),
            Err(ImageError::TileSize { .. })
        ));
        let huge = TileRect::new(u32::MAX, 0, 2, 1);
        assert!(Image::new(3, 2)
            .try_insert(huge, &Image::new(2, 1))
            .is_err());
    }

    /// Values a quantised format would lose: negative, above one, tiny, NaN, infinite.
    fn linear_test_image() -> Image {
        let mut img = Image::new(5, 3);
        let specials = [-0.5, 1e-30, 7.25, f32::INFINITY, f32::NAN, 0.1, 1.0 / 3.0];
        for (i, p) in img.pixels.iter_mut().enumerate() {
            *p = specials[i % specials.len()] * (1.0 + i as f32 / 64.0);
        }
        img
    }

    fn bits(pixels: &[f32]) -> Vec<u32> {
        pixels.iter().map(|v| v.to_bits()).collect()
    }

    #[test]
    fn exr_round_trip_keeps_every_bit() {
        use exr::prelude::{ReadChannels, ReadLayers};
        let img = linear_test_image();
        let bytes = img.to_exr();
        assert_eq!(bytes, img.to_exr(), "encoding is deterministic");
        let read = exr::prelude::read()
            .no_deep_data()
            .largest_resolution_level()
            .rgb_channels(
                |size, _| Image::new(size.width() as u32, size.height() as u32),
                |back: &mut Image, pos, (r, g, b): (f32, f32, f32)| {
                    let i = 3 * (pos.y() * back.width as usize + pos.x());
                    back.pixels[i..i + 3].copy_from_slice(&[r, g, b]);
                },
            )
            .first_valid_layer()
            .all_attributes()
            .from_buffered(Cursor::new(bytes))
            .unwrap();
        let back = read.layer_data.channel_data.pixels;
        assert_eq!((back.width, back.height), (img.width, img.height));
        assert_eq!(bits(&back.pixels), bits(&img.pixels));
    }

    #[test]
    fn pfm_round_trip_keeps_every_bit() {
        let img = linear_test_image();
        let bytes = img.to_pfm();
        let header = b"PF\n5 3\n-1.0\n";
        assert_eq!(&bytes[..header.len()], header);
        let floats: Vec<f32> = bytes[header.len()..]
            .chunks_exact(4)
            .map(|b| f32::from_le_bytes(b.try_into().unwrap()))
            .collect();
        // PFM stores the bottom row first.
        let top_first: Vec<f32> = floats.chunks_exact(15).rev().flatten().copied().collect();
        assert_eq!(bits(&top_first), bits(&img.pixels));
        assert_eq!(Image::new(0, 0).to_pfm(), b"PF\n0 0\n-1.0\n");
        let back = Image::from_pfm_bytes(&bytes).unwrap();
        assert_eq!((back.width, back.height), (5, 3));
        assert_eq!(bits(&back.pixels), bits(&img.pixels));
        // Cut short, grey, big-endian or with a bad size: errors, not images.
        assert!(Image::from_pfm_bytes(&bytes[..bytes.len() - 1]).is_err());
        assert!(Image::from_pfm_bytes(&bytes[..6]).is_err());
        assert!(Image::from_pfm_bytes(b"Pf\n1 1\n-1.0\n\0\0\0\0").is_err());
        assert!(Image::from_pfm_bytes(b"PF\n1 1\n1.0\n\0\0\0\0\0\0\0\0\0\0\0\0").is_err());
        assert!(Image::from_pfm_bytes(b"PF\n1\n-1.0\n").is_err());
    }

    #[test]
    fn formats_are_named_by_extension() {
        assert_eq!(
            ImageFormat::from_path(Path::new("a/x.EXR")),
            Some(ImageFormat::Exr)
        );
        assert_eq!(
            ImageFormat::from_path(Path::new("x.pfm")),
            Some(ImageFormat::Pfm)
        );
        assert_eq!(
            ImageFormat::from_path(Path::new("x.png")),
            Some(ImageFormat::Png)
        );
        assert_eq!(ImageFormat::from_path(Path::new("x.jpg")), None);
        assert_eq!(ImageFormat::from_path(Path::new("exr")), None);
        let img = linear_test_image();
        for format in ImageFormat::ALL {
            let encoded = img.encode(format);
            assert!(!encoded.is_empty());
        }
        assert_eq!(img.encode(ImageFormat::Png), img.to_png());
    }

    #[test]
    fn png_round_trip_keeps_quantised_values() {
        let img = Image::from_pixels(2, 1, vec![0.8, 0.1, 1.0, 0.0, 0.5, 0.25]).unwrap();
        let back = Image::from_png_bytes(&img.to_png()).unwrap();
        assert_eq!(back.to_rgb8(), img.to_rgb8());
    }
}
