//! Decoded voxels shared by every client of one process: the virtual
//! engine simulates a thousand clients in one process, and a thousand
//! decoded copies of the same voxel would make its memory grow with the
//! clients instead of the model. A voxel is decoded once while any
//! client's cache (or packet) holds it; each client still accounts it in
//! its own cache, budget and LRU order as if it had its own copy, frees
//! it when only caches hold it (as it frees its own copy when only it
//! does), and is still charged the decode's time by the cost model.

use dray_scene::db::manifest::VoxelEntry;
use dray_trace::accel::PreparedVoxel;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};

/// Voxels decoded by some client and still held by one, by id.
#[derive(Default)]
pub struct DecodedVoxels {
    live: Mutex<HashMap<u32, Shared>>,
}

#[derive(Default)]
struct Shared {
    voxel: Weak<PreparedVoxel>,
    /// Clients' caches holding it: a cache may free a voxel that only
    /// caches hold, as it frees one only it holds where nothing is shared.
    caches: usize,
}

impl DecodedVoxels {
    pub fn new() -> Arc<DecodedVoxels> {
        Arc::new(DecodedVoxels::default())
    }

    /// Voxel `id` from `blob`: the copy another client holds where there
    /// is one and the blob is the one the manifest names (its length and
    /// stored checksum), else decoded here (and checked in full).
    pub(crate) fn get_or_decode(
        &self,
        id: u32,
        entry: &VoxelEntry,
        blob: &[u8],
    ) -> Result<Arc<PreparedVoxel>, String> {
        let same_blob = blob.len() as u64 == entry.compressed_bytes
            && dray_scene::voxel::stored_checksum(blob) == Some(entry.checksum);
        if same_blob {
            if let Some(v) = self.lock().get(&id).and_then(|s| s.voxel.upgrade()) {
                return Ok(v);
            }
        }
        let v = super::loader::decode(id, entry, blob)?;
        // One entry per voxel id at most: a voxel no one holds keeps only
        // its entry, not its data.
        self.lock().entry(id).or_default().voxel = Arc::downgrade(&v);
        Ok(v)
    }

    /// A client's cache took voxel `id` in (`true`) or freed it.
    pub(crate) fn cached(&self, id: u32, taken: bool) {
        let mut live = self.lock();
        let s = live.entry(id).or_default();
        if taken {
            s.caches += 1;
        } else {
            s.caches = s.caches.saturating_sub(1);
        }
    }

    /// Whether `v` is held by nothing but clients' caches (the asking
    /// cache's own hold among them).
    pub(crate) fn only_cached(&self, v: &Arc<PreparedVoxel>) -> bool {
        let caches = self.lock().get(&v.id).map_or(1, |s| s.caches.max(1));
        Arc::strong_count(v) <= caches
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u32, Shared>> {
        self.live.lock().unwrap_or_else(|e| e.into_inner())
    }
}
