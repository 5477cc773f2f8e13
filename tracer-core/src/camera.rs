//! The pinhole camera of conventions §3: vertical fov, aspect from the image, +X right; with
//! an aperture, a thin lens focused on a plane (depth of field).

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
    /// Lens radius; 0 is a pinhole.
    pub aperture: f64,
    /// Distance of the plane in focus, along the view direction.
    pub focus_distance: f64,
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
            aperture: 0.0,
            focus_distance: 1.0,
        }
    }

    /// The same camera with a thin lens of radius `aperture` focused at `focus_distance`.
    pub fn with_lens(self, aperture: f64, focus_distance: f64) -> Camera {
        Camera {
            aperture,
            focus_distance,
            ..self
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

    /// The thin-lens eye ray through image point (x, y) from lens point `lens` (a point of
    /// the unit disk): it leaves the aperture there and passes through the point of the focal
    /// plane that the pinhole ray meets, so only that plane stays sharp.
    #[inline]
    pub fn lens_ray(&self, x: f64, y: f64, width: f64, height: f64, lens: (f64, f64)) -> Ray {
        let pinhole = self.ray(x, y, width, height);
        let focus = pinhole.at(self.focus_distance / pinhole.dir.dot(self.forward));
        let origin = self.position + self.aperture * (lens.0 * self.right + lens.1 * self.up);
        Ray::new(origin, (focus - origin).normalize())
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
    fn lens_rays_meet_on_the_focal_plane() {
        let cam = Camera::from_orientation(DVec3::ZERO, DQuat::IDENTITY, 1.0, 0.1, 10.0, 1.0)
            .with_lens(0.5, 4.0);
        let pinhole = cam.ray(30.0, 70.0, 100.0, 100.0);
        let focus = pinhole.at(4.0 / -pinhole.dir.z);
        assert!((focus.z + 4.0).abs() < 1e-12);
        for lens in [(1.0, 0.0), (-0.3, 0.7), (0.0, -1.0)] {
            let r = cam.lens_ray(30.0, 70.0, 100.0, 100.0, lens);
            assert!(
                (r.origin.length() - 0.5 * (lens.0 * lens.0 + lens.1 * lens.1).sqrt()).abs()
                    < 1e-12
            );
            let t = (focus - r.origin).length();
            assert!((r.at(t) - focus).length() < 1e-12);
        }
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
