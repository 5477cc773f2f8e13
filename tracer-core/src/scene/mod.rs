//! Scene loading: XML → [`SceneDescription`] (no asset I/O) → [`Scene`] (assets read, BVHs
//! built), optionally under [`LoadLimits`].

mod assets;
mod build;
mod desc;
mod error;
mod limits;
mod obj;
mod xml;

pub use assets::{AssetSource, FsAssets, MemoryAssets};
pub use build::{Scene, SceneStats};
pub use desc::{
    parse_c_double, CameraDesc, CausticsDesc, EnvironmentDesc, Keyframe, LightDesc, MaterialDesc,
    MeshDesc, ModelDesc, Motion, SceneDescription, SphereDesc, TransformDesc, TriangleDesc,
    VertexDesc,
};
pub use error::SceneError;
pub use limits::LoadLimits;
pub use obj::{parse_obj, parse_obj_with_limit, smooth_normals, MeshData};
pub use xml::{Pos, MAX_DEPTH};
