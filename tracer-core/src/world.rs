//! The renderable geometry: spheres, world-space scene triangles and mesh instances under a
//! top-level BVH, with closest-hit, any-hit and surface queries.

use glam::{DVec2, DVec3};

use crate::accel::{Bvh, PADDING};
use crate::geometry::{
    any_candidate, intersect_triangle, intersect_unit_sphere_scaled, Aabb, Ray, Transform,
    TriangleBlock, TriangleRay, TriangleRayF32, BLOCK,
};
use crate::settings::TextureFilter;
use crate::texture::Texture;

#[derive(Clone, Debug)]
pub struct Material {
    pub ambient: DVec3,
    pub diffuse: DVec3,
    pub specular: DVec3,
    /// 0 is opaque; anything else a dielectric.
    pub ior: f64,
    pub texture: Option<u32>,
}

#[derive(Clone, Debug)]
pub struct Sphere {
    pub transform: Transform,
    pub radius: f64,
    pub material: u32,
}

/// A scene-level triangle, already in world space, with a material per vertex.
#[derive(Clone, Debug)]
pub struct WorldTriangle {
    pub positions: [DVec3; 3],
    pub normals: [DVec3; 3],
    pub tex_coords: [DVec2; 3],
    pub materials: [u32; 3],
}

/// A mesh in local space with its own BVH; triangles are stored in BVH leaf order, each leaf
/// starting a block of four (gaps are padding slots, never reached).
#[derive(Clone, Debug)]
pub struct Mesh {
    pub corners: Vec<[DVec3; 3]>,
    pub indices: Vec<[u32; 3]>,
    pub normals: Vec<DVec3>,
    pub tex_coords: Vec<DVec2>,
    pub bvh: Bvh,
    /// `corners` in f32 blocks for the traversal's pre-test.
    pub blocks: Vec<TriangleBlock>,
}

impl Mesh {
    pub fn new(
        positions: &[DVec3],
        normals: Vec<DVec3>,
        tex_coords: Vec<DVec2>,
        triangles: &[[u32; 3]],
    ) -> Mesh {
        let corners: Vec<[DVec3; 3]> = triangles
            .iter()
            .map(|t| t.map(|i| positions[i as usize]))
            .collect();
        Mesh::in_leaf_order(&corners, triangles, normals, tex_coords)
    }

    /// The same mesh with its BVH built again from scratch (benchmarks time this).
    pub fn rebuilt(&self) -> Mesh {
        Mesh::in_leaf_order(
            &self.corners,
            &self.indices,
            self.normals.clone(),
            self.tex_coords.clone(),
        )
    }

    /// Builds the BVH over `corners` (padding slots are skipped) and stores the triangles in
    /// its leaf order.
    fn in_leaf_order(
        corners: &[[DVec3; 3]],
        indices: &[[u32; 3]],
        normals: Vec<DVec3>,
        tex_coords: Vec<DVec2>,
    ) -> Mesh {
        use rayon::prelude::*;
        let live: Vec<u32> = (0..indices.len() as u32)
            .filter(|&i| indices[i as usize] != PADDING_TRIANGLE)
            .collect();
        let bounds: Vec<Aabb> = live
            .par_iter()
            .map(|&i| Aabb::from_points(&corners[i as usize]))
            .collect();
        let bvh = Bvh::build_aligned(&bounds, BLOCK);
        let (corners, indices): (Vec<[DVec3; 3]>, Vec<[u32; 3]>) = bvh
            .order
            .par_iter()
            .map(|&o| match o {
                PADDING => ([DVec3::ZERO; 3], PADDING_TRIANGLE),
                o => {
                    let i = live[o as usize] as usize;
                    (corners[i], indices[i])
                }
            })
            .unzip();
        let blocks = corners.par_chunks(BLOCK).map(TriangleBlock::new).collect();
        Mesh {
            corners,
            indices,
            normals,
            tex_coords,
            bvh,
            blocks,
        }
    }
}

/// The indices of a padding slot.
const PADDING_TRIANGLE: [u32; 3] = [u32::MAX; 3];

#[derive(Clone, Debug)]
pub struct Model {
    pub transform: Transform,
    pub mesh: u32,
    pub material: u32,
}

#[derive(Clone, Copy, Debug)]
enum Object {
    Sphere(u32),
    Triangle(u32),
    Model(u32),
}

/// The closest intersection found along a ray.
#[derive(Clone, Copy, Debug)]
pub struct Hit {
    pub t: f64,
    object: u32,
    /// Triangle slot within a model's mesh.
    prim: u32,
    bary: [f64; 3],
}

/// Everything shading needs at a hit point.
#[derive(Clone, Copy, Debug)]
pub struct Surface {
    pub position: DVec3,
    /// Interpolated shading normal, unit length, pointing out of the surface as modelled.
    pub normal: DVec3,
    /// Geometric normal (same side as `normal`'s intent), for offsetting spawned rays.
    pub geometric_normal: DVec3,
    pub ambient: DVec3,
    pub diffuse: DVec3,
    pub specular: DVec3,
    pub ior: f64,
    /// Texture colour at the hit (white where there is no texture).
    pub texture: DVec3,
}

#[derive(Clone, Debug, Default)]
pub struct World {
    pub spheres: Vec<Sphere>,
    pub triangles: Vec<WorldTriangle>,
    pub meshes: Vec<Mesh>,
    pub models: Vec<Model>,
    objects: Vec<Object>,
    top: Bvh,
}

impl World {
    pub fn new(
        spheres: Vec<Sphere>,
        triangles: Vec<WorldTriangle>,
        meshes: Vec<Mesh>,
        models: Vec<Model>,
    ) -> World {
        let mut objects = Vec::new();
        let mut bounds = Vec::new();
        for (i, s) in spheres.iter().enumerate() {
            objects.push(Object::Sphere(i as u32));
            let r = DVec3::splat(s.radius);
            bounds.push(s.transform.bounds_to_world(Aabb { min: -r, max: r }));
        }
        for (i, t) in triangles.iter().enumerate() {
            objects.push(Object::Triangle(i as u32));
            bounds.push(Aabb::from_points(&t.positions));
        }
        for (i, m) in models.iter().enumerate() {
            objects.push(Object::Model(i as u32));
            let local = meshes[m.mesh as usize].bvh.bounds();
            bounds.push(m.transform.bounds_to_world(local));
        }
        let top = Bvh::build(&bounds);
        let objects = top.order.iter().map(|&o| objects[o as usize]).collect();
        World {
            spheres,
            triangles,
            meshes,
            models,
            objects,
            top,
        }
    }

    pub fn bounds(&self) -> Aabb {
        self.top.bounds()
    }

    /// Every BVH built again, meshes in parallel (what `tracer bench` reports as build time).
    pub fn rebuilt(&self) -> World {
        use rayon::prelude::*;
        let meshes = self.meshes.par_iter().map(Mesh::rebuilt).collect();
        World::new(
            self.spheres.clone(),
            self.triangles.clone(),
            meshes,
            self.models.clone(),
        )
    }

    /// The top-level BVH's traversal, skipped when it holds a single object (whose own test
    /// is exact, so its box adds nothing).
    #[inline(always)]
    fn traverse_top<const ORDERED: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
    ) -> bool {
        if self.objects.len() == 1 {
            leaf(0..1, t_max)
        } else if ORDERED {
            self.top.traverse(ray, t_max, leaf)
        } else {
            self.top.traverse_any(ray, t_max, leaf)
        }
    }

    /// The nearest hit with t in (t_min, t_max); `ray.dir` need not be unit length.
    pub fn intersect(&self, ray: &Ray, t_min: f64, t_max: f64) -> Option<Hit> {
        let world_tri_ray = TriangleRay::new(ray);
        let mut best: Option<Hit> = None;
        let mut t_max = t_max;
        self.traverse_top::<true>(ray, &mut t_max, |range, t_max| {
            for slot in range {
                match self.objects[slot] {
                    Object::Sphere(i) => {
                        let s = &self.spheres[i as usize];
                        let local = s.transform.ray_to_local(ray);
                        if let Some(t) = intersect_unit_sphere_scaled(
                            local.origin,
                            local.dir,
                            s.radius,
                            t_min,
                            *t_max,
                        ) {
                            *t_max = t;
                            best = Some(Hit {
                                t,
                                object: slot as u32,
                                prim: 0,
                                bary: [0.0; 3],
                            });
                        }
                    }
                    Object::Triangle(i) => {
                        let [a, b, c] = self.triangles[i as usize].positions;
                        if let Some(h) = intersect_triangle(&world_tri_ray, a, b, c, t_min, *t_max)
                        {
                            *t_max = h.t;
                            best = Some(Hit {
                                t: h.t,
                                object: slot as u32,
                                prim: 0,
                                bary: h.bary,
                            });
                        }
                    }
                    Object::Model(i) => {
                        let model = &self.models[i as usize];
                        let mesh = &self.meshes[model.mesh as usize];
                        let local = model.transform.ray_to_local(ray);
                        let tri_ray = TriangleRay::new(&local);
                        let ray32 = TriangleRayF32::new(&tri_ray);
                        mesh.bvh.traverse(&local, t_max, |tris, t_max| {
                            any_candidate(&mesh.blocks, &mesh.corners, &ray32, tris, |tri| {
                                let [a, b, c] = mesh.corners[tri];
                                if let Some(h) =
                                    intersect_triangle(&tri_ray, a, b, c, t_min, *t_max)
                                {
                                    *t_max = h.t;
                                    best = Some(Hit {
                                        t: h.t,
                                        object: slot as u32,
                                        prim: tri as u32,
                                        bary: h.bary,
                                    });
                                }
                                false
                            })
                        });
                    }
                }
            }
            false
        });
        best
    }

    /// Whether anything lies along the ray with t in (0, t_max).
    pub fn occluded(&self, ray: &Ray, t_max: f64) -> bool {
        let world_tri_ray = TriangleRay::new(ray);
        let mut t_limit = t_max;
        self.traverse_top::<false>(ray, &mut t_limit, |range, t_max| {
            for slot in range {
                let blocked = match self.objects[slot] {
                    Object::Sphere(i) => {
                        let s = &self.spheres[i as usize];
                        let local = s.transform.ray_to_local(ray);
                        intersect_unit_sphere_scaled(local.origin, local.dir, s.radius, 0.0, *t_max)
                            .is_some()
                    }
                    Object::Triangle(i) => {
                        let [a, b, c] = self.triangles[i as usize].positions;
                        intersect_triangle(&world_tri_ray, a, b, c, 0.0, *t_max).is_some()
                    }
                    Object::Model(i) => {
                        let model = &self.models[i as usize];
                        let mesh = &self.meshes[model.mesh as usize];
                        let local = model.transform.ray_to_local(ray);
                        let tri_ray = TriangleRay::new(&local);
                        let ray32 = TriangleRayF32::new(&tri_ray);
                        let mut limit = *t_max;
                        mesh.bvh.traverse_any(&local, &mut limit, |tris, t_max| {
                            any_candidate(&mesh.blocks, &mesh.corners, &ray32, tris, |tri| {
                                let [a, b, c] = mesh.corners[tri];
                                intersect_triangle(&tri_ray, a, b, c, 0.0, *t_max).is_some()
                            })
                        })
                    }
                };
                if blocked {
                    return true;
                }
            }
            false
        })
    }

    /// Position, normals and material values at `hit`.
    pub fn surface(
        &self,
        ray: &Ray,
        hit: &Hit,
        materials: &[Material],
        textures: &[Texture],
        filter: TextureFilter,
    ) -> Surface {
        let position = ray.at(hit.t);
        let tex_color = |material: &Material, uv: DVec2| match material.texture {
            Some(t) => textures[t as usize].sample(uv, filter),
            None => DVec3::ONE,
        };
        let [b0, b1, b2] = hit.bary;
        match self.objects[hit.object as usize] {
            Object::Sphere(i) => {
                let s = &self.spheres[i as usize];
                let local = s.transform.to_local.transform_point3(position) / s.radius;
                let unit = local.normalize_or_zero();
                let normal = s.transform.normal_to_world(unit);
                let m = &materials[s.material as usize];
                Surface {
                    position,
                    normal,
                    geometric_normal: normal,
                    ambient: m.ambient,
                    diffuse: m.diffuse,
                    specular: m.specular,
                    ior: m.ior,
                    texture: tex_color(m, sphere_uv(unit)),
                }
            }
            Object::Triangle(i) => {
                let t = &self.triangles[i as usize];
                let [p0, p1, p2] = t.positions;
                let geometric = (p1 - p0).cross(p2 - p0).normalize_or_zero();
                let interpolated = b0 * t.normals[0] + b1 * t.normals[1] + b2 * t.normals[2];
                let uv = b0 * t.tex_coords[0] + b1 * t.tex_coords[1] + b2 * t.tex_coords[2];
                let ms = t.materials.map(|m| &materials[m as usize]);
                let blend =
                    |f: &dyn Fn(&Material) -> DVec3| b0 * f(ms[0]) + b1 * f(ms[1]) + b2 * f(ms[2]);
                Surface {
                    position,
                    normal: interpolated.try_normalize().unwrap_or(geometric),
                    geometric_normal: geometric,
                    ambient: blend(&|m| m.ambient),
                    diffuse: blend(&|m| m.diffuse),
                    specular: blend(&|m| m.specular),
                    ior: b0 * ms[0].ior + b1 * ms[1].ior + b2 * ms[2].ior,
                    texture: blend(&|m| tex_color(m, uv)),
                }
            }
            Object::Model(i) => {
                let model = &self.models[i as usize];
                let mesh = &self.meshes[model.mesh as usize];
                let [i0, i1, i2] = mesh.indices[hit.prim as usize].map(|i| i as usize);
                let [p0, p1, p2] = mesh.corners[hit.prim as usize];
                let geometric = model.transform.normal_to_world((p1 - p0).cross(p2 - p0));
                let local_n = b0 * mesh.normals[i0] + b1 * mesh.normals[i1] + b2 * mesh.normals[i2];
                let normal = model.transform.normal_to_world(local_n);
                let uv =
                    b0 * mesh.tex_coords[i0] + b1 * mesh.tex_coords[i1] + b2 * mesh.tex_coords[i2];
                let m = &materials[model.material as usize];
                Surface {
                    position,
                    normal: if normal == DVec3::ZERO {
                        geometric
                    } else {
                        normal
                    },
                    geometric_normal: geometric,
                    ambient: m.ambient,
                    diffuse: m.diffuse,
                    specular: m.specular,
                    ior: m.ior,
                    texture: tex_color(m, uv),
                }
            }
        }
    }
}

/// Latitude/longitude mapping of conventions §6 for a unit local-space point: u grows from
/// +Z toward +X, v = 1 at the +Y pole.
pub fn sphere_uv(p: DVec3) -> DVec2 {
    let mut u = p.x.atan2(p.z) / std::f64::consts::TAU;
    if u < 0.0 {
        u += 1.0;
    }
    let v = 1.0 - p.y.clamp(-1.0, 1.0).acos() / std::f64::consts::PI;
    DVec2::new(u, v)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sphere_uv_follows_the_preview_mesh() {
        let close = |a: DVec2, b: DVec2| (a - b).length() < 1e-12;
        assert!(close(sphere_uv(DVec3::Z), DVec2::new(0.0, 0.5)));
        assert!(close(sphere_uv(DVec3::X), DVec2::new(0.25, 0.5)));
        assert!(close(sphere_uv(DVec3::NEG_Z), DVec2::new(0.5, 0.5)));
        assert!(close(sphere_uv(DVec3::NEG_X), DVec2::new(0.75, 0.5)));
        assert!((sphere_uv(DVec3::Y).y - 1.0).abs() < 1e-12);
        assert!(sphere_uv(DVec3::NEG_Y).y.abs() < 1e-12);
    }
}
