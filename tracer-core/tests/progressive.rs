//! Progressive passes: sample ranges continued from running sums give exactly the bytes of a
//! one-shot render, and the one-shot render's default order is untouched by the option.

mod common;

use std::sync::atomic::AtomicBool;

use tracer_core::adaptive::{SumImage, SUMS};
use tracer_core::{Renderer, SampleOrder, TileRect};

fn bits(pixels: &[f32]) -> Vec<u32> {
    pixels.iter().map(|v| v.to_bits()).collect()
}

#[test]
fn passes_continue_the_one_shot_sum_bit_for_bit() {
    // Soft shadows and glass: every sample differs, so an order mistake changes bits.
    let scene = common::load(common::course("cornell_box.scene"));
    let settings = common::settings(24, 18, 13);
    let never = AtomicBool::new(false);
    for order in [SampleOrder::Grid, SampleOrder::Progressive] {
        let renderer = Renderer::new(&scene, &settings)
            .unwrap()
            .with_sample_order(order);
        let one_shot = renderer.render_image(&|_, _| {});
        // Three passes of uneven sizes, over tiles that do not align with the 8x8 blocks.
        let mut sums = SumImage::new(24, 18);
        for samples in [0..4, 4..6, 6..13] {
            for rect in TileRect::grid(24, 18, 7) {
                let mut tile = sums.tile(rect);
                assert!(renderer.render_tile_samples(
                    rect,
                    &|_, _| samples.clone(),
                    &mut tile,
                    &never
                ));
                sums.put_tile(rect, &tile);
            }
        }
        let blocks = tracer_core::adaptive::blocks(24, 18);
        let counts = vec![13; (blocks.0 * blocks.1) as usize];
        let passes = sums.image(&counts);
        assert_eq!(bits(&passes.pixels), bits(&one_shot.pixels), "{order:?}");
        assert!(sums.error(&counts) > 0.0 && sums.error(&counts).is_finite());
    }
}

#[test]
fn inactive_pixels_keep_their_sums_and_orders_differ() {
    let scene = common::load(common::course("cornell_box.scene"));
    let settings = common::settings(16, 8, 16);
    let never = AtomicBool::new(false);
    let rect = TileRect::new(0, 0, 16, 8);
    let render = |order| {
        let renderer = Renderer::new(&scene, &settings)
            .unwrap()
            .with_sample_order(order);
        let mut sums = vec![0.0; rect.pixel_count() * SUMS];
        renderer.render_tile_samples(
            rect,
            &|x, _| if x < 8 { 0..4 } else { 0..0 },
            &mut sums,
            &never,
        );
        sums
    };
    let grid = render(SampleOrder::Grid);
    let progressive = render(SampleOrder::Progressive);
    // Pixels right of x = 8 were not sampled.
    for y in 0..8 {
        for x in 8..16 {
            let p = (y * 16 + x) * SUMS;
            assert_eq!(&grid[p..p + SUMS], &[0.0; SUMS]);
        }
    }
    // The first four grid samples sit in the top row of strata; the progressive ones spread
    // over the pixel: different rays, different sums.
    assert_ne!(grid, progressive);
}
