//! Blocks of 4 KiB to 1 MiB for a streaming node, apart from glibc's heap.
//!
//! Our own, because no allocator here keeps such a node's memory flat: a
//! client decodes a few thousand voxels a second into arrays of 4 KiB to
//! a few hundred KiB that live from moments (decoding's temporaries) to
//! minutes (a cached voxel). In glibc's heap, among small blocks, the free
//! space they leave is cut up and the heap keeps growing (`scripts/soak`:
//! 80 → 170 MB in 7 minutes with 30–95 MB in use); giving each its own
//! mapping keeps it flat but runs three times slower; mimalloc and
//! jemalloc grow faster still (`docs/benchmarks.md`). Here every block
//! is rounded up to one of 28 sizes and an idle block is handed to the
//! next request of its size, so these blocks take what the most of them
//! in use at once took; blocks left idle through a whole
//! [`Pool::release_idle`] period give their pages back to the kernel (all
//! but the first, which links them), away from the allocating threads.

use std::ptr;
use std::sync::{Mutex, MutexGuard};

/// The page size these blocks are made of (x86-64 Linux's; where pages
/// are larger, giving pages back is refused and they stay in memory).
pub const PAGE: usize = 4096;
/// The smallest block served here.
pub const MIN: usize = PAGE;
/// The largest block served here (larger ones are glibc's own mappings).
pub const MAX: usize = 1 << 20;
/// Sizes: 4, 8, 12 and 16 KiB, then four steps per doubling up to 1 MiB.
pub const CLASSES: usize = 4 + 4 * 6;
/// Blocks of a size are cut from runs of about this many bytes.
const RUN: usize = 1 << 20;

/// The size class of a block of `size` bytes (`MIN..=MAX`).
pub fn class_of(size: usize) -> usize {
    debug_assert!((MIN..=MAX).contains(&size));
    if size <= 4 * PAGE {
        return size.div_ceil(PAGE) - 1;
    }
    // size in (2^p, 2^(p+1)], in four steps of 2^(p-2).
    let p = (usize::BITS - 1 - (size - 1).leading_zeros()) as usize;
    let step = 1 << (p - 2);
    let i = (size - (1 << p)).div_ceil(step);
    4 + (p - 14) * 4 + (i - 1)
}

/// The bytes of a block of class `c`.
pub fn class_size(c: usize) -> usize {
    if c < 4 {
        return (c + 1) * PAGE;
    }
    let p = 14 + (c - 4) / 4;
    let i = (c - 4) % 4 + 1;
    (1 << p) + i * (1 << (p - 2))
}

/// An idle block's header, in its first bytes.
struct Idle {
    next: *mut Idle,
    /// The release period in which it was freed.
    period: u64,
}

/// Lists of idle blocks, newest first, one per class.
type Lists = [*mut Idle; CLASSES];

struct State {
    /// Idle blocks in memory.
    idle: Lists,
    /// Idle blocks whose pages after the first were given back.
    released: Lists,
    /// The uncut rest of the newest run of each class: start, bytes.
    run: [(*mut u8, usize); CLASSES],
    /// Counts the calls of `release_idle`.
    period: u64,
    /// Bytes of address space taken from the kernel.
    mapped: usize,
}

// SAFETY: the pointers are to memory only this pool hands out, touched
// under its lock or, once taken off its lists, by the one thread that
// took them.
unsafe impl Send for State {}

/// A pool of blocks of [`CLASSES`] sizes.
pub struct Pool {
    state: Mutex<State>,
}

/// A block from [`Pool::alloc`]: where, and whether its bytes are zero.
pub struct Block {
    pub ptr: *mut u8,
    pub zeroed: bool,
}

/// Takes the first block off `list`.
///
/// # Safety
/// `list` is a list of idle blocks that the caller may change.
unsafe fn pop(list: &mut *mut Idle) -> Option<*mut u8> {
    let idle = *list;
    if idle.is_null() {
        return None;
    }
    // SAFETY: an idle block, its header written by `push`.
    *list = unsafe { (*idle).next };
    Some(idle.cast())
}

/// Puts `block` first on `list`.
///
/// # Safety
/// `block` is an idle block of at least a page, page-aligned, on no list.
unsafe fn push(list: &mut *mut Idle, block: *mut u8, period: u64) {
    let idle = block.cast::<Idle>();
    // SAFETY: the block is ours, idle, and holds a header.
    unsafe {
        idle.write(Idle {
            next: *list,
            period,
        })
    };
    *list = idle;
}

impl Pool {
    pub const fn new() -> Pool {
        Pool {
            state: Mutex::new(State {
                idle: [ptr::null_mut(); CLASSES],
                released: [ptr::null_mut(); CLASSES],
                run: [(ptr::null_mut(), 0); CLASSES],
                period: 0,
                mapped: 0,
            }),
        }
    }

    fn lock(&self) -> MutexGuard<'_, State> {
        // Nothing under the lock can panic; a poisoned lock is still whole.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }

    /// A block of at least `size` bytes (`MIN..=MAX`), page-aligned; null
    /// when the kernel has no memory to give.
    pub fn alloc(&self, size: usize) -> Block {
        let c = class_of(size);
        let bytes = class_size(c);
        let mut s = self.lock();
        let s = &mut *s;
        // SAFETY: the lists are the pool's, changed under its lock.
        if let Some(ptr) = unsafe { pop(&mut s.idle[c]).or_else(|| pop(&mut s.released[c])) } {
            return Block { ptr, zeroed: false };
        }
        let (start, left) = s.run[c];
        if left >= bytes {
            // SAFETY: within the run, which has `left` bytes from `start`.
            s.run[c] = (unsafe { start.add(bytes) }, left - bytes);
            return Block {
                ptr: start,
                zeroed: true,
            };
        }
        let run = (RUN / bytes).max(1) * bytes;
        let Some(start) = map(run) else {
            return Block {
                ptr: ptr::null_mut(),
                zeroed: false,
            };
        };
        s.mapped += run;
        // SAFETY: `run` is at least `bytes` long.
        s.run[c] = (unsafe { start.add(bytes) }, run - bytes);
        Block {
            ptr: start,
            zeroed: true,
        }
    }

    /// Takes back a block that `alloc(size)` made.
    ///
    /// # Safety
    /// `ptr` came from `self.alloc(size)` (or a size of the same class)
    /// and is not used after this.
    pub unsafe fn free(&self, ptr: *mut u8, size: usize) {
        let c = class_of(size);
        let mut s = self.lock();
        let period = s.period;
        // SAFETY: the caller gives the block up; it is at least a page.
        unsafe { push(&mut s.idle[c], ptr, period) };
    }

    /// Gives back the pages of the blocks that stayed idle since the last
    /// call (all but each block's first page). Called every few seconds
    /// from a thread of its own: the system calls happen off the lock.
    pub fn release_idle(&self) {
        let mut stale: Lists = [ptr::null_mut(); CLASSES];
        {
            let mut s = self.lock();
            let before = s.period;
            s.period += 1;
            for (c, list) in s.idle.iter_mut().enumerate() {
                // Newest first: from the first block freed before this
                // period on, every block is stale.
                let mut link: *mut *mut Idle = list;
                // SAFETY: walking the pool's list under its lock.
                unsafe {
                    while !(*link).is_null() && (**link).period >= before {
                        link = &mut (**link).next;
                    }
                    stale[c] = *link;
                    *link = ptr::null_mut();
                }
            }
        }
        for (c, &head) in stale.iter().enumerate() {
            let mut block = head;
            while !block.is_null() {
                // SAFETY: off every list, so only this thread touches it.
                unsafe {
                    release(block.cast::<u8>().add(PAGE), class_size(c) - PAGE);
                    block = (*block).next;
                }
            }
        }
        let mut s = self.lock();
        for (c, &head) in stale.iter().enumerate() {
            let mut block = head;
            while !block.is_null() {
                // SAFETY: taken off the lists above; each goes back once.
                unsafe {
                    let next = (*block).next;
                    push(&mut s.released[c], block.cast(), 0);
                    block = next;
                }
            }
        }
    }

    /// Idle blocks in memory and released, and bytes of address space
    /// mapped.
    #[cfg(test)]
    pub fn usage(&self) -> (usize, usize, usize) {
        let s = self.lock();
        let count = |lists: &Lists| {
            lists
                .iter()
                .map(|&head| {
                    let (mut n, mut b) = (0, head);
                    while !b.is_null() {
                        n += 1;
                        // SAFETY: walking the pool's list under its lock.
                        b = unsafe { (*b).next };
                    }
                    n
                })
                .sum()
        };
        (count(&s.idle), count(&s.released), s.mapped)
    }
}

fn map(bytes: usize) -> Option<*mut u8> {
    // SAFETY: a fresh private anonymous mapping, touching nothing else.
    let p = unsafe {
        libc::mmap(
            ptr::null_mut(),
            bytes,
            libc::PROT_READ | libc::PROT_WRITE,
            libc::MAP_PRIVATE | libc::MAP_ANONYMOUS,
            -1,
            0,
        )
    };
    (p != libc::MAP_FAILED).then_some(p.cast())
}

/// Gives the pages back; they read as zero when next touched.
unsafe fn release(ptr: *mut u8, bytes: usize) {
    if bytes > 0 {
        // SAFETY: the caller owns these whole pages. A refusal only leaves
        // them in memory.
        unsafe { libc::madvise(ptr.cast(), bytes, libc::MADV_DONTNEED) };
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn the_classes_run_from_a_page_to_a_mebibyte() {
        assert_eq!(class_size(0), MIN);
        assert_eq!(class_size(CLASSES - 1), MAX);
        for c in 1..CLASSES {
            assert!(class_size(c) > class_size(c - 1));
            assert_eq!(class_size(c) % PAGE, 0);
            assert_eq!(class_of(class_size(c)), c);
            assert_eq!(class_of(class_size(c - 1) + 1), c);
        }
    }

    proptest! {
        #[test]
        fn a_class_holds_its_size_with_at_most_a_quarter_to_spare(size in MIN..=MAX) {
            let bytes = class_size(class_of(size));
            prop_assert!(bytes >= size);
            prop_assert!(size <= 4 * PAGE || bytes - size <= size / 4);
        }
    }

    #[test]
    fn blocks_are_apart_and_idle_ones_are_reused() {
        let pool = Pool::new();
        let sizes = [MIN, 5000, 20_000, 100_000, 300_000, MAX];
        let blocks: Vec<(*mut u8, usize)> = sizes
            .iter()
            .flat_map(|&n| (0..3).map(move |_| n))
            .map(|n| (pool.alloc(n), n))
            .map(|(b, n)| {
                assert!(b.zeroed && !b.ptr.is_null() && (b.ptr as usize).is_multiple_of(PAGE));
                // SAFETY: a fresh block of n bytes.
                unsafe { std::slice::from_raw_parts_mut(b.ptr, n).fill(n as u8) };
                (b.ptr, n)
            })
            .collect();
        for &(p, n) in &blocks {
            // SAFETY: the block was filled above and nothing else wrote it.
            let bytes = unsafe { std::slice::from_raw_parts(p, n) };
            assert!(bytes.iter().all(|&b| b == n as u8), "blocks overlap");
        }
        let (idle, released, mapped) = pool.usage();
        assert_eq!((idle, released), (0, 0));
        for &(p, n) in &blocks {
            // SAFETY: each block once, unused after.
            unsafe { pool.free(p, n) };
        }
        assert_eq!(pool.usage(), (blocks.len(), 0, mapped));
        // The next block of a size is the last one freed of its class.
        let again = pool.alloc(100_000);
        assert_eq!(again.ptr, blocks[11].0);
        assert!(!again.zeroed);
        assert_eq!(pool.usage().2, mapped, "no new mapping");
    }

    #[test]
    fn blocks_idle_for_a_whole_period_give_their_pages_back() {
        let pool = Pool::new();
        let n = 4 * PAGE;
        let blocks: Vec<*mut u8> = (0..6).map(|_| pool.alloc(n).ptr).collect();
        for &p in &blocks {
            // SAFETY: a block of n bytes.
            unsafe { p.write_bytes(7, n) };
        }
        // SAFETY: each block once.
        unsafe { blocks[..3].iter().for_each(|&p| pool.free(p, n)) };
        pool.release_idle();
        assert_eq!(
            (pool.usage().0, pool.usage().1),
            (3, 0),
            "freed this period: kept"
        );
        // SAFETY: each block once.
        unsafe { blocks[3..].iter().for_each(|&p| pool.free(p, n)) };
        pool.release_idle();
        assert_eq!((pool.usage().0, pool.usage().1), (3, 3));
        // Blocks in memory go out first; then released ones, zero past
        // their first page.
        let kept: Vec<*mut u8> = (0..3).map(|_| pool.alloc(n).ptr).collect();
        assert_eq!(kept, [blocks[5], blocks[4], blocks[3]]);
        for _ in 0..3 {
            let b = pool.alloc(n);
            assert!(blocks[..3].contains(&b.ptr) && !b.zeroed);
            // SAFETY: a block of n bytes.
            let tail = unsafe { std::slice::from_raw_parts(b.ptr.add(PAGE), n - PAGE) };
            assert!(tail.iter().all(|&x| x == 0));
        }
        assert_eq!(pool.usage().0 + pool.usage().1, 0);
    }
}
