//! The Client against a faulty store (written here): the first answer for
//! some voxels has a flipped byte, for others it is a VoxelError. The
//! client fetches them again and the frame is still exactly right; a
//! manifest that does not parse stops the client with a clear error.

mod client_common;

use client_common::*;
use dray_actors::client::{run_client, ClientOptions};
use dray_actors::{names, ActorError};
use dray_protocol::{Blob, Compression, ManifestData, Message, Shutdown, VoxelError, VoxelLoaded};
use dray_runtime::{InProcNet, LinkShape, Mailbox, Role};
use dray_scene::db::manifest::MANIFEST_FILE;
use dray_scene::db::Database;
use dray_trace::render::Isa;
use dray_trace::tile::MissMode;
use std::collections::HashMap;
use std::path::Path;
use std::time::Duration;

/// What the fake store does to voxel `id`'s first answer.
#[derive(Clone, Copy, PartialEq, Debug)]
enum Fault {
    None,
    FlipByte,
    Refuse,
}

fn fault(id: u32) -> Fault {
    match id % 3 {
        0 => Fault::FlipByte,
        1 => Fault::Refuse,
        _ => Fault::None,
    }
}

/// Serves `db` until told to stop; returns how often each voxel was asked for.
async fn faulty_store(mut mb: Mailbox, dir: &Path, manifest: Vec<u8>) -> HashMap<u32, u32> {
    let db = Database::open(dir).unwrap();
    let mut asked: HashMap<u32, u32> = HashMap::new();
    while let Some((from, msg)) = mb.recv_message().await {
        let reply = match msg {
            Message::FetchManifest(_) => Message::ManifestData(ManifestData {
                data: Blob(manifest.clone()),
            }),
            Message::FetchVoxel(f) => {
                let n = asked.entry(f.id).or_default();
                *n += 1;
                let mut blob = db.read_blob(f.id).unwrap();
                match (*n, fault(f.id)) {
                    (1, Fault::FlipByte) => {
                        let k = blob.len() / 2;
                        blob[k] ^= 0x10;
                    }
                    (1, Fault::Refuse) => {
                        mb.send(
                            &from,
                            Message::VoxelError(VoxelError {
                                id: f.id,
                                message: "busy".into(),
                            }),
                        )
                        .await
                        .unwrap();
                        continue;
                    }
                    _ => {}
                }
                Message::VoxelLoaded(VoxelLoaded {
                    id: f.id,
                    data: Blob(blob),
                })
            }
            Message::Shutdown(_) => break,
            other => panic!("unexpected {other:?}"),
        };
        let _ = mb.send(&from, reply).await;
    }
    asked
}

fn options(mode: MissMode) -> ClientOptions {
    ClientOptions {
        threads: 2,
        cache_bytes: 1 << 30,
        miss_mode: mode,
        max_inflight_fetches: 4,
        tiles_ahead: 2,
        max_tiles_ahead: 2,
        preload: false,
        pixel_compression: Compression::Lz4,
        isa: Isa::detect(),
        stores: routes(1),
        scheduler: names::scheduler(),
        display: names::display(),
        corrupt_voxel: Default::default(),
        virtual_clock: None,
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn corrupt_and_refused_voxels_are_fetched_again() {
    let db = plant_db(20_000);
    let want = reference(&db.db);
    for mode in [MissMode::Suspend, MissMode::Block] {
        let net = InProcNet::new();
        let store_bus = net.add_node(names::store_node(0), Role::Store).unwrap();
        let store_mb = store_bus.mailbox(name(names::STORE), 1024).unwrap();
        let manifest = std::fs::read(db.path.join(MANIFEST_FILE)).unwrap();
        let dir = db.path.clone();
        let store = tokio::spawn(async move { faulty_store(store_mb, &dir, manifest).await });
        let mut fe = FakeFrontEnd::new(&net);
        let client_bus = net.add_node(names::client_node(0), Role::Client).unwrap();
        net.set_shape(
            &names::client_node(0),
            &names::store_node(0),
            LinkShape {
                latency: Duration::from_millis(5),
                ..LinkShape::default()
            },
        )
        .unwrap();
        let mb = client_bus.mailbox(name(names::CLIENT), 1024).unwrap();
        let opts = options(mode);
        let capacity = opts.threads + opts.tiles_ahead;
        let client = tokio::spawn(run_client(mb, opts));
        let out = render_frame(&mut fe, &db.db, &names::client(0), capacity, false).await;
        let summary = client.await.unwrap().unwrap();
        fe.display
            .send(
                &names::store(0),
                Message::Shutdown(Shutdown {
                    reason: "over".into(),
                }),
            )
            .await
            .unwrap();
        let asked = store.await.unwrap();
        assert_same(&out, &want, &format!("{mode:?} with faults"));
        let mut faulty = 0;
        for (&id, &n) in &asked {
            match fault(id) {
                Fault::None => assert_eq!(n, 1, "voxel {id} asked {n} times"),
                f => {
                    assert_eq!(n, 2, "voxel {id} ({f:?}) asked {n} times");
                    faulty += 1;
                }
            }
        }
        assert!(faulty > 2, "only {faulty} faulty voxels were needed");
        assert_eq!(summary.fetched, asked.len() as u64);
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn an_unusable_manifest_stops_the_client_with_an_error() {
    let net = InProcNet::new();
    let store_bus = net.add_node(names::store_node(0), Role::Store).unwrap();
    let store_mb = store_bus.mailbox(name(names::STORE), 16).unwrap();
    let _fe = FakeFrontEnd::new(&net);
    let client_bus = net.add_node(names::client_node(0), Role::Client).unwrap();
    let mb = client_bus.mailbox(name(names::CLIENT), 16).unwrap();
    let client = tokio::spawn(run_client(mb, options(MissMode::Suspend)));
    // The client asks again (another store, here the same) before it
    // gives up: each ask gets the same bad bytes.
    let store = tokio::spawn(async move {
        let mut mb = store_mb;
        for _ in 0..2 {
            let (from, msg) = mb.recv_message().await.unwrap();
            assert!(matches!(msg, Message::FetchManifest(_)), "{msg:?}");
            mb.send(
                &from,
                Message::ManifestData(ManifestData {
                    data: Blob(b"DRAYMANI but not really a manifest".to_vec()),
                }),
            )
            .await
            .unwrap();
        }
        mb
    });
    let err = tokio::time::timeout(Duration::from_secs(30), client)
        .await
        .unwrap()
        .unwrap()
        .unwrap_err();
    assert!(matches!(err, ActorError::Peer { .. }), "{err:?}");
    assert!(err.to_string().contains("manifest"), "{err}");
    drop(store.await.unwrap());
}
