//! `GET /metrics`: counters kept with atomics on the hot path, plus gauges read from the farm's
//! state and from `/proc/self` when scraped, encoded by `prometheus-client` as OpenMetrics text
//! (which Prometheus, and KEDA's `metrics-api` scaler, read as is).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;
use std::time::Duration;

use prometheus_client::encoding::text::encode;
use prometheus_client::metrics::counter::{ConstCounter, Counter};
use prometheus_client::metrics::family::Family;
use prometheus_client::metrics::gauge::{ConstGauge, Gauge};
use prometheus_client::metrics::histogram::Histogram;
use prometheus_client::registry::{Registry, Unit};
use protocol::{WorkerInfo, WorkerState};

/// The `Content-Type` of [`Metrics::render`]'s text.
pub const CONTENT_TYPE: &str = "application/openmetrics-text; version=1.0.0; charset=utf-8";

/// Upper bounds of the lease-latency histogram, in seconds.
const LEASE_BUCKETS: [f64; 10] = [0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 30.0];

#[derive(Debug)]
pub struct Metrics {
    pub leases_granted: AtomicU64,
    pub lease_polls_empty: AtomicU64,
    pub tiles_completed: AtomicU64,
    pub stale_requests: AtomicU64,
    pub leases_expired: AtomicU64,
    pub tile_failures: AtomicU64,
    pub handed_back: AtomicU64,
    pub jobs_submitted: AtomicU64,
    pub submissions_rejected: AtomicU64,
    /// Tile failures by worker id; pruned to the workers still listed at each scrape.
    worker_failures: Mutex<HashMap<u64, u64>>,
    lease_latency: Histogram,
}

impl Default for Metrics {
    fn default() -> Self {
        Self {
            leases_granted: AtomicU64::new(0),
            lease_polls_empty: AtomicU64::new(0),
            tiles_completed: AtomicU64::new(0),
            stale_requests: AtomicU64::new(0),
            leases_expired: AtomicU64::new(0),
            tile_failures: AtomicU64::new(0),
            handed_back: AtomicU64::new(0),
            jobs_submitted: AtomicU64::new(0),
            submissions_rejected: AtomicU64::new(0),
            worker_failures: Mutex::default(),
            lease_latency: Histogram::new(LEASE_BUCKETS),
        }
    }
}

/// Values read from the farm's state when the metrics are scraped.
#[derive(Debug, Default)]
pub struct Gauges<'a> {
    pub jobs_by_state: BTreeMap<&'a str, u64>,
    pub tiles_queued: u64,
    pub tiles_running: u64,
    pub tiles_done: u64,
    pub leases: u64,
    pub workers_seen: u64,
    pub workers_active: u64,
}

/// The labels of a per-worker series: the coordinator-issued id (unique) and the name (a label
/// two workers may share).
type WorkerLabels = Vec<(&'static str, String)>;

fn worker_labels(w: &WorkerInfo) -> WorkerLabels {
    vec![("worker_id", w.id.to_string()), ("worker", w.name.clone())]
}

fn gauge(v: u64) -> ConstGauge {
    ConstGauge::new(i64::try_from(v).unwrap_or(i64::MAX))
}

fn counter(c: &AtomicU64) -> ConstCounter {
    ConstCounter::new(c.load(Ordering::Relaxed))
}

impl Metrics {
    /// Records how long a lease request took to be answered with a tile (long-poll wait
    /// included).
    pub fn observe_lease_latency(&self, latency: Duration) {
        self.lease_latency.observe(latency.as_secs_f64());
    }

    /// Counts a tile failure, overall and for the worker that reported it.
    pub fn tile_failed(&self, worker_id: u64) {
        self.tile_failures.fetch_add(1, Ordering::Relaxed);
        let mut by_worker = self
            .worker_failures
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        *by_worker.entry(worker_id).or_default() += 1;
    }

    /// The OpenMetrics text of every series (see `docs/api.md`, "GET /metrics").
    pub fn render(&self, g: &Gauges, workers: &[WorkerInfo]) -> String {
        let mut root = Registry::default();
        // The farm's series under `tessera_`, the process's under the standard `process_`.
        let r = root.sub_registry_with_prefix("tessera");
        let jobs = Family::<Vec<(&'static str, &'static str)>, Gauge>::default();
        for s in ["queued", "running", "done", "failed", "cancelled"] {
            let n = g.jobs_by_state.get(s).copied().unwrap_or(0);
            jobs.get_or_create(&vec![("state", s)])
                .set(i64::try_from(n).unwrap_or(i64::MAX));
        }
        r.register("jobs", "Jobs by state", jobs);
        let tiles = Family::<Vec<(&'static str, &'static str)>, Gauge>::default();
        for (s, n) in [
            ("queued", g.tiles_queued),
            ("running", g.tiles_running),
            ("done", g.tiles_done),
        ] {
            tiles
                .get_or_create(&vec![("state", s)])
                .set(i64::try_from(n).unwrap_or(i64::MAX));
        }
        r.register(
            "tiles",
            "Tiles by state (queued: waiting for a worker, what autoscalers read)",
            tiles,
        );
        r.register("leases", "Live leases", gauge(g.leases));
        r.register(
            "workers_seen",
            "Distinct workers seen since start-up",
            gauge(g.workers_seen),
        );
        r.register(
            "workers_active",
            "Workers seen in the last minute",
            gauge(g.workers_active),
        );
        let counters: [(&str, &str, &AtomicU64); 9] = [
            ("jobs_submitted", "Jobs accepted", &self.jobs_submitted),
            (
                "submissions_rejected",
                "Submissions refused with a 4xx",
                &self.submissions_rejected,
            ),
            ("leases_granted", "Leases granted", &self.leases_granted),
            (
                "lease_polls_empty",
                "Lease requests answered 204",
                &self.lease_polls_empty,
            ),
            ("tiles_completed", "Tiles finished", &self.tiles_completed),
            (
                "stale_requests",
                "Requests refused with 409 (stale lease)",
                &self.stale_requests,
            ),
            (
                "leases_expired",
                "Leases that lapsed without a heartbeat",
                &self.leases_expired,
            ),
            (
                "tile_failures",
                "Tile failures reported",
                &self.tile_failures,
            ),
            ("tiles_handed_back", "Tiles handed back", &self.handed_back),
        ];
        for (name, help, c) in counters {
            r.register(name, help, counter(c));
        }
        r.register_with_unit(
            "lease_latency",
            "Time from a lease request to its tile (long-poll wait included)",
            Unit::Seconds,
            self.lease_latency.clone(),
        );
        self.register_workers(r, workers);
        register_process(&mut root);
        let mut out = String::new();
        encode(&mut out, &root).expect("writing to a String cannot fail");
        out
    }

    /// Per-worker series, one per worker the coordinator lists (bounded by `--max-workers`).
    fn register_workers(&self, r: &mut Registry, workers: &[WorkerInfo]) {
        let failures = {
            let mut by_worker = self
                .worker_failures
                .lock()
                .unwrap_or_else(|e| e.into_inner());
            // Forgotten workers' counts go, so the map stays as small as the registry.
            let listed: HashSet<u64> = workers.iter().map(|w| w.id).collect();
            by_worker.retain(|id, _| listed.contains(id));
            by_worker.clone()
        };
        // The registry is built per scrape, so counters start from the values kept elsewhere.
        let done = Family::<WorkerLabels, Counter>::default();
        let failed = Family::<WorkerLabels, Counter>::default();
        let seen = Family::<WorkerLabels, Gauge<f64, AtomicU64>>::default();
        let busy = Family::<WorkerLabels, Gauge>::default();
        for w in workers {
            let labels = worker_labels(w);
            done.get_or_create(&labels).inc_by(w.tiles_done);
            failed
                .get_or_create(&labels)
                .inc_by(failures.get(&w.id).copied().unwrap_or(0));
            seen.get_or_create(&labels)
                .set(w.last_seen_ms as f64 / 1000.0);
            busy.get_or_create(&labels)
                .set(i64::from(w.state == WorkerState::Rendering));
        }
        r.register(
            "worker_tiles_completed",
            "Tiles a worker finished (first result) since the coordinator started",
            done,
        );
        r.register(
            "worker_tile_failures",
            "Tile failures a worker reported since the coordinator started",
            failed,
        );
        r.register_with_unit(
            "worker_last_seen",
            "Unix time of a worker's last lease request or heartbeat",
            Unit::Seconds,
            seen,
        );
        r.register(
            "worker_busy",
            "1 while a worker holds a lease, else 0",
            busy,
        );
    }
}

/// The standard process series (`process_cpu_seconds_total`, `process_resident_memory_bytes`,
/// `process_open_fds`, `process_max_fds`, `process_start_time_seconds`), read from `/proc/self`
/// where there is one; elsewhere they are left out.
fn register_process(r: &mut Registry) {
    let Some(p) = ProcessStats::read() else {
        return;
    };
    let sub = r.sub_registry_with_prefix("process");
    // Registered without a unit: the names are the standard ones, units spelled in them.
    sub.register(
        "cpu_seconds",
        "User and system CPU time spent, in seconds",
        ConstCounter::new(p.cpu_seconds),
    );
    sub.register(
        "resident_memory_bytes",
        "Resident memory size in bytes",
        gauge(p.resident_bytes),
    );
    sub.register(
        "virtual_memory_bytes",
        "Virtual memory size in bytes",
        gauge(p.virtual_bytes),
    );
    sub.register("open_fds", "Open file descriptors", gauge(p.open_fds));
    if let Some(max) = crate::server::descriptor_limit() {
        sub.register("max_fds", "The soft descriptor limit", gauge(max));
    }
    sub.register(
        "start_time_seconds",
        "Start time of the process since the Unix epoch, in seconds",
        ConstGauge::new(p.start_time_seconds),
    );
}

/// What `/proc/self` says about this process.
#[derive(Debug, PartialEq)]
struct ProcessStats {
    cpu_seconds: f64,
    resident_bytes: u64,
    virtual_bytes: u64,
    open_fds: u64,
    start_time_seconds: f64,
}

impl ProcessStats {
    fn read() -> Option<ProcessStats> {
        let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
        let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
        let boot = std::fs::read_to_string("/proc/stat").ok()?;
        let open_fds = std::fs::read_dir("/proc/self/fd").ok()?.count() as u64;
        // SAFETY: sysconf only reads a configuration value.
        let (ticks, page) = unsafe {
            (
                libc::sysconf(libc::_SC_CLK_TCK),
                libc::sysconf(libc::_SC_PAGESIZE),
            )
        };
        if ticks <= 0 || page <= 0 {
            return None;
        }
        Self::parse(&stat, &statm, &boot, ticks as u64, page as u64, open_fds)
    }

    /// `stat`: /proc/self/stat; `statm`: /proc/self/statm; `boot`: /proc/stat (for `btime`).
    fn parse(
        stat: &str,
        statm: &str,
        boot: &str,
        ticks_per_second: u64,
        page_bytes: u64,
        open_fds: u64,
    ) -> Option<ProcessStats> {
        // The command name (field 2) is in parentheses and may hold spaces: count fields from
        // the last ')'. Field 3 (state) is then the first.
        let rest = &stat[stat.rfind(')')? + 1..];
        let fields: Vec<&str> = rest.split_whitespace().collect();
        let field = |n: usize| -> Option<u64> { fields.get(n - 3)?.parse().ok() };
        let (utime, stime, start_ticks) = (field(14)?, field(15)?, field(22)?);
        let mut pages = statm.split_whitespace().map(|v| v.parse::<u64>().ok());
        let (size, resident) = (pages.next()??, pages.next()??);
        let btime: u64 = boot
            .lines()
            .find_map(|l| l.strip_prefix("btime "))?
            .trim()
            .parse()
            .ok()?;
        let hz = ticks_per_second as f64;
        Some(ProcessStats {
            cpu_seconds: (utime + stime) as f64 / hz,
            resident_bytes: resident * page_bytes,
            virtual_bytes: size * page_bytes,
            open_fds,
            start_time_seconds: btime as f64 + start_ticks as f64 / hz,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(text: &str) -> prometheus_parse::Scrape {
        prometheus_parse::Scrape::parse(text.lines().map(|l| Ok(l.to_string())))
            .expect("the text parses")
    }

    fn value(scrape: &prometheus_parse::Scrape, name: &str, labels: &[(&str, &str)]) -> f64 {
        let sample = scrape
            .samples
            .iter()
            .find(|s| s.metric == name && labels.iter().all(|(k, v)| s.labels.get(k) == Some(*v)))
            .unwrap_or_else(|| panic!("no {name} {labels:?}"));
        match sample.value {
            prometheus_parse::Value::Counter(v)
            | prometheus_parse::Value::Gauge(v)
            | prometheus_parse::Value::Untyped(v) => v,
            ref other => panic!("{name}: {other:?}"),
        }
    }

    #[test]
    fn renders_text_a_prometheus_parser_reads() {
        let m = Metrics::default();
        m.leases_granted.fetch_add(3, Ordering::Relaxed);
        m.observe_lease_latency(Duration::from_millis(2));
        m.tile_failed(7);
        m.tile_failed(7);
        m.tile_failed(99); // a worker no longer listed: pruned
        let mut g = Gauges::default();
        g.jobs_by_state.insert("running", 2);
        g.tiles_queued = 12;
        let workers = [WorkerInfo {
            id: 7,
            name: "render-01".into(),
            address: None,
            state: WorkerState::Rendering,
            lease: None,
            tiles_done: 5,
            last_seen_ms: 1_700_000_000_500,
        }];
        let text = m.render(&g, &workers);
        assert!(text.ends_with("# EOF\n"), "{text}");
        assert!(text.contains("# TYPE tessera_tiles gauge\n"), "{text}");
        // The exact lines the KEDA trigger and the farm tests read.
        assert!(
            text.contains("tessera_tiles{state=\"queued\"} 12\n"),
            "{text}"
        );
        assert!(text.contains("tessera_leases_granted_total 3\n"), "{text}");
        // Every line is a comment or a sample (the parser skips what it cannot read).
        for line in text.lines().filter(|l| !l.starts_with('#')) {
            assert!(
                matches!(
                    prometheus_parse::LineInfo::parse(line),
                    prometheus_parse::LineInfo::Sample { .. }
                ),
                "{line}"
            );
        }
        let s = parse(&text);
        assert_eq!(value(&s, "tessera_jobs", &[("state", "running")]), 2.0);
        assert_eq!(value(&s, "tessera_jobs", &[("state", "done")]), 0.0);
        assert_eq!(value(&s, "tessera_tile_failures_total", &[]), 3.0);
        let w = [("worker_id", "7"), ("worker", "render-01")];
        assert_eq!(value(&s, "tessera_worker_tiles_completed_total", &w), 5.0);
        assert_eq!(value(&s, "tessera_worker_tile_failures_total", &w), 2.0);
        assert_eq!(value(&s, "tessera_worker_busy", &w), 1.0);
        assert_eq!(
            value(&s, "tessera_worker_last_seen_seconds", &w),
            1_700_000_000.5
        );
        assert!(!text.contains("worker_id=\"99\""), "{text}");
        assert_eq!(m.worker_failures.lock().unwrap().len(), 1);
        let bucket = |le: &str| {
            s.samples
                .iter()
                .find(|x| x.metric == "tessera_lease_latency_seconds")
                .map(|x| match &x.value {
                    prometheus_parse::Value::Histogram(h) => h
                        .iter()
                        .find(|b| (b.less_than - le.parse::<f64>().unwrap()).abs() < 1e-12)
                        .map(|b| b.count)
                        .unwrap(),
                    other => panic!("{other:?}"),
                })
                .unwrap()
        };
        assert_eq!(bucket("0.001"), 0.0);
        assert_eq!(bucket("0.005"), 1.0);
        if cfg!(target_os = "linux") {
            assert!(value(&s, "process_resident_memory_bytes", &[]) > 0.0);
            assert!(value(&s, "process_open_fds", &[]) >= 1.0);
            assert!(value(&s, "process_start_time_seconds", &[]) > 1.5e9);
            assert!(value(&s, "process_cpu_seconds_total", &[]) >= 0.0);
        }
    }

    #[test]
    fn process_stats_are_read_from_proc_text() {
        // A command name with spaces and parentheses, as the kernel writes it.
        let stat = "4242 (tessera (co) rd) S 1 4242 4242 0 -1 4194560 1 0 0 0 250 150 0 0 20 0 \
                    9 0 5000 123456789 300 18446744073709551615";
        let statm = "30000 300 100 1 0 200 0\n";
        let boot = "cpu  1 2 3\nbtime 1700000000\nprocesses 9\n";
        let p = ProcessStats::parse(stat, statm, boot, 100, 4096, 12).unwrap();
        assert_eq!(
            p,
            ProcessStats {
                cpu_seconds: 4.0,
                resident_bytes: 300 * 4096,
                virtual_bytes: 30000 * 4096,
                open_fds: 12,
                start_time_seconds: 1_700_000_050.0,
            }
        );
        assert!(ProcessStats::parse("garbage", statm, boot, 100, 4096, 1).is_none());
        assert!(ProcessStats::parse(stat, statm, "no btime", 100, 4096, 1).is_none());
    }
}
