//! Image files: PNG for people, and the comparison formats of docs/design.md:
//! depth as a grey PFM (rows bottom to top, +inf on a miss) and primitive
//! ids as raw little-endian u32 (rows top to bottom, 0xFFFFFFFF on a miss).
//! Every file is written to a temporary name and renamed into place.

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

#[cfg(test)]
mod tests {
    use super::*;

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
