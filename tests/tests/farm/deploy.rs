//! Deployment: workers started over ssh by `scripts/farm-ssh` (against an sshd this test
//! starts on loopback) and its host-file parsing, the docker compose farm losing a worker
//! container mid-job, the worker's health probes, and the Kubernetes autoscaler's metric
//! selectors against a real coordinator's `/metrics`.
//!
//! The ssh and compose tests need something from the machine (openssh-server; a Docker
//! daemon). Without it the test says so and passes, unless `TESSERA_REQUIRE_SSH=1` /
//! `TESSERA_REQUIRE_DOCKER=1` (set by `.ci/run` where it installed them) make the absence a
//! failure.

use std::net::TcpListener;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::JobState;

use crate::helpers::*;

/// Whether a prerequisite is present; panics when it is absent but required.
fn available(present: bool, what: &str, require_var: &str) -> bool {
    if present {
        return true;
    }
    assert!(
        std::env::var(require_var).as_deref() != Ok("1"),
        "{what} is required ({require_var}=1) but not available"
    );
    eprintln!("skipping: {what} is not available (set {require_var}=1 to require it)");
    false
}

fn free_port() -> u16 {
    TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port()
}

fn run(cmd: &mut Command) -> String {
    let out = cmd.output().unwrap_or_else(|e| panic!("{cmd:?}: {e}"));
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(out.status.success(), "{cmd:?} failed:\n{text}");
    text
}

fn keygen(path: &Path) {
    run(Command::new("ssh-keygen")
        .args(["-q", "-t", "ed25519", "-N", "", "-f"])
        .arg(path));
}

/// An sshd on a loopback port that accepts one throwaway key, stopped when dropped.
struct Sshd {
    _proc: Proc,
    port: u16,
    opts: String,
}

fn start_sshd(dir: &Path) -> Sshd {
    keygen(&dir.join("host_key"));
    keygen(&dir.join("client_key"));
    std::fs::copy(dir.join("client_key.pub"), dir.join("authorized_keys")).unwrap();
    // Privilege separation needs this directory to exist.
    std::fs::create_dir_all("/run/sshd").unwrap();
    let port = free_port();
    let v6 = if ipv6_loopback() {
        "ListenAddress ::1\n"
    } else {
        ""
    };
    let config = format!(
        "Port {port}\nListenAddress 127.0.0.1\n{v6}HostKey {dir}/host_key\n\
         AuthorizedKeysFile {dir}/authorized_keys\nPidFile {dir}/sshd.pid\nStrictModes no\n\
         PasswordAuthentication no\nKbdInteractiveAuthentication no\nUsePAM no\n\
         PermitRootLogin prohibit-password\n",
        dir = dir.display()
    );
    std::fs::write(dir.join("sshd_config"), config).unwrap();
    let mut cmd = Command::new("/usr/sbin/sshd");
    cmd.args(["-D", "-e", "-f"]).arg(dir.join("sshd_config"));
    let proc = Proc::spawn(cmd, dir.join("sshd.log"));
    let opts = format!(
        "-i {} -o StrictHostKeyChecking=no -o UserKnownHostsFile=/dev/null -o BatchMode=yes \
         -o LogLevel=ERROR -o ConnectTimeout=5",
        dir.join("client_key").display()
    );
    // Wait until it accepts a login.
    let start = Instant::now();
    loop {
        let ok = Command::new("ssh")
            .args(opts.split(' '))
            .args([
                "-p",
                &port.to_string(),
                &format!("{}@127.0.0.1", user()),
                "true",
            ])
            .stdin(Stdio::null())
            .output()
            .map(|o| o.status.success())
            .unwrap_or(false);
        if ok {
            break;
        }
        assert!(
            start.elapsed() < Duration::from_secs(10),
            "sshd did not come up: {}",
            proc.log_text()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
    Sshd {
        _proc: proc,
        port,
        opts,
    }
}

/// Whether this machine has an IPv6 loopback to listen on.
fn ipv6_loopback() -> bool {
    TcpListener::bind("[::1]:0").is_ok()
}

fn user() -> String {
    std::env::var("USER").unwrap_or_else(|_| "root".into())
}

fn script(name: &str) -> PathBuf {
    workspace().join("scripts").join(name)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_ssh_launcher_installs_once_per_host_starts_workers_that_render_a_job_and_stops_them() {
    let has = Path::new("/usr/sbin/sshd").is_file()
        && Command::new("ssh-keygen").arg("-?").output().is_ok();
    if !available(has, "openssh-server", "TESSERA_REQUIRE_SSH") {
        return;
    }
    let tmp = tempfile::tempdir().unwrap();
    let sshd = start_sshd(tmp.path());
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", "ssh-farm-token"],
        tmp.path().join("c.log"),
    );
    // Two workers on one host (one copy of the binary), and a third over IPv6 where this
    // machine has it: a second destination, so a second copy.
    let target = format!("{}@127.0.0.1:{}", user(), sshd.port);
    let mut hosts_text = format!("# two workers on one host\n{target} 1\n\n{target} 1\n");
    let mut names = vec!["127.0.0.1-1", "127.0.0.1-2"];
    if ipv6_loopback() {
        hosts_text += &format!("{}@[::1]:{} 1   # the same sshd\n", user(), sshd.port);
        names.push("::1-3");
    } else {
        eprintln!("no IPv6 loopback: the launcher runs two workers over IPv4 only");
    }
    let destinations = names.len() - 1;
    let hosts = tmp.path().join("hosts");
    std::fs::write(&hosts, hosts_text).unwrap();
    let remote_dir = tmp.path().join("remote");
    let launcher = |action: &str| {
        let mut cmd = Command::new(script("farm-ssh"));
        cmd.arg(action)
            .arg(&hosts)
            .env("TESSERA_SSH_OPTS", &sshd.opts)
            .env("TESSERA_REMOTE_DIR", &remote_dir)
            .env("TESSERA_TOKEN", "ssh-farm-token")
            .stdin(Stdio::null());
        if action == "start" {
            cmd.args(["--coordinator", &coord.url, "--install"])
                .arg(&bins().worker);
        }
        run(&mut cmd)
    };
    let started = launcher("start");
    assert_eq!(
        started.matches(": installed ").count(),
        destinations,
        "one copy per destination: {started}"
    );
    assert!(remote_dir.join("worker").is_file(), "{started}");
    assert_eq!(
        started.matches("started pid").count(),
        names.len(),
        "{started}"
    );
    let status = launcher("status");
    assert_eq!(
        status.matches("running pid").count(),
        names.len(),
        "{status}"
    );

    let client = Client::new(&coord.url, Some("ssh-farm-token".into())).unwrap();
    let scene = course_scene("stacks.scene");
    let spec = small_spec(8, 16);
    let job = submit(&client, &scene, spec.clone()).await;
    let done = wait_finished(&client, job.id, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    assert!(client.image(job.id).await.unwrap() == tracer_png(&scene, &spec, tmp.path()));
    // Every worker, named after its host and its place among the workers, took tiles.
    let logs: Vec<String> = names
        .iter()
        .map(|name| std::fs::read_to_string(remote_dir.join(format!("{name}.log"))).unwrap())
        .collect();
    for log in &logs {
        assert!(log.contains(": rendered in "), "{log}");
    }
    assert_eq!(rendered_tiles(&logs, job.id).len() as u32, done.tiles_total);

    let stopped = launcher("stop");
    assert_eq!(
        stopped.matches(": stopped").count(),
        names.len(),
        "{stopped}"
    );
    let status = launcher("status");
    assert_eq!(status.matches(": stopped").count(), names.len(), "{status}");
    let final_logs: Vec<String> = names
        .iter()
        .map(|name| std::fs::read_to_string(remote_dir.join(format!("{name}.log"))).unwrap())
        .collect();
    for log in final_logs {
        assert!(log.contains("stopped:"), "a clean exit on SIGTERM: {log}");
    }
}

#[test]
fn the_ssh_launcher_plans_workers_from_comments_duplicates_and_ipv6_hosts() {
    let tmp = tempfile::tempdir().unwrap();
    let hosts = tmp.path().join("hosts");
    std::fs::write(
        &hosts,
        "# render nodes\n\
         \n\
         render@10.0.0.11\n\
         render@10.0.0.12:2222 8   # two workers here\n\
         render@10.0.0.12:2222 8\n\
         \t\n\
         [::1] 2\n\
         me@[fe80::1%eth0]:2200\n\
         fe80::2\n\
         node.example:22 0\n",
    )
    .unwrap();
    let plan = |extra: &[&str]| {
        Command::new(script("farm-ssh"))
            .arg("plan")
            .arg(&hosts)
            .args(extra)
            .stdin(Stdio::null())
            .output()
            .unwrap()
    };
    let out = plan(&[]);
    assert!(out.status.success(), "{out:?}");
    assert_eq!(
        String::from_utf8_lossy(&out.stdout),
        "worker 10.0.0.11-1 render@10.0.0.11 22 all\n\
         worker 10.0.0.12-2 render@10.0.0.12 2222 8\n\
         worker 10.0.0.12-3 render@10.0.0.12 2222 8\n\
         worker ::1-4 ::1 22 2\n\
         worker fe80::1%eth0-5 me@fe80::1%eth0 2200 all\n\
         worker fe80::2-6 fe80::2 22 all\n\
         worker node.example-7 node.example 22 all\n"
    );
    // The binary goes to each destination once, before any worker starts.
    let binary = tmp.path().join("worker-binary");
    std::fs::write(&binary, b"\x7fELF").unwrap();
    let out = plan(&["--install", binary.to_str().unwrap()]);
    let text = String::from_utf8_lossy(&out.stdout);
    let installs: Vec<&str> = text.lines().filter(|l| l.starts_with("install ")).collect();
    assert_eq!(
        installs,
        [
            "install render@10.0.0.11 22",
            "install render@10.0.0.12 2222",
            "install ::1 22",
            "install me@fe80::1%eth0 2200",
            "install fe80::2 22",
            "install node.example 22",
        ],
        "{text}"
    );
    assert!(text
        .lines()
        .take(installs.len())
        .all(|l| l.starts_with("install ")));

    // A malformed line stops everything before any ssh, naming the file and line.
    for (line, why) in [
        ("render@[::1", "unclosed '['"),
        ("[::1]2222", "expected ':port'"),
        ("host:http", "bad port 'http'"),
        ("host:70000", "bad port '70000'"),
        ("[10.0.0.1]", "is not an IPv6 address"),
        ("host four", "threads must be a number"),
        ("host 2 3", "unexpected '3'"),
    ] {
        std::fs::write(&hosts, format!("# fine\nhost\n{line}\n")).unwrap();
        let out = Command::new(script("farm-ssh"))
            .args(["start"])
            .arg(&hosts)
            .args(["--coordinator", "http://127.0.0.1:9"])
            // An ssh that would fail loudly if it were ever run.
            .env("TESSERA_SSH_OPTS", "-o ProxyCommand=false -o BatchMode=yes")
            .stdin(Stdio::null())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{line}: {err}");
        assert!(
            err.contains(&format!("{}:3: ", hosts.display())) && err.contains(why),
            "{line}: {err}"
        );
        assert!(out.stdout.is_empty(), "{line}: nothing may start");
    }
}

/// `docker-compose -p NAME ...` run where a copy of the workspace's docker-compose.yml sits
/// beside an `.env` made from `.env.example`: no farm variable in the environment, as after
/// `docker-compose up` in another shell.
struct Compose {
    project: String,
    dir: tempfile::TempDir,
}

impl Compose {
    fn new(project: String, token: &str, port: u16) -> Compose {
        let dir = tempfile::tempdir().unwrap();
        std::fs::copy(
            workspace().join("docker-compose.yml"),
            dir.path().join("docker-compose.yml"),
        )
        .unwrap();
        let example = std::fs::read_to_string(workspace().join(".env.example")).unwrap();
        let mut set = 0;
        let env: String = example
            .lines()
            .map(|line| match line.split_once('=') {
                Some(("TESSERA_TOKEN", _)) => {
                    set += 1;
                    format!("TESSERA_TOKEN={token}\n")
                }
                Some(("TESSERA_PORT", _)) => {
                    set += 1;
                    format!("TESSERA_PORT={port}\n")
                }
                _ => format!("{line}\n"),
            })
            .collect();
        assert_eq!(set, 2, ".env.example sets TESSERA_TOKEN and TESSERA_PORT");
        std::fs::write(dir.path().join(".env"), env).unwrap();
        Compose { project, dir }
    }

    fn cmd(&self) -> Command {
        let mut cmd = Command::new("docker-compose");
        cmd.current_dir(self.dir.path())
            .args(["-p", &self.project])
            .env_remove("TESSERA_TOKEN")
            .env_remove("TESSERA_PORT")
            .stdin(Stdio::null());
        cmd
    }
}

impl Drop for Compose {
    fn drop(&mut self) {
        let _ = self
            .cmd()
            .args(["down", "-v", "-t", "2"])
            .stdout(Stdio::null())
            .stderr(Stdio::null())
            .status();
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn docker_compose_runs_a_farm_that_survives_losing_a_worker_container() {
    let daemon = Command::new("docker")
        .arg("info")
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .status()
        .is_ok_and(|s| s.success());
    let compose = Command::new("docker-compose")
        .arg("version")
        .output()
        .is_ok_and(|o| o.status.success());
    if !available(
        daemon && compose,
        "a Docker daemon with docker-compose",
        "TESSERA_REQUIRE_DOCKER",
    ) {
        return;
    }
    let bin_dir = bins().coordinator.parent().unwrap().to_path_buf();
    run(Command::new(script("docker-build"))
        .arg("--bin-dir")
        .arg(&bin_dir)
        .current_dir(workspace()));
    let port = free_port();
    let farm = Compose::new(
        format!("tessera-test-{}", std::process::id()),
        "compose-token",
        port,
    );
    run(farm.cmd().args(["up", "-d"]));
    let url = format!("http://127.0.0.1:{port}");
    let client = Client::new(&url, Some("compose-token".into())).unwrap();
    let start = Instant::now();
    while client.healthz().await.is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the coordinator never answered"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    // Commands after `up` find the token in .env, not in the environment.
    let containers = run(farm.cmd().args(["ps", "-q", "worker"]));
    let logs = run(farm.cmd().args(["logs", "--no-color", "coordinator"]));
    assert!(logs.contains("listening on http://0.0.0.0:7878"), "{logs}");
    let workers: Vec<&str> = containers.split_whitespace().collect();
    assert_eq!(workers.len(), 3, "three workers by default: {containers}");

    let scene = course_scene("stacks.scene");
    let spec = small_spec(48, 16);
    let job = submit(&client, &scene, spec.clone()).await;
    wait_until(&client, job.id, Duration::from_secs(60), |j| {
        j.tiles_done >= 6
    })
    .await;
    run(Command::new("docker").args(["kill", "--signal", "KILL", workers[0]]));
    let killed_at = client.job(job.id).await.unwrap();
    assert!(
        killed_at.tiles_done < killed_at.tiles_total,
        "killed too late: {killed_at:?}"
    );
    let done = wait_finished(&client, job.id, Duration::from_secs(120)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    assert!(done.failures.is_empty(), "{done:?}");
    let tmp = tempfile::tempdir().unwrap();
    assert!(client.image(job.id).await.unwrap() == tracer_png(&scene, &spec, tmp.path()));
}

/// The status of `GET url` (0 when nothing answers).
async fn status_of(http: &reqwest::Client, url: &str) -> u16 {
    http.get(url)
        .send()
        .await
        .map(|r| r.status().as_u16())
        .unwrap_or(0)
}

/// Polls `url` until it answers `want`.
async fn wait_for_status(http: &reqwest::Client, url: &str, want: u16, worker: &Proc) {
    let start = Instant::now();
    loop {
        let got = status_of(http, url).await;
        if got == want {
            return;
        }
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "{url}: {got}, not {want}: {}",
            worker.log_text()
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_worker_is_ready_while_its_coordinator_answers_and_alive_throughout() {
    let tmp = tempfile::tempdir().unwrap();
    let mut coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &["--token", "probe-token"],
        tmp.path().join("c.log"),
    );
    let health = format!("127.0.0.1:{}", free_port());
    let worker = start_worker(
        &coord.url,
        "probed",
        &["--token", "probe-token", "--health-listen", &health],
        tmp.path().join("w.log"),
    );
    let http = reqwest::Client::new();
    let (ready, live) = (
        format!("http://{health}/readyz"),
        format!("http://{health}/livez"),
    );
    wait_for_status(&http, &ready, 200, &worker).await;
    assert_eq!(status_of(&http, &live).await, 200);
    coord.proc.kill9();
    wait_for_status(&http, &ready, 503, &worker).await;
    assert_eq!(
        status_of(&http, &live).await,
        200,
        "alive without its coordinator"
    );
    assert_eq!(
        status_of(&http, &format!("http://{health}/metrics")).await,
        404
    );
}

/// `name{label="value",...}` from a KEDA `valueLocation`.
fn parse_selector(text: &str) -> (String, Vec<(String, String)>) {
    let (name, labels) = match text.split_once('{') {
        Some((name, rest)) => (name, rest.strip_suffix('}').expect("a closing brace")),
        None => (text, ""),
    };
    let labels = labels
        .split(',')
        .filter(|l| !l.trim().is_empty())
        .map(|l| {
            let (k, v) = l.split_once('=').expect("label=\"value\"");
            (k.trim().to_string(), v.trim().trim_matches('"').to_string())
        })
        .collect();
    (name.trim().to_string(), labels)
}

/// The value of the one sample of `/metrics` text that the selector picks.
fn select_sample(metrics: &str, selector: &(String, Vec<(String, String)>)) -> f64 {
    let (name, labels) = selector;
    let hits: Vec<f64> = metrics
        .lines()
        .filter(|l| !l.starts_with('#'))
        .filter_map(|l| {
            let (series, value) = l.rsplit_once(' ')?;
            let (series_name, series_labels) = parse_selector(series);
            let all = labels.iter().all(|want| series_labels.contains(want));
            (series_name == *name && all).then(|| value.parse().ok())?
        })
        .collect();
    assert_eq!(
        hits.len(),
        1,
        "{name}{labels:?} picks {hits:?} in\n{metrics}"
    );
    hits[0]
}

/// What KEDA's metrics-api scaler does: `GET /metrics` with the bearer token.
async fn scrape(url: &str, token: Option<&str>) -> String {
    let mut req = reqwest::Client::new().get(format!("{url}/metrics"));
    if let Some(token) = token {
        req = req.bearer_auth(token);
    }
    let resp = req.send().await.unwrap();
    assert!(resp.status().is_success(), "{resp:?}");
    resp.text().await.unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_autoscalers_queries_read_the_coordinators_metrics() {
    let manifest =
        std::fs::read_to_string(workspace().join("deploy/kubernetes/autoscaling.yaml")).unwrap();
    let selectors: Vec<_> = manifest
        .lines()
        .filter_map(|l| l.trim().strip_prefix("valueLocation:"))
        .map(|v| parse_selector(v.trim().trim_matches('\'')))
        .collect();
    let queued = selectors
        .iter()
        .position(|(name, labels)| {
            name == "tessera_tiles" && labels == &[("state".into(), "queued".into())]
        })
        .expect("a trigger on tessera_tiles{state=\"queued\"}");
    let tmp = tempfile::tempdir().unwrap();
    // The scaler holds the scrape-only metrics token (deploy/kubernetes/autoscaling.yaml), and
    // a second listener serves the same text without any token.
    let scrape_port = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let metrics_listen = format!("127.0.0.1:{scrape_port}");
    let coord = start_coordinator(
        &tmp.path().join("data"),
        0,
        &[
            "--token",
            "submit-token",
            "--metrics-token",
            "scaler-token",
            "--metrics-listen",
            &metrics_listen,
        ],
        tmp.path().join("c.log"),
    );
    let client = Client::new(&coord.url, Some("submit-token".into())).unwrap();
    let http = reqwest::Client::new();
    let status = |req: reqwest::RequestBuilder| async move { req.send().await.unwrap().status() };
    let metrics_url = format!("{}/metrics", coord.url);
    assert_eq!(status(http.get(&metrics_url)).await.as_u16(), 401);
    let jobs_url = format!("{}/api/v1/jobs", coord.url);
    assert_eq!(
        status(http.get(&jobs_url).bearer_auth("scaler-token"))
            .await
            .as_u16(),
        401,
        "the metrics token opens nothing else"
    );
    let idle = scrape(&coord.url, Some("scaler-token")).await;
    for selector in &selectors {
        assert_eq!(
            select_sample(&idle, selector),
            0.0,
            "an idle farm scales to zero"
        );
    }
    // No worker: every tile of a job waits in the queue, and the scaler sees them all.
    let job = submit(&client, &course_scene("stacks.scene"), small_spec(1, 40)).await;
    let busy = scrape(&coord.url, Some("scaler-token")).await;
    assert_eq!(
        select_sample(&busy, &selectors[queued]),
        f64::from(job.tiles_total)
    );
    // The main token still scrapes; the metrics listener needs none and serves nothing else.
    let with_main = scrape(&coord.url, Some("submit-token")).await;
    assert_eq!(
        select_sample(&with_main, &selectors[queued]),
        f64::from(job.tiles_total)
    );
    let open_url = format!("http://{metrics_listen}");
    let open = scrape(&open_url, None).await;
    assert_eq!(
        select_sample(&open, &selectors[queued]),
        f64::from(job.tiles_total)
    );
    assert!(open.contains("process_resident_memory_bytes "), "{open}");
    assert_eq!(
        status(http.get(format!("{open_url}/api/v1/jobs")))
            .await
            .as_u16(),
        404
    );
}
