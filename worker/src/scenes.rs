//! Scenes by job: each job's bundle is fetched and its scene built once, however many of its
//! tiles a worker renders, and however many in-process workers share the cache.

use std::collections::{HashMap, VecDeque};
use std::sync::{Arc, Mutex};
use std::time::Instant;

use tokio::sync::OnceCell;
use tracer_core::scene::SceneDescription;
use tracer_core::{MemoryAssets, Scene};

use protocol::client::{Client, ClientError};

/// How many jobs' scenes stay loaded: the current one and a few recent ones, so tiles of
/// interleaved jobs (stragglers) don't rebuild scenes.
const KEEP_JOBS: usize = 4;

/// Why a job's scene is not available.
#[derive(Debug, Clone, thiserror::Error)]
pub enum LoadError {
    /// The bundle could not be fetched (network, coordinator restart): worth retrying.
    #[error("fetching the bundle failed: {0}")]
    Fetch(String),
    /// The scene does not load: the job cannot be rendered by any worker.
    #[error("{0}")]
    Scene(String),
}

type Slot = Arc<OnceCell<Arc<Scene>>>;

#[derive(Default)]
pub struct SceneCache {
    /// Most recently used last.
    slots: Mutex<VecDeque<(u64, Slot)>>,
}

impl SceneCache {
    pub fn new() -> Arc<Self> {
        Arc::new(Self::default())
    }

    /// Stores the scene of `job_id` built elsewhere in this process (the embedded farm's
    /// coordinator builds it to check the submission), so no worker fetches or builds it
    /// again. A scene already there, or being loaded, stays.
    pub fn insert(&self, job_id: u64, scene: Arc<Scene>) {
        let mut slots = self.slots.lock().unwrap();
        let slot = match slots.iter().position(|(id, _)| *id == job_id) {
            Some(i) => slots.remove(i).unwrap().1,
            None => Slot::default(),
        };
        let _ = slot.set(scene);
        slots.push_back((job_id, slot));
        while slots.len() > KEEP_JOBS {
            slots.pop_front();
        }
    }

    /// The scene of `job_id`, fetching and building it on first use. Concurrent callers for
    /// the same job wait for one load; a failed load is not cached, so it is retried.
    pub async fn get(&self, client: &Client, job_id: u64) -> Result<Arc<Scene>, LoadError> {
        let slot = {
            // A std Mutex: nothing awaits while it is held.
            let mut slots = self.slots.lock().unwrap();
            let slot = match slots.iter().position(|(id, _)| *id == job_id) {
                Some(i) => slots.remove(i).unwrap().1,
                None => Slot::default(),
            };
            slots.push_back((job_id, slot.clone()));
            while slots.len() > KEEP_JOBS {
                slots.pop_front();
            }
            slot
        };
        slot.get_or_try_init(|| load(client, job_id)).await.cloned()
    }
}

async fn load(client: &Client, job_id: u64) -> Result<Arc<Scene>, LoadError> {
    let start = Instant::now();
    let fetch = |e: ClientError| LoadError::Fetch(e.to_string());
    let bundle = client.bundle(job_id).await.map_err(fetch)?;
    let scene_bytes = client.blob(&bundle.scene_hash).await.map_err(fetch)?;
    let mut assets = MemoryAssets {
        files: HashMap::new(),
    };
    // Several paths may share one content; fetch each hash once.
    let mut by_hash: HashMap<&str, Vec<u8>> = HashMap::new();
    for file in &bundle.assets {
        if !by_hash.contains_key(file.hash.as_str()) {
            let bytes = client.blob(&file.hash).await.map_err(fetch)?;
            if protocol::hash_hex(&bytes) != file.hash {
                return Err(LoadError::Fetch(format!(
                    "asset {} arrived corrupted (hash mismatch)",
                    file.path
                )));
            }
            by_hash.insert(&file.hash, bytes);
        }
        assets
            .files
            .insert(file.path.clone(), by_hash[file.hash.as_str()].clone());
    }
    let scene_file = bundle.scene_file.clone();
    let scene = tokio::task::spawn_blocking(move || {
        let text = String::from_utf8(scene_bytes)
            .map_err(|_| LoadError::Scene(format!("{scene_file}: the scene is not UTF-8 text")))?;
        let desc = SceneDescription::parse(&text, &scene_file)
            .map_err(|e| LoadError::Scene(e.to_string()))?;
        Scene::build(&desc, &scene_file, &assets).map_err(|e| LoadError::Scene(e.to_string()))
    })
    .await
    .map_err(|e| LoadError::Scene(format!("loading the scene panicked: {e}")))??;
    tracing::info!(
        "job {job_id}: loaded {} ({} assets) in {:.2}s",
        bundle.scene_file,
        bundle.assets.len(),
        start.elapsed().as_secs_f64()
    );
    Ok(Arc::new(scene))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test]
    async fn an_inserted_scene_is_served_without_fetching_anything() {
        let text = r#"<scene><camera><fov v="0.9"/><near_clip v="0.1"/><far_clip v="100"/>
            <position x="0" y="0" z="10"/><orientation a="0" x="0" y="1" z="0"/>
            </camera><background_color r="0" g="0" b="0"/><refractive_index v="1"/></scene>"#;
        let desc = SceneDescription::parse(text, "t.scene").unwrap();
        let assets = MemoryAssets {
            files: HashMap::new(),
        };
        let scene = Arc::new(Scene::build(&desc, "t.scene", &assets).unwrap());
        let cache = SceneCache::new();
        cache.insert(7, scene.clone());
        // Nothing listens on the discard port: any fetch would fail.
        let client = Client::new("http://127.0.0.1:9", None).unwrap();
        let got = cache.get(&client, 7).await.unwrap();
        assert!(Arc::ptr_eq(&got, &scene));
        assert!(matches!(
            cache.get(&client, 8).await,
            Err(LoadError::Fetch(_))
        ));
    }
}
