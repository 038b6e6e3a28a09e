//! Image files: PNG for people, and the comparison formats of docs/design.md:
//! depth as a grey PFM (rows bottom to top, +inf on a miss) and primitive
//! ids as raw little-endian u32 (rows top to bottom, 0xFFFFFFFF on a miss).
//! Every file is written to a temporary name and renamed into place.
//! [`Accumulator`] averages samples of one view into one image.

use std::io::{self, Write};
use std::path::{Path, PathBuf};

#[derive(Debug, thiserror::Error)]
pub enum ImageError {
    #[error("{path}: {source}")]
    Io { path: PathBuf, source: io::Error },
    #[error("{path}: {message}")]
    Format { path: PathBuf, message: String },
}

fn write_atomic(
    path: &Path,
    write: impl FnOnce(&mut dyn Write) -> io::Result<()>,
) -> Result<(), ImageError> {
    let io_err = |source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    };
    let dir = match path.parent() {
        Some(d) if !d.as_os_str().is_empty() => d,
        _ => Path::new("."),
    };
    let mut builder = tempfile::Builder::new();
    builder.prefix(".dray-image-");
    #[cfg(unix)]
    builder.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o644));
    let mut tmp = builder.tempfile_in(dir).map_err(io_err)?;
    {
        let mut out = io::BufWriter::new(tmp.as_file_mut());
        write(&mut out).map_err(io_err)?;
        out.flush().map_err(io_err)?;
    }
    tmp.persist(path).map_err(|e| io_err(e.error))?;
    Ok(())
}

/// Writes a grey PFM: `Pf`, size, scale -1.0 (little-endian), rows from the
/// bottom.
pub fn write_pfm(path: &Path, width: u32, height: u32, depth: &[f32]) -> Result<(), ImageError> {
    write_atomic(path, |out| {
        write!(out, "Pf\n{width} {height}\n-1.0\n")?;
        for y in (0..height).rev() {
            let row = &depth[(y * width) as usize..((y + 1) * width) as usize];
            for v in row {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        Ok(())
    })
}

/// Reads a grey PFM as written by [`write_pfm`] (or Embree's bench) into
/// rows top to bottom.
pub fn read_pfm(path: &Path) -> Result<(u32, u32, Vec<f32>), ImageError> {
    let bytes = std::fs::read(path).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    let bad = |message: &str| ImageError::Format {
        path: path.to_path_buf(),
        message: message.to_string(),
    };
    let mut fields = Vec::new();
    let mut at = 0;
    while fields.len() < 4 {
        let rest = bytes.get(at..).ok_or_else(|| bad("truncated header"))?;
        let skip = rest.iter().take_while(|b| b.is_ascii_whitespace()).count();
        at += skip;
        let len = bytes[at..]
            .iter()
            .take_while(|b| !b.is_ascii_whitespace())
            .count();
        if len == 0 {
            return Err(bad("truncated header"));
        }
        fields.push(String::from_utf8_lossy(&bytes[at..at + len]).into_owned());
        at += len;
    }
    at += 1; // the single whitespace after the scale
    if fields[0] != "Pf" {
        return Err(bad("not a grey PFM (expected Pf)"));
    }
    let w: u32 = fields[1].parse().map_err(|_| bad("bad width"))?;
    let h: u32 = fields[2].parse().map_err(|_| bad("bad height"))?;
    let scale: f32 = fields[3].parse().map_err(|_| bad("bad scale"))?;
    let n = w as usize * h as usize;
    let body = bytes.get(at..).ok_or_else(|| bad("truncated data"))?;
    if body.len() != n * 4 {
        return Err(bad(&format!("{} data bytes for {w}x{h}", body.len())));
    }
    let mut out = vec![0.0; n];
    for (k, c) in body.chunks_exact(4).enumerate() {
        let raw = [c[0], c[1], c[2], c[3]];
        let v = if scale < 0.0 {
            f32::from_le_bytes(raw)
        } else {
            f32::from_be_bytes(raw)
        };
        let (x, y_from_bottom) = (k % w as usize, k / w as usize);
        out[(h as usize - 1 - y_from_bottom) * w as usize + x] = v;
    }
    Ok((w, h, out))
}

/// Writes primitive ids as raw little-endian u32, rows top to bottom.
pub fn write_u32(path: &Path, ids: &[u32]) -> Result<(), ImageError> {
    write_atomic(path, |out| {
        for v in ids {
            out.write_all(&v.to_le_bytes())?;
        }
        Ok(())
    })
}

pub fn read_u32(path: &Path) -> Result<Vec<u32>, ImageError> {
    let bytes = std::fs::read(path).map_err(|source| ImageError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    if bytes.len() % 4 != 0 {
        return Err(ImageError::Format {
            path: path.to_path_buf(),
            message: format!("{} bytes is not a whole number of u32", bytes.len()),
        });
    }
    Ok(bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect())
}

fn png_to(out: impl io::Write, width: u32, height: u32, rgba: &[[u8; 4]]) -> io::Result<()> {
    let mut enc = png::Encoder::new(out, width, height);
    enc.set_color(png::ColorType::Rgba);
    enc.set_depth(png::BitDepth::Eight);
    let mut w = enc.write_header().map_err(io::Error::other)?;
    w.write_image_data(rgba.as_flattened())
        .map_err(io::Error::other)?;
    w.finish().map_err(io::Error::other)
}

/// Writes an 8-bit RGBA PNG.
pub fn write_png(path: &Path, width: u32, height: u32, rgba: &[[u8; 4]]) -> Result<(), ImageError> {
    write_atomic(path, |out| png_to(out, width, height, rgba))
}

/// An 8-bit RGBA PNG in memory (`rgba` must hold `width * height` pixels).
pub fn encode_png(width: u32, height: u32, rgba: &[[u8; 4]]) -> io::Result<Vec<u8>> {
    let mut out = Vec::new();
    png_to(&mut out, width, height, rgba)?;
    Ok(out)
}

/// Reads an 8-bit RGBA PNG from memory: width, height and pixels.
pub fn decode_png(bytes: &[u8]) -> io::Result<(u32, u32, Vec<[u8; 4]>)> {
    let dec = png::Decoder::new(io::Cursor::new(bytes));
    let mut reader = dec.read_info().map_err(io::Error::other)?;
    let mut buf = vec![0; reader.output_buffer_size()];
    let info = reader.next_frame(&mut buf).map_err(io::Error::other)?;
    if info.color_type != png::ColorType::Rgba || info.bit_depth != png::BitDepth::Eight {
        return Err(io::Error::other("not an 8-bit RGBA PNG"));
    }
    buf.truncate(info.buffer_size());
    let px = buf
        .chunks_exact(4)
        .map(|c| [c[0], c[1], c[2], c[3]])
        .collect();
    Ok((info.width, info.height, px))
}

/// A grey PNG of the depth (near bright, far dark, misses black), for a
/// quick look when no shading was asked for.
pub fn depth_to_rgba(depth: &[f32]) -> Vec<[u8; 4]> {
    let finite = depth.iter().copied().filter(|d| d.is_finite());
    let (lo, hi) = finite.fold((f32::INFINITY, 0.0f32), |(lo, hi), d| {
        (lo.min(d), hi.max(d))
    });
    depth
        .iter()
        .map(|&d| {
            if d.is_finite() {
                let g = (255.0 * (1.0 - 0.8 * (d - lo) / (hi - lo).max(1e-30))) as u8;
                [g, g, g, 255]
            } else {
                [0, 0, 0, 255]
            }
        })
        .collect()
}

/// Why [`Accumulator::add`] refused an image.
#[derive(Clone, Debug, PartialEq, Eq, thiserror::Error)]
pub enum AccumulateError {
    #[error("{got} pixels for a {width}x{height} image")]
    Size { width: u32, height: u32, got: usize },
    #[error(
        "the image already holds {} samples, the most its sums take",
        Accumulator::MAX_SAMPLES
    )]
    Full,
}

/// Samples of one view (the same camera, size and settings; sample k's rays
/// moved by [`crate::camera::sample_offset`]) added into one image: per
/// pixel and channel the sum of the samples' values, in integers, so the
/// result is exact and the same whatever order the samples come in. That
/// is what makes a cluster's accumulated frames equal `dray render
/// --spp`'s.
#[derive(Clone, Debug)]
pub struct Accumulator {
    width: u32,
    height: u32,
    /// Per pixel, the sums of red, green and blue.
    sums: Vec<[u32; 3]>,
    samples: u32,
}

impl Accumulator {
    /// The most samples the u32 sums take (each adds at most 255).
    pub const MAX_SAMPLES: u32 = u32::MAX / 255;

    /// An empty `width` × `height` image (no sample yet).
    pub fn new(width: u32, height: u32) -> Accumulator {
        Accumulator {
            width,
            height,
            sums: vec![[0; 3]; width as usize * height as usize],
            samples: 0,
        }
    }

    /// Adds one sample: `rgba` holds `width × height` pixels, rows top to
    /// bottom; its alpha is ignored.
    pub fn add(&mut self, rgba: &[[u8; 4]]) -> Result<(), AccumulateError> {
        if rgba.len() != self.sums.len() {
            return Err(AccumulateError::Size {
                width: self.width,
                height: self.height,
                got: rgba.len(),
            });
        }
        if self.samples >= Self::MAX_SAMPLES {
            return Err(AccumulateError::Full);
        }
        for (s, p) in self.sums.iter_mut().zip(rgba) {
            for c in 0..3 {
                s[c] += u32::from(p[c]);
            }
        }
        self.samples += 1;
        Ok(())
    }

    /// Samples added so far.
    pub fn samples(&self) -> u32 {
        self.samples
    }

    /// Forgets every sample (the camera moved).
    pub fn clear(&mut self) {
        self.sums.fill([0; 3]);
        self.samples = 0;
    }

    /// The mean of the samples: per channel `(sum + n/2) / n` in integers
    /// (rounded half up), alpha 255; black before the first sample.
    pub fn image(&self) -> Vec<[u8; 4]> {
        let n = self.samples;
        if n == 0 {
            return vec![[0, 0, 0, 255]; self.sums.len()];
        }
        // At most 255: the sums are of n values up to 255 each.
        let mean = |sum: u32| ((u64::from(sum) + u64::from(n / 2)) / u64::from(n)) as u8;
        self.sums
            .iter()
            .map(|s| [mean(s[0]), mean(s[1]), mean(s[2]), 255])
            .collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn pixels(n: usize) -> impl Strategy<Value = Vec<[u8; 4]>> {
        proptest::collection::vec(any::<[u8; 4]>(), n)
    }

    proptest! {
        #[test]
        fn one_sample_is_the_image_itself(img in pixels(12)) {
            let mut a = Accumulator::new(4, 3);
            a.add(&img).unwrap();
            prop_assert_eq!(a.samples(), 1);
            let opaque: Vec<[u8; 4]> = img.iter().map(|p| [p[0], p[1], p[2], 255]).collect();
            prop_assert_eq!(a.image(), opaque);
        }

        #[test]
        fn the_order_of_the_samples_does_not_matter(
            imgs in proptest::collection::vec(pixels(6), 1..9),
            seed in any::<u64>(),
        ) {
            let mut forward = Accumulator::new(3, 2);
            for img in &imgs {
                forward.add(img).unwrap();
            }
            let mut order: Vec<usize> = (0..imgs.len()).collect();
            // A permutation from the seed: Fisher-Yates on an LCG.
            let mut x = seed;
            for i in (1..order.len()).rev() {
                x = x.wrapping_mul(0x9E37_79B9_7F4A_7C15).wrapping_add(1);
                order.swap(i, (x >> 33) as usize % (i + 1));
            }
            let mut shuffled = Accumulator::new(3, 2);
            for &i in &order {
                shuffled.add(&imgs[i]).unwrap();
            }
            prop_assert_eq!(forward.image(), shuffled.image());
            // And it is the rounded mean, channel by channel.
            let n = imgs.len() as u32;
            for (k, p) in forward.image().iter().enumerate() {
                for c in 0..3 {
                    let sum: u32 = imgs.iter().map(|img| u32::from(img[k][c])).sum();
                    prop_assert_eq!(u32::from(p[c]), (sum + n / 2) / n);
                }
                prop_assert_eq!(p[3], 255);
            }
        }

        #[test]
        fn a_constant_image_stays_constant(c in any::<[u8; 3]>(), n in 1u32..300) {
            let img = vec![[c[0], c[1], c[2], 255]; 6];
            let mut a = Accumulator::new(2, 3);
            for _ in 0..n {
                a.add(&img).unwrap();
            }
            prop_assert_eq!(a.samples(), n);
            prop_assert_eq!(a.image(), img);
        }
    }

    #[test]
    fn a_wrong_size_or_a_full_image_is_refused() {
        let mut a = Accumulator::new(2, 2);
        assert_eq!(a.image(), vec![[0, 0, 0, 255]; 4], "no sample yet");
        assert_eq!(
            a.add(&[[1, 2, 3, 4]; 3]),
            Err(AccumulateError::Size {
                width: 2,
                height: 2,
                got: 3
            })
        );
        assert_eq!(a.samples(), 0);
        a.add(&[[255; 4]; 4]).unwrap();
        a.add(&[[0; 4]; 4]).unwrap();
        assert_eq!(a.image(), vec![[128, 128, 128, 255]; 4], "half rounds up");
        a.clear();
        assert_eq!(a.samples(), 0);
        a.samples = Accumulator::MAX_SAMPLES - 1;
        a.sums.fill([u32::MAX - 255 - 254; 3]);
        a.add(&[[255; 4]; 4]).unwrap();
        assert_eq!(a.add(&[[255; 4]; 4]), Err(AccumulateError::Full));
        assert_eq!(a.image(), vec![[255, 255, 255, 255]; 4]);
    }

    #[test]
    fn pfm_and_u32_round_trip_in_the_shared_layouts() {
        let dir = tempfile::tempdir().unwrap();
        let depth = vec![1.0, 2.0, f32::INFINITY, 4.0, 5.0, 6.0];
        let p = dir.path().join("d.pfm");
        write_pfm(&p, 3, 2, &depth).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert!(bytes.starts_with(b"Pf\n3 2\n-1.0\n"));
        // The first stored row is the bottom one.
        assert_eq!(&bytes[12..16], &4.0f32.to_le_bytes());
        assert_eq!(read_pfm(&p).unwrap(), (3, 2, depth));

        let ids = vec![7, u32::MAX, 9];
        let q = dir.path().join("p.u32");
        write_u32(&q, &ids).unwrap();
        assert_eq!(std::fs::read(&q).unwrap()[..4], 7u32.to_le_bytes());
        assert_eq!(read_u32(&q).unwrap(), ids);

        std::fs::write(&p, b"Pf\n3 2\n-1.0\n\0\0").unwrap();
        assert!(read_pfm(&p).unwrap_err().to_string().contains("data bytes"));
    }
}
