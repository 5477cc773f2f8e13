//! Counters kept with atomics on the hot path, rendered with the state's gauges in Prometheus
//! text format for `GET /metrics`.

use std::collections::BTreeMap;
use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

/// Upper bounds of the lease-latency histogram, in seconds.
const LEASE_BUCKETS: [f64; 10] = [0.0005, 0.001, 0.005, 0.01, 0.05, 0.1, 0.5, 1.0, 5.0, 30.0];

#[derive(Debug, Default)]
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
    lease_latency_buckets: [AtomicU64; LEASE_BUCKETS.len()],
    lease_latency_count: AtomicU64,
    lease_latency_sum_us: AtomicU64,
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

impl Metrics {
    /// Records how long a lease request took to be answered with a tile (long-poll wait
    /// included).
    pub fn observe_lease_latency(&self, latency: Duration) {
        let seconds = latency.as_secs_f64();
        for (bucket, bound) in self.lease_latency_buckets.iter().zip(LEASE_BUCKETS) {
            if seconds <= bound {
                bucket.fetch_add(1, Ordering::Relaxed);
            }
        }
        self.lease_latency_count.fetch_add(1, Ordering::Relaxed);
        self.lease_latency_sum_us
            .fetch_add(latency.as_micros() as u64, Ordering::Relaxed);
    }

    pub fn render(&self, g: &Gauges) -> String {
        let mut out = String::new();
        let mut metric = |name: &str, kind: &str, help: &str, samples: &[(String, f64)]| {
            let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}");
            for (labels, value) in samples {
                let _ = writeln!(out, "{name}{labels} {value}");
            }
        };
        let one = |v: u64| vec![(String::new(), v as f64)];
        let counter = |c: &AtomicU64| one(c.load(Ordering::Relaxed));
        let jobs: Vec<(String, f64)> = ["queued", "running", "done", "failed", "cancelled"]
            .iter()
            .map(|s| {
                let n = g.jobs_by_state.get(s).copied().unwrap_or(0);
                (format!("{{state=\"{s}\"}}"), n as f64)
            })
            .collect();
        metric("tessera_jobs", "gauge", "Jobs by state.", &jobs);
        let tiles = vec![
            ("{state=\"queued\"}".to_string(), g.tiles_queued as f64),
            ("{state=\"running\"}".to_string(), g.tiles_running as f64),
            ("{state=\"done\"}".to_string(), g.tiles_done as f64),
        ];
        metric("tessera_tiles", "gauge", "Tiles by state.", &tiles);
        metric("tessera_leases", "gauge", "Live leases.", &one(g.leases));
        metric(
            "tessera_workers_seen",
            "gauge",
            "Distinct workers seen since start-up.",
            &one(g.workers_seen),
        );
        metric(
            "tessera_workers_active",
            "gauge",
            "Workers seen in the last minute.",
            &one(g.workers_active),
        );
        let counters: [(&str, &str, &AtomicU64); 9] = [
            (
                "tessera_jobs_submitted_total",
                "Jobs accepted.",
                &self.jobs_submitted,
            ),
            (
                "tessera_submissions_rejected_total",
                "Submissions refused with a 4xx.",
                &self.submissions_rejected,
            ),
            (
                "tessera_leases_granted_total",
                "Leases granted.",
                &self.leases_granted,
            ),
            (
                "tessera_lease_polls_empty_total",
                "Lease requests answered 204.",
                &self.lease_polls_empty,
            ),
            (
                "tessera_tiles_completed_total",
                "Tiles finished.",
                &self.tiles_completed,
            ),
            (
                "tessera_stale_requests_total",
                "Requests refused with 409 (stale lease).",
                &self.stale_requests,
            ),
            (
                "tessera_leases_expired_total",
                "Leases that lapsed without a heartbeat.",
                &self.leases_expired,
            ),
            (
                "tessera_tile_failures_total",
                "Tile failures reported.",
                &self.tile_failures,
            ),
            (
                "tessera_tiles_handed_back_total",
                "Tiles handed back.",
                &self.handed_back,
            ),
        ];
        for (name, help, c) in counters {
            metric(name, "counter", help, &counter(c));
        }
        let mut hist: Vec<(String, f64)> = self
            .lease_latency_buckets
            .iter()
            .zip(LEASE_BUCKETS)
            .map(|(b, bound)| {
                (
                    format!("_bucket{{le=\"{bound}\"}}"),
                    b.load(Ordering::Relaxed) as f64,
                )
            })
            .collect();
        let count = self.lease_latency_count.load(Ordering::Relaxed) as f64;
        hist.push(("_bucket{le=\"+Inf\"}".into(), count));
        hist.push((
            "_sum".into(),
            self.lease_latency_sum_us.load(Ordering::Relaxed) as f64 / 1e6,
        ));
        hist.push(("_count".into(), count));
        metric(
            "tessera_lease_latency_seconds",
            "histogram",
            "Time from a lease request to its tile (long-poll wait included).",
            &hist,
        );
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn renders_prometheus_text() {
        let m = Metrics::default();
        m.leases_granted.fetch_add(3, Ordering::Relaxed);
        m.observe_lease_latency(Duration::from_millis(2));
        let mut g = Gauges::default();
        g.jobs_by_state.insert("running", 2);
        let text = m.render(&g);
        assert!(text.contains("tessera_leases_granted_total 3\n"), "{text}");
        assert!(
            text.contains("tessera_jobs{state=\"running\"} 2\n"),
            "{text}"
        );
        assert!(text.contains("tessera_lease_latency_seconds_bucket{le=\"0.001\"} 0\n"));
        assert!(text.contains("tessera_lease_latency_seconds_bucket{le=\"0.005\"} 1\n"));
        assert!(text.contains("tessera_lease_latency_seconds_count 1\n"));
        assert!(text.contains("# TYPE tessera_tiles gauge\n"));
    }
}
