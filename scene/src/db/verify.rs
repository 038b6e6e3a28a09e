//! `dray verify`: decompress every voxel and check it against the manifest
//! and the BSP, naming each bad voxel.

use super::manifest::BspNode;
use super::Database;
use crate::geometry::{clipped_bounds, triangle_touches_box, Aabb};
use crate::progress::Progress;
use rayon::prelude::*;
use std::sync::atomic::{AtomicU64, Ordering};

/// What `verify` found; `problems` is empty for a good database.
#[derive(Debug, Default)]
pub struct VerifyReport {
    pub voxels: usize,
    pub triangles: u64,
    /// One line per problem, each naming the voxel (or the manifest part).
    pub problems: Vec<String>,
}

impl VerifyReport {
    pub fn is_ok(&self) -> bool {
        self.problems.is_empty()
    }
}

/// Checks every voxel: blob checksum and length, decoding, structure (done
/// by the decoder), agreement with its manifest entry and its BSP cell, and
/// that each triangle touches the voxel. Then that every input triangle id
/// is stored somewhere.
pub fn verify(db: &Database, progress: &Progress) -> VerifyReport {
    let m = &db.manifest;
    let mut report = VerifyReport {
        voxels: (0..m.voxels.len() as u32)
            .filter(|&id| db.holds(id))
            .count(),
        ..Default::default()
    };
    // The cell of each voxel, from the BSP.
    let mut cells: Vec<Option<(Aabb, u32)>> = vec![None; m.voxels.len()];
    let mut stack = vec![(0u32, m.root_bounds, 0u32)];
    while let Some((node, cell, depth)) = stack.pop() {
        match m.nodes[node as usize] {
            BspNode::Leaf { voxel: Some(v) } => cells[v as usize] = Some((cell, depth)),
            BspNode::Leaf { voxel: None } => {}
            BspNode::Split {
                axis,
                pos,
                left,
                right,
            } => {
                let (l, r) = cell.split(axis as usize, pos);
                stack.push((left, l, depth + 1));
                stack.push((right, r, depth + 1));
            }
        }
    }

    let ids = m.input_triangles;
    let seen: Vec<AtomicU64> = (0..ids.div_ceil(64)).map(|_| AtomicU64::new(0)).collect();
    progress.stage("verifying voxels", report.voxels as u64);
    // A shard checks the voxels it holds.
    let mut problems: Vec<(u32, String)> = (0..m.voxels.len() as u32)
        .into_par_iter()
        .filter(|&id| db.holds(id))
        .filter_map(|id| {
            let result = check_voxel(db, id, cells[id as usize], &seen);
            progress.advance(1);
            result.err().map(|msg| (id, msg))
        })
        .collect();
    progress.finish();
    problems.sort_by_key(|p| p.0);
    report.problems = problems
        .into_iter()
        .map(|(id, msg)| format!("voxel {id}: {msg}"))
        .collect();
    report.triangles = (m.voxels.iter().enumerate())
        .filter(|(id, _)| db.holds(*id as u32))
        .map(|(_, v)| v.triangles as u64)
        .sum();

    let missing: u64 = (0..ids)
        .filter(|&i| seen[(i / 64) as usize].load(Ordering::Relaxed) & (1 << (i % 64)) == 0)
        .count() as u64;
    // Missing ids are only meaningful when every voxel could be read.
    if missing > 0 && report.problems.is_empty() && db.shard().is_none() {
        report.problems.push(format!(
            "manifest: {missing} of {ids} input triangles are stored in no voxel"
        ));
    }
    report
}

fn check_voxel(
    db: &Database,
    id: u32,
    cell: Option<(Aabb, u32)>,
    seen: &[AtomicU64],
) -> Result<(), String> {
    let entry = db.entry(id).map_err(|e| e.to_string())?;
    let voxel = db.load_voxel(id).map_err(|e| match e {
        super::DbError::Voxel { source, .. } => source.to_string(),
        super::DbError::Entry { message, .. } => message,
        other => other.to_string(),
    })?;
    let Some((cell, depth)) = cell else {
        return Err("in no BSP leaf".into());
    };
    if entry.bounds != cell || voxel.bounds != cell {
        return Err(format!(
            "bounds {:?} (manifest {:?}) differ from its BSP cell {:?}",
            voxel.bounds, entry.bounds, cell
        ));
    }
    if entry.depth != depth {
        return Err(format!(
            "manifest depth {} but its leaf is at depth {depth}",
            entry.depth
        ));
    }
    if voxel.triangles.len() as u32 != entry.triangles
        || voxel.positions.len() as u32 != entry.vertices
        || voxel.raw_size() as u64 != entry.raw_bytes
    {
        return Err(format!(
            "holds {} triangles, {} vertices, {} raw bytes; the manifest says {}, {}, {}",
            voxel.triangles.len(),
            voxel.positions.len(),
            voxel.raw_size(),
            entry.triangles,
            entry.vertices,
            entry.raw_bytes
        ));
    }
    // Clipping decides cells in f32; allow for its rounding.
    let eps = 1e-5 * cell.diagonal().max(1e-30)
        + 1e-6 * cell.hi().abs().max(cell.lo().abs()).max_element();
    for i in 0..voxel.triangles.len() {
        let t = voxel.triangle(i);
        if !triangle_touches_box(&t.positions, &cell, eps) {
            return Err(format!(
                "triangle {} (local {i}) does not touch the voxel's bounds",
                t.id
            ));
        }
        // Traversal skips what lies outside the content box: it must hold
        // every part of every triangle inside the cell.
        if let Some(inside) = clipped_bounds(&t.positions, &cell) {
            if !entry.content.expanded(eps).contains_box(&inside) {
                return Err(format!(
                    "triangle {} (local {i}) sticks out of the voxel's content bounds",
                    t.id
                ));
            }
        }
        let word = (t.id / 64) as usize;
        match seen.get(word) {
            Some(w) => {
                w.fetch_or(1 << (t.id % 64), Ordering::Relaxed);
            }
            None => {
                return Err(format!(
                    "triangle id {} is beyond the input's {} triangles",
                    t.id,
                    seen.len() * 64
                ))
            }
        }
    }
    Ok(())
}
