//! Experiment: does the order in which shadow rays are grouped into
//! packets matter? Renders one view's primary hits (one thread), then
//! traces a shadow ray from every hit towards the light in packets of 16
//! formed six ways, and prints Mrays/s for each:
//!
//! - `per block`: 4×4 pixel blocks, as the kernel forms them (lanes
//!   without a hit are dead);
//! - `compacted`: the hits in block order, 16 to a packet;
//! - `sorted`: every hit of the frame in Morton order of its position on
//!   the plane across the light (then along it), so that rays running side
//!   by side share a packet;
//! - `tile-sorted`: the same within each 32×32 tile, which is what a
//!   tile's job could do;
//! - `broken blocks sorted`: within each tile, the blocks that straddle a
//!   step in depth ([`STEP`]) or the sky sorted so, the other blocks kept;
//! - `broken blocks by voxel`: those blocks' rays bucketed by the voxel
//!   their hits lie in instead.
//!
//! The three orderings a tile could form also print the time forming them
//! took (once, every tile) and the rate with it added: what a tile's job
//! would pay for the order.
//!
//! CODE says which packet code traces them: `generic` (the default: the
//! packet code as the example is built; built for this CPU it compares the
//! orderings fairly, though the absolute figures are not the kernel's),
//! `avx2` (the kernel's AVX2 code) or `avx2-groups` (that code handing
//! sparse subtrees over to groups of lanes, as the kernel's shadow packets
//! do in tiles whose rays part):
//!
//! ```text
//! RUSTFLAGS="-C target-cpu=native" CARGO_TARGET_DIR=target/native \
//!   cargo run --release -p dray-trace --example shadow_order -- DB EYE LOOK [CODE]
//! ```
//!
//! (EYE and LOOK as `x,y,z`; field of view 50°, 640×480, light 0.3,1,0.2:
//! `scripts/bench-kernel`'s views.) Every ordering must report the same
//! number of occluded rays.
use dray_scene::db::Database;
use dray_trace::camera::Camera;
use dray_trace::packet::{Packet, Traversal};
use dray_trace::render::{render, Isa, RenderSettings};
/// As the kernel's shadow rays start (`render::SHADOW_EPS`, times the
/// scene's diagonal).
const SHADOW_EPS: f32 = 1e-4;
use dray_trace::accel::{ResidentSource, TopLevel};
use glam::Vec3;
use std::time::Instant;

const N: usize = 16;

/// A block whose nearest and farthest hits differ by more than this share
/// of the nearest is taken to straddle a step in depth.
const STEP: f32 = 0.05;

fn v3(s: &str) -> Vec3 {
    let p: Vec<f32> = s.split(',').map(|x| x.parse().unwrap()).collect();
    Vec3::new(p[0], p[1], p[2])
}

/// A tile's blocks, split: whole blocks whose depths lie within [`STEP`]
/// of each other (a packet each), and the points of the others (those
/// that straddle a step in depth or see the sky), with the voxels they lie
/// in.
struct TileBlocks {
    smooth: Vec<Vec<Vec3>>,
    loose: Vec<Vec3>,
    voxels: Vec<u32>,
}

/// Which packet code traces the shadow rays.
#[derive(Clone, Copy, PartialEq)]
enum Code {
    Generic,
    Avx2,
    Avx2Groups,
}

/// What every shadow ray of the view shares.
struct Shadows<'a> {
    top: &'a TopLevel,
    src: &'a ResidentSource,
    light: Vec3,
    eps: f32,
}

#[inline(always)]
fn trace(view: &Shadows, packets: &[Vec<Vec3>], groups: bool) -> (f64, usize) {
    let mut occluded = 0;
    let t0 = Instant::now();
    let mut tr = Traversal::<N>::default();
    for chunk in packets {
        let mut o = [Vec3::ZERO; N];
        o[..chunk.len()].copy_from_slice(chunk);
        let mut pk = Packet::<N>::new(&o, &[view.light; N], view.eps, f32::INFINITY);
        pk.any_hit = true;
        if groups {
            pk.hand_off_sparse_subtrees(Isa::Avx2);
        }
        // Lanes without a hit take no part.
        pk.t[chunk.len()..].fill(f32::NEG_INFINITY);
        tr.reset();
        tr.run(&mut pk, view.top, view.src);
        occluded += (0..chunk.len()).filter(|&i| pk.occluded(i)).count();
    }
    (t0.elapsed().as_secs_f64(), occluded)
}

/// [`trace`] compiled with the kernel's AVX2 target features.
///
/// # Safety
/// The CPU must have them ([`Isa::supported`]).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn trace_avx2(view: &Shadows, packets: &[Vec<Vec3>], groups: bool) -> (f64, usize) {
    trace(view, packets, groups)
}

fn trace_with(code: Code, view: &Shadows, packets: &[Vec<Vec3>]) -> (f64, usize) {
    match code {
        Code::Generic => trace(view, packets, false),
        // SAFETY: `main` takes an AVX2 code only where the CPU has AVX2.
        #[cfg(target_arch = "x86_64")]
        _ => unsafe { trace_avx2(view, packets, code == Code::Avx2Groups) },
        #[cfg(not(target_arch = "x86_64"))]
        _ => unreachable!("AVX2 codes are refused off x86-64"),
    }
}

fn main() {
    let a: Vec<String> = std::env::args().collect();
    let code = match a.get(4).map(String::as_str) {
        None | Some("generic") => Code::Generic,
        Some("avx2") => Code::Avx2,
        Some("avx2-groups") => Code::Avx2Groups,
        Some(other) => {
            eprintln!("shadow_order: CODE {other:?}: expected generic, avx2 or avx2-groups");
            std::process::exit(2);
        }
    };
    if code != Code::Generic && !Isa::Avx2.supported() {
        eprintln!(
            "shadow_order: CODE {:?} needs AVX2, which this CPU lacks",
            a[4]
        );
        std::process::exit(2);
    }
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
    let view = Shadows {
        top: &top,
        src: &src,
        light,
        eps,
    };
    // The hit points of the 4x4 block at (bx, by), with their depths.
    let block_hits = |bx: u32, by: u32| -> Vec<(Vec3, f32)> {
        let mut hits = Vec::new();
        for y in by..by + 4 {
            for x in bx..bx + 4 {
                let t = frame.depth[(y * 640 + x) as usize];
                if t.is_finite() {
                    let r = b.ray(x, y);
                    hits.push((r.origin + r.dir * t, t));
                }
            }
        }
        hits
    };
    // Pixel blocks of 4x4, as the kernel forms them.
    let mut blocks = Vec::new();
    let mut per_block: Vec<Vec<Vec3>> = Vec::new();
    for by in (0..480).step_by(4) {
        for bx in (0..640).step_by(4) {
            let first = blocks.len();
            blocks.extend(block_hits(bx, by).into_iter().map(|(p, _)| p));
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
    let key_within = |p: &Vec3, lo: Vec3, hi: Vec3| {
        let q = (*p - lo) / (hi - lo).max(Vec3::splat(1e-9)) * 1023.0;
        let mut k = 0u64;
        for bit in 0..10 {
            for (axis, c) in [q.x as u64, q.y as u64, q.z as u64].iter().enumerate() {
                k |= ((c >> bit) & 1) << (3 * bit + axis);
            }
        }
        k
    };
    let key = |p: &Vec3| key_within(p, lo, hi);
    let mut order: Vec<usize> = (0..blocks.len()).collect();
    order.sort_by_key(|&i| key(&proj[i]));
    let sorted: Vec<Vec3> = order.iter().map(|&i| blocks[i]).collect();
    // A tile's points in Morton order across the light, quantized within
    // the tile's own bounds (the frame's would leave most of a tile's
    // points on one key); the time it takes is summed in `sorting`.
    let sorting = std::cell::Cell::new(std::time::Duration::ZERO);
    let sort_across = |pts: Vec<Vec3>| -> Vec<Vec3> {
        let t0 = Instant::now();
        let across: Vec<Vec3> = pts
            .iter()
            .map(|p| Vec3::new(p.dot(u), p.dot(v), p.dot(light)))
            .collect();
        let (mut tlo, mut thi) = (Vec3::splat(f32::MAX), Vec3::splat(f32::MIN));
        for q in &across {
            tlo = tlo.min(*q);
            thi = thi.max(*q);
        }
        let mut keyed: Vec<(u64, Vec3)> = across
            .iter()
            .zip(&pts)
            .map(|(q, p)| (key_within(q, tlo, thi), *p))
            .collect();
        keyed.sort_unstable_by_key(|&(k, _)| k);
        let sorted = keyed.into_iter().map(|(_, p)| p).collect();
        sorting.set(sorting.get() + t0.elapsed());
        sorted
    };
    let mut split: Vec<TileBlocks> = Vec::new();
    for ty in (0..480).step_by(32) {
        for tx in (0..640).step_by(32) {
            let (mut smooth, mut loose) = (Vec::new(), Vec::new());
            for by in (ty..ty + 32).step_by(4) {
                for bx in (tx..tx + 32).step_by(4) {
                    let hits = block_hits(bx, by);
                    let tmin = hits.iter().fold(f32::MAX, |m, h| m.min(h.1));
                    let tmax = hits.iter().fold(0f32, |m, h| m.max(h.1));
                    let pts: Vec<Vec3> = hits.iter().map(|h| h.0).collect();
                    if pts.len() == N && tmax <= tmin * (1.0 + STEP) {
                        smooth.push(pts);
                    } else {
                        loose.extend(pts);
                    }
                }
            }
            let voxels = loose
                .iter()
                .map(|p| top.voxel_at(*p).unwrap_or(u32::MAX))
                .collect();
            split.push(TileBlocks {
                smooth,
                loose,
                voxels,
            });
        }
    }
    // Every point of each tile sorted (as a tile's job could).
    let mut tiled: Vec<Vec<Vec3>> = Vec::new();
    for tile in &split {
        let mut pts = tile.smooth.concat();
        pts.extend_from_slice(&tile.loose);
        let pts = sort_across(pts);
        tiled.extend(pts.chunks(N).map(|c| c.to_vec()));
    }
    let tile_sorting = sorting.replace(std::time::Duration::ZERO);
    // The broken blocks' points sorted within their tile.
    let mut mixed: Vec<Vec<Vec3>> = Vec::new();
    for tile in &split {
        mixed.extend(tile.smooth.iter().cloned());
        let loose = sort_across(tile.loose.clone());
        mixed.extend(loose.chunks(N).map(|c| c.to_vec()));
    }
    let broken_sorting = sorting.get();
    // The same points bucketed by their voxel, in the order the voxels
    // first appear (the kernel knows each hit's voxel: only the bucketing
    // is timed).
    let mut buckets: Vec<Vec<Vec3>> = Vec::new();
    let mut bucketing = std::time::Duration::ZERO;
    for tile in &split {
        buckets.extend(tile.smooth.iter().cloned());
        let t0 = Instant::now();
        let mut seen: Vec<u32> = Vec::new();
        let mut by_voxel: Vec<Vec<Vec3>> = Vec::new();
        for (p, id) in tile.loose.iter().zip(&tile.voxels) {
            let k = match seen.iter().position(|s| s == id) {
                Some(k) => k,
                None => {
                    seen.push(*id);
                    by_voxel.push(Vec::new());
                    seen.len() - 1
                }
            };
            by_voxel[k].push(*p);
        }
        let flat: Vec<Vec3> = by_voxel.into_iter().flatten().collect();
        bucketing += t0.elapsed();
        buckets.extend(flat.chunks(N).map(|c| c.to_vec()));
    }
    // Every ordering traces the same rays: each must find the same ones
    // occluded, or the comparison is void.
    let mut first_occluded: Option<(&str, usize)> = None;
    for _ in 0..2 {
        let chunks = |v: &Vec<Vec3>| v.chunks(N).map(|c| c.to_vec()).collect::<Vec<_>>();
        let (compact, sorted_p) = (chunks(&blocks), chunks(&sorted));
        for (name, pts, ordering) in [
            ("per block", &per_block, None),
            ("compacted", &compact, None),
            ("sorted", &sorted_p, None),
            ("tile-sorted", &tiled, Some(tile_sorting)),
            ("broken blocks sorted", &mixed, Some(broken_sorting)),
            ("broken blocks by voxel", &buckets, Some(bucketing)),
        ] {
            let mut best = f64::MAX;
            let mut occ = 0;
            for _ in 0..5 {
                let (s, o) = trace_with(code, &view, pts);
                best = best.min(s);
                occ = o;
            }
            let n = blocks.len();
            // What a tile's job would add: forming the order, timed once.
            let ordering = ordering.map_or(String::new(), |d: std::time::Duration| {
                format!(
                    ", ordering {:.2} ms ({:.2} Mrays/s with it)",
                    d.as_secs_f64() * 1e3,
                    n as f64 / (best + d.as_secs_f64()) / 1e6
                )
            });
            println!(
                "{name}: {} packets, {n} rays, {:.2} Mrays/s, occluded {occ}{ordering}",
                pts.len(),
                n as f64 / best / 1e6
            );
            match first_occluded {
                None => first_occluded = Some((name, occ)),
                Some((first, o)) if o != occ => {
                    eprintln!(
                        "shadow_order: {name} found {occ} rays occluded, {first} {o}: the orderings disagree"
                    );
                    std::process::exit(1);
                }
                Some(_) => {}
            }
        }
    }
}
