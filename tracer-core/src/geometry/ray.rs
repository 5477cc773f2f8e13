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
    /// The sheared frame's axes (kx, ky, kz): rays with the same ones take a triangle's
    /// corners in the same order, so their tests can share lanes.
    #[inline(always)]
    pub fn axes(&self) -> [usize; 3] {
        [self.kx, self.ky, self.kz]
    }

    #[inline(always)]
    pub fn new(ray: &Ray) -> Self {
        // Without branches: which axis is largest, and the sign along it, change from ray to
        // ray, and the branches (and `DVec3`'s index match) mispredicted for incoherent rays.
        let d = ray.dir.extend(0.0).to_array();
        let a = ray.dir.abs();
        // The first axis of largest magnitude: x where it is at least y and z, else y where it
        // is at least z, else z.
        // (As `>=` reads them: a NaN component compares false, so y is not "at least" it.)
        let x_largest = (a.x >= a.y) & (a.x >= a.z);
        let y_at_least_z = a.y >= a.z;
        let kz = (!x_largest) as usize * (1 + (!y_at_least_z) as usize);
        // The next two axes cyclically; swapped where the direction points down z, which keeps
        // the winding (the edge functions' signs).
        const NEXT: [usize; 3] = [1, 2, 0];
        let (mut kx, mut ky) = (NEXT[kz], NEXT[NEXT[kz]]);
        let swap = (kx ^ ky) & ((d[kz & 3] < 0.0) as usize).wrapping_neg();
        kx ^= swap;
        ky ^= swap;
        let dz = d[kz & 3];
        Self {
            origin: ray.origin,
            kx,
            ky,
            kz,
            shear: DVec3::new(d[kx & 3] / dz, d[ky & 3] / dz, 1.0 / dz),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The set-up as first written, with branches: the reference the branch-free one must
    /// equal.
    fn with_branches(ray: &Ray) -> (usize, usize, usize, DVec3) {
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
        if ray.dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        let dz = ray.dir[kz];
        let shear = DVec3::new(ray.dir[kx] / dz, ray.dir[ky] / dz, 1.0 / dz);
        (kx, ky, kz, shear)
    }

    #[test]
    fn the_branch_free_set_up_is_the_branching_one() {
        // Every mix of magnitudes (ties included) and signs (zeros of both signs), plus NaN.
        let values = [0.0, -0.0, 0.5, -0.5, 1.0, -1.0, 2.0, -2.0, f64::NAN];
        let mut checked = 0;
        for &x in &values {
            for &y in &values {
                for &z in &values {
                    let ray = Ray {
                        origin: DVec3::new(1.0, 2.0, 3.0),
                        dir: DVec3::new(x, y, z),
                        inv_dir: DVec3::ONE,
                        time: 0.0,
                    };
                    let t = TriangleRay::new(&ray);
                    let (kx, ky, kz, shear) = with_branches(&ray);
                    assert_eq!(
                        (t.kx, t.ky, t.kz),
                        (kx, ky, kz),
                        "direction ({x}, {y}, {z})"
                    );
                    let bits = |v: DVec3| v.to_array().map(f64::to_bits);
                    assert_eq!(bits(t.shear), bits(shear), "direction ({x}, {y}, {z})");
                    checked += 1;
                }
            }
        }
        assert_eq!(checked, 729);
    }
}
