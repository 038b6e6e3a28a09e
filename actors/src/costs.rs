//! The virtual engine's cost model: what a client's tracing and decoding
//! would take on a real machine, charged to the virtual clock
//! ([`crate::nodes::sim_virtual`]) instead of measured.
//!
//! A render thread's time is linear in the work it counts
//! ([`dray_trace::work::Work`]): a cost per tile started, per primary ray,
//! per shadow or reflection ray and per voxel a packet enters (the
//! top-level walk, and a proxy for the nodes and triangles behind it). A
//! decode costs a time per byte of the voxel after decompression. Where
//! the clients share one host, each finished pixel also costs the host
//! what its other actors spend on it.
//!
//! [`calibrate`] measures the tracing and decoding costs on this machine,
//! with the run's own model, views and kernel: it traces tiles of the
//! run's cameras with every voxel resident, on as many threads at once as
//! a client has (or as the shared host has cores), timing each; fits the
//! tile costs by least squares; and times the decoding of a sample of the
//! database's voxels. [`measure_host_overhead`] measures the host's cost
//! by running the real engine. `clients.speed` scales the tracing costs
//! (2 is a client twice as fast as this machine's core),
//! `clients.decode_speed` the decoding cost.

use crate::settings::{kernel_camera, kernel_settings, wire_settings};
use dray_config::Config;
use dray_trace::accel::{PreparedVoxel, ResidentSource, TopLevel, VoxelRef, VoxelSource};
use dray_trace::render::{Isa, PacketChooser, Packets, RenderSettings};
use dray_trace::tile::{render_tile_sample, LoadError, MissMode, Rect, VoxelLoader};
use dray_trace::work::Work;
use futures::future::BoxFuture;
use serde::{Deserialize, Serialize};
use std::path::Path;
use std::sync::Arc;
use std::time::{Duration, Instant};

/// What the virtual engine gives each client: the cost model (already
/// scaled by `clients.speed` and `clients.decode_speed`), the process's
/// shared decoded voxels and, where the clients share one host, its cores.
#[derive(Clone)]
pub struct VirtualClock {
    pub cost: CostModel,
    pub voxels: Arc<crate::client::shared_voxels::DecodedVoxels>,
    /// Where every client runs on one host of this many cores (to
    /// compare with a `sim` run on this machine): its render threads and
    /// decodes take turns on them, a poll's work at a time. `None`: each
    /// client has a machine of its own.
    pub cores: Option<Arc<tokio::sync::Semaphore>>,
}

impl std::fmt::Debug for VirtualClock {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("VirtualClock")
            .field("cost", &self.cost)
            .finish_non_exhaustive()
    }
}

/// A run on the virtual clock ([`crate::nodes::sim_virtual`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct VirtualRun {
    /// The cost model as measured (`clients.speed` scales it per run).
    pub cost: CostModel,
    /// Every client on one host of this many cores
    /// ([`VirtualClock::cores`]); `None`: a machine each.
    pub host_cores: Option<u32>,
}

/// Nanoseconds a client spends per unit of work, on a core as fast as the
/// one the model was calibrated on.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CostModel {
    /// Per tile started (its buffers, its set-up).
    pub ns_per_tile: f64,
    /// Per primary ray.
    pub ns_per_primary_ray: f64,
    /// Per shadow or reflection ray.
    pub ns_per_secondary_ray: f64,
    /// Per voxel entered by a packet.
    pub ns_per_voxel_visit: f64,
    /// Per byte of a voxel after decompression, to verify, decode and
    /// prepare it.
    pub ns_per_decoded_byte: f64,
    /// Per pixel of the tiles finished, what every other actor of a host
    /// running the whole cluster spends on them (the client's actor, the
    /// display, the scheduler, the stores, the transport): charged only
    /// where the clients share one host ([`VirtualRun::host_cores`]).
    #[serde(default)]
    pub ns_per_pixel_host: f64,
}

impl CostModel {
    /// The model in `file`: a virtual run's `calibration.json` (its
    /// `model`, as the experiment engine writes it) or the model's keys
    /// alone, as JSON; checked by [`Self::validate`]. Errors name `file`.
    pub fn read(file: &Path) -> Result<CostModel, String> {
        let at = file.display();
        let text = std::fs::read_to_string(file).map_err(|e| format!("{at}: {e}"))?;
        let mut v: serde_json::Value =
            serde_json::from_str(&text).map_err(|e| format!("{at}: not JSON: {e}"))?;
        if let Some(model) = v.get_mut("model") {
            v = model.take();
        }
        let model: CostModel =
            serde_json::from_value(v).map_err(|e| format!("{at}: not a cost model: {e}"))?;
        model.validate(&at.to_string())?;
        Ok(model)
    }

    /// For a client that traces `speed` times and decodes `decode_speed`
    /// times as fast (the host's other actors go at `speed`).
    pub fn scaled(self, speed: f64, decode_speed: f64) -> CostModel {
        CostModel {
            ns_per_tile: self.ns_per_tile / speed,
            ns_per_primary_ray: self.ns_per_primary_ray / speed,
            ns_per_secondary_ray: self.ns_per_secondary_ray / speed,
            ns_per_voxel_visit: self.ns_per_voxel_visit / speed,
            ns_per_decoded_byte: self.ns_per_decoded_byte / decode_speed,
            ns_per_pixel_host: self.ns_per_pixel_host / speed,
        }
    }

    /// What the host's other actors spend on finished tiles of `pixels`.
    pub fn host(&self, pixels: u64) -> Duration {
        Duration::from_nanos((self.ns_per_pixel_host * pixels as f64).max(0.0).round() as u64)
    }

    /// What tracing `w` takes.
    pub fn trace(&self, w: Work) -> Duration {
        let ns = self.ns_per_tile * w.tiles as f64
            + self.ns_per_primary_ray * w.primary_rays as f64
            + self.ns_per_secondary_ray * w.secondary_rays as f64
            + self.ns_per_voxel_visit * w.voxel_visits as f64;
        Duration::from_nanos(ns.max(0.0).round() as u64)
    }

    /// What decoding a voxel of `raw_bytes` takes.
    pub fn decode(&self, raw_bytes: u64) -> Duration {
        Duration::from_nanos(
            (self.ns_per_decoded_byte * raw_bytes as f64)
                .max(0.0)
                .round() as u64,
        )
    }

    /// Checks that every cost is finite and not negative; `place` names
    /// where the model came from.
    pub fn validate(&self, place: &str) -> Result<(), String> {
        let costs = [
            ("ns_per_tile", self.ns_per_tile),
            ("ns_per_primary_ray", self.ns_per_primary_ray),
            ("ns_per_secondary_ray", self.ns_per_secondary_ray),
            ("ns_per_voxel_visit", self.ns_per_voxel_visit),
            ("ns_per_decoded_byte", self.ns_per_decoded_byte),
            ("ns_per_pixel_host", self.ns_per_pixel_host),
        ];
        for (key, v) in costs {
            if !v.is_finite() || v < 0.0 {
                return Err(format!(
                    "{place}.{key}: {v} is not a cost (a number of nanoseconds, 0 or more)"
                ));
            }
        }
        Ok(())
    }
}

/// A measured cost model and how well it fits.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Calibration {
    pub model: CostModel,
    /// Tiles timed for the fit (over every thread).
    pub tiles: usize,
    /// Threads that traced at once.
    pub threads: usize,
    /// Share of the tiles' time variance the fit explains.
    pub r2: f64,
    /// Voxels timed for the decode cost.
    pub voxels: usize,
    /// The kernel traced with.
    pub isa: String,
    /// Seconds the calibration took.
    pub seconds: f64,
}

/// The threads a calibration for `clients` clients traces on: a client's
/// threads, or where they share a host of `host_cores`, as many of the
/// host's cores as the clients' threads keep busy.
pub fn calibration_threads(cfg: &Config, clients: u32, host_cores: Option<u32>) -> usize {
    let per_client = cfg.clients.threads.max(1);
    match host_cores {
        Some(cores) => cores.min(clients.saturating_mul(per_client)).max(1) as usize,
        None => per_client as usize,
    }
}

/// The cost model of a virtual run of `cfg` with `clients` clients, kernel
/// `isa`, measured on this machine: [`calibrate`] on the threads
/// [`calibration_threads`] gives, and where the clients share a host of
/// `host_cores`, [`measure_host_overhead`] on `engine`.
pub fn measure(
    cfg: &Config,
    clients: u32,
    isa: Isa,
    host_cores: Option<u32>,
    engine: &HostEngine,
) -> Result<Calibration, String> {
    let threads = calibration_threads(cfg, clients, host_cores);
    let mut c = calibrate(cfg, isa, threads)?;
    if host_cores.is_some() {
        measure_host_overhead(cfg, clients, isa, engine, &mut c.model)?;
    }
    Ok(c)
}

/// Most tiles traced per camera: enough for the fit, few enough to keep
/// calibrating a large frame short.
const TILES_PER_CAMERA: usize = 400;
/// Cameras of the run traced: spread along its path.
const CAMERAS: usize = 3;
/// Most voxels decoded for the decode cost.
const VOXELS: usize = 400;

/// Measures the cost model of `cfg`'s run on this machine with kernel
/// `isa`, on `threads` threads tracing at once (see the module's
/// documentation). Errors name the database.
pub fn calibrate(cfg: &Config, isa: Isa, threads: usize) -> Result<Calibration, String> {
    let start = Instant::now();
    let path = &cfg.scene.database;
    let place = |e: &dyn std::fmt::Display| format!("scene.database {}: {e}", path.display());
    let db = dray_scene::db::Database::open(path).map_err(|e| place(&e))?;
    let source = ResidentSource::load(&db).map_err(|e| place(&e))?;
    let top = TopLevel::from_manifest(&db.manifest);
    let cameras = crate::nodes::frame_cameras(cfg).map_err(|e| e.to_string())?;
    let (w, h) = (cfg.render.width, cfg.render.height);
    let settings = kernel_settings(
        &wire_settings(&cfg.render),
        db.manifest.model_bounds.diagonal(),
        1,
        isa,
    );
    let tile = cfg.render.tile_size.max(1);
    let rects: Vec<Rect> = (0..h.div_ceil(tile))
        .flat_map(|ty| (0..w.div_ceil(tile)).map(move |tx| (tx, ty)))
        .map(|(tx, ty)| Rect {
            x0: tx * tile,
            y0: ty * tile,
            width: tile.min(w - tx * tile),
            height: tile.min(h - ty * tile),
        })
        .collect();
    let every = rects.len().div_ceil(TILES_PER_CAMERA).max(1);
    let picked: Vec<usize> = (0..CAMERAS.min(cameras.len()))
        .map(|k| k * (cameras.len() - 1) / (CAMERAS - 1).max(1))
        .collect();
    let loader = Resident(&source);
    let cams: Vec<_> = picked
        .iter()
        .map(|&c| kernel_camera(&cameras[c], w, h))
        .collect();
    // Every thread traces the same tiles at once: a client's threads
    // share their machine's memory and caches as the run's will.
    let trace_all = || -> Result<Vec<([f64; 4], f64)>, String> {
        let mut rows = Vec::new();
        let mut chooser = PacketChooser::new(Packets::Auto);
        for camera in &cams {
            for rect in rects.iter().step_by(every) {
                let s = RenderSettings {
                    packets: match settings.packets {
                        Packets::Auto => chooser.next(),
                        fixed => fixed,
                    },
                    ..settings.clone()
                };
                // The median of three traces: a client traces a tile once,
                // after other tiles of the same views, so the first is as
                // cold as a client's and the later ones as warm, and the
                // median leaves out a pass the machine's noise slowed.
                let mut times = [0.0f64; 3];
                let mut work = Work::default();
                for t in times.iter_mut() {
                    let before = dray_trace::work::done();
                    let start = Instant::now();
                    let image = futures::executor::block_on(render_tile_sample(
                        &top,
                        &loader,
                        camera,
                        0,
                        *rect,
                        &s,
                        MissMode::Suspend,
                    ))
                    .map_err(|e| place(&e))?;
                    *t = start.elapsed().as_secs_f64() * 1e9;
                    work = dray_trace::work::done().since(before);
                    chooser.learn(s.isa, image.stats.child_hits, image.stats.child_lanes);
                }
                times.sort_by(f64::total_cmp);
                let median = times[1];
                rows.push((
                    [
                        work.tiles as f64,
                        work.primary_rays as f64,
                        work.secondary_rays as f64,
                        work.voxel_visits as f64,
                    ],
                    median,
                ));
            }
        }
        Ok(rows)
    };
    let threads = threads.max(1);
    let mut rows = Vec::new();
    std::thread::scope(|scope| -> Result<(), String> {
        let running: Vec<_> = (0..threads).map(|_| scope.spawn(trace_all)).collect();
        for t in running {
            rows.extend(
                t.join()
                    .map_err(|_| "a calibration thread panicked".to_string())??,
            );
        }
        Ok(())
    })?;
    let (coef, r2) = fit_non_negative(&rows);

    // Decoding: a sample spread over the ids, as the loader does it.
    let count = db.manifest.voxels.len();
    let step = count.div_ceil(VOXELS).max(1);
    let (mut ns, mut bytes, mut voxels) = (0.0, 0u64, 0usize);
    for id in (0..count).step_by(step) {
        let entry = &db.manifest.voxels[id];
        let blob = db.read_blob(id as u32).map_err(|e| place(&e))?;
        let t = Instant::now();
        let v = crate::client::decode_voxel(id as u32, entry, &blob)
            .map_err(|e| place(&format!("voxel {id}: {e}")))?;
        ns += t.elapsed().as_secs_f64() * 1e9;
        drop(v);
        bytes += entry.raw_bytes;
        voxels += 1;
    }
    let model = CostModel {
        ns_per_tile: coef[0],
        ns_per_primary_ray: coef[1],
        ns_per_secondary_ray: coef[2],
        ns_per_voxel_visit: coef[3],
        ns_per_decoded_byte: if bytes > 0 { ns / bytes as f64 } else { 0.0 },
        ns_per_pixel_host: 0.0,
    };
    Ok(Calibration {
        model,
        tiles: rows.len(),
        threads,
        r2,
        voxels,
        isa: isa.name().to_string(),
        seconds: start.elapsed().as_secs_f64(),
    })
}

/// The real engine whose host a virtual run on one host stands for: how
/// [`measure_host_overhead`] measures what the host's other actors cost.
pub enum HostEngine<'a> {
    /// Every node in one process (`dray sim`).
    Sim,
    /// Every node a process over QUIC (`dray cluster`), started from the
    /// `dray` binary with the config written at `config_file`.
    Cluster {
        dray: &'a Path,
        config_file: &'a Path,
    },
}

/// Measures [`CostModel::ns_per_pixel_host`]: runs the real `sim` of `cfg`
/// with `clients` clients, once for its first frame and once whole, and
/// takes the process's CPU time that neither the render threads nor the
/// decodes (as `model` prices them) account for, per pixel of the
/// difference (which leaves out what starting a run costs). For
/// [`HostEngine::Cluster`] it then runs the cluster once whole and adds
/// the CPU time (its processes' and this one's) it spent beyond `sim`'s
/// whole run, per pixel: the same frames, rays and voxels, carried over
/// QUIC, TLS and relays between processes. Sets it in `model`.
pub fn measure_host_overhead(
    cfg: &Config,
    clients: u32,
    isa: Isa,
    engine: &HostEngine,
    model: &mut CostModel,
) -> Result<(), String> {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .map_err(|e| format!("cannot start a runtime: {e}"))?;
    // (CPU seconds in all, CPU seconds not accounted for, pixels shown) of
    // a run.
    let overhead = |frames: Option<usize>| -> Result<(f64, f64, u64), String> {
        let opts = crate::nodes::RunOptions {
            clients: Some(clients),
            isa: Some(isa),
            keep_frame_metrics: false,
            max_frames: frames,
            ..crate::nodes::RunOptions::default()
        };
        let before = process_cpu();
        let run = rt
            .block_on(crate::nodes::sim(cfg, &opts))
            .map_err(|e| format!("measuring the host's overhead: {e}"))?;
        let cpu = process_cpu().saturating_sub(before).as_secs_f64();
        let render: f64 = run.clients.iter().map(|c| c.render_cpu_s).sum();
        let raw: u64 = run.clients.iter().map(|c| c.bytes_raw).sum();
        let decode = model.ns_per_decoded_byte * raw as f64 / 1e9;
        let pixels = run.display.frames_shown as u64
            * u64::from(cfg.render.width)
            * u64::from(cfg.render.height);
        Ok((cpu, cpu - render - decode, pixels))
    };
    let (_, short, few) = overhead(Some(1))?;
    let (sim_cpu, long, many) = overhead(None)?;
    let mut ns = ((long - short).max(0.0) * 1e9) / many.saturating_sub(few).max(1) as f64;
    if let HostEngine::Cluster { dray, config_file } = engine {
        let before = process_cpu() + children_cpu();
        let report = rt
            .block_on(crate::supervisor::cluster(dray, config_file, cfg, &[]))
            .map_err(|e| format!("measuring the cluster's overhead: {e}"))?;
        if report.summary["complete"] != serde_json::Value::Bool(true) {
            return Err("measuring the cluster's overhead: the run stopped early".into());
        }
        let cpu = (process_cpu() + children_cpu())
            .saturating_sub(before)
            .as_secs_f64();
        ns += ((cpu - sim_cpu).max(0.0) * 1e9) / many.max(1) as f64;
    }
    model.ns_per_pixel_host = ns;
    Ok(())
}

/// CPU time of this process's children that have ended and been waited
/// for.
fn children_cpu() -> Duration {
    // SAFETY: an all-zero rusage is a valid value for the call to fill.
    let mut u: libc::rusage = unsafe { std::mem::zeroed() };
    // SAFETY: `u` is a valid rusage for the call to fill.
    if unsafe { libc::getrusage(libc::RUSAGE_CHILDREN, &mut u) } != 0 {
        return Duration::ZERO;
    }
    let t = |v: libc::timeval| Duration::new(v.tv_sec as u64, v.tv_usec as u32 * 1000);
    t(u.ru_utime) + t(u.ru_stime)
}

/// CPU time of this process so far.
fn process_cpu() -> Duration {
    cpu_time(libc::CLOCK_PROCESS_CPUTIME_ID)
}

/// CPU time so far by `clock`: the process's or the calling thread's
/// (`CLOCK_PROCESS_CPUTIME_ID`, `CLOCK_THREAD_CPUTIME_ID`); zero where
/// the system cannot tell.
pub(crate) fn cpu_time(clock: libc::clockid_t) -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec for the call to fill.
    if unsafe { libc::clock_gettime(clock, &mut t) } != 0 {
        return Duration::ZERO;
    }
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

/// Every voxel resident: what calibration traces against.
struct Resident<'a>(&'a ResidentSource);

impl VoxelSource for Resident<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        self.0.voxel(id)
    }

    fn prefetch(&self, id: u32) {
        self.0.prefetch(id)
    }
}

impl VoxelLoader for Resident<'_> {
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>> {
        Box::pin(std::future::ready(Err(LoadError {
            voxel: id,
            message: "not in the database".into(),
        })))
    }
}

/// Least squares through the origin with every coefficient 0 or more: a
/// regressor whose coefficient comes out negative (or that never varies)
/// is dropped and the rest refitted. Returns the coefficients and R².
fn fit_non_negative<const K: usize>(rows: &[([f64; K], f64)]) -> ([f64; K], f64) {
    let mut used = [true; K];
    let mut coef = [0.0; K];
    loop {
        let idx: Vec<usize> = (0..K).filter(|&k| used[k]).collect();
        let n = idx.len();
        if n == 0 {
            break;
        }
        // Normal equations over the used regressors.
        let mut a = vec![vec![0.0f64; n + 1]; n];
        for (x, y) in rows {
            for (i, &p) in idx.iter().enumerate() {
                for (j, &q) in idx.iter().enumerate() {
                    a[i][j] += x[p] * x[q];
                }
                a[i][n] += x[p] * y;
            }
        }
        match solve(a) {
            Some(sol) => {
                coef = [0.0; K];
                for (i, &p) in idx.iter().enumerate() {
                    coef[p] = sol[i];
                }
                let worst = idx
                    .iter()
                    .copied()
                    .filter(|&p| coef[p] < 0.0)
                    .min_by(|&p, &q| coef[p].total_cmp(&coef[q]));
                match worst {
                    Some(p) => used[p] = false,
                    None => break,
                }
            }
            None => {
                // Singular: drop the regressor with the least spread.
                let p = *idx
                    .iter()
                    .min_by(|&&p, &&q| {
                        let sq = |k: usize| rows.iter().map(|(x, _)| x[k] * x[k]).sum::<f64>();
                        sq(p).total_cmp(&sq(q))
                    })
                    .expect("n > 0");
                used[p] = false;
            }
        }
    }
    let mean = rows.iter().map(|r| r.1).sum::<f64>() / rows.len().max(1) as f64;
    let (mut ss_res, mut ss_tot) = (0.0, 0.0);
    for (x, y) in rows {
        let fit: f64 = (0..K).map(|k| coef[k] * x[k]).sum();
        ss_res += (y - fit) * (y - fit);
        ss_tot += (y - mean) * (y - mean);
    }
    let r2 = if ss_tot > 0.0 {
        1.0 - ss_res / ss_tot
    } else {
        1.0
    };
    (coef, r2)
}

/// Gaussian elimination with partial pivoting on an augmented matrix;
/// `None` where it is (nearly) singular.
fn solve(mut a: Vec<Vec<f64>>) -> Option<Vec<f64>> {
    let n = a.len();
    let scale = a
        .iter()
        .flat_map(|r| r[..n].iter())
        .fold(0.0f64, |m, v| m.max(v.abs()));
    for col in 0..n {
        let pivot = (col..n).max_by(|&i, &j| a[i][col].abs().total_cmp(&a[j][col].abs()))?;
        if a[pivot][col].abs() <= scale * 1e-12 {
            return None;
        }
        a.swap(col, pivot);
        let pivot_row = a[col].clone();
        for (row, r) in a.iter_mut().enumerate() {
            if row != col {
                let f = r[col] / pivot_row[col];
                for (x, p) in r[col..].iter_mut().zip(&pivot_row[col..]) {
                    *x -= f * p;
                }
            }
        }
    }
    Some((0..n).map(|i| a[i][n] / a[i][i]).collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_cost_model_is_read_from_a_calibration_or_alone_and_a_bad_one_is_named() {
        let dir = tempfile::tempdir().unwrap();
        let model = CostModel {
            ns_per_tile: 1000.0,
            ns_per_primary_ray: 20.0,
            ns_per_secondary_ray: 15.0,
            ns_per_voxel_visit: 900.0,
            ns_per_decoded_byte: 1.5,
            ns_per_pixel_host: 0.0,
        };
        let alone = dir.path().join("model.json");
        std::fs::write(&alone, serde_json::to_string(&model).unwrap()).unwrap();
        assert_eq!(CostModel::read(&alone), Ok(model));
        let calibration = dir.path().join("calibration.json");
        let record = serde_json::json!({ "model": model, "host_cores": null, "speed": 1.0 });
        std::fs::write(&calibration, record.to_string()).unwrap();
        assert_eq!(CostModel::read(&calibration), Ok(model));
        let bad = dir.path().join("bad.json");
        std::fs::write(&bad, r#"{ "model": { "ns_per_tile": 1 } }"#).unwrap();
        let e = CostModel::read(&bad).unwrap_err();
        assert!(
            e.contains("bad.json") && e.contains("ns_per_primary_ray"),
            "{e}"
        );
        let negative = dir.path().join("negative.json");
        let model = CostModel {
            ns_per_tile: -1.0,
            ..model
        };
        std::fs::write(&negative, serde_json::to_string(&model).unwrap()).unwrap();
        let e = CostModel::read(&negative).unwrap_err();
        assert!(
            e.contains("negative.json") && e.contains("ns_per_tile"),
            "{e}"
        );
    }

    #[test]
    fn the_fit_recovers_known_costs_and_drops_a_column_that_never_varies() {
        // y = 1000 per tile + 50 per primary + 3 per visit; no secondary rays.
        let rows: Vec<([f64; 4], f64)> = (1..40)
            .map(|i| {
                let p = (i * 37 % 101) as f64 * 10.0;
                let v = (i * 53 % 89) as f64 * 7.0;
                ([1.0, p, 0.0, v], 1000.0 + 50.0 * p + 3.0 * v)
            })
            .collect();
        let (c, r2) = fit_non_negative(&rows);
        assert!((c[0] - 1000.0).abs() < 1e-6, "{c:?}");
        assert!((c[1] - 50.0).abs() < 1e-9, "{c:?}");
        assert_eq!(c[2], 0.0);
        assert!((c[3] - 3.0).abs() < 1e-9, "{c:?}");
        assert!((r2 - 1.0).abs() < 1e-9);
    }

    #[test]
    fn a_negative_coefficient_is_dropped_and_the_rest_refitted() {
        // Visits anti-correlated with time: a free fit would give them a
        // negative cost.
        let rows: Vec<([f64; 4], f64)> = (1..30)
            .map(|i| {
                let p = i as f64 * 100.0;
                ([1.0, p, 0.0, 3000.0 - p], 20.0 * p)
            })
            .collect();
        let (c, _) = fit_non_negative(&rows);
        assert!(c.iter().all(|&v| v >= 0.0), "{c:?}");
        assert!(c[1] > 0.0, "{c:?}");
    }

    #[test]
    fn costs_scale_with_speed() {
        let m = CostModel {
            ns_per_tile: 1000.0,
            ns_per_primary_ray: 100.0,
            ns_per_secondary_ray: 50.0,
            ns_per_voxel_visit: 10.0,
            ns_per_decoded_byte: 2.0,
            ns_per_pixel_host: 10.0,
        };
        let w = Work {
            tiles: 1,
            primary_rays: 10,
            secondary_rays: 10,
            voxel_visits: 100,
        };
        assert_eq!(m.trace(w), Duration::from_nanos(1000 + 1000 + 500 + 1000));
        assert_eq!(m.scaled(2.0, 1.0).trace(w), Duration::from_nanos(1750));
        assert_eq!(m.decode(1000), Duration::from_micros(2));
        assert_eq!(m.scaled(2.0, 1.0).decode(1000), Duration::from_micros(2));
        assert_eq!(m.scaled(1.0, 4.0).decode(1000), Duration::from_nanos(500));
        assert!(m.validate("x").is_ok());
        let bad = CostModel {
            ns_per_voxel_visit: -1.0,
            ..m
        };
        assert!(bad
            .validate("virtual.cost")
            .unwrap_err()
            .contains("virtual.cost.ns_per_voxel_visit"));
    }
}
