//! The course's shading model (conventions §8.3 as corrected by §0): Whitted recursion with
//! ambient + shadowed diffuse, mirror reflection tinted by specular × texture, and dielectrics
//! blending reflection and Snell refraction by Schlick's approximation.
//!
//! - [`optics`]: reflection, refraction, Schlick, the one dielectric crossing decision;
//! - [`medium`]: the refraction-index stack;
//! - [`material`]: materials and texture look-up at a hit;
//! - [`light`]: lights, area-light sampling and the shadowed diffuse term;
//! - [`caustics`]: the photon map gathered at diffuse hits (built by `photon.rs`).
//!
//! Shading sees the scene through a [`Stage`], so that this module does not depend on how a
//! scene is loaded.

pub mod caustics;
pub mod light;
pub mod material;
pub mod medium;
pub mod optics;

use glam::DVec3;

pub use caustics::{CausticCache, CausticMap, CausticsParams};
pub use light::{Aim, Light};
pub use material::{Material, Materials, Surface};
pub use medium::MediumStack;
pub use optics::{glossy, reflect, refract, schlick, spawn_ray, toward_viewer, Crossing};

use crate::geometry::Ray;
use crate::sampler::Rng;
use crate::texture::Environment;
use crate::world::{Hit, Leaving, ShadowCache, World};

/// Radiance rays one pixel sample may trace at most. Dielectrics branch in two at every level,
/// so a deep limit could otherwise ask for 2^depth rays; the course's depth 5 needs at most 31.
pub const RAY_BUDGET_PER_SAMPLE: u32 = 4096;

/// What shading sees of a scene.
#[derive(Clone, Copy, Debug)]
pub struct Stage<'a> {
    pub world: &'a World,
    pub materials: Materials<'a>,
    pub lights: &'a [Light],
    pub ambient: DVec3,
    /// Seen by rays that leave the scene, unless there is an environment map.
    pub background: DVec3,
    pub environment: Option<&'a Environment>,
    /// Refractive index of the medium the camera sits in.
    pub outer_ior: f64,
    /// Caustic photons gathered at diffuse hits, when the render has them.
    pub caustics: Option<&'a CausticMap>,
    /// Per top-level object ([`Hit::object`]), whether all its materials are opaque with a
    /// diffuse colour, so that the lights shade every hit on it.
    pub lit_objects: &'a [bool],
}

impl Stage<'_> {
    /// What a ray leaving the scene along unit `dir` sees.
    #[inline]
    pub fn background(&self, dir: DVec3) -> DVec3 {
        match self.environment {
            Some(env) => env.lookup(dir),
            None => self.background,
        }
    }

    /// The surface at `hit` along `ray`: its geometry and its material's values.
    #[inline(always)]
    pub fn surface(&self, ray: &Ray, hit: &Hit) -> Surface {
        self.materials.surface(&self.world.patch(ray, hit))
    }
}

/// How [`Tracer::sample`] finds the eye ray's hit.
#[derive(Clone, Copy, Debug)]
pub enum Eye<'s> {
    /// By the top-level walk ([`World::intersect`]), as every later ray does.
    Walk,
    /// Among these top-level slots, every one the ray can hit (an eye ray's pixel's
    /// [`World::frustum_slots`], a mirror ray's [`World::mirror_slots`]), without a traversal
    /// ([`World::intersect_among`]).
    Among(&'s [u32]),
    /// Already found, the same hit either query gives (traced in a packet with other eye
    /// rays, [`World::intersect_packet`]).
    Found(Option<Hit>),
}

/// Rays one pixel sample traced.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RayCounts {
    pub radiance: u32,
    pub shadow: u32,
}

/// Traces pixel samples through one stage; one per thread, reused sample after sample.
pub struct Tracer<'a> {
    stage: Stage<'a>,
    max_depth: u32,
    /// Rays traced for the current sample (the radiance count is bounded by the budget).
    counts: RayCounts,
    /// The sample's glossy-lobe stream (see [`crate::sampler::Stream::Gloss`]).
    gloss_rng: Rng,
    /// The camera's medium, where every eye ray starts (built once: the stack is ~0.5 kB,
    /// so rays pass it by reference and only a refraction copies it).
    outer: std::rc::Rc<MediumStack>,
    /// Each light's last shadow-ray blocker per recursion level (0, 1, deeper: hits at one
    /// level of neighbouring samples lie close together, a level apart they do not), see
    /// [`World::occluded_by`].
    shadow: Vec<ShadowCache>,
    mirrors: PixelMirrors,
    /// Whether the first two lights are spherical, so that a hit aiming early at the first
    /// aims at the second too.
    second_soft: bool,
}

/// The current pixel's eye frustum, and the top-level slots its eye rays' mirror rays off one
/// axis-aligned plane may meet ([`World::mirror_slots`]), made for the first such ray.
#[derive(Default)]
struct PixelMirrors {
    /// Apex and inward plane normals, as [`World::frustum_slots`] takes them.
    eye: Option<(DVec3, [DVec3; 4])>,
    /// The plane (axis, coordinate bits) and what its rays leave, that `slots` are for.
    plane: Option<(usize, u64, Leaving)>,
    slots: Vec<u32>,
}

/// `color` seen through `distance` of the innermost medium of `media` (infinite for a ray
/// that escapes). Read after the trace: nothing about the medium is kept across it.
#[inline(always)]
fn through(media: &MediumStack, color: DVec3, distance: f64) -> DVec3 {
    if !media.absorbs() {
        return color;
    }
    let absorption = media.absorption();
    // Beer's law over the distance travelled inside the medium (an escaping ray travels
    // forever: exp(-σ·∞) = 0 wherever σ > 0).
    let transmittance = (-absorption * distance).exp();
    color * DVec3::select(absorption.cmpeq(DVec3::ZERO), DVec3::ONE, transmittance)
}

/// Recursion levels with their own [`ShadowCache`] per light; deeper levels share the last.
const SHADOW_LEVELS: usize = 3;

impl<'a> Tracer<'a> {
    pub fn new(stage: Stage<'a>, max_depth: u32) -> Self {
        Self {
            stage,
            max_depth,
            counts: RayCounts::default(),
            gloss_rng: Rng::for_sample(0, 0, 0, 0),
            outer: std::rc::Rc::new(MediumStack::new(stage.outer_ior)),
            shadow: vec![ShadowCache::default(); stage.lights.len() * SHADOW_LEVELS],
            mirrors: PixelMirrors::default(),
            second_soft: stage.lights.len() >= 2
                && stage.lights[..2].iter().all(|l| l.radius > 0.0),
        }
    }

    /// Starts a pixel whose eye rays all leave `apex` between the planes through it with
    /// inward normals `planes` (its [`crate::camera::EyeRays::pixel_frustum`]), or None
    /// where they do not share an origin. Mirror rays of its eye rays off axis-aligned planes
    /// then test only the objects their frustum meets.
    pub fn start_pixel(&mut self, frustum: Option<(DVec3, [DVec3; 4])>) {
        self.mirrors.eye = frustum;
        self.mirrors.plane = None;
    }

    /// The colour one pixel sample sees along the eye ray `ray` (unit direction), hits
    /// accepted for t in [near, far], with the rays it traced. `rng` is the sample's main
    /// stream; `gloss` its glossy-lobe stream, needed only where a material is glossy.
    ///
    /// `eye` says how the eye ray's hit is found ([`Eye`]).
    pub fn sample(
        &mut self,
        ray: &Ray,
        near: f64,
        far: f64,
        rng: &mut Rng,
        gloss: Option<Rng>,
        eye: Eye,
    ) -> (DVec3, RayCounts) {
        if let Some(gloss) = gloss {
            self.gloss_rng = gloss;
        }
        self.counts = RayCounts::default();
        let outer = std::rc::Rc::clone(&self.outer);
        let color = self.radiance(ray, near, far, 0, &outer, rng, eye, Leaving::NOTHING);
        (color, self.counts)
    }

    /// What [`Tracer::sample`] returns for an eye ray that meets nothing, where that does not
    /// depend on the ray (no environment map): the background through the camera's medium,
    /// and the one radiance ray it counts. None where a miss sees a direction's texel.
    pub fn uniform_miss(&mut self) -> Option<(DVec3, RayCounts)> {
        if self.stage.environment.is_some() {
            return None;
        }
        // Any ray: with the hit already given as none, neither its direction nor the random
        // stream is read (the glossy stream is left as it is).
        let ray = Ray::new(DVec3::ZERO, DVec3::Z);
        let mut rng = Rng::from_state(0);
        Some(self.sample(&ray, 0.0, f64::INFINITY, &mut rng, None, Eye::Found(None)))
    }

    /// Colour seen along `ray` (unit direction) at recursion `level` (the eye ray is level 0;
    /// a ray at level max_depth contributes black). `eye`: how the eye ray's hit is found
    /// (see [`Tracer::sample`]), [`Eye::Walk`] past level 0.
    #[allow(clippy::too_many_arguments)]
    fn radiance(
        &mut self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        level: u32,
        media: &MediumStack,
        rng: &mut Rng,
        eye: Eye,
        leaving: Leaving,
    ) -> DVec3 {
        let (color, distance) = self.trace(ray, t_min, t_max, level, media, rng, eye, leaving);
        through(media, color, distance)
    }

    /// What [`Tracer::radiance`] returns at `level` for a ray along unit `dir` through
    /// `media` that is known to meet nothing: the background (or environment) along `dir`
    /// through the medium, the ray counted as traced, black past the depth or the budget.
    #[inline(never)]
    fn escaped(&mut self, dir: DVec3, level: u32, media: &MediumStack) -> DVec3 {
        if !self.count_ray(level) {
            return DVec3::ZERO;
        }
        through(media, self.stage.background(dir), f64::INFINITY)
    }

    /// Counts a radiance ray at `level` as traced, or returns false where it would see
    /// black: past the depth, or past the sample's ray budget (then it is not counted).
    #[inline(always)]
    fn count_ray(&mut self, level: u32) -> bool {
        if level >= self.max_depth || self.counts.radiance >= RAY_BUDGET_PER_SAMPLE {
            return false;
        }
        self.counts.radiance += 1;
        true
    }

    /// The colour along `ray`, and the distance to what it hit (infinite on a miss).
    #[allow(clippy::too_many_arguments)]
    fn trace(
        &mut self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        level: u32,
        media: &MediumStack,
        rng: &mut Rng,
        eye: Eye,
        leaving: Leaving,
    ) -> (DVec3, f64) {
        if !self.count_ray(level) {
            return (DVec3::ZERO, 0.0);
        }
        let world = self.stage.world;
        let hit = match eye {
            Eye::Walk => world.intersect_leaving(ray, t_min, t_max, leaving),
            Eye::Among(slots) => world.intersect_among(ray, t_min, t_max, slots),
            Eye::Found(hit) => hit,
        };
        let Some(hit) = hit else {
            return (self.stage.background(ray.dir), f64::INFINITY);
        };
        (self.shade(ray, &hit, level, media, rng), hit.t)
    }

    fn shade(
        &mut self,
        ray: &Ray,
        hit: &Hit,
        level: u32,
        media: &MediumStack,
        rng: &mut Rng,
    ) -> DVec3 {
        // The fields shading reads, each copied alone: a copy of the whole stage was made in
        // memory at every hit (about 18 instructions), for the closures that borrowed it.
        let Stage {
            world,
            lights,
            ambient,
            caustics,
            lit_objects,
            ..
        } = self.stage;
        // At a hit on an object the lights shade, the first light's point is drawn before
        // the surface is made, from a copy of the stream: its draws and arithmetic then
        // overlap the surface's instead of waiting for it, and the stream takes the copy's
        // state where the light is shaded, so every sample draws what it drew before.
        // (Drawn at every hit, the points wasted at mirrors and glass made stacks.scene
        // 1.5% slower; a point light has no draws or arithmetic to overlap.)
        // The direction toward it needs only the hit's position, so it is found early too.
        // Where the second light is spherical too, its point follows the first's (kept in
        // two plain options: an array of them cost the one-light scenes what they saved).
        // `s.position` will be this very point (`World::patch` makes it so); made here, it comes
        // from registers instead of a load that waits on the patch's narrower stores (that wait
        // was 14-18% of this function's time).
        let position = ray.at(hit.t);
        let mut after_early = rng.clone();
        let first_aim = lights
            .first()
            .filter(|light| light.radius > 0.0 && lit_objects[hit.object() as usize])
            .map(|light| Aim::new(light.sample_point(&mut after_early), position));
        let second_aim = match first_aim {
            Some(_) if self.second_soft => {
                Some(Aim::new(lights[1].sample_point(&mut after_early), position))
            }
            _ => None,
        };
        let s = self.stage.surface(ray, hit);
        // What a ray spawned here leaves, by the side it heads to (found for each ray: both
        // sides' found up front were stored narrow and copied wide, which stalled).
        let leaving_toward = |dir: DVec3| world.leaving(hit, dir.dot(s.geometric_normal) > 0.0);
        let error_scale = position.abs().max_element() + hit.t;
        // A ray spawned at the last level would see black (`Tracer::trace`), so none is made
        // there; the glossy draw of a reflection still is, so that the sample's later draws
        // stay in place.
        let last = level + 1 >= self.max_depth;
        let d = ray.dir;

        if s.ior == 0.0 {
            // Opaque: shade the side the ray sees (conventions §0.3).
            let n = toward_viewer(s.normal, d);
            let mut direct = ambient * s.ambient;
            let shadow_level = (level as usize).min(SHADOW_LEVELS - 1);
            // A surface without a diffuse colour (a perfect mirror) takes nothing from the
            // lights or the caustics: each term is a finite value times zero. Its shadow rays
            // are not traced and no photons are gathered; each light still makes its random
            // draws, so the sample's later draws are unchanged.
            // The lights aimed at early have made their draws on the copy (none where no light
            // was: the copy is then the stream as it was).
            *rng = after_early;
            if s.diffuse == DVec3::ZERO {
                let drawn = first_aim.is_some() as usize + second_aim.is_some() as usize;
                let rest = lights.iter().skip(drawn);
                rest.for_each(|light| light.skip_sample(rng));
            } else {
                for (i, light) in lights.iter().enumerate() {
                    let cache = &mut self.shadow[i * SHADOW_LEVELS + shadow_level];
                    let time = ray.time;
                    let early = match i {
                        0 => first_aim,
                        1 => second_aim,
                        _ => None,
                    };
                    let (light, traced) = match early {
                        Some(aim) => {
                            light.direct_along(aim, world, &s, n, error_scale, time, cache, hit)
                        }
                        None => light.direct(world, &s, n, error_scale, time, rng, cache, hit),
                    };
                    self.counts.shadow += traced as u32;
                    direct += light * s.diffuse;
                }
                if let Some(map) = caustics {
                    direct += map.irradiance(s.position, n) * s.diffuse;
                }
            }
            let mut color = s.texture * direct;
            let tint = s.texture * s.specular;
            if tint != DVec3::ZERO {
                let dir = glossy(reflect(d, n), n, s.glossiness, &mut self.gloss_rng);
                if last {
                    return color;
                }
                let reflected =
                    spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
                let leaving = leaving_toward(dir);
                // An eye ray's perfect mirror ray off an axis-aligned plane: among its pixel's
                // mirror slots, made for the first such ray (taken out of `self` while the
                // ray is traced; deeper levels never read them).
                let plane = match self.mirrors.eye {
                    Some(_) if level == 0 && s.glossiness == 0.0 => world.mirror_plane(hit),
                    _ => None,
                };
                let mut slots = Vec::new();
                if let (Some((axis, c)), Some((apex, planes))) = (plane, &self.mirrors.eye) {
                    slots = std::mem::take(&mut self.mirrors.slots);
                    let key = Some((axis, c.to_bits(), leaving));
                    if self.mirrors.plane != key {
                        world.mirror_slots((axis, c), (*apex, planes), leaving, &mut slots);
                        self.mirrors.plane = key;
                    }
                }
                let eye = match plane {
                    Some(_) => Eye::Among(&slots),
                    None => Eye::Walk,
                };
                // No slot: the ray meets nothing and sees what lies along `dir`, as `trace`
                // finds it, without being traced (most of cube.scene's floor reflects only
                // the sky). (Made only where it is traced, its set-up moved the compiler's
                // code for every other hit: 1% more instructions on spheres.scene.)
                let seen = if plane.is_some() && slots.is_empty() {
                    self.escaped(dir, level + 1, media)
                } else {
                    let (near, far, next) = (0.0, f64::INFINITY, level + 1);
                    self.radiance(&reflected, near, far, next, media, rng, eye, leaving)
                };
                color += tint * seen;
                if plane.is_some() {
                    self.mirrors.slots = slots;
                }
            }
            return color;
        }

        let crossing = Crossing::new(*media, s.normal, d, s.ior, s.absorption);
        let reflectance = crossing.reflectance;
        let tint = s.texture * s.specular;
        let mut color = DVec3::ZERO;
        if reflectance > 0.0 && tint != DVec3::ZERO {
            let dir = glossy(
                crossing.reflected(d),
                crossing.facing,
                s.glossiness,
                &mut self.gloss_rng,
            );
            if last {
                return color;
            }
            let reflected = spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
            color += reflectance
                * tint
                * self.radiance(
                    &reflected,
                    0.0,
                    f64::INFINITY,
                    level + 1,
                    media,
                    rng,
                    Eye::Walk,
                    leaving_toward(dir),
                );
        }
        if reflectance < 1.0 && !last {
            if let Some(dir) = crossing.refracted(d) {
                let refracted =
                    spawn_ray(s.position, s.geometric_normal, dir, error_scale, ray.time);
                color += (1.0 - reflectance)
                    * self.radiance(
                        &refracted,
                        0.0,
                        f64::INFINITY,
                        level + 1,
                        &crossing.beyond,
                        rng,
                        Eye::Walk,
                        leaving_toward(dir),
                    );
            }
        }
        color
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::texture::TextureFilter;
    use crate::Scene;

    /// The scene `xml` describes (written to a file first: scenes load from files).
    fn load(xml: &str) -> Scene {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("test.scene");
        std::fs::write(&path, xml).unwrap();
        Scene::load(&path).unwrap_or_else(|e| panic!("{e}"))
    }

    #[test]
    fn drawing_the_first_lights_point_early_changes_no_sample() {
        // A soft light over a matte sphere, a glass sphere, a mirror, a matte scene triangle
        // and one blending matte and glass: only the matte objects are lit, and their hits
        // draw the light's point before the surface is made.
        let xml = r#"<scene>
    <camera><fov v="0.9"/><near_clip v=".01"/><far_clip v="100"/>
        <position x="0" y="0" z="0"/><orientation a="0" x="1" y="0" z="0"/></camera>
    <background_color r="0.2" g="0.3" b="0.5"/>
    <refractive_index v="1"/>
    <ambient_light r="0.1" g="0.1" b="0.1"/>
    <point_light><position x="1" y="5" z="-4"/><color r="1" g="1" b="1"/><radius v="0.7"/>
    </point_light>
    <point_light><position x="-3" y="2" z="0"/><color r="0.5" g="0.5" b="0.5"/><radius v="0.3"/>
    </point_light>
    <material name="matte"><diffuse r="0.8" g="0.7" b="0.2"/><specular r="0.2" g="0.2" b="0.2"/>
        <refractive_index v="0"/></material>
    <material name="glass"><diffuse r="0.1" g="0.1" b="0.1"/><specular r="1" g="1" b="1"/>
        <refractive_index v="1.5"/></material>
    <material name="mirror"><diffuse r="0" g="0" b="0"/><specular r="1" g="1" b="1"/>
        <refractive_index v="0"/></material>
    <vertex name="a" material="matte"><position x="-6" y="-1.5" z="-2"/>
        <normal x="0" y="1" z="0"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="b" material="matte"><position x="6" y="-1.5" z="-2"/>
        <normal x="0" y="1" z="0"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="c" material="matte"><position x="0" y="-1.5" z="-14"/>
        <normal x="0" y="1" z="0"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="d" material="glass"><position x="-6" y="3" z="-14"/>
        <normal x="0" y="1" z="0"/><tex_coord u="0" v="0"/></vertex>
    <sphere material="matte"><position x="-1.6" y="0" z="-6"/><radius v="1"/></sphere>
    <sphere material="glass"><position x="1.6" y="0" z="-6"/><radius v="1"/></sphere>
    <sphere material="mirror"><position x="0" y="1.5" z="-8"/><radius v="1"/></sphere>
    <triangle><position x="0" y="0" z="0"/><vertex name="a"/><vertex name="b"/><vertex name="c"/></triangle>
    <triangle><position x="0" y="0" z="0"/><vertex name="a"/><vertex name="c"/><vertex name="d"/></triangle>
</scene>"#;
        let scene = load(xml);
        let stage = scene.stage(TextureFilter::Nearest, None);
        let mut lit = stage.lit_objects.to_vec();
        lit.sort();
        assert_eq!(
            lit,
            [false, false, false, true, true],
            "two lit objects of five"
        );
        let none_lit = vec![false; stage.lit_objects.len()];
        let late = Stage {
            lit_objects: &none_lit,
            ..stage
        };
        let (mut early, mut late) = (Tracer::new(stage, 5), Tracer::new(late, 5));
        let mut lit_hits = 0;
        for y in 0..24 {
            for x in 0..32 {
                let dir = DVec3::new(x as f64 / 16.0 - 1.0, 0.6 - y as f64 / 20.0, -1.0);
                let ray = Ray::new(DVec3::ZERO, dir.normalize());
                let seed = (y * 32 + x) as u64;
                let (mut rng_a, mut rng_b) = (Rng::from_state(seed), Rng::from_state(seed));
                let a = early.sample(&ray, 0.0, f64::INFINITY, &mut rng_a, None, Eye::Walk);
                let b = late.sample(&ray, 0.0, f64::INFINITY, &mut rng_b, None, Eye::Walk);
                assert_eq!(a, b, "pixel ({x}, {y})");
                assert_eq!(rng_a.next_u64(), rng_b.next_u64(), "pixel ({x}, {y})");
                let hit = stage.world.intersect(&ray, 0.0, f64::INFINITY);
                lit_hits += hit.is_some_and(|h| stage.lit_objects[h.object() as usize]) as u32;
            }
        }
        assert!(lit_hits > 100, "{lit_hits} eye rays hit lit objects");
    }

    #[test]
    fn the_last_level_traces_no_spawned_ray_but_makes_its_glossy_draw() {
        // Two large, nearly flat glossy mirrors facing each other across the camera: the eye
        // ray meets the one ahead, its reflection the one behind, and so on, with a glossy
        // draw (three numbers) at every hit. At the last level the spawned ray is not made,
        // but its draw is.
        let xml = r#"<scene>
    <camera><fov v="0.5"/><near_clip v=".01"/><far_clip v="100"/>
        <position x="0" y="0" z="0"/><orientation a="0" x="1" y="0" z="0"/></camera>
    <background_color r="0.2" g="0.3" b="0.5"/>
    <refractive_index v="1"/>
    <ambient_light r="0" g="0" b="0"/>
    <material name="gloss"><ambient r="0" g="0" b="0"/><diffuse r="0" g="0" b="0"/>
        <specular r="0.9" g="0.9" b="0.9"/><glossiness v="0.01"/>
        <refractive_index v="0"/></material>
    <sphere material="gloss"><position x="0" y="0" z="-60"/><radius v="50"/></sphere>
    <sphere material="gloss"><position x="0" y="0" z="60"/><radius v="50"/></sphere>
</scene>"#;
        // One sample straight ahead at `depth`: its colour, its radiance rays, and whether its
        // glossy stream ends `draws` numbers past its seed.
        let sample = |scene: &Scene, depth: u32, draws: u32| {
            let mut tracer = Tracer::new(scene.stage(TextureFilter::Nearest, None), depth);
            let gloss = Rng::from_state(11);
            let ray = Ray::new(DVec3::ZERO, DVec3::new(0.0, 0.0, -1.0));
            let mut rng = Rng::from_state(5);
            let (color, counts) = tracer.sample(
                &ray,
                0.0,
                f64::INFINITY,
                &mut rng,
                Some(gloss.clone()),
                Eye::Walk,
            );
            let mut expected = gloss;
            for _ in 0..draws {
                expected.next_f64();
            }
            let drew = tracer.gloss_rng.next_u64() == expected.next_u64();
            (color, counts.radiance, drew)
        };
        let mirrors = load(xml);
        for depth in 1..=5u32 {
            // Every level hits a mirror: `depth` radiance rays, none escaping to the sky, and
            // one glossy draw per hit, the last level's included.
            let (color, rays, drew) = sample(&mirrors, depth, 3 * depth);
            assert_eq!(
                (color, rays, drew),
                (DVec3::ZERO, depth, true),
                "depth {depth}"
            );
        }

        // A glossy glass ball met at the last level (depth 1): it reflects a little (Schlick),
        // so its reflected ray's draw is made though neither ray is.
        let glass = load(
            &xml.replace(
                "<refractive_index v=\"0\"/></material>",
                "<refractive_index v=\"1.5\"/></material>",
            )
            .replace(
                "<position x=\"0\" y=\"0\" z=\"60\"/>",
                "<position x=\"0\" y=\"0\" z=\"600\"/>",
            ),
        );
        let (_, rays, drew) = sample(&glass, 1, 3);
        assert_eq!((rays, drew), (1, true));
    }

    #[test]
    fn a_surface_without_diffuse_colour_traces_no_shadow_ray_but_keeps_its_draws() {
        // A perfect mirror (diffuse 0) and a matte sphere, lit by a spherical light. The camera
        // sits at the origin, so the scene's coordinates are the world's (built eye-relative).
        let xml = r#"<scene>
    <camera><fov v="0.8"/><near_clip v=".01"/><far_clip v="100"/>
        <position x="0" y="0" z="0"/><orientation a="0" x="1" y="0" z="0"/></camera>
    <background_color r="0.2" g="0.3" b="0.5"/>
    <refractive_index v="1"/>
    <ambient_light r="0.1" g="0.1" b="0.1"/>
    <point_light><position x="3" y="4" z="-1"/><color r="1" g="1" b="1"/><radius v="0.5"/>
    </point_light>
    <material name="mirror"><ambient r="0" g="0" b="0"/><diffuse r="0" g="0" b="0"/>
        <specular r="1" g="1" b="1"/><refractive_index v="0"/></material>
    <material name="matte"><diffuse r="0.8" g="0.2" b="0.2"/><refractive_index v="0"/></material>
    <sphere material="mirror"><position x="0" y="0" z="-6"/><radius v="1"/></sphere>
    <sphere material="matte"><position x="4" y="0" z="-6"/><radius v="1"/></sphere>
</scene>"#;
        let scene = load(xml);
        let stage = scene.stage(TextureFilter::Nearest, None);
        let light = &stage.lights[0];
        let mut tracer = Tracer::new(stage, 5);
        let trace = |tracer: &mut Tracer, origin: DVec3, toward: DVec3| {
            let ray = Ray::new(origin, (toward - origin).normalize());
            let mut rng = Rng::from_state(3);
            let (color, counts) =
                tracer.sample(&ray, 0.0, f64::INFINITY, &mut rng, None, Eye::Walk);
            (color, counts, rng)
        };
        let draws = |n: usize| {
            let mut rng = Rng::from_state(3);
            for _ in 0..n {
                light.sample_point(&mut rng);
            }
            rng
        };

        // Head-on at the mirror: its ray comes straight back past the camera to the sky.
        let (color, counts, mut rng) = trace(&mut tracer, DVec3::ZERO, DVec3::new(0.0, 0.0, -6.0));
        assert_eq!((counts.radiance, counts.shadow), (2, 0));
        assert_eq!(color, stage.background);
        assert_eq!(rng.next_u64(), draws(1).next_u64());

        // At the matte sphere's lit side: its shadow ray is traced, with the same draws.
        let (_, counts, mut rng) = trace(
            &mut tracer,
            DVec3::new(4.0, 0.5, 0.0),
            DVec3::new(4.3, 0.3, -5.1),
        );
        assert_eq!((counts.radiance, counts.shadow), (1, 1));
        assert_eq!(rng.next_u64(), draws(1).next_u64());

        // Off the mirror onto the matte sphere: the mirror's draws come first, so the matte
        // hit's light point is the second, as when the mirror's shadow ray was traced.
        let (color, counts, mut rng) =
            trace(&mut tracer, DVec3::ZERO, DVec3::new(0.64, 0.0, -5.24));
        assert_eq!((counts.radiance, counts.shadow), (2, 1));
        assert_ne!(color, stage.background);
        assert_eq!(rng.next_u64(), draws(2).next_u64());
    }
}
