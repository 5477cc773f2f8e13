use glam::{DAffine3, DMat3, DQuat, DVec3};

use super::{Aabb, Ray};

/// World = T·R·S·local, with its inverse and normal matrix precomputed (conventions §2.3).
#[derive(Clone, Copy, Debug)]
pub struct Transform {
    pub to_world: DAffine3,
    pub to_local: DAffine3,
    /// (upper 3×3 of to_world)⁻ᵀ = R·S⁻¹; its results need re-normalising.
    pub normal_matrix: DMat3,
}

impl Transform {
    pub fn new(position: DVec3, orientation: DQuat, scale: DVec3) -> Self {
        let to_world = DAffine3::from_scale_rotation_translation(scale, orientation, position);
        // Built from the factors rather than a general inverse, so it stays exact in structure.
        let to_local = DAffine3::from_scale(1.0 / scale)
            * DAffine3::from_quat(orientation.conjugate())
            * DAffine3::from_translation(-position);
        let normal_matrix = DMat3::from_quat(orientation) * DMat3::from_diagonal(1.0 / scale);
        Self {
            to_world,
            to_local,
            normal_matrix,
        }
    }

    /// The ray in local space. The direction is not re-normalised, so distances t agree.
    /// Inlined: it runs once per ray and instance, and a call cost more than its arithmetic.
    #[inline(always)]
    pub fn ray_to_local(&self, ray: &Ray) -> Ray {
        Ray::new(
            self.to_local.transform_point3(ray.origin),
            self.to_local.transform_vector3(ray.dir),
        )
        .at_time(ray.time)
    }

    pub fn normal_to_world(&self, n: DVec3) -> DVec3 {
        (self.normal_matrix * n).normalize_or_zero()
    }

    pub fn bounds_to_world(&self, local: Aabb) -> Aabb {
        let corners = local.corners().map(|c| self.to_world.transform_point3(c));
        Aabb::from_points(&corners)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn normal_matrix_keeps_normals_perpendicular_under_non_uniform_scale() {
        let t = Transform::new(
            DVec3::new(1.0, 2.0, 3.0),
            DQuat::from_axis_angle(DVec3::new(1.0, 1.0, 0.0).normalize(), 1.56),
            DVec3::new(2.0, 1.0, 1.5),
        );
        // A plane through the origin with a tilted normal, and two vectors in it.
        let n = DVec3::new(1.0, 1.0, 1.0).normalize();
        let tangents = [DVec3::new(1.0, -1.0, 0.0), DVec3::new(0.0, 1.0, -1.0)];
        let world_n = t.normal_to_world(n);
        assert!((world_n.length() - 1.0).abs() < 1e-12);
        for tangent in tangents {
            let world_tangent = t.to_world.transform_vector3(tangent);
            assert!(world_n.dot(world_tangent).abs() < 1e-12);
        }
    }

    #[test]
    fn to_local_inverts_to_world() {
        let t = Transform::new(
            DVec3::new(-5.0, 1.5, 0.0),
            DQuat::from_axis_angle(DVec3::Y, -1.570795),
            DVec3::splat(1.5),
        );
        let p = DVec3::new(0.3, -0.7, 2.0);
        let back = t.to_local.transform_point3(t.to_world.transform_point3(p));
        assert!((back - p).length() < 1e-12);
        // A quarter turn about +X takes +Y to +Z (right-handed, conventions §2.1).
        let q = Transform::new(
            DVec3::ZERO,
            DQuat::from_axis_angle(DVec3::X, std::f64::consts::FRAC_PI_2),
            DVec3::ONE,
        );
        assert!((q.to_world.transform_vector3(DVec3::Y) - DVec3::Z).length() < 1e-12);
    }
}
