//! Where a scene's textures and meshes come from: the file system for local renders, an
//! in-memory bundle on farm workers.

use std::collections::HashMap;
use std::io;
use std::path::{Path, PathBuf};

/// Reads an asset by the path exactly as the scene file writes it.
pub trait AssetSource: Sync {
    fn read(&self, path: &str) -> io::Result<Vec<u8>>;

    /// A name for error messages (the resolved file path where there is one).
    fn display_name(&self, path: &str) -> String {
        path.to_string()
    }
}

/// Resolves asset paths relative to the scene file's folder, falling back to that folder's
/// parent (the course's original project-root layout, conventions §1.13).
#[derive(Clone, Debug)]
pub struct FsAssets {
    scene_dir: PathBuf,
}

impl FsAssets {
    pub fn for_scene(scene_path: &Path) -> Self {
        let scene_dir = scene_path
            .parent()
            .map(Path::to_path_buf)
            .unwrap_or_default();
        Self { scene_dir }
    }

    /// The file an asset path names, or None when neither candidate exists.
    pub fn resolve(&self, path: &str) -> Option<PathBuf> {
        let relative = Path::new(path);
        if relative.is_absolute() {
            return relative.is_file().then(|| relative.to_path_buf());
        }
        let primary = self.scene_dir.join(relative);
        if primary.is_file() {
            return Some(primary);
        }
        let fallback = self.scene_dir.parent()?.join(relative);
        fallback.is_file().then_some(fallback)
    }
}

impl AssetSource for FsAssets {
    fn read(&self, path: &str) -> io::Result<Vec<u8>> {
        match self.resolve(path) {
            Some(file) => std::fs::read(file),
            None => Err(io::Error::new(
                io::ErrorKind::NotFound,
                format!(
                    "not found in {} or its parent folder",
                    self.scene_dir.display()
                ),
            )),
        }
    }

    fn display_name(&self, path: &str) -> String {
        match self.resolve(path) {
            Some(file) => file.display().to_string(),
            None => path.to_string(),
        }
    }
}

/// Assets held in memory, keyed by the path the scene uses (a farm job's bundle).
#[derive(Clone, Debug, Default)]
pub struct MemoryAssets {
    pub files: HashMap<String, Vec<u8>>,
}

impl AssetSource for MemoryAssets {
    fn read(&self, path: &str) -> io::Result<Vec<u8>> {
        self.files.get(path).cloned().ok_or_else(|| {
            io::Error::new(io::ErrorKind::NotFound, "not part of the scene's bundle")
        })
    }
}
