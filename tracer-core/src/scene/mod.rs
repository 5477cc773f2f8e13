//! Scene loading: XML → [`SceneDescription`] (no asset I/O) → [`Scene`] (assets read, BVHs
//! built).

mod assets;
mod build;
mod desc;
mod error;
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
pub use obj::{parse_obj, smooth_normals, MeshData};
pub use xml::Pos;
