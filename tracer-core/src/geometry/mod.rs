//! Rays, bounds, transforms and the two primitive intersectors (sphere and watertight triangle).

mod bounds;
mod ray;
mod sphere;
mod transform;
mod triangle;

pub use bounds::Aabb;
pub use ray::{Ray, TriangleRay};
pub use sphere::intersect_unit_sphere_scaled;
pub use transform::Transform;
pub use triangle::{
    any_candidate, intersect_triangle, TriangleBlock, TriangleHit, TriangleRayF32, BLOCK,
};
