//! Rendering a frame in one process: tiles handed to threads, packets
//! from pixel blocks, primary rays, shadow rays, shading; the kernel is
//! compiled for AVX-512, AVX2 and a portable baseline and picked at run
//! time.

// Lane loops index several arrays in lockstep on purpose: that is the
// shape LLVM vectorizes.
#![allow(clippy::needless_range_loop)]

use crate::accel::{TopLevel, VoxelSource};
use crate::camera::{Camera, CameraBasis};
use crate::clock::Calibration;
use crate::image::Accumulator;
pub use crate::job::depth_grey;
use crate::job::{Ctx, PacketJob, Region};
use crate::packet::Step;
use crate::tile::Rect;
use glam::Vec3;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Mutex;
use std::time::Instant;

/// Tile edge in pixels (the unit of work a thread takes).
pub const TILE: u32 = 32;
/// Ambient share of the light.
pub(crate) const AMBIENT: f32 = 0.25;
/// Shadow rays start this fraction of the scene diagonal away from the hit
/// (the same rule as the Embree yardstick).
pub(crate) const SHADOW_EPS: f32 = 1e-4;

/// The instruction set the kernel runs with.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Isa {
    /// 16-lane packets (4×4 pixels), 32 (8×4) where rays stay together.
    Avx512,
    /// The same packets, each lane array in two or four registers: a
    /// packet's node and triangle loads, its stack and its top-level walk
    /// are shared by twice the rays of one register's width, which pays
    /// more than it costs on every view of `scripts/bench-kernel`.
    Avx2,
    /// 8-lane packets in portable code.
    Portable,
}

impl Isa {
    pub fn detect() -> Isa {
        #[cfg(target_arch = "x86_64")]
        {
            // The scalar extensions the vector entry points are compiled
            // with (`tile_avx512`, `tile_avx2`).
            let scalar = std::arch::is_x86_feature_detected!("bmi1")
                && std::arch::is_x86_feature_detected!("bmi2")
                && std::arch::is_x86_feature_detected!("lzcnt")
                && std::arch::is_x86_feature_detected!("popcnt");
            let avx2 = scalar
                && std::arch::is_x86_feature_detected!("avx2")
                && std::arch::is_x86_feature_detected!("fma");
            if avx2
                && std::arch::is_x86_feature_detected!("avx512f")
                && std::arch::is_x86_feature_detected!("avx512vl")
                && std::arch::is_x86_feature_detected!("avx512bw")
            {
                return Isa::Avx512;
            }
            if avx2 {
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

    /// Rays in a packet that is not wide.
    pub fn lanes(self) -> usize {
        match self {
            Isa::Avx512 | Isa::Avx2 => 16,
            Isa::Portable => 8,
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
    /// Color by voxel instead of by vertex color (the voxel whose cell
    /// holds the hit point).
    pub voxel_colors: bool,
    /// Rays per packet, where the ISA offers a choice.
    pub packets: Packets,
    /// Shadow packets first try the triangle that blocked a lane of the
    /// packet before ([`crate::packet::Packet::occlude_with`]); the
    /// answers are the same either way.
    pub occluder_cache: bool,
}

/// Rays per packet on AVX-512 and AVX2: 16 (4×4 pixels) or 32 (8×4), and
/// how 16 are traced. Wide packets pay off where the rays of a block stay
/// together (inside the plants; with AVX2 only where they stay together
/// the most, [`PacketChooser`]), narrow ones where they part (a whole
/// plant seen from afar), and sparse ones where they part most: a node
/// that at most four of the 16 lanes enter tests its four children for
/// them at once (`crate::quad`, AVX-512 only: AVX2 traces them as
/// narrow). The portable kernel always uses 8. Measured by
/// `scripts/bench-kernel`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Packets {
    /// Chosen per tile from the tiles the same thread traced before
    /// ([`PacketChooser`]); [`crate::tile::render_tile`], which traces one
    /// tile, takes it as `Narrow`.
    Auto,
    /// Always 16.
    Narrow,
    /// Always 32.
    Wide,
    /// Always 16, each stack entry with the lanes that entered its box,
    /// and nodes that at most four lanes entered tested four lanes at a
    /// time. Keeping the lanes costs where many enter each box (inside the
    /// plants) and pays where few do (a plant seen from outside).
    Sparse,
}

/// Picks the packets of a thread's next tile from the tiles it traced
/// before: how many lanes of a primary packet enter each BVH child box
/// that some lane enters (measured on a sample of the packets): where many
/// do 32 lanes are faster, where few do sparse 16 lanes are. The
/// thresholds below are set from `scripts/bench-kernel`'s views.
#[derive(Clone, Copy, Debug)]
pub struct PacketChooser {
    mode: Packets,
    next: Packets,
    scattered: bool,
}

impl PacketChooser {
    /// Narrow to start with under `Auto`.
    pub fn new(mode: Packets) -> PacketChooser {
        PacketChooser {
            mode,
            next: match mode {
                Packets::Auto => Packets::Narrow,
                fixed => fixed,
            },
            scattered: true,
        }
    }

    /// The packets of the next tile: `Wide`, `Narrow` or `Sparse`.
    pub fn next(&self) -> Packets {
        self.next
    }

    /// Whether the next tile's rays are taken to part ways: its shadow
    /// packets hand sparse subtrees over to groups of lanes, and its
    /// surfaces are prefetched. Until a tile says its rays stay together
    /// (below `SCATTERED_BELOW` lanes a child box), and always under a
    /// fixed choice of packets.
    pub fn scattered(&self) -> bool {
        self.scattered
    }

    /// Learns from a tile traced with [`Self::next`]'s packets by the
    /// kernel of `isa`, from its [`FrameStats::child_hits`] and
    /// [`FrameStats::child_lanes`].
    pub fn learn(&mut self, isa: Isa, child_hits: u64, child_lanes: u64) {
        if self.mode != Packets::Auto || child_hits < MIN_CHILD_HITS {
            return;
        }
        let lanes = child_lanes as f64 / child_hits as f64;
        self.scattered = lanes < SCATTERED_BELOW;
        let WideFrom { go, stay } = WideFrom::of(isa);
        // A wide tile's figure counts lanes of 32: below `stay` it goes
        // back to 16 first.
        self.next = match self.next {
            Packets::Wide if lanes >= stay => Packets::Wide,
            Packets::Wide => Packets::Narrow,
            Packets::Sparse if lanes < STAY_SPARSE => Packets::Sparse,
            _ if lanes >= go => Packets::Wide,
            _ if lanes < GO_SPARSE => Packets::Sparse,
            _ => Packets::Narrow,
        };
    }
}

/// Lanes of 16 entering a child box together below which the next tile's
/// rays are taken to part ways: its shadow packets hand sparse subtrees
/// over to groups of lanes
/// ([`crate::packet::Packet::hand_off_sparse_subtrees`]) and its surface
/// stage prefetches every hit first ([`Ctx::scattered`]). Above, where a
/// tile's rays stay together, the packets' search is the one without
/// hand-overs, which is faster there (`scripts/bench-kernel`).
const SCATTERED_BELOW: f64 = 4.0;
/// When 32-lane packets pay off, by the lanes entering a child box
/// together.
struct WideFrom {
    /// Lanes of 16 from which 32 pay off.
    go: f64,
    /// Lanes of 32 below which 16 are better again.
    stay: f64,
}

impl WideFrom {
    /// With AVX2 a 32-lane packet pays off only where its rays stay
    /// together more than with AVX-512: there 16-lane packets are the
    /// faster ones for primary rays, and only the shadow rays of the views
    /// whose rays stay together the most still gain from 32 lanes
    /// (`scripts/bench-kernel`, `docs/benchmarks.md`).
    fn of(isa: Isa) -> WideFrom {
        match isa {
            Isa::Avx2 => WideFrom {
                go: 13.0,
                stay: 20.0,
            },
            _ => WideFrom {
                go: 8.0,
                stay: 11.0,
            },
        }
    }
}
/// Lanes of 16 below which sparse packets pay off, and above which narrow
/// ones are better again.
const GO_SPARSE: f64 = 3.0;
const STAY_SPARSE: f64 = 3.5;
/// A tile with fewer sampled child boxes (mostly sky) says nothing.
const MIN_CHILD_HITS: u64 = 32;

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
            packets: Packets::Auto,
            occluder_cache: true,
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
    /// Shaded color (empty unless shading was asked for; see
    /// [`Frame::fill_grey`] for the unshaded colors).
    pub rgba: Vec<[u8; 4]>,
    pub stats: FrameStats,
}

impl Frame {
    /// Where the frame was not shaded (`rgba` empty), fills `rgba` with
    /// each pixel's [`depth_grey`]: exactly what
    /// [`crate::tile::render_tile`] writes without shading.
    pub fn fill_grey(&mut self, scene_diagonal: f32) {
        if self.rgba.is_empty() {
            self.rgba = self
                .depth
                .iter()
                .map(|&t| depth_grey(t, scene_diagonal))
                .collect();
        }
    }
}

#[derive(Clone, Copy, Debug, Default)]
pub struct FrameStats {
    pub primary_rays: u64,
    pub shadow_rays: u64,
    pub occluded: u64,
    /// Shadow packets traced, and those of them that the last occluder
    /// blocked entirely, so that they skipped the traversal.
    pub shadow_packets: u64,
    pub occluder_skips: u64,
    pub reflection_rays: u64,
    pub hits: u64,
    pub seconds: f64,
    /// Thread time spent in shadow packets, summed over threads (set by
    /// [`render`] from `shadow_ticks`).
    pub shadow_seconds: f64,
    /// The same in [`crate::clock::ticks`], as the packets count it.
    pub(crate) shadow_ticks: u64,
    pub voxels_visited: u64,
    /// In the sampled primary packets, the BVH child boxes some lane
    /// entered and the lanes that entered them.
    pub child_hits: u64,
    pub child_lanes: u64,
    /// Tiles traced with 32-lane packets, and with sparse 16-lane ones.
    pub wide_tiles: u64,
    pub sparse_tiles: u64,
}

impl FrameStats {
    /// Adds another frame's counts and times to these.
    pub fn add(&mut self, o: &FrameStats) {
        self.primary_rays += o.primary_rays;
        self.shadow_rays += o.shadow_rays;
        self.occluded += o.occluded;
        self.shadow_packets += o.shadow_packets;
        self.occluder_skips += o.occluder_skips;
        self.reflection_rays += o.reflection_rays;
        self.hits += o.hits;
        self.seconds += o.seconds;
        self.shadow_seconds += o.shadow_seconds;
        self.shadow_ticks += o.shadow_ticks;
        self.voxels_visited += o.voxels_visited;
        self.child_hits += o.child_hits;
        self.child_lanes += o.child_lanes;
        self.wide_tiles += o.wide_tiles;
        self.sparse_tiles += o.sparse_tiles;
    }
}

struct Shared<'a> {
    top: &'a TopLevel,
    source: &'a dyn VoxelSource,
    basis: CameraBasis,
    settings: RenderSettings,
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
/// `Err`): sample 0, every ray through its pixel's centre.
pub fn render(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    settings: &RenderSettings,
) -> Result<Frame, u32> {
    render_sample(top, source, camera, 0, settings)
}

/// [`render`] of sample `sample`: every ray moved by
/// [`crate::camera::sample_offset`]`(sample)` within its pixel.
pub fn render_sample(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    sample: u32,
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
        basis: camera.sample_basis(sample),
        settings: settings.clone(),
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
    let calibration = Calibration::start();
    std::thread::scope(|scope| {
        for _ in 0..settings.threads.max(1) {
            scope.spawn(|| {
                let mut chooser = PacketChooser::new(settings.packets);
                loop {
                    let k = next.fetch_add(1, Ordering::Relaxed);
                    if k >= tiles {
                        break;
                    }
                    let (tx, ty) = (k as u32 % tiles_x, k as u32 / tiles_x);
                    match render_tile(
                        &shared,
                        tx * TILE,
                        ty * TILE,
                        chooser.next(),
                        chooser.scattered(),
                    ) {
                        Ok(out) => {
                            chooser.learn(
                                settings.isa,
                                out.stats.child_hits,
                                out.stats.child_lanes,
                            );
                            merge(&frame, out)
                        }
                        Err(id) => {
                            *missing.lock().unwrap_or_else(|p| p.into_inner()) = Some(id);
                            next.store(tiles, Ordering::Relaxed);
                        }
                    }
                }
            });
        }
    });
    let mut frame = frame.into_inner().unwrap_or_else(|p| p.into_inner());
    frame.stats.seconds = start.elapsed().as_secs_f64();
    frame.stats.shadow_seconds = frame.stats.shadow_ticks as f64 * calibration.seconds_per_tick();
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
    f.stats.add(&out.stats);
}

fn render_tile(
    shared: &Shared,
    x0: u32,
    y0: u32,
    packets: Packets,
    scattered: bool,
) -> Result<TileOut, u32> {
    match shared.settings.isa {
        #[cfg(target_arch = "x86_64")]
        // SAFETY: `render` keeps an ISA only where `Isa::supported` says
        // this CPU has its features.
        Isa::Avx512 if packets == Packets::Wide => {
            unsafe { tile_avx512::<32, 8>(shared, x0, y0, false, scattered) }.map(|mut out| {
                out.stats.wide_tiles = 1;
                out
            })
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx512 if packets == Packets::Sparse => {
            unsafe { tile_avx512::<16, 4>(shared, x0, y0, true, scattered) }.map(|mut out| {
                out.stats.sparse_tiles = 1;
                out
            })
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx512 => unsafe { tile_avx512::<16, 4>(shared, x0, y0, false, scattered) },
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2 if packets == Packets::Wide => {
            unsafe { tile_avx2::<32, 8>(shared, x0, y0, scattered) }.map(|mut out| {
                out.stats.wide_tiles = 1;
                out
            })
        }
        #[cfg(target_arch = "x86_64")]
        // SAFETY: as above.
        Isa::Avx2 => unsafe { tile_avx2::<16, 4>(shared, x0, y0, scattered) },
        _ => tile::<8, 4>(shared, x0, y0, false, scattered),
    }
}

/// AVX-512 at either packet width: 16 lanes in 4-pixel-wide blocks, or 32
/// in 8-pixel-wide ones.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn tile_avx512<const N: usize, const BW: u32>(
    shared: &Shared,
    x0: u32,
    y0: u32,
    sparse: bool,
    scattered: bool,
) -> Result<TileOut, u32> {
    tile::<N, BW>(shared, x0, y0, sparse, scattered)
}

/// AVX2 at either packet width: 16 lanes (two registers per lane array)
/// in 4-pixel-wide blocks, or 32 in 8-pixel-wide ones.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
unsafe fn tile_avx2<const N: usize, const BW: u32>(
    shared: &Shared,
    x0: u32,
    y0: u32,
    scattered: bool,
) -> Result<TileOut, u32> {
    tile::<N, BW>(shared, x0, y0, false, scattered)
}

/// One tile in packets of N rays from BW-pixel-wide blocks, each run
/// through the same resumable [`PacketJob`] as [`crate::tile::render_tile`]'s
/// (here every voxel is resident, so a job never stops before it is done);
/// `sparse` packets as [`Packets::Sparse`] says; `scattered` is the packet
/// chooser's answer whether the tile's rays part ways
/// ([`PacketChooser::scattered`]): where they do, shadow packets hand
/// sparse subtrees over to groups (AVX-512, AVX2) and the surface stage starts
/// every hit's reads first ([`Ctx::scattered`]).
#[inline(always)]
fn tile<const N: usize, const BW: u32>(
    shared: &Shared,
    x0: u32,
    y0: u32,
    sparse: bool,
    scattered: bool,
) -> Result<TileOut, u32> {
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
    let mut ctx = Ctx::new(shared.top, shared.basis, settings, false);
    ctx.quad &= sparse;
    ctx.groups &= scattered;
    ctx.scattered = scattered;
    let rect = Rect {
        x0,
        y0,
        width: w,
        height: h,
    };
    let mut region = Region {
        width: w,
        depth: &mut out.depth,
        primid: &mut out.primid,
        rgba: &mut out.rgba,
    };
    let mut job = PacketJob::<N, BW>::new(&ctx, rect, 0, 0);
    let mut first = true;
    for by in (0..h).step_by(bh as usize) {
        for bx in (0..w).step_by(BW as usize) {
            if !first {
                job.start(&ctx, rect, bx, by);
            }
            first = false;
            if let Step::Missing(id) = job.step(&ctx, shared.source, &mut region, &mut out.stats) {
                return Err(id);
            }
        }
    }
    Ok(out)
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
    pub(crate) fn matches(&self, id: u32, color: Vec3) -> bool {
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
pub(crate) fn voxel_color(id: u32) -> Vec3 {
    let h = (id.wrapping_mul(0x9E37_79B9) >> 8) as f32 / (1 << 24) as f32;
    let k = |n: f32| {
        let x = (n + h * 6.0) % 6.0;
        (1.0 - (x.min(4.0 - x).clamp(0.0, 1.0))) * 0.55 + 0.35
    };
    Vec3::new(k(5.0), k(3.0), k(1.0))
}

pub(crate) const BACKGROUND: Vec3 = Vec3::new(0.094, 0.11, 0.14);

/// Renders samples `0..samples` of `camera`'s view ([`render_sample`])
/// and returns sample 0's frame (its depth and ids) with the samples'
/// colours averaged by an [`Accumulator`] and their statistics summed
/// (seconds too): what `dray render --spp` writes and reports. One sample
/// (or 0) is [`render`]'s frame; more than [`Accumulator::MAX_SAMPLES`]
/// count as that many.
pub fn render_samples(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    samples: u32,
    settings: &RenderSettings,
) -> Result<Frame, u32> {
    let mut frame = render_sample(top, source, camera, 0, settings)?;
    let samples = samples.min(Accumulator::MAX_SAMPLES);
    if samples <= 1 {
        return Ok(frame);
    }
    // Unshaded frames have no colours to average.
    let mut acc = (!frame.rgba.is_empty()).then(|| Accumulator::new(frame.width, frame.height));
    let add = |acc: &mut Option<Accumulator>, rgba: &[[u8; 4]]| {
        if let Some(a) = acc {
            a.add(rgba)
                .expect("every sample has the camera's size, and there are at most MAX_SAMPLES");
        }
    };
    add(&mut acc, &frame.rgba);
    for k in 1..samples {
        let f = render_sample(top, source, camera, k, settings)?;
        add(&mut acc, &f.rgba);
        frame.stats.add(&f.stats);
    }
    if let Some(a) = acc {
        frame.rgba = a.image();
    }
    Ok(frame)
}

/// The timed passes of [`render_repeated`].
#[derive(Clone, Debug)]
pub struct Passes {
    /// The last pass's frame ([`render_samples`]: sample 0's depth and ids,
    /// the samples' mean colours, their summed statistics).
    pub frame: Frame,
    /// Samples per pass.
    pub samples: u32,
    /// Each pass's wall-clock seconds.
    pub seconds: Vec<f64>,
    /// Each pass's seconds in shadow packets, summed over the threads
    /// ([`FrameStats::shadow_seconds`]).
    pub shadow_seconds: Vec<f64>,
}

/// Renders once untimed (warm-up), then `repeat` timed passes, each of
/// samples `0..samples` ([`render_samples`]). Every pass traces the same
/// rays, so the best pass of each figure is as fair a measure as the
/// yardstick's best of its passes.
pub fn render_repeated(
    top: &TopLevel,
    source: &dyn VoxelSource,
    camera: &Camera,
    settings: &RenderSettings,
    repeat: usize,
    samples: u32,
) -> Result<Passes, u32> {
    let mut frame = render_samples(top, source, camera, samples, settings)?;
    let mut seconds = Vec::with_capacity(repeat);
    let mut shadow_seconds = Vec::with_capacity(repeat);
    for _ in 0..repeat.max(1) {
        frame = render_samples(top, source, camera, samples, settings)?;
        seconds.push(frame.stats.seconds);
        shadow_seconds.push(frame.stats.shadow_seconds);
    }
    Ok(Passes {
        frame,
        samples: samples.clamp(1, Accumulator::MAX_SAMPLES),
        seconds,
        shadow_seconds,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Teaches `c` a tile of `lanes` sampled lanes a box with the kernel
    /// of `isa`.
    fn learn(c: &mut PacketChooser, isa: Isa, lanes: f64) {
        c.learn(isa, 1000, (lanes * 1000.0) as u64);
    }

    /// Feeds a fresh chooser `steps` (lanes a box, the packets then
    /// chosen) with `isa`, checking each choice and whether the tile is
    /// taken as scattered; the chooser.
    fn feed(isa: Isa, steps: &[(f64, Packets)]) -> PacketChooser {
        let mut c = PacketChooser::new(Packets::Auto);
        assert_eq!(c.next(), Packets::Narrow);
        for (k, &(lanes, want)) in steps.iter().enumerate() {
            learn(&mut c, isa, lanes);
            assert_eq!(c.next(), want, "{isa:?} step {k}: {lanes} lanes");
            assert_eq!(
                c.scattered(),
                lanes < SCATTERED_BELOW,
                "{isa:?} step {k}: {lanes} lanes"
            );
        }
        c
    }

    /// The chooser's moves between packets, with their hysteresis, from
    /// sampled lanes per entered child box (a wide tile's in lanes of 32).
    #[test]
    fn the_chooser_moves_between_sparse_narrow_and_wide() {
        let mut c = feed(
            Isa::Avx512,
            &[
                (2.5, Packets::Sparse),
                (3.2, Packets::Sparse),
                (3.6, Packets::Narrow),
                (3.2, Packets::Narrow),
                (2.9, Packets::Sparse),
                (9.0, Packets::Wide),
                (10.0, Packets::Narrow),
                (8.5, Packets::Wide),
                (11.5, Packets::Wide),
                (2.0, Packets::Narrow),
                (2.0, Packets::Sparse),
            ],
        );
        // Too few sampled boxes (a tile of sky) change nothing.
        c.learn(Isa::Avx512, MIN_CHILD_HITS - 1, 0);
        assert_eq!(c.next(), Packets::Sparse);
        // Fixed choices stay.
        for fixed in [Packets::Narrow, Packets::Wide, Packets::Sparse] {
            let mut c = PacketChooser::new(fixed);
            learn(&mut c, Isa::Avx512, 20.0);
            assert!(c.scattered());
            learn(&mut c, Isa::Avx512, 1.0);
            assert_eq!(c.next(), fixed);
        }
    }

    /// With AVX2, 32 lanes take rays that stay together more than with
    /// AVX-512: the same figures that take AVX-512 wide leave AVX2 narrow.
    #[test]
    fn avx2_goes_wide_only_where_rays_stay_together_more() {
        feed(
            Isa::Avx2,
            &[
                (9.0, Packets::Narrow),
                (12.0, Packets::Narrow),
                (13.5, Packets::Wide),
                (21.0, Packets::Wide),
                (15.0, Packets::Narrow),
                (2.5, Packets::Sparse),
                (14.0, Packets::Wide),
            ],
        );
        feed(Isa::Avx512, &[(9.0, Packets::Wide)]);
    }
}
