//! `--resume DIR`: which runs DIR already holds, and making its files
//! consistent before the missing runs are appended.

use crate::error::ExperimentError;
use crate::results::{self, FRAMES_CSV, POINTS_CSV};
use std::collections::HashSet;
use std::path::Path;

/// A run: its point's swept values (as CSV cells) and its repeat.
pub(crate) type RunKey = (Vec<String>, u32);

/// The runs recorded in `dir/points.csv`. A row cut short is dropped, and
/// `frames.csv` keeps only the frames of recorded runs, so that the runs
/// about to be redone leave no duplicate.
pub(crate) fn completed(
    dir: &Path,
    points_header: &[String],
    frames_header: &[String],
) -> Result<HashSet<RunKey>, ExperimentError> {
    let points = dir.join(POINTS_CSV);
    if !points.is_file() {
        return Err(ExperimentError::output(
            &points,
            "missing: --resume needs the directory of an earlier run of this experiment",
        ));
    }
    let (lines, cut) = results::read(&points)?;
    if cut {
        results::rewrite(&points, &lines)?;
    }
    let done: HashSet<RunKey> = results::read_points(&points, points_header)?
        .into_iter()
        .map(|r| (r.cells, r.repeat))
        .collect();

    let frames = dir.join(FRAMES_CSV);
    if !frames.is_file() {
        results::create(&frames, frames_header)?;
        return Ok(done);
    }
    let rows = results::read_frames(&frames, frames_header)?;
    let keys = frames_header.len() - results::frame_columns().count();
    let recorded = |row: &Vec<String>| {
        row.len() == frames_header.len()
            && row[keys - 1]
                .parse()
                .is_ok_and(|repeat| done.contains(&(row[..keys - 1].to_vec(), repeat)))
    };
    let kept: Vec<Vec<String>> = std::iter::once(frames_header.to_vec())
        .chain(rows.into_iter().filter(recorded))
        .collect();
    results::rewrite(&frames, &kept)?;
    Ok(done)
}
