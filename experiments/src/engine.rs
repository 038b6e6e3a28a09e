//! Running one point once, on either engine, and collecting what the
//! display reports.

use crate::spec::Engine;
use dray_actors::cluster::RunOptions;
use dray_config::Config;
use std::path::Path;
use std::time::Instant;

/// What one run reported.
pub(crate) struct RunOutput {
    /// The display's summary (`DisplaySummary::to_json`), with `frames`.
    pub summary: serde_json::Value,
    /// Wall time of the whole run, seconds.
    pub wall_s: f64,
}

/// Why a run gave no result.
pub(crate) enum RunFailure {
    /// Ctrl-C stopped it.
    Interrupted,
    /// It failed.
    Failed(String),
}

/// Runs `cfg` (written at `config_file`, which the `cluster` engine's
/// processes read) until the display has shown every frame. `dray` is the
/// binary the `cluster` engine starts nodes of.
pub(crate) fn run(
    engine: Engine,
    cfg: &Config,
    config_file: &Path,
    dray: Option<&Path>,
    rt: &tokio::runtime::Runtime,
    interrupted: &dyn Fn() -> bool,
) -> Result<RunOutput, RunFailure> {
    let start = Instant::now();
    let summary = match engine {
        Engine::Sim => {
            let run = rt
                .block_on(dray_actors::cluster::sim(cfg, &RunOptions::default()))
                .map_err(|e| RunFailure::Failed(e.to_string()))?;
            run.display.to_json()
        }
        Engine::Cluster => {
            let dray = dray.ok_or_else(|| {
                RunFailure::Failed("engine \"cluster\" needs the dray binary to start nodes".into())
            })?;
            let report = rt
                .block_on(dray_actors::launch::cluster(dray, config_file, cfg, &[]))
                .map_err(|e| match e {
                    dray_actors::launch::LaunchError::Interrupted => RunFailure::Interrupted,
                    e => RunFailure::Failed(e.to_string()),
                })?;
            report.summary
        }
    };
    let wall_s = start.elapsed().as_secs_f64();
    if summary["complete"] != serde_json::Value::Bool(true) {
        if interrupted() {
            return Err(RunFailure::Interrupted);
        }
        let why = summary["stopped_early"]
            .as_str()
            .unwrap_or("not every frame was shown");
        return Err(RunFailure::Failed(format!("the run stopped early: {why}")));
    }
    Ok(RunOutput { summary, wall_s })
}
