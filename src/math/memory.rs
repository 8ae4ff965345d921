//! The allocator of a program that steps large grids: glibc's malloc, tuned for a process of
//! few large arrays that a step frees and allocates again, with the largest arrays on 2 MiB
//! pages.
//!
//! A step's whole-grid arrays are freed and made again every step (most are kept by the
//! step's pools, not all). glibc hands an array above its mmap threshold (at most 32 MiB)
//! back to the kernel when it is freed, and the next one of the same size is page-faulted
//! in again, a zeroed 4 KiB page at a time (docs/performance.md measures what that cost at
//! 256×128×256 cells). And an array of tens of MB read at random places (a particle's cell,
//! a stencil's neighbours) misses the TLB at nearly every read with 4 KiB pages, whose few
//! thousand TLB entries reach a few MB.
//!
//! [`GridAllocator`] is the system allocator with two changes, for a binary to install as its
//! `#[global_allocator]` and to [`GridAllocator::tune`] before its threads start:
//! - glibc keeps what is freed ([`GridAllocator::tune`]: one arena, nothing mapped apart,
//!   nothing trimmed), so the next step's arrays take the same pages without a fault. The
//!   process's peak is its peak either way; its resident memory then stays at that peak.
//! - An allocation of [`LARGE`] bytes or more is advised to the kernel as huge-page memory
//!   (`madvise(MADV_HUGEPAGE)` over its whole 2 MiB pages), so its pages are 2 MiB where the
//!   kernel's transparent huge pages allow it (`enabled` set to `always` or `madvise`). Only
//!   large allocations: a 2 MiB page partly used is resident whole, and a smaller array fits
//!   the TLB's reach anyway.
//!
//! Each is a hint: where the kernel or the C library does not take it, the allocator is the
//! system's. Off Linux with glibc it is the system's allocator. The library itself never
//! installs it; the `diffluid` binary and the large-grid example do.

use std::alloc::{GlobalAlloc, Layout, System};

/// Allocations of at least this many bytes are advised to the kernel as huge-page memory:
/// 16 MiB, two million f64s (at 2.5 cm cells `large_tank`'s per-cell arrays are 8 MB and its
/// particle positions 15 MB, so its resident memory is that of 4 KiB pages; at 1.25 cm every
/// whole-grid array is above it).
pub const LARGE: usize = 16 << 20;

/// The size of a transparent huge page on x86-64 and most aarch64 kernels.
const HUGE_PAGE: usize = 2 << 20;

/// The system allocator, with glibc tuned and the large allocations on huge pages (see the
/// module's notes).
#[derive(Clone, Copy, Debug, Default)]
pub struct GridAllocator;

impl GridAllocator {
    /// Sets glibc's malloc for a process of few large arrays, before any thread but the main
    /// one exists: one arena (rayon's workers each grew their own, which kept what was freed
    /// in it: `large_tank`, 8 steps, peak 472 → 390 MB), no allocation mapped apart and no
    /// trimming of the heap's top, so what a step frees the next step reuses without a page
    /// fault. A parameter set in the environment (`MALLOC_ARENA_MAX`, `MALLOC_MMAP_MAX_`,
    /// `MALLOC_TRIM_THRESHOLD_`, or its name in `GLIBC_TUNABLES`) is left as it is.
    pub fn tune() {
        #[cfg(all(target_os = "linux", target_env = "gnu"))]
        {
            let tunables = std::env::var("GLIBC_TUNABLES").unwrap_or_default();
            let unset = |env: &str, tunable: &str| {
                std::env::var_os(env).is_none() && !tunables.contains(tunable)
            };
            let settings = [
                ("MALLOC_ARENA_MAX", "glibc.malloc.arena_max", libc::M_ARENA_MAX, 1),
                ("MALLOC_MMAP_MAX_", "glibc.malloc.mmap_max", libc::M_MMAP_MAX, 0),
                (
                    "MALLOC_TRIM_THRESHOLD_",
                    "glibc.malloc.trim_threshold",
                    libc::M_TRIM_THRESHOLD,
                    i32::MAX,
                ),
            ];
            for (env, tunable, param, value) in settings {
                if unset(env, tunable) {
                    // SAFETY: mallopt only sets a parameter of glibc's allocator.
                    unsafe {
                        libc::mallopt(param, value);
                    }
                }
            }
        }
    }
}

/// Advises the whole 2 MiB pages of `size` bytes at `p` as huge-page memory, when `size` is
/// at least [`LARGE`]. Pages already resident keep their size; the rest fault in as 2 MiB
/// pages where the kernel allows them.
fn advise(p: *mut u8, size: usize) {
    if p.is_null() || size < LARGE {
        return;
    }
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    {
        let start = (p as usize).next_multiple_of(HUGE_PAGE);
        let end = (p as usize + size) / HUGE_PAGE * HUGE_PAGE;
        if end > start {
            // SAFETY: the range lies inside the allocation just made, which the caller owns;
            // MADV_HUGEPAGE changes neither its contents nor its mapping, only how later
            // faults in it are served. A refusal (no THP in the kernel) leaves it as it was.
            unsafe {
                libc::madvise(start as *mut libc::c_void, end - start, libc::MADV_HUGEPAGE);
            }
        }
    }
}

// SAFETY: every call is the system allocator's, with the same layout; `advise` only hints the
// kernel about memory the allocation owns.
unsafe impl GlobalAlloc for GridAllocator {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        // SAFETY: the caller's contract is the system allocator's.
        let p = unsafe { System.alloc(layout) };
        advise(p, layout.size());
        p
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        // calloc zeroes only what was used before; the fresh pages it leaves untouched fault
        // in later, as huge pages once advised.
        // SAFETY: as in `alloc`.
        let p = unsafe { System.alloc_zeroed(layout) };
        advise(p, layout.size());
        p
    }

    unsafe fn dealloc(&self, p: *mut u8, layout: Layout) {
        // SAFETY: `p` came from this allocator, which is the system's.
        unsafe { System.dealloc(p, layout) }
    }

    unsafe fn realloc(&self, p: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        // SAFETY: as in `dealloc`.
        let q = unsafe { System.realloc(p, layout, new_size) };
        advise(q, new_size);
        q
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Large and small allocations come back zeroed where asked, keep their contents through
    /// a reallocation that grows them past [`LARGE`] and one that shrinks them below it.
    #[test]
    fn allocates_as_the_system_does() {
        let a = GridAllocator;
        for size in [64, LARGE - 8, LARGE, 3 * LARGE + 24] {
            let layout = Layout::from_size_align(size, 8).unwrap();
            // SAFETY: a non-zero layout, freed with the same layout below.
            unsafe {
                let p = a.alloc_zeroed(layout);
                assert!(!p.is_null());
                let s = std::slice::from_raw_parts_mut(p, size);
                assert!(s.iter().all(|&b| b == 0), "{size} bytes not zeroed");
                for (i, b) in s.iter_mut().enumerate() {
                    *b = (i % 251) as u8;
                }
                let grown = 2 * LARGE + size;
                let q = a.realloc(p, layout, grown);
                let s = std::slice::from_raw_parts(q, size);
                assert!(s.iter().enumerate().all(|(i, &b)| b == (i % 251) as u8));
                let q = a.realloc(q, Layout::from_size_align(grown, 8).unwrap(), 32);
                let s = std::slice::from_raw_parts(q, 32);
                assert!(s.iter().enumerate().all(|(i, &b)| b == (i % 251) as u8));
                a.dealloc(q, Layout::from_size_align(32, 8).unwrap());
            }
        }
    }

    /// Where the kernel offers transparent huge pages, a large allocation's memory is eligible
    /// for them (`THPeligible: 1` in `/proc/self/smaps` for the mapping that holds it) and a
    /// small one's heap is not made so by it.
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    #[test]
    fn large_allocations_are_advised_as_huge_pages() {
        let thp = std::fs::read_to_string("/sys/kernel/mm/transparent_hugepage/enabled");
        if !thp.is_ok_and(|s| s.contains("[madvise]") || s.contains("[always]")) {
            eprintln!("no transparent huge pages here: nothing to check");
            return;
        }
        let eligible = |addr: usize| -> bool {
            let smaps = std::fs::read_to_string("/proc/self/smaps").unwrap();
            let mut inside = false;
            for line in smaps.lines() {
                // A mapping's first line starts with its address range, `lo-hi` in hex.
                let range = line.split_whitespace().next().and_then(|r| r.split_once('-'));
                let hex = |x: &str| usize::from_str_radix(x, 16).ok();
                if let Some((lo, hi)) = range.and_then(|(lo, hi)| Some((hex(lo)?, hex(hi)?))) {
                    inside = (lo..hi).contains(&addr);
                    continue;
                }
                if inside && line.starts_with("THPeligible:") {
                    return line.split_whitespace().nth(1) == Some("1");
                }
            }
            panic!("{addr:#x} is in no mapping");
        };
        let a = GridAllocator;
        let layout = Layout::from_size_align(4 * LARGE, 8).unwrap();
        // SAFETY: a non-zero layout, freed with the same layout.
        unsafe {
            let p = a.alloc(layout);
            let middle = p as usize + 2 * LARGE;
            assert!(eligible(middle), "a large allocation is not eligible for huge pages");
            a.dealloc(p, layout);
        }
    }
}
