//! A job's tile bookkeeping in memory proportional to what is *happening*, not to the tile
//! count: one bit per tile for "done", a cursor over tiles never handed out, and small maps
//! for the few tiles that are leased, requeued or have failed. Tile rectangles and frames are
//! computed from the index on demand ([`TileGrid`]).

use std::collections::{BTreeMap, BTreeSet, HashMap};

use crate::store::files::Frame;
use protocol::JobSpec;
use tracer_core::TileRect;

/// Where tile `i` of a job lies: frame by frame, each frame row-major in `tile_size` squares
/// (the order of [`TileRect::grid`]).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    width: u32,
    height: u32,
    tile_size: u32,
    columns: u32,
    per_frame: u32,
    first_frame: u32,
    frames: u32,
}

impl TileGrid {
    pub fn new(spec: &JobSpec) -> TileGrid {
        let (width, height) = (spec.render.width, spec.render.height);
        let tile_size = spec.tile_size.max(1);
        let columns = width.div_ceil(tile_size);
        let rows = height.div_ceil(tile_size);
        let (first_frame, frames) = match spec.frames {
            Some(range) => (range.first, range.len()),
            None => (spec.render.frame, 1),
        };
        TileGrid {
            width,
            height,
            tile_size,
            columns,
            per_frame: columns.saturating_mul(rows),
            first_frame,
            frames,
        }
    }

    /// Every tile of every frame, without overflow: a budget compares this.
    pub fn total_u64(&self) -> u64 {
        self.per_frame as u64 * self.frames as u64
    }

    /// The side of a full tile (edge tiles are smaller).
    pub fn tile_size(&self) -> u32 {
        self.tile_size
    }

    pub fn per_frame(&self) -> u32 {
        self.per_frame
    }

    pub fn frame(&self, tile: u32) -> u32 {
        self.first_frame + tile / self.per_frame.max(1)
    }

    /// Frame `number` of the job, with its size.
    pub fn frame_at(&self, number: u32) -> Frame {
        Frame {
            number,
            width: self.width,
            height: self.height,
        }
    }

    pub fn rect(&self, tile: u32) -> TileRect {
        let i = tile % self.per_frame.max(1);
        let x = (i % self.columns.max(1)) * self.tile_size;
        let y = (i / self.columns.max(1)) * self.tile_size;
        TileRect::new(
            x,
            y,
            self.tile_size.min(self.width - x),
            self.tile_size.min(self.height - y),
        )
    }

    /// The tile indices of `frame`, in order.
    pub fn frame_tiles(&self, frame: u32) -> std::ops::Range<u32> {
        let k = frame - self.first_frame;
        k * self.per_frame..(k + 1) * self.per_frame
    }
}

/// Failures of one tile.
#[derive(Clone, Debug, Default, PartialEq, Eq)]
pub struct TileFailures {
    pub attempts: u32,
    /// Worker ids it failed on, each once.
    pub workers: Vec<u64>,
}

/// Which tiles are done, leased, waiting or failed.
///
/// A tile is *queued* when it is neither done nor leased and either lies at or beyond the
/// cursor (never handed out since the book was made) or sits in the requeued set.
#[derive(Clone, Debug, Default)]
pub struct TileBook {
    total: u32,
    done: Vec<u64>,
    done_count: u32,
    cursor: u32,
    requeued: BTreeSet<u32>,
    leased: BTreeMap<u32, Vec<u64>>,
    failed: HashMap<u32, TileFailures>,
}

impl TileBook {
    pub fn new(total: u32) -> TileBook {
        TileBook {
            total,
            done: vec![0; total.div_ceil(64) as usize],
            ..TileBook::default()
        }
    }

    pub fn total(&self) -> u32 {
        self.total
    }

    pub fn done_count(&self) -> u32 {
        self.done_count
    }

    pub fn all_done(&self) -> bool {
        self.done_count == self.total
    }

    pub fn contains(&self, tile: u32) -> bool {
        tile < self.total
    }

    pub fn is_done(&self, tile: u32) -> bool {
        self.done
            .get(tile as usize / 64)
            .is_some_and(|w| w & (1 << (tile % 64)) != 0)
    }

    /// Marks a tile done (its leases must be ended by the caller). False if it already was.
    pub fn mark_done(&mut self, tile: u32) -> bool {
        if !self.contains(tile) || self.is_done(tile) {
            return false;
        }
        self.done[tile as usize / 64] |= 1 << (tile % 64);
        self.done_count += 1;
        self.requeued.remove(&tile);
        self.advance_cursor();
        true
    }

    pub fn leases(&self, tile: u32) -> &[u64] {
        self.leased.get(&tile).map_or(&[], Vec::as_slice)
    }

    /// Tiles with at least one live lease, with their lease ids.
    pub fn leased(&self) -> impl Iterator<Item = (u32, &[u64])> {
        self.leased.iter().map(|(t, l)| (*t, l.as_slice()))
    }

    pub fn leased_count(&self) -> u32 {
        self.leased.len() as u32
    }

    pub fn add_lease(&mut self, tile: u32, lease: u64) {
        self.requeued.remove(&tile);
        self.leased.entry(tile).or_default().push(lease);
        self.advance_cursor();
    }

    /// Drops a lease; returns true when the tile is left with none.
    pub fn remove_lease(&mut self, tile: u32, lease: u64) -> bool {
        let Some(ids) = self.leased.get_mut(&tile) else {
            return true;
        };
        ids.retain(|l| *l != lease);
        if ids.is_empty() {
            self.leased.remove(&tile);
            return true;
        }
        false
    }

    /// Puts a tile with no lease back in the queue (the cursor covers tiles beyond it).
    pub fn requeue(&mut self, tile: u32) {
        if self.contains(tile)
            && !self.is_done(tile)
            && !self.leased.contains_key(&tile)
            && tile < self.cursor
        {
            self.requeued.insert(tile);
        }
    }

    /// Queues every tile that is neither done nor leased (a retried job).
    pub fn requeue_all(&mut self) {
        self.requeued.clear();
        self.cursor = 0;
        self.advance_cursor();
    }

    /// Drops the queue (a finished job): nothing is handed out any more.
    pub fn clear_queue(&mut self) {
        self.requeued.clear();
        self.cursor = self.total;
    }

    pub fn is_queued(&self, tile: u32) -> bool {
        self.contains(tile)
            && !self.is_done(tile)
            && !self.leased.contains_key(&tile)
            && (tile >= self.cursor || self.requeued.contains(&tile))
    }

    pub fn queued_count(&self) -> u64 {
        // Tiles beyond the cursor are queued unless done or leased (resumed jobs have both).
        let mut beyond_done = 0;
        let mut start = self.cursor;
        while start < self.total {
            beyond_done += self.done_bits_from(start);
            start = (start / 64 + 1) * 64;
        }
        let beyond_leased = self.leased.range(self.cursor..).count() as u64;
        self.requeued.len() as u64 + (self.total - self.cursor) as u64 - beyond_done - beyond_leased
    }

    /// Done tiles among the 64 (or fewer) from `start` up to the word's end or `total`.
    fn done_bits_from(&self, start: u32) -> u64 {
        let word = self.done[start as usize / 64];
        let end = (start / 64 * 64 + 64).min(self.total);
        let mask = if end - start == 64 {
            u64::MAX
        } else {
            ((1u64 << (end - start)) - 1) << (start % 64)
        };
        (word & mask).count_ones() as u64
    }

    /// Queued tiles, lowest index first.
    pub fn queued(&self) -> impl Iterator<Item = u32> + '_ {
        let mut requeued = self.requeued.iter().copied().peekable();
        let mut fresh = self.next_fresh(self.cursor);
        std::iter::from_fn(move || match (requeued.peek().copied(), fresh) {
            (Some(r), Some(f)) if r < f => requeued.next(),
            (_, Some(f)) => {
                fresh = self.next_fresh(f + 1);
                Some(f)
            }
            (Some(_), None) => requeued.next(),
            (None, None) => None,
        })
    }

    /// The first tile at or after `from` that is neither done nor leased.
    fn next_fresh(&self, mut from: u32) -> Option<u32> {
        while from < self.total {
            let word = self.done[from as usize / 64];
            if from & 63 == 0 && word == u64::MAX {
                from += 64;
                continue;
            }
            if !self.is_done(from) && !self.leased.contains_key(&from) {
                return Some(from);
            }
            from += 1;
        }
        None
    }

    /// Moves the cursor past tiles that are done or leased, so it always rests on a tile that
    /// was never handed out (or at the end).
    fn advance_cursor(&mut self) {
        while self.cursor < self.total
            && (self.is_done(self.cursor) || self.leased.contains_key(&self.cursor))
        {
            self.cursor += 1;
        }
    }

    pub fn failures(&self, tile: u32) -> Option<&TileFailures> {
        self.failed.get(&tile)
    }

    /// Counts a failure of `tile` on `worker`; returns the tile's failures so far.
    pub fn record_failure(&mut self, tile: u32, worker: u64) -> &TileFailures {
        let entry = self.failed.entry(tile).or_default();
        entry.attempts += 1;
        if !entry.workers.contains(&worker) {
            entry.workers.push(worker);
        }
        entry
    }

    pub fn clear_failures(&mut self) {
        self.failed.clear();
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_matches_tile_rect_grid_for_every_frame() {
        let mut spec = JobSpec::default();
        spec.render.width = 70;
        spec.render.height = 33;
        spec.tile_size = 16;
        spec.frames = Some(tracer_core::FrameRange::new(2, 4).unwrap());
        let grid = TileGrid::new(&spec);
        let rects = TileRect::grid(70, 33, 16);
        assert_eq!(grid.per_frame() as usize, rects.len());
        assert_eq!(grid.total_u64(), 3 * rects.len() as u64);
        for t in 0..grid.total_u64() as u32 {
            assert_eq!(grid.rect(t), rects[t as usize % rects.len()], "tile {t}");
            assert_eq!(grid.frame(t), 2 + t / grid.per_frame());
        }
        assert_eq!(grid.frame_tiles(3), 15..30);
    }

    #[test]
    fn the_queue_is_lowest_first_and_skips_done_and_leased_tiles() {
        let mut book = TileBook::new(200);
        assert_eq!(book.queued().take(3).collect::<Vec<_>>(), [0, 1, 2]);
        book.add_lease(0, 10);
        book.add_lease(1, 11);
        for t in 2..150 {
            book.mark_done(t);
        }
        assert_eq!(book.queued().next(), Some(150));
        assert_eq!(book.queued_count(), 50);
        assert!(book.remove_lease(1, 11));
        book.requeue(1);
        assert_eq!(book.queued().take(2).collect::<Vec<_>>(), [1, 150]);
        assert_eq!(book.queued_count(), 51);
        assert!(book.is_queued(1) && !book.is_queued(0) && !book.is_queued(2));
        book.clear_queue();
        assert_eq!(book.queued().next(), None);
        book.requeue_all();
        assert_eq!(book.queued().take(2).collect::<Vec<_>>(), [1, 150]);
    }

    #[test]
    fn a_million_tiles_cost_a_bit_each() {
        let book = TileBook::new(1_000_000);
        assert_eq!(book.done.len(), 15_625);
        assert_eq!(book.queued_count(), 1_000_000);
    }
}
