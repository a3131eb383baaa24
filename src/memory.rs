//! The process's allocator: the system allocator, with every allocation of at
//! least [`HUGE_MIN_BYTES`] placed on 2 MiB boundaries and offered to the kernel
//! for transparent huge pages (`madvise(MADV_HUGEPAGE)`; Linux only).
//!
//! Why: the learner's buffers (activations, gradients, Adam moments, the rollout,
//! the critic pass over it) are megabytes each and are touched once per phase of
//! an iteration. On the 2-core VMs this project is measured on, a 4 KiB page left
//! untouched for a few hundred milliseconds costs ~50 us to touch again (8 MiB:
//! 101 ms after 800 ms idle, 13 ms after 50 ms), while the same 8 MiB on 2 MiB
//! pages costs 0.34 ms (`benches/memory.rs`). Debian's default THP mode is
//! `madvise`, so without the advice every buffer stays on 4 KiB pages.
//!
//! MuJoCo's own arenas are allocated by MuJoCo (C `malloc`), not here: they keep
//! 4 KiB pages, which is what lets the simulation layer give their unused pages
//! back (see `sim::Data`).

use std::alloc::{GlobalAlloc, Layout, System};

/// Allocations at least this large get huge pages.
pub const HUGE_MIN_BYTES: usize = 1 << 20;
/// A transparent huge page (x86-64, aarch64 with 4 KiB base pages).
pub const HUGE_PAGE_BYTES: usize = 2 << 20;

/// [`System`] plus huge pages for large allocations (see the module doc).
pub struct HugePageAlloc;

/// The layout a large request is served with: size rounded up to whole huge
/// pages, aligned to a huge page (so the advice covers whole huge pages only).
fn huge_layout(layout: Layout) -> Option<Layout> {
    if layout.size() < HUGE_MIN_BYTES {
        return None;
    }
    let size = layout.size().checked_next_multiple_of(HUGE_PAGE_BYTES)?;
    Layout::from_size_align(size, layout.align().max(HUGE_PAGE_BYTES)).ok()
}

#[cfg(target_os = "linux")]
fn advise_huge(ptr: *mut u8, layout: Layout) {
    if !ptr.is_null() {
        // SAFETY: [ptr, ptr + size) is the allocation just made, page-aligned and
        // a whole number of pages long; MADV_HUGEPAGE changes no contents, and a
        // refusal (e.g. THP disabled) is harmless, so the result is ignored.
        unsafe {
            libc::madvise(ptr.cast(), layout.size(), libc::MADV_HUGEPAGE);
        }
    }
}

#[cfg(not(target_os = "linux"))]
fn advise_huge(_ptr: *mut u8, _layout: Layout) {}

// SAFETY: every block is allocated and freed by `System` with one layout, the
// one `huge_layout` derives from the caller's layout (the same on both sides,
// since `dealloc` gets the layout `alloc` was called with); that layout is at
// least as large and as aligned as the caller's.
unsafe impl GlobalAlloc for HugePageAlloc {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match huge_layout(layout) {
            Some(big) => {
                // SAFETY: `big` has a non-zero size (at least the caller's).
                let p = unsafe { System.alloc(big) };
                advise_huge(p, big);
                p
            }
            // SAFETY: the caller's layout, forwarded unchanged (non-zero size).
            None => unsafe { System.alloc(layout) },
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match huge_layout(layout) {
            Some(big) => {
                // SAFETY: `big` has a non-zero size (at least the caller's).
                let p = unsafe { System.alloc_zeroed(big) };
                advise_huge(p, big);
                p
            }
            // SAFETY: the caller's layout, forwarded unchanged (non-zero size).
            None => unsafe { System.alloc_zeroed(layout) },
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `alloc` with this same derived layout (the
        // caller passes the layout it allocated with, and the derivation is pure).
        unsafe { System.dealloc(ptr, huge_layout(layout).unwrap_or(layout)) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY (from the caller): new_size > 0 and, rounded up to the alignment,
        // does not overflow isize.
        let new_layout = unsafe { Layout::from_size_align_unchecked(new_size, layout.align()) };
        if huge_layout(layout).is_none() && huge_layout(new_layout).is_none() {
            // SAFETY: neither layout is enlarged, so `ptr` was allocated by System
            // with `layout` itself; the caller's contract covers new_size.
            return unsafe { System.realloc(ptr, layout, new_size) };
        }
        // SAFETY: new_layout has a non-zero size (the caller's contract).
        let new = unsafe { self.alloc(new_layout) };
        if !new.is_null() {
            // SAFETY: both blocks are live, distinct, and at least this long.
            unsafe {
                std::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
                self.dealloc(ptr, layout);
            }
        }
        new
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_requests_keep_their_layout_and_large_ones_get_whole_huge_pages() {
        let small = Layout::from_size_align(HUGE_MIN_BYTES - 1, 8).unwrap();
        assert_eq!(huge_layout(small), None);
        let big = huge_layout(Layout::from_size_align(HUGE_MIN_BYTES, 8).unwrap()).unwrap();
        assert_eq!(
            (big.size(), big.align()),
            (HUGE_PAGE_BYTES, HUGE_PAGE_BYTES)
        );
        let odd = huge_layout(Layout::from_size_align(5 << 20, 64).unwrap()).unwrap();
        assert_eq!(odd.size(), 6 << 20);
    }

    #[test]
    fn blocks_across_the_threshold_keep_their_contents() {
        let a = HugePageAlloc;
        let small = Layout::from_size_align(4096, 8).unwrap();
        // SAFETY: every block is used within its layout and freed with it.
        unsafe {
            let p = a.alloc(small);
            assert!(!p.is_null());
            for i in 0..4096 {
                *p.add(i) = (i % 251) as u8;
            }
            // small -> huge -> small, through realloc
            let big = a.realloc(p, small, 3 << 20);
            assert!((big as usize).is_multiple_of(HUGE_PAGE_BYTES));
            assert!((0..4096).all(|i| *big.add(i) == (i % 251) as u8));
            *big.add((3 << 20) - 1) = 7;
            let big_layout = Layout::from_size_align(3 << 20, 8).unwrap();
            let back = a.realloc(big, big_layout, 4096);
            assert!((0..4096).all(|i| *back.add(i) == (i % 251) as u8));
            a.dealloc(back, small);
            let z_layout = Layout::from_size_align(4 << 20, 64).unwrap();
            let z = a.alloc_zeroed(z_layout);
            assert!((0..4 << 20).step_by(4093).all(|i| *z.add(i) == 0));
            a.dealloc(z, z_layout);
        }
    }
}
