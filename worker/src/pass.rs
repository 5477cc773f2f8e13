//! Progressive passes: a lease with a `pass` continues the tile's running sums (fetched from
//! the coordinator) over its sample range and answers with the new sums; any other lease
//! renders the tile whole and answers with pixels. Kept apart from the pull loop, which only
//! asks this module what to render and where to send it.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::AtomicBool;

use protocol::client::{Bytes, Client, ClientError, TileBuffers};
use protocol::{Completion, Lease};
use tracer_core::adaptive::{block_of, SumImage};
use tracer_core::{Renderer, SampleOrder, Scene};

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

/// Fetches what `lease` continues from (a first pass starts from zeros without asking).
pub async fn start(client: &Client, lease: &Lease) -> Result<Start, ClientError> {
    let Some(pass) = &lease.pass else {
        return Ok(Start::Tile);
    };
    let pixels = lease.rect.pixel_count();
    if pass.samples_from == 0 {
        return Ok(Start::Pass(vec![0.0; pixels * tracer_core::adaptive::SUMS]));
    }
    let bytes = client.lease_sums(lease.lease_id).await?;
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

/// A way to hand rendered leases to the coordinator other than its HTTP routes. A worker
/// in the coordinator's own process (the embedded farm) gives them to the farm in memory: a
/// tile's pixels then cross no loopback socket and are not copied into a request body on
/// the way (an 800×600 tile of f32 RGB took 13 ms from render end to acceptance over HTTP).
/// Leases, heartbeats and everything else still go over HTTP.
pub trait Handover: Send + Sync {
    /// Delivers `lease_id`'s output as its route would: f32 pixels, or with `pass` a
    /// progressive pass's f64 running sums, little-endian either way. Errors are the ones
    /// the route's answer would give ([`ClientError::from_answer`]).
    fn complete(
        &self,
        lease_id: u64,
        bytes: Bytes,
        pass: bool,
    ) -> Pin<Box<dyn Future<Output = Result<Completion, ClientError>> + Send + '_>>;
}

/// Sends a rendered lease to the route that takes it, or to `handover` when there is one.
pub async fn deliver(
    client: &Client,
    handover: Option<&dyn Handover>,
    lease: &Lease,
    output: &Output,
) -> Result<Completion, ClientError> {
    if let Some(handover) = handover {
        return handover
            .complete(lease.lease_id, output.bytes.clone(), output.pass)
            .await;
    }
    if output.pass {
        client
            .complete_sums(lease.lease_id, output.bytes.clone())
            .await
    } else {
        client.complete(lease.lease_id, output.bytes.clone()).await
    }
}
