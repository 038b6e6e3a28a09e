//! The experiment file: its format, and every check that needs no run.
//!
//! ```toml
//! name = "latency-hiding"
//! config = "../config/examples/local.toml"   # relative to this file
//! engine = "sim"                             # or "cluster"
//! repeat = 3
//! [model]  generate = "plant", triangles = 1_000_000, seed = 1   # or database = "PATH"
//! [walk]   frames = 60, loops = 1, warm = false                  # or camera_path = "PATH"
//! [set]    "clients.count" = 2
//! [sweep]  "clients.miss_mode" = ["suspend", "block"], "walk.frames" = [60, 30]
//! [[plot]] x = "…", y = "fps", series = "…"        # a swept key against measures
//! [[plot]] x = "frame", y = ["fps", "voxel_mb_raw_per_s"]   # over the frames
//! ```
//!
//! Every key is documented in `docs/experiments.md`.

use crate::error::ExperimentError;
use crate::measure::{frame_column, measure, FRAME, FRAME_COLUMNS, MEASURES};
use dray_actors::display::CameraPath;
use serde::Deserialize;
use std::path::{Path, PathBuf};

/// How the frames of a run are made.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Engine {
    /// Every node in this process over the in-process transport (`dray sim`).
    Sim,
    /// Every node as a process over QUIC (`dray cluster`).
    Cluster,
    /// No cluster: this process renders every frame with the whole model
    /// loaded, on as many threads as the clients have together (`dray
    /// render --path`): the baseline a cluster's efficiency is measured by.
    Render,
    /// `sim` on a virtual clock: tracing and decoding charged from a cost
    /// model calibrated on this machine, as if each client had a machine
    /// of its own (`dray sim --virtual`).
    Virtual,
}

/// Every engine, in the order the documentation lists them.
pub const ENGINES: [Engine; 4] = [
    Engine::Sim,
    Engine::Cluster,
    Engine::Render,
    Engine::Virtual,
];

/// The key that sweeps the engine, like a config key.
pub const ENGINE: &str = "engine";

impl Engine {
    /// The name the file uses.
    pub fn name(self) -> &'static str {
        match self {
            Engine::Sim => "sim",
            Engine::Cluster => "cluster",
            Engine::Render => "render",
            Engine::Virtual => "virtual",
        }
    }

    /// The engine called `name`.
    pub fn from_name(name: &str) -> Option<Engine> {
        ENGINES.into_iter().find(|e| e.name() == name)
    }
}

/// The model every run renders.
#[derive(Clone, Debug, PartialEq)]
pub enum Model {
    /// A voxel database made by `dray preprocess`.
    Database(PathBuf),
    /// A generated plant, preprocessed once into the model cache.
    Plant {
        /// Triangles of the plant.
        triangles: u64,
        /// The generator's seed.
        seed: u64,
    },
}

/// Where the camera goes: a path file, or a generated walkthrough.
#[derive(Clone, Debug, PartialEq)]
pub enum Route {
    /// A camera path file.
    File(PathBuf),
    /// The walkthrough of `dray walkthrough` with this many frames.
    Frames(u32),
    /// The walkthrough with the frames the sweep's [`WALK_FRAMES`] gives
    /// each point.
    SweptFrames,
}

/// The one swept key that is not a config key: the frames of the
/// walkthrough, flown along the same keyframes, so that fewer frames
/// mean a faster camera.
pub const WALK_FRAMES: &str = "walk.frames";

/// The camera path of every run.
#[derive(Clone, Debug, PartialEq)]
pub struct Walk {
    /// The path.
    pub route: Route,
    /// Times the path is flown.
    pub loops: u32,
    /// Only the last loop is measured.
    pub warm: bool,
    /// A generated walkthrough flies only its part inside the model.
    pub inside: bool,
}

/// One `[[plot]]`.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Plot {
    /// A swept key with numbers for values, or [`FRAME`]: a plot over the
    /// frames of `frames.csv`.
    pub x: String,
    /// Measured columns (of `frames.csv` for a plot over the frames), one
    /// or a list: `y = "fps"` or `y = ["fps", "voxel_mb_raw_per_s"]`.
    #[serde(deserialize_with = "one_or_many")]
    pub y: Vec<String>,
    /// A swept key: one line per value.
    pub series: Option<String>,
    /// The horizontal axis: `"linear"` (the default) or `"log"`, for a
    /// sweep over powers (1, 2, 4, … 1024 clients).
    #[serde(default)]
    pub x_scale: Scale,
}

/// How an axis maps values.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum Scale {
    #[default]
    Linear,
    Log,
}

impl Plot {
    /// Whether it is drawn over the frames (from `frames.csv`).
    pub fn over_frames(&self) -> bool {
        self.x == FRAME
    }

    /// The unit of a y column.
    pub fn unit(&self, y: &str) -> &'static str {
        let unit = if self.over_frames() {
            frame_column(y).map(|c| c.unit)
        } else {
            measure(y).map(|m| m.unit)
        };
        unit.unwrap_or("")
    }
}

fn one_or_many<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Vec<String>, D::Error> {
    #[derive(Deserialize)]
    #[serde(untagged)]
    enum Columns {
        One(String),
        Many(Vec<String>),
    }
    match Columns::deserialize(d)? {
        Columns::One(y) => Ok(vec![y]),
        Columns::Many(ys) => Ok(ys),
    }
}

/// A checked experiment file.
#[derive(Clone, Debug)]
pub struct Experiment {
    /// The file, as an absolute path.
    pub file: PathBuf,
    /// Names the results directory.
    pub name: String,
    /// One line for the summary.
    pub description: String,
    /// The base cluster config, as an absolute path.
    pub config: PathBuf,
    /// How nodes start.
    pub engine: Engine,
    /// Runs per point.
    pub repeat: u32,
    /// The model; none: the base config's `scene.database`.
    pub model: Option<Model>,
    /// The camera path; none: the base config's.
    pub walk: Option<Walk>,
    /// Fixed config overrides: dotted key and value, in key order.
    pub set: Vec<(String, toml::Value)>,
    /// Swept config keys and their values, in key order.
    pub sweep: Vec<(String, Vec<toml::Value>)>,
    /// The plots.
    pub plots: Vec<Plot>,
    /// How the `virtual` engine runs.
    pub virtual_engine: VirtualEngine,
}

/// The `[virtual]` table: how the `virtual` engine runs.
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct VirtualEngine {
    /// Every client on one host of this many cores (to compare with
    /// `sim` on this machine); none: a machine each.
    pub host_cores: Option<u32>,
    /// A fixed cost model instead of calibrating one (every key of
    /// [`dray_actors::costs::CostModel`]): runs that repeat exactly.
    pub cost: Option<dray_actors::costs::CostModel>,
    /// With `host_cores`: the real engine whose host's overhead is
    /// measured, `sim` (the default) or `cluster`.
    #[serde(default)]
    pub host_overhead: HostOverhead,
}

/// The real engine a virtual run on one host stands for.
#[derive(Clone, Copy, Debug, Default, Deserialize, serde::Serialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum HostOverhead {
    #[default]
    Sim,
    Cluster,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct File {
    name: String,
    #[serde(default)]
    description: String,
    config: PathBuf,
    engine: Engine,
    #[serde(default = "one")]
    repeat: u32,
    model: Option<ModelFile>,
    walk: Option<WalkFile>,
    #[serde(default)]
    set: toml::Table,
    #[serde(default)]
    sweep: toml::Table,
    #[serde(default)]
    plot: Vec<Plot>,
    #[serde(default, rename = "virtual")]
    virtual_engine: VirtualEngine,
}

fn one() -> u32 {
    1
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct ModelFile {
    database: Option<PathBuf>,
    generate: Option<String>,
    triangles: Option<u64>,
    seed: Option<u64>,
}

#[derive(Deserialize)]
#[serde(deny_unknown_fields)]
struct WalkFile {
    camera_path: Option<PathBuf>,
    frames: Option<u32>,
    loops: Option<u32>,
    warm: Option<bool>,
    inside: Option<bool>,
}

/// Most runs per point.
const MAX_REPEAT: u32 = 1000;
/// Most times a path is flown (the config's `render.loops` limit).
const MAX_LOOPS: u32 = 1000;
/// Most frames of a walkthrough (the camera path file's limit).
const MAX_FRAMES: u32 = 100_000;

impl Experiment {
    /// Reads and checks an experiment file: every key, the model's
    /// database or generator parameters, the camera path, the plots.
    pub fn load(file: &Path) -> Result<Experiment, ExperimentError> {
        let file = std::path::absolute(file).map_err(|e| ExperimentError::Unreadable {
            file: file.to_path_buf(),
            message: e.to_string(),
        })?;
        let text = std::fs::read_to_string(&file).map_err(|e| ExperimentError::Unreadable {
            file: file.clone(),
            message: e.to_string(),
        })?;
        let raw: File = toml::from_str(&text).map_err(|e| ExperimentError::Unreadable {
            file: file.clone(),
            message: e.to_string(),
        })?;
        let dir = file.parent().unwrap_or(Path::new("/")).to_path_buf();
        let bad = |key: &str, problem: String| ExperimentError::invalid(&file, key, problem);

        if raw.name.is_empty()
            || !raw
                .name
                .chars()
                .all(|c| c.is_ascii_alphanumeric() || "-_.".contains(c))
            || raw.name.starts_with('.')
        {
            return Err(bad(
                "name",
                format!(
                    "{:?} must be letters, digits, '-', '_' or '.' (it names a directory)",
                    raw.name
                ),
            ));
        }
        if !(1..=MAX_REPEAT).contains(&raw.repeat) {
            return Err(bad(
                "repeat",
                format!("{} is not in 1..={MAX_REPEAT}", raw.repeat),
            ));
        }
        let config = dir.join(&raw.config);
        if !config.is_file() {
            return Err(bad("config", format!("{}: no such file", config.display())));
        }
        let model = raw.model.map(|m| model(&file, &dir, m)).transpose()?;

        let set = flatten(raw.set);
        let mut sweep = Vec::new();
        for (key, values) in flatten(raw.sweep) {
            let label = format!("[sweep] {key}");
            let toml::Value::Array(values) = values else {
                return Err(bad(&label, "must be a list of values".into()));
            };
            if values.is_empty() {
                return Err(bad(&label, "the list is empty".into()));
            }
            if set.iter().any(|(k, _)| *k == key) {
                return Err(bad(&label, "is also in [set]".into()));
            }
            if key == WALK_FRAMES {
                check_walk_frames(&file, &values)?;
            }
            if key == ENGINE {
                check_engines(&file, &values)?;
            }
            sweep.push((key, values));
        }
        let frames_swept = sweep.iter().any(|(k, _)| k == WALK_FRAMES);
        let walk = match raw.walk {
            Some(w) => Some(walk(&file, &dir, w, frames_swept)?),
            // A swept walkthrough needs no [walk] table: flown once.
            None if frames_swept => Some(Walk {
                route: Route::SweptFrames,
                loops: 1,
                warm: false,
                inside: false,
            }),
            None => None,
        };
        for (i, p) in raw.plot.iter().enumerate() {
            check_plot(&file, i, p, &sweep)?;
        }
        if let Some(cost) = &raw.virtual_engine.cost {
            cost.validate("virtual.cost")
                .map_err(|e| ExperimentError::invalid(&file, "virtual.cost", e))?;
        }
        if raw.virtual_engine.host_overhead != HostOverhead::Sim
            && raw.virtual_engine.host_cores.is_none()
        {
            return Err(bad(
                "virtual.host_overhead",
                "only means something with virtual.host_cores".into(),
            ));
        }
        if let Some(n) = raw.virtual_engine.host_cores {
            if !(1..=4096).contains(&n) {
                return Err(bad("virtual.host_cores", format!("{n} is not in 1..=4096")));
            }
        }
        Ok(Experiment {
            name: raw.name,
            description: raw.description,
            config,
            engine: raw.engine,
            repeat: raw.repeat,
            model,
            walk,
            set,
            sweep,
            plots: raw.plot,
            virtual_engine: raw.virtual_engine,
            file,
        })
    }

    /// The engine of a point whose swept values are `values`: the swept
    /// [`ENGINE`], or the file's.
    pub fn engine_of<'a>(
        &self,
        mut values: impl Iterator<Item = (&'a str, &'a toml::Value)>,
    ) -> Engine {
        values
            .find(|(k, _)| *k == ENGINE)
            .and_then(|(_, v)| v.as_str().and_then(Engine::from_name))
            .unwrap_or(self.engine)
    }

    /// Every engine some point runs on.
    pub fn engines(&self) -> Vec<Engine> {
        match self.sweep.iter().find(|(k, _)| k == ENGINE) {
            Some((_, values)) => values
                .iter()
                .filter_map(|v| v.as_str().and_then(Engine::from_name))
                .collect(),
            None => vec![self.engine],
        }
    }

    /// The swept keys, in order.
    pub fn sweep_keys(&self) -> Vec<&str> {
        self.sweep.iter().map(|(k, _)| k.as_str()).collect()
    }

    /// The frames of the walkthrough the sweep gives ([`WALK_FRAMES`];
    /// empty when it is not swept).
    pub fn swept_walk_frames(&self) -> Vec<u32> {
        self.sweep
            .iter()
            .filter(|(k, _)| k == WALK_FRAMES)
            .flat_map(|(_, values)| values.iter().filter_map(walk_frames))
            .collect()
    }
}

fn model(file: &Path, dir: &Path, m: ModelFile) -> Result<Model, ExperimentError> {
    let bad = |key: &str, problem: String| ExperimentError::invalid(file, key, problem);
    match (m.database, m.generate) {
        (Some(db), None) => {
            if m.triangles.is_some() || m.seed.is_some() {
                return Err(bad(
                    "model.database",
                    "triangles and seed go with generate, not with database".into(),
                ));
            }
            let db = dir.join(db);
            dray_scene::db::Database::open(&db)
                .map_err(|e| bad("model.database", e.to_string()))?;
            Ok(Model::Database(db))
        }
        (None, Some(kind)) => {
            if kind != "plant" {
                return Err(bad(
                    "model.generate",
                    format!("{kind:?} is not a generator (the one there is: \"plant\")"),
                ));
            }
            let Some(triangles) = m.triangles else {
                return Err(bad("model.triangles", "is required with generate".into()));
            };
            let range = dray_scene::generate::MIN_TRIANGLES..=dray_scene::generate::MAX_TRIANGLES;
            if !range.contains(&triangles) {
                return Err(bad(
                    "model.triangles",
                    format!("{triangles} is not in {}..={}", range.start(), range.end()),
                ));
            }
            Ok(Model::Plant {
                triangles,
                seed: m.seed.unwrap_or(1),
            })
        }
        _ => Err(bad(
            "model",
            "needs either database = \"PATH\" or generate = \"plant\"".into(),
        )),
    }
}

fn walk(file: &Path, dir: &Path, w: WalkFile, frames_swept: bool) -> Result<Walk, ExperimentError> {
    let bad = |key: &str, problem: String| ExperimentError::invalid(file, key, problem);
    let route = match (w.camera_path, w.frames) {
        (None, None) if frames_swept => Route::SweptFrames,
        (camera_path, _) if frames_swept => {
            let key = if camera_path.is_some() {
                "walk.camera_path"
            } else {
                "walk.frames"
            };
            return Err(bad(
                key,
                format!(
                    "goes with no [sweep] {WALK_FRAMES} (the sweep gives the walkthrough's frames)"
                ),
            ));
        }
        (Some(p), None) => {
            let p = dir.join(p);
            CameraPath::load(&p).map_err(|e| bad("walk.camera_path", e.to_string()))?;
            Route::File(p)
        }
        (None, Some(n)) if (1..=MAX_FRAMES).contains(&n) => Route::Frames(n),
        (None, Some(n)) => {
            return Err(bad(
                "walk.frames",
                format!("{n} is not in 1..={MAX_FRAMES}"),
            ))
        }
        _ => {
            return Err(bad(
                "walk",
                "needs either camera_path = \"PATH\" or frames = N".into(),
            ))
        }
    };
    let loops = w.loops.unwrap_or(1);
    if !(1..=MAX_LOOPS).contains(&loops) {
        return Err(bad(
            "walk.loops",
            format!("{loops} is not in 1..={MAX_LOOPS}"),
        ));
    }
    let inside = w.inside.unwrap_or(false);
    if inside && matches!(route, Route::File(_)) {
        return Err(bad(
            "walk.inside",
            "takes part of the generated walkthrough, not of a camera_path".into(),
        ));
    }
    Ok(Walk {
        route,
        loops,
        warm: w.warm.unwrap_or(false),
        inside,
    })
}

/// The swept frames of the walkthrough: each a whole number of frames.
fn check_walk_frames(file: &Path, values: &[toml::Value]) -> Result<(), ExperimentError> {
    for v in values {
        let ok = v
            .as_integer()
            .is_some_and(|n| (1..=i64::from(MAX_FRAMES)).contains(&n));
        if !ok {
            return Err(ExperimentError::invalid(
                file,
                format!("[sweep] {WALK_FRAMES} = {v}"),
                format!("frames of the walkthrough must be whole numbers in 1..={MAX_FRAMES}"),
            ));
        }
    }
    Ok(())
}

/// The swept engines: each a name of one.
fn check_engines(file: &Path, values: &[toml::Value]) -> Result<(), ExperimentError> {
    for v in values {
        if v.as_str().and_then(Engine::from_name).is_none() {
            let names: Vec<String> = ENGINES.iter().map(|e| format!("{:?}", e.name())).collect();
            return Err(ExperimentError::invalid(
                file,
                format!("[sweep] {ENGINE} = {v}"),
                format!("is not an engine ({})", names.join(", ")),
            ));
        }
    }
    Ok(())
}

/// Most units of the y columns of one plot: one per side of the chart.
const MAX_PLOT_UNITS: usize = 2;

fn check_plot(
    file: &Path,
    i: usize,
    p: &Plot,
    sweep: &[(String, Vec<toml::Value>)],
) -> Result<(), ExperimentError> {
    let bad = |key: &str, problem: String| {
        ExperimentError::invalid(file, format!("plot[{i}].{key}"), problem)
    };
    let swept = sweep
        .iter()
        .map(|(k, _)| k.as_str())
        .collect::<Vec<_>>()
        .join(", ");
    if !p.over_frames() {
        let Some((_, xs)) = sweep.iter().find(|(k, _)| *k == p.x) else {
            return Err(bad(
                "x",
                format!("{:?} is not a swept key or {FRAME:?} (swept: {swept})", p.x),
            ));
        };
        if let Some(v) = xs.iter().find(|v| number(v).is_none()) {
            return Err(bad(
                "x",
                format!("{:?} sweeps {v}, not a number: x must be numeric", p.x),
            ));
        }
        let not_positive = xs.iter().find(|v| number(v).is_some_and(|x| x <= 0.0));
        if let Some(v) = not_positive.filter(|_| p.x_scale == Scale::Log) {
            return Err(bad(
                "x_scale",
                format!(
                    "\"log\", but {:?} sweeps {v}: a log axis needs values above 0",
                    p.x
                ),
            ));
        }
    }
    let (columns, what): (Vec<&str>, &str) = if p.over_frames() {
        (
            FRAME_COLUMNS.iter().map(|c| c.name).collect(),
            "a column of frames.csv",
        )
    } else {
        (
            MEASURES.iter().map(|m| m.name).collect(),
            "a measured column",
        )
    };
    if p.y.is_empty() {
        return Err(bad("y", "names no column".into()));
    }
    if let Some(y) = p.y.iter().find(|y| !columns.contains(&y.as_str())) {
        return Err(bad(
            "y",
            format!("{y:?} is not {what} ({})", columns.join(", ")),
        ));
    }
    let mut units: Vec<&str> = p.y.iter().map(|y| p.unit(y)).collect();
    units.sort_unstable();
    units.dedup();
    if units.len() > MAX_PLOT_UNITS {
        return Err(bad(
            "y",
            format!(
                "has columns in {} units ({}): a chart has one axis per side",
                units.len(),
                units.join(", ")
            ),
        ));
    }
    if let Some(s) = &p.series {
        if *s == p.x || !sweep.iter().any(|(k, _)| k == s) {
            return Err(bad(
                "series",
                format!("{s:?} is not a swept key other than x (swept: {swept})"),
            ));
        }
    }
    Ok(())
}

/// A value of [`WALK_FRAMES`] as frames (checked when the file loads).
pub(crate) fn walk_frames(v: &toml::Value) -> Option<u32> {
    v.as_integer().and_then(|n| u32::try_from(n).ok())
}

/// A TOML number as f64.
pub(crate) fn number(v: &toml::Value) -> Option<f64> {
    if let Some((label, _)) = crate::points::labelled(v) {
        return number(label);
    }
    match v {
        toml::Value::Integer(i) => Some(*i as f64),
        toml::Value::Float(f) => Some(*f),
        _ => None,
    }
}

/// `[set]` and `[sweep]` accept `"clients.count" = 2` and the nested
/// `clients.count = 2` (or `[set.clients]`) alike: both become the dotted
/// key `clients.count`.
fn flatten(table: toml::Table) -> Vec<(String, toml::Value)> {
    let mut out = Vec::new();
    for (key, value) in table {
        match value {
            toml::Value::Table(t) => {
                out.extend(
                    flatten(t)
                        .into_iter()
                        .map(|(k, v)| (format!("{key}.{k}"), v)),
                );
            }
            v => out.push((key, v)),
        }
    }
    out
}
