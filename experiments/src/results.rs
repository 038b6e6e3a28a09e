//! The result files `points.csv` and `frames.csv`: their columns, rows
//! appended whole, and reading them back.
//!
//! A run's rows are appended when it ends: first its frames to
//! `frames.csv`, then its one row to `points.csv`, each in one write and
//! flushed. `points.csv` is the record of what is done; a run killed
//! between the two writes leaves frames without a point row, which
//! `--resume` removes before running it again.

use crate::error::ExperimentError;
use crate::measure::{derived, format_value, Frame, DERIVED, MEASURES};
use std::fs::OpenOptions;
use std::io::Write;
use std::path::Path;

/// One row per run.
pub const POINTS_CSV: &str = "points.csv";
/// One row per frame of every run.
pub const FRAMES_CSV: &str = "frames.csv";
/// The column after the swept keys, in both files.
pub const REPEAT: &str = "repeat";

/// `points.csv`'s columns: the swept keys, `repeat`, the measures.
pub(crate) fn points_header(sweep_keys: &[&str]) -> Vec<String> {
    let mut h: Vec<String> = sweep_keys.iter().map(|k| k.to_string()).collect();
    h.push(REPEAT.into());
    h.extend(MEASURES.iter().map(|m| m.name.to_string()));
    h
}

/// `frames.csv`'s columns: the swept keys, `repeat`, the frame's.
pub(crate) fn frames_header(sweep_keys: &[&str]) -> Vec<String> {
    let mut h: Vec<String> = sweep_keys.iter().map(|k| k.to_string()).collect();
    h.push(REPEAT.into());
    h.extend(frame_columns().map(str::to_string));
    h
}

/// A frame's columns in `frames.csv`: the display's `metrics.csv`
/// columns, then the rates the runner derives from them.
pub(crate) fn frame_columns() -> impl Iterator<Item = &'static str> {
    display_columns().chain(DERIVED)
}

fn display_columns() -> impl Iterator<Item = &'static str> {
    dray_actors::display::CSV_HEADER.split(',')
}

/// The `frames.csv` rows of one run: `key` (its swept values and repeat)
/// and each frame of the display's summary (`json`, read as `frames`).
pub(crate) fn frame_rows(
    key: &[String],
    json: &[serde_json::Value],
    frames: &[Frame],
) -> Vec<Vec<String>> {
    json.iter()
        .zip(derived(frames))
        .map(|(f, derived)| {
            let mut row = key.to_vec();
            row.extend(display_columns().map(|col| match &f[col] {
                serde_json::Value::String(s) => s.clone(),
                serde_json::Value::Number(n) => match n.as_u64() {
                    Some(i) => i.to_string(),
                    None => format_value(n.as_f64()),
                },
                serde_json::Value::Null => String::new(),
                other => other.to_string(),
            }));
            row.extend(derived.iter().map(|v| format_value(Some(*v))));
            row
        })
        .collect()
}

fn csv_bytes(rows: &[Vec<String>], path: &Path) -> Result<Vec<u8>, ExperimentError> {
    let mut w = csv::Writer::from_writer(Vec::new());
    for row in rows {
        w.write_record(row)
            .map_err(|e| ExperimentError::output(path, e))?;
    }
    w.into_inner().map_err(|e| ExperimentError::output(path, e))
}

/// Writes a file under a temporary name and renames it over `path`, so
/// that `path` is never seen half-written.
pub(crate) fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), ExperimentError> {
    let name = path
        .file_name()
        .map(|n| n.to_string_lossy().into_owned())
        .unwrap_or_default();
    let tmp = path.with_file_name(format!(".{name}.tmp"));
    std::fs::write(&tmp, bytes).map_err(|e| ExperimentError::output(&tmp, e))?;
    std::fs::rename(&tmp, path).map_err(|e| ExperimentError::output(path, e))
}

/// Makes a CSV file holding only its header.
pub(crate) fn create(path: &Path, header: &[String]) -> Result<(), ExperimentError> {
    write_atomic(path, &csv_bytes(&[header.to_vec()], path)?)
}

/// Rewrites a CSV file with these rows (header first).
pub(crate) fn rewrite(path: &Path, rows: &[Vec<String>]) -> Result<(), ExperimentError> {
    write_atomic(path, &csv_bytes(rows, path)?)
}

/// Appends whole rows in one write, flushed to the disk.
pub(crate) fn append(path: &Path, rows: &[Vec<String>]) -> Result<(), ExperimentError> {
    let bytes = csv_bytes(rows, path)?;
    let mut f = OpenOptions::new()
        .append(true)
        .open(path)
        .map_err(|e| ExperimentError::output(path, e))?;
    f.write_all(&bytes)
        .and_then(|()| f.sync_data())
        .map_err(|e| ExperimentError::output(path, e))
}

/// A CSV file's rows, header first, without a last line cut short (a
/// process killed while appending): only lines ended by a newline count.
/// The flag says whether such a partial line was left out.
pub(crate) fn read(path: &Path) -> Result<(Vec<Vec<String>>, bool), ExperimentError> {
    let bytes = std::fs::read(path).map_err(|e| ExperimentError::output(path, e))?;
    let whole = bytes.iter().rposition(|&b| b == b'\n').map_or(0, |i| i + 1);
    let mut r = csv::ReaderBuilder::new()
        .has_headers(false)
        .flexible(true)
        .from_reader(&bytes[..whole]);
    let rows = r
        .records()
        .map(|rec| rec.map(|rec| rec.iter().map(str::to_string).collect()))
        .collect::<Result<Vec<Vec<String>>, _>>()
        .map_err(|e| ExperimentError::output(path, e))?;
    Ok((rows, whole < bytes.len()))
}

/// The rows of `frames.csv` after its header, checked against the
/// expected one.
pub(crate) fn read_frames(
    path: &Path,
    header: &[String],
) -> Result<Vec<Vec<String>>, ExperimentError> {
    let (mut rows, _) = read(path)?;
    if rows.first().map(Vec::as_slice) != Some(header) {
        return Err(ExperimentError::output(
            path,
            "its columns are not this experiment's",
        ));
    }
    rows.remove(0);
    Ok(rows)
}

/// A row of `points.csv` read back.
#[derive(Clone, Debug, PartialEq)]
pub struct PointRow {
    /// The swept values, as written.
    pub cells: Vec<String>,
    /// Which run of the point.
    pub repeat: u32,
    /// The measures, in [`MEASURES`] order (None: empty cell).
    pub values: Vec<Option<f64>>,
}

/// Every row of `points.csv`, checked against the expected header.
pub(crate) fn read_points(
    path: &Path,
    header: &[String],
) -> Result<Vec<PointRow>, ExperimentError> {
    let (rows, _) = read(path)?;
    let Some((head, rows)) = rows.split_first() else {
        return Err(ExperimentError::output(path, "empty: no header"));
    };
    if head != header {
        return Err(ExperimentError::output(
            path,
            format!(
                "its columns ({}) are not this experiment's ({})",
                head.join(","),
                header.join(",")
            ),
        ));
    }
    let keys = header.len() - 1 - MEASURES.len();
    rows.iter()
        .enumerate()
        .map(|(i, row)| {
            let bad = |what: &str| ExperimentError::output(path, format!("row {}: {what}", i + 2));
            if row.len() != header.len() {
                return Err(bad("has the wrong number of columns"));
            }
            let repeat = row[keys]
                .parse()
                .map_err(|_| bad("repeat is not a number"))?;
            let values = row[keys + 1..]
                .iter()
                .map(|c| {
                    if c.is_empty() {
                        Ok(None)
                    } else {
                        c.parse().map(Some)
                    }
                })
                .collect::<Result<_, _>>()
                .map_err(|_| bad("a measure is not a number"))?;
            Ok(PointRow {
                cells: row[..keys].to_vec(),
                repeat,
                values,
            })
        })
        .collect()
}
