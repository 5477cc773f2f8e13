//! The opt-in effects of issue #6, each checked against what it must do: depth of field
//! blurs only off the focal plane, glossiness 0 is the mirror, Beer's law follows exp(−σd),
//! motion that does not move changes nothing, a frame equals the static scene at its time,
//! and the environment map is what escaping rays see. Plus the determinism contract.

mod common;

use std::sync::atomic::AtomicBool;

use tracer_core::scene::{Motion, SceneDescription};
use tracer_core::{Image, MemoryAssets, RenderSettings, Renderer, Scene, TileRect};

use common::settings;

/// A scene with a camera at (0,0,5) looking down −Z; `camera_extra` goes inside `<camera>`.
fn scene(camera_extra: &str, body: &str) -> String {
    format!(
        r#"<scene>
    <camera>
        <fov v="0.6"/>
        <near_clip v="0.01"/>
        <far_clip v="1000"/>
        <position x="0" y="0" z="5"/>
        <orientation a="0" x="0" y="1" z="0"/>
{camera_extra}
    </camera>
    <background_color r="0.8" g="0.8" b="0.8"/>
    <refractive_index v="1"/>
    <ambient_light r="1" g="1" b="1"/>
{body}
</scene>
"#
    )
}

fn build(text: &str, assets: &MemoryAssets) -> Scene {
    let desc = SceneDescription::parse(text, "fx.scene").unwrap_or_else(|e| panic!("{e}"));
    Scene::build(&desc, "fx.scene", assets).unwrap_or_else(|e| panic!("{e}"))
}

fn render(scene: &Scene, s: &RenderSettings) -> Image {
    Renderer::new(scene, s)
        .unwrap_or_else(|e| panic!("{e}"))
        .render_image(&|_, _| {})
}

/// Pixels in columns [x0, x1) whose red lies between the flat objects' 0.1 and the
/// background's 0.8: the width of the soft band around edges. Noise cannot add to it (pixels
/// wholly on an object or on the background are exact), blur widens it.
fn soft_pixels(image: &Image, x0: u32, x1: u32) -> usize {
    (0..image.height)
        .flat_map(|y| (x0..x1).map(move |x| (x, y)))
        .filter(|&(x, y)| (0.15..0.75).contains(&image.pixel(x, y)[0]))
        .count()
}

/// Soft pixels of `image` over those of `reference`, in columns [x0, x1).
fn blur_ratio(image: &Image, reference: &Image, x0: u32, x1: u32) -> f64 {
    soft_pixels(image, x0, x1) as f64 / soft_pixels(reference, x0, x1).max(1) as f64
}

const FLAT: &str = r#"    <material name="flat">
        <ambient r="0.1" g="0.9" b="0.2"/>
        <diffuse r="0" g="0" b="0"/>
    </material>"#;

#[test]
fn depth_of_field_blurs_only_what_is_off_the_focal_plane() {
    // A near ball on the left at distance 5 (in focus), a far one on the right at 25.
    let body = format!(
        "{FLAT}\n    <sphere material=\"flat\"><position x=\"-0.9\" y=\"0\" z=\"0\"/><radius v=\"0.6\"/></sphere>\n    <sphere material=\"flat\"><position x=\"4.5\" y=\"0\" z=\"-20\"/><radius v=\"3\"/></sphere>"
    );
    let pinhole = build(&scene("", &body), &MemoryAssets::default());
    let lens = build(
        &scene(
            "        <aperture v=\"0.25\"/>\n        <focus_distance v=\"5\"/>",
            &body,
        ),
        &MemoryAssets::default(),
    );
    let s = settings(96, 64, 36);
    let (sharp, thin) = (render(&pinhole, &s), render(&lens, &s));
    let near = blur_ratio(&thin, &sharp, 0, 48);
    let far = blur_ratio(&thin, &sharp, 48, 96);
    assert!(
        near < 1.3,
        "the ball on the focal plane must stay sharp: {near}"
    );
    assert!(far > 3.0, "the far ball must blur: {far}");
    // Focusing on the far ball instead swaps the roles.
    let refocused = build(
        &scene(
            "        <aperture v=\"0.25\"/>\n        <focus_distance v=\"25\"/>",
            &body,
        ),
        &MemoryAssets::default(),
    );
    let image = render(&refocused, &s);
    assert!(blur_ratio(&image, &sharp, 0, 48) > 3.0);
    assert!(blur_ratio(&image, &sharp, 48, 96) < 1.3);
}

#[test]
fn a_focus_pull_moves_the_focal_plane_frame_by_frame() {
    let body = format!(
        "{FLAT}\n    <sphere material=\"flat\"><position x=\"-0.9\" y=\"0\" z=\"0\"/><radius v=\"0.6\"/></sphere>\n    <sphere material=\"flat\"><position x=\"4.5\" y=\"0\" z=\"-20\"/><radius v=\"3\"/></sphere>\n    <animation frames=\"9\"/>"
    );
    let lens = |focus: &str| format!("        <aperture v=\"0.25\"/>\n{focus}");
    // Focus on the near ball, hold it to frame 2, pull to the far ball by frame 6.
    let pull = build(
        &scene(
            &lens("        <focus_distance v=\"5\"/>\n        <focus_key time=\"2\" v=\"5\"/>\n        <focus_key time=\"6\" v=\"25\"/>"),
            &body,
        ),
        &MemoryAssets::default(),
    );
    let camera = &pull.description.camera;
    assert_eq!(
        [0.0, 2.0, 4.0, 6.0, 8.0].map(|t| camera.focus_at(t)),
        [5.0, 5.0, 15.0, 25.0, 25.0]
    );
    // Each frame is the still with that focus distance, bit for bit.
    for (frame, focus) in [(0, 5.0), (4, 15.0), (8, 25.0)] {
        let still = build(
            &scene(
                &lens(&format!("        <focus_distance v=\"{focus}\"/>")),
                &body,
            ),
            &MemoryAssets::default(),
        );
        let s = RenderSettings {
            frame,
            ..settings(48, 32, 4)
        };
        assert!(
            render(&pull, &s) == render(&still, &s),
            "frame {frame} must be the still focused at {focus}"
        );
    }
    // A focus key needs a lens, and keys must move forward in time.
    for (extra, needle) in [
        (
            "        <focus_key time=\"1\" v=\"5\"/>".to_string(),
            "needs an <aperture>",
        ),
        (
            lens("        <focus_distance v=\"5\"/>\n        <focus_key time=\"0\" v=\"6\"/>"),
            "must come after",
        ),
        (
            lens("        <focus_distance v=\"5\"/>\n        <focus_key time=\"1\" v=\"-2\"/>"),
            "must be positive",
        ),
    ] {
        let err = SceneDescription::parse(&scene(&extra, &body), "fx.scene").unwrap_err();
        assert!(err.to_string().contains(needle), "{err}");
    }
}

/// A mirror ball in front of a striped wall, with `gloss` as the mirror's extra element.
fn mirror_scene(gloss: &str) -> String {
    scene(
        "",
        &format!(
            r#"    <point_light><position x="3" y="4" z="6"/><color r="0.6" g="0.6" b="0.6"/></point_light>
    <material name="mirror">
        <ambient r="0" g="0" b="0"/>
        <diffuse r="0" g="0" b="0"/>
        <specular r="0.9" g="0.9" b="0.9"/>
        {gloss}
    </material>
    <material name="red"><ambient r="0.6" g="0.05" b="0.05"/><diffuse r="0.4" g="0" b="0"/></material>
    <material name="blue"><ambient r="0.05" g="0.05" b="0.6"/><diffuse r="0" g="0" b="0.4"/></material>
    <sphere material="mirror"><position x="0" y="0" z="0"/><radius v="1.2"/></sphere>
    <sphere material="red"><position x="-1.8" y="0" z="4"/><radius v="0.7"/></sphere>
    <sphere material="blue"><position x="1.8" y="0" z="4"/><radius v="0.7"/></sphere>"#
        ),
    )
}

fn rmse(a: &Image, b: &Image) -> f64 {
    let n = a.pixels.len() as f64;
    let sum: f64 = a
        .pixels
        .iter()
        .zip(&b.pixels)
        .map(|(x, y)| (*x as f64 - *y as f64).powi(2))
        .sum();
    (sum / n).sqrt()
}

#[test]
fn glossiness_zero_is_the_mirror_and_roughness_spreads_the_reflection() {
    let s = settings(64, 48, 8);
    let assets = MemoryAssets::default();
    let mirror = render(&build(&mirror_scene(""), &assets), &s);
    let zero = render(&build(&mirror_scene("<glossiness v=\"0\"/>"), &assets), &s);
    assert_eq!(
        zero.pixels, mirror.pixels,
        "glossiness 0 must be the mirror"
    );
    let slight = render(
        &build(&mirror_scene("<glossiness v=\"0.02\"/>"), &assets),
        &s,
    );
    let rough = render(
        &build(&mirror_scene("<glossiness v=\"0.5\"/>"), &assets),
        &s,
    );
    let (e_slight, e_rough) = (rmse(&slight, &mirror), rmse(&rough, &mirror));
    assert!(e_slight > 0.0, "a glossy surface is not a mirror");
    assert!(
        e_slight < e_rough / 3.0,
        "the lobe widens with roughness: {e_slight} vs {e_rough}"
    );
}

/// One eye ray straight through the centre of a clear (index 1) absorbing ball of radius `r`.
fn through_ball(r: f64, sigma: [f64; 3]) -> [f32; 3] {
    let body = format!(
        r#"    <material name="tinted">
        <refractive_index v="1"/>
        <absorption r="{}" g="{}" b="{}"/>
    </material>
    <sphere material="tinted"><position x="0" y="0" z="0"/><radius v="{r}"/></sphere>"#,
        sigma[0], sigma[1], sigma[2]
    );
    let scene = build(&scene("", &body), &MemoryAssets::default());
    render(&scene, &settings(1, 1, 1)).pixel(0, 0)
}

#[test]
fn beers_law_darkens_as_exp_of_minus_sigma_d() {
    let sigma = [0.1, 0.5, 1.3];
    let thin = through_ball(0.25, sigma);
    let thick = through_ball(1.5, sigma);
    for c in 0..3 {
        // Absolute: the background (0.8) seen through 2r of glass.
        for (value, r) in [(thin[c], 0.25), (thick[c], 1.5)] {
            let expected = 0.8 * (-sigma[c] * 2.0 * r).exp();
            assert!(
                (value as f64 - expected).abs() < 1e-6,
                "channel {c}, r {r}: {value} vs {expected}"
            );
        }
        // The measured ratio against the formula for the extra 2.5 units of thickness.
        let ratio = thick[c] as f64 / thin[c] as f64;
        let formula = (-sigma[c] * 2.0 * (1.5 - 0.25)).exp();
        assert!(
            (ratio - formula).abs() < 1e-5,
            "channel {c}: measured {ratio}, formula {formula}"
        );
    }
    // No absorption: clear glass of index 1 is invisible.
    assert_eq!(through_ball(1.5, [0.0; 3]), [0.8f32; 3]);
}

const BALLS: &str = r#"    <point_light><position x="3" y="4" z="6"/><color r="0.7" g="0.7" b="0.7"/><radius v="0.5"/></point_light>
    <material name="white"><ambient r="0.1" g="0.1" b="0.1"/><diffuse r="0.8" g="0.8" b="0.8"/></material>
    <material name="shiny"><ambient r="0.1" g="0.1" b="0.2"/><diffuse r="0.2" g="0.3" b="0.7"/><specular r="0.3" g="0.3" b="0.3"/></material>"#;

#[test]
fn motion_that_does_not_move_renders_the_static_image() {
    let still = scene(
        "",
        &format!("{BALLS}\n    <sphere material=\"shiny\"><position x=\"0.3\" y=\"0\" z=\"0\"/><radius v=\"1\"/></sphere>\n    <sphere material=\"white\"><position x=\"-1.5\" y=\"-0.5\" z=\"1\"/><radius v=\"0.5\"/></sphere>"),
    );
    // The same balls, one keyed to stay where it is and one spun about its own centre, under
    // an open shutter: the moving-object path, the time samples, and no visible change.
    let keyed = scene(
        "        <shutter open=\"0\" close=\"1\"/>",
        &format!("{BALLS}\n    <sphere material=\"shiny\"><position x=\"0.3\" y=\"0\" z=\"0\"/><radius v=\"1\"/><keyframe time=\"1\"><position x=\"0.3\" y=\"0\" z=\"0\"/></keyframe></sphere>\n    <sphere material=\"white\"><position x=\"-1.5\" y=\"-0.5\" z=\"1\"/><radius v=\"0.5\"/><velocity x=\"0\" y=\"0\" z=\"0\"/></sphere>"),
    );
    let assets = MemoryAssets::default();
    let (a, b) = (build(&still, &assets), build(&keyed, &assets));
    assert_eq!(
        b.world().movers.len(),
        1,
        "the keyed ball takes the moving path"
    );
    let s = settings(64, 48, 4);
    assert_eq!(render(&a, &s).pixels, render(&b, &s).pixels);

    // Moving it does blur: along the motion, edge pixels take in-between values.
    let ball = |extra: &str, shutter: &str| {
        let body = format!("{FLAT}\n    <sphere material=\"flat\"><position x=\"0.3\" y=\"0\" z=\"0\"/><radius v=\"1\"/>{extra}</sphere>");
        render(
            &build(&scene(shutter, &body), &assets),
            &settings(64, 48, 16),
        )
    };
    let open = "        <shutter open=\"0\" close=\"1\"/>";
    let sharp = ball("", open);
    let blurred = ball("<velocity x=\"1.2\" y=\"0\" z=\"0\"/>", open);
    assert!(blur_ratio(&blurred, &sharp, 0, 64) > 3.0);
    // A closed shutter freezes the same motion (at the frame's start).
    assert_eq!(
        ball("<velocity x=\"1.2\" y=\"0\" z=\"0\"/>", "").pixels,
        ball("", "").pixels
    );
}

/// A unit cube as OBJ text.
fn cube_obj() -> Vec<u8> {
    let mut obj = String::new();
    for i in 0..8 {
        let c = |bit: i32| if i & bit != 0 { 1 } else { -1 };
        obj += &format!("v {} {} {}\n", c(1), c(2), c(4));
    }
    for f in [
        [1, 3, 4, 2],
        [5, 6, 8, 7],
        [1, 2, 6, 5],
        [3, 7, 8, 4],
        [1, 5, 7, 3],
        [2, 4, 8, 6],
    ] {
        obj += &format!("f {} {} {} {}\n", f[0], f[1], f[2], f[3]);
    }
    obj.into_bytes()
}

fn animated() -> (String, MemoryAssets) {
    let text = scene(
        r#"        <keyframe time="2.5"><position x="1" y="1" z="6"/><orientation a="0.2" x="0" y="1" z="0"/></keyframe>
        <keyframe time="4"><position x="2" y="0.5" z="5"/></keyframe>"#,
        &format!(
            r#"{BALLS}
    <animation frames="5"/>
    <mesh name="cube" filename="cube.obj"/>
    <sphere material="shiny"><position x="-1" y="0" z="0"/><radius v="0.8"/>
        <keyframe time="2"><position x="0" y="0.5" z="-1"/><scale x="1" y="0.6" z="1"/></keyframe>
        <keyframe time="4"><position x="1" y="0" z="0"/></keyframe>
    </sphere>
    <model mesh="cube" material="white"><position x="1.2" y="-0.4" z="0.5"/><scale x="0.4" y="0.4" z="0.4"/>
        <spin a="0.4" x="0" y="1" z="0.3"/>
        <velocity x="-0.2" y="0.05" z="0"/>
    </model>"#
        ),
    );
    let mut assets = MemoryAssets::default();
    assets.files.insert("cube.obj".into(), cube_obj());
    (text, assets)
}

#[test]
fn a_frame_equals_the_static_scene_at_its_time() {
    let (text, assets) = animated();
    let desc = SceneDescription::parse(&text, "fx.scene").unwrap();
    let scene = Scene::build(&desc, "fx.scene", &assets).unwrap();
    assert_eq!(scene.frame_count(), 5);
    for frame in [0u32, 3] {
        let time = frame as f64;
        // The static scene at that time: camera and objects placed where the keys put them.
        let mut still = desc.clone();
        let (position, orientation) = desc.camera.at(time);
        still.camera.position = position;
        still.camera.orientation = orientation;
        still.camera.motion = Motion::default();
        for s in &mut still.spheres {
            s.transform = s.motion.at(&s.transform, time);
            s.motion = Motion::default();
        }
        for m in &mut still.models {
            m.transform = m.motion.at(&m.transform, time);
            m.motion = Motion::default();
        }
        still.frames = 1;
        let still = Scene::build(&still, "fx.scene", &assets).unwrap();
        assert!(still.world().movers.is_empty());
        let s = settings(48, 36, 2);
        let animated = render(&scene, &RenderSettings { frame, ..s.clone() });
        assert_eq!(
            animated.pixels,
            render(&still, &s).pixels,
            "frame {frame} differs from the static scene at time {time}"
        );
    }
    // Frames differ from one another, and a frame past the end is refused.
    let f1 = render(
        &scene,
        &RenderSettings {
            frame: 1,
            ..settings(48, 36, 2)
        },
    );
    let f2 = render(
        &scene,
        &RenderSettings {
            frame: 2,
            ..settings(48, 36, 2)
        },
    );
    assert_ne!(f1.pixels, f2.pixels);
    let err = Renderer::new(
        &scene,
        &RenderSettings {
            frame: 5,
            ..settings(8, 8, 1)
        },
    )
    .err()
    .unwrap();
    assert!(err.to_string().contains("out of range"), "{err}");
}

#[test]
fn every_effect_keeps_tiles_and_threads_bit_identical() {
    // Depth of field, a moving camera and objects under an open shutter, gloss, absorption.
    let (text, assets) = animated();
    let text = text
        .replace(
            "<orientation a=\"0\" x=\"0\" y=\"1\" z=\"0\"/>\n",
            "<orientation a=\"0\" x=\"0\" y=\"1\" z=\"0\"/>\n        <aperture v=\"0.1\"/><focus_distance v=\"5\"/><shutter open=\"0.2\" close=\"0.9\"/>\n",
        )
        .replace(
            "<specular r=\"0.3\" g=\"0.3\" b=\"0.3\"/>",
            "<specular r=\"0.3\" g=\"0.3\" b=\"0.3\"/><glossiness v=\"0.2\"/>",
        )
        .replace(
            "<material name=\"white\">",
            "<material name=\"glass\"><refractive_index v=\"1.5\"/><specular r=\"1\" g=\"1\" b=\"1\"/><absorption r=\"0.5\" g=\"0.1\" b=\"0.1\"/></material>\n    <sphere material=\"glass\"><position x=\"0.5\" y=\"-0.8\" z=\"1.5\"/><radius v=\"0.5\"/></sphere>\n    <material name=\"white\">",
        );
    let scene = build(&text, &assets);
    assert!(scene.description.camera.aperture > 0.0);
    let s = RenderSettings {
        frame: 2,
        ..settings(40, 30, 3)
    };
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    let whole = pool(1).install(|| render(&scene, &s));
    assert_eq!(whole.pixels, pool(3).install(|| render(&scene, &s)).pixels);
    let renderer = Renderer::new(&scene, &s).unwrap();
    let never = AtomicBool::new(false);
    for rect in TileRect::grid(40, 30, 16) {
        let tile = renderer.render_tile(rect, &never).unwrap();
        assert_eq!(tile.pixels, whole.crop(rect).pixels, "tile {rect:?}");
    }
}

/// A PNG whose left half is red and right half blue, top row green.
fn env_png() -> Vec<u8> {
    let mut image = Image::new(8, 4);
    for y in 0..4 {
        for x in 0..8 {
            let c = if y == 0 {
                [0.0, 1.0, 0.0]
            } else if x < 4 {
                [1.0, 0.0, 0.0]
            } else {
                [0.0, 0.0, 1.0]
            };
            let i = 3 * (y * 8 + x) as usize;
            image.pixels[i..i + 3].copy_from_slice(&c);
        }
    }
    image.to_png()
}

#[test]
fn the_environment_map_is_what_escaping_rays_see() {
    let mut assets = MemoryAssets::default();
    assets.files.insert("sky.png".into(), env_png());
    let look = |orientation: &str, env: &str| {
        let text = scene("", env).replace(
            "<orientation a=\"0\" x=\"0\" y=\"1\" z=\"0\"/>",
            orientation,
        );
        render(&build(&text, &assets), &settings(1, 1, 1)).pixel(0, 0)
    };
    let env = "    <environment_map file=\"sky.png\" intensity=\"0.5\"/>";
    // Looking left of −Z sees the red half, a little right the blue half, up the
    // green top row; intensity scales it.
    let left = "<orientation a=\"1.2\" x=\"0\" y=\"1\" z=\"0\"/>";
    let right = "<orientation a=\"-1.2\" x=\"0\" y=\"1\" z=\"0\"/>";
    let up = "<orientation a=\"1.5\" x=\"1\" y=\"0\" z=\"0\"/>";
    assert_eq!(look(left, env), [0.5, 0.0, 0.0]);
    assert_eq!(look(right, env), [0.0, 0.0, 0.5]);
    assert_eq!(look(up, env), [0.0, 0.5, 0.0]);
    // A half turn of the map swaps the halves; without a map the background colour is seen.
    let turned =
        "    <environment_map file=\"sky.png\" intensity=\"0.5\" rotation=\"3.14159265\"/>";
    assert_eq!(look(left, turned), [0.0, 0.0, 0.5]);
    assert_eq!(look(left, ""), [0.8, 0.8, 0.8]);
    // A mirror ball reflects it: the ball's centre sends the eye ray straight back (+Z, the
    // map's seam between blue and red); its top edge reflects the sky upward (green).
    let ball = format!(
        "{env}\n    <material name=\"mirror\"><ambient r=\"0\" g=\"0\" b=\"0\"/><diffuse r=\"0\" g=\"0\" b=\"0\"/><specular r=\"1\" g=\"1\" b=\"1\"/></material>\n    <sphere material=\"mirror\"><position x=\"0\" y=\"-0.3\" z=\"0\"/><radius v=\"1\"/></sphere>"
    );
    let image = render(&build(&scene("", &ball), &assets), &settings(32, 32, 1));
    let top = image.pixel(16, 11);
    assert!(top[1] > 0.4 && top[0] < 0.1 && top[2] < 0.1, "{top:?}");
    let centre = image.pixel(16, 20);
    assert!(centre[1] < 0.1 && centre[0] + centre[2] > 0.4, "{centre:?}");
}

#[test]
fn a_keyed_scene_triangle_moves_with_its_keys() {
    let tri = |motion: &str| {
        scene(
            "        <shutter open=\"0\" close=\"1\"/>",
            &format!(
                r#"{FLAT}
    <vertex name="a" material="flat"><position x="-1" y="-1" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="b" material="flat"><position x="1" y="-1" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
    <vertex name="c" material="flat"><position x="0" y="1" z="0"/><normal x="0" y="0" z="1"/><tex_coord u="0" v="0"/></vertex>
    <triangle><position x="0" y="0" z="0"/><orientation a="0.3" x="0" y="0" z="1"/>{motion}<vertex name="a"/><vertex name="b"/><vertex name="c"/></triangle>"#
            ),
        )
    };
    let assets = MemoryAssets::default();
    let s = settings(48, 48, 16);
    let still = render(&build(&tri(""), &assets), &s);
    // Keyed in place: the moving path (ray taken into the triangle's space) sees the same
    // triangle; only rounding on its edges may differ.
    let keyed = build(
        &tri("<keyframe time=\"1\"><position x=\"0\" y=\"0\" z=\"0\"/></keyframe>"),
        &assets,
    );
    assert_eq!(keyed.world().movers.len(), 1);
    let same = render(&keyed, &s);
    let differing = still
        .pixels
        .iter()
        .zip(&same.pixels)
        .filter(|(a, b)| (*a - *b).abs() > 1e-6)
        .count();
    assert!(differing <= 6, "{differing} channels differ");
    // Turned by a keyframe while the shutter is open: a wider soft band.
    let turning = render(
        &build(
            &tri(
                "<keyframe time=\"1\"><orientation a=\"1.0\" x=\"0\" y=\"0\" z=\"1\"/></keyframe>",
            ),
            &assets,
        ),
        &s,
    );
    assert!(blur_ratio(&turning, &still, 0, 48) > 3.0);
}
