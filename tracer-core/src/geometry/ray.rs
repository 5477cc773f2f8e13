use glam::DVec3;

/// A ray with its precomputed inverse direction for slab tests, and the time (in frames) it
/// samples, which only moving geometry reads.
#[derive(Clone, Copy, Debug)]
pub struct Ray {
    pub origin: DVec3,
    pub dir: DVec3,
    pub inv_dir: DVec3,
    pub time: f64,
}

impl Ray {
    #[inline(always)]
    pub fn new(origin: DVec3, dir: DVec3) -> Self {
        // A zero component would give 1/0 = inf, and inf·0 = NaN in the slab test when the origin
        // lies on a slab plane; a huge finite reciprocal keeps the test well defined. Selected
        // rather than branched on: every ray is set up here, and the three branches cost more
        // than the three divisions (the same values either way).
        let tiny = dir.abs().cmplt(DVec3::splat(1e-300));
        let inv_dir = DVec3::select(tiny, DVec3::splat(1e300).copysign(dir), DVec3::ONE / dir);
        debug_assert!(
            inv_dir.is_finite(),
            "ray direction {dir} gives a non-finite inverse"
        );
        Self {
            origin,
            dir,
            inv_dir,
            time: 0.0,
        }
    }

    /// A ray whose inverse direction the caller worked out as [`Ray::new`] does (several
    /// rays at a time, [`crate::camera::EyeRays::samples_in`]).
    #[inline(always)]
    pub(crate) fn with_inverse(origin: DVec3, dir: DVec3, inv_dir: DVec3) -> Self {
        debug_assert_eq!(Ray::new(origin, dir).inv_dir, inv_dir);
        Self {
            origin,
            dir,
            inv_dir,
            time: 0.0,
        }
    }

    /// The same ray at another time.
    #[inline(always)]
    pub fn at_time(self, time: f64) -> Self {
        Self { time, ..self }
    }

    pub fn at(&self, t: f64) -> DVec3 {
        self.origin + t * self.dir
    }
}

/// Per-ray constants of the watertight triangle test (Woop, Benthin, Wald 2013): the axis the
/// direction is largest along becomes z, and the shear maps the direction onto +z.
#[derive(Clone, Copy, Debug)]
pub struct TriangleRay {
    pub origin: DVec3,
    pub kx: usize,
    pub ky: usize,
    pub kz: usize,
    pub shear: DVec3,
}

impl TriangleRay {
    #[inline(always)]
    pub fn new(ray: &Ray) -> Self {
        // Worked out without branches: which axis is largest, and the direction's sign on it,
        // differ from ray to ray, and the branches on them mispredicted for incoherent rays.
        let a = ray.dir.abs();
        let x_largest = (a.x >= a.y) & (a.x >= a.z);
        let y_larger_than_z = a.y >= a.z;
        // 0 where x is largest, else 1 for y, 2 for z (ties as x, then y).
        let kz = (!x_largest as usize) * (2 - y_larger_than_z as usize);
        let dir = ray.dir.to_array();
        let dz = dir[kz];
        // Keep the winding: swapping x and y when dir.z < 0 preserves the edge-function signs.
        let swap = (dz < 0.0) as usize;
        let (next, after) = ((kz + 1) % 3, (kz + 2) % 3);
        let kx = next + swap * (after.wrapping_sub(next));
        let ky = after + swap * (next.wrapping_sub(after));
        Self {
            origin: ray.origin,
            kx,
            ky,
            kz,
            shear: DVec3::new(dir[kx] / dz, dir[ky] / dz, 1.0 / dz),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The branch-free axis choice picks what the plain rule picks: z is the largest |d|
    /// (ties to x, then y), x and y follow it cyclically, swapped where d·z < 0.
    #[test]
    fn the_sheared_frame_is_the_largest_axis_with_the_winding_kept() {
        let rule = |d: DVec3| {
            let a = d.abs();
            let kz = if a.x >= a.y && a.x >= a.z {
                0
            } else if a.y >= a.z {
                1
            } else {
                2
            };
            let (kx, ky) = ((kz + 1) % 3, (kz + 2) % 3);
            if d[kz] < 0.0 {
                (ky, kx, kz)
            } else {
                (kx, ky, kz)
            }
        };
        let values = [-2.0, -1.0, -0.5, -0.0, 0.0, 0.5, 1.0, 2.0];
        let mut seen = std::collections::HashSet::new();
        for x in values {
            for y in values {
                for z in values {
                    let d = DVec3::new(x, y, z);
                    if d == DVec3::ZERO {
                        continue;
                    }
                    let t = TriangleRay::new(&Ray::new(DVec3::ZERO, d));
                    assert_eq!((t.kx, t.ky, t.kz), rule(d), "direction {d}");
                    seen.insert((t.kx, t.ky, t.kz));
                }
            }
        }
        // Every permutation occurs.
        assert_eq!(seen.len(), 6);
    }
}
