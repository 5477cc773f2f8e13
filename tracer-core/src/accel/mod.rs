//! Bounding volume hierarchies: one generic binned-SAH BVH, used per mesh over triangles and
//! at the top level over spheres, scene triangles and mesh instances. `build` makes one,
//! `bvh` holds the node layout and the traversals.

mod build;
mod bvh;
mod memory;

pub use build::PADDING;
pub(crate) use bvh::{t_limit, Bounds, RayF32};
pub use bvh::{Bvh, Fetch, Node, PacketBounds, Spread, PACKET};
pub(crate) use memory::with_capacity_huge;
