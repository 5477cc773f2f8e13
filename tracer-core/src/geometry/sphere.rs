use glam::DVec3;

/// Intersects a ray (in the sphere's local frame, direction not necessarily unit) with the
/// sphere of `radius` at the origin. Returns the nearest t in (t_min, t_max).
///
/// The discriminant is computed from the distance between the centre and the ray's line
/// (Ray Tracing Gems, ch. 7), not from b² − ac, so it keeps its precision far from the origin
/// and at grazing angles; the roots come from the cancellation-free pair c/q and q/a.
#[inline]
pub fn intersect_unit_sphere_scaled(
    origin: DVec3,
    dir: DVec3,
    radius: f64,
    t_min: f64,
    t_max: f64,
) -> Option<f64> {
    let a = dir.length_squared();
    let b = origin.dot(dir);
    let c = origin.length_squared() - radius * radius;
    if c > 0.0 && b >= 0.0 && t_min >= 0.0 {
        // From outside and heading away from the centre: both roots are at t ≤ 0 (their
        // product c/a is positive, their sum −2b/a is not), and the arithmetic below keeps
        // their signs (q ≤ 0, so c/q and q/a are ≤ 0), so it would find no hit either. Rays
        // leaving a sphere's lit side (shadow rays, reflections) meet this first.
        return None;
    }
    let closest = origin - (b / a) * dir;
    let discriminant = a * (radius * radius - closest.length_squared());
    if discriminant < 0.0 {
        return None;
    }
    let q = -b - discriminant.sqrt().copysign(b);
    let (mut t0, mut t1) = (c / q, q / a);
    if q == 0.0 {
        // Origin at the centre along a null b: the roots are ±√(−c/a).
        let r = (-c / a).max(0.0).sqrt();
        (t0, t1) = (-r, r);
    }
    if t0 > t1 {
        std::mem::swap(&mut t0, &mut t1);
    }
    if t0 > t_min && t0 < t_max {
        Some(t0)
    } else if t1 > t_min && t1 < t_max {
        Some(t1)
    } else {
        None
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn rays_from_outside_hit_only_when_heading_towards_the_centre() {
        let mut next = crate::test_rng::uniform(41);
        let mut point = || DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
        let (mut towards, mut away) = (0, 0);
        for _ in 0..20_000 {
            let radius = 0.5;
            let origin = point().normalize() * (radius * 1.000_001 + 3.0 * point().length());
            let dir = point();
            let b = origin.dot(dir);
            let closest = origin - b / dir.length_squared() * dir;
            let hit = intersect_unit_sphere_scaled(origin, dir, radius, 0.0, f64::INFINITY);
            if b >= 0.0 {
                assert_eq!(hit, None, "{origin} {dir}: a hit behind the ray");
                away += 1;
            } else if closest.length() < 0.99 * radius {
                let t = hit.unwrap_or_else(|| panic!("{origin} {dir}: the sphere was missed"));
                assert!(((origin + t * dir).length() - radius).abs() < 1e-9);
                towards += 1;
            }
        }
        assert!(towards > 200 && away > 5000, "{towards} {away}");
    }

    #[test]
    fn hits_front_and_from_inside() {
        let t = intersect_unit_sphere_scaled(
            DVec3::new(0.0, 0.0, 5.0),
            -DVec3::Z,
            1.0,
            0.0,
            f64::INFINITY,
        );
        assert_eq!(t, Some(4.0));
        let t = intersect_unit_sphere_scaled(DVec3::ZERO, DVec3::X, 2.0, 0.0, f64::INFINITY);
        assert_eq!(t, Some(2.0));
        let t = intersect_unit_sphere_scaled(
            DVec3::new(0.5, 0.0, 0.0),
            DVec3::new(-2.0, 0.0, 0.0),
            1.0,
            0.0,
            f64::INFINITY,
        );
        assert_eq!(t, Some(0.75), "unnormalised directions scale t");
        assert_eq!(
            intersect_unit_sphere_scaled(
                DVec3::new(0.0, 0.0, 5.0),
                DVec3::Z,
                1.0,
                0.0,
                f64::INFINITY
            ),
            None
        );
    }

    #[test]
    fn grazing_rays_hit_or_miss_by_the_right_side() {
        let origin = DVec3::new(1.0 - 1e-9, 0.0, 10.0);
        assert!(intersect_unit_sphere_scaled(origin, -DVec3::Z, 1.0, 0.0, f64::INFINITY).is_some());
        let origin = DVec3::new(1.0 + 1e-9, 0.0, 10.0);
        assert!(intersect_unit_sphere_scaled(origin, -DVec3::Z, 1.0, 0.0, f64::INFINITY).is_none());
    }

    #[test]
    fn stays_accurate_far_from_the_origin() {
        // Seen from 1e8 away, a unit sphere's surface is still found to ~1e-8 relative.
        let far = 1e8;
        let t = intersect_unit_sphere_scaled(
            DVec3::new(0.3, 0.0, far),
            -DVec3::Z,
            1.0,
            0.0,
            f64::INFINITY,
        )
        .unwrap();
        let z = far - t;
        let expected = (1.0f64 - 0.09).sqrt();
        assert!((z - expected).abs() < 1e-7, "z = {z}, expected {expected}");
        // A near-grazing hit far away keeps its lateral position.
        let t = intersect_unit_sphere_scaled(
            DVec3::new(0.999999, 0.0, far),
            -DVec3::Z,
            1.0,
            0.0,
            f64::INFINITY,
        )
        .unwrap();
        let z = far - t;
        let expected = (1.0f64 - 0.999999f64 * 0.999999).sqrt();
        assert!((z - expected).abs() < 1e-6, "z = {z}, expected {expected}");
    }
}
