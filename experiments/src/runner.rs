//! Running an experiment: check everything, make the model and the walk,
//! run every missing (point, repeat), append its rows, then draw the plots
//! and write the summary.

use crate::engine::{self, RunFailure, RunOutput};
use crate::error::ExperimentError;
use crate::measure::{format_value, Frame, RunFigures, MEASURES};
use crate::model;
use crate::overrides::{path_value, BaseConfig, Origin, Override};
use crate::points::{points, Point};
use crate::results::{self, write_atomic, FRAMES_CSV, POINTS_CSV};
use crate::resume;
use crate::spec::{walk_frames, Engine, Experiment, Route, ENGINE, WALK_FRAMES};
use crate::summary::{self, RunInfo};
use indicatif::{ProgressBar, ProgressDrawTarget, ProgressStyle};
use std::collections::HashSet;
use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

/// Choices of the command line.
#[derive(Clone, Debug)]
pub struct Options {
    /// The results directory (default: `results/NAME/YYYYmmdd-HHMMSS/`
    /// under `results`).
    pub out: Option<PathBuf>,
    /// Go on with the runs missing from this earlier results directory.
    pub resume: Option<PathBuf>,
    /// Each point once, on a tenth of the frames.
    pub quick: bool,
    /// The `dray` binary, which the `cluster` engine starts as nodes.
    pub dray: Option<PathBuf>,
    /// Where generated models are kept between experiments.
    pub models: PathBuf,
    /// Where default results directories go.
    pub results: PathBuf,
}

impl Default for Options {
    fn default() -> Options {
        Options {
            out: None,
            resume: None,
            quick: false,
            dray: None,
            models: PathBuf::from("data/experiments/models"),
            results: PathBuf::from("results"),
        }
    }
}

/// What an experiment did.
#[derive(Clone, Debug)]
pub struct Report {
    /// The results directory.
    pub dir: PathBuf,
    /// Runs of the experiment (points × repeats).
    pub runs_total: usize,
    /// Runs done by this invocation.
    pub runs_done: usize,
    /// Runs found done in the directory (`--resume`).
    pub runs_resumed: usize,
    /// Ctrl-C stopped it; `--resume` goes on.
    pub interrupted: bool,
}

/// Runs the experiment file `file`.
pub fn run(file: &Path, opts: &Options) -> Result<Report, ExperimentError> {
    let exp = Experiment::load(file)?;
    if exp.engines().contains(&Engine::Cluster) && opts.dray.is_none() {
        return Err(ExperimentError::invalid(
            &exp.file,
            "engine",
            "\"cluster\" starts dray processes: run the experiment with the dray binary",
        ));
    }
    let base = BaseConfig::load(&exp.file, &exp.config)?;
    let dir = results_dir(&exp, opts)?;
    let models =
        std::path::absolute(&opts.models).map_err(|e| ExperimentError::output(&opts.models, e))?;
    let points = points(&exp.sweep);
    let repeats = if opts.quick { 1 } else { exp.repeat };
    let database = match &exp.model {
        Some(m) => model::database_path(m, &models),
        None => base.config.scene.database.clone(),
    };
    let plan = Plan {
        fixed: fixed_overrides(&exp, &base, &database, &dir, opts.quick),
        exp: &exp,
        base: &base,
        dir: &dir,
    };
    // Every point's config is checked before anything is made or run.
    for p in &points {
        plan.config(p, 0)?;
    }

    std::fs::create_dir_all(dir.join("runs")).map_err(|e| ExperimentError::output(&dir, e))?;
    let database = match &exp.model {
        Some(m) => model::prepare(m, &models)?,
        None => database,
    };
    let frames = match &exp.walk {
        Some(w) => model::write_walks(
            &exp.file,
            w,
            &exp.swept_walk_frames(),
            &database,
            opts.quick,
            &dir,
        )?,
        None => None,
    };

    let keys = exp.sweep_keys();
    let (points_header, frames_header) =
        (results::points_header(&keys), results::frames_header(&keys));
    let done = if opts.resume.is_some() {
        resume::completed(&dir, &points_header, &frames_header)?
    } else {
        results::create(&dir.join(POINTS_CSV), &points_header)?;
        results::create(&dir.join(FRAMES_CSV), &frames_header)?;
        let text = std::fs::read(&exp.file).map_err(|e| ExperimentError::output(&exp.file, e))?;
        write_atomic(&dir.join("experiment.toml"), &text)?;
        HashSet::new()
    };
    let all: Vec<(&Point, u32)> = points
        .iter()
        .flat_map(|p| (0..repeats).map(move |r| (p, r)))
        .collect();
    let todo: Vec<(&Point, u32)> = all
        .iter()
        .copied()
        .filter(|(p, r)| !done.contains(&(p.cells(), *r)))
        .collect();

    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| ExperimentError::Run {
            run: "start".into(),
            message: format!("the async runtime: {e}"),
        })?;
    let interrupted = Arc::new(AtomicBool::new(false));
    let flag = interrupted.clone();
    rt.spawn(async move {
        if tokio::signal::ctrl_c().await.is_ok() {
            flag.store(true, Ordering::SeqCst);
        }
    });
    let is_interrupted = || interrupted.load(Ordering::SeqCst);

    let mut costs = engine::CostModels::new(exp.virtual_engine.clone());
    let started = now();
    let progress = Progress::new(todo.len());
    let mut runs_done = 0;
    let mut failure = None;
    for (i, &(point, repeat)) in todo.iter().enumerate() {
        if is_interrupted() {
            break;
        }
        let name = point.run_dir_name(repeat);
        progress.start(&format!("{name} {}", point.label()));
        let (cfg, table, run_dir) = plan.config(point, repeat)?;
        std::fs::create_dir_all(&run_dir).map_err(|e| ExperimentError::output(&run_dir, e))?;
        let config_file = run_dir.join("config.toml");
        let text = toml::to_string(&table).map_err(|e| ExperimentError::output(&config_file, e))?;
        write_atomic(&config_file, text.as_bytes())?;
        match engine::run(
            exp.engine_of(point.values.iter().map(|(k, v)| (k.as_str(), v))),
            &cfg,
            &config_file,
            opts.dray.as_deref(),
            &rt,
            &mut costs,
            &is_interrupted,
        ) {
            Ok(out) => {
                let fps = record(&dir, point, repeat, cfg.render.loops, &exp, &out)?;
                runs_done += 1;
                progress.finished(&format!(
                    "run {}/{} {name} {}: {fps} fps, {:.1} s",
                    i + 1,
                    todo.len(),
                    point.label(),
                    out.wall_s
                ));
            }
            Err(RunFailure::Interrupted) => {
                interrupted.store(true, Ordering::SeqCst);
                break;
            }
            Err(RunFailure::Failed(message)) => {
                failure = Some(ExperimentError::Run {
                    run: format!("{name} ({})", point.label()),
                    message,
                });
                break;
            }
        }
    }
    progress.clear();

    // The plots and the summary show every recorded run, also when the
    // experiment stopped early.
    let rows = results::read_points(&dir.join(POINTS_CSV), &points_header)?;
    let frame_rows = if exp.plots.iter().any(|p| p.over_frames()) {
        results::read_frames(&dir.join(FRAMES_CSV), &frames_header)?
    } else {
        Vec::new()
    };
    let plots = crate::plot::draw_all(&dir, &exp.plots, &keys, &rows, &frame_rows)?;
    let info = RunInfo {
        quick: opts.quick,
        repeats,
        frames,
        database: &database,
        started,
        finished: now(),
        runs_total: all.len(),
        interrupted: is_interrupted(),
    };
    summary::write(&dir, &exp, &info, &points, &rows, &plots)?;
    if let Some(e) = failure {
        return Err(e);
    }
    Ok(Report {
        dir,
        runs_total: all.len(),
        runs_done,
        runs_resumed: all.len() - todo.len(),
        interrupted: is_interrupted(),
    })
}

fn now() -> String {
    chrono::Local::now().format("%Y-%m-%d %H:%M:%S").to_string()
}

/// The results directory, absolute: the one resumed, `--out`, or a new
/// `results/NAME/YYYYmmdd-HHMMSS`.
fn results_dir(exp: &Experiment, opts: &Options) -> Result<PathBuf, ExperimentError> {
    let dir = match (&opts.resume, &opts.out) {
        (Some(dir), _) => dir.clone(),
        (None, Some(dir)) => dir.clone(),
        (None, None) => opts
            .results
            .join(&exp.name)
            .join(chrono::Local::now().format("%Y%m%d-%H%M%S").to_string()),
    };
    let dir = std::path::absolute(&dir).map_err(|e| ExperimentError::output(&dir, e))?;
    if opts.resume.is_none() && dir.join(POINTS_CSV).exists() {
        return Err(ExperimentError::output(
            &dir,
            "already holds results: choose another --out, or go on with --resume",
        ));
    }
    Ok(dir)
}

/// The overrides every run shares, in the order they apply: the runner's,
/// the model, the walk, then `[set]`. `dir` is the results directory.
fn fixed_overrides(
    exp: &Experiment,
    base: &BaseConfig,
    database: &Path,
    dir: &Path,
    quick: bool,
) -> Vec<Override> {
    let mut o = vec![
        // Frames cost time and disk; `[set]` can ask for them.
        Override::new(
            Origin::Runner,
            "display.save_frames",
            toml::Value::Boolean(false),
        ),
        // An experiment is never interactive.
        Override {
            origin: Origin::Runner,
            key: "display.web".into(),
            value: None,
        },
    ];
    if exp.model.is_some() {
        o.push(Override::new(
            Origin::Model,
            "scene.database",
            path_value(database),
        ));
    }
    match &exp.walk {
        Some(w) => {
            // A swept walkthrough's path is each point's (`Plan::config`).
            if w.route != Route::SweptFrames {
                o.push(Override::new(
                    Origin::Walk,
                    "render.camera_path",
                    path_value(&model::walk_file(dir, None)),
                ));
            }
            o.push(Override::new(
                Origin::Walk,
                "render.loops",
                toml::Value::Integer(w.loops.into()),
            ));
        }
        None if quick => {
            let frames = model::quick_frames(base.config.render.frames);
            o.push(Override::new(
                Origin::Runner,
                "render.frames",
                toml::Value::Integer(frames.into()),
            ));
        }
        None => {}
    }
    let exp_dir = exp.file.parent().unwrap_or(Path::new("/"));
    o.extend(
        exp.set
            .iter()
            .map(|(k, v)| Override::from_file(Origin::Set, k, v, exp_dir)),
    );
    o
}

/// What every run's config is built from.
struct Plan<'a> {
    exp: &'a Experiment,
    base: &'a BaseConfig,
    fixed: Vec<Override>,
    dir: &'a Path,
}

impl Plan<'_> {
    /// The config of one run, its table and its directory.
    fn config(
        &self,
        point: &Point,
        repeat: u32,
    ) -> Result<(dray_config::Config, toml::Table, PathBuf), ExperimentError> {
        let run_dir = self.dir.join("runs").join(point.run_dir_name(repeat));
        let exp_dir = self.exp.file.parent().unwrap_or(Path::new("/"));
        let mut o = vec![
            Override::new(Origin::Runner, "display.output", path_value(&run_dir)),
            // Certificates for exactly this run's nodes (`cluster` engine).
            Override::new(
                Origin::Runner,
                "certs.dir",
                path_value(&run_dir.join("certs")),
            ),
        ];
        o.extend(self.fixed.iter().cloned());
        // The engine is no config key: the runner picks it per point.
        o.extend(point.values.iter().filter(|(k, _)| k != ENGINE).map(
            |(k, v)| match walk_frames(v) {
                Some(n) if k == WALK_FRAMES => Override::new(
                    Origin::Sweep,
                    "render.camera_path",
                    path_value(&model::walk_file(self.dir, Some(n))),
                ),
                _ => Override::from_file(Origin::Sweep, k, crate::points::config_value(v), exp_dir),
            },
        ));
        let (cfg, table) = self.base.build(&self.exp.file, &o)?;
        Ok((cfg, table, run_dir))
    }
}

/// Appends a finished run's frames and its row; returns its fps, formatted.
fn record(
    dir: &Path,
    point: &Point,
    repeat: u32,
    loops: u32,
    exp: &Experiment,
    out: &RunOutput,
) -> Result<String, ExperimentError> {
    let frames_json = out.summary["frames"]
        .as_array()
        .cloned()
        .unwrap_or_default();
    let frames: Vec<Frame> = frames_json
        .iter()
        .map(|f| serde_json::from_value(f.clone()))
        .collect::<Result<_, _>>()
        .map_err(|e| ExperimentError::Run {
            run: point.run_dir_name(repeat),
            message: format!("the display's summary: {e}"),
        })?;
    let warm = exp.walk.as_ref().is_some_and(|w| w.warm);
    let measured_from = if warm {
        frames.len() - frames.len() / loops.max(1) as usize
    } else {
        0
    };
    let figures = RunFigures {
        measured: &frames[measured_from..],
        wall_s: out.wall_s,
    };
    let mut key = point.cells();
    key.push(repeat.to_string());
    results::append(
        &dir.join(FRAMES_CSV),
        &results::frame_rows(&key, &frames_json, &frames),
    )?;
    let values: Vec<Option<f64>> = MEASURES.iter().map(|m| m.of(&figures)).collect();
    let mut row = key;
    row.extend(values.iter().map(|v| format_value(*v)));
    results::append(&dir.join(POINTS_CSV), &[row])?;
    Ok(format_value(values[0].map(|v| (v * 100.0).round() / 100.0)))
}

/// A bar with ETA over the runs on a terminal, plain lines otherwise.
struct Progress {
    bar: Option<ProgressBar>,
}

impl Progress {
    fn new(runs: usize) -> Progress {
        let bar = std::io::stderr().is_terminal().then(|| {
            let bar =
                ProgressBar::with_draw_target(Some(runs as u64), ProgressDrawTarget::stderr());
            if let Ok(style) = ProgressStyle::with_template(
                "{msg:40!} [{elapsed_precise}] {wide_bar} {pos}/{len} runs (ETA {eta})",
            ) {
                bar.set_style(style);
            }
            bar
        });
        Progress { bar }
    }

    fn start(&self, what: &str) {
        match &self.bar {
            Some(bar) => bar.set_message(what.to_string()),
            None => eprintln!("running {what}"),
        }
    }

    fn finished(&self, line: &str) {
        match &self.bar {
            Some(bar) => {
                bar.println(line);
                bar.inc(1);
            }
            None => eprintln!("{line}"),
        }
    }

    fn clear(&self) {
        if let Some(bar) = &self.bar {
            bar.finish_and_clear();
        }
    }
}
