//! Decoded voxels shared by every client of one process: the virtual
//! engine simulates a thousand clients in one process, and a thousand
//! decoded copies of the same voxel would make its memory grow with the
//! clients instead of the model. A voxel is decoded once while any
//! client's cache (or packet) holds it; each client still accounts it in
//! its own cache, budget and LRU order as if it had its own copy, and is
//! still charged the decode's time by the cost model.

use dray_scene::db::manifest::VoxelEntry;
use dray_trace::accel::PreparedVoxel;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, Weak};

/// Voxels decoded by some client and still held by one, by id.
#[derive(Default)]
pub struct DecodedVoxels {
    live: Mutex<HashMap<u32, Weak<PreparedVoxel>>>,
    decoded: std::sync::atomic::AtomicU64,
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
            if let Some(v) = self.lock().get(&id).and_then(Weak::upgrade) {
                return Ok(v);
            }
        }
        let v = super::loader::decode(id, entry, blob)?;
        self.decoded
            .fetch_add(1, std::sync::atomic::Ordering::Relaxed);
        let mut live = self.lock();
        // Forget voxels no client holds any more, now and then: the map
        // stays as large as what is held.
        if live.len() >= 1024 && live.len().is_power_of_two() {
            live.retain(|_, w| w.strong_count() > 0);
        }
        live.insert(id, Arc::downgrade(&v));
        Ok(v)
    }

    /// Voxels decoded so far (not those shared).
    pub fn decodes(&self) -> u64 {
        self.decoded.load(std::sync::atomic::Ordering::Relaxed)
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, HashMap<u32, Weak<PreparedVoxel>>> {
        self.live.lock().unwrap_or_else(|e| e.into_inner())
    }
}
