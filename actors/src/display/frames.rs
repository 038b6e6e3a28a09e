//! Frame assembly: tiles into images, frames completed in order.
//!
//! Only the frames whose camera was sent and that are not yet handed out
//! are buffered (at most `frames_ahead` of them), so memory is bounded by
//! `(frames_ahead + MAX_SPARE_IMAGES) × width × height` pixels (of the
//! largest size asked for) whatever the peers send (a few images of frames
//! shown are kept to assemble later frames in). Each frame has its own
//! size: an interactive viewer changes the resolution between frames.

use dray_protocol::{FrameStats, TileDone};
use std::collections::BTreeMap;
use tokio::time::Instant;

/// One frame, fully assembled.
#[derive(Clone, Debug)]
pub struct FrameImage {
    /// Frame number.
    pub frame: u64,
    /// Its size in pixels.
    pub width: u32,
    pub height: u32,
    /// RGBA8 pixels, rows top to bottom.
    pub rgba: Vec<[u8; 4]>,
    /// Per-pixel hit distance (+inf on a miss) when the tiles carried it.
    pub depth: Option<Vec<f32>>,
    /// Per-pixel original triangle index (0xFFFFFFFF on a miss) when the
    /// tiles carried it.
    pub primid: Option<Vec<u32>>,
}

/// Why a tile was not used.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum TileRejected {
    /// The frame is not outstanding (never asked for, or already shown).
    UnknownFrame(u64),
    /// The rectangle is empty or leaves the image.
    OutsideImage(String),
    /// Pixel, depth or id counts disagree with the rectangle.
    BadSize(String),
}

impl std::fmt::Display for TileRejected {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            TileRejected::UnknownFrame(n) => write!(f, "frame {n} is not outstanding"),
            TileRejected::OutsideImage(m) | TileRejected::BadSize(m) => f.write_str(m),
        }
    }
}

/// Which pixels of a frame arrived: one bit each. At 640×480 that is
/// 38 KB, which stays in the caches and on the heap; a byte per pixel
/// (300 KB, fresh pages every frame) would keep the display waiting on
/// memory in its check of each tile row.
#[derive(Debug)]
struct Coverage(Vec<u64>);

impl Coverage {
    fn new(pixels: usize) -> Coverage {
        Coverage(vec![0; pixels.div_ceil(64)])
    }

    /// The words of pixels `start..start + len` with the bits in range.
    fn words(start: usize, len: usize) -> impl Iterator<Item = (usize, u64)> {
        let end = start + len;
        (start / 64..end.div_ceil(64)).map(move |w| {
            let lo = start.max(w * 64) - w * 64;
            let hi = end.min(w * 64 + 64) - w * 64;
            let mask = if hi - lo == 64 {
                u64::MAX
            } else {
                ((1u64 << (hi - lo)) - 1) << lo
            };
            (w, mask)
        })
    }

    fn any(&self, start: usize, len: usize) -> bool {
        Self::words(start, len).any(|(w, m)| self.0[w] & m != 0)
    }

    fn set_all(&mut self, start: usize, len: usize) {
        for (w, m) in Self::words(start, len) {
            self.0[w] |= m;
        }
    }

    fn get(&self, i: usize) -> bool {
        self.0[i / 64] >> (i % 64) & 1 != 0
    }

    fn set(&mut self, i: usize) {
        self.0[i / 64] |= 1 << (i % 64);
    }
}

/// Color of a pixel never received.
const MISSING: [u8; 4] = [0, 0, 0, 255];

/// Images kept for reuse: about the frames in flight.
const MAX_SPARE_IMAGES: usize = 4;

/// A frame being assembled.
#[derive(Debug)]
pub(crate) struct PendingFrame {
    pub frame: u64,
    pub width: u32,
    pub height: u32,
    /// Pixels not covered yet may hold an older frame's (a reused buffer).
    pub rgba: Vec<[u8; 4]>,
    pub depth: Option<Vec<f32>>,
    pub primid: Option<Vec<u32>>,
    covered: Coverage,
    /// Pixels covered so far (each counted once).
    pub covered_count: usize,
    /// The scheduler's report, once it came.
    pub done: Option<FrameStats>,
    /// When the frame had both its report and all its pixels.
    pub completed_at: Option<Instant>,
    /// When the report came.
    pub done_at: Option<Instant>,
}

impl PendingFrame {
    fn new(frame: u64, (width, height): (u32, u32), rgba: Vec<[u8; 4]>) -> PendingFrame {
        let pixels = rgba.len();
        PendingFrame {
            frame,
            width,
            height,
            rgba,
            depth: None,
            primid: None,
            covered: Coverage::new(pixels),
            covered_count: 0,
            done: None,
            completed_at: None,
            done_at: None,
        }
    }

    /// Whether every pixel is in.
    pub fn pixels_complete(&self) -> bool {
        self.covered_count == self.rgba.len()
    }

    fn check_complete(&mut self, now: Instant) {
        if self.completed_at.is_none() && self.done.is_some() && self.pixels_complete() {
            self.completed_at = Some(now);
        }
    }

    fn into_image(self) -> (FrameImage, FrameStats) {
        (
            FrameImage {
                frame: self.frame,
                width: self.width,
                height: self.height,
                rgba: self.rgba,
                depth: self.depth,
                primid: self.primid,
            },
            self.done.unwrap_or_default(),
        )
    }
}

/// A frame handed out in order.
#[derive(Debug)]
pub(crate) struct ReadyFrame {
    pub image: FrameImage,
    pub stats: FrameStats,
    /// When it had its report and all its pixels.
    pub completed_at: Instant,
    /// Pixels never received (only when forced out after a grace time).
    pub missing_pixels: usize,
}

/// The outstanding frames.
#[derive(Debug)]
pub(crate) struct Frames {
    pending: BTreeMap<u64, PendingFrame>,
    /// The next frame to hand out, in order.
    next_out: u64,
    /// Images of frames shown, to assemble the next ones in: a fresh one
    /// every frame is a megabyte of new pages to fault in and clear.
    spare: Vec<Vec<[u8; 4]>>,
    /// Where compressed tiles are decompressed, kept from tile to tile.
    unpacked: Vec<u8>,
}

impl Frames {
    pub fn new() -> Frames {
        Frames {
            pending: BTreeMap::new(),
            next_out: 0,
            spare: Vec::new(),
            unpacked: Vec::new(),
        }
    }

    /// Starts buffering `frame` (its camera was just sent), of `width` ×
    /// `height` pixels.
    pub fn open(&mut self, frame: u64, width: u32, height: u32) {
        if self.pending.contains_key(&frame) {
            return;
        }
        let n = width as usize * height as usize;
        let rgba = match self.spare.iter().position(|s| s.len() == n) {
            Some(i) => self.spare.swap_remove(i),
            None => vec![MISSING; n],
        };
        self.pending
            .insert(frame, PendingFrame::new(frame, (width, height), rgba));
    }

    /// Takes back a shown frame's pixels for a later frame (the oldest
    /// spare goes when there are too many: sizes change rarely).
    pub fn recycle(&mut self, rgba: Vec<[u8; 4]>) {
        if self.spare.len() >= MAX_SPARE_IMAGES {
            self.spare.remove(0);
        }
        self.spare.push(rgba);
    }

    /// Frames opened and not handed out yet.
    pub fn outstanding(&self) -> usize {
        self.pending.len()
    }

    /// The next frame to hand out.
    pub fn next_out(&self) -> u64 {
        self.next_out
    }

    /// The pixels `frame` is being assembled in.
    #[cfg(test)]
    pub fn pending_rgba(&self, frame: u64) -> Option<&[[u8; 4]]> {
        self.pending.get(&frame).map(|f| f.rgba.as_slice())
    }

    /// Puts a tile's pixels in place (first wins per pixel).
    /// Returns how many new pixels it brought.
    pub fn add_tile(&mut self, t: &TileDone, now: Instant) -> Result<usize, TileRejected> {
        let f = self
            .pending
            .get_mut(&t.frame)
            .ok_or(TileRejected::UnknownFrame(t.frame))?;
        let (w, h) = (f.width, f.height);
        let r = t.tile;
        if r.w == 0
            || r.h == 0
            || u64::from(r.x) + u64::from(r.w) > u64::from(w)
            || u64::from(r.y) + u64::from(r.h) > u64::from(h)
        {
            return Err(TileRejected::OutsideImage(format!(
                "tile {}x{} at ({}, {}) is empty or outside the {w}x{h} image",
                r.w, r.h, r.x, r.y
            )));
        }
        let n = r.area();
        let pixels = t
            .pixels
            .decode_into(n, &mut self.unpacked)
            .map_err(|e| TileRejected::BadSize(format!("a {}x{} tile: {e}", r.w, r.h)))?;
        if t.depth.as_ref().is_some_and(|d| d.0.len() != n)
            || t.prim_ids.as_ref().is_some_and(|p| p.0.len() != n)
        {
            return Err(TileRejected::BadSize(format!(
                "depth or id count differs from the {}x{} tile's pixels",
                r.w, r.h
            )));
        }
        let total = w as usize * h as usize;
        if t.depth.is_some() && f.depth.is_none() {
            f.depth = Some(vec![f32::INFINITY; total]);
        }
        if t.prim_ids.is_some() && f.primid.is_none() {
            f.primid = Some(vec![u32::MAX; total]);
        }
        let mut new = 0;
        for row in 0..r.h as usize {
            let y = r.y as usize + row;
            let line = y * w as usize + r.x as usize;
            let cols = r.w as usize;
            if !f.covered.any(line, cols) {
                // A row nobody sent before (nearly always): copied whole.
                let src = row * cols;
                f.covered.set_all(line, cols);
                new += cols;
                pixels.copy_to(src, &mut f.rgba[line..line + cols]);
                if let (Some(d), Some(out)) = (&t.depth, &mut f.depth) {
                    out[line..line + cols].copy_from_slice(&d.0[src..src + cols]);
                }
                if let (Some(ids), Some(out)) = (&t.prim_ids, &mut f.primid) {
                    out[line..line + cols].copy_from_slice(&ids.0[src..src + cols]);
                }
                continue;
            }
            for col in 0..r.w as usize {
                let dst = y * w as usize + r.x as usize + col;
                if f.covered.get(dst) {
                    continue;
                }
                let src = row * r.w as usize + col;
                f.covered.set(dst);
                new += 1;
                pixels.copy_to(src, &mut f.rgba[dst..dst + 1]);
                if let (Some(d), Some(out)) = (&t.depth, &mut f.depth) {
                    out[dst] = d.0[src];
                }
                if let (Some(ids), Some(out)) = (&t.prim_ids, &mut f.primid) {
                    out[dst] = ids.0[src];
                }
            }
        }
        f.covered_count += new;
        f.check_complete(now);
        Ok(new)
    }

    /// Records the scheduler's report for `frame`; false if the frame is
    /// not outstanding (the report is then ignored).
    pub fn frame_done(&mut self, frame: u64, stats: FrameStats, now: Instant) -> bool {
        let Some(f) = self.pending.get_mut(&frame) else {
            return false;
        };
        if f.done.is_none() {
            f.done = Some(stats);
            f.done_at = Some(now);
        }
        f.check_complete(now);
        true
    }

    /// The next frame in order, if it is complete.
    pub fn pop_ready(&mut self) -> Option<ReadyFrame> {
        let f = self.pending.get(&self.next_out)?;
        let completed_at = f.completed_at?;
        let f = self.pending.remove(&self.next_out)?;
        self.next_out += 1;
        let (image, stats) = f.into_image();
        Some(ReadyFrame {
            image,
            stats,
            completed_at,
            missing_pixels: 0,
        })
    }

    /// When the next frame in order got its report but still lacks pixels:
    /// since when.
    pub fn stuck_next(&self) -> Option<Instant> {
        let f = self.pending.get(&self.next_out)?;
        if f.completed_at.is_some() {
            return None;
        }
        f.done_at
    }

    /// Hands out the next frame as it is (missing pixels stay black).
    pub fn force_next(&mut self, now: Instant) -> Option<ReadyFrame> {
        let mut f = self.pending.remove(&self.next_out)?;
        self.next_out += 1;
        let missing = f.rgba.len() - f.covered_count;
        if missing > 0 {
            for i in 0..f.rgba.len() {
                if !f.covered.get(i) {
                    f.rgba[i] = MISSING;
                }
            }
        }
        let completed_at = f.completed_at.unwrap_or(now);
        let (image, stats) = f.into_image();
        Some(ReadyFrame {
            image,
            stats,
            completed_at,
            missing_pixels: missing,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_protocol::{Blob, TilePixels, TileRect, TileStats};

    fn tile(frame: u64, x: u32, y: u32, w: u32, h: u32, v: u8) -> TileDone {
        TileDone {
            frame,
            tile: TileRect { x, y, w, h },
            pixels: TilePixels::Rgba(Blob(vec![v; (w * h * 4) as usize])),
            depth: None,
            prim_ids: None,
            stats: TileStats::default(),
            hits: Default::default(),
        }
    }

    #[test]
    fn in_order_first_wins() {
        let now = Instant::now();
        let mut f = Frames::new();
        f.open(0, 4, 2);
        f.open(1, 4, 2);
        assert_eq!(f.add_tile(&tile(1, 0, 0, 4, 2, 9), now), Ok(8));
        assert!(f.frame_done(1, FrameStats::default(), now));
        assert!(f.pop_ready().is_none(), "frame 1 waits for frame 0");
        assert_eq!(f.add_tile(&tile(0, 0, 0, 2, 2, 1), now), Ok(4));
        assert_eq!(f.add_tile(&tile(0, 0, 0, 2, 2, 7), now), Ok(0));
        assert_eq!(f.add_tile(&tile(0, 2, 0, 2, 2, 2), now), Ok(4));
        assert!(f.pop_ready().is_none(), "no report yet");
        assert!(f.frame_done(0, FrameStats::default(), now));
        let a = f.pop_ready().unwrap();
        assert_eq!(a.image.frame, 0);
        assert_eq!(a.image.rgba[0], [1; 4]);
        assert_eq!(a.image.rgba[3], [2; 4]);
        assert_eq!(f.pop_ready().unwrap().image.frame, 1);
        assert!(matches!(
            f.add_tile(&tile(0, 0, 0, 1, 1, 0), now),
            Err(TileRejected::UnknownFrame(0))
        ));
    }

    #[test]
    fn a_tile_over_part_of_a_row_brings_only_its_new_pixels() {
        let now = Instant::now();
        let mut f = Frames::new();
        f.open(0, 4, 2);
        let mut a = tile(0, 0, 0, 2, 1, 1);
        a.depth = Some(dray_protocol::PackedF32(vec![1.0; 2]));
        a.prim_ids = Some(dray_protocol::PackedU32(vec![10; 2]));
        assert_eq!(f.add_tile(&a, now), Ok(2));
        // Rows 0 (half covered) and 1 (new) of a 3-wide tile at x = 1.
        let mut b = tile(0, 1, 0, 3, 2, 5);
        b.depth = Some(dray_protocol::PackedF32(vec![2.0; 6]));
        b.prim_ids = Some(dray_protocol::PackedU32(vec![20; 6]));
        assert_eq!(f.add_tile(&b, now), Ok(5));
        assert_eq!(f.add_tile(&tile(0, 0, 1, 1, 1, 3), now), Ok(1));
        assert!(f.frame_done(0, FrameStats::default(), now));
        let img = f.pop_ready().unwrap().image;
        let rgba: Vec<u8> = img.rgba.iter().map(|p| p[0]).collect();
        assert_eq!(rgba, [1, 1, 5, 5, 3, 5, 5, 5]);
        assert_eq!(
            img.depth.unwrap(),
            [1.0, 1.0, 2.0, 2.0, f32::INFINITY, 2.0, 2.0, 2.0]
        );
        assert_eq!(img.primid.unwrap(), [10, 10, 20, 20, u32::MAX, 20, 20, 20]);
    }

    #[test]
    fn a_reused_image_shows_none_of_its_old_pixels() {
        let now = Instant::now();
        let mut f = Frames::new();
        f.open(0, 4, 2);
        assert_eq!(f.add_tile(&tile(0, 0, 0, 4, 2, 9), now), Ok(8));
        assert!(f.frame_done(0, FrameStats::default(), now));
        let shown = f.pop_ready().unwrap().image;
        assert_eq!(shown.rgba, [[9; 4]; 8]);
        f.recycle(shown.rgba);
        f.open(1, 4, 2);
        assert_eq!(f.add_tile(&tile(1, 1, 0, 2, 1, 5), now), Ok(2));
        assert!(f.frame_done(1, FrameStats::default(), now));
        assert!(f.pop_ready().is_none(), "6 pixels missing");
        let forced = f.force_next(now).unwrap();
        assert_eq!(forced.missing_pixels, 6);
        let mut want = [MISSING; 8];
        want[1] = [5; 4];
        want[2] = [5; 4];
        assert_eq!(forced.image.rgba, want);
        // An image of another size is not kept.
        f.recycle(vec![[1; 4]; 3]);
        f.open(2, 4, 2);
        assert_eq!(f.pending[&2].rgba, [MISSING; 8]);
    }

    #[test]
    fn coverage_bits_match_a_flag_per_pixel() {
        // Rows of every length at every offset around word boundaries.
        let n = 200;
        for start in 0..n {
            for len in 1..=(n - start).min(130) {
                let mut c = Coverage::new(n);
                let mut flags = vec![false; n];
                c.set(start / 2);
                flags[start / 2] = true;
                let any = flags[start..start + len].contains(&true);
                assert_eq!(c.any(start, len), any, "any({start}, {len})");
                c.set_all(start, len);
                flags[start..start + len].fill(true);
                for (i, &f) in flags.iter().enumerate() {
                    assert_eq!(c.get(i), f, "bit {i} after set_all({start}, {len})");
                }
            }
        }
    }
}
