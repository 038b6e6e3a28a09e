//! Wavefront OBJ: `v` (optionally with w or r g b), `vn`, `f` in all index
//! forms, negative (relative) indices, polygons as fans. Other statements
//! are ignored. Two passes: the first loads vertices, validates every face
//! and accumulates computed normals; the second emits triangles.

use super::input::Input;
use super::{
    color_channel, Ids, ImportError, ImportOptions, ImportSummary, ModelFormat, ModelProbe,
    VertexTable,
};
use crate::mesh::{Triangle, DEFAULT_COLOR};
use glam::Vec3;
use std::path::Path;

/// How much of the start of the file is checked for binary content.
const SNIFF: usize = 64 << 10;

fn not_text(path: &Path, at: u64, why: &str) -> ImportError {
    ImportError::at_byte(path, at, format!("not a text OBJ file ({why})"))
}

/// Refuses files whose start holds NUL bytes or invalid UTF-8.
fn check_text(inp: &mut Input) -> Result<(), ImportError> {
    let path = inp.path.clone();
    let head = inp.peek(SNIFF)?;
    if let Some(i) = head.iter().position(|&c| c == 0) {
        return Err(not_text(&path, i as u64, "NUL byte"));
    }
    if let Err(e) = std::str::from_utf8(head) {
        // An error at the very end may be a character cut by the sniff window.
        if e.error_len().is_some() || head.len() < SNIFF {
            return Err(not_text(&path, e.valid_up_to() as u64, "invalid UTF-8"));
        }
    }
    Ok(())
}

/// Runs `f` on each line's text with its 1-based number.
fn for_each_line(
    inp: &mut Input,
    mut f: impl FnMut(u64, &str) -> Result<(), ImportError>,
) -> Result<(), ImportError> {
    let path = inp.path.clone();
    inp.seek(0)?;
    let mut line_no = 0u64;
    loop {
        let (s, e) = match inp.line() {
            Ok(Some(r)) => r,
            Ok(None) => return Ok(()),
            Err(Some(e)) => return Err(e),
            Err(None) => {
                return Err(ImportError::at_line(
                    &path,
                    line_no + 1,
                    "line longer than 1 MiB (not a text OBJ file?)",
                ))
            }
        };
        line_no += 1;
        let bytes = &inp.buf[s..e];
        if bytes.contains(&0) {
            return Err(ImportError::at_line(
                &path,
                line_no,
                "not a text OBJ file (NUL byte)",
            ));
        }
        let text = std::str::from_utf8(bytes).map_err(|_| {
            ImportError::at_line(&path, line_no, "not a text OBJ file (invalid UTF-8)")
        })?;
        f(line_no, text)?;
    }
}

fn resolve(s: &str, count: usize, what: &str) -> Result<u32, String> {
    let i: i64 = s
        .parse()
        .map_err(|_| format!("invalid {what} index '{}'", short(s)))?;
    let r = if i > 0 {
        i - 1
    } else if i < 0 {
        count as i64 + i
    } else {
        return Err(format!(
            "{what} index 0 is invalid (OBJ indices start at 1)"
        ));
    };
    if r < 0 || r >= count as i64 {
        return Err(format!(
            "{what} index {i} out of range ({count} defined so far)"
        ));
    }
    Ok(r as u32)
}

fn short(s: &str) -> String {
    s.chars().take(40).collect()
}

/// Parses the corners of an `f` statement: (position index, normal index).
fn parse_face<'a>(
    words: impl Iterator<Item = &'a str>,
    nv: usize,
    nvn: usize,
    corners: &mut Vec<(u32, Option<u32>)>,
) -> Result<(), String> {
    corners.clear();
    for w in words {
        let mut parts = w.split('/');
        let v = parts.next().unwrap_or("");
        let _vt = parts.next();
        let n = parts.next();
        if parts.next().is_some() {
            return Err(format!("invalid face corner '{}'", short(w)));
        }
        let v = resolve(v, nv, "vertex")?;
        let n = match n {
            Some(s) if !s.is_empty() => Some(resolve(s, nvn, "normal")?),
            _ => None,
        };
        corners.push((v, n));
    }
    if corners.len() < 3 {
        return Err(format!(
            "face has {} vertices; a face needs at least 3",
            corners.len()
        ));
    }
    Ok(())
}

fn numbers<'a>(
    words: impl Iterator<Item = &'a str>,
    stmt: &str,
    out: &mut Vec<f64>,
) -> Result<(), String> {
    out.clear();
    for w in words {
        let x: f64 = w
            .parse()
            .map_err(|_| format!("invalid number '{}' in '{stmt}' statement", short(w)))?;
        if x.is_nan() {
            return Err(format!("NaN in '{stmt}' statement"));
        }
        if !(x as f32).is_finite() {
            return Err(format!(
                "infinite number (or one too large for f32) in '{stmt}' statement"
            ));
        }
        out.push(x);
        if out.len() > 16 {
            return Err(format!("too many numbers in '{stmt}' statement"));
        }
    }
    if out.len() < 3 {
        return Err(format!("'{stmt}' statement needs 3 numbers"));
    }
    Ok(())
}

pub(crate) fn import(
    mut inp: Input,
    first_id: u32,
    opts: &ImportOptions,
    sink: &mut dyn FnMut(&Triangle) -> std::io::Result<()>,
) -> Result<ImportSummary, ImportError> {
    check_text(&mut inp)?;
    let path = inp.path.clone();
    let mut table = VertexTable {
        positions: Vec::new(),
        normals: Vec::new(),
        colors: None,
    };
    let mut vn: Vec<Vec3> = Vec::new();
    let mut nums = Vec::new();
    let mut corners = Vec::new();
    let mut tris = 0u64;

    // Pass 1: vertices, normals, validation, computed normals.
    for_each_line(&mut inp, |line, text| {
        let err = |m: String| ImportError::at_line(&path, line, m);
        let mut words = text.split_ascii_whitespace();
        match words.next() {
            Some("v") => {
                numbers(words, "v", &mut nums).map_err(err)?;
                let bytes =
                    VertexTable::bytes_per_vertex(table.colors.is_some() || nums.len() >= 6)
                        * (table.positions.len() as u64 + 1)
                        + 12 * vn.len() as u64;
                if bytes > opts.max_vertex_bytes {
                    return Err(err(format!(
                        "vertex data exceeds the memory budget of {} bytes (ImportOptions::max_vertex_bytes)",
                        opts.max_vertex_bytes
                    )));
                }
                if table.positions.len() >= u32::MAX as usize {
                    return Err(err("more vertices than u32 indices allow".into()));
                }
                let n = table.positions.len();
                if nums.len() >= 6 && table.colors.is_none() {
                    table.colors = Some(vec![DEFAULT_COLOR; n]);
                }
                if let Some(c) = &mut table.colors {
                    c.push(if nums.len() >= 6 {
                        [
                            color_channel(nums[3], true),
                            color_channel(nums[4], true),
                            color_channel(nums[5], true),
                            255,
                        ]
                    } else {
                        DEFAULT_COLOR
                    });
                }
                table
                    .positions
                    .push(Vec3::new(nums[0] as f32, nums[1] as f32, nums[2] as f32));
                table.normals.push(Vec3::ZERO);
            }
            Some("vn") => {
                numbers(words, "vn", &mut nums).map_err(err)?;
                let bytes = VertexTable::bytes_per_vertex(table.colors.is_some())
                    * table.positions.len() as u64
                    + 12 * (vn.len() as u64 + 1);
                if bytes > opts.max_vertex_bytes {
                    return Err(err(format!(
                        "vertex data exceeds the memory budget of {} bytes (ImportOptions::max_vertex_bytes)",
                        opts.max_vertex_bytes
                    )));
                }
                vn.push(
                    Vec3::new(nums[0] as f32, nums[1] as f32, nums[2] as f32).normalize_or_zero(),
                );
            }
            Some("f") => {
                parse_face(words, table.positions.len(), vn.len(), &mut corners).map_err(err)?;
                let a = corners[0].0;
                for w in corners[1..].windows(2) {
                    table.accumulate([a, w[0].0, w[1].0]);
                    tris += 1;
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    if tris == 0 {
        return Err(ImportError::file(&path, "no faces"));
    }
    table.normalize();
    let mut ids = Ids::new(first_id);
    ids.check(&path, tris)?;

    // Pass 2: emit.
    let (mut nv, mut nvn) = (0usize, 0usize);
    let mut emitted = 0u64;
    for_each_line(&mut inp, |line, text| {
        let mut words = text.split_ascii_whitespace();
        match words.next() {
            Some("v") => nv += 1,
            Some("vn") => nvn += 1,
            Some("f") => {
                parse_face(
                    words,
                    nv.min(table.positions.len()),
                    nvn.min(vn.len()),
                    &mut corners,
                )
                .map_err(|m| ImportError::at_line(&path, line, m))?;
                let normal = |c: (u32, Option<u32>)| match c.1 {
                    Some(j) => vn[j as usize],
                    None => table.normals[c.0 as usize],
                };
                let a = corners[0];
                for w in corners[1..].windows(2) {
                    let idx = [a.0, w[0].0, w[1].0];
                    let id = ids.next(&path)?;
                    let t = table.triangle(idx, [normal(a), normal(w[0]), normal(w[1])], id);
                    emitted += 1;
                    sink(&t).map_err(|e| ImportError::sink(&path, e))?;
                }
            }
            _ => {}
        }
        Ok(())
    })?;
    Ok(ImportSummary {
        vertices: table.positions.len() as u64,
        triangles: emitted,
        has_normals: !vn.is_empty(),
        has_colors: table.colors.is_some(),
    })
}

pub(crate) fn probe(mut inp: Input) -> Result<ModelProbe, ImportError> {
    check_text(&mut inp)?;
    let (mut vertices, mut faces) = (0u64, 0u64);
    for_each_line(&mut inp, |_, text| {
        match text.split_ascii_whitespace().next() {
            Some("v") => vertices += 1,
            Some("f") => faces += 1,
            _ => {}
        }
        Ok(())
    })?;
    Ok(ModelProbe {
        format: ModelFormat::Obj,
        vertices,
        faces,
    })
}
