//! Point and spherical area lights: where a sample aims, how light falls off, and the
//! shadowed diffuse term. The caustic photons leave the lights through the same sampling.

use glam::DVec3;

use super::material::Surface;
use super::optics::spawn_ray;
use crate::sampler::{uniform_sphere, Rng};
use crate::world::{Hit, ShadowCache, World};

#[derive(Clone, Debug)]
pub struct Light {
    pub position: DVec3,
    pub color: DVec3,
    pub attenuation: [f64; 3],
    pub radius: f64,
}

impl Light {
    /// A point of the light: its centre, or for a light with a radius one uniform point of
    /// its sphere's surface (soft shadows; two numbers drawn).
    // Inlined into `direct`: as a call, its point came back through memory, on the path
    // every soft shadow ray waits on (cube 0.985, toy 0.99).
    #[inline(always)]
    pub fn sample_point(&self, rng: &mut Rng) -> DVec3 {
        if self.radius > 0.0 {
            self.position + self.radius * uniform_sphere(rng.next_f64(), rng.next_f64())
        } else {
            self.position
        }
    }

    /// Makes the random draws [`Light::sample_point`] makes, for a sample that does not need
    /// the point, so that the draws after it stay the same.
    #[inline]
    pub fn skip_sample(&self, rng: &mut Rng) {
        // Through `sample_point` itself, so the two cannot drift apart; nothing reads the
        // point, so the compiler drops its arithmetic and keeps the draws.
        let _ = self.sample_point(rng);
    }

    /// The attenuation's denominator a_c + a_l·d + a_q·d² at distance `d` (conventions §0.5),
    /// clamped so that all-zero terms at zero distance stay finite.
    #[inline]
    pub fn falloff(&self, d: f64) -> f64 {
        let [a_c, a_l, a_q] = self.attenuation;
        (a_c + a_l * d + a_q * d * d).max(1e-12)
    }

    /// This light's shadowed, attenuated diffuse term c·att·max(N·L, 0) at surface `s` with
    /// shading normal `n` (the caller multiplies by the material's diffuse colour), toward a
    /// point it draws from `rng` ([`Light::sample_point`]), and whether a shadow ray was
    /// traced for it (at `time`). `shadow` serves this light's shadow rays (see
    /// [`World::occluded_by`]); `hit` is the surface's, for what the shadow ray leaves (see
    /// [`World::leaving`]).
    #[allow(clippy::too_many_arguments)]
    pub fn direct(
        &self,
        world: &World,
        s: &Surface,
        n: DVec3,
        error_scale: f64,
        time: f64,
        rng: &mut Rng,
        shadow: &mut ShadowCache,
        hit: &Hit,
    ) -> (DVec3, bool) {
        // Drawn here rather than passed in: a point passed in comes through memory, which a
        // point light's position (no draws) need not wait on (spheres.scene 1.03).
        let aim = Aim::new(self.sample_point(rng), s.position);
        self.term(aim, world, s, n, error_scale, time, shadow, hit)
    }

    /// [`Light::direct`] along `aim`, which the caller made from a point it drew
    /// ([`Light::sample_point`]) and the surface's position.
    #[allow(clippy::too_many_arguments)]
    pub fn direct_along(
        &self,
        aim: Aim,
        world: &World,
        s: &Surface,
        n: DVec3,
        error_scale: f64,
        time: f64,
        shadow: &mut ShadowCache,
        hit: &Hit,
    ) -> (DVec3, bool) {
        self.term(aim, world, s, n, error_scale, time, shadow, hit)
    }

    /// The body of [`Light::direct`] and [`Light::direct_along`], inlined into each. Both
    /// stay out of line: `direct` calling an out-of-line `direct_along` passed the point
    /// through memory (spheres.scene 1.03), and the term inlined into `Tracer::shade` cost
    /// cube.scene what the early aim saved (0.989 against 0.946).
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn term(
        &self,
        aim: Aim,
        world: &World,
        s: &Surface,
        n: DVec3,
        error_scale: f64,
        time: f64,
        shadow: &mut ShadowCache,
        hit: &Hit,
    ) -> (DVec3, bool) {
        let Aim {
            target,
            distance,
            l,
        } = aim;
        if distance == 0.0 || !distance.is_finite() {
            return (DVec3::ZERO, false);
        }
        let cos = n.dot(l);
        if cos.is_nan() || cos <= 0.0 {
            return (DVec3::ZERO, false);
        }
        let p = s.position;
        let shadow_ray = spawn_ray(p, s.geometric_normal, l, error_scale, time);
        let shadow_length = (target - shadow_ray.origin).dot(l);
        let leaving = world.leaving(hit, l.dot(s.geometric_normal) > 0.0);
        if world.occluded_by(&shadow_ray, shadow_length, shadow, leaving) {
            return (DVec3::ZERO, true);
        }
        let attenuation = 1.0 / self.falloff(distance);
        (self.color * (attenuation * cos), true)
    }
}

/// A light's point seen from a surface point: the point, its distance and the unit direction
/// toward it (not finite where the distance is 0 or not finite; [`Light::direct`] then takes
/// nothing from the light). Needs only the hit's position, so it can be made before the rest
/// of the surface.
#[derive(Clone, Copy, Debug)]
pub struct Aim {
    target: DVec3,
    distance: f64,
    l: DVec3,
}

impl Aim {
    #[inline(always)]
    pub fn new(target: DVec3, p: DVec3) -> Aim {
        let to_light = target - p;
        let distance = to_light.length();
        Aim {
            target,
            distance,
            l: to_light / distance,
        }
    }
}
