//! One tile's primary rays with voxels that arrive over time: the packets
//! that meet a missing voxel wait (suspend mode) while the others go on,
//! or the whole tile waits for each miss in turn (block mode, the
//! demand-paging baseline the paper compares against).

use crate::camera::CameraBasis;
use crate::packet::{Packet, Step, Traversal};
use crate::render::Isa;
use crate::scene::{TopLevel, VoxelSource};
use futures::future::BoxFuture;
use futures::stream::{FuturesUnordered, StreamExt};
use glam::Vec3;
use std::collections::HashMap;

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
    /// Resolves once voxel `id` is resident (it may already be).
    fn load(&self, id: u32) -> BoxFuture<'_, Result<(), LoadError>>;
}

/// A rectangle of the image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Rect {
    pub x0: u32,
    pub y0: u32,
    pub width: u32,
    pub height: u32,
}

/// A tile's primary hits, rows top to bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct TileHits {
    pub rect: Rect,
    pub depth: Vec<f32>,
    pub primid: Vec<u32>,
    pub rays: u64,
    /// Times a packet met a missing voxel.
    pub misses: u64,
    /// Distinct voxels requested.
    pub requested: u64,
}

/// Traces the primary rays of `rect`, loading voxels through `loader`.
pub async fn trace_tile(
    top: &TopLevel,
    loader: &dyn VoxelLoader,
    basis: &CameraBasis,
    rect: Rect,
    mode: MissMode,
    isa: Isa,
) -> Result<TileHits, LoadError> {
    // A kernel the CPU cannot run would be undefined behaviour.
    let isa = if isa.supported() { isa } else { Isa::Portable };
    match isa {
        #[cfg(target_arch = "x86_64")]
        Isa::Avx512 => drive::<16, 4>(top, loader, basis, rect, mode, run_avx512).await,
        #[cfg(target_arch = "x86_64")]
        Isa::Avx2 => drive::<8, 4>(top, loader, basis, rect, mode, run_avx2).await,
        _ => drive::<8, 4>(top, loader, basis, rect, mode, run_portable).await,
    }
}

type Runner<const N: usize> =
    fn(&mut Traversal<N>, &mut Packet<N>, &TopLevel, &dyn VoxelSource) -> Step;

fn run_portable(
    t: &mut Traversal<8>,
    p: &mut Packet<8>,
    top: &TopLevel,
    s: &dyn VoxelSource,
) -> Step {
    t.run(p, top, s)
}

#[cfg(target_arch = "x86_64")]
fn run_avx2(t: &mut Traversal<8>, p: &mut Packet<8>, top: &TopLevel, s: &dyn VoxelSource) -> Step {
    #[target_feature(enable = "avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn inner(
        t: &mut Traversal<8>,
        p: &mut Packet<8>,
        top: &TopLevel,
        s: &dyn VoxelSource,
    ) -> Step {
        t.run(p, top, s)
    }
    // SAFETY: `trace_tile` picks this only where `Isa::supported` says the
    // CPU has AVX2.
    unsafe { inner(t, p, top, s) }
}

#[cfg(target_arch = "x86_64")]
fn run_avx512(
    t: &mut Traversal<16>,
    p: &mut Packet<16>,
    top: &TopLevel,
    s: &dyn VoxelSource,
) -> Step {
    #[target_feature(enable = "avx512f,avx512vl,avx512bw,avx2,fma,bmi1,bmi2,lzcnt,popcnt")]
    unsafe fn inner(
        t: &mut Traversal<16>,
        p: &mut Packet<16>,
        top: &TopLevel,
        s: &dyn VoxelSource,
    ) -> Step {
        t.run(p, top, s)
    }
    // SAFETY: `trace_tile` picks this only where `Isa::supported` says the
    // CPU has AVX-512.
    unsafe { inner(t, p, top, s) }
}

struct Job<const N: usize> {
    trav: Traversal<N>,
    packet: Packet<N>,
    /// Tile-local pixel of each lane; `None` for lanes past the edge.
    pixels: [Option<(u32, u32)>; N],
}

async fn drive<const N: usize, const BW: u32>(
    top: &TopLevel,
    loader: &dyn VoxelLoader,
    basis: &CameraBasis,
    rect: Rect,
    mode: MissMode,
    run: Runner<N>,
) -> Result<TileHits, LoadError> {
    let bh = N as u32 / BW;
    let n = (rect.width * rect.height) as usize;
    let mut out = TileHits {
        rect,
        depth: vec![f32::INFINITY; n],
        primid: vec![u32::MAX; n],
        rays: n as u64,
        misses: 0,
        requested: 0,
    };
    let mut ready: Vec<Job<N>> = Vec::new();
    for by in (0..rect.height).step_by(bh as usize) {
        for bx in (0..rect.width).step_by(BW as usize) {
            let mut pixels = [None; N];
            let mut dirs = [Vec3::ZERO; N];
            for i in 0..N {
                let (x, y) = (bx + i as u32 % BW, by + i as u32 / BW);
                let (cx, cy) = (x.min(rect.width - 1), y.min(rect.height - 1));
                dirs[i] = basis.direction(rect.x0 + cx, rect.y0 + cy);
                if x < rect.width && y < rect.height {
                    pixels[i] = Some((x, y));
                }
            }
            ready.push(Job {
                trav: Traversal::default(),
                packet: Packet::new(&[basis.eye; N], &dirs, 0.0, f32::INFINITY),
                pixels,
            });
        }
    }
    // Packets waiting for each voxel, and the requests in flight.
    let mut waiting: HashMap<u32, Vec<Job<N>>> = HashMap::new();
    let mut inflight = FuturesUnordered::new();
    let source: &dyn VoxelSource = loader;
    loop {
        while let Some(mut job) = ready.pop() {
            match run(&mut job.trav, &mut job.packet, top, source) {
                Step::Done => {
                    for (i, p) in job.pixels.iter().enumerate() {
                        if let (Some((x, y)), true) = (p, job.packet.hit(i)) {
                            let k = (y * rect.width + x) as usize;
                            out.depth[k] = job.packet.t[i];
                            out.primid[k] = job.packet.id[i];
                        }
                    }
                }
                Step::Missing(id) => {
                    out.misses += 1;
                    match mode {
                        MissMode::Block => {
                            out.requested += 1;
                            loader.load(id).await?;
                            ready.push(job);
                        }
                        MissMode::Suspend => {
                            let list = waiting.entry(id).or_default();
                            if list.is_empty() {
                                out.requested += 1;
                                inflight.push(async move { (id, loader.load(id).await) });
                            }
                            list.push(job);
                        }
                    }
                }
            }
        }
        let Some((id, result)) = inflight.next().await else {
            break;
        };
        result?;
        ready.extend(waiting.remove(&id).unwrap_or_default());
    }
    Ok(out)
}
