use glam::DVec3;

use super::Ray;

/// An axis-aligned box; the empty box has min > max.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Aabb {
    pub min: DVec3,
    pub max: DVec3,
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: DVec3::splat(f64::INFINITY),
        max: DVec3::splat(f64::NEG_INFINITY),
    };

    pub fn from_points(points: &[DVec3]) -> Aabb {
        points.iter().fold(Aabb::EMPTY, |b, &p| b.grow(p))
    }

    pub fn grow(self, p: DVec3) -> Aabb {
        Aabb {
            min: self.min.min(p),
            max: self.max.max(p),
        }
    }

    pub fn union(self, o: Aabb) -> Aabb {
        Aabb {
            min: self.min.min(o.min),
            max: self.max.max(o.max),
        }
    }

    pub fn is_empty(&self) -> bool {
        self.min.x > self.max.x || self.min.y > self.max.y || self.min.z > self.max.z
    }

    pub fn centroid(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }

    pub fn extent(&self) -> DVec3 {
        self.max - self.min
    }

    pub fn surface_area(&self) -> f64 {
        if self.is_empty() {
            return 0.0;
        }
        let e = self.extent();
        2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
    }

    pub fn corners(&self) -> [DVec3; 8] {
        let (a, b) = (self.min, self.max);
        [
            DVec3::new(a.x, a.y, a.z),
            DVec3::new(b.x, a.y, a.z),
            DVec3::new(a.x, b.y, a.z),
            DVec3::new(b.x, b.y, a.z),
            DVec3::new(a.x, a.y, b.z),
            DVec3::new(b.x, a.y, b.z),
            DVec3::new(a.x, b.y, b.z),
            DVec3::new(b.x, b.y, b.z),
        ]
    }

    /// Grows the box by a relative margin so that rounding in the primitives' own
    /// intersection tests can never put a hit outside it.
    pub fn padded(self) -> Aabb {
        let pad = (self.min.abs().max(self.max.abs())) * 1e-12 + DVec3::splat(1e-300);
        Aabb {
            min: self.min - pad,
            max: self.max + pad,
        }
    }

    /// Slab test: the entry distance if the ray meets the box within [0, t_max].
    #[inline(always)]
    pub fn hit(&self, ray: &Ray, t_max: f64) -> Option<f64> {
        self.hit_within(ray, 0.0, t_max)
    }

    /// Slab test: the entry distance if the ray meets the box within [t_min, t_max]. An axis
    /// whose distances come out NaN (0·∞: a ray along the box's face) limits nothing, as
    /// `f64::max` and `min` pass over a NaN operand.
    #[inline(always)]
    pub fn hit_within(&self, ray: &Ray, t_min: f64, t_max: f64) -> Option<f64> {
        let t0 = (self.min - ray.origin) * ray.inv_dir;
        let t1 = (self.max - ray.origin) * ray.inv_dir;
        let near = t0.min(t1).max_element().max(t_min);
        let far = t0.max(t1).min_element().min(t_max);
        (near <= far).then_some(near)
    }

    /// The squared distance from `p` to the box (0 inside it).
    pub fn distance_squared(&self, p: DVec3) -> f64 {
        (self.min - p)
            .max(p - self.max)
            .max(DVec3::ZERO)
            .length_squared()
    }
}
