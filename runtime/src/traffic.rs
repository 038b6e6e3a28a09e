//! Bytes a node's links carried, by the role of the node at the other end:
//! what an experiment's `link_mb` columns are made of.
//!
//! Counted as the transports encode and decode envelopes (the bytes a wire
//! carries, less QUIC's and UDP's own headers), on both transports alike.
//! Messages between actors of one node cross no link and are not counted.

use dray_protocol::{LinkBytes, Role};
use std::sync::atomic::{AtomicU64, Ordering};

const ROLES: usize = 5;

fn slot(role: Role) -> usize {
    match role {
        Role::Scheduler => 0,
        Role::Client => 1,
        Role::Store => 2,
        Role::Display => 3,
        Role::Tool => 4,
    }
}

/// Live counters of one node.
#[derive(Debug, Default)]
pub(crate) struct TrafficCounters {
    sent: [AtomicU64; ROLES],
    received: [AtomicU64; ROLES],
}

impl TrafficCounters {
    pub(crate) fn sent(&self, to: Role, bytes: usize) {
        self.sent[slot(to)].fetch_add(bytes as u64, Ordering::Relaxed);
    }

    pub(crate) fn received(&self, from: Role, bytes: usize) {
        self.received[slot(from)].fetch_add(bytes as u64, Ordering::Relaxed);
    }

    pub(crate) fn snapshot(&self) -> Traffic {
        let load = |a: &[AtomicU64; ROLES]| a.each_ref().map(|c| c.load(Ordering::Relaxed));
        Traffic {
            sent: load(&self.sent),
            received: load(&self.received),
        }
    }
}

/// Bytes one node sent to and received from nodes of each role, since it
/// started ([`crate::Bus::traffic`]); subtract two to get an interval's.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Traffic {
    sent: [u64; ROLES],
    received: [u64; ROLES],
}

impl Traffic {
    /// Bytes sent to nodes of `role`.
    pub fn sent_to(&self, role: Role) -> u64 {
        self.sent[slot(role)]
    }

    /// Bytes received from nodes of `role`.
    pub fn received_from(&self, role: Role) -> u64 {
        self.received[slot(role)]
    }

    /// Bytes both ways between this node and nodes of `role`.
    pub fn with(&self, role: Role) -> u64 {
        self.sent_to(role) + self.received_from(role)
    }

    /// Bytes received from anyone.
    pub fn received(&self) -> u64 {
        self.received.iter().sum()
    }

    /// The link classes (the config's `[links.*]`) this traffic of a node
    /// of role `own` crossed. A store's or the scheduler's own view adds
    /// nothing: clients and the display count every class from their end.
    pub fn link_bytes(&self, own: Role) -> LinkBytes {
        match own {
            Role::Client => LinkBytes {
                client_store: self.with(Role::Store),
                client_scheduler: self.with(Role::Scheduler) + self.with(Role::Display),
                display: 0,
                store_uplink: self.received_from(Role::Store),
                client_downlink: self.received(),
            },
            Role::Display => LinkBytes {
                display: self.with(Role::Scheduler),
                ..LinkBytes::default()
            },
            Role::Scheduler | Role::Store | Role::Tool => LinkBytes::default(),
        }
    }

    /// What was counted between `earlier` and `self`.
    pub fn since(&self, earlier: &Traffic) -> Traffic {
        let sub =
            |a: [u64; ROLES], b: [u64; ROLES]| std::array::from_fn(|i| a[i].saturating_sub(b[i]));
        Traffic {
            sent: sub(self.sent, earlier.sent),
            received: sub(self.received, earlier.received),
        }
    }
}

/// Hands out what a node's links carried since the last call, by link
/// class: a client charges it to each tile, the display to each frame.
pub struct LinkMeter {
    bus: crate::Bus,
    seen: Traffic,
}

impl LinkMeter {
    /// Counts from now on.
    pub fn new(bus: crate::Bus) -> LinkMeter {
        let seen = bus.traffic();
        LinkMeter { bus, seen }
    }

    /// What was carried since the previous call (or since [`LinkMeter::new`]).
    pub fn take(&mut self) -> LinkBytes {
        let now = self.bus.traffic();
        let d = now.since(&self.seen);
        self.seen = now;
        d.link_bytes(self.bus.role())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn counts_by_role_and_subtracts() {
        let c = TrafficCounters::default();
        c.sent(Role::Store, 100);
        c.received(Role::Store, 4000);
        c.received(Role::Scheduler, 60);
        let a = c.snapshot();
        assert_eq!(a.with(Role::Store), 4100);
        assert_eq!(a.received(), 4060);
        assert_eq!(a.sent_to(Role::Scheduler), 0);
        c.sent(Role::Display, 3000);
        let b = c.snapshot().since(&a);
        assert_eq!(b.sent_to(Role::Display), 3000);
        assert_eq!(b.with(Role::Store), 0);
        let l = a.link_bytes(Role::Client);
        assert_eq!((l.client_store, l.client_scheduler), (4100, 60));
        assert_eq!(
            (l.store_uplink, l.client_downlink, l.display),
            (4000, 4060, 0)
        );
        assert_eq!(a.link_bytes(Role::Display).display, 60);
    }
}
