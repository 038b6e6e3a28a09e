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

    /// The index of the tile holding pixel (x, y), if inside the image.
    pub fn tile_at(&self, x: u32, y: u32) -> Option<usize> {
        (x < self.width && y < self.height).then(|| {
            (y / self.tile_size) as usize * self.cols as usize + (x / self.tile_size) as usize
        })
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
}
