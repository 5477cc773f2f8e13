//! The extreme-case suite over `scenes/extreme/`: every case renders with finite pixels, no
//! panic and bounded work, or is rejected at load. docs/numerics.md describes each case.

use glam::DVec3;
use tracer_core::geometry::{Motion, Ray, Transform};
use tracer_core::scene::SceneDescription;
use tracer_core::shade::RAY_BUDGET_PER_SAMPLE;
use tracer_core::{CameraOverride, FsAssets, Image, MemoryAssets, RenderSettings, Renderer, Scene};

mod common;

use common::{extreme, settings};

fn load(name: &str) -> Scene {
    common::load(extreme(&format!("{name}.scene")))
}

fn render(scene: &Scene, s: &RenderSettings) -> (Image, u64) {
    let renderer = Renderer::new(scene, s).unwrap();
    let image = renderer.render_image(&|_, _| {});
    assert!(
        image.pixels.iter().all(|v| v.is_finite()),
        "a pixel is not finite"
    );
    (image, renderer.rays_traced())
}

/// The eye ray through a pixel centre, and the pixel's colour, for every pixel of a 1-spp
/// render (pixel centres are exactly what 1 spp traces).
fn pixels_with_rays(scene: &Scene, s: &RenderSettings) -> Vec<(Ray, [f32; 3])> {
    let renderer = Renderer::new(scene, s).unwrap();
    let image = renderer.render_image(&|_, _| {});
    let (w, h) = (s.width, s.height);
    let mut out = Vec::new();
    for row in 0..h {
        for x in 0..w {
            let y = h - 1 - row;
            let ray = renderer
                .camera()
                .ray(x as f64 + 0.5, y as f64 + 0.5, w as f64, h as f64);
            out.push((ray, image.pixel(x, row)));
        }
    }
    out
}

#[test]
fn every_extreme_scene_renders_finite_pixels() {
    for entry in std::fs::read_dir(extreme("")).unwrap() {
        let path = entry.unwrap().path();
        if path.extension().is_none_or(|e| e != "scene") || path.ends_with("zero_scale.scene") {
            continue;
        }
        let scene = Scene::load(&path).unwrap_or_else(|e| panic!("{e}"));
        for depth in [1, 5, 12] {
            let s = RenderSettings {
                max_depth: depth,
                ..settings(48, 36, 2)
            };
            render(&scene, &s);
        }
    }
}

#[test]
fn a_zero_scale_is_rejected_at_load() {
    let err = Scene::load(&extreme("zero_scale.scene")).unwrap_err();
    assert!(err.message.contains("zero scale"), "{err}");
    assert_eq!((err.line, err.column), (24, 70), "{err}");
}

/// Any scene description scaled about the world origin by `scale`, then moved by `offset`:
/// positions, radii, model and triangle scales, clip planes, lens, light sizes, keyed motion,
/// velocities, absorption and the caustic gather radius, with attenuation rescaled so that
/// 1/(a_c + a_l·d + a_q·d²) is the same at the scaled distances. The image must not change.
fn transformed(desc: &SceneDescription, scale: f64, offset: DVec3) -> SceneDescription {
    let mut d = desc.clone();
    let place = |p: DVec3| p * scale + offset;
    let place_motion = |m: &mut Motion| {
        for key in &mut m.keys {
            key.transform.position = place(key.transform.position);
        }
        m.velocity *= scale;
    };
    let c = &mut d.camera;
    c.position = place(c.position);
    c.near_clip *= scale;
    c.far_clip *= scale;
    c.aperture *= scale;
    c.focus_distance *= scale;
    for key in &mut c.focus_keys {
        key.1 *= scale;
    }
    place_motion(&mut c.motion);
    for l in &mut d.lights {
        l.position = place(l.position);
        l.radius *= scale;
        l.attenuation[1] /= scale;
        l.attenuation[2] /= scale * scale;
    }
    for m in &mut d.materials {
        m.absorption /= scale;
    }
    for s in &mut d.spheres {
        s.transform.position = place(s.transform.position);
        s.radius *= scale;
        place_motion(&mut s.motion);
    }
    for t in &mut d.triangles {
        t.transform.position = place(t.transform.position);
        for v in &mut t.vertices {
            v.position *= scale;
        }
        place_motion(&mut t.motion);
    }
    for m in &mut d.models {
        m.transform.position = place(m.transform.position);
        m.transform.scale *= scale;
        for key in &mut m.motion.keys {
            key.transform.scale *= scale;
        }
        place_motion(&mut m.motion);
    }
    if let Some(radius) = d.caustics.as_mut().and_then(|c| c.radius.as_mut()) {
        *radius *= scale;
    }
    d
}

/// Pixels whose 8-bit value differs by more than 2 levels in some channel.
fn differing_pixels(a: &Image, b: &Image) -> usize {
    let (a, b) = (a.to_rgb8(), b.to_rgb8());
    a.chunks(3)
        .zip(b.chunks(3))
        .filter(|(p, q)| p.iter().zip(q.iter()).any(|(x, y)| x.abs_diff(*y) > 2))
        .count()
}

#[test]
fn scaling_and_translating_the_scene_keeps_the_image() {
    let path = extreme("base.scene");
    let text = std::fs::read_to_string(&path).unwrap();
    let base = SceneDescription::parse(&text, "base.scene").unwrap();
    let assets = FsAssets::for_scene(&path);
    let s = settings(160, 120, 4);
    let reference = render(&Scene::build(&base, "base", &assets).unwrap(), &s).0;
    // Tolerance: at most 0.5% of pixels may differ by more than 2 levels (edge pixels whose
    // sub-pixel samples land on the other side of a silhouette after rounding).
    let allowed = (160 * 120) / 200;
    for (scale, offset) in [
        (1e-4, DVec3::ZERO),
        (1e4, DVec3::ZERO),
        (1.0, DVec3::new(1e5, -1e5, 1e5)),
    ] {
        let variant = Scene::build(&transformed(&base, scale, offset), "variant", &assets).unwrap();
        let image = render(&variant, &s).0;
        let differing = differing_pixels(&image, &reference);
        eprintln!("scale {scale:e}, offset {offset}: {differing} pixels differ");
        assert!(
            differing <= allowed,
            "scale {scale:e} offset {offset}: {differing} pixels differ (allowed {allowed})"
        );
    }
}

/// The course scenes themselves, moved 1e7 away and shrunk to 1e-5 of their size 1e3 away
/// from the world origin (where f64 keeps about 1e-8 of the scene's size and f32 boxes about
/// 1e-2): rendering relative to the eye keeps their images. Same tolerance as above.
#[test]
fn course_scenes_keep_their_image_far_away_and_tiny() {
    let (w, h) = (160, 120);
    let s = settings(w, h, 4);
    let allowed = (w * h) as usize / 200;
    for name in [
        "test",
        "spheres",
        "tetrahedron",
        "stacks",
        "cube",
        "cornell_box",
        "dragon",
        "toy",
    ] {
        let path = common::course(&format!("{name}.scene"));
        let text = std::fs::read_to_string(&path).unwrap();
        let base = SceneDescription::parse(&text, name).unwrap();
        let assets = FsAssets::for_scene(&path);
        let reference = render(&Scene::build(&base, name, &assets).unwrap(), &s).0;
        for (scale, offset) in [
            (1.0, DVec3::new(1e7, -1e7, 1e7)),
            (1e-5, DVec3::new(1e3, 1e3, -1e3)),
        ] {
            let variant = Scene::build(&transformed(&base, scale, offset), name, &assets).unwrap();
            let differing = differing_pixels(&render(&variant, &s).0, &reference);
            eprintln!(
                "{name}: scale {scale:e}, offset {offset}: {differing} pixels differ ({:.2}%)",
                100.0 * differing as f64 / (w * h) as f64
            );
            assert!(
                differing <= allowed,
                "{name} scale {scale:e} offset {offset}: {differing} pixels differ (allowed {allowed})"
            );
        }
    }
}

#[test]
fn a_plane_lit_at_a_grazing_angle_has_no_shadow_acne() {
    let scene = load("grazing_plane");
    let s = settings(160, 120, 1);
    let (near, far) = (0.1, 2000.0);
    let mut floor_pixels = 0;
    for (ray, pixel) in pixels_with_rays(&scene, &s) {
        if scene.world().intersect(&ray, near, far).is_some() {
            floor_pixels += 1;
            // Ambient alone is 0.1; any direct light at all lifts it.
            assert!(
                pixel[0] > 0.1 + 1e-6,
                "an unoccluded floor point is shadowed: {pixel:?}"
            );
        }
    }
    assert!(
        floor_pixels > 160 * 40,
        "the floor should fill much of the view"
    );
}

#[test]
fn a_sphere_lit_from_behind_has_no_terminator_acne() {
    let scene = load("backlit_sphere");
    let light = DVec3::new(0.0, 8.0, -6.0);
    let mut lit = 0;
    for (ray, pixel) in pixels_with_rays(&scene, &settings(160, 120, 1)) {
        let Some(hit) = scene.world().intersect(&ray, 0.1, 100.0) else {
            continue;
        };
        // Rays and the world are relative to the scene's origin; the sphere is at the world's.
        let p = scene.origin() + ray.at(hit.t);
        let n = p.normalize();
        if n.dot((light - p).normalize()) > 1e-6 {
            lit += 1;
            assert!(
                pixel[0] > 0.1 + 1e-9,
                "a point facing the light is shadowed: {p}"
            );
        } else {
            assert!(
                (pixel[0] - 0.1).abs() < 1e-6,
                "a point facing away is lit: {p}"
            );
        }
    }
    assert!(
        lit > 20,
        "some of the visible rim faces the light ({lit} pixels)"
    );
}

#[test]
fn a_cube_resting_on_the_floor_keeps_its_contact_shadow() {
    let scene = load("contact");
    let view = |position: [f64; 3], look_at: [f64; 3]| RenderSettings {
        camera: Some(CameraOverride {
            position,
            look_at,
            up: [0.0, 1.0, 0.0],
        }),
        ..settings(160, 120, 1)
    };
    // The +x side faces away from the light: the floor there is in shadow up to the cube.
    let mut shadowed = 0;
    for (ray, pixel) in pixels_with_rays(&scene, &view([7.0, 0.6, 0.0], [0.0, 0.3, 0.0])) {
        let Some(hit) = scene.world().intersect(&ray, 0.1, 100.0) else {
            continue;
        };
        let p = scene.origin() + ray.at(hit.t);
        if p.y.abs() < 1e-6 && p.x > 1.0 && p.x < 6.0 && p.z.abs() < 0.9 {
            shadowed += 1;
            assert!(
                (pixel[0] - 0.1).abs() < 1e-6,
                "light leaks under the cube at {p}"
            );
        }
    }
    assert!(
        shadowed > 200,
        "the shadowed strip is in view ({shadowed} pixels)"
    );
    // The -x side faces the light: the floor is lit right up to the contact line.
    let mut lit = 0;
    for (ray, pixel) in pixels_with_rays(&scene, &view([-7.0, 0.6, 0.0], [0.0, 0.3, 0.0])) {
        let Some(hit) = scene.world().intersect(&ray, 0.1, 100.0) else {
            continue;
        };
        let p = scene.origin() + ray.at(hit.t);
        if p.y.abs() < 1e-6 && p.x < -1.0 && p.x > -6.0 && p.z.abs() < 0.9 {
            lit += 1;
            assert!(pixel[0] > 0.1 + 1e-6, "acne on the lit floor at {p}");
        }
    }
    assert!(lit > 200, "the lit strip is in view ({lit} pixels)");
}

/// A closed latitude–longitude sphere mesh with shared vertices, as OBJ text.
fn sphere_obj(rings: usize, segments: usize) -> (String, Vec<DVec3>, Vec<[usize; 3]>) {
    let mut positions = vec![DVec3::Y];
    for i in 1..rings {
        let theta = std::f64::consts::PI * i as f64 / rings as f64;
        for j in 0..segments {
            let phi = std::f64::consts::TAU * j as f64 / segments as f64;
            positions.push(DVec3::new(
                theta.sin() * phi.cos(),
                theta.cos(),
                theta.sin() * phi.sin(),
            ));
        }
    }
    positions.push(DVec3::NEG_Y);
    let ring = |i: usize, j: usize| 1 + (i - 1) * segments + j % segments;
    let south = positions.len() - 1;
    let mut tris = Vec::new();
    for j in 0..segments {
        tris.push([0, ring(1, j + 1), ring(1, j)]);
        tris.push([south, ring(rings - 1, j), ring(rings - 1, j + 1)]);
        for i in 1..rings - 1 {
            tris.push([ring(i, j), ring(i, j + 1), ring(i + 1, j + 1)]);
            tris.push([ring(i + 1, j + 1), ring(i + 1, j), ring(i, j)]);
        }
    }
    let mut text = String::new();
    for p in &positions {
        text += &format!("v {} {} {}\n", p.x, p.y, p.z);
    }
    for t in &tris {
        text += &format!("f {} {} {}\n", t[0] + 1, t[1] + 1, t[2] + 1);
    }
    (text, positions, tris)
}

fn inline_scene(body: &str) -> String {
    format!(
        r#"<scene>
    <camera><fov v="0.8"/><near_clip v="0.01"/><far_clip v="100"/><position x="0" y="0" z="6"/><orientation a="0" x="0" y="1" z="0"/></camera>
    <background_color r="0" g="0" b="0"/>
    <refractive_index v="1"/>
    <point_light><position x="3" y="5" z="5"/><color r="1" g="1" b="1"/></point_light>
    <material name="m"/>
    <mesh name="mesh" filename="mesh.obj"/>
{body}
</scene>"#
    )
}

#[test]
fn rays_through_shared_edges_and_vertices_of_a_closed_mesh_all_hit() {
    let (obj, positions, tris) = sphere_obj(16, 24);
    let text = inline_scene(
        r#"    <model mesh="mesh" material="m"><position x="0.3" y="-0.2" z="0.1"/><orientation a="0.7" x="1" y="2" z="0.5"/><scale x="1.5" y="0.8" z="1.1"/></model>"#,
    );
    let desc = SceneDescription::parse(&text, "watertight").unwrap();
    let assets = MemoryAssets {
        files: [("mesh.obj".to_string(), obj.into_bytes())].into(),
    };
    let scene = Scene::build(&desc, "watertight", &assets).unwrap();
    // The model's transform in the scene's frame (relative to its origin, like the world).
    let t = &desc.models[0].transform;
    let xf = Transform::new(t.position - scene.origin(), t.orientation, t.scale);
    let world = |p: DVec3| xf.to_world.transform_point3(p);

    // Targets: every vertex and every edge midpoint, in world space, with the outward
    // normal there (the mesh approximates a unit sphere in its local frame).
    let mut targets: Vec<(DVec3, DVec3)> = positions
        .iter()
        .map(|&p| (world(p), xf.normal_to_world(p)))
        .collect();
    for tri in &tris {
        for k in 0..3 {
            let mid = 0.5 * (positions[tri[k]] + positions[tri[(k + 1) % 3]]);
            targets.push((world(mid), xf.normal_to_world(mid)));
        }
    }
    let mut state = 0x2545F4914F6CDD1Du64;
    let mut random = || {
        state ^= state << 13;
        state ^= state >> 7;
        state ^= state << 17;
        (state >> 11) as f64 / (1u64 << 53) as f64
    };
    for (target, normal) in &targets {
        let mut tried = 0;
        while tried < 4 {
            // Come in from outside, well away from tangency: a ray that only grazes the
            // surface at the target may miss by rounding alone, crack or no crack.
            let dir = DVec3::new(random() - 0.5, random() - 0.5, random() - 0.5).normalize();
            if dir.dot(*normal) < 0.3 {
                continue;
            }
            tried += 1;
            let origin = *target + 5.0 * dir;
            let ray = Ray::new(origin, (*target - origin).normalize());
            assert!(
                scene.world().intersect(&ray, 0.0, f64::INFINITY).is_some(),
                "a ray from outside through {target} slipped through the mesh"
            );
        }
    }
    // From inside, every direction meets the surface, including ones through edges and
    // vertices.
    let centre = world(DVec3::ZERO);
    for (target, _) in &targets {
        let ray = Ray::new(centre, (*target - centre).normalize());
        assert!(scene.world().intersect(&ray, 0.0, f64::INFINITY).is_some());
    }
    for _ in 0..5000 {
        let dir = DVec3::new(random() - 0.5, random() - 0.5, random() - 0.5).normalize();
        assert!(scene
            .world()
            .intersect(&Ray::new(centre, dir), 0.0, f64::INFINITY)
            .is_some());
    }
}

#[test]
fn dielectric_ray_counts_stay_bounded_at_any_depth() {
    for name in [
        "nested_glass",
        "camera_in_glass",
        "prism",
        "ior_extremes",
        "unmatched_exit",
    ] {
        let scene = load(name);
        let lights = scene.description.lights.len() as u64;
        let pixels = 32 * 24;
        for depth in [5, 64] {
            let s = RenderSettings {
                max_depth: depth,
                ..settings(32, 24, 1)
            };
            let (_, rays) = render(&scene, &s);
            // Radiance rays per sample: at most 2^depth − 1, and never above the budget;
            // each may send one shadow ray per light.
            let per_sample = (1u64 << depth.min(62)).min(RAY_BUDGET_PER_SAMPLE as u64 + 1);
            let bound = pixels * per_sample * (1 + lights);
            assert!(rays <= bound, "{name} depth {depth}: {rays} rays > {bound}");
        }
    }
}

#[test]
fn glass_inside_water_refracts_differently_from_glass_alone() {
    let scene = load("nested_glass");
    let nested = render(&scene, &settings(64, 48, 1)).0;
    let mut glass_only = scene.description.clone();
    glass_only.spheres.retain(|s| s.radius < 1.0);
    let alone = Scene::build(&glass_only, "glass", &MemoryAssets::default()).unwrap();
    let single = render(&alone, &settings(64, 48, 1)).0;
    assert!(differing_pixels(&nested, &single) > 100);
}

#[test]
fn a_million_tiny_triangles_load_and_render() {
    let n = 708; // 708² quads, split into 1,002,528 triangles of about 1.4e-3 across
    let mut obj = String::with_capacity(40 << 20);
    for i in 0..=n {
        for j in 0..=n {
            obj += &format!(
                "v {} {} 0\n",
                i as f64 / n as f64 - 0.5,
                j as f64 / n as f64 - 0.5
            );
        }
    }
    let id = |i: usize, j: usize| i * (n + 1) + j + 1;
    for i in 0..n {
        for j in 0..n {
            obj += &format!(
                "f {} {} {} {}\n",
                id(i, j),
                id(i + 1, j),
                id(i + 1, j + 1),
                id(i, j + 1)
            );
        }
    }
    let text = inline_scene(
        r#"    <model mesh="mesh" material="m"><position x="0" y="0" z="0"/><scale x="3" y="3" z="3"/></model>"#,
    );
    let desc = SceneDescription::parse(&text, "million").unwrap();
    let assets = MemoryAssets {
        files: [("mesh.obj".to_string(), obj.into_bytes())].into(),
    };
    let scene = Scene::build(&desc, "million", &assets).unwrap();
    assert_eq!(scene.stats.triangles, 2 * n * n);
    let (image, _) = render(&scene, &settings(64, 48, 1));
    // The plane faces the camera and the light: the centre is lit.
    assert!(image.pixel(32, 24)[0] > 0.5);
}

#[test]
fn equal_clip_planes_show_only_the_background() {
    let (image, _) = render(&load("clip_equal"), &settings(32, 24, 1));
    for px in image.pixels.chunks(3) {
        assert_eq!(px, [0.2, 0.3, 0.5]);
    }
}

#[test]
fn extreme_fields_of_view_and_coordinates_still_see_their_subject() {
    let background = [0.2f32, 0.3, 0.5];
    for name in ["fov_tiny", "fov_wide", "huge_coordinates"] {
        let (image, _) = render(&load(name), &settings(33, 25, 1));
        assert_ne!(
            image.pixel(16, 12),
            background,
            "{name}: the centre pixel misses"
        );
    }
}
