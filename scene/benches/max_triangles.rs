//! How the voxel size limit (`--max-triangles`) trades database size,
//! replication and preprocessing time against ray query speed: the
//! measurement behind `DEFAULT_MAX_TRIANGLES`.
//!
//! `cargo bench -p dray-scene --bench max_triangles` generates a plant
//! (`DRAY_BENCH_TRIANGLES`, default 1 M) in a temporary directory,
//! preprocesses it with each limit, and traces primary rays (docs/design.md's
//! camera, 256×192, the generator's suggested views from outside to deep
//! inside) with the reference two-level traversal on one thread, every
//! voxel resident. The real kernel (dray-trace) is much faster; the ratios
//! between rows are what this measures.

use dray_scene::db::info::DbInfo;
use dray_scene::db::{intersect, Database};
use dray_scene::generate::{generate_plant, suggested_views, PlantParams};
use dray_scene::preprocess::{preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use dray_scene::voxel::Voxel;
use dray_scene::Ray;
use glam::Vec3;
use std::time::Instant;

const WIDTH: u32 = 256;
const HEIGHT: u32 = 192;
const FOV_DEGREES: f32 = 60.0;

fn camera_rays(eye: Vec3, look: Vec3) -> Vec<Ray> {
    let forward = (look - eye).normalize();
    let right = forward.cross(Vec3::Y).normalize();
    let up = right.cross(forward);
    let tan = (FOV_DEGREES.to_radians() / 2.0).tan();
    let aspect = WIDTH as f32 / HEIGHT as f32;
    let mut rays = Vec::with_capacity((WIDTH * HEIGHT) as usize);
    for y in 0..HEIGHT {
        for x in 0..WIDTH {
            let u = ((x as f32 + 0.5) / WIDTH as f32 * 2.0 - 1.0) * tan * aspect;
            let v = (1.0 - (y as f32 + 0.5) / HEIGHT as f32 * 2.0) * tan;
            rays.push(Ray {
                origin: eye,
                dir: (forward + u * right + v * up).normalize(),
            });
        }
    }
    rays
}

fn main() {
    let triangles: u64 = std::env::var("DRAY_BENCH_TRIANGLES")
        .ok()
        .and_then(|v| v.parse().ok())
        .unwrap_or(1_000_000);
    let dir = tempfile::tempdir().expect("temporary directory");
    let model = dir.path().join("plant.ply");
    let summary = generate_plant(&PlantParams { triangles, seed: 1 }, &model, &mut |_| {})
        .expect("generate the plant");
    let views = suggested_views(&summary.bounds);
    let rays: Vec<Ray> = views
        .iter()
        .flat_map(|&(eye, look)| camera_rays(eye, look))
        .collect();

    println!(
        "plant of {triangles} triangles, {} rays over {} views, 1 thread",
        rays.len(),
        views.len()
    );
    println!("| max triangles | voxels | replication | voxel raw KiB | voxel compressed KiB | DB MiB | preprocess s | reference Mrays/s | voxels per ray |");
    println!("|---:|---:|---:|---:|---:|---:|---:|---:|---:|");
    for max in [512u32, 1024, 2048, 4096, 8192, 16384] {
        let db_path = dir.path().join(format!("db-{max}"));
        let start = Instant::now();
        preprocess(
            &PreprocessOptions {
                max_triangles: max,
                ..PreprocessOptions::new(vec![model.clone()], db_path.clone())
            },
            &Progress::hidden(),
        )
        .expect("preprocess");
        let build_s = start.elapsed().as_secs_f64();
        let db = Database::open(&db_path).expect("open");
        let info = DbInfo::from_manifest(&db.manifest);
        let voxels: Vec<Voxel> = db.load_all().expect("load");
        let mut visited = 0u64;
        let mut best = f64::INFINITY;
        for _ in 0..3 {
            visited = 0;
            let start = Instant::now();
            for ray in &rays {
                let hit = intersect(&db.manifest, ray, f32::INFINITY, &mut |id| {
                    visited += 1;
                    &voxels[id as usize]
                });
                std::hint::black_box(hit);
            }
            best = best.min(start.elapsed().as_secs_f64());
        }
        println!(
            "| {max} | {} | {:.3} | {:.0} | {:.0} | {:.1} | {build_s:.2} | {:.2} | {:.2} |",
            info.voxels,
            info.replication_factor,
            info.voxel_raw_mean_bytes / 1024.0,
            info.voxel_compressed_mean_bytes / 1024.0,
            info.compressed_bytes as f64 / 1048576.0,
            rays.len() as f64 / best / 1e6,
            visited as f64 / rays.len() as f64
        );
    }
}
