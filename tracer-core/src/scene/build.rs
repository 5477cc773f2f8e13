//! From a description to a renderable scene, reading only the assets that geometry uses.

use std::path::Path;
use std::time::{Duration, Instant};

use super::desc::{MaterialDesc, SceneDescription};
use super::obj::parse_obj;
use super::{AssetSource, FsAssets, SceneError};
use crate::geometry::Transform;
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
    pub stats: SceneStats,
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
        }
    }

    /// The geometry, for direct ray queries (benchmarks, robustness tests).
    pub fn world(&self) -> &World {
        &self.world
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

    /// Builds from a parsed description; `file` names the scene file in asset errors.
    pub fn build(
        description: &SceneDescription,
        file: &str,
        assets: &dyn AssetSource,
    ) -> Result<Scene, SceneError> {
        let d = description;
        let load_started = Instant::now();
        let scene_error = |pos: super::xml::Pos, message: String| {
            SceneError::new(file, pos.line, pos.column, message)
        };

        // Textures of used materials only, each file decoded once.
        let mut textures: Vec<Texture> = Vec::new();
        let mut texture_paths: Vec<&str> = Vec::new();
        let mut materials = Vec::with_capacity(d.materials.len());
        for (index, m) in d.materials.iter().enumerate() {
            let texture = match &m.texture {
                Some(path) if d.material_used(index) => {
                    if let Some(existing) = texture_paths.iter().position(|p| p == path) {
                        Some(existing as u32)
                    } else {
                        textures.push(
                            load_texture(m, path, assets).map_err(|e| scene_error(m.pos, e))?,
                        );
                        texture_paths.push(path);
                        Some(textures.len() as u32 - 1)
                    }
                }
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

        // Meshes some model uses; parsed in parallel, since the big ones dominate load time.
        let used_meshes: Vec<usize> = (0..d.meshes.len()).filter(|&i| d.mesh_used(i)).collect();
        let mesh_data = used_meshes
            .iter()
            .map(|&i| {
                let m = &d.meshes[i];
                let Some(path) = &m.filename else {
                    return Err(scene_error(
                        m.pos,
                        format!("mesh \"{}\" has no filename", m.name),
                    ));
                };
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
                parse_obj(&text, &assets.display_name(path))
            })
            .collect::<Result<Vec<_>, _>>()?;
        let environment = match &d.environment {
            Some(e) => {
                let image = load_png(&e.file, assets)
                    .map_err(|m| scene_error(e.pos, format!("environment map: {m}")))?;
                Some(Environment::new(image, e.intensity, e.rotation))
            }
            None => None,
        };
        let asset_load = load_started.elapsed();

        let build_started = Instant::now();
        let mut mesh_slot = vec![u32::MAX; d.meshes.len()];
        let mut triangles_total = 0;
        let meshes: Vec<Mesh> = used_meshes
            .iter()
            .zip(mesh_data)
            .enumerate()
            .map(|(slot, (&i, data))| {
                mesh_slot[i] = slot as u32;
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
                base: s.transform,
                motion: s.motion.clone(),
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
                base: t.transform,
                motion: t.motion.clone(),
            });
        }
        for m in d.models.iter().filter(|m| !m.motion.is_static()) {
            movers.push(Mover {
                shape: MoverShape::Model {
                    mesh: mesh_slot[m.mesh],
                    material: m.material as u32,
                },
                base: m.transform,
                motion: m.motion.clone(),
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
                position: l.position,
                color: l.color,
                attenuation: l.attenuation,
                radius: l.radius,
            })
            .collect();
        let has_gloss = materials
            .iter()
            .enumerate()
            .any(|(i, m)| m.glossiness > 0.0 && d.material_used(i));
        Ok(Scene {
            description: d.clone(),
            lights,
            has_gloss,
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
        })
    }
}

fn transform(t: &super::desc::TransformDesc) -> Transform {
    Transform::new(t.position, t.orientation, t.scale)
}

fn load_texture(m: &MaterialDesc, path: &str, assets: &dyn AssetSource) -> Result<Texture, String> {
    // The course's loader accepts only names ending in the lower-case suffix.
    if !path.ends_with(".png") {
        return Err(format!(
            "material \"{}\": texture '{path}' must be a .png file",
            m.name
        ));
    }
    let bytes = assets.read(path).map_err(|e| {
        format!(
            "material \"{}\": cannot read texture '{}': {e}",
            m.name,
            assets.display_name(path)
        )
    })?;
    Texture::decode_png(&bytes).map_err(|e| {
        format!(
            "material \"{}\": texture '{}': {e}",
            m.name,
            assets.display_name(path)
        )
    })
}

fn load_png(path: &str, assets: &dyn AssetSource) -> Result<Texture, String> {
    if !path.ends_with(".png") {
        return Err(format!("'{path}' must be a .png file"));
    }
    let bytes = assets
        .read(path)
        .map_err(|e| format!("cannot read '{}': {e}", assets.display_name(path)))?;
    Texture::decode_png(&bytes).map_err(|e| format!("'{}': {e}", assets.display_name(path)))
}
