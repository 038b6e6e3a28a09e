//! `dray experiment FILE.toml`: scripted experiments on the distributed
//! renderer. An experiment file names a base cluster config, a model, a
//! camera walk, fixed overrides and a sweep of config keys; every
//! combination of the swept values (a *point*) is run `repeat` times on
//! the in-process engine (`dray sim`), as processes over QUIC (`dray
//! cluster`) or, for a baseline, in one process holding the whole model
//! (`dray render --path`), and the results land in one directory: `points.csv`,
//! `frames.csv`, a plot per `[[plot]]` (SVG and PNG) and `summary.md`.
//! The file format, the outputs and the columns are documented in
//! `docs/experiments.md`.
//!
//! The layout of the crate:
//!
//! * [`spec`]: the experiment file, and every check that needs no run;
//! * `overrides`: a run's config, the base config's TOML with keys set by
//!   dotted path, validated by `dray_config`, errors naming the key;
//! * [`points`]: the sweep's combinations;
//! * `model`: the generated plant (kept in a cache) and the walk;
//! * `engine`: one run on one engine, and what the display reported (or,
//!   for `render`, the same figures of the frames it traced);
//! * [`measure`]: the measured columns, computed from the frames;
//! * `results`: `points.csv` and `frames.csv`, rows appended whole;
//! * `resume`: what an earlier results directory already holds;
//! * `plot`: the charts; `summary`: `summary.md`;
//! * `runner`: all of it in order, with a progress bar.
//!
//! Nothing is left half-written: files are written under a temporary name
//! and renamed, CSV rows are appended whole when a run ends, and Ctrl-C
//! abandons the run under way (it records nothing) and stops;
//! `--resume DIR` goes on with the runs missing.

mod engine;
mod error;
pub mod measure;
mod model;
mod overrides;
mod plot;
pub mod points;
mod results;
mod resume;
mod runner;
pub mod spec;
mod summary;

pub use error::ExperimentError;
pub use results::{FRAMES_CSV, POINTS_CSV, REPEAT};
pub use runner::{run, Options, Report};
