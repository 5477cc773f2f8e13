//! Large arrays that rays read at random, on 2 MiB pages where the kernel offers them.
//!
//! A 10 M-triangle mesh keeps about 1 GB of blocks, corners and nodes, and a ray through it
//! touches a few cache lines in each of several far-apart places. With 4 KiB pages nearly
//! every such load also misses the TLB, and the page walk (two-dimensional under a
//! hypervisor) costs as much as the load itself. Linux's transparent huge pages are often in
//! `madvise` mode, so they must be asked for, before the pages are first touched.

/// Arrays smaller than this stay on ordinary pages: they fit the TLB's reach anyway.
const HUGE_MIN_BYTES: usize = 8 << 20;

/// `Vec::with_capacity(capacity)`, its memory advised for huge pages when it is large. Fill
/// it without growing it past `capacity` (a reallocation may lose the advice).
pub(crate) fn with_capacity_huge<T>(capacity: usize) -> Vec<T> {
    let v: Vec<T> = Vec::with_capacity(capacity);
    advise_huge(
        v.as_ptr().cast::<u8>(),
        capacity.saturating_mul(size_of::<T>()),
    );
    v
}

/// The 2 MiB-aligned part of `bytes` bytes at `p`, advised for huge pages (a hint: failure
/// changes nothing but speed).
#[cfg(target_os = "linux")]
fn advise_huge(p: *const u8, bytes: usize) {
    const HUGE_PAGE: usize = 2 << 20;
    if bytes < HUGE_MIN_BYTES {
        return;
    }
    let start = (p as usize).next_multiple_of(HUGE_PAGE);
    let end = (p as usize + bytes) / HUGE_PAGE * HUGE_PAGE;
    if end > start {
        // SAFETY: the range lies inside the Vec's own allocation; MADV_HUGEPAGE changes how
        // its pages are backed, never their contents.
        unsafe {
            libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge(_p: *const u8, _bytes: usize) {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_huge_vec_holds_what_is_put_in_it() {
        for n in [0, 10, 3 << 20] {
            let mut v: Vec<u64> = with_capacity_huge(n);
            assert!(v.capacity() >= n);
            let ptr = v.as_ptr();
            v.extend((0..n as u64).map(|i| i * 3));
            assert_eq!(v.as_ptr(), ptr, "filled in place");
            assert!(v.iter().enumerate().all(|(i, &x)| x == 3 * i as u64));
        }
    }
}
