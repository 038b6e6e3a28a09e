//! The client's voxel cache: a byte budget over the prepared voxels, least
//! recently used first out, shared by every render thread of the client.
//!
//! Lookups happen for every voxel every packet enters, from several
//! threads at once, so a lookup is one uncontended slot lock (a slot per
//! voxel id) and, unless the voxel already is the most recently used one,
//! one atomic increment of the LRU clock. Inserts (a few per second) take
//! the eviction lock and scan the slots: there are only thousands.
//!
//! A voxel that someone else holds (its `Arc` has another owner: a packet
//! is inside it, or a waiter is about to get it) is never freed; when
//! everything is in use the cache goes over budget until some of it is
//! released, and [`VoxelCache::peak_bytes`] records how far.

use super::shared_voxels::DecodedVoxels;
use dray_trace::accel::PreparedVoxel;
use std::sync::atomic::{AtomicU64, AtomicUsize, Ordering};
use std::sync::{Arc, Mutex, MutexGuard};

struct Slot {
    voxel: Mutex<Option<Arc<PreparedVoxel>>>,
    /// Value of the LRU clock at the last use.
    stamp: AtomicU64,
}

/// A voxel cache with a byte budget.
pub struct VoxelCache {
    slots: Vec<Slot>,
    budget: u64,
    clock: AtomicU64,
    resident: AtomicU64,
    /// Voxels resident (of `slots.len()`).
    count: AtomicUsize,
    peak: AtomicU64,
    evicted: AtomicU64,
    /// Serializes inserts and evictions.
    evict: Mutex<()>,
    /// Voxels shared with other clients' caches (the virtual engine).
    shared: Option<Arc<DecodedVoxels>>,
}

impl Drop for VoxelCache {
    /// Shared voxels this cache held are no longer held by it.
    fn drop(&mut self) {
        if let Some(shared) = &self.shared {
            for (i, slot) in self.slots.iter().enumerate() {
                if lock(&slot.voxel).is_some() {
                    shared.cached(i as u32, false);
                }
            }
        }
    }
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Each critical section is one take, put or clone: a panic elsewhere
    // cannot leave a slot half updated.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl VoxelCache {
    /// A cache for voxel ids `0..voxels` holding at most `budget_bytes` of
    /// voxels that are not in use.
    pub fn new(voxels: usize, budget_bytes: u64) -> VoxelCache {
        VoxelCache {
            slots: (0..voxels)
                .map(|_| Slot {
                    voxel: Mutex::new(None),
                    stamp: AtomicU64::new(0),
                })
                .collect(),
            budget: budget_bytes,
            // Above every initial stamp, so a first use always stamps.
            clock: AtomicU64::new(1),
            resident: AtomicU64::new(0),
            count: AtomicUsize::new(0),
            peak: AtomicU64::new(0),
            evicted: AtomicU64::new(0),
            evict: Mutex::new(()),
            shared: None,
        }
    }

    /// A cache whose voxels other clients' caches may hold too
    /// ([`DecodedVoxels`]).
    pub fn sharing(voxels: usize, budget_bytes: u64, shared: Arc<DecodedVoxels>) -> VoxelCache {
        let mut c = VoxelCache::new(voxels, budget_bytes);
        c.shared = Some(shared);
        c
    }

    /// Whether nothing but this cache (or other caches, where voxels are
    /// shared) holds `v`: then it may be freed.
    fn unused(&self, v: &Arc<PreparedVoxel>) -> bool {
        match &self.shared {
            Some(s) => s.only_cached(v),
            None => Arc::strong_count(v) == 1,
        }
    }

    fn touch(&self, slot: &Slot) {
        // Only one slot can hold the clock's current value: the most
        // recently used one, whose repeated uses cost nothing.
        if slot.stamp.load(Ordering::Relaxed) != self.clock.load(Ordering::Relaxed) {
            let now = self.clock.fetch_add(1, Ordering::Relaxed) + 1;
            slot.stamp.store(now, Ordering::Relaxed);
        }
    }

    /// Voxel `id` if it is resident (and marks it used).
    pub fn get(&self, id: u32) -> Option<Arc<PreparedVoxel>> {
        let slot = self.slots.get(id as usize)?;
        let v = lock(&slot.voxel).clone();
        if v.is_some() {
            self.touch(slot);
        }
        v
    }

    /// Whether voxel `id` is resident (without marking it used).
    pub fn contains(&self, id: u32) -> bool {
        self.slots
            .get(id as usize)
            .is_some_and(|s| lock(&s.voxel).is_some())
    }

    /// Makes `voxel` resident (unless a copy already is: that one is kept
    /// and returned), then frees least recently used voxels that are not
    /// in use until the budget holds again. Returns the resident copy and
    /// the number of voxels freed.
    pub fn insert(&self, voxel: Arc<PreparedVoxel>) -> (Arc<PreparedVoxel>, u64) {
        let id = voxel.id;
        let Some(slot) = self.slots.get(id as usize) else {
            // Not one of the manifest's voxels: usable, never cached.
            return (voxel, 0);
        };
        let _g = lock(&self.evict);
        {
            let mut s = lock(&slot.voxel);
            if let Some(v) = s.as_ref() {
                let v = v.clone();
                drop(s);
                self.touch(slot);
                return (v, 0);
            }
            *s = Some(voxel.clone());
        }
        if let Some(shared) = &self.shared {
            shared.cached(id, true);
        }
        self.count.fetch_add(1, Ordering::Relaxed);
        self.touch(slot);
        let now = self
            .resident
            .fetch_add(voxel.bytes as u64, Ordering::Relaxed)
            + voxel.bytes as u64;
        let mut freed = 0;
        if now > self.budget {
            freed = self.evict_to_budget(id);
        }
        self.peak
            .fetch_max(self.resident.load(Ordering::Relaxed), Ordering::Relaxed);
        (voxel, freed)
    }

    /// Frees unused voxels, oldest first, until the budget holds; never
    /// `keep`. Called with the eviction lock held.
    fn evict_to_budget(&self, keep: u32) -> u64 {
        let mut candidates: Vec<(u64, u32)> = self
            .slots
            .iter()
            .enumerate()
            .filter(|&(i, _)| i as u32 != keep)
            .filter_map(|(i, s)| {
                let v = lock(&s.voxel);
                let v = v.as_ref()?;
                self.unused(v)
                    .then(|| (s.stamp.load(Ordering::Relaxed), i as u32))
            })
            .collect();
        candidates.sort_unstable();
        let mut freed = 0;
        for (_, i) in candidates {
            if self.resident.load(Ordering::Relaxed) <= self.budget {
                break;
            }
            let slot = &self.slots[i as usize];
            let mut s = lock(&slot.voxel);
            // Someone may have taken it since the scan: check again under
            // the slot's lock (a lookup clones under the same lock).
            if let Some(v) = s.as_ref() {
                if self.unused(v) {
                    let bytes = v.bytes as u64;
                    if let Some(shared) = &self.shared {
                        shared.cached(i, false);
                    }
                    *s = None;
                    self.resident.fetch_sub(bytes, Ordering::Relaxed);
                    self.count.fetch_sub(1, Ordering::Relaxed);
                    freed += 1;
                }
            }
        }
        self.evicted.fetch_add(freed, Ordering::Relaxed);
        freed
    }

    /// The byte budget.
    pub fn budget(&self) -> u64 {
        self.budget
    }

    /// Bytes of the voxels held now.
    pub fn resident_bytes(&self) -> u64 {
        self.resident.load(Ordering::Relaxed)
    }

    /// Whether every voxel is resident: nothing can miss.
    pub fn holds_all(&self) -> bool {
        self.count.load(Ordering::Relaxed) == self.slots.len()
    }

    /// The most bytes ever resident at once.
    pub fn peak_bytes(&self) -> u64 {
        self.peak.load(Ordering::Relaxed)
    }

    /// Voxels freed so far.
    pub fn evicted(&self) -> u64 {
        self.evicted.load(Ordering::Relaxed)
    }

    /// Ids of the resident voxels (for tests and logs).
    pub fn resident_ids(&self) -> Vec<u32> {
        (0..self.slots.len() as u32)
            .filter(|&i| self.contains(i))
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn voxel(id: u32, bytes: usize) -> Arc<PreparedVoxel> {
        Arc::new(PreparedVoxel {
            id,
            nodes: Vec::new(),
            frame: dray_trace::accel::Frame::EMPTY,
            corners: Vec::new(),
            ids: Vec::new(),
            triangles: Vec::new(),
            normals: Vec::new(),
            colors: Vec::new(),
            bytes,
        })
    }

    #[test]
    fn budget_holds_when_nothing_is_in_use() {
        let c = VoxelCache::new(100, 1000);
        for id in 0..100 {
            c.insert(voxel(id, 90 + id as usize % 20));
            assert!(c.resident_bytes() <= 1000, "after voxel {id}");
        }
        assert!(c.peak_bytes() <= 1000);
        assert!(c.evicted() > 80);
        let total: u64 = c
            .resident_ids()
            .iter()
            .map(|&i| c.get(i).unwrap().bytes as u64)
            .sum();
        assert_eq!(total, c.resident_bytes());
    }

    #[test]
    fn voxels_in_use_are_never_evicted() {
        let c = VoxelCache::new(12, 250);
        let held: Vec<_> = (0..3).map(|id| c.insert(voxel(id, 100)).0).collect();
        // Over budget, but everything is in use.
        assert_eq!(c.resident_bytes(), 300);
        assert_eq!(c.evicted(), 0);
        for id in 3..10 {
            c.insert(voxel(id, 100));
        }
        for v in &held {
            assert!(c.contains(v.id), "voxel {} in use was evicted", v.id);
        }
        assert_eq!(c.peak_bytes(), 400);
        drop(held);
        // Re-inserting a resident voxel changes nothing; the next insert
        // frees what was in use.
        let (_, freed) = c.insert(voxel(9, 100));
        assert_eq!(freed, 0);
        let (_, freed) = c.insert(voxel(10, 100));
        assert_eq!(freed, 3);
        assert_eq!(c.resident_ids(), vec![9, 10]);
    }

    #[test]
    fn least_recently_used_goes_first() {
        let c = VoxelCache::new(10, 300);
        for id in 0..3 {
            c.insert(voxel(id, 100));
        }
        // Use 0 and 2 again: 1 is now the oldest.
        assert!(c.get(0).is_some());
        assert!(c.get(2).is_some());
        c.insert(voxel(3, 100));
        assert_eq!(c.resident_ids(), vec![0, 2, 3]);
        // Repeated uses of the newest change nothing; 0 is the oldest now.
        c.get(2);
        c.get(2);
        c.get(3);
        c.insert(voxel(4, 100));
        assert_eq!(c.resident_ids(), vec![2, 3, 4]);
        assert_eq!(c.evicted(), 2);
        assert!(c.get(1).is_none());
    }

    #[test]
    fn it_holds_all_only_while_every_voxel_is_resident() {
        let c = VoxelCache::new(3, 1000);
        c.insert(voxel(0, 100));
        c.insert(voxel(1, 100));
        assert!(!c.holds_all());
        // The same voxel again is no new one.
        c.insert(voxel(1, 100));
        assert!(!c.holds_all());
        c.insert(voxel(2, 100));
        assert!(c.holds_all());
        // A budget for two: the third insert frees one.
        let c = VoxelCache::new(3, 250);
        for id in 0..3 {
            c.insert(voxel(id, 100));
        }
        assert!(!c.holds_all());
        assert_eq!(c.resident_ids(), vec![1, 2]);
        // Held, all three stay (over budget): the count followed.
        let held: Vec<_> = [0, 1, 2].map(|id| c.insert(voxel(id, 100)).0).into();
        assert_eq!(c.resident_ids().len(), 3, "{:?}", c.resident_ids());
        assert!(c.holds_all());
        drop(held);
    }

    #[test]
    fn a_voxel_larger_than_the_budget_stays_until_replaced() {
        let c = VoxelCache::new(4, 50);
        c.insert(voxel(0, 100));
        assert!(c.contains(0));
        c.insert(voxel(1, 100));
        assert_eq!(c.resident_ids(), vec![1]);
        assert_eq!(c.peak_bytes(), 100);
    }
}
