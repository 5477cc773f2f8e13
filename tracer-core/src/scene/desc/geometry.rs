//! Geometry: `<mesh>` files, `<vertex>` definitions, `<sphere>`, `<triangle>` and `<model>`.

use glam::{DVec2, DVec3};

use super::motion::{Motion, TransformDesc};
use super::parser::{Motions, Names, Parser};
use crate::scene::xml::{Element, Pos};
use crate::scene::SceneError;

#[derive(Clone, Debug, PartialEq)]
pub struct MeshDesc {
    pub name: String,
    pub filename: Option<String>,
    pub pos: Pos,
}

#[derive(Clone, Debug, PartialEq)]
pub struct VertexDesc {
    pub position: DVec3,
    /// Unit length (normalised at load).
    pub normal: DVec3,
    pub tex_coord: DVec2,
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct SphereDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub radius: f64,
    pub material: usize,
}

#[derive(Clone, Debug, PartialEq)]
pub struct TriangleDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub vertices: [VertexDesc; 3],
}

#[derive(Clone, Debug, PartialEq)]
pub struct ModelDesc {
    pub transform: TransformDesc,
    pub motion: Motion,
    pub mesh: usize,
    pub material: usize,
}

/// The root's geometry, in the order §1.1 reads it.
pub(super) struct Geometry {
    pub(super) meshes: Vec<MeshDesc>,
    pub(super) spheres: Vec<SphereDesc>,
    pub(super) triangles: Vec<TriangleDesc>,
    pub(super) models: Vec<ModelDesc>,
}

impl Parser<'_> {
    /// Meshes, vertices, spheres, triangles and models; `materials` are the defined material
    /// names and `motions` the root's named motions.
    pub(super) fn geometry(
        &self,
        root: &Element,
        materials: &Names,
        motions: &Motions,
    ) -> Result<Geometry, SceneError> {
        let mut meshes = Vec::new();
        let mut mesh_names = Names::new();
        for el in root.children_named("mesh") {
            let name = self.attr(el, "name")?;
            self.check_unique(el, "mesh", name, &mesh_names)?;
            mesh_names.insert(name, meshes.len());
            meshes.push(MeshDesc {
                name: name.to_string(),
                filename: el
                    .attr("filename")
                    .filter(|f| !f.is_empty())
                    .map(str::to_string),
                pos: el.pos,
            });
        }

        let mut vertices = Vec::new();
        let mut vertex_names = Names::new();
        for el in root.children_named("vertex") {
            let position = self.vec3(self.required(el, "position")?)?;
            let normal_el = self.required(el, "normal")?;
            let normal = self.vec3(normal_el)?;
            if normal == DVec3::ZERO {
                return Err(self.error(normal_el, "in <normal>, the normal must not be zero"));
            }
            let tex = self.required(el, "tex_coord")?;
            let tex_coord = DVec2::new(self.number(tex, "u")?, self.number(tex, "v")?);
            let material = self.lookup(el, "material", "material", materials)?;
            let name = self.attr(el, "name")?;
            self.check_unique(el, "vertex", name, &vertex_names)?;
            vertex_names.insert(name, vertices.len());
            vertices.push(VertexDesc {
                position,
                normal: normal.normalize(),
                tex_coord,
                material,
            });
        }

        let mut spheres = Vec::new();
        for el in root.children_named("sphere") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions)?;
            let radius_el = self.required(el, "radius")?;
            let radius = self.scalar(radius_el)?;
            if radius <= 0.0 {
                return Err(
                    self.error(radius_el, "in <radius>, a sphere's radius must be positive")
                );
            }
            let material = self.lookup(el, "material", "material", materials)?;
            spheres.push(SphereDesc {
                transform,
                motion,
                radius,
                material,
            });
        }

        let mut triangles = Vec::new();
        for el in root.children_named("triangle") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions)?;
            let refs: Vec<&Element> = el.children_named("vertex").collect();
            if refs.len() > 3 {
                return Err(self.error(
                    refs[3],
                    "in <triangle>, too many vertices (a triangle has 3)",
                ));
            }
            if refs.len() < 3 {
                return Err(self.error(
                    el,
                    format!("in <triangle>, too few vertices: {} of 3", refs.len()),
                ));
            }
            let corner = |i: usize| -> Result<VertexDesc, SceneError> {
                let index = self.lookup(refs[i], "name", "vertex", &vertex_names)?;
                Ok(vertices[index].clone())
            };
            let vertices = [corner(0)?, corner(1)?, corner(2)?];
            triangles.push(TriangleDesc {
                transform,
                motion,
                vertices,
            });
        }

        let mut models = Vec::new();
        for el in root.children_named("model") {
            let transform = self.transform(el)?;
            let motion = self.motion(el, &transform, motions)?;
            let mesh = self.lookup(el, "mesh", "mesh", &mesh_names)?;
            let material = self.lookup(el, "material", "material", materials)?;
            models.push(ModelDesc {
                transform,
                motion,
                mesh,
                material,
            });
        }
        Ok(Geometry {
            meshes,
            spheres,
            triangles,
            models,
        })
    }
}
