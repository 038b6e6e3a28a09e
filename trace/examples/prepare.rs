//! Measures how fast voxels are made ready for the kernel: each voxel of a
//! database decoded from its compressed blob ([`Voxel::decode`]: zstd,
//! validation) and then prepared ([`PreparedVoxel::new`]: BVH clipped to
//! the cell, widened and quantized, corners gathered), from blobs already
//! in memory, one thread; best of five rounds. This is the work a client
//! does for every voxel it fetches, and `dray render` for every voxel
//! before its first pass.
//!
//! ```text
//! cargo run --release -p dray-trace --example prepare -- DB [VOXELS]
//! ```
//!
//! (VOXELS: the first that many voxels with triangles, default 400.)
use dray_scene::db::Database;
use dray_scene::voxel::Voxel;
use dray_trace::accel::PreparedVoxel;
use std::time::Instant;

fn main() -> anyhow::Result<()> {
    let args: Vec<String> = std::env::args().collect();
    let Some(dir) = args.get(1) else {
        anyhow::bail!("usage: prepare DB [VOXELS]");
    };
    let want: usize = args.get(2).map_or(Ok(400), |s| s.parse())?;
    let db = Database::open(std::path::Path::new(dir))?;
    let mut blobs = Vec::new();
    for id in 0..db.manifest.voxels.len() as u32 {
        if blobs.len() == want {
            break;
        }
        if db.manifest.voxels[id as usize].triangles > 0 {
            blobs.push((id, db.read_blob(id)?));
        }
    }
    let voxels: Vec<Voxel> = blobs
        .iter()
        .map(|(_, b)| Voxel::decode(b))
        .collect::<Result<_, _>>()?;
    let triangles: usize = voxels.iter().map(|v| v.triangles.len()).sum();
    let mut best = (f64::INFINITY, f64::INFINITY);
    for _ in 0..5 {
        let t = Instant::now();
        for (_, b) in &blobs {
            std::hint::black_box(Voxel::decode(b)?);
        }
        let decode = t.elapsed().as_secs_f64();
        let t = Instant::now();
        for ((id, _), v) in blobs.iter().zip(&voxels) {
            std::hint::black_box(PreparedVoxel::new(*id, v));
        }
        let prepare = t.elapsed().as_secs_f64();
        best = (best.0.min(decode), best.1.min(prepare));
    }
    let n = blobs.len() as f64;
    println!(
        "{} voxels, {triangles} triangles (with replicas): decode {:.1} µs a voxel, prepare {:.1} µs a voxel ({:.2} M triangles/s prepared)",
        blobs.len(),
        best.0 / n * 1e6,
        best.1 / n * 1e6,
        triangles as f64 / best.1 / 1e6
    );
    Ok(())
}
