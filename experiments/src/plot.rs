//! One chart per `[[plot]]`, as SVG and PNG: the median of the repeats as
//! a line with points, the smallest to largest as an error bar; or, over
//! the frames, the median of the repeats per frame as a plain line. The
//! columns of a second unit are drawn against a right-hand axis.
//!
//! Text is drawn with the DejaVu Sans font embedded from `fonts/`, so
//! plots come out the same on a machine without system fonts.

use crate::error::ExperimentError;
use crate::measure::{spread, FRAME, MEASURES};
use crate::results::{frame_columns, write_atomic, PointRow};
use crate::spec::{Plot, WALK_FRAMES};
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Plot size in pixels.
const SIZE: (u32, u32) = (900, 560);

static FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// One line of a chart: its label, its axis, and per x (x, median, min,
/// max) over the repeats.
#[derive(Clone)]
struct Line {
    label: String,
    /// Drawn against the right-hand axis (the plot's second unit).
    secondary: bool,
    points: Vec<(f64, f64, f64, f64)>,
}

/// The files of one plot, relative to the results directory.
#[derive(Clone, Debug)]
pub struct PlotFiles {
    /// Caption: `Y against X`.
    pub title: String,
    /// The SVG file's name.
    pub svg: String,
    /// The PNG file's name.
    pub png: String,
}

/// Draws every plot into `dir`: from the rows of `points.csv`, or over
/// the frames from the rows of `frames.csv` (`frames`, without header).
pub(crate) fn draw_all(
    dir: &Path,
    plots: &[Plot],
    sweep_keys: &[&str],
    rows: &[PointRow],
    frames: &[Vec<String>],
) -> Result<Vec<PlotFiles>, ExperimentError> {
    register_font(dir)?;
    plots
        .iter()
        .enumerate()
        .map(|(i, p)| {
            let lines = if p.over_frames() {
                frame_lines(p, sweep_keys, frames)
            } else {
                point_lines(p, sweep_keys, rows)
            };
            draw_one(dir, i + 1, p, &lines)
        })
        .collect()
}

fn register_font(dir: &Path) -> Result<(), ExperimentError> {
    static REGISTERED: OnceLock<bool> = OnceLock::new();
    let ok = *REGISTERED.get_or_init(|| {
        plotters::style::register_font("sans-serif", FontStyle::Normal, FONT).is_ok()
    });
    if ok {
        Ok(())
    } else {
        Err(ExperimentError::output(
            dir,
            "the embedded font is not a valid font",
        ))
    }
}

/// `links.client_store.latency_ms` → `links.client_store.latency_ms (ms)`:
/// the x axis's label, with the unit a key's suffix names.
fn x_label(key: &str) -> String {
    match key {
        FRAME => "frame (number, from 0)".into(),
        WALK_FRAMES => format!("{WALK_FRAMES} (frames of the walk: fewer = faster camera)"),
        _ => {
            let units = [
                ("_mbps", "Mbit/s"),
                ("_ms", "ms"),
                ("_mb", "MB"),
                ("_px", "pixels"),
                ("_deg", "degrees"),
                ("_s", "s"),
            ];
            match units.iter().find(|(suffix, _)| key.ends_with(suffix)) {
                Some((_, unit)) => format!("{key} ({unit})"),
                None => key.to_string(),
            }
        }
    }
}

/// A y axis's label: its columns and their unit, `fps (frames/s)`.
fn y_label(p: &Plot, secondary: bool) -> String {
    let columns: Vec<&str> =
        p.y.iter()
            .filter(|y| is_secondary(p, y) == secondary)
            .map(String::as_str)
            .collect();
    let unit = columns.first().map_or("", |y| p.unit(y));
    format!("{} ({unit})", columns.join(", "))
}

/// Whether column `y` goes on the right-hand axis: its unit is not the
/// first column's.
fn is_secondary(p: &Plot, y: &str) -> bool {
    p.unit(y) != p.unit(&p.y[0])
}

/// The swept keys that tell a plot's lines apart, by index: every one but
/// x, the series key first.
fn line_keys(p: &Plot, sweep_keys: &[&str]) -> Vec<usize> {
    let mut keys: Vec<usize> = (0..sweep_keys.len())
        .filter(|&k| sweep_keys[k] != p.x)
        .collect();
    if let Some(s) = sweep_keys
        .iter()
        .position(|k| Some(*k) == p.series.as_deref())
    {
        keys.retain(|&k| k != s);
        keys.insert(0, s);
    }
    keys
}

/// Rows grouped by their values of the swept keys `keys` (`cells` gives a
/// row's swept values), in the order first seen.
fn groups<'r, R>(
    rows: &'r [R],
    cells: impl Fn(&R) -> &[String],
    keys: &[usize],
) -> Vec<(Vec<String>, Vec<&'r R>)> {
    let mut groups: Vec<(Vec<String>, Vec<&R>)> = Vec::new();
    for row in rows {
        let key: Vec<String> = keys.iter().map(|&k| cells(row)[k].clone()).collect();
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => members.push(row),
            None => groups.push((key, vec![row])),
        }
    }
    groups
}

/// A line's label: the column when the plot has several, and the values
/// of the keys that tell its group apart.
fn line_label(p: &Plot, y: &str, sweep_keys: &[&str], keys: &[usize], values: &[String]) -> String {
    let mut parts: Vec<String> = Vec::new();
    if p.y.len() > 1 || keys.is_empty() {
        parts.push(y.to_string());
    }
    parts.extend(
        keys.iter()
            .zip(values)
            .map(|(&k, v)| format!("{}={v}", sweep_keys[k])),
    );
    parts.join(", ")
}

/// (x, y) samples as (x, median, min, max) per distinct x, by x.
fn by_x(samples: impl Iterator<Item = (f64, f64)>) -> Vec<(f64, f64, f64, f64)> {
    let mut samples: Vec<(f64, f64)> = samples.collect();
    samples.sort_by(|a, b| a.0.total_cmp(&b.0));
    samples
        .chunk_by(|a, b| a.0 == b.0)
        .filter_map(|same_x| {
            let ys: Vec<f64> = same_x.iter().map(|s| s.1).collect();
            spread(&ys).map(|(median, lo, hi)| (same_x[0].0, median, lo, hi))
        })
        .collect()
}

/// The lines of a plot of `points.csv`: per group and y column, the
/// measure at each swept x.
fn point_lines(p: &Plot, sweep_keys: &[&str], rows: &[PointRow]) -> Vec<Line> {
    let x = sweep_keys.iter().position(|k| *k == p.x).unwrap_or(0);
    let keys = line_keys(p, sweep_keys);
    let mut lines = Vec::new();
    for (values, members) in groups(rows, |r| &r.cells, &keys) {
        for y in &p.y {
            let column = MEASURES.iter().position(|m| m.name == *y).unwrap_or(0);
            let samples = members
                .iter()
                .filter_map(|r| Some((r.cells[x].parse().ok()?, r.values[column]?)));
            lines.push(Line {
                label: line_label(p, y, sweep_keys, &keys, &values),
                secondary: is_secondary(p, y),
                points: by_x(samples),
            });
        }
    }
    lines
}

/// The lines of a plot over the frames: per group and y column, the
/// column at each frame number (the median over the repeats).
fn frame_lines(p: &Plot, sweep_keys: &[&str], frames: &[Vec<String>]) -> Vec<Line> {
    // A frames.csv row: the swept values, repeat, then the frame's columns.
    let column =
        |name: &str| sweep_keys.len() + 1 + frame_columns().position(|c| c == name).unwrap_or(0);
    let frame = column(FRAME);
    let keys = line_keys(p, sweep_keys);
    let mut lines = Vec::new();
    for (values, members) in groups(frames, |r| r.as_slice(), &keys) {
        for y in &p.y {
            let c = column(y);
            let samples = members
                .iter()
                .filter_map(|r| Some((r.get(frame)?.parse().ok()?, r.get(c)?.parse().ok()?)));
            lines.push(Line {
                label: line_label(p, y, sweep_keys, &keys, &values),
                secondary: is_secondary(p, y),
                points: by_x(samples),
            });
        }
    }
    lines
}

/// Axis range over the values with a margin; from 0 when all are positive
/// (a measure's size is read against zero).
fn range(values: impl Iterator<Item = f64>, from_zero: bool) -> std::ops::Range<f64> {
    let (lo, hi) = values.fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), v| {
        (lo.min(v), hi.max(v))
    });
    if !lo.is_finite() {
        return 0.0..1.0;
    }
    let lo = if from_zero && lo >= 0.0 { 0.0 } else { lo };
    let pad = if hi > lo {
        (hi - lo) * 0.06
    } else {
        lo.abs().max(1.0) * 0.5
    };
    let start = if from_zero && lo == 0.0 {
        0.0
    } else {
        lo - pad
    };
    start..hi + pad
}

/// The y range of the lines on one axis (the whole spread of the repeats).
fn y_range(lines: &[Line], secondary: bool) -> std::ops::Range<f64> {
    let values = lines
        .iter()
        .filter(|l| l.secondary == secondary)
        .flat_map(|l| l.points.iter().flat_map(|q| [q.2, q.3]));
    range(values, true)
}

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    p: &Plot,
    lines: &[Line],
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    // A log axis is a linear one over log2(x), labelled with x.
    let log = p.x_scale == crate::spec::Scale::Log;
    let lines: Vec<Line> = if log {
        lines
            .iter()
            .map(|l| Line {
                points: l
                    .points
                    .iter()
                    .map(|q| (q.0.log2(), q.1, q.2, q.3))
                    .collect(),
                ..l.clone()
            })
            .collect()
    } else {
        lines.to_vec()
    };
    let lines = &lines;
    let xs = range(
        lines.iter().flat_map(|l| l.points.iter().map(|q| q.0)),
        false,
    );
    let x_text = |v: &f64| {
        let x = if log { v.exp2() } else { *v };
        let r = (x * 100.0).round() / 100.0;
        if r == r.trunc() {
            format!("{r:.0}")
        } else {
            format!("{r}")
        }
    };
    let two_axes = lines.iter().any(|l| l.secondary);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(72)
        .right_y_label_area_size(if two_axes { 72 } else { 0 })
        .build_cartesian_2d(xs.clone(), y_range(lines, false))?
        .set_secondary_coord(xs.clone(), y_range(lines, true));
    chart
        .configure_mesh()
        .x_label_formatter(&x_text)
        .x_desc(x_label(&p.x))
        .y_desc(y_label(p, false))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()?;
    if two_axes {
        chart
            .configure_secondary_axes()
            .y_desc(y_label(p, true))
            .label_style(("sans-serif", 14))
            .axis_desc_style(("sans-serif", 16))
            .draw()?;
    }
    // A plot over the frames has a point per frame: a plain line reads
    // best there; a sweep's few points get markers and the repeats' spread.
    let marked = !p.over_frames();
    let bar = ((xs.end - xs.start) * 0.006).max(f64::MIN_POSITIVE);
    for (i, line) in lines.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let path = LineSeries::new(
            line.points.iter().map(|q| (q.0, q.1)),
            color.stroke_width(2),
        );
        let markers = line
            .points
            .iter()
            .filter(|_| marked)
            .map(|q| Circle::new((q.0, q.1), 4, color.filled()));
        let bars = line.points.iter().filter(|_| marked).flat_map(|q| {
            [
                PathElement::new(vec![(q.0, q.2), (q.0, q.3)], color.stroke_width(1)),
                PathElement::new(
                    vec![(q.0 - bar, q.2), (q.0 + bar, q.2)],
                    color.stroke_width(1),
                ),
                PathElement::new(
                    vec![(q.0 - bar, q.3), (q.0 + bar, q.3)],
                    color.stroke_width(1),
                ),
            ]
        });
        let anno = if line.secondary {
            chart.draw_secondary_series(markers)?;
            chart.draw_secondary_series(bars)?;
            chart.draw_secondary_series(path)?
        } else {
            chart.draw_series(markers)?;
            chart.draw_series(bars)?;
            chart.draw_series(path)?
        };
        let axis = if two_axes && line.secondary {
            " (right)"
        } else {
            ""
        };
        anno.label(format!("{}{axis}", line.label))
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
    }
    chart
        .configure_series_labels()
        .background_style(WHITE.mix(0.85))
        .border_style(BLACK)
        .label_font(("sans-serif", 14))
        .position(SeriesLabelPosition::UpperRight)
        .draw()?;
    root.present()
}

fn draw_one(dir: &Path, n: usize, p: &Plot, lines: &[Line]) -> Result<PlotFiles, ExperimentError> {
    let title = format!("{} against {}", p.y.join(" and "), p.x);
    let short_x = p.x.rsplit('.').next().unwrap_or(&p.x);
    let stem = format!("plot{n}-{}-by-{short_x}", p.y.join("-"));
    let svg_path: PathBuf = dir.join(format!("{stem}.svg"));
    let png_path: PathBuf = dir.join(format!("{stem}.png"));

    let mut svg = String::new();
    draw(
        SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(),
        &title,
        p,
        lines,
    )
    .map_err(|e| ExperimentError::output(&svg_path, e))?;
    write_atomic(&svg_path, svg.as_bytes())?;

    let (w, h) = SIZE;
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    draw(
        BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area(),
        &title,
        p,
        lines,
    )
    .map_err(|e| ExperimentError::output(&png_path, e))?;
    write_atomic(
        &png_path,
        &encode_png(&rgb, w, h).map_err(|e| ExperimentError::output(&png_path, e))?,
    )?;

    Ok(PlotFiles {
        title,
        svg: format!("{stem}.svg"),
        png: format!("{stem}.png"),
    })
}

fn encode_png(rgb: &[u8], w: u32, h: u32) -> Result<Vec<u8>, png::EncodingError> {
    let mut out = Vec::new();
    let mut enc = png::Encoder::new(&mut out, w, h);
    enc.set_color(png::ColorType::Rgb);
    enc.set_depth(png::BitDepth::Eight);
    let mut writer = enc.write_header()?;
    writer.write_image_data(rgb)?;
    writer.finish()?;
    Ok(out)
}
