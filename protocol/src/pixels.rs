//! A tile's colors on the wire: RGB, RGB compressed, or RGBA.
//!
//! The renderer writes RGBA8, but its pixels are always opaque. Every
//! byte a tile carries is copied, encrypted, sent in QUIC packets and
//! acknowledged by a client, and decrypted and copied again by the
//! display, and on a 100 Mbit/s link it is what bounds the frame rate: an
//! opaque tile goes as three bytes a pixel, or, as the client is asked
//! to ([`Compression`]), as those bytes compressed with LZ4 or zstd's
//! fastest level (a rendered image has flat background and smooth
//! shading, which both compress several times); only a tile with some
//! alpha below 255 goes as four bytes a pixel.

use crate::bounded::Blob;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::cell::RefCell;
use std::fmt;

/// zstd's level for pixels: the fastest, as the clients' CPU is the
/// render threads'.
const ZSTD_LEVEL: i32 = 1;

/// How a client compresses the opaque tiles it sends (`clients.pixel_compression`).
///
/// LZ4 by default: zstd's fastest level makes about a fifth fewer bytes
/// but costs more CPU on both ends, and where the nodes share cores the
/// CPU is what counts. Uncompressed costs more CPU than either even over
/// loopback (every packet is syscalls, encryption and acknowledgements).
/// zstd's fewer bytes are for slow links (a few tens of Mbit/s a client).
/// Measured by `experiments/efficiency.toml` and `links.toml`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Compression {
    /// Three bytes a pixel, as rendered.
    None,
    /// LZ4 (a block, no frame): the least CPU on both ends.
    #[default]
    Lz4,
    /// zstd's fastest level: the fewest bytes.
    Zstd,
}

/// A tile's pixels, rows top to bottom.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum TilePixels {
    /// Opaque pixels: red, green and blue.
    Rgb(Blob),
    /// Red, green, blue and alpha.
    Rgba(Blob),
    /// Opaque pixels, red, green and blue, as one zstd frame.
    RgbZstd(Blob),
    /// Opaque pixels, red, green and blue, as one LZ4 block.
    RgbLz4(Blob),
}

/// Why a tile's pixels cannot be read.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum PixelError {
    /// The bytes are not as many as the tile's pixels need.
    #[error("{got} pixel bytes for {pixels} pixels (want {want})")]
    Size {
        /// Bytes carried (decompressed, for a compressed tile).
        got: usize,
        /// The tile's pixels.
        pixels: usize,
        /// Bytes they need.
        want: usize,
    },
    /// Compressed pixels that do not decompress into the tile.
    #[error("compressed pixels do not decode into {pixels} pixels: {reason}")]
    Corrupt {
        /// The tile's pixels.
        pixels: usize,
        /// zstd's complaint.
        reason: String,
    },
}

impl fmt::Debug for TilePixels {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self {
            TilePixels::Rgb(_) => "Rgb",
            TilePixels::Rgba(_) => "Rgba",
            TilePixels::RgbZstd(_) => "RgbZstd",
            TilePixels::RgbLz4(_) => "RgbLz4",
        };
        write!(f, "{name}({} bytes)", self.bytes().len())
    }
}

/// What a thread keeps from one tile it encodes to the next: fresh
/// buffers (the RGB, the compressor's output at its worst-case size, LZ4's
/// hash table) would be allocated and zeroed on a client's actor thread
/// for every tile.
#[derive(Default)]
struct Scratch {
    rgb: Vec<u8>,
    packed: Vec<u8>,
    lz4: lz4_flex::block::CompressTable,
}

thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
    // One context per thread: making one for every tile would cost about
    // as much as compressing it.
    static COMPRESSOR: RefCell<Option<zstd::bulk::Compressor<'static>>> =
        const { RefCell::new(None) };
    static DECOMPRESSOR: RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { RefCell::new(None) };
}

impl TilePixels {
    /// Encodes `rgba` uncompressed, in the smaller encoding that keeps
    /// every pixel.
    pub fn encode(rgba: &[[u8; 4]]) -> TilePixels {
        Self::encode_with(rgba, Compression::None)
    }

    /// Encodes `rgba` as [`Self::encode`] does, then compresses opaque
    /// pixels as `how` says when that makes them smaller.
    pub fn encode_with(rgba: &[[u8; 4]], how: Compression) -> TilePixels {
        SCRATCH.with(|s| {
            let s = &mut *s.borrow_mut();
            if !pack_rgb(rgba, &mut s.rgb) {
                return TilePixels::Rgba(Blob(rgba.as_flattened().to_vec()));
            }
            let rgb = &s.rgb[..];
            let (packed, wrap): (_, fn(Blob) -> TilePixels) = match how {
                Compression::None => (None, TilePixels::Rgb),
                Compression::Lz4 => {
                    s.packed
                        .resize(lz4_flex::block::get_maximum_output_size(rgb.len()), 0);
                    let len =
                        lz4_flex::block::compress_into_with_table(rgb, &mut s.packed, &mut s.lz4);
                    (len.ok(), TilePixels::RgbLz4)
                }
                // Without a context (zstd out of memory) the tile goes as
                // it is.
                Compression::Zstd => {
                    let len = COMPRESSOR.with(|c| {
                        let mut c = c.borrow_mut();
                        let c = match c.as_mut() {
                            Some(c) => c,
                            None => c.insert(zstd::bulk::Compressor::new(ZSTD_LEVEL).ok()?),
                        };
                        s.packed.clear();
                        s.packed.reserve(zstd::zstd_safe::compress_bound(rgb.len()));
                        c.compress_to_buffer(rgb, &mut s.packed).ok()
                    });
                    (len, TilePixels::RgbZstd)
                }
            };
            match packed {
                Some(len) if len < rgb.len() => wrap(Blob(s.packed[..len].to_vec())),
                _ => TilePixels::Rgb(Blob(rgb.to_vec())),
            }
        })
    }

    /// The encoded bytes.
    pub fn bytes(&self) -> &[u8] {
        match self {
            TilePixels::Rgb(b)
            | TilePixels::Rgba(b)
            | TilePixels::RgbZstd(b)
            | TilePixels::RgbLz4(b) => &b.0,
        }
    }

    /// Checks what can be checked without decompressing: an uncompressed
    /// tile has exactly the bytes `n` pixels need, a compressed one fewer
    /// (it is only sent compressed when that is smaller).
    pub fn check_size(&self, n: usize) -> Result<(), PixelError> {
        let got = self.bytes().len();
        let (want, ok) = match self {
            TilePixels::Rgb(_) => (n.saturating_mul(3), got == n.saturating_mul(3)),
            TilePixels::Rgba(_) => (n.saturating_mul(4), got == n.saturating_mul(4)),
            TilePixels::RgbZstd(_) | TilePixels::RgbLz4(_) => {
                (n.saturating_mul(3), got < n.saturating_mul(3))
            }
        };
        if ok {
            Ok(())
        } else {
            Err(PixelError::Size {
                got,
                pixels: n,
                want,
            })
        }
    }

    /// The `n` pixels, decompressed if need be; an error if they are not
    /// exactly `n` (never more memory than `n` pixels take).
    pub fn decode(&self, n: usize) -> Result<Pixels<'_>, PixelError> {
        let mut out = Vec::new();
        match self.unpack(n, &mut out)? {
            Some(len) => {
                out.truncate(len);
                Ok(Pixels {
                    bytes: Cow::Owned(out),
                    bpp: 3,
                })
            }
            None => self.uncompressed(n),
        }
    }

    /// As [`Self::decode`], decompressing into `scratch` (grown to the
    /// tile's bytes if need be, and kept for the next tile: the display
    /// would otherwise take and zero a fresh buffer for every tile).
    pub fn decode_into<'a>(
        &'a self,
        n: usize,
        scratch: &'a mut Vec<u8>,
    ) -> Result<Pixels<'a>, PixelError> {
        match self.unpack(n, scratch)? {
            Some(len) => Ok(Pixels {
                bytes: Cow::Borrowed(&scratch[..len]),
                bpp: 3,
            }),
            None => self.uncompressed(n),
        }
    }

    /// An uncompressed tile's pixels, if they are `n`.
    fn uncompressed(&self, n: usize) -> Result<Pixels<'_>, PixelError> {
        let bpp = if matches!(self, TilePixels::Rgba(_)) {
            4
        } else {
            3
        };
        let bytes = self.bytes();
        let want = n.saturating_mul(bpp);
        if bytes.len() != want {
            return Err(PixelError::Size {
                got: bytes.len(),
                pixels: n,
                want,
            });
        }
        Ok(Pixels {
            bytes: Cow::Borrowed(bytes),
            bpp,
        })
    }

    /// Decompresses a compressed tile's `n` pixels into the start of
    /// `out` and says how many bytes they took (`None` for a tile that
    /// is not compressed); an error unless they are exactly `n`.
    fn unpack(&self, n: usize, out: &mut Vec<u8>) -> Result<Option<usize>, PixelError> {
        let want = n.saturating_mul(3);
        let corrupt = |reason: String| PixelError::Corrupt { pixels: n, reason };
        let got = match self {
            TilePixels::Rgb(_) | TilePixels::Rgba(_) => return Ok(None),
            TilePixels::RgbZstd(b) => {
                out.clear();
                // The capacity bounds the output: a hostile frame that
                // claims more fails instead of allocating it.
                out.reserve_exact(want);
                DECOMPRESSOR
                    .with(|d| {
                        let mut d = d.borrow_mut();
                        let d = match d.as_mut() {
                            Some(d) => d,
                            None => d.insert(
                                zstd::bulk::Decompressor::new().map_err(|e| e.to_string())?,
                            ),
                        };
                        d.decompress_to_buffer(&b.0, out).map_err(|e| e.to_string())
                    })
                    .map_err(corrupt)?
            }
            TilePixels::RgbLz4(b) => {
                if out.len() < want {
                    out.resize(want, 0);
                }
                // Writes at most `want` bytes: more is an error.
                lz4_flex::block::decompress_into(&b.0, &mut out[..want])
                    .map_err(|e| corrupt(e.to_string()))?
            }
        };
        if got != want {
            return Err(PixelError::Size {
                got,
                pixels: n,
                want,
            });
        }
        Ok(Some(got))
    }
}

/// Writes `rgba`'s red, green and blue into `out` (resized to fit) and
/// says whether every pixel is opaque.
fn pack_rgb(rgba: &[[u8; 4]], out: &mut Vec<u8>) -> bool {
    out.resize(rgba.len() * 3, 0);
    // Four pixels at a time as three words, alpha ANDed along without a
    // branch: faster than a pixel at a time.
    let (quads, rest) = rgba.as_chunks::<4>();
    let (words, tail) = out.as_chunks_mut::<12>();
    let mut alpha = 255u8;
    for (q, w) in quads.iter().zip(words.iter_mut()) {
        let p = q.map(u32::from_le_bytes);
        alpha &= q[0][3] & q[1][3] & q[2][3] & q[3][3];
        w[0..4].copy_from_slice(&((p[0] & 0xff_ffff) | (p[1] << 24)).to_le_bytes());
        w[4..8].copy_from_slice(&(((p[1] >> 8) & 0xffff) | (p[2] << 16)).to_le_bytes());
        w[8..12].copy_from_slice(&(((p[2] >> 16) & 0xff) | (p[3] << 8)).to_le_bytes());
    }
    for (p, o) in rest.iter().zip(tail.chunks_exact_mut(3)) {
        o.copy_from_slice(&p[..3]);
        alpha &= p[3];
    }
    alpha == 255
}

/// Writes the RGB pixels `rgb` into `out` as opaque RGBA.
fn expand_rgb(rgb: &[u8], out: &mut [[u8; 4]]) {
    // Three words into four pixels at a time, faster than a pixel at a time:
    // this and the decompression are the display's largest costs.
    let (words, tail) = rgb.as_chunks::<12>();
    let (quads, rest) = out.as_chunks_mut::<4>();
    const ALPHA: u32 = 0xff00_0000;
    for (w, q) in words.iter().zip(quads.iter_mut()) {
        let w0 = u32::from_le_bytes([w[0], w[1], w[2], w[3]]);
        let w1 = u32::from_le_bytes([w[4], w[5], w[6], w[7]]);
        let w2 = u32::from_le_bytes([w[8], w[9], w[10], w[11]]);
        q[0] = (w0 | ALPHA).to_le_bytes();
        q[1] = ((w0 >> 24) | (w1 << 8) | ALPHA).to_le_bytes();
        q[2] = ((w1 >> 16) | (w2 << 16) | ALPHA).to_le_bytes();
        q[3] = ((w2 >> 8) | ALPHA).to_le_bytes();
    }
    for (p, o) in tail.chunks_exact(3).zip(rest.iter_mut()) {
        *o = [p[0], p[1], p[2], 255];
    }
}

/// A tile's pixels, uncompressed and of the right count
/// ([`TilePixels::decode`]).
pub struct Pixels<'a> {
    bytes: Cow<'a, [u8]>,
    bpp: usize,
}

impl Pixels<'_> {
    /// How many pixels.
    pub fn len(&self) -> usize {
        self.bytes.len() / self.bpp
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.bytes.is_empty()
    }

    /// Writes the pixels from index `first` on into `out`, as RGBA.
    ///
    /// # Panics
    ///
    /// If there are fewer than `first + out.len()` pixels.
    pub fn copy_to(&self, first: usize, out: &mut [[u8; 4]]) {
        let n = out.len();
        let b = &self.bytes;
        if self.bpp == 3 {
            expand_rgb(&b[first * 3..(first + n) * 3], out);
        } else {
            out.as_flattened_mut()
                .copy_from_slice(&b[first * 4..(first + n) * 4]);
        }
    }

    /// Every pixel as RGBA.
    pub fn to_rgba(&self) -> Vec<[u8; 4]> {
        let mut out = vec![[0; 4]; self.len()];
        self.copy_to(0, &mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    const EVERY: [Compression; 3] = [Compression::None, Compression::Lz4, Compression::Zstd];

    #[test]
    fn each_kind_of_tile_takes_its_encoding() {
        let opaque = [[7, 7, 7, 255], [1, 2, 3, 255]];
        let p = TilePixels::encode(&opaque);
        assert!(matches!(p, TilePixels::Rgb(_)));
        assert_eq!(p.bytes(), &[7, 7, 7, 1, 2, 3]);
        let clear = [[7, 7, 7, 254], [1, 2, 3, 255]];
        assert!(TilePixels::encode(&clear).check_size(2).is_ok());
        assert!(TilePixels::encode(&clear).check_size(3).is_err());
        for how in EVERY {
            assert!(matches!(
                TilePixels::encode_with(&clear, how),
                TilePixels::Rgba(_)
            ));
            // Too short to gain from compression: sent as it is.
            assert!(matches!(
                TilePixels::encode_with(&opaque, how),
                TilePixels::Rgb(_)
            ));
        }
    }

    #[test]
    fn a_flat_tile_is_compressed_and_comes_back() {
        let rgba: Vec<[u8; 4]> = (0..1024).map(|i| [24, 28, (i / 100) as u8, 255]).collect();
        for how in [Compression::Lz4, Compression::Zstd] {
            let p = TilePixels::encode_with(&rgba, how);
            match how {
                Compression::Lz4 => assert!(matches!(p, TilePixels::RgbLz4(_))),
                _ => assert!(matches!(p, TilePixels::RgbZstd(_))),
            }
            assert!(p.bytes().len() < 200, "{p:?}");
            assert!(p.check_size(1024).is_ok());
            assert_eq!(p.decode(1024).unwrap().to_rgba(), rgba);
            // Another pixel count is refused, with no more memory than
            // asked.
            assert!(p.decode(1023).is_err());
            assert!(matches!(p.decode(1025), Err(PixelError::Size { .. })));
            // A scratch buffer left longer by a bigger tile changes nothing.
            let mut scratch = vec![1; 5000];
            assert_eq!(p.decode_into(1024, &mut scratch).unwrap().to_rgba(), rgba);
            assert!(p.decode_into(1025, &mut scratch).is_err());
        }
    }

    #[test]
    fn a_part_of_the_tile_is_copied_from_where_it_starts() {
        let rgba: Vec<[u8; 4]> = (0..6).map(|i| [i, i + 1, i + 2, 255]).collect();
        let mut out = [[0; 4]; 3];
        TilePixels::encode(&rgba)
            .decode(6)
            .unwrap()
            .copy_to(2, &mut out);
        assert_eq!(out, [[2, 3, 4, 255], [3, 4, 5, 255], [4, 5, 6, 255]]);
    }

    proptest! {
        #[test]
        fn every_tile_comes_back_exactly(
            pixels in proptest::collection::vec((any::<[u8; 3]>(), any::<bool>()), 0..64),
            flat in 0usize..2000,
            clear in any::<bool>(),
            how in proptest::sample::select(EVERY.to_vec()),
            first in 0usize..70,
        ) {
            // Random pixels after a flat run, some translucent by the flag.
            let rgba: Vec<[u8; 4]> = std::iter::repeat_n(([9, 9, 9], false), flat)
                .chain(pixels.iter().copied())
                .map(|([r, g, b], odd)| [r, g, b, if clear && odd { 128 } else { 255 }])
                .collect();
            let p = TilePixels::encode_with(&rgba, how);
            prop_assert!(p.check_size(rgba.len()).is_ok());
            prop_assert_eq!(p.decode(rgba.len()).unwrap().to_rgba(), rgba.clone());
            let mut scratch = Vec::new();
            let px = p.decode_into(rgba.len(), &mut scratch).unwrap();
            // Any stretch of the tile, as the display copies its rows.
            let first = first.min(rgba.len());
            let mut part = vec![[0; 4]; rgba.len() - first];
            px.copy_to(first, &mut part);
            prop_assert_eq!(&part[..], &rgba[first..]);
            let translucent = clear && pixels.iter().any(|p| p.1);
            prop_assert_eq!(matches!(p, TilePixels::Rgba(_)), translucent);
            if how == Compression::None {
                prop_assert!(matches!(p, TilePixels::Rgb(_) | TilePixels::Rgba(_)));
            }
        }

        #[test]
        fn garbage_never_panics_and_never_passes_for_more_pixels(
            bytes in proptest::collection::vec(any::<u8>(), 0..256),
            n in 0usize..4096,
        ) {
            let m = bytes.len() / 3;
            let mut scratch = Vec::new();
            for p in [TilePixels::RgbZstd(Blob(bytes.clone())), TilePixels::RgbLz4(Blob(bytes.clone()))] {
                if let Ok(px) = p.decode(n) {
                    prop_assert_eq!(px.len(), n);
                }
                if let Ok(px) = p.decode_into(n, &mut scratch) {
                    prop_assert_eq!(px.len(), n);
                }
                prop_assert!(scratch.capacity() <= 4096 * 3 + 64);
            }
            // A sound block of other pixels is refused for n, whatever n.
            let zstd = zstd::bulk::compress(&bytes[..m * 3], 1).unwrap();
            let lz4 = lz4_flex::block::compress(&bytes[..m * 3]);
            for p in [TilePixels::RgbZstd(Blob(zstd)), TilePixels::RgbLz4(Blob(lz4))] {
                prop_assert_eq!(p.decode(n).is_ok(), n == m);
                prop_assert_eq!(p.decode_into(n, &mut scratch).is_ok(), n == m);
            }
        }
    }
}
