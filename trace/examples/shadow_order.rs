//! Experiment: does the order in which shadow rays are grouped into
//! packets matter? Renders one view's primary hits (one thread), then
//! traces a shadow ray from every hit towards the light in packets of 16
//! formed four ways, and prints Mrays/s for each:
//!
//! - `per block`: 4×4 pixel blocks, as the kernel forms them (lanes
//!   without a hit are dead);
//! - `compacted`: the hits in block order, 16 to a packet;
//! - `sorted`: every hit of the frame in Morton order of its position on
//!   the plane across the light (then along it), so that rays running side
//!   by side share a packet;
//! - `tile-sorted`: the same within each 32×32 tile, which is what a
//!   tile's job could do.
//!
//! The packet code is generic; built for this CPU it compares the
//! orderings fairly (the absolute figures are not the kernel's):
//!
//! ```text
//! RUSTFLAGS="-C target-cpu=native" CARGO_TARGET_DIR=target/native \
//!   cargo run --release -p dray-trace --example shadow_order -- DB EYE LOOK
//! ```
//!
//! (EYE and LOOK as `x,y,z`; field of view 50°, 640×480, light 0.3,1,0.2:
//! `scripts/bench-kernel`'s views.) Every ordering must report the same
//! number of occluded rays.
use dray_scene::db::Database;
use dray_trace::camera::Camera;
use dray_trace::packet::{Packet, Traversal};
use dray_trace::render::{render, RenderSettings};
/// As the kernel's shadow rays start (`render::SHADOW_EPS`, times the
/// scene's diagonal).
const SHADOW_EPS: f32 = 1e-4;
use dray_trace::accel::{ResidentSource, TopLevel};
use glam::Vec3;
use std::time::Instant;

const N: usize = 16;

fn v3(s: &str) -> Vec3 {
    let p: Vec<f32> = s.split(',').map(|x| x.parse().unwrap()).collect();
    Vec3::new(p[0], p[1], p[2])
}

fn trace(
    top: &TopLevel,
    src: &ResidentSource,
    packets: &[Vec<Vec3>],
    light: Vec3,
    eps: f32,
) -> (f64, usize) {
    let mut occluded = 0;
    let t0 = Instant::now();
    let mut tr = Traversal::<N>::default();
    for chunk in packets {
        let mut o = [Vec3::ZERO; N];
        o[..chunk.len()].copy_from_slice(chunk);
        let mut pk = Packet::<N>::new(&o, &[light; N], eps, f32::INFINITY);
        pk.any_hit = true;
        // Lanes without a hit take no part.
        pk.t[chunk.len()..].fill(f32::NEG_INFINITY);
        tr.reset();
        tr.run(&mut pk, top, src);
        occluded += (0..chunk.len()).filter(|&i| pk.occluded(i)).count();
    }
    (t0.elapsed().as_secs_f64(), occluded)
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let db = Database::open(std::path::Path::new(&a[1])).unwrap();
    let top = TopLevel::from_manifest(&db.manifest);
    let src = ResidentSource::load(&db).unwrap();
    let diag = db.manifest.model_bounds.diagonal();
    let cam = Camera {
        eye: v3(&a[2]),
        look: v3(&a[3]),
        up: Vec3::Y,
        fov_degrees: 50.0,
        width: 640,
        height: 480,
    };
    let settings = RenderSettings {
        threads: 1,
        ..RenderSettings::primary(diag)
    };
    let frame = render(&top, &src, &cam, &settings).unwrap();
    let b = cam.basis();
    let light = Vec3::new(0.3, 1.0, 0.2).normalize();
    let eps = SHADOW_EPS * diag;
    // Pixel blocks of 4x4, as the kernel forms them.
    let mut blocks = Vec::new();
    let mut per_block: Vec<Vec<Vec3>> = Vec::new();
    for by in (0..480).step_by(4) {
        for bx in (0..640).step_by(4) {
            let first = blocks.len();
            for y in by..by + 4 {
                for x in bx..bx + 4 {
                    let t = frame.depth[(y * 640 + x) as usize];
                    if t.is_finite() {
                        let r = b.ray(x, y);
                        blocks.push(r.origin + r.dir * t);
                    }
                }
            }
            if blocks.len() > first {
                per_block.push(blocks[first..].to_vec());
            }
        }
    }
    // Sorted: Morton order of the points projected on the plane across the
    // light (rays that run side by side), then along the light.
    let u = light.cross(Vec3::Z).normalize();
    let v = light.cross(u);
    let (mut lo, mut hi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
    let proj: Vec<Vec3> = blocks
        .iter()
        .map(|p| Vec3::new(p.dot(u), p.dot(v), p.dot(light)))
        .collect();
    for p in &proj {
        lo = lo.min(*p);
        hi = hi.max(*p);
    }
    let key = |p: &Vec3| {
        let q = (*p - lo) / (hi - lo).max(Vec3::splat(1e-9)) * 1023.0;
        let mut k = 0u64;
        for bit in 0..10 {
            for (axis, c) in [q.x as u64, q.y as u64, q.z as u64].iter().enumerate() {
                k |= ((c >> bit) & 1) << (3 * bit + axis);
            }
        }
        k
    };
    let mut order: Vec<usize> = (0..blocks.len()).collect();
    order.sort_by_key(|&i| key(&proj[i]));
    let sorted: Vec<Vec3> = order.iter().map(|&i| blocks[i]).collect();
    // Sorted within each 32x32 tile (as a tile's job could).
    let mut tiled: Vec<Vec<Vec3>> = Vec::new();
    for ty in (0..480).step_by(32) {
        for tx in (0..640).step_by(32) {
            let mut pts = Vec::new();
            for y in ty..(ty + 32).min(480) {
                for x in tx..(tx + 32).min(640) {
                    let t = frame.depth[(y * 640 + x) as usize];
                    if t.is_finite() {
                        let r = b.ray(x, y);
                        pts.push(r.origin + r.dir * t);
                    }
                }
            }
            pts.sort_by_key(|p| key(&Vec3::new(p.dot(u), p.dot(v), p.dot(light))));
            tiled.extend(pts.chunks(N).map(|c| c.to_vec()));
        }
    }
    for _ in 0..2 {
        let chunks = |v: &Vec<Vec3>| v.chunks(N).map(|c| c.to_vec()).collect::<Vec<_>>();
        let (compact, sorted_p) = (chunks(&blocks), chunks(&sorted));
        for (name, pts) in [
            ("per block", &per_block),
            ("compacted", &compact),
            ("sorted", &sorted_p),
            ("tile-sorted", &tiled),
        ] {
            let mut best = f64::MAX;
            let mut occ = 0;
            for _ in 0..5 {
                let (s, o) = trace(&top, &src, pts, light, eps);
                best = best.min(s);
                occ = o;
            }
            let n = blocks.len();
            println!(
                "{name}: {} packets, {n} rays, {:.2} Mrays/s, occluded {occ}",
                pts.len(),
                n as f64 / best / 1e6
            );
        }
    }
}
