//! An allocator that remembers the largest single request since it was last reset, so a
//! fuzz case that makes the program ask for memory its input cannot back is caught even
//! when the request would have succeeded (Linux overcommits: a 64 GiB zeroed vector
//! "succeeds" and only fails once touched, or never).
//!
//! Install it with `#[global_allocator] static A: Tracking = Tracking;` in the binary or
//! test that runs the cases.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicUsize, Ordering};

/// Requests above this are refused outright (the process then aborts with Rust's
/// "memory allocation of N bytes failed", naming the size): the runner writes each case to
/// disk before running it, so the case that did it is left behind.
pub const HARD_LIMIT: usize = 4 << 30;

static LARGEST: AtomicUsize = AtomicUsize::new(0);

pub struct Tracking;

impl Tracking {
    /// The largest single request since the last [`reset`](Self::reset).
    pub fn largest() -> usize {
        LARGEST.load(Ordering::Relaxed)
    }

    pub fn reset() {
        LARGEST.store(0, Ordering::Relaxed);
    }
}

#[inline]
fn note(size: usize) -> bool {
    LARGEST.fetch_max(size, Ordering::Relaxed);
    size <= HARD_LIMIT
}

// SAFETY: every call is forwarded to `System` with the caller's layout unchanged; a
// refused request returns null, which the GlobalAlloc contract allows.
unsafe impl GlobalAlloc for Tracking {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if !note(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as is.
        unsafe { System.alloc(layout) }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if !note(layout.size()) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as is.
        unsafe { System.alloc_zeroed(layout) }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        // SAFETY: `ptr` came from `System` with this layout.
        unsafe { System.dealloc(ptr, layout) }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if !note(new_size) {
            return std::ptr::null_mut();
        }
        // SAFETY: forwarded as is.
        unsafe { System.realloc(ptr, layout, new_size) }
    }
}
