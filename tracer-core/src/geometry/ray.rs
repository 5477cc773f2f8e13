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
        let a = ray.dir.abs();
        let kz = if a.x >= a.y && a.x >= a.z {
            0
        } else if a.y >= a.z {
            1
        } else {
            2
        };
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        // Keep the winding: swapping x and y when dir.z < 0 preserves the edge-function signs.
        if ray.dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let dz = ray.dir[kz];
        Self {
            origin: ray.origin,
            kx,
            ky,
            kz,
            shear: DVec3::new(ray.dir[kx] / dz, ray.dir[ky] / dz, 1.0 / dz),
        }
    }
}
