//! The scene as the XML file describes it: plain values with their file positions, names
//! resolved to indices, no assets read. Follows conventions.md §1 and §2.

mod camera;
mod geometry;
mod materials;
mod motion;
mod parser;

use glam::DVec3;

pub use camera::CameraDesc;
pub use geometry::{MeshDesc, ModelDesc, SphereDesc, TriangleDesc, VertexDesc};
pub use materials::{CausticsDesc, EnvironmentDesc, LightDesc, MaterialDesc};
pub use motion::{Keyframe, Motion, TransformDesc};
pub use parser::parse_c_double;

use super::xml::{parse_document, Element};
use super::{LoadLimits, SceneError};
use geometry::Geometry;
use parser::{Motions, Names, Parser};

/// A parsed, validated scene file. Building a renderable scene from it reads only the assets
/// that [`SceneDescription::referenced_assets`] lists.
#[derive(Clone, Debug, PartialEq)]
pub struct SceneDescription {
    pub file: String,
    pub camera: CameraDesc,
    pub background: DVec3,
    /// Index of the medium the camera sits in.
    pub refractive_index: f64,
    pub ambient: DVec3,
    pub lights: Vec<LightDesc>,
    pub materials: Vec<MaterialDesc>,
    pub meshes: Vec<MeshDesc>,
    pub spheres: Vec<SphereDesc>,
    pub triangles: Vec<TriangleDesc>,
    pub models: Vec<ModelDesc>,
    /// Replaces `background` for rays that leave the scene.
    pub environment: Option<EnvironmentDesc>,
    /// Frames the scene describes (frame k is time k).
    pub frames: u32,
    /// Present when the scene asks for caustics.
    pub caustics: Option<CausticsDesc>,
}

impl SceneDescription {
    /// Parses scene XML; `file` names it in error messages. No load limits: the same as
    /// [`parse_with_limits`](Self::parse_with_limits) with [`LoadLimits::UNLIMITED`].
    pub fn parse(text: &str, file: &str) -> Result<Self, SceneError> {
        Self::parse_with_limits(text, file, &LoadLimits::UNLIMITED)
    }

    /// Parses scene XML under `limits`: spheres, triangles and models are counted against
    /// `max_primitives` as the XML is read, so an oversized file is refused before its element
    /// tree is complete. (Mesh triangles and texture pixels are checked by
    /// [`Scene::build_with_limits`](super::Scene::build_with_limits), which reads the assets.)
    pub fn parse_with_limits(
        text: &str,
        file: &str,
        limits: &LoadLimits,
    ) -> Result<Self, SceneError> {
        let root = parse_document(text, file, limits)?;
        Parser::new(file, limits).scene(&root)
    }

    /// Spheres, scene triangles and models (each model one instance in the top-level BVH; its
    /// mesh's triangles count once per mesh file): the primitives counted before any mesh is
    /// read.
    pub fn scene_primitives(&self) -> u64 {
        self.spheres.len() as u64 + self.triangles.len() as u64 + self.models.len() as u64
    }

    /// For each material, whether some geometry uses it (one pass over the geometry).
    pub fn used_materials(&self) -> Vec<bool> {
        let mut used = vec![false; self.materials.len()];
        let indices = self.spheres.iter().map(|s| s.material);
        let indices = indices.chain(self.models.iter().map(|m| m.material));
        let indices = indices.chain(
            self.triangles
                .iter()
                .flat_map(|t| t.vertices.iter().map(|v| v.material)),
        );
        for index in indices {
            if let Some(flag) = used.get_mut(index) {
                *flag = true;
            }
        }
        used
    }

    /// For each mesh, whether some model instances it.
    pub fn used_meshes(&self) -> Vec<bool> {
        let mut used = vec![false; self.meshes.len()];
        for m in &self.models {
            if let Some(flag) = used.get_mut(m.mesh) {
                *flag = true;
            }
        }
        used
    }

    /// Whether any geometry uses material `index`.
    pub fn material_used(&self, index: usize) -> bool {
        self.spheres.iter().any(|s| s.material == index)
            || self.models.iter().any(|m| m.material == index)
            || self
                .triangles
                .iter()
                .any(|t| t.vertices.iter().any(|v| v.material == index))
    }

    /// Whether anything in the scene moves (the camera included).
    pub fn has_motion(&self) -> bool {
        !self.camera.motion.is_static()
            || self.spheres.iter().any(|s| !s.motion.is_static())
            || self.triangles.iter().any(|t| !t.motion.is_static())
            || self.models.iter().any(|m| !m.motion.is_static())
    }

    /// Whether any model instances mesh `index`.
    pub fn mesh_used(&self, index: usize) -> bool {
        self.models.iter().any(|m| m.mesh == index)
    }

    /// The asset paths, exactly as written, that rendering this scene reads: textures of
    /// materials some geometry uses and meshes some model uses. Deduplicated, in file order.
    pub fn referenced_assets(&self) -> Vec<String> {
        let used_materials = self.used_materials();
        let used_meshes = self.used_meshes();
        let textures = self
            .materials
            .iter()
            .zip(used_materials)
            .filter(|(_, used)| *used)
            .filter_map(|(m, _)| m.texture.clone());
        let meshes = self
            .meshes
            .iter()
            .zip(used_meshes)
            .filter(|(_, used)| *used)
            .filter_map(|(m, _)| m.filename.clone());
        let environment = self.environment.iter().map(|e| e.file.clone());
        let mut seen = std::collections::HashSet::new();
        textures
            .chain(meshes)
            .chain(environment)
            .filter(|path| seen.insert(path.clone()))
            .collect()
    }
}

impl Parser<'_> {
    /// The whole document; the passes run in the order of §1.1, whatever the document order.
    fn scene(&self, root: &Element) -> Result<SceneDescription, SceneError> {
        // Named motions (an extension) may be used by the camera and any geometry.
        let mut motions = Motions::default();
        for el in root.children_named("motion") {
            let name = self.attr(el, "name")?;
            self.check_unique(el, "motion", name, &motions.names)?;
            motions.names.insert(name, motions.definitions.len());
            motions.definitions.push(el);
        }
        // The passes run in the order of §1.1, whatever the document order.
        let camera = self.camera(self.required(root, "camera")?, &motions)?;
        let background = self.color(self.required(root, "background_color")?)?;
        let refractive_index = self.scalar(self.required(root, "refractive_index")?)?;
        let ambient = self.optional_color(root, "ambient_light", DVec3::ZERO)?;
        let environment = self
            .single(root, "environment_map")?
            .map(|el| self.environment(el))
            .transpose()?;
        let frames = match self.single(root, "animation")? {
            Some(el) => {
                let frames = self.number(el, "frames")?;
                if frames.fract() != 0.0 || !(1.0..=1e6).contains(&frames) {
                    return Err(self.error(
                        el,
                        format!("in <animation>, frames must be a whole number from 1 to 1000000, not {frames}"),
                    ));
                }
                frames as u32
            }
            None => 1,
        };
        let lights = root
            .children_named("point_light")
            .map(|el| self.light(el))
            .collect::<Result<Vec<_>, _>>()?;

        let mut materials = Vec::new();
        let mut material_names = Names::new();
        for el in root.children_named("material") {
            let material = self.material(el)?;
            let name = self.attr(el, "name")?;
            self.check_unique(el, "material", name, &material_names)?;
            material_names.insert(name, materials.len());
            materials.push(material);
        }

        let Geometry {
            meshes,
            spheres,
            triangles,
            models,
        } = self.geometry(root, &material_names, &motions)?;

        Ok(SceneDescription {
            file: self.file.to_string(),
            camera,
            background,
            refractive_index,
            ambient,
            lights,
            materials,
            meshes,
            spheres,
            triangles,
            models,
            environment,
            frames,
            caustics: self
                .single(root, "caustics")?
                .map(|el| self.caustics(el))
                .transpose()?,
        })
    }
}
