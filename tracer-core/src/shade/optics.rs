//! Mirror reflection, Snell refraction, Schlick's approximation, the one decision of what a
//! ray crossing a dielectric passes from and into, and the offset of spawned rays.

use glam::DVec3;

use super::medium::MediumStack;
use crate::geometry::Ray;
use crate::sampler::{uniform_sphere, Rng};

/// Schlick's approximation with cos θ of the incident ray (conventions §0.2); 1 past the
/// critical angle.
pub fn schlick(n1: f64, n2: f64, cos_incident: f64) -> f64 {
    let eta = n1 / n2;
    let sin2_t = eta * eta * (1.0 - cos_incident * cos_incident);
    if sin2_t > 1.0 {
        return 1.0;
    }
    let r0 = ((n1 - n2) / (n1 + n2)).powi(2);
    r0 + (1.0 - r0) * (1.0 - cos_incident).powi(5)
}

/// Snell refraction of unit `dir` through a surface whose unit normal `n` faces the incoming
/// ray (n·dir < 0), from index n1 into n2. None on total internal reflection.
pub fn refract(dir: DVec3, n: DVec3, n1: f64, n2: f64) -> Option<DVec3> {
    let eta = n1 / n2;
    let cos_i = -n.dot(dir);
    let sin2_t = eta * eta * (1.0 - cos_i * cos_i);
    if sin2_t > 1.0 {
        return None;
    }
    let cos_t = (1.0 - sin2_t).sqrt();
    Some((eta * dir + (eta * cos_i - cos_t) * n).normalize())
}

pub fn reflect(dir: DVec3, n: DVec3) -> DVec3 {
    dir - 2.0 * dir.dot(n) * n
}

/// The normal of an opaque surface turned toward the ray arriving along `dir`
/// (conventions §0.3: back faces are shaded with a flipped normal).
#[inline(always)]
pub fn toward_viewer(normal: DVec3, dir: DVec3) -> DVec3 {
    if normal.dot(dir) > 0.0 {
        -normal
    } else {
        normal
    }
}

/// A ray meeting a dielectric's surface: which side it comes from, the indices on either
/// side, the media beyond the surface and Schlick's reflectance.
#[derive(Clone, Copy, Debug)]
pub struct Crossing {
    /// The unit normal on the side the ray arrives from.
    pub facing: DVec3,
    pub n1: f64,
    pub n2: f64,
    /// The media a refracted ray travels in.
    pub beyond: MediumStack,
    pub reflectance: f64,
}

impl Crossing {
    /// Ray direction `dir` meets a surface with unmatched outward normal `normal` of a
    /// dielectric of index `ior` absorbing `absorption`, while inside `media`. Entering or
    /// leaving is decided by the unflipped outward normal (conventions §0.3); an exit that
    /// matches no entry of the stack passes from the object's own index.
    pub fn new(
        media: MediumStack,
        normal: DVec3,
        dir: DVec3,
        ior: f64,
        absorption: DVec3,
    ) -> Crossing {
        let entering = normal.dot(dir) < 0.0;
        let facing = if entering { normal } else { -normal };
        let (n1, n2, beyond) = if entering {
            (
                media.current(),
                ior,
                media.entered_absorbing(ior, absorption),
            )
        } else {
            let after = media.left(ior);
            let n1 = if after.depth() < media.depth() {
                media.current()
            } else {
                ior
            };
            (n1, after.current(), after)
        };
        let cos_incident = dir.dot(normal).abs().min(1.0);
        Crossing {
            facing,
            n1,
            n2,
            beyond,
            reflectance: schlick(n1, n2, cos_incident),
        }
    }

    /// The mirror direction of `dir` on this surface.
    pub fn reflected(&self, dir: DVec3) -> DVec3 {
        reflect(dir, self.facing)
    }

    /// The refracted direction of `dir`; None on total internal reflection.
    pub fn refracted(&self, dir: DVec3) -> Option<DVec3> {
        refract(dir, self.facing, self.n1, self.n2)
    }
}

/// How far a spawned ray's origin moves off the surface, relative to the magnitudes that bound
/// the hit point's rounding error. A hit point `o + t·d` is off the true surface by a few ulps
/// of (|p| + t), multiplied by the condition of a model's transform (rays are intersected in
/// the mesh's own frame); 1e-9 is about 2^22 ulps (f64::EPSILON = 2^-52) of that magnitude,
/// room for transforms of condition up to ~1e4, and still far below stacks.scene's 0.001
/// gaps. Because scenes are built relative to the eye (`scene::build`), |p| is the distance
/// from the eye, not from the world origin, so the offset no longer grows with the scene's
/// position in the world.
pub const SPAWN_OFFSET: f64 = 1e-9;

/// Moves a spawned ray's origin off the surface, to the side its direction leaves toward, by
/// [`SPAWN_OFFSET`] × `error_scale` along the geometric normal (`error_scale`: the largest
/// coordinate of the hit point plus the distance travelled to it). Each coordinate the normal
/// moves at all moves by at least one ulp (as in Ray Tracing Gems ch. 6), so an offset smaller
/// than the coordinate's spacing cannot vanish in the addition. The ray keeps its parent's
/// `time`.
#[inline(always)]
pub fn spawn_ray(
    position: DVec3,
    geometric_normal: DVec3,
    dir: DVec3,
    error_scale: f64,
    time: f64,
) -> Ray {
    let side = if dir.dot(geometric_normal) >= 0.0 {
        geometric_normal
    } else {
        -geometric_normal
    };
    let offset = SPAWN_OFFSET * error_scale * side;
    let origin = DVec3::new(
        nudge(position.x, offset.x),
        nudge(position.y, offset.y),
        nudge(position.z, offset.z),
    );
    Ray::new(origin, dir).at_time(time)
}

/// `p + offset`, but at least one ulp away from `p` in the offset's direction when the offset
/// is not zero.
#[inline(always)]
fn nudge(p: f64, offset: f64) -> f64 {
    let moved = p + offset;
    if moved != p || offset == 0.0 {
        moved
    } else if offset > 0.0 {
        p.next_up()
    } else {
        p.next_down()
    }
}

/// A mirror direction spread over a lobe: `mirror` plus a uniform point of a ball of radius
/// `glossiness`, folded back above the surface whose unit normal `n` faces the reflected side.
/// Glossiness 0 returns `mirror` unchanged and draws nothing.
#[inline(always)]
pub fn glossy(mirror: DVec3, n: DVec3, glossiness: f64, rng: &mut Rng) -> DVec3 {
    if glossiness == 0.0 {
        return mirror;
    }
    spread(mirror, n, glossiness, rng)
}

#[cold]
fn spread(mirror: DVec3, n: DVec3, glossiness: f64, rng: &mut Rng) -> DVec3 {
    let ball = uniform_sphere(rng.next_f64(), rng.next_f64()) * rng.next_f64().cbrt();
    let dir = (mirror + glossiness * ball).normalize_or(mirror);
    let below = dir.dot(n);
    if below < 0.0 {
        (dir - 2.0 * below * n).normalize_or(mirror)
    } else {
        dir
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schlick_is_r0_at_normal_incidence_and_one_past_the_critical_angle() {
        let r0 = ((1.0f64 - 1.5) / (1.0 + 1.5)).powi(2);
        assert!((schlick(1.0, 1.5, 1.0) - r0).abs() < 1e-15);
        assert!((schlick(1.5, 1.0, 1.0) - r0).abs() < 1e-15);
        assert_eq!(schlick(1.0, 1.5, 0.0), 1.0);
        // Glass to air: critical angle asin(1/1.5) ≈ 41.8°; at 45° the light cannot leave.
        assert_eq!(schlick(1.5, 1.0, 45f64.to_radians().cos()), 1.0);
        assert!(schlick(1.5, 1.0, 40f64.to_radians().cos()) < 1.0);
        assert_eq!(schlick(1.3, 1.3, 0.5), 0.5f64.powi(5));
    }

    #[test]
    fn snell_bends_toward_the_normal_entering_a_denser_medium() {
        let n = DVec3::Y;
        let angle = 30f64.to_radians();
        let d = DVec3::new(angle.sin(), -angle.cos(), 0.0);
        let t = refract(d, n, 1.0, 1.5).unwrap();
        let sin_t = t.x;
        assert!((sin_t - angle.sin() / 1.5).abs() < 1e-12);
        assert!(t.y < 0.0 && (t.length() - 1.0).abs() < 1e-12);
        // Equal indices: straight through.
        assert!((refract(d, n, 1.2, 1.2).unwrap() - d).length() < 1e-12);
        // Total internal reflection.
        let grazing = DVec3::new(60f64.to_radians().sin(), -60f64.to_radians().cos(), 0.0);
        assert!(refract(grazing, n, 1.5, 1.0).is_none());
    }

    #[test]
    fn crossings_enter_leave_and_survive_unmatched_exits() {
        let air = MediumStack::new(1.0);
        let down = DVec3::new(0.0, -1.0, 0.0);
        // Entering glass from above: air to glass, the glass pushed.
        let enter = Crossing::new(air, DVec3::Y, down, 1.5, DVec3::ZERO);
        assert_eq!((enter.n1, enter.n2), (1.0, 1.5));
        assert_eq!(enter.facing, DVec3::Y);
        assert_eq!(enter.beyond.current(), 1.5);
        // Leaving it again: glass to air, popped.
        let leave = Crossing::new(enter.beyond, DVec3::NEG_Y, down, 1.5, DVec3::ZERO);
        assert_eq!((leave.n1, leave.n2), (1.5, 1.0));
        assert_eq!(leave.facing, DVec3::Y);
        assert_eq!(leave.beyond.depth(), 1);
        // Leaving glass never entered (a camera inside it): from its own index to the air.
        let unmatched = Crossing::new(air, DVec3::NEG_Y, down, 1.5, DVec3::ZERO);
        assert_eq!((unmatched.n1, unmatched.n2), (1.5, 1.0));
        assert_eq!(unmatched.reflectance, schlick(1.5, 1.0, 1.0));
    }

    #[test]
    fn spawned_origins_leave_the_surface_toward_the_ray_by_at_least_an_ulp() {
        // A normal with a z component far too small to move z = 5 by the relative offset.
        let n = DVec3::new(0.0, 1.0, 1e-12).normalize();
        let p = DVec3::new(3.0, 1e-3, 5.0);
        let up = spawn_ray(p, n, DVec3::new(0.3, 1.0, 0.0).normalize(), 10.0, 0.5);
        assert_eq!(up.time, 0.5);
        assert!((up.origin.y - p.y - SPAWN_OFFSET * 10.0).abs() < 1e-18);
        assert_eq!(up.origin.z, p.z.next_up());
        assert_eq!(up.origin.x, p.x, "the normal does not move x");
        let down = spawn_ray(p, n, DVec3::NEG_Y, 10.0, 0.0);
        assert!((p.y - down.origin.y - SPAWN_OFFSET * 10.0).abs() < 1e-18);
        assert_eq!(down.origin.z, p.z.next_down());
        // The offset follows the error scale, not a fixed epsilon.
        let tiny = spawn_ray(p * 1e-6, n, DVec3::Y, 1e-5, 0.0);
        assert!((tiny.origin.y - 1e-9 - SPAWN_OFFSET * 1e-5).abs() < 1e-24);
    }

    #[test]
    fn gloss_zero_is_the_mirror_and_gloss_stays_above_the_surface() {
        let mut rng = Rng::for_sample(1, 2, 3, 4);
        let n = DVec3::Y;
        let mirror = DVec3::new(1.0, 0.05, 0.0).normalize();
        let before = rng.clone().next_u64();
        assert_eq!(glossy(mirror, n, 0.0, &mut rng), mirror);
        assert_eq!(rng.next_u64(), before, "glossiness 0 draws nothing");
        let mut spread = 0.0f64;
        for _ in 0..2000 {
            let d = glossy(mirror, n, 0.5, &mut rng);
            assert!(d.dot(n) >= 0.0 && (d.length() - 1.0).abs() < 1e-12);
            spread = spread.max(d.angle_between(mirror));
        }
        assert!(spread > 0.3, "a rough lobe spreads: {spread}");
    }
}
