//! The renderable geometry: spheres, world-space scene triangles and mesh instances under a
//! top-level BVH, with closest-hit, any-hit and surface-geometry queries. Objects carry
//! material indices only; what a material looks like is `shade::material`'s business.

use glam::{DMat3, DVec2, DVec3};

use crate::accel::{with_capacity_huge, Bvh, Fetch, PacketBounds, Spread, PACKET, PADDING};

mod top;
use crate::geometry::{
    any_candidate, intersect_triangle, intersect_unit_sphere_scaled, prefetch_blocks,
    prefetch_leaf, Aabb, Motion, Ray, Transform, TransformDesc, TriangleBlock, TriangleRay,
    TriangleRayF32, BLOCK,
};
use top::TopLevel;

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
    pub corners: Corners,
    pub indices: Vec<[u32; 3]>,
    pub normals: Vec<DVec3>,
    pub tex_coords: Vec<DVec2>,
    pub bvh: Bvh,
    /// The triangles' corners in f32 blocks for the traversal's pre-test.
    pub blocks: Vec<TriangleBlock>,
    /// Per triangle slot of a mesh of at most [`EXITS_UP_TO`] slots (empty for a larger
    /// one), the sides of its plane that a ray leaving it cannot meet the mesh from: bit 0
    /// ([`FRONT_EXITS`]) where the whole mesh lies on or behind the plane (its winding
    /// normal's side is open), bit 1 ([`BACK_EXITS`]) where it lies on or in front.
    exits: Vec<u8>,
}

/// Meshes of at most this many triangle slots get [`Mesh::exits`]: a byte each, made from
/// the corners of the mesh's box.
const EXITS_UP_TO: usize = 4096;
/// [`Mesh::exits`] bits.
const FRONT_EXITS: u8 = 1;
const BACK_EXITS: u8 = 2;

/// Where the exact triangle test finds a mesh's corners.
#[derive(Clone, Debug)]
pub enum Corners {
    /// In the f32 blocks themselves: the mesh's vertices are f32 values (see [`Mesh::new`]),
    /// so the blocks hold its corners exactly and the leaf test reads nothing else.
    InBlocks,
    /// In f64 by slot, for a mesh with a coordinate that f32 cannot hold to its relative
    /// precision (beyond its range, or below its normal numbers).
    Inline(Vec<[DVec3; 3]>),
}

impl Mesh {
    /// The mesh of these vertices and triangles. Its positions are rounded to f32 where every
    /// coordinate is zero or within f32's normal range (as Embree and pbrt-v4 store
    /// vertices): a change below the 7 significant digits OBJ files carry, which cuts what a
    /// ray reads in a leaf from 112 bytes a triangle to the f32 block's 40 (the f64 corners
    /// were the other 72). The exact f64 triangle test runs on those values, and a vertex
    /// shared by two triangles is rounded alike in both, so hits stay watertight.
    pub fn new(
        positions: &[DVec3],
        normals: Vec<DVec3>,
        tex_coords: Vec<DVec2>,
        triangles: &[[u32; 3]],
    ) -> Mesh {
        let in_blocks = positions
            .iter()
            .all(|p| p.to_array().into_iter().all(fits_f32));
        let rounded: Vec<DVec3>;
        let positions = if in_blocks {
            rounded = positions.iter().map(|p| p.as_vec3().as_dvec3()).collect();
            &rounded
        } else {
            positions
        };
        let corner_of = |i: usize| triangles[i].map(|v| positions[v as usize]);
        Mesh::in_leaf_order(corner_of, triangles, in_blocks, normals, tex_coords)
    }

    /// The f64 corners of triangle slot `slot` (zeros for a padding slot).
    #[inline(always)]
    pub fn corners(&self, slot: usize) -> [DVec3; 3] {
        match &self.corners {
            Corners::InBlocks => self.blocks[slot / BLOCK].corners(slot % BLOCK),
            Corners::Inline(corners) => corners[slot],
        }
    }

    /// Triangle slots, padding included.
    pub fn slots(&self) -> usize {
        self.indices.len()
    }

    /// Whether a ray leaving triangle slot `slot` toward the side its winding normal points
    /// to (`front`), or toward the other, can meet no triangle of the mesh: the whole mesh
    /// lies on the plane or beyond it, and the ray, spawned off the plane on its own side,
    /// heads away from it (a convex mesh's outward rays, from every face).
    #[inline]
    pub fn exits(&self, slot: u32, front: bool) -> bool {
        let bit = if front { FRONT_EXITS } else { BACK_EXITS };
        self.exits.get(slot as usize).is_some_and(|&e| e & bit != 0)
    }

    /// [`Mesh::exits`] for every slot, tested against the eight corners of the mesh's box
    /// (which hold every vertex): exact where the mesh is a box with faces on its box's
    /// planes, and never claimed where rounding leaves a corner a hair beyond a plane.
    fn exits_by_slot(&self) -> Vec<u8> {
        let b = self.bvh.bounds();
        if !(b.min.is_finite() && b.max.is_finite()) {
            return vec![0; self.slots()];
        }
        let box_corners: [DVec3; 8] = std::array::from_fn(|k| {
            DVec3::new(
                if k & 1 == 0 { b.min.x } else { b.max.x },
                if k & 2 == 0 { b.min.y } else { b.max.y },
                if k & 4 == 0 { b.min.z } else { b.max.z },
            )
        });
        (0..self.slots())
            .map(|slot| {
                if self.indices[slot] == PADDING_TRIANGLE {
                    return 0;
                }
                let [p0, p1, p2] = self.corners(slot);
                let n = (p1 - p0).cross(p2 - p0);
                if n == DVec3::ZERO || !n.is_finite() {
                    return 0;
                }
                let sides = box_corners.map(|c| n.dot(c - p0));
                let mut exits = 0;
                if sides.iter().all(|&d| d <= 0.0) {
                    exits |= FRONT_EXITS;
                }
                if sides.iter().all(|&d| d >= 0.0) {
                    exits |= BACK_EXITS;
                }
                exits
            })
            .collect()
    }

    /// Bytes of the f64 corners (none where the blocks hold them).
    pub fn corner_bytes(&self) -> usize {
        match &self.corners {
            Corners::InBlocks => 0,
            Corners::Inline(corners) => size_of_val(&corners[..]),
        }
    }

    /// Bytes of the triangle data rays read in its leaves: f32 blocks and any f64 corners.
    pub fn leaf_bytes(&self) -> usize {
        size_of_val(&self.blocks[..]) + self.corner_bytes()
    }

    /// Whether the mesh outgrows the last-level cache (see [`LARGE_MESH_FROM`]).
    #[inline]
    pub fn large(&self) -> bool {
        self.leaf_bytes() >= LARGE_MESH_FROM
    }

    /// Starts fetching what the exact test of slots `tris` reads (a hint: nothing is read).
    #[inline(always)]
    fn prefetch_leaf(&self, tris: std::ops::Range<usize>) {
        match &self.corners {
            Corners::InBlocks => prefetch_blocks(&self.blocks, tris),
            Corners::Inline(corners) => prefetch_leaf(&self.blocks, corners, tris),
        }
    }

    /// The same mesh with its BVH built again from scratch (benchmarks time this).
    pub fn rebuilt(&self) -> Mesh {
        let in_blocks = matches!(self.corners, Corners::InBlocks);
        Mesh::in_leaf_order(
            |i| self.corners(i),
            &self.indices,
            in_blocks,
            self.normals.clone(),
            self.tex_coords.clone(),
        )
    }

    /// Builds the BVH over the triangles `indices` (padding slots are skipped), whose f64
    /// corners `corner_of` gives, and stores them in its leaf order: f32 blocks, and f64
    /// corners unless `in_blocks` (the corners are f32 values, the blocks hold them).
    fn in_leaf_order(
        corner_of: impl Fn(usize) -> [DVec3; 3] + Sync,
        indices: &[[u32; 3]],
        in_blocks: bool,
        normals: Vec<DVec3>,
        tex_coords: Vec<DVec2>,
    ) -> Mesh {
        use rayon::prelude::*;
        let live: Vec<u32> = (0..indices.len() as u32)
            .filter(|&i| indices[i as usize] != PADDING_TRIANGLE)
            .collect();
        let bounds: Vec<Aabb> = live
            .par_iter()
            .map(|&i| Aabb::from_points(&corner_of(i as usize)))
            .collect();
        let mut bvh = Bvh::build_aligned(&bounds, BLOCK);
        drop(bounds);
        // What rays read is laid out on huge pages where large (`with_capacity_huge`).
        let slots = bvh.order.len();
        let corner_at = |o: u32| match o {
            PADDING => [DVec3::ZERO; 3],
            o => corner_of(live[o as usize] as usize),
        };
        let mut sorted_indices = Vec::new();
        bvh.order
            .par_iter()
            .map(|&o| match o {
                PADDING => PADDING_TRIANGLE,
                o => indices[live[o as usize] as usize],
            })
            .collect_into_vec(&mut sorted_indices);
        // The blocks straight from the leaf order, without f64 corners in leaf order made for
        // them: 72 bytes a triangle (720 MB at 10 M triangles), dropped at once where the
        // blocks hold the corners.
        let mut blocks = with_capacity_huge(slots.div_ceil(BLOCK));
        bvh.order
            .par_chunks(BLOCK)
            .map(|chunk| {
                let mut corners = [[DVec3::ZERO; 3]; BLOCK];
                for (c, &o) in corners.iter_mut().zip(chunk) {
                    *c = corner_at(o);
                }
                TriangleBlock::new(&corners[..chunk.len()])
            })
            .collect_into_vec(&mut blocks);
        let corners = if in_blocks {
            debug_assert!(
                (0..slots).all(|s| blocks[s / BLOCK].corners(s % BLOCK) == corner_at(bvh.order[s]))
            );
            Corners::InBlocks
        } else {
            let mut sorted = with_capacity_huge(slots);
            bvh.order
                .par_iter()
                .map(|&o| corner_at(o))
                .collect_into_vec(&mut sorted);
            Corners::Inline(sorted)
        };
        // The triangles are stored in leaf order now; the order itself is not needed again.
        bvh.order = Vec::new();
        let mut mesh = Mesh {
            corners,
            indices: sorted_indices,
            normals,
            tex_coords,
            bvh,
            blocks,
            exits: Vec::new(),
        };
        if mesh.slots() <= EXITS_UP_TO {
            mesh.exits = mesh.exits_by_slot();
        }
        if mesh.large() {
            mesh.bvh = std::mem::take(&mut mesh.bvh).with_spans();
        }
        mesh
    }
}

/// Whether `v` rounded to f32 keeps f32's full relative precision: zero, or a finite value
/// within the normal range (NaN and infinities stay f64, so they stay what they are).
fn fits_f32(v: f64) -> bool {
    v == 0.0 || (v.abs() >= f32::MIN_POSITIVE as f64 && v.abs() <= f32::MAX as f64)
}

/// Meshes whose leaf data (f32 blocks and any f64 corners) is at least this large have the
/// leaves a packet reaches at a node prefetched before they are tested
/// ([`Bvh::traverse_packet`]'s `fetch`): such a mesh outgrows the last-level cache, so each
/// leaf is a memory miss, and the misses overlap. A smaller one mostly stays in cache, where
/// the prefetches are only instructions (the 100k-triangle dragon, then 11 MB of leaf data,
/// ran 6-10% slower with them).
const LARGE_MESH_FROM: usize = 32 << 20;

/// A world box around an instance of `mesh`: the transformed boxes near the root of its BVH,
/// joined, and cut to the transformed root box. A rotated instance's transformed root box
/// takes in much empty space (its corners), and in a crowd of instances every ray that
/// crosses that space enters the instance for nothing.
fn instance_bounds(mesh: &Mesh, transform: &Transform) -> Aabb {
    let whole = transform.bounds_to_world(mesh.bvh.bounds());
    let parts = mesh
        .bvh
        .boxes_near_root()
        .into_iter()
        .fold(Aabb::EMPTY, |acc, b| {
            acc.union(transform.bounds_to_world(b))
        });
    Aabb {
        min: whole.min.max(parts.min),
        max: whole.max.min(parts.max),
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

/// A sphere, scene triangle or model that moves. It is intersected by taking the ray into
/// its local space at the ray's time, so the top-level BVH is built once, over bounds that
/// cover the whole animation, and static objects pay nothing for it.
#[derive(Clone, Debug)]
pub struct Mover {
    pub shape: MoverShape,
    /// The transform at time 0, and how it changes.
    pub base: TransformDesc,
    pub motion: Motion,
}

#[derive(Clone, Debug)]
pub enum MoverShape {
    Sphere {
        radius: f64,
        material: u32,
    },
    /// A scene triangle in its own local space.
    Triangle(WorldTriangle),
    Model {
        mesh: u32,
        material: u32,
    },
}

impl Mover {
    pub fn transform_at(&self, time: f64) -> Transform {
        let t = self.motion.at(&self.base, time);
        Transform::new(t.position, t.orientation, t.scale)
    }

    fn local_bounds(&self, meshes: &[Mesh]) -> Aabb {
        match &self.shape {
            MoverShape::Sphere { radius, .. } => {
                let r = DVec3::splat(*radius);
                Aabb { min: -r, max: r }
            }
            MoverShape::Triangle(t) => Aabb::from_points(&t.positions),
            MoverShape::Model { mesh, .. } => meshes[*mesh as usize].bvh.bounds(),
        }
    }

    /// World bounds over times in `span`: the local box's corners at every key and at fine
    /// steps between, padded by the largest step a corner takes, so the swept path between
    /// samples stays inside.
    pub fn bounds(&self, meshes: &[Mesh], span: (f64, f64)) -> Aabb {
        let corners = self.local_bounds(meshes).corners();
        let mut times: Vec<f64> = self
            .motion
            .key_times()
            .filter(|t| *t > span.0 && *t < span.1)
            .collect();
        times.insert(0, span.0);
        times.push(span.1);
        let spin_rate = self.motion.spin.map_or(0.0, |(_, rate)| rate.abs());
        let mut bounds = Aabb::EMPTY;
        let mut pad = 0.0f64;
        let mut previous: Option<[DVec3; 8]> = None;
        for pair in times.windows(2) {
            let (a, b) = (pair[0], pair[1]);
            // Steps of at most ~1° of spin keep the padding small.
            let steps = (64.0f64)
                .max((spin_rate * (b - a) / 0.02).ceil())
                .min(16_384.0) as usize;
            for i in 0..=steps {
                let t = a + (b - a) * i as f64 / steps as f64;
                let xf = self.transform_at(t);
                let world = corners.map(|c| xf.to_world.transform_point3(c));
                bounds = bounds.union(Aabb::from_points(&world));
                if let Some(prev) = previous {
                    for (p, q) in prev.iter().zip(&world) {
                        pad = pad.max(p.distance(*q));
                    }
                }
                previous = Some(world);
            }
        }
        Aabb {
            min: bounds.min - DVec3::splat(pad),
            max: bounds.max + DVec3::splat(pad),
        }
    }
}

#[derive(Clone, Copy, Debug)]
enum Object {
    Sphere(u32),
    /// A sphere whose transform only translates (no rotation, unit scale: the course's).
    TranslatedSphere(u32),
    Triangle(u32),
    Model(u32),
    Mover(u32),
    /// One triangle of a small static model, in world space (see [`FLAT_MODEL_LIMIT`]).
    ModelTriangle(u32),
}

/// Static models whose mesh has at most this many triangles are not instanced: their
/// triangles join the top-level BVH in world space. Entering an instance (taking the ray to
/// local space, setting up its triangle test and traversing the mesh's BVH) cost ~500
/// instructions per model a ray meets, more than testing a few world-space triangles; the
/// course's cubes (12 triangles) are the case. t and the barycentrics then come from the
/// world-space corners, equal to the local-space ones up to rounding (barycentrics are
/// invariant under affine maps); shading still reads the mesh through the model.
pub const FLAT_MODEL_LIMIT: usize = 32;

/// Small models are flattened only when a scene has at least this many: a lone one costs a
/// ray one instance box, which turns most rays away before any set-up, while its triangles'
/// overlapping boxes at the top level cost every ray near it several tests (cube.scene, one
/// 12-triangle cube: 8% slower flattened; stacks.scene, five: 20% faster).
pub const FLAT_MODELS_MIN: usize = 2;

/// The top-level SAH's cost of testing a mesh instance (or a mover), in node visits; a sphere
/// or a triangle costs one. Entering an instance takes several times a node visit's work (see
/// [`FLAT_MODEL_LIMIT`]); 4 and 16 gave the 10,000-dragon scene the same tree.
const INSTANCE_INTERSECT_COST: f64 = 4.0;

/// Scenes of at most this many top-level objects, all of them spheres or triangles, test each
/// in turn instead of walking the top level: their exact tests cost about what the walk's box
/// tests do (test.scene, two spheres and a triangle: 3% faster). A model is left to the walk,
/// whose box turns most rays away before the model's set-up (cube.scene tested linearly:
/// 17% slower), unless it is the only object: its own test is exact, so its box adds nothing.
const LINEAR_TOP: usize = 4;

/// A triangle of a flattened model: its world-space corners, the model, and its slot in
/// the mesh.
#[derive(Clone, Copy, Debug)]
struct ModelTriangle {
    corners: [DVec3; 3],
    model: u32,
    prim: u32,
}

/// A block of pixels' candidate slots ([`World::block_candidates`]), reused block after block.
#[derive(Clone, Debug, Default)]
pub struct BlockSlots {
    slots: Vec<u32>,
    /// Per slot, whether a pixel must test its frustum against it.
    tested: Vec<bool>,
    /// Per slot of a mesh instance, the mesh's triangle that last met a pixel's frustum
    /// ([`NO_TRIANGLE_HINT`]: none yet), tried before the mesh's walk: the next pixel's
    /// frustum mostly meets it too.
    hints: Vec<u32>,
}

/// A mesh-triangle hint of [`World::may_meet_frustum`] that names no triangle: the walk
/// runs at once. (A hint of 0 would test triangle 0 first, for nothing.)
const NO_TRIANGLE_HINT: u32 = u32::MAX;

/// The surface a spawned ray leaves, and with it the objects it cannot meet (it starts nudged
/// off the surface to the side it heads for):
/// - off a triangle on an axis-aligned plane, every triangle on that plane (coplanarity is
///   then exact); off any other triangle, that triangle;
/// - off a sphere (or ellipsoid) heading out of it, that sphere: it is convex.
///
/// - off a triangle of a mesh model, that triangle (the model's other triangles are tested).
///
/// Those are skipped without a test: a floor's or a wall's own triangles, or the sphere
/// itself, which every shadow and mirror ray leaving it would otherwise test and miss; in a
/// mesh, the triangle under the ray's origin, which passes the f32 pre-test (its edges
/// enclose the origin) and would cost every ray off a mesh one exact test.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Leaving {
    surface: u32,
    /// The mesh model's top-level slot and the triangle slot within its mesh, or
    /// [`NO_MESH_TRIANGLE`].
    mesh_triangle: (u32, u32),
}

impl Leaving {
    /// A ray that leaves nothing it cannot meet again (an eye ray, a ray into a sphere, or
    /// one leaving a mover).
    pub const NOTHING: Leaving = Leaving {
        surface: u32::MAX - 1,
        mesh_triangle: NO_MESH_TRIANGLE,
    };

    /// The triangle slot within the mesh of top-level `slot` that the ray leaves, or
    /// [`NO_PRIM`].
    #[inline(always)]
    fn prim_in(self, slot: usize) -> u32 {
        if self.mesh_triangle.0 == slot as u32 {
            self.mesh_triangle.1
        } else {
            NO_PRIM
        }
    }
}

/// [`Leaving::mesh_triangle`] of a ray that leaves no mesh triangle.
const NO_MESH_TRIANGLE: (u32, u32) = (u32::MAX, u32::MAX);

/// A triangle slot no mesh has: [`World::hit_object`] skips nothing.
const NO_PRIM: u32 = u32::MAX;

/// [`World::slot_surface`] of a slot no ray skips; never equal to a [`Leaving`].
const NO_SURFACE: u32 = u32::MAX;

/// What [`World::occluded_by`] remembers of a family of shadow rays: the object that blocked
/// the last one, if it was blocked, and the triangle slot within its mesh that did.
#[derive(Clone, Debug, Default)]
pub struct ShadowCache {
    last: Option<u32>,
    prim: u32,
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

impl Hit {
    /// The top-level object hit (see [`World::object_materials`]).
    #[inline]
    pub fn object(&self) -> u32 {
        self.object
    }
}

/// The geometry at a hit point: everything shading needs except the material's values.
#[derive(Clone, Copy, Debug)]
pub struct Patch<'a> {
    pub position: DVec3,
    /// Interpolated shading normal, unit length, pointing out of the surface as modelled.
    pub normal: DVec3,
    /// Geometric normal (same side as `normal`'s intent), for offsetting spawned rays.
    pub geometric_normal: DVec3,
    /// Texture coordinates at the hit.
    pub uv: Uv<'a>,
    pub material: MaterialAt,
}

/// Texture coordinates at a hit, worked out only where a texture is read: a sphere's take
/// an arc tangent and an arc cosine, a mesh's three more loads, and most surfaces have no
/// texture.
#[derive(Clone, Copy, Debug)]
pub enum Uv<'a> {
    At(DVec2),
    /// A sphere's unit local-space point ([`sphere_uv`]).
    Sphere(DVec3),
    /// A mesh triangle's corner coordinates, blended by barycentrics.
    Mesh {
        coords: &'a [DVec2],
        corners: [u32; 3],
        bary: [f64; 3],
    },
}

impl Uv<'_> {
    #[inline(always)]
    pub fn get(self) -> DVec2 {
        match self {
            Uv::At(uv) => uv,
            Uv::Sphere(unit) => sphere_uv(unit),
            Uv::Mesh {
                coords,
                corners: [i0, i1, i2],
                bary: [_, b1, b2],
            } => corner_lerp(
                [
                    coords[i0 as usize],
                    coords[i1 as usize],
                    coords[i2 as usize],
                ],
                b1,
                b2,
            ),
        }
    }
}

/// Which material applies at a hit.
#[derive(Clone, Copy, Debug)]
pub enum MaterialAt {
    /// One material for the whole object (spheres, models).
    One(u32),
    /// A scene triangle's three vertex materials, blended by the hit's barycentrics.
    Blend { materials: [u32; 3], bary: [f64; 3] },
}

#[derive(Clone, Debug, Default)]
pub struct World {
    pub spheres: Vec<Sphere>,
    pub triangles: Vec<WorldTriangle>,
    pub meshes: Vec<Mesh>,
    pub models: Vec<Model>,
    pub movers: Vec<Mover>,
    /// Times (in frames) the movers' bounds cover.
    pub time_span: (f64, f64),
    objects: Vec<Object>,
    /// Per scene triangle, its unit geometric normal (made once: a hit on a floor or a wall
    /// would otherwise take a cross product and a square root), and its unit shading normal
    /// where its three vertex normals are one (see [`flat_normal`]).
    triangle_normals: Vec<(DVec3, Option<DVec3>)>,
    model_triangles: Vec<ModelTriangle>,
    top: Bvh,
    /// `top`'s nodes in the layout of the top level's own traversal.
    top_level: TopLevel,
    /// Per top-level slot, what a ray leaving it skips ([`Leaving`]): an index shared by
    /// every triangle on one axis-aligned plane, the slot's own for another triangle, a
    /// sphere or a mesh instance (skipped whole only by rays its mesh lies behind), or
    /// [`NO_SURFACE`].
    slot_surface: Vec<u32>,
    /// Per surface (an index of `slot_surface`), what a ray leaving it tests instead of
    /// walking `top` ([`OffSurface`], see [`World::traverse_top`]); None where it walks `top`.
    off_surface: Vec<Option<OffSurface>>,
    /// Whether rays test every object in turn rather than walk `top`: a single object, or a
    /// few spheres and triangles ([`LINEAR_TOP`]).
    linear_top: bool,
    /// Whether the top level holds mesh instances or movers, whose tests cost many node
    /// visits: closest-hit walks then take leaves nearest first ([`TopLevel::walk_nearest`]),
    /// and a frustum's slots list instances nearest first (`nearest_instances_first`).
    costly_top: bool,
    /// Per model, its instance's world box ([`instance_bounds`]; empty for a flattened
    /// model), against which a packet's rays are tested one by one before they enter it.
    model_bounds: Vec<Aabb>,
}

impl World {
    /// A world with moving objects too, whose rays' times lie in `time_span`.
    pub fn with_movers(
        spheres: Vec<Sphere>,
        triangles: Vec<WorldTriangle>,
        meshes: Vec<Mesh>,
        models: Vec<Model>,
        movers: Vec<Mover>,
        time_span: (f64, f64),
    ) -> World {
        let mut objects = Vec::new();
        let mut bounds = Vec::new();
        for (i, s) in spheres.iter().enumerate() {
            objects.push(if s.transform.to_local.matrix3 == DMat3::IDENTITY {
                Object::TranslatedSphere(i as u32)
            } else {
                Object::Sphere(i as u32)
            });
            let r = DVec3::splat(s.radius);
            bounds.push(s.transform.bounds_to_world(Aabb { min: -r, max: r }));
        }
        for (i, t) in triangles.iter().enumerate() {
            objects.push(Object::Triangle(i as u32));
            bounds.push(Aabb::from_points(&t.positions));
        }
        let mut model_triangles = Vec::new();
        let mut model_bounds = vec![Aabb::EMPTY; models.len()];
        // Which models are small enough to flatten; none are unless there are several.
        // Counted per mesh, not per model: 10,000 instances of one 100,000-triangle mesh
        // counted its triangles 10,000 times (most of that scene's build time).
        let small_meshes: Vec<bool> = (meshes.iter())
            .map(|mesh| {
                let live = mesh.indices.iter().filter(|&&t| t != PADDING_TRIANGLE);
                live.count() <= FLAT_MODEL_LIMIT
            })
            .collect();
        let mut small: Vec<bool> = models
            .iter()
            .map(|m| small_meshes[m.mesh as usize])
            .collect();
        if small.iter().filter(|&&s| s).count() < FLAT_MODELS_MIN {
            small.fill(false);
        }
        for (i, m) in models.iter().enumerate() {
            let mesh = &meshes[m.mesh as usize];
            if small[i] {
                let live =
                    (0..mesh.indices.len()).filter(|&slot| mesh.indices[slot] != PADDING_TRIANGLE);
                for slot in live {
                    let corners = mesh
                        .corners(slot)
                        .map(|c| m.transform.to_world.transform_point3(c));
                    objects.push(Object::ModelTriangle(model_triangles.len() as u32));
                    bounds.push(Aabb::from_points(&corners));
                    model_triangles.push(ModelTriangle {
                        corners,
                        model: i as u32,
                        prim: slot as u32,
                    });
                }
                continue;
            }
            objects.push(Object::Model(i as u32));
            model_bounds[i] = instance_bounds(mesh, &m.transform);
            bounds.push(model_bounds[i]);
        }
        for (i, m) in movers.iter().enumerate() {
            objects.push(Object::Mover(i as u32));
            bounds.push(m.bounds(&meshes, time_span));
        }
        // A mesh instance's test (a transform and a walk of its mesh) costs several node
        // visits: the SAH gets the objects' mean cost, so a top level of instances gives each
        // its own leaf (two thirds of the 10,000-dragon scene's leaves held two or three,
        // and its rays tested both), while spheres and triangles keep theirs as before.
        let costly = (objects.iter())
            .filter(|o| matches!(o, Object::Model(_) | Object::Mover(_)))
            .count();
        let mean_cost =
            1.0 + (INSTANCE_INTERSECT_COST - 1.0) * costly as f64 / objects.len().max(1) as f64;
        let top = Bvh::build_costed(&bounds, mean_cost);
        let objects: Vec<Object> = top.order.iter().map(|&o| objects[o as usize]).collect();
        let slot_surface = surfaces(&objects, &triangles, &model_triangles);
        let slot_bounds: Vec<Aabb> = top.order.iter().map(|&o| bounds[o as usize]).collect();
        let off_surface = off_surfaces(&objects, &slot_surface, &slot_bounds, mean_cost);
        let top_level = TopLevel::new(&top);
        let triangle_normals = triangles
            .iter()
            .map(|t| (geometric_normal(t), flat_normal(t)))
            .collect();
        let linear_top = objects.len() == 1
            || objects.len() <= LINEAR_TOP
                && objects
                    .iter()
                    .all(|o| !matches!(o, Object::Model(_) | Object::Mover(_)));
        World {
            spheres,
            triangles,
            meshes,
            models,
            movers,
            time_span,
            objects,
            triangle_normals,
            model_triangles,
            top,
            top_level,
            slot_surface,
            off_surface,
            linear_top,
            costly_top: costly > 0,
            model_bounds,
        }
    }

    pub fn bounds(&self) -> Aabb {
        self.top.bounds()
    }

    /// Every BVH built again, meshes in parallel (what `tracer bench` reports as build time).
    pub fn rebuilt(&self) -> World {
        use rayon::prelude::*;
        let meshes = self.meshes.par_iter().map(Mesh::rebuilt).collect();
        World::with_movers(
            self.spheres.clone(),
            self.triangles.clone(),
            meshes,
            self.models.clone(),
            self.movers.clone(),
            self.time_span,
        )
    }

    /// Hands `test` every top-level slot the ray may reach before `*t_max` (which `test`
    /// shrinks), nearest first, or with `ANY` farthest first until `test` returns true. The
    /// traversal is skipped where every slot is tested in turn (a single object, or a few
    /// spheres and triangles: `linear_top`), and rays outside the f32 box test's range take
    /// the generic one.
    ///
    /// A ray leaving a surface takes what `off_surface` has for it: the surface's own slots,
    /// which `test` would skip, hold the ray's origin, so the walk would enter their boxes
    /// for nothing (a shadow ray off cube.scene's floor walked both floor triangles' leaves
    /// to reach the cube's).
    #[inline(always)]
    fn traverse_top<const ANY: bool>(
        &self,
        ray: &Ray,
        t_max: &mut f64,
        leaving: Leaving,
        mut test: impl FnMut(usize, &mut f64) -> bool,
    ) -> bool {
        match self.off_surface.get(leaving.surface as usize) {
            Some(Some(OffSurface::Listed(rest))) => {
                return self.test_in_turn(rest, ray, t_max, test);
            }
            Some(Some(OffSurface::Walked(sub))) => {
                let leaf = |positions: std::ops::Range<usize>, t_max: &mut f64| {
                    for &slot in &sub.slots[positions] {
                        if test(slot as usize, t_max) {
                            return true;
                        }
                    }
                    false
                };
                return walk_top::<ANY>(&sub.bvh, &sub.level, sub.costly, ray, t_max, leaf);
            }
            _ => {}
        }
        let mut leaf = |slots: std::ops::Range<usize>, t_max: &mut f64| {
            for slot in slots {
                if test(slot, t_max) {
                    return true;
                }
            }
            false
        };
        if self.linear_top {
            return leaf(0..self.objects.len(), t_max);
        }
        walk_top::<ANY>(
            &self.top,
            &self.top_level,
            self.costly_top,
            ray,
            t_max,
            leaf,
        )
    }

    /// `test` on each of `slots` in turn, a mesh instance only where the ray may enter its
    /// box, until it returns true.
    #[inline(always)]
    fn test_in_turn(
        &self,
        slots: &[u32],
        ray: &Ray,
        t_max: &mut f64,
        mut test: impl FnMut(usize, &mut f64) -> bool,
    ) -> bool {
        for &slot in slots {
            let slot = slot as usize;
            if let Object::Model(i) = self.objects[slot] {
                if !may_enter(&self.model_bounds[i as usize], ray, 0.0, *t_max) {
                    continue;
                }
            }
            if test(slot, t_max) {
                return true;
            }
        }
        false
    }

    /// The nearest hit with t in (t_min, t_max); `ray.dir` need not be unit length.
    pub fn intersect(&self, ray: &Ray, t_min: f64, t_max: f64) -> Option<Hit> {
        self.intersect_leaving(ray, t_min, t_max, Leaving::NOTHING)
    }

    /// [`World::intersect`] for a ray spawned off a surface that `leaving` names (see
    /// [`World::leaving`]): the same hit, without testing the triangles it cannot meet.
    pub fn intersect_leaving(
        &self,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        leaving: Leaving,
    ) -> Option<Hit> {
        // Set up on the first scene triangle only: rays that meet none (every ray of a
        // mesh-only scene) skip its divisions.
        let mut world_tri_ray = None;
        let mut best: Option<Hit> = None;
        let mut t_max = t_max;
        self.traverse_top::<false>(ray, &mut t_max, leaving, |slot, t_max| {
            if self.skips(slot, leaving) {
                return false;
            }
            let bound = tie_bound(best.is_some(), *t_max);
            if let Some(h) = self.hit_object::<false>(
                slot,
                ray,
                t_min,
                bound,
                leaving.prim_in(slot),
                &mut world_tri_ray,
            ) {
                keep_nearer(&mut best, t_max, slot, h);
            }
            false
        });
        best
    }

    /// The top-level slots a bundle of rays from `origin` between the planes through it with
    /// inward normals `planes` may hit (see [`crate::camera::EyeRays::pixel_frustum`]), into
    /// `slots`, for [`World::intersect_among`].
    pub fn frustum_slots(&self, origin: DVec3, planes: &[DVec3; 4], slots: &mut Vec<u32>) {
        self.frustum_slots_leaving(origin, planes, Leaving::NOTHING, slots);
    }

    /// [`World::frustum_slots`] less the slots a ray leaving `leaving` skips (which are not
    /// tested against the frustum at all).
    fn frustum_slots_leaving(
        &self,
        origin: DVec3,
        planes: &[DVec3; 4],
        leaving: Leaving,
        slots: &mut Vec<u32>,
    ) {
        slots.clear();
        // Made for the first triangle met (a frustum that meets none, as among spheres, never
        // needs them).
        let mut edges = None;
        // A single object too: pixels whose frustum misses its box (most of dragon.scene's)
        // then test nothing at all.
        self.top_level.frustum(origin, planes, &mut |range| {
            slots.extend(
                range
                    .filter(|&slot| {
                        // A fresh hint per slot: one set by a mesh's walk names a triangle of
                        // that mesh only.
                        let mut no_hint = NO_TRIANGLE_HINT;
                        !self.skips(slot, leaving)
                            && self.may_meet_frustum(slot, origin, planes, &mut edges, &mut no_hint)
                    })
                    .map(|s| s as u32),
            )
        });
        if self.costly_top && slots.len() > 1 {
            self.nearest_instances_first(origin, slots);
        }
    }

    /// The top-level slots the frustum of a block of pixels (apex `origin`, inward normals
    /// `planes`, enclosing each of its pixels' frustums) may hit, for
    /// [`World::frustum_slots_among`]: found once for the block, they spare each pixel the
    /// top-level walk, and a triangle whose cone from the apex holds the whole block's
    /// frustum (a floor seen through a block) is kept for every pixel without a test.
    pub fn block_candidates(&self, origin: DVec3, planes: &[DVec3; 4], out: &mut BlockSlots) {
        self.frustum_slots(origin, planes, &mut out.slots);
        let mut edges = None;
        out.tested.clear();
        out.tested.extend(out.slots.iter().map(|&slot| {
            let corners = match self.objects[slot as usize] {
                Object::Triangle(i) => &self.triangles[i as usize].positions,
                Object::ModelTriangle(i) => &self.model_triangles[i as usize].corners,
                _ => return true,
            };
            !triangle_holds_frustum(
                corners,
                origin,
                edges.get_or_insert_with(|| frustum_edges(planes)),
            )
        }));
        out.hints.clear();
        out.hints.resize(out.slots.len(), NO_TRIANGLE_HINT);
    }

    /// [`World::frustum_slots`] of a pixel inside a block, from the block's
    /// [`World::block_candidates`]: each candidate the pixel's frustum may meet, in the
    /// block's order (already nearest instances first). It keeps every slot the pixel's eye
    /// rays can hit (a slot the block's frustum leaves out lies outside each of its pixels'),
    /// and [`World::intersect_among`] finds the same hit among any such slots.
    pub fn frustum_slots_among(
        &self,
        origin: DVec3,
        planes: &[DVec3; 4],
        block: &mut BlockSlots,
        slots: &mut Vec<u32>,
    ) {
        slots.clear();
        let mut edges = None;
        let candidates = block.slots.iter().zip(&block.tested).zip(&mut block.hints);
        for ((&slot, &tested), hint) in candidates {
            if !tested || self.may_meet_frustum(slot as usize, origin, planes, &mut edges, hint) {
                slots.push(slot);
            }
        }
    }

    /// Orders `slots` so that mesh instances come nearest first by their boxes' distance
    /// from `origin` (a frustum's apex), after every other object: the bundle's rays then
    /// meet a near instance before a far one, whose walk a near hit culls (at its root for a
    /// single ray, before it is entered for a packet's, see `object_packet`). Any order finds
    /// the same hits.
    fn nearest_instances_first(&self, origin: DVec3, slots: &mut [u32]) {
        slots.sort_unstable_by(|&a, &b| {
            let (ka, kb) = (self.slot_order(a, origin), self.slot_order(b, origin));
            ka.total_cmp(&kb).then(a.cmp(&b))
        });
    }

    /// The key [`World::nearest_instances_first`] sorts by: a mesh instance's squared box
    /// distance from `origin`, -1 for every other object.
    fn slot_order(&self, slot: u32, origin: DVec3) -> f64 {
        match self.objects[slot as usize] {
            Object::Model(i) => self.model_bounds[i as usize].distance_squared(origin),
            _ => -1.0,
        }
    }

    /// The axis-aligned plane (axis, coordinate) of the scene triangle `hit` lies on, where
    /// every corner's normal is that plane's (see [`World::mirror_slots`]); None elsewhere.
    #[inline]
    pub fn mirror_plane(&self, hit: &Hit) -> Option<(usize, f64)> {
        let Object::Triangle(i) = self.objects[hit.object as usize] else {
            return None;
        };
        let t = &self.triangles[i as usize];
        let n = t.normals[0];
        let axis = (0..3).find(|&a| n[a] != 0.0)?;
        let along_axis = (0..3).all(|a| a == axis || n[a] == 0.0);
        let c = t.positions[0][axis];
        let flat = t.positions.iter().all(|p| p[axis] == c) && t.normals.iter().all(|m| *m == n);
        (along_axis && flat).then_some((axis, c))
    }

    /// The top-level slots that mirror rays off the plane `(axis, c)` (a
    /// [`World::mirror_plane`]) may meet, into `slots`, for the eye rays of the pixel frustum
    /// `eye` (apex and inward plane normals, as for [`World::frustum_slots`]) that hit it.
    ///
    /// On such a plane the shading normal is the unit axis, and `reflect` about it negates one
    /// coordinate of the eye ray's direction, exactly. So every mirror ray of the pixel lies on
    /// a line from the eye's mirror image through the mirrored frustum, beyond the plane: the
    /// mirrored frustum's slots, less what a ray leaving the plane skips (`leaving`), hold
    /// every object such a ray can meet, and [`World::intersect_among`] over them finds the
    /// hit [`World::intersect_leaving`] does. A mirror ray's origin differs from the exact
    /// point by its rounding and its offset off the plane, far inside the frustum's twentieth
    /// of a pixel.
    pub fn mirror_slots(
        &self,
        (axis, c): (usize, f64),
        (apex, planes): (DVec3, &[DVec3; 4]),
        leaving: Leaving,
        slots: &mut Vec<u32>,
    ) {
        let mut mirrored_apex = apex;
        mirrored_apex[axis] = 2.0 * c - apex[axis];
        let mirrored_planes = planes.map(|mut n| {
            n[axis] = -n[axis];
            n
        });
        self.frustum_slots_leaving(mirrored_apex, &mirrored_planes, leaving, slots);
    }

    /// Whether the object in `slot`, whose box meets the frustum, may itself: false when a
    /// sphere or triangle lies wholly behind one of the planes. A box takes in much that its
    /// object does not (a rotated ellipsoid's corners, a slanted triangle's half), and a
    /// pixel left with no slot needs no eye ray at all. The frustum is a twentieth of a pixel
    /// wider than its rays, far beyond the rounding of these tests. A triangle is also left
    /// out where the plane through the apex and one of its sides has the whole frustum on
    /// the far side (its edge directions, made into `edges` when first needed): the planes
    /// alone keep a large triangle beside the frustum, such as the half of cube.scene's floor
    /// a pixel does not see. For a mesh instance, `hint` names a triangle to try before the
    /// walk ([`NO_TRIANGLE_HINT`]: none) and is set to the one the walk stops at.
    fn may_meet_frustum(
        &self,
        slot: usize,
        origin: DVec3,
        planes: &[DVec3; 4],
        edges: &mut Option<[DVec3; 4]>,
        hint: &mut u32,
    ) -> bool {
        let mut behind_one = |corners| {
            triangle_behind_a_plane(corners, origin, planes)
                || triangle_beside_a_frustum(
                    corners,
                    origin,
                    edges.get_or_insert_with(|| frustum_edges(planes)),
                )
        };
        match self.objects[slot] {
            Object::Sphere(i) | Object::TranslatedSphere(i) => {
                // The world ellipsoid is M·p + c for |p| ≤ r: along a plane's normal n it
                // reaches at most n·(c − o) + r·|Mᵀn| past the plane (compared squared: no
                // square root per plane).
                let s = &self.spheres[i as usize];
                let m = s.transform.to_world.matrix3.transpose();
                let centre = s.transform.to_world.translation - origin;
                let r2 = s.radius * s.radius;
                !planes.iter().any(|&n| {
                    let d = n.dot(centre);
                    d < 0.0 && d * d > r2 * (m * n).length_squared()
                })
            }
            Object::Triangle(i) => !behind_one(&self.triangles[i as usize].positions),
            Object::ModelTriangle(i) => !behind_one(&self.model_triangles[i as usize].corners),
            Object::Model(i) => {
                // In the model's space the planes keep passing through the (mapped) apex,
                // with normals Mᵀn: n·(M·p + c − o) = (Mᵀn)·(p − M⁻¹(o − c)).
                let model = &self.models[i as usize];
                let m = model.transform.to_world.matrix3.transpose();
                let apex = model.transform.to_local.transform_point3(origin);
                let local = planes.map(|n| m * n);
                let mesh = &self.meshes[model.mesh as usize];
                // A triangle no plane has wholly behind it is one the walk would stop at.
                if (*hint as usize) < mesh.slots()
                    && !triangle_behind_a_plane(&mesh.corners(*hint as usize), apex, &local)
                {
                    return true;
                }
                let met = (!mesh.bvh.nodes.is_empty())
                    .then(|| mesh_meets_frustum(mesh, 0, apex, &local))
                    .flatten();
                if let Some(slot) = met {
                    *hint = slot;
                }
                met.is_some()
            }
            Object::Mover(_) => true,
        }
    }

    /// [`World::intersect`] for a ray that can hit nothing outside the top-level `slots`
    /// (a pixel's eye ray, with its pixel's [`World::frustum_slots`]): those slots are tested
    /// without a traversal. The nearest hit is the same (ties in t go to the lower slot,
    /// then the lower triangle slot, whatever the order of the tests).
    pub fn intersect_among(&self, ray: &Ray, t_min: f64, t_max: f64, slots: &[u32]) -> Option<Hit> {
        let mut world_tri_ray = None;
        let mut best: Option<Hit> = None;
        let mut t_max = t_max;
        for &slot in slots {
            let slot = slot as usize;
            let bound = tie_bound(best.is_some(), t_max);
            if let Some(h) =
                self.hit_object::<false>(slot, ray, t_min, bound, NO_PRIM, &mut world_tri_ray)
            {
                keep_nearer(&mut best, &mut t_max, slot, h);
            }
        }
        best
    }

    /// Whether [`World::intersect_among_lanes`] serves rays among these top-level slots:
    /// some slot is a scene triangle (which it tests four rays at a time) and none is a mesh
    /// model (whose packet walk serves them better, [`World::intersect_packet`]).
    pub fn lanes_among(&self, slots: &[u32]) -> bool {
        let kind = |slot: &u32| &self.objects[*slot as usize];
        slots.iter().any(|s| matches!(kind(s), Object::Triangle(_)))
            && !slots.iter().any(|s| matches!(kind(s), Object::Model(_)))
    }

    /// [`World::intersect_among`] for up to four rays at once (`hits[i]` for `rays[i]`):
    /// the same hits to the bit. Scene triangles are tested four rays at a time, each ray's
    /// watertight test in its own lane with the scalar test's operations in its order; other
    /// objects ray by ray, as `intersect_among` tests them. Rays whose sheared frames differ
    /// take `intersect_among` itself.
    pub fn intersect_among_lanes(
        &self,
        rays: &[&Ray],
        t_min: f64,
        t_max: f64,
        slots: &[u32],
        hits: &mut [Option<Hit>],
    ) {
        let n = rays.len();
        assert!(
            (1..=LANES).contains(&n) && hits.len() == n,
            "{n} rays for {LANES} lanes"
        );
        let tri_rays: [TriangleRay; LANES] =
            std::array::from_fn(|i| TriangleRay::new(rays[i.min(n - 1)]));
        if tri_rays[1..n]
            .iter()
            .any(|r| r.axes() != tri_rays[0].axes())
        {
            for (ray, hit) in rays.iter().zip(hits.iter_mut()) {
                *hit = self.intersect_among(ray, t_min, t_max, slots);
            }
            return;
        }
        let frame = LaneFrame::new(&tri_rays);
        let mut best: [Option<Hit>; LANES] = [None; LANES];
        let mut limit = [t_max; LANES];
        for &slot in slots {
            let slot = slot as usize;
            let bounds: [f64; LANES] =
                std::array::from_fn(|l| tie_bound(best[l].is_some(), limit[l]));
            let Object::Triangle(i) = self.objects[slot] else {
                for l in 0..n {
                    // The lane's own set-up, as `intersect_among` caches it for the ray.
                    let mut tri_ray = Some(tri_rays[l]);
                    let hit = self.hit_object::<false>(
                        slot,
                        rays[l],
                        t_min,
                        bounds[l],
                        NO_PRIM,
                        &mut tri_ray,
                    );
                    if let Some(h) = hit {
                        keep_nearer(&mut best[l], &mut limit[l], slot, h);
                    }
                }
                continue;
            };
            let found = frame.triangle(self.triangles[i as usize].positions, t_min, bounds);
            for l in 0..n {
                if let Some((t, bary)) = found[l] {
                    let h = ObjectHit { t, prim: 0, bary };
                    keep_nearer(&mut best[l], &mut limit[l], slot, h);
                }
            }
        }
        hits.copy_from_slice(&best[..n]);
    }

    /// Whether any of these top-level slots holds a mesh model (the only kind of object
    /// [`World::intersect_packet`] walks once for a whole packet).
    pub fn any_model_among(&self, slots: &[u32]) -> bool {
        slots
            .iter()
            .any(|&slot| matches!(self.objects[slot as usize], Object::Model(_)))
    }

    /// [`World::intersect`] for up to [`PACKET`] rays at once, into `hits` (one per ray),
    /// each the same hit `intersect` finds for that ray. Coherent rays (a block of eye rays)
    /// share the work: a mesh's BVH is walked once for the packet (see
    /// [`Bvh::traverse_packet`]), and a packet that misses an object's box skips it. `slots`,
    /// when given, holds every top-level slot any of the rays can hit (as for
    /// [`World::intersect_among`]). `spread` says how far the rays part ([`Spread`]); it
    /// changes the work, never the hits.
    pub fn intersect_packet(
        &self,
        rays: &[Ray],
        t_min: f64,
        t_max: f64,
        slots: Option<&[u32]>,
        spread: Spread,
        hits: &mut [Option<Hit>],
    ) {
        let n = rays.len();
        assert!(n <= PACKET && hits.len() == n, "a packet of {n} rays");
        hits.fill(None);
        let mut limits = [t_max; PACKET];
        let limits = &mut limits[..n];
        let mut world_tri_rays = [None; PACKET];
        let mut visit = |slot: usize, limits: &mut [f64]| {
            self.object_packet(slot, rays, t_min, limits, spread, hits, &mut world_tri_rays)
        };
        // Every object takes a packet whatever its rays (a mesh's walk falls back to single
        // rays where the f32 tests cannot take them); the packet's world-space bounds are
        // needed only to skip objects without being given the candidates.
        match slots {
            Some(slots) => {
                for &slot in slots {
                    visit(slot as usize, limits);
                }
            }
            None if self.objects.len() == 1 => {
                if PacketBounds::new(rays).is_none_or(|p| p.may_hit(&self.top.bounds(), t_max)) {
                    visit(0, limits);
                }
            }
            None => match PacketBounds::new(rays) {
                Some(packet) => {
                    self.top
                        .traverse_packet_leaves(&packet, limits, |slots, limits| {
                            for slot in slots {
                                visit(slot, limits);
                            }
                        });
                }
                None => {
                    for (ray, hit) in rays.iter().zip(hits) {
                        *hit = self.intersect(ray, t_min, t_max);
                    }
                }
            },
        }
    }

    /// The object in top-level slot `slot` against every ray of a packet, each ray's hit
    /// kept in `hits` where it is nearer (ties as in [`World::intersect`]); `limits` are the
    /// rays' current nearest distances.
    #[allow(clippy::too_many_arguments)]
    fn object_packet(
        &self,
        slot: usize,
        rays: &[Ray],
        t_min: f64,
        limits: &mut [f64],
        spread: Spread,
        hits: &mut [Option<Hit>],
        world_tri_rays: &mut [Option<TriangleRay>; PACKET],
    ) {
        let n = rays.len();
        let Object::Model(i) = self.objects[slot] else {
            for i in 0..n {
                let bound = tie_bound(hits[i].is_some(), limits[i]);
                let h = self.hit_object::<false>(
                    slot,
                    &rays[i],
                    t_min,
                    bound,
                    NO_PRIM,
                    &mut world_tri_rays[i],
                );
                if let Some(h) = h {
                    keep_nearer(&mut hits[i], &mut limits[i], slot, h);
                }
            }
            return;
        };
        let model = &self.models[i as usize];
        let mesh = &self.meshes[model.mesh as usize];
        let instance = &self.model_bounds[i as usize];
        // The rays that may meet the instance's box before their nearest hit so far, in local
        // space, packed; `index` maps them back. A packet reaches an instance where any of its
        // rays may, and among overlapping instances most of its rays miss each one or have
        // met a nearer one: taken into the walk, each paid a transform and the root's test
        // (the 10,000-dragon scene's primary packets ran 1.2x slower than single rays).
        // Left uninitialised past `live`: a pixel's packet holds a few rays, and filling 64
        // rays per object and pixel was a measurable share of a render.
        let mut local = [const { std::mem::MaybeUninit::<Ray>::uninit() }; PACKET];
        let mut bounds = [0.0; PACKET];
        let mut index = [0u8; PACKET];
        let mut live = 0;
        // (In a world of one object the packet has been tested against its box already, and
        // the few rays that miss it leave at the mesh's root: the test would only add work.)
        let filter = self.objects.len() > 1;
        for i in 0..n {
            let bound = tie_bound(hits[i].is_some(), limits[i]);
            if filter && !may_enter(instance, &rays[i], t_min, bound) {
                continue;
            }
            local[live].write(model.transform.ray_to_local(&rays[i]));
            bounds[live] = bound;
            index[live] = i as u8;
            live += 1;
        }
        if live == 0 {
            return;
        }
        // SAFETY: the first `live` entries were written above; MaybeUninit<Ray> has Ray's
        // layout.
        let local: &[Ray] =
            unsafe { std::slice::from_raw_parts(local.as_ptr().cast::<Ray>(), live) };
        // Each ray's triangle-test set-up, made when it first reaches a leaf.
        let mut tri_rays: [Option<(TriangleRay, TriangleRayF32)>; PACKET] = [None; PACKET];
        let mut found: [Option<ObjectHit>; PACKET] = [None; PACKET];
        let large = mesh.large();
        let fetch = |tris, what| match what {
            Fetch::Leaf if large => mesh.prefetch_leaf(tris),
            // The f64 corners of a whole subtree would be too many lines for the few a ray
            // tests.
            Fetch::Subtree => prefetch_blocks(&mesh.blocks, tris),
            Fetch::Leaf => {}
        };
        mesh.bvh.traverse_packet(
            local,
            &mut bounds[..live],
            spread,
            fetch,
            |i, tris, t_max| {
                let (tri_ray, ray32) = tri_rays[i].get_or_insert_with(|| {
                    let tri_ray = TriangleRay::new(&local[i]);
                    (tri_ray, TriangleRayF32::new(&tri_ray))
                });
                mesh_leaf::<false>(
                    mesh,
                    (tri_ray, ray32),
                    tris,
                    t_min,
                    t_max,
                    NO_PRIM,
                    &mut found[i],
                );
            },
        );
        for (j, &i) in index[..live].iter().enumerate() {
            if let Some(h) = found[j] {
                let i = i as usize;
                keep_nearer(&mut hits[i], &mut limits[i], slot, h);
            }
        }
    }

    /// Whether anything lies along the ray with t in (0, t_max).
    pub fn occluded(&self, ray: &Ray, t_max: f64) -> bool {
        self.occluded_leaving(ray, t_max, Leaving::NOTHING)
    }

    /// [`World::occluded`] for a ray spawned off the surface `leaving` names (see
    /// [`World::leaving`]): the same answer, without testing what it cannot meet.
    pub fn occluded_leaving(&self, ray: &Ray, t_max: f64, leaving: Leaving) -> bool {
        let mut world_tri_ray = None;
        let mut t_limit = t_max;
        self.traverse_top::<true>(ray, &mut t_limit, leaving, |slot, t_max| {
            !self.skips(slot, leaving)
                && self
                    .hit_object::<true>(
                        slot,
                        ray,
                        0.0,
                        *t_max,
                        leaving.prim_in(slot),
                        &mut world_tri_ray,
                    )
                    .is_some()
        })
    }

    /// [`World::occluded`] for up to [`PACKET`] rays at once: `blocked[i]` is whether
    /// anything lies along `rays[i]` with t in (0, `t_max[i]`), the answer `occluded` gives
    /// that ray. Coherent rays (the shadow rays of a block of pixels toward one light) share
    /// the work: a mesh's BVH is walked once for the packet ([`Bvh::traverse_packet_any`]),
    /// a multi-object world's top level too, and a packet that misses an object's box skips
    /// it. A ray leaves the packet as soon as it is blocked. `leaving[i]` is what `rays[i]`
    /// leaves ([`World::occluded_leaving`]).
    pub fn occluded_packet(
        &self,
        rays: &[Ray],
        t_max: &[f64],
        leaving: &[Leaving],
        blocked: &mut [bool],
    ) {
        let n = rays.len();
        assert!(
            n <= PACKET && t_max.len() == n && leaving.len() == n && blocked.len() == n,
            "a packet of {n} rays"
        );
        if n == 0 {
            return;
        }
        let mut limits = [0.0; PACKET];
        let limits = &mut limits[..n];
        limits.copy_from_slice(t_max);
        let mut world_tri_rays = [None; PACKET];
        let mut live = u64::MAX >> (64 - n);
        if self.objects.len() == 1 {
            // No world-space bounds: shadow rays start on surfaces inside the object's box,
            // so they would skip nothing, and a mesh's walk culls a packet that misses it at
            // its root (it also takes rays outside the f32 tests' range one by one).
            self.object_packet_any(0, rays, limits, leaving, &mut live, &mut world_tri_rays);
        } else {
            let Some(packet) = PacketBounds::new(rays) else {
                // A ray outside the f32 tests' range: the mesh walks would go ray by ray.
                for i in 0..n {
                    blocked[i] = self.occluded_leaving(&rays[i], t_max[i], leaving[i]);
                }
                return;
            };
            live = self
                .top
                .traverse_packet_leaves_any(&packet, limits, |slots, limits, live| {
                    for slot in slots {
                        self.object_packet_any(
                            slot,
                            rays,
                            limits,
                            leaving,
                            live,
                            &mut world_tri_rays,
                        );
                        if *live == 0 {
                            break;
                        }
                    }
                });
        }
        for (i, b) in blocked.iter_mut().enumerate() {
            *b = live & (1 << i) == 0;
        }
    }

    /// The object in top-level slot `slot` against the rays of a packet in `live`, for t in
    /// (0, `limits[i]`): clears the bit of each ray it blocks.
    fn object_packet_any(
        &self,
        slot: usize,
        rays: &[Ray],
        limits: &[f64],
        leaving: &[Leaving],
        live: &mut u64,
        world_tri_rays: &mut [Option<TriangleRay>; PACKET],
    ) {
        let Object::Model(m) = self.objects[slot] else {
            let mut a = *live;
            while a != 0 {
                let i = a.trailing_zeros() as usize;
                a &= a - 1;
                if self.skips(slot, leaving[i]) {
                    continue;
                }
                let hit = self.hit_object::<true>(
                    slot,
                    &rays[i],
                    0.0,
                    limits[i],
                    NO_PRIM,
                    &mut world_tri_rays[i],
                );
                if hit.is_some() {
                    *live &= !(1 << i);
                }
            }
            return;
        };
        let model = &self.models[m as usize];
        let mesh = &self.meshes[model.mesh as usize];
        // The live rays in local space, packed (rays blocked by other objects stay out of the
        // packet's bounds); `index` maps them back.
        let mut local = [const { std::mem::MaybeUninit::<Ray>::uninit() }; PACKET];
        let mut bounds = [0.0; PACKET];
        let mut index = [0u8; PACKET];
        let mut n = 0;
        let instance = &self.model_bounds[m as usize];
        let filter = self.objects.len() > 1;
        let mut a = *live;
        while a != 0 {
            let i = a.trailing_zeros() as usize;
            a &= a - 1;
            // Rays that miss the instance's box stay out, as in `object_packet`.
            if filter && !may_enter(instance, &rays[i], 0.0, limits[i]) {
                continue;
            }
            local[n].write(model.transform.ray_to_local(&rays[i]));
            bounds[n] = limits[i];
            index[n] = i as u8;
            n += 1;
        }
        if n == 0 {
            return;
        }
        // SAFETY: the first `n` entries were written above; MaybeUninit<Ray> has Ray's layout.
        let local: &[Ray] = unsafe { std::slice::from_raw_parts(local.as_ptr().cast::<Ray>(), n) };
        // Each ray's triangle-test set-up, made when it first reaches a leaf.
        let mut tri_rays: [Option<(TriangleRay, TriangleRayF32)>; PACKET] = [None; PACKET];
        let large = mesh.large();
        let fetch = |tris, what| match what {
            Fetch::Leaf if large => mesh.prefetch_leaf(tris),
            // The f64 corners of a whole subtree would be too many lines for the few a ray
            // tests.
            Fetch::Subtree => prefetch_blocks(&mesh.blocks, tris),
            Fetch::Leaf => {}
        };
        let mut blocked =
            mesh.bvh
                .traverse_packet_any(local, &mut bounds[..n], fetch, |j, tris, t_max| {
                    let (tri_ray, ray32) = tri_rays[j].get_or_insert_with(|| {
                        let tri_ray = TriangleRay::new(&local[j]);
                        (tri_ray, TriangleRayF32::new(&tri_ray))
                    });
                    let skip = leaving[index[j] as usize].prim_in(slot);
                    let mut found = None;
                    mesh_leaf::<true>(mesh, (tri_ray, ray32), tris, 0.0, t_max, skip, &mut found)
                });
        while blocked != 0 {
            let j = blocked.trailing_zeros() as usize;
            blocked &= blocked - 1;
            *live &= !(1 << index[j]);
        }
    }

    /// [`World::occluded`] for one of a family of coherent shadow rays (one light's, from
    /// one recursion level of a row's samples), whose last blocker `cache` remembers. That
    /// object is tested first: where a pixel's samples and its neighbours' lie in one shadow,
    /// the same object blocks most of their rays, and the walk is skipped. Lit rays forget
    /// it, so rays in the open pay nothing. The answer is the same either way (a blocker is
    /// a blocker, whichever is found).
    pub fn occluded_by(
        &self,
        ray: &Ray,
        t_max: f64,
        cache: &mut ShadowCache,
        leaving: Leaving,
    ) -> bool {
        let remembered = cache
            .last
            .filter(|&slot| !self.skips(slot as usize, leaving));
        // A mesh's remembered triangle first: one exact test, where the mesh's walk would
        // make dozens (neighbouring samples' rays mostly pass the same triangle).
        // (Never the triangle the ray leaves, which the walk skips.)
        if remembered.is_some_and(|slot| {
            cache.prim != leaving.prim_in(slot as usize)
                && self.mesh_triangle_blocks(slot, cache.prim, ray, t_max)
        }) {
            return true;
        }
        let mut world_tri_ray = None;
        if self.objects.len() == 1 {
            if self.skips(0, leaving) {
                return false;
            }
            // The one object is all the walk would test.
            let hit =
                self.hit_object::<true>(0, ray, 0.0, t_max, leaving.prim_in(0), &mut world_tri_ray);
            cache.last = hit.map(|_| 0);
            cache.prim = hit.map_or(0, |h| h.prim);
            return hit.is_some();
        }
        if let Some(slot) = remembered {
            if let Some(hit) = self.hit_object::<true>(
                slot as usize,
                ray,
                0.0,
                t_max,
                leaving.prim_in(slot as usize),
                &mut world_tri_ray,
            ) {
                cache.prim = hit.prim;
                return true;
            }
        }
        let mut t_limit = t_max;
        let mut blocker = None;
        let found = self.traverse_top::<true>(ray, &mut t_limit, leaving, |slot, t_max| {
            if self.skips(slot, leaving) {
                return false;
            }
            let hit = self.hit_object::<true>(
                slot,
                ray,
                0.0,
                *t_max,
                leaving.prim_in(slot),
                &mut world_tri_ray,
            );
            if let Some(hit) = hit {
                blocker = Some((slot as u32, hit.prim));
            }
            hit.is_some()
        });
        cache.last = blocker.map(|(slot, _)| slot);
        cache.prim = blocker.map_or(0, |(_, prim)| prim);
        found
    }

    /// Whether triangle slot `prim` of the mesh model in top-level `slot` blocks `ray` for t
    /// in (0, `t_max`), by the exact test the mesh's walk makes (the same local ray, so a
    /// triangle found here is one the walk finds too); false for any other object.
    fn mesh_triangle_blocks(&self, slot: u32, prim: u32, ray: &Ray, t_max: f64) -> bool {
        let Object::Model(i) = self.objects[slot as usize] else {
            return false;
        };
        let model = &self.models[i as usize];
        let mesh = &self.meshes[model.mesh as usize];
        if prim as usize >= mesh.slots() {
            return false;
        }
        let [a, b, c] = mesh.corners(prim as usize);
        let tri_ray = TriangleRay::new(&model.transform.ray_to_local(ray));
        intersect_triangle(&tri_ray, a, b, c, 0.0, t_max).is_some()
    }

    /// The object in top-level slot `slot` against the ray, for t in (t_min, t_max): its
    /// closest hit, or with `ANY` the first one found. `world_tri_ray` caches the ray's
    /// set-up for world-space triangles.
    #[inline(always)]
    fn hit_object<const ANY: bool>(
        &self,
        slot: usize,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        skip_prim: u32,
        world_tri_ray: &mut Option<TriangleRay>,
    ) -> Option<ObjectHit> {
        match self.objects[slot] {
            Object::Sphere(i) => {
                // Only the local origin and direction: `ray_to_local`'s inverse direction
                // (three divisions) is for slab tests, which a sphere does not make.
                let s = &self.spheres[i as usize];
                let origin = s.transform.to_local.transform_point3(ray.origin);
                let dir = s.transform.to_local.transform_vector3(ray.dir);
                intersect_unit_sphere_scaled(origin, dir, s.radius, t_min, t_max).map(ObjectHit::at)
            }
            Object::TranslatedSphere(i) => {
                // The affine map multiplies by exact ones and zeros here, so the shifted ray
                // is the local ray it computes (up to the sign of a zero), at 3 additions
                // instead of 33 operations.
                let s = &self.spheres[i as usize];
                let origin = ray.origin + s.transform.to_local.translation;
                intersect_unit_sphere_scaled(origin, ray.dir, s.radius, t_min, t_max)
                    .map(ObjectHit::at)
            }
            Object::Triangle(i) => {
                let [a, b, c] = self.triangles[i as usize].positions;
                let tri_ray = world_tri_ray.get_or_insert_with(|| TriangleRay::new(ray));
                intersect_triangle(tri_ray, a, b, c, t_min, t_max).map(|h| ObjectHit {
                    t: h.t,
                    prim: 0,
                    bary: h.bary,
                })
            }
            Object::Model(i) => self.hit_model::<ANY>(i, ray, t_min, t_max, skip_prim),
            Object::Mover(i) => self.hit_mover::<ANY>(i, ray, t_min, t_max),
            Object::ModelTriangle(i) => {
                let t = &self.model_triangles[i as usize];
                let [a, b, c] = t.corners;
                let tri_ray = world_tri_ray.get_or_insert_with(|| TriangleRay::new(ray));
                intersect_triangle(tri_ray, a, b, c, t_min, t_max).map(|h| ObjectHit {
                    t: h.t,
                    prim: t.prim,
                    bary: h.bary,
                })
            }
        }
    }

    /// A mesh model's hit: the ray taken into the mesh's space and its BVH walked. Out of
    /// line: inlined, the mesh walk's set-up shared the register allocation of every caller
    /// of [`World::hit_object`], and the sphere and triangle paths' speed moved with changes
    /// to code they never run.
    #[inline(never)]
    fn hit_model<const ANY: bool>(
        &self,
        index: u32,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
        skip_prim: u32,
    ) -> Option<ObjectHit> {
        let model = &self.models[index as usize];
        let mesh = &self.meshes[model.mesh as usize];
        let local = model.transform.ray_to_local(ray);
        let tri_ray = TriangleRay::new(&local);
        let ray32 = TriangleRayF32::new(&tri_ray);
        let mut found = None;
        let mut limit = t_max;
        let leaf = |tris: std::ops::Range<usize>, t_max: &mut f64| {
            mesh_leaf::<ANY>(
                mesh,
                (&tri_ray, &ray32),
                tris,
                t_min,
                t_max,
                skip_prim,
                &mut found,
            )
        };
        if ANY {
            mesh.bvh.traverse_any(&local, &mut limit, leaf);
        } else {
            mesh.bvh.traverse(&local, &mut limit, leaf);
        }
        found
    }

    /// A moving object's hit, the ray taken into its local space at the ray's time.
    fn hit_mover<const ANY: bool>(
        &self,
        index: u32,
        ray: &Ray,
        t_min: f64,
        t_max: f64,
    ) -> Option<ObjectHit> {
        let mover = &self.movers[index as usize];
        let local = mover.transform_at(ray.time).ray_to_local(ray);
        match &mover.shape {
            MoverShape::Sphere { radius, .. } => {
                intersect_unit_sphere_scaled(local.origin, local.dir, *radius, t_min, t_max)
                    .map(ObjectHit::at)
            }
            MoverShape::Triangle(tri) => {
                let [a, b, c] = tri.positions;
                intersect_triangle(&TriangleRay::new(&local), a, b, c, t_min, t_max).map(|h| {
                    ObjectHit {
                        t: h.t,
                        prim: 0,
                        bary: h.bary,
                    }
                })
            }
            MoverShape::Model { mesh, .. } => {
                let mesh = &self.meshes[*mesh as usize];
                let tri_ray = TriangleRay::new(&local);
                let mut found = None;
                let mut limit = t_max;
                mesh.bvh.traverse(&local, &mut limit, |tris, t_max| {
                    for tri in tris {
                        let [a, b, c] = mesh.corners(tri);
                        if let Some(h) = intersect_triangle(&tri_ray, a, b, c, t_min, *t_max) {
                            *t_max = h.t;
                            found = Some(ObjectHit {
                                t: h.t,
                                prim: tri as u32,
                                bary: h.bary,
                            });
                            if ANY {
                                return true;
                            }
                        }
                    }
                    false
                });
                found
            }
        }
    }

    /// Whether a ray leaving `leaving` skips the object in top-level `slot`. Rays leaving
    /// nothing (eye rays, and every ray of a mesh-only scene) read nothing.
    #[inline(always)]
    fn skips(&self, slot: usize, leaving: Leaving) -> bool {
        leaving.surface != Leaving::NOTHING.surface && self.slot_surface[slot] == leaving.surface
    }

    /// What a ray spawned off the surface at `hit` leaves (see [`Leaving`]), `outward` where
    /// it heads to the side the geometric normal points to (strictly).
    #[inline]
    pub fn leaving(&self, hit: &Hit, outward: bool) -> Leaving {
        let slot = hit.object as usize;
        if let Object::Model(i) = self.objects[slot] {
            // A mesh triangle is flat: a ray off it to either side cannot meet it again. Where
            // the mesh lies wholly behind the side the ray heads to, it cannot meet the mesh
            // at all (the model's own surface: see `surfaces`).
            let mesh = &self.meshes[self.models[i as usize].mesh as usize];
            return Leaving {
                surface: if mesh.exits(hit.prim, outward) {
                    self.slot_surface[slot]
                } else {
                    Leaving::NOTHING.surface
                },
                mesh_triangle: (hit.object, hit.prim),
            };
        }
        match self.slot_surface[slot] {
            NO_SURFACE => Leaving::NOTHING,
            // A ray into a sphere meets its far side.
            _ if !outward
                && matches!(
                    self.objects[slot],
                    Object::Sphere(_) | Object::TranslatedSphere(_)
                ) =>
            {
                Leaving::NOTHING
            }
            surface => Leaving {
                surface,
                mesh_triangle: NO_MESH_TRIANGLE,
            },
        }
    }

    /// The materials top-level object `object` (a [`Hit::object`]) can show at a hit: its
    /// one material three times, or a scene triangle's per-vertex materials.
    pub fn object_materials(&self, object: u32) -> [u32; 3] {
        match self.objects[object as usize] {
            Object::Sphere(i) | Object::TranslatedSphere(i) => {
                [self.spheres[i as usize].material; 3]
            }
            Object::Triangle(i) => self.triangles[i as usize].materials,
            Object::Model(i) => [self.models[i as usize].material; 3],
            Object::ModelTriangle(i) => {
                let model = self.model_triangles[i as usize].model;
                [self.models[model as usize].material; 3]
            }
            Object::Mover(i) => match &self.movers[i as usize].shape {
                MoverShape::Sphere { material, .. } | MoverShape::Model { material, .. } => {
                    [*material; 3]
                }
                MoverShape::Triangle(local) => local.materials,
            },
        }
    }

    /// The number of top-level objects (the range of [`Hit::object`]).
    pub fn object_count(&self) -> usize {
        self.objects.len()
    }

    /// Position, normals, texture coordinates and material at `hit`.
    pub fn patch(&self, ray: &Ray, hit: &Hit) -> Patch<'_> {
        let position = ray.at(hit.t);
        match self.objects[hit.object as usize] {
            Object::Sphere(i) => {
                let s = &self.spheres[i as usize];
                sphere_patch(position, &s.transform, s.radius, s.material)
            }
            Object::TranslatedSphere(i) => {
                let s = &self.spheres[i as usize];
                translated_sphere_patch(position, &s.transform, s.radius, s.material)
            }
            Object::Triangle(i) => {
                let (geometric, flat) = self.triangle_normals[i as usize];
                triangle_patch(
                    position,
                    &self.triangles[i as usize],
                    geometric,
                    flat,
                    hit.bary,
                )
            }
            Object::Model(i) => {
                let model = &self.models[i as usize];
                let mesh = &self.meshes[model.mesh as usize];
                model_patch(position, &model.transform, mesh, model.material, hit)
            }
            Object::ModelTriangle(i) => {
                // `hit.prim` is the triangle's slot in its mesh, as for an instanced model.
                let model = &self.models[self.model_triangles[i as usize].model as usize];
                let mesh = &self.meshes[model.mesh as usize];
                model_patch(position, &model.transform, mesh, model.material, hit)
            }
            Object::Mover(i) => {
                let mover = &self.movers[i as usize];
                let xf = mover.transform_at(ray.time);
                match &mover.shape {
                    MoverShape::Sphere { radius, material } => {
                        sphere_patch(position, &xf, *radius, *material)
                    }
                    MoverShape::Triangle(local) => {
                        let world = WorldTriangle {
                            positions: local.positions.map(|p| xf.to_world.transform_point3(p)),
                            normals: local.normals.map(|n| xf.normal_to_world(n)),
                            tex_coords: local.tex_coords,
                            materials: local.materials,
                        };
                        triangle_patch(position, &world, geometric_normal(&world), None, hit.bary)
                    }
                    MoverShape::Model { mesh, material } => {
                        let mesh = &self.meshes[*mesh as usize];
                        model_patch(position, &xf, mesh, *material, hit)
                    }
                }
            }
        }
    }
}

/// Per top-level slot, what a ray leaving it skips: the index of the axis-aligned plane its
/// triangle lies in (all three corners share one coordinate exactly), shared by every slot on
/// the same plane; a fresh index for any other triangle, a sphere or a mesh instance;
/// [`NO_SURFACE`] for movers.
fn surfaces(
    objects: &[Object],
    triangles: &[WorldTriangle],
    model_triangles: &[ModelTriangle],
) -> Vec<u32> {
    let mut planes = std::collections::HashMap::new();
    let mut plane_of = |corners: &[DVec3; 3]| {
        let axis = (0..3).find(|&k| {
            corners[0][k].is_finite()
                && corners[0][k] == corners[1][k]
                && corners[0][k] == corners[2][k]
        })?;
        // +0 and −0 are one plane.
        let value = corners[0][axis] + 0.0;
        let next = planes.len() as u32;
        Some(*planes.entry((axis, value.to_bits())).or_insert(next))
    };
    let slots: Vec<Option<Option<u32>>> = objects
        .iter()
        .map(|object| match *object {
            Object::Triangle(i) => Some(plane_of(&triangles[i as usize].positions)),
            Object::ModelTriangle(i) => Some(plane_of(&model_triangles[i as usize].corners)),
            Object::Sphere(_) | Object::TranslatedSphere(_) => Some(None),
            // Named only by rays that leave the mesh from a side it lies wholly behind
            // (`Mesh::exits`); other rays leaving it skip just their own triangle.
            Object::Model(_) => Some(None),
            _ => None,
        })
        .collect();
    // A triangle on no axis-aligned plane, a sphere or a mesh instance is a surface of its
    // own: rays leaving it skip it alone (whether another triangle shares a plane exactly is
    // not known).
    let mut next = planes.len() as u32;
    slots
        .into_iter()
        .map(|slot| match slot {
            Some(Some(plane)) => plane,
            Some(None) => {
                next += 1;
                next - 1
            }
            None => NO_SURFACE,
        })
        .collect()
}

/// A top level's walk (`level`, the layout of `bvh`'s nodes), `leaf` handed the positions of
/// its leaves' objects: nearest leaf first for closest hits among costly objects
/// ([`TopLevel::walk_nearest`]), else as [`TopLevel::walk`] orders them; rays out of the f32
/// test's range take `bvh`'s generic traversal.
#[inline(always)]
fn walk_top<const ANY: bool>(
    bvh: &Bvh,
    level: &TopLevel,
    costly: bool,
    ray: &Ray,
    t_max: &mut f64,
    mut leaf: impl FnMut(std::ops::Range<usize>, &mut f64) -> bool,
) -> bool {
    let walked = if !ANY && costly {
        level.walk_nearest(ray, t_max, &mut leaf)
    } else {
        level.walk::<ANY>(ray, t_max, &mut leaf)
    };
    if let Some(found) = walked {
        return found;
    }
    if ANY {
        bvh.traverse_any(ray, t_max, leaf)
    } else {
        bvh.traverse(ray, t_max, leaf)
    }
}

/// What a ray leaving one surface tests instead of walking the world's top level.
#[derive(Clone, Debug)]
enum OffSurface {
    /// The slots off the surface, at most [`LINEAR_TOP`]: tested in turn (a mesh instance
    /// behind its box), which costs less than a walk.
    Listed(Box<[u32]>),
    /// A top level over the slots off the surface, in a world of at most
    /// [`SURFACE_TOPS_UP_TO`] slots.
    Walked(Box<SubTop>),
}

/// The top level over the slots off one surface ([`OffSurface::Walked`]).
#[derive(Clone, Debug)]
struct SubTop {
    bvh: Bvh,
    level: TopLevel,
    /// The world slot at each of `bvh`'s leaf positions.
    slots: Box<[u32]>,
    /// Whether those slots hold mesh instances (see [`World::costly_top`]).
    costly: bool,
}

/// Worlds of at most this many top-level slots get a top level per surface without it: a
/// few dozen small trees, built in microseconds each.
const SURFACE_TOPS_UP_TO: usize = 64;

/// Per surface index of `slot_surface` (see [`surfaces`]), what a ray leaving it tests
/// ([`OffSurface`]); None in a world with movers (whose boxes the rays' times decide) and
/// where a large world's surface has more than [`LINEAR_TOP`] slots off it. The top levels
/// are built as the world's is (`mean_cost`, the slots' boxes `slot_bounds`).
fn off_surfaces(
    objects: &[Object],
    slot_surface: &[u32],
    slot_bounds: &[Aabb],
    mean_cost: f64,
) -> Vec<Option<OffSurface>> {
    if objects.iter().any(|o| matches!(o, Object::Mover(_))) {
        return Vec::new();
    }
    // Slots per surface counted in one pass: a world of many triangles has as many surfaces,
    // and counting each surface's slots over all of them would be quadratic. (At most one
    // surface holds more than half the slots, so a large world makes at most one list.)
    let mut on = Vec::new();
    for &surface in slot_surface.iter().filter(|&&s| s != NO_SURFACE) {
        if on.len() <= surface as usize {
            on.resize(surface as usize + 1, 0);
        }
        on[surface as usize] += 1;
    }
    on.iter()
        .enumerate()
        .map(|(surface, &count)| {
            let others = objects.len() - count;
            if others > LINEAR_TOP && objects.len() > SURFACE_TOPS_UP_TO {
                return None;
            }
            let off: Box<[u32]> = (0..objects.len() as u32)
                .filter(|&slot| slot_surface[slot as usize] != surface as u32)
                .collect();
            if others <= LINEAR_TOP {
                return Some(OffSurface::Listed(off));
            }
            let bounds: Vec<Aabb> = off.iter().map(|&slot| slot_bounds[slot as usize]).collect();
            let bvh = Bvh::build_costed(&bounds, mean_cost);
            Some(OffSurface::Walked(Box::new(SubTop {
                level: TopLevel::new(&bvh),
                slots: bvh.order.iter().map(|&i| off[i as usize]).collect(),
                costly: off
                    .iter()
                    .any(|&slot| matches!(objects[slot as usize], Object::Model(_))),
                bvh,
            })))
        })
        .collect()
}

/// A triangle below node `index` of `mesh`'s BVH that may lie inside the frustum of `planes`
/// (inward normals, through `apex`), if any: a box or triangle wholly behind one plane is
/// left out. Stops at the first triangle that is not.
fn mesh_meets_frustum(mesh: &Mesh, index: usize, apex: DVec3, planes: &[DVec3; 4]) -> Option<u32> {
    let node = &mesh.bvh.nodes[index];
    (0..node.index.len()).find_map(|c| {
        if node.index[c] == u32::MAX || box_behind_a_plane(&node.bounds, c, apex, planes) {
            return None;
        }
        let first = node.index[c] as usize;
        match node.count[c] {
            0 => mesh_meets_frustum(mesh, first, apex, planes),
            count => (first..first + count as usize)
                .find(|&slot| !triangle_behind_a_plane(&mesh.corners(slot), apex, planes))
                .map(|slot| slot as u32),
        }
    })
}

/// Whether child `c`'s box in a node's `bounds` (rows: min x, max x, min y, …, f32) lies
/// wholly behind one of the planes through `apex` with inward normals `planes`: even its
/// corner farthest along the normal is behind.
fn box_behind_a_plane<const N: usize>(
    bounds: &[[f32; N]; 6],
    c: usize,
    apex: DVec3,
    planes: &[DVec3; 4],
) -> bool {
    let b = bounds;
    let min = DVec3::new(b[0][c] as f64, b[2][c] as f64, b[4][c] as f64) - apex;
    let max = DVec3::new(b[1][c] as f64, b[3][c] as f64, b[5][c] as f64) - apex;
    planes.iter().any(|n| {
        let far = DVec3::select(n.cmpge(DVec3::ZERO), max, min);
        n.dot(far) < 0.0
    })
}

/// The edge directions of the frustum whose inward plane normals are `planes` (plane k
/// between edges k and k + 1, as [`crate::camera::Camera::frustum`] makes them): each the
/// line where two neighbouring planes meet, pointing into the frustum. Its rays are the
/// positive combinations of these.
fn frustum_edges(planes: &[DVec3; 4]) -> [DVec3; 4] {
    std::array::from_fn(|k| {
        let d = planes[(k + 3) % 4].cross(planes[k]);
        if planes[(k + 1) % 4].dot(d) + planes[(k + 2) % 4].dot(d) < 0.0 {
            -d
        } else {
            d
        }
    })
}

/// Whether the triangle with `corners` lies beside the frustum from `apex` with edge
/// directions `edges` ([`frustum_edges`]): for one of its sides, the plane through the apex
/// and that side has the triangle's third corner on one side and every edge direction
/// strictly on the other, so no ray of the frustum (a positive combination of the edges)
/// reaches the triangle. A triangle whose plane holds the apex is never left out this way.
fn triangle_beside_a_frustum(corners: &[DVec3; 3], apex: DVec3, edges: &[DVec3; 4]) -> bool {
    let v = corners.map(|c| c - apex);
    (0..3).any(|i| {
        let (normal, third) = side_plane(&v, i);
        third != 0.0 && edges.iter().all(|&d| normal.dot(d) * third < 0.0)
    })
}

/// The plane through the apex and side `i` (corners i and i + 1) of a triangle whose corners
/// relative to the apex are `v`: its normal, and the third corner's product with it (0 where
/// the apex lies in the triangle's plane).
#[inline(always)]
fn side_plane(v: &[DVec3; 3], i: usize) -> (DVec3, f64) {
    let normal = v[i].cross(v[(i + 1) % 3]);
    (normal, normal.dot(v[(i + 2) % 3]))
}

/// Whether the cone from `apex` through the triangle with `corners` holds the whole frustum
/// with edge directions `edges`: every edge direction lies strictly inside the plane through
/// the apex and each side (on the third corner's side). Then every ray of the frustum passes
/// through the triangle's cone, and a test of the frustum against the triangle would keep it.
fn triangle_holds_frustum(corners: &[DVec3; 3], apex: DVec3, edges: &[DVec3; 4]) -> bool {
    let v = corners.map(|c| c - apex);
    (0..3).all(|i| {
        let (normal, third) = side_plane(&v, i);
        third != 0.0 && edges.iter().all(|&d| normal.dot(d) * third > 0.0)
    })
}

/// Whether the triangle with `corners` lies wholly behind one of the planes through `apex`
/// with inward normals `planes`.
fn triangle_behind_a_plane(corners: &[DVec3; 3], apex: DVec3, planes: &[DVec3; 4]) -> bool {
    planes
        .iter()
        .any(|n| corners.iter().all(|&v| n.dot(v - apex) < 0.0))
}

/// Whether `ray` may meet the box `b` for t in [t_min, t_max]: false only where it surely
/// does not, so that an object inside `b` can be left untested. The f64 slab test runs
/// against the box padded by 2^-40 of the coordinates' reach (the ray's origin included), far
/// beyond the test's rounding (about 2^-52 of it). A ray with an infinite inverse direction
/// (parallel to an axis) is kept.
#[inline(always)]
fn may_enter(b: &Aabb, ray: &Ray, t_min: f64, t_max: f64) -> bool {
    if !ray.inv_dir.is_finite() {
        return true;
    }
    let reach = (b.min.abs().max(b.max.abs()).max(ray.origin.abs())).max_element();
    let pad = DVec3::splat(reach * (1.0 / (1u64 << 40) as f64));
    let padded = Aabb {
        min: b.min - pad,
        max: b.max + pad,
    };
    padded.hit_within(ray, t_min, t_max).is_some()
}

/// The bound to test an object or triangle against when the nearest hit so far (if
/// `found`) lies at `t_max`: just above it, so that a hit at the same distance is seen and
/// the tie can go to the lower slot whatever order the tests come in (closest-hit walks of
/// a packet and of a single ray meet the same triangles in different orders).
#[inline(always)]
fn tie_bound(found: bool, t_max: f64) -> f64 {
    if found {
        t_max.next_up()
    } else {
        t_max
    }
}

/// Rays of [`World::intersect_among_lanes`]: one AVX2 register of f64.
pub const LANES: usize = 4;

/// Four rays' constants of the watertight test (their sheared frames share their axes),
/// lane by lane: each origin on the frame's axes and each shear.
struct LaneFrame {
    axes: [usize; 3],
    /// Origin on kx, ky, kz, then shear x, y, z, each a lane per ray.
    rows: [[f64; LANES]; 6],
}

impl LaneFrame {
    #[inline(always)]
    fn new(rays: &[TriangleRay; LANES]) -> LaneFrame {
        let axes = rays[0].axes();
        let row = |f: &dyn Fn(&TriangleRay) -> f64| std::array::from_fn(|l| f(&rays[l]));
        LaneFrame {
            axes,
            rows: [
                row(&|r| r.origin[axes[0]]),
                row(&|r| r.origin[axes[1]]),
                row(&|r| r.origin[axes[2]]),
                row(&|r| r.shear.x),
                row(&|r| r.shear.y),
                row(&|r| r.shear.z),
            ],
        }
    }

    /// [`intersect_triangle`] of `[v0, v1, v2]` for the four rays, each accepted within
    /// (t_min, t_max[lane]): per lane the scalar test's operations in its order (none fused,
    /// as the scalar code has none), so the same t and barycentrics to the bit.
    #[inline(always)]
    fn triangle(
        &self,
        corners: [DVec3; 3],
        t_min: f64,
        t_max: [f64; LANES],
    ) -> [Option<(f64, [f64; 3])>; LANES] {
        #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
        {
            self.triangle_avx2(corners, t_min, t_max)
        }
        #[cfg(not(all(target_arch = "x86_64", target_feature = "avx2")))]
        {
            self.triangle_scalar(corners, t_min, t_max)
        }
    }

    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    #[inline(always)]
    #[allow(unused_unsafe)]
    fn triangle_avx2(
        &self,
        corners: [DVec3; 3],
        t_min: f64,
        t_max: [f64; LANES],
    ) -> [Option<(f64, [f64; 3])>; LANES] {
        use std::arch::x86_64::*;
        let [kx, ky, kz] = self.axes;
        // SAFETY: AVX2 is enabled for the build; every load and store is of a [f64; 4].
        unsafe {
            let row = |r: usize| _mm256_loadu_pd(self.rows[r].as_ptr());
            let (ox, oy, oz) = (row(0), row(1), row(2));
            let (sx, sy, sz) = (row(3), row(4), row(5));
            let corner = |v: DVec3| {
                let az = _mm256_sub_pd(_mm256_set1_pd(v[kz]), oz);
                let ax = _mm256_sub_pd(
                    _mm256_sub_pd(_mm256_set1_pd(v[kx]), ox),
                    _mm256_mul_pd(sx, az),
                );
                let ay = _mm256_sub_pd(
                    _mm256_sub_pd(_mm256_set1_pd(v[ky]), oy),
                    _mm256_mul_pd(sy, az),
                );
                (ax, ay, az)
            };
            let (ax, ay, az) = corner(corners[0]);
            let (bx, by, bz) = corner(corners[1]);
            let (cx, cy, cz) = corner(corners[2]);
            let cross = |p, q, r, s| _mm256_sub_pd(_mm256_mul_pd(p, q), _mm256_mul_pd(r, s));
            let u = cross(cx, by, cy, bx);
            let v = cross(ax, cy, ay, cx);
            let w = cross(bx, ay, by, ax);
            let zero = _mm256_setzero_pd();
            let lt = |a, b| _mm256_cmp_pd::<_CMP_LT_OQ>(a, b);
            let gt = |a, b| _mm256_cmp_pd::<_CMP_GT_OQ>(a, b);
            let or3 = |a, b, c| _mm256_or_pd(_mm256_or_pd(a, b), c);
            let outside = _mm256_and_pd(
                or3(lt(u, zero), lt(v, zero), lt(w, zero)),
                or3(gt(u, zero), gt(v, zero), gt(w, zero)),
            );
            // Most triangles a pixel's rays test are missed by all of them: no divisions then
            // (the scalar test returns at its first comparison).
            if _mm256_movemask_pd(outside) == 0xf {
                return [None; LANES];
            }
            let det = _mm256_add_pd(_mm256_add_pd(u, v), w);
            let t_scaled = _mm256_add_pd(
                _mm256_add_pd(
                    _mm256_mul_pd(u, _mm256_mul_pd(sz, az)),
                    _mm256_mul_pd(v, _mm256_mul_pd(sz, bz)),
                ),
                _mm256_mul_pd(w, _mm256_mul_pd(sz, cz)),
            );
            let t = _mm256_div_pd(t_scaled, det);
            let inv = _mm256_div_pd(_mm256_set1_pd(1.0), det);
            let abs = _mm256_andnot_pd(_mm256_set1_pd(-0.0), det);
            let finite = lt(abs, _mm256_set1_pd(f64::INFINITY));
            let nonzero = _mm256_cmp_pd::<_CMP_NEQ_UQ>(det, zero);
            let within = _mm256_and_pd(
                gt(t, _mm256_set1_pd(t_min)),
                lt(t, _mm256_loadu_pd(t_max.as_ptr())),
            );
            let keep = _mm256_andnot_pd(
                outside,
                _mm256_and_pd(_mm256_and_pd(finite, nonzero), within),
            );
            let mask = _mm256_movemask_pd(keep);
            let mut out = [[0.0; LANES]; 4];
            _mm256_storeu_pd(out[0].as_mut_ptr(), t);
            _mm256_storeu_pd(out[1].as_mut_ptr(), _mm256_mul_pd(u, inv));
            _mm256_storeu_pd(out[2].as_mut_ptr(), _mm256_mul_pd(v, inv));
            _mm256_storeu_pd(out[3].as_mut_ptr(), _mm256_mul_pd(w, inv));
            std::array::from_fn(|l| {
                (mask & (1 << l) != 0).then(|| (out[0][l], [out[1][l], out[2][l], out[3][l]]))
            })
        }
    }

    /// The same lane by lane (targets without AVX2, and the vector version's check).
    #[cfg_attr(all(target_arch = "x86_64", target_feature = "avx2"), allow(dead_code))]
    fn triangle_scalar(
        &self,
        corners: [DVec3; 3],
        t_min: f64,
        t_max: [f64; LANES],
    ) -> [Option<(f64, [f64; 3])>; LANES] {
        let [kx, ky, kz] = self.axes;
        std::array::from_fn(|l| {
            // The origin's rows are on the frame's axes: back to x, y, z.
            let mut origin = DVec3::ZERO;
            for (row, axis) in self.axes.into_iter().enumerate() {
                origin[axis] = self.rows[row][l];
            }
            let shear = DVec3::new(self.rows[3][l], self.rows[4][l], self.rows[5][l]);
            let ray = TriangleRay {
                origin,
                kx,
                ky,
                kz,
                shear,
            };
            let [a, b, c] = corners;
            intersect_triangle(&ray, a, b, c, t_min, t_max[l]).map(|h| (h.t, h.bary))
        })
    }
}

/// Keeps `h`, the hit of the object in `slot` (found below [`tie_bound`]), as `best` if it
/// is nearer, or as near and in a lower slot.
#[inline(always)]
fn keep_nearer(best: &mut Option<Hit>, t_max: &mut f64, slot: usize, h: ObjectHit) {
    if best.is_some_and(|b| h.t == b.t && slot as u32 > b.object) {
        return;
    }
    *t_max = h.t;
    *best = Some(Hit {
        t: h.t,
        object: slot as u32,
        prim: h.prim,
        bary: h.bary,
    });
}

/// The triangles of a mesh leaf `tris` against a ray, for t in (t_min, `*t_max`): a nearer
/// hit (or, at the same distance, one in a lower slot) replaces `found` and shrinks
/// `*t_max`. With `ANY`, returns true at the first hit.
#[inline(always)]
fn mesh_leaf<const ANY: bool>(
    mesh: &Mesh,
    rays: (&TriangleRay, &TriangleRayF32),
    tris: std::ops::Range<usize>,
    t_min: f64,
    t_max: &mut f64,
    skip_prim: u32,
    found: &mut Option<ObjectHit>,
) -> bool {
    // Each layout its own loop, so that reading a corner takes no branch.
    let test = (t_min, t_max, skip_prim, found);
    match &mesh.corners {
        Corners::InBlocks => {
            let corner_of = |tri: usize| mesh.blocks[tri / BLOCK].corners(tri % BLOCK);
            leaf_candidates::<ANY>(mesh, &[], corner_of, rays, tris, test)
        }
        Corners::Inline(corners) => {
            leaf_candidates::<ANY>(mesh, corners, |tri| corners[tri], rays, tris, test)
        }
    }
}

/// [`mesh_leaf`] over one corner layout: `corner_of` gives a slot's f64 corners, which
/// `inline` holds where the blocks do not ([`any_candidate`]).
#[inline(always)]
fn leaf_candidates<const ANY: bool>(
    mesh: &Mesh,
    inline: &[[DVec3; 3]],
    corner_of: impl Fn(usize) -> [DVec3; 3],
    (tri_ray, ray32): (&TriangleRay, &TriangleRayF32),
    tris: std::ops::Range<usize>,
    (t_min, t_max, skip_prim, found): (f64, &mut f64, u32, &mut Option<ObjectHit>),
) -> bool {
    any_candidate(&mesh.blocks, inline, ray32, tris, |tri| {
        if tri as u32 == skip_prim {
            return false;
        }
        let [a, b, c] = corner_of(tri);
        let bound = if ANY {
            *t_max
        } else {
            tie_bound(found.is_some(), *t_max)
        };
        let Some(h) = intersect_triangle(tri_ray, a, b, c, t_min, bound) else {
            return false;
        };
        if !ANY && found.is_some_and(|f| h.t == f.t && tri as u32 > f.prim) {
            return false;
        }
        *t_max = h.t;
        *found = Some(ObjectHit {
            t: h.t,
            prim: tri as u32,
            bary: h.bary,
        });
        ANY
    })
}

/// One object's hit: distance, triangle slot (within a mesh) and barycentrics.
#[derive(Clone, Copy, Debug)]
struct ObjectHit {
    t: f64,
    prim: u32,
    bary: [f64; 3],
}

impl ObjectHit {
    /// A hit with no triangle (spheres).
    fn at(t: f64) -> ObjectHit {
        ObjectHit {
            t,
            prim: 0,
            bary: [0.0; 3],
        }
    }
}

#[inline(always)]
fn sphere_patch(position: DVec3, xf: &Transform, radius: f64, material: u32) -> Patch<'static> {
    let local = xf.to_local.transform_point3(position) / radius;
    let unit = local.normalize_or_zero();
    let normal = xf.normal_to_world(unit);
    Patch {
        position,
        normal,
        geometric_normal: normal,
        uv: Uv::Sphere(unit),
        material: MaterialAt::One(material),
    }
}

/// [`sphere_patch`] for a sphere whose transform only translates: the unit vector from its
/// centre to the hit is its normal, without the normal matrix (the identity) and a second
/// normalisation, which changed the vector's last bits at most (every course scene's f32
/// image is unchanged; spheres.scene renders 14% faster).
#[inline(always)]
fn translated_sphere_patch(
    position: DVec3,
    xf: &Transform,
    radius: f64,
    material: u32,
) -> Patch<'static> {
    // Scaled by the reciprocal of the radius rather than normalised: the reciprocal does not
    // wait on the hit, where the normalisation's square root and division did (a third of the
    // patch's time on spheres.scene). The hit lies on the sphere to within rounding, so the
    // two differ in the last bits only.
    let offset = position + xf.to_local.translation;
    let unit = match 1.0 / radius {
        inverse if inverse.is_finite() && inverse > 0.0 => offset * inverse,
        _ => offset.normalize_or_zero(),
    };
    Patch {
        position,
        normal: unit,
        geometric_normal: unit,
        uv: Uv::Sphere(unit),
        material: MaterialAt::One(material),
    }
}

/// A scene triangle's unit geometric normal (zero where it is degenerate).
fn geometric_normal(t: &WorldTriangle) -> DVec3 {
    let [p0, p1, p2] = t.positions;
    (p1 - p0).cross(p2 - p0).normalize_or_zero()
}

/// A scene triangle's unit shading normal where its three vertex normals are one vector (a
/// flat floor or wall): the interpolated normal is then that vector times b0 + b1 + b2, and
/// normalising it gives the vector normalised, to its last bit (exactly, for an axis-aligned
/// one). Made once, so that such a hit's shading normal waits on no square root or division.
fn flat_normal(t: &WorldTriangle) -> Option<DVec3> {
    let [n0, n1, n2] = t.normals;
    (n0 == n1 && n1 == n2).then(|| n0.try_normalize()).flatten()
}

#[inline(always)]
fn triangle_patch(
    position: DVec3,
    t: &WorldTriangle,
    geometric: DVec3,
    flat: Option<DVec3>,
    bary: [f64; 3],
) -> Patch<'static> {
    let [b0, b1, b2] = bary;
    let normal = flat.unwrap_or_else(|| {
        let interpolated = b0 * t.normals[0] + b1 * t.normals[1] + b2 * t.normals[2];
        interpolated.try_normalize().unwrap_or(geometric)
    });
    Patch {
        position,
        normal,
        geometric_normal: geometric,
        uv: Uv::At(corner_lerp(t.tex_coords, b1, b2)),
        // One material at all three vertices (most scene triangles): its values as they are,
        // rather than blended with weights that sum to one only up to rounding.
        material: match t.materials {
            [m0, m1, m2] if m0 == m1 && m1 == m2 => MaterialAt::One(m0),
            materials => MaterialAt::Blend { materials, bary },
        },
    }
}

#[inline(always)]
fn model_patch<'a>(
    position: DVec3,
    xf: &Transform,
    mesh: &'a Mesh,
    material: u32,
    hit: &Hit,
) -> Patch<'a> {
    let [b0, b1, b2] = hit.bary;
    let [i0, i1, i2] = mesh.indices[hit.prim as usize].map(|i| i as usize);
    let [p0, p1, p2] = mesh.corners(hit.prim as usize);
    let geometric = xf.normal_to_world((p1 - p0).cross(p2 - p0));
    let local_n = b0 * mesh.normals[i0] + b1 * mesh.normals[i1] + b2 * mesh.normals[i2];
    let normal = xf.normal_to_world(local_n);
    Patch {
        position,
        normal: if normal == DVec3::ZERO {
            geometric
        } else {
            normal
        },
        geometric_normal: geometric,
        uv: Uv::Mesh {
            coords: &mesh.tex_coords,
            corners: mesh.indices[hit.prim as usize],
            bary: hit.bary,
        },
        material: MaterialAt::One(material),
    }
}

/// The attribute at barycentrics (1 − b1 − b2, b1, b2) of the corners `c`, interpolated as
/// c0 plus b1·(c1 − c0) plus b2·(c2 − c0): exact where the corners agree, whatever the
/// barycentrics' rounding. (A mesh giving every corner the one texture coordinate (0, 1),
/// like the course's toy plane, would otherwise sample either side of the texture's wrap seam
/// as b0 + b1 + b2 rounds to either side of 1, and its image would change with the scene's
/// scale and position.)
#[inline(always)]
fn corner_lerp(c: [DVec2; 3], b1: f64, b2: f64) -> DVec2 {
    c[0] + b1 * (c[1] - c[0]) + b2 * (c[2] - c[0])
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
    use glam::DQuat;

    #[test]
    fn a_flat_triangles_normal_is_the_interpolated_one_to_the_last_bits() {
        let triangle = |normals: [DVec3; 3]| WorldTriangle {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y],
            normals,
            tex_coords: [glam::DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let mut next = crate::test_rng::uniform(17);
        let tilted = DVec3::new(0.3, -1.7, 2.2);
        for n in [DVec3::Y, -DVec3::X, DVec3::Z * 3.0, tilted] {
            let t = triangle([n; 3]);
            let flat = flat_normal(&t).expect("three equal normals are flat");
            let geometric = geometric_normal(&t);
            for _ in 0..500 {
                let (b1, b2) = (next() * 0.5, next() * 0.5);
                let bary = [1.0 - b1 - b2, b1, b2];
                let interpolated = (bary[0] * n + bary[1] * n + bary[2] * n).normalize();
                let patch = triangle_patch(DVec3::ZERO, &t, geometric, Some(flat), bary);
                assert_eq!(patch.normal, flat);
                if n == tilted {
                    assert!(
                        (flat - interpolated).length() < 1e-15,
                        "{flat} {interpolated}"
                    );
                } else {
                    // An axis-aligned normal: the same bits up to the last one.
                    assert!((flat - interpolated).abs().max_element() <= f64::EPSILON);
                }
            }
        }
        // Normals that differ, or none, take the interpolation.
        assert_eq!(flat_normal(&triangle([DVec3::Y, DVec3::Y, DVec3::X])), None);
        assert_eq!(flat_normal(&triangle([DVec3::ZERO; 3])), None);
    }

    #[test]
    fn a_triangle_with_one_material_takes_its_values_unblended() {
        // Blended with barycentric weights, a glass triangle's index of refraction came out as
        // 1.5 at some hits and 1.4999999999999998 at others, and the refraction stack, which
        // matches an exit to its entry by the index, then missed the exit from a glass body
        // made of scene triangles (scenes/extreme/prism.scene).
        let mut t = WorldTriangle {
            positions: [DVec3::ZERO, DVec3::X, DVec3::Y],
            normals: [DVec3::Z; 3],
            tex_coords: [glam::DVec2::ZERO; 3],
            materials: [4; 3],
        };
        let mut next = crate::test_rng::uniform(23);
        let mut blend_off = 0;
        for _ in 0..1000 {
            let (b1, b2) = (next() * 0.5, next() * 0.5);
            let bary = [1.0 - b1 - b2, b1, b2];
            let patch = triangle_patch(DVec3::ZERO, &t, DVec3::Z, None, bary);
            assert!(matches!(patch.material, MaterialAt::One(4)));
            blend_off += (bary[0] * 1.5 + bary[1] * 1.5 + bary[2] * 1.5 != 1.5) as u32;
        }
        assert!(blend_off > 0, "the blend was exact at every hit tried");
        t.materials = [4, 4, 5];
        let patch = triangle_patch(DVec3::ZERO, &t, DVec3::Z, None, [0.2, 0.3, 0.5]);
        assert!(matches!(
            patch.material,
            MaterialAt::Blend {
                materials: [4, 4, 5],
                ..
            }
        ));
    }

    #[test]
    fn a_translated_spheres_normal_is_the_unit_offset_to_the_last_bits() {
        // Hits on spheres of many sizes, near and far from the eye: the normal made with the
        // radius's reciprocal is the normalised offset to within a few units of roundoff.
        let mut next = crate::test_rng::uniform(11);
        for radius in [1e-6, 1e-3, 0.3, 1.0, 7.5, 1e4] {
            for offset in [0.0, 1.0, 1e3] {
                let centre = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * offset;
                let xf = Transform::new(centre, glam::DQuat::IDENTITY, DVec3::ONE);
                for _ in 0..200 {
                    let u = crate::sampler::uniform_sphere(next(), next());
                    let hit = centre + radius * u;
                    let patch = translated_sphere_patch(hit, &xf, radius, 0);
                    let exact = (hit - centre).normalize();
                    // The hit's own rounding (relative to |centre| + radius) bounds the error.
                    let bound = 1e-14 * (1.0 + centre.length() / radius);
                    assert!(
                        (patch.normal - exact).length() <= bound,
                        "radius {radius}, centre {centre}: {} against {exact}",
                        patch.normal
                    );
                    assert_eq!(patch.geometric_normal, patch.normal);
                }
            }
        }
        // A degenerate radius falls back to normalising.
        let xf = Transform::new(DVec3::ZERO, glam::DQuat::IDENTITY, DVec3::ONE);
        let patch = translated_sphere_patch(DVec3::new(0.0, 2.0, 0.0), &xf, 0.0, 0);
        assert_eq!(patch.normal, DVec3::Y);
    }

    #[test]
    fn a_movers_bounds_cover_its_whole_path() {
        let base = TransformDesc {
            position: DVec3::new(1.0, 0.0, 0.0),
            orientation: DQuat::IDENTITY,
            scale: DVec3::new(2.0, 0.5, 1.0),
        };
        let motion = Motion {
            keys: vec![crate::geometry::Keyframe {
                time: 1.5,
                transform: TransformDesc {
                    position: DVec3::new(-2.0, 3.0, 1.0),
                    orientation: DQuat::from_axis_angle(DVec3::Z, 2.5),
                    ..base
                },
            }],
            velocity: DVec3::new(0.0, 0.0, -0.3),
            spin: Some((DVec3::Y, 4.0)),
        };
        let mover = Mover {
            shape: MoverShape::Sphere {
                radius: 0.7,
                material: 0,
            },
            base,
            motion,
        };
        let span = (0.0, 3.0);
        let bounds = mover.bounds(&[], span);
        // Points of the sphere's surface at many times, between the sampled ones too.
        for i in 0..=997 {
            let t = span.1 * i as f64 / 997.0;
            let xf = mover.transform_at(t);
            for j in 0..64 {
                let d =
                    crate::sampler::uniform_sphere(j as f64 / 64.0, (j * 37 % 64) as f64 / 64.0);
                let p = xf.to_world.transform_point3(0.7 * d);
                assert!(
                    p.cmpge(bounds.min).all() && p.cmple(bounds.max).all(),
                    "{p} at t={t} outside {bounds:?}"
                );
            }
        }
        // And the box is not absurdly loose: within a unit of the path's extent.
        assert!(bounds.extent().max_element() < 10.0, "{bounds:?}");
    }

    /// A camera at the origin looking down −z (fov 0.9, 4:3, clipped to [0.01, 100]).
    fn looking_down_z() -> crate::camera::Camera {
        crate::camera::Camera::from_orientation(
            DVec3::ZERO,
            glam::DQuat::IDENTITY,
            0.9,
            0.01,
            100.0,
            4.0 / 3.0,
        )
    }

    #[test]
    fn a_pixels_frustum_slots_give_its_eye_rays_the_same_hits() {
        let mut next = crate::test_rng::uniform(5);
        // Spheres, rotated and stretched ellipsoids and triangles scattered in front of a camera
        // at the origin looking down −z.
        let spheres = (0..40)
            .map(|i| {
                let (orientation, scale) = if i % 2 == 0 {
                    (glam::DQuat::IDENTITY, DVec3::ONE)
                } else {
                    let axis = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                    (
                        glam::DQuat::from_axis_angle(axis.normalize(), next() * 3.0),
                        DVec3::new(0.3 + next() * 2.0, 0.3 + next() * 2.0, 0.3 + next()),
                    )
                };
                Sphere {
                    transform: Transform::new(
                        DVec3::new(next() * 8.0 - 4.0, next() * 6.0 - 3.0, -4.0 - next() * 10.0),
                        orientation,
                        scale,
                    ),
                    radius: 0.1 + next() * 0.6,
                    material: i,
                }
            })
            .collect();
        let triangles = (0..40)
            .map(|_| {
                let c = DVec3::new(next() * 8.0 - 4.0, next() * 6.0 - 3.0, -4.0 - next() * 10.0);
                let corner = |c: DVec3, next: &mut dyn FnMut() -> f64| {
                    c + 2.0 * DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5)
                };
                WorldTriangle {
                    positions: [
                        corner(c, &mut next),
                        corner(c, &mut next),
                        corner(c, &mut next),
                    ],
                    normals: [DVec3::Z; 3],
                    tex_coords: [DVec2::ZERO; 3],
                    materials: [0; 3],
                }
            })
            .collect();
        let world = World::with_movers(spheres, triangles, vec![], vec![], vec![], (0.0, 0.0));
        let (w, h) = (64u32, 48u32);
        let camera = looking_down_z();
        let (hits, kept, boxes_met) =
            check_frustum_slots(&world, &camera, (w, h), (0.01, 100.0), &mut next);
        let culled = (w * h) as usize * world.objects.len() - kept;
        assert!(hits > 1000, "{hits} hits");
        // The candidates are few: most objects lie outside a pixel's frustum.
        assert!(culled > (w * h) as usize * 60, "{culled} culled");
        // And fewer than the boxes the frustums meet: the ellipsoids' and triangles' own
        // tests leave out at least a fifth of those.
        assert!(
            kept * 5 < boxes_met * 4,
            "{kept} slots kept of {boxes_met} boxes met"
        );
    }

    #[test]
    fn a_triangle_holds_a_frustum_only_where_its_cone_takes_in_every_edge() {
        // A camera at the origin looking down −z; a block of 8 pixels in the middle of a
        // 64×48 image.
        let camera = looking_down_z();
        let planes = camera.frustum(27.95, 23.95, 36.05, 25.05, 64.0, 48.0);
        let edges = frustum_edges(&planes);
        let big = |z: f64| {
            [
                DVec3::new(-9.0, -9.0, z),
                DVec3::new(9.0, -9.0, z),
                DVec3::new(0.0, 9.0, z),
            ]
        };
        assert!(triangle_holds_frustum(&big(-5.0), DVec3::ZERO, &edges));
        // Behind the apex, the cone through the triangle points the other way.
        assert!(!triangle_holds_frustum(&big(5.0), DVec3::ZERO, &edges));
        // A side through the frustum: some of its rays pass beside the triangle.
        let half = [
            DVec3::new(0.0, -9.0, -5.0),
            DVec3::new(9.0, -9.0, -5.0),
            DVec3::new(0.0, 9.0, -5.0),
        ];
        assert!(!triangle_holds_frustum(&half, DVec3::ZERO, &edges));
        // Wholly beside it.
        let beside = [
            DVec3::new(1.0, -9.0, -5.0),
            DVec3::new(9.0, -9.0, -5.0),
            DVec3::new(1.0, 9.0, -5.0),
        ];
        assert!(!triangle_holds_frustum(&beside, DVec3::ZERO, &edges));
        assert!(triangle_beside_a_frustum(&beside, DVec3::ZERO, &edges));
        // The apex in the triangle's plane.
        let edge_on = [
            DVec3::new(-9.0, 0.0, -5.0),
            DVec3::new(9.0, 0.0, -5.0),
            DVec3::new(0.0, 0.0, 5.0),
        ];
        assert!(!triangle_holds_frustum(&edge_on, DVec3::ZERO, &edges));

        // In a world, a block inside the big triangle keeps it for every pixel untested, and
        // the half triangle is tested per pixel.
        let triangle = |positions| WorldTriangle {
            positions,
            normals: [DVec3::Z; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let world = World::with_movers(
            vec![],
            vec![triangle(big(-5.0)), triangle(half)],
            vec![],
            vec![],
            vec![],
            (0.0, 0.0),
        );
        let mut block = BlockSlots::default();
        world.block_candidates(DVec3::ZERO, &planes, &mut block);
        assert_eq!(block.slots.len(), 2);
        let tested: Vec<(u32, bool)> = block
            .slots
            .iter()
            .copied()
            .zip(block.tested.iter().copied())
            .collect();
        let big_slot = world
            .objects
            .iter()
            .position(|o| matches!(o, Object::Triangle(0)))
            .unwrap();
        for (slot, tested) in tested {
            assert_eq!(tested, slot as usize != big_slot, "slot {slot}");
        }
    }

    /// Points of the floor y = corner.y walked in rows of `columns`, as a row of pixels
    /// would, `per_unit` points per unit along x and z from `corner`.
    struct Floor<'a> {
        rays: usize,
        columns: usize,
        corner: DVec3,
        per_unit: (f64, f64),
        light: DVec3,
        /// The light point's random offset per axis, in [−jitter/2, jitter/2).
        jitter: f64,
        /// Ray i stops at `stops[i % stops.len()]` of the distance to its light point.
        stops: &'a [f64],
    }

    impl Floor<'_> {
        /// A shadow ray from each point toward a jittered light point, with its `t_max`.
        fn shadow_rays(&self, next: &mut impl FnMut() -> f64) -> Vec<(Ray, f64)> {
            (0..self.rays)
                .map(|i| {
                    let p = self.corner
                        + DVec3::new(
                            (i % self.columns) as f64 / self.per_unit.0,
                            0.0,
                            (i / self.columns) as f64 / self.per_unit.1,
                        );
                    let target =
                        self.light + self.jitter * (DVec3::new(next(), next(), next()) - 0.5);
                    let to = target - p;
                    let stop = self.stops[i % self.stops.len()];
                    (Ray::new(p, to.normalize()), to.length() * stop)
                })
                .collect()
        }
    }

    #[test]
    fn a_remembered_blocker_gives_the_walks_answer() {
        let mut next = crate::test_rng::uniform(17);
        let spheres = (0..30)
            .map(|i| Sphere {
                transform: Transform::new(
                    DVec3::new(next() * 8.0 - 4.0, next() * 4.0, next() * 8.0 - 4.0),
                    glam::DQuat::IDENTITY,
                    DVec3::ONE,
                ),
                radius: 0.2 + next() * 0.5,
                material: i,
            })
            .collect();
        let triangles = (0..30)
            .map(|_| {
                let c = DVec3::new(next() * 8.0 - 4.0, next() * 4.0, next() * 8.0 - 4.0);
                let mut corner = || c + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                WorldTriangle {
                    positions: [corner(), corner(), corner()],
                    normals: [DVec3::Y; 3],
                    tex_coords: [DVec2::ZERO; 3],
                    materials: [0; 3],
                }
            })
            .collect();
        let world = World::with_movers(spheres, triangles, vec![], vec![], vec![], (0.0, 0.0));
        let mut cache = ShadowCache::default();
        let (mut blocked, mut remembered) = (0, 0);
        // Some rays stop short of their blocker.
        let floor = Floor {
            rays: 4000,
            columns: 80,
            corner: DVec3::new(-4.0, 0.0, -4.0),
            per_unit: (10.0, 6.0),
            light: DVec3::new(1.0, 9.0, 2.0),
            jitter: 1.0,
            stops: &[0.3, 1.0, 1.0],
        };
        for (i, (ray, t_max)) in floor.shadow_rays(&mut next).into_iter().enumerate() {
            let had = cache.last.is_some();
            let by = world.occluded_by(&ray, t_max, &mut cache, Leaving::NOTHING);
            assert_eq!(by, world.occluded(&ray, t_max), "ray {i}");
            blocked += by as u32;
            remembered += (had && by) as u32;
        }
        assert!(blocked > 400 && blocked < 3600, "{blocked} blocked");
        assert!(remembered > 200, "{remembered} blocked after a blocked ray");
    }

    #[test]
    fn a_remembered_mesh_triangle_gives_the_walks_answer() {
        // A bumpy mesh held over a floor, alone (the one-object path) and beside a sphere (the
        // walk's path): shadow rays from the floor's points in rows, some stopping short of
        // the mesh, each answered as the full walk answers it.
        let mesh = grid_mesh(12, |x, y| 0.3 * (11.0 * x).sin() * (7.0 * y).cos());
        let model = Model {
            transform: Transform::new(
                DVec3::new(-1.5, 2.0, 1.5),
                glam::DQuat::from_rotation_x(-std::f64::consts::FRAC_PI_2),
                DVec3::splat(3.0),
            ),
            mesh: 0,
            material: 0,
        };
        let sphere = Sphere {
            transform: Transform::new(DVec3::new(3.0, 1.0, 0.0), glam::DQuat::IDENTITY, DVec3::ONE),
            radius: 0.5,
            material: 0,
        };
        for spheres in [vec![], vec![sphere]] {
            let world = World::with_movers(
                spheres,
                vec![],
                vec![mesh.clone()],
                vec![model.clone()],
                vec![],
                (0.0, 0.0),
            );
            let slot = (world.objects.iter())
                .position(|o| matches!(o, Object::Model(_)))
                .unwrap() as u32;
            let mut cache = ShadowCache::default();
            let (mut blocked, mut by_triangle) = (0, 0);
            // Some rays stop short of the mesh, or about at it.
            let floor = Floor {
                rays: 3000,
                columns: 60,
                corner: DVec3::new(-2.5, 0.0, -2.5),
                per_unit: (12.0, 10.0),
                light: DVec3::new(0.5, 8.0, -0.5),
                jitter: 0.2,
                stops: &[1.0, 1.0, 0.2, 0.25],
            };
            let rays = floor.shadow_rays(&mut crate::test_rng::uniform(5));
            for (i, (ray, t_max)) in rays.into_iter().enumerate() {
                if cache.last == Some(slot)
                    && world.mesh_triangle_blocks(slot, cache.prim, &ray, t_max)
                {
                    by_triangle += 1;
                }
                let by = world.occluded_by(&ray, t_max, &mut cache, Leaving::NOTHING);
                assert_eq!(by, world.occluded(&ray, t_max), "ray {i}");
                blocked += by as u32;
            }
            assert!(blocked > 300 && blocked < 2700, "{blocked} blocked");
            assert!(
                by_triangle > 100,
                "{by_triangle} blocked by the remembered triangle"
            );
        }
    }

    #[test]
    fn rays_leaving_a_surface_skip_what_they_cannot_meet_and_find_the_same_hits() {
        // A room: a floor of 72 triangles on y = 0, an underlay on y = −1e-7 just below part
        // of it (a parallel plane: rays leaving the floor downward must still hit it), walls,
        // a ceiling, and spheres and tilted triangles in between.
        let mut next = crate::test_rng::uniform(29);
        let flat = |a: DVec3, b: DVec3, c: DVec3| WorldTriangle {
            positions: [a, b, c],
            normals: [(b - a).cross(c - a).normalize(); 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let mut triangles = Vec::new();
        let quad = |triangles: &mut Vec<WorldTriangle>, o: DVec3, u: DVec3, v: DVec3| {
            triangles.push(flat(o, o + u, o + u + v));
            triangles.push(flat(o, o + u + v, o + v));
        };
        for j in 0..6 {
            for i in 0..6 {
                let o = DVec3::new(i as f64 - 3.0, 0.0, j as f64 - 3.0);
                quad(&mut triangles, o, DVec3::Z, DVec3::X);
            }
        }
        quad(
            &mut triangles,
            DVec3::new(-1.0, 1e-7, -1.0),
            DVec3::Z * 2.0,
            DVec3::X * 2.0,
        );
        quad(
            &mut triangles,
            DVec3::new(-3.0, 5.0, -3.0),
            DVec3::X * 6.0,
            DVec3::Z * 6.0,
        );
        quad(
            &mut triangles,
            DVec3::new(-3.0, 0.0, -3.0),
            DVec3::Y * 5.0,
            DVec3::Z * 6.0,
        );
        quad(
            &mut triangles,
            DVec3::new(3.0, 0.0, -3.0),
            DVec3::Z * 6.0,
            DVec3::Y * 5.0,
        );
        for _ in 0..10 {
            let c = DVec3::new(next() * 5.0 - 2.5, next() * 4.0 + 0.5, next() * 5.0 - 2.5);
            let mut corner = || c + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            triangles.push(flat(corner(), corner(), corner()));
        }
        let spheres = (0..6)
            .map(|i| Sphere {
                transform: Transform::new(
                    DVec3::new(next() * 5.0 - 2.5, next() * 3.0 + 0.5, next() * 5.0 - 2.5),
                    glam::DQuat::IDENTITY,
                    DVec3::ONE,
                ),
                radius: 0.2 + next() * 0.4,
                material: i,
            })
            .collect();
        let world = World::with_movers(spheres, triangles, vec![], vec![], vec![], (0.0, 0.0));
        let same = |a: Option<Hit>, b: Option<Hit>| {
            a.map(|h| (h.t.to_bits(), h.object, h.prim))
                == b.map(|h| (h.t.to_bits(), h.object, h.prim))
        };
        let direction = |next: &mut dyn FnMut() -> f64| {
            let d = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
            if d.length() > 1e-3 {
                d.normalize()
            } else {
                DVec3::Y
            }
        };
        let (mut leaving_planes, mut underlay_from_floor, mut blocked) = (0, 0, 0);
        let (mut out_of_spheres, mut into_spheres) = (0, 0);
        let plane_met = |from: DVec3, dir: DVec3| {
            world.leaving(
                &world
                    .intersect(&Ray::new(from, dir), 0.0, f64::INFINITY)
                    .unwrap(),
                true,
            )
        };
        let floor = plane_met(DVec3::new(0.1, 1.0, 0.2), -DVec3::Y);
        let underlay = plane_met(DVec3::new(0.1, -1.0, 0.2), DVec3::Y);
        assert_ne!(floor, underlay);
        for i in 0..6000 {
            let eye = Ray::new(DVec3::new(0.3, 2.5, 0.7), direction(&mut next));
            let Some(hit) = world.intersect(&eye, 0.0, f64::INFINITY) else {
                continue;
            };
            // Spawned as shading spawns them: mirror-like and shadow rays off the surface,
            // to either side (rays into a sphere must still meet its far side).
            let p = eye.at(hit.t);
            let n = world.patch(&eye, &hit).geometric_normal;
            let error_scale = p.abs().max_element() + hit.t;
            let dir = direction(&mut next);
            let leaving = world.leaving(&hit, dir.dot(n) > 0.0);
            let sphere = world.slot_surface[hit.object as usize] != NO_SURFACE
                && matches!(
                    world.objects[hit.object as usize],
                    Object::TranslatedSphere(_)
                );
            if sphere {
                if leaving == Leaving::NOTHING {
                    into_spheres += 1;
                } else {
                    out_of_spheres += 1;
                }
            } else if leaving != Leaving::NOTHING {
                leaving_planes += 1;
            }
            let spawned = crate::shade::spawn_ray(p, n, dir, error_scale, 0.0);
            let walked = world.intersect(&spawned, 0.0, f64::INFINITY);
            let skipping = world.intersect_leaving(&spawned, 0.0, f64::INFINITY, leaving);
            assert!(
                same(walked, skipping),
                "ray {i}: {walked:?} against {skipping:?}"
            );
            underlay_from_floor += (leaving == floor
                && skipping.is_some_and(|h| world.leaving(&h, true) == underlay))
                as u32;
            let light = DVec3::new(next() * 4.0 - 2.0, 4.5, next() * 4.0 - 2.0);
            let to = light - p;
            let shadow = crate::shade::spawn_ray(p, n, to.normalize(), error_scale, 0.0);
            let leaving = world.leaving(&hit, to.dot(n) > 0.0);
            let by = world.occluded_by(&shadow, to.length(), &mut ShadowCache::default(), leaving);
            assert_eq!(by, world.occluded(&shadow, to.length()), "shadow ray {i}");
            blocked += by as u32;
        }
        assert!(leaving_planes > 2000, "{leaving_planes} rays left a plane");
        assert!(
            out_of_spheres > 100 && into_spheres > 100,
            "{out_of_spheres} rays out of spheres, {into_spheres} into them"
        );
        assert!(
            underlay_from_floor > 20,
            "{underlay_from_floor} rays met the underlay from the floor"
        );
        assert!(blocked > 150, "{blocked} shadow rays blocked");
    }

    #[test]
    fn mesh_vertices_are_held_as_f32_only_where_f32_keeps_their_precision() {
        let triangle = [[0u32, 1, 2]];
        let attributes = || (vec![DVec3::Z; 3], vec![DVec2::ZERO; 3]);
        // Coordinates with more digits than f32 holds; a zero; and scales from f32's
        // smallest normal numbers to its largest.
        for (scale, fits) in [
            (1.0, true),
            (1e-30, true),
            (1e30, true),
            (1e-39, false),
            (1e39, false),
        ] {
            let positions = [
                DVec3::new(0.1, 0.2, 0.0),
                DVec3::new(0.7, 0.3, 0.123_456_789_012),
                DVec3::new(0.2, 0.9, -0.3),
            ]
            .map(|p| p * scale);
            let (normals, tex_coords) = attributes();
            let mesh = Mesh::new(&positions, normals, tex_coords, &triangle);
            let slot = (0..mesh.slots())
                .find(|&s| mesh.indices[s] == triangle[0])
                .unwrap();
            let held = if fits {
                positions.map(|p| p.as_vec3().as_dvec3())
            } else {
                positions
            };
            assert_eq!(mesh.corners(slot), held, "scale {scale}");
            assert_eq!(
                matches!(mesh.corners, Corners::InBlocks),
                fits,
                "scale {scale}"
            );
            assert_ne!(
                held[1].z,
                positions[1].z * f64::from(fits),
                "rounded where held as f32"
            );
        }
    }

    #[test]
    fn corners_read_from_the_f32_blocks_find_the_hits_their_f64_copy_finds() {
        // One bumpy mesh as `Mesh::new` stores it (corners in its blocks), and the same mesh,
        // tree and slots with its vertices rounded to f32 in f64 corners (the layout of
        // meshes that f32 cannot hold): every query must give the same bits.
        let bump = |x: f64, y: f64| 0.08 * (17.0 * x).sin() * (11.0 * y).cos();
        let in_blocks = grid_mesh(40, bump);
        assert!(matches!(in_blocks.corners, Corners::InBlocks));
        let (positions, _) = grid(40, bump);
        let mut inline = in_blocks.clone();
        let held = |tri: &[u32; 3]| match *tri {
            PADDING_TRIANGLE => [DVec3::ZERO; 3],
            tri => tri.map(|v| positions[v as usize].as_vec3().as_dvec3()),
        };
        inline.corners = Corners::Inline(inline.indices.iter().map(held).collect());
        let place = (DVec3::new(-0.5, -0.5, -1.5), -0.6);
        let worlds = [in_blocks, inline].map(|m| lone_model(m, place.0, place.1));
        let camera = test_camera(DVec3::ZERO);
        let mut next = crate::test_rng::uniform(47);
        let (mut hits, mut blocked) = (0, 0);
        for _ in 0..200 {
            let rays: Vec<Ray> = (0..16)
                .map(|_| camera.ray(next() * 64.0, next() * 48.0, 64.0, 48.0))
                .collect();
            let mut packets = [[None; 16]; 4];
            for (k, found) in packets.iter_mut().enumerate() {
                let spread = [Spread::Wide, Spread::Pixel][k / 2];
                worlds[k % 2].intersect_packet(&rays, 0.0, f64::INFINITY, None, spread, found);
            }
            for (k, ray) in rays.iter().enumerate() {
                let [a, b] = [&worlds[0], &worlds[1]].map(|w| w.intersect(ray, 0.0, f64::INFINITY));
                assert!(same_hit(a, b), "{a:?} against {b:?}");
                assert!(packets.iter().all(|p| same_hit(a, p[k])));
                let Some(hit) = a else { continue };
                hits += 1;
                // Toward a point behind the grid, from just off the hit: some are blocked.
                let p = ray.at(hit.t);
                let n = worlds[0].patch(ray, &hit).geometric_normal;
                let dir = (DVec3::new(next() - 0.5, next() - 0.5, -2.0) - p).normalize();
                let spawned = crate::shade::spawn_ray(p, n, dir, p.abs().max_element(), 0.0);
                let leaving = worlds[0].leaving(&hit, dir.dot(n) > 0.0);
                let [x, y] =
                    [&worlds[0], &worlds[1]].map(|w| w.occluded_leaving(&spawned, 3.0, leaving));
                assert_eq!(x, y);
                blocked += x as u32;
                let [x, y] = [&worlds[0], &worlds[1]]
                    .map(|w| w.intersect_leaving(&spawned, 0.0, f64::INFINITY, leaving));
                assert!(same_hit(x, y), "{x:?} against {y:?}");
            }
        }
        assert!(
            hits > 400 && blocked > 100,
            "{hits} hits, {blocked} blocked"
        );
    }

    #[test]
    fn rays_leaving_a_mesh_triangle_skip_it_and_find_the_same_hits() {
        // Bumpy grids (rays off a bump meet the next one), two instances of one mesh (a ray
        // leaving one instance's triangle k must still meet the other's), near the origin,
        // small and far from it; and one model alone (the one-object paths).
        let mut next = crate::test_rng::uniform(31);
        let alone = lone_model(
            grid_mesh(40, |x, y| 0.08 * (17.0 * x).sin() * (11.0 * y).cos()),
            DVec3::new(-0.5, -0.5, -1.5),
            -0.6,
        );
        let worlds = [
            (packet_world(1.0, DVec3::ZERO), DVec3::ZERO),
            (
                packet_world(1e-3, DVec3::new(3e3, -2e3, 1e3)),
                DVec3::new(3e3, -2e3, 1e3),
            ),
            (alone, DVec3::ZERO),
        ];
        for (w, (world, offset)) in worlds.iter().enumerate() {
            let camera = test_camera(*offset);
            let (mut left_mesh, mut met_own_model, mut blocked) = (0, 0, 0);
            let (mut packet, mut limits, mut leavings) = (Vec::new(), Vec::new(), Vec::new());
            for _ in 0..20_000 {
                let eye = camera.ray(next() * 64.0, next() * 48.0, 64.0, 48.0);
                let Some(hit) = world.intersect(&eye, 0.0, f64::INFINITY) else {
                    continue;
                };
                let p = eye.at(hit.t);
                let n = world.patch(&eye, &hit).geometric_normal;
                let error_scale = p.abs().max_element() + hit.t;
                // Mostly grazing directions, to either side: they meet the next bump.
                let dir = (DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5)
                    + n * (next() - 0.5) * 0.3)
                    .normalize();
                let leaving = world.leaving(&hit, dir.dot(n) > 0.0);
                if leaving.prim_in(hit.object as usize) == hit.prim {
                    left_mesh += 1;
                }
                let spawned = crate::shade::spawn_ray(p, n, dir, error_scale, 0.0);
                let walked = world.intersect(&spawned, 0.0, f64::INFINITY);
                let skipping = world.intersect_leaving(&spawned, 0.0, f64::INFINITY, leaving);
                assert!(
                    same_hit(walked, skipping),
                    "world {w}: {walked:?} against {skipping:?}"
                );
                met_own_model += walked.is_some_and(|h| h.object == hit.object) as u32;
                for t_max in [0.05, 10.0] {
                    let t_max = t_max * error_scale.max(1e-3);
                    let alone = world.occluded(&spawned, t_max);
                    assert_eq!(alone, world.occluded_leaving(&spawned, t_max, leaving));
                    let mut cache = ShadowCache::default();
                    assert_eq!(
                        alone,
                        world.occluded_by(&spawned, t_max, &mut cache, leaving)
                    );
                    blocked += alone as u32;
                    packet.push(spawned);
                    limits.push(t_max);
                    leavings.push(leaving);
                }
                if packet.len() == PACKET {
                    let mut found = [false; PACKET];
                    world.occluded_packet(&packet, &limits, &leavings, &mut found);
                    for (i, ray) in packet.iter().enumerate() {
                        assert_eq!(found[i], world.occluded(ray, limits[i]), "world {w}");
                    }
                    packet.clear();
                    limits.clear();
                    leavings.clear();
                }
            }
            assert!(left_mesh > 3000, "world {w}: {left_mesh} rays left a mesh");
            assert!(
                met_own_model > 250,
                "world {w}: {met_own_model} rays met the model they left"
            );
            assert!(blocked > 1000, "world {w}: {blocked} shadow rays blocked");
        }
    }

    #[test]
    fn mirror_rays_off_a_plane_meet_among_its_mirror_slots_what_the_walk_meets() {
        // A floor on y = 0 and a wall on x = 3 (axis-aligned, flat normals), a floor patch
        // with tilted normals (no mirror plane), spheres, tilted triangles and a bumpy mesh
        // model above them, near the origin and far from it at a small scale.
        let mut next = crate::test_rng::uniform(37);
        for (scale, offset) in [(1.0, DVec3::ZERO), (1e-3, DVec3::new(3e3, -2e3, 1e3))] {
            let at = |p: DVec3| offset + p * scale;
            let tri = |a: DVec3, b: DVec3, c: DVec3, normal: DVec3| WorldTriangle {
                positions: [at(a), at(b), at(c)],
                normals: [normal; 3],
                tex_coords: [DVec2::ZERO; 3],
                materials: [0; 3],
            };
            let mut triangles = Vec::new();
            for j in 0..6 {
                for i in 0..6 {
                    let o = DVec3::new(i as f64 - 3.0, 0.0, j as f64 - 5.0);
                    let normal = if (i, j) == (2, 3) {
                        DVec3::new(0.1, 1.0, 0.0).normalize()
                    } else {
                        DVec3::Y
                    };
                    triangles.push(tri(o, o + DVec3::Z, o + DVec3::X + DVec3::Z, normal));
                    triangles.push(tri(o, o + DVec3::X + DVec3::Z, o + DVec3::X, normal));
                }
            }
            let w = DVec3::new(3.0, 0.0, -5.0);
            triangles.push(tri(w, w + DVec3::Y * 3.0, w + DVec3::Z * 6.0, -DVec3::X));
            for _ in 0..8 {
                let c = DVec3::new(next() * 5.0 - 2.5, next() * 2.0 + 0.3, next() * 5.0 - 4.5);
                let mut corner = || c + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                triangles.push(tri(corner(), corner(), corner(), DVec3::Y));
            }
            let spheres = (0..5)
                .map(|i| Sphere {
                    transform: Transform::new(
                        at(DVec3::new(
                            next() * 5.0 - 2.5,
                            next() * 2.0 + 0.4,
                            next() * 4.0 - 4.0,
                        )),
                        glam::DQuat::IDENTITY,
                        DVec3::ONE,
                    ),
                    radius: (0.2 + next() * 0.3) * scale,
                    material: i,
                })
                .collect();
            let models = vec![Model {
                transform: Transform::new(
                    at(DVec3::new(-1.0, 0.8, -3.0)),
                    glam::DQuat::from_rotation_x(-1.2),
                    DVec3::splat(1.5 * scale),
                ),
                mesh: 0,
                material: 0,
            }];
            let mesh = grid_mesh(20, |x, y| 0.1 * (9.0 * x).sin() * (7.0 * y).cos());
            let world =
                World::with_movers(spheres, triangles, vec![mesh], models, vec![], (0.0, 0.0));
            let camera = crate::camera::Camera::from_orientation(
                at(DVec3::new(0.0, 1.5, 1.5)),
                glam::DQuat::from_rotation_x(-0.45),
                1.2,
                0.0,
                f64::INFINITY,
                4.0 / 3.0,
            );
            let (w, h) = (48u32, 36u32);
            let mut slots = Vec::new();
            let (mut checked, mut hits, mut empty, mut kept) = (0, 0, 0, 0);
            for y in 0..h {
                for x in 0..w {
                    let (x0, y0) = (x as f64 - 0.05, y as f64 - 0.05);
                    let planes = camera.frustum(x0, y0, x0 + 1.1, y0 + 1.1, w as f64, h as f64);
                    for k in 0..6 {
                        let (jx, jy) = if k < 2 {
                            (k as f64, k as f64)
                        } else {
                            (next(), next())
                        };
                        let eye = camera.ray(x as f64 + jx, y as f64 + jy, w as f64, h as f64);
                        let Some(hit) = world.intersect(&eye, 0.0, f64::INFINITY) else {
                            continue;
                        };
                        let Some(plane) = world.mirror_plane(&hit) else {
                            continue;
                        };
                        // Spawned as shading spawns a perfect mirror ray.
                        let s = world.patch(&eye, &hit);
                        let n = crate::shade::toward_viewer(s.normal, eye.dir);
                        let dir = crate::shade::reflect(eye.dir, n);
                        let error_scale = eye.at(hit.t).abs().max_element() + hit.t;
                        let mirror = crate::shade::spawn_ray(
                            s.position,
                            s.geometric_normal,
                            dir,
                            error_scale,
                            0.0,
                        );
                        let leaving = world.leaving(&hit, dir.dot(s.geometric_normal) > 0.0);
                        world.mirror_slots(plane, (camera.position, &planes), leaving, &mut slots);
                        let walked = world.intersect_leaving(&mirror, 0.0, f64::INFINITY, leaving);
                        let among = world.intersect_among(&mirror, 0.0, f64::INFINITY, &slots);
                        assert!(
                            same_hit(walked, among),
                            "scale {scale}, pixel ({x}, {y}): {walked:?} against {among:?}"
                        );
                        checked += 1;
                        hits += walked.is_some() as u32;
                        empty += slots.is_empty() as u32;
                        kept += slots.len();
                    }
                }
            }
            assert!(checked > 3000, "scale {scale}: {checked} mirror rays");
            assert!(hits > 300, "scale {scale}: {hits} mirror rays hit");
            assert!(empty > 300, "scale {scale}: {empty} with no slot");
            // Of 87 objects, fewer than one slot a ray on average.
            assert!(
                kept < checked,
                "scale {scale}: {kept} slots for {checked} rays"
            );
        }
    }

    #[test]
    fn a_ray_leaving_a_plane_meets_none_of_its_triangles() {
        // Even one that starts below the floor heading up: what it leaves is the caller's word.
        let floor = |x: f64| WorldTriangle {
            positions: [
                DVec3::new(x, 0.0, -1.0),
                DVec3::new(x, 0.0, 1.0),
                DVec3::new(x + 1.0, 0.0, 0.0),
            ],
            normals: [DVec3::Y; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let world = World::with_movers(
            vec![],
            vec![floor(0.0), floor(5.0)],
            vec![],
            vec![],
            vec![],
            (0.0, 0.0),
        );
        let down = Ray::new(DVec3::new(5.2, 1.0, 0.0), -DVec3::Y);
        let on_floor = world.intersect(&down, 0.0, f64::INFINITY).unwrap();
        let leaving = world.leaving(&on_floor, false);
        assert_ne!(leaving, Leaving::NOTHING);
        let up = Ray::new(DVec3::new(0.2, -1.0, 0.0), DVec3::Y);
        assert!(world.intersect(&up, 0.0, f64::INFINITY).is_some());
        assert!(world
            .intersect_leaving(&up, 0.0, f64::INFINITY, leaving)
            .is_none());
        assert!(world.occluded(&up, 5.0));
        assert!(!world.occluded_by(&up, 5.0, &mut ShadowCache::default(), leaving));
    }

    #[test]
    fn rays_leaving_a_surface_test_only_what_lies_off_it_and_find_every_hit() {
        // cube.scene's make-up: a floor of two triangles, a mesh instance above it (a bumpy
        // grid, tilted), a sphere and a tilted triangle. Rays leaving the floor test the
        // other three slots in turn, the instance behind its box; with six more spheres they
        // walk a top level of the nine slots off the floor.
        for extra in [0, 6] {
            check_rays_leaving_the_floor(extra);
        }
    }

    fn check_rays_leaving_the_floor(extra_spheres: usize) {
        let mut next = crate::test_rng::uniform(41);
        let floor = |a: DVec3, b: DVec3, c: DVec3| WorldTriangle {
            positions: [a, b, c],
            normals: [DVec3::Y; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let (a, b, c, d) = (
            DVec3::new(-4.0, 0.0, -4.0),
            DVec3::new(-4.0, 0.0, 4.0),
            DVec3::new(4.0, 0.0, 4.0),
            DVec3::new(4.0, 0.0, -4.0),
        );
        let mut tilted = floor(
            DVec3::new(-2.0, 0.5, 1.0),
            DVec3::new(-1.0, 2.0, 1.5),
            DVec3::new(-2.5, 1.0, 2.5),
        );
        tilted.normals = [DVec3::X; 3];
        let triangles = vec![floor(a, b, c), floor(c, d, a), tilted];
        let mesh = grid_mesh(6, |x, y| 0.2 * (x * 7.0).sin() * (y * 5.0).cos());
        let model = Model {
            transform: Transform::new(
                DVec3::new(0.5, 1.0, -0.5),
                glam::DQuat::from_rotation_x(1.1),
                DVec3::splat(1.5),
            ),
            mesh: 0,
            material: 0,
        };
        let sphere = |centre: DVec3, radius: f64| Sphere {
            transform: Transform::new(centre, glam::DQuat::IDENTITY, DVec3::ONE),
            radius,
            material: 0,
        };
        let mut spheres = vec![sphere(DVec3::new(1.5, 0.7, 1.5), 0.6)];
        for _ in 0..extra_spheres {
            let centre = DVec3::new(next() * 6.0 - 3.0, next() * 2.0 + 0.3, next() * 6.0 - 3.0);
            spheres.push(sphere(centre, 0.1 + next() * 0.3));
        }
        let world = World::with_movers(
            spheres,
            triangles,
            vec![mesh],
            vec![model],
            vec![],
            (0.0, 0.0),
        );
        let down = Ray::new(DVec3::new(3.0, 5.0, -3.0), -DVec3::Y);
        let on_floor = world.intersect(&down, 0.0, f64::INFINITY).unwrap();
        let up = world.leaving(&on_floor, true);
        let surface = up.surface as usize;
        let off_floor = 3 + extra_spheres;
        match &world.off_surface[surface] {
            Some(OffSurface::Listed(rest)) => {
                assert!(
                    off_floor <= LINEAR_TOP,
                    "the floor's rays test the slots off it in turn"
                );
                assert_eq!(rest.len(), off_floor);
            }
            Some(OffSurface::Walked(sub)) => {
                assert!(
                    off_floor > LINEAR_TOP,
                    "the floor's rays walk the slots off it"
                );
                assert_eq!(sub.slots.len(), off_floor);
            }
            None => panic!("no slots off the floor kept"),
        }
        // Every slot off the floor, tested in slot order with no culling: what a ray leaving
        // the floor can meet, by definition.
        let brute = |ray: &Ray, t_max: f64| {
            let (mut best, mut limit) = (None, t_max);
            for slot in 0..world.objects.len() {
                if world.skips(slot, up) {
                    continue;
                }
                let bound = tie_bound(best.is_some(), limit);
                if let Some(h) =
                    world.hit_object::<false>(slot, ray, 0.0, bound, up.prim_in(slot), &mut None)
                {
                    keep_nearer(&mut best, &mut limit, slot, h);
                }
            }
            best
        };
        let (mut hits, mut model_hits, mut blocked) = (0, 0, 0);
        let mut cache = ShadowCache::default();
        for _ in 0..4000 {
            let from = DVec3::new(next() * 8.0 - 4.0, 0.0, next() * 8.0 - 4.0);
            let dir = DVec3::new(next() - 0.5, next(), next() - 0.5).normalize();
            let ray = Ray::new(from, dir);
            let expected = brute(&ray, f64::INFINITY);
            let found = world.intersect_leaving(&ray, 0.0, f64::INFINITY, up);
            assert_eq!(
                found.map(|h| (h.t.to_bits(), h.object, h.prim)),
                expected.map(|h| (h.t.to_bits(), h.object, h.prim)),
                "ray from {from} along {dir}"
            );
            hits += found.is_some() as usize;
            model_hits += found
                .is_some_and(|h| matches!(world.objects[h.object as usize], Object::Model(_)))
                as usize;
            // A shadow ray toward a point 3 units along: blocked where the nearest hit is
            // nearer, whichever remembered blocker the cache holds.
            let length = 3.0;
            let is_blocked = expected.is_some_and(|h| h.t < length);
            assert_eq!(world.occluded_leaving(&ray, length, up), is_blocked);
            assert_eq!(world.occluded_by(&ray, length, &mut cache, up), is_blocked);
            blocked += is_blocked as usize;
        }
        assert!(
            hits > 200 && model_hits > 50 && blocked > 150,
            "{hits} {model_hits} {blocked}"
        );
    }

    #[test]
    fn rays_leaving_a_box_mesh_outward_skip_it_whole_and_find_every_hit() {
        // A cube mesh (wound outward) turned and scaled above a floor, as in cube.scene.
        let corner = |k: usize| {
            DVec3::new(
                (k & 1) as f64 * 2.0 - 1.0,
                (k >> 1 & 1) as f64 * 2.0 - 1.0,
                (k >> 2 & 1) as f64 * 2.0 - 1.0,
            )
        };
        let positions: Vec<DVec3> = (0..8).map(corner).collect();
        let mut triangles = Vec::new();
        for axis in 0..3 {
            for side in 0..2 {
                let on: Vec<u32> = (0..8u32)
                    .filter(|&k| (k as usize >> axis & 1) == side)
                    .collect();
                // The face's corners in a cycle: 0, 1, 3, 2 of those four.
                let [a, b, c, d] = [on[0], on[1], on[3], on[2]];
                for tri in [[a, b, c], [a, c, d]] {
                    let [p, q, r] = tri.map(|v| positions[v as usize]);
                    let outward = (q - p).cross(r - p).dot(p + q + r) > 0.0;
                    triangles.push(if outward {
                        tri
                    } else {
                        [tri[0], tri[2], tri[1]]
                    });
                }
            }
        }
        let mesh = Mesh::new(
            &positions,
            vec![DVec3::Y; 8],
            vec![DVec2::ZERO; 8],
            &triangles,
        );
        assert!(
            (0..mesh.slots() as u32)
                .filter(|&s| mesh.indices[s as usize] != PADDING_TRIANGLE)
                .all(|s| mesh.exits(s, true) && !mesh.exits(s, false)),
            "every face of a box is left to the outside only"
        );
        let bumpy = grid_mesh(4, |x, y| 0.3 * (x * 5.0).sin() * (y * 3.0).cos());
        assert!(
            (0..bumpy.slots() as u32).any(|s| !bumpy.exits(s, true) && !bumpy.exits(s, false)),
            "a bumpy grid's triangles do not all have the grid on one side"
        );
        let model = Model {
            transform: Transform::new(
                DVec3::new(0.0, 1.5, 0.0),
                glam::DQuat::from_rotation_y(1.3),
                DVec3::new(1.0, 0.7, 1.3),
            ),
            mesh: 0,
            material: 0,
        };
        let world = World::with_movers(
            vec![],
            square_floor(9.0),
            vec![mesh],
            vec![model],
            vec![],
            (0.0, 0.0),
        );
        let mut next = crate::test_rng::uniform(77);
        let (mut outward, mut inward, mut floor_hits) = (0, 0, 0);
        for _ in 0..3000 {
            let from = DVec3::new(next() * 8.0 - 4.0, 6.0, next() * 8.0 - 4.0);
            let eye = Ray::new(from, (DVec3::new(0.0, 1.5, 0.0) - from).normalize());
            let Some(hit) = world.intersect(&eye, 0.0, f64::INFINITY) else {
                continue;
            };
            if !matches!(world.objects[hit.object as usize], Object::Model(_)) {
                continue;
            }
            let patch = world.patch(&eye, &hit);
            let p = eye.at(hit.t);
            let error_scale = p.abs().max_element() + hit.t;
            let dir = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5).normalize();
            let front = dir.dot(patch.geometric_normal) > 0.0;
            let leaving = world.leaving(&hit, front);
            assert_eq!(leaving.surface != Leaving::NOTHING.surface, front);
            let ray = crate::shade::spawn_ray(p, patch.geometric_normal, dir, error_scale, 0.0);
            // Every slot tested, the model too, skipping only the triangle left.
            let mut brute = None;
            let mut limit = f64::INFINITY;
            for slot in 0..world.objects.len() {
                let skip = leaving.prim_in(slot);
                let bound = tie_bound(brute.is_some(), limit);
                if let Some(h) = world.hit_object::<false>(slot, &ray, 0.0, bound, skip, &mut None)
                {
                    keep_nearer(&mut brute, &mut limit, slot, h);
                }
            }
            let found = world.intersect_leaving(&ray, 0.0, f64::INFINITY, leaving);
            assert_eq!(
                found.map(|h| (h.t.to_bits(), h.object, h.prim)),
                brute.map(|h| (h.t.to_bits(), h.object, h.prim)),
                "ray from {p} along {dir}"
            );
            assert_eq!(
                world.occluded_leaving(&ray, 50.0, leaving),
                brute.is_some_and(|h| h.t < 50.0)
            );
            outward += front as usize;
            inward += !front as usize;
            floor_hits += found.is_some() as usize;
        }
        assert!(
            outward > 500 && inward > 500 && floor_hits > 300,
            "{outward} {inward} {floor_hits}"
        );
    }

    /// cube.scene's floor at `half` units: the square of side 2·`half` on y = 0, as two
    /// triangles meeting on the diagonal x = z, normals up.
    fn square_floor(half: f64) -> Vec<WorldTriangle> {
        let floor = |corners: [[f64; 2]; 3]| WorldTriangle {
            positions: corners.map(|[x, z]| DVec3::new(x * half, 0.0, z * half)),
            normals: [DVec3::Y; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let (a, b, c, d) = ([-1.0, -1.0], [-1.0, 1.0], [1.0, 1.0], [1.0, -1.0]);
        vec![floor([a, b, c]), floor([c, d, a])]
    }

    /// A world of `mesh` alone, as one model at `position` turned by `tilt` about x.
    fn lone_model(mesh: Mesh, position: DVec3, tilt: f64) -> World {
        let model = Model {
            transform: Transform::new(position, glam::DQuat::from_rotation_x(tilt), DVec3::ONE),
            mesh: 0,
            material: 0,
        };
        World::with_movers(vec![], vec![], vec![mesh], vec![model], vec![], (0.0, 0.0))
    }

    /// A `n`×`n` grid of squares over [0, 1]² (two triangles each) at height `bump(x, y)`.
    fn grid_mesh(n: usize, bump: impl Fn(f64, f64) -> f64) -> Mesh {
        let (positions, triangles) = grid(n, bump);
        let normals = vec![DVec3::Z; positions.len()];
        let tex_coords = vec![DVec2::ZERO; positions.len()];
        Mesh::new(&positions, normals, tex_coords, &triangles)
    }

    /// [`grid_mesh`]'s vertices and triangles.
    fn grid(n: usize, bump: impl Fn(f64, f64) -> f64) -> (Vec<DVec3>, Vec<[u32; 3]>) {
        let mut positions = Vec::new();
        for j in 0..=n {
            for i in 0..=n {
                let (x, y) = (i as f64 / n as f64, j as f64 / n as f64);
                positions.push(DVec3::new(x, y, bump(x, y)));
            }
        }
        let v = |i: usize, j: usize| (j * (n + 1) + i) as u32;
        let mut triangles = Vec::new();
        for j in 0..n {
            for i in 0..n {
                triangles.push([v(i, j), v(i + 1, j), v(i + 1, j + 1)]);
                triangles.push([v(i, j), v(i + 1, j + 1), v(i, j + 1)]);
            }
        }
        (positions, triangles)
    }

    /// For every pixel of a `size` image of `camera`: the pixel's frustum slots (its frustum
    /// a twentieth of a pixel wider each way, as the renderer's), checked to give its eye rays
    /// through the pixel's corners and random points the same hits in (near, far) as the
    /// full walk. Returns the hits, the slots kept and the top-level boxes the frustums met.
    fn check_frustum_slots(
        world: &World,
        camera: &crate::camera::Camera,
        (w, h): (u32, u32),
        (near, far): (f64, f64),
        next: &mut impl FnMut() -> f64,
    ) -> (u32, usize, usize) {
        let (mut slots, mut among_block) = (Vec::new(), Vec::new());
        let mut block = BlockSlots::default();
        let (mut hits, mut kept, mut boxes_met) = (0, 0, 0);
        for y in 0..h {
            for x in 0..w {
                // Blocks of 8 pixels, as the renderer's.
                if x % 8 == 0 {
                    let (x0, y0) = (x as f64 - 0.05, y as f64 - 0.05);
                    let x1 = (x + 8).min(w) as f64 + 0.05;
                    let planes = camera.frustum(x0, y0, x1, y0 + 1.1, w as f64, h as f64);
                    world.block_candidates(camera.position, &planes, &mut block);
                }
                let (x0, y0) = (x as f64 - 0.05, y as f64 - 0.05);
                let planes = camera.frustum(x0, y0, x0 + 1.1, y0 + 1.1, w as f64, h as f64);
                world.frustum_slots(camera.position, &planes, &mut slots);
                world.frustum_slots_among(camera.position, &planes, &mut block, &mut among_block);
                kept += slots.len();
                if world.costly_top {
                    // Instances nearest first, after every other object.
                    let keys: Vec<f64> = slots
                        .iter()
                        .map(|&slot| world.slot_order(slot, camera.position))
                        .collect();
                    assert!(
                        keys.windows(2).all(|k| k[0] <= k[1]),
                        "pixel ({x}, {y}): {keys:?}"
                    );
                }
                world
                    .top_level
                    .frustum(camera.position, &planes, &mut |r| boxes_met += r.len());
                for k in 0..12 {
                    let (jx, jy) = match k {
                        0 => (0.0, 0.0),
                        1 => (1.0, 1.0),
                        2 => (0.0, 1.0),
                        3 => (1.0, 0.0),
                        _ => (next(), next()),
                    };
                    let ray = camera.ray(x as f64 + jx, y as f64 + jy, w as f64, h as f64);
                    let full = world.intersect(&ray, near, far);
                    let among = world.intersect_among(&ray, near, far, &slots);
                    assert!(
                        same_hit(full, among),
                        "pixel ({x}, {y}), sample {k}: {full:?} against {among:?}"
                    );
                    let among = world.intersect_among(&ray, near, far, &among_block);
                    assert!(
                        same_hit(full, among),
                        "pixel ({x}, {y}), sample {k}, block's candidates: {full:?} against {among:?}"
                    );
                    hits += full.is_some() as u32;
                }
            }
        }
        (hits, kept, boxes_met)
    }

    fn same_hit(a: Option<Hit>, b: Option<Hit>) -> bool {
        match (a, b) {
            (None, None) => true,
            (Some(a), Some(b)) => {
                a.t.to_bits() == b.t.to_bits()
                    && a.object == b.object
                    && a.prim == b.prim
                    && a.bary.map(f64::to_bits) == b.bary.map(f64::to_bits)
            }
            _ => false,
        }
    }

    /// Two instances of a bumpy grid (one turned and scaled), a flat one, and spheres, at
    /// scale `scale` around `offset`.
    fn packet_world(scale: f64, offset: DVec3) -> World {
        let bumpy = grid_mesh(40, |x, y| 0.05 * (13.0 * x).sin() * (9.0 * y).cos());
        let flat = grid_mesh(16, |_, _| 0.0);
        let at = |p: DVec3, turn: f64, s: f64| Model {
            transform: Transform::new(
                offset + p * scale,
                glam::DQuat::from_rotation_z(turn) * glam::DQuat::from_rotation_x(-0.3),
                DVec3::splat(s * scale),
            ),
            mesh: 0,
            material: 0,
        };
        let models = vec![
            at(DVec3::new(-1.0, -0.5, -3.0), 0.0, 2.0),
            at(DVec3::new(0.2, -0.8, -4.0), 0.7, 1.5),
            Model {
                mesh: 1,
                ..at(DVec3::new(-0.5, 0.3, -2.5), 0.2, 1.0)
            },
        ];
        let spheres = (0..3)
            .map(|i| Sphere {
                transform: Transform::new(
                    offset + DVec3::new(i as f64 * 0.6 - 0.6, 0.2, -3.2) * scale,
                    glam::DQuat::IDENTITY,
                    DVec3::ONE,
                ),
                radius: 0.15 * scale,
                material: 0,
            })
            .collect();
        World::with_movers(
            spheres,
            vec![],
            vec![bumpy, flat],
            models,
            vec![],
            (0.0, 0.0),
        )
    }

    /// A camera at `offset` looking down −z (the packet worlds' view), 4:3, no clipping.
    fn test_camera(offset: DVec3) -> crate::camera::Camera {
        crate::camera::Camera::from_orientation(
            offset,
            glam::DQuat::IDENTITY,
            1.0,
            0.0,
            f64::INFINITY,
            4.0 / 3.0,
        )
    }

    #[test]
    fn a_pixels_frustum_keeps_a_model_only_where_its_triangles_may_meet_it() {
        // Tilted, bumpy grid models (boxes with much empty space) near the origin and far
        // from it at a small scale.
        let mut next = crate::test_rng::uniform(11);
        for (scale, offset) in [(1.0, DVec3::ZERO), (1e-3, DVec3::new(3e3, -2e3, 1e3))] {
            let world = packet_world(scale, offset);
            let camera = test_camera(offset);
            let (hits, kept, boxes_met) =
                check_frustum_slots(&world, &camera, (64, 48), (0.0, f64::INFINITY), &mut next);
            assert!(hits > 5_000, "scale {scale}: {hits} hits");
            assert!(
                kept * 10 < boxes_met * 9,
                "scale {scale}: {kept} slots kept of {boxes_met} boxes met"
            );
        }
    }

    #[test]
    fn a_pixels_frustum_leaves_out_the_floor_triangle_beside_it() {
        // cube.scene's floor and view: two triangles of 4,000 units meeting on a diagonal
        // under the camera. Each pixel's frustum lies beside one of them, except near the
        // diagonal, though neither lies behind one of its planes.
        let world = World::with_movers(
            vec![],
            square_floor(2e3),
            vec![],
            vec![],
            vec![],
            (0.0, 0.0),
        );
        let camera = crate::camera::Camera::from_orientation(
            DVec3::new(0.0, 6.0, 11.0),
            glam::DQuat::from_axis_angle(DVec3::X, -0.5),
            0.785,
            0.01,
            200.0,
            4.0 / 3.0,
        );
        let mut next = crate::test_rng::uniform(5);
        let (w, h) = (64, 48);
        let (hits, kept, boxes_met) =
            check_frustum_slots(&world, &camera, (w, h), (0.01, 200.0), &mut next);
        let pixels = (w * h) as usize;
        assert!(hits > 12 * pixels as u32 / 2, "{hits} hits");
        assert_eq!(
            boxes_met,
            2 * pixels,
            "both boxes hold every pixel's frustum"
        );
        assert!(
            kept * 10 < pixels * 12,
            "{kept} slots kept over {pixels} pixels"
        );
    }

    #[test]
    fn a_packet_finds_exactly_each_rays_own_hit() {
        let mut next = crate::test_rng::uniform(2024);
        for (scale, offset) in [
            (1.0, DVec3::ZERO),
            (1e-3, DVec3::new(0.5, -0.2, 0.1)),
            (1e4, DVec3::new(3e4, 1e3, -2e4)),
        ] {
            let world = packet_world(scale, offset);
            let all: Vec<u32> = (0..world.objects.len() as u32).collect();
            let camera = test_camera(offset);
            let (w, h) = (96.0, 72.0);
            let (mut hits, mut rays_traced) = (0, 0);
            for k in 0..160 {
                // 8×8 pixel blocks (some with jittered samples), single rays, every ray of
                // a packet from its own origin in its own direction, and odd sizes.
                let n = [64, 64, 1, 17, 64, 5][k % 6];
                let (bx, by) = ((k * 8) as f64 % w, ((k * 8) as f64 / w).floor() * 8.0 % h);
                let rays: Vec<Ray> = (0..n)
                    .map(|i| {
                        if k % 6 == 4 {
                            let o = offset + DVec3::new(next() - 0.5, next() - 0.5, next()) * scale;
                            let d = DVec3::new(next() - 0.5, next() - 0.5, -next());
                            return Ray::new(o, d.normalize());
                        }
                        let (jx, jy) = if k % 2 == 0 {
                            (0.5, 0.5)
                        } else {
                            (next(), next())
                        };
                        let (x, y) = (bx + (i % 8) as f64 + jx, by + (i / 8) as f64 + jy);
                        camera.ray(x, y, w, h)
                    })
                    .collect();
                let (t_min, t_max) = if k % 5 == 0 {
                    (0.1 * scale, 3.1 * scale)
                } else {
                    (0.0, f64::INFINITY)
                };
                let mut found = vec![None; n];
                let mut among = vec![None; n];
                // Eye rays of a block of pixels, taken as a wide packet and (what the renderer
                // does only for one pixel's) as a pixel packet: the same hits either way.
                let spread = [Spread::Wide, Spread::Pixel][k % 3 / 2];
                world.intersect_packet(&rays, t_min, t_max, None, spread, &mut found);
                world.intersect_packet(&rays, t_min, t_max, Some(&all), spread, &mut among);
                for (i, ray) in rays.iter().enumerate() {
                    let single = world.intersect(ray, t_min, t_max);
                    assert!(
                        same_hit(single, found[i]) && same_hit(single, among[i]),
                        "scale {scale}, packet {k}, ray {i}: {single:?} {:?} {:?}",
                        found[i],
                        among[i]
                    );
                    assert!(same_hit(
                        single,
                        world.intersect_among(ray, t_min, t_max, &all)
                    ));
                    hits += single.is_some() as usize;
                    rays_traced += 1;
                }
            }
            assert!(
                hits > rays_traced / 8 && hits < rays_traced,
                "{hits} of {rays_traced}"
            );
        }
        // An empty packet, and one no ray of which hits anything.
        let world = packet_world(1.0, DVec3::ZERO);
        world.intersect_packet(&[], 0.0, f64::INFINITY, None, Spread::Wide, &mut []);
        let away: Vec<Ray> = (0..64)
            .map(|i| {
                Ray::new(
                    DVec3::ZERO,
                    DVec3::new(i as f64 * 0.01, 0.1, 1.0).normalize(),
                )
            })
            .collect();
        for spread in [Spread::Wide, Spread::Pixel] {
            let mut found = vec![None; 64];
            world.intersect_packet(&away, 0.0, f64::INFINITY, None, spread, &mut found);
            assert!(found.iter().all(Option::is_none));
        }
    }

    #[test]
    fn may_enter_keeps_every_ray_through_the_box_and_drops_clear_misses() {
        // Boxes at three scales and offsets. A ray aimed at a point of the box (on a face, an
        // edge or a corner for some draws), from outside or inside, must be kept for every
        // t range holding that point; one stopped at half its distance to the box, or leaving
        // it, must be dropped (the filter has to filter, or packets gain nothing).
        let mut next = crate::test_rng::uniform(77);
        for (scale, offset) in [
            (1.0, DVec3::ZERO),
            (1e-5, DVec3::new(1e3, -2e3, 5e2)),
            (1e6, DVec3::new(-3e7, 1e7, 2e6)),
        ] {
            let b = Aabb {
                min: offset + DVec3::new(-1.0, -0.5, -2.0) * scale,
                max: offset + DVec3::new(0.5, 1.5, -1.0) * scale,
            };
            let (mut short, mut away) = (0, 0);
            for k in 0..3000 {
                let mut pick = |lo: f64, hi: f64| match k % 4 {
                    0 => lo,
                    1 => hi,
                    _ => lo + (hi - lo) * next(),
                };
                let target = DVec3::new(
                    pick(b.min.x, b.max.x),
                    pick(b.min.y, b.max.y),
                    pick(b.min.z, b.max.z),
                );
                let origin =
                    offset + DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5) * (8.0 * scale);
                let dir = (target - origin).normalize();
                let ray = Ray::new(origin, dir);
                let t = (target - origin).dot(dir);
                assert!(
                    may_enter(&b, &ray, 0.0, f64::INFINITY),
                    "{ray:?} toward {target}"
                );
                assert!(may_enter(&b, &ray, t, t), "{ray:?} at t = {t} alone");
                // Its distance to the box bounds the distance at which it can enter.
                let gap = b.distance_squared(origin).sqrt();
                if gap > 0.0 {
                    short += !may_enter(&b, &ray, 0.0, 0.5 * gap) as usize;
                    let leaving = Ray::new(origin, -dir);
                    away += !may_enter(&b, &leaving, 0.0, f64::INFINITY) as usize;
                }
            }
            assert!(
                short > 1000 && away > 1000,
                "scale {scale}: {short} and {away} dropped"
            );
            // Parallel to an axis, along the box's edge: kept (an infinite inverse direction).
            let along = Ray::new(DVec3::new(b.min.x, b.max.y, b.min.z - scale), DVec3::Z);
            assert!(may_enter(&b, &along, 0.0, f64::INFINITY));
        }
    }

    #[test]
    fn a_lone_small_model_stays_an_instance_and_several_are_flattened() {
        let small = |x: f64| Model {
            transform: Transform::new(DVec3::new(x, 0.0, -3.0), glam::DQuat::IDENTITY, DVec3::ONE),
            mesh: 0,
            material: 0,
        };
        let world = |models: Vec<Model>| {
            World::with_movers(
                vec![],
                vec![],
                vec![grid_mesh(2, |x, _| 0.2 * x)],
                models,
                vec![],
                (0.0, 0.0),
            )
        };
        let lone = world(vec![small(0.0)]);
        assert!(lone.model_triangles.is_empty());
        assert!(matches!(lone.objects[..], [Object::Model(0)]));
        let pair = world(vec![small(0.0), small(2.0)]);
        assert_eq!(pair.model_triangles.len(), 16);
        assert!(pair
            .objects
            .iter()
            .all(|o| matches!(o, Object::ModelTriangle(_))));
    }

    #[test]
    fn a_few_spheres_and_triangles_are_tested_in_turn_and_hit_as_among_all_slots() {
        let sphere = |x: f64, r: f64| Sphere {
            transform: Transform::new(DVec3::new(x, 0.0, -5.0), glam::DQuat::IDENTITY, DVec3::ONE),
            radius: r,
            material: 0,
        };
        let triangle = WorldTriangle {
            positions: [
                DVec3::new(-3.0, -1.0, -4.0),
                DVec3::new(3.0, -1.0, -4.0),
                DVec3::new(0.0, 2.0, -6.0),
            ],
            normals: [DVec3::Z; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let world = |spheres: Vec<Sphere>| {
            World::with_movers(
                spheres,
                vec![triangle.clone()],
                vec![],
                vec![],
                vec![],
                (0.0, 0.0),
            )
        };
        let few = world(vec![sphere(-1.0, 0.8), sphere(1.2, 0.6)]);
        assert!(few.linear_top);
        let many = world((0..6).map(|i| sphere(i as f64 - 2.5, 0.4)).collect());
        assert!(!many.linear_top);
        // The hits of rays fanned over the scene, against every slot's own test.
        let all: Vec<u32> = (0..few.objects.len() as u32).collect();
        let mut next = crate::test_rng::uniform(17);
        let mut hits = 0;
        for _ in 0..2000 {
            let dir = DVec3::new(next() * 1.6 - 0.8, next() * 1.2 - 0.6, -1.0).normalize();
            let ray = Ray::new(DVec3::ZERO, dir);
            let each = few.intersect_among(&ray, 0.0, f64::INFINITY, &all);
            let linear = few.intersect(&ray, 0.0, f64::INFINITY);
            let key = |h: Option<Hit>| h.map(|h| (h.t, h.object, h.prim));
            assert_eq!(key(linear), key(each));
            assert_eq!(few.occluded(&ray, 5.0), each.is_some_and(|h| h.t < 5.0));
            hits += usize::from(linear.is_some());
        }
        assert!(hits > 200, "the rays meet the objects ({hits} hits)");
    }

    #[test]
    fn eye_rays_in_lanes_hit_what_each_finds_alone_to_the_bit() {
        // Scene triangles of a fan sharing edges and a vertex, a copy of one in a later slot
        // (ties in t go to the lower slot), a degenerate one, one far behind another and a
        // tilted one, seen by rays from one eye in groups of one to four, some groups mixing
        // the sheared frames' axes (the scalar test's fallback).
        let tri = |a: [f64; 3], b: [f64; 3], c: [f64; 3]| WorldTriangle {
            positions: [a, b, c].map(DVec3::from_array),
            normals: [DVec3::Z; 3],
            tex_coords: [DVec2::ZERO; 3],
            materials: [0; 3],
        };
        let mut triangles = Vec::new();
        for k in 0..6 {
            let (a0, a1) = (
                k as f64 * std::f64::consts::FRAC_PI_3,
                (k + 1) as f64 * std::f64::consts::FRAC_PI_3,
            );
            triangles.push(tri(
                [0.0, 0.0, -4.0],
                [2.0 * a0.cos(), 2.0 * a0.sin(), -4.0],
                [2.0 * a1.cos(), 2.0 * a1.sin(), -4.0],
            ));
        }
        triangles.push(triangles[2].clone());
        triangles.push(tri([0.0, 0.0, -3.0], [1.0, 1.0, -3.0], [2.0, 2.0, -3.0]));
        triangles.push(tri([-5.0, -5.0, -9.0], [5.0, -5.0, -9.0], [0.0, 5.0, -9.0]));
        triangles.push(tri([-1.0, -0.5, -2.0], [0.5, -1.0, -3.5], [0.3, 1.2, -2.5]));
        // Spheres among the slots too (one moved only, one turned and stretched), which
        // each ray tests alone.
        let spheres = vec![
            Sphere {
                transform: Transform::new(DVec3::new(0.5, 0.3, -3.5), DQuat::IDENTITY, DVec3::ONE),
                radius: 0.4,
                material: 0,
            },
            Sphere {
                transform: Transform::new(
                    DVec3::new(-0.6, 0.2, -5.0),
                    DQuat::from_rotation_z(0.4),
                    DVec3::new(1.0, 2.0, 1.0),
                ),
                radius: 0.5,
                material: 0,
            },
        ];
        let world = World::with_movers(spheres, triangles, vec![], vec![], vec![], (0.0, 0.0));
        let slots: Vec<u32> = (0..world.objects.len() as u32).collect();
        assert!(world.lanes_among(&slots));
        assert!(slots
            .iter()
            .any(|&s| matches!(world.objects[s as usize], Object::TranslatedSphere(_))));
        assert!(slots
            .iter()
            .any(|&s| matches!(world.objects[s as usize], Object::Sphere(_))));
        let mut next = crate::test_rng::uniform(29);
        let (mut hits, mut mixed) = (0, 0);
        for group in 0..3000 {
            let n = 1 + group % LANES;
            // Mostly down -z; every seventh group also fans out to the side, mixing axes.
            let spread = if group % 7 == 0 { 6.0 } else { 1.2 };
            let rays: Vec<Ray> = (0..n)
                .map(|_| {
                    let d = DVec3::new((next() - 0.5) * spread, (next() - 0.5) * spread, -1.0);
                    Ray::new(DVec3::new(0.0, 0.0, 0.5), d.normalize())
                })
                .collect();
            let axes = |r: &Ray| TriangleRay::new(r).axes();
            mixed += usize::from(rays.iter().any(|r| axes(r) != axes(&rays[0])));
            let refs: Vec<&Ray> = rays.iter().collect();
            let mut lanes = vec![None; n];
            world.intersect_among_lanes(&refs, 0.01, 100.0, &slots, &mut lanes);
            let key = |h: Option<Hit>| {
                h.map(|h| (h.t.to_bits(), h.object, h.prim, h.bary.map(f64::to_bits)))
            };
            for (ray, lane) in rays.iter().zip(&lanes) {
                let alone = world.intersect_among(ray, 0.01, 100.0, &slots);
                assert_eq!(key(*lane), key(alone), "ray {ray:?}");
                hits += usize::from(alone.is_some());
            }
        }
        assert!(
            hits > 2000 && mixed > 50,
            "{hits} hits, {mixed} mixed groups"
        );
    }

    #[test]
    fn the_lane_triangle_test_is_the_scalar_one_in_every_lane() {
        let mut next = crate::test_rng::uniform(31);
        let mut point = || DVec3::new(next() * 4.0 - 2.0, next() * 4.0 - 2.0, next() * 4.0 - 6.0);
        let mut met = 0;
        for _ in 0..5000 {
            let origin = point() * 0.1;
            let target = point();
            let rays: [TriangleRay; LANES] = std::array::from_fn(|l| {
                let jitter = DVec3::new(l as f64 * 0.03, -(l as f64) * 0.02, 0.0);
                TriangleRay::new(&Ray::new(origin, (target + jitter - origin).normalize()))
            });
            if rays.iter().any(|r| r.axes() != rays[0].axes()) {
                continue;
            }
            let frame = LaneFrame::new(&rays);
            let corners = [target, point(), point()];
            let t_max = [100.0, 5.0, 3.0, 100.0];
            let bits = |h: [Option<(f64, [f64; 3])>; LANES]| {
                h.map(|h| h.map(|(t, b)| (t.to_bits(), b.map(f64::to_bits))))
            };
            let lanes = frame.triangle(corners, 0.0, t_max);
            assert_eq!(
                bits(lanes),
                bits(frame.triangle_scalar(corners, 0.0, t_max))
            );
            for (l, ray) in rays.iter().enumerate() {
                let [a, b, c] = corners;
                let alone = intersect_triangle(ray, a, b, c, 0.0, t_max[l]).map(|h| (h.t, h.bary));
                assert_eq!(
                    alone.map(|(t, b)| (t.to_bits(), b.map(f64::to_bits))),
                    lanes[l].map(|(t, b)| (t.to_bits(), b.map(f64::to_bits)))
                );
                met += usize::from(alone.is_some());
            }
        }
        assert!(met > 1000, "{met} hits");
    }

    #[test]
    fn a_shadow_packet_is_blocked_exactly_as_each_ray_alone() {
        let mut next = crate::test_rng::uniform(99);
        let mut worlds = Vec::new();
        for (scale, offset) in [
            (1.0, DVec3::ZERO),
            (1e-3, DVec3::new(0.5, -0.2, 0.1)),
            (1e4, DVec3::new(3e4, 1e3, -2e4)),
        ] {
            // The packet scene's models and spheres, with scene triangles and two small
            // models flattened into the top level added.
            let w = packet_world(scale, offset);
            let mut models = w.models.clone();
            let mut meshes = w.meshes.clone();
            meshes.push(grid_mesh(2, |x, _| 0.2 * x));
            for (at, turn) in [
                (DVec3::new(0.3, -0.2, -2.8), 0.4),
                (DVec3::new(-0.6, 0.1, -3.1), -0.7),
            ] {
                models.push(Model {
                    transform: Transform::new(
                        offset + at * scale,
                        glam::DQuat::from_rotation_y(turn),
                        DVec3::splat(0.4 * scale),
                    ),
                    mesh: 2,
                    material: 0,
                });
            }
            let triangles = (0..6)
                .map(|i| {
                    let c = offset + DVec3::new(i as f64 * 0.3 - 0.8, 0.4, -2.9) * scale;
                    WorldTriangle {
                        positions: [
                            c,
                            c + DVec3::new(0.2, 0.0, 0.05) * scale,
                            c + DVec3::new(0.0, 0.25, -0.05) * scale,
                        ],
                        normals: [DVec3::Z; 3],
                        tex_coords: [DVec2::ZERO; 3],
                        materials: [0; 3],
                    }
                })
                .collect();
            let world = World::with_movers(
                w.spheres.clone(),
                triangles,
                meshes,
                models,
                vec![],
                (0.0, 0.0),
            );
            assert!(world.objects.len() > 10);
            assert_eq!(
                world.model_triangles.len(),
                16,
                "both small models flattened"
            );
            worlds.push((scale, offset, world));
        }
        // And a world of one model, which skips the top level.
        let single = lone_model(
            grid_mesh(40, |x, y| 0.3 * (9.0 * x).sin() * (7.0 * y).cos()),
            DVec3::new(-0.5, -0.5, -2.0),
            -0.2,
        );
        assert_eq!(single.objects.len(), 1);
        worlds.push((1.0, DVec3::ZERO, single));

        for (scale, offset, world) in &worlds {
            let (scale, offset) = (*scale, *offset);
            let camera = test_camera(offset);
            let (w, h) = (48.0, 36.0);
            let (mut blocked, mut open) = (0, 0);
            for k in 0..120 {
                let n = [64, 64, 1, 23, 64, 40, 7, 64][k % 8];
                let (bx, by) = ((k * 8) as f64 % w, ((k * 8) as f64 / w).floor() * 8.0 % h);
                let light =
                    offset + DVec3::new(next() * 2.0 - 1.0, 1.5 + next(), next() - 2.0) * scale;
                let mut rays = Vec::new();
                let mut limits = Vec::new();
                for i in 0..n {
                    let (x, y) = (bx + (i % 8) as f64 + 0.5, by + (i / 8) as f64 + 0.5);
                    let eye = camera.ray(x, y, w, h);
                    let start = world
                        .intersect(&eye, 0.0, f64::INFINITY)
                        .map_or(eye.origin + eye.dir * 3.0 * scale, |hit| eye.at(hit.t));
                    let (ray, t_max) = match k % 4 {
                        // A block's shadow rays to one light, offset off their surfaces as
                        // the shader offsets them (some start on the far side).
                        0 | 1 => {
                            let to = light - start;
                            let d = to.normalize();
                            let o = start + d * 1e-6 * scale;
                            (Ray::new(o, d), to.length())
                        }
                        // Mixed-sign directions from scattered origins, short or unbounded.
                        2 => {
                            let o = offset
                                + DVec3::new(next() - 0.5, next() - 0.5, -2.0 - next() * 2.0)
                                    * scale;
                            let d = DVec3::new(next() - 0.5, next() - 0.5, next() - 0.5);
                            let t = if i % 2 == 0 {
                                f64::INFINITY
                            } else {
                                0.7 * scale
                            };
                            (Ray::new(o, d.normalize()), t)
                        }
                        // One ray outside the f32 tests' range (axis-parallel, or far off).
                        _ => {
                            let to = light - start;
                            let mut d = to.normalize();
                            let mut o = start + d * 1e-6 * scale;
                            if i == n / 2 {
                                if k % 8 == 3 {
                                    d = DVec3::NEG_Z;
                                } else {
                                    o.x = 1e31;
                                }
                            }
                            (Ray::new(o, d), to.length())
                        }
                    };
                    rays.push(ray);
                    limits.push(t_max);
                }
                let mut found = vec![false; n];
                world.occluded_packet(&rays, &limits, &vec![Leaving::NOTHING; n], &mut found);
                for i in 0..n {
                    let alone = world.occluded(&rays[i], limits[i]);
                    assert_eq!(found[i], alone, "scale {scale}, packet {k}, ray {i} of {n}");
                    blocked += alone as usize;
                    open += !alone as usize;
                }
            }
            assert!(
                blocked > 200 && open > 200,
                "scale {scale}: {blocked} blocked, {open} open"
            );
        }
        worlds[0].2.occluded_packet(&[], &[], &[], &mut []);
    }

    #[test]
    fn ties_go_to_the_lower_slot_whatever_the_order() {
        // Rays through the vertices and edges of a flat grid meet several triangles at the
        // same t; the nearest hit must be the lowest slot among them, by brute force.
        let world = World::with_movers(
            vec![],
            vec![],
            vec![grid_mesh(8, |_, _| 0.0)],
            vec![Model {
                transform: Transform::new(DVec3::ZERO, glam::DQuat::IDENTITY, DVec3::ONE),
                mesh: 0,
                material: 0,
            }],
            vec![],
            (0.0, 0.0),
        );
        let mesh = &world.meshes[0];
        let mut ties = 0;
        let mut rays = Vec::new();
        for j in 0..=16 {
            for i in 0..=16 {
                let aim = DVec3::new(i as f64 / 16.0, j as f64 / 16.0, 0.0);
                let origin = DVec3::new(0.5, 0.25, 2.0);
                rays.push(Ray::new(origin, (aim - origin).normalize()));
            }
        }
        for ray in &rays {
            let tri_ray = TriangleRay::new(ray);
            let brute = (0..mesh.slots())
                .filter(|&s| mesh.indices[s] != PADDING_TRIANGLE)
                .filter_map(|s| {
                    let [a, b, c] = mesh.corners(s);
                    intersect_triangle(&tri_ray, a, b, c, 0.0, f64::INFINITY).map(|h| (h.t, s))
                })
                .collect::<Vec<_>>();
            let best = brute
                .iter()
                .copied()
                .min_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
            ties += (brute
                .iter()
                .filter(|h| Some(h.0) == best.map(|b| b.0))
                .count()
                > 1) as usize;
            let hit = world.intersect(ray, 0.0, f64::INFINITY);
            assert_eq!(hit.map(|h| (h.t, h.prim as usize)), best);
        }
        assert!(ties > 20, "{ties} rays with tied hits");
        for packet in rays.chunks(PACKET) {
            for spread in [Spread::Wide, Spread::Pixel] {
                let mut hits = vec![None; packet.len()];
                world.intersect_packet(packet, 0.0, f64::INFINITY, None, spread, &mut hits);
                for (ray, hit) in packet.iter().zip(hits) {
                    assert!(same_hit(hit, world.intersect(ray, 0.0, f64::INFINITY)));
                }
            }
        }
    }

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
