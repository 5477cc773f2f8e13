//! The pinhole camera of conventions §3: vertical fov, aspect from the image, +X right.

use glam::{DQuat, DVec3};

use crate::geometry::Ray;
use crate::settings::CameraOverride;

#[derive(Clone, Copy, Debug)]
pub struct Camera {
    pub position: DVec3,
    forward: DVec3,
    up: DVec3,
    right: DVec3,
    tan_half_fov: f64,
    aspect: f64,
    /// Eye-ray hits are accepted only for t in [near, far] (unit directions).
    pub near: f64,
    pub far: f64,
}

impl Camera {
    pub fn from_orientation(
        position: DVec3,
        orientation: DQuat,
        fov: f64,
        near: f64,
        far: f64,
        aspect: f64,
    ) -> Camera {
        let forward = orientation * DVec3::NEG_Z;
        let up = orientation * DVec3::Y;
        Camera {
            position,
            forward,
            up,
            right: forward.cross(up),
            tan_half_fov: (fov / 2.0).tan(),
            aspect,
            near,
            far,
        }
    }

    /// The scene camera's fov and clip planes, placed by a look-at override.
    pub fn with_override(&self, o: &CameraOverride) -> Camera {
        let position = DVec3::from_array(o.position);
        let forward = (DVec3::from_array(o.look_at) - position).normalize();
        let right = forward.cross(DVec3::from_array(o.up)).normalize();
        Camera {
            position,
            forward,
            up: right.cross(forward),
            right,
            ..*self
        }
    }

    /// The eye ray through image point (x, y), in pixels from the **bottom-left** corner.
    #[inline]
    pub fn ray(&self, x: f64, y: f64, width: f64, height: f64) -> Ray {
        let i = 2.0 * x / width - 1.0;
        let j = 2.0 * y / height - 1.0;
        let dir = self.forward + self.tan_half_fov * (j * self.up + self.aspect * i * self.right);
        Ray::new(self.position, dir.normalize())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn centre_ray_looks_down_minus_z_and_corners_follow_fov() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 1.0, 0.1, 10.0, 2.0);
        let centre = cam.ray(50.0, 25.0, 100.0, 50.0);
        assert!((centre.dir - DVec3::NEG_Z).length() < 1e-15);
        // Top edge centre: vertical half-angle = fov/2.
        let top = cam.ray(50.0, 50.0, 100.0, 50.0);
        assert!((top.dir.y.atan2(-top.dir.z) - 0.5).abs() < 1e-12);
        // Right edge: horizontal half-extent is aspect·tan(fov/2), toward +X.
        let right = cam.ray(100.0, 25.0, 100.0, 50.0);
        assert!((right.dir.x / -right.dir.z - 2.0 * 0.5f64.tan()).abs() < 1e-12);
    }

    #[test]
    fn override_looks_at_its_target() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 0.8, 0.1, 10.0, 1.0);
        let moved = cam.with_override(&CameraOverride {
            position: [5.0, 5.0, 5.0],
            look_at: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
        });
        let ray = moved.ray(0.5, 0.5, 1.0, 1.0);
        assert!((ray.dir + DVec3::ONE.normalize()).length() < 1e-12);
        assert_eq!(moved.near, 0.1);
    }
}
