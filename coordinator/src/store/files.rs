//! Files under the data dir: content-addressed blobs (scenes and assets, each stored once),
//! finished tiles' pixels and finished images (each frame's PNG and, beside it, its linear
//! f32 pixels, from which EXR and PFM are encoded on request). Blobs and images go to a
//! temporary name first and are renamed into place, so a crash never leaves a half-written
//! file under a real name.
//!
//! A job's tiles share one sparse file, each at a fixed slot (its index times the slot of a
//! full tile): a tile costs one positioned write, no file of its own and no rename. Each slot
//! starts with a header naming its tile, so a slot never written (a hole reads as zeros) or
//! cut off is an error, not a black tile. A tile is counted done only after its write, so a
//! killed process never leaves a done tile whose slot was half written.
//!
//! A farm that ends with its process (`coordinator render` without `--data-dir`) keeps the
//! same things in memory instead ([`Files::in_memory`]): each tile decoded straight into its
//! place in its frame as it lands, images as they were made. The final image is that frame
//! itself: nothing is read back, copied or converted at the end, and there is no folder to
//! remove at exit.

use std::collections::{BTreeMap, BTreeSet, HashMap};
use std::fs;
use std::io::{ErrorKind, Write};
use std::os::unix::fs::FileExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

use protocol::{pixels_from_bytes, pixels_to_bytes};
use tracer_core::{Image, TileRect};

use super::StoreError;

#[derive(Debug)]
pub struct Files {
    root: PathBuf,
    tmp_counter: AtomicU64,
    /// Set for a store kept in memory: `root` then only names the paths used as keys.
    memory: Option<Memory>,
}

/// An in-memory store's contents, keyed by the paths the disk store would use.
#[derive(Debug, Default)]
struct Memory {
    /// What the disk store writes as whole files: blobs, PNGs, sums.
    bytes: Mutex<HashMap<PathBuf, Vec<u8>>>,
    /// What it writes as linear f32 pixels: each finished image, kept as it was made.
    images: Mutex<HashMap<PathBuf, Arc<Image>>>,
    /// Each job's frames being rendered, by frame number.
    frames: Mutex<HashMap<u64, HashMap<u32, Canvas>>>,
}

/// A frame of a job in memory: its finished tiles decoded into place as they land, so the
/// final image is this one, not a copy assembled after the last tile (on an 800×600 frame
/// that copy took 5 ms, most of it faulting in the fresh 5.8 MB image, all after the render).
#[derive(Debug)]
struct Canvas {
    /// Shared with the final image's encoder and store until the tiles are dropped; a tile
    /// landing meanwhile (a lapsed lease's late copy) writes into a copy of its own.
    image: Arc<Image>,
    /// The tiles in it, and where each lies.
    tiles: BTreeMap<u32, TileRect>,
}

/// The frame a tile belongs to: its number and size.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Frame {
    pub number: u32,
    pub width: u32,
    pub height: u32,
}

impl Memory {
    /// Decodes a tile's pixels (f32 little-endian) into its place in its frame.
    fn place_tile(
        &self,
        job_id: u64,
        frame: Frame,
        tile: u32,
        rect: TileRect,
        pixels: &[u8],
    ) -> Result<(), StoreError> {
        let corrupt = |why: String| StoreError::Corrupt(format!("job {job_id} tile {tile}: {why}"));
        let row_bytes = 12 * rect.width as usize;
        if pixels.len() != rect.pixel_count() * 12 || pixels.is_empty() {
            return Err(corrupt(format!(
                "a {}x{} tile is {} bytes of f32 RGB, got {}",
                rect.width,
                rect.height,
                rect.pixel_count() * 12,
                pixels.len()
            )));
        }
        let inside =
            |start: u32, len: u32, size: u32| start.checked_add(len).is_some_and(|end| end <= size);
        if !inside(rect.x, rect.width, frame.width) || !inside(rect.y, rect.height, frame.height) {
            return Err(corrupt(format!(
                "{}x{} at {},{} lies outside the {}x{} frame",
                rect.width, rect.height, rect.x, rect.y, frame.width, frame.height
            )));
        }
        let mut frames = locked(&self.frames);
        let canvas = frames
            .entry(job_id)
            .or_default()
            .entry(frame.number)
            .or_insert_with(|| Canvas {
                image: Arc::new(Image::new(frame.width, frame.height)),
                tiles: BTreeMap::new(),
            });
        if (canvas.image.width, canvas.image.height) != (frame.width, frame.height) {
            return Err(corrupt(format!(
                "its frame is {}x{}, not {}x{}",
                canvas.image.width, canvas.image.height, frame.width, frame.height
            )));
        }
        let image = Arc::make_mut(&mut canvas.image);
        for (row, bytes) in pixels.chunks_exact(row_bytes).enumerate() {
            let start = 3 * ((rect.y as usize + row) * frame.width as usize + rect.x as usize);
            let values = &mut image.pixels[start..start + 3 * rect.width as usize];
            for (value, b) in values.iter_mut().zip(bytes.chunks_exact(4)) {
                *value = f32::from_le_bytes([b[0], b[1], b[2], b[3]]);
            }
        }
        canvas.tiles.insert(tile, rect);
        Ok(())
    }

    fn assemble(
        &self,
        job_id: u64,
        frame: Frame,
        tiles: &[(u32, TileRect)],
    ) -> Result<Arc<Image>, StoreError> {
        let frames = locked(&self.frames);
        let canvas = frames.get(&job_id).and_then(|f| f.get(&frame.number));
        let landed =
            |index: u32, rect: TileRect| canvas.is_some_and(|c| c.tiles.get(&index) == Some(&rect));
        if let Some(&(index, _)) = tiles.iter().find(|&&(i, r)| !landed(i, r)) {
            return Err(StoreError::Corrupt(format!(
                "job {job_id}: tile {index} is missing"
            )));
        }
        let Some(canvas) = canvas else {
            return Ok(Arc::new(Image::new(frame.width, frame.height)));
        };
        if (canvas.image.width, canvas.image.height) != (frame.width, frame.height) {
            return Err(StoreError::Corrupt(format!(
                "job {job_id}: frame {} is {}x{}, not {}x{}",
                frame.number, canvas.image.width, canvas.image.height, frame.width, frame.height
            )));
        }
        let asked: BTreeSet<u32> = tiles.iter().map(|&(i, _)| i).collect();
        if asked.len() == canvas.tiles.len() {
            // Every tile that landed, and only those: the frame as it is.
            return Ok(canvas.image.clone());
        }
        // A preview of some of them (a tile landed but is not counted done yet).
        let mut image = Image::new(frame.width, frame.height);
        for &(_, rect) in tiles {
            image.try_insert(rect, &canvas.image.crop(rect))?;
        }
        Ok(Arc::new(image))
    }
}

fn locked<T>(mutex: &Mutex<T>) -> MutexGuard<'_, T> {
    // Every change to these maps is a single insert or removal: a panic elsewhere while one
    // was held leaves nothing half-done.
    mutex.lock().unwrap_or_else(|p| p.into_inner())
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
            memory: None,
        })
    }

    /// A store that keeps everything in this process's memory and nothing on disk, for a
    /// farm whose data ends with its process (its database is in memory too).
    pub fn in_memory() -> Files {
        Files {
            root: PathBuf::from("memory"),
            tmp_counter: AtomicU64::new(0),
            memory: Some(Memory::default()),
        }
    }

    fn write_atomic(&self, path: &Path, bytes: &[u8]) -> Result<(), StoreError> {
        if let Some(memory) = &self.memory {
            locked(&memory.bytes).insert(path.to_path_buf(), bytes.to_vec());
            return Ok(());
        }
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
        if !self.exists(&path) {
            self.write_atomic(&path, bytes)?;
        }
        Ok(hash)
    }

    fn exists(&self, path: &Path) -> bool {
        match &self.memory {
            Some(memory) => locked(&memory.bytes).contains_key(path),
            None => path.is_file(),
        }
    }

    pub fn has_blob(&self, hash: &str) -> bool {
        is_hash(hash) && self.exists(&self.blob_path(hash))
    }

    /// The blob's bytes; `None` for an unknown or malformed hash.
    pub fn blob(&self, hash: &str) -> Result<Option<Vec<u8>>, StoreError> {
        if !is_hash(hash) {
            return Ok(None);
        }
        self.read_optional(&self.blob_path(hash))
    }

    fn job_dir(&self, job_id: u64) -> PathBuf {
        self.root.join("jobs").join(job_id.to_string())
    }

    fn tiles_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("tiles").join("pixels.f32")
    }

    pub fn image_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("image.png")
    }

    fn linear_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("image.f32")
    }

    /// Persists a finished tile's pixels (f32 little-endian) in its slot, before it is
    /// acknowledged. `tile_size` is the job's: it sets the slot size; `rect` is the tile's, in
    /// `frame`.
    pub fn put_tile(
        &self,
        job_id: u64,
        frame: Frame,
        tile: u32,
        tile_size: u32,
        rect: TileRect,
        pixels: &[u8],
    ) -> Result<(), StoreError> {
        let path = self.tiles_path(job_id);
        let slot = TileSlot::new(tile, tile_size);
        if pixels.len() as u64 > slot.pixel_bytes {
            return Err(StoreError::Corrupt(format!(
                "tile {tile}: {} bytes of pixels do not fit a {tile_size}x{tile_size} tile",
                pixels.len()
            )));
        }
        if let Some(memory) = &self.memory {
            return memory.place_tile(job_id, frame, tile, rect, pixels);
        }
        let open = || {
            fs::OpenOptions::new()
                .write(true)
                .create(true)
                .truncate(false)
                .open(&path)
        };
        let write = || -> std::io::Result<()> {
            let file = match open() {
                Err(e) if e.kind() == ErrorKind::NotFound => {
                    // The job's first tile: its folder does not exist yet.
                    if let Some(parent) = path.parent() {
                        fs::create_dir_all(parent)?;
                    }
                    open()?
                }
                other => other?,
            };
            // One write: the header lands with the pixels.
            let mut record = Vec::with_capacity(TILE_HEADER + pixels.len());
            record.extend_from_slice(&slot.header(pixels.len()));
            record.extend_from_slice(pixels);
            file.write_all_at(&record, slot.offset)
        };
        write().map_err(|e| StoreError::io(format!("writing tile {tile} to {}", path.display()), e))
    }

    pub fn tile(
        &self,
        job_id: u64,
        tile: u32,
        tile_size: u32,
        rect: TileRect,
    ) -> Result<Image, StoreError> {
        let path = self.tiles_path(job_id);
        if let Some(memory) = &self.memory {
            let frames = locked(&memory.frames);
            let canvas = frames
                .get(&job_id)
                .and_then(|f| f.values().find(|c| c.tiles.get(&tile) == Some(&rect)));
            return match canvas {
                Some(canvas) => Ok(canvas.image.crop(rect)),
                None => Err(StoreError::Corrupt(format!(
                    "{}: tile {tile} is missing",
                    path.display()
                ))),
            };
        }
        let slot = TileSlot::new(tile, tile_size);
        let len = rect.pixel_count() * 12;
        let mut record = vec![0u8; TILE_HEADER + len];
        let read = fs::File::open(&path).and_then(|f| f.read_exact_at(&mut record, slot.offset));
        let missing = || StoreError::Corrupt(format!("{}: tile {tile} is missing", path.display()));
        match read {
            Ok(()) => {}
            Err(e) if e.kind() == ErrorKind::UnexpectedEof => return Err(missing()),
            Err(e) => {
                return Err(StoreError::io(
                    format!("reading tile {tile} from {}", path.display()),
                    e,
                ))
            }
        }
        if record[..TILE_HEADER] != slot.header(len) {
            return Err(missing());
        }
        let pixels = pixels_from_bytes(&record[TILE_HEADER..], rect)
            .map_err(|e| StoreError::Corrupt(format!("{}: {e}", path.display())))?;
        Image::from_pixels(rect.width, rect.height, pixels)
            .map_err(|e| StoreError::Corrupt(format!("{}: {e}", path.display())))
    }

    /// Assembles `frame` from the given finished tiles of it (tracer-core's one assembly
    /// path); the others stay black. In memory, when they are every tile that has landed in
    /// the frame, that is the frame itself, shared rather than copied.
    pub fn assemble(
        &self,
        job_id: u64,
        frame: Frame,
        tile_size: u32,
        tiles: &[(u32, TileRect)],
    ) -> Result<Arc<Image>, StoreError> {
        if let Some(memory) = &self.memory {
            return memory.assemble(job_id, frame, tiles);
        }
        let tiles = tiles
            .iter()
            .map(|&(index, rect)| Ok((rect, self.tile(job_id, index, tile_size, rect)?)));
        tracer_core::film::assemble(frame.width, frame.height, tiles).map(Arc::new)
    }

    /// Writes the final PNG and its linear pixels, then drops the tiles they were made of.
    /// The linear pixels take what the tiles took, so a job never holds more on disk than
    /// while it rendered. The PNG is written last: its presence marks a complete image.
    pub fn put_image(&self, job_id: u64, png: &[u8], linear: Arc<Image>) -> Result<(), StoreError> {
        self.put_linear(&self.linear_path(job_id), linear)?;
        self.write_atomic(&self.image_path(job_id), png)?;
        match &self.memory {
            Some(memory) => drop(locked(&memory.frames).remove(&job_id)),
            None => drop(fs::remove_dir_all(self.job_dir(job_id).join("tiles"))),
        }
        Ok(())
    }

    /// Stores linear pixels at `path`: as f32 little-endian on disk, as they are in memory.
    fn put_linear(&self, path: &Path, linear: Arc<Image>) -> Result<(), StoreError> {
        match &self.memory {
            Some(memory) => {
                locked(&memory.images).insert(path.to_path_buf(), linear);
                Ok(())
            }
            None => self.write_atomic(path, &pixels_to_bytes(&linear.pixels)),
        }
    }

    fn sums_path(&self, job_id: u64) -> PathBuf {
        self.job_dir(job_id).join("sums.bin")
    }

    /// A progressive job's state after its last finished pass (see `farm::progressive`),
    /// replaced whole: a crash leaves the previous pass's or this one's, never a mix.
    pub fn put_sums(&self, job_id: u64, bytes: &[u8]) -> Result<(), StoreError> {
        self.write_atomic(&self.sums_path(job_id), bytes)
    }

    pub fn sums(&self, job_id: u64) -> Result<Option<Vec<u8>>, StoreError> {
        self.read_optional(&self.sums_path(job_id))
    }

    pub fn image(&self, job_id: u64) -> Result<Option<Vec<u8>>, StoreError> {
        self.read_optional(&self.image_path(job_id))
    }

    /// The linear pixels stored by [`Files::put_image`] for a `width`×`height` job.
    pub fn linear_image(
        &self,
        job_id: u64,
        width: u32,
        height: u32,
    ) -> Result<Option<Image>, StoreError> {
        self.read_linear(&self.linear_path(job_id), width, height)
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
        linear: Arc<Image>,
    ) -> Result<(), StoreError> {
        self.put_linear(&self.frame_path(job_id, frame, "f32"), linear)?;
        self.write_atomic(&self.frame_path(job_id, frame, "png"), png)
    }

    pub fn frame_image(&self, job_id: u64, frame: u32) -> Result<Option<Vec<u8>>, StoreError> {
        self.read_optional(&self.frame_path(job_id, frame, "png"))
    }

    /// The linear pixels of one frame stored by [`Files::put_frame_image`].
    pub fn frame_linear_image(
        &self,
        job_id: u64,
        frame: u32,
        width: u32,
        height: u32,
    ) -> Result<Option<Image>, StoreError> {
        self.read_linear(&self.frame_path(job_id, frame, "f32"), width, height)
    }

    fn read_linear(
        &self,
        path: &Path,
        width: u32,
        height: u32,
    ) -> Result<Option<Image>, StoreError> {
        let corrupt =
            |e: &dyn std::fmt::Display| StoreError::Corrupt(format!("{}: {e}", path.display()));
        if let Some(memory) = &self.memory {
            return match locked(&memory.images).get(path) {
                Some(image) if (image.width, image.height) == (width, height) => {
                    Ok(Some(Image::clone(image)))
                }
                Some(image) => Err(corrupt(&format!(
                    "a {}x{} image, not {width}x{height}",
                    image.width, image.height
                ))),
                None => Ok(None),
            };
        }
        let Some(bytes) = self.read_optional(path)? else {
            return Ok(None);
        };
        let pixels = pixels_from_bytes(&bytes, TileRect::new(0, 0, width, height))
            .map_err(|e| corrupt(&e))?;
        Image::from_pixels(width, height, pixels)
            .map(Some)
            .map_err(|e| corrupt(&e))
    }

    fn read_optional(&self, path: &Path) -> Result<Option<Vec<u8>>, StoreError> {
        if let Some(memory) = &self.memory {
            return Ok(locked(&memory.bytes).get(path).cloned());
        }
        match fs::read(path) {
            Ok(bytes) => Ok(Some(bytes)),
            Err(e) if e.kind() == ErrorKind::NotFound => Ok(None),
            Err(e) => Err(StoreError::io(format!("reading {}", path.display()), e)),
        }
    }
}

/// Bytes before a tile's pixels in its slot.
const TILE_HEADER: usize = 16;
const TILE_MAGIC: &[u8; 4] = b"TILE";

/// Where a tile lies in its job's pixel file.
struct TileSlot {
    tile: u32,
    offset: u64,
    pixel_bytes: u64,
}

impl TileSlot {
    fn new(tile: u32, tile_size: u32) -> TileSlot {
        let pixel_bytes = tile_size as u64 * tile_size as u64 * 12;
        TileSlot {
            tile,
            offset: tile as u64 * (TILE_HEADER as u64 + pixel_bytes),
            pixel_bytes,
        }
    }

    /// Magic, tile index and pixel byte count: a hole or another tile's bytes never match.
    fn header(&self, len: usize) -> [u8; TILE_HEADER] {
        let mut header = [0u8; TILE_HEADER];
        header[..4].copy_from_slice(TILE_MAGIC);
        header[4..8].copy_from_slice(&self.tile.to_le_bytes());
        header[8..16].copy_from_slice(&(len as u64).to_le_bytes());
        header
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
    fn a_store_in_memory_writes_no_file() {
        let files = Files::in_memory();
        let hash = files.put_blob(b"hello").unwrap();
        assert!(files.has_blob(&hash));
        assert_eq!(files.blob(&hash).unwrap().unwrap(), b"hello");
        assert!(!files.has_blob(&protocol::hash_hex(b"other")));
        files.put_sums(3, b"sums").unwrap();
        assert_eq!(files.sums(3).unwrap().unwrap(), b"sums");
        assert!(!files.root.exists(), "{:?}", files.root);
    }

    /// The disk store in a temporary folder, and the store in memory.
    fn both_stores() -> Vec<(Files, Option<tempfile::TempDir>)> {
        let dir = tempfile::tempdir().unwrap();
        let disk = Files::open(dir.path()).unwrap();
        vec![(disk, Some(dir)), (Files::in_memory(), None)]
    }

    #[test]
    fn tiles_assemble_into_an_image() {
        for (files, _dir) in both_stores() {
            tiles_assemble_into_an_image_in(&files);
        }
    }

    /// Frame 0 of a job, the only frame most tests need.
    const fn first_frame(width: u32, height: u32) -> Frame {
        Frame {
            number: 0,
            width,
            height,
        }
    }

    const FRAME_3X2: Frame = first_frame(3, 2);

    fn tiles_assemble_into_an_image_in(files: &Files) {
        let rects = TileRect::grid(3, 2, 2);
        let mut expected = Image::new(3, 2);
        for (i, rect) in rects.iter().enumerate() {
            let mut tile = Image::new(rect.width, rect.height);
            tile.pixels.iter_mut().for_each(|p| *p = i as f32 / 4.0);
            expected.insert(*rect, &tile);
            files
                .put_tile(
                    7,
                    FRAME_3X2,
                    i as u32,
                    2,
                    *rect,
                    &pixels_to_bytes(&tile.pixels),
                )
                .unwrap();
        }
        let all: Vec<(u32, TileRect)> = rects
            .iter()
            .enumerate()
            .map(|(i, r)| (i as u32, *r))
            .collect();
        let assembled = files.assemble(7, FRAME_3X2, 2, &all).unwrap();
        assert_eq!(*assembled, expected);
        let some = files.assemble(7, FRAME_3X2, 2, &all[1..]).unwrap();
        let mut only_some = expected.clone();
        only_some.insert(rects[0], &Image::new(rects[0].width, rects[0].height));
        assert_eq!(*some, only_some, "the tiles not asked for stay black");
        assert_eq!(files.linear_image(7, 3, 2).unwrap(), None);
        files.put_image(7, b"png", assembled).unwrap();
        assert_eq!(files.image(7).unwrap().unwrap(), b"png");
        assert_eq!(files.linear_image(7, 3, 2).unwrap(), Some(expected));
        assert!(
            matches!(files.linear_image(7, 3, 3), Err(StoreError::Corrupt(_))),
            "a stored image of the wrong size is corrupt, not a panic"
        );
        assert!(
            files.tile(7, 0, 2, rects[0]).is_err(),
            "tiles are dropped with the image"
        );
    }

    #[test]
    fn in_memory_a_tile_outside_its_frame_is_refused_and_a_late_copy_leaves_the_image_alone() {
        let files = Files::in_memory();
        let frame = first_frame(2, 2);
        let rect = TileRect::new(0, 0, 2, 2);
        let half = pixels_to_bytes(&[0.5; 12]);
        let outside = files.put_tile(1, frame, 0, 4, TileRect::new(1, 1, 2, 2), &half);
        let err = outside.unwrap_err().to_string();
        assert!(err.contains("outside the 2x2 frame"), "{err}");
        files.put_tile(1, frame, 0, 4, rect, &half).unwrap();
        let image = files.assemble(1, frame, 4, &[(0, rect)]).unwrap();
        // A lapsed lease's copy of the tile lands while the final image is being stored.
        let quarter = pixels_to_bytes(&[0.25; 12]);
        files.put_tile(1, frame, 0, 4, rect, &quarter).unwrap();
        assert_eq!(image.pixels, vec![0.5; 12]);
        assert_eq!(files.tile(1, 0, 4, rect).unwrap().pixels, vec![0.25; 12]);
    }

    #[test]
    fn a_tile_never_written_is_missing_not_black() {
        for (files, _dir) in both_stores() {
            a_tile_never_written_is_missing_not_black_in(&files);
        }
    }

    fn a_tile_never_written_is_missing_not_black_in(files: &Files) {
        let frame = first_frame(4, 4);
        let rect = TileRect::new(0, 0, 4, 4);
        let pixels = pixels_to_bytes(&[0.5; 48]);
        // Tile 3 extends the file past tile 1's slot, which stays a hole.
        files.put_tile(1, frame, 3, 4, rect, &pixels).unwrap();
        files.put_tile(1, frame, 0, 4, rect, &pixels).unwrap();
        assert_eq!(files.tile(1, 0, 4, rect).unwrap().pixels, vec![0.5; 48]);
        for missing in [1, 7] {
            let err = files.tile(1, missing, 4, rect).unwrap_err().to_string();
            assert!(err.contains(&format!("tile {missing} is missing")), "{err}");
        }
        // A tile read with another tile's index is not mistaken for it.
        assert!(files.tile(1, 3, 4, TileRect::new(0, 0, 4, 2)).is_err());
        assert!(
            files.put_tile(1, frame, 2, 2, rect, &pixels).is_err(),
            "too big for its slot"
        );
        let whole = [(0, rect), (3, rect)];
        assert_eq!(
            files.assemble(1, frame, 4, &whole).unwrap().pixels,
            vec![0.5; 48]
        );
        let err = files.assemble(1, frame, 4, &[(1, rect)]).unwrap_err();
        assert!(err.to_string().contains("tile 1 is missing"), "{err}");
    }
}
