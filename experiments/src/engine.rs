//! Running one point once, on one engine, and collecting what the display
//! reports (or, for `render`, the same figures of the frames it traced).

use crate::spec::{Engine, HostOverhead, VirtualEngine};
use dray_actors::costs::{Calibration, CostModel, HostEngine, VirtualRun};
use dray_actors::nodes::RunOptions;
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

/// The `virtual` engine's cost models, measured once per kind of run.
pub(crate) struct CostModels {
    spec: VirtualEngine,
    /// Calibrations by what they depend on: the model, the render
    /// settings, the kernel, the threads and (on one host) the clients.
    measured: std::collections::BTreeMap<String, Calibration>,
}

/// The file in a run's directory that holds the cost model it ran with.
pub(crate) const CALIBRATION_JSON: &str = "calibration.json";

impl CostModels {
    pub fn new(spec: VirtualEngine) -> CostModels {
        CostModels {
            spec,
            measured: Default::default(),
        }
    }

    /// The cost model for `cfg`: the file's fixed one, or measured on this
    /// machine (once for every run alike).
    fn for_run(
        &mut self,
        cfg: &Config,
        config_file: &Path,
        dray: Option<&Path>,
    ) -> Result<(CostModel, Option<Calibration>), String> {
        if let Some(fixed) = self.spec.cost {
            return Ok((fixed, None));
        }
        let isa = dray_trace::render::Isa::detect();
        let clients = cfg.clients.count;
        let threads = dray_actors::costs::calibration_threads(cfg, clients, self.spec.host_cores);
        let key = format!(
            "{}|{:?}|{}|{threads}|{}|{:?}",
            cfg.scene.database.display(),
            cfg.render,
            isa.name(),
            self.spec.host_cores.map_or(0, |_| clients),
            self.spec.host_overhead,
        );
        if let Some(c) = self.measured.get(&key) {
            return Ok((c.model, Some(c.clone())));
        }
        let engine = match self.spec.host_overhead {
            HostOverhead::Sim => HostEngine::Sim,
            HostOverhead::Cluster => HostEngine::Cluster {
                dray: dray.ok_or("measuring the cluster's overhead needs the dray binary")?,
                config_file,
            },
        };
        let c = dray_actors::costs::measure(cfg, clients, isa, self.spec.host_cores, &engine)?;
        self.measured.insert(key, c.clone());
        Ok((c.model, Some(c)))
    }

    /// The virtual run of `cfg`, its cost model written beside
    /// `config_file`.
    fn prepare(
        &mut self,
        cfg: &Config,
        config_file: &Path,
        dray: Option<&Path>,
    ) -> Result<VirtualRun, RunFailure> {
        let (cost, calibration) = self
            .for_run(cfg, config_file, dray)
            .map_err(|e| RunFailure::Failed(format!("calibrating the cost model: {e}")))?;
        let record = serde_json::json!({
            "model": cost,
            "calibration": calibration,
            "host_cores": self.spec.host_cores,
            "host_overhead": self.spec.host_cores.map(|_| self.spec.host_overhead),
            "speed": cfg.clients.speed,
            "decode_speed": cfg.clients.decode_speed,
        });
        let file = config_file.with_file_name(CALIBRATION_JSON);
        std::fs::write(&file, format!("{record:#}\n"))
            .map_err(|e| RunFailure::Failed(format!("{}: {e}", file.display())))?;
        Ok(VirtualRun {
            cost,
            host_cores: self.spec.host_cores,
        })
    }
}

/// Runs `cfg` (written at `config_file`, which the `cluster` engine's
/// processes read) until the display has shown every frame. `dray` is the
/// binary the `cluster` engine starts nodes of; `costs` gives the
/// `virtual` engine its cost model (which is written beside the config).
pub(crate) fn run(
    engine: Engine,
    cfg: &Config,
    config_file: &Path,
    dray: Option<&Path>,
    rt: &tokio::runtime::Runtime,
    costs: &mut CostModels,
    interrupted: &dyn Fn() -> bool,
) -> Result<RunOutput, RunFailure> {
    let mut start = Instant::now();
    let summary = match engine {
        Engine::Sim => {
            let run = rt
                .block_on(dray_actors::nodes::sim(cfg, &RunOptions::default()))
                .map_err(|e| RunFailure::Failed(e.to_string()))?;
            run.display.to_json()
        }
        Engine::Render => render(cfg).map_err(RunFailure::Failed)?,
        Engine::Virtual => {
            let run = costs.prepare(cfg, config_file, dray)?;
            // Calibrating is not the run.
            start = Instant::now();
            dray_actors::nodes::sim_virtual(cfg, &RunOptions::default(), run)
                .map_err(|e| RunFailure::Failed(e.to_string()))?
                .display
                .to_json()
        }
        Engine::Cluster => {
            let dray = dray.ok_or_else(|| {
                RunFailure::Failed("engine \"cluster\" needs the dray binary to start nodes".into())
            })?;
            let report = rt
                .block_on(dray_actors::supervisor::cluster(
                    dray,
                    config_file,
                    cfg,
                    &[],
                ))
                .map_err(|e| match e {
                    dray_actors::supervisor::LaunchError::Interrupted => RunFailure::Interrupted,
                    e => RunFailure::Failed(e.to_string()),
                })?;
            report.summary
        }
    };
    finished(summary, start.elapsed().as_secs_f64(), interrupted)
}

/// A run's output, or why it has none: it stopped before every frame.
fn finished(
    summary: serde_json::Value,
    wall_s: f64,
    interrupted: &dyn Fn() -> bool,
) -> Result<RunOutput, RunFailure> {
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

/// The `render` engine: every frame of the run's cameras (each camera's
/// `render.samples` samples, as the cluster renders them) traced in this
/// process with the whole model loaded, on as many threads as the clients
/// have together, reported as the display reports a cluster's frames
/// (nothing fetched, no link used). Loading is not timed, as a client's
/// preload is not.
fn render(cfg: &Config) -> Result<serde_json::Value, String> {
    use dray_actors::settings::{kernel_camera, kernel_settings, wire_settings};
    let db = dray_scene::db::Database::open(&cfg.scene.database)
        .map_err(|e| format!("scene.database: {e}"))?;
    let source =
        dray_trace::accel::ResidentSource::load(&db).map_err(|e| format!("scene.database: {e}"))?;
    let top = dray_trace::accel::TopLevel::from_manifest(&db.manifest);
    let cameras = dray_actors::nodes::frame_cameras(cfg).map_err(|e| e.to_string())?;
    let threads = (cfg.clients.count as usize).saturating_mul(cfg.clients.threads as usize);
    let settings = kernel_settings(
        &wire_settings(&cfg.render),
        db.manifest.model_bounds.diagonal(),
        threads,
        dray_trace::render::Isa::detect(),
    );
    let (w, h) = (cfg.render.width, cfg.render.height);
    let samples = cfg.render.samples.max(1);
    let mut frames = Vec::with_capacity(cameras.len() * samples as usize);
    let each_sample = cameras
        .iter()
        .flat_map(|c| (0..samples).map(move |k| (c, k)));
    for (i, (c, sample)) in each_sample.enumerate() {
        let camera = kernel_camera(c, w, h);
        let frame = dray_trace::render::render_sample(&top, &source, &camera, sample, &settings)
            .map_err(|id| format!("voxel {id} was not loaded"))?;
        let s = &frame.stats;
        let stats = dray_protocol::FrameStats {
            rays: s.primary_rays + s.shadow_rays + s.reflection_rays,
            time_us: (s.seconds * 1e6) as u64,
            ..Default::default()
        };
        frames.push(dray_actors::display::FrameMetrics::compute(
            i as u64,
            &stats,
            s.seconds * 1e3,
        ));
    }
    let seconds: f64 = frames.iter().map(|f| f.frame_ms).sum::<f64>() / 1e3;
    Ok(serde_json::json!({
        "complete": true,
        "seconds": seconds,
        "frames": frames,
    }))
}
