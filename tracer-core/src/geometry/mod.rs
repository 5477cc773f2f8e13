//! Rays, bounds, transforms (static and keyed over time) and the two primitive intersectors
//! (sphere and watertight triangle).

mod bounds;
mod motion;
mod ray;
mod sphere;
mod transform;
mod triangle;

pub use bounds::Aabb;
pub use motion::{Keyframe, Motion, TransformDesc};
pub use ray::{Ray, TriangleRay};
pub use sphere::intersect_unit_sphere_scaled;
pub use transform::Transform;
pub use triangle::{
    any_candidate, intersect_triangle, prefetch_blocks, prefetch_leaf, TriangleBlock, TriangleHit,
    TriangleRayF32, BLOCK,
};
