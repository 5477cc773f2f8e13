//! Coordinator throughput: lease + complete round trips per second over HTTP on loopback,
//! with hundreds of simulated workers returning blank tiles (no rendering).
//!
//!   cargo bench -p coordinator --bench lease_throughput -- [WORKERS] [TILE] [SECONDS]
//!
//! Defaults: 256 workers, 8x8 tiles, 5 seconds. The coordinator is the real one (state
//! machine, SQLite write-through, pixel files, axum), in this process with the workers.

use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use coordinator::clock::SystemClock;
use coordinator::config::FarmConfig;
use coordinator::farm::{Farm, NewJob};
use protocol::client::Client;
use protocol::{pixels_to_bytes, JobSpec, LeaseRequest};

fn main() {
    let args: Vec<String> = std::env::args()
        .skip(1)
        .filter(|a| !a.starts_with('-'))
        .collect();
    let workers: usize = args.first().and_then(|a| a.parse().ok()).unwrap_or(256);
    let tile: u32 = args.get(1).and_then(|a| a.parse().ok()).unwrap_or(8);
    let seconds: u64 = args.get(2).and_then(|a| a.parse().ok()).unwrap_or(5);
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .unwrap();
    runtime.block_on(run(workers, tile, Duration::from_secs(seconds)));
}

async fn run(workers: usize, tile: u32, duration: Duration) {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(dir.path(), FarmConfig::default(), Arc::new(SystemClock)).unwrap();
    // More tiles than a run finishes: 512x512 tiles, at most 8192x8192 pixels.
    let side = (tile * 512).min(8192);
    let mut spec = JobSpec::default();
    spec.render.width = side;
    spec.render.height = side;
    spec.tile_size = tile;
    let job = farm
        .submit(NewJob {
            name: "bench".into(),
            scene_file: "bench.scene".into(),
            scene_hash: "0".repeat(64),
            spec,
            assets: vec![],
        })
        .unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop_tx, stop_rx) = tokio::sync::oneshot::channel::<()>();
    let server = tokio::spawn(coordinator::server::serve(
        listener,
        farm.clone(),
        None,
        async move {
            let _ = stop_rx.await;
        },
    ));
    let client = Client::new(&url, None).unwrap();
    let blank = pixels_to_bytes(&vec![0.0; (tile * tile * 3) as usize]);
    let done = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let start = Instant::now();
    let mut tasks = Vec::new();
    for i in 0..workers {
        let (client, blank, done, stop) =
            (client.clone(), blank.clone(), done.clone(), stop.clone());
        tasks.push(tokio::spawn(async move {
            let identity = client.register(&format!("sim-{i}")).await.unwrap();
            let req = LeaseRequest {
                worker_id: identity.worker_id,
                wait_ms: 0,
            };
            while !stop.load(Ordering::Relaxed) {
                let Some(lease) = client.lease(&req).await.unwrap() else {
                    break;
                };
                client
                    .complete(lease.lease_id, blank.clone())
                    .await
                    .unwrap();
                done.fetch_add(1, Ordering::Relaxed);
            }
        }));
    }
    while start.elapsed() < duration && !tasks.iter().all(|t| t.is_finished()) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop.store(true, Ordering::Relaxed);
    for task in tasks {
        task.await.unwrap();
    }
    let elapsed = start.elapsed().as_secs_f64();
    let n = done.load(Ordering::Relaxed);
    let info = farm.job(job.id).unwrap();
    assert_eq!(
        info.tiles_done as u64, n,
        "every acknowledged tile is recorded"
    );
    println!(
        "{workers} simulated workers, {tile}x{tile} blank tiles: {n} lease+complete round trips \
         in {elapsed:.2}s = {:.0}/s",
        n as f64 / elapsed
    );
    let _ = stop_tx.send(());
    server.await.unwrap().unwrap();
}
