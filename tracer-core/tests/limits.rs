//! Bounded loading (issue #10): nesting depth, byte-order marks, a total position mapping, and
//! the [`LoadLimits`] budgets on texture pixels and primitives.

mod common;

use std::io::Cursor;

use common::scene;

use tracer_core::scene::{FsAssets, SceneDescription, MAX_DEPTH};
use tracer_core::{Image, LoadLimits, MemoryAssets, RenderSettings, Renderer, Scene};

fn limits(max_texture_pixels: u64, max_primitives: u64) -> LoadLimits {
    LoadLimits {
        max_texture_pixels,
        max_primitives,
    }
}

/// The error of a load that must fail (a loaded scene is too big to print).
fn refused(result: Result<Scene, tracer_core::SceneError>) -> tracer_core::SceneError {
    match result {
        Ok(_) => panic!("the scene loaded"),
        Err(e) => e,
    }
}

fn render(scene: &Scene) -> Image {
    let settings = RenderSettings {
        width: 20,
        height: 15,
        spp: 1,
        ..RenderSettings::default()
    };
    Renderer::new(scene, &settings)
        .unwrap()
        .render_image(&|_, _| {})
}

#[test]
fn fifty_thousand_nested_elements_are_refused_without_deep_recursion() {
    let depth = 50_000;
    let text = "<a>".repeat(depth) + &"</a>".repeat(depth);
    // A small stack proves that neither parsing nor dropping the partial tree recurses per level.
    let err = std::thread::Builder::new()
        .stack_size(256 * 1024)
        .spawn(move || SceneDescription::parse(&text, "deep.scene").unwrap_err())
        .unwrap()
        .join()
        .expect("no stack overflow");
    // The element one level too deep opens at column 3·MAX_DEPTH + 1.
    assert_eq!(
        (err.file.as_str(), err.line, err.column),
        ("deep.scene", 1, 3 * MAX_DEPTH as u32 + 1),
        "{err}"
    );
    assert!(err.message.contains("at most 32"), "{err}");
    assert_eq!(err.limit(), None);
}

#[test]
fn a_byte_order_mark_before_a_bare_bracket_is_a_clean_error() {
    let bytes = [0xEF, 0xBB, 0xBF, 0x0A, 0x3C];
    let text = std::str::from_utf8(&bytes).unwrap();
    let err = SceneDescription::parse(text, "bom.scene").unwrap_err();
    assert!(err.to_string().starts_with("bom.scene:"), "{err}");
    assert!(err.line >= 1 && err.column >= 1, "{err}");
}

#[test]
fn errors_inside_multibyte_text_have_positions() {
    // Every prefix of a scene full of multi-byte characters fails or loads; none panics.
    let text =
        scene("    <!-- é€😀 --> <point_light><position x=\"1\" y=\"2\" z=\"€\"/></point_light>");
    for end in (0..text.len()).filter(|&i| text.is_char_boundary(i)) {
        let _ = SceneDescription::parse(&text[..end], "t.scene");
    }
    let err = SceneDescription::parse(&text, "t.scene").unwrap_err();
    // Columns count characters: 4 spaces, 12 for the comment, a space, 13 for <point_light>.
    assert_eq!((err.line, err.column), (12, 31), "{err}");
}

#[test]
fn a_course_scene_with_a_byte_order_mark_loads_and_renders_identically() {
    for name in ["cube.scene", "stacks.scene", "toy.scene"] {
        let path = common::course(name);
        let text = std::fs::read_to_string(&path).unwrap();
        let file = path.display().to_string();
        let plain = SceneDescription::parse(&text, &file).unwrap();
        let marked = SceneDescription::parse(&format!("\u{FEFF}{text}"), &file).unwrap();
        assert_eq!(plain, marked, "{name}: positions count from after the mark");
        let assets = FsAssets::for_scene(&path);
        let plain = Scene::build(&plain, &file, &assets).unwrap();
        let marked = Scene::build(&marked, &file, &assets).unwrap();
        assert_eq!(render(&plain).to_png(), render(&marked).to_png(), "{name}");
    }
}

#[test]
fn default_limits_load_every_course_scene() {
    for entry in std::fs::read_dir(common::course("")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "scene") {
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap();
        let file = path.display().to_string();
        let desc = SceneDescription::parse_with_limits(&text, &file, &LoadLimits::default())
            .unwrap_or_else(|e| panic!("{e}"));
        assert_eq!(desc, SceneDescription::parse(&text, &file).unwrap());
        Scene::build_with_limits(
            &desc,
            &file,
            &FsAssets::for_scene(&path),
            &LoadLimits::default(),
        )
        .unwrap_or_else(|e| panic!("{e}"));
    }
}

fn spheres(n: usize) -> String {
    (0..n)
        .map(|i| {
            format!("    <sphere material=\"m\"><position x=\"{i}\" y=\"0\" z=\"0\"/><radius v=\"1\"/></sphere>\n")
        })
        .collect()
}

const TRIANGLE: &str = r#"    <vertex name="a" material="m"><position x="0" y="0" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="b" material="m"><position x="1" y="0" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="c" material="m"><position x="0" y="1" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
"#;

fn triangles(n: usize) -> String {
    let one = r#"    <triangle><position x="0" y="0" z="0"/><vertex name="a"/><vertex name="b"/><vertex name="c"/></triangle>
"#;
    TRIANGLE.to_string() + &one.repeat(n)
}

#[test]
fn spheres_and_triangles_over_the_limit_are_refused_where_they_cross_it() {
    // Spheres start on line 12; the 1001st is the one that crosses 1000.
    let text = scene(&spheres(5_000));
    let err = SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 1_000)).unwrap_err();
    assert_eq!((err.line, err.column), (12 + 1_000, 5), "{err}");
    assert_eq!(err.limit(), Some("max_primitives"));
    assert!(err.message.contains("1001 is over") && err.message.contains("max_primitives = 1000"));
    assert!(SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 5_000)).is_ok());

    let text = scene(&(spheres(2) + &triangles(3)));
    let err = SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 4)).unwrap_err();
    assert_eq!(
        (err.line, err.column, err.limit()),
        (12 + 2 + 3 + 2, 5, Some("max_primitives"))
    );
    let desc = SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 5)).unwrap();
    assert_eq!(desc.scene_primitives(), 5);

    // A description parsed without limits is still checked when it is built.
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    let assets = MemoryAssets::default();
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &limits(0, 4),
    ));
    assert_eq!(err.limit(), Some("max_primitives"), "{err}");
    assert!(err.message.contains("5 is over"), "{err}");
    assert!(Scene::build_with_limits(&desc, "t.scene", &assets, &limits(0, 5)).is_ok());
}

#[test]
fn mesh_triangles_count_once_per_mesh_file_and_models_once_each() {
    let quad = "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1 2 3 4\n";
    let mut assets = MemoryAssets::default();
    assets
        .files
        .insert("quad.obj".into(), quad.as_bytes().to_vec());
    // Two <mesh> elements naming the same file: it is read and built once.
    let model = r#"    <mesh name="q" filename="quad.obj"/>
    <mesh name="again" filename="quad.obj"/>
    <model mesh="q" material="m"><position x="0" y="0" z="0"/></model>
    <model mesh="q" material="m"><position x="3" y="0" z="0"/></model>
    <model mesh="again" material="m"><position x="6" y="0" z="0"/></model>
"#;
    let text = scene(&(spheres(2) + model));
    // 2 spheres + 3 models, counted as the XML is read.
    assert!(SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 4)).is_err());
    let desc = SceneDescription::parse_with_limits(&text, "t.scene", &limits(0, 5)).unwrap();
    assert_eq!(desc.scene_primitives(), 5);
    // ... + 2 triangles of quad.obj, however many instances and <mesh> elements: 7.
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &limits(0, 6),
    ));
    assert_eq!(err.limit(), Some("max_primitives"), "{err}");
    assert_eq!(
        (err.file.as_str(), err.line, err.column),
        ("quad.obj", 5, 1),
        "{err}"
    );
    assert!(
        err.message.contains("7 is over") && err.message.contains("= 6"),
        "{err}"
    );
    let scene = Scene::build_with_limits(&desc, "t.scene", &assets, &limits(0, 7)).unwrap();
    assert_eq!((scene.stats.triangles, scene.stats.meshes), (2, 1));
}

/// An 8-bit grey PNG of `width` × `height`.
fn png(width: u32, height: u32) -> Vec<u8> {
    let mut out = Vec::new();
    image::GrayImage::new(width, height)
        .write_to(&mut Cursor::new(&mut out), image::ImageFormat::Png)
        .unwrap();
    out
}

/// A valid grey PNG of `width` × `height` zeros, compressed by hand (each run of 258 zeros is
/// one 13-bit back-reference) so that the test never holds the decoded pixels: 13000 × 13000
/// is about 1 MB of file for 169 MB of pixels.
fn zeros_png(width: u32, height: u32) -> Vec<u8> {
    let mut out = png(1, 1);
    // Signature (8), IHDR length and type (8), then width and height; the CRC follows the
    // 13 data bytes.
    out[16..20].copy_from_slice(&width.to_be_bytes());
    out[20..24].copy_from_slice(&height.to_be_bytes());
    let crc = crc32(&out[12..29]);
    out[29..33].copy_from_slice(&crc.to_be_bytes());
    out.truncate(33);
    let raw = u64::from(height) * (u64::from(width) + 1); // a filter byte per row
    let mut bits = BitWriter::default();
    bits.write(0b011, 3); // final block, fixed Huffman codes
    let literal_zero = 0b0011_0000;
    bits.code(literal_zero, 8);
    for _ in 0..(raw - 1) / 258 {
        bits.code(0b1100_0101, 8); // length 258
        bits.code(0, 5); // distance 1
    }
    for _ in 0..(raw - 1) % 258 {
        bits.code(literal_zero, 8);
    }
    bits.code(0, 7); // end of block
    let mut data = vec![0x78, 0x01];
    data.extend_from_slice(&bits.finish());
    let adler = ((raw % 65_521) as u32) << 16 | 1;
    data.extend_from_slice(&adler.to_be_bytes());
    for (kind, data) in [(b"IDAT", &data[..]), (b"IEND", &[][..])] {
        let chunk = [&kind[..], data].concat();
        out.extend_from_slice(&(data.len() as u32).to_be_bytes());
        out.extend_from_slice(&chunk);
        out.extend_from_slice(&crc32(&chunk).to_be_bytes());
    }
    out
}

/// Deflate's bit order: values least significant bit first, Huffman codes most significant first.
#[derive(Default)]
struct BitWriter {
    bytes: Vec<u8>,
    used: u32,
}

impl BitWriter {
    fn write(&mut self, value: u32, count: u32) {
        for i in 0..count {
            let bit = self.used % 8;
            if bit == 0 {
                self.bytes.push(0);
            }
            *self.bytes.last_mut().unwrap() |= (((value >> i) & 1) as u8) << bit;
            self.used += 1;
        }
    }

    fn code(&mut self, code: u32, length: u32) {
        self.write(code.reverse_bits() >> (32 - length), length);
    }

    fn finish(self) -> Vec<u8> {
        self.bytes
    }
}

fn crc32(bytes: &[u8]) -> u32 {
    let mut crc = !0u32;
    for &b in bytes {
        crc ^= b as u32;
        for _ in 0..8 {
            crc = if crc & 1 != 0 {
                (crc >> 1) ^ 0xEDB8_8320
            } else {
                crc >> 1
            };
        }
    }
    !crc
}

fn textured(materials: &[(&str, &str)]) -> String {
    let mut extra = String::new();
    for (name, texture) in materials {
        extra += &format!("    <material name=\"{name}\" texture=\"{texture}\"/>\n");
        extra += &format!("    <sphere material=\"{name}\"><position x=\"0\" y=\"0\" z=\"0\"/><radius v=\"1\"/></sphere>\n");
    }
    scene(&extra)
}

#[test]
fn a_texture_over_the_pixel_budget_is_refused_from_its_header() {
    let mut assets = MemoryAssets::default();
    assets
        .files
        .insert("huge.png".into(), zeros_png(13_000, 13_000));
    let text = textured(&[("h", "huge.png")]);
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &limits(16_000_000, u64::MAX),
    ));
    assert_eq!(err.limit(), Some("max_texture_pixels"), "{err}");
    assert_eq!((err.line, err.column), (12, 5), "at the material: {err}");
    assert!(err.message.contains("169000000 is over"), "{err}");
    assert!(
        err.message.contains("max_texture_pixels = 16000000"),
        "{err}"
    );
    let just_under = limits(169_000_000 - 1, u64::MAX);
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &just_under,
    ));
    assert!(
        err.to_string().contains("max_texture_pixels = 168999999"),
        "{err}"
    );
    assert!(zeros_png(13_000, 13_000).len() < 1_100_000, "a small file");
}

#[test]
fn the_hand_compressed_png_decodes() {
    let texture = tracer_core::texture::Texture::decode_png(&zeros_png(300, 7)).unwrap();
    assert_eq!(texture.dimensions(), (300, 7));
}

#[test]
fn texture_pixels_add_up_over_distinct_textures_and_the_environment() {
    let mut assets = MemoryAssets::default();
    assets.files.insert("a.png".into(), png(4, 4));
    assets.files.insert("b.png".into(), png(2, 3));
    let text = textured(&[("a", "a.png"), ("again", "a.png"), ("b", "b.png")]);
    let desc = SceneDescription::parse(&text, "t.scene").unwrap();
    // a.png counts once: 16 + 6.
    assert!(Scene::build_with_limits(&desc, "t.scene", &assets, &limits(22, u64::MAX)).is_ok());
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &limits(21, u64::MAX),
    ));
    assert_eq!(
        (err.line, err.limit()),
        (16, Some("max_texture_pixels")),
        "at material b: {err}"
    );
    assert!(
        err.message.contains("22 is over") && err.message.contains("'b.png' (2×3)"),
        "{err}"
    );

    let sky = text.replace("</scene>", "<environment_map file=\"a.png\"/>\n</scene>");
    let desc = SceneDescription::parse(&sky, "t.scene").unwrap();
    let err = refused(Scene::build_with_limits(
        &desc,
        "t.scene",
        &assets,
        &limits(22, u64::MAX),
    ));
    assert!(
        err.message.contains("environment map") && err.message.contains("38 is over"),
        "{err}"
    );
    assert!(Scene::build_with_limits(&desc, "t.scene", &assets, &limits(38, u64::MAX)).is_ok());
}

#[test]
fn the_limit_names_are_the_fields() {
    let defaults = LoadLimits::default();
    assert_eq!(
        (defaults.max_texture_pixels, defaults.max_primitives),
        (256_000_000, 20_000_000)
    );
    assert_eq!(LoadLimits::UNLIMITED.max_elements(), u64::MAX);
    let plain = SceneDescription::parse("<scene>", "t.scene").unwrap_err();
    assert_eq!(plain.limit(), None);
}

#[test]
fn named_motions_copied_into_many_elements_count_against_the_element_bound() {
    let keys: String = (1..=1_000)
        .map(|t| format!("<keyframe time=\"{t}\"/>"))
        .collect();
    let users = |n: usize| -> String {
        (0..n)
            .map(|_| "    <sphere material=\"m\" motion=\"w\"><position x=\"0\" y=\"0\" z=\"0\"/><radius v=\"1\"/></sphere>\n")
            .collect()
    };
    let budget = limits(u64::MAX, 100);
    // 100 primitives allow 100·64 + 65,536 = 71,936 elements: 72 users copy 72,000 keys.
    let text = scene(&format!(
        "    <motion name=\"w\">{keys}</motion>\n{}",
        users(100)
    ));
    let err = SceneDescription::parse_with_limits(&text, "t.scene", &budget).unwrap_err();
    assert_eq!((err.line, err.column), (13 + 71, 5), "{err}");
    assert_eq!(err.limit(), Some("max_primitives"), "{err}");
    assert!(err.message.contains("72000 is over 71936"), "{err}");
    assert!(err.message.contains("max_primitives = 100"), "{err}");
    let text = scene(&format!(
        "    <motion name=\"w\">{keys}</motion>\n{}",
        users(71)
    ));
    let desc = SceneDescription::parse_with_limits(&text, "t.scene", &budget).unwrap();
    assert_eq!(desc.spheres[70].motion.keys.len(), 1_000);
}
