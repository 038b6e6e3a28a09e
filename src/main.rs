//! The `dray` command line: it parses arguments and calls into the crates.

mod allocator;
mod cli;
mod view;

use anyhow::{bail, Context, Result};
use clap::Parser;
use cli::{CertsAction, Cli, Command, GenerateModel, RenderArgs};
use dray_actors::display::path::CameraPath;
use dray_actors::nodes::{NodeOutcome, RunOptions};
use dray_protocol::{CameraField, Role};
use dray_scene::db::info::DbInfo;
use dray_scene::db::shard::write_shards;
use dray_scene::db::verify::verify;
use dray_scene::db::Database;
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::preprocess::{preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use dray_trace::accel::{ResidentSource, TopLevel};
use dray_trace::camera::Camera;
use dray_trace::render::{render_repeated, RenderSettings};
use dray_trace::report::{render_path, PathReport, ViewReport};
use std::path::{Path, PathBuf};
use std::process::ExitCode;

fn certs(action: CertsAction) -> anyhow::Result<()> {
    use dray_runtime::certs;
    match action {
        CertsAction::Init {
            dir,
            config,
            nodes,
            ca_dir,
        } => {
            let nodes = match config {
                Some(path) => dray_config::Config::load(&path)?.node_names(),
                None if nodes.is_empty() => {
                    bail!("name the nodes with --config CONFIG or --nodes a,b,c")
                }
                None => nodes,
            };
            let names: Vec<&str> = nodes.iter().map(String::as_str).collect();
            let written = certs::init_cluster_in(&dir, ca_dir.as_deref(), &names)?;
            println!(
                "{}: cluster CA and certificates for {} nodes ({} files); the CA key is {} \
                 (keep it off the nodes' hosts; give each host `dray certs bundle`)",
                dir.display(),
                names.len(),
                written.len(),
                certs::ca_key_path(&dir, ca_dir.as_deref()).display()
            );
        }
        CertsAction::Add { dir, nodes, ca_dir } => {
            let names: Vec<&str> = nodes.iter().map(String::as_str).collect();
            let written = certs::add_nodes(&dir, ca_dir.as_deref(), &names)?;
            println!(
                "{}: certificates for {} more nodes ({} files)",
                dir.display(),
                names.len(),
                written.len()
            );
        }
        CertsAction::Bundle { dir, node, out } => {
            let out = out.unwrap_or_else(|| dir.join("bundles").join(&node));
            certs::bundle(&dir, &node, &out)?;
            println!(
                "{}: ca.pem, {node}.pem and {node}.key, the certs.dir of {node}'s host",
                out.display()
            );
        }
    }
    Ok(())
}

fn main() -> ExitCode {
    let cli = Cli::parse();
    // An experiment runs many clusters in this process: their info lines
    // would bury its progress (RUST_LOG still shows them).
    let default_log = match cli.command {
        Command::Experiment { .. } => "warn",
        _ => "info",
    };
    dray_runtime::logging::init(default_log);
    match run(cli) {
        Ok(code) => code,
        Err(e) => {
            eprintln!("error: {}", describe(&e));
            ExitCode::FAILURE
        }
    }
}

/// The error and its causes, joined by ": ". Many errors already end with
/// their cause's text (`"{path}: {source}"`), which anyhow's `{:#}` would
/// print a second time: a cause the message so far ends with is skipped.
fn describe(e: &anyhow::Error) -> String {
    let mut out = String::new();
    for cause in e.chain() {
        let text = cause.to_string();
        if out.ends_with(&text) {
            continue;
        }
        if !out.is_empty() {
            out.push_str(": ");
        }
        out.push_str(&text);
    }
    out
}

fn run(cli: Cli) -> Result<ExitCode> {
    match cli.command {
        Command::Generate {
            model:
                GenerateModel::Plant {
                    triangles,
                    seed,
                    out,
                },
        } => generate(triangles, seed, &out)?,
        Command::Preprocess {
            inputs,
            out,
            max_triangles,
            max_depth,
            copies,
            spacing,
            threads,
            memory_mb,
            zstd_level,
        } => {
            let opts = PreprocessOptions {
                max_triangles,
                max_depth,
                copies: copies.unwrap_or([1, 1, 1]),
                spacing,
                threads,
                memory_mb,
                zstd_level,
                ..PreprocessOptions::new(inputs, out)
            };
            build_database(&opts)?;
        }
        Command::Verify { db } => {
            let db = Database::open(&db)?;
            let report = verify(&db, &Progress::auto());
            for p in &report.problems {
                println!("{p}");
            }
            if !report.is_ok() {
                eprintln!(
                    "{}: {} problem(s) in {} voxels",
                    db.dir().display(),
                    report.problems.len(),
                    report.voxels
                );
                return Ok(ExitCode::FAILURE);
            }
            println!(
                "{}: ok ({} voxels, {} triangles)",
                db.dir().display(),
                report.voxels,
                report.triangles
            );
        }
        Command::Shard { db, count, out } => {
            let db = Database::open(&db)?;
            let dirs = write_shards(&db, count, &out, &Progress::auto())?;
            for (i, d) in dirs.iter().enumerate() {
                println!("shard {i}/{count}: {}", d.display());
            }
        }
        Command::Info { db, json } => {
            let info = DbInfo::from_manifest(&Database::open(&db)?.manifest);
            if json {
                println!("{}", serde_json::to_string(&info)?);
            } else {
                print!("{}", info.to_text());
            }
        }
        Command::Certs { action } => certs(action)?,
        Command::Render(args) => render(&args)?,
        Command::Demo {
            config,
            triangles,
            frames,
        } => {
            CameraPath::check_frames(frames).map_err(|m| anyhow::anyhow!("--frames: {m}"))?;
            demo(&config, triangles, frames)?
        }
        Command::View {
            target,
            clients,
            threads,
            web,
            width,
            height,
        } => {
            let args = view::ViewArgs {
                target,
                clients,
                threads,
                web,
                width,
                height,
            };
            let exe = std::env::current_exe().context("finding the dray binary")?;
            let report = view::view(&args, &exe)?;
            print_report(&report.summary, &report.events, false);
        }
        Command::Cluster {
            config,
            save_frames,
            isa,
            json,
        } => {
            let cfg = dray_config::Config::load(&config)?;
            dray_actors::nodes::preflight(&cfg, None)?;
            let mut extra = Vec::new();
            if let Some(isa) = isa {
                extra.extend(["--isa".to_string(), isa.name().to_string()]);
            }
            if let Some(dir) = &save_frames {
                let dir = std::path::absolute(dir).context("the --save-frames directory")?;
                extra.extend(["--save-frames".to_string(), dir.display().to_string()]);
            }
            let exe = std::env::current_exe().context("finding the dray binary")?;
            let report = runtime()?.block_on(dray_actors::supervisor::cluster(
                &exe, &config, &cfg, &extra,
            ))?;
            print_report(&report.summary, &report.events, json);
        }
        Command::Node {
            config,
            save_frames,
            role,
            index,
            print_node,
            isa,
        } => {
            let mut cfg = dray_config::Config::load(&config)?;
            save_frames_to(&mut cfg, save_frames);
            let (role, index) = match role {
                Some(role) => (role, index.unwrap_or(0)),
                None => {
                    let env = |var: &str| std::env::var(var).ok();
                    let node = cfg
                        .node_from_launcher(&env)
                        .with_context(|| format!("{}", config.display()))?;
                    let l = &node.launch;
                    tracing::info!(
                        launcher = l.launcher,
                        rank = l.rank,
                        from = l.rank_from,
                        role = %node.role,
                        index = node.index,
                        hosts = ?cfg.launch.hosts,
                        "node from the launcher's rank"
                    );
                    (node.role, node.index)
                }
            };
            if print_node {
                let name = dray_actors::nodes::node_name(role, index)
                    .map_err(|m| anyhow::anyhow!("{m}"))?;
                if !cfg.node_names().contains(&name.to_string()) {
                    bail!("{}: {name} is not a node of this config", config.display());
                }
                println!("{name}");
                return Ok(ExitCode::SUCCESS);
            }
            if !(role == Role::Client && cfg.clients.preload) {
                allocator::streaming();
            }
            let opts = RunOptions {
                isa,
                ..RunOptions::default()
            };
            // One thread for the node's actors and transport: render threads
            // and blocking work have their own threads, and a single
            // scheduler thread saves the cross-thread wakeups of a pool.
            let mut rt = tokio::runtime::Builder::new_current_thread();
            if role == Role::Client {
                // A client decodes voxels on the blocking pool, as many at
                // once as it has fetches in flight (64 by default): that
                // many threads on two cores only take turns, so one per
                // core, at least two (`experiments/efficiency.toml`
                // and `latency-hiding.toml`).
                let cores = std::thread::available_parallelism().map_or(2, |n| n.get());
                rt.max_blocking_threads(cores.max(2));
            }
            let rt = rt
                .enable_all()
                .build()
                .context("starting the async runtime")?;
            let outcome = match rt.block_on(dray_actors::nodes::node(&cfg, role, index, &opts)) {
                Ok(outcome) => outcome,
                Err(e @ dray_actors::nodes::ClusterError::AddressInUse { .. }) => {
                    // Starting this node again would fail the same way.
                    eprintln!("error: {e}");
                    return Ok(ExitCode::from(dray_actors::supervisor::EXIT_NO_RESTART));
                }
                Err(e) => return Err(e.into()),
            };
            if let NodeOutcome::Display(summary) = outcome {
                println!("summary {}", summary.to_json());
            }
        }
        Command::Sim {
            config,
            save_frames,
            clients,
            isa,
            virtual_clock,
            host_cores,
            cost,
            json,
        } => {
            let mut cfg = dray_config::Config::load(&config)?;
            save_frames_to(&mut cfg, save_frames);
            if !cfg.clients.preload {
                allocator::streaming();
            }
            let opts = RunOptions {
                clients,
                isa,
                // Only the JSON report lists each frame; a long run keeps
                // its sums (and writes its rows to display.output, if set).
                keep_frame_metrics: json,
                ..RunOptions::default()
            };
            if virtual_clock {
                let kernel = isa.unwrap_or_else(dray_trace::render::Isa::detect);
                let clients = clients.unwrap_or(cfg.clients.count);
                let (model, calibration) = match cost {
                    Some(file) => (
                        dray_actors::costs::CostModel::read(&file)
                            .map_err(|e| anyhow::anyhow!("--cost {e}"))?,
                        None,
                    ),
                    None => {
                        let cal = dray_actors::costs::measure(
                            &cfg,
                            clients,
                            kernel,
                            host_cores,
                            &dray_actors::costs::HostEngine::Sim,
                        )
                        .map_err(|e| anyhow::anyhow!("calibrating the cost model: {e}"))?;
                        (cal.model, Some(cal))
                    }
                };
                let run = dray_actors::costs::VirtualRun {
                    cost: model,
                    host_cores,
                };
                let run = dray_actors::nodes::sim_virtual(&cfg, &opts, run)?;
                let mut report = run.to_json();
                report["cost_model"] = serde_json::to_value(model)?;
                report["calibration"] = serde_json::to_value(&calibration)?;
                print_report(&report, &[], json);
            } else {
                let run = runtime()?.block_on(dray_actors::nodes::sim(&cfg, &opts))?;
                print_report(&run.to_json(), &[], json);
            }
        }
        Command::Experiment {
            file,
            out,
            quick,
            resume,
        } => {
            // Most experiments stream voxels through cold caches (see
            // allocator.rs); `cluster` nodes choose for themselves.
            allocator::no_huge_pages();
            let opts = dray_experiments::Options {
                out,
                resume,
                quick,
                dray: Some(std::env::current_exe().context("finding the dray binary")?),
                ..dray_experiments::Options::default()
            };
            let report = dray_experiments::run(&file, &opts)?;
            println!(
                "{}: {} of {} runs done{}",
                report.dir.display(),
                report.runs_done + report.runs_resumed,
                report.runs_total,
                if report.runs_resumed > 0 {
                    format!(" ({} by an earlier run)", report.runs_resumed)
                } else {
                    String::new()
                }
            );
            if report.interrupted {
                println!(
                    "interrupted; go on with: dray experiment {}{} --resume {}",
                    file.display(),
                    if quick { " --quick" } else { "" },
                    report.dir.display()
                );
                return Ok(ExitCode::from(130));
            }
            println!("summary: {}", report.dir.join("summary.md").display());
        }
        Command::Walkthrough { db, frames, out } => {
            CameraPath::check_frames(frames).map_err(|m| anyhow::anyhow!("--frames: {m}"))?;
            let db = Database::open(&db)?;
            let frames = write_walkthrough(&db, frames, &out)?;
            println!("{}: {frames} frames", out.display());
        }
    }
    Ok(ExitCode::SUCCESS)
}

fn generate(triangles: u64, seed: u64, out: &Path) -> Result<()> {
    let progress = Progress::auto();
    progress.stage("generating plant", triangles);
    let mut last = 0;
    let summary = generate_plant(&PlantParams { triangles, seed }, out, &mut |done| {
        progress.advance(done - last);
        last = done;
    })?;
    progress.finish();
    println!(
        "{}: {} triangles, {} vertices",
        out.display(),
        summary.triangles,
        summary.vertices
    );
    Ok(())
}

fn build_database(opts: &PreprocessOptions) -> Result<()> {
    allocator::use_system();
    let progress = Progress::auto();
    let cancel = progress.cancel_flag();
    // Ctrl-C stops the build at its next check; the temporary directory is
    // removed on the way out. A second Ctrl-C kills the process outright.
    ctrlc::set_handler(move || {
        if cancel.swap(true, std::sync::atomic::Ordering::Relaxed) {
            std::process::exit(130);
        }
        eprintln!("\ncancelling (Ctrl-C again to kill)...");
    })
    .context("installing the Ctrl-C handler")?;
    let report = preprocess(opts, &progress)?;
    let peak = dray_runtime::process::peak_rss_bytes()
        .map(|b| format!(", peak RSS {} MiB", b >> 20))
        .unwrap_or_default();
    println!("{}{peak}", report.summary(&opts.out));
    Ok(())
}

/// `--save-frames DIR`: every frame as a PNG, and the metrics, in DIR.
fn save_frames_to(cfg: &mut dray_config::Config, dir: Option<PathBuf>) {
    if let Some(dir) = dir {
        cfg.display.output = Some(dir);
        cfg.display.save_frames = true;
    }
}

fn runtime() -> Result<tokio::runtime::Runtime> {
    tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .context("starting the async runtime")
}

/// Prints a run's summary: the display's text (or JSON) and what happened.
fn print_report(summary: &serde_json::Value, events: &[String], json: bool) {
    if json {
        println!("{summary}");
        return;
    }
    if let Some(text) = summary.get("text").and_then(|t| t.as_str()) {
        print!("{text}");
    } else {
        println!("{summary:#}");
    }
    for e in events {
        println!("event: {e}");
    }
}

/// Writes the walkthrough of `db` (temporary file, then rename); returns
/// its number of frames.
fn write_walkthrough(db: &Database, frames: u32, out: &Path) -> Result<u32> {
    let path = CameraPath::walkthrough(&db.manifest.model_bounds, frames);
    path.save(out)
        .with_context(|| format!("writing {}", out.display()))?;
    Ok(path.frames)
}

/// The README's first command: model, database, walkthrough and
/// certificates are made on the first run and kept; then a local cluster
/// renders the walk.
fn demo(config: &Path, triangles: u64, frames: u32) -> Result<()> {
    let cfg = dray_config::Config::load(config)
        .with_context(|| format!("the demo's config {}", config.display()))?;
    let db_path = cfg.scene.database.clone();
    let dir = db_path
        .parent()
        .map(Path::to_path_buf)
        .unwrap_or_else(|| PathBuf::from("."));
    std::fs::create_dir_all(&dir).with_context(|| format!("creating {}", dir.display()))?;
    if Database::open(&db_path).is_ok() {
        println!(
            "{}: reusing the database from an earlier run",
            db_path.display()
        );
    } else {
        let model = dir.join(format!("plant-{triangles}.ply"));
        if !model.exists() {
            generate(triangles, 1, &model)?;
        }
        build_database(&PreprocessOptions::new(vec![model], db_path.clone()))?;
    }
    let db = Database::open(&db_path)?;
    let report = verify(&db, &Progress::auto());
    if !report.is_ok() {
        bail!("{}: {}", db_path.display(), report.problems.join("; "));
    }
    print!("{}", DbInfo::from_manifest(&db.manifest).to_text());
    if let Some(walk) = &cfg.render.camera_path {
        if !walk.exists() {
            let frames = write_walkthrough(&db, frames, walk)?;
            println!("{}: a walkthrough of {frames} frames", walk.display());
        }
    }
    let exe = std::env::current_exe().context("finding the dray binary")?;
    let report = runtime()?.block_on(dray_actors::supervisor::cluster(&exe, config, &cfg, &[]))?;
    print_report(&report.summary, &report.events, false);
    if let Some(out) = &cfg.display.output {
        println!(
            "frames in {}, metrics in {}",
            out.join("frames").display(),
            out.join("metrics.csv").display()
        );
    }
    Ok(())
}

fn render(a: &RenderArgs) -> Result<()> {
    dray_config::check_image_side("--width", a.width)?;
    dray_config::check_image_side("--height", a.height)?;
    dray_protocol::check_reflectance(a.reflectance).map_err(flag("--reflectance"))?;
    dray_protocol::check_reflection_depth(a.reflections).map_err(flag("--reflections"))?;
    dray_protocol::check_light_dir(a.light.to_array()).map_err(flag("--light"))?;
    dray_protocol::check_samples(a.spp).map_err(flag("--spp"))?;
    let db = Database::open(&a.db)?;
    let load = std::time::Instant::now();
    let source = ResidentSource::load(&db)?;
    let load_seconds = load.elapsed().as_secs_f64();
    let top = TopLevel::from_manifest(&db.manifest);
    let bounds = db.manifest.model_bounds;
    let default = Camera::default_for(&bounds, a.width, a.height);
    let camera = Camera {
        eye: a.eye.unwrap_or(default.eye),
        look: a.look.unwrap_or(default.look),
        up: a.up,
        fov_degrees: a.fov,
        ..default
    };
    check_camera_flags(&camera)?;
    let defaults = RenderSettings::primary(bounds.diagonal());
    let settings = RenderSettings {
        shade: a.out.is_some()
            || a.shadows
            || a.reflections > 0
            || a.voxel_colors
            || a.path.is_some(),
        shadows: a.shadows,
        light: a.light,
        threads: if a.threads == 0 {
            defaults.threads
        } else {
            a.threads
        },
        isa: a.isa.unwrap_or(defaults.isa),
        reflections: a.reflections,
        reflective: dray_actors::settings::reflect_rule(&a.reflective),
        reflectance: a.reflectance,
        voxel_colors: a.voxel_colors,
        packets: a.packets,
        occluder_cache: !a.no_occluder_cache,
        ..defaults
    };
    let not_loaded = |id| anyhow::anyhow!("voxel {id} was not loaded");
    if let Some(path) = &a.path {
        let cameras: Vec<Camera> = CameraPath::load(path)
            .with_context(|| format!("camera path {}", path.display()))?
            .cameras()
            .iter()
            .map(|c| dray_actors::settings::kernel_camera(c, a.width, a.height))
            .collect();
        let report = PathReport {
            load_seconds,
            ..render_path(&top, &source, &cameras, a.spp, &settings, a.working_set)
                .map_err(not_loaded)?
        };
        print!("{}", report.text());
        if a.json {
            println!("{}", report.to_json());
        }
        return Ok(());
    }
    let passes =
        render_repeated(&top, &source, &camera, &settings, a.repeat, a.spp).map_err(not_loaded)?;
    let frame = &passes.frame;
    if let Some(p) = &a.out {
        dray_trace::image::write_png(p, frame.width, frame.height, &frame.rgba)?;
    }
    if let Some(p) = &a.depth_out {
        dray_trace::image::write_pfm(p, frame.width, frame.height, &frame.depth)?;
    }
    if let Some(p) = &a.primid_out {
        dray_trace::image::write_u32(p, &frame.primid)?;
    }
    let report = ViewReport {
        voxels: db.manifest.voxels.len(),
        resident_bytes: source.bytes(),
        huge_pages_bytes: dray_runtime::process::huge_pages_bytes(),
        load_seconds,
        ..ViewReport::new(&passes, &settings, &camera)
    };
    println!("{}", report.text());
    if a.json {
        println!("{}", report.to_json());
    }
    Ok(())
}

/// `dray render`'s camera, checked as a config's or a received one is; the
/// error names the flag.
fn check_camera_flags(c: &Camera) -> Result<()> {
    let wire = dray_protocol::Camera {
        eye: c.eye.to_array(),
        look: c.look.to_array(),
        up: c.up.to_array(),
        fov_y_deg: c.fov_degrees,
    };
    dray_protocol::check_camera(&wire).map_err(|e| {
        let name = match e.field {
            CameraField::Eye => "--eye",
            CameraField::Look => "--look",
            CameraField::Up => "--up",
            CameraField::FovYDeg => "--fov",
        };
        anyhow::anyhow!("{name}: {}", e.message)
    })
}

/// Names the flag a check refused.
fn flag(name: &'static str) -> impl Fn(String) -> anyhow::Error {
    move |message| anyhow::anyhow!("{name}: {message}")
}
