//! Every fatal case of conventions §1.12 (and the inputs §12 says to reject) is an error value
//! located at file:line:column, never a panic.

mod common;

use common::scene;
use tracer_core::scene::SceneDescription;
use tracer_core::{MemoryAssets, Scene};

/// Parses and asserts the error's line, column and message fragment.
fn fails_at(text: &str, line: u32, column: u32, fragment: &str) {
    let err = SceneDescription::parse(text, "t.scene").expect_err("the scene must be rejected");
    assert_eq!(err.file, "t.scene");
    assert_eq!(
        (err.line, err.column),
        (line, column),
        "wrong position for: {err}"
    );
    assert!(
        err.message.contains(fragment),
        "message '{}' lacks '{fragment}'",
        err.message
    );
    assert!(err
        .to_string()
        .starts_with(&format!("t.scene:{line}:{column}: ")));
}

#[test]
fn the_minimal_scene_loads() {
    let desc = SceneDescription::parse(&scene(""), "t.scene").unwrap();
    assert_eq!(desc.materials.len(), 1);
    // Material defaults: white ambient and diffuse, black specular, opaque.
    let m = &desc.materials[0];
    assert_eq!(m.ambient, glam::DVec3::ONE);
    assert_eq!(m.specular, glam::DVec3::ZERO);
    assert_eq!(m.refractive_index, 0.0);
    assert_eq!(
        desc.ambient,
        glam::DVec3::ZERO,
        "ambient light defaults to black"
    );
}

#[test]
fn malformed_xml() {
    fails_at("<scene>\n  <camera>\n</scene>\n", 3, 1, "XML parse error");
}

#[test]
fn missing_required_root_element() {
    let text = scene("").replace("    <refractive_index v=\"1\"/>\n", "");
    fails_at(&text, 1, 1, "<refractive_index> is missing");
}

#[test]
fn missing_required_camera_child() {
    let text = scene("").replace("        <near_clip v=\".01\"/>\n", "");
    fails_at(&text, 2, 5, "<near_clip> is missing");
}

#[test]
fn duplicate_singleton_is_reported_at_the_first_occurrence() {
    let text = scene("").replace(
        "<far_clip v=\"100\"/>",
        "<far_clip v=\"100\"/>\n        <far_clip v=\"50\"/>",
    );
    fails_at(&text, 5, 9, "appears more than once");
    // Even for an optional field.
    let extra = "    <point_light>\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <color r=\"1\" g=\"1\" b=\"1\"/>\n        <radius v=\"1\"/>\n        <radius v=\"2\"/>\n    </point_light>";
    fails_at(&scene(extra), 15, 9, "<radius> appears more than once");
}

#[test]
fn missing_attribute_and_unparsable_number() {
    fails_at(&scene("    <material/>"), 12, 5, "'name' is missing");
    let text = scene("").replace("<fov v=\".785\"/>", "<fov v=\"wide\"/>");
    fails_at(&text, 3, 9, "error parsing");
    // Trailing junk is ignored as sscanf does.
    let text = scene("").replace("<fov v=\".785\"/>", "<fov v=\".785rad\"/>");
    assert!(SceneDescription::parse(&text, "t.scene").is_ok());
}

#[test]
fn non_finite_numbers_are_rejected() {
    let text = scene("").replace("<far_clip v=\"100\"/>", "<far_clip v=\"inf\"/>");
    fails_at(&text, 5, 9, "not a finite number");
    let text = scene("").replace("x=\"0\" y=\"0\" z=\"5\"", "x=\"nan\" y=\"0\" z=\"5\"");
    fails_at(&text, 6, 9, "not a finite number");
}

#[test]
fn unknown_references() {
    let sphere = "    <sphere material=\"glass\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <radius v=\"1\"/>\n    </sphere>";
    fails_at(&scene(sphere), 12, 5, "material \"glass\"");
    let model = "    <model mesh=\"teapot\" material=\"m\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n    </model>";
    fails_at(&scene(model), 12, 5, "mesh \"teapot\"");
    let tri = "    <triangle>\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <vertex name=\"a\"/>\n        <vertex name=\"b\"/>\n        <vertex name=\"c\"/>\n    </triangle>";
    fails_at(&scene(tri), 14, 9, "vertex \"a\"");
}

#[test]
fn duplicate_names_are_reported_at_the_repeat() {
    fails_at(
        &scene("    <material name=\"m\"/>"),
        12,
        5,
        "material \"m\" is defined twice",
    );
    let meshes =
        "    <mesh name=\"x\" filename=\"a.obj\"/>\n    <mesh name=\"x\" filename=\"b.obj\"/>";
    fails_at(&scene(meshes), 13, 5, "mesh \"x\" is defined twice");
    // Names live in separate namespaces: a mesh may share a material's name.
    assert!(
        SceneDescription::parse(&scene("    <mesh name=\"m\" filename=\"a.obj\"/>"), "t").is_ok()
    );
}

fn vertex(name: &str, normal: &str) -> String {
    format!(
        "    <vertex name=\"{name}\" material=\"m\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <normal {normal}/>\n        <tex_coord u=\"0\" v=\"0\"/>\n    </vertex>\n"
    )
}

#[test]
fn wrong_vertex_counts() {
    let n = "x=\"0\" y=\"0\" z=\"1\"";
    let verts = format!(
        "{}{}{}{}",
        vertex("a", n),
        vertex("b", n),
        vertex("c", n),
        vertex("d", n)
    );
    let refs = |k: usize| {
        ["a", "b", "c", "d"][..k]
            .iter()
            .map(|v| format!("        <vertex name=\"{v}\"/>\n"))
            .collect::<String>()
    };
    let tri = |k: usize| {
        format!(
            "{verts}    <triangle>\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n{}    </triangle>",
            refs(k)
        )
    };
    // The vertices take lines 12..31; the triangle opens on line 32.
    fails_at(&scene(&tri(4)), 37, 9, "too many vertices");
    fails_at(&scene(&tri(2)), 32, 5, "too few vertices: 2 of 3");
    fails_at(&scene(&tri(1)), 32, 5, "too few vertices: 1 of 3");
    assert!(SceneDescription::parse(&scene(&tri(3)), "t").is_ok());
}

#[test]
fn zero_normals_and_rotation_axes() {
    fails_at(
        &scene(&vertex("a", "x=\"0\" y=\"0\" z=\"0\"")),
        14,
        9,
        "normal must not be zero",
    );
    let text = scene("").replace(
        "a=\"0\" x=\"0\" y=\"1\" z=\"0\"",
        "a=\"1\" x=\"0\" y=\"0\" z=\"0\"",
    );
    fails_at(&text, 7, 9, "rotation axis must not be zero");
}

#[test]
fn tabs_count_to_the_next_multiple_of_four() {
    let text = scene("\t<material name=\"m\"/>");
    fails_at(&text, 12, 5, "defined twice");
}

#[test]
fn asset_errors_name_the_file_and_position() {
    let textured = "    <material name=\"t\" texture=\"images/missing.png\"/>\n    <sphere material=\"t\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <radius v=\"1\"/>\n    </sphere>";
    let desc = SceneDescription::parse(&scene(textured), "t.scene").unwrap();
    let err = Scene::build(&desc, "t.scene", &MemoryAssets::default()).unwrap_err();
    assert_eq!((err.line, err.column), (12, 5));
    assert!(err.message.contains("images/missing.png"), "{err}");

    let jpeg = textured.replace("missing.png", "photo.jpg");
    let desc = SceneDescription::parse(&scene(&jpeg), "t.scene").unwrap();
    let err = Scene::build(&desc, "t.scene", &MemoryAssets::default()).unwrap_err();
    assert!(err.message.contains("must be a .png"), "{err}");

    // A broken OBJ reports its own line and column.
    let model = "    <mesh name=\"k\" filename=\"k.obj\"/>\n    <model mesh=\"k\" material=\"m\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n    </model>";
    let desc = SceneDescription::parse(&scene(model), "t.scene").unwrap();
    let mut assets = MemoryAssets::default();
    assets.files.insert(
        "k.obj".into(),
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 9\n".to_vec(),
    );
    let err = Scene::build(&desc, "t.scene", &assets).unwrap_err();
    assert_eq!(
        (err.file.as_str(), err.line, err.column),
        ("k.obj", 4, 7),
        "{err}"
    );
}

#[test]
fn only_referenced_assets_are_listed_and_read() {
    let text = scene(
        "    <material name=\"unused\" texture=\"images/unused.png\"/>\n    <mesh name=\"spare\" filename=\"models/spare.obj\"/>",
    );
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    assert!(desc.referenced_assets().is_empty());
    // Nothing is read: an empty asset source suffices.
    assert!(Scene::build(&desc, "t.scene", &MemoryAssets::default()).is_ok());

    let course = std::fs::read_to_string(concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../../shared/scenes/course/stacks.scene"
    ))
    .unwrap();
    let desc = SceneDescription::parse(&course, "stacks.scene").unwrap();
    assert_eq!(
        desc.referenced_assets(),
        vec!["images/cube.png", "images/tiles.png", "models/cube.obj"]
    );
}

#[test]
fn processing_order_lets_references_point_forward() {
    // A vertex names a material defined after it, and a triangle a vertex after it.
    let text = scene(
        "    <triangle>\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <vertex name=\"a\"/>\n        <vertex name=\"b\"/>\n        <vertex name=\"c\"/>\n    </triangle>\n    <vertex name=\"a\" material=\"late\"><position x=\"0\" y=\"0\" z=\"0\"/><normal x=\"0\" y=\"0\" z=\"1\"/><tex_coord u=\"0\" v=\"0\"/></vertex>\n    <vertex name=\"b\" material=\"late\"><position x=\"1\" y=\"0\" z=\"0\"/><normal x=\"0\" y=\"0\" z=\"1\"/><tex_coord u=\"0\" v=\"0\"/></vertex>\n    <vertex name=\"c\" material=\"late\"><position x=\"0\" y=\"1\" z=\"0\"/><normal x=\"0\" y=\"0\" z=\"1\"/><tex_coord u=\"0\" v=\"0\"/></vertex>\n    <material name=\"late\"/>",
    );
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    assert_eq!(desc.triangles.len(), 1);
    assert_eq!(desc.triangles[0].vertices[0].material, 1);
}

/// The minimal scene with `extra` lines added to the camera, after its orientation (line 8).
fn camera_with(extra: &str) -> String {
    scene("").replace(
        "<orientation a=\"0\" x=\"0\" y=\"1\" z=\"0\"/>\n",
        &format!("<orientation a=\"0\" x=\"0\" y=\"1\" z=\"0\"/>\n{extra}\n"),
    )
}

#[test]
fn effect_elements_load_with_their_values() {
    let text = camera_with(
        "        <aperture v=\"0.2\"/>\n        <focus_distance v=\"7\"/>\n        <shutter open=\"0.25\" close=\"0.75\"/>",
    )
    .replace(
        "<material name=\"m\"/>",
        "<material name=\"m\"><refractive_index v=\"1.5\"/><glossiness v=\"0.3\"/><absorption r=\"0.1\" g=\"0.2\" b=\"0.3\"/></material>\n    <environment_map file=\"sky.png\" intensity=\"2\" rotation=\"1\"/>\n    <animation frames=\"24\"/>",
    );
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    let c = &desc.camera;
    assert_eq!(
        (c.aperture, c.focus_distance, c.shutter),
        (0.2, 7.0, [0.25, 0.75])
    );
    assert_eq!(desc.materials[0].glossiness, 0.3);
    assert_eq!(
        desc.materials[0].absorption,
        glam::DVec3::new(0.1, 0.2, 0.3)
    );
    assert_eq!(desc.frames, 24);
    let env = desc.environment.as_ref().unwrap();
    assert_eq!(
        (env.file.as_str(), env.intensity, env.rotation),
        ("sky.png", 2.0, 1.0)
    );
    // The map is a referenced asset (the farm bundles it), although no geometry uses it.
    assert_eq!(desc.referenced_assets(), vec!["sky.png"]);
    // Defaults: a pinhole, an instant shutter, one frame, no map, no gloss or absorption.
    let plain = SceneDescription::parse(&scene(""), "t.scene").unwrap();
    assert_eq!(
        (plain.camera.aperture, plain.camera.shutter),
        (0.0, [0.0; 2])
    );
    assert_eq!((plain.frames, plain.environment.is_none()), (1, true));
    assert_eq!(plain.materials[0].glossiness, 0.0);
    assert!(!plain.has_motion());
}

#[test]
fn bad_camera_lens_and_shutter_values() {
    fails_at(
        &camera_with("        <aperture v=\"-0.1\"/>\n        <focus_distance v=\"5\"/>"),
        8,
        9,
        "aperture radius must not be negative",
    );
    fails_at(
        &camera_with("        <aperture v=\"0.1\"/>"),
        2,
        5,
        "needs a <focus_distance>",
    );
    fails_at(
        &camera_with("        <aperture v=\"0.1\"/>\n        <focus_distance v=\"inf\"/>"),
        9,
        9,
        "not a finite number",
    );
    fails_at(
        &camera_with("        <focus_distance v=\"0\"/>"),
        8,
        9,
        "must be positive",
    );
    fails_at(
        &camera_with("        <shutter open=\"0.5\" close=\"0.2\"/>"),
        8,
        9,
        "open ≤ close",
    );
    fails_at(
        &camera_with("        <shutter open=\"nan\" close=\"1\"/>"),
        8,
        9,
        "not a finite number",
    );
    fails_at(
        &camera_with("        <aperture v=\"0.1\"/>\n        <aperture v=\"0.2\"/>"),
        8,
        9,
        "<aperture> appears more than once",
    );
}

#[test]
fn bad_material_and_root_effect_values() {
    let material = |inner: &str| {
        scene("").replace(
            "<material name=\"m\"/>",
            &format!("<material name=\"m\">\n        {inner}\n    </material>"),
        )
    };
    fails_at(
        &material("<glossiness v=\"-1\"/>"),
        12,
        9,
        "glossiness must not be negative",
    );
    fails_at(
        &material("<glossiness v=\"inf\"/>"),
        12,
        9,
        "not a finite number",
    );
    fails_at(
        &material("<absorption r=\"0.1\" g=\"-0.2\" b=\"0\"/>"),
        12,
        9,
        "must not be negative",
    );
    fails_at(
        &material("<absorption r=\"0.1\" g=\"0.2\"/>"),
        12,
        9,
        "'b' is missing",
    );
    fails_at(
        &scene("    <animation frames=\"0\"/>"),
        12,
        5,
        "whole number from 1",
    );
    fails_at(
        &scene("    <animation frames=\"2.5\"/>"),
        12,
        5,
        "whole number from 1",
    );
    fails_at(&scene("    <environment_map/>"), 12, 5, "'file' is missing");
    fails_at(
        &scene("    <environment_map file=\"sky.png\" intensity=\"-1\"/>"),
        12,
        5,
        "intensity must not be negative",
    );
    fails_at(
        &scene("    <environment_map file=\"sky.png\" rotation=\"nan\"/>"),
        12,
        5,
        "not a finite number",
    );
}

#[test]
fn bad_motion_keyframes_and_references() {
    let ball = |inner: &str| {
        scene(&format!(
            "    <sphere material=\"m\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <radius v=\"1\"/>\n{inner}\n    </sphere>"
        ))
    };
    fails_at(
        &ball("        <keyframe time=\"2\"/>\n        <keyframe time=\"1\"/>"),
        16,
        9,
        "must come after the previous key's time 2",
    );
    fails_at(
        &ball("        <keyframe time=\"0\"/>"),
        15,
        9,
        "must come after",
    );
    fails_at(&ball("        <keyframe/>"), 15, 9, "'time' is missing");
    fails_at(
        &ball("        <keyframe time=\"1\"><scale x=\"0\" y=\"1\" z=\"1\"/></keyframe>"),
        15,
        28,
        "zero scale",
    );
    fails_at(
        &ball("        <keyframe time=\"1\"><position x=\"inf\" y=\"0\" z=\"0\"/></keyframe>"),
        15,
        28,
        "not a finite number",
    );
    fails_at(
        &ball("        <spin a=\"1\" x=\"0\" y=\"0\" z=\"0\"/>"),
        15,
        9,
        "axis must not be zero",
    );
    // A motion reference must name a root <motion>, and excludes inline motion.
    let referenced = scene(
        "    <motion name=\"orbit\"><velocity x=\"1\" y=\"0\" z=\"0\"/></motion>\n    <sphere material=\"m\" motion=\"orbi\">\n        <position x=\"0\" y=\"0\" z=\"0\"/>\n        <radius v=\"1\"/>\n    </sphere>",
    );
    fails_at(&referenced, 13, 5, "motion \"orbi\", which is not defined");
    let fixed = referenced.replace("\"orbi\"", "\"orbit\"");
    let desc = SceneDescription::parse(&fixed, "t.scene").unwrap();
    assert_eq!(desc.spheres[0].motion.velocity, glam::DVec3::X);
    let both = fixed.replace(
        "<radius v=\"1\"/>",
        "<radius v=\"1\"/><velocity x=\"0\" y=\"1\" z=\"0\"/>",
    );
    fails_at(&both, 13, 5, "not both");
    fails_at(
        &scene("    <motion name=\"a\"/>\n    <motion name=\"a\"/>"),
        13,
        5,
        "motion \"a\" is defined twice",
    );
    // The camera takes a referenced path too.
    let camera_path = camera_with("").replace("    <camera>", "    <camera motion=\"dolly\">");
    fails_at(&camera_path, 2, 5, "motion \"dolly\"");
}

#[test]
fn a_missing_environment_map_is_an_asset_error_at_its_element() {
    let text = scene("    <environment_map file=\"maps/sky.png\"/>");
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    let err = Scene::build(&desc, "t.scene", &MemoryAssets::default()).unwrap_err();
    assert_eq!((err.line, err.column), (12, 5), "{err}");
    assert!(
        err.message.contains("environment map") && err.message.contains("maps/sky.png"),
        "{err}"
    );
    let hdr = scene("    <environment_map file=\"sky.hdr\"/>");
    let desc = SceneDescription::parse(&hdr, "t.scene").unwrap();
    let err = Scene::build(&desc, "t.scene", &MemoryAssets::default()).unwrap_err();
    assert!(err.message.contains("must be a .png"), "{err}");
    let mut assets = MemoryAssets::default();
    assets.files.insert("sky.png".into(), b"not a png".to_vec());
    let junk = scene("    <environment_map file=\"sky.png\"/>");
    let desc = SceneDescription::parse(&junk, "t.scene").unwrap();
    let err = Scene::build(&desc, "t.scene", &assets).unwrap_err();
    assert!(err.message.contains("cannot decode"), "{err}");
}
