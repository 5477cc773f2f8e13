//! Load generator: N simulated workers drive the coordinator's real HTTP API (register, lease,
//! complete with a valid tile of the right size; nothing is rendered).
//!
//! Throughput (lease + complete round trips per second, and the CPU each side spent):
//!
//!   cargo run --release -p coordinator --example loadgen -- --workers 256 --tile-size 8 --seconds 10
//!
//! Scheduling efficiency (workers that take a fixed time per tile, 1 to 256 of them, against
//! the ideal `ceil(tiles / N) * tile time`):
//!
//!   cargo run --release -p coordinator --example loadgen -- --efficiency --tile-ms 200 --waves 4
//!
//! By default the coordinator runs in this process, on its own runtime whose threads are named
//! `coordinator`, with the same farm and server as `coordinator serve` and a data dir in a
//! temporary folder; its CPU is the process's minus the load generator's threads (named
//! `loadgen`). `--server URL --pid PID` drives a separate `coordinator serve` instead and reads
//! that process's CPU from /proc.

use std::path::Path;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

use coordinator::clock::SystemClock;
use coordinator::config::FarmConfig;
use coordinator::farm::Farm;
use protocol::client::{Client, Submission};
use protocol::{pixels_to_bytes, JobSpec, JobState, LeaseRequest};

/// A still scene with one sphere: loads, and nothing here renders it.
const SCENE: &str = r#"<scene>
    <camera><fov v="0.785"/><near_clip v="0.1"/><far_clip v="100"/>
        <position x="0" y="0" z="5"/><orientation a="0" x="0" y="1" z="0"/></camera>
    <background_color r="0" g="0" b="0"/><refractive_index v="1"/>
    <material name="m"><ambient r="1" g="1" b="1"/><diffuse r="1" g="1" b="1"/>
        <specular r="0" g="0" b="0"/><shininess v="1"/></material>
    <sphere material="m"><position x="0" y="0" z="0"/><radius v="1"/></sphere>
</scene>"#;

struct Args {
    workers: usize,
    tile_size: u32,
    seconds: f64,
    server: Option<String>,
    pid: Option<u32>,
    efficiency: bool,
    tile_ms: u64,
    waves: u32,
    max_workers: usize,
}

fn usage() -> ! {
    eprintln!(
        "usage: loadgen [--workers N] [--tile-size PX] [--seconds S] [--server URL [--pid PID]]\n\
         \x20      loadgen --efficiency [--tile-ms MS] [--waves W] [--max-workers N] [--server URL]"
    );
    std::process::exit(2)
}

fn parse_args() -> Args {
    let mut args = Args {
        workers: 256,
        tile_size: 8,
        seconds: 10.0,
        server: None,
        pid: None,
        efficiency: false,
        tile_ms: 200,
        waves: 4,
        max_workers: 256,
    };
    let mut it = std::env::args().skip(1);
    while let Some(flag) = it.next() {
        if flag == "--efficiency" {
            args.efficiency = true;
            continue;
        }
        if flag == "--bench" {
            // Passed by `cargo bench`; nothing to do.
            continue;
        }
        let Some(value) = it.next() else { usage() };
        let ok = match flag.as_str() {
            "--workers" => value.parse().map(|v| args.workers = v).is_ok(),
            "--tile-size" => value.parse().map(|v| args.tile_size = v).is_ok(),
            "--seconds" => value.parse().map(|v| args.seconds = v).is_ok(),
            "--server" => {
                args.server = Some(value);
                true
            }
            "--pid" => value.parse().map(|v| args.pid = Some(v)).is_ok(),
            "--tile-ms" => value.parse().map(|v| args.tile_ms = v).is_ok(),
            "--waves" => value.parse().map(|v| args.waves = v).is_ok(),
            "--max-workers" => value.parse().map(|v| args.max_workers = v).is_ok(),
            _ => false,
        };
        if !ok {
            usage();
        }
    }
    if args.workers == 0 || args.tile_size == 0 || args.waves == 0 || args.max_workers == 0 {
        usage();
    }
    args
}

/// A coordinator in this process, on its own runtime, stopped on drop.
struct InProcess {
    url: String,
    stop: Option<tokio::sync::oneshot::Sender<()>>,
    runtime: Option<tokio::runtime::Runtime>,
    server: Option<tokio::task::JoinHandle<std::io::Result<()>>>,
    _dir: tempfile::TempDir,
}

impl InProcess {
    fn start() -> InProcess {
        let dir = tempfile::tempdir().expect("a temporary data dir");
        // The same runtime shape as `coordinator serve` (two async threads).
        let runtime = tokio::runtime::Builder::new_multi_thread()
            .worker_threads(2)
            .thread_name("coordinator")
            .enable_all()
            .build()
            .expect("the coordinator's runtime");
        coordinator::server::raise_descriptor_limit();
        let farm = Farm::open(dir.path(), FarmConfig::default(), Arc::new(SystemClock))
            .expect("a farm in the temporary dir");
        let listener = runtime
            .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
            .expect("a loopback port");
        let url = format!("http://{}", listener.local_addr().unwrap());
        let (stop, stop_rx) = tokio::sync::oneshot::channel::<()>();
        let server = runtime.spawn(coordinator::server::serve(
            listener,
            farm,
            None,
            async move {
                let _ = stop_rx.await;
            },
        ));
        InProcess {
            url,
            stop: Some(stop),
            runtime: Some(runtime),
            server: Some(server),
            _dir: dir,
        }
    }
}

impl Drop for InProcess {
    fn drop(&mut self) {
        if let (Some(stop), Some(runtime), Some(server)) =
            (self.stop.take(), self.runtime.take(), self.server.take())
        {
            let _ = stop.send(());
            let _ = runtime.block_on(server);
            runtime.shutdown_timeout(Duration::from_secs(5));
        }
    }
}

/// CPU seconds (user + system) from a /proc `stat` line: fields 14 and 15, counted after the
/// command name, which may hold spaces but ends at the last ')'.
fn stat_cpu(stat: &str) -> Option<(String, f64)> {
    let open = stat.find('(')?;
    let close = stat.rfind(')')?;
    let name = stat[open + 1..close].to_string();
    let fields: Vec<&str> = stat[close + 1..].split_whitespace().collect();
    let utime: f64 = fields.get(11)?.parse().ok()?;
    let stime: f64 = fields.get(12)?.parse().ok()?;
    // SAFETY: sysconf only reads a configuration value.
    let ticks = unsafe { libc::sysconf(libc::_SC_CLK_TCK) } as f64;
    Some((name, (utime + stime) / ticks))
}

fn process_cpu(pid: &str) -> f64 {
    std::fs::read_to_string(format!("/proc/{pid}/stat"))
        .ok()
        .and_then(|s| stat_cpu(&s))
        .map_or(0.0, |(_, cpu)| cpu)
}

/// CPU seconds of this process's live threads whose name starts with `prefix`.
fn threads_cpu(prefix: &str) -> f64 {
    let Ok(tasks) = std::fs::read_dir("/proc/self/task") else {
        return 0.0;
    };
    tasks
        .flatten()
        .filter_map(|t| std::fs::read_to_string(t.path().join("stat")).ok())
        .filter_map(|s| stat_cpu(&s))
        .filter(|(name, _)| name.starts_with(prefix))
        .map(|(_, cpu)| cpu)
        .sum()
}

/// CPU seconds spent so far by (the coordinator, the load generator).
fn cpu_split(external_pid: Option<u32>) -> (Option<f64>, f64) {
    let load = threads_cpu("loadgen");
    match external_pid {
        Some(pid) => (Some(process_cpu(&pid.to_string())), load),
        None if Path::new("/proc/self/stat").exists() => (Some(process_cpu("self") - load), load),
        None => (None, load),
    }
}

fn submission(side_x: u32, side_y: u32, tile: u32) -> Submission {
    let mut spec = JobSpec::default();
    spec.render.width = side_x;
    spec.render.height = side_y;
    spec.tile_size = tile;
    Submission {
        spec,
        scene_file: "loadgen.scene".into(),
        scene: SCENE.as_bytes().to_vec(),
        assets: vec![],
    }
}

async fn tiles_done(client: &Client) -> u64 {
    let jobs = client.jobs().await.expect("the job list");
    jobs.iter().map(|j| j.tiles_done as u64).sum()
}

async fn register_all(url: &str, n: usize) -> Vec<(Client, LeaseRequest)> {
    let mut out = Vec::with_capacity(n);
    for i in 0..n {
        // One client (one connection pool) per simulated worker, as separate workers have.
        let client = Client::new(url, None).expect("a client");
        let identity = client
            .register(&format!("loadgen-{i}"))
            .await
            .expect("registration");
        out.push((
            client,
            LeaseRequest {
                worker_id: identity.worker_id,
                wait_ms: 0,
            },
        ));
    }
    out
}

async fn throughput(url: String, args: &Args) {
    let tile = args.tile_size;
    // More tiles than a run finishes at 90,000 round trips/s, within the default limits
    // (960 x 960 tiles at most).
    let side = (tile * 960).min(16_384);
    let client = Client::new(&url, None).unwrap();
    // Against a long-running server, tiles may land on an older job: count them all.
    let done_before = tiles_done(&client).await;
    client
        .submit(&submission(side, side, tile))
        .await
        .expect("the job is accepted");
    let workers = register_all(&url, args.workers).await;
    let blank = pixels_to_bytes(&vec![0.25; (tile * tile * 3) as usize]);
    let done = Arc::new(AtomicU64::new(0));
    let stop = Arc::new(AtomicBool::new(false));
    let (cpu0, load0) = cpu_split(args.pid);
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (client, req) in workers {
        let (blank, done, stop) = (blank.clone(), done.clone(), stop.clone());
        tasks.push(tokio::spawn(async move {
            // An error (a timeout on a starved machine, a refusal) ends this worker and is
            // reported; the others go on.
            let mut error = None;
            while !stop.load(Ordering::Relaxed) {
                let lease = match client.lease(&req).await {
                    Ok(Some(lease)) => lease,
                    Ok(None) => break,
                    Err(e) => {
                        error = Some(format!("lease: {e}"));
                        break;
                    }
                };
                // Every tile of this job is tile x tile pixels (the side is a multiple).
                if let Err(e) = client.complete(lease.lease_id, blank.clone()).await {
                    error = Some(format!("complete: {e}"));
                    break;
                }
                done.fetch_add(1, Ordering::Relaxed);
            }
            error
        }));
    }
    let duration = Duration::from_secs_f64(args.seconds);
    while start.elapsed() < duration && !tasks.iter().all(|t| t.is_finished()) {
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    stop.store(true, Ordering::Relaxed);
    let n_at_stop = done.load(Ordering::Relaxed);
    let elapsed = start.elapsed().as_secs_f64();
    let (cpu1, load1) = cpu_split(args.pid);
    let mut errors = Vec::new();
    for task in tasks {
        errors.extend(task.await.expect("a simulated worker"));
    }
    if let Some(first) = errors.first() {
        eprintln!(
            "{} simulated workers stopped on an error; the first: {first}",
            errors.len()
        );
    }
    let n = done.load(Ordering::Relaxed);
    let recorded = tiles_done(&client).await - done_before;
    // A completion that timed out on the client may still have been stored.
    if errors.is_empty() {
        assert_eq!(recorded, n, "every acknowledged tile is recorded");
    } else {
        assert!(recorded >= n, "every acknowledged tile is recorded");
    }
    let rate = n_at_stop as f64 / elapsed;
    println!(
        "{} simulated workers, {tile}x{tile} tiles: {n_at_stop} lease+complete round trips in \
         {elapsed:.2} s = {rate:.0}/s",
        args.workers
    );
    let load = load1 - load0;
    match cpu0.zip(cpu1) {
        Some((a, b)) => {
            let coord = b - a;
            println!(
                "coordinator CPU {coord:.2} s = {:.2} cores, {:.0} µs per round trip; \
                 load generator CPU {load:.2} s = {:.2} cores (machine: {} cores)",
                coord / elapsed,
                coord * 1e6 / n_at_stop.max(1) as f64,
                load / elapsed,
                std::thread::available_parallelism().map_or(0, |n| n.get())
            );
        }
        None => println!(
            "coordinator CPU unknown (pass --pid); load generator CPU {load:.2} s = {:.2} cores",
            load / elapsed
        ),
    }
}

/// One row of the scheduling table: `n` workers that each take `tile_ms` per tile finish a
/// job of `waves * n` tiles; returns (tiles, measured seconds, ideal seconds).
async fn efficiency_row(url: &str, n: usize, tile_ms: u64, waves: u32) -> (u32, f64, f64) {
    let workers = register_all(url, n).await;
    // One row of `n` tiles per wave: n tiles of 8x8 across, `waves` rows down.
    let tile = 8;
    let tiles = n as u32 * waves;
    let sub = submission(tile * n as u32, tile * waves, tile);
    let finished: Arc<Mutex<Option<Instant>>> = Arc::new(Mutex::new(None));
    let blank = pixels_to_bytes(&vec![0.25; (tile * tile * 3) as usize]);
    let client = Client::new(url, None).unwrap();
    let job = client.submit(&sub).await.expect("the job is accepted");
    // From the job's acceptance (its scene is loaded and checked by then) to its last tile.
    let start = Instant::now();
    let mut tasks = Vec::new();
    for (client, mut req) in workers {
        let (blank, finished) = (blank.clone(), finished.clone());
        // Idle workers long-poll, as real ones do.
        req.wait_ms = 2_000;
        tasks.push(tokio::spawn(async move {
            loop {
                let Some(lease) = client.lease(&req).await.expect("a lease answer") else {
                    break;
                };
                tokio::time::sleep(Duration::from_millis(tile_ms)).await;
                match client.complete(lease.lease_id, blank.clone()).await {
                    Ok(done) if done.tiles_done == done.tiles_total => {
                        finished.lock().unwrap().get_or_insert_with(Instant::now);
                        break;
                    }
                    Ok(_) => {}
                    Err(e) => panic!("completion refused: {e}"),
                }
            }
        }));
    }
    while finished.lock().unwrap().is_none() {
        tokio::time::sleep(Duration::from_millis(1)).await;
    }
    let end = finished.lock().unwrap().unwrap();
    // The others see an empty queue and stop after their poll.
    for task in tasks {
        task.abort();
    }
    while client.job(job.id).await.unwrap().state != JobState::Done {
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    let ideal = tiles.div_ceil(n as u32) as f64 * tile_ms as f64 / 1000.0;
    (tiles, (end - start).as_secs_f64(), ideal)
}

async fn efficiency(url: String, args: &Args) {
    println!(
        "| workers | tiles | ideal (s) | measured (s) | overhead |\n|---:|---:|---:|---:|---:|"
    );
    let mut n = 1;
    while n <= args.max_workers {
        let (tiles, measured, ideal) = efficiency_row(&url, n, args.tile_ms, args.waves).await;
        println!(
            "| {n} | {tiles} | {ideal:.3} | {measured:.3} | {:+.1}% |",
            (measured / ideal - 1.0) * 100.0
        );
        n *= 2;
    }
}

fn main() {
    let args = parse_args();
    let local = match &args.server {
        Some(_) => None,
        None => Some(InProcess::start()),
    };
    let url = args
        .server
        .clone()
        .or_else(|| local.as_ref().map(|l| l.url.clone()))
        .expect("a server");
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .thread_name("loadgen")
        .enable_all()
        .build()
        .expect("the load generator's runtime");
    runtime.block_on(async {
        if args.efficiency {
            efficiency(url, &args).await;
        } else {
            throughput(url, &args).await;
        }
    });
    drop(runtime);
    drop(local);
}
