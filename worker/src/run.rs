//! The pull loop: lease → cached scene → render on the worker's thread pool while
//! heartbeating → complete. Stateless: everything it needs comes with the lease and the bundle.

use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use tokio::sync::watch;

use crate::link::Link;
use crate::pass;
use crate::scenes::{LoadError, SceneCache};
use protocol::client::{Client, ClientError, TileBuffers};
use protocol::{FailureReport, Lease, LeaseRequest};

#[derive(Clone, Debug)]
pub struct WorkerConfig {
    /// A label for listings and logs; the coordinator issues the identity leases are keyed by.
    pub name: String,
    /// Render threads (the worker's own rayon pool).
    pub threads: usize,
    /// How long one lease request may wait on the coordinator for work.
    pub poll_wait: Duration,
    /// The longest pause between retries while the coordinator is unreachable.
    pub max_backoff: Duration,
}

impl WorkerConfig {
    pub fn new(name: impl Into<String>, threads: usize) -> Self {
        Self {
            name: name.into(),
            threads: threads.max(1),
            poll_wait: Duration::from_secs(20),
            max_backoff: Duration::from_secs(5),
        }
    }
}

/// The name a worker gets without `--name`: host and process id.
pub fn default_name() -> String {
    let host = std::fs::read_to_string("/proc/sys/kernel/hostname")
        .ok()
        .or_else(|| std::env::var("HOSTNAME").ok())
        .map(|h| h.trim().to_string())
        .filter(|h| !h.is_empty())
        .unwrap_or_else(|| "worker".into());
    format!("{host}-{}", std::process::id())
}

/// A stop request that remembers it has fired.
#[derive(Clone, Debug)]
pub struct Shutdown(watch::Receiver<bool>);

impl Shutdown {
    /// The sender stops everything holding a clone of the receiver (`send(true)`).
    pub fn new() -> (watch::Sender<bool>, Shutdown) {
        let (tx, rx) = watch::channel(false);
        (tx, Shutdown(rx))
    }

    pub fn is_set(&self) -> bool {
        *self.0.borrow()
    }

    /// Resolves once a stop is requested; never, if the sender is dropped without one.
    pub async fn wait(&mut self) {
        if self.0.wait_for(|stop| *stop).await.is_err() {
            std::future::pending::<()>().await;
        }
    }
}

/// What one worker did.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct WorkerStats {
    pub rendered: u64,
    pub failed: u64,
    /// Tiles given up because their lease went stale (cancelled job, a copy finished first).
    pub dropped: u64,
    pub handed_back: u64,
}

pub struct Worker {
    client: Client,
    config: WorkerConfig,
    scenes: Arc<SceneCache>,
    pool: Arc<rayon::ThreadPool>,
    /// How the worker registers, leases and delivers: `client` itself, unless an
    /// in-process link replaced it ([`Worker::with_link`]).
    link: Arc<dyn Link>,
    /// Buffers of tiles already sent, rendered into again.
    buffers: TileBuffers,
}

/// Why a render was cancelled.
#[derive(Debug, PartialEq)]
enum Stop {
    Stale(String),
    Shutdown,
}

impl Worker {
    pub fn new(
        client: Client,
        config: WorkerConfig,
        scenes: Arc<SceneCache>,
    ) -> Result<Self, String> {
        let name = config.name.clone();
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(config.threads)
            .thread_name(move |i| format!("{name}-render-{i}"))
            .build()
            .map_err(|e| e.to_string())?;
        Ok(Self::with_pool(client, config, scenes, Arc::new(pool)))
    }

    /// A worker that renders on `pool`, which other workers may share. Several pull loops on
    /// one pool keep its threads busy while one waits on the coordinator or finishes the last
    /// rows of its tile: rayon hands idle threads the other loops' rows (`EmbeddedFarm`).
    pub fn with_pool(
        client: Client,
        config: WorkerConfig,
        scenes: Arc<SceneCache>,
        pool: Arc<rayon::ThreadPool>,
    ) -> Self {
        Self {
            link: Arc::new(client.clone()),
            client,
            config,
            scenes,
            pool,
            buffers: TileBuffers::default(),
        }
    }

    /// Registers, leases and delivers through `link` rather than over HTTP: for a worker in
    /// the coordinator's own process.
    pub fn with_link(mut self, link: Arc<dyn Link>) -> Self {
        self.link = link;
        self
    }

    /// Pulls and renders tiles until `shutdown` fires. Returns an error only for problems no
    /// retry can fix (a wrong token, a refused request).
    pub async fn run(&self, mut shutdown: Shutdown) -> Result<WorkerStats, ClientError> {
        let mut stats = WorkerStats::default();
        let mut backoff = Backoff::new(Duration::from_millis(100), self.config.max_backoff);
        let wait_ms = self.config.poll_wait.as_millis() as u64;
        // Registered lazily, and again whenever the coordinator forgets the id.
        let mut request: Option<LeaseRequest> = None;
        let mut reported_down = false;
        while !shutdown.is_set() {
            let answer = tokio::select! {
                answer = self.next_lease(&mut request, wait_ms) => answer,
                _ = shutdown.wait() => break,
            };
            match answer {
                Err(ClientError::UnknownWorker(why)) => {
                    tracing::warn!("{why}; registering again");
                    request = None;
                }
                Ok(lease) => {
                    if reported_down {
                        tracing::info!("coordinator {} is back", self.client.base_url());
                        reported_down = false;
                    }
                    backoff.reset();
                    if let Some(lease) = lease {
                        self.work(lease, &mut shutdown, &mut stats, &mut backoff)
                            .await;
                    }
                }
                Err(e) if e.is_transient() => {
                    let pause = backoff.next_delay();
                    if !reported_down {
                        tracing::warn!("{e}; retrying with back-off");
                        reported_down = true;
                    }
                    tokio::select! {
                        _ = tokio::time::sleep(pause) => {}
                        _ = shutdown.wait() => break,
                    }
                }
                Err(e) => return Err(e),
            }
        }
        Ok(stats)
    }

    /// Registers when there is no identity yet, then asks for a tile.
    async fn next_lease(
        &self,
        request: &mut Option<LeaseRequest>,
        wait_ms: u64,
    ) -> Result<Option<Lease>, ClientError> {
        let req = match request {
            Some(req) => req,
            None => {
                let identity = self.link.register(&self.config.name).await?;
                tracing::info!(
                    "registered as worker {} ({})",
                    identity.worker_id,
                    identity.name
                );
                request.insert(LeaseRequest {
                    worker_id: identity.worker_id,
                    wait_ms,
                })
            }
        };
        self.link.lease(req.clone()).await
    }

    async fn work(
        &self,
        lease: Lease,
        shutdown: &mut Shutdown,
        stats: &mut WorkerStats,
        backoff: &mut Backoff,
    ) {
        let tag = format!(
            "job {} tile {} ({}x{} at {},{})",
            lease.job_id,
            lease.tile,
            lease.rect.width,
            lease.rect.height,
            lease.rect.x,
            lease.rect.y
        );
        let scene = match self.scenes.get(&self.client, lease.job_id).await {
            Ok(scene) => scene,
            Err(LoadError::Scene(error)) => {
                tracing::error!("{tag}: the scene does not load: {error}");
                self.report_failure(&lease, &tag, error, true, stats).await;
                return;
            }
            Err(LoadError::Fetch(error)) => {
                tracing::warn!("{tag}: {error}");
                self.retry_later(&lease, &tag, shutdown, stats, backoff)
                    .await;
                return;
            }
        };

        let begin = match pass::start(self.link.as_ref(), &lease).await {
            Ok(begin) => begin,
            Err(ClientError::Stale(why)) => {
                stats.dropped += 1;
                tracing::info!("{tag}: dropped before rendering: {why}");
                return;
            }
            Err(e) => {
                tracing::warn!("{tag}: fetching the pass's sums failed: {e}");
                self.retry_later(&lease, &tag, shutdown, stats, backoff)
                    .await;
                return;
            }
        };
        let start = Instant::now();
        let cancel = Arc::new(AtomicBool::new(false));
        let render = {
            let (cancel, lease, buffers) = (cancel.clone(), lease.clone(), self.buffers.clone());
            on_pool(&self.pool, move || {
                pass::render(&scene, &lease, begin, &cancel, &buffers)
            })
        };
        tokio::pin!(render);
        let beat = Duration::from_millis(lease.heartbeat_ms.max(50));
        let mut ticker = tokio::time::interval_at(tokio::time::Instant::now() + beat, beat);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
        let mut stop: Option<Stop> = None;
        let outcome = loop {
            tokio::select! {
                outcome = &mut render => break outcome,
                _ = ticker.tick(), if stop.is_none() => {
                    match self.client.heartbeat(lease.lease_id).await {
                        Ok(_) => {}
                        Err(ClientError::Stale(why)) => {
                            cancel.store(true, Ordering::Relaxed);
                            stop = Some(Stop::Stale(why));
                        }
                        // Keep rendering through a coordinator restart; the result is retried.
                        Err(e) => tracing::debug!("{tag}: heartbeat failed: {e}"),
                    }
                }
                _ = shutdown.wait(), if stop.is_none() => {
                    cancel.store(true, Ordering::Relaxed);
                    stop = Some(Stop::Shutdown);
                }
            }
        };
        let seconds = start.elapsed().as_secs_f64();
        let output = match outcome {
            Ok(Ok(Some(output))) => output,
            Ok(Ok(None)) => {
                match stop {
                    Some(Stop::Stale(why)) => {
                        stats.dropped += 1;
                        tracing::info!("{tag}: dropped after {seconds:.3}s: {why}");
                    }
                    _ => self.hand_back(&lease, &tag, stats).await,
                }
                return;
            }
            Ok(Err(error)) => {
                self.report_failure(&lease, &tag, error, false, stats).await;
                return;
            }
            Err(panicked) => {
                self.report_failure(&lease, &tag, panicked, false, stats)
                    .await;
                return;
            }
        };
        // Retry through network trouble: the pixels are worth keeping, and a restarted
        // coordinator honours leases granted before it went down.
        let mut retry = Backoff::new(Duration::from_millis(100), self.config.max_backoff);
        loop {
            match pass::deliver(self.link.as_ref(), &lease, &output).await {
                Ok(done) => {
                    stats.rendered += 1;
                    tracing::info!(
                        "{tag}: rendered in {seconds:.3}s, accepted ({}/{} done)",
                        done.tiles_done,
                        done.tiles_total
                    );
                    return;
                }
                Err(ClientError::Stale(why)) => {
                    stats.rendered += 1;
                    stats.dropped += 1;
                    tracing::info!("{tag}: rendered in {seconds:.3}s, dropped: {why}");
                    return;
                }
                Err(e) if e.is_transient() && !shutdown.is_set() => {
                    tracing::warn!("{tag}: sending the pixels failed: {e}; retrying");
                    tokio::select! {
                        _ = tokio::time::sleep(retry.next_delay()) => {}
                        _ = shutdown.wait() => {}
                    }
                }
                Err(e) => {
                    stats.rendered += 1;
                    tracing::error!("{tag}: rendered in {seconds:.3}s, not delivered: {e}");
                    return;
                }
            }
        }
    }

    async fn report_failure(
        &self,
        lease: &Lease,
        tag: &str,
        error: String,
        scene: bool,
        stats: &mut WorkerStats,
    ) {
        stats.failed += 1;
        tracing::error!("{tag}: failed: {error}");
        let report = FailureReport { error, scene };
        if let Err(e) = self.client.fail(lease.lease_id, &report).await {
            tracing::warn!("{tag}: could not report the failure: {e}");
        }
    }

    /// After a transient failure before rendering: waits out the backoff (or a shutdown), and
    /// hands the lease back if shutting down. Otherwise asking for work again answers this same
    /// lease, so nothing is lost.
    async fn retry_later(
        &self,
        lease: &Lease,
        tag: &str,
        shutdown: &mut Shutdown,
        stats: &mut WorkerStats,
        backoff: &mut Backoff,
    ) {
        tokio::select! {
            _ = tokio::time::sleep(backoff.next_delay()) => {}
            _ = shutdown.wait() => {}
        }
        if shutdown.is_set() {
            self.hand_back(lease, tag, stats).await;
        }
    }

    async fn hand_back(&self, lease: &Lease, tag: &str, stats: &mut WorkerStats) {
        match self.client.hand_back(lease.lease_id).await {
            Ok(()) => {
                stats.handed_back += 1;
                tracing::info!("{tag}: handed back");
            }
            Err(e) => tracing::warn!("{tag}: could not hand back ({e}); its lease will lapse"),
        }
    }
}

/// Runs `job` on `pool` and answers with its result, or with a panic's message. The job is
/// queued on the pool itself rather than run by a blocking thread parked in `install`: no
/// thread is started or woken per tile besides the pool's own.
fn on_pool<T: Send + 'static>(
    pool: &rayon::ThreadPool,
    job: impl FnOnce() -> T + Send + 'static,
) -> impl std::future::Future<Output = Result<T, String>> {
    let (answer, answered) = tokio::sync::oneshot::channel();
    pool.spawn(move || {
        let _ = answer.send(std::panic::catch_unwind(std::panic::AssertUnwindSafe(job)));
    });
    async move {
        match answered.await {
            Ok(Ok(value)) => Ok(value),
            Ok(Err(payload)) => Err(panic_message(payload.as_ref())),
            Err(_) => Err("rendering was aborted: the render pool dropped the tile".into()),
        }
    }
}

fn panic_message(payload: &(dyn std::any::Any + Send)) -> String {
    let text = payload
        .downcast_ref::<&str>()
        .map(|s| s.to_string())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "unknown panic".into());
    format!("rendering panicked: {text}")
}

/// Exponential back-off with jitter, so a farm of workers does not retry in lock step.
pub struct Backoff {
    first: Duration,
    max: Duration,
    current: Duration,
    rng: u64,
}

impl Backoff {
    pub fn new(first: Duration, max: Duration) -> Self {
        let seed = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.as_nanos() as u64)
            .unwrap_or(1)
            ^ ((std::process::id() as u64) << 32);
        Self {
            first,
            max: max.max(first),
            current: first,
            rng: seed | 1,
        }
    }

    pub fn reset(&mut self) {
        self.current = self.first;
    }

    /// The next pause: the current step scaled by a random factor in [0.5, 1.0), after
    /// which the step doubles up to the maximum.
    pub fn next_delay(&mut self) -> Duration {
        // xorshift64: jitter needs no quality, only independence between workers.
        self.rng ^= self.rng << 13;
        self.rng ^= self.rng >> 7;
        self.rng ^= self.rng << 17;
        let factor = 0.5 + (self.rng >> 11) as f64 / (1u64 << 53) as f64 * 0.5;
        let delay = self.current.mul_f64(factor);
        self.current = (self.current * 2).min(self.max);
        delay
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn a_job_on_the_pool_answers_with_its_value_or_its_panic() {
        let pool = rayon::ThreadPoolBuilder::new()
            .num_threads(1)
            .build()
            .unwrap();
        let threads = on_pool(&pool, rayon::current_num_threads).await;
        assert_eq!(threads, Ok(1), "ran on the pool itself");
        let panicked = on_pool(&pool, || -> u32 { panic!("a broken tile") }).await;
        assert_eq!(
            panicked,
            Err("rendering panicked: a broken tile".to_string())
        );
        // The pool survives a panicking job.
        assert_eq!(on_pool(&pool, || 7).await, Ok(7));
    }

    #[test]
    fn backoff_doubles_up_to_its_cap_with_jitter() {
        let mut b = Backoff::new(Duration::from_millis(100), Duration::from_millis(400));
        let d: Vec<Duration> = (0..5).map(|_| b.next_delay()).collect();
        let steps = [100, 200, 400, 400, 400];
        for (delay, step) in d.iter().zip(steps) {
            let step = Duration::from_millis(step);
            assert!(*delay >= step / 2 && *delay < step, "{delay:?} vs {step:?}");
        }
        b.reset();
        assert!(b.next_delay() < Duration::from_millis(100));
    }

    #[tokio::test]
    async fn shutdown_fires_once_for_every_clone() {
        let (tx, shutdown) = Shutdown::new();
        let mut a = shutdown.clone();
        assert!(!a.is_set());
        tx.send(true).unwrap();
        a.wait().await;
        assert!(shutdown.is_set());
    }
}
