//! What each fuzz target does with one input. Shared by the cargo-fuzz targets in `fuzz/` and,
//! through `#[path]`, by tracer-core's stable regression tests: an input that once crashed a
//! target is replayed by the same code. Each function panics exactly when the input finds a bug.

use tracer_core::scene::{parse_obj, LoadLimits, SceneDescription};
use tracer_core::{MemoryAssets, RenderSettings, Renderer, Scene};

/// Budgets that keep any one input to a few hundred MB: what the farm does with its defaults,
/// scaled down to the fuzzer's memory limit.
pub const LIMITS: LoadLimits = LoadLimits {
    max_texture_pixels: 1 << 22,
    max_primitives: 1 << 16,
};

/// The target named `target` (`scene_xml`, `obj` or `obj_render`) on `data`.
pub fn run(target: &str, data: &[u8]) {
    match target {
        "scene_xml" => scene_xml(data),
        "obj" => obj(data),
        "obj_render" => obj_render(data),
        other => panic!("no fuzz target called {other}"),
    }
}

/// The scene loader on a scene and its assets: the input is the scene text up to the first NUL
/// byte, then assets, each a little-endian u32 length and that many bytes, given in the order
/// [`SceneDescription::referenced_assets`] lists the paths. Parse and build, under [`LIMITS`].
pub fn scene_xml(data: &[u8]) {
    let (text, mut rest) = match data.iter().position(|&b| b == 0) {
        Some(nul) => (&data[..nul], &data[nul + 1..]),
        None => (data, &[][..]),
    };
    let text = String::from_utf8_lossy(text);
    let Ok(desc) = SceneDescription::parse_with_limits(&text, "fuzz.scene", &LIMITS) else {
        return;
    };
    let mut assets = MemoryAssets::default();
    for path in desc.referenced_assets() {
        let Some((length, tail)) = rest.split_first_chunk::<4>() else {
            break;
        };
        let length = (u32::from_le_bytes(*length) as usize).min(tail.len());
        assets.files.insert(path, tail[..length].to_vec());
        rest = &tail[length..];
    }
    if let Ok(scene) = Scene::build_with_limits(&desc, "fuzz.scene", &assets, &LIMITS) {
        assert!(scene.stats.triangles as u64 <= LIMITS.max_primitives);
    }
}

/// The OBJ parser alone; a mesh it accepts must be internally consistent.
pub fn obj(data: &[u8]) {
    let text = String::from_utf8_lossy(data);
    let Ok(mesh) = parse_obj(&text, "fuzz.obj") else {
        return;
    };
    let n = mesh.positions.len();
    assert_eq!(mesh.normals.len(), n);
    assert_eq!(mesh.tex_coords.len(), n);
    assert!(!mesh.triangles.is_empty());
    assert!(mesh.triangles.iter().flatten().all(|&i| (i as usize) < n));
    assert!(mesh.positions.iter().all(|p| p.is_finite()));
    assert!(mesh.normals.iter().all(|v| v.is_finite()));
}

/// A fixed scene that looks at one instance of the fuzzed OBJ, lit by a point light.
const OBJ_SCENE: &str = r#"<scene>
    <camera>
        <fov v=".785"/>
        <near_clip v=".01"/>
        <far_clip v="100"/>
        <position x="0" y="0" z="4"/>
        <orientation a="0" x="0" y="1" z="0"/>
    </camera>
    <background_color r=".1" g=".2" b=".3"/>
    <refractive_index v="1"/>
    <ambient_light r=".2" g=".2" b=".2"/>
    <point_light>
        <position x="2" y="3" z="4"/>
        <color r="1" g="1" b="1"/>
    </point_light>
    <material name="glass">
        <diffuse r=".4" g=".5" b=".6"/>
        <specular r=".3" g=".3" b=".3"/>
        <refractive_index v="1.5"/>
    </material>
    <mesh name="m" filename="m.obj"/>
    <model material="glass" mesh="m">
        <position x="0" y="0" z="0"/>
        <orientation a=".5" x="1" y="1" z="0"/>
    </model>
</scene>
"#;

/// The fuzzed OBJ as a refracting mesh in [`OBJ_SCENE`], rendered at 8×6 and 1 sample per
/// pixel: every pixel must be finite.
pub fn obj_render(data: &[u8]) {
    let desc = SceneDescription::parse(OBJ_SCENE, "obj_render.scene").expect("the fixed scene");
    let mut assets = MemoryAssets::default();
    assets.files.insert("m.obj".into(), data.to_vec());
    let Ok(scene) = Scene::build_with_limits(&desc, "obj_render.scene", &assets, &LIMITS) else {
        return;
    };
    let settings = RenderSettings {
        width: 8,
        height: 6,
        spp: 1,
        ..RenderSettings::default()
    };
    let renderer = Renderer::new(&scene, &settings).expect("valid settings");
    let image = renderer.render_image(&|_, _| {});
    for y in 0..settings.height {
        for x in 0..settings.width {
            let pixel = image.pixel(x, y);
            assert!(
                pixel.iter().all(|c| c.is_finite()),
                "pixel ({x}, {y}) is {pixel:?}"
            );
        }
    }
}
