//! The command line's definition: every subcommand and flag with its
//! help, and the parsers of flag values. `main.rs` dispatches on it.

use clap::{Parser, Subcommand};
use dray_protocol::{Reflective, Role};
use dray_scene::preprocess;
use dray_trace::render::{Isa, Packets};
use glam::Vec3;
use std::path::PathBuf;

#[derive(Parser)]
#[command(
    name = "dray",
    version,
    about = "Interactive distributed ray tracing of massive models"
)]
pub(crate) struct Cli {
    #[command(subcommand)]
    pub(crate) command: Command,
}

#[derive(Subcommand)]
pub(crate) enum Command {
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
    /// Cut a database into shards, for stores on hosts of their own.
    ///
    /// Writes DIR/shard-0 to DIR/shard-(N-1), each holding the voxels whose
    /// id is I modulo N and the whole manifest; a store serving shard I/N
    /// reads it with `stores[I].database`.
    Shard {
        /// The database directory.
        db: PathBuf,
        /// How many shards.
        #[arg(long = "of", value_name = "N")]
        count: u32,
        /// Where to write the shard directories.
        #[arg(long, value_name = "DIR")]
        out: PathBuf,
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
    /// Fly through a model in the browser: start a local cluster on a
    /// database (or on a cluster config with `display.web` and no camera
    /// path) and print the viewer's address; Ctrl-C stops it.
    View {
        /// A database (from `dray preprocess`) or a cluster config (TOML).
        target: PathBuf,
        /// Render clients (on a database).
        #[arg(long, default_value_t = 2)]
        clients: u32,
        /// Render threads per client, 0: one per core (on a database).
        #[arg(long, default_value_t = 1)]
        threads: usize,
        /// Where the viewer listens [default: 127.0.0.1:7480, or a free
        /// port when it is taken] (on a database).
        #[arg(long, value_name = "IP:PORT")]
        web: Option<String>,
        /// Image width at the 1× resolution (on a database).
        #[arg(long, default_value_t = 960)]
        width: u32,
        /// Image height at the 1× resolution (on a database).
        #[arg(long, default_value_t = 540)]
        height: u32,
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
    ///
    /// Without --role, the node is the one of this process's rank under
    /// Slurm, an MPI launcher or Kubernetes (`launch.ranks` in the config;
    /// docs/deploy.md).
    Node {
        /// The cluster config (TOML), the same file on every machine.
        #[arg(long)]
        config: PathBuf,
        /// Display: write every frame as a PNG (and the metrics CSV) in
        /// this directory, instead of the config's `display.output`.
        #[arg(long, value_name = "DIR")]
        save_frames: Option<PathBuf>,
        /// scheduler, store, client or display [default: from the
        /// launcher's rank].
        #[arg(long, value_parser = parse_role)]
        role: Option<Role>,
        /// Which store or client [default: 0 with --role].
        #[arg(long, requires = "role")]
        index: Option<usize>,
        /// Print the node's name (e.g. `store-1`) and exit: for a
        /// launcher's script that prepares the node's files.
        #[arg(long)]
        print_node: bool,
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
        /// Run on a virtual clock: each client's tracing and decoding take
        /// the time a cost model measured on this machine says (scaled by
        /// `clients.speed`), as if every client had machines of its own
        /// (docs/experiments.md, "The virtual engine").
        #[arg(long = "virtual")]
        virtual_clock: bool,
        /// With --virtual: every client shares one host of N cores, as the
        /// clients of a plain `dray sim` share this machine's (to compare
        /// the two), instead of each having a machine of its own.
        #[arg(long, value_name = "N", requires = "virtual_clock", value_parser = clap::value_parser!(u32).range(1..=4096))]
        host_cores: Option<u32>,
        /// With --virtual: this cost model instead of calibrating one: a
        /// run's `calibration.json` from an experiment (its `model`), or
        /// the model's keys alone, as JSON.
        #[arg(long, value_name = "FILE", requires = "virtual_clock")]
        cost: Option<PathBuf>,
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
pub(crate) const DEMO_CONFIG: &str = "config/examples/demo.toml";

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
pub(crate) struct RenderArgs {
    /// The database directory.
    pub(crate) db: PathBuf,
    /// Camera position (default: a view of the whole model).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub(crate) eye: Option<Vec3>,
    /// Point looked at (default: the model's centre).
    #[arg(long, value_parser = parse_vec3, allow_hyphen_values = true)]
    pub(crate) look: Option<Vec3>,
    /// Up direction of the image.
    #[arg(long, value_parser = parse_vec3, default_value = "0,1,0", allow_hyphen_values = true)]
    pub(crate) up: Vec3,
    /// Vertical field of view in degrees.
    #[arg(long, default_value_t = 50.0)]
    pub(crate) fov: f32,
    /// Image width in pixels.
    #[arg(long, default_value_t = 640)]
    pub(crate) width: u32,
    /// Image height in pixels.
    #[arg(long, default_value_t = 480)]
    pub(crate) height: u32,
    /// Shaded image (PNG).
    #[arg(long)]
    pub(crate) out: Option<PathBuf>,
    /// Hit distances as a grey PFM (docs/design.md's comparison format).
    #[arg(long)]
    pub(crate) depth_out: Option<PathBuf>,
    /// Original triangle ids as raw little-endian u32.
    #[arg(long)]
    pub(crate) primid_out: Option<PathBuf>,
    /// Hard shadows from the light.
    #[arg(long)]
    pub(crate) shadows: bool,
    /// Direction towards the distant light.
    #[arg(long, value_parser = parse_vec3, default_value = "0.3,1,0.2", allow_hyphen_values = true)]
    pub(crate) light: Vec3,
    /// Mirror bounces on reflective surfaces.
    #[arg(long, default_value_t = 0)]
    pub(crate) reflections: u32,
    /// Which surfaces reflect: all, ids:A-B (original triangle ids, B
    /// exclusive) or color:R,G,B (vertex color).
    #[arg(long, default_value = "all")]
    pub(crate) reflective: Reflective,
    /// Share of the light a reflective surface mirrors (0-1).
    #[arg(long, default_value_t = 0.6)]
    pub(crate) reflectance: f32,
    /// Color each voxel differently (the paper's Figure 5).
    #[arg(long)]
    pub(crate) voxel_colors: bool,
    /// Render threads (default: every core).
    #[arg(long, default_value_t = 0)]
    pub(crate) threads: usize,
    /// Kernel instruction set: avx512, avx2 or portable (default: the best
    /// this CPU has).
    #[arg(long, value_parser = parse_isa)]
    pub(crate) isa: Option<Isa>,
    /// Rays per packet with AVX-512: auto (per tile, from how coherent the
    /// rays of the tiles before were), 16, 32, or sparse (16, and nodes
    /// that at most four lanes enter tested for those four at once).
    #[arg(long, value_parser = parse_packets, default_value = "auto")]
    pub(crate) packets: Packets,
    /// Trace every shadow packet through the voxels, without first trying
    /// the triangle that blocked the packet before (the answers are the
    /// same; for measuring the traversal alone).
    #[arg(long)]
    pub(crate) no_occluder_cache: bool,
    /// Timed passes (after one untimed warm-up); best and median are reported.
    #[arg(long, default_value_t = 1)]
    pub(crate) repeat: usize,
    /// Samples per pixel, 1-1024: samples 0 to N-1 of the view, averaged
    /// into the image (anti-aliasing). Sample 0's rays pass through the
    /// pixel centres, each other sample's through every pixel at the same
    /// sub-pixel offset; the depth and ids are sample 0's, and the rays
    /// and rates count every sample. With --path, each camera is rendered
    /// N times, as the cluster does with render.samples.
    #[arg(long, default_value_t = 1)]
    pub(crate) spp: u32,
    /// Print one JSON object as the last line.
    #[arg(long)]
    pub(crate) json: bool,
    /// Render every camera of this camera path (TOML keyframes, as the
    /// cluster's `render.camera_path`) instead of one view, shaded, and
    /// report frames per second: the one-process baseline of the cluster.
    #[arg(long, conflicts_with_all = ["eye", "look", "up", "fov", "repeat", "out", "depth_out", "primid_out"])]
    pub(crate) path: Option<PathBuf>,
    /// With `--path`: record which voxels each frame enters and report each
    /// frame's working set (voxel bytes in the kernel's layout, as a
    /// client's cache counts them).
    #[arg(long, requires = "path")]
    pub(crate) working_set: bool,
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
pub(crate) enum CertsAction {
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

#[derive(Subcommand)]
pub(crate) enum GenerateModel {
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
