//! The centre alone: a config's Scheduler node (scheduler and frame
//! assigner) and Display, unchanged, driven by N stand-in clients that
//! answer every tile at once, over the in-process transport. Nothing is
//! rendered or fetched, so what the run costs is what the centre costs per
//! frame and per message as the clients grow, the figure that says how
//! many clients one scheduler and one display can serve
//! (`bench/src/bin/bench-centre.rs`).
//!
//! The scheduler node and the display each run on a thread of their own,
//! whose CPU time is measured; the stand-ins share a third. A stand-in asks
//! for as many tiles as a one-thread client asks ahead, and answers each
//! with flat pixels and a few hits on a plane in front of the camera, as
//! a client does (the scheduler's affinity policy reprojects them).

use crate::display::run_display_until;
use crate::names;
use crate::nodes::{display_options, joined, open_mailbox, spawn_scheduler, ClusterError};
use crate::nodes::{scheduler_mailboxes, RunOptions, MAILBOX};
use crate::scheduler::SchedulerSummary;
use crate::settings::kernel_camera;
use dray_config::Config;
use dray_protocol::{
    AssignTile, Blob, BoundedVec, Message, RequestWork, Role, Shutdown, TileDone, TilePixels,
    TileStats,
};
use dray_runtime::{Delivery, InProcNet, Mailbox};
use std::path::Path;
use std::time::{Duration, Instant};

/// Tiles a stand-in holds at once: a one-thread client's tile and one
/// asked ahead.
const STAND_IN_SLOTS: u16 = 2;
/// Hits a stand-in reports per tile (a client reports up to
/// `MAX_TILE_HITS`, spread over the tile).
const HITS_PER_TILE: u32 = 4;
/// Distance of the plane the stand-ins' hits lie on, in front of the eye.
const HIT_DISTANCE: f32 = 10.0;

/// What one run of the centre did.
#[derive(Clone, Debug, serde::Serialize)]
pub struct CentreRun {
    /// Stand-in clients.
    pub clients: usize,
    /// Frames shown.
    pub frames: usize,
    /// Tiles of every frame together.
    pub tiles: u64,
    /// Wall time from the first frame asked for to the last shown.
    pub seconds: f64,
    /// Frames per second.
    pub fps: f64,
    /// CPU time of the scheduler node's thread (scheduler and assigner).
    pub scheduler_cpu_s: f64,
    /// CPU time of the display's thread.
    pub display_cpu_s: f64,
    /// CPU time of the stand-ins' thread.
    pub clients_cpu_s: f64,
    /// Messages the scheduler received: requests for work and the
    /// display's tile reports (one per assignment).
    pub scheduler_received: u64,
    /// Assignments the scheduler sent.
    pub scheduler_sent: u64,
}

impl CentreRun {
    /// Scheduler CPU per frame, milliseconds.
    pub fn scheduler_ms_per_frame(&self) -> f64 {
        1e3 * self.scheduler_cpu_s / self.frames.max(1) as f64
    }

    /// Display CPU per frame, milliseconds.
    pub fn display_ms_per_frame(&self) -> f64 {
        1e3 * self.display_cpu_s / self.frames.max(1) as f64
    }

    /// Messages through the scheduler per second of its CPU: how many it
    /// could take with a core of its own.
    pub fn scheduler_messages_per_cpu_s(&self) -> f64 {
        (self.scheduler_received + self.scheduler_sent) as f64 / self.scheduler_cpu_s.max(1e-9)
    }
}

/// CPU time of the calling thread.
fn thread_cpu() -> Duration {
    let mut t = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: `t` is a valid timespec for the call to fill.
    let r = unsafe { libc::clock_gettime(libc::CLOCK_THREAD_CPUTIME_ID, &mut t) };
    if r != 0 {
        return Duration::ZERO;
    }
    Duration::new(t.tv_sec as u64, t.tv_nsec as u32)
}

fn runtime(what: &str) -> Result<tokio::runtime::Runtime, ClusterError> {
    tokio::runtime::Builder::new_current_thread()
        .enable_time()
        .build()
        .map_err(|e| ClusterError::Node {
            node: what.into(),
            message: format!("cannot start a runtime: {e}"),
        })
}

fn thread_failed(what: &str) -> ClusterError {
    ClusterError::Node {
        node: what.into(),
        message: "its thread panicked".into(),
    }
}

/// What a stand-in counted.
#[derive(Default)]
struct StandInCounts {
    assigned: u64,
    asked: u64,
}

/// A stand-in client: answers every tile at once, until Shutdown.
async fn stand_in(mut mb: Mailbox) -> StandInCounts {
    let mut counts = StandInCounts::default();
    let ask = |slots: u16| {
        Message::RequestWork(RequestWork {
            slots,
            holds_model: false,
        })
    };
    if mb
        .send(&names::scheduler(), ask(STAND_IN_SLOTS))
        .await
        .is_ok()
    {
        counts.asked += 1;
    }
    while let Some(d) = mb.recv().await {
        let Delivery::Message { msg, .. } = d else {
            continue;
        };
        match msg {
            Message::AssignTile(a) => {
                counts.assigned += 1;
                let done = Message::TileDone(answer(&a));
                let _ = mb.send(&names::display(), done).await;
                if mb.send(&names::scheduler(), ask(1)).await.is_ok() {
                    counts.asked += 1;
                }
            }
            Message::Shutdown(_) => break,
            _ => {}
        }
    }
    counts
}

/// A tile's answer: flat grey pixels and hits on a plane facing the eye.
fn answer(a: &AssignTile) -> TileDone {
    let t = a.tile;
    let area = u64::from(t.w) * u64::from(t.h);
    let basis = kernel_camera(&a.camera, a.width, a.height).basis();
    let hits: Vec<[f32; 3]> = (0..HITS_PER_TILE)
        .map(|k| {
            let x = t.x + (2 * k + 1) * t.w / (2 * HITS_PER_TILE);
            let y = t.y + (2 * k + 1) * t.h / (2 * HITS_PER_TILE);
            (basis.eye + basis.direction(x, y) * HIT_DISTANCE).to_array()
        })
        .collect();
    TileDone {
        frame: a.frame,
        tile: t,
        pixels: TilePixels::Rgb(Blob(vec![128; area as usize * 3])),
        depth: None,
        prim_ids: None,
        stats: TileStats {
            rays: area,
            time_us: 1,
            ..TileStats::default()
        },
        hits: BoundedVec::new(hits).unwrap_or_default(),
    }
}

/// A walk towards a point, turning a little (the affinity policy
/// reprojects, as on a real walkthrough).
const WALK: &str = r#"
[[keyframe]]
eye = [0.0, 5.0, -40.0]
look = [0.0, 2.0, 0.0]
fov_y_deg = 60.0

[[keyframe]]
eye = [5.0, 5.0, -20.0]
look = [0.0, 2.0, 0.0]
fov_y_deg = 60.0
"#;

/// A config for [`run_centre`]: `frames` frames of a walk at `size`
/// pixels in tiles of `tile_size`, its camera path written in `dir`. The
/// centre needs no model: no node of the config but the scheduler and the
/// display runs, and they never bind their addresses.
pub fn walk_config(
    dir: &Path,
    (width, height): (u32, u32),
    tile_size: u32,
    frames: u32,
) -> Result<Config, ClusterError> {
    let err = |message: String| ClusterError::Node {
        node: "centre".into(),
        message,
    };
    let path = dir.join("walk.toml");
    std::fs::write(&path, format!("frames = {frames}\n{WALK}"))
        .map_err(|e| err(format!("writing {}: {e}", path.display())))?;
    let text = format!(
        r#"
[scene]
database = "{db}"

[render]
width = {width}
height = {height}
tile_size = {tile_size}
camera_path = "{path}"

[render.camera]
eye = [0.0, 5.0, -40.0]
look = [0.0, 2.0, 0.0]

[prefetch]
enabled = false

[scheduler]
address = "127.0.0.1:7400"

[display]
address = "127.0.0.1:7401"

[[stores]]
address = "127.0.0.1:7402"

[clients]
count = 1
threads = 1
cache_mb = 64

[certs]
dir = "{certs}"
"#,
        db = dir.join("no-model.dray").display(),
        path = path.display(),
        certs = dir.join("certs").display(),
    );
    Config::parse(&text).map_err(|e| err(e.to_string()))
}

/// Runs `cfg`'s scheduler node and display with `clients` stand-ins until
/// the display has every frame of the config's cameras. The prefetcher
/// and the stores are left out: nothing is fetched.
pub fn run_centre(cfg: &Config, clients: usize) -> Result<CentreRun, ClusterError> {
    let mut cfg = cfg.clone();
    cfg.prefetch.enabled = false;
    // The stand-ins' runtime, entered for the network's setup.
    let rt = runtime("clients")?;
    let _entered = rt.enter();
    let net = InProcNet::new();
    let add = |n: dray_protocol::Name, role: Role| {
        net.add_node(n.clone(), role)
            .map_err(|e| ClusterError::Node {
                node: n.to_string(),
                message: e.to_string(),
            })
    };
    let sched_bus = add(names::scheduler().node, Role::Scheduler)?;
    let display_bus = add(names::display().node, Role::Display)?;
    let client_buses = (0..clients)
        .map(|i| add(names::client_node(i), Role::Client))
        .collect::<Result<Vec<_>, _>>()?;
    let sched_boxes = scheduler_mailboxes(&sched_bus)?;
    let display_box = open_mailbox(&display_bus, names::DISPLAY, MAILBOX)?;
    let control = open_mailbox(&display_bus, "centre", 16)?;
    let client_boxes = client_buses
        .iter()
        .map(|b| open_mailbox(b, names::CLIENT, MAILBOX))
        .collect::<Result<Vec<_>, _>>()?;
    let display_opts = display_options(
        &cfg,
        &RunOptions {
            keep_frame_metrics: false,
            ..RunOptions::default()
        },
    )?;

    let sched_cfg = cfg.clone();
    let scheduler = std::thread::Builder::new()
        .name("centre-scheduler".into())
        .spawn(
            move || -> Result<(SchedulerSummary, Duration), ClusterError> {
                let rt = runtime("scheduler")?;
                let summary = rt.block_on(async {
                    let tasks = spawn_scheduler(&sched_cfg, sched_boxes)?;
                    let s = joined("scheduler", tasks.scheduler).await?;
                    joined("assigner", tasks.assigner).await?;
                    Ok::<_, ClusterError>(s)
                })?;
                Ok((summary, thread_cpu()))
            },
        )
        .map_err(|e| ClusterError::Node {
            node: "scheduler".into(),
            message: format!("cannot start its thread: {e}"),
        })?;
    let (done_tx, done_rx) = tokio::sync::oneshot::channel();
    let display = std::thread::Builder::new()
        .name("centre-display".into())
        .spawn(move || {
            let rt = runtime("display")?;
            let started = Instant::now();
            let summary = rt.block_on(run_display_until(
                display_box,
                display_opts,
                std::future::pending(),
            ));
            let seconds = started.elapsed().as_secs_f64();
            let _ = done_tx.send(());
            let summary = summary?;
            Ok::<_, ClusterError>((summary, seconds, thread_cpu()))
        })
        .map_err(|e| ClusterError::Node {
            node: "display".into(),
            message: format!("cannot start its thread: {e}"),
        })?;

    let counts = rt.block_on(async {
        let tasks: Vec<_> = client_boxes
            .into_iter()
            .map(|mb| tokio::spawn(stand_in(mb)))
            .collect();
        let _ = done_rx.await;
        let mut everyone = vec![names::scheduler(), names::assigner()];
        everyone.extend((0..clients).map(names::client));
        for to in everyone {
            let reason = "the centre's run is over".to_string();
            let _ = control
                .send(&to, Message::Shutdown(Shutdown { reason }))
                .await;
        }
        let mut total = StandInCounts::default();
        for t in tasks {
            if let Ok(c) = t.await {
                total.assigned += c.assigned;
                total.asked += c.asked;
            }
        }
        total
    });
    let clients_cpu = thread_cpu();
    let (summary, seconds, display_cpu) =
        display.join().map_err(|_| thread_failed("display"))??;
    let (sched_summary, scheduler_cpu) =
        scheduler.join().map_err(|_| thread_failed("scheduler"))??;
    if !summary.complete {
        return Err(ClusterError::Node {
            node: "display".into(),
            message: format!(
                "showed {} of {} frames: {}",
                summary.frames_shown,
                summary.frames_requested,
                summary.stopped_early.unwrap_or_default()
            ),
        });
    }
    Ok(CentreRun {
        clients,
        frames: summary.frames_shown,
        tiles: sched_summary.tiles,
        seconds,
        fps: summary.frames_shown as f64 / seconds.max(1e-9),
        scheduler_cpu_s: scheduler_cpu.as_secs_f64(),
        display_cpu_s: display_cpu.as_secs_f64(),
        clients_cpu_s: clients_cpu.as_secs_f64(),
        scheduler_received: counts.asked + counts.assigned,
        scheduler_sent: counts.assigned,
    })
}
