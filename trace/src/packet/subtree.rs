//! What the two forms of a group's search share
//! ([`Packet::hand_off_sparse_subtrees`]): a group of at most four of a
//! shadow packet's lanes searches one subtree of a voxel's BVH, with
//! position `4 * r + c` of its vectors the group's r-th lane against child
//! c of a node, or against triangle c of a leaf. `group` (AVX-512, one
//! vector) and `group_avx2` (one or two vectors) say how a node's children
//! and a leaf's triangles are tested ([`GroupTests`]); the stack walk, the
//! packet's record of a blocked lane and the exact redo of a position on a
//! triangle's edge are here.

use super::{edge_lane, prefetch_children, Packet};
use crate::accel::{PreparedVoxel, WideNode};

/// Each node pushes at most 4 entries and the BVH is at most 64 binary
/// levels deep (as `Packet::search`).
const STACK: usize = 4 * 64 + 4;

/// One form's tests of a group's lanes.
pub(super) trait GroupTests<const N: usize> {
    /// Bit `4r + c`: lane r of the group, if in `lanes` (bit r), enters
    /// child c of `node` (slots past the last child never).
    ///
    /// # Safety
    /// The CPU must have what the form needs.
    unsafe fn children(&self, node: &WideNode, lanes: u32) -> u32;

    /// The group's lanes `lanes` against the `count` (1-4) triangles of a
    /// leaf of `vox` from `first`: blocks the packet's lanes they block
    /// ([`block_lanes`]); the group's bits of those lanes.
    ///
    /// # Safety
    /// As [`Self::children`].
    unsafe fn leaf(
        &self,
        p: &mut Packet<N>,
        vox: &PreparedVoxel,
        first: u32,
        count: u32,
        lanes: u32,
    ) -> u32;

    /// The group's lanes (bit r) of bits `4r + c` of `hit`.
    ///
    /// # Safety
    /// As [`Self::children`].
    #[inline(always)]
    unsafe fn child_lanes(hit: u32, c: usize) -> u32 {
        column(hit, c)
    }
}

/// Bits `c`, `4 + c`, `8 + c` and `12 + c` of `hit` as bits 0 to 3.
#[inline(always)]
fn column(hit: u32, c: usize) -> u32 {
    // Times 2^9 + 2^6 + 2^3 + 1, bits 0, 4, 8 and 12 land on bits 9 to 12
    // in order and every other product bit elsewhere, with no carries.
    ((((hit >> c) & 0x1111) * 0x249) >> 9) & 0xF
}

/// The packet's lanes of `group` (a bit each, one to four) in order, the
/// group's lane r at index r; indices past the last repeat the first.
#[inline(always)]
pub(super) fn lane_order(group: u32) -> [usize; 4] {
    let mut lane_of = [group.trailing_zeros() as usize; 4];
    let mut g = group;
    for slot in lane_of.iter_mut().take(group.count_ones() as usize) {
        *slot = g.trailing_zeros() as usize;
        g &= g - 1;
    }
    lane_of
}

/// Searches the subtree below `root` (a child slot of a node of `vox`,
/// `WideNode::child`, or 0 for the voxel's root) for the group's `count`
/// lanes with `tests`, until every lane is blocked or nothing is left.
///
/// # Safety
/// As [`GroupTests::children`].
#[inline(always)]
pub(super) unsafe fn walk<const N: usize, G: GroupTests<N>>(
    p: &mut Packet<N>,
    tests: &G,
    vox: &PreparedVoxel,
    count: u32,
    root: u32,
) {
    // Bit r: the group's r-th lane is not blocked yet.
    let mut alive = (1u32 << count) - 1;
    let mut stack = [std::mem::MaybeUninit::<(u32, u32)>::uninit(); STACK];
    stack[0].write((root, alive));
    let mut top = 1usize;
    while top > 0 {
        top -= 1;
        // SAFETY: slots below `top` were all written.
        let (entry, entered) = stack[top].assume_init();
        // Lanes blocked since the entry was pushed need nothing below it.
        let lanes = entered & alive;
        if lanes == 0 {
            continue;
        }
        let kind = entry >> WideNode::KIND_SHIFT;
        let index = entry & WideNode::INDEX_MASK;
        if kind != 0 {
            alive &= !tests.leaf(p, vox, index, kind, lanes);
            if alive == 0 {
                return;
            }
            continue;
        }
        let node = &vox.nodes[index as usize];
        prefetch_children::<N>(vox, node);
        let hit = tests.children(node, lanes);
        // Stored order, the last child on top (as `Packet::any_children`
        // does for shadow packets). Every slot is written and kept where some
        // lane enters it: which children a group's rays enter is data no
        // branch predictor learns (`scripts/bench-kernel`).
        for c in 0..4 {
            let child_lanes = G::child_lanes(hit, c);
            stack[top].write((node.child[c], child_lanes));
            top += (child_lanes != 0) as usize;
        }
    }
}

/// Blocks each lane of the group that a triangle of the leaf from `first`
/// blocks: bit `4r + j` of `take` is lane `lane_of[r]` against triangle
/// `first + j`; the packet keeps the first in the leaf's order, as its own
/// loop does (and, like it, no barycentrics). The group's bits of the
/// lanes blocked.
#[inline(always)]
pub(super) fn block_lanes<const N: usize>(
    p: &mut Packet<N>,
    vox: &PreparedVoxel,
    first: usize,
    lane_of: &[usize; 4],
    take: u32,
) -> u32 {
    let mut blocked = 0u32;
    for (r, &lane) in lane_of.iter().enumerate() {
        let nibble = (take >> (4 * r)) & 0xF;
        if nibble == 0 {
            continue;
        }
        let j = nibble.trailing_zeros() as usize;
        p.t[lane] = f32::NEG_INFINITY;
        p.id[lane] = vox.ids[first + j];
        p.voxel[lane] = vox.id;
        p.tri[lane] = (first + j) as u32;
        blocked |= 1 << r;
    }
    blocked
}

/// The reference's double-precision redo ([`edge_lane`]) at each position
/// of `edge`: `corners[corner][slot]` are the corners' components on the
/// shear's axes relative to each position's origin, `shear` its factors;
/// `u`, `v`, `w`, `t` and `det` are replaced there.
#[inline(never)]
pub(super) fn redo_edges<const L: usize>(
    edge: u32,
    corners: &[[[f32; L]; 3]; 3],
    shear: [&[f32; L]; 3],
    [u, v, w, t, det]: [&mut [f32; L]; 5],
) {
    let mut e = edge;
    while e != 0 {
        let i = e.trailing_zeros() as usize;
        e &= e - 1;
        let c = [0, 1, 2].map(|corner| [0, 1, 2].map(|slot| corners[corner][slot][i]));
        (u[i], v[i], w[i], t[i]) = edge_lane(c, (shear[0][i], shear[1][i], shear[2][i]));
        det[i] = u[i] + v[i] + w[i];
    }
}

#[cfg(test)]
mod tests {
    use super::column;

    #[test]
    fn column_picks_one_bit_of_each_nibble() {
        for hit in 0..=0xFFFFu32 {
            for c in 0..4 {
                let by_bit = (0..4).fold(0, |m, r| m | (((hit >> (4 * r + c)) & 1) << r));
                assert_eq!(
                    column(hit | 0xABCD_0000, c),
                    by_bit,
                    "hit {hit:#x}, child {c}"
                );
            }
        }
    }
}
