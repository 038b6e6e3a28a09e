//! Latency hiding on tokio's paused clock: a tile whose packets need 16
//! different missing voxels, each delivered 50 ms after its request.

use dray_trace::accel::{PreparedVoxel, ResidentSource, TopLevel, VoxelRef, VoxelSource};
use dray_trace::camera::Camera;
use dray_trace::render::Isa;
use dray_trace::render::RenderSettings;
use dray_trace::tile::{render_tile, LoadError, MissMode, Rect, TileImage, VoxelLoader};
use futures::future::BoxFuture;
use glam::Vec3;
use std::collections::HashSet;
use std::io::Write;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::time::Instant;

const DELAY: Duration = Duration::from_millis(50);

/// Voxels become resident `DELAY` after they are asked for.
struct SlowLoader {
    all: ResidentSource,
    resident: Mutex<HashSet<u32>>,
}

impl VoxelSource for SlowLoader {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        if self.resident.lock().unwrap().contains(&id) {
            self.all.voxel(id)
        } else {
            None
        }
    }
}

impl VoxelLoader for SlowLoader {
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>> {
        Box::pin(async move {
            tokio::time::sleep(DELAY).await;
            self.resident.lock().unwrap().insert(id);
            self.all.shared(id).ok_or(LoadError {
                voxel: id,
                message: "no such voxel".into(),
            })
        })
    }
}

/// A 32×32 tile facing a wall of 4×4 squares, each covering an 8×8 pixel
/// block (with gaps no pixel centre falls in), two triangles per voxel: 16
/// voxels, each the only one its rays need.
fn scene() -> (tempfile::TempDir, Camera, TopLevel, ResidentSource) {
    let cam = Camera {
        eye: Vec3::new(0.0, 0.0, 10.0),
        look: Vec3::ZERO,
        up: Vec3::Y,
        fov_degrees: 40.0,
        width: 32,
        height: 32,
    };
    let basis = cam.basis();
    // Where the ray through (sub)pixel (px, py) meets the plane z = 0.
    let at = |px: f32, py: f32| {
        let sx = 2.0 * px / 32.0 - 1.0;
        let sy = 1.0 - 2.0 * py / 32.0;
        let d = basis.forward + basis.right * sx + basis.up * sy;
        basis.eye + d * (-basis.eye.z / d.z)
    };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("wall.obj");
    let mut obj = std::io::BufWriter::new(std::fs::File::create(&path).unwrap());
    let mut v = 0;
    for j in 0..4 {
        for i in 0..4 {
            let (x0, y0) = (8.0 * i as f32 + 0.1, 8.0 * j as f32 + 0.1);
            for (px, py) in [
                (x0, y0),
                (x0 + 7.8, y0),
                (x0 + 7.8, y0 + 7.8),
                (x0, y0 + 7.8),
            ] {
                let p = at(px, py);
                writeln!(obj, "v {} {} {}", p.x, p.y, p.z).unwrap();
            }
            writeln!(obj, "f {} {} {} {}", v + 1, v + 2, v + 3, v + 4).unwrap();
            v += 4;
        }
    }
    drop(obj);
    let db = dray_testkit::preprocess_into(&path, &dir.path().join("db"), 2);
    assert_eq!(db.manifest.voxels.len(), 16, "one voxel per square");
    let top = TopLevel::from_manifest(&db.manifest);
    let all = ResidentSource::load(&db).unwrap();
    (dir, cam, top, all)
}

async fn run(mode: MissMode) -> (Duration, TileImage) {
    let (_dir, cam, top, all) = scene();
    let loader = SlowLoader {
        all,
        resident: Mutex::new(HashSet::new()),
    };
    let rect = Rect {
        x0: 0,
        y0: 0,
        width: 32,
        height: 32,
    };
    let start = Instant::now();
    let settings = RenderSettings {
        isa: Isa::detect(),
        ..RenderSettings::primary(20.0)
    };
    let hits = render_tile(&top, &loader, &cam, rect, &settings, mode)
        .await
        .unwrap();
    (start.elapsed(), hits)
}

#[tokio::test(start_paused = true)]
async fn suspend_mode_overlaps_the_sixteen_fetches() {
    let (elapsed, hits) = run(MissMode::Suspend).await;
    assert_eq!(hits.stats.requested, 16);
    assert!(
        hits.primid.iter().all(|&p| p != u32::MAX),
        "every pixel hits a square"
    );
    assert!(
        elapsed >= DELAY && elapsed < DELAY * 2,
        "suspend mode took {elapsed:?}, expected about {DELAY:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn block_mode_waits_for_each_fetch_in_turn() {
    let (elapsed, hits) = run(MissMode::Block).await;
    assert_eq!(hits.stats.requested, 16);
    assert_eq!(elapsed, DELAY * 16, "block mode");
    let (_, suspended) = run(MissMode::Suspend).await;
    assert_eq!(
        hits.primid, suspended.primid,
        "both modes give the same image"
    );
    assert_eq!(hits.depth, suspended.depth);
}
