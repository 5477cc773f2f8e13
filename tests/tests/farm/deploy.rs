//! Deployment: workers started over ssh by `scripts/farm-ssh` (against an sshd this test
//! starts on loopback), and the docker compose farm losing a worker container mid-job.
//!
//! Each needs something from the machine (openssh-server; a Docker daemon). Without it the
//! test says so and passes, unless `TESSERA_REQUIRE_SSH=1` / `TESSERA_REQUIRE_DOCKER=1`
//! (set by `.ci/run` where it installed them) make the absence a failure.

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
    let config = format!(
        "Port {port}\nListenAddress 127.0.0.1\nHostKey {dir}/host_key\n\
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

fn user() -> String {
    std::env::var("USER").unwrap_or_else(|_| "root".into())
}

fn script(name: &str) -> PathBuf {
    workspace().join("scripts").join(name)
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_ssh_launcher_starts_two_workers_that_render_a_job_and_stops_them() {
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
    let target = format!("{}@127.0.0.1:{}", user(), sshd.port);
    let hosts = tmp.path().join("hosts");
    std::fs::write(
        &hosts,
        format!("# two workers on one host\n{target} 1\n\n{target} 1\n"),
    )
    .unwrap();
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
            cmd.args(["--coordinator", &coord.url, "--worker"])
                .arg(&bins().worker);
        }
        run(&mut cmd)
    };
    let started = launcher("start");
    assert_eq!(started.matches("started pid").count(), 2, "{started}");
    let status = launcher("status");
    assert_eq!(status.matches("running pid").count(), 2, "{status}");

    let client = Client::new(&coord.url, Some("ssh-farm-token".into())).unwrap();
    let scene = course_scene("stacks.scene");
    let spec = small_spec(8, 16);
    let job = submit(&client, &scene, spec.clone()).await;
    let done = wait_finished(&client, job.id, Duration::from_secs(60)).await;
    assert_eq!(done.state, JobState::Done, "{done:?}");
    assert!(client.image(job.id).await.unwrap() == tracer_png(&scene, &spec, tmp.path()));
    // Both workers, named after their host and line, took tiles.
    let logs: Vec<String> = ["127.0.0.1-2", "127.0.0.1-4"]
        .iter()
        .map(|name| std::fs::read_to_string(remote_dir.join(format!("{name}.log"))).unwrap())
        .collect();
    for log in &logs {
        assert!(log.contains(": rendered in "), "{log}");
    }
    assert_eq!(rendered_tiles(&logs, job.id).len() as u32, done.tiles_total);

    let stopped = launcher("stop");
    assert_eq!(stopped.matches(": stopped").count(), 2, "{stopped}");
    let status = launcher("status");
    assert_eq!(status.matches(": stopped").count(), 2, "{status}");
    let final_logs: Vec<String> = ["127.0.0.1-2", "127.0.0.1-4"]
        .iter()
        .map(|name| std::fs::read_to_string(remote_dir.join(format!("{name}.log"))).unwrap())
        .collect();
    for log in final_logs {
        assert!(log.contains("stopped:"), "a clean exit on SIGTERM: {log}");
    }
}

/// `docker-compose -p NAME ...` in the workspace, with the farm's variables.
struct Compose {
    project: String,
    port: u16,
}

impl Compose {
    fn cmd(&self) -> Command {
        let mut cmd = Command::new("docker-compose");
        cmd.current_dir(workspace())
            .args(["-p", &self.project])
            .env("TESSERA_TOKEN", "compose-token")
            .env("TESSERA_PORT", self.port.to_string())
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
    let farm = Compose {
        project: format!("tessera-test-{}", std::process::id()),
        port: free_port(),
    };
    run(farm.cmd().args(["up", "-d"]));
    let url = format!("http://127.0.0.1:{}", farm.port);
    let client = Client::new(&url, Some("compose-token".into())).unwrap();
    let start = Instant::now();
    while client.healthz().await.is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(30),
            "the coordinator never answered"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    let containers = run(farm.cmd().args(["ps", "-q", "worker"]));
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
