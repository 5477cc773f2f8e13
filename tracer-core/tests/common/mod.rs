//! Helpers shared by the integration tests.

// Each test binary compiles this module and uses only part of it.
#![allow(dead_code)]

use std::path::PathBuf;

use tracer_core::{RenderSettings, Scene};

/// A file of the course's scenes in `../shared` beside the checkout.
pub fn course(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../../shared/scenes/course")
        .join(file)
}

/// A file of the project's extreme-case suite.
pub fn extreme(file: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes/extreme")
        .join(file)
}

pub fn load(path: PathBuf) -> Scene {
    Scene::load(&path).unwrap_or_else(|e| panic!("{e}"))
}

pub fn settings(width: u32, height: u32, spp: u32) -> RenderSettings {
    RenderSettings {
        width,
        height,
        spp,
        ..RenderSettings::default()
    }
}

/// A minimal valid scene; `{extra}` lands inside the root.
pub fn scene(extra: &str) -> String {
    format!(
        r#"<scene>
    <camera>
        <fov v=".785"/>
        <near_clip v=".01"/>
        <far_clip v="100"/>
        <position x="0" y="0" z="5"/>
        <orientation a="0" x="0" y="1" z="0"/>
    </camera>
    <background_color r="0" g="0" b="0"/>
    <refractive_index v="1"/>
    <material name="m"/>
{extra}
</scene>
"#
    )
}
