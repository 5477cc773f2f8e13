//! Caustics by photon mapping (issue #6): they light the floor under a glass ball, keep the
//! direct term's units, stay within the light's power, keep the determinism contract, and
//! change nothing when off.

use std::f64::consts::TAU;
use std::sync::atomic::AtomicBool;

use glam::DVec3;
use tracer_core::photon::{CausticMap, CausticsParams};
use tracer_core::scene::SceneDescription;
use tracer_core::{
    CausticsSettings, Image, MemoryAssets, RenderSettings, Renderer, Scene, TextureFilter, TileRect,
};

/// A glass ball of radius 0.5 at (0, 1, 0) over a white floor at y = 0, lit from `light` with
/// the given attenuation; the camera looks straight down through the ball's centre.
fn scene_text(light: DVec3, attenuation: [f64; 3], ior: f64, extra: &str) -> String {
    format!(
        r#"<scene>
  <camera>
    <fov v="0.6"/><near_clip v="0.01"/><far_clip v="100"/>
    <position x="0" y="6" z="0"/><orientation a="-1.5707963267948966" x="1" y="0" z="0"/>
  </camera>
  <background_color r="0" g="0" b="0"/>
  <refractive_index v="1"/>
  <ambient_light r="0.1" g="0.1" b="0.1"/>
  <point_light>
    <attenuation_constant v="{}"/><attenuation_linear v="{}"/><attenuation_quadratic v="{}"/>
    <position x="{}" y="{}" z="{}"/><color r="0.8" g="0.8" b="0.8"/>
  </point_light>
  {extra}
  <material name="white"><diffuse r="1" g="1" b="1"/><ambient r="1" g="1" b="1"/></material>
  <material name="glass"><refractive_index v="{ior}"/><specular r="1" g="1" b="1"/></material>
  <vertex name="a" material="white"><position x="-20" y="0" z="-20"/><normal x="0" y="1" z="0"/><tex_coord u="0" v="0"/></vertex>
  <vertex name="b" material="white"><position x="-20" y="0" z="20"/><normal x="0" y="1" z="0"/><tex_coord u="0" v="1"/></vertex>
  <vertex name="c" material="white"><position x="20" y="0" z="20"/><normal x="0" y="1" z="0"/><tex_coord u="1" v="1"/></vertex>
  <vertex name="d" material="white"><position x="20" y="0" z="-20"/><normal x="0" y="1" z="0"/><tex_coord u="1" v="0"/></vertex>
  <triangle><position x="0" y="0" z="0"/><vertex name="a"/><vertex name="b"/><vertex name="c"/></triangle>
  <triangle><position x="0" y="0" z="0"/><vertex name="c"/><vertex name="d"/><vertex name="a"/></triangle>
  <sphere material="glass"><position x="0" y="1" z="0"/><radius v="0.5"/></sphere>
</scene>"#,
        attenuation[0], attenuation[1], attenuation[2], light.x, light.y, light.z
    )
}

const OVERHEAD: DVec3 = DVec3::new(0.0, 4.0, 0.0);
const NO_FALLOFF: [f64; 3] = [1.0, 0.0, 0.0];

fn parse(text: &str) -> Result<Scene, tracer_core::SceneError> {
    let desc = SceneDescription::parse(text, "caustics.scene")?;
    Scene::build(&desc, "caustics.scene", &MemoryAssets::default())
}

fn build(text: &str) -> Scene {
    parse(text).unwrap_or_else(|e| panic!("{e}"))
}

fn small(caustics: CausticsSettings) -> RenderSettings {
    RenderSettings {
        width: 48,
        height: 48,
        spp: 2,
        caustics,
        ..RenderSettings::default()
    }
}

fn render(scene: &Scene, s: &RenderSettings) -> Image {
    Renderer::new(scene, s).unwrap().render_image(&|_, _| {})
}

/// Mean of the red channel over the centre `size`×`size` pixels.
fn centre_mean(image: &Image, size: u32) -> f64 {
    let (x0, y0) = ((image.width - size) / 2, (image.height - size) / 2);
    let mut sum = 0.0;
    for y in y0..y0 + size {
        for x in x0..x0 + size {
            sum += image.pixels[3 * (y * image.width + x) as usize] as f64;
        }
    }
    sum / (size * size) as f64
}

const ON: &str = r#"<caustics photons="40000" radius="0.08"/>"#;

#[test]
fn caustics_brighten_the_floor_under_a_glass_ball() {
    let plain = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ""));
    let with = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ON));
    let before = render(&plain, &small(CausticsSettings::default()));
    let after = render(&with, &small(CausticsSettings::default()));
    // Seen through the ball's centre, the floor sits in the ball's full shadow: ambient only
    // (0.1, dimmed by the glass) without caustics, the focused light with them.
    let (dark, lit) = (centre_mean(&before, 4), centre_mean(&after, 4));
    assert!(dark < 0.1, "shadowed floor {dark}");
    assert!(lit > 0.5, "caustic {lit} against {dark} without");
    // The ball focuses: the caustic outshines the direct light beside the shadow.
    let beside = before.pixels[0] as f64;
    assert!(lit > 1.5 * beside, "caustic {lit}, direct light {beside}");
    // Away from the ball the floor is lit directly and the caustic adds nothing.
    assert_eq!(before.pixels[..3], after.pixels[..3]);
}

#[test]
fn caustics_off_change_nothing() {
    let plain = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ""));
    let with = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ON));
    let off = CausticsSettings {
        enabled: Some(false),
        ..Default::default()
    };
    let reference = render(&plain, &small(CausticsSettings::default()));
    let renderer = Renderer::new(&with, &small(off)).unwrap();
    assert!(renderer.caustics().is_none());
    assert_eq!(renderer.render_image(&|_, _| {}).pixels, reference.pixels);
    // A scene that does not ask builds no map.
    assert!(Renderer::new(&plain, &small(CausticsSettings::default()))
        .unwrap()
        .caustics()
        .is_none());
    // Nor does one with nothing that can focus light.
    let matte = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ON).replace(
        r#"<sphere material="glass">"#,
        r#"<sphere material="white">"#,
    ));
    assert!(Renderer::new(&matte, &small(CausticsSettings::default()))
        .unwrap()
        .caustics()
        .is_none());
}

/// A lamp at (0, 4, 0) over the floor and a vertical mirror at x = 2 (nothing else).
fn mirror_scene(attenuation: [f64; 3]) -> String {
    let [a_c, a_l, a_q] = attenuation;
    let corner = |name: &str, y: f64, z: f64| {
        format!(
            r#"<vertex name="{name}" material="mirror"><position x="2" y="{y}" z="{z}"/><normal x="-1" y="0" z="0"/><tex_coord u="0" v="0"/></vertex>"#
        )
    };
    let mirror = [
        corner("m0", 0.01, -0.75),
        corner("m1", 0.01, 0.75),
        corner("m2", 2.0, 0.75),
        corner("m3", 2.0, -0.75),
        r#"<material name="mirror"><ambient r="0" g="0" b="0"/><diffuse r="0" g="0" b="0"/><specular r="1" g="1" b="1"/></material>"#.into(),
        r#"<triangle><position x="0" y="0" z="0"/><vertex name="m0"/><vertex name="m1"/><vertex name="m2"/></triangle>"#.into(),
        r#"<triangle><position x="0" y="0" z="0"/><vertex name="m2"/><vertex name="m3"/><vertex name="m0"/></triangle>"#.into(),
    ]
    .join("\n  ");
    scene_text(OVERHEAD, attenuation, 1.5, &mirror).replace(
        r#"<sphere material="glass"><position x="0" y="1" z="0"/><radius v="0.5"/></sphere>"#,
        "",
    ) + &format!("<!-- attenuation {a_c} {a_l} {a_q} -->")
}

#[test]
fn a_mirror_lights_the_floor_like_the_mirrored_lamp() {
    // The lamp's image in the mirror sits at (4, 4, 0): the photons must give the floor
    // exactly the direct term that lamp would, c·att(d)·cosθ with d its unfolded distance.
    // This pins down the photon power c·att(L)·L²·dω for every attenuation model.
    let p = DVec3::new(0.5, 0.0, 0.3);
    let image = DVec3::new(4.0, 4.0, 0.0);
    for attenuation in [NO_FALLOFF, [1.0, 0.3, 0.0], [0.0, 0.0, 1.0]] {
        let scene = build(&mirror_scene(attenuation));
        let params = CausticsParams {
            photons: 200_000,
            radius: Some(0.25),
        };
        let map = CausticMap::build(&scene, &params, 1, TextureFilter::Nearest);
        // The map is in the scene's frame, relative to its origin (the eye).
        let e = map.irradiance(p - scene.origin(), DVec3::Y).x;
        let d = (image - p).length();
        let [a_c, a_l, a_q] = attenuation;
        let direct = 0.8 / (a_c + a_l * d + a_q * d * d) * (image.y / d);
        eprintln!("attenuation {attenuation:?}: caustic {e:.4}, mirrored lamp {direct:.4}");
        assert!(
            (e / direct - 1.0).abs() < 0.05,
            "attenuation {attenuation:?}: caustic {e}, mirrored lamp {direct}"
        );
    }
}

#[test]
fn caustic_energy_stays_within_the_light_through_the_ball() {
    // A physical 1/d² light: the flux into the ball's cone of directions is 0.8·Ω, and glass
    // neither creates light nor (here) absorbs it.
    let light = DVec3::new(1.0, 4.0, 0.5);
    let scene = build(&scene_text(light, [0.0, 0.0, 1.0], 1.5, ""));
    let params = CausticsParams {
        photons: 60_000,
        radius: Some(0.05),
    };
    let map = CausticMap::build(&scene, &params, 3, TextureFilter::Nearest);
    let distance = (DVec3::new(0.0, 1.0, 0.0) - light).length();
    let sin2 = (0.5 / distance).powi(2);
    let omega = TAU * (1.0 - (1.0 - sin2).sqrt());
    let budget = 0.8 * omega;
    let stored = map.total_power();
    assert!(
        stored.x <= budget,
        "photons carry {stored} of {budget} through the ball"
    );
    // Most of it gets through: Fresnel reflection at n = 1.5 takes roughly a tenth.
    assert!(stored.x > 0.75 * budget, "{stored} of {budget}");

    // The gathered irradiance, integrated over the floor, accounts for the same flux: the
    // kernel neither loses nor invents energy.
    let step = 0.02;
    let mut integral = 0.0;
    for i in -150..150 {
        for j in -150..150 {
            let p = DVec3::new((i as f64 + 0.5) * step, 0.0, (j as f64 + 0.5) * step);
            integral += map.irradiance(p - scene.origin(), DVec3::Y).x * step * step;
        }
    }
    assert!(
        integral <= budget && (integral / stored.x - 1.0).abs() < 0.03,
        "integrated {integral}, stored {}, budget {budget}",
        stored.x
    );
}

fn showcase_like() -> Scene {
    build(&scene_text(DVec3::new(1.5, 4.0, 1.0), NO_FALLOFF, 1.5, ON))
}

#[test]
fn tiles_and_threads_do_not_change_caustics() {
    let s = RenderSettings {
        width: 40,
        height: 30,
        ..small(CausticsSettings::default())
    };
    let scene = showcase_like();
    let renderer = Renderer::new(&scene, &s).unwrap();
    let whole = renderer.render_image(&|_, _| {});
    let cancel = AtomicBool::new(false);
    let mut tiled = Image::new(s.width, s.height);
    for rect in TileRect::grid(s.width, s.height, 16) {
        let tile = renderer.render_tile(rect, &cancel).unwrap();
        tiled.insert(rect, &tile);
    }
    assert_eq!(whole.pixels, tiled.pixels);

    // Each pool builds its own map from a fresh scene.
    let in_pool = |threads: usize| {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(threads)
            .build()
            .unwrap();
        let scene = showcase_like();
        pool.install(|| render(&scene, &s))
    };
    assert_eq!(in_pool(1).pixels, whole.pixels);
    assert_eq!(in_pool(3).pixels, whole.pixels);
}

#[test]
fn renderers_of_one_scene_share_one_map() {
    let scene = showcase_like();
    let s = small(CausticsSettings::default());
    let first = Renderer::new(&scene, &s).unwrap();
    let second = Renderer::new(&scene, &s).unwrap();
    assert!(std::ptr::eq(
        first.caustics().unwrap(),
        second.caustics().unwrap()
    ));
    // Different settings get their own map.
    let reseeded = Renderer::new(&scene, &RenderSettings { seed: 9, ..s }).unwrap();
    assert!(!std::ptr::eq(
        first.caustics().unwrap(),
        reseeded.caustics().unwrap()
    ));
}

#[test]
fn settings_turn_caustics_on_and_override_the_scene() {
    let plain = build(&scene_text(OVERHEAD, NO_FALLOFF, 1.5, ""));
    let on = CausticsSettings {
        photons: Some(5000),
        radius: Some(0.2),
        ..Default::default()
    };
    let renderer = Renderer::new(&plain, &small(on)).unwrap();
    let map = renderer.caustics().expect("--photons turns caustics on");
    assert_eq!((map.emitted(), map.radius()), (5000, 0.2));
    let enabled = CausticsSettings {
        enabled: Some(true),
        ..Default::default()
    };
    let map = Renderer::new(&plain, &small(enabled)).unwrap();
    // The default radius follows the ball: a twentieth of its radius.
    assert_eq!(map.caustics().unwrap().radius(), 0.5 / 20.0);
    for bad in [
        CausticsSettings {
            photons: Some(0),
            ..Default::default()
        },
        CausticsSettings {
            radius: Some(-1.0),
            ..Default::default()
        },
        CausticsSettings {
            radius: Some(f64::NAN),
            ..Default::default()
        },
    ] {
        assert!(Renderer::new(&plain, &small(bad)).is_err(), "{bad:?}");
    }
}

#[test]
fn settings_without_caustics_serialise_as_before() {
    let json = serde_json::to_string(&RenderSettings::default()).unwrap();
    assert!(!json.contains("caustics"), "{json}");
    let s: RenderSettings =
        serde_json::from_str(r#"{"caustics": {"enabled": true, "photons": 10}}"#).unwrap();
    assert_eq!(s.caustics.photons, Some(10));
    assert!(serde_json::from_str::<RenderSettings>(r#"{"caustics": {"photon": 10}}"#).is_err());
}

#[test]
fn bad_caustics_elements_are_reported_where_they_are() {
    let at = |element: &str| {
        let text = scene_text(OVERHEAD, NO_FALLOFF, 1.5, element);
        let err = parse(&text).expect_err(element);
        let line = text.lines().position(|l| l.contains("<caustics")).unwrap() as u32 + 1;
        assert_eq!(
            (err.file.as_str(), err.line),
            ("caustics.scene", line),
            "{err}"
        );
        err.to_string()
    };
    assert!(at(r#"<caustics photons="0"/>"#).contains("'photons'"));
    assert!(at(r#"<caustics photons="1.5"/>"#).contains("whole number"));
    assert!(at(r#"<caustics photons="99999999999"/>"#).contains("between 1 and"));
    assert!(at(r#"<caustics photons="many"/>"#).contains("error parsing"));
    assert!(at(r#"<caustics radius="0"/>"#).contains("must be positive"));
    assert!(at(r#"<caustics radius="-0.1"/>"#).contains("'radius'"));
    assert!(at(r#"<caustics radius="inf"/>"#).contains("not a finite number"));
    assert!(at("<caustics/>\n  <caustics/>").contains("more than once"));
    // Both attributes are optional.
    let desc = SceneDescription::parse(
        &scene_text(OVERHEAD, NO_FALLOFF, 1.5, "<caustics/>"),
        "caustics.scene",
    )
    .unwrap();
    let c = desc.caustics.unwrap();
    assert_eq!((c.photons, c.radius), (None, None));
}
