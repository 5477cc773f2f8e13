//! Progressive passes: a lease with a `pass` continues the tile's running sums (fetched from
//! the coordinator) over its sample range and answers with the new sums; any other lease
//! renders the tile whole and answers with pixels. Kept apart from the pull loop, which only
//! asks this module what to render and where to send it.

use std::future::Future;
use std::pin::Pin;
use std::sync::atomic::AtomicBool;

use protocol::client::{Bytes, Client, ClientError, TileBuffers};
use protocol::{Completion, Lease, LeaseRequest, WorkerIdentity};
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

/// Fetches what `lease` continues from (a first pass starts from zeros without asking), from
/// `handover` when there is one.
pub async fn start(
    client: &Client,
    handover: Option<&dyn Handover>,
    lease: &Lease,
) -> Result<Start, ClientError> {
    let Some(pass) = &lease.pass else {
        return Ok(Start::Tile);
    };
    let pixels = lease.rect.pixel_count();
    if pass.samples_from == 0 {
        return Ok(Start::Pass(vec![0.0; pixels * tracer_core::adaptive::SUMS]));
    }
    let bytes = match handover {
        Some(handover) => handover.sums(lease.lease_id).await?,
        None => client.lease_sums(lease.lease_id).await?,
    };
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

/// A way to reach the coordinator other than its HTTP routes, for the calls a worker makes
/// on every tile. A worker in the coordinator's own process (the embedded farm) registers,
/// asks for leases, reads a pass's sums and hands its output over in memory, through the
/// same code the routes run: nothing crosses a loopback socket, and a tile's pixels are not
/// copied into a request body on the way (an 800×600 tile of f32 RGB took 13 ms from render
/// end to acceptance over HTTP). Heartbeats, failures and hand-backs, which are rare, still
/// go over HTTP. Errors are the ones the routes' answers would give
/// ([`ClientError::from_answer`]; an unknown worker's lease request is
/// [`ClientError::UnknownWorker`]).
pub trait Handover: Send + Sync {
    /// Registers a worker called `name`, as `POST /workers` does.
    fn register(&self, name: &str) -> BoxFuture<'_, WorkerIdentity>;

    /// A lease for `req`'s worker, waiting as `POST /leases` does; None when none turned up.
    fn lease(&self, req: LeaseRequest) -> BoxFuture<'_, Option<Lease>>;

    /// A pass lease's running sums so far (f64 little-endian), as its sums route answers.
    fn sums(&self, lease_id: u64) -> BoxFuture<'_, Vec<u8>>;

    /// Delivers `lease_id`'s output as its route would: f32 pixels, or with `pass` a
    /// progressive pass's f64 running sums, little-endian either way.
    fn complete(&self, lease_id: u64, bytes: Bytes, pass: bool) -> BoxFuture<'_, Completion>;
}

/// What a [`Handover`] call answers.
pub type BoxFuture<'a, T> = Pin<Box<dyn Future<Output = Result<T, ClientError>> + Send + 'a>>;

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
