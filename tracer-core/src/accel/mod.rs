//! Bounding volume hierarchies: one generic binned-SAH BVH, used per mesh over triangles and
//! at the top level over spheres, scene triangles and mesh instances.

mod bvh;

pub use bvh::{Bvh, Node, PADDING};
