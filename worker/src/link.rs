//! How a worker reaches the coordinator for the calls it makes on every tile: registering,
//! asking for a lease, reading a pass's sums and delivering what it rendered. A remote worker
//! goes over HTTP ([`Client`]); a worker in the coordinator's own process (the embedded farm)
//! is handed a link that runs the routes' code in memory, so nothing crosses a loopback socket
//! and a tile's pixels are not copied into a request body (an 800×600 tile of f32 RGB took
//! 13 ms from render end to acceptance over HTTP). Heartbeats, failures and hand-backs, which
//! are rare, always go over HTTP.

use std::future::Future;
use std::pin::Pin;

use protocol::client::{Bytes, Client, ClientError};
use protocol::{Completion, Lease, LeaseRequest, WorkerIdentity};

/// What a [`Link`] call answers.
pub type Answer<'a, T> = Pin<Box<dyn Future<Output = Result<T, ClientError>> + Send + 'a>>;

/// The coordinator as the pull loop sees it. Errors are the ones the routes' answers give
/// ([`ClientError::from_answer`]; an unknown worker's lease request is
/// [`ClientError::UnknownWorker`]).
pub trait Link: Send + Sync {
    /// Registers a worker called `name` (`POST /workers`).
    fn register<'a>(&'a self, name: &'a str) -> Answer<'a, WorkerIdentity>;

    /// A lease for `req`'s worker, waiting as `POST /leases` does; None when none turned up.
    fn lease(&self, req: LeaseRequest) -> Answer<'_, Option<Lease>>;

    /// A pass lease's running sums so far (f64 little-endian).
    fn sums(&self, lease_id: u64) -> Answer<'_, Vec<u8>>;

    /// Delivers `lease_id`'s output: f32 pixels, or with `pass` a progressive pass's f64
    /// running sums, little-endian either way.
    fn complete(&self, lease_id: u64, bytes: Bytes, pass: bool) -> Answer<'_, Completion>;
}

impl Link for Client {
    fn register<'a>(&'a self, name: &'a str) -> Answer<'a, WorkerIdentity> {
        Box::pin(Client::register(self, name))
    }

    fn lease(&self, req: LeaseRequest) -> Answer<'_, Option<Lease>> {
        Box::pin(async move { Client::lease(self, &req).await })
    }

    fn sums(&self, lease_id: u64) -> Answer<'_, Vec<u8>> {
        Box::pin(self.lease_sums(lease_id))
    }

    fn complete(&self, lease_id: u64, bytes: Bytes, pass: bool) -> Answer<'_, Completion> {
        if pass {
            Box::pin(self.complete_sums(lease_id, bytes))
        } else {
            Box::pin(Client::complete(self, lease_id, bytes))
        }
    }
}
