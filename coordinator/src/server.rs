//! Serving: the API on a bound listener, plus the reaper that expires lapsed leases, until a
//! shutdown future resolves.

use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpListener;

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
    let reaper = tokio::spawn(reap(farm.clone()));
    let app = crate::api::router(farm.clone(), token.as_deref());
    let stopping = farm.clone();
    // Connection info gives the dashboard each worker's address.
    let app = app.into_make_service_with_connect_info::<SocketAddr>();
    let result = axum::serve(listener, app)
        .with_graceful_shutdown(async move {
            shutdown.await;
            stopping.stop();
        })
        .await;
    reaper.abort();
    result
}

async fn reap(farm: Arc<Farm>) {
    let mut ticker = tokio::time::interval(REAP_EVERY);
    ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        ticker.tick().await;
        if let Err(e) = farm.expire_leases() {
            tracing::error!("expiring leases: {e}");
        }
    }
}
