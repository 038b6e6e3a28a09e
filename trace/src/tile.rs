//! One tile, fully shaded, with voxels that arrive over time: the packets
//! that meet a missing voxel wait (suspend mode) while the others go on,
//! or the whole tile waits for each miss in turn (block mode, the
//! demand-paging baseline the paper compares against). Each packet runs
//! the same resumable per-packet state machine (`job.rs`) as
//! [`crate::render::render`], so the pixels are the frame's, bit for bit.

use crate::accel::{PreparedVoxel, TopLevel, VoxelRef, VoxelSource};
use crate::camera::{Camera, CameraBasis};
use crate::job::{Ctx, PacketJob, Region};
use crate::packet::Step;
use crate::render::{FrameStats, Isa, Packets, RenderSettings};
use futures::future::BoxFuture;
use futures::stream::{FuturesUnordered, StreamExt};
use std::collections::HashMap;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What a render thread does when a packet needs a voxel that is not
/// resident.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum MissMode {
    /// Suspend the packet, request the voxel, go on with other packets.
    Suspend,
    /// Wait for the voxel before doing anything else.
    Block,
}

#[derive(Debug, thiserror::Error)]
#[error("voxel {voxel}: {message}")]
pub struct LoadError {
    pub voxel: u32,
    pub message: String,
}

/// A voxel source that can be asked to make a voxel resident.
pub trait VoxelLoader: VoxelSource {
    /// Resolves with voxel `id` once it is resident. The Arc returned is
    /// held by the packets that waited for it until they finish, so a
    /// cache cannot free it under them.
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>>;
}

/// A rectangle of the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

/// What a tile cost.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct TileStats {
    pub primary_rays: u64,
    pub shadow_rays: u64,
    pub reflection_rays: u64,
    /// Times a packet met a missing voxel.
    pub misses: u64,
    /// Load requests made (one per voxel at a time, whatever the number of
    /// packets waiting for it).
    pub requested: u64,
    /// Distinct voxels the tile's rays entered.
    pub voxels_touched: u32,
    /// Distinct voxels the tile met missing: on the same basis as
    /// `voxels_touched` (each of them is entered once it arrives).
    pub voxels_missed: u32,
    /// Time spent waiting for loads while no packet of the tile could run.
    pub stall: Duration,
    /// In the sampled primary packets, the BVH child boxes some lane
    /// entered and the lanes that entered them (for
    /// [`crate::render::PacketChooser`]).
    pub child_hits: u64,
    pub child_lanes: u64,
}

/// A rendered tile, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct TileImage {
    pub rect: Rect,
    /// Shaded colors, or without shading each pixel's
    /// [`crate::render::depth_grey`].
    pub rgba: Vec<[u8; 4]>,
    /// Distance to the nearest hit, +inf on a miss.
    pub depth: Vec<f32>,
    /// ORIGINAL triangle id, `u32::MAX` on a miss.
    pub primid: Vec<u32>,
    pub stats: TileStats,
}

impl TileImage {
    /// World positions of the primary hits at an `n` × `n` grid of pixels
    /// spread evenly over the tile (misses left out): where the tile's
    /// content lies, for the scheduler's reprojection affinity. `b` is the
    /// basis the tile's rays came from ([`Camera::sample_basis`] of its
    /// sample).
    pub fn sample_hits(&self, b: &CameraBasis, n: u32) -> Vec<glam::Vec3> {
        let Rect {
            x0,
            y0,
            width,
            height,
        } = self.rect;
        let mut hits = Vec::new();
        for j in 0..n.min(height) {
            for i in 0..n.min(width) {
                // The centres of an n × n split of the tile.
                let (x, y) = (
                    (2 * i + 1) * width / (2 * n),
                    (2 * j + 1) * height / (2 * n),
                );
                let t = self.depth[(y * width + x) as usize];
                if t.is_finite() {
                    hits.push(b.eye + b.direction(x0 + x, y0 + y) * t);
                }
            }
        }
        hits
    }
}

/// Renders `rect` of `camera`'s image with `settings` (its `threads` is
/// ignored: the tile runs on the caller's task), loading voxels through
/// `loader`. Every pixel is bit-identical to what
/// [`crate::render::render`] gives it, whatever the rect and whatever the
/// order and timing in which voxels arrive. A rect not inside the image
/// (or empty) is an error naming voxel `u32::MAX`.
pub async fn render_tile(
    top: &TopLevel,
    loader: &dyn VoxelLoader,
    camera: &Camera,
    rect: Rect,
    settings: &RenderSettings,
    mode: MissMode,
) -> Result<TileImage, LoadError> {
    render_tile_sample(top, loader, camera, 0, rect, settings, mode).await
}

/// [`render_tile`] of sample `sample` ([`crate::camera::sample_offset`]):
/// every pixel bit-identical to [`crate::render::render_sample`]'s.
pub async fn render_tile_sample(
    top: &TopLevel,
    loader: &dyn VoxelLoader,
    camera: &Camera,
    sample: u32,
    rect: Rect,
    settings: &RenderSettings,
    mode: MissMode,
) -> Result<TileImage, LoadError> {
    let inside = rect.width > 0
        && rect.height > 0
        && rect
            .x0
            .checked_add(rect.width)
            .is_some_and(|x| x <= camera.width)
        && rect
            .y0
            .checked_add(rect.height)
            .is_some_and(|y| y <= camera.height);
    if !inside {
        return Err(LoadError {
            voxel: u32::MAX,
            message: format!(
                "tile {rect:?} is not inside the {}x{} image",
                camera.width, camera.height
            ),
        });
    }
    // A kernel the CPU cannot run would be undefined behaviour.
    let isa = if settings.isa.supported() {
        settings.isa
    } else {
        Isa::Portable
    };
    let mut ctx = Ctx::new(top, camera.sample_basis(sample), settings, true);
    ctx.quad &= settings.packets == Packets::Sparse;
    // No packet chooser says here whether a tile's rays part: AVX-512
    // groups cost little where they do not (3-7 %), AVX2 groups up to 20 %
    // (`docs/benchmarks.md`), so only AVX-512 hands subtrees over.
    ctx.groups &= isa == Isa::Avx512;
    match isa {
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 if settings.packets == Packets::Wide => {
            drive::<32, 8>(&ctx, loader, rect, mode, step_avx512).await
        }
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => drive::<16, 4>(&ctx, loader, rect, mode, step_avx512).await,
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 if settings.packets == Packets::Wide => {
            drive::<32, 8>(&ctx, loader, rect, mode, step_avx2).await
        }
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => drive::<16, 4>(&ctx, loader, rect, mode, step_avx2).await,
        _ => drive::<8, 4>(&ctx, loader, rect, mode, step_portable).await,
    }
}

/// Runs a job until it is done or misses a voxel, first starting it on
/// the block at (x, y) of the rect when one is given. Both are compiled
/// for the kernel's instruction set, as `dray render`'s are: inlined into
/// the tile loop (baseline x86-64), a block's start would compute the
/// rays' directions and inverses as SSE2, four lanes at a time.
type Stepper<const N: usize, const BW: u32> = fn(
    &mut PacketJob<N, BW>,
    &Ctx,
    Option<(Rect, u32, u32)>,
    &dyn VoxelSource,
    &mut Region,
    &mut FrameStats,
) -> Step;

#[inline(always)]
fn start_and_step<const N: usize, const BW: u32>(
    j: &mut PacketJob<N, BW>,
    c: &Ctx,
    block: Option<(Rect, u32, u32)>,
    s: &dyn VoxelSource,
    r: &mut Region,
    st: &mut FrameStats,
) -> Step {
    if let Some((rect, x, y)) = block {
        j.start(c, rect, x, y);
    }
    j.step(c, s, r, st)
}

fn step_portable(
    j: &mut PacketJob<8, 4>,
    c: &Ctx,
    b: Option<(Rect, u32, u32)>,
    s: &dyn VoxelSource,
    r: &mut Region,
    st: &mut FrameStats,
) -> Step {
    start_and_step(j, c, b, s, r, st)
}

/// AVX2 at either packet width, as AVX-512.
#[cfg(target_arch = "x86_64")]
fn step_avx2<const N: usize, const BW: u32>(
    j: &mut PacketJob<N, BW>,
    c: &Ctx,
    b: Option<(Rect, u32, u32)>,
    s: &dyn VoxelSource,
    r: &mut Region,
    st: &mut FrameStats,
) -> Step {
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn inner<const N: usize, const BW: u32>(
        j: &mut PacketJob<N, BW>,
        c: &Ctx,
        b: Option<(Rect, u32, u32)>,
        s: &dyn VoxelSource,
        r: &mut Region,
        st: &mut FrameStats,
    ) -> Step {
        start_and_step(j, c, b, s, r, st)
    }
    // SAFETY: `render_tile` picks this only where `Isa::supported` says
    // the CPU has AVX2.
    unsafe { inner(j, c, b, s, r, st) }
}

/// AVX-512 at either packet width: 16 lanes in 4-pixel-wide blocks, or 32
/// in 8-pixel-wide ones.
#[cfg(target_arch = "x86_64")]
fn step_avx512<const N: usize, const BW: u32>(
    j: &mut PacketJob<N, BW>,
    c: &Ctx,
    b: Option<(Rect, u32, u32)>,
    s: &dyn VoxelSource,
    r: &mut Region,
    st: &mut FrameStats,
) -> Step {
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn inner<const N: usize, const BW: u32>(
        j: &mut PacketJob<N, BW>,
        c: &Ctx,
        b: Option<(Rect, u32, u32)>,
        s: &dyn VoxelSource,
        r: &mut Region,
        st: &mut FrameStats,
    ) -> Step {
        start_and_step(j, c, b, s, r, st)
    }
    // SAFETY: `render_tile` picks this only where `Isa::supported` says
    // the CPU has AVX-512.
    unsafe { inner(j, c, b, s, r, st) }
}

/// A packet and the voxels it waited for.
struct Job<const N: usize, const BW: u32> {
    job: PacketJob<N, BW>,
    /// What `load` returned for this packet: looked up before the loader,
    /// so a voxel the cache evicted meanwhile is still found, and dropped
    /// when the packet is done.
    held: Vec<Arc<PreparedVoxel>>,
}

/// The loader as one job sees it: its held voxels first; records every
/// voxel asked for.
struct JobSource<'a> {
    held: &'a [Arc<PreparedVoxel>],
    loader: &'a dyn VoxelLoader,
    /// A bit per voxel id: entered by one of the tile's packets. (Not a
    /// set under a mutex: this runs at every voxel a packet enters.)
    touched: &'a [AtomicU64],
}

impl VoxelSource for JobSource<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        if let Some(word) = self.touched.get(id as usize / 64) {
            let bit = 1u64 << (id % 64);
            // Read first: a voxel is entered many times, marked once.
            if word.load(Ordering::Relaxed) & bit == 0 {
                word.fetch_or(bit, Ordering::Relaxed);
            }
        }
        match self.held.iter().find(|v| v.id == id) {
            Some(v) => Some(VoxelRef::Borrowed(v)),
            None => self.loader.voxel(id),
        }
    }
}

async fn drive<const N: usize, const BW: u32>(
    ctx: &Ctx<'_>,
    loader: &dyn VoxelLoader,
    rect: Rect,
    mode: MissMode,
    step: Stepper<N, BW>,
) -> Result<TileImage, LoadError> {
    let bh = N as u32 / BW;
    let n = (rect.width * rect.height) as usize;
    let mut depth = vec![f32::INFINITY; n];
    let mut primid = vec![u32::MAX; n];
    let mut rgba = vec![[0, 0, 0, 255]; n];
    let mut region = Region {
        width: rect.width,
        depth: &mut depth,
        primid: &mut primid,
        rgba: &mut rgba,
    };
    let mut stats = TileStats::default();
    let mut missed = std::collections::HashSet::new();
    let mut fs = FrameStats::default();
    let mut flushed = crate::work::Work::default();
    crate::work::tile_started();
    let touched: Vec<AtomicU64> = (0..ctx.top.voxel_count.div_ceil(64))
        .map(|_| AtomicU64::new(0))
        .collect();
    // The blocks not started yet, in rows.
    let blocks_x = rect.width.div_ceil(BW);
    let blocks = blocks_x * rect.height.div_ceil(bh);
    let mut next_block = 0;
    // Resumable jobs, finished ones kept for reuse, packets waiting for
    // each voxel, and the requests in flight.
    let mut ready: Vec<Box<Job<N, BW>>> = Vec::new();
    let mut spare: Vec<Box<Job<N, BW>>> = Vec::new();
    let mut waiting: HashMap<u32, Vec<Box<Job<N, BW>>>> = HashMap::new();
    let mut inflight = FuturesUnordered::new();
    loop {
        // A spare job starts on its block within the step.
        let (mut job, block) = match ready.pop() {
            Some(job) => (job, None),
            None if next_block < blocks => {
                let (bx, by) = ((next_block % blocks_x) * BW, (next_block / blocks_x) * bh);
                next_block += 1;
                match spare.pop() {
                    Some(job) => (job, Some((rect, bx, by))),
                    None => {
                        let job = Box::new(Job {
                            job: PacketJob::new(ctx, rect, bx, by),
                            held: Vec::new(),
                        });
                        (job, None)
                    }
                }
            }
            None => {
                // Nothing can run: wait for the next voxel.
                crate::work::flush(&fs, &mut flushed);
                let started = Instant::now();
                let Some((id, result)) = inflight.next().await else {
                    break;
                };
                stats.stall += started.elapsed();
                let voxel: Arc<PreparedVoxel> = result?;
                for mut job in waiting.remove(&id).unwrap_or_default() {
                    job.held.push(voxel.clone());
                    ready.push(job);
                }
                continue;
            }
        };
        let source = JobSource {
            held: &job.held,
            loader,
            touched: &touched,
        };
        let result = step(&mut job.job, ctx, block, &source, &mut region, &mut fs);
        match result {
            Step::Done => {
                job.held.clear();
                spare.push(job);
            }
            Step::Missing(id) => {
                stats.misses += 1;
                missed.insert(id);
                match mode {
                    MissMode::Block => {
                        stats.requested += 1;
                        crate::work::flush(&fs, &mut flushed);
                        let started = Instant::now();
                        let voxel = loader.load(id).await?;
                        stats.stall += started.elapsed();
                        job.held.push(voxel);
                        ready.push(job);
                    }
                    MissMode::Suspend => {
                        let list = waiting.entry(id).or_default();
                        if list.is_empty() {
                            stats.requested += 1;
                            inflight.push(async move { (id, loader.load(id).await) });
                        }
                        list.push(job);
                    }
                }
            }
        }
    }
    crate::work::flush(&fs, &mut flushed);
    stats.primary_rays = fs.primary_rays;
    stats.shadow_rays = fs.shadow_rays;
    stats.reflection_rays = fs.reflection_rays;
    stats.child_hits = fs.child_hits;
    stats.child_lanes = fs.child_lanes;
    stats.voxels_missed = u32::try_from(missed.len()).unwrap_or(u32::MAX);
    stats.voxels_touched = touched
        .iter()
        .map(|w| w.load(Ordering::Relaxed).count_ones())
        .sum();
    Ok(TileImage {
        rect,
        rgba,
        depth,
        primid,
        stats,
    })
}
