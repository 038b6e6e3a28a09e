//! The store's state and handlers: which requests it refuses, which reads
//! it starts (at most `max_concurrent` at once, the others wait in order),
//! and what it counts. Nothing here touches the disk or the network: the
//! handlers push [`Out`] effects that the run loop carries out.

use super::StoreSummary;
use crate::Shard;
use dray_protocol::{Address, Ping};
use std::collections::VecDeque;
use tracing::debug;

/// What the store's handlers ask the run loop to do.
#[derive(Debug, PartialEq)]
pub(super) enum Out {
    /// Read voxel `id` and send it (or why it could not be read) to `to`;
    /// the loop calls [`Store::blob_read`] once it is read and
    /// [`Store::answer_sent`] once the answer has left.
    Read { to: Address, id: u32 },
    /// Answer `to` with a [`dray_protocol::VoxelError`] for `id`.
    Refuse { to: Address, id: u32, why: String },
    /// Send `to` the manifest.
    Manifest { to: Address },
    /// Answer a ping.
    Pong { to: Address, ping: Ping },
}

/// How a read ended.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum ReadOutcome {
    /// The blob, of this many bytes, was read and goes to the client.
    Served { bytes: u64 },
    /// It could not be read: a [`dray_protocol::VoxelError`] goes instead.
    Failed,
}

/// A store's state: what it serves, the reads under way and those waiting.
pub(super) struct Store {
    /// The store's address, for messages.
    actor: String,
    shard: Shard,
    /// Voxels in the database.
    voxels: u64,
    /// Most reads under way at once (each holds a blob until it is sent).
    max_concurrent: usize,
    /// Reads started whose answer has not left yet.
    reading: usize,
    /// Reads asked for beyond `max_concurrent`, oldest first.
    waiting: VecDeque<(Address, u32)>,
    summary: StoreSummary,
}

impl Store {
    pub fn new(actor: String, shard: Shard, voxels: u64, max_concurrent: usize) -> Store {
        Store {
            actor,
            shard,
            voxels,
            max_concurrent: max_concurrent.max(1),
            reading: 0,
            waiting: VecDeque::new(),
            summary: StoreSummary::default(),
        }
    }

    /// `from` asks for voxel `id`: refused if this store does not serve it
    /// or it does not exist, else read now or once a read slot frees.
    pub fn fetch_voxel(&mut self, from: Address, id: u32, out: &mut Vec<Out>) {
        let why = if !self.shard.owns(id) {
            format!(
                "voxel {id} is not in shard {} served by {}",
                self.shard, self.actor
            )
        } else if u64::from(id) >= self.voxels {
            format!(
                "voxel {id}: no such voxel (the database has {})",
                self.voxels
            )
        } else {
            self.waiting.push_back((from, id));
            self.start_reads(out);
            return;
        };
        self.summary.refused += 1;
        debug!(voxel = id, to = %from, %why, "refused");
        out.push(Out::Refuse { to: from, id, why });
    }

    /// `from` asks for the manifest.
    pub fn fetch_manifest(&mut self, from: Address, out: &mut Vec<Out>) {
        self.summary.manifests += 1;
        out.push(Out::Manifest { to: from });
    }

    /// `from` pings.
    pub fn ping(&mut self, from: Address, ping: Ping, out: &mut Vec<Out>) {
        out.push(Out::Pong { to: from, ping });
    }

    /// A read ended (its answer may still wait to be sent): count it.
    pub fn blob_read(&mut self, outcome: ReadOutcome) {
        match outcome {
            ReadOutcome::Served { bytes } => {
                self.summary.served += 1;
                self.summary.bytes_served += bytes;
            }
            ReadOutcome::Failed => self.summary.refused += 1,
        }
    }

    /// A read's answer has left: its slot frees, the next waiting read
    /// starts. Until then the blob is in memory, so a slow peer holds a slot.
    pub fn answer_sent(&mut self, out: &mut Vec<Out>) {
        self.reading = self.reading.saturating_sub(1);
        self.start_reads(out);
    }

    /// What the store did so far.
    pub fn summary(&self) -> &StoreSummary {
        &self.summary
    }

    fn start_reads(&mut self, out: &mut Vec<Out>) {
        while self.reading < self.max_concurrent {
            let Some((to, id)) = self.waiting.pop_front() else {
                break;
            };
            self.reading += 1;
            out.push(Out::Read { to, id });
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn client() -> Address {
        crate::names::client(0)
    }

    fn reads(out: &mut Vec<Out>) -> Vec<u32> {
        out.drain(..)
            .map(|o| match o {
                Out::Read { id, .. } => id,
                other => panic!("not a read: {other:?}"),
            })
            .collect()
    }

    #[test]
    fn a_voxel_it_serves_is_read_for_whoever_asked() {
        let mut s = Store::new("store-0".into(), Shard::ALL, 10, 4);
        let mut out = Vec::new();
        s.fetch_voxel(client(), 3, &mut out);
        assert_eq!(
            out,
            [Out::Read {
                to: client(),
                id: 3
            }]
        );
    }

    #[test]
    fn a_voxel_of_another_shard_or_beyond_the_database_is_refused() {
        let shard = Shard { index: 1, count: 2 };
        let mut s = Store::new("store-1".into(), shard, 10, 4);
        let mut out = Vec::new();
        s.fetch_voxel(client(), 4, &mut out);
        s.fetch_voxel(client(), 11, &mut out);
        let whys: Vec<&str> = out
            .iter()
            .map(|o| match o {
                Out::Refuse { why, .. } => why.as_str(),
                other => panic!("not a refusal: {other:?}"),
            })
            .collect();
        assert_eq!(whys[0], "voxel 4 is not in shard 1/2 served by store-1");
        assert_eq!(whys[1], "voxel 11: no such voxel (the database has 10)");
        assert_eq!(s.summary().refused, 2);
        assert_eq!(s.summary().served, 0);
    }

    #[test]
    fn beyond_max_concurrent_reads_wait_in_order_for_a_slot() {
        let mut s = Store::new("store-0".into(), Shard::ALL, 10, 2);
        let mut out = Vec::new();
        for id in [5, 6, 7, 8] {
            s.fetch_voxel(client(), id, &mut out);
        }
        assert_eq!(reads(&mut out), [5, 6], "two slots");
        s.blob_read(ReadOutcome::Served { bytes: 100 });
        s.blob_read(ReadOutcome::Failed);
        assert!(
            out.is_empty(),
            "read, but the answers have not left: {out:?}"
        );
        s.answer_sent(&mut out);
        assert_eq!(reads(&mut out), [7]);
        s.answer_sent(&mut out);
        assert_eq!(reads(&mut out), [8]);
        s.blob_read(ReadOutcome::Served { bytes: 50 });
        s.blob_read(ReadOutcome::Served { bytes: 20 });
        s.answer_sent(&mut out);
        s.answer_sent(&mut out);
        assert!(out.is_empty(), "{out:?}");
        let sum = s.summary();
        assert_eq!((sum.served, sum.bytes_served, sum.refused), (3, 170, 1));
        // Both slots are free again.
        s.fetch_voxel(client(), 1, &mut out);
        s.fetch_voxel(client(), 2, &mut out);
        assert_eq!(reads(&mut out), [1, 2]);
    }

    #[test]
    fn refusals_do_not_wait_for_a_read_slot() {
        let mut s = Store::new("store-0".into(), Shard::ALL, 10, 1);
        let mut out = Vec::new();
        s.fetch_voxel(client(), 1, &mut out);
        s.fetch_voxel(client(), 2, &mut out);
        s.fetch_voxel(client(), 99, &mut out);
        assert!(
            matches!(
                &out[..],
                [Out::Read { id: 1, .. }, Out::Refuse { id: 99, .. }]
            ),
            "{out:?}"
        );
    }

    #[test]
    fn manifests_and_pings_are_answered_and_manifests_counted() {
        let mut s = Store::new("store-0".into(), Shard::ALL, 10, 1);
        let mut out = Vec::new();
        s.fetch_manifest(client(), &mut out);
        s.ping(client(), Ping { seq: 9 }, &mut out);
        assert_eq!(
            out,
            [
                Out::Manifest { to: client() },
                Out::Pong {
                    to: client(),
                    ping: Ping { seq: 9 }
                }
            ]
        );
        assert_eq!(s.summary().manifests, 1);
    }
}
