//! Choosing and applying the high-level BSP's split planes.
//!
//! Every triangle reference carries its *clipped* bounds: the bounds of the
//! part of the triangle inside the current cell. Deciding sides with them
//! (instead of the whole triangle's bounds) replicates a triangle only into
//! cells it really touches, which keeps the replication factor low.

use crate::geometry::{clipped_bounds, Aabb};
use crate::mesh::Triangle;

/// Bins per axis of the SAH sweep.
const BINS: usize = 32;

/// A split plane of the high-level BSP.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Plane {
    pub axis: usize,
    pub pos: f32,
}

/// Picks the plane with the lowest surface area heuristic cost among
/// `BINS - 1` candidates per axis. Returns `None` when no plane separates
/// anything (every candidate leaves all references on both sides), which
/// happens for a heap of triangles that all straddle every candidate.
pub fn choose_plane(cell: &Aabb, refs: &[Aabb]) -> Option<Plane> {
    let n = refs.len();
    let ext = cell.extent();
    let mut best: Option<(f32, Plane)> = None;
    for axis in 0..3 {
        let width = ext[axis];
        if width <= 0.0 || !width.is_finite() {
            continue;
        }
        let lo = cell.min[axis];
        let scale = BINS as f32 / width;
        let bin = |x: f32| (((x - lo) * scale) as isize).clamp(0, BINS as isize - 1) as usize;
        let mut starts = [0u32; BINS];
        let mut ends = [0u32; BINS];
        for r in refs {
            starts[bin(r.min[axis])] += 1;
            ends[bin(r.max[axis])] += 1;
        }
        // left[k]: references that start left of plane k; right[k]: that end right of it.
        let mut left = [0usize; BINS];
        let mut right = [0usize; BINS];
        for k in 1..BINS {
            left[k] = left[k - 1] + starts[k - 1] as usize;
        }
        let mut acc = 0;
        for k in (1..BINS).rev() {
            acc += ends[k] as usize;
            right[k] = acc;
        }
        for k in 1..BINS {
            let (nl, nr) = (left[k], right[k]);
            if nl == n && nr == n {
                continue;
            }
            let pos = lo + k as f32 * width / BINS as f32;
            let (lc, rc) = cell.split(axis, pos);
            let cost = lc.area() * nl as f32 + rc.area() * nr as f32;
            if best.is_none_or(|(c, _)| cost < c) {
                best = Some((cost, Plane { axis, pos }));
            }
        }
    }
    best.map(|(_, p)| p)
}

/// Which sides of `plane` a reference with clipped bounds `cb` goes to.
/// A triangle lying in the plane goes left only.
pub fn sides(cb: &Aabb, plane: Plane) -> (bool, bool) {
    let left = cb.min[plane.axis] < plane.pos;
    let right = cb.max[plane.axis] > plane.pos;
    if !left && !right {
        (true, false)
    } else {
        (left, right)
    }
}

/// Clipped bounds of `t` in `child`, given that its clipped bounds in the
/// parent cell were `parent_cb` and the side test sent it there. Falls back to
/// the parent bounds squeezed into the child when rounding makes the exact
/// clip come out empty, so a triangle is never lost.
pub fn clip_into(t: &Triangle, parent_cb: &Aabb, child: &Aabb) -> Aabb {
    if child.contains_box(parent_cb) {
        return *parent_cb;
    }
    match clipped_bounds(&t.positions, child) {
        Some(cb) => cb,
        None => {
            let mut squeezed = *parent_cb;
            for a in 0..3 {
                squeezed.min[a] = squeezed.min[a].clamp(child.min[a], child.max[a]);
                squeezed.max[a] = squeezed.max[a].clamp(child.min[a], child.max[a]);
            }
            squeezed
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use glam::Vec3;

    #[test]
    fn separates_two_clusters_between_them() {
        // The cell fits the clusters tightly, so the only gain is between them.
        let cell = Aabb::new(Vec3::new(0.0, 1.0, 1.0), Vec3::new(9.0, 2.0, 2.0));
        let mut refs = vec![];
        for i in 0..10 {
            let x = i as f32 * 0.1;
            refs.push(Aabb::new(
                Vec3::new(x, 1.0, 1.0),
                Vec3::new(x + 0.1, 2.0, 2.0),
            ));
            refs.push(Aabb::new(
                Vec3::new(8.0 + x, 1.0, 1.0),
                Vec3::new(8.1 + x, 2.0, 2.0),
            ));
        }
        let p = choose_plane(&cell, &refs).unwrap();
        let (mut l, mut r) = (0, 0);
        for cb in &refs {
            let (a, b) = sides(cb, p);
            l += a as usize;
            r += b as usize;
        }
        assert!(l <= 10 && r <= 10 && l + r == 20, "{p:?} {l} {r}");
    }

    #[test]
    fn cuts_off_empty_space_first() {
        let cell = Aabb::new(Vec3::ZERO, Vec3::splat(10.0));
        let refs = vec![Aabb::new(Vec3::splat(0.5), Vec3::splat(1.5)); 20];
        let p = choose_plane(&cell, &refs).unwrap();
        let (l, r) = sides(&refs[0], p);
        assert!(l && !r, "{p:?} should leave the empty part on its own");
    }

    #[test]
    fn no_plane_when_everything_straddles() {
        let cell = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let refs = vec![cell; 50];
        assert_eq!(choose_plane(&cell, &refs), None);
    }
}
