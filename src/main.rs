//! The `dray` command line: it parses arguments and calls into the crates.

mod allocator;

use anyhow::{bail, Context, Result};
use clap::{Parser, Subcommand};
use dray_actors::cluster::{NodeOutcome, RunOptions};
use dray_actors::display::path::CameraPath;
use dray_protocol::{CameraField, Reflective, Role};
use dray_scene::db::info::DbInfo;
use dray_scene::db::verify::verify;
use dray_scene::db::Database;
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::preprocess::{self, preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use dray_trace::camera::Camera;
use dray_trace::render::{render_repeated, Isa, Packets, RenderSettings};
use dray_trace::report::{render_path, PathReport, ViewReport};
use dray_trace::scene::{ResidentSource, TopLevel};
use glam::Vec3;
use std::path::{Path, PathBuf};
use std::process::ExitCode;

#[derive(Parser)]
#[command(
    name = "dray",
    version,
    about = "Interactive distributed ray tracing of massive models"
)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// Generate a synthetic model.
    Generate {
        #[command(subcommand)]
        model: GenerateModel,
    },
    /// Build a voxel database from model files (PLY, OBJ), out of core.
    Preprocess {
        /// Model files; triangle ids continue from one file to the next.
        #[arg(required = true)]
        inputs: Vec<PathBuf>,
        /// The database directory to create (replaced atomically if it is one).
        #[arg(long)]
        out: PathBuf,
        /// A BSP node with at most this many triangles becomes a voxel.
        #[arg(long, default_value_t = preprocess::DEFAULT_MAX_TRIANGLES)]
        max_triangles: u32,
        /// A BSP node at this depth becomes a voxel whatever it holds.
        #[arg(long, default_value_t = preprocess::DEFAULT_MAX_DEPTH)]
        max_depth: u32,
        /// Place AxBxC copies of the whole input on a grid, e.g. 2x1x2.
        #[arg(long, value_parser = parse_copies)]
        copies: Option<[u32; 3]>,
        /// Grid step between copies, as a multiple of the input's extent.
        #[arg(long, default_value_t = 1.1)]
        spacing: f32,
        /// Worker threads (default: every core).
        #[arg(long, default_value_t = 0)]
        threads: usize,
        /// Peak memory budget in MiB.
        #[arg(long, default_value_t = preprocess::DEFAULT_MEMORY_MB)]
        memory_mb: u64,
        /// zstd level of the voxel blobs (1-22).
        #[arg(long, default_value_t = preprocess::DEFAULT_ZSTD_LEVEL)]
        zstd_level: i32,
    },
    /// Render one view of a database in this process, every voxel loaded.
    Render(RenderArgs),
    /// Check every voxel of a database; exits non-zero naming each bad one.
    Verify {
        /// The database directory.
        db: PathBuf,
    },
    /// Summarize a database.
    Info {
        /// The database directory.
        db: PathBuf,
        /// One JSON object instead of text.
        #[arg(long)]
        json: bool,
    },
    /// Cluster certificates (mutual TLS between nodes).
    Certs {
        #[command(subcommand)]
        action: CertsAction,
    },
    /// Generate a default plant, preprocess it (kept for the next run), and
    /// render a walkthrough from outside to deep inside on a local cluster
    /// (config/examples/demo.toml: 2 clients, 2 stores, over QUIC).
    Demo {
        /// The demo's cluster config.
        #[arg(long, default_value = DEMO_CONFIG)]
        config: PathBuf,
        /// Triangles of the generated plant.
        #[arg(long, default_value_t = 1_000_000)]
        triangles: u64,
        /// Frames of the walkthrough (when the config's camera path is not
        /// written yet).
        #[arg(long, default_value_t = 90)]
        frames: u32,
    },
    /// Start every node of a config on this machine as separate processes
    /// over QUIC, run the camera path, print a summary, stop them all.
    Cluster {
        /// The cluster config (TOML).
        config: PathBuf,
        /// Write every frame as a PNG (and the metrics CSV) in this
        /// directory, instead of the config's `display.output`.
        #[arg(long, value_name = "DIR")]
        save_frames: Option<PathBuf>,
        /// Kernel instruction set for the clients (default: the best).
        #[arg(long, value_parser = parse_isa)]
        isa: Option<Isa>,
        /// Print the summary as one JSON line.
        #[arg(long)]
        json: bool,
    },
    /// Run one node of a config (for a cluster across machines, from the
    /// same config file on each).
    Node {
        /// The cluster config (TOML), the same file on every machine.
        #[arg(long)]
        config: PathBuf,
        /// Display: write every frame as a PNG (and the metrics CSV) in
        /// this directory, instead of the config's `display.output`.
        #[arg(long, value_name = "DIR")]
        save_frames: Option<PathBuf>,
        /// scheduler, store, client or display.
        #[arg(long, value_parser = parse_role)]
        role: Role,
        /// Which store or client.
        #[arg(long, default_value_t = 0)]
        index: usize,
        /// Kernel instruction set (clients).
        #[arg(long, value_parser = parse_isa)]
        isa: Option<Isa>,
    },
    /// Run every node of a config in this process over the in-process
    /// transport (with the config's link shaping).
    Sim {
        /// The cluster config (TOML).
        config: PathBuf,
        /// Write every frame as a PNG (and the metrics CSV) in this
        /// directory, instead of the config's `display.output`.
        #[arg(long, value_name = "DIR")]
        save_frames: Option<PathBuf>,
        /// Number of clients instead of the config's.
        #[arg(long)]
        clients: Option<u32>,
        /// Kernel instruction set for the clients (default: the best).
        #[arg(long, value_parser = parse_isa)]
        isa: Option<Isa>,
        /// Print the summary as one JSON line.
        #[arg(long)]
        json: bool,
    },
    /// Run an experiment file: every combination of its swept config keys,
    /// `repeat` times; writes points.csv, frames.csv, plots and summary.md
    /// (docs/experiments.md).
    Experiment {
        /// The experiment file (TOML).
        file: PathBuf,
        /// The results directory (default: results/NAME/YYYYmmdd-HHMMSS).
        #[arg(long, conflicts_with = "resume")]
        out: Option<PathBuf>,
        /// Each point once, on a tenth of the frames (at least 2).
        #[arg(long)]
        quick: bool,
        /// Go on with the runs missing from this earlier results directory.
        #[arg(long)]
        resume: Option<PathBuf>,
    },
    /// Write a camera path (TOML keyframes) that flies from outside a
    /// database's model to deep inside it.
    Walkthrough {
        /// The database whose model the path flies into.
        db: PathBuf,
        /// Frames of the path.
        #[arg(long, default_value_t = 90)]
        frames: u32,
        /// The camera path file to write.
        #[arg(long)]
        out: PathBuf,
    },
}

/// The demo's config, relative to the workspace (where `cargo run` runs).
const DEMO_CONFIG: &str = "config/examples/demo.toml";

fn parse_role(s: &str) -> Result<Role, String> {
    match s {
        "scheduler" => Ok(Role::Scheduler),
        "store" => Ok(Role::Store),
        "client" => Ok(Role::Client),
        "display" => Ok(Role::Display),
        _ => Err(format!(
            "'{s}' is not a role (scheduler, store, client, display)"
        )),
    }
}

#[derive(clap::Args)]
struct RenderArgs {
    /// The database directory.
    db: PathBuf,
    /// Camera position (default: a view of the whole model).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    eye: Option<Vec3>,
    /// Point looked at (default: the model's centre).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    look: Option<Vec3>,
    /// Up direction of the image.
    #[arg(long, value_parser = parse_vec3, default_value = "0,1,0", allow_hyphen_values = true)]
    up: Vec3,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 50.0)]
    fov: f32,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    height: u32,
    /// Shaded image (PNG).
    #[arg(long)]
    out: Option<PathBuf>,
    /// Hit distances as a grey PFM (docs/design.md's comparison format).
    #[arg(long)]
    depth_out: Option<PathBuf>,
    /// Original triangle ids as raw little-endian u32.
    #[arg(long)]
    primid_out: Option<PathBuf>,
    /// Hard shadows from the light.
    #[arg(long)]
    shadows: bool,
    /// Direction towards the distant light.
    #[arg(long, value_parser = parse_vec3, default_value = "0.3,1,0.2", allow_hyphen_values = true)]
    light: Vec3,
    /// Mirror bounces on reflective surfaces.
    #[arg(long, default_value_t = 0)]
    reflections: u32,
    /// Which surfaces reflect: all, ids:A-B (original triangle ids, B
    /// exclusive) or color:R,G,B (vertex color).
    #[arg(long, default_value = "all")]
    reflective: Reflective,
    /// Share of the light a reflective surface mirrors (0-1).
    #[arg(long, default_value_t = 0.6)]
    reflectance: f32,
    /// Color each voxel differently (the paper's Figure 5).
    #[arg(long)]
    voxel_colors: bool,
    /// Render threads (default: every core).
    #[arg(long, default_value_t = 0)]
    threads: usize,
    /// Kernel instruction set: avx512, avx2 or portable (default: the best
    /// this CPU has).
    #[arg(long, value_parser = parse_isa)]
    isa: Option<Isa>,
    /// Rays per packet with AVX-512: auto (per tile, from how coherent the
    /// rays of the tiles before were), 16, 32, or sparse (16, and nodes
    /// that at most four lanes enter tested for those four at once).
    #[arg(long, value_parser = parse_packets, default_value = "auto")]
    packets: Packets,
    /// Trace every shadow packet through the voxels, without first trying
    /// the triangle that blocked the packet before (the answers are the
    /// same; for measuring the traversal alone).
    #[arg(long)]
    no_occluder_cache: bool,
    /// Timed passes (after one untimed warm-up); best and median are reported.
    #[arg(long, default_value_t = 1)]
    repeat: usize,
    /// Print one JSON object as the last line.
    #[arg(long)]
    json: bool,
    /// Render every camera of this camera path (TOML keyframes, as the
    /// cluster's `render.camera_path`) instead of one view, shaded, and
    /// report frames per second: the one-process baseline of the cluster.
    #[arg(long, conflicts_with_all = ["eye", "look", "up", "fov", "repeat", "out", "depth_out", "primid_out"])]
    path: Option<PathBuf>,
    /// With `--path`: record which voxels each frame enters and report each
    /// frame's working set (voxel bytes in the kernel's layout, as a
    /// client's cache counts them).
    #[arg(long, requires = "path")]
    working_set: bool,
}

fn parse_isa(s: &str) -> Result<Isa, String> {
    let isa = match s {
        "avx512" => Isa::Avx512,
        "avx2" => Isa::Avx2,
        "portable" => Isa::Portable,
        _ => return Err(format!("'{s}' is not avx512, avx2 or portable")),
    };
    if isa.supported() {
        Ok(isa)
    } else {
        Err(format!("this CPU cannot run the {s} kernel"))
    }
}

fn parse_packets(s: &str) -> Result<Packets, String> {
    match s {
        "auto" => Ok(Packets::Auto),
        "16" => Ok(Packets::Narrow),
        "32" => Ok(Packets::Wide),
        "sparse" => Ok(Packets::Sparse),
        _ => Err(format!("'{s}' is not auto, 16, 32 or sparse")),
    }
}

fn parse_vec3(s: &str) -> Result<Vec3, String> {
    let v: Vec<f32> = s
        .split(',')
        .map(|p| p.trim().parse::<f32>())
        .collect::<Result<_, _>>()
        .map_err(|_| format!("'{s}' is not x,y,z"))?;
    match v[..] {
        [x, y, z] if v.iter().all(|c| c.is_finite()) => Ok(Vec3::new(x, y, z)),
        _ => Err(format!("'{s}' is not x,y,z (three finite numbers)")),
    }
}

#[derive(Subcommand)]
enum CertsAction {
    /// Create a cluster CA and a certificate for every node, named from a
    /// cluster config (--config) or listed (--nodes): DIR/ca.pem and
    /// DIR/NODE.pem, DIR/NODE.key; the CA key goes to DIR/ca/ca.key (or
    /// --ca-dir), apart from the node keys and never needed at run time.
    Init {
        /// The certificate directory to create.
        dir: PathBuf,
        /// Issue certificates for every node of this cluster config.
        #[arg(long, conflicts_with = "nodes")]
        config: Option<PathBuf>,
        /// Node names, comma separated (e.g. scheduler,display,store-0,client-0).
        #[arg(long, value_delimiter = ',')]
        nodes: Vec<String>,
        /// Folder for the CA key (default DIR/ca).
        #[arg(long)]
        ca_dir: Option<PathBuf>,
    },
    /// Issue certificates for more nodes from DIR's existing CA, leaving
    /// the others' as they are.
    Add {
        /// The certificate directory made by `dray certs init`.
        dir: PathBuf,
        /// Node names, comma separated.
        #[arg(long = "node", alias = "nodes", value_delimiter = ',', required = true)]
        nodes: Vec<String>,
        /// Folder of the CA key (default DIR/ca).
        #[arg(long)]
        ca_dir: Option<PathBuf>,
    },
    /// Copy what one node needs at run time (ca.pem, NODE.pem, NODE.key;
    /// never the CA key) to a folder for its host, to use as its certs.dir.
    Bundle {
        /// The certificate directory made by `dray certs init`.
        dir: PathBuf,
        /// The node.
        #[arg(long)]
        node: String,
        /// Where to write the bundle (default DIR/bundles/NODE).
        #[arg(long)]
        out: Option<PathBuf>,
    },
}

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

#[derive(Subcommand)]
enum GenerateModel {
    /// A power plant like the paper's: steel frame, pipes, tanks, machinery.
    Plant {
        /// Triangles of the plant (about; the last part is cut to fit).
        #[arg(long)]
        triangles: u64,
        /// Random seed: the same seed and count give the same file.
        #[arg(long, default_value_t = 1)]
        seed: u64,
        /// The PLY file to write.
        #[arg(long)]
        out: PathBuf,
    },
}

fn parse_copies(s: &str) -> Result<[u32; 3], String> {
    let parts: Vec<&str> = s.split(['x', 'X']).collect();
    let bad = || format!("'{s}' is not AxBxC (three positive integers, e.g. 2x1x2)");
    if parts.len() != 3 {
        return Err(bad());
    }
    let mut out = [0u32; 3];
    for (o, p) in out.iter_mut().zip(parts) {
        *o = p.trim().parse().map_err(|_| bad())?;
        if *o == 0 {
            return Err(bad());
        }
    }
    Ok(out)
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
        Command::Cluster {
            config,
            save_frames,
            isa,
            json,
        } => {
            let cfg = dray_config::Config::load(&config)?;
            dray_actors::cluster::preflight(&cfg, None)?;
            let mut extra = Vec::new();
            if let Some(isa) = isa {
                extra.extend(["--isa".to_string(), isa.name().to_string()]);
            }
            if let Some(dir) = &save_frames {
                let dir = std::path::absolute(dir).context("the --save-frames directory")?;
                extra.extend(["--save-frames".to_string(), dir.display().to_string()]);
            }
            let exe = std::env::current_exe().context("finding the dray binary")?;
            let report =
                runtime()?.block_on(dray_actors::launch::cluster(&exe, &config, &cfg, &extra))?;
            print_report(&report.summary, &report.events, json);
        }
        Command::Node {
            config,
            save_frames,
            role,
            index,
            isa,
        } => {
            let mut cfg = dray_config::Config::load(&config)?;
            save_frames_to(&mut cfg, save_frames);
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
            let outcome = match rt.block_on(dray_actors::cluster::node(&cfg, role, index, &opts)) {
                Ok(outcome) => outcome,
                Err(e @ dray_actors::cluster::ClusterError::AddressInUse { .. }) => {
                    // Starting this node again would fail the same way.
                    eprintln!("error: {e}");
                    return Ok(ExitCode::from(dray_actors::launch::EXIT_NO_RESTART));
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
                ..RunOptions::default()
            };
            let run = runtime()?.block_on(dray_actors::cluster::sim(&cfg, &opts))?;
            print_report(&run.to_json(), &[], json);
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
    let m = &report.manifest;
    let peak = dray_runtime::process::peak_rss_bytes()
        .map(|b| format!(", peak RSS {} MiB", b >> 20))
        .unwrap_or_default();
    println!(
        "{}: {} triangles -> {} voxels in {:.1} s ({:.2} M triangles/s), replication {:.3}{peak}",
        opts.out.display(),
        m.input_triangles,
        m.voxels.len(),
        report.seconds,
        m.input_triangles as f64 / report.seconds / 1e6,
        m.stored_triangles as f64 / m.input_triangles as f64
    );
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
    let report = runtime()?.block_on(dray_actors::launch::cluster(&exe, config, &cfg, &[]))?;
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
            ..render_path(&top, &source, &cameras, &settings, a.working_set).map_err(not_loaded)?
        };
        print!("{}", report.text());
        if a.json {
            println!("{}", report.to_json());
        }
        return Ok(());
    }
    let passes =
        render_repeated(&top, &source, &camera, &settings, a.repeat).map_err(not_loaded)?;
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

#[cfg(test)]
mod tests {
    use super::Cli;
    use clap::CommandFactory;

    /// Adds to `missing` each subcommand under `cmd` without an about text
    /// and each argument without a help text.
    fn undocumented(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
        let blank = |t: Option<&clap::builder::StyledStr>| {
            t.is_none_or(|t| t.to_string().trim().is_empty())
        };
        for arg in cmd.get_arguments() {
            if blank(arg.get_help()) {
                missing.push(format!("{path} {}", arg.get_id()));
            }
        }
        for sub in cmd.get_subcommands() {
            let path = format!("{path} {}", sub.get_name());
            if blank(sub.get_about()) {
                missing.push(path.clone());
            }
            undocumented(sub, &path, missing);
        }
    }

    #[test]
    fn every_subcommand_and_argument_has_help() {
        let cli = Cli::command();
        cli.clone().debug_assert();
        let mut missing = Vec::new();
        undocumented(&cli, "dray", &mut missing);
        assert!(missing.is_empty(), "no help text: {missing:?}");
    }

    /// A flag name means one kind of value in every subcommand: `--frames`
    /// is always a count, and the frames' directory is `--save-frames`.
    #[test]
    fn a_flag_name_takes_one_kind_of_value_everywhere() {
        let mut kinds = std::collections::BTreeMap::<String, Vec<String>>::new();
        fn collect(
            cmd: &clap::Command,
            kinds: &mut std::collections::BTreeMap<String, Vec<String>>,
        ) {
            for arg in cmd.get_arguments() {
                if let Some(long) = arg.get_long() {
                    let kind = format!("{:?}", arg.get_value_parser().type_id());
                    let seen = kinds.entry(long.to_string()).or_default();
                    if !seen.contains(&kind) {
                        seen.push(kind);
                    }
                }
            }
            for sub in cmd.get_subcommands() {
                collect(sub, kinds);
            }
        }
        collect(&Cli::command(), &mut kinds);
        let mixed: Vec<_> = kinds.iter().filter(|(_, k)| k.len() > 1).collect();
        assert!(
            mixed.is_empty(),
            "flags with values of different types: {mixed:?}"
        );
        assert!(kinds.contains_key("save-frames") && kinds.contains_key("frames"));
    }
}
