//! Serving: the API on a bound listener, plus the reaper that expires lapsed leases, until a
//! shutdown future resolves.
//!
//! Connections are served here rather than by `axum::serve` so that each is bounded
//! ([`ConnectionLimits`]): a semaphore permit is taken before `accept` (so the server never
//! runs out of descriptors, and excess clients wait in the kernel's backlog), a request's head
//! must arrive within the header timeout, a kept-alive connection is closed after the idle
//! timeout, and accept errors back off instead of spinning. HTTP/1.1 only: the workers,
//! the CLI and browsers on plain HTTP all speak it.

use std::convert::Infallible;
use std::future::Future;
use std::net::SocketAddr;
use std::pin::{pin, Pin};
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::Arc;
use std::task::{Context, Poll};
use std::time::Duration;

use axum::body::{Body, HttpBody};
use axum::extract::ConnectInfo;
use axum::Router;
use hyper::body::{Frame, Incoming, SizeHint};
use hyper_util::rt::{TokioIo, TokioTimer};
use tokio::io::{AsyncRead, AsyncWrite, ReadBuf};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use tokio::time::Instant;
use tower::ServiceExt;

use crate::api::Auth;
use crate::config::ConnectionLimits;
use crate::farm::Farm;

/// How often lapsed leases are looked for. A dead worker's tile is requeued within
/// `lease_timeout + REAP_EVERY`.
pub const REAP_EVERY: Duration = Duration::from_millis(250);

/// Serves the API on `listener` until `shutdown` resolves; long polls then answer 204 and
/// in-flight requests finish before this returns.
pub async fn serve(
    listener: TcpListener,
    farm: Arc<Farm>,
    token: Option<String>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    serve_with(listener, farm, Auth::from(token), shutdown).await
}

/// [`serve`] with credentials beyond the API token (`--metrics-token`).
pub async fn serve_with(
    listener: TcpListener,
    farm: Arc<Farm>,
    auth: Auth,
    shutdown: impl Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let reaper = tokio::spawn(reap(farm.clone()));
    let app = crate::api::router(farm.clone(), &auth);
    let limits = farm.config().connections.clone();
    // Stopping the farm ends long polls (204), so their connections can finish.
    let stopping = farm.clone();
    serve_router(listener, app, limits, shutdown, move || stopping.stop()).await;
    reaper.abort();
    Ok(())
}

/// Serves `/metrics` alone, without a token, on `listener` (`--metrics-listen`) until
/// `shutdown` resolves, under the same connection limits as the API.
pub async fn serve_metrics(
    listener: TcpListener,
    farm: Arc<Farm>,
    shutdown: impl Future<Output = ()> + Send + 'static,
) {
    let limits = farm.config().connections.clone();
    let app = crate::api::metrics_router(farm);
    serve_router(listener, app, limits, shutdown, || ()).await;
}

/// Serves `app` on `listener`, each connection bounded by `limits`, until `shutdown` resolves;
/// then calls `on_stop` and returns once in-flight requests have finished.
async fn serve_router(
    listener: TcpListener,
    app: Router,
    limits: ConnectionLimits,
    shutdown: impl Future<Output = ()> + Send + 'static,
    on_stop: impl FnOnce(),
) {
    let max_connections = connection_cap(limits.max_connections, descriptor_limit());
    tracing::debug!("serving at most {max_connections} connections at once");
    let permits = Arc::new(Semaphore::new(max_connections));
    // Connections watch `stop` to finish gracefully; each holds a `live` receiver, so
    // `live_tx.closed()` resolves once the last one has ended.
    let (stop_tx, stop_rx) = watch::channel(false);
    let (live_tx, live_rx) = watch::channel(());
    let mut shutdown = pin!(shutdown);
    loop {
        let next = async {
            let permit = permits.clone().acquire_owned().await.expect("never closed");
            (permit, accept(&listener).await)
        };
        let (permit, (stream, peer)) = tokio::select! {
            next = next => next,
            () = &mut shutdown => break,
        };
        tokio::spawn(connection(
            stream,
            peer,
            app.clone(),
            limits.clone(),
            permit,
            stop_rx.clone(),
            live_rx.clone(),
        ));
    }
    drop(listener);
    on_stop();
    let _ = stop_tx.send(true);
    drop(live_rx);
    live_tx.closed().await;
}

/// The connections to serve at once: as configured, but at most three quarters of the
/// descriptor limit, leaving the rest for the database, blobs and tiles.
fn connection_cap(configured: usize, descriptors: Option<u64>) -> usize {
    let budget = descriptors.map_or(usize::MAX, |n| {
        usize::try_from(n - n / 4).unwrap_or(usize::MAX)
    });
    configured.min(budget).max(1)
}

/// Accepts the next connection. A failure that concerns one client (it reset before being
/// accepted) is skipped; one that concerns the process (out of descriptors or memory) is
/// retried after a pause that doubles up to a second, so the server neither spins nor dies.
async fn accept(listener: &TcpListener) -> (TcpStream, SocketAddr) {
    let mut pause = Duration::from_millis(10);
    loop {
        match listener.accept().await {
            Ok(accepted) => return accepted,
            Err(e) if is_per_connection(&e) => continue,
            Err(e) => {
                tracing::warn!("accepting a connection: {e}; retrying in {pause:?}");
                tokio::time::sleep(pause).await;
                pause = (pause * 2).min(Duration::from_secs(1));
            }
        }
    }
}

fn is_per_connection(e: &std::io::Error) -> bool {
    use std::io::ErrorKind::*;
    matches!(
        e.kind(),
        ConnectionAborted | ConnectionReset | ConnectionRefused | Interrupted
    )
}

/// One connection: served until it ends, the client is too slow with a request head, or
/// the server stops (in-flight requests then finish).
async fn connection(
    stream: TcpStream,
    peer: SocketAddr,
    app: Router,
    limits: ConnectionLimits,
    _permit: OwnedSemaphorePermit,
    mut stop: watch::Receiver<bool>,
    _live: watch::Receiver<()>,
) {
    let activity = Arc::new(Activity::new());
    let io = TokioIo::new(Watched {
        inner: stream,
        activity: activity.clone(),
    });
    let service = {
        let activity = activity.clone();
        hyper::service::service_fn(move |req: hyper::Request<Incoming>| {
            let in_flight = activity.request_started();
            let mut req = req.map(Body::new);
            // The dashboard shows each worker's address.
            req.extensions_mut().insert(ConnectInfo(peer));
            let response = app.clone().oneshot(req);
            async move {
                let response = response.await?;
                Ok::<_, Infallible>(response.map(|body| Tracked {
                    inner: body,
                    _in_flight: in_flight,
                }))
            }
        })
    };
    // hyper's own head timer runs whenever the connection waits for a head, idle time after
    // a response included: it is the idle timeout. The shorter header timeout is ours.
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(TokioTimer::new())
        .header_read_timeout(limits.idle_timeout);
    let mut conn = pin!(http.serve_connection(io, service));
    let tick = (limits.header_timeout / 4).clamp(Duration::from_millis(10), Duration::from_secs(1));
    let mut ticker = tokio::time::interval(tick);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut stopping = *stop.borrow();
    if stopping {
        conn.as_mut().graceful_shutdown();
    }
    loop {
        tokio::select! {
            result = conn.as_mut() => {
                if let Err(e) = result {
                    tracing::debug!("connection from {peer}: {e}");
                }
                return;
            }
            _ = ticker.tick() => {
                if activity.head_overdue(limits.header_timeout) {
                    tracing::debug!(
                        "connection from {peer}: no complete request head within {:?}; closed",
                        limits.header_timeout
                    );
                    return;
                }
            }
            changed = stop.changed(), if !stopping => {
                stopping = changed.is_err() || *stop.borrow();
                if stopping {
                    conn.as_mut().graceful_shutdown();
                }
            }
        }
    }
}

/// What a connection is doing, as far as its timeouts care.
struct Activity {
    origin: Instant,
    /// Requests between their complete head and the end of their response body.
    in_flight: AtomicUsize,
    /// When the head now arriving began (milliseconds since `origin`), or [`Activity::NONE`].
    head_since_ms: AtomicU64,
}

impl Activity {
    const NONE: u64 = u64::MAX;

    /// A new connection owes its first head from the start.
    fn new() -> Self {
        Self {
            origin: Instant::now(),
            in_flight: AtomicUsize::new(0),
            head_since_ms: AtomicU64::new(0),
        }
    }

    fn now_ms(&self) -> u64 {
        self.origin.elapsed().as_millis() as u64
    }

    /// Bytes arrived: between requests, they start a head and its clock.
    fn bytes_read(&self) {
        if self.in_flight.load(Ordering::SeqCst) == 0 {
            let _ = self.head_since_ms.compare_exchange(
                Self::NONE,
                self.now_ms(),
                Ordering::SeqCst,
                Ordering::SeqCst,
            );
        }
    }

    /// hyper parsed a head: its clock stops until the response has been sent.
    fn request_started(self: &Arc<Self>) -> InFlight {
        self.in_flight.fetch_add(1, Ordering::SeqCst);
        self.head_since_ms.store(Self::NONE, Ordering::SeqCst);
        InFlight(self.clone())
    }

    fn head_overdue(&self, timeout: Duration) -> bool {
        let since = self.head_since_ms.load(Ordering::SeqCst);
        since != Self::NONE
            && self.in_flight.load(Ordering::SeqCst) == 0
            && self.now_ms().saturating_sub(since) >= timeout.as_millis() as u64
    }
}

/// Held by a request until its response body is finished or dropped.
struct InFlight(Arc<Activity>);

impl Drop for InFlight {
    fn drop(&mut self) {
        self.0.in_flight.fetch_sub(1, Ordering::SeqCst);
    }
}

/// A response body that releases its request's [`InFlight`] when it is done.
struct Tracked {
    inner: Body,
    _in_flight: InFlight,
}

impl HttpBody for Tracked {
    type Data = <Body as HttpBody>::Data;
    type Error = <Body as HttpBody>::Error;

    fn poll_frame(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
    ) -> Poll<Option<Result<Frame<Self::Data>, Self::Error>>> {
        Pin::new(&mut self.inner).poll_frame(cx)
    }

    fn is_end_stream(&self) -> bool {
        self.inner.is_end_stream()
    }

    fn size_hint(&self) -> SizeHint {
        self.inner.size_hint()
    }
}

/// The connection's socket, reporting reads to its [`Activity`].
struct Watched {
    inner: TcpStream,
    activity: Arc<Activity>,
}

impl AsyncRead for Watched {
    fn poll_read(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &mut ReadBuf<'_>,
    ) -> Poll<std::io::Result<()>> {
        let before = buf.filled().len();
        let result = Pin::new(&mut self.inner).poll_read(cx, buf);
        if matches!(result, Poll::Ready(Ok(()))) && buf.filled().len() > before {
            self.activity.bytes_read();
        }
        result
    }
}

impl AsyncWrite for Watched {
    fn poll_write(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        buf: &[u8],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write(cx, buf)
    }

    fn poll_write_vectored(
        mut self: Pin<&mut Self>,
        cx: &mut Context<'_>,
        bufs: &[std::io::IoSlice<'_>],
    ) -> Poll<std::io::Result<usize>> {
        Pin::new(&mut self.inner).poll_write_vectored(cx, bufs)
    }

    fn is_write_vectored(&self) -> bool {
        self.inner.is_write_vectored()
    }

    fn poll_flush(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_flush(cx)
    }

    fn poll_shutdown(mut self: Pin<&mut Self>, cx: &mut Context<'_>) -> Poll<std::io::Result<()>> {
        Pin::new(&mut self.inner).poll_shutdown(cx)
    }
}

/// The process's soft descriptor limit, when the platform has one.
pub fn descriptor_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit only writes the struct it is given.
        if unsafe { libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) } == 0 {
            #[allow(clippy::unnecessary_cast)] // rlim_t is not u64 on every platform
            return Some(limit.rlim_cur as u64);
        }
    }
    None
}

/// Raises the soft descriptor limit to the hard one (often 1024 against 500k+), so the
/// connection cap, not the limit, decides how many clients are served. Returns the soft
/// limit now in force.
pub fn raise_descriptor_limit() -> Option<u64> {
    #[cfg(unix)]
    {
        let mut limit = libc::rlimit {
            rlim_cur: 0,
            rlim_max: 0,
        };
        // SAFETY: getrlimit and setrlimit only read or write the struct they are given.
        unsafe {
            if libc::getrlimit(libc::RLIMIT_NOFILE, &mut limit) == 0
                && limit.rlim_cur < limit.rlim_max
            {
                let raised = libc::rlimit {
                    rlim_cur: limit.rlim_max,
                    rlim_max: limit.rlim_max,
                };
                // macOS refuses an unlimited soft limit: the old one then stays.
                if libc::setrlimit(libc::RLIMIT_NOFILE, &raised) != 0 {
                    tracing::debug!(
                        "could not raise the descriptor limit: {}",
                        std::io::Error::last_os_error()
                    );
                }
            }
        }
    }
    descriptor_limit()
}

async fn reap(farm: Arc<Farm>) {
    let mut ticker = tokio::time::interval(REAP_EVERY);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        ticker.tick().await;
        if let Err(e) = farm.expire_leases() {
            tracing::error!("expiring leases: {e}");
        }
        if let Err(e) = farm.check_time_limits() {
            tracing::error!("ending progressive jobs on their time limit: {e}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_connection_cap_stays_below_the_descriptor_limit() {
        assert_eq!(connection_cap(4096, Some(1024)), 768);
        assert_eq!(connection_cap(4096, Some(1 << 20)), 4096);
        assert_eq!(connection_cap(4096, None), 4096);
        assert_eq!(connection_cap(0, Some(1024)), 1);
    }

    #[test]
    fn a_head_is_overdue_only_between_requests() {
        let activity = Arc::new(Activity::new());
        assert!(
            activity.head_overdue(Duration::ZERO),
            "a new connection owes a head"
        );
        let in_flight = activity.request_started();
        activity.bytes_read(); // the request's body
        assert!(!activity.head_overdue(Duration::ZERO));
        drop(in_flight);
        assert!(
            !activity.head_overdue(Duration::ZERO),
            "idle: the idle timeout's turn"
        );
        activity.bytes_read(); // the next head begins
        assert!(activity.head_overdue(Duration::ZERO));
        assert!(!activity.head_overdue(Duration::from_secs(60)));
    }
}
