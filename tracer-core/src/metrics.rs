//! Image error metrics for golden tests and convergence reports.

use crate::film::Image;

/// Images that cannot be compared as asked.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MetricsError {
    #[error("image sizes differ: {0}x{1} against {2}x{3}")]
    SizeMismatch(u32, u32, u32, u32),
    #[error("{0}x{1} does not divide by {2}")]
    Indivisible(u32, u32, u32),
}

fn check_sizes(a: &Image, b: &Image) -> Result<(), MetricsError> {
    if (a.width, a.height) != (b.width, b.height) {
        return Err(MetricsError::SizeMismatch(
            a.width, a.height, b.width, b.height,
        ));
    }
    Ok(())
}

/// Root mean square error over all channels, after clamping both images to [0, 1].
pub fn rmse(a: &Image, b: &Image) -> Result<f64, MetricsError> {
    check_sizes(a, b)?;
    let sum: f64 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(&x, &y)| {
            let d = x.clamp(0.0, 1.0) as f64 - y.clamp(0.0, 1.0) as f64;
            d * d
        })
        .sum();
    Ok((sum / a.pixels.len().max(1) as f64).sqrt())
}

/// Peak signal-to-noise ratio in dB for a peak of 1.
pub fn psnr(a: &Image, b: &Image) -> Result<f64, MetricsError> {
    let e = rmse(a, b)?;
    Ok(if e == 0.0 {
        f64::INFINITY
    } else {
        -20.0 * e.log10()
    })
}

/// The small constant of relMSE: keeps dark reference pixels from dominating.
pub const REL_MSE_EPSILON: f64 = 1e-2;

/// Relative MSE: mean of (a − ref)² / (ref² + ε) over all channels, ε = [`REL_MSE_EPSILON`].
pub fn rel_mse(image: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check_sizes(image, reference)?;
    let sum: f64 = image
        .pixels
        .iter()
        .zip(&reference.pixels)
        .map(|(&x, &r)| {
            let (x, r) = (x as f64, r as f64);
            (x - r) * (x - r) / (r * r + REL_MSE_EPSILON)
        })
        .sum();
    Ok(sum / image.pixels.len().max(1) as f64)
}

/// Averages `factor`×`factor` blocks (box filter), to compare a reduced render with a
/// full-size reference. Dimensions must divide.
pub fn downsample(image: &Image, factor: u32) -> Result<Image, MetricsError> {
    if factor == 0 || !image.width.is_multiple_of(factor) || !image.height.is_multiple_of(factor) {
        return Err(MetricsError::Indivisible(image.width, image.height, factor));
    }
    let (w, h) = (image.width / factor, image.height / factor);
    let mut out = Image::new(w, h);
    let n = (factor * factor) as f32;
    for y in 0..h {
        for x in 0..w {
            let mut acc = [0.0f32; 3];
            for dy in 0..factor {
                for dx in 0..factor {
                    let p = image.pixel(x * factor + dx, y * factor + dy);
                    for c in 0..3 {
                        acc[c] += p[c];
                    }
                }
            }
            let i = 3 * (y * w + x) as usize;
            for (out, sum) in out.pixels[i..i + 3].iter_mut().zip(acc) {
                *out = sum / n;
            }
        }
    }
    Ok(out)
}

/// Mean FLIP error (NVIDIA's perceptual metric, 0 = identical) of two LDR images, each
/// quantised to 8 bits as it would be written, at the given pixels per degree (67 is the
/// metric's default viewing condition).
#[cfg(feature = "flip")]
pub fn mean_flip(test: &Image, reference: &Image) -> Result<f64, MetricsError> {
    check_sizes(test, reference)?;
    let to_flip =
        |img: &Image| nv_flip::FlipImageRgb8::with_data(img.width, img.height, &img.to_rgb8());
    let error = nv_flip::flip(
        to_flip(reference),
        to_flip(test),
        nv_flip::DEFAULT_PIXELS_PER_DEGREE,
    );
    let pool = nv_flip::FlipPool::from_image(&error);
    Ok(pool.mean() as f64)
}

/// The metrics golden tests and reports quote, for one image against a reference.
#[cfg(feature = "flip")]
#[derive(Clone, Copy, Debug)]
pub struct Comparison {
    pub rmse: f64,
    pub psnr: f64,
    pub mean_flip: f64,
}

#[cfg(feature = "flip")]
impl Comparison {
    pub fn of(image: &Image, reference: &Image) -> Result<Comparison, MetricsError> {
        Ok(Comparison {
            rmse: rmse(image, reference)?,
            psnr: psnr(image, reference)?,
            mean_flip: mean_flip(image, reference)?,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn identical_images_have_zero_error() {
        let img = Image::from_pixels(2, 1, vec![0.1, 0.2, 0.3, 0.4, 0.5, 0.6]).unwrap();
        assert_eq!(rmse(&img, &img).unwrap(), 0.0);
        assert_eq!(psnr(&img, &img).unwrap(), f64::INFINITY);
        assert_eq!(rel_mse(&img, &img).unwrap(), 0.0);
    }

    #[test]
    fn rmse_of_a_uniform_offset_is_the_offset() {
        let a = Image::from_pixels(2, 2, vec![0.5; 12]).unwrap();
        let b = Image::from_pixels(2, 2, vec![0.25; 12]).unwrap();
        assert!((rmse(&a, &b).unwrap() - 0.25).abs() < 1e-9);
        assert!((psnr(&a, &b).unwrap() - 12.0412).abs() < 1e-3);
        assert!(rmse(&a, &Image::new(1, 1)).is_err());
    }

    #[test]
    fn downsample_averages_blocks() {
        let img = Image::from_pixels(
            2,
            2,
            vec![0.0, 0.0, 0.0, 1.0, 1.0, 1.0, 0.5, 0.5, 0.5, 0.5, 0.5, 0.5],
        )
        .unwrap();
        let small = downsample(&img, 2).unwrap();
        assert_eq!(small.pixels, vec![0.5; 3]);
        assert!(downsample(&img, 3).is_err());
    }

    #[cfg(feature = "flip")]
    #[test]
    fn flip_grows_with_the_difference() {
        let base = Image::from_pixels(32, 32, vec![0.5; 32 * 32 * 3]).unwrap();
        let mut slightly = base.clone();
        let mut very = base.clone();
        for i in (0..slightly.pixels.len()).step_by(7) {
            slightly.pixels[i] = 0.55;
            very.pixels[i] = 1.0;
        }
        assert_eq!(mean_flip(&base, &base).unwrap(), 0.0);
        let small = mean_flip(&slightly, &base).unwrap();
        let large = mean_flip(&very, &base).unwrap();
        assert!(0.0 < small && small < large, "{small} {large}");
    }
}
