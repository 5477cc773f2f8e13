//! Scene loading: XML → description (no asset I/O) → renderable scene.

mod assets;
mod error;

pub use assets::{AssetSource, FsAssets, MemoryAssets};
pub use error::SceneError;
