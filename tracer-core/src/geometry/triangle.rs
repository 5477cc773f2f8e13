use glam::DVec3;

use super::TriangleRay;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TriangleHit {
    pub t: f64,
    /// Barycentric weights of vertices 0, 1 and 2.
    pub bary: [f64; 3],
}

/// Watertight ray–triangle test (Woop, Benthin, Wald 2013): edge functions evaluated in a
/// sheared frame, so a ray through a shared edge or vertex hits at least one of the triangles
/// and never slips between them. Degenerate triangles (zero determinant) are never hit.
#[inline(always)]
pub fn intersect_triangle(
    ray: &TriangleRay,
    v0: DVec3,
    v1: DVec3,
    v2: DVec3,
    t_min: f64,
    t_max: f64,
) -> Option<TriangleHit> {
    let (kx, ky, kz) = (ray.kx, ray.ky, ray.kz);
    let a = v0 - ray.origin;
    let b = v1 - ray.origin;
    let c = v2 - ray.origin;
    let s = ray.shear;
    let ax = a[kx] - s.x * a[kz];
    let ay = a[ky] - s.y * a[kz];
    let bx = b[kx] - s.x * b[kz];
    let by = b[ky] - s.y * b[kz];
    let cx = c[kx] - s.x * c[kz];
    let cy = c[ky] - s.y * c[kz];
    let u = cx * by - cy * bx;
    let v = ax * cy - ay * cx;
    let w = bx * ay - by * ax;
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 || !det.is_finite() {
        return None;
    }
    let t_scaled = u * (s.z * a[kz]) + v * (s.z * b[kz]) + w * (s.z * c[kz]);
    let t = t_scaled / det;
    if !(t > t_min && t < t_max) {
        return None;
    }
    let inv = 1.0 / det;
    Some(TriangleHit {
        t,
        bary: [u * inv, v * inv, w * inv],
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::Ray;

    fn shoot(origin: DVec3, dir: DVec3, tri: [DVec3; 3]) -> Option<TriangleHit> {
        intersect_triangle(
            &TriangleRay::new(&Ray::new(origin, dir)),
            tri[0],
            tri[1],
            tri[2],
            0.0,
            f64::INFINITY,
        )
    }

    #[test]
    fn barycentrics_and_distance() {
        let tri = [DVec3::ZERO, DVec3::X, DVec3::Y];
        let hit = shoot(DVec3::new(0.25, 0.5, 2.0), -DVec3::Z, tri).unwrap();
        assert!((hit.t - 2.0).abs() < 1e-15);
        let [b0, b1, b2] = hit.bary;
        assert!((b0 - 0.25).abs() < 1e-15 && (b1 - 0.25).abs() < 1e-15 && (b2 - 0.5).abs() < 1e-15);
        // Both sides are hit (back faces are shaded with a flipped normal).
        assert!(shoot(DVec3::new(0.25, 0.25, -2.0), DVec3::Z, tri).is_some());
        assert!(shoot(DVec3::new(1.0, 1.0, 2.0), -DVec3::Z, tri).is_none());
    }

    #[test]
    fn shared_edges_and_vertices_leave_no_gap() {
        // A fan of 6 triangles around the origin; rays through the shared edges and the centre.
        let ring: Vec<DVec3> = (0..6)
            .map(|i| {
                let a = i as f64 * std::f64::consts::TAU / 6.0 + 0.1;
                DVec3::new(a.cos() * 3.3, a.sin() * 1.7, 0.37 * a.sin())
            })
            .collect();
        let tris: Vec<[DVec3; 3]> = (0..6)
            .map(|i| [DVec3::ZERO, ring[i], ring[(i + 1) % 6]])
            .collect();
        let origin = DVec3::new(0.123, -0.456, 9.0);
        let mut targets = vec![DVec3::ZERO];
        for r in &ring {
            for k in 1..50 {
                targets.push(*r * (k as f64 / 50.0));
            }
        }
        for target in targets {
            let dir = target - origin;
            let hits = tris
                .iter()
                .filter(|t| shoot(origin, dir, **t).is_some())
                .count();
            assert!(hits >= 1, "ray through {target} slipped between triangles");
        }
    }

    #[test]
    fn degenerate_triangles_are_never_hit() {
        let flat = [DVec3::ZERO, DVec3::X, DVec3::X * 2.0];
        assert!(shoot(DVec3::new(1.0, 0.0, 1.0), -DVec3::Z, flat).is_none());
        let point = [DVec3::ONE; 3];
        assert!(shoot(DVec3::new(1.0, 1.0, 2.0), -DVec3::Z, point).is_none());
    }
}
