//! The course's shading model (conventions §8.3 as corrected by §0): Whitted recursion with
//! ambient + shadowed diffuse, mirror reflection tinted by specular × texture, and dielectrics
//! blending reflection and Snell refraction by Schlick's approximation.

use glam::DVec3;

use crate::geometry::Ray;
use crate::photon::CausticMap;
use crate::sampler::Rng;
use crate::scene::{Light, Scene};
use crate::settings::TextureFilter;
use crate::world::Surface;

/// Radiance rays one pixel sample may trace at most. Dielectrics branch in two at every level,
/// so a deep limit could otherwise ask for 2^depth rays; the course's depth 5 needs at most 31.
pub const RAY_BUDGET_PER_SAMPLE: u32 = 4096;

/// Deepest nesting of media tracked; entries past it are not pushed (wrong colour, no crash).
const MAX_MEDIA: usize = 16;

/// Refractive indices of the media the ray is inside, outermost first, with each medium's
/// Beer's-law absorption. Copied per branch, so reflected and refracted rays each carry their
/// own.
#[derive(Clone, Copy, Debug)]
pub struct MediumStack {
    indices: [f64; MAX_MEDIA],
    absorption: [DVec3; MAX_MEDIA],
    len: usize,
}

impl MediumStack {
    pub fn new(outer: f64) -> Self {
        let mut indices = [0.0; MAX_MEDIA];
        indices[0] = outer;
        Self {
            indices,
            absorption: [DVec3::ZERO; MAX_MEDIA],
            len: 1,
        }
    }

    pub fn current(&self) -> f64 {
        self.indices[self.len - 1]
    }

    /// Absorption coefficients of the innermost medium (zero outside absorbing dielectrics).
    pub fn absorption(&self) -> DVec3 {
        self.absorption[self.len - 1]
    }

    /// Entering a medium of index `ior`.
    pub fn entered(self, ior: f64) -> Self {
        self.entered_absorbing(ior, DVec3::ZERO)
    }

    /// Entering a medium of index `ior` that absorbs `absorption` per unit distance.
    pub fn entered_absorbing(mut self, ior: f64, absorption: DVec3) -> Self {
        if self.len < MAX_MEDIA {
            self.indices[self.len] = ior;
            self.absorption[self.len] = absorption;
            self.len += 1;
        }
        self
    }

    /// Leaving a medium of index `ior`: removes its innermost entry. An exit that matches no
    /// entry (a camera inside glass, overlapping objects) leaves the stack as it is; the
    /// outermost medium is never removed.
    pub fn left(mut self, ior: f64) -> Self {
        if let Some(i) = (1..self.len).rev().find(|&i| self.indices[i] == ior) {
            self.indices.copy_within(i + 1..self.len, i);
            self.absorption.copy_within(i + 1..self.len, i);
            self.len -= 1;
        }
        self
    }
}

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

/// Moves a spawned ray's origin off the surface, to the side its direction leaves toward.
/// The offset scales with the magnitudes that bound the hit point's rounding error (its
/// coordinates and the distance travelled to it), so it works at any scene scale without a
/// fixed epsilon; at 1e-9 relative it stays far below the 0.001 gaps in stacks.scene.
/// The ray keeps its parent's `time`.
pub fn spawn_ray(
    position: DVec3,
    geometric_normal: DVec3,
    dir: DVec3,
    error_scale: f64,
    time: f64,
) -> Ray {
    let offset = 1e-9 * error_scale;
    let side = if dir.dot(geometric_normal) >= 0.0 {
        geometric_normal
    } else {
        -geometric_normal
    };
    Ray::new(position + offset * side, dir).at_time(time)
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

/// Per-sample tracing state.
pub struct Tracer<'a> {
    pub scene: &'a Scene,
    pub filter: TextureFilter,
    pub max_depth: u32,
    /// Radiance rays traced for this sample (bounded by the budget).
    pub radiance_rays: u32,
    /// Shadow rays traced for this sample.
    pub shadow_rays: u32,
    /// The sample's glossy-lobe stream (see [`crate::sampler::Stream::Gloss`]).
    pub gloss_rng: Rng,
    /// Caustic photons gathered at diffuse hits, when the render has them.
    pub caustics: Option<&'a CausticMap>,
}

impl<'a> Tracer<'a> {
    pub fn new(scene: &'a Scene, filter: TextureFilter, max_depth: u32) -> Self {
        Self {
            scene,
            filter,
            max_depth,
            radiance_rays: 0,
            shadow_rays: 0,
            gloss_rng: Rng::for_sample(0, 0, 0, 0),
            caustics: None,
        }
    }

    /// Colour seen along `ray` (unit direction) at recursion `level` (the eye ray is level 0;
    /// a ray at level max_depth contributes black).
    pub fn radiance(
        &mut self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        level: u32,
        media: MediumStack,
        rng: &mut Rng,
    ) -> DVec3 {
        let absorption = media.absorption();
        let (color, distance) = self.trace(ray, t_min, t_max, level, media, rng);
        if absorption == DVec3::ZERO {
            return color;
        }
        // Beer's law over the distance travelled inside the medium (an escaping ray
        // travels forever: exp(-σ·∞) = 0 wherever σ > 0).
        let transmittance = (-absorption * distance).exp();
        color * DVec3::select(absorption.cmpeq(DVec3::ZERO), DVec3::ONE, transmittance)
    }

    /// The colour along `ray`, and the distance to what it hit (infinite on a miss).
    fn trace(
        &mut self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        level: u32,
        media: MediumStack,
        rng: &mut Rng,
    ) -> (DVec3, f64) {
        if level >= self.max_depth || self.radiance_rays >= RAY_BUDGET_PER_SAMPLE {
            return (DVec3::ZERO, 0.0);
        }
        self.radiance_rays += 1;
        let scene = self.scene;
        let Some(hit) = scene.world.intersect(ray, t_min, t_max) else {
            return (scene.background(ray.dir), f64::INFINITY);
        };
        (self.shade(ray, &hit, level, media, rng), hit.t)
    }

    fn shade(
        &mut self,
        ray: &Ray,
        hit: &crate::world::Hit,
        level: u32,
        media: MediumStack,
        rng: &mut Rng,
    ) -> DVec3 {
        let scene = self.scene;
        let s = scene
            .world
            .surface(ray, hit, &scene.materials, &scene.textures, self.filter);
        let error_scale = s.position.abs().max_element() + hit.t;
        let d = ray.dir;

        if s.ior == 0.0 {
            // Opaque: shade the side the ray sees (conventions §0.3).
            let n = if s.normal.dot(d) > 0.0 {
                -s.normal
            } else {
                s.normal
            };
            let mut direct = scene.description.ambient * s.ambient;
            for light in &scene.lights {
                direct += self.direct_light(light, &s, n, error_scale, ray.time, rng) * s.diffuse;
            }
            if let Some(map) = self.caustics {
                direct += map.irradiance(s.position, n) * s.diffuse;
            }
            let mut color = s.texture * direct;
            let tint = s.texture * s.specular;
            if tint != DVec3::ZERO {
                let dir = glossy(reflect(d, n), n, s.glossiness, &mut self.gloss_rng);
                let reflected =
                    spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
                color +=
                    tint * self.radiance(&reflected, 0.0, f64::INFINITY, level + 1, media, rng);
            }
            return color;
        }

        // Dielectric: entering or leaving decided by the unflipped outward normal.
        let entering = s.normal.dot(d) < 0.0;
        let facing = if entering { s.normal } else { -s.normal };
        let (n1, n2, inside) = if entering {
            (
                media.current(),
                s.ior,
                media.entered_absorbing(s.ior, s.absorption),
            )
        } else {
            let after = media.left(s.ior);
            let n1 = if after.len < media.len {
                media.current()
            } else {
                s.ior
            };
            (n1, after.current(), after)
        };
        let cos_incident = d.dot(s.normal).abs().min(1.0);
        let reflectance = schlick(n1, n2, cos_incident);
        let tint = s.texture * s.specular;
        let mut color = DVec3::ZERO;
        if reflectance > 0.0 && tint != DVec3::ZERO {
            let dir = glossy(
                reflect(d, facing),
                facing,
                s.glossiness,
                &mut self.gloss_rng,
            );
            let reflected = spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
            color += reflectance
                * tint
                * self.radiance(&reflected, 0.0, f64::INFINITY, level + 1, media, rng);
        }
        if reflectance < 1.0 {
            if let Some(dir) = refract(d, facing, n1, n2) {
                let refracted =
                    spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
                color += (1.0 - reflectance)
                    * self.radiance(&refracted, 0.0, f64::INFINITY, level + 1, inside, rng);
            }
        }
        color
    }

    /// One light's shadowed, attenuated diffuse term b·c·att·max(N·L, 0) at surface `s` with
    /// shading normal `n`; a light with a radius is sampled at one uniform point of its
    /// sphere's surface. The shadow ray is traced at `time`.
    fn direct_light(
        &mut self,
        light: &Light,
        s: &Surface,
        n: DVec3,
        error_scale: f64,
        time: f64,
        rng: &mut Rng,
    ) -> DVec3 {
        let p = s.position;
        let target = if light.radius > 0.0 {
            light.position + light.radius * uniform_sphere(rng.next_f64(), rng.next_f64())
        } else {
            light.position
        };
        let to_light = target - p;
        let distance = to_light.length();
        if distance == 0.0 || !distance.is_finite() {
            return DVec3::ZERO;
        }
        let l = to_light / distance;
        let cos = n.dot(l);
        if cos.is_nan() || cos <= 0.0 {
            return DVec3::ZERO;
        }
        let shadow = spawn_ray(p, s.geometric_normal, l, error_scale, time);
        let shadow_length = (target - shadow.origin).dot(l);
        self.shadow_rays += 1;
        if self.scene.world.occluded(&shadow, shadow_length) {
            return DVec3::ZERO;
        }
        let [a_c, a_l, a_q] = light.attenuation;
        // Clamped so that all-zero terms at zero distance stay finite.
        let attenuation = 1.0 / (a_c + a_l * distance + a_q * distance * distance).max(1e-12);
        light.color * (attenuation * cos)
    }
}

/// A uniform point on the unit sphere from two uniform numbers.
pub fn uniform_sphere(u1: f64, u2: f64) -> DVec3 {
    let z = 1.0 - 2.0 * u1;
    let r = (1.0 - z * z).max(0.0).sqrt();
    let phi = std::f64::consts::TAU * u2;
    DVec3::new(r * phi.cos(), r * phi.sin(), z)
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
    fn medium_stack_survives_unmatched_exits_and_overflow() {
        let air = MediumStack::new(1.0);
        let water = air.entered(1.33);
        let glass = water.entered(1.5);
        assert_eq!(glass.current(), 1.5);
        assert_eq!(glass.left(1.5).current(), 1.33);
        // Leaving water while still in glass (overlap) removes water, keeps glass.
        assert_eq!(glass.left(1.33).current(), 1.5);
        // An exit nothing matches, and an exit of the outer medium, change nothing.
        assert_eq!(air.left(2.0).current(), 1.0);
        assert_eq!(air.left(1.0).current(), 1.0);
        let mut deep = air;
        for _ in 0..100 {
            deep = deep.entered(1.5);
        }
        assert_eq!(deep.len, MAX_MEDIA);
    }

    #[test]
    fn absorption_follows_the_medium_it_belongs_to() {
        let sigma = DVec3::new(0.5, 0.0, 2.0);
        let air = MediumStack::new(1.0);
        let tinted = air.entered_absorbing(1.5, sigma);
        assert_eq!(tinted.absorption(), sigma);
        assert_eq!(tinted.entered(1.33).absorption(), DVec3::ZERO);
        assert_eq!(tinted.entered(1.33).left(1.33).absorption(), sigma);
        // Leaving the tinted glass from inside water that overlaps it keeps water's (none).
        assert_eq!(tinted.entered(1.33).left(1.5).absorption(), DVec3::ZERO);
        assert_eq!(tinted.left(1.5).absorption(), DVec3::ZERO);
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

    #[test]
    fn sphere_samples_are_unit_and_unbiased() {
        let mut rng = Rng::for_sample(3, 1, 2, 0);
        let mut mean = DVec3::ZERO;
        for _ in 0..20_000 {
            let p = uniform_sphere(rng.next_f64(), rng.next_f64());
            assert!((p.length() - 1.0).abs() < 1e-12);
            mean += p;
        }
        assert!((mean / 20_000.0).length() < 0.02);
    }
}
