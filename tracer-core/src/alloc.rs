//! A global allocator that gives every allocation cache lines of its own.
//!
//! Render threads write per-row state (shadow-ray caches, a pixel's slot lists, reference
//! counts) into small heap allocations many times per sample. With the system allocator such
//! an allocation can share a cache line with one the other thread reads or writes as often
//! (scene data freed and reused next to it, the other thread's row state where they share an
//! arena), and the line then moves between cores on every write: false sharing. Which
//! allocations end up neighbours changes from run to run, so the cost came and went at random.
//! On a 2-vCPU Intel VM it made test.scene 1.3×, spheres.scene up to 1.38× and cube.scene up
//! to 1.33× slower in most runs of a binary named `tracer`, and in fewer runs of the same
//! binary under a longer name (docs/performance.md). Rounding every small allocation out to
//! whole lines, aligned, removes the class of problem rather than one instance: no two of them
//! ever share a line. Large ones (4 KiB and up) are left as they are: only their first and last
//! lines could be shared, and the system grows them without copying.
//!
//! The binaries that render (`tracer`, `worker`, `coordinator`) install it:
//! `#[global_allocator] static ALLOC: tracer_core::alloc::OwnLines = tracer_core::alloc::OwnLines;`

use std::alloc::{GlobalAlloc, Layout, System};

/// The unit no two small allocations share: two cache lines, since Intel's spatial
/// prefetcher fetches lines in 128-byte aligned pairs.
pub const UNIT: usize = 128;

/// Allocations of at least this many bytes go to the system allocator unchanged: their
/// interior lines are theirs alone anyway, and the system's `realloc` grows them in place or
/// by remapping, where an over-aligned block is always copied (aligning them made the dragon's
/// BVH build 10% slower).
pub const LARGE: usize = 4096;

/// [`System`], with every allocation under [`LARGE`] bytes aligned to and padded out to
/// [`UNIT`] bytes.
pub struct OwnLines;

/// The layout [`OwnLines`] asks [`System`] for on behalf of `layout`: widened to whole units
/// below [`LARGE`] bytes, unchanged from there on (None where widening overflows).
#[inline]
fn widened(layout: Layout) -> Option<Layout> {
    if layout.size() >= LARGE {
        return Some(layout);
    }
    let size = layout.size().checked_add(UNIT - 1)? & !(UNIT - 1);
    Layout::from_size_align(size, layout.align().max(UNIT)).ok()
}

// SAFETY: every call forwards to `System` with the layout `widened` gives for the caller's,
// and `dealloc`/`realloc` widen the caller's layout exactly as the `alloc` that made the block
// did, so `System` always sees the layout it allocated with.
unsafe impl GlobalAlloc for OwnLines {
    #[inline]
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match widened(layout) {
            // SAFETY: forwarded; the layout has a non-zero size (the caller's, or a unit).
            Some(wide) => unsafe { System.alloc(wide) },
            None => std::ptr::null_mut(),
        }
    }

    #[inline]
    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match widened(layout) {
            // SAFETY: as in `alloc`.
            Some(wide) => unsafe { System.alloc_zeroed(wide) },
            None => std::ptr::null_mut(),
        }
    }

    #[inline]
    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // The block was made by `alloc` with this layout, so widening succeeded then.
        if let Some(wide) = widened(layout) {
            // SAFETY: `ptr` was allocated by `System` with `wide`.
            unsafe { System.dealloc(ptr, wide) }
        }
    }

    #[inline]
    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        let Ok(new_layout) = Layout::from_size_align(new_size, layout.align()) else {
            return std::ptr::null_mut();
        };
        let (Some(wide), Some(new_wide)) = (widened(layout), widened(new_layout)) else {
            return std::ptr::null_mut();
        };
        if wide.align() == new_wide.align() {
            // Both small or both large: the system resizes the block it made with `wide`.
            // SAFETY: `ptr` was allocated by `System` with `wide`; the new size is non-zero
            // and the alignment is unchanged.
            return unsafe { System.realloc(ptr, wide, new_wide.size()) };
        }
        // Between the small and large classes: a new block, the contents moved.
        // SAFETY: `alloc` and `dealloc` as above; both blocks hold at least the bytes copied.
        unsafe {
            let new = self.alloc(new_layout);
            if !new.is_null() {
                std::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
                self.dealloc(ptr, layout);
            }
            new
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn allocations_own_their_lines() {
        let a = OwnLines;
        for (size, align) in [
            (1, 1),
            (24, 8),
            (128, 16),
            (129, 4),
            (4096, 4096),
            (3000, 64),
        ] {
            let layout = Layout::from_size_align(size, align).unwrap();
            // SAFETY: the layouts have non-zero sizes; every block is freed with its layout.
            unsafe {
                let p = a.alloc(layout);
                assert!(!p.is_null());
                assert_eq!(p as usize % UNIT.max(align), 0, "{size} bytes at {p:?}");
                p.write_bytes(0xab, size);
                let q = a.realloc(p, layout, size + 1000);
                assert!(!q.is_null());
                assert_eq!(q as usize % UNIT.max(align), 0);
                assert!(std::slice::from_raw_parts(q, size)
                    .iter()
                    .all(|&b| b == 0xab));
                a.dealloc(q, Layout::from_size_align(size + 1000, align).unwrap());
                let z = a.alloc_zeroed(layout);
                assert!(std::slice::from_raw_parts(z, size).iter().all(|&b| b == 0));
                a.dealloc(z, layout);
            }
        }
        // Growing into the large class and shrinking back keep the contents.
        let small = Layout::from_size_align(100, 8).unwrap();
        // SAFETY: as above; each block is freed with the layout of its last size.
        unsafe {
            let p = a.alloc(small);
            p.write_bytes(7, 100);
            let big = a.realloc(p, small, 3 * LARGE);
            assert!(std::slice::from_raw_parts(big, 100).iter().all(|&b| b == 7));
            big.add(100).write_bytes(9, 3 * LARGE - 100);
            let grown = a.realloc(
                big,
                Layout::from_size_align(3 * LARGE, 8).unwrap(),
                5 * LARGE,
            );
            assert_eq!(*grown.add(3 * LARGE - 1), 9);
            let back = a.realloc(grown, Layout::from_size_align(5 * LARGE, 8).unwrap(), 50);
            assert_eq!(back as usize % UNIT, 0);
            assert!(std::slice::from_raw_parts(back, 50).iter().all(|&b| b == 7));
            a.dealloc(back, Layout::from_size_align(50, 8).unwrap());
        }
        // A huge request goes to the system as it is, to be refused there, not wrapped
        // around by the rounding.
        let huge = Layout::from_size_align(isize::MAX as usize - 10, 1).unwrap();
        assert_eq!(widened(huge), Some(huge));
    }

    #[test]
    fn widening_rounds_out_to_whole_units() {
        let w = |size, align| widened(Layout::from_size_align(size, align).unwrap()).unwrap();
        assert_eq!((w(1, 1).size(), w(1, 1).align()), (UNIT, UNIT));
        assert_eq!(w(UNIT, 8).size(), UNIT);
        assert_eq!(w(UNIT + 1, 8).size(), 2 * UNIT);
        assert_eq!(w(10, 4096).align(), 4096);
        assert_eq!((w(LARGE, 8).size(), w(LARGE, 8).align()), (LARGE, 8));
    }
}
