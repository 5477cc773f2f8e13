//! Packets of eye rays (`World::intersect_packet`) and of shadow rays
//! (`World::occluded_packet`) against the single-ray queries on the course's mesh scenes: the
//! same hit for every ray, and `tracer bench`'s primary and shadow measures count the same
//! hits and blocked rays both ways.

mod common;

use tracer_core::accel::Spread;
use tracer_core::bench::{trace, Measure, RaySets};
use tracer_core::Renderer;

#[test]
fn eye_ray_packets_find_each_rays_own_hit_on_course_scenes() {
    for file in ["dragon.scene", "toy.scene", "cube.scene"] {
        let scene = common::load(common::course(file));
        let settings = common::settings(96, 72, 1);
        let camera = *Renderer::new(&scene, &settings).unwrap().camera();
        let world = scene.world();
        let (w, h) = (settings.width as usize, settings.height as usize);
        let mut hits = 0;
        for (bx, by) in (0..h / 8).flat_map(|y| (0..w / 8).map(move |x| (x * 8, y * 8))) {
            // Each 8×8 block at the pixel centres, then jittered the same way in every pixel.
            for (jx, jy) in [(0.5, 0.5), (0.13, 0.91)] {
                let rays: Vec<_> = (0..64)
                    .map(|i| {
                        let (x, y) = ((bx + i % 8) as f64 + jx, (by + i / 8) as f64 + jy);
                        camera.ray(x, y, w as f64, h as f64)
                    })
                    .collect();
                // Taken as an 8×8 block (tracer bench's packets) and, with the jitter, as
                // what the renderer does only for one pixel's samples: the same hits.
                let spread = if jx == 0.5 {
                    Spread::Wide
                } else {
                    Spread::Pixel
                };
                let mut found = vec![None; rays.len()];
                world.intersect_packet(&rays, camera.near, camera.far, None, spread, &mut found);
                for (ray, packet) in rays.iter().zip(&found) {
                    let single = world.intersect(ray, camera.near, camera.far);
                    // The distance, and through the surface the triangle and barycentrics.
                    let key = |hit: &Option<tracer_core::world::Hit>| {
                        hit.map(|hit| {
                            let p = world.patch(ray, &hit);
                            (hit.t.to_bits(), p.normal.to_array().map(f64::to_bits))
                        })
                    };
                    assert_eq!(key(&single), key(packet), "{file}: block ({bx}, {by})");
                    hits += single.is_some() as usize;
                }
            }
        }
        assert!(hits > 200, "{file}: {hits} hits");
        let rays = RaySets::new(&scene, &settings).unwrap();
        assert_eq!(
            trace(&scene, &rays, Measure::Primary),
            trace(&scene, &rays, Measure::PrimarySingle),
            "{file}"
        );
        let blocked = trace(&scene, &rays, Measure::ShadowSingle);
        assert_eq!(trace(&scene, &rays, Measure::Shadow), blocked, "{file}");
        assert!(
            blocked > 0 && blocked < rays.shadow.len(),
            "{file}: {blocked} of {} shadow rays blocked",
            rays.shadow.len()
        );
    }
}
