//! Tessera's ray tracer: the CMU 15-462 assignment's scenes rendered exactly as its shading
//! model says, plus soft shadows and anti-aliasing. No HTTP here: the farm builds on this API.
//!
//! Modules import one way: each names only modules above it in this list.
//! - [`sampler`], [`geometry`] (rays, bounds, transforms, keyed motion, intersectors),
//!   [`texture`] (textures, their filter, the environment map): the leaves;
//! - [`settings`]: the plain data of a render (settings, tiles, frame ranges);
//! - [`film`]: f32 images, tiles assembled into frames, PNG encoding; [`metrics`],
//!   [`convergence`] and (feature `report`) `report` measure images; [`adaptive`]: the running
//!   sums and per-block decisions of progressive renders;
//! - [`accel`]: the BVH; [`world`]: objects under a top-level BVH, closest-hit, any-hit and
//!   the geometry at a hit — material indices only;
//! - [`shade`]: materials, lights, optics, the medium stack, the caustic map's gather and
//!   the Whitted recursion, over a [`shade::Stage`] (what shading sees of a scene);
//! - [`scene`]: XML and OBJ parsing into a [`scene::SceneDescription`], then a renderable
//!   [`Scene`] built from only the assets the description references;
//! - [`photon`]: the opt-in caustic photon map, traced with shade's optics and lights;
//! - [`camera`]: where each pixel sample's eye ray is born;
//! - [`render`]: tiles and whole images in parallel, and the sample ranges of progressive
//!   passes whose decisions [`adaptive`] makes; (feature `bench`) `bench`;
//!   (feature `cli-args`) `cli_args`, the render flags both command lines share;
//! - [`cpu`]: the instruction set the binaries are built for, checked before `main`.

pub mod accel;
pub mod adaptive;
pub mod alloc;
#[cfg(feature = "bench")]
pub mod bench;
pub mod camera;
#[cfg(feature = "cli-args")]
pub mod cli_args;
pub mod convergence;
pub mod cpu;
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
#[cfg(test)]
mod test_rng;
pub mod texture;
pub mod world;

pub use film::{Image, ImageFormat};
pub use render::{RenderError, Renderer};
pub use sampler::SampleOrder;
pub use scene::{AssetSource, FsAssets, LoadLimits, MemoryAssets, Scene, SceneError};
pub use settings::{
    CameraOverride, CausticsSettings, FrameRange, RenderSettings, SettingsError, TextureFilter,
    TileRect,
};
