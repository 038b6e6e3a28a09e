//! Building the high-level BSP, in memory for a set of triangles that fits
//! the memory budget, and out-of-core (sample, split, distribute to chunk
//! files, recurse) for one that does not.

use super::spill::{SpillFile, SpillWriter};
use super::split::{choose_plane, clip_into, sides, Plane};
use super::PreprocessError;
use crate::db::manifest::VoxelEntry;
use crate::geometry::Aabb;
use crate::mesh::Triangle;
use crate::progress::Progress;
use crate::voxel::Voxel;
use glam::Vec3;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Mutex;

/// Subtrees with more references than this are built with `rayon::join`.
const PARALLEL_REFS: usize = 8192;
/// Triangles sampled to place the out-of-core split planes.
const SAMPLE_TRIANGLES: usize = 1 << 18;

/// The BSP as it is being built; flattened into the manifest at the end.
pub enum BuildNode {
    Split {
        plane: Plane,
        children: Box<[BuildNode; 2]>,
    },
    /// A voxel written to the voxels file, or `None` for empty space.
    Leaf(Option<VoxelEntry>),
}

/// A stream of triangles that can be read (at least) twice.
pub trait TriangleStream: Sync {
    fn count(&self) -> u64;
    fn for_each(
        &self,
        f: &mut dyn FnMut(Triangle) -> Result<(), PreprocessError>,
    ) -> Result<(), PreprocessError>;
}

impl TriangleStream for SpillFile {
    fn count(&self) -> u64 {
        self.count
    }
    fn for_each(
        &self,
        f: &mut dyn FnMut(Triangle) -> Result<(), PreprocessError>,
    ) -> Result<(), PreprocessError> {
        SpillFile::for_each(self, f)
    }
}

/// Appends voxel blobs to the voxels file from any render thread.
pub struct VoxelSink {
    path: PathBuf,
    out: Mutex<(BufWriter<File>, u64)>,
}

impl VoxelSink {
    pub fn create(path: &Path) -> Result<VoxelSink, PreprocessError> {
        let file = File::create(path).map_err(|e| PreprocessError::io(path, e))?;
        Ok(VoxelSink {
            path: path.to_path_buf(),
            out: Mutex::new((BufWriter::with_capacity(1 << 20, file), 0)),
        })
    }

    /// Writes `blob` and returns its offset.
    fn append(&self, blob: &[u8]) -> Result<u64, PreprocessError> {
        let mut guard = self.out.lock().unwrap_or_else(|p| p.into_inner());
        let (out, len) = &mut *guard;
        out.write_all(blob)
            .map_err(|e| PreprocessError::io(&self.path, e))?;
        let offset = *len;
        *len += blob.len() as u64;
        Ok(offset)
    }

    /// Flushes and syncs the file to disk.
    pub fn finish(self) -> Result<u64, PreprocessError> {
        let (out, len) = self.out.into_inner().unwrap_or_else(|p| p.into_inner());
        let file = out
            .into_inner()
            .map_err(|e| PreprocessError::io(&self.path, e.into_error()))?;
        file.sync_all()
            .map_err(|e| PreprocessError::io(&self.path, e))?;
        Ok(len)
    }
}

/// What every part of the build shares.
pub struct BuildContext<'a> {
    pub max_triangles: u32,
    pub max_depth: u32,
    pub zstd_level: i32,
    /// Largest number of triangles built in memory at once.
    pub chunk_triangles: u64,
    pub spill_dir: &'a Path,
    pub sink: &'a VoxelSink,
    pub progress: &'a Progress,
    /// Counts chunk files, to name them.
    pub chunk_counter: AtomicU64,
}

/// Builds the BSP below `cell` for every triangle of `stream`.
pub fn build_stream(
    ctx: &BuildContext,
    stream: &dyn TriangleStream,
    cell: Aabb,
    depth: u32,
) -> Result<BuildNode, PreprocessError> {
    if stream.count() <= ctx.chunk_triangles || depth >= ctx.max_depth {
        let mut tris = Vec::with_capacity(stream.count() as usize);
        stream.for_each(&mut |t| {
            tris.push(t);
            Ok(())
        })?;
        return build_in_memory(ctx, &tris, cell, depth);
    }

    // Out of core: place planes on a sample, then distribute every triangle
    // to the chunk files of the top tree's leaves in one streaming pass.
    let sample = reservoir_sample(stream, SAMPLE_TRIANGLES)?;
    let scale = stream.count() as f64 / sample.len().max(1) as f64;
    let refs: Vec<(usize, Aabb)> = sample
        .iter()
        .enumerate()
        .filter_map(|(i, p)| crate::geometry::clipped_bounds(p, &cell).map(|cb| (i, cb)))
        .collect();
    let mut chunk_cells = Vec::new();
    let target = (ctx.chunk_triangles / 2).max(1) as f64;
    let top = top_tree(
        ctx,
        &sample,
        refs,
        cell,
        depth,
        scale,
        target,
        &mut chunk_cells,
    );
    if chunk_cells.len() < 2 {
        // The sample cannot be split: build what there is in memory.
        tracing::warn!(
            triangles = stream.count(),
            "no split plane separates these triangles; building them in memory"
        );
        let mut tris = Vec::new();
        stream.for_each(&mut |t| {
            tris.push(t);
            Ok(())
        })?;
        return build_in_memory(ctx, &tris, cell, depth);
    }

    let mut writers = Vec::with_capacity(chunk_cells.len());
    for _ in &chunk_cells {
        let n = ctx.chunk_counter.fetch_add(1, Ordering::Relaxed);
        let path = ctx.spill_dir.join(format!("chunk-{n}.spill"));
        writers.push(SpillWriter::create(&path).map_err(|e| PreprocessError::io(&path, e))?);
    }
    ctx.progress.stage(
        &format!("distributing to {} chunks", writers.len()),
        stream.count(),
    );
    let mut walk = Vec::new();
    let mut pending = 0u64;
    stream.for_each(&mut |t| {
        if ctx.progress.is_cancelled() {
            return Err(PreprocessError::Cancelled);
        }
        walk.clear();
        walk.push((&top, cell, clip_into(&t, &t.bounds(), &cell)));
        while let Some((node, node_cell, cb)) = walk.pop() {
            match node {
                TopNode::Chunk(k) => {
                    let w = &mut writers[*k];
                    w.push(&t)?;
                }
                TopNode::Split { plane, children } => {
                    let (l, r) = sides(&cb, *plane);
                    let (lc, rc) = node_cell.split(plane.axis, plane.pos);
                    if l {
                        walk.push((&children[0], lc, clip_into(&t, &cb, &lc)));
                    }
                    if r {
                        walk.push((&children[1], rc, clip_into(&t, &cb, &rc)));
                    }
                }
            }
        }
        // Report in batches: this closure runs once per triangle.
        pending += 1;
        if pending == 4096 {
            ctx.progress.advance(pending);
            pending = 0;
        }
        Ok(())
    })?;
    ctx.progress.advance(pending);
    let mut chunks = Vec::with_capacity(writers.len());
    for w in writers {
        chunks.push(w.finish()?);
    }

    // Chunks one after the other, so only one is in memory at a time; each
    // uses every thread inside.
    let mut built: Vec<Option<BuildNode>> = Vec::with_capacity(chunks.len());
    for (chunk, (chunk_cell, chunk_depth)) in chunks.into_iter().zip(&chunk_cells) {
        let node = build_stream(ctx, &chunk, *chunk_cell, *chunk_depth)?;
        chunk.remove();
        built.push(Some(node));
    }
    Ok(graft(top, &mut built))
}

/// The top of an out-of-core split: planes placed on a sample, leaves are
/// chunks (indices into the chunk list).
enum TopNode {
    Split {
        plane: Plane,
        children: Box<[TopNode; 2]>,
    },
    Chunk(usize),
}

#[allow(clippy::too_many_arguments)]
fn top_tree(
    ctx: &BuildContext,
    sample: &[[Vec3; 3]],
    refs: Vec<(usize, Aabb)>,
    cell: Aabb,
    depth: u32,
    scale: f64,
    target: f64,
    chunk_cells: &mut Vec<(Aabb, u32)>,
) -> TopNode {
    let leaf = |chunk_cells: &mut Vec<(Aabb, u32)>| {
        chunk_cells.push((cell, depth));
        TopNode::Chunk(chunk_cells.len() - 1)
    };
    if refs.len() as f64 * scale <= target || depth + 1 >= ctx.max_depth {
        return leaf(chunk_cells);
    }
    let bounds: Vec<Aabb> = refs.iter().map(|r| r.1).collect();
    let Some(plane) = choose_plane(&cell, &bounds) else {
        return leaf(chunk_cells);
    };
    drop(bounds);
    let (lc, rc) = cell.split(plane.axis, plane.pos);
    let (mut left, mut right) = (Vec::new(), Vec::new());
    for (i, cb) in &refs {
        let (l, r) = sides(cb, plane);
        let tri = sample_triangle(&sample[*i]);
        if l {
            left.push((*i, clip_into(&tri, cb, &lc)));
        }
        if r {
            right.push((*i, clip_into(&tri, cb, &rc)));
        }
    }
    if left.len() == refs.len() && right.len() == refs.len() {
        return leaf(chunk_cells);
    }
    drop(refs);
    let l = top_tree(ctx, sample, left, lc, depth + 1, scale, target, chunk_cells);
    let r = top_tree(
        ctx,
        sample,
        right,
        rc,
        depth + 1,
        scale,
        target,
        chunk_cells,
    );
    TopNode::Split {
        plane,
        children: Box::new([l, r]),
    }
}

fn sample_triangle(p: &[Vec3; 3]) -> Triangle {
    Triangle {
        positions: *p,
        normals: [Vec3::Z; 3],
        colors: [[0; 4]; 3],
        id: 0,
    }
}

fn graft(top: TopNode, built: &mut [Option<BuildNode>]) -> BuildNode {
    match top {
        TopNode::Chunk(k) => built[k].take().expect("each chunk is grafted once"),
        TopNode::Split { plane, children } => {
            let [l, r] = *children;
            BuildNode::Split {
                plane,
                children: Box::new([graft(l, built), graft(r, built)]),
            }
        }
    }
}

/// A uniform sample of `k` triangles' positions (deterministic).
fn reservoir_sample(
    stream: &dyn TriangleStream,
    k: usize,
) -> Result<Vec<[Vec3; 3]>, PreprocessError> {
    let mut sample = Vec::with_capacity(k.min(stream.count() as usize));
    let mut seen = 0u64;
    let mut rng = crate::rng::Rng::new(stream.count());
    stream.for_each(&mut |t| {
        seen += 1;
        if sample.len() < k {
            sample.push(t.positions);
        } else {
            // Modulo bias is irrelevant at these sizes.
            let j = rng.next_u64() % seen;
            if (j as usize) < k {
                sample[j as usize] = t.positions;
            }
        }
        Ok(())
    })?;
    Ok(sample)
}

/// A triangle reference inside an in-memory build: index into the
/// triangles and clipped bounds in the current cell.
#[derive(Clone, Copy)]
struct Ref {
    index: u32,
    clipped: Aabb,
}

/// Builds the BSP below `cell` for `tris`, writing one voxel per leaf.
pub fn build_in_memory(
    ctx: &BuildContext,
    tris: &[Triangle],
    cell: Aabb,
    depth: u32,
) -> Result<BuildNode, PreprocessError> {
    let refs: Vec<Ref> = tris
        .iter()
        .enumerate()
        .map(|(i, t)| Ref {
            index: i as u32,
            clipped: clip_into(t, &t.bounds(), &cell),
        })
        .collect();
    ctx.progress.stage("building voxels", tris.len() as u64);
    recurse(ctx, tris, refs, cell, depth)
}

fn recurse(
    ctx: &BuildContext,
    tris: &[Triangle],
    refs: Vec<Ref>,
    cell: Aabb,
    depth: u32,
) -> Result<BuildNode, PreprocessError> {
    if refs.is_empty() {
        return Ok(BuildNode::Leaf(None));
    }
    let n = refs.len();
    if n <= ctx.max_triangles as usize || depth >= ctx.max_depth {
        return emit_leaf(ctx, tris, &refs, cell, depth);
    }
    let bounds: Vec<Aabb> = refs.iter().map(|r| r.clipped).collect();
    let Some(plane) = choose_plane(&cell, &bounds) else {
        return emit_leaf(ctx, tris, &refs, cell, depth);
    };
    drop(bounds);
    let (lc, rc) = cell.split(plane.axis, plane.pos);
    let (mut left, mut right) = (Vec::with_capacity(n / 2), Vec::with_capacity(n / 2));
    for r in &refs {
        let (l, rt) = sides(&r.clipped, plane);
        let t = &tris[r.index as usize];
        if l {
            left.push(Ref {
                index: r.index,
                clipped: clip_into(t, &r.clipped, &lc),
            });
        }
        if rt {
            right.push(Ref {
                index: r.index,
                clipped: clip_into(t, &r.clipped, &rc),
            });
        }
    }
    if left.len() == n && right.len() == n {
        return emit_leaf(ctx, tris, &refs, cell, depth);
    }
    drop(refs);
    let (l, r) = if n > PARALLEL_REFS {
        rayon::join(
            || recurse(ctx, tris, left, lc, depth + 1),
            || recurse(ctx, tris, right, rc, depth + 1),
        )
    } else {
        (
            recurse(ctx, tris, left, lc, depth + 1),
            recurse(ctx, tris, right, rc, depth + 1),
        )
    };
    Ok(BuildNode::Split {
        plane,
        children: Box::new([l?, r?]),
    })
}

fn emit_leaf(
    ctx: &BuildContext,
    tris: &[Triangle],
    refs: &[Ref],
    cell: Aabb,
    depth: u32,
) -> Result<BuildNode, PreprocessError> {
    if ctx.progress.is_cancelled() {
        return Err(PreprocessError::Cancelled);
    }
    let leaf_tris: Vec<Triangle> = refs.iter().map(|r| tris[r.index as usize]).collect();
    let voxel = Voxel::build(cell, &leaf_tris);
    let blob = voxel.encode(ctx.zstd_level);
    let offset = ctx.sink.append(&blob)?;
    ctx.progress.advance(refs.len() as u64);
    let content = refs
        .iter()
        .fold(Aabb::EMPTY, |b, r| b.union(&r.clipped))
        .intersection(&cell);
    Ok(BuildNode::Leaf(Some(VoxelEntry {
        bounds: cell,
        content,
        triangles: voxel.triangles.len() as u32,
        vertices: voxel.positions.len() as u32,
        raw_bytes: voxel.raw_size() as u64,
        compressed_bytes: blob.len() as u64,
        offset,
        checksum: crate::voxel::checksum(&blob),
        depth,
    })))
}
