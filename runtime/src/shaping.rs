//! Link shaping: one-way latency, jitter, bandwidth cap and loss.
//!
//! [`Shaper`] turns a message (or datagram) size into a delivery instant; the
//! in-process transport uses it per message on tokio's clock (paused in
//! tests), the UDP relay per datagram. A [`Path`] chains shapers: a node's
//! uplink, the pair's link and the receiver's downlink, where the node links
//! are [`SharedShaper`]s that every connection of that node crosses.

use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::time::Instant;

/// How one direction of a link behaves.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct LinkShape {
    /// Added one-way delay.
    pub latency: Duration,
    /// Extra delay drawn uniformly from `[0, jitter]` per message or datagram
    /// (order is kept: nothing overtakes what was sent before it).
    pub jitter: Duration,
    /// Bandwidth cap in bits per second; `None`: unlimited.
    pub bandwidth_bps: Option<u64>,
    /// Loss probability in `[0, 1)`. The relay drops datagrams; the
    /// in-process transport, which is reliable like a QUIC stream, delays a
    /// "lost" message by one more round trip and transmission, as a
    /// retransmission would.
    pub loss: f64,
}

/// Why a shape is unusable.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ShapeError {
    /// Loss outside `[0, 1)`.
    #[error("loss {0} is not in [0, 1)")]
    Loss(f64),
    /// A zero bandwidth cap.
    #[error("a bandwidth cap of 0 bit/s would never deliver anything")]
    ZeroBandwidth,
}

impl LinkShape {
    /// An unshaped link.
    pub fn none() -> Self {
        LinkShape::default()
    }

    /// Whether this shape changes anything.
    pub fn is_none(&self) -> bool {
        self.latency.is_zero()
            && self.jitter.is_zero()
            && self.bandwidth_bps.is_none()
            && self.loss == 0.0
    }

    /// Checks the values.
    pub fn validate(&self) -> Result<(), ShapeError> {
        if !(0.0..1.0).contains(&self.loss) {
            return Err(ShapeError::Loss(self.loss));
        }
        if self.bandwidth_bps == Some(0) {
            return Err(ShapeError::ZeroBandwidth);
        }
        Ok(())
    }

    /// Time to put `bytes` on the link at the capped bandwidth.
    pub fn transmission_time(&self, bytes: usize) -> Duration {
        match self.bandwidth_bps {
            Some(bps) if bps > 0 => {
                let nanos = (bytes as u128 * 8 * 1_000_000_000).div_ceil(bps as u128);
                Duration::from_nanos(u64::try_from(nanos).unwrap_or(u64::MAX))
            }
            _ => Duration::ZERO,
        }
    }
}

/// A small deterministic generator (xorshift64*), so shaping is reproducible.
#[derive(Clone, Debug)]
pub struct Rng(u64);

impl Rng {
    /// Seeds the generator (a zero seed is replaced).
    pub fn new(seed: u64) -> Self {
        Rng(if seed == 0 {
            0x9e37_79b9_7f4a_7c15
        } else {
            seed
        })
    }

    /// A uniform value in `[0, 1)`.
    pub fn unit(&mut self) -> f64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        let v = self.0.wrapping_mul(0x2545_f491_4f6c_dd1d);
        (v >> 11) as f64 / (1u64 << 53) as f64
    }
}

/// What the shaper decided for one message or datagram.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Verdict {
    /// Deliver at this instant.
    At(Instant),
    /// Drop it: lost by the loss probability.
    Drop,
    /// Drop it: the queue in front of the capped link is full.
    Overflow,
}

/// Which queue of a link a reliable message takes. QUIC carries control
/// messages on one stream and each bulk message on its own, and schedules
/// them fairly, so a small control message does not wait behind a large
/// voxel; the in-process model gives the two classes separate ordered lanes
/// on a shared bandwidth (control first, its bytes delay the bulk lane).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Lane {
    /// Small messages, in order.
    Control,
    /// Large payloads (tile results, voxels), in order among themselves.
    Bulk,
}

/// The state of one shaped direction: when each lane is free again, when
/// its last delivery happens, the random stream.
#[derive(Debug)]
pub struct Shaper {
    shape: LinkShape,
    free_at: [Instant; 2],
    last_delivery: [Instant; 2],
    rng: Rng,
    queue_limit: Duration,
}

impl Shaper {
    /// A shaper starting now. `queue_limit` bounds how far ahead of now the
    /// transmission queue may reach before new datagrams are dropped (the
    /// router buffer); ignored by [`Shaper::reliable`].
    pub fn new(shape: LinkShape, seed: u64, queue_limit: Duration) -> Self {
        let now = Instant::now();
        Shaper {
            shape,
            free_at: [now; 2],
            last_delivery: [now; 2],
            rng: Rng::new(seed),
            queue_limit,
        }
    }

    /// The shape.
    pub fn shape(&self) -> &LinkShape {
        &self.shape
    }

    fn jitter(&mut self) -> Duration {
        if self.shape.jitter.is_zero() {
            Duration::ZERO
        } else {
            self.shape.jitter.mul_f64(self.rng.unit())
        }
    }

    /// A reliable message of `bytes` sent now on `lane`: its transmission
    /// after whatever is still queued on that lane, plus latency and jitter;
    /// a "lost" one is retransmitted one round trip later. Nothing overtakes
    /// an earlier message of the same lane.
    pub fn reliable(&mut self, bytes: usize, lane: Lane) -> Instant {
        self.reliable_from(Instant::now(), bytes, lane)
    }

    /// As [`Shaper::reliable`] for a message that reaches this link at
    /// `ready` (not before now), e.g. when it leaves the previous hop.
    pub fn reliable_from(&mut self, ready: Instant, bytes: usize, lane: Lane) -> Instant {
        let ready = ready.max(Instant::now());
        let i = lane as usize;
        let tx = self.shape.transmission_time(bytes);
        let start = self.free_at[i].max(ready);
        self.free_at[i] = start + tx;
        if lane == Lane::Control {
            // Control bytes use the bandwidth the bulk lane would have had.
            self.free_at[1] = self.free_at[1].max(ready) + tx;
        }
        let mut at = self.free_at[i] + self.shape.latency + self.jitter();
        if self.shape.loss > 0.0 && self.rng.unit() < self.shape.loss {
            at += 2 * self.shape.latency + tx;
            self.free_at[i] += tx;
        }
        at = at.max(self.last_delivery[i]);
        self.last_delivery[i] = at;
        at
    }

    /// A datagram of `bytes` arriving now: dropped with the loss probability
    /// or when the queue is full, else paced at the bandwidth and delayed.
    pub fn datagram(&mut self, bytes: usize) -> Verdict {
        self.datagram_from(Instant::now(), bytes)
    }

    /// As [`Shaper::datagram`] for a datagram that reaches this link at
    /// `ready` (not before now).
    pub fn datagram_from(&mut self, ready: Instant, bytes: usize) -> Verdict {
        let ready = ready.max(Instant::now());
        if self.shape.loss > 0.0 && self.rng.unit() < self.shape.loss {
            return Verdict::Drop;
        }
        let start = self.free_at[0].max(ready);
        if start > ready + self.queue_limit {
            return Verdict::Overflow;
        }
        self.free_at[0] = start + self.shape.transmission_time(bytes);
        let at = (self.free_at[0] + self.shape.latency + self.jitter()).max(self.last_delivery[0]);
        self.last_delivery[0] = at;
        Verdict::At(at)
    }
}

/// A shaper that several links share: a node's uplink or downlink, the one
/// bottleneck that every connection of that node crosses.
pub type SharedShaper = Arc<Mutex<Shaper>>;

/// A new [`SharedShaper`].
pub fn shared(shaper: Shaper) -> SharedShaper {
    Arc::new(Mutex::new(shaper))
}

fn lock(s: &SharedShaper) -> MutexGuard<'_, Shaper> {
    s.lock().unwrap_or_else(|p| p.into_inner())
}

/// The shaped hops a message or datagram crosses, in order (e.g. the
/// sender's uplink, the pair's link, the receiver's downlink). Each hop is
/// store-and-forward: it takes the message when the previous hop delivers
/// it. Times are reserved when the message is sent, so each hop serves its
/// messages in the order they were sent (a FIFO link).
#[derive(Clone, Debug, Default)]
pub struct Path {
    hops: Vec<SharedShaper>,
}

impl Path {
    /// A path through `hops`, in order; no hops: unshaped.
    pub fn new(hops: Vec<SharedShaper>) -> Self {
        Path { hops }
    }

    /// Whether nothing on the path shapes anything.
    pub fn is_unshaped(&self) -> bool {
        self.hops.is_empty()
    }

    /// When a reliable message of `bytes` sent now on `lane` arrives.
    pub fn reliable(&self, bytes: usize, lane: Lane) -> Instant {
        let mut at = Instant::now();
        for hop in &self.hops {
            at = lock(hop).reliable_from(at, bytes, lane);
        }
        at
    }

    /// What happens to a datagram of `bytes` arriving now: the first hop
    /// that drops it decides; otherwise it arrives when the last one
    /// delivers it.
    pub fn datagram(&self, bytes: usize) -> Verdict {
        let mut at = Instant::now();
        for hop in &self.hops {
            match lock(hop).datagram_from(at, bytes) {
                Verdict::At(t) => at = t,
                dropped => return dropped,
            }
        }
        Verdict::At(at)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[tokio::test(start_paused = true)]
    async fn reliable_messages_queue_behind_each_other() {
        let shape = LinkShape {
            latency: Duration::from_millis(10),
            bandwidth_bps: Some(8_000_000), // one byte per microsecond
            ..LinkShape::none()
        };
        let mut s = Shaper::new(shape, 1, Duration::ZERO);
        let t0 = Instant::now();
        assert_eq!(
            s.reliable(1000, Lane::Bulk),
            t0 + Duration::from_micros(11_000)
        );
        assert_eq!(
            s.reliable(1000, Lane::Bulk),
            t0 + Duration::from_micros(12_000)
        );
        // A control message does not wait for the bulk lane, but delays it.
        assert_eq!(
            s.reliable(500, Lane::Control),
            t0 + Duration::from_micros(10_500)
        );
        assert_eq!(
            s.reliable(1000, Lane::Bulk),
            t0 + Duration::from_micros(13_500)
        );
    }

    #[tokio::test(start_paused = true)]
    async fn datagrams_drop_when_the_queue_is_full() {
        let shape = LinkShape {
            bandwidth_bps: Some(8_000), // one byte per millisecond
            ..LinkShape::none()
        };
        let mut s = Shaper::new(shape, 1, Duration::from_millis(5));
        let mut kept = 0;
        for _ in 0..10 {
            if let Verdict::At(_) = s.datagram(2) {
                kept += 1;
            }
        }
        // 2 ms each; the queue may reach 5 ms ahead: 0, 2, 4 start in time.
        assert_eq!(kept, 3);
    }

    #[test]
    fn loss_is_validated_and_roughly_honoured() {
        assert!(LinkShape {
            loss: 1.0,
            ..LinkShape::none()
        }
        .validate()
        .is_err());
        let mut r = Rng::new(7);
        let hits = (0..10_000).filter(|_| r.unit() < 0.1).count();
        assert!((800..1200).contains(&hits), "{hits}");
    }
}
