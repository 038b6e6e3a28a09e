//! `dray info`: what a database holds, for people and (as JSON) for scripts.

use super::manifest::Manifest;
use crate::geometry::Aabb;
use serde::Serialize;

/// One bucket of a size histogram: voxels whose size is in `[from, to)`.
#[derive(Clone, Debug, Serialize)]
pub struct Bucket {
    pub from_bytes: u64,
    pub to_bytes: u64,
    pub voxels: u64,
}

#[derive(Clone, Debug, Serialize)]
pub struct DbInfo {
    pub format_version: u32,
    pub input_triangles: u64,
    pub stored_triangles: u64,
    pub replication_factor: f64,
    pub voxels: u64,
    pub empty_leaves: u64,
    pub bsp_nodes: u64,
    pub depth_max: u32,
    pub depth_mean: f64,
    pub raw_bytes: u64,
    pub compressed_bytes: u64,
    pub compression_ratio: f64,
    pub voxel_raw_mean_bytes: f64,
    pub voxel_compressed_mean_bytes: f64,
    pub voxel_triangles_mean: f64,
    pub voxel_triangles_max: u32,
    pub raw_histogram: Vec<Bucket>,
    pub compressed_histogram: Vec<Bucket>,
    pub bounds: Aabb,
    pub max_triangles: u32,
    pub max_depth: u32,
    pub copies: [u32; 3],
    pub inputs: Vec<String>,
}

impl DbInfo {
    pub fn from_manifest(m: &Manifest) -> DbInfo {
        let n = m.voxels.len() as u64;
        let raw: u64 = m.voxels.iter().map(|v| v.raw_bytes).sum();
        let compressed: u64 = m.voxels.iter().map(|v| v.compressed_bytes).sum();
        let mean = |x: u64| if n == 0 { 0.0 } else { x as f64 / n as f64 };
        DbInfo {
            format_version: m.format_version,
            input_triangles: m.input_triangles,
            stored_triangles: m.stored_triangles,
            replication_factor: m.replication_factor(),
            voxels: n,
            empty_leaves: m
                .nodes
                .iter()
                .filter(|node| matches!(node, super::manifest::BspNode::Leaf { voxel: None }))
                .count() as u64,
            bsp_nodes: m.nodes.len() as u64,
            depth_max: m.depth(),
            depth_mean: mean(m.voxels.iter().map(|v| v.depth as u64).sum()),
            raw_bytes: raw,
            compressed_bytes: compressed,
            compression_ratio: raw as f64 / compressed.max(1) as f64,
            voxel_raw_mean_bytes: mean(raw),
            voxel_compressed_mean_bytes: mean(compressed),
            voxel_triangles_mean: mean(m.stored_triangles),
            voxel_triangles_max: m.voxels.iter().map(|v| v.triangles).max().unwrap_or(0),
            raw_histogram: histogram(m.voxels.iter().map(|v| v.raw_bytes)),
            compressed_histogram: histogram(m.voxels.iter().map(|v| v.compressed_bytes)),
            bounds: m.model_bounds,
            max_triangles: m.build.max_triangles,
            max_depth: m.build.max_depth,
            copies: m.build.copies,
            inputs: m.build.inputs.iter().map(|i| i.path.clone()).collect(),
        }
    }

    /// The human-readable report.
    pub fn to_text(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        let kib = |b: f64| b / 1024.0;
        let _ = writeln!(s, "format version      {}", self.format_version);
        let _ = writeln!(s, "inputs              {}", self.inputs.join(", "));
        let _ = writeln!(
            s,
            "triangles           {} input, {} stored (replication factor {:.3})",
            self.input_triangles, self.stored_triangles, self.replication_factor
        );
        let _ = writeln!(
            s,
            "voxels              {} (max {} triangles each, built with max {}; {} empty leaves)",
            self.voxels, self.voxel_triangles_max, self.max_triangles, self.empty_leaves
        );
        let _ = writeln!(
            s,
            "BSP                 {} nodes, depth {} max, {:.1} mean (limit {})",
            self.bsp_nodes, self.depth_max, self.depth_mean, self.max_depth
        );
        let _ = writeln!(
            s,
            "size                {:.1} MiB raw, {:.1} MiB compressed, ratio {:.2}:1",
            self.raw_bytes as f64 / 1048576.0,
            self.compressed_bytes as f64 / 1048576.0,
            self.compression_ratio
        );
        let _ = writeln!(
            s,
            "voxel mean          {:.1} KiB raw, {:.1} KiB compressed, {:.0} triangles",
            kib(self.voxel_raw_mean_bytes),
            kib(self.voxel_compressed_mean_bytes),
            self.voxel_triangles_mean
        );
        let b = &self.bounds;
        let _ = writeln!(
            s,
            "bounds              ({:.4}, {:.4}, {:.4}) - ({:.4}, {:.4}, {:.4})",
            b.min[0], b.min[1], b.min[2], b.max[0], b.max[1], b.max[2]
        );
        for (name, hist) in [
            ("raw", &self.raw_histogram),
            ("compressed", &self.compressed_histogram),
        ] {
            let _ = writeln!(s, "voxel sizes, {name}:");
            let most = hist.iter().map(|b| b.voxels).max().unwrap_or(1).max(1);
            for bucket in hist {
                let bar = "#".repeat((40 * bucket.voxels).div_ceil(most) as usize);
                let _ = writeln!(
                    s,
                    "  {:>9} - {:<9} {:>7} {bar}",
                    human(bucket.from_bytes),
                    human(bucket.to_bytes),
                    bucket.voxels
                );
            }
        }
        s
    }
}

fn human(bytes: u64) -> String {
    if bytes >= 1 << 20 {
        format!("{} MiB", bytes >> 20)
    } else if bytes >= 1 << 10 {
        format!("{} KiB", bytes >> 10)
    } else {
        format!("{bytes} B")
    }
}

/// Power-of-two buckets from the smallest to the largest size present.
fn histogram(sizes: impl Iterator<Item = u64>) -> Vec<Bucket> {
    let mut counts = [0u64; 64];
    for s in sizes {
        counts[63 - s.max(1).leading_zeros() as usize] += 1;
    }
    let Some(first) = counts.iter().position(|&c| c > 0) else {
        return Vec::new();
    };
    let last = counts.iter().rposition(|&c| c > 0).unwrap_or(first);
    (first..=last)
        .map(|k| Bucket {
            from_bytes: 1 << k,
            to_bytes: 1u64.checked_shl(k as u32 + 1).unwrap_or(u64::MAX),
            voxels: counts[k],
        })
        .collect()
}
