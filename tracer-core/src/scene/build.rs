//! From a description to a renderable scene, reading only the assets that geometry uses.

use std::collections::HashMap;
use std::io::Cursor;
use std::path::Path;
use std::time::{Duration, Instant};

use glam::DVec3;

use super::desc::SceneDescription;
use super::obj::parse_obj_with_limit;
use super::{AssetSource, FsAssets, LoadLimits, SceneError};
use crate::geometry::{Motion, Transform, TransformDesc};
use crate::shade::{CausticCache, CausticMap, Light, Material, Materials, Stage};
use crate::texture::{Environment, Texture, TextureFilter};
use crate::world::{Mesh, Model, Mover, MoverShape, Sphere, World, WorldTriangle};

/// What building a scene cost and what it holds.
#[derive(Clone, Debug, Default)]
pub struct SceneStats {
    pub triangles: usize,
    pub textures: usize,
    pub meshes: usize,
    /// Time spent building BVHs (all meshes and the top level).
    pub bvh_build: Duration,
    /// Time spent reading and decoding assets.
    pub asset_load: Duration,
}

/// A scene ready to render: immutable and shared by every render thread.
#[derive(Clone, Debug)]
pub struct Scene {
    pub description: SceneDescription,
    pub(crate) lights: Vec<Light>,
    pub(crate) materials: Vec<Material>,
    pub(crate) textures: Vec<Texture>,
    pub(crate) world: World,
    pub(crate) environment: Option<Environment>,
    /// Whether any used material reflects glossily (the tracer then seeds the gloss stream).
    pub(crate) has_gloss: bool,
    /// Per top-level object, whether every material it can show is opaque (refractive index
    /// 0) with a diffuse colour, so that shading knows before it makes a hit's surface that
    /// the lights will shade it.
    pub(crate) lit_objects: Vec<bool>,
    pub stats: SceneStats,
    /// The world point the scene is built around (the eye at frame 0's shutter opening):
    /// geometry, lights and cameras are stored relative to it, so f64 positions and f32 BVH
    /// boxes keep their precision however far from the world origin the scene lies.
    pub(crate) origin: DVec3,
    /// The caustic photon map, built by the first renderer that needs it (`photon.rs`).
    pub(crate) caustic_cache: CausticCache,
}

impl Scene {
    /// The number of frames the scene describes (1 unless it has an `<animation>`).
    pub fn frame_count(&self) -> u32 {
        self.description.frames
    }

    /// What shading sees of this scene, textures sampled with `filter`.
    pub(crate) fn stage<'a>(
        &'a self,
        filter: TextureFilter,
        caustics: Option<&'a CausticMap>,
    ) -> Stage<'a> {
        Stage {
            world: &self.world,
            materials: Materials {
                materials: &self.materials,
                textures: &self.textures,
                filter,
            },
            lights: &self.lights,
            ambient: self.description.ambient,
            background: self.description.background,
            environment: self.environment.as_ref(),
            outer_ior: self.description.refractive_index,
            caustics,
            lit_objects: &self.lit_objects,
        }
    }

    /// The geometry, for direct ray queries (benchmarks, robustness tests). Its coordinates
    /// are relative to [`origin`](Self::origin), like the renderer's cameras.
    pub fn world(&self) -> &World {
        &self.world
    }

    /// Where the renderer's frame sits in the scene's world coordinates: a world point `p` is
    /// `p - origin()` for [`world`](Self::world) and the renderer's cameras.
    pub fn origin(&self) -> DVec3 {
        self.origin
    }

    /// Loads a scene file and the assets it references (relative to its folder, then the
    /// folder's parent).
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let file = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| SceneError::new(&file, 0, 0, format!("cannot read scene file: {e}")))?;
        let description = SceneDescription::parse(&text, &file)?;
        Scene::build(&description, &file, &FsAssets::for_scene(path))
    }

    /// Builds from a parsed description; `file` names the scene file in asset errors. No load
    /// limits: the same as [`build_with_limits`](Self::build_with_limits) with
    /// [`LoadLimits::UNLIMITED`].
    pub fn build(
        description: &SceneDescription,
        file: &str,
        assets: &dyn AssetSource,
    ) -> Result<Scene, SceneError> {
        Self::build_with_limits(description, file, assets, &LoadLimits::UNLIMITED)
    }

    /// Builds from a parsed description under `limits`: each texture's size is read from its
    /// PNG header and counted against `max_texture_pixels` before it is decoded, and each used
    /// mesh file's triangles are counted (once, however many models instance it) against what
    /// `max_primitives` leaves after the spheres, the scene's triangles, the models (one each:
    /// an entry of the top-level BVH) and earlier meshes, while the OBJ is parsed, before any BVH is
    /// built. `file` names the scene file in errors.
    pub fn build_with_limits(
        description: &SceneDescription,
        file: &str,
        assets: &dyn AssetSource,
        limits: &LoadLimits,
    ) -> Result<Scene, SceneError> {
        let d = description;
        let load_started = Instant::now();
        let scene_error = |pos: super::xml::Pos, message: String| {
            SceneError::new(file, pos.line, pos.column, message)
        };
        let scene_primitives = d.scene_primitives();
        if scene_primitives > limits.max_primitives {
            return Err(SceneError::over_limit(
                file,
                0,
                0,
                "max_primitives",
                scene_primitives,
                limits.max_primitives,
                "spheres, triangles and models",
            ));
        }
        let used_materials = d.used_materials();

        // Textures of used materials only, each file decoded once.
        let mut pixels = PixelBudget {
            used: 0,
            max: limits.max_texture_pixels,
        };
        let mut textures: Vec<Texture> = Vec::new();
        let mut texture_slots: HashMap<&str, u32> = HashMap::new();
        let mut materials = Vec::with_capacity(d.materials.len());
        for (m, used) in d.materials.iter().zip(&used_materials) {
            let texture = match &m.texture {
                Some(path) if *used => match texture_slots.get(path.as_str()) {
                    Some(&slot) => Some(slot),
                    None => {
                        let owner = format!("material \"{}\": ", m.name);
                        let texture = load_png(path, assets, &owner, "texture ", &mut pixels)
                            .map_err(|e| e.at(file, m.pos))?;
                        textures.push(texture);
                        texture_slots.insert(path, textures.len() as u32 - 1);
                        Some(textures.len() as u32 - 1)
                    }
                },
                _ => None,
            };
            materials.push(Material {
                ambient: m.ambient,
                diffuse: m.diffuse,
                specular: m.specular,
                ior: m.refractive_index,
                texture,
                glossiness: m.glossiness,
                absorption: m.absorption,
            });
        }

        // Meshes some model uses, in order, each file parsed once (however many <mesh>
        // elements name it) against what the primitive budget has left after the spheres, the
        // scene triangles, the models and the meshes before it.
        let mut primitives_left = limits.max_primitives - scene_primitives;
        let mut mesh_slot = vec![u32::MAX; d.meshes.len()];
        let mut slot_of_file: HashMap<&str, u32> = HashMap::new();
        let mut mesh_data = Vec::new();
        for (i, used) in d.used_meshes().into_iter().enumerate() {
            let m = &d.meshes[i];
            if !used {
                continue;
            }
            let Some(path) = &m.filename else {
                return Err(scene_error(
                    m.pos,
                    format!("mesh \"{}\" has no filename", m.name),
                ));
            };
            if let Some(&slot) = slot_of_file.get(path.as_str()) {
                mesh_slot[i] = slot;
                continue;
            }
            let bytes = assets.read(path).map_err(|e| {
                scene_error(
                    m.pos,
                    format!(
                        "cannot read mesh \"{}\" from '{}': {e}",
                        m.name,
                        assets.display_name(path)
                    ),
                )
            })?;
            let text = String::from_utf8_lossy(&bytes);
            let mesh = parse_obj_with_limit(
                &text,
                &assets.display_name(path),
                primitives_left,
                limits.max_primitives,
            )?;
            primitives_left -= mesh.triangles.len() as u64;
            mesh_slot[i] = mesh_data.len() as u32;
            slot_of_file.insert(path, mesh_data.len() as u32);
            mesh_data.push(mesh);
        }
        let environment = match &d.environment {
            Some(e) => {
                let image = load_png(&e.file, assets, "environment map: ", "", &mut pixels)
                    .map_err(|failure| failure.at(file, e.pos))?;
                Some(Environment::new(image, e.intensity, e.rotation))
            }
            None => None,
        };
        let asset_load = load_started.elapsed();

        let build_started = Instant::now();
        // Camera-relative rendering (as pbrt-v4): everything is placed relative to the eye,
        // where the eye rays start, so precision is spent where the image is made.
        let origin = d.camera.at(d.camera.shutter[0]).0;
        let transform = |t: &TransformDesc| placed(t, origin);
        let mut triangles_total = 0;
        let meshes: Vec<Mesh> = mesh_data
            .into_iter()
            .map(|data| {
                triangles_total += data.triangles.len();
                Mesh::new(
                    &data.positions,
                    data.normals,
                    data.tex_coords,
                    &data.triangles,
                )
            })
            .collect();

        let mut movers = Vec::new();
        let spheres = d
            .spheres
            .iter()
            .filter(|s| s.motion.is_static())
            .map(|s| Sphere {
                transform: transform(&s.transform),
                radius: s.radius,
                material: s.material as u32,
            })
            .collect();
        let world_triangles: Vec<WorldTriangle> = d
            .triangles
            .iter()
            .filter(|t| t.motion.is_static())
            .map(|t| {
                let xf = transform(&t.transform);
                WorldTriangle {
                    positions: t
                        .vertices
                        .each_ref()
                        .map(|v| xf.to_world.transform_point3(v.position)),
                    normals: t.vertices.each_ref().map(|v| xf.normal_to_world(v.normal)),
                    tex_coords: t.vertices.each_ref().map(|v| v.tex_coord),
                    materials: t.vertices.each_ref().map(|v| v.material as u32),
                }
            })
            .collect();
        triangles_total += d.triangles.len();
        let models = d
            .models
            .iter()
            .filter(|m| m.motion.is_static())
            .map(|m| Model {
                transform: transform(&m.transform),
                mesh: mesh_slot[m.mesh],
                material: m.material as u32,
            })
            .collect();
        // Moving geometry, kept apart so that static objects are intersected as before.
        for s in d.spheres.iter().filter(|s| !s.motion.is_static()) {
            movers.push(Mover {
                shape: MoverShape::Sphere {
                    radius: s.radius,
                    material: s.material as u32,
                },
                base: relative(&s.transform, origin),
                motion: relative_motion(&s.motion, origin),
            });
        }
        for t in d.triangles.iter().filter(|t| !t.motion.is_static()) {
            movers.push(Mover {
                shape: MoverShape::Triangle(WorldTriangle {
                    positions: t.vertices.each_ref().map(|v| v.position),
                    normals: t.vertices.each_ref().map(|v| v.normal),
                    tex_coords: t.vertices.each_ref().map(|v| v.tex_coord),
                    materials: t.vertices.each_ref().map(|v| v.material as u32),
                }),
                base: relative(&t.transform, origin),
                motion: relative_motion(&t.motion, origin),
            });
        }
        for m in d.models.iter().filter(|m| !m.motion.is_static()) {
            movers.push(Mover {
                shape: MoverShape::Model {
                    mesh: mesh_slot[m.mesh],
                    material: m.material as u32,
                },
                base: relative(&m.transform, origin),
                motion: relative_motion(&m.motion, origin),
            });
        }
        // Ray times run from frame 0's shutter opening to the last frame's closing.
        let time_span = (0.0, (d.frames - 1) as f64 + d.camera.shutter[1]);
        let world = World::with_movers(spheres, world_triangles, meshes, models, movers, time_span);
        let bvh_build = build_started.elapsed();

        let lights = d
            .lights
            .iter()
            .map(|l| Light {
                position: l.position - origin,
                color: l.color,
                attenuation: l.attenuation,
                radius: l.radius,
            })
            .collect();
        let has_gloss = materials
            .iter()
            .zip(&used_materials)
            .any(|(m, used)| m.glossiness > 0.0 && *used);
        let lit_objects = (0..world.object_count() as u32)
            .map(|object| {
                world.object_materials(object).iter().all(|&m| {
                    let m = &materials[m as usize];
                    m.ior == 0.0 && m.diffuse != DVec3::ZERO
                })
            })
            .collect();
        Ok(Scene {
            description: d.clone(),
            lights,
            has_gloss,
            lit_objects,
            environment,
            materials,
            stats: SceneStats {
                triangles: triangles_total,
                textures: textures.len(),
                meshes: world.meshes.len(),
                bvh_build,
                asset_load,
            },
            textures,
            world,
            caustic_cache: Default::default(),
            origin,
        })
    }
}

/// `t` in the frame whose origin is the world point `origin`.
fn relative(t: &TransformDesc, origin: DVec3) -> TransformDesc {
    TransformDesc {
        position: t.position - origin,
        ..*t
    }
}

/// `motion`'s keys in the frame whose origin is `origin` (velocity and spin do not depend on
/// where the origin is).
fn relative_motion(motion: &Motion, origin: DVec3) -> Motion {
    let mut moved = motion.clone();
    for key in &mut moved.keys {
        key.transform = relative(&key.transform, origin);
    }
    moved
}

/// The transform `t` describes, in the frame whose origin is `origin`.
fn placed(t: &TransformDesc, origin: DVec3) -> Transform {
    let t = relative(t, origin);
    Transform::new(t.position, t.orientation, t.scale)
}

/// Texture pixels counted so far against `max_texture_pixels`.
struct PixelBudget {
    used: u64,
    max: u64,
}

/// Why a PNG asset could not be loaded, before it is placed at the element that asked for it.
enum PngFailure {
    Invalid(String),
    OverBudget { count: u64, max: u64, what: String },
}

impl PngFailure {
    fn at(self, file: &str, pos: super::xml::Pos) -> SceneError {
        match self {
            PngFailure::Invalid(message) => SceneError::new(file, pos.line, pos.column, message),
            PngFailure::OverBudget { count, max, what } => SceneError::over_limit(
                file,
                pos.line,
                pos.column,
                "max_texture_pixels",
                count,
                max,
                &what,
            ),
        }
    }
}

/// Reads the PNG at `path`, counts its header's width × height against `budget`, and only then
/// decodes it. `owner` and `noun` start the messages ("material \"m\": ", "texture ").
fn load_png(
    path: &str,
    assets: &dyn AssetSource,
    owner: &str,
    noun: &str,
    budget: &mut PixelBudget,
) -> Result<Texture, PngFailure> {
    // The course's loader accepts only names ending in the lower-case suffix.
    if !path.ends_with(".png") {
        return Err(PngFailure::Invalid(format!(
            "{owner}{noun}'{path}' must be a .png file"
        )));
    }
    let name = assets.display_name(path);
    let bytes = assets
        .read(path)
        .map_err(|e| PngFailure::Invalid(format!("{owner}cannot read {noun}'{name}': {e}")))?;
    let invalid = |e: String| PngFailure::Invalid(format!("{owner}{noun}'{name}': {e}"));
    let (width, height) =
        image::ImageReader::with_format(Cursor::new(&bytes), image::ImageFormat::Png)
            .into_dimensions()
            .map_err(|e| invalid(format!("cannot decode PNG: {e}")))?;
    let count = budget
        .used
        .saturating_add(u64::from(width) * u64::from(height));
    if count > budget.max {
        return Err(PngFailure::OverBudget {
            count,
            max: budget.max,
            what: format!("texture pixels with {owner}{noun}'{name}' ({width}×{height})"),
        });
    }
    budget.used = count;
    Texture::decode_png(&bytes).map_err(|e| invalid(e.to_string()))
}
