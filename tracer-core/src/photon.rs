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

use std::collections::HashMap;
use std::f64::consts::{PI, TAU};
use std::fmt;
use std::sync::{Arc, Mutex};

use glam::DVec3;
use rayon::prelude::*;

use crate::geometry::{Aabb, Ray};
use crate::sampler::Rng;
use crate::scene::{CausticsDesc, Light, Scene};
use crate::settings::{CausticsSettings, RenderSettings, TextureFilter};
use crate::shade::{reflect, refract, schlick, spawn_ray, uniform_sphere};

/// Most photons one map may emit (each stored photon takes 48 bytes).
pub const MAX_PHOTONS: u32 = 5_000_000;
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
/// A photon counts only on surfaces facing within 60° of the one it landed on, so light does
/// not leak round corners.
const MIN_NORMAL_COS: f64 = 0.5;
/// Photon streams use pixel row u32::MAX, which no image has, so they never repeat a pixel
/// sample's numbers.
const PHOTON_ROW: u32 = u32::MAX;
/// Deepest nesting of media a photon tracks (as the camera's tracer does).
const MAX_MEDIA: usize = 16;

/// What a render asks of the caustic map once the scene and the settings are combined.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct CausticsParams {
    pub photons: u32,
    /// Gather radius; None derives it from the casters ([`DEFAULT_RADIUS_FRACTION`]).
    pub radius: Option<f64>,
}

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
    // Held while building, so that concurrent renderers wait for one map instead of each
    // building their own. A panic mid-build leaves the slot as it was.
    let mut slot = scene
        .caustic_cache
        .0
        .lock()
        .unwrap_or_else(|poisoned| poisoned.into_inner());
    let map = match &*slot {
        Some((k, map)) if *k == key => map.clone(),
        _ => {
            let map = Arc::new(CausticMap::build(
                scene,
                &params,
                settings.seed,
                settings.texture_filter,
            ));
            *slot = Some((key, map.clone()));
            map
        }
    };
    (!map.is_empty()).then_some(map)
}

/// Everything a map depends on besides the scene.
#[derive(Clone, Copy, Debug, PartialEq)]
struct MapKey {
    params: CausticsParams,
    seed: u64,
    filter: TextureFilter,
}

/// The last map built for a scene. A cloned scene starts with an empty cache, so a clone that
/// is then changed can never be handed a stale map.
#[derive(Default)]
pub struct CausticCache(Mutex<Option<(MapKey, Arc<CausticMap>)>>);

impl Clone for CausticCache {
    fn clone(&self) -> Self {
        Self::default()
    }
}

impl fmt::Debug for CausticCache {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let built = self.0.lock().map(|s| s.is_some()).unwrap_or(false);
        f.debug_struct("CausticCache")
            .field("built", &built)
            .finish()
    }
}

/// One photon's landing: where, how much flux, and the normal of the side it arrived on.
#[derive(Clone, Copy, Debug)]
struct Photon {
    position: DVec3,
    power: [f32; 3],
    normal: [f32; 3],
}

/// Caustic photons in a uniform grid of cells twice the gather radius wide, so that a gather
/// looks at no more than 2×2×2 cells.
pub struct CausticMap {
    radius: f64,
    cell: f64,
    /// Sorted by cell, then by emission order.
    photons: Vec<Photon>,
    cells: HashMap<[i32; 3], (u32, u32)>,
    emitted: u32,
}

impl fmt::Debug for CausticMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.debug_struct("CausticMap")
            .field("radius", &self.radius)
            .field("emitted", &self.emitted)
            .field("stored", &self.photons.len())
            .finish()
    }
}

impl CausticMap {
    /// Emits `params.photons` photons, shared evenly among the lights, and keeps where they land.
    pub fn build(
        scene: &Scene,
        params: &CausticsParams,
        seed: u64,
        filter: TextureFilter,
    ) -> CausticMap {
        let casters = casters(scene);
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
        if casters.is_empty() || scene.lights.is_empty() {
            return CausticMap::from_photons(Vec::new(), radius, params.photons);
        }
        let targets = if casters.len() > MAX_CONES {
            vec![Caster::around(&casters)]
        } else {
            casters
        };
        let emitter = Emitter {
            scene,
            targets: &targets,
            filter,
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

    fn from_photons(photons: Vec<Photon>, radius: f64, emitted: u32) -> CausticMap {
        let cell = 2.0 * radius;
        let key_of = |p: DVec3| cell_key(p, cell);
        // (cell, emission order) is a total order: the layout cannot depend on the sort.
        let mut order: Vec<([i32; 3], u32)> = photons
            .iter()
            .enumerate()
            .map(|(i, ph)| (key_of(ph.position), i as u32))
            .collect();
        order.sort_unstable();
        let sorted: Vec<Photon> = order.iter().map(|&(_, i)| photons[i as usize]).collect();
        let mut cells = HashMap::new();
        let mut start = 0;
        while start < order.len() {
            let key = order[start].0;
            let end = start + order[start..].partition_point(|(k, _)| *k == key);
            cells.insert(key, (start as u32, end as u32));
            start = end;
        }
        CausticMap {
            radius,
            cell,
            photons: sorted,
            cells,
            emitted,
        }
    }

    pub fn radius(&self) -> f64 {
        self.radius
    }

    /// Photons emitted from the lights.
    pub fn emitted(&self) -> u32 {
        self.emitted
    }

    /// Photons stored (landings on diffuse surfaces).
    pub fn len(&self) -> usize {
        self.photons.len()
    }

    pub fn is_empty(&self) -> bool {
        self.photons.is_empty()
    }

    /// The flux of every stored photon together.
    pub fn total_power(&self) -> DVec3 {
        self.photons
            .iter()
            .map(|p| DVec3::from(p.power.map(f64::from)))
            .sum()
    }

    /// Caustic irradiance at `p` on a surface whose unit normal `n` faces the viewer: the
    /// photons within the radius, weighted by the Epanechnikov kernel 1 − d²/r², whose
    /// integral over the disc is πr²/2.
    pub fn irradiance(&self, p: DVec3, n: DVec3) -> DVec3 {
        let r2 = self.radius * self.radius;
        let lo = cell_key(p - DVec3::splat(self.radius), self.cell);
        let hi = cell_key(p + DVec3::splat(self.radius), self.cell);
        // At most two cells per axis, unless coordinates are so large that keys saturate.
        if (0..3).any(|a| hi[a] as i64 - lo[a] as i64 > 2) {
            return DVec3::ZERO;
        }
        let mut sum = DVec3::ZERO;
        for x in lo[0]..=hi[0] {
            for y in lo[1]..=hi[1] {
                for z in lo[2]..=hi[2] {
                    let Some(&(start, end)) = self.cells.get(&[x, y, z]) else {
                        continue;
                    };
                    for ph in &self.photons[start as usize..end as usize] {
                        let d2 = (ph.position - p).length_squared();
                        if d2 < r2 && DVec3::from(ph.normal.map(f64::from)).dot(n) >= MIN_NORMAL_COS
                        {
                            sum += DVec3::from(ph.power.map(f64::from)) * (1.0 - d2 / r2);
                        }
                    }
                }
            }
        }
        sum * (2.0 / (PI * r2))
    }
}

/// The grid cell holding `p` (saturating for coordinates beyond the i32 range).
fn cell_key(p: DVec3, cell: f64) -> [i32; 3] {
    (p / cell).floor().to_array().map(|v| v as i32)
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
fn casters(scene: &Scene) -> Vec<Caster> {
    let world = &scene.world;
    let focuses = |m: u32| {
        let m = &scene.materials[m as usize];
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
    scene: &'a Scene,
    targets: &'a [Caster],
    filter: TextureFilter,
    seed: u64,
    photons: u32,
}

impl Emitter<'_> {
    /// Traces photon `index` and appends its landings on diffuse surfaces to `out`.
    fn trace(&self, index: u32, out: &mut Vec<Photon>) {
        let scene = self.scene;
        let lights = scene.lights.len() as u32;
        let light = &scene.lights[(index % lights) as usize];
        // Photons go round-robin over the lights: light l emits ⌈(N − l)/L⌉ of them.
        let emitted = (self.photons - index % lights).div_ceil(lights);
        let mut rng = Rng::for_sample(self.seed, index, PHOTON_ROW, 0);
        let origin = if light.radius > 0.0 {
            light.position + light.radius * uniform_sphere(rng.next_f64(), rng.next_f64())
        } else {
            light.position
        };

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
        let scene = self.scene;
        let world = &scene.world;
        let mut throughput = DVec3::ONE;
        let mut travelled = 0.0;
        let mut media = Media::new(scene.description.refractive_index);
        for bounce in 0..MAX_BOUNCES {
            let Some(hit) = world.intersect(&ray, 0.0, f64::INFINITY) else {
                return;
            };
            let s = world.surface(&ray, &hit, &scene.materials, &scene.textures, self.filter);
            travelled += hit.t;
            let error_scale = s.position.abs().max_element() + hit.t;
            let d = ray.dir;
            let next = if s.ior == 0.0 {
                // Opaque: the side the photon arrives on, as the camera's tracer flips it.
                let n = if s.normal.dot(d) > 0.0 {
                    -s.normal
                } else {
                    s.normal
                };
                if bounce > 0 && s.texture * s.diffuse != DVec3::ZERO {
                    let [a_c, a_l, a_q] = light.attenuation;
                    let falloff = (a_c + a_l * travelled + a_q * travelled * travelled).max(1e-12);
                    let flux = travelled * travelled * solid_angle / falloff;
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
                // Dielectric, decided as in shade.rs; Russian roulette on Schlick's R picks
                // reflection or refraction without changing the photon's expected flux.
                let entering = s.normal.dot(d) < 0.0;
                let facing = if entering { s.normal } else { -s.normal };
                let (n1, n2, inside) = if entering {
                    (media.current(), s.ior, media.entered(s.ior))
                } else {
                    let (after, removed) = media.left(s.ior);
                    let n1 = if removed { media.current() } else { s.ior };
                    (n1, after.current(), after)
                };
                let cos_incident = d.dot(s.normal).abs().min(1.0);
                let reflectance = schlick(n1, n2, cos_incident);
                if rng.next_f64() < reflectance {
                    let tint = s.texture * s.specular;
                    if tint == DVec3::ZERO {
                        return;
                    }
                    throughput *= tint;
                    reflect(d, facing)
                } else {
                    let Some(dir) = refract(d, facing, n1, n2) else {
                        return;
                    };
                    media = inside;
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

/// The media a photon is inside, outermost first: shade.rs's stack, with the exit reporting
/// whether it matched an entry.
#[derive(Clone, Copy, Debug)]
struct Media {
    indices: [f64; MAX_MEDIA],
    len: usize,
}

impl Media {
    fn new(outer: f64) -> Self {
        let mut indices = [0.0; MAX_MEDIA];
        indices[0] = outer;
        Self { indices, len: 1 }
    }

    fn current(&self) -> f64 {
        self.indices[self.len - 1]
    }

    fn entered(mut self, ior: f64) -> Self {
        if self.len < MAX_MEDIA {
            self.indices[self.len] = ior;
            self.len += 1;
        }
        self
    }

    fn left(mut self, ior: f64) -> (Self, bool) {
        match (1..self.len).rev().find(|&i| self.indices[i] == ior) {
            Some(i) => {
                self.indices.copy_within(i + 1..self.len, i);
                self.len -= 1;
                (self, true)
            }
            None => (self, false),
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

    #[test]
    fn media_exits_report_whether_they_matched() {
        let glass = Media::new(1.0).entered(1.5);
        let (out, removed) = glass.left(1.5);
        assert!(removed);
        assert_eq!(out.current(), 1.0);
        let (same, removed) = glass.left(1.33);
        assert!(!removed);
        assert_eq!(same.current(), 1.5);
    }

    #[test]
    fn grid_gathers_with_a_normalised_kernel() {
        // Photons of power 1 on a fine lattice of the plane y = 0 with spacing h: the
        // irradiance anywhere well inside is 1/h².
        let h = 0.01;
        let mut photons = Vec::new();
        for i in -100..=100 {
            for j in -100..=100 {
                photons.push(Photon {
                    position: DVec3::new(i as f64 * h, 0.0, j as f64 * h),
                    power: [1.0; 3],
                    normal: [0.0, 1.0, 0.0],
                });
            }
        }
        let map = CausticMap::from_photons(photons, 0.1, 1);
        let e = map.irradiance(DVec3::new(0.013, 0.0, -0.021), DVec3::Y);
        assert!((e.x * h * h - 1.0).abs() < 0.02, "{e}");
        // The other side of the surface sees none of it.
        assert_eq!(map.irradiance(DVec3::ZERO, DVec3::NEG_Y), DVec3::ZERO);
        // Nor does a point beyond the radius.
        assert_eq!(
            map.irradiance(DVec3::new(1.2, 0.0, 0.0), DVec3::Y),
            DVec3::ZERO
        );
    }
}
