//! `summary.md`: what ran, on which machine and commit, the medians of
//! every point, and the plots.

use crate::error::ExperimentError;
use crate::measure::{format_value, spread, MEASURES};
use crate::plot::PlotFiles;
use crate::points::{cell, Point};
use crate::results::{write_atomic, PointRow, FRAMES_CSV, POINTS_CSV};
use crate::spec::{Experiment, Model, Route};
use std::path::{Component, Path, PathBuf};
use std::process::Command;

/// What the summary tells besides the experiment file and the rows.
pub(crate) struct RunInfo<'a> {
    pub quick: bool,
    pub repeats: u32,
    pub frames: Option<u32>,
    pub database: &'a Path,
    pub started: String,
    pub finished: String,
    pub runs_total: usize,
    pub interrupted: bool,
}

/// The `virtual` engine's cost models, from its runs' `calibration.json`:
/// one row per distinct model, with the runs that used it.
fn cost_models(dir: &Path) -> String {
    let mut models: Vec<(serde_json::Value, Vec<String>)> = Vec::new();
    let mut runs: Vec<_> = std::fs::read_dir(dir.join("runs"))
        .into_iter()
        .flatten()
        .flatten()
        .map(|e| e.path())
        .collect();
    runs.sort();
    for run in runs {
        let file = run.join(crate::engine::CALIBRATION_JSON);
        let Some(v) = std::fs::read_to_string(&file)
            .ok()
            .and_then(|t| serde_json::from_str::<serde_json::Value>(&t).ok())
        else {
            continue;
        };
        let name = run
            .file_name()
            .map(|n| n.to_string_lossy().into_owned())
            .unwrap_or_default();
        match models.iter_mut().find(|(m, _)| *m == v) {
            Some((_, names)) => names.push(name),
            None => models.push((v, vec![name])),
        }
    }
    if models.is_empty() {
        return String::new();
    }
    let mut s = String::from(
        "## Cost model of the virtual engine\n\n\
         Nanoseconds per unit of work of a client core, measured on this machine \
         (`calibrated`: traced tiles of the run's views on `threads` threads at once, \
         fitted by least squares with fit R²; `fixed`: given by the file), \
         before `clients.speed` (tracing) and `clients.decode_speed` divide them. Each run's: `runs/*/calibration.json`.\n\n\
         | runs | source | threads | tiles | R² | tile | primary ray | secondary ray | voxel visit | decoded byte | host pixel | host cores | speed | decode speed |\n\
         |---|---|---|---|---|---|---|---|---|---|---|---|---|---|\n",
    );
    for (v, names) in &models {
        let m = &v["model"];
        let c = &v["calibration"];
        let num =
            |x: &serde_json::Value| x.as_f64().map_or("–".into(), |f| format!("{}", round3(f)));
        let runs = if names.len() > 3 {
            format!(
                "{} … {} ({})",
                names[0],
                names[names.len() - 1],
                names.len()
            )
        } else {
            names.join(", ")
        };
        s += &format!(
            "| {runs} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} | {} |\n",
            if c.is_null() { "fixed" } else { "calibrated" },
            num(&c["threads"]),
            num(&c["tiles"]),
            num(&c["r2"]),
            num(&m["ns_per_tile"]),
            num(&m["ns_per_primary_ray"]),
            num(&m["ns_per_secondary_ray"]),
            num(&m["ns_per_voxel_visit"]),
            num(&m["ns_per_decoded_byte"]),
            num(&m["ns_per_pixel_host"]),
            v["host_cores"]
                .as_u64()
                .map_or("–".into(), |n| n.to_string()),
            num(&v["speed"]),
            num(&v["decode_speed"]),
        );
    }
    s + "\n"
}

/// The CPU model, cores and the kernel's instruction set.
fn machine() -> String {
    let cpu = std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|text| {
            text.lines()
                .find(|l| l.starts_with("model name"))
                .and_then(|l| l.split_once(':'))
                .map(|(_, v)| v.trim().to_string())
        })
        .unwrap_or_else(|| "unknown CPU".into());
    let cores = std::thread::available_parallelism().map_or(0, |n| n.get());
    let isa = dray_trace::render::Isa::detect().name();
    format!("{cpu}, {cores} cores, kernel ISA {isa}")
}

/// `git rev-parse --short HEAD` where the experiment file is, marked when
/// the work tree has changes; "unknown" outside a repository.
fn commit(dir: &Path) -> String {
    let git = |args: &[&str]| {
        Command::new("git")
            .args(args)
            .current_dir(dir)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_string())
    };
    match git(&["rev-parse", "--short", "HEAD"]) {
        Some(hash) => match git(&["status", "--porcelain", "--untracked-files=no"]) {
            Some(changes) if !changes.is_empty() => format!("{hash} (with uncommitted changes)"),
            _ => hash,
        },
        None => "unknown".into(),
    }
}

/// A path as the summary shows it: without `dir/..` steps, and relative
/// to the current directory when inside it (so that a committed summary
/// reads `experiments/x.toml`), absolute otherwise.
fn shown(path: &Path) -> PathBuf {
    // Lexical: `experiments/../config` is `config` unless `experiments`
    // is a link, and the summary only names the file.
    let mut clean = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir
                if matches!(clean.components().next_back(), Some(Component::Normal(_))) =>
            {
                clean.pop();
            }
            Component::CurDir => {}
            c => clean.push(c),
        }
    }
    let relative = std::env::current_dir()
        .ok()
        .and_then(|cwd| clean.strip_prefix(cwd).ok().map(Path::to_path_buf))
        .filter(|p| !p.as_os_str().is_empty());
    relative.unwrap_or(clean)
}

fn table_cell(s: &str) -> String {
    s.replace('|', "\\|")
}

/// Writes `dir/summary.md`.
pub(crate) fn write(
    dir: &Path,
    exp: &Experiment,
    info: &RunInfo,
    points: &[Point],
    rows: &[PointRow],
    plots: &[PlotFiles],
) -> Result<(), ExperimentError> {
    let mut s = format!("# {}\n\n", exp.name);
    if !exp.description.is_empty() {
        s += &format!("{}\n\n", exp.description);
    }
    let model = match &exp.model {
        Some(Model::Plant { triangles, seed }) => {
            format!("generated plant, {triangles} triangles, seed {seed}")
        }
        Some(Model::Database(_)) | None => "database".into(),
    };
    let walk = match exp.walk.as_ref().map(|w| (&w.route, w.loops, w.warm)) {
        Some((Route::Frames(_), loops, warm)) => format!(
            "walkthrough, {loops} loop(s){}",
            if warm { ", last loop measured" } else { "" }
        ),
        Some((Route::SweptFrames, loops, warm)) => format!(
            "walkthrough with the frames of `walk.frames` (`walks/`), {loops} loop(s){}",
            if warm { ", last loop measured" } else { "" }
        ),
        Some((Route::File(p), loops, warm)) => format!(
            "{}, {loops} loop(s){}",
            shown(p).display(),
            if warm { ", last loop measured" } else { "" }
        ),
        None => "the base config's camera".into(),
    };
    let frames = info
        .frames
        .map_or(String::new(), |f| format!(" of {f} frames"));
    s += &format!(
        "| | |\n|---|---|\n\
         | experiment | `{}` |\n\
         | base config | `{}` |\n\
         | engine | {} |\n\
         | model | {model} (`{}`) |\n\
         | walk | {walk}{frames} |\n\
         | runs | {} of {} ({} per point{}){} |\n\
         | started | {} |\n\
         | finished | {} |\n\
         | machine | {} |\n\
         | commit | {} |\n\n",
        shown(&exp.file).display(),
        shown(&exp.config).display(),
        exp.engines()
            .iter()
            .map(|e| e.name())
            .collect::<Vec<_>>()
            .join(", "),
        shown(info.database).display(),
        rows.len(),
        info.runs_total,
        info.repeats,
        if info.quick { ", --quick" } else { "" },
        if info.interrupted {
            ", interrupted"
        } else {
            ""
        },
        info.started,
        info.finished,
        machine(),
        commit(exp.file.parent().unwrap_or(Path::new("."))),
    );
    if !exp.set.is_empty() {
        s += "Fixed (`[set]`): ";
        let parts: Vec<String> = exp
            .set
            .iter()
            .map(|(k, v)| format!("`{k} = {v}`"))
            .collect();
        s += &parts.join(", ");
        s += "\n\n";
    }
    if !exp.sweep.is_empty() {
        s += "Swept (`[sweep]`, every combination): ";
        let parts: Vec<String> = exp
            .sweep
            .iter()
            .map(|(k, vs)| {
                let vs: Vec<String> = vs.iter().map(cell).collect();
                format!("`{k}` = {}", vs.join(", "))
            })
            .collect();
        s += &parts.join("; ");
        s += "\n\n";
    }

    if exp.engines().contains(&crate::spec::Engine::Virtual) {
        s += &cost_models(dir);
    }
    s += "## Medians\n\nThe median over the repeats of each point; `runs` is how many there are.\n\n";
    let mut header: Vec<String> = exp.sweep_keys().iter().map(|k| format!("`{k}`")).collect();
    header.push("runs".into());
    header.extend(MEASURES.iter().map(|m| format!("{} ({})", m.name, m.unit)));
    s += &format!(
        "| {} |\n|{}\n",
        header.join(" | "),
        "---|".repeat(header.len())
    );
    for p in points {
        let cells = p.cells();
        let mine: Vec<&PointRow> = rows.iter().filter(|r| r.cells == cells).collect();
        let mut line: Vec<String> = cells.iter().map(|c| table_cell(c)).collect();
        line.push(mine.len().to_string());
        for (i, _) in MEASURES.iter().enumerate() {
            let values: Vec<f64> = mine.iter().filter_map(|r| r.values[i]).collect();
            line.push(format_value(
                spread(&values).map(|(median, _, _)| round3(median)),
            ));
        }
        s += &format!("| {} |\n", line.join(" | "));
    }
    s += &format!(
        "\nEvery run: [`{POINTS_CSV}`]({POINTS_CSV}); every frame: [`{FRAMES_CSV}`]({FRAMES_CSV}); \
         each run's config and `metrics.csv`: `runs/`.\n"
    );
    if !plots.is_empty() {
        s += "\n## Plots\n\nThe line joins the medians; the bars span the smallest to the largest run.\n\n";
        for p in plots {
            s += &format!("![{}]({})\n\n[SVG]({})\n\n", p.title, p.png, p.svg);
        }
    }
    write_atomic(&dir.join("summary.md"), s.as_bytes())
}

/// Three significant digits, enough for a table read by people.
fn round3(v: f64) -> f64 {
    if v == 0.0 || !v.is_finite() {
        return v;
    }
    let scale = 10f64.powi(2 - v.abs().log10().floor() as i32);
    (v * scale).round() / scale
}
