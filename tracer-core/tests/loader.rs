//! Every fatal case of conventions §1.12 (and the inputs §12 says to reject) is an error value
//! located at file:line:column, never a panic.

use tracer_core::scene::SceneDescription;
use tracer_core::{MemoryAssets, Scene};

/// A minimal valid scene; `{extra}` lands inside the root and `{camera_extra}` in the camera.
fn scene(extra: &str) -> String {
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
