//! Where a tile's packets write their pixels: a rectangle of an image's
//! planes (depth, primitive ids, colors), written where it lies.
//!
//! A frame rendered on several threads is handed out a tile at a time by a
//! [`TileQueue`]: each tile is claimed once, so every thread writes its
//! tiles straight into the frame, with no tile buffers to fill, copy and
//! merge under a lock. The raw pointers this takes live here alone.

use crate::tile::Rect;
use std::marker::PhantomData;
use std::sync::atomic::{AtomicUsize, Ordering};

/// One plane of a rectangle of pixels, `stride` pixels a row in the image
/// that holds it; borrowed as `&mut` would be, but only the rectangle, so
/// that tiles side by side in the same rows are written at once.
pub(crate) struct Plane<'a, T> {
    /// The rectangle's top left pixel.
    first: *mut T,
    stride: usize,
    width: u32,
    height: u32,
    _image: PhantomData<&'a mut [T]>,
}

// SAFETY: a plane is the only way to its rectangle while it lives, as a
// `&mut [T]` is to its elements.
unsafe impl<T: Send> Send for Plane<'_, T> {}

impl<'a, T: Copy> Plane<'a, T> {
    /// All of `pixels`, `width` pixels a row; `None` unless that is whole
    /// rows.
    pub fn whole(pixels: &'a mut [T], width: u32) -> Option<Self> {
        let height = match width {
            0 => 0,
            _ if !pixels.len().is_multiple_of(width as usize) => return None,
            _ => u32::try_from(pixels.len() / width as usize).ok()?,
        };
        Some(Plane {
            first: pixels.as_mut_ptr(),
            stride: width as usize,
            width,
            height,
            _image: PhantomData,
        })
    }

    /// No pixels: where nobody asked for that plane.
    pub fn empty() -> Self {
        Plane {
            first: std::ptr::NonNull::dangling().as_ptr(),
            stride: 0,
            width: 0,
            height: 0,
            _image: PhantomData,
        }
    }

    /// Writes pixel (`x`, `y`) of the rectangle. Panics outside it.
    #[inline(always)]
    pub fn set(&mut self, x: u32, y: u32, value: T) {
        assert!(
            x < self.width && y < self.height,
            "pixel outside the region"
        );
        // SAFETY: inside the rectangle (just checked), which this plane
        // alone reaches while it lives.
        unsafe {
            self.first
                .add(y as usize * self.stride + x as usize)
                .write(value)
        }
    }

    /// Writes `values` to the rectangle's row `y` from pixel `x` on.
    /// Panics where they do not fit in it.
    #[inline(always)]
    pub fn write_row(&mut self, x: u32, y: u32, values: &[T]) {
        assert!(
            y < self.height && x as usize + values.len() <= self.width as usize,
            "row outside the region"
        );
        // SAFETY: as in `set`; `values` is not in the image, which this
        // plane borrows mutably.
        unsafe {
            let at = self.first.add(y as usize * self.stride + x as usize);
            std::ptr::copy_nonoverlapping(values.as_ptr(), at, values.len());
        }
    }
}

/// The planes packets write: depth and primitive ids always, colors where
/// asked for (otherwise empty).
pub(crate) struct Region<'a> {
    pub depth: Plane<'a, f32>,
    pub primid: Plane<'a, u32>,
    pub rgba: Plane<'a, [u8; 4]>,
}

/// A frame's planes, handed out one [`TILE`](crate::render::TILE)-sized
/// tile at a time, in rows: each tile is claimed once, so the threads
/// that claim them write their tiles in place at the same time.
pub(crate) struct TileQueue<'a> {
    depth: *mut f32,
    primid: *mut u32,
    /// Null where the frame has no colors.
    rgba: *mut [u8; 4],
    width: u32,
    height: u32,
    tile: u32,
    tiles_x: u32,
    tiles: usize,
    next: AtomicUsize,
    _frame: PhantomData<&'a mut [u8]>,
}

// SAFETY: the pointers are only used through the regions `claim` hands
// out, no two of which overlap.
unsafe impl Sync for TileQueue<'_> {}

impl<'a> TileQueue<'a> {
    /// The tiles of a `width`×`height` frame whose planes are `depth`,
    /// `primid` and `rgba` (`width` pixels a row; `rgba` may be empty).
    /// Panics where a plane has another size: a bug of the caller.
    pub fn new(
        width: u32,
        height: u32,
        tile: u32,
        depth: &'a mut [f32],
        primid: &'a mut [u32],
        rgba: &'a mut [[u8; 4]],
    ) -> Self {
        let pixels = width as usize * height as usize;
        assert!(tile > 0, "tiles of no pixels");
        assert_eq!(depth.len(), pixels, "depth plane of another size");
        assert_eq!(primid.len(), pixels, "id plane of another size");
        assert!(
            rgba.is_empty() || rgba.len() == pixels,
            "color plane of another size"
        );
        let tiles_x = width.div_ceil(tile);
        TileQueue {
            depth: depth.as_mut_ptr(),
            primid: primid.as_mut_ptr(),
            rgba: if rgba.is_empty() {
                std::ptr::null_mut()
            } else {
                rgba.as_mut_ptr()
            },
            width,
            height,
            tile,
            tiles_x,
            tiles: tiles_x as usize * height.div_ceil(tile) as usize,
            next: AtomicUsize::new(0),
            _frame: PhantomData,
        }
    }

    /// The next tile nobody has claimed, and its pixels; `None` once every
    /// tile is claimed or [`Self::stop`] was called.
    pub fn claim(&self) -> Option<(Rect, Region<'_>)> {
        let k = self.next.fetch_add(1, Ordering::Relaxed);
        if k >= self.tiles {
            return None;
        }
        let x0 = (k % self.tiles_x as usize) as u32 * self.tile;
        let y0 = (k / self.tiles_x as usize) as u32 * self.tile;
        let rect = Rect {
            x0,
            y0,
            width: self.tile.min(self.width - x0),
            height: self.tile.min(self.height - y0),
        };
        let first = y0 as usize * self.width as usize + x0 as usize;
        // SAFETY: the rect is clipped to the frame, and tile `k` is handed
        // out only this once (`fetch_add`), so no other region reaches its
        // pixels.
        let region = unsafe {
            Region {
                depth: self.plane(self.depth, first, rect),
                primid: self.plane(self.primid, first, rect),
                rgba: if self.rgba.is_null() {
                    Plane::empty()
                } else {
                    self.plane(self.rgba, first, rect)
                },
            }
        };
        Some((rect, region))
    }

    /// The rectangle `rect` of a plane of the frame, from its pixel
    /// `first` on.
    ///
    /// # Safety
    ///
    /// `plane` is one of the frame's planes, `rect` lies inside the frame,
    /// `first` is its top left pixel, and nothing else reaches its pixels
    /// while the plane returned lives.
    unsafe fn plane<T>(&self, plane: *mut T, first: usize, rect: Rect) -> Plane<'_, T> {
        Plane {
            // SAFETY: inside the plane, as the caller promises.
            first: unsafe { plane.add(first) },
            stride: self.width as usize,
            width: rect.width,
            height: rect.height,
            _image: PhantomData,
        }
    }

    /// Hands out no more tiles.
    pub fn stop(&self) {
        self.next.fetch_max(self.tiles, Ordering::Relaxed);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every pixel of an awkwardly sized frame is in exactly one claimed
    /// tile, and each tile's writes land on its own pixels.
    #[test]
    fn claimed_tiles_cover_the_frame_once() {
        for (w, h, tile) in [(70, 33, 32), (32, 32, 32), (1, 5, 4), (9, 1, 4)] {
            let n = (w * h) as usize;
            let (mut depth, mut primid, mut rgba) = (vec![0.0; n], vec![0; n], vec![[0; 4]; n]);
            let queue = TileQueue::new(w, h, tile, &mut depth, &mut primid, &mut rgba);
            let mut k = 0u32;
            while let Some((rect, mut region)) = queue.claim() {
                k += 1;
                for y in 0..rect.height {
                    for x in 0..rect.width {
                        region.depth.set(x, y, 1.0);
                        region.rgba.set(x, y, [k as u8; 4]);
                    }
                    let ids: Vec<u32> = (0..rect.width)
                        .map(|x| (y + rect.y0) * w + x + rect.x0)
                        .collect();
                    region.primid.write_row(0, y, &ids);
                }
            }
            assert!(queue.claim().is_none());
            assert!(
                depth.iter().all(|&d| d == 1.0),
                "{w}x{h}: a pixel written twice or never"
            );
            assert!(
                primid.iter().enumerate().all(|(i, &id)| id == i as u32),
                "{w}x{h}"
            );
            assert_eq!(rgba[0], [1; 4]);
            assert_eq!(k, w.div_ceil(tile) * h.div_ceil(tile));
        }
    }

    #[test]
    fn a_stopped_queue_hands_out_nothing() {
        let (mut depth, mut primid) = (vec![0.0; 64], vec![0; 64]);
        let queue = TileQueue::new(8, 8, 4, &mut depth, &mut primid, &mut []);
        assert!(queue.claim().is_some());
        queue.stop();
        assert!(queue.claim().is_none());
    }

    #[test]
    #[should_panic(expected = "pixel outside the region")]
    fn a_write_outside_the_tile_panics() {
        let (mut depth, mut primid) = (vec![0.0; 64], vec![0; 64]);
        let queue = TileQueue::new(8, 8, 4, &mut depth, &mut primid, &mut []);
        let (_, mut region) = queue.claim().expect("a tile");
        region.depth.set(4, 0, 1.0);
    }

    #[test]
    fn whole_takes_only_whole_rows() {
        let mut pixels = [0u32; 12];
        assert!(Plane::whole(&mut pixels, 5).is_none());
        let mut plane = Plane::whole(&mut pixels, 4).expect("three rows");
        plane.write_row(1, 2, &[7, 8, 9]);
        assert_eq!(pixels[8..], [0, 7, 8, 9]);
    }
}
