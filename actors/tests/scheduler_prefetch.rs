//! The prefetcher on a real (small) voxel database, against a fake store
//! and fake clients: its hints name exactly the voxels that a brute-force
//! walk of the same sample rays of the predicted camera enters first.

use dray_actors::names::{self, Shard, StoreRoutes};
use dray_actors::scheduler::{run_prefetcher, PrefetcherOptions, TileGrid, TilePolicy, WARM_AFTER};
use dray_actors::settings::kernel_camera;
use dray_protocol::{
    Blob, BoundedVec, Camera, CameraUpdate, ManifestData, Message, Name, PackedF32, PackedU32,
    PrefetchHint, Role, Shutdown, TileOwners,
};
use dray_runtime::{InProcNet, Mailbox};
use dray_scene::db::manifest::{Manifest, MANIFEST_FILE};
use dray_scene::Ray;
use glam::Vec3;
use std::collections::HashSet;
use std::time::Duration;

const W: u32 = 128;
const H: u32 = 96;
const STEP: u32 = 8;
const PER_RAY: usize = 2;

fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

/// A plant preprocessed into a temporary database: the manifest's bytes.
fn database() -> (tempfile::TempDir, Vec<u8>) {
    let t = dray_testkit::plant_db(20_000, 3, 256);
    let bytes = std::fs::read(t.path.join(MANIFEST_FILE)).unwrap();
    (t.dir, bytes)
}

/// Left half of the tiles to client 0, right half to client 1, the top
/// left tile to nobody.
fn owners() -> TileOwners {
    let grid = TileGrid::new(W, H, 32);
    let owners = (0..grid.count())
        .map(|i| {
            if i == 0 {
                u32::MAX
            } else if (i as u32 % grid.cols) < grid.cols / 2 {
                0
            } else {
                1
            }
        })
        .collect();
    TileOwners {
        frame: 1,
        width: W,
        height: H,
        tile_size: 32,
        owners: PackedU32(owners),
        clients: BoundedVec::new(vec![names::client_node(0), names::client_node(1)]).unwrap(),
        // No content known: hints go by the tiles' owners.
        hit_counts: Blob(vec![0; grid.count()]),
        hits: PackedF32(Vec::new()),
        misses: 1,
        holds_model: BoundedVec::default(),
    }
}

/// [`owners`] as frame `frame`'s, whose packets met `misses` missing voxels.
fn owners_of(frame: u64, misses: u64) -> Message {
    Message::TileOwners(TileOwners {
        frame,
        misses,
        ..owners()
    })
}

/// Per client, the voxels the first `PER_RAY` content boxes entered along
/// each sample ray (by entry distance, over every voxel), and every voxel
/// any of its rays enters.
fn brute_force(m: &Manifest, cam: &Camera) -> Vec<(HashSet<u32>, HashSet<u32>, HashSet<u32>)> {
    let basis = kernel_camera(cam, W, H).basis();
    let o = owners();
    let grid = TileGrid::new(W, H, 32);
    let mut out = vec![(HashSet::new(), HashSet::new(), HashSet::new()); 2];
    for by in (0..H).step_by(STEP as usize) {
        for bx in (0..W).step_by(STEP as usize) {
            let (x, y) = (bx + STEP.min(W - bx) / 2, by + STEP.min(H - by) / 2);
            let c = o.owners.0[grid.tile_at(x, y).unwrap()];
            if c == u32::MAX {
                continue;
            }
            let ray = Ray {
                origin: basis.eye,
                dir: basis.direction(x, y),
            };
            let mut hits: Vec<(f32, u32)> = m
                .voxels
                .iter()
                .enumerate()
                .filter_map(|(v, e)| {
                    e.content
                        .ray_interval(&ray, 0.0, f32::INFINITY)
                        .map(|(t0, _)| (t0, v as u32))
                })
                .collect();
            hits.sort_by(|a, b| a.0.total_cmp(&b.0));
            let entry = &mut out[c as usize];
            if let Some(&(_, v)) = hits.first() {
                entry.2.insert(v);
            }
            entry.1.extend(hits.iter().map(|h| h.1));
            entry.0.extend(hits.iter().take(PER_RAY).map(|h| h.1));
        }
    }
    out
}

async fn hint(mb: &mut Mailbox) -> Option<PrefetchHint> {
    match tokio::time::timeout(Duration::from_secs(10), mb.recv_message()).await {
        Ok(Some((_, Message::PrefetchHint(h)))) => Some(h),
        Ok(other) => panic!("client got {other:?}"),
        Err(_) => None,
    }
}

#[tokio::test(start_paused = true)]
async fn scheduler_prefetcher_hints_the_voxels_of_each_clients_tiles() {
    let (_dir, manifest_bytes) = database();
    let manifest = Manifest::decode(&manifest_bytes).unwrap();
    assert!(
        manifest.voxels.len() > 20,
        "{} voxels",
        manifest.voxels.len()
    );

    let net = InProcNet::new();
    let sched = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let pmb = sched.mailbox(name(names::PREFETCHER), 1024).unwrap();
    let feeder = sched.mailbox(name(names::ASSIGNER), 1024).unwrap();
    // Store 0 is not there: the prefetcher must turn to store 1.
    let store = net.add_node(names::store_node(1), Role::Store).unwrap();
    let mut smb = store.mailbox(name(names::STORE), 16).unwrap();
    let data = manifest_bytes.clone();
    let store_task = tokio::spawn(async move {
        let mut asked = 0;
        while let Some((from, msg)) = smb.recv_message().await {
            if let Message::FetchManifest(_) = msg {
                asked += 1;
                let reply = Message::ManifestData(ManifestData {
                    data: data.clone().into(),
                });
                smb.send(&from, reply).await.unwrap();
            }
        }
        asked
    });
    let c0 = net.add_node(names::client_node(0), Role::Client).unwrap();
    let c1 = net.add_node(names::client_node(1), Role::Client).unwrap();
    let mut clients = [
        c0.mailbox(name(names::CLIENT), 64).unwrap(),
        c1.mailbox(name(names::CLIENT), 64).unwrap(),
    ];
    let routes = StoreRoutes::new(vec![
        (Shard::ALL, names::store(0)),
        (Shard::ALL, names::store(1)),
    ])
    .unwrap();
    let task = tokio::spawn(run_prefetcher(
        pmb,
        PrefetcherOptions {
            stores: routes,
            step: STEP,
            voxels_per_ray: PER_RAY as u32,
            width: W,
            height: H,
            policy: TilePolicy::Affinity,
        },
    ));

    // Two cameras walking towards the model.
    let base = dray_trace::camera::Camera::default_for(&manifest.model_bounds, W, H);
    let cam = |k: f32| {
        let eye = base.eye + (base.look - base.eye) * (0.1 * k);
        Camera {
            eye: eye.to_array(),
            look: base.look.to_array(),
            up: base.up.to_array(),
            fov_y_deg: base.fov_degrees,
        }
    };
    for (seq, k) in [(0, 0.0), (1, 1.0)] {
        let u = Message::CameraUpdate(CameraUpdate {
            seq,
            camera: cam(k),
            sample: 0,
            format: None,
        });
        feeder.send(&names::prefetcher(), u).await.unwrap();
    }
    // No owners yet: no hint, whatever the wait.
    assert!(hint(&mut clients[0]).await.is_none());
    assert!(hint(&mut clients[1]).await.is_none());
    feeder
        .send(&names::prefetcher(), Message::TileOwners(owners()))
        .await
        .unwrap();

    // The predicted camera: the eye goes on by one more step.
    let (e0, e1) = (
        Vec3::from_array(cam(0.0).eye),
        Vec3::from_array(cam(1.0).eye),
    );
    let predicted = Camera {
        eye: (e1 + (e1 - e0) * 1.0).to_array(),
        ..cam(1.0)
    };
    let truth = brute_force(&manifest, &predicted);
    for (c, mb) in clients.iter_mut().enumerate() {
        let h = hint(mb).await.expect("a hint for each owner");
        assert_eq!(
            h.frame, 2,
            "the hint is for the frame after the last camera"
        );
        let ids = &h.voxels.0;
        assert!(!ids.is_empty());
        let set: HashSet<u32> = ids.iter().copied().collect();
        assert_eq!(set.len(), ids.len(), "no voxel twice");
        assert!(ids.iter().all(|&v| (v as usize) < manifest.voxels.len()));
        let (first, any, nearest) = &truth[c];
        assert!(
            set.is_subset(any),
            "client {c}: a hinted voxel is on none of its rays"
        );
        assert_eq!(
            &set, first,
            "client {c}: the first {PER_RAY} voxels of each ray"
        );
        // Most urgent first: the voxels some ray enters first lead.
        let lead: HashSet<u32> = ids[..nearest.len()].iter().copied().collect();
        assert_eq!(&lead, nearest, "client {c}");
    }
    // The two halves of the image see different voxels.
    assert_ne!(truth[0].0, truth[1].0);

    // A new camera: a new hint for the next frame.
    let u = Message::CameraUpdate(CameraUpdate {
        seq: 2,
        camera: cam(2.0),
        sample: 0,
        format: None,
    });
    feeder.send(&names::prefetcher(), u).await.unwrap();
    for mb in clients.iter_mut() {
        assert_eq!(hint(mb).await.expect("another hint").frame, 3);
    }

    // Warm caches: eight frames in a row done without a miss. Then only
    // every fourth frame is planned, until a frame misses again.
    for frame in 2..2 + u64::from(WARM_AFTER) {
        feeder
            .send(&names::prefetcher(), owners_of(frame, 0))
            .await
            .unwrap();
    }
    let mut hinted = Vec::new();
    for seq in 3..11u64 {
        let u = Message::CameraUpdate(CameraUpdate {
            seq,
            camera: cam(seq as f32 * 0.5),
            sample: 0,
            format: None,
        });
        feeder.send(&names::prefetcher(), u).await.unwrap();
        if let Some(h) = hint(&mut clients[0]).await {
            hinted.push(h.frame);
            assert_eq!(hint(&mut clients[1]).await.map(|h| h.frame), Some(h.frame));
        }
    }
    assert_eq!(hinted, vec![4, 8], "warm: every fourth frame planned");
    feeder
        .send(
            &names::prefetcher(),
            owners_of(2 + u64::from(WARM_AFTER), 3),
        )
        .await
        .unwrap();
    let u = Message::CameraUpdate(CameraUpdate {
        seq: 11,
        camera: cam(5.5),
        sample: 0,
        format: None,
    });
    feeder.send(&names::prefetcher(), u).await.unwrap();
    assert_eq!(
        hint(&mut clients[0]).await.map(|h| h.frame),
        Some(12),
        "a miss: planned again"
    );
    assert_eq!(hint(&mut clients[1]).await.map(|h| h.frame), Some(12));

    // Client 1's cache holds the whole model: hints for client 0 only,
    // then, once both hold it, no plan at all.
    for (frame, whole) in [
        (11, vec![names::client_node(1)]),
        (12, vec![names::client_node(0), names::client_node(1)]),
    ] {
        let o = Message::TileOwners(TileOwners {
            frame,
            misses: 3,
            holds_model: BoundedVec::new(whole).unwrap(),
            ..owners()
        });
        feeder.send(&names::prefetcher(), o).await.unwrap();
        let u = Message::CameraUpdate(CameraUpdate {
            seq: frame + 1,
            camera: cam(frame as f32 * 0.5),
            sample: 0,
            format: None,
        });
        feeder.send(&names::prefetcher(), u).await.unwrap();
        let to_0 = hint(&mut clients[0]).await.map(|h| h.frame);
        assert_eq!(to_0, (frame == 11).then_some(13), "frame {frame}");
        assert_eq!(hint(&mut clients[1]).await, None, "frame {frame}");
    }

    let bye = Message::Shutdown(Shutdown {
        reason: "test over".into(),
    });
    feeder.send(&names::prefetcher(), bye).await.unwrap();
    let summary = task.await.unwrap().unwrap();
    assert_eq!(summary.hints, 4 + 2 * 2 + 2 + 1);
    assert_eq!(summary.frames_skipped, 6 + 1);
    assert!(summary.voxels_hinted >= 4);
    drop(store);
    store_task.abort();
}
