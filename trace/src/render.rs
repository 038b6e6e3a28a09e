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

    /// Whether this CPU can run the kernel compiled for `self`.
    pub fn supported(self) -> bool {
        match (self, Isa::detect()) {
            (Isa::Portable, _) => true,
            (Isa::Avx2, best) => best != Isa::Portable,
            (Isa::Avx512, best) => best == Isa::Avx512,
        }
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
#[derive(Clone, Debug)]
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
    /// Mirror bounces (0: none).
    pub reflections: u32,
    /// Which surfaces reflect, and how much of the light they reflect.
    pub reflective: ReflectRule,
    pub reflectance: f32,
    /// Color by voxel instead of by vertex color.
    pub voxel_colors: bool,
}

impl RenderSettings {
    /// Primary rays only, on every core with the best kernel this CPU
    /// runs, for a scene of diagonal `scene_diagonal`; the other fields are
    /// meant to be set with struct update syntax.
    pub fn primary(scene_diagonal: f32) -> RenderSettings {
        RenderSettings {
            shade: false,
            shadows: false,
            light: DEFAULT_LIGHT,
            threads: std::thread::available_parallelism().map_or(1, |n| n.get()),
            isa: Isa::detect(),
            scene_diagonal,
            reflections: 0,
            reflective: ReflectRule::All,
            reflectance: 0.6,
            voxel_colors: false,
        }
    }
}

/// Direction towards the light unless one is given (the Embree
/// yardstick's default).
pub const DEFAULT_LIGHT: Vec3 = Vec3::new(0.3, 1.0, 0.2);

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
    pub reflection_rays: u64,
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
    let mut settings = settings.clone();
    // A kernel the CPU cannot run would be undefined behaviour.
    if !settings.isa.supported() {
        settings.isa = Isa::Portable;
    }
    let settings = &settings;
    let shared = Shared {
        top,
        source,
        basis: camera.basis(),
        settings: settings.clone(),
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
    s.reflection_rays += out.stats.reflection_rays;
    s.occluded += out.stats.occluded;
    s.hits += out.stats.hits;
    s.shadow_seconds += out.stats.shadow_seconds;
    s.voxels_visited += out.stats.voxels_visited;
}

fn render_tile(shared: &Shared, x0: u32, y0: u32) -> Result<TileOut, u32> {
    match shared.settings.isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `render` keeps an ISA only where `Isa::supported` says
        // this CPU has its features.
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
            let mut own = [false; N];
            for (i, &(x, y)) in px.iter().enumerate() {
                own[i] = is_own_lane::<BW>(i, x, y, bx, by);
                if !own[i] {
                    continue;
                }
                let k = (y * w + x) as usize;
                out.stats.primary_rays += 1;
                if packet.hit(i) {
                    out.depth[k] = packet.t[i];
                    out.primid[k] = packet.id[i];
                    out.stats.hits += 1;
                }
            }
            if !settings.shade {
                continue;
            }
            let colors = shade_bounces(shared, &mut trav, packet, &dirs, &own, &mut out.stats)?;
            for (i, &(x, y)) in px.iter().enumerate() {
                if own[i] {
                    let c = |v: f32| (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8;
                    out.rgba[(y * w + x) as usize] =
                        [c(colors[i].x), c(colors[i].y), c(colors[i].z), 255];
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

/// Which surfaces are mirrors (models carry no materials).
#[derive(Clone, Debug, PartialEq)]
pub enum ReflectRule {
    /// Every surface.
    All,
    /// Triangles whose ORIGINAL id is in the range.
    Ids(std::ops::Range<u32>),
    /// Surfaces of this vertex color (within a few units per channel).
    Color([u8; 3]),
}

impl ReflectRule {
    fn matches(&self, id: u32, color: Vec3) -> bool {
        match self {
            ReflectRule::All => true,
            ReflectRule::Ids(r) => r.contains(&id),
            ReflectRule::Color(c) => {
                let target = Vec3::new(c[0] as f32, c[1] as f32, c[2] as f32) / 255.0;
                (color - target).abs().max_element() <= 6.0 / 255.0
            }
        }
    }
}

/// A color per voxel (the paper's Figure 5).
fn voxel_color(id: u32) -> Vec3 {
    let h = (id.wrapping_mul(0x9E37_79B9) >> 8) as f32 / (1 << 24) as f32;
    let k = |n: f32| {
        let x = (n + h * 6.0) % 6.0;
        (1.0 - (x.min(4.0 - x).clamp(0.0, 1.0))) * 0.55 + 0.35
    };
    Vec3::new(k(5.0), k(3.0), k(1.0))
}

const BACKGROUND: Vec3 = Vec3::new(0.094, 0.11, 0.14);

/// Colors of a packet's pixels: Lambert shading with the interpolated
/// vertex normal and color, an ambient term, hard shadows, and mirror
/// bounces up to `reflections` deep, each traced as a packet. Inlined into
/// the ISA-specific tile functions so its packets get their SIMD code too.
#[inline(always)]
fn shade_bounces<const N: usize>(
    shared: &Shared,
    trav: &mut Traversal<N>,
    primary: Packet<N>,
    dirs: &[Vec3; N],
    own: &[bool; N],
    stats: &mut FrameStats,
) -> Result<[Vec3; N], u32> {
    let s = &shared.settings;
    let eps = SHADOW_EPS * s.scene_diagonal;
    let mut color = [Vec3::ZERO; N];
    let mut weight = [1.0f32; N];
    let mut cur = primary;
    let mut cur_dirs = *dirs;
    let mut origins = [shared.basis.eye; N];
    let mut last: Option<std::sync::Arc<crate::scene::PreparedVoxel>> = None;
    for bounce in 0..=s.reflections {
        let mut points = [Vec3::ZERO; N];
        let mut normals = [Vec3::Y; N];
        let mut albedo = [Vec3::ZERO; N];
        let mut mirror = [0.0f32; N];
        for i in 0..N {
            if weight[i] == 0.0 {
                continue;
            }
            if !cur.hit(i) {
                color[i] += BACKGROUND * weight[i];
                weight[i] = 0.0;
                continue;
            }
            // Neighbouring lanes mostly hit the same voxel: fetch it once.
            if last.as_ref().is_none_or(|v| v.id != cur.voxel[i]) {
                last = Some(shared.source.voxel(cur.voxel[i]).ok_or(cur.voxel[i])?);
            }
            let vox = last.as_ref().expect("just set");
            let (mut n, c) = vox.surface(cur.tri[i], cur.u[i], cur.v[i]);
            let c = Vec3::from_array(c);
            if n.dot(cur_dirs[i]) > 0.0 {
                n = -n;
            }
            points[i] = origins[i] + cur_dirs[i] * cur.t[i];
            normals[i] = n;
            albedo[i] = if s.voxel_colors {
                voxel_color(cur.voxel[i])
            } else {
                c
            };
            if bounce < s.reflections && s.reflective.matches(cur.id[i], c) {
                mirror[i] = s.reflectance;
            }
        }
        let mut lit = [true; N];
        if s.shadows {
            let started = Instant::now();
            let mut shadow = Packet::<N>::new(&points, &[shared.light; N], eps, f32::INFINITY);
            shadow.any_hit = true;
            for i in 0..N {
                // Lanes without a surface to light take no part.
                if weight[i] == 0.0 {
                    shadow.t[i] = f32::NEG_INFINITY;
                }
            }
            trav.reset();
            if let Step::Missing(id) = trav.run(&mut shadow, shared.top, shared.source) {
                return Err(id);
            }
            for i in 0..N {
                if weight[i] > 0.0 {
                    lit[i] = !shadow.occluded(i);
                    if own[i] {
                        stats.shadow_rays += 1;
                        stats.occluded += !lit[i] as u64;
                    }
                }
            }
            stats.shadow_seconds += started.elapsed().as_secs_f64();
        }
        let mut any_mirror = false;
        for i in 0..N {
            if weight[i] == 0.0 {
                continue;
            }
            let diffuse = if lit[i] {
                normals[i].dot(shared.light).max(0.0)
            } else {
                0.0
            };
            let local = albedo[i] * (AMBIENT + (1.0 - AMBIENT) * diffuse);
            color[i] += local * (weight[i] * (1.0 - mirror[i]));
            weight[i] *= mirror[i];
            any_mirror |= weight[i] > 0.0;
        }
        if !any_mirror {
            break;
        }
        let mut reflected = [Vec3::Y; N];
        for i in 0..N {
            let d = cur_dirs[i];
            reflected[i] = (d - normals[i] * (2.0 * d.dot(normals[i]))).normalize_or(normals[i]);
        }
        let mut next = Packet::<N>::new(&points, &reflected, eps, f32::INFINITY);
        for i in 0..N {
            if weight[i] == 0.0 {
                next.t[i] = f32::NEG_INFINITY;
            } else if own[i] {
                stats.reflection_rays += 1;
            }
        }
        trav.reset();
        if let Step::Missing(id) = trav.run(&mut next, shared.top, shared.source) {
            return Err(id);
        }
        cur = next;
        cur_dirs = reflected;
        origins = points;
    }
    Ok(color)
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
