//! Caustics by photon mapping (issue #6): light that reaches a diffuse surface only by way of
//! mirrors and glass, which the course's model leaves dark (transparent objects cast full
//! shadows). Off unless the scene's `<caustics>` element or the render settings ask for it; a
//! render without it builds nothing and shades exactly as before.
//!
//! Only caustic paths are stored: light → one or more specular bounces (mirror reflection,
//! dielectric reflection or refraction) → a diffuse surface. Direct light stays with the
//! shadow-ray term, so the two never count the same path twice. Photons are aimed at the
//! bounding spheres of the objects that can focus light ("casters"), so none is wasted on
//! directions that cannot make a caustic.
//!
//! Determinism: the map is a pure function of (scene, photon count, radius, seed, texture
//! filter). Photon i draws from its own counter-based stream, photons are traced in parallel
//! into index-ordered slots, and the grid is sorted by a total order, so every worker and
//! thread count builds the same map and every gather sums in the same order.
//!
//! Units. The direct term lights a diffuse point with k_d·c·att(d)·cosθ: the light delivers the
//! irradiance c·att(d) to a surface facing it at distance d. The flux it sends through a solid
//! angle dω to that distance is therefore c·att(d)·d²·dω, and a photon carries
//! Φ = c·att(L)·L²·dω·throughput, with L the length of its whole (unfolded) path. With a
//! physical light (attenuation a_q only) that is the constant c·dω/a_q; through an
//! index-matched object it gives back c·att(d)·cosθ, the light the object's full shadow took
//! away. The gather adds k_d·texture·E, E = Σ Φ·K(distance), to the diffuse term just as the
//! direct term adds k_d·texture·c·att·cosθ.

use std::f64::consts::TAU;
use std::sync::Arc;

use glam::DVec3;
use rayon::prelude::*;

use crate::geometry::{Aabb, Ray};
use crate::sampler::Rng;
use crate::scene::{CausticsDesc, Scene};
use crate::settings::{CausticsSettings, RenderSettings, TextureFilter};
use crate::shade::caustics::{MapKey, Photon};
use crate::shade::{reflect, spawn_ray, toward_viewer, Crossing, Light, MediumStack, Stage};

pub use crate::shade::{CausticMap, CausticsParams};

pub use crate::settings::MAX_PHOTONS;
/// Photons emitted when neither the scene nor the settings give a count.
pub const DEFAULT_PHOTONS: u32 = 200_000;
/// Default gather radius as a fraction of the smallest caster's bounding-sphere radius: a
/// caustic's detail scales with the object that focuses it.
pub const DEFAULT_RADIUS_FRACTION: f64 = 0.05;
/// Specular bounces a photon may make (light trapped in glass by total internal reflection
/// would otherwise bounce for ever).
const MAX_BOUNCES: u32 = 12;
/// Casters aimed at one by one; past this many, photons aim at one sphere around them all,
/// since the cost of testing every cone for every photon grows with their number.
const MAX_CONES: usize = 32;
/// Photons per parallel task; where tasks split never changes the map.
const CHUNK: u32 = 4096;
/// Photon streams use pixel row u32::MAX, which no image has, so they never repeat a pixel
/// sample's numbers.
const PHOTON_ROW: u32 = u32::MAX;

impl CausticsParams {
    /// The settings win over the scene; None when caustics are off.
    pub fn resolve(scene: Option<&CausticsDesc>, settings: &CausticsSettings) -> Option<Self> {
        let asked = scene.is_some() || settings.photons.is_some() || settings.radius.is_some();
        settings.enabled.unwrap_or(asked).then(|| CausticsParams {
            photons: settings
                .photons
                .or(scene.and_then(|c| c.photons))
                .unwrap_or(DEFAULT_PHOTONS),
            radius: settings.radius.or(scene.and_then(|c| c.radius)),
        })
    }
}

/// The caustic map a render of `scene` with `settings` uses: built by the first renderer that
/// asks and shared by later ones (a worker makes a renderer per tile). None when caustics are
/// off or nothing in the scene can carry light to a diffuse surface by way of a specular one.
pub fn caustic_map(scene: &Scene, settings: &RenderSettings) -> Option<Arc<CausticMap>> {
    let params = CausticsParams::resolve(scene.description.caustics.as_ref(), &settings.caustics)?;
    let key = MapKey {
        params,
        seed: settings.seed,
        filter: settings.texture_filter,
    };
    let cached = |slot: &Option<(MapKey, Arc<CausticMap>)>| match slot {
        Some((k, map)) if *k == key => Some(map.clone()),
        _ => None,
    };
    let lock = || {
        scene
            .caustic_cache
            .0
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    };
    let found = cached(&lock());
    let map = match found {
        Some(map) => map,
        None => {
            // Built without the lock held. Renderers are made on rayon threads, and a thread
            // that waits inside the build's parallel work may be handed another renderer's
            // creation: had the lock been held, that one would wait for a lock held lower on
            // its own stack, for ever (the embedded farm's pull loops share one pool). Two
            // renderers that start together may so build the same map twice; the first one
            // stored is kept, and both are equal (the map depends on the key alone).
            let built = Arc::new(CausticMap::build(
                scene,
                &params,
                settings.seed,
                settings.texture_filter,
            ));
            let mut slot = lock();
            match cached(&slot) {
                Some(map) => map,
                None => {
                    *slot = Some((key, built.clone()));
                    built
                }
            }
        }
    };
    (!map.is_empty()).then_some(map)
}

// The map's storage and gather are shading's (`shade::caustics`); filling it is here.
impl CausticMap {
    /// Emits `params.photons` photons, shared evenly among the lights, and keeps where they land.
    pub fn build(
        scene: &Scene,
        params: &CausticsParams,
        seed: u64,
        filter: TextureFilter,
    ) -> CausticMap {
        let stage = scene.stage(filter, None);
        let casters = casters(&stage);
        let radius = params.radius.unwrap_or_else(|| {
            let smallest = casters
                .iter()
                .map(|c| c.radius)
                .fold(f64::INFINITY, f64::min);
            if smallest.is_finite() {
                smallest * DEFAULT_RADIUS_FRACTION
            } else {
                1.0
            }
        });
        if casters.is_empty() || stage.lights.is_empty() {
            return CausticMap::from_photons(Vec::new(), radius, params.photons);
        }
        let targets = if casters.len() > MAX_CONES {
            vec![Caster::around(&casters)]
        } else {
            casters
        };
        let emitter = Emitter {
            stage,
            targets: &targets,
            seed,
            photons: params.photons,
        };
        let chunks = params.photons.div_ceil(CHUNK);
        let parts: Vec<Vec<Photon>> = (0..chunks)
            .into_par_iter()
            .map(|chunk| {
                let mut out = Vec::new();
                let end = ((chunk + 1) * CHUNK).min(params.photons);
                for index in chunk * CHUNK..end {
                    emitter.trace(index, &mut out);
                }
                out
            })
            .collect();
        CausticMap::from_photons(parts.concat(), radius, params.photons)
    }
}

/// A bounding sphere of something that can reflect or refract light.
#[derive(Clone, Copy, Debug)]
struct Caster {
    center: DVec3,
    radius: f64,
}

impl Caster {
    fn from_box(b: Aabb) -> Option<Caster> {
        let radius = 0.5 * b.extent().length();
        (!b.is_empty() && b.centroid().is_finite() && radius.is_finite() && radius > 0.0).then(
            || Caster {
                center: b.centroid(),
                radius,
            },
        )
    }

    /// A sphere around all of `casters`.
    fn around(casters: &[Caster]) -> Caster {
        let b = casters.iter().fold(Aabb::EMPTY, |b, c| {
            b.grow(c.center - DVec3::splat(c.radius))
                .grow(c.center + DVec3::splat(c.radius))
        });
        Caster {
            center: b.centroid(),
            radius: 0.5 * b.extent().length(),
        }
    }
}

/// Every object with a dielectric material or a mirror tint, in the world's object order.
fn casters(stage: &Stage) -> Vec<Caster> {
    let world = stage.world;
    let focuses = |m: u32| {
        let m = &stage.materials.materials[m as usize];
        m.ior != 0.0 || m.specular != DVec3::ZERO
    };
    // A sphere's own bounding sphere: its box's would be √3 times wider and waste photons.
    let spheres = world
        .spheres
        .iter()
        .filter(|s| focuses(s.material))
        .filter_map(|s| {
            let m = s.transform.to_world.matrix3;
            let stretch = m
                .x_axis
                .length()
                .max(m.y_axis.length())
                .max(m.z_axis.length());
            let c = Caster {
                center: s.transform.to_world.translation,
                radius: s.radius * stretch,
            };
            (c.center.is_finite() && c.radius.is_finite() && c.radius > 0.0).then_some(c)
        });
    let triangles = world
        .triangles
        .iter()
        .filter(|t| t.materials.iter().any(|&m| focuses(m)))
        .map(|t| Aabb::from_points(&t.positions));
    let models = world
        .models
        .iter()
        .filter(|m| focuses(m.material))
        .map(|m| {
            m.transform
                .bounds_to_world(world.meshes[m.mesh as usize].bvh.bounds())
        });
    spheres
        .chain(triangles.chain(models).filter_map(Caster::from_box))
        .collect()
}

/// A cone of directions from a light point toward a caster.
#[derive(Clone, Copy, Debug)]
struct Cone {
    axis: DVec3,
    cos_max: f64,
    solid_angle: f64,
}

impl Cone {
    fn toward(origin: DVec3, target: &Caster) -> Cone {
        let to = target.center - origin;
        let distance = to.length();
        if distance <= target.radius {
            // The light is inside the bounding sphere: every direction may hit.
            return Cone {
                axis: DVec3::Z,
                cos_max: -1.0,
                solid_angle: 2.0 * TAU,
            };
        }
        let sin2 = (target.radius / distance).powi(2);
        let cos_max = (1.0 - sin2).max(0.0).sqrt();
        Cone {
            axis: to / distance,
            cos_max,
            // 1 − cos written as sin²/(1 + cos), exact for far, small casters.
            solid_angle: TAU * sin2 / (1.0 + cos_max),
        }
    }

    /// A uniform direction inside the cone.
    fn sample(&self, u1: f64, u2: f64) -> DVec3 {
        let one_minus_cos = u1 * (1.0 - self.cos_max);
        let cos = 1.0 - one_minus_cos;
        let sin = (one_minus_cos * (2.0 - one_minus_cos)).max(0.0).sqrt();
        let (a, b) = self.axis.any_orthonormal_pair();
        let phi = TAU * u2;
        (sin * (phi.cos() * a + phi.sin() * b) + cos * self.axis).normalize()
    }

    fn contains(&self, dir: DVec3) -> bool {
        dir.dot(self.axis) >= self.cos_max
    }
}

struct Emitter<'a> {
    stage: Stage<'a>,
    targets: &'a [Caster],
    seed: u64,
    photons: u32,
}

impl Emitter<'_> {
    /// Traces photon `index` and appends its landings on diffuse surfaces to `out`.
    fn trace(&self, index: u32, out: &mut Vec<Photon>) {
        let lights = self.stage.lights.len() as u32;
        let light = &self.stage.lights[(index % lights) as usize];
        // Photons go round-robin over the lights: light l emits ⌈(N − l)/L⌉ of them.
        let emitted = (self.photons - index % lights).div_ceil(lights);
        let mut rng = Rng::for_sample(self.seed, index, PHOTON_ROW, 0);
        let origin = light.sample_point(&mut rng);

        // Pick a cone in proportion to its solid angle, then a direction in it. Cones may
        // overlap, so the direction's density is (cones holding it)/(total solid angle).
        let mut cones = [Cone {
            axis: DVec3::Z,
            cos_max: 1.0,
            solid_angle: 0.0,
        }; MAX_CONES];
        for (cone, target) in cones.iter_mut().zip(self.targets) {
            *cone = Cone::toward(origin, target);
        }
        let cones = &cones[..self.targets.len()];
        let total: f64 = cones.iter().map(|c| c.solid_angle).sum();
        if !(total > 0.0 && total.is_finite()) {
            return;
        }
        let mut pick = rng.next_f64() * total;
        let mut chosen = cones.len() - 1;
        for (i, c) in cones.iter().enumerate() {
            if pick < c.solid_angle {
                chosen = i;
                break;
            }
            pick -= c.solid_angle;
        }
        let dir = cones[chosen].sample(rng.next_f64(), rng.next_f64());
        let holding = 1 + cones
            .iter()
            .enumerate()
            .filter(|&(i, c)| i != chosen && c.contains(dir))
            .count();
        let solid_angle = total / (holding as f64 * emitted as f64);
        self.follow(light, Ray::new(origin, dir), solid_angle, &mut rng, out);
    }

    /// Follows a photon through specular bounces, storing it at every diffuse surface it
    /// reaches after at least one of them.
    fn follow(
        &self,
        light: &Light,
        mut ray: Ray,
        solid_angle: f64,
        rng: &mut Rng,
        out: &mut Vec<Photon>,
    ) {
        let stage = &self.stage;
        let mut throughput = DVec3::ONE;
        let mut travelled = 0.0;
        let mut media = MediumStack::new(stage.outer_ior);
        for bounce in 0..MAX_BOUNCES {
            let Some(hit) = stage.world.intersect(&ray, 0.0, f64::INFINITY) else {
                return;
            };
            let s = stage.surface(&ray, &hit);
            travelled += hit.t;
            let error_scale = s.position.abs().max_element() + hit.t;
            let d = ray.dir;
            let next = if s.ior == 0.0 {
                // Opaque: the side the photon arrives on, as the camera's tracer flips it.
                let n = toward_viewer(s.normal, d);
                if bounce > 0 && s.texture * s.diffuse != DVec3::ZERO {
                    let flux = travelled * travelled * solid_angle / light.falloff(travelled);
                    let power = light.color * flux * throughput;
                    if power.is_finite() && s.position.is_finite() && n.is_finite() {
                        out.push(Photon {
                            position: s.position,
                            power: power.as_vec3().to_array(),
                            normal: n.as_vec3().to_array(),
                        });
                    }
                }
                let tint = s.texture * s.specular;
                if tint == DVec3::ZERO {
                    return;
                }
                throughput *= tint;
                reflect(d, n)
            } else {
                // The camera's dielectric decision; Russian roulette on Schlick's R picks
                // reflection or refraction without changing the photon's expected flux.
                let crossing = Crossing::new(media, s.normal, d, s.ior, s.absorption);
                if rng.next_f64() < crossing.reflectance {
                    let tint = s.texture * s.specular;
                    if tint == DVec3::ZERO {
                        return;
                    }
                    throughput *= tint;
                    crossing.reflected(d)
                } else {
                    let Some(dir) = crossing.refracted(d) else {
                        return;
                    };
                    media = crossing.beyond;
                    dir
                }
            };
            if throughput.max_element() < 1e-9 {
                return;
            }
            ray = spawn_ray(s.position, s.geometric_normal, next, error_scale, ray.time);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cone_samples_stay_inside_and_cover_the_cone() {
        let target = Caster {
            center: DVec3::new(3.0, 4.0, 0.0),
            radius: 1.0,
        };
        let cone = Cone::toward(DVec3::ZERO, &target);
        let expected = TAU * (1.0 - (1.0f64 - 1.0 / 25.0).sqrt());
        assert!((cone.solid_angle - expected).abs() < 1e-12);
        let mut rng = Rng::for_sample(1, 2, 3, 4);
        let mut widest: f64 = 1.0;
        for _ in 0..10_000 {
            let d = cone.sample(rng.next_f64(), rng.next_f64());
            assert!((d.length() - 1.0).abs() < 1e-12);
            assert!(d.dot(cone.axis) >= cone.cos_max - 1e-12);
            widest = widest.min(d.dot(cone.axis));
        }
        assert!(widest < cone.cos_max + 1e-3, "samples reach the rim");
        let inside = Cone::toward(DVec3::new(3.0, 4.5, 0.0), &target);
        assert_eq!(inside.solid_angle, 2.0 * TAU);
    }

    #[test]
    fn settings_override_the_scene_and_can_turn_caustics_off() {
        let scene = CausticsDesc {
            photons: Some(1000),
            radius: Some(0.1),
            pos: Default::default(),
        };
        let follow = CausticsSettings::default();
        assert_eq!(CausticsParams::resolve(None, &follow), None);
        assert_eq!(
            CausticsParams::resolve(Some(&scene), &follow),
            Some(CausticsParams {
                photons: 1000,
                radius: Some(0.1)
            })
        );
        let more = CausticsSettings {
            photons: Some(5000),
            ..Default::default()
        };
        assert_eq!(
            CausticsParams::resolve(None, &more),
            Some(CausticsParams {
                photons: 5000,
                radius: None
            })
        );
        let off = CausticsSettings {
            enabled: Some(false),
            ..more
        };
        assert_eq!(CausticsParams::resolve(Some(&scene), &off), None);
        let on = CausticsSettings {
            enabled: Some(true),
            ..Default::default()
        };
        assert_eq!(
            CausticsParams::resolve(None, &on).map(|p| p.photons),
            Some(DEFAULT_PHOTONS)
        );
    }
}
