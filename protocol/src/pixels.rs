//! A tile's colors on the wire: RGB, RGB compressed, or RGBA.
//!
//! The renderer writes RGBA8, but its pixels are always opaque. Every
//! byte a tile carries is copied, encrypted, sent in QUIC packets and
//! acknowledged by a client, and decrypted and copied again by the
//! display, and on a 100 Mbit/s link it is what bounds the frame rate: an
//! opaque tile goes as three bytes a pixel, or, when the client is asked
//! to, as those bytes compressed with zstd's fastest level (a rendered
//! image has flat background and smooth shading: a whole frame of the
//! plant's default view shrinks 8.5 times, at about 1 GB/s); only a tile with some alpha below
//! 255 goes as four bytes a pixel.

use crate::bounded::Blob;
use serde::{Deserialize, Serialize};
use std::borrow::Cow;
use std::cell::RefCell;
use std::fmt;

/// zstd's level for pixels: the fastest, as the clients' CPU is the
/// render threads'.
const ZSTD_LEVEL: i32 = 1;

/// A tile's pixels, rows top to bottom.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum TilePixels {
    /// Opaque pixels: red, green and blue.
    Rgb(Blob),
    /// Red, green, blue and alpha.
    Rgba(Blob),
    /// Opaque pixels, red, green and blue, as one zstd frame.
    RgbZstd(Blob),
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
        };
        write!(f, "{name}({} bytes)", self.bytes().len())
    }
}

thread_local! {
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
        // A reduction without a branch per pixel, which the compiler
        // vectorizes.
        let opaque = rgba.iter().fold(true, |all, p| all & (p[3] == 255));
        if opaque {
            TilePixels::Rgb(Blob(rgba.iter().flat_map(|p| [p[0], p[1], p[2]]).collect()))
        } else {
            TilePixels::Rgba(Blob(rgba.as_flattened().to_vec()))
        }
    }

    /// Encodes `rgba` as [`Self::encode`] does, then compresses opaque
    /// pixels when that makes them smaller.
    pub fn encode_compressed(rgba: &[[u8; 4]]) -> TilePixels {
        let raw = match Self::encode(rgba) {
            TilePixels::Rgb(raw) => raw,
            translucent => return translucent,
        };
        // Without a context (zstd out of memory) the tile goes as it is.
        let packed = COMPRESSOR.with(|c| {
            let mut c = c.borrow_mut();
            let c = match c.as_mut() {
                Some(c) => c,
                None => c.insert(zstd::bulk::Compressor::new(ZSTD_LEVEL).ok()?),
            };
            c.compress(&raw.0).ok()
        });
        match packed {
            Some(z) if z.len() < raw.0.len() => TilePixels::RgbZstd(Blob(z)),
            _ => TilePixels::Rgb(raw),
        }
    }

    /// The encoded bytes.
    pub fn bytes(&self) -> &[u8] {
        match self {
            TilePixels::Rgb(b) | TilePixels::Rgba(b) | TilePixels::RgbZstd(b) => &b.0,
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
            TilePixels::RgbZstd(_) => (n.saturating_mul(3), got < n.saturating_mul(3)),
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
        let (bytes, bpp) = match self {
            TilePixels::Rgb(b) => (Cow::Borrowed(b.0.as_slice()), 3),
            TilePixels::Rgba(b) => (Cow::Borrowed(b.0.as_slice()), 4),
            TilePixels::RgbZstd(b) => {
                let want = n.saturating_mul(3);
                let out = DECOMPRESSOR.with(|d| {
                    let mut d = d.borrow_mut();
                    let d = match d.as_mut() {
                        Some(d) => d,
                        None => {
                            d.insert(zstd::bulk::Decompressor::new().map_err(|e| e.to_string())?)
                        }
                    };
                    // The capacity bounds the output: a hostile frame that
                    // claims more fails instead of allocating it.
                    d.decompress(&b.0, want).map_err(|e| e.to_string())
                });
                let out = out.map_err(|reason| PixelError::Corrupt { pixels: n, reason })?;
                (Cow::Owned(out), 3)
            }
        };
        let want = n.saturating_mul(bpp);
        if bytes.len() != want {
            return Err(PixelError::Size {
                got: bytes.len(),
                pixels: n,
                want,
            });
        }
        Ok(Pixels { bytes, bpp })
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
            let src = b[first * 3..(first + n) * 3].chunks_exact(3);
            for (o, p) in out.iter_mut().zip(src) {
                *o = [p[0], p[1], p[2], 255];
            }
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

    #[test]
    fn each_kind_of_tile_takes_its_encoding() {
        let opaque = [[7, 7, 7, 255], [1, 2, 3, 255]];
        let p = TilePixels::encode(&opaque);
        assert!(matches!(p, TilePixels::Rgb(_)));
        assert_eq!(p.bytes(), &[7, 7, 7, 1, 2, 3]);
        let clear = [[7, 7, 7, 254], [1, 2, 3, 255]];
        assert!(matches!(TilePixels::encode(&clear), TilePixels::Rgba(_)));
        assert!(matches!(
            TilePixels::encode_compressed(&clear),
            TilePixels::Rgba(_)
        ));
        assert!(TilePixels::encode(&clear).check_size(2).is_ok());
        assert!(TilePixels::encode(&clear).check_size(3).is_err());
        // Too short to gain from compression: sent as it is.
        assert!(matches!(
            TilePixels::encode_compressed(&opaque),
            TilePixels::Rgb(_)
        ));
    }

    #[test]
    fn a_flat_tile_is_compressed_and_comes_back() {
        let rgba: Vec<[u8; 4]> = (0..1024).map(|i| [24, 28, (i / 100) as u8, 255]).collect();
        let p = TilePixels::encode_compressed(&rgba);
        assert!(matches!(p, TilePixels::RgbZstd(_)));
        assert!(p.bytes().len() < 200, "{p:?}");
        assert!(p.check_size(1024).is_ok());
        assert_eq!(p.decode(1024).unwrap().to_rgba(), rgba);
        // Another pixel count is refused, with no more memory than asked.
        assert!(matches!(p.decode(1023), Err(PixelError::Corrupt { .. })));
        assert!(matches!(p.decode(1025), Err(PixelError::Size { .. })));
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
            compress in any::<bool>(),
        ) {
            // Random pixels after a flat run, some translucent by the flag.
            let rgba: Vec<[u8; 4]> = std::iter::repeat_n(([9, 9, 9], false), flat)
                .chain(pixels.iter().copied())
                .map(|([r, g, b], odd)| [r, g, b, if clear && odd { 128 } else { 255 }])
                .collect();
            let p = if compress {
                TilePixels::encode_compressed(&rgba)
            } else {
                TilePixels::encode(&rgba)
            };
            prop_assert!(p.check_size(rgba.len()).is_ok());
            prop_assert_eq!(p.decode(rgba.len()).unwrap().to_rgba(), rgba.clone());
            let translucent = clear && pixels.iter().any(|p| p.1);
            prop_assert_eq!(matches!(p, TilePixels::Rgba(_)), translucent);
            if !compress {
                prop_assert!(!matches!(p, TilePixels::RgbZstd(_)));
            }
        }

        #[test]
        fn garbage_never_panics_and_never_passes_for_more_pixels(
            bytes in proptest::collection::vec(any::<u8>(), 0..256),
            n in 0usize..4096,
        ) {
            let p = TilePixels::RgbZstd(Blob(bytes.clone()));
            if let Ok(px) = p.decode(n) {
                prop_assert_eq!(px.len(), n);
            }
            // A sound frame of other pixels is refused for n, whatever n.
            let m = bytes.len() / 3;
            let real = zstd::bulk::compress(&bytes[..m * 3], 1).unwrap();
            let p = TilePixels::RgbZstd(Blob(real));
            prop_assert_eq!(p.decode(n).is_ok(), n == m);
        }
    }
}
