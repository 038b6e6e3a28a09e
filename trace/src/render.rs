//! Rendering a frame in one process: tiles handed to threads, packets
//! from pixel blocks, primary rays, shadow rays, shading; the kernel is
//! compiled for AVX-512, AVX2 and a portable baseline and picked at run
//! time.

// Lane loops index several arrays in lockstep on purpose: that is the
// shape LLVM vectorizes.
#![allow(clippy::needless_range_loop)]

use crate::camera::{Camera, CameraBasis};
use crate::packet::{Packet, Step, Traversal};
use crate::scene::{TopLevel, VoxelSource};
use glam::Vec3;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// Tile edge in pixels (the unit of work a thread takes).
pub const TILE: u32 = 32;
/// Ambient share of the light.
const AMBIENT: f32 = 0.25;
/// Shadow rays start this fraction of the scene diagonal away from the hit
/// (the same rule as the Embree yardstick).
const SHADOW_EPS: f32 = 1e-4;

/// The instruction set the kernel runs with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// 16-lane packets (4×4 pixels).
    Avx512,
    /// 8-lane packets (4×2 pixels).
    Avx2,
    /// 8-lane packets in portable code.
    Portable,
}

impl Isa {
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512bw")
                && std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                return Isa::Avx512;
            }
            if std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma")
            {
                return Isa::Avx2;
            }
        }
        Isa::Portable
    }

    pub fn lanes(self) -> usize {
        match self {
            Isa::Avx512 => 16,
            Isa::Avx2 | Isa::Portable => 8,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Isa::Avx512 => "avx512",
            Isa::Avx2 => "avx2",
            Isa::Portable => "portable",
        }
    }
}

/// What to compute besides the primary hits.
#[derive(Clone, Copy, Debug)]
pub struct RenderSettings {
    /// Shade the image (vertex normals and colors, one distant light).
    pub shade: bool,
    /// Trace a shadow ray from every primary hit towards the light.
    pub shadows: bool,
    /// Direction towards the light (normalized by the renderer).
    pub light: Vec3,
    pub threads: usize,
    pub isa: Isa,
    /// Diagonal of the scene, for the shadow ray offset.
    pub scene_diagonal: f32,
}

/// One rendered frame.
#[derive(Clone, Debug)]
pub struct Frame {
    pub width: u32,
    pub height: u32,
    /// Distance to the nearest hit per pixel, rows top to bottom, +inf on a
    /// miss.
    pub depth: Vec<f32>,
    /// ORIGINAL triangle id per pixel, `u32::MAX` on a miss.
    pub primid: Vec<u32>,
    /// Shaded color (empty unless shading was asked for).
    pub rgba: Vec<[u8; 4]>,
    pub stats: FrameStats,
}

#[derive(Clone, Copy, Debug, Default)]
pub struct FrameStats {
    pub primary_rays: u64,
    pub shadow_rays: u64,
    pub occluded: u64,
    pub hits: u64,
    pub seconds: f64,
    /// Thread time spent in shadow packets, summed over threads.
    pub shadow_seconds: f64,
    pub voxels_visited: u64,
}

struct Shared<'a> {
    top: &'a TopLevel,
    source: &'a dyn VoxelSource,
    basis: CameraBasis,
    settings: RenderSettings,
    light: Vec3,
    width: u32,
    height: u32,
}

/// Per-thread output of a tile, merged into the frame under a lock.
struct TileOut {
    x0: u32,
    y0: u32,
    w: u32,
    h: u32,
    depth: Vec<f32>,
    primid: Vec<u32>,
    rgba: Vec<[u8; 4]>,
    stats: FrameStats,
}

/// Renders `camera`'s view with every voxel from `source` (which must hold
/// them all: a missing voxel here is a bug of the caller, reported by
/// `Err`).
pub fn render(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Frame, u32> {
    let (w, h) = (camera.width, camera.height);
    let shared = Shared {
        top,
        source,
        basis: camera.basis(),
        settings: *settings,
        light: settings.light.normalize_or(Vec3::Y),
        width: w,
        height: h,
    };
    let tiles_x = w.div_ceil(TILE);
    let tiles = (tiles_x * h.div_ceil(TILE)) as usize;
    let next = AtomicUsize::new(0);
    let pixels = (w * h) as usize;
    let frame = Mutex::new(Frame {
        width: w,
        height: h,
        depth: vec![f32::INFINITY; pixels],
        primid: vec![u32::MAX; pixels],
        rgba: if settings.shade {
            vec![[0, 0, 0, 255]; pixels]
        } else {
            Vec::new()
        },
        stats: FrameStats::default(),
    });
    let missing = Mutex::new(None);
    let start = Instant::now();
    std::thread::scope(|scope| {
        for _ in 0..settings.threads.max(1) {
            scope.spawn(|| loop {
                let k = next.fetch_add(1, Ordering::Relaxed);
                if k >= tiles {
                    break;
                }
                let (tx, ty) = (k as u32 % tiles_x, k as u32 / tiles_x);
                match render_tile(&shared, tx * TILE, ty * TILE) {
                    Ok(out) => merge(&frame, out),
                    Err(id) => {
                        *missing.lock().unwrap_or_else(|p| p.into_inner()) = Some(id);
                        next.store(tiles, Ordering::Relaxed);
                    }
                }
            });
        }
    });
    let mut frame = frame.into_inner().unwrap_or_else(|p| p.into_inner());
    frame.stats.seconds = start.elapsed().as_secs_f64();
    match missing.into_inner().unwrap_or_else(|p| p.into_inner()) {
        Some(id) => Err(id),
        None => Ok(frame),
    }
}

fn merge(frame: &Mutex<Frame>, out: TileOut) {
    let mut f = frame.lock().unwrap_or_else(|p| p.into_inner());
    let width = f.width;
    for row in 0..out.h {
        let src = (row * out.w) as usize..((row + 1) * out.w) as usize;
        let dst = ((out.y0 + row) * width + out.x0) as usize;
        let n = out.w as usize;
        f.depth[dst..dst + n].copy_from_slice(&out.depth[src.clone()]);
        f.primid[dst..dst + n].copy_from_slice(&out.primid[src.clone()]);
        if !out.rgba.is_empty() {
            f.rgba[dst..dst + n].copy_from_slice(&out.rgba[src]);
        }
    }
    let s = &mut f.stats;
    s.primary_rays += out.stats.primary_rays;
    s.shadow_rays += out.stats.shadow_rays;
    s.occluded += out.stats.occluded;
    s.hits += out.stats.hits;
    s.shadow_seconds += out.stats.shadow_seconds;
    s.voxels_visited += out.stats.voxels_visited;
}

fn render_tile(shared: &Shared, x0: u32, y0: u32) -> Result<TileOut, u32> {
    match shared.settings.isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `Isa::detect` found these features on this CPU.
        Isa::Avx512 => unsafe { tile_avx512(shared, x0, y0) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2 => unsafe { tile_avx2(shared, x0, y0) },
        _ => tile::<8, 4>(shared, x0, y0),
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn tile_avx512(shared: &Shared, x0: u32, y0: u32) -> Result<TileOut, u32> {
    tile::<16, 4>(shared, x0, y0)
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn tile_avx2(shared: &Shared, x0: u32, y0: u32) -> Result<TileOut, u32> {
    tile::<8, 4>(shared, x0, y0)
}

/// One tile in packets of N rays from BW-pixel-wide blocks.
#[inline(always)]
fn tile<const N: usize, const BW: u32>(shared: &Shared, x0: u32, y0: u32) -> Result<TileOut, u32> {
    let bh = N as u32 / BW;
    let w = TILE.min(shared.width - x0);
    let h = TILE.min(shared.height - y0);
    let settings = &shared.settings;
    let mut out = TileOut {
        x0,
        y0,
        w,
        h,
        depth: vec![f32::INFINITY; (w * h) as usize],
        primid: vec![u32::MAX; (w * h) as usize],
        rgba: if settings.shade {
            vec![[0, 0, 0, 255]; (w * h) as usize]
        } else {
            Vec::new()
        },
        stats: FrameStats::default(),
    };
    let mut trav = Traversal::<N>::default();
    let eye = [shared.basis.eye; N];
    let shadow_eps = SHADOW_EPS * settings.scene_diagonal;
    for by in (0..h).step_by(bh as usize) {
        for bx in (0..w).step_by(BW as usize) {
            // Lanes past the tile's edge repeat its last pixel; their
            // results are dropped.
            let mut px = [(0u32, 0u32); N];
            let mut dirs = [Vec3::ZERO; N];
            for (i, p) in px.iter_mut().enumerate() {
                let x = (bx + i as u32 % BW).min(w - 1);
                let y = (by + i as u32 / BW).min(h - 1);
                *p = (x, y);
                dirs[i] = shared.basis.direction(x0 + x, y0 + y);
            }
            let mut packet = Packet::<N>::new(&eye, &dirs, 0.0, f32::INFINITY);
            trav.reset();
            if let Step::Missing(id) = trav.run(&mut packet, shared.top, shared.source) {
                return Err(id);
            }
            out.stats.voxels_visited += trav.voxels_visited as u64;
            let mut lit = [true; N];
            if settings.shadows {
                let started = Instant::now();
                let mut origins = [Vec3::ZERO; N];
                for i in 0..N {
                    origins[i] = shared.basis.eye + dirs[i] * packet.t[i];
                }
                let mut shadow =
                    Packet::<N>::new(&origins, &[shared.light; N], shadow_eps, f32::INFINITY);
                shadow.any_hit = true;
                for i in 0..N {
                    // Lanes without a primary hit take no part.
                    if !packet.hit(i) {
                        shadow.t[i] = f32::NEG_INFINITY;
                    }
                }
                trav.reset();
                if let Step::Missing(id) = trav.run(&mut shadow, shared.top, shared.source) {
                    return Err(id);
                }
                for (i, l) in lit.iter_mut().enumerate() {
                    *l = !(packet.hit(i) && shadow.occluded(i));
                }
                out.stats.shadow_seconds += started.elapsed().as_secs_f64();
                // Count each pixel's shadow ray once (edge lanes repeat).
                for (i, &(x, y)) in px.iter().enumerate() {
                    if is_own_lane::<BW>(i, x, y, bx, by) && packet.hit(i) {
                        out.stats.shadow_rays += 1;
                        out.stats.occluded += !lit[i] as u64;
                    }
                }
            }
            for (i, &(x, y)) in px.iter().enumerate() {
                if !is_own_lane::<BW>(i, x, y, bx, by) {
                    continue;
                }
                let k = (y * w + x) as usize;
                out.stats.primary_rays += 1;
                if packet.hit(i) {
                    out.depth[k] = packet.t[i];
                    out.primid[k] = packet.id[i];
                    out.stats.hits += 1;
                }
                if settings.shade {
                    out.rgba[k] = shade(shared, &packet, i, dirs[i], lit[i]);
                }
            }
        }
    }
    Ok(out)
}

/// Whether lane `i` is the pixel it traced (not a repeat past the edge).
#[inline(always)]
fn is_own_lane<const BW: u32>(i: usize, x: u32, y: u32, bx: u32, by: u32) -> bool {
    x == bx + i as u32 % BW && y == by + i as u32 / BW
}

/// Lambert shading with the interpolated vertex normal (turned towards the
/// viewer) and color, an ambient term, and the shadow.
fn shade<const N: usize>(
    shared: &Shared,
    p: &Packet<N>,
    i: usize,
    dir: Vec3,
    lit: bool,
) -> [u8; 4] {
    if !p.hit(i) {
        return [24, 28, 36, 255];
    }
    let Some(vox) = shared.source.voxel(p.voxel[i]) else {
        return [255, 0, 255, 255];
    };
    let (mut n, color) = vox.surface(p.tri[i], p.u[i], p.v[i]);
    if n.dot(dir) > 0.0 {
        n = -n;
    }
    let diffuse = if lit {
        n.dot(shared.light).max(0.0)
    } else {
        0.0
    };
    let k = AMBIENT + (1.0 - AMBIENT) * diffuse;
    let c = |x: f32| ((x * k).clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
    [c(color[0]), c(color[1]), c(color[2]), 255]
}

/// Renders once untimed (warm-up), then `repeat` timed passes; returns the
/// last frame and each timed pass's seconds.
pub fn render_repeated(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    settings: &RenderSettings,
    repeat: usize,
) -> Result<(Frame, Vec<f64>), u32> {
    let mut frame = render(top, source, camera, settings)?;
    let mut seconds = Vec::with_capacity(repeat);
    for _ in 0..repeat.max(1) {
        frame = render(top, source, camera, settings)?;
        seconds.push(frame.stats.seconds);
    }
    Ok((frame, seconds))
}
