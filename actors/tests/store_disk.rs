//! A store's modelled disk (`links.store_disk`), on tokio's paused clock:
//! reads go one after another, each taking the access time plus its bytes
//! over the bandwidth; without a model the store answers at once.

#[path = "client_common/mod.rs"]
mod common;

use common::*;
use dray_actors::names;
use dray_actors::store::{run_store, StoreDisk, StoreOptions};
use dray_actors::Shard;
use dray_protocol::{FetchVoxel, Message};
use dray_runtime::{InProcNet, Role};
use std::time::Duration;
use tokio::time::Instant;

/// Starts a store on `db` with `disk`, fetches every voxel, and returns
/// the virtual time that took.
async fn fetch_all(db: &Db, disk: StoreDisk) -> Duration {
    let n = db.db.manifest.voxels.len() as u32;
    let net = InProcNet::new();
    let store_bus = net.add_node(names::store_node(0), Role::Store).unwrap();
    let store_mb = store_bus.mailbox(name(names::STORE), 1024).unwrap();
    let opts = StoreOptions {
        database: db.path.clone(),
        shard: Shard::ALL,
        max_concurrent: 4,
        disk,
    };
    let store = tokio::spawn(run_store(store_mb, opts));
    let bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    let mut mb = bus.mailbox(name("client"), 4096).unwrap();
    let to = names::store(0);
    let t0 = Instant::now();
    for id in 0..n {
        mb.send(&to, Message::FetchVoxel(FetchVoxel { id }))
            .await
            .unwrap();
    }
    for _ in 0..n {
        let (_, msg) = mb.recv_message().await.unwrap();
        assert!(matches!(msg, Message::VoxelLoaded(_)), "{msg:?}");
    }
    let took = t0.elapsed();
    store.abort();
    took
}

#[tokio::test(start_paused = true)]
async fn a_disk_serves_at_most_its_bandwidth() {
    let db = plant_db(20_000);
    let voxels = &db.db.manifest.voxels;
    let bytes: u64 = voxels.iter().map(|v| v.compressed_bytes).sum();
    let disk = StoreDisk {
        access_time: Duration::from_millis(2),
        bandwidth_bps: Some(440_000_000),
    };
    let least = Duration::from_secs_f64(bytes as f64 * 8.0 / 440e6)
        + disk.access_time * voxels.len() as u32;
    let took = fetch_all(&db, disk).await;
    assert!(took >= least, "{took:?} < {least:?}");
    assert!(
        took <= least.mul_f64(1.05) + Duration::from_millis(1),
        "{took:?}: the disk idled (least {least:?})"
    );
    // Without a model, reads take only the real time, which the paused
    // clock does not count.
    let unmodelled = fetch_all(&db, StoreDisk::default()).await;
    assert!(unmodelled < least / 10, "{unmodelled:?}");
}
