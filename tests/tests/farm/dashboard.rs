//! The dashboard in a real browser: headless Chromium driven through chromedriver submits a
//! course scene through the page's form, watches it reach 100%, checks that the preview shows
//! exactly the job's PNG, cancels a second job, orbits the camera into a new job, shows a scene
//! error inline, opens afresh by a `#token=` URL on the job rendering, and saves screenshots
//! under `target/test-artifacts/`. Also: what `coordinator serve` prints for the page.
//!
//! Skips (with a message) when no Chromium or chromedriver is installed, unless
//! `TESSERA_REQUIRE_CHROMIUM=1`, which CI sets.

use std::net::TcpListener;
use std::os::unix::process::CommandExt;
use std::path::{Path, PathBuf};
use std::process::Command;
use std::time::{Duration, Instant};

use protocol::client::Client;
use protocol::JobState;
use serde_json::{json, Value};

use crate::helpers::*;
use crate::webdriver::{Browser, Element};

const TOKEN: &str = "dashboard-token";

/// The first of `names` found in `PATH` (or the path in `env`, when set).
fn find_program(env: &str, names: &[&str]) -> Option<PathBuf> {
    if let Some(path) = std::env::var_os(env) {
        return Some(PathBuf::from(path));
    }
    let dirs: Vec<PathBuf> = std::env::var_os("PATH")
        .map(|p| std::env::split_paths(&p).collect())
        .unwrap_or_default();
    // Debian's chromium-driver also ships it beside the browser.
    let extra = [PathBuf::from("/usr/lib/chromium")];
    names.iter().find_map(|name| {
        dirs.iter()
            .chain(&extra)
            .map(|d| d.join(name))
            .find(|p| p.is_file())
    })
}

/// Chromium and chromedriver, or why the test cannot run.
fn browser_programs() -> Result<(PathBuf, PathBuf), String> {
    let chromium = find_program(
        "TESSERA_CHROMIUM",
        &["chromium", "chromium-browser", "google-chrome"],
    )
    .ok_or("no chromium binary in PATH (apt-get install chromium chromium-driver)")?;
    let driver = find_program("TESSERA_CHROMEDRIVER", &["chromedriver"])
        .ok_or("no chromedriver in PATH (apt-get install chromium-driver)")?;
    Ok((chromium, driver))
}

fn artifacts_dir() -> PathBuf {
    let target = std::env::var_os("CARGO_TARGET_DIR")
        .map(PathBuf::from)
        .unwrap_or_else(|| workspace().join("target"));
    let dir = target.join("test-artifacts");
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// chromedriver in a process group of its own, with the Chromium it starts: dropping it kills
/// the whole group. Killing chromedriver alone orphaned the browser whenever a test ended
/// without closing its session (a failed assertion, or a test that never closes it), and
/// every such run left a headless Chromium running on the machine.
struct Driver(Proc);

impl Drop for Driver {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-KILL", "--", &format!("-{}", self.0.pid())])
            .status();
    }
}

/// Starts chromedriver on a free loopback port and waits until it answers.
async fn start_driver(driver: &Path, log: PathBuf) -> (Driver, String) {
    let port = TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap()
        .port();
    let mut cmd = Command::new(driver);
    cmd.arg(format!("--port={port}"))
        .arg(format!(
            "--log-path={}",
            log.with_extension("driver.log").display()
        ))
        .stdout(std::process::Stdio::null())
        .process_group(0);
    let proc = Proc::spawn(cmd, log);
    let url = format!("http://127.0.0.1:{port}");
    let start = Instant::now();
    while reqwest::get(format!("{url}/status")).await.is_err() {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "chromedriver did not start: {}",
            proc.log_text()
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
    (Driver(proc), url)
}

async fn open_browser(chromium: &Path, driver_url: &str) -> Browser {
    let caps = json!({
        "goog:chromeOptions": {
            "binary": chromium,
            // No sandbox: CI runs as root in a container.
            "args": ["--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage",
                     "--window-size=1500,1100", "--hide-scrollbars"]
        }
    });
    Browser::connect(driver_url, caps)
        .await
        .unwrap_or_else(|e| panic!("starting a Chromium session: {e}"))
}

async fn find<'a>(browser: &'a Browser, css: &str) -> Element<'a> {
    browser
        .wait_for(css, Duration::from_secs(20))
        .await
        .unwrap_or_else(|e| panic!("no {css} on the page: {e}"))
}

/// Evaluates the JavaScript expression in the page until `ok` accepts its value.
async fn wait_js(browser: &Browser, expr: &str, ok: impl Fn(&Value) -> bool) -> Value {
    let start = Instant::now();
    let script = format!("return {expr};");
    loop {
        let value = browser.execute(&script).await.unwrap_or(Value::Null);
        if ok(&value) {
            return value;
        }
        assert!(
            start.elapsed() < Duration::from_secs(60),
            "`{expr}` never got there; last {value}"
        );
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

/// Clicks the element `css` names. The dashboard redraws its job table as jobs move on, so an
/// element found a moment ago may be replaced or not shown yet when the click arrives; the
/// WebDriver server then refuses it ("element not interactable", "stale element reference")
/// without clicking, and the element is found again and clicked until 20 s have passed.
async fn click(browser: &Browser, css: &str) {
    let start = Instant::now();
    loop {
        let error = match find(browser, css).await.click().await {
            Ok(()) => return,
            Err(e) => e.to_string(),
        };
        let not_yet = error.contains("not interactable") || error.contains("stale element");
        assert!(
            not_yet && start.elapsed() < Duration::from_secs(20),
            "clicking {css}: {error}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

async fn set_field(browser: &Browser, id: &str, value: &str) {
    let el = find(browser, &format!("#{id}")).await;
    el.clear().await.unwrap();
    el.send_keys(value).await.unwrap();
}

/// Chooses files in a file input (chromedriver takes them newline-separated).
async fn choose_files(browser: &Browser, files: &[PathBuf]) {
    let input = find(browser, "#scene-files").await;
    input.clear().await.unwrap();
    let list: Vec<String> = files.iter().map(|f| f.display().to_string()).collect();
    input.send_keys(&list.join("\n")).await.unwrap();
}

async fn screenshot(browser: &Browser, path: &Path) {
    let png = browser.screenshot().await.unwrap();
    std::fs::write(path, png).unwrap();
    eprintln!("saved {}", path.display());
}

/// The bytes of the image the preview shows (a `blob:` URL), read back inside the page.
async fn preview_bytes(browser: &Browser) -> Vec<u8> {
    let script = r#"
        const done = arguments[arguments.length - 1];
        fetch(document.getElementById('preview').src)
            .then((r) => r.arrayBuffer())
            .then((b) => done(Array.from(new Uint8Array(b))), (e) => done(String(e)));
    "#;
    let value = browser.execute_async(script).await.unwrap();
    let Value::Array(bytes) = value else {
        panic!("reading the preview failed: {value}")
    };
    bytes.iter().map(|b| b.as_u64().unwrap() as u8).collect()
}

/// What each browser test starts: a coordinator with a token, one single-threaded worker
/// (slow enough, a few seconds a job, to watch the render go by), chromedriver and a headless
/// Chromium. Fields are dropped (processes stopped) when the test ends.
struct DashboardFarm {
    tmp: tempfile::TempDir,
    coord: Coordinator,
    client: Client,
    _worker: Proc,
    _driver: Driver,
    browser: Browser,
}

impl DashboardFarm {
    /// None (after saying so) where Chromium or chromedriver is missing, unless
    /// `TESSERA_REQUIRE_CHROMIUM=1`, which makes that a failure.
    async fn start(test: &str, worker: &str) -> Option<DashboardFarm> {
        let (chromium, driver) = match browser_programs() {
            Ok(found) => found,
            Err(why) if std::env::var("TESSERA_REQUIRE_CHROMIUM").as_deref() == Ok("1") => {
                panic!("TESSERA_REQUIRE_CHROMIUM=1 but {why}")
            }
            Err(why) => {
                eprintln!("SKIPPED {test}: {why}");
                return None;
            }
        };
        let tmp = tempfile::tempdir().unwrap();
        let coord = start_coordinator(
            &tmp.path().join("data"),
            0,
            &["--token", TOKEN],
            tmp.path().join("c.log"),
        );
        let client = Client::new(&coord.url, Some(TOKEN.into())).unwrap();
        let worker = start_worker(
            &coord.url,
            worker,
            &["--token", TOKEN, "--threads", "1"],
            tmp.path().join("w.log"),
        );
        let (driver, driver_url) = start_driver(&driver, tmp.path().join("chromedriver.log")).await;
        let browser = open_browser(&chromium, &driver_url).await;
        Some(DashboardFarm {
            tmp,
            coord,
            client,
            _worker: worker,
            _driver: driver,
            browser,
        })
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_renders_a_submitted_scene_in_chromium() {
    // Every field bound by name: one left to `..` would be dropped (its process stopped) here.
    let Some(DashboardFarm {
        tmp,
        coord,
        client,
        _worker,
        _driver,
        browser,
    }) = DashboardFarm::start("the dashboard browser test", "dash-worker").await
    else {
        return;
    };
    let artifacts = artifacts_dir();

    // The page asks for the token once.
    browser.goto(&format!("{}/", coord.url)).await.unwrap();
    wait_js(
        &browser,
        "!document.getElementById('token-form').hidden",
        |v| v == true,
    )
    .await;
    set_field(&browser, "token-input", TOKEN).await;
    click(&browser, "#token-form button").await;
    wait_js(
        &browser,
        "document.getElementById('connection').textContent",
        |v| v == "live",
    )
    .await;

    // Submit cube.scene through the form, its assets as separate files.
    let cube = course_scene("cube.scene");
    let dir = cube.parent().unwrap();
    let files: Vec<PathBuf> = std::iter::once(cube.clone())
        .chain(["images/cube.png", "images/tiles.png", "models/cube.obj"].map(|p| dir.join(p)))
        .collect();
    choose_files(&browser, &files).await;
    wait_js(
        &browser,
        "document.getElementById('scene-select').value",
        |v| v == "cube.scene",
    )
    .await;
    for (field, value) in [
        ("width", "480"),
        ("height", "360"),
        ("spp", "12"),
        ("tile-size", "40"),
    ] {
        set_field(&browser, field, value).await;
    }
    click(&browser, "#submit-button").await;
    let status = wait_js(
        &browser,
        "document.getElementById('submit-status').textContent",
        |v| {
            v.as_str()
                .is_some_and(|s| s.starts_with("submitted as job"))
        },
    )
    .await;
    let a: u64 = status
        .as_str()
        .unwrap()
        .rsplit(' ')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let job_a = client.job(a).await.unwrap();
    assert_eq!(
        (job_a.spec.render.width, job_a.tiles_total),
        (480, 108),
        "{job_a:?}"
    );

    // A second job, queued behind the first (one worker), submitted from elsewhere: the page
    // learns of it from the event stream. Large enough (1280×960 at 64 spp, some seconds of
    // work) that it is still queued or running when the page cancels it, however fast the
    // first job finished: a small one could be done by then, its cancel button hidden.
    let mut spec_b = small_spec(64, 64);
    (spec_b.render.width, spec_b.render.height) = (1280, 960);
    let b = submit(&client, &cube, spec_b).await.id;
    let row_b = format!("document.getElementById('job-{b}')");
    wait_js(&browser, &format!("{row_b} !== null"), |v| v == true).await;

    // Mid-render: progress under way, tiles leased on the map, the worker listed.
    let progress_a = format!("document.querySelector('#job-{a} .progress span').textContent");
    let percent = |v: &Value| -> u32 {
        let text = v.as_str().unwrap_or_default();
        let inner = text
            .split('(')
            .nth(1)
            .unwrap_or("0%")
            .trim_end_matches("%)");
        inner.parse().unwrap_or(0)
    };
    let shown = wait_js(&browser, &progress_a, |v| percent(v) >= 25).await;
    wait_js(
        &browser,
        "document.querySelector('#workers tbody').textContent",
        |v| v.as_str().is_some_and(|t| t.contains("dash-worker")),
    )
    .await;
    if percent(&shown) < 100 {
        screenshot(&browser, &artifacts.join("dashboard-rendering.png")).await;
    } else {
        eprintln!("the render finished before the mid-render screenshot");
    }

    // Cancel the second job from the page.
    click(&browser, &format!("#job-{b} button.cancel")).await;
    wait_js(&browser, &format!("{row_b}.dataset.state"), |v| {
        v == "cancelled"
    })
    .await;
    assert_eq!(client.job(b).await.unwrap().state, JobState::Cancelled);

    // The first reaches 100%, and the preview is exactly the job's PNG.
    wait_js(&browser, &progress_a, |v| v == "108/108 (100%)").await;
    wait_js(
        &browser,
        &format!("document.getElementById('job-{a}').dataset.state"),
        |v| v == "done",
    )
    .await;
    wait_js(
        &browser,
        &format!("(p => p.dataset.job === '{a}' && p.dataset.final === 'true')(document.getElementById('preview'))"),
        |v| v == true,
    )
    .await;
    let png = client.image(a).await.unwrap();
    assert_eq!(
        preview_bytes(&browser).await,
        png,
        "the preview differs from the job's PNG"
    );
    let done_tiles = "document.querySelectorAll('#tile-map .tile.done').length";
    wait_js(&browser, done_tiles, |v| v == 108).await;

    // Orbit right and ask for a quick look: a new job from the moved camera.
    let camera: Value = reqwest::Client::new()
        .get(format!("{}/api/v1/jobs/{a}/camera", coord.url))
        .bearer_auth(TOKEN)
        .send()
        .await
        .unwrap()
        .json()
        .await
        .unwrap();
    click(&browser, "[data-orbit='yaw,15']").await;
    click(&browser, "#view-quick").await;
    let c = wait_js(
        &browser,
        "document.getElementById('preview-title').textContent",
        |v| v.as_str().is_some_and(|t| t.ends_with("(quick look)")),
    )
    .await;
    let c: u64 = c.as_str().unwrap()["Job ".len()..]
        .split(':')
        .next()
        .unwrap()
        .parse()
        .unwrap();
    let job_c = client.job(c).await.unwrap();
    let moved = job_c
        .spec
        .render
        .camera
        .expect("the quick look has a camera override");
    assert_eq!(
        serde_json::to_value(moved.look_at).unwrap(),
        camera["look_at"]
    );
    assert_ne!(
        serde_json::to_value(moved.position).unwrap(),
        camera["position"]
    );
    let distance = |p: [f64; 3]| {
        let l = &camera["look_at"];
        (0..3)
            .map(|i| (p[i] - l[i].as_f64().unwrap()).powi(2))
            .sum::<f64>()
            .sqrt()
    };
    let original: [f64; 3] = serde_json::from_value(camera["position"].clone()).unwrap();
    assert!(
        (distance(moved.position) - distance(original)).abs() < 1e-9,
        "an orbit keeps its radius"
    );
    assert_eq!((job_c.spec.render.width, job_c.spec.render.spp), (120, 1));

    // A broken scene is refused with its location shown by the form.
    let broken = tmp.path().join("broken.scene");
    let text = std::fs::read_to_string(&cube).unwrap();
    assert!(text.contains(r#"<fov v=".785"/>"#));
    std::fs::write(
        &broken,
        text.replace(r#"<fov v=".785"/>"#, r#"<fov v="wide"/>"#),
    )
    .unwrap();
    choose_files(&browser, &[broken]).await;
    wait_js(
        &browser,
        "document.getElementById('scene-select').value",
        |v| v == "broken.scene",
    )
    .await;
    click(&browser, "#submit-button").await;
    let error = wait_js(
        &browser,
        "document.getElementById('submit-error').textContent",
        |v| v.as_str().is_some_and(|t| !t.is_empty()),
    )
    .await;
    assert!(
        error.as_str().unwrap().starts_with("broken.scene:4:"),
        "{error}"
    );

    // The finished job again, for the record.
    click(&browser, &format!("#job-{a} td")).await;
    wait_js(
        &browser,
        &format!("(p => p.dataset.job === '{a}' && p.dataset.final === 'true')(document.getElementById('preview'))"),
        |v| v == true,
    )
    .await;
    screenshot(&browser, &artifacts.join("dashboard.png")).await;

    // Opened afresh, by the `#token=` URL `coordinator serve` prints on a terminal, the page
    // shows the job rendering, not the newest (queued behind it) and not none.
    let mut long = small_spec(64, 40);
    (long.render.width, long.render.height) = (480, 360);
    let d = submit(&client, &cube, long).await.id;
    let e = submit(&client, &cube, small_spec(1, 16)).await.id;
    wait_until(&client, d, Duration::from_secs(30), |j| {
        j.state == JobState::Running
    })
    .await;
    browser
        .execute("sessionStorage.clear(); return null;")
        .await
        .unwrap();
    browser
        .goto(&format!("{}/#token={TOKEN}", coord.url))
        .await
        .unwrap();
    browser.refresh().await.unwrap();
    wait_js(
        &browser,
        "document.getElementById('connection').textContent",
        |v| v == "live",
    )
    .await;
    wait_js(
        &browser,
        "document.getElementById('preview-title').textContent",
        |v| {
            v.as_str()
                .is_some_and(|t| t.starts_with(&format!("Job {d}:")))
        },
    )
    .await;
    wait_js(
        &browser,
        &format!("document.getElementById('preview').dataset.job === '{d}'"),
        |v| v == true,
    )
    .await;
    assert_eq!(client.job(e).await.unwrap().state, JobState::Queued);
    assert_eq!(
        browser.current_url().await.unwrap().split_once('#'),
        None,
        "the token is taken out of the address bar"
    );
    for id in [d, e] {
        client.cancel(id).await.unwrap();
    }
    browser.close().await.unwrap();
}

/// A progressive job refines live on the page: the preview, the convergence plot and the
/// sample map change pass after pass while the job runs, and end on the job's final PNG.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_dashboard_shows_a_progressive_job_refine_pass_by_pass() {
    let Some(DashboardFarm {
        tmp: _tmp,
        coord,
        client,
        _worker,
        _driver,
        browser,
    }) = DashboardFarm::start("the progressive dashboard test", "progressive-worker").await
    else {
        return;
    };
    // About nine passes (mean spp 2, 3, 4.5, ... up to 32) on one thread: several seconds.
    let mut spec = small_spec(1, 40);
    spec.render.width = 240;
    spec.render.height = 180;
    spec.adaptive = Some(protocol::AdaptiveSpec {
        noise_threshold: 0.0,
        spp_min: 2,
        spp_max: 32,
        time_limit_s: None,
    });
    let job = submit(&client, &course_scene("cornell_box.scene"), spec).await;
    browser
        .goto(&format!("{}/#token={TOKEN}", coord.url))
        .await
        .unwrap();
    wait_js(
        &browser,
        "!document.getElementById('progressive').hidden",
        |v| v == true,
    )
    .await;
    let plotted = "Number(document.getElementById('convergence-plot').dataset.passes || 0)";
    wait_js(&browser, plotted, |v| v.as_u64().is_some_and(|n| n >= 1)).await;
    let early = preview_bytes(&browser).await;
    let early_running = client.job(job.id).await.unwrap().state == JobState::Running;
    let map = "Number(document.getElementById('sample-map').dataset.passes || 0)";
    wait_js(&browser, map, |v| v.as_u64().is_some_and(|n| n >= 3)).await;
    let status = wait_js(
        &browser,
        "document.getElementById('progressive-status').textContent",
        |v| v.as_str().is_some_and(|s| s.contains("mean spp")),
    )
    .await;
    assert!(
        status.as_str().unwrap().contains("estimated error"),
        "{status}"
    );
    screenshot(&browser, &artifacts_dir().join("dashboard-progressive.png")).await;
    let done = wait_finished(&client, job.id, Duration::from_secs(120)).await;
    assert_eq!(done.state, JobState::Done);
    wait_js(&browser, plotted, |v| {
        v.as_u64() == done.passes.map(u64::from)
    })
    .await;
    let png = client.image(job.id).await.unwrap();
    let start = Instant::now();
    while preview_bytes(&browser).await != png {
        assert!(
            start.elapsed() < Duration::from_secs(20),
            "the preview never showed the final PNG"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
    if early_running {
        assert_ne!(early, png, "the preview refined after the first passes");
    }
    browser.close().await.unwrap();
}

/// Reads `coordinator serve`'s stdout until its dashboard line.
fn dashboard_line(mut cmd: Command, log: PathBuf) -> String {
    use std::io::{BufRead, BufReader};
    cmd.stdout(std::process::Stdio::piped());
    let mut proc = Proc::spawn(cmd, log);
    let stdout = proc.child.stdout.take().unwrap();
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines() {
            let Ok(line) = line else { break };
            if line.contains("dashboard: ") {
                let _ = tx.send(line.trim().to_string());
                break;
            }
        }
    });
    let line = rx
        .recv_timeout(Duration::from_secs(20))
        .unwrap_or_else(|_| panic!("no dashboard line: {}", proc.log_text()));
    line[line.find("dashboard: ").unwrap()..].to_string()
}

#[test]
fn serve_hands_the_dashboard_its_token_on_a_terminal_only() {
    let tmp = tempfile::tempdir().unwrap();
    let serve = |dir: &str| {
        [
            "serve",
            "--listen",
            "127.0.0.1:0",
            "--data-dir",
            tmp.path().join(dir).to_str().unwrap(),
            "--token",
            "a+b/c=",
        ]
        .map(String::from)
    };
    // Through a pipe (a service's log): the URL without the token.
    let mut piped = Command::new(&bins().coordinator);
    piped.args(serve("piped"));
    let line = dashboard_line(piped, tmp.path().join("piped.log"));
    assert!(
        line.starts_with("dashboard: http://127.0.0.1:") && line.ends_with('/'),
        "{line}"
    );
    // On a terminal (util-linux `script` gives it one): the token, percent-encoded.
    if Command::new("script").arg("--version").output().is_err() {
        eprintln!("skipping the terminal half: no `script` (util-linux)");
        return;
    }
    let command: Vec<String> = std::iter::once(bins().coordinator.display().to_string())
        .chain(serve("tty"))
        .collect();
    let mut tty = Command::new("script");
    tty.args(["-qfec", &command.join(" "), "/dev/null"]);
    let line = dashboard_line(tty, tmp.path().join("tty.log"));
    assert!(
        line.starts_with("dashboard: http://127.0.0.1:") && line.ends_with("/#token=a%2Bb%2Fc%3D"),
        "{line}"
    );
}
