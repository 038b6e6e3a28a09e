//! A tile's colors on the wire, in the smaller of two exact encodings.
//!
//! The renderer writes RGBA8, but its pixels are always opaque. Every
//! byte a tile carries is copied, encrypted, sent in QUIC packets and
//! acknowledged by a client, and decrypted and copied again by the
//! display, and on a 100 Mbit/s link it is what bounds the frame rate: an
//! opaque tile goes as three bytes a pixel, and only a tile with some
//! alpha below 255 as four.

use crate::bounded::Blob;
use serde::{Deserialize, Serialize};
use std::fmt;

/// A tile's pixels, rows top to bottom.
#[derive(Clone, PartialEq, Eq, Serialize, Deserialize)]
pub enum TilePixels {
    /// Opaque pixels: red, green and blue.
    Rgb(Blob),
    /// Red, green, blue and alpha.
    Rgba(Blob),
}

impl fmt::Debug for TilePixels {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = match self {
            TilePixels::Rgb(_) => "Rgb",
            TilePixels::Rgba(_) => "Rgba",
        };
        write!(f, "{name}({} bytes)", self.bytes().len())
    }
}

impl TilePixels {
    /// Encodes `rgba` in the smaller encoding that keeps every pixel.
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

    /// Bytes a pixel takes in this encoding.
    pub fn bytes_per_pixel(&self) -> usize {
        match self {
            TilePixels::Rgb(_) => 3,
            TilePixels::Rgba(_) => 4,
        }
    }

    /// The encoded bytes.
    pub fn bytes(&self) -> &[u8] {
        match self {
            TilePixels::Rgb(b) | TilePixels::Rgba(b) => &b.0,
        }
    }

    /// Whether the encoding holds exactly `n` pixels.
    pub fn holds(&self, n: usize) -> bool {
        n.checked_mul(self.bytes_per_pixel()) == Some(self.bytes().len())
    }

    /// Writes the pixels from index `first` on into `out`, as RGBA.
    ///
    /// # Panics
    ///
    /// If the encoding holds fewer than `first + out.len()` pixels (see
    /// [`Self::holds`]).
    pub fn copy_to(&self, first: usize, out: &mut [[u8; 4]]) {
        let n = out.len();
        match self {
            TilePixels::Rgb(b) => {
                let src = b.0[first * 3..(first + n) * 3].chunks_exact(3);
                for (o, p) in out.iter_mut().zip(src) {
                    *o = [p[0], p[1], p[2], 255];
                }
            }
            TilePixels::Rgba(b) => {
                out.as_flattened_mut()
                    .copy_from_slice(&b.0[first * 4..(first + n) * 4]);
            }
        }
    }

    /// Every pixel as RGBA.
    pub fn to_rgba(&self) -> Vec<[u8; 4]> {
        let mut out = vec![[0; 4]; self.bytes().len() / self.bytes_per_pixel()];
        self.copy_to(0, &mut out);
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    #[test]
    fn each_kind_of_tile_takes_its_smaller_encoding() {
        let opaque = [[7, 7, 7, 255], [1, 2, 3, 255]];
        let p = TilePixels::encode(&opaque);
        assert!(matches!(p, TilePixels::Rgb(_)));
        assert_eq!(p.bytes(), &[7, 7, 7, 1, 2, 3]);
        let clear = [[7, 7, 7, 254], [1, 2, 3, 255]];
        assert!(matches!(TilePixels::encode(&clear), TilePixels::Rgba(_)));
        assert!(TilePixels::encode(&clear).holds(2));
        assert!(!TilePixels::encode(&clear).holds(3));
    }

    #[test]
    fn a_part_of_the_tile_is_copied_from_where_it_starts() {
        let rgba: Vec<[u8; 4]> = (0..6).map(|i| [i, i + 1, i + 2, 255]).collect();
        let mut out = [[0; 4]; 3];
        TilePixels::encode(&rgba).copy_to(2, &mut out);
        assert_eq!(out, [[2, 3, 4, 255], [3, 4, 5, 255], [4, 5, 6, 255]]);
    }

    proptest! {
        #[test]
        fn every_tile_comes_back_exactly(
            pixels in proptest::collection::vec((any::<[u8; 3]>(), any::<bool>()), 0..64),
            clear in any::<bool>(),
        ) {
            // Opaque pixels, some of them translucent by the flag.
            let rgba: Vec<[u8; 4]> = pixels
                .iter()
                .map(|&([r, g, b], odd)| [r, g, b, if clear && odd { 128 } else { 255 }])
                .collect();
            let p = TilePixels::encode(&rgba);
            prop_assert!(p.holds(rgba.len()));
            prop_assert_eq!(p.to_rgba(), rgba.clone());
            // The smaller encoding that can hold them.
            let want = if clear && pixels.iter().any(|p| p.1) { 4 } else { 3 };
            prop_assert_eq!(p.bytes_per_pixel(), want);
        }
    }
}
