//! The voxel blob: a fixed header, then one zstd frame holding the filtered
//! arrays. Everything is little-endian.
//!
//! # Header (`HEADER_LEN` = 80 bytes)
//!
//! | offset | size | field |
//! |-------:|-----:|-------|
//! | 0  | 8  | magic `b"DRAYVOXL"` |
//! | 8  | 4  | format version, u32 (= [`FORMAT_VERSION`]) |
//! | 12 | 4  | flags, u32, must be 0 |
//! | 16 | 8  | checksum: xxh3-64 of every byte from offset 24 to the end ([`checksum`]) |
//! | 24 | 4  | vertex count `nv`, u32 |
//! | 28 | 4  | triangle count `nt`, u32 |
//! | 32 | 4  | BVH node count `nn`, u32 |
//! | 36 | 4  | reserved, must be 0 |
//! | 40 | 8  | raw size, u64: bytes of the decoded arrays, [`Voxel::raw_size`] = 20·nv + 16·nt + 32·nn |
//! | 48 | 8  | payload size, u64: bytes of the decompressed payload = 20·nv + 16·nt + 8·nn |
//! | 56 | 24 | voxel (BSP cell) bounds: min x, y, z, max x, y, z as f32 bit patterns |
//! | 80 | .. | one zstd frame: the payload, to the end of the blob |
//!
//! # Payload (before zstd)
//!
//! Each section is a list of u32 words written as 4 byte planes (all low
//! bytes, then all second bytes, ...), so that zstd sees the slowly varying
//! high bytes together. The words are filtered first:
//!
//! 1. positions, `3·nv` words: all x, then all y, then all z; each the f32 bit
//!    pattern minus the previous one of the same axis (wrapping; exact).
//! 2. normals, `nv` words: the octahedral codes as they are.
//! 3. colors, `nv` words: RGBA as a little-endian u32 (planes = channels).
//! 4. triangles, `3·nt` words: each vertex index `i` as `next − i` (wrapping),
//!    where `next` is one past the largest index seen so far: vertices are
//!    numbered by first use, so a new vertex is 0 and a reused recent one small.
//! 5. triangle ids, `nt` words: difference to the previous id (wrapping).
//! 6. node counts, `nn` words: [`BvhNode::count`].
//! 7. node links, `nn` words: [`BvhNode::first`] minus its prediction: for a
//!    leaf, the sum of the counts of the leaves before it; for an interior
//!    node `i`, `i + 1` (wrapping).
//!
//! Node bounds are not stored: they are recomputed exactly (min/max of the
//! corner positions) after the tree has been validated.
//!
//! Decoding checks, in order: length, magic, version, checksum, flags, that
//! the raw size is within [`MAX_VOXEL_RAW_BYTES`] and both sizes match the
//! counts, that the frame decompresses to exactly the payload size (never
//! more is allocated), then the structure that [`Voxel::validate`] checks
//! (the bounds are then made right by construction). Peak memory while decoding
//! is the payload (at most the raw size) plus the decoded arrays (the raw
//! size), both bounded by [`MAX_VOXEL_RAW_BYTES`] before any allocation.

use super::bvh::{self, BvhNode};
use super::{raw_size_of, Voxel, VoxelError};
use crate::geometry::Aabb;

/// First 8 bytes of every voxel blob.
pub const MAGIC: [u8; 8] = *b"DRAYVOXL";
/// The format version this build writes and reads.
pub const FORMAT_VERSION: u32 = 1;
/// Bytes before the compressed payload.
pub const HEADER_LEN: usize = 80;
/// Largest decoded voxel accepted (and largest payload allocated): 256 MiB.
pub const MAX_VOXEL_RAW_BYTES: u64 = 256 << 20;
/// Suggested zstd level: on CAD-like voxels level 3 gives ~11:1 at about
/// 1 GB/s (raw) encode; 9 gives ~13:1 at ~150 MB/s. Decode speed barely
/// depends on the level (~1.5 GB/s raw).
pub const DEFAULT_ZSTD_LEVEL: i32 = 3;
/// Offset where the checksummed bytes start.
const CHECKSUM_FROM: usize = 24;

/// xxh3-64 of every byte after the checksum field (offset 24 on): the value
/// a valid blob stores at offset 16, and what a manifest records.
pub fn checksum(blob: &[u8]) -> u64 {
    xxhash_rust::xxh3::xxh3_64(blob.get(CHECKSUM_FROM..).unwrap_or(&[]))
}

/// The checksum a blob's header claims (offset 16), without hashing:
/// `None` for a blob too short to have one. Compare it with a manifest's
/// before [`Voxel::decode`](super::Voxel::decode), which checks the
/// content against this same field: one hash instead of two.
pub fn stored_checksum(blob: &[u8]) -> Option<u64> {
    (blob.len() >= CHECKSUM_FROM).then(|| u64_at(blob, 16))
}

fn payload_size_of(nv: u64, nt: u64, nn: u64) -> u64 {
    nv * 20 + nt * 16 + nn * 8
}

fn put_planes(out: &mut Vec<u8>, words: &[u32]) {
    for shift in [0, 8, 16, 24] {
        out.extend(words.iter().map(|w| (w >> shift) as u8));
    }
}

/// Reads `n` words written by [`put_planes`]. The caller has checked that
/// the payload holds them; a short payload still only yields an error.
fn get_planes(payload: &[u8], pos: &mut usize, n: usize) -> Result<Vec<u32>, VoxelError> {
    let bytes = payload.get(*pos..*pos + 4 * n).ok_or_else(|| {
        VoxelError::Truncated(format!(
            "payload ends before byte {} ({} bytes)",
            *pos + 4 * n,
            payload.len()
        ))
    })?;
    *pos += 4 * n;
    let (p0, rest) = bytes.split_at(n);
    let (p1, rest) = rest.split_at(n);
    let (p2, p3) = rest.split_at(n);
    Ok((0..n)
        .map(|i| u32::from_le_bytes([p0[i], p1[i], p2[i], p3[i]]))
        .collect())
}

pub(crate) fn encode(v: &Voxel, zstd_level: i32) -> Vec<u8> {
    let nv = v.positions.len();
    let nt = v.triangles.len();
    let nn = v.bvh.len();
    let mut payload = Vec::with_capacity(payload_size_of(nv as u64, nt as u64, nn as u64) as usize);
    let mut words: Vec<u32> = Vec::with_capacity(3 * nv.max(nt).max(nn));

    // 1. positions
    words.clear();
    for axis in 0..3 {
        let mut prev = 0u32;
        for p in &v.positions {
            let b = p[axis].to_bits();
            words.push(b.wrapping_sub(prev));
            prev = b;
        }
    }
    put_planes(&mut payload, &words);
    // 2. normals
    put_planes(&mut payload, &v.normals);
    // 3. colors
    words.clear();
    words.extend(v.colors.iter().map(|c| u32::from_le_bytes(*c)));
    put_planes(&mut payload, &words);
    // 4. triangles
    words.clear();
    let mut next = 0u32;
    for t in &v.triangles {
        for &i in t {
            words.push(next.wrapping_sub(i));
            next = next.max(i.wrapping_add(1));
        }
    }
    put_planes(&mut payload, &words);
    // 5. ids
    words.clear();
    let mut prev = 0u32;
    for &id in &v.triangle_ids {
        words.push(id.wrapping_sub(prev));
        prev = id;
    }
    put_planes(&mut payload, &words);
    // 6. + 7. nodes
    words.clear();
    words.extend(v.bvh.iter().map(|n| n.count));
    put_planes(&mut payload, &words);
    words.clear();
    let mut leaf_start = 0u32;
    for (i, n) in v.bvh.iter().enumerate() {
        let predicted = if n.is_leaf() {
            let p = leaf_start;
            leaf_start = leaf_start.wrapping_add(n.count);
            p
        } else {
            (i as u32).wrapping_add(1)
        };
        words.push(n.first.wrapping_sub(predicted));
    }
    put_planes(&mut payload, &words);
    // Equal to `payload_size_of` unless the arrays are inconsistent, which
    // decode then reports.
    let payload_len = payload.len() as u64;

    // Compressing into memory only fails on allocation failure or a
    // corrupt context; neither can be handled here.
    let compressed = zstd::bulk::compress(&payload, zstd_level).expect("zstd compression failed");

    let mut blob = Vec::with_capacity(HEADER_LEN + compressed.len());
    blob.extend_from_slice(&MAGIC);
    blob.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    blob.extend_from_slice(&0u32.to_le_bytes()); // flags
    blob.extend_from_slice(&0u64.to_le_bytes()); // checksum, below
    blob.extend_from_slice(&(nv as u32).to_le_bytes());
    blob.extend_from_slice(&(nt as u32).to_le_bytes());
    blob.extend_from_slice(&(nn as u32).to_le_bytes());
    blob.extend_from_slice(&0u32.to_le_bytes()); // reserved
    blob.extend_from_slice(&(v.raw_size() as u64).to_le_bytes());
    blob.extend_from_slice(&payload_len.to_le_bytes());
    for x in v.bounds.min.iter().chain(&v.bounds.max) {
        blob.extend_from_slice(&x.to_bits().to_le_bytes());
    }
    debug_assert_eq!(blob.len(), HEADER_LEN);
    blob.extend_from_slice(&compressed);
    let sum = checksum(&blob);
    blob[16..24].copy_from_slice(&sum.to_le_bytes());
    blob
}

fn u32_at(b: &[u8], at: usize) -> u32 {
    u32::from_le_bytes([b[at], b[at + 1], b[at + 2], b[at + 3]])
}

fn u64_at(b: &[u8], at: usize) -> u64 {
    u64::from(u32_at(b, at)) | (u64::from(u32_at(b, at + 4)) << 32)
}

pub(crate) fn decode(blob: &[u8]) -> Result<Voxel, VoxelError> {
    if blob.len() >= 8 && blob[..8] != MAGIC {
        let mut found = [0u8; 8];
        found.copy_from_slice(&blob[..8]);
        return Err(VoxelError::BadMagic { found });
    }
    if blob.len() >= 12 && u32_at(blob, 8) != FORMAT_VERSION {
        return Err(VoxelError::UnsupportedVersion {
            found: u32_at(blob, 8),
            supported: FORMAT_VERSION,
        });
    }
    if blob.len() < HEADER_LEN {
        return Err(VoxelError::Truncated(format!(
            "blob has {} bytes, the header alone needs {HEADER_LEN}",
            blob.len()
        )));
    }
    let stored = u64_at(blob, 16);
    let computed = checksum(blob);
    if stored != computed {
        return Err(VoxelError::ChecksumMismatch { stored, computed });
    }
    let flags = u32_at(blob, 12);
    let reserved = u32_at(blob, 36);
    if flags != 0 || reserved != 0 {
        return Err(VoxelError::Inconsistent(format!(
            "unknown flags {flags:#x} / reserved field {reserved:#x} set"
        )));
    }
    let nv = u32_at(blob, 24) as u64;
    let nt = u32_at(blob, 28) as u64;
    let nn = u32_at(blob, 32) as u64;
    let header_raw = u64_at(blob, 40);
    let header_payload = u64_at(blob, 48);
    let raw = raw_size_of(nv, nt, nn);
    if raw > MAX_VOXEL_RAW_BYTES {
        return Err(VoxelError::TooLarge {
            what: format!("{nv} vertices, {nt} triangles and {nn} nodes"),
            bytes: raw,
            limit: MAX_VOXEL_RAW_BYTES,
        });
    }
    if header_raw != raw {
        return Err(VoxelError::SizeMismatch(format!(
            "header says raw size {header_raw}, its counts ({nv} vertices, {nt} triangles, {nn} nodes) give {raw}"
        )));
    }
    let payload_len = payload_size_of(nv, nt, nn);
    if header_payload != payload_len {
        return Err(VoxelError::SizeMismatch(format!(
            "header says payload size {header_payload}, its counts give {payload_len}"
        )));
    }
    let mut bounds = [0f32; 6];
    for (k, x) in bounds.iter_mut().enumerate() {
        *x = f32::from_bits(u32_at(blob, 56 + 4 * k));
    }

    // payload_len <= raw <= MAX_VOXEL_RAW_BYTES: the allocation is bounded,
    // and zstd refuses to write past the capacity.
    let mut payload = Vec::with_capacity(payload_len as usize);
    let got = with_decompressor(|dec| {
        dec.decompress_to_buffer(&blob[HEADER_LEN..], &mut payload)
            .map_err(|e| {
                VoxelError::Decompress(format!(
                    "{e} (expected {payload_len} bytes from {} compressed)",
                    blob.len() - HEADER_LEN
                ))
            })
    })?;
    if got as u64 != payload_len {
        return Err(VoxelError::Truncated(format!(
            "header says the payload has {payload_len} bytes, it decompresses to {got}"
        )));
    }
    let (nv, nt, nn) = (nv as usize, nt as usize, nn as usize);
    let mut pos = 0usize;

    let pw = get_planes(&payload, &mut pos, 3 * nv)?;
    let mut positions = vec![[0f32; 3]; nv];
    for axis in 0..3 {
        let mut prev = 0u32;
        for (p, &d) in positions.iter_mut().zip(&pw[axis * nv..(axis + 1) * nv]) {
            prev = prev.wrapping_add(d);
            p[axis] = f32::from_bits(prev);
        }
    }
    drop(pw);
    let normals = get_planes(&payload, &mut pos, nv)?;
    let colors = get_planes(&payload, &mut pos, nv)?
        .into_iter()
        .map(u32::to_le_bytes)
        .collect();
    let tw = get_planes(&payload, &mut pos, 3 * nt)?;
    let mut next = 0u32;
    let triangles = tw
        .chunks_exact(3)
        .map(|c| {
            let mut t = [0u32; 3];
            for k in 0..3 {
                t[k] = next.wrapping_sub(c[k]);
                next = next.max(t[k].wrapping_add(1));
            }
            t
        })
        .collect();
    drop(tw);
    let mut prev = 0u32;
    let triangle_ids = get_planes(&payload, &mut pos, nt)?
        .into_iter()
        .map(|d| {
            prev = prev.wrapping_add(d);
            prev
        })
        .collect();
    let counts = get_planes(&payload, &mut pos, nn)?;
    let links = get_planes(&payload, &mut pos, nn)?;
    let mut leaf_start = 0u32;
    let bvh = counts
        .iter()
        .zip(&links)
        .enumerate()
        .map(|(i, (&count, &link))| {
            let predicted = if count > 0 {
                let p = leaf_start;
                leaf_start = leaf_start.wrapping_add(count);
                p
            } else {
                (i as u32).wrapping_add(1)
            };
            BvhNode {
                bounds: Aabb::EMPTY,
                first: link.wrapping_add(predicted),
                count,
            }
        })
        .collect();
    drop(payload);

    let mut v = Voxel {
        bounds: Aabb {
            min: [bounds[0], bounds[1], bounds[2]],
            max: [bounds[3], bounds[4], bounds[5]],
        },
        positions,
        normals,
        colors,
        triangles,
        triangle_ids,
        bvh,
    };
    // The structure is checked once, and the bounds are not checked at
    // all: refitting computes them from validated, finite positions, so
    // every box holds its triangles and children by construction (the
    // check would be a real share of decoding and preparing a voxel,
    // `trace/examples/prepare.rs`; the tests decode and validate).
    v.validate_structure()?;
    bvh::refit(&mut v.bvh, &v.triangles, &v.positions);
    debug_assert!(v.validate_bounds().is_ok());
    Ok(v)
}

thread_local! {
    /// This thread's zstd decompression context, made on its first voxel:
    /// making one for every voxel would add to decoding each
    /// (`trace/examples/prepare.rs`).
    static DECOMPRESSOR: std::cell::RefCell<Option<zstd::bulk::Decompressor<'static>>> =
        const { std::cell::RefCell::new(None) };
}

/// Runs `f` with this thread's decompressor.
fn with_decompressor<T>(
    f: impl FnOnce(&mut zstd::bulk::Decompressor<'static>) -> Result<T, VoxelError>,
) -> Result<T, VoxelError> {
    DECOMPRESSOR.with(|cell| {
        let mut slot = cell.borrow_mut();
        let dec =
            match &mut *slot {
                Some(dec) => dec,
                empty => empty.insert(zstd::bulk::Decompressor::new().map_err(|e| {
                    VoxelError::Decompress(format!("cannot create decompressor: {e}"))
                })?),
            };
        f(dec)
    })
}
