//! Progressive passes: a lease with a `pass` continues the tile's running sums (fetched from
//! the coordinator) over its sample range and answers with the new sums; any other lease
//! renders the tile whole and answers with pixels. Kept apart from the pull loop, which only
//! asks this module what to render and where to send it.

use std::sync::atomic::AtomicBool;

use protocol::client::{Bytes, ClientError, TileBuffers};
use protocol::{Completion, Lease};
use tracer_core::adaptive::{block_of, SumImage};
use tracer_core::{Renderer, SampleOrder, Scene};

use crate::link::Link;

/// What a lease needs before rendering: nothing, or the sums a pass continues.
pub enum Start {
    Tile,
    Pass(Vec<f64>),
}

/// A rendered lease, as the bytes its completion route takes (shared, not copied, by each
/// try to send them).
pub struct Output {
    bytes: Bytes,
    pass: bool,
}

/// Fetches what `lease` continues from over `link` (a first pass starts from zeros without
/// asking).
pub async fn start(link: &dyn Link, lease: &Lease) -> Result<Start, ClientError> {
    let Some(pass) = &lease.pass else {
        return Ok(Start::Tile);
    };
    let pixels = lease.rect.pixel_count();
    if pass.samples_from == 0 {
        return Ok(Start::Pass(vec![0.0; pixels * tracer_core::adaptive::SUMS]));
    }
    let bytes = link.sums(lease.lease_id).await?;
    SumImage::from_bytes(&bytes, pixels, "the lease's sums")
        .map(Start::Pass)
        .map_err(|e| ClientError::Protocol(e.to_string()))
}

/// Renders `lease` (on the current rayon pool); None if `cancel` was set first. A tile is
/// rendered into a buffer from `buffers`, which its body gives back once sent.
pub fn render(
    scene: &Scene,
    lease: &Lease,
    start: Start,
    cancel: &AtomicBool,
    buffers: &TileBuffers,
) -> Result<Option<Output>, String> {
    let renderer = Renderer::new(scene, &lease.settings).map_err(|e| e.to_string())?;
    match (start, &lease.pass) {
        (Start::Pass(mut sums), Some(pass)) => {
            let renderer = renderer.with_sample_order(SampleOrder::Progressive);
            let width = lease.settings.width;
            let samples = |x: u32, y: u32| pass.block_range(block_of(width, x, y) as u32);
            let done = renderer.render_tile_samples(lease.rect, &samples, &mut sums, cancel);
            Ok(done.then(|| Output {
                bytes: Bytes::from(SumImage::to_bytes(&sums)),
                pass: true,
            }))
        }
        _ => Ok(renderer
            .render_tile_in(lease.rect, cancel, buffers.take())
            .map(|image| Output {
                bytes: buffers.body(image.pixels),
                pass: false,
            })),
    }
}

/// Sends a rendered lease to the coordinator over `link`.
pub async fn deliver(
    link: &dyn Link,
    lease: &Lease,
    output: &Output,
) -> Result<Completion, ClientError> {
    link.complete(lease.lease_id, output.bytes.clone(), output.pass)
        .await
}
