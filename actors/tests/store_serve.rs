//! The VoxelStore actor over the in-process transport: every voxel
//! byte-identical to the database, refusals that say why, the manifest as
//! stored, a missing database named in the error, and a slow peer cannot
//! make the store read more than it may hold.

#[path = "client_common/mod.rs"]
mod common;

use common::*;
use dray_actors::names;
use dray_actors::store::{run_store, StoreOptions};
use dray_actors::{ActorError, Shard};
use dray_protocol::{FetchManifest, FetchVoxel, Message, Ping, Shutdown};
use dray_runtime::{InProcNet, Role};
use dray_scene::db::manifest::MANIFEST_FILE;
use std::collections::HashMap;
use std::time::Duration;

async fn next(mb: &mut dray_runtime::Mailbox) -> Message {
    tokio::time::timeout(Duration::from_secs(30), mb.recv_message())
        .await
        .expect("an answer in time")
        .expect("bus alive")
        .1
}

/// Sends a fetch of each of voxels `0..n` to the store at `to`.
async fn ask_for_every_voxel(mb: &dray_runtime::Mailbox, to: &dray_protocol::Address, n: u32) {
    for id in 0..n {
        mb.send(to, Message::FetchVoxel(FetchVoxel { id }))
            .await
            .unwrap();
    }
}

/// A mailbox on the display's node, the one node that may stop a store.
fn stopper(net: &InProcNet) -> dray_runtime::Mailbox {
    net.add_node(name("display"), Role::Display)
        .unwrap()
        .mailbox(name("control"), 4)
        .unwrap()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn serves_every_voxel_as_stored_and_refuses_unknown_ids() {
    let db = plant_db(20_000);
    let n = db.db.manifest.voxels.len() as u32;
    assert!(n > 8, "{n} voxels: too few for the test");
    let net = InProcNet::new();
    let (_store_bus, store) = start_store(&net, 0, db.path.clone(), Shard::ALL);
    let bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    let mut mb = bus.mailbox(name("client"), 4096).unwrap();
    let to = names::store(0);
    // Every voxel at once: the store reads at most two at a time.
    ask_for_every_voxel(&mb, &to, n).await;
    let mut got = HashMap::new();
    while got.len() < n as usize {
        match next(&mut mb).await {
            Message::VoxelLoaded(v) => assert!(got.insert(v.id, v.data.0).is_none()),
            other => panic!("unexpected {other:?}"),
        }
    }
    for id in 0..n {
        assert!(
            got[&id] == db.db.read_blob(id).unwrap(),
            "voxel {id} differs from the database"
        );
    }
    mb.send(&to, Message::FetchVoxel(FetchVoxel { id: n + 3 }))
        .await
        .unwrap();
    match next(&mut mb).await {
        Message::VoxelError(e) => {
            assert_eq!(e.id, n + 3);
            assert!(e.message.contains("no such voxel"), "{}", e.message);
        }
        other => panic!("unexpected {other:?}"),
    }
    mb.send(&to, Message::FetchManifest(FetchManifest {}))
        .await
        .unwrap();
    match next(&mut mb).await {
        Message::ManifestData(m) => {
            assert_eq!(
                m.data.0,
                std::fs::read(db.path.join(MANIFEST_FILE)).unwrap()
            )
        }
        other => panic!("unexpected {other:?}"),
    }
    mb.send(&to, Message::Ping(Ping { seq: 9 })).await.unwrap();
    assert_eq!(next(&mut mb).await, Message::Pong(Ping { seq: 9 }));
    stopper(&net)
        .send(
            &to,
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let summary = store.await.unwrap().unwrap();
    assert_eq!(summary.served, u64::from(n));
    assert_eq!(
        summary.bytes_served,
        db.db
            .manifest
            .voxels
            .iter()
            .map(|v| v.compressed_bytes)
            .sum::<u64>()
    );
    assert_eq!(summary.refused, 1);
    assert_eq!(summary.manifests, 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_shard_serves_its_voxels_only() {
    let db = plant_db(20_000);
    let n = db.db.manifest.voxels.len() as u32;
    let net = InProcNet::new();
    let shard = Shard { index: 1, count: 2 };
    let (_store_bus, store) = start_store(&net, 1, db.path.clone(), shard);
    let bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    let mut mb = bus.mailbox(name("client"), 1024).unwrap();
    let to = names::store(1);
    ask_for_every_voxel(&mb, &to, n).await;
    for _ in 0..n {
        match next(&mut mb).await {
            Message::VoxelLoaded(v) => {
                assert!(shard.owns(v.id), "served voxel {} of another shard", v.id);
                assert!(v.data.0 == db.db.read_blob(v.id).unwrap());
            }
            Message::VoxelError(e) => {
                assert!(
                    !shard.owns(e.id),
                    "refused its own voxel {}: {}",
                    e.id,
                    e.message
                );
                assert!(e.message.contains("shard 1/2"), "{}", e.message);
            }
            other => panic!("unexpected {other:?}"),
        }
    }
    stopper(&net)
        .send(
            &to,
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let summary = store.await.unwrap().unwrap();
    assert_eq!(summary.served + summary.refused, u64::from(n));
    assert_eq!(summary.refused, u64::from(n.div_ceil(2)));
}

#[tokio::test]
async fn a_missing_database_is_named() {
    let net = InProcNet::new();
    let bus = net.add_node(names::store_node(0), Role::Store).unwrap();
    let mb = bus.mailbox(name(names::STORE), 16).unwrap();
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("no-such-db");
    let err = run_store(
        mb,
        StoreOptions {
            database: missing.clone(),
            shard: Shard::ALL,
            max_concurrent: 1,
            disk: Default::default(),
        },
    )
    .await
    .unwrap_err();
    assert!(matches!(err, ActorError::Database { .. }), "{err:?}");
    let text = err.to_string();
    assert!(text.contains(&missing.display().to_string()), "{text}");
    assert!(text.contains("no such database"), "{text}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_peer_that_does_not_take_its_voxels_holds_at_most_max_concurrent_in_memory() {
    let db = plant_db(20_000);
    let n = db.db.manifest.voxels.len() as u32;
    assert!(n > 8, "{n} voxels: too few for the test");
    let net = InProcNet::new();
    let (_store_bus, store) = start_store(&net, 0, db.path.clone(), Shard::ALL);
    let bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    // A mailbox of one, never read: the store's answers wait to be sent.
    let slow = bus.mailbox(name("slow"), 1).unwrap();
    let to = names::store(0);
    ask_for_every_voxel(&slow, &to, n).await;
    tokio::time::sleep(Duration::from_millis(500)).await;
    stopper(&net)
        .send(
            &to,
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let summary = store.await.unwrap().unwrap();
    // One answer delivered into the mailbox, then two (the store's
    // max_concurrent) read and waiting to be sent; no more were read (a
    // store that let go of its permit before sending read all of them).
    assert!((1..=3).contains(&summary.served), "{summary:?}");
    drop(slow);
}
