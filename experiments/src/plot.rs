//! One chart per `[[plot]]`, as SVG and PNG: the median of the repeats as
//! a line with points, the smallest to largest as an error bar.
//!
//! Text is drawn with the DejaVu Sans font embedded from `fonts/`, so
//! plots come out the same on a machine without system fonts.

use crate::error::ExperimentError;
use crate::measure::{measure, spread};
use crate::results::{write_atomic, PointRow};
use crate::spec::Plot;
use plotters::coord::Shift;
use plotters::prelude::*;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Plot size in pixels.
const SIZE: (u32, u32) = (900, 560);

static FONT: &[u8] = include_bytes!("../fonts/DejaVuSans.ttf");

/// One line of a chart: its label and, per x, (x, median, min, max).
struct Series {
    label: String,
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

/// Draws every plot into `dir` from the rows of `points.csv`.
pub(crate) fn draw_all(
    dir: &Path,
    plots: &[Plot],
    sweep_keys: &[&str],
    rows: &[PointRow],
) -> Result<Vec<PlotFiles>, ExperimentError> {
    register_font(dir)?;
    plots
        .iter()
        .enumerate()
        .map(|(i, p)| draw_one(dir, i + 1, p, sweep_keys, rows))
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
/// the unit a key's suffix names, for axis labels.
fn axis_label(key: &str) -> String {
    if let Some(m) = measure(key) {
        return format!("{key} ({})", m.unit);
    }
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

fn series_of(p: &Plot, sweep_keys: &[&str], rows: &[PointRow]) -> Vec<Series> {
    let x = sweep_keys.iter().position(|k| *k == p.x).unwrap_or(0);
    let y = crate::measure::MEASURES
        .iter()
        .position(|m| m.name == p.y)
        .unwrap_or(0);
    // Lines are told apart by every other swept key, the series key first.
    let mut others: Vec<usize> = (0..sweep_keys.len()).filter(|&k| k != x).collect();
    if let Some(s) = sweep_keys
        .iter()
        .position(|k| Some(*k) == p.series.as_deref())
    {
        others.retain(|&k| k != s);
        others.insert(0, s);
    }
    let mut groups: Vec<(Vec<String>, Vec<&PointRow>)> = Vec::new();
    for row in rows {
        let key: Vec<String> = others.iter().map(|&k| row.cells[k].clone()).collect();
        match groups.iter_mut().find(|(k, _)| *k == key) {
            Some((_, members)) => members.push(row),
            None => groups.push((key, vec![row])),
        }
    }
    groups
        .into_iter()
        .map(|(key, members)| {
            let mut xs: Vec<f64> = members
                .iter()
                .filter_map(|r| r.cells[x].parse().ok())
                .collect();
            xs.sort_by(f64::total_cmp);
            xs.dedup();
            let points = xs
                .iter()
                .filter_map(|&xv| {
                    let ys: Vec<f64> = members
                        .iter()
                        .filter(|r| r.cells[x].parse::<f64>().ok() == Some(xv))
                        .filter_map(|r| r.values[y])
                        .collect();
                    spread(&ys).map(|(med, lo, hi)| (xv, med, lo, hi))
                })
                .collect();
            let label = if key.is_empty() {
                p.y.clone()
            } else {
                others
                    .iter()
                    .zip(&key)
                    .map(|(&k, v)| format!("{}={v}", sweep_keys[k]))
                    .collect::<Vec<_>>()
                    .join(", ")
            };
            Series { label, points }
        })
        .collect()
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

fn draw<DB: DrawingBackend>(
    root: DrawingArea<DB, Shift>,
    title: &str,
    p: &Plot,
    series: &[Series],
) -> Result<(), DrawingAreaErrorKind<DB::ErrorType>> {
    root.fill(&WHITE)?;
    let all = series.iter().flat_map(|s| s.points.iter());
    let xs = range(all.clone().map(|q| q.0), false);
    let ys = range(all.flat_map(|q| [q.2, q.3]), true);
    let mut chart = ChartBuilder::on(&root)
        .caption(title, ("sans-serif", 22))
        .margin(16)
        .x_label_area_size(48)
        .y_label_area_size(72)
        .build_cartesian_2d(xs.clone(), ys)?;
    chart
        .configure_mesh()
        .x_desc(axis_label(&p.x))
        .y_desc(axis_label(&p.y))
        .label_style(("sans-serif", 14))
        .axis_desc_style(("sans-serif", 16))
        .draw()?;
    let bar = ((xs.end - xs.start) * 0.006).max(f64::MIN_POSITIVE);
    for (i, s) in series.iter().enumerate() {
        let color = Palette99::pick(i).to_rgba();
        let style = color.stroke_width(2);
        chart
            .draw_series(LineSeries::new(s.points.iter().map(|q| (q.0, q.1)), style))?
            .label(s.label.clone())
            .legend(move |(x, y)| {
                PathElement::new(vec![(x, y), (x + 20, y)], color.stroke_width(2))
            });
        chart.draw_series(
            s.points
                .iter()
                .map(|q| Circle::new((q.0, q.1), 4, color.filled())),
        )?;
        chart.draw_series(s.points.iter().flat_map(|q| {
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
        }))?;
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

fn draw_one(
    dir: &Path,
    n: usize,
    p: &Plot,
    sweep_keys: &[&str],
    rows: &[PointRow],
) -> Result<PlotFiles, ExperimentError> {
    let series = series_of(p, sweep_keys, rows);
    let title = format!("{} against {}", p.y, p.x);
    let short_x = p.x.rsplit('.').next().unwrap_or(&p.x);
    let stem = format!("plot{n}-{}-by-{short_x}", p.y);
    let svg_path: PathBuf = dir.join(format!("{stem}.svg"));
    let png_path: PathBuf = dir.join(format!("{stem}.png"));

    let mut svg = String::new();
    draw(
        SVGBackend::with_string(&mut svg, SIZE).into_drawing_area(),
        &title,
        p,
        &series,
    )
    .map_err(|e| ExperimentError::output(&svg_path, e))?;
    write_atomic(&svg_path, svg.as_bytes())?;

    let (w, h) = SIZE;
    let mut rgb = vec![0u8; (w * h * 3) as usize];
    draw(
        BitMapBackend::with_buffer(&mut rgb, SIZE).into_drawing_area(),
        &title,
        p,
        &series,
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
