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
//! binary under a longer name (docs/performance.md). Rounding every allocation out to whole
//! lines, aligned, removes the class of problem rather than one instance: no two allocations
//! ever share a line.
//!
//! The binaries that render (`tracer`, `worker`, `coordinator`) install it:
//! `#[global_allocator] static ALLOC: tracer_core::alloc::OwnLines = tracer_core::alloc::OwnLines;`

use std::alloc::{GlobalAlloc, Layout, System};

/// The unit no two allocations share: two cache lines, since Intel's spatial prefetcher
/// fetches lines in 128-byte aligned pairs.
pub const UNIT: usize = 128;

/// [`System`], with every allocation aligned to and padded out to [`UNIT`] bytes.
pub struct OwnLines;

/// `layout` widened to whole units, or None where that size overflows.
#[inline]
fn widened(layout: Layout) -> Option<Layout> {
    let size = layout.size().checked_add(UNIT - 1)? & !(UNIT - 1);
    Layout::from_size_align(size, layout.align().max(UNIT)).ok()
}

// SAFETY: every call forwards to `System` with the widened layout, and `dealloc`/`realloc`
// widen the caller's layout exactly as the `alloc` that made the block did, so `System`
// always sees the layout it allocated with.
unsafe impl GlobalAlloc for OwnLines {
    #[inline]
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match widened(layout) {
            // SAFETY: forwarded; a widened layout has a non-zero size.
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
        let (Some(wide), Some(new_wide)) = (
            widened(layout),
            Layout::from_size_align(new_size, layout.align())
                .ok()
                .and_then(widened),
        ) else {
            return std::ptr::null_mut();
        };
        // SAFETY: `ptr` was allocated by `System` with `wide`; the new size is a non-zero
        // multiple of the alignment, which is unchanged.
        unsafe { System.realloc(ptr, wide, new_wide.size()) }
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
                let q = a.realloc(p, layout, size * 3);
                assert!(!q.is_null());
                assert_eq!(q as usize % UNIT.max(align), 0);
                assert!(std::slice::from_raw_parts(q, size)
                    .iter()
                    .all(|&b| b == 0xab));
                a.dealloc(q, Layout::from_size_align(size * 3, align).unwrap());
                let z = a.alloc_zeroed(layout);
                assert!(std::slice::from_raw_parts(z, size).iter().all(|&b| b == 0));
                a.dealloc(z, layout);
            }
        }
        // Sizes that cannot be widened are refused, not wrapped around.
        let huge = Layout::from_size_align(isize::MAX as usize - 10, 1).unwrap();
        // SAFETY: a refused allocation returns null and is not freed.
        assert!(unsafe { a.alloc(huge) }.is_null());
    }

    #[test]
    fn widening_rounds_out_to_whole_units() {
        let w = |size, align| widened(Layout::from_size_align(size, align).unwrap()).unwrap();
        assert_eq!((w(1, 1).size(), w(1, 1).align()), (UNIT, UNIT));
        assert_eq!(w(UNIT, 8).size(), UNIT);
        assert_eq!(w(UNIT + 1, 8).size(), 2 * UNIT);
        assert_eq!(w(10, 4096).align(), 4096);
    }
}
