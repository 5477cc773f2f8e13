//! Tessera's ray tracer: the CMU 15-462 assignment's scenes rendered exactly as its shading
//! model says, plus soft shadows and anti-aliasing. No HTTP here: the farm builds on this API.
//!
//! Data flows one way:
//! - [`scene`]: XML and OBJ parsing into a [`scene::SceneDescription`], then a renderable
//!   [`Scene`] built from only the assets the description references;
//! - [`geometry`] and [`accel`]: rays, transforms, intersectors and BVHs; [`world`] puts
//!   them together for closest-hit and shadow queries;
//! - [`shade`]: the course's shading model, with [`photon`]'s opt-in caustic map; [`camera`]
//!   and [`sampler`] make eye rays and per-sample random numbers;
//! - [`render`]: tiles and whole images in parallel; [`film`]: f32 images and PNG encoding.

pub mod accel;
pub mod bench;
pub mod camera;
pub mod convergence;
pub mod film;
pub mod geometry;
pub mod metrics;
pub mod photon;
pub mod render;
#[cfg(feature = "report")]
pub mod report;
pub mod sampler;
pub mod scene;
pub mod settings;
pub mod shade;
pub mod texture;
pub mod world;

pub use film::Image;
pub use render::Renderer;
pub use scene::{AssetSource, FsAssets, LoadLimits, MemoryAssets, Scene, SceneError};
pub use settings::{
    CameraOverride, CausticsSettings, FrameRange, RenderSettings, TextureFilter, TileRect,
};
