//! Sector affinity: while the camera travels, what it shows streams along
//! lines through the focus of expansion, the point the motion heads for
//! as the image shows it. Walking forward, content comes into view near it
//! and flows outward to the image's edges (walking back, the reverse;
//! sideways, across the image along nearly parallel lines). Cut into one
//! angular sector per client around a point near the focus, the image
//! keeps each piece of content in one client's sector for as long as it
//! stays in view.
//! Compact regions, even when they follow the content by reprojection,
//! hand it on from region to region as it crosses them, and every client
//! on its way fetches it.
//!
//! The focus comes from the content itself: where the lines cross along
//! which the previous frame's hit samples move into the new camera (as
//! reprojection finds them). While it lies in view the scheduler cuts the
//! sectors around the image's centre, which stays put as the focus
//! drifts (see [`super::affinity`]).

use crate::scheduler::tiles::TileGrid;
use dray_trace::camera::CameraBasis;
use glam::Vec3;

/// Each tile's client by sectors, between a frame seen through `then` and
/// one seen through `now` (on `grid`): when the image streams from a
/// point in view (by where the earlier frame's `hits` land in each), one
/// sector around the image's centre per client that had a tile before
/// (`before`, per tile; clients in their order), turned to keep the most
/// tiles with them. `None` when the content shifts as a whole or does not
/// move (reprojection then decides), or nobody had a tile.
///
/// Around the centre, not around that point: the point drifts across the
/// image as the camera turns while it walks, and sectors that stay put
/// keep their content (fewer voxels fetched than around the point or by
/// reprojected regions: `experiments/affinity-inside.toml`).
pub fn assign<N: Ord + Clone>(
    grid: &TileGrid,
    then: &CameraBasis,
    now: &CameraBasis,
    hits: impl IntoIterator<Item = Vec3>,
    before: &[Option<N>],
) -> Option<Vec<N>> {
    // Positions scaled to `now`'s image when the size changed.
    let (sx, sy) = (now.width / then.width, now.height / then.height);
    let moves = hits.into_iter().filter_map(|p| {
        let (x0, y0) = then.project(p)?;
        Some(((x0 * sx, y0 * sy), now.project(p)?))
    });
    let (x, y) = flow_focus(moves)?;
    if !(0.0..=now.width).contains(&x) || !(0.0..=now.height).contains(&y) {
        return None;
    }
    let mut clients: Vec<&N> = before.iter().flatten().collect();
    clients.sort();
    clients.dedup();
    if clients.is_empty() {
        return None;
    }
    let sector = sectors(grid, (now.width / 2.0, now.height / 2.0), clients.len());
    let before: Vec<Option<&N>> = before.iter().map(|b| b.as_ref()).collect();
    let owners = owners(&sector, &clients, &before);
    Some(owners.into_iter().map(|n| (*n).clone()).collect())
}

/// The point the image streams from between two frames: the least-squares
/// crossing of the lines along which `moves` (each a point's pixel position
/// in the earlier frame and in the later one) carry the content. It is the
/// focus of expansion when the camera travels, and the image's centre when
/// it zooms. `None` where the lines are nearly parallel (the camera turns
/// in place, or slides sideways: the content shifts as a whole and crosses
/// any partition) or where nothing moved.
fn flow_focus(moves: impl IntoIterator<Item = ((f32, f32), (f32, f32))>) -> Option<(f32, f32)> {
    // Sum over the lines of n nᵀ and n (n · p), n the line's unit normal,
    // each weighted by how far its point moved (a point that hardly moves
    // has no reliable direction).
    let (mut a, mut b, mut c, mut bx, mut by) = (0.0f64, 0.0f64, 0.0f64, 0.0f64, 0.0f64);
    for ((x0, y0), (x1, y1)) in moves {
        let (dx, dy) = (f64::from(x1 - x0), f64::from(y1 - y0));
        let len = (dx * dx + dy * dy).sqrt();
        if !len.is_finite() || len <= 1e-3 {
            continue;
        }
        let (nx, ny) = (-dy / len, dx / len);
        let w = len;
        let d = nx * f64::from(x0) + ny * f64::from(y0);
        a += w * nx * nx;
        b += w * nx * ny;
        c += w * ny * ny;
        bx += w * nx * d;
        by += w * ny * d;
    }
    // The smaller eigenvalue of [[a, b], [b, c]] against the larger: how
    // far from parallel the lines are.
    let tr = a + c;
    let det = a * c - b * b;
    let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
    let (lo, hi) = (tr / 2.0 - disc, tr / 2.0 + disc);
    if !hi.is_finite() || hi <= 0.0 || lo < 0.05 * hi {
        return None;
    }
    let fx = (c * bx - b * by) / det;
    let fy = (a * by - b * bx) / det;
    (fx.is_finite() && fy.is_finite()).then_some((fx as f32, fy as f32))
}

/// Per tile of `grid`, its sector (`0..k`) around `focus`: the tiles in
/// order of the angle of their centres around it, clockwise from straight
/// up, cut into `k` runs of as many tiles each as can be. Two sectors are
/// the left and right halves, as the image's left and right show different
/// parts of the model, while its top and bottom share the distant ones
/// near the horizon (`experiments/affinity-inside.toml` and `latency-hiding.toml`).
fn sectors(grid: &TileGrid, focus: (f32, f32), k: usize) -> Vec<usize> {
    let n = grid.count();
    let k = k.max(1);
    let mut order: Vec<(f32, usize)> = (0..n)
        .map(|i| {
            let r = grid.rect(i);
            let dx = r.x as f32 + r.w as f32 / 2.0 - focus.0;
            let dy = r.y as f32 + r.h as f32 / 2.0 - focus.1;
            // Angles from straight up, clockwise: two sectors are the
            // left and right halves.
            (dx.atan2(-dy).rem_euclid(std::f32::consts::TAU), i)
        })
        .collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
    let mut sector = vec![0; n];
    for (rank, &(_, i)) in order.iter().enumerate() {
        sector[i] = rank * k / n.max(1);
    }
    sector
}

/// Which of `clients` (sorted, no repeats) gets each sector of `sectors`
/// (tile by tile): the clients in their order round the sectors, turned
/// so that the most tiles stay with the client that had them before
/// (`before`, per tile), and the sectors keep their clients while the
/// focus drifts. Each tile votes for the one turn that keeps it: one pass
/// over the tiles, not one per turn (with a client per sector, that would
/// be clients × tiles).
fn owners<'c, N: Ord>(sectors: &[usize], clients: &'c [N], before: &[Option<N>]) -> Vec<&'c N> {
    debug_assert!(clients.windows(2).all(|w| w[0] < w[1]), "clients sorted");
    let k = clients.len();
    let mut kept = vec![0usize; k];
    for (&s, b) in sectors.iter().zip(before) {
        if let Some(j) = b.as_ref().and_then(|b| clients.binary_search(b).ok()) {
            // clients[(s + turn) % k] == clients[j]
            kept[(j + k - s % k) % k] += 1;
        }
    }
    let turn = (0..k)
        .max_by_key(|&t| (kept[t], std::cmp::Reverse(t)))
        .unwrap_or(0);
    sectors.iter().map(|&s| &clients[(s + turn) % k]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_focus_is_where_the_image_streams_from() {
        // Content streaming out of (400, 200), as walking towards it.
        let pts = [
            (100.0, 100.0),
            (600.0, 50.0),
            (500.0, 450.0),
            (50.0, 400.0),
            (300.0, 300.0),
        ];
        let out = pts.map(|(x, y): (f32, f32)| {
            (
                (x, y),
                (400.0 + (x - 400.0) * 1.1, 200.0 + (y - 200.0) * 1.1),
            )
        });
        let (x, y) = flow_focus(out).unwrap();
        assert!(
            (x - 400.0).abs() < 0.1 && (y - 200.0).abs() < 0.1,
            "{x} {y}"
        );
        // Streaming in (walking back): the same point.
        let back = out.map(|(p, q)| (q, p));
        let (x, y) = flow_focus(back).unwrap();
        assert!(
            (x - 400.0).abs() < 0.1 && (y - 200.0).abs() < 0.1,
            "{x} {y}"
        );
        // Everything shifting left (turning in place), or nothing moving.
        let shift = pts.map(|(x, y)| ((x, y), (x - 20.0, y + 0.5)));
        assert_eq!(flow_focus(shift), None);
        assert_eq!(flow_focus(pts.map(|p| (p, p))), None);
    }

    #[test]
    fn sectors_are_even_and_run_outward_from_the_focus() {
        let grid = TileGrid::new(640, 480, 32);
        for k in [1, 2, 3, 4, 7] {
            let s = sectors(&grid, (320.0, 240.0), k);
            let mut sizes = vec![0; k];
            for &x in &s {
                sizes[x] += 1;
            }
            let (lo, hi) = (sizes.iter().min().unwrap(), sizes.iter().max().unwrap());
            assert!(hi - lo <= 1, "k {k}: {sizes:?}");
        }
        // Tiles along one line out of the focus share their sector.
        let s = sectors(&grid, (320.0, 240.0), 4);
        let along: Vec<usize> = (0..9)
            .map(|j| s[grid.tile_at(336 + 32 * j, 256 + 24 * j).unwrap()])
            .collect();
        assert!(along.iter().all(|&x| x == along[0]), "{along:?}");
    }

    #[test]
    fn the_turn_is_the_one_that_keeps_most_tiles() {
        // Against trying every turn in full, on scrambled inputs.
        let mut x = 11u32;
        let mut next = |m: u32| {
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            (x >> 8) % m
        };
        for _ in 0..200 {
            let k = 1 + next(9) as usize;
            let clients: Vec<u32> = (0..k as u32).map(|c| 3 * c + 1).collect();
            let n = 1 + next(60) as usize;
            let sectors: Vec<usize> = (0..n).map(|_| next(k as u32) as usize).collect();
            let before: Vec<Option<u32>> = (0..n)
                .map(|_| (next(4) > 0).then(|| 3 * next(k as u32 + 2) + 1))
                .collect();
            let kept = |turn: usize| {
                sectors
                    .iter()
                    .zip(&before)
                    .filter(|(&s, b)| b.as_ref() == Some(&clients[(s + turn) % k]))
                    .count()
            };
            let turn = (0..k)
                .max_by_key(|&t| (kept(t), std::cmp::Reverse(t)))
                .unwrap();
            let want: Vec<&u32> = sectors.iter().map(|&s| &clients[(s + turn) % k]).collect();
            assert_eq!(owners(&sectors, &clients, &before), want);
        }
    }

    #[test]
    fn sectors_keep_their_clients() {
        let grid = TileGrid::new(640, 480, 32);
        let clients = ["a", "b", "c", "d"];
        let first = sectors(&grid, (320.0, 240.0), 4);
        let was: Vec<Option<&str>> = first.iter().map(|&s| Some(clients[(s + 2) % 4])).collect();
        // The same sectors go to the same clients, whatever their order.
        let again = owners(&first, &clients, &was);
        assert!(again.iter().zip(&was).all(|(n, w)| Some(**n) == *w));
        // The centre moves a little: most tiles keep their client.
        let next = sectors(&grid, (330.0, 250.0), 4);
        let now = owners(&next, &clients, &was);
        let kept = now
            .iter()
            .zip(&was)
            .filter(|(n, w)| Some(***n) == **w)
            .count();
        assert!(kept * 5 > grid.count() * 4, "{kept} of {}", grid.count());
    }
}
