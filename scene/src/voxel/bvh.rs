//! The low-level BVH of a voxel: binned SAH build, exact refit, statistics.
//!
//! Layout (see [`BvhNode`]): depth-first pre-order, node 0 is the root, the
//! left child of an interior node `i` is `i + 1`, its right child is
//! `node.first`; a leaf holds the triangles `first .. first + count`.

use crate::geometry::Aabb;
use glam::Vec3;

/// Most triangles a leaf built by [`super::Voxel::build`] holds.
pub const MAX_LEAF_TRIANGLES: usize = 4;
/// Deepest level (root = 0) a valid tree may reach; traversal uses a fixed
/// stack of this size. The build switches to median splits well before.
pub const MAX_BVH_DEPTH: usize = 64;
/// Number of SAH bins per axis.
pub const SAH_BINS: usize = 16;
/// SAH cost of visiting an interior node, relative to one triangle test.
pub const SAH_TRAVERSAL_COST: f32 = 1.0;
/// SAH cost of one ray-triangle test.
pub const SAH_INTERSECT_COST: f32 = 1.0;
/// Depth from which the build stops trusting SAH and halves by count, which
/// bounds the depth by `MEDIAN_FROM_DEPTH + log2(triangles)`.
const MEDIAN_FROM_DEPTH: usize = 32;

/// One node of the low-level BVH.
///
/// Encoding: `count > 0` is a leaf with triangles `first .. first + count`
/// (indices into [`super::Voxel::triangles`]); `count == 0` is an interior
/// node whose left child is the next node (`index + 1`) and whose right child
/// is node `first`. Nodes are stored depth-first (pre-order), node 0 = root,
/// so children always come after their parent and leaves list the triangles
/// in order. `bounds` is never stored in a blob: it is recomputed exactly
/// from the triangles (min/max of their corners) when a blob is decoded.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BvhNode {
    pub bounds: Aabb,
    /// Leaf: first triangle. Interior: index of the right child.
    pub first: u32,
    /// Leaf: number of triangles (> 0). Interior: 0.
    pub count: u32,
}

impl BvhNode {
    pub fn is_leaf(&self) -> bool {
        self.count > 0
    }
}

/// Builds a BVH over primitives with the given bounds. Returns the nodes
/// (bounds left EMPTY, call [`refit`]) and the primitive order: leaf `first`
/// indexes into that order.
pub(crate) fn build(prim_bounds: &[Aabb]) -> (Vec<BvhNode>, Vec<u32>) {
    let centroids: Vec<Vec3> = prim_bounds.iter().map(|b| b.center()).collect();
    let mut order: Vec<u32> = (0..prim_bounds.len() as u32).collect();
    let mut nodes = Vec::with_capacity(prim_bounds.len().max(1) * 2 / MAX_LEAF_TRIANGLES + 1);
    if !prim_bounds.is_empty() {
        let mut b = Builder {
            bounds: prim_bounds,
            centroids: &centroids,
            nodes: &mut nodes,
        };
        b.node(&mut order, 0, 0);
    }
    (nodes, order)
}

struct Builder<'a> {
    bounds: &'a [Aabb],
    centroids: &'a [Vec3],
    nodes: &'a mut Vec<BvhNode>,
}

#[derive(Clone, Copy)]
struct Bin {
    bounds: Aabb,
    count: u32,
}

impl Builder<'_> {
    /// Builds the subtree over `prims` (which start at `offset` in the final
    /// order), appending its nodes in pre-order.
    fn node(&mut self, prims: &mut [u32], offset: usize, depth: usize) {
        let me = self.nodes.len();
        self.nodes.push(BvhNode {
            bounds: Aabb::EMPTY,
            first: offset as u32,
            count: prims.len() as u32,
        });
        let n = prims.len();
        if n <= 1 {
            return;
        }
        let split = if depth >= MEDIAN_FROM_DEPTH {
            None
        } else {
            self.sah_split(prims)
        };
        let mid = match split {
            Some((cost, axis, bin, cmin, scale)) => {
                if n <= MAX_LEAF_TRIANGLES && n as f32 * SAH_INTERSECT_COST <= cost {
                    return; // SAH says leaf
                }
                let c = self.centroids;
                partition(prims, |&p| bin_of(c[p as usize][axis], cmin, scale) <= bin)
            }
            None => {
                if n <= MAX_LEAF_TRIANGLES {
                    return;
                }
                n / 2
            }
        };
        // A degenerate partition cannot happen (a SAH split has both sides
        // non-empty), but stay safe.
        let mid = if mid == 0 || mid == n { n / 2 } else { mid };
        let (left, right) = prims.split_at_mut(mid);
        self.node(left, offset, depth + 1);
        let right_index = self.nodes.len() as u32;
        self.node(right, offset + mid, depth + 1);
        self.nodes[me].first = right_index;
        self.nodes[me].count = 0;
    }

    /// Best binned SAH split: (cost, axis, last bin on the left, centroid
    /// min, bin scale), or None when the centroids do not spread.
    fn sah_split(&self, prims: &[u32]) -> Option<(f32, usize, usize, f32, f32)> {
        let mut cb = Aabb::EMPTY;
        let mut nb = Aabb::EMPTY;
        for &p in prims {
            cb.grow(self.centroids[p as usize]);
            nb = nb.union(&self.bounds[p as usize]);
        }
        let node_area = nb.area();
        // A box without area (all triangles on one line or point): rank
        // splits by counts alone.
        let inv_area = if node_area > 0.0 && node_area.is_finite() {
            1.0 / node_area
        } else {
            0.0
        };
        let mut best: Option<(f32, usize, usize, f32, f32)> = None;
        for axis in 0..3 {
            let cmin = cb.min[axis];
            let extent = cb.max[axis] - cmin;
            if extent.is_nan() || extent <= 0.0 || !extent.is_finite() {
                continue;
            }
            let scale = SAH_BINS as f32 * (1.0 - 1e-6) / extent;
            let mut bins = [Bin {
                bounds: Aabb::EMPTY,
                count: 0,
            }; SAH_BINS];
            for &p in prims {
                let b = &mut bins[bin_of(self.centroids[p as usize][axis], cmin, scale)];
                b.count += 1;
                b.bounds = b.bounds.union(&self.bounds[p as usize]);
            }
            // Right-to-left sweep: area * count of the right part.
            let mut right_cost = [0.0f32; SAH_BINS];
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0u32;
            for i in (1..SAH_BINS).rev() {
                acc = acc.union(&bins[i].bounds);
                cnt += bins[i].count;
                right_cost[i] = weighted(&acc, cnt, inv_area);
            }
            let mut acc = Aabb::EMPTY;
            let mut cnt = 0u32;
            for i in 0..SAH_BINS - 1 {
                acc = acc.union(&bins[i].bounds);
                cnt += bins[i].count;
                if cnt == 0 || cnt as usize == prims.len() {
                    continue;
                }
                let cost = SAH_TRAVERSAL_COST
                    + SAH_INTERSECT_COST * (weighted(&acc, cnt, inv_area) + right_cost[i + 1]);
                match best {
                    Some(b) if b.0 <= cost => {}
                    _ => best = Some((cost, axis, i, cmin, scale)),
                }
            }
        }
        best
    }
}

/// Probability-weighted count of one side: area(side)/area(node) * count, or
/// the plain count when the node has no area.
fn weighted(b: &Aabb, count: u32, inv_area: f32) -> f32 {
    if inv_area > 0.0 {
        b.area() * inv_area * count as f32
    } else {
        count as f32
    }
}

fn bin_of(c: f32, cmin: f32, scale: f32) -> usize {
    let x = (c - cmin) * scale;
    // `as` saturates and maps NaN to 0.
    (x as usize).min(SAH_BINS - 1)
}

/// In-place partition: elements for which `left` holds come first; returns
/// their number.
fn partition(v: &mut [u32], left: impl Fn(&u32) -> bool) -> usize {
    let mut i = 0;
    for j in 0..v.len() {
        if left(&v[j]) {
            v.swap(i, j);
            i += 1;
        }
    }
    i
}

/// Recomputes every node's bounds exactly from the triangles' corner
/// positions (min/max only, no rounding). Requires a structurally valid tree
/// (children after parents, indices in range).
pub(crate) fn refit(nodes: &mut [BvhNode], triangles: &[[u32; 3]], positions: &[[f32; 3]]) {
    for i in (0..nodes.len()).rev() {
        let n = nodes[i];
        let bounds = if n.is_leaf() {
            let mut b = Aabb::EMPTY;
            for t in &triangles[n.first as usize..(n.first + n.count) as usize] {
                for &v in t {
                    b.grow(Vec3::from_array(positions[v as usize]));
                }
            }
            b
        } else {
            nodes[i + 1].bounds.union(&nodes[n.first as usize].bounds)
        };
        nodes[i].bounds = bounds;
    }
}

/// Shape statistics of a BVH.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct BvhStats {
    pub nodes: usize,
    pub leaves: usize,
    pub max_depth: usize,
    pub max_leaf_triangles: usize,
    /// Triangles per leaf, averaged over the leaves.
    pub average_leaf_triangles: f32,
    /// SAH cost of the tree with [`SAH_TRAVERSAL_COST`] and
    /// [`SAH_INTERSECT_COST`] (area ratios relative to the root).
    pub sah_cost: f32,
    /// SAH cost of one leaf holding every triangle.
    pub single_leaf_cost: f32,
}

/// Statistics of a (valid) tree.
pub fn stats(nodes: &[BvhNode]) -> BvhStats {
    let mut s = BvhStats {
        nodes: nodes.len(),
        leaves: 0,
        max_depth: 0,
        max_leaf_triangles: 0,
        average_leaf_triangles: 0.0,
        sah_cost: 0.0,
        single_leaf_cost: 0.0,
    };
    let Some(root) = nodes.first() else {
        return s;
    };
    let root_area = root.bounds.area();
    let ratio = |b: &Aabb| {
        if root_area > 0.0 {
            b.area() / root_area
        } else {
            1.0
        }
    };
    let mut tris = 0usize;
    let mut stack = vec![(0usize, 0usize)];
    while let Some((i, d)) = stack.pop() {
        let n = &nodes[i];
        s.max_depth = s.max_depth.max(d);
        if n.is_leaf() {
            s.leaves += 1;
            tris += n.count as usize;
            s.max_leaf_triangles = s.max_leaf_triangles.max(n.count as usize);
            s.sah_cost += ratio(&n.bounds) * n.count as f32 * SAH_INTERSECT_COST;
        } else {
            s.sah_cost += ratio(&n.bounds) * SAH_TRAVERSAL_COST;
            stack.push((n.first as usize, d + 1));
            stack.push((i + 1, d + 1));
        }
    }
    s.average_leaf_triangles = tris as f32 / s.leaves.max(1) as f32;
    s.single_leaf_cost = tris as f32 * SAH_INTERSECT_COST;
    s
}
