//! Starting the farm's real binaries as child processes: a coordinator on port 0 (its address
//! read from its first stdout line) and workers, each logging to a file the test can read.

use std::io::{BufRead, BufReader};
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::sync::OnceLock;
use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::{JobInfo, JobSpec};

pub fn workspace() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .parent()
        .expect("tests/ sits in the workspace")
        .to_path_buf()
}

/// `shared/` beside the project (CI clones the repository with it there).
pub fn shared() -> PathBuf {
    let dir = workspace().join("..").join("shared");
    dir.canonicalize().unwrap_or_else(|e| {
        panic!(
            "{} is missing ({e}): the course scenes live there",
            dir.display()
        )
    })
}

/// One of Tessera's own scenes in `scenes/`.
pub fn own_scene(name: &str) -> PathBuf {
    workspace().join("scenes").join(name)
}

pub fn course_scene(name: &str) -> PathBuf {
    shared().join("scenes").join("course").join(name)
}

pub struct Bins {
    pub coordinator: PathBuf,
    pub worker: PathBuf,
    pub tracer: PathBuf,
}

/// The binaries of the coordinator, the worker and the tracer that cargo built for this test
/// run: `cargo test --workspace` builds each package's binaries for its own integration tests
/// (coordinator/tests, worker/tests, tracer-core/tests) into the profile's directory, the
/// parent of this test executable's `deps/`. `TESSERA_BIN_DIR` points elsewhere (installed
/// binaries, another profile). A binary missing, or older than a source file of the crates it
/// is built from, fails the test: it would test other code than the checkout's (as after
/// `cargo test -p tessera-tests` alone, which builds no binaries).
pub fn bins() -> &'static Bins {
    static BINS: OnceLock<Bins> = OnceLock::new();
    BINS.get_or_init(|| {
        let (dir, check) = match std::env::var_os("TESSERA_BIN_DIR") {
            Some(dir) => (PathBuf::from(dir), false),
            None => {
                let exe = std::env::current_exe().expect("the test executable's path");
                let deps = exe.parent().expect("the test executable sits in deps/");
                let dir = deps
                    .parent()
                    .expect("deps/ sits in the profile's directory");
                (dir.to_path_buf(), true)
            }
        };
        let bins = Bins {
            coordinator: dir.join("coordinator"),
            worker: dir.join("worker"),
            tracer: dir.join("tracer"),
        };
        // What each binary is compiled from (its crates' sources and included files).
        let tracer = ["tracer-core/src"];
        let worker = ["tracer-core/src", "protocol/src", "worker/src"];
        let coordinator = [
            "tracer-core/src",
            "protocol/src",
            "worker/src",
            "coordinator/src",
            "coordinator/dashboard",
        ];
        for (bin, sources) in [
            (&bins.coordinator, &coordinator[..]),
            (&bins.worker, &worker[..]),
            (&bins.tracer, &tracer[..]),
        ] {
            let fresh = if check {
                check_fresh(bin, sources)
            } else if bin.is_file() {
                Ok(())
            } else {
                Err(format!("{} is missing.", bin.display()))
            };
            if let Err(why) = fresh {
                panic!(
                    "{why}\nThe farm tests run the binaries `cargo test --release --workspace` \
                     builds; with `-p tessera-tests` alone, run `cargo build --release --bins` \
                     first, or set TESSERA_BIN_DIR."
                );
            }
        }
        bins
    })
}

/// Whether `bin` exists and is newer than every file it was compiled from: the files cargo's
/// dep-info (`<bin>.d`) lists, or, without one, every file under `sources` (paths in the
/// workspace). The dep-info leaves out `#[cfg(test)]` modules, which the binary does not
/// contain and cargo does not rebuild it for.
fn check_fresh(bin: &Path, sources: &[&str]) -> Result<(), String> {
    let built = std::fs::metadata(bin)
        .and_then(|m| m.modified())
        .map_err(|e| format!("{} was not built ({e}).", bin.display()))?;
    let dep_info = std::fs::read_to_string(bin.with_extension("d")).ok();
    let mut pending: Vec<PathBuf> = match dep_info.as_deref().and_then(dep_info_inputs) {
        Some(inputs) => inputs,
        None => sources.iter().map(|s| workspace().join(s)).collect(),
    };
    while let Some(path) = pending.pop() {
        let meta = std::fs::metadata(&path).map_err(|e| format!("{}: {e}", path.display()))?;
        if meta.is_dir() {
            let entries =
                std::fs::read_dir(&path).map_err(|e| format!("{}: {e}", path.display()))?;
            pending.extend(entries.filter_map(|e| e.ok()).map(|e| e.path()));
        } else if meta.modified().is_ok_and(|changed| changed > built) {
            return Err(format!(
                "{} is stale: {} changed after it was built.",
                bin.display(),
                path.display()
            ));
        }
    }
    Ok(())
}

/// The inputs a cargo dep-info file lists for its first target (`target: a b\ c ...`, spaces
/// in names escaped); None if it lists none.
fn dep_info_inputs(text: &str) -> Option<Vec<PathBuf>> {
    let line = text.lines().next()?;
    let (_, inputs) = line.split_once(": ")?;
    let mut out = Vec::new();
    let mut name = String::new();
    let mut chars = inputs.chars();
    while let Some(c) = chars.next() {
        match c {
            '\\' => name.extend(chars.next()),
            ' ' => {
                if !name.is_empty() {
                    out.push(PathBuf::from(std::mem::take(&mut name)));
                }
            }
            c => name.push(c),
        }
    }
    if !name.is_empty() {
        out.push(PathBuf::from(name));
    }
    (!out.is_empty()).then_some(out)
}

/// A child process that is killed when dropped, with its stderr in a file.
pub struct Proc {
    pub child: Child,
    pub log: PathBuf,
}

impl Proc {
    pub fn spawn(mut cmd: Command, log: PathBuf) -> Proc {
        let file = std::fs::File::create(&log).unwrap();
        cmd.stderr(file).stdin(Stdio::null());
        let child = cmd
            .spawn()
            .unwrap_or_else(|e| panic!("starting {cmd:?}: {e}"));
        Proc { child, log }
    }

    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// SIGKILL: no chance to hand anything back.
    pub fn kill9(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }

    pub fn signal(&self, sig: &str) {
        let status = Command::new("kill")
            .args([&format!("-{sig}"), &self.pid().to_string()])
            .status()
            .unwrap();
        assert!(status.success());
    }

    /// Waits for the process to exit by itself.
    pub fn wait_exit(&mut self, timeout: Duration) -> std::process::ExitStatus {
        let start = Instant::now();
        loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                return status;
            }
            assert!(
                start.elapsed() < timeout,
                "{} did not exit",
                self.log.display()
            );
            std::thread::sleep(Duration::from_millis(20));
        }
    }

    pub fn log_text(&self) -> String {
        std::fs::read_to_string(&self.log).unwrap_or_default()
    }
}

impl Drop for Proc {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}

pub struct Coordinator {
    pub proc: Proc,
    pub url: String,
    pub port: u16,
}

/// Starts `coordinator serve` on 127.0.0.1 (`port` 0 picks one) with `data_dir`.
pub fn start_coordinator(data_dir: &Path, port: u16, extra: &[&str], log: PathBuf) -> Coordinator {
    let mut cmd = Command::new(&bins().coordinator);
    cmd.arg("serve")
        .arg("--listen")
        .arg(format!("127.0.0.1:{port}"))
        .arg("--data-dir")
        .arg(data_dir)
        .args(extra)
        .stdout(Stdio::piped());
    let mut proc = Proc::spawn(cmd, log);
    let stdout = proc.child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let mut reader = BufReader::new(stdout);
        let mut line = String::new();
        let _ = reader.read_line(&mut line);
        let _ = tx.send(line);
        // Keep draining: the coordinator prints more (the dashboard's URL).
        let _ = std::io::copy(&mut reader, &mut std::io::sink());
    });
    let line = rx
        .recv_timeout(Duration::from_secs(20))
        .unwrap_or_else(|_| panic!("the coordinator did not start: {}", proc.log_text()));
    let url = line
        .trim()
        .strip_prefix("listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}: {}", proc.log_text()))
        .to_string();
    let port = url.rsplit(':').next().unwrap().parse().unwrap();
    Coordinator { proc, url, port }
}

/// Starts a worker process.
pub fn start_worker(url: &str, name: &str, extra: &[&str], log: PathBuf) -> Proc {
    let mut cmd = Command::new(&bins().worker);
    cmd.args(["--coordinator", url, "--name", name, "--max-backoff", "0.3"])
        .args(extra)
        .stdout(Stdio::null());
    Proc::spawn(cmd, log)
}

/// `tracer render` with the same settings: the reference the farm must equal byte for byte.
pub fn tracer_png(scene: &Path, spec: &JobSpec, out_dir: &Path) -> Vec<u8> {
    tracer_image(scene, spec, out_dir, "png")
}

/// Like [`tracer_png`], written as `tracer.<extension>` (`exr`, `pfm`): the file's bytes.
pub fn tracer_image(scene: &Path, spec: &JobSpec, out_dir: &Path, extension: &str) -> Vec<u8> {
    let out = out_dir.join(format!("tracer.{extension}"));
    let s = &spec.render;
    let status = Command::new(&bins().tracer)
        .arg("render")
        .arg(scene)
        .arg("-o")
        .arg(&out)
        .arg("-q")
        .args([
            "--width",
            &s.width.to_string(),
            "--height",
            &s.height.to_string(),
        ])
        .args([
            "--spp",
            &s.spp.to_string(),
            "--depth",
            &s.max_depth.to_string(),
        ])
        .args(["--seed", &s.seed.to_string()])
        .args(["--frame", &s.frame.to_string()])
        .stderr(Stdio::null())
        .status()
        .unwrap();
    assert!(status.success(), "tracer render failed");
    std::fs::read(out).unwrap()
}

/// `coordinator render scene -o out [args]` (the embedded farm); the PNG it wrote.
pub fn coordinator_render(scene: &Path, out: &Path, args: &[&str]) -> Vec<u8> {
    let status = Command::new(&bins().coordinator)
        .arg("render")
        .arg(scene)
        .arg("-o")
        .arg(out)
        .args(args)
        .status()
        .unwrap();
    assert!(status.success(), "coordinator render {args:?} failed");
    std::fs::read(out).unwrap()
}

/// A small job: 160x120 of `spp` samples in `tile`-pixel tiles.
pub fn small_spec(spp: u32, tile: u32) -> JobSpec {
    let mut spec = JobSpec::default();
    spec.render.width = 160;
    spec.render.height = 120;
    spec.render.spp = spp;
    spec.tile_size = tile;
    spec
}

pub async fn submit(client: &Client, scene: &Path, spec: JobSpec) -> JobInfo {
    let sub = coordinator::cli::collect_submission(scene, spec).unwrap();
    client.submit(&sub).await.unwrap()
}

/// Polls the job until `done` holds, failing after `timeout`.
pub async fn wait_until(
    client: &Client,
    id: u64,
    timeout: Duration,
    done: impl Fn(&JobInfo) -> bool,
) -> JobInfo {
    let start = Instant::now();
    let mut last = None;
    loop {
        if let Ok(info) = client.job(id).await {
            if done(&info) {
                return info;
            }
            last = Some(info);
        }
        assert!(
            start.elapsed() < timeout,
            "job {id} did not get there in {timeout:?}: {last:?}"
        );
        tokio::time::sleep(Duration::from_millis(25)).await;
    }
}

pub async fn wait_finished(client: &Client, id: u64, timeout: Duration) -> JobInfo {
    wait_until(client, id, timeout, |j| j.state.is_finished()).await
}

/// How many times each tile index of `job` appears as rendered in the workers' logs.
pub fn rendered_tiles(logs: &[String], job: u64) -> std::collections::BTreeMap<u32, usize> {
    let mut counts = std::collections::BTreeMap::new();
    let prefix = format!("job {job} tile ");
    for log in logs {
        for line in log.lines().filter(|l| l.contains(": rendered in ")) {
            if let Some(rest) = line.split(&prefix).nth(1) {
                let tile: u32 = rest.split(' ').next().unwrap().parse().unwrap();
                *counts.entry(tile).or_default() += 1;
            }
        }
    }
    counts
}

#[test]
fn dep_info_lists_each_input_with_escaped_spaces_kept() {
    let text = "/t/release/coordinator: /w/a.rs /w/my\\ file.rs  /w/b.html\n\n/w/a.rs:\n";
    assert_eq!(
        dep_info_inputs(text),
        Some(vec![
            PathBuf::from("/w/a.rs"),
            PathBuf::from("/w/my file.rs"),
            PathBuf::from("/w/b.html"),
        ])
    );
    assert_eq!(dep_info_inputs("/t/release/tracer:\n"), None);
}
