//! The process's memory allocator: mimalloc for rendering, the system's
//! (glibc's) for preprocessing, glibc with a pool of page-sized blocks
//! ([`pool`]) for nodes that stream voxels; and where huge pages are used.
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
//! process whose voxels come and go to glibc and the pool, without huge
//! pages). A node that streams voxels allocates a blob in one thread (a
//! store's reader, the transport, a client's decoder) and frees it in
//! another, all the time; mimalloc keeps such memory in the allocating
//! thread's pages, and `dray sim` with 8 clients and 0.5 MB caches grew
//! without bound (1.2 GB after 5 s, 3.5 GB after 90 s) where glibc and the
//! pool hold it flat (`scripts/soak`). With huge pages, each fresh fault
//! would also clear a whole 2 MiB page (`clear_page_erms`), making cold
//! clients slower (`experiments/latency-hiding.toml`). The experiment
//! runner stays on mimalloc without huge pages: its `render` engine must
//! trace as `dray render` does, and its in-process runs are short.
//!
//! Why not mimalloc for preprocessing: its memory budget (`--memory-mb`)
//! holds for the whole process, and mimalloc's huge pages (committed
//! 2 MiB at a time) and delayed return of freed memory overshoot a small
//! budget several times over; with both turned off it keeps the budget but
//! builds slower than glibc (`scripts/bench-preprocess`). [`use_system`]
//! switches new allocations over before a build starts; every block goes
//! back to the allocator that made it.

mod pool;

use std::alloc::{GlobalAlloc, Layout, System};
use std::sync::atomic::{AtomicU8, Ordering};

#[global_allocator]
static ALLOCATOR: Dispatch = Dispatch;

/// Where new blocks come from: [`MIMALLOC`] until a switch to [`SYSTEM`]
/// or [`STREAMING`], which is for good (so a block's size tells which of
/// glibc and the pool made it).
static MODE: AtomicU8 = AtomicU8::new(MIMALLOC);
const MIMALLOC: u8 = 0;
const SYSTEM: u8 = 1;
const STREAMING: u8 = 2;

static POOL: pool::Pool = pool::Pool::new();

/// From now on, new blocks come from the system allocator (blocks made
/// before stay mimalloc's until freed).
pub fn use_system() {
    let _ = MODE.compare_exchange(MIMALLOC, SYSTEM, Ordering::Relaxed, Ordering::Relaxed);
}

/// For a process whose voxels come and go (a node that does not preload
/// them): from now on the pool for blocks of a page to a MiB, glibc for
/// the rest, told to give freed memory back, and no huge pages. Not
/// after [`use_system`].
pub fn streaming() {
    no_huge_pages();
    if MODE
        .compare_exchange(MIMALLOC, STREAMING, Ordering::Relaxed, Ordering::Relaxed)
        .is_ok()
    {
        give_back_freed_memory();
    }
}

/// Whether a block of `layout` is (or, made now, would be) the pool's.
fn pooled(layout: Layout) -> bool {
    MODE.load(Ordering::Relaxed) == STREAMING
        && layout.align() <= pool::PAGE
        && (pool::MIN..=pool::MAX).contains(&layout.size())
}

/// glibc keeps freed memory in its arenas: its mmap threshold rises to the
/// largest block freed (so blocks past the pool's stop being mapped of
/// their own), and threads that come and go (tokio's blocking pool) spread
/// small blocks over up to 8 arenas a core. So: one arena (no slower in
/// `dray sim` here), blocks of 64 KiB and more in mappings of their own
/// that a free unmaps, and a trim every few seconds for what is left.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
fn tune_glibc() {
    const MMAP_THRESHOLD: libc::c_int = 64 << 10;
    // SAFETY: mallopt sets a tunable and touches no memory of ours; a
    // refusal (0) leaves glibc as it was.
    unsafe {
        libc::mallopt(libc::M_ARENA_MAX, 1);
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD);
    }
}

/// Every few seconds, the pool's blocks idle since the last time and
/// glibc's free pages go back to the kernel.
fn give_back_freed_memory() {
    const EVERY: std::time::Duration = std::time::Duration::from_secs(5);
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    tune_glibc();
    let trimmer = std::thread::Builder::new()
        .name("memory-trim".into())
        .spawn(|| loop {
            std::thread::sleep(EVERY);
            POOL.release_idle();
            #[cfg(all(target_os = "linux", target_env = "gnu"))]
            // SAFETY: malloc_trim only returns glibc's free pages to the
            // kernel, under glibc's own locks.
            unsafe {
                libc::malloc_trim(0);
            }
        });
    if let Err(e) = trimmer {
        tracing::warn!("freed memory is not given back: no thread for it: {e}");
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

// SAFETY: each block is made by one of three allocators and always resized
// and freed by the one that made it (mimalloc's are found by address, the
// pool's by size), which meets the `GlobalAlloc` contract of each.
unsafe impl GlobalAlloc for Dispatch {
    unsafe fn alloc(&self, layout: Layout) -> *mut u8 {
        match MODE.load(Ordering::Relaxed) {
            MIMALLOC => mimalloc::MiMalloc.alloc(layout),
            _ if pooled(layout) => POOL.alloc(layout.size()).ptr,
            _ => System.alloc(layout),
        }
    }

    unsafe fn alloc_zeroed(&self, layout: Layout) -> *mut u8 {
        match MODE.load(Ordering::Relaxed) {
            MIMALLOC => mimalloc::MiMalloc.alloc_zeroed(layout),
            _ if pooled(layout) => {
                let block = POOL.alloc(layout.size());
                if !block.zeroed && !block.ptr.is_null() {
                    block.ptr.write_bytes(0, layout.size());
                }
                block.ptr
            }
            _ => System.alloc_zeroed(layout),
        }
    }

    unsafe fn dealloc(&self, ptr: *mut u8, layout: Layout) {
        if mimallocs(ptr) {
            mimalloc::MiMalloc.dealloc(ptr, layout)
        } else if pooled(layout) {
            POOL.free(ptr, layout.size())
        } else {
            System.dealloc(ptr, layout)
        }
    }

    unsafe fn realloc(&self, ptr: *mut u8, layout: Layout, new_size: usize) -> *mut u8 {
        if mimallocs(ptr) {
            return mimalloc::MiMalloc.realloc(ptr, layout, new_size);
        }
        // SAFETY: the caller promises a valid size for the same alignment.
        let new_layout = Layout::from_size_align_unchecked(new_size, layout.align());
        match (pooled(layout), pooled(new_layout)) {
            (false, false) => System.realloc(ptr, layout, new_size),
            (true, true) if pool::class_of(layout.size()) == pool::class_of(new_size) => ptr,
            _ => {
                let new = self.alloc(new_layout);
                if !new.is_null() {
                    std::ptr::copy_nonoverlapping(ptr, new, layout.size().min(new_size));
                    self.dealloc(ptr, layout);
                }
                new
            }
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

    /// Run in a process of its own (the switch is for good): blocks that
    /// grow and shrink across the pool's sizes keep their bytes, and a
    /// zeroed block from the pool is zero even when it was used before.
    #[test]
    fn streaming_blocks_move_between_glibc_and_the_pool() {
        const CHILD: &str = "DRAY_ALLOCATOR_TEST_CHILD";
        if std::env::var_os(CHILD).is_none() {
            let out = std::process::Command::new(std::env::current_exe().unwrap())
                .args([
                    "--exact",
                    "allocator::tests::streaming_blocks_move_between_glibc_and_the_pool",
                ])
                .env(CHILD, "1")
                .output()
                .unwrap();
            assert!(
                out.status.success(),
                "{}",
                String::from_utf8_lossy(&out.stdout)
            );
            assert!(String::from_utf8_lossy(&out.stdout).contains("1 passed"));
            return;
        }
        let before: Vec<u32> = (0..50_000).collect();
        streaming();
        assert_eq!(MODE.load(Ordering::Relaxed), STREAMING);
        use_system();
        assert_eq!(
            MODE.load(Ordering::Relaxed),
            STREAMING,
            "the switch is for good"
        );
        let mut v: Vec<u32> = Vec::new();
        for i in 0..600_000u32 {
            v.push(i);
        }
        assert!(v.iter().copied().eq(0..600_000));
        for keep in [300_000, 100_000, 5000, 2000, 700, 10] {
            v.truncate(keep);
            v.shrink_to_fit();
            assert!(v.iter().copied().eq(0..keep as u32));
        }
        for _ in 0..3 {
            let mut dirty = vec![0xffu8; 10_000];
            dirty[9999] = 1;
            drop(dirty);
            let zero = vec![0u8; 10_000];
            assert!(zero.iter().all(|&b| b == 0));
        }
        let blocks: Vec<Box<[u8]>> = (1..200).map(|k| vec![k as u8; k * 997].into()).collect();
        for (k, b) in (1..200).zip(&blocks) {
            assert!(b.len() == k * 997 && b.iter().all(|&x| x == k as u8));
        }
        assert!(mimallocs(before.as_ptr() as *mut u8));
        assert!(before.iter().copied().eq(0..50_000));
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
