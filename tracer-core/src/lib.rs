//! Tessera's ray tracer: the CMU 15-462 assignment's scenes rendered exactly as its shading
//! model says, plus soft shadows and anti-aliasing. No HTTP here: the farm builds on this API.
//!
//! - [`scene`]: XML and OBJ parsing into a description, then building a renderable [`Scene`]
//!   from only the assets the description references.
//! - [`settings`]: image size, samples, depth, seed, camera override; tile rectangles.
//! - [`film`]: linear f32 images and their 8-bit PNG encoding.

pub mod film;
pub mod scene;
pub mod settings;

pub use film::Image;
pub use scene::{AssetSource, FsAssets, MemoryAssets, SceneError};
pub use settings::{CameraOverride, RenderSettings, TextureFilter, TileRect};
