//! Files under the data dir: content-addressed blobs (scenes and assets, each stored once),
//! finished tiles' pixels and finished images (each frame's PNG and, beside it, its linear
//! f32 pixels, from which EXR and PFM are encoded on request). Every write goes to a temporary name first and
//! is renamed into place, so a crash never leaves a half-written file under a real name.

use std::fs;
use std::io::{ErrorKind, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use protocol::{pixels_from_bytes, pixels_to_bytes};
use tracer_core::{Image, TileRect};

use super::StoreError;

#[derive(Debug)]
pub struct Files {
    root: PathBuf,
    tmp_counter: AtomicU64,
}

fn is_hash(hash: &str) -> bool {
    hash.len() == 64
        && hash
            .bytes()
            .all(|b| b.is_ascii_hexdigit() && !b.is_ascii_uppercase())
}

impl Files {
    pub fn open(root: &Path) -> Result<Files, StoreError> {
        for dir in ["blobs", "jobs", "tmp"] {
            let path = root.join(dir);
            fs::create_dir_all(&path)
                .map_err(|e| StoreError::io(format!("creating {}", path.display()), e))?;
        }
        // Leftovers of writes a crash interrupted.
        if let Ok(entries) = fs::read_dir(root.join("tmp")) {
            for entry in entries.flatten() {
                let _ = fs::remove_file(entry.path());
            }
        }
        Ok(Files {
            root: root.to_path_buf(),
            tmp_counter: AtomicU64::new(0),
        })
    }

    fn write_atomic(&self, path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
        let n = self.tmp_counter.fetch_add(1, Ordering::Relaxed);
        let tmp = self
            .root
            .join("tmp")
            .join(format!("{}-{n}", std::process::id()));
        let write = || -> std::io::Result<()> {
            if let Some(parent) = path.parent() {
                fs::create_dir_all(parent)?;
            }
            let mut file = fs::File::create(&tmp)?;
            file.write_all(bytes)?;
            drop(file);
            fs::rename(&tmp, path)
        };
        write().map_err(|e| {
            let _ = fs::remove_file(&tmp);
            StoreError::io(format!("writing {}", path.display()), e)
        })
    }

    fn blob_path(&self, hash: &str) -> PathBuf {
        self.root.join("blobs").join(&hash[..2]).join(hash)
    }

    /// Stores `bytes` under their hash unless already there; returns the hash.
    pub fn put_blob(&self, bytes: &[u8]) -> Result<String, StoreError> {
        let hash = protocol::hash_hex(bytes);
        let path = self.blob_path(&hash);
        if !path.exists() {
            self.write_atomic(&path, bytes)?;
        }
        Ok(hash)
    }

    pub fn has_blob(&self, hash: &str) -> bool {
        is_hash(hash) && self.blob_path(hash).is_file()
    }

    /// The blob's bytes; `None` for an unknown or malformed hash.
    pub fn blob(&self, hash: &str) -> Result<Option<Vec<u8>>, StoreError> {
        if !is_hash(hash) {
            return Ok(None);
        }
        let path = self.blob_path(hash);
        match fs::read(&path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
            Err(e) => Err(StoreError::io(format!("reading {}", path.display()), e)),
        }
    }

    fn job_dir(&self, job_id: u64) -> PathBuf {
        self.root.join("jobs").join(job_id.to_string())
    }

    fn tile_path(&self, job_id: u64, tile: u32) -> PathBuf {
        self.job_dir(job_id)
            .join("tiles")
            .join(format!("{tile}.f32"))
    }

    pub fn image_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("image.png")
    }

    fn linear_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("image.f32")
    }

    /// Persists a finished tile's pixels (f32 little-endian), before it is acknowledged.
    pub fn put_tile(&self, job_id: u64, tile: u32, pixels: &[u8]) -> Result<(), StoreError> {
        self.write_atomic(&self.tile_path(job_id, tile), pixels)
    }

    pub fn tile(&self, job_id: u64, tile: u32, rect: TileRect) -> Result<Image, StoreError> {
        let path = self.tile_path(job_id, tile);
        let bytes = fs::read(&path)
            .map_err(|e| StoreError::io(format!("reading {}", path.display()), e))?;
        let pixels = pixels_from_bytes(&bytes, rect)
            .map_err(|e| StoreError::Corrupt(format!("{}: {e}", path.display())))?;
        Image::from_pixels(rect.width, rect.height, pixels)
            .map_err(|e| StoreError::Corrupt(format!("{}: {e}", path.display())))
    }

    /// Assembles an image from the given finished tiles (tracer-core's one assembly path);
    /// the others stay black.
    pub fn assemble(
        &self,
        job_id: u64,
        width: u32,
        height: u32,
        tiles: &[(u32, TileRect)],
    ) -> Result<Image, StoreError> {
        let tiles = tiles
            .iter()
            .map(|&(index, rect)| Ok((rect, self.tile(job_id, index, rect)?)));
        tracer_core::film::assemble(width, height, tiles)
    }

    /// Writes the final PNG and its linear pixels, then drops the tiles they were made of.
    /// The linear pixels take what the tiles took, so a job never holds more on disk than
    /// while it rendered. The PNG is written last: its presence marks a complete image.
    pub fn put_image(&self, job_id: u64, png: &[u8], linear: &Image) -> Result<(), StoreError> {
        self.write_atomic(&self.linear_path(job_id), &pixels_to_bytes(&linear.pixels))?;
        self.write_atomic(&self.image_path(job_id), png)?;
        let _ = fs::remove_dir_all(self.job_dir(job_id).join("tiles"));
        Ok(())
    }

    pub fn image(&self, job_id: u64) -> Result<Option<Vec<u8>>, StoreError> {
        Self::read_optional(&self.image_path(job_id))
    }

    /// The linear pixels stored by [`Files::put_image`] for a `width`×`height` job.
    pub fn linear_image(
        &self,
        job_id: u64,
        width: u32,
        height: u32,
    ) -> Result<Option<Image>, StoreError> {
        Self::read_linear(&self.linear_path(job_id), width, height)
    }

    fn frame_path(&self, job_id: u64, frame: u32, extension: &str) -> PathBuf {
        self.job_dir(job_id)
            .join("frames")
            .join(format!("{frame:04}.{extension}"))
    }

    /// One frame of a frame-range job, PNG and linear pixels. Written before
    /// [`Files::put_image`], which drops the tiles every frame is assembled from.
    pub fn put_frame_image(
        &self,
        job_id: u64,
        frame: u32,
        png: &[u8],
        linear: &Image,
    ) -> Result<(), StoreError> {
        let linear_bytes = pixels_to_bytes(&linear.pixels);
        self.write_atomic(&self.frame_path(job_id, frame, "f32"), &linear_bytes)?;
        self.write_atomic(&self.frame_path(job_id, frame, "png"), png)
    }

    pub fn frame_image(&self, job_id: u64, frame: u32) -> Result<Option<Vec<u8>>, StoreError> {
        Self::read_optional(&self.frame_path(job_id, frame, "png"))
    }

    /// The linear pixels of one frame stored by [`Files::put_frame_image`].
    pub fn frame_linear_image(
        &self,
        job_id: u64,
        frame: u32,
        width: u32,
        height: u32,
    ) -> Result<Option<Image>, StoreError> {
        Self::read_linear(&self.frame_path(job_id, frame, "f32"), width, height)
    }

    fn read_linear(path: &Path, width: u32, height: u32) -> Result<Option<Image>, StoreError> {
        let Some(bytes) = Self::read_optional(path)? else {
            return Ok(None);
        };
        let corrupt =
            |e: &dyn std::fmt::Display| StoreError::Corrupt(format!("{}: {e}", path.display()));
        let pixels = pixels_from_bytes(&bytes, TileRect::new(0, 0, width, height))
            .map_err(|e| corrupt(&e))?;
        Image::from_pixels(width, height, pixels)
            .map(Some)
            .map_err(|e| corrupt(&e))
    }

    fn read_optional(path: &Path) -> Result<Option<Vec<u8>>, StoreError> {
        match fs::read(path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
            Err(e) => Err(StoreError::io(format!("reading {}", path.display()), e)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn blobs_are_stored_once_by_content() {
        let dir = tempfile::tempdir().unwrap();
        let files = Files::open(dir.path()).unwrap();
        let a = files.put_blob(b"hello").unwrap();
        let b = files.put_blob(b"hello").unwrap();
        assert_eq!(a, b);
        assert!(files.has_blob(&a));
        assert_eq!(files.blob(&a).unwrap().unwrap(), b"hello");
        let stored: usize = fs::read_dir(dir.path().join("blobs"))
            .unwrap()
            .map(|d| fs::read_dir(d.unwrap().path()).unwrap().count())
            .sum();
        assert_eq!(stored, 1);
        assert_eq!(files.blob("../../etc/passwd").unwrap(), None);
        assert!(!files.has_blob("zz"));
    }

    #[test]
    fn tiles_assemble_into_an_image() {
        let dir = tempfile::tempdir().unwrap();
        let files = Files::open(dir.path()).unwrap();
        let rects = TileRect::grid(3, 2, 2);
        let mut expected = Image::new(3, 2);
        for (i, rect) in rects.iter().enumerate() {
            let mut tile = Image::new(rect.width, rect.height);
            tile.pixels.iter_mut().for_each(|p| *p = i as f32 / 4.0);
            expected.insert(*rect, &tile);
            files
                .put_tile(7, i as u32, &pixels_to_bytes(&tile.pixels))
                .unwrap();
        }
        let all: Vec<(u32, TileRect)> = rects
            .iter()
            .enumerate()
            .map(|(i, r)| (i as u32, *r))
            .collect();
        let assembled = files.assemble(7, 3, 2, &all).unwrap();
        assert_eq!(assembled, expected);
        assert_eq!(files.linear_image(7, 3, 2).unwrap(), None);
        files.put_image(7, b"png", &assembled).unwrap();
        assert_eq!(files.image(7).unwrap().unwrap(), b"png");
        assert_eq!(files.linear_image(7, 3, 2).unwrap(), Some(expected));
        assert!(
            matches!(files.linear_image(7, 3, 3), Err(StoreError::Corrupt(_))),
            "a stored image of the wrong size is corrupt, not a panic"
        );
        assert!(
            files.tile(7, 0, rects[0]).is_err(),
            "tiles are dropped with the image"
        );
    }
}
