//! The process's memory allocator: mimalloc for rendering, the system's
//! (glibc's) for preprocessing; and where huge pages are used.
//!
//! Why mimalloc: it places each voxel's nodes and corners in large
//! segments that it asks the kernel to back with transparent huge pages,
//! where glibc gives every voxel array (100–250 KB) a mapping of 4 KiB
//! pages of its own. A far view's packets wait on node loads spread over
//! the whole model, so fewer TLB misses and denser placement speed up
//! `dray render` and warm cluster clients (`scripts/bench-kernel`,
//! `experiments/efficiency.toml`).
//!
//! Mimalloc only where the voxels stay put ([`streaming`] switches a
//! process whose voxels come and go to glibc, without huge pages). A node
//! that streams voxels allocates a blob in one thread (a store's reader,
//! the transport, a client's decoder) and frees it in another, all the
//! time; mimalloc keeps such memory in the allocating thread's pages, and
//! `dray sim` with 8 clients and 0.5 MB caches grew without bound (1.2 GB
//! after 5 s, 3.5 GB after 90 s) where glibc, tuned by [`streaming`],
//! holds about 110-240 MB over 20 minutes at the same speed
//! (`scripts/soak`). With huge pages, each fresh fault would also
//! clear a whole 2 MiB page (`clear_page_erms`), making cold clients
//! slower (`experiments/latency-hiding.toml`). The experiment runner stays
//! on mimalloc without huge pages: its `render` engine must trace as
//! `dray render` does, and its in-process runs are short.
//!
//! Why not mimalloc for preprocessing: its memory budget (`--memory-mb`)
//! holds for the whole process, and mimalloc's huge pages (committed
//! 2 MiB at a time) and delayed return of freed memory overshoot a small
//! budget several times over; with both turned off it keeps the budget but
//! builds slower than glibc (`scripts/bench-preprocess`). [`use_system`]
//! switches new allocations over before a build starts; every block goes
//! back to the allocator that made it.

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicBool, Ordering};

#[global_allocator]
static ALLOCATOR: Dispatch = Dispatch;

/// Whether new blocks come from the system allocator.
static SYSTEM: AtomicBool = AtomicBool::new(false);

/// From now on, new blocks come from the system allocator (blocks made
/// before stay mimalloc's until freed).
pub fn use_system() {
    SYSTEM.store(true, Ordering::Relaxed);
}

/// For a process whose voxels come and go (a node that does not preload
/// them): the system allocator and no huge pages from now on, with glibc
/// told to give freed memory back.
pub fn streaming() {
    no_huge_pages();
    use_system();
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    give_back_freed_memory();
}

/// glibc keeps freed memory in its arenas: its mmap threshold rises to the
/// largest blob freed (so 100-300 KB blobs stop being mapped of their own),
/// and threads that come and go (tokio's blocking pool) spread small
/// blocks over up to 8 arenas a core. With a flat heap (heaptrack: 35-100
/// MB) the process still grew by about 11 MB a minute (`scripts/soak`).
/// So: one arena (no slower in `dray sim` here), blobs of 64 KiB and more
/// in mappings of their own that a free unmaps, and a trim every few
/// seconds for what is left.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn give_back_freed_memory() {
    const MMAP_THRESHOLD: libc::c_int = 64 << 10;
    const TRIM_EVERY: std::time::Duration = std::time::Duration::from_secs(5);
    // SAFETY: mallopt sets a tunable and touches no memory of ours; a
    // refusal (0) leaves glibc as it was.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
    }
    let trimmer = std::thread::Builder::new()
        .name("malloc-trim".into())
        .spawn(|| loop {
            std::thread::sleep(TRIM_EVERY);
            // SAFETY: malloc_trim only returns glibc's free pages to the
            // kernel, under glibc's own locks.
            unsafe {
                libc::malloc_trim(0);
            }
        });
    if let Err(e) = trimmer {
        tracing::warn!("freed memory is not trimmed: no thread for it: {e}");
    }
}

/// No transparent huge pages for this process from now on (its pages
/// already mapped stay as they are), for a process whose voxels come and
/// go. Linux only: elsewhere mimalloc decides. Inherited by the
/// processes it starts.
pub fn no_huge_pages() {
    #[cfg(target_os = "linux")]
    // SAFETY: PR_SET_THP_DISABLE takes a flag and touches no memory of
    // ours; it can only fail on kernels without it (before 3.15), where
    // the process goes on as it was.
    unsafe {
        libc::prctl(libc::PR_SET_THP_DISABLE, 1 as libc::c_ulong, 0, 0, 0);
    }
}

struct Dispatch;

/// Whether mimalloc made the block at `ptr` (a lookup in its page map,
/// safe for any address; its own free does the same lookup).
fn mimallocs(ptr: *mut u8) -> bool {
    // SAFETY: takes any pointer and only reads mimalloc's page map.
    unsafe { libmimalloc_sys::mi_is_in_heap_region(ptr as *const _) }
}

// SAFETY: each block is made by one of two allocators and always resized
// and freed by the one that made it, which meets the `GlobalAlloc`
// contract of each.
unsafe impl GlobalAlloc for Dispatch {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        if SYSTEM.load(Ordering::Relaxed) {
            System.alloc(layout)
        } else {
            mimalloc::MiMalloc.alloc(layout)
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        if SYSTEM.load(Ordering::Relaxed) {
            System.alloc_zeroed(layout)
        } else {
            mimalloc::MiMalloc.alloc_zeroed(layout)
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if mimallocs(ptr) {
            mimalloc::MiMalloc.dealloc(ptr, layout)
        } else {
            System.dealloc(ptr, layout)
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if mimallocs(ptr) {
            mimalloc::MiMalloc.realloc(ptr, layout, new_size)
        } else {
            System.realloc(ptr, layout, new_size)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Blocks made before and after the switch are each resized and freed
    /// by their own allocator (a block freed by the wrong one would abort
    /// the process or corrupt its heap).
    #[test]
    fn every_block_goes_back_to_the_allocator_that_made_it() {
        let before: Vec<u64> = (0..1000).collect();
        assert!(mimallocs(before.as_ptr() as *mut u8));
        use_system();
        let mut after: Vec<u64> = (0..1000).collect();
        assert!(!mimallocs(after.as_ptr() as *mut u8));
        let mut grown = before.clone();
        assert!(!mimallocs(grown.as_ptr() as *mut u8));
        let mut before = before;
        before.extend(0..100_000);
        after.extend(0..100_000);
        grown.extend(0..100_000);
        assert!(
            mimallocs(before.as_ptr() as *mut u8),
            "a resized block stays mimalloc's"
        );
        assert!(!mimallocs(after.as_ptr() as *mut u8));
        assert_eq!(before[..1000], after[..1000]);
        assert_eq!(before.iter().sum::<u64>(), grown.iter().sum::<u64>());
    }

    #[cfg(target_os = "linux")]
    #[test]
    fn no_huge_pages_turns_them_off_for_the_process() {
        no_huge_pages();
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let line = status.lines().find(|l| l.starts_with("THP_enabled:"));
        // Kernels before 5.0 do not report it.
        if let Some(line) = line {
            assert_eq!(line.split_whitespace().nth(1), Some("0"), "{line}");
        }
    }
}
