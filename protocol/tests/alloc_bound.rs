//! Decoding untrusted bytes never allocates more than the kind's limit, and
//! an oversized body allocates nothing. A counting global allocator measures
//! the peak of the calling thread alone: the test harness's own threads
//! allocate at times of their own choosing.

use dray_protocol::examples::one_of_each;
use dray_protocol::*;
use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;

struct Counting;

thread_local! {
    // Const-initialised without destructors, so the allocator may touch them.
    static CURRENT: Cell<usize> = const { Cell::new(0) };
    static PEAK: Cell<usize> = const { Cell::new(0) };
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        let _ = CURRENT.try_with(|current| {
            let now = current.get() + l.size();
            current.set(now);
            let _ = PEAK.try_with(|peak| peak.set(peak.get().max(now)));
        });
        System.alloc(l)
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        // Memory allocated on another thread may be freed here.
        let _ = CURRENT.try_with(|current| current.set(current.get().saturating_sub(l.size())));
        System.dealloc(p, l)
    }
}

#[global_allocator]
static A: Counting = Counting;

/// Bytes this thread allocated at the peak of `f`, above what it held before.
fn peak_of(f: impl FnOnce()) -> usize {
    let base = CURRENT.with(Cell::get);
    PEAK.with(|peak| peak.set(base));
    f();
    PEAK.with(Cell::get) - base
}

/// A tiny xorshift so the test needs no random crate and is reproducible.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 << 13;
        self.0 ^= self.0 >> 7;
        self.0 ^= self.0 << 17;
        self.0
    }
}

#[test]
fn decoding_allocation_is_bounded_by_the_kind_limit() {
    let mut rng = Rng(0x9e37_79b9_7f4a_7c15);
    let valid: Vec<Vec<u8>> = one_of_each(5000)
        .into_iter()
        .map(|msg| {
            encode_envelope(&Envelope {
                msg,
                from: Address::parse("a", "b").unwrap(),
                to: Address::parse("c", "d").unwrap(),
            })
            .unwrap()
        })
        .collect();
    let mut worst = 0.0f64;
    for round in 0..20_000 {
        let mut body = if round % 2 == 0 {
            // Random garbage behind a valid tag, with length prefixes that
            // claim huge sizes.
            let len = (rng.next() % 600) as usize + 1;
            let mut b: Vec<u8> = (0..len).map(|_| rng.next() as u8).collect();
            b[0] = (rng.next() % 12) as u8;
            b
        } else {
            let mut b = valid[(rng.next() % 12) as usize].clone();
            for _ in 0..(rng.next() % 6 + 1) {
                let at = (rng.next() as usize) % b.len();
                b[at] = rng.next() as u8;
            }
            b
        };
        if round % 3 == 0 {
            // Plant a maximal varint length somewhere.
            let at = (rng.next() as usize) % body.len();
            for (i, byte) in [0xff, 0xff, 0xff, 0xff, 0x0f].iter().enumerate() {
                if at + i < body.len() {
                    body[at + i] = *byte;
                }
            }
        }
        let Ok(kind) = peek_kind(&body) else { continue };
        let peak = peak_of(|| {
            let _ = decode_envelope(&body);
        });
        assert!(
            peak <= kind.max_wire_size(),
            "{kind:?}: decoding {} bytes allocated {peak} bytes",
            body.len()
        );
        worst = worst.max(peak as f64 / body.len() as f64);
    }
    eprintln!("worst allocation/input ratio {worst:.2}");
    // Memory follows the input, not the claimed lengths.
    assert!(worst < 64.0, "worst allocation/input ratio {worst}");

    // Oversized bodies are refused before any decoding.
    let mut big = vec![0u8; MessageKind::AssignTile.max_wire_size() + 10];
    big[0] = 1;
    let peak = peak_of(|| {
        assert!(matches!(
            decode_envelope(&big),
            Err(ProtocolError::Oversized { .. })
        ));
    });
    assert_eq!(peak, 0);
}
