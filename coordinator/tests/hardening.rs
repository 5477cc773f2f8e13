//! The coordinator over HTTP in this process: budgets checked before a job is stored, for
//! submissions and resubmits alike, and worker identities issued by the coordinator.

use std::sync::Arc;

use coordinator::clock::SystemClock;
use coordinator::config::FarmConfig;
use coordinator::farm::Farm;
use protocol::client::{Client, ClientError, Submission};
use protocol::{JobSpec, LeaseRequest};

struct Server {
    client: Client,
    url: String,
    stop: tokio::sync::oneshot::Sender<()>,
    task: tokio::task::JoinHandle<std::io::Result<()>>,
    _dir: tempfile::TempDir,
}

async fn start(config: FarmConfig) -> Server {
    let dir = tempfile::tempdir().unwrap();
    let farm = Farm::open(dir.path(), config, Arc::new(SystemClock)).unwrap();
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0").await.unwrap();
    let url = format!("http://{}", listener.local_addr().unwrap());
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let task = tokio::spawn(coordinator::server::serve(
        listener,
        farm,
        None,
        async move {
            let _ = stopped.await;
        },
    ));
    Server {
        client: Client::new(&url, None).unwrap(),
        url,
        stop,
        task,
        _dir: dir,
    }
}

impl Server {
    async fn shutdown(self) {
        let _ = self.stop.send(());
        self.task.await.unwrap().unwrap();
    }
}

/// A still scene with one sphere: enough to load, nothing to render here.
fn submission(tile_size: u32) -> Submission {
    let scene = r#"<scene>
        <camera><fov v="0.785"/><near_clip v="0.1"/><far_clip v="100"/>
            <position x="0" y="0" z="5"/><orientation a="0" x="0" y="1" z="0"/></camera>
        <background_color r="0" g="0" b="0"/><refractive_index v="1"/>
        <material name="m"><ambient r="1" g="1" b="1"/><diffuse r="1" g="1" b="1"/>
            <specular r="0" g="0" b="0"/><shininess v="1"/></material>
        <sphere material="m"><position x="0" y="0" z="0"/><radius v="1"/></sphere>
    </scene>"#;
    let mut spec = JobSpec::default();
    spec.render.width = 64;
    spec.render.height = 64;
    spec.tile_size = tile_size;
    Submission {
        spec,
        scene_file: "one.scene".into(),
        scene: scene.as_bytes().to_vec(),
        assets: vec![],
    }
}

fn refused(result: Result<impl std::fmt::Debug, ClientError>, needle: &str) {
    match result {
        Err(ClientError::Api {
            status: 400,
            message,
            ..
        }) => assert!(message.contains(needle), "{message}"),
        other => panic!("expected a 400 naming {needle:?}, got {other:?}"),
    }
}

#[tokio::test]
async fn the_tile_budget_refuses_submissions_and_resubmits_before_they_are_stored() {
    let server = start(FarmConfig {
        limits: coordinator::config::Limits {
            max_job_tiles: 100,
            ..Default::default()
        },
        ..FarmConfig::default()
    })
    .await;
    let client = &server.client;
    // 64x64 in 4-pixel tiles: 256 tiles.
    refused(client.submit(&submission(4)).await, "--max-job-tiles");
    let job = client.submit(&submission(16)).await.unwrap();
    assert_eq!(job.tiles_total, 16);

    let http = reqwest::Client::new();
    let resubmit = |body: serde_json::Value| {
        let url = format!("{}/api/v1/jobs/{}/resubmit", server.url, job.id);
        let http = http.clone();
        async move {
            let resp = http.post(url).json(&body).send().await.unwrap();
            let status = resp.status().as_u16();
            (status, resp.json::<serde_json::Value>().await.unwrap())
        }
    };
    let (status, body) =
        resubmit(serde_json::json!({"render": {"width": 64, "height": 64}, "tile_size": 4})).await;
    assert_eq!(status, 400, "{body}");
    assert!(
        body["error"].as_str().unwrap().contains("--max-job-tiles"),
        "{body}"
    );
    // A still scene cannot be resubmitted as a frame range either.
    let (status, body) = resubmit(serde_json::json!({
        "render": {"width": 64, "height": 64}, "tile_size": 16, "frames": {"first": 0, "last": 3}
    }))
    .await;
    assert_eq!(status, 400, "{body}");
    assert!(body["error"].as_str().unwrap().contains("frame"), "{body}");
    // Nothing refused was stored.
    assert_eq!(client.jobs().await.unwrap().len(), 1);
    server.shutdown().await;
}

#[tokio::test]
async fn workers_sharing_a_name_get_their_own_identities_and_leases() {
    let server = start(FarmConfig::default()).await;
    let client = &server.client;
    client.submit(&submission(16)).await.unwrap();
    let a = client.register("same-host").await.unwrap();
    let b = client.register("same-host").await.unwrap();
    assert_ne!(a.worker_id, b.worker_id);
    let lease = |worker_id| LeaseRequest {
        worker_id,
        wait_ms: 0,
    };
    let la = client.lease(&lease(a.worker_id)).await.unwrap().unwrap();
    let lb = client.lease(&lease(b.worker_id)).await.unwrap().unwrap();
    assert_ne!(la.lease_id, lb.lease_id);
    assert_ne!(la.tile, lb.tile);
    // An id the coordinator never issued is told to register.
    assert!(matches!(
        client.lease(&lease(a.worker_id + 1000)).await,
        Err(ClientError::UnknownWorker(_))
    ));
    let page = client.tiles(la.job_id, 0, 16).await.unwrap();
    let holders: Vec<&Vec<String>> = page
        .tiles
        .iter()
        .filter(|t| !t.workers.is_empty())
        .map(|t| &t.workers)
        .collect();
    assert_eq!(holders.len(), 2, "two tiles, one holder each");
    server.shutdown().await;
}
