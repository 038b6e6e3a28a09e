//! How a frame is cut into tiles: squares of `tile_size` pixels, row-major,
//! the last column and row smaller when the image is not a multiple.

use dray_protocol::TileRect;

/// The tiles of a `width` × `height` image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct TileGrid {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Tile side, pixels (at least 1).
    pub tile_size: u32,
    /// Tiles per row.
    pub cols: u32,
    /// Tile rows.
    pub rows: u32,
}

impl TileGrid {
    /// The grid of an image; a `tile_size` of 0 is taken as 1.
    pub fn new(width: u32, height: u32, tile_size: u32) -> TileGrid {
        let tile_size = tile_size.max(1);
        TileGrid {
            width,
            height,
            tile_size,
            cols: width.div_ceil(tile_size),
            rows: height.div_ceil(tile_size),
        }
    }

    /// Number of tiles.
    pub fn count(&self) -> usize {
        self.cols as usize * self.rows as usize
    }

    /// Tile `i`'s rectangle (row-major index, `i < count()`).
    pub fn rect(&self, i: usize) -> TileRect {
        let (cx, cy) = (
            (i % self.cols as usize) as u32,
            (i / self.cols as usize) as u32,
        );
        let (x, y) = (cx * self.tile_size, cy * self.tile_size);
        TileRect {
            x,
            y,
            w: self.tile_size.min(self.width - x),
            h: self.tile_size.min(self.height - y),
        }
    }

    /// The index of the tile `r` is exactly, if it is one of this grid's.
    pub fn index_of(&self, r: &TileRect) -> Option<usize> {
        if !r.x.is_multiple_of(self.tile_size) || !r.y.is_multiple_of(self.tile_size) {
            return None;
        }
        let (cx, cy) = (r.x / self.tile_size, r.y / self.tile_size);
        if cx >= self.cols || cy >= self.rows {
            return None;
        }
        let i = cy as usize * self.cols as usize + cx as usize;
        (self.rect(i) == *r).then_some(i)
    }

    /// The tiles of the aligned block of `side` × `side` tiles that holds
    /// tile `i`, clipped to the grid, row by row (`i` among them). Blocks
    /// are aligned on the grid's middle column and middle row, not on its
    /// corner, so that none straddles the lines through the image's centre
    /// where the scheduler's sectors meet (the left and right halves with
    /// two clients). Aligned on the corner, the blocks of 4 × 4 down the
    /// middle of a 640-pixel image went out as blocks of 2 × 2.
    pub fn block_of(&self, i: usize, side: u32) -> Vec<usize> {
        let side = i64::from(side.max(1));
        let cols = self.cols as usize;
        // First tile of the block along an axis of `n` tiles.
        let start = |c: usize, n: u32| {
            let offset = i64::from(n / 2) % side;
            offset + (c as i64 - offset).div_euclid(side) * side
        };
        let (bx, by) = (start(i % cols, self.cols), start(i / cols, self.rows));
        let mut tiles = Vec::new();
        for y in by.max(0)..(by + side).min(i64::from(self.rows)) {
            for x in bx.max(0)..(bx + side).min(i64::from(self.cols)) {
                tiles.push(y as usize * cols + x as usize);
            }
        }
        tiles
    }

    /// The rectangle that the tiles `first` to `last` (indices, `last`
    /// right of and below `first`) span together.
    pub fn span(&self, first: usize, last: usize) -> TileRect {
        let (a, b) = (self.rect(first), self.rect(last));
        TileRect {
            x: a.x,
            y: a.y,
            w: b.x + b.w - a.x,
            h: b.y + b.h - a.y,
        }
    }

    /// The tiles `r` covers, row by row, if it is exactly a rectangle of
    /// whole tiles of this grid (one tile, or a block of them).
    pub fn tiles_of(&self, r: &TileRect) -> Option<Vec<usize>> {
        if r.w == 0 || r.h == 0 {
            return None;
        }
        let first = self.index_of(&TileRect {
            x: r.x,
            y: r.y,
            w: self.tile_size.min(self.width.saturating_sub(r.x)),
            h: self.tile_size.min(self.height.saturating_sub(r.y)),
        })?;
        let (x1, y1) = (r.x.checked_add(r.w)?, r.y.checked_add(r.h)?);
        let last = self.tile_at(x1 - 1, y1 - 1)?;
        (self.span(first, last) == *r).then(|| {
            let (c0, r0) = (first % self.cols as usize, first / self.cols as usize);
            let (c1, r1) = (last % self.cols as usize, last / self.cols as usize);
            (r0..=r1)
                .flat_map(|y| (c0..=c1).map(move |x| y * self.cols as usize + x))
                .collect()
        })
    }

    /// Each tile's position along a Hilbert curve generalized to
    /// rectangles: consecutive positions are neighbouring tiles (a
    /// diagonal step at most, where a side is odd), so a run of positions
    /// is a compact region of the image (affinity hands each client such a
    /// region; see the scheduler).
    pub fn curve_ranks(&self) -> Vec<u32> {
        let mut ranks = vec![0; self.count()];
        let mut next = 0u32;
        let (w, h) = (self.cols as i64, self.rows as i64);
        let mut visit = |x: i64, y: i64| {
            ranks[(y * w + x) as usize] = next;
            next += 1;
        };
        if w >= h {
            gilbert(&mut visit, (0, 0), (w, 0), (0, h));
        } else {
            gilbert(&mut visit, (0, 0), (0, h), (w, 0));
        }
        ranks
    }

    /// The index of the tile holding pixel (x, y), if inside the image.
    pub fn tile_at(&self, x: u32, y: u32) -> Option<usize> {
        (x < self.width && y < self.height).then(|| {
            (y / self.tile_size) as usize * self.cols as usize + (x / self.tile_size) as usize
        })
    }
}

/// Visits every cell of the rectangle at `origin` spanned by the major
/// axis `a` and the minor axis `b` (each a vector along x or y) along a
/// generalized Hilbert curve (J. Červený's "gilbert"): split the long side
/// in two when the rectangle is long, else into three parts (the usual
/// Hilbert U), keeping each part's sides even where the curve must turn so
/// that it ends next to where the next part starts.
fn gilbert(
    visit: &mut impl FnMut(i64, i64),
    (x, y): (i64, i64),
    (ax, ay): (i64, i64),
    (bx, by): (i64, i64),
) {
    let w = (ax + ay).abs();
    let h = (bx + by).abs();
    let (dax, day) = (ax.signum(), ay.signum());
    let (dbx, dby) = (bx.signum(), by.signum());
    if h == 1 || w == 1 {
        let (n, dx, dy) = if h == 1 { (w, dax, day) } else { (h, dbx, dby) };
        for i in 0..n {
            visit(x + i * dx, y + i * dy);
        }
        return;
    }
    // Halves rounded towards minus infinity, as the curve's corners need.
    let (mut ax2, mut ay2) = (ax.div_euclid(2), ay.div_euclid(2));
    let (mut bx2, mut by2) = (bx.div_euclid(2), by.div_euclid(2));
    let w2 = (ax2 + ay2).abs();
    let h2 = (bx2 + by2).abs();
    if 2 * w > 3 * h {
        if w2 % 2 == 1 && w > 2 {
            (ax2, ay2) = (ax2 + dax, ay2 + day);
        }
        gilbert(visit, (x, y), (ax2, ay2), (bx, by));
        gilbert(visit, (x + ax2, y + ay2), (ax - ax2, ay - ay2), (bx, by));
    } else {
        if h2 % 2 == 1 && h > 2 {
            (bx2, by2) = (bx2 + dbx, by2 + dby);
        }
        gilbert(visit, (x, y), (bx2, by2), (ax2, ay2));
        gilbert(visit, (x + bx2, y + by2), (ax, ay), (bx - bx2, by - by2));
        gilbert(
            visit,
            (x + (ax - dax) + (bx2 - dbx), y + (ay - day) + (by2 - dby)),
            (-bx2, -by2),
            (-(ax - ax2), -(ay - ay2)),
        );
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn edge_tiles_are_smaller_and_indices_round_trip() {
        let g = TileGrid::new(100, 70, 32);
        assert_eq!((g.cols, g.rows, g.count()), (4, 3, 12));
        assert_eq!(
            g.rect(3),
            TileRect {
                x: 96,
                y: 0,
                w: 4,
                h: 32
            }
        );
        assert_eq!(g.rect(11).h, 6);
        let area: usize = (0..g.count()).map(|i| g.rect(i).area()).sum();
        assert_eq!(area, 100 * 70);
        for i in 0..g.count() {
            assert_eq!(g.index_of(&g.rect(i)), Some(i));
        }
        assert_eq!(
            g.index_of(&TileRect {
                x: 0,
                y: 0,
                w: 16,
                h: 32
            }),
            None
        );
        assert_eq!(g.tile_at(99, 69), Some(11));
        assert_eq!(g.tile_at(100, 0), None);
    }

    #[test]
    fn blocks_are_aligned_clipped_and_their_rects_map_back_to_their_tiles() {
        let g = TileGrid::new(100, 70, 32);
        // 4 × 3 tiles; blocks of 2 × 2 with edges on the middle column (2)
        // and row (1): the first row alone.
        assert_eq!(g.block_of(0, 2), vec![0, 1]);
        assert_eq!(g.block_of(5, 2), vec![4, 5, 8, 9]);
        assert_eq!(g.block_of(11, 2), vec![6, 7, 10, 11]);
        assert_eq!(g.block_of(7, 4), vec![6, 7, 10, 11]);
        assert_eq!(g.block_of(1, 4), vec![0, 1]);
        assert_eq!(g.block_of(6, 1), vec![6]);
        // No block crosses the middle column of a 640 × 480 image.
        let wide = TileGrid::new(640, 480, 32);
        for side in [2, 4, 8] {
            for i in 0..wide.count() {
                let cols: Vec<u32> = wide
                    .block_of(i, side)
                    .iter()
                    .map(|&j| j as u32 % wide.cols)
                    .collect();
                let left = |c: &u32| *c < wide.cols / 2;
                assert!(
                    cols.iter().all(left) || !cols.iter().any(left),
                    "side {side}, tile {i}: {cols:?}"
                );
            }
        }
        for side in [1, 2, 3, 4, 8] {
            for i in 0..g.count() {
                let b = g.block_of(i, side);
                assert!(b.contains(&i));
                let r = g.span(b[0], b[b.len() - 1]);
                let area: usize = b.iter().map(|&j| g.rect(j).area()).sum();
                assert_eq!(r.area(), area, "block {b:?} spans {r:?}");
                assert_eq!(g.tiles_of(&r), Some(b));
            }
        }
        assert_eq!(
            g.span(9, 11),
            TileRect {
                x: 32,
                y: 64,
                w: 68,
                h: 6
            }
        );
        // Rects that are not whole tiles of the grid.
        for (x, y, w, h) in [
            (0, 0, 16, 32),
            (0, 0, 48, 32),
            (16, 0, 32, 32),
            (0, 0, 64, 40),
            (96, 0, 8, 32),
            (0, 64, 32, 7),
            (0, 0, 0, 32),
            (u32::MAX, 0, 32, 32),
            (0, u32::MAX - 3, 32, 32),
        ] {
            assert_eq!(
                g.tiles_of(&TileRect { x, y, w, h }),
                None,
                "{x} {y} {w} {h}"
            );
        }
    }

    #[test]
    fn curve_ranks_are_a_permutation_of_screen_neighbours() {
        for (w, h, t) in [
            (640, 480, 32),
            (640, 480, 64),
            (256, 256, 32),
            (100, 37, 16),
            (37, 100, 16),
            (1, 1, 32),
            (300, 16, 16),
        ] {
            let g = TileGrid::new(w, h, t);
            let ranks = g.curve_ranks();
            let mut sorted = ranks.clone();
            sorted.sort_unstable();
            assert_eq!(sorted, (0..g.count() as u32).collect::<Vec<_>>());
            let mut by_rank = vec![0; g.count()];
            for (i, &r) in ranks.iter().enumerate() {
                by_rank[r as usize] = i;
            }
            // Each step is to a neighbour, diagonally at most.
            for k in by_rank.windows(2) {
                let (a, b) = (g.rect(k[0]), g.rect(k[1]));
                let (dx, dy) = (a.x.abs_diff(b.x) / t, a.y.abs_diff(b.y) / t);
                assert!(
                    dx <= 1 && dy <= 1 && dx + dy >= 1,
                    "{w}x{h}: {a:?} to {b:?}"
                );
            }
        }
    }
}
