//! dray-config: the one cluster config (TOML) with validation.
//!
//! One file describes a whole cluster: the scene database, the render
//! settings, where the scheduler, the display and each store listen, how many
//! clients run and how (threads, cache budget, miss mode), link shaping per
//! link class, and the certificate directory. [`Config::load`] parses and
//! validates it; every error names the key and the problem. Relative paths
//! are taken relative to the config file's directory.
//!
//! Node names are fixed by role: `scheduler`, `display`, `store-I`,
//! `client-I` (I from 0); [`Config::node_names`] lists them, e.g. for
//! issuing certificates.
//!
//! The preprocessing parameters live with the preprocessor in `dray-scene`.

/// Most voxel stores a cluster may have (shards count up to 1024 too).
pub const MAX_STORES: usize = 1024;

/// Whether shards `(index, count)` together serve every voxel id: every
/// residue of their counts' common multiple must be some shard's. The
/// problem in words otherwise (a count of 0, an index not below its
/// count, counts too many or too mixed, a residue nobody serves).
pub fn check_shards(shards: &[(u32, u32)]) -> Result<(), String> {
    if let Some(&(i, c)) = shards.iter().find(|&&(i, c)| c == 0 || i >= c) {
        return Err(format!("shard {i}/{c} is not of the form I/N with I < N"));
    }
    // Stops growing past the limit, so that no product overflows.
    let lcm = shards.iter().fold(1u64, |l, &(_, c)| {
        if l > 1 << 16 {
            return l;
        }
        let (mut a, mut b) = (l, u64::from(c));
        while b != 0 {
            (a, b) = (b, a % b);
        }
        l / a * u64::from(c)
    });
    if lcm > 1 << 16 {
        return Err("shard counts are too many or too mixed".into());
    }
    for r in 0..lcm as u32 {
        if !shards.iter().any(|&(i, c)| r % c == i) {
            return Err(format!(
                "no store serves the voxels whose id is {r} modulo {lcm}"
            ));
        }
    }
    Ok(())
}

pub mod address;
pub mod launch;

pub use address::NodeAddress;
use dray_protocol::Role;
pub use dray_protocol::{Compression, Reflective};
use serde::Deserialize;
use std::net::{IpAddr, Ipv4Addr, Ipv6Addr, SocketAddr};
use std::path::{Path, PathBuf};
use std::time::Duration;

/// Largest tile side (the wire limit of a tile result).
pub const MAX_TILE_SIZE: u32 = 256;
/// Largest image side (the wire's limit).
pub const MAX_IMAGE_SIZE: u32 = dray_protocol::MAX_IMAGE_SIDE;
/// Most bytes of pixels the display may hold for the frames in flight
/// (`display.frames_ahead` frames of `render.width` x `render.height`).
pub const MAX_FRAMES_IN_FLIGHT_BYTES: u64 = 4 << 30;

/// Checks an image side: `render.width` and `render.height` here, and
/// `dray render`'s `--width` and `--height`; the error names `key`.
pub fn check_image_side(key: &str, side: u32) -> Result<(), ConfigError> {
    dray_protocol::check_image_side(side).map_err(|m| invalid(key, m))
}

/// Checks a camera ([`dray_protocol::check_camera`]); the error names the
/// field under `key` (e.g. `render.camera.up`).
fn check_camera(key: &str, c: &CameraConfig) -> Result<(), ConfigError> {
    dray_protocol::check_camera(&c.to_wire())
        .map_err(|e| invalid(format!("{key}.{}", e.field.name()), e.message))
}

/// Bytes the display holds per pixel of a frame in flight: the colors,
/// and depth and primitive ids when the tiles carry them.
pub fn display_bytes_per_pixel(depth_and_ids: bool) -> u64 {
    if depth_and_ids {
        12
    } else {
        4
    }
}

/// Why a config is unusable.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    /// The file could not be read.
    #[error("{path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// What happened.
        source: std::io::Error,
    },
    /// Not valid TOML, an unknown field, or a value of the wrong type.
    #[error("{path}: {message}")]
    Parse {
        /// The file.
        path: PathBuf,
        /// toml's message, with the line and the key.
        message: String,
    },
    /// A value is out of range or inconsistent.
    #[error("{key}: {problem}")]
    Invalid {
        /// The dotted key, e.g. `clients.cache_mb` or `stores[1].address`.
        key: String,
        /// What is wrong.
        problem: String,
    },
}

fn invalid(key: impl Into<String>, problem: impl Into<String>) -> ConfigError {
    ConfigError::Invalid {
        key: key.into(),
        problem: problem.into(),
    }
}

/// The whole cluster.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Config {
    /// The voxel database.
    pub scene: SceneConfig,
    /// What to render.
    pub render: RenderConfig,
    /// The scheduler node.
    pub scheduler: SchedulerConfig,
    /// The display node.
    pub display: DisplayConfig,
    /// The voxel stores (at least one); each serves a shard.
    pub stores: Vec<StoreConfig>,
    /// The render clients.
    pub clients: ClientsConfig,
    /// The prefetcher.
    #[serde(default)]
    pub prefetch: PrefetchConfig,
    /// Link shaping per link class.
    #[serde(default)]
    pub links: LinksConfig,
    /// The cluster certificates.
    pub certs: CertsConfig,
    /// How a launcher's ranks map to nodes, and the hosts `{host:N}` names.
    #[serde(default)]
    pub launch: LaunchConfig,
}

/// What `dray node` does when a launcher (Slurm, MPI, Kubernetes) starts
/// it without `--role` ([`launch`]).
#[derive(Clone, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LaunchConfig {
    /// The node each rank runs, in rank order (e.g. `["scheduler",
    /// "display", "store-0", "client-0"]`): any of the config's nodes, each
    /// at most once. Default: every node, in [`Config::node_names`] order.
    #[serde(default)]
    pub ranks: Option<Vec<String>>,
    /// The hosts that `{host:N}` in an address names, when the launcher
    /// gives none (Slurm gives its node list; this list wins over it).
    #[serde(default)]
    pub hosts: Vec<String>,
    /// Where `hosts` came from when a launcher gave them (its variable).
    #[serde(skip)]
    pub hosts_from: Option<&'static str>,
}

/// The scene.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SceneConfig {
    /// Directory of the voxel database made by `dray preprocess`.
    pub database: PathBuf,
}

/// A pinhole camera (docs/design.md, "Conventions").
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CameraConfig {
    /// Eye position.
    pub eye: [f32; 3],
    /// Point looked at.
    pub look: [f32; 3],
    /// Up hint.
    #[serde(default = "default_up")]
    pub up: [f32; 3],
    /// Vertical field of view, degrees.
    #[serde(default = "default_fov")]
    pub fov_y_deg: f32,
}

impl CameraConfig {
    /// The camera as the messages carry it.
    pub fn to_wire(&self) -> dray_protocol::Camera {
        dray_protocol::Camera {
            eye: self.eye,
            look: self.look,
            up: self.up,
            fov_y_deg: self.fov_y_deg,
        }
    }
}

fn default_up() -> [f32; 3] {
    [0.0, 1.0, 0.0]
}
fn default_fov() -> f32 {
    45.0
}

/// What to render.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct RenderConfig {
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// Tile side, pixels.
    #[serde(default = "default_tile")]
    pub tile_size: u32,
    /// Trace shadow rays.
    #[serde(default)]
    pub shadows: bool,
    /// Reflection recursion depth.
    #[serde(default)]
    pub reflection_depth: u8,
    /// Direction towards the distant light (need not be normalized).
    #[serde(default = "default_light")]
    pub light_dir: [f32; 3],
    /// Which surfaces are mirrors: `all`, `ids:A-B` or `color:R,G,B`.
    #[serde(default = "default_reflective", deserialize_with = "reflective")]
    pub reflective: Reflective,
    /// Share of the light a mirror reflects, in [0, 1].
    #[serde(default = "default_reflectance")]
    pub reflectance: f32,
    /// Color each voxel differently (the paper's Figure 5).
    #[serde(default)]
    pub voxel_colors: bool,
    /// Also send per-pixel depth and primitive ids to the display (for
    /// comparisons with `dray render`).
    #[serde(default)]
    pub depth_and_ids: bool,
    /// The camera when there is no camera path (interactive: where the
    /// user starts).
    pub camera: CameraConfig,
    /// A camera path to follow (keyframes, TOML; one camera per frame).
    #[serde(default)]
    pub camera_path: Option<PathBuf>,
    /// Frames of the fixed camera to render when there is no camera path
    /// and no web viewer (with `display.web` and no path the display is
    /// interactive and renders until it is stopped).
    #[serde(default = "default_frames")]
    pub frames: u32,
    /// Times the camera path is flown (later loops run on warm caches).
    #[serde(default = "default_loops")]
    pub loops: u32,
    /// Samples per pixel of each camera (of the path, or of `frames`):
    /// each camera is rendered this many times, samples 0..samples with
    /// jittered rays, as consecutive frames, and the display averages
    /// them into the camera's image. Not used in interactive mode.
    #[serde(default = "default_samples")]
    pub samples: u32,
}

fn default_samples() -> u32 {
    1
}

fn default_loops() -> u32 {
    1
}

fn default_light() -> [f32; 3] {
    [0.3, 1.0, 0.2]
}
fn default_reflective() -> Reflective {
    Reflective::All
}
fn default_reflectance() -> f32 {
    0.6
}
fn default_frames() -> u32 {
    1
}

fn reflective<'de, D: serde::Deserializer<'de>>(d: D) -> Result<Reflective, D::Error> {
    let s = String::deserialize(d)?;
    s.parse().map_err(serde::de::Error::custom)
}

fn default_tile() -> u32 {
    32
}

/// The scheduler node (with the frame assigner and the prefetcher).
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct SchedulerConfig {
    /// `host:port` it listens on (QUIC, UDP).
    pub address: String,
    /// Which tile policy hands out the tiles (see [`TilePolicy`]).
    #[serde(default, deserialize_with = "tile_policy")]
    pub policy: TilePolicy,
    /// A knob of the `affinity` policy: hand out a client's tiles (and
    /// tiles taken from others) costliest first, by the last frame's time
    /// of each tile.
    #[serde(default = "yes")]
    pub costliest_first: bool,
    /// A tile not done this long after its assignment (and at least 8
    /// times the frame's median tile time) is given to another client, ms.
    #[serde(default = "default_deadline")]
    pub tile_deadline_ms: u64,
    /// A knob of the `affinity` policy: early in a frame a client gets an
    /// aligned block of its tiles as one assignment, at most this many pixels a side (its
    /// pixels come back in one message; the blocks shrink to single tiles
    /// as the frame's tiles run out, and only tiles the previous frame
    /// rendered without a miss go in blocks, unless the client's cache
    /// holds the whole model). A value under twice the
    /// tile size hands out single tiles only.
    #[serde(default = "default_max_block_px")]
    pub max_block_px: u32,
}

/// The closed set of tile policies, chosen by name with `scheduler.policy`.
/// The scheduler implements each in its own file under
/// `actors/src/scheduler/policy/`.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Hash)]
pub enum TilePolicy {
    /// Each tile preferably to the client whose cache holds what it shows:
    /// while the camera travels the way it looks, the client whose sector
    /// around the image's centre it lies in; else the client that rendered
    /// in the last frame what the tile shows now (reprojection); else its
    /// last client.
    #[default]
    Affinity,
    /// A uniformly random fresh tile to whichever client asks (the
    /// baseline affinity is measured against).
    Random,
}

impl TilePolicy {
    /// Every policy, in the order the choices are listed.
    pub const ALL: [TilePolicy; 2] = [TilePolicy::Affinity, TilePolicy::Random];

    /// The policy's name in the config.
    pub fn name(self) -> &'static str {
        match self {
            TilePolicy::Affinity => "affinity",
            TilePolicy::Random => "random",
        }
    }
}

impl std::fmt::Display for TilePolicy {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

impl std::str::FromStr for TilePolicy {
    type Err = String;

    /// A policy by its name; the error names the key and the choices.
    fn from_str(s: &str) -> Result<TilePolicy, String> {
        TilePolicy::ALL
            .into_iter()
            .find(|p| p.name() == s)
            .ok_or_else(|| {
                let names: Vec<&str> = TilePolicy::ALL.iter().map(|p| p.name()).collect();
                format!(
                    "scheduler.policy: {s:?} is not a tile policy; the choices are {}",
                    names.join(", ")
                )
            })
    }
}

fn tile_policy<'de, D: serde::Deserializer<'de>>(d: D) -> Result<TilePolicy, D::Error> {
    let s = String::deserialize(d)?;
    s.parse().map_err(serde::de::Error::custom)
}

fn yes() -> bool {
    true
}
fn default_deadline() -> u64 {
    2000
}
/// The default [`SchedulerConfig::max_block_px`]: 4 × 4 tiles of 32 pixels.
pub const DEFAULT_MAX_BLOCK_PX: u32 = 128;
fn default_max_block_px() -> u32 {
    DEFAULT_MAX_BLOCK_PX
}

/// A voxel store.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct StoreConfig {
    /// `host:port` it listens on (QUIC, UDP).
    pub address: String,
    /// The voxels it serves, `I/N`: ids equal to I modulo N. Default: store
    /// i of n serves `i/n`.
    #[serde(default)]
    pub shard: Option<String>,
    /// Most voxel reads at once.
    #[serde(default = "default_store_concurrency")]
    pub max_concurrent: u32,
    /// The database this store reads, instead of `scene.database`: a
    /// shard of it made by `dray shard` (holding at least the voxels of
    /// `shard`), or a copy on the store's host.
    #[serde(default)]
    pub database: Option<PathBuf>,
}

fn default_store_concurrency() -> u32 {
    16
}

/// The prefetcher.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct PrefetchConfig {
    /// Send clients hints for the predicted next frame.
    #[serde(default = "yes")]
    pub enabled: bool,
    /// One sample ray per `step` x `step` pixels.
    #[serde(default = "default_prefetch_step")]
    pub step: u32,
    /// Voxels along each sample ray to hint, nearest first.
    #[serde(default = "default_prefetch_depth")]
    pub voxels_per_ray: u32,
}

impl Default for PrefetchConfig {
    fn default() -> Self {
        PrefetchConfig {
            enabled: true,
            step: default_prefetch_step(),
            voxels_per_ray: default_prefetch_depth(),
        }
    }
}

fn default_prefetch_step() -> u32 {
    8
}
fn default_prefetch_depth() -> u32 {
    2
}

/// The display node.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DisplayConfig {
    /// `host:port` it listens on (QUIC, UDP).
    pub address: String,
    /// `host:port` of the live web viewer (HTTP); none: no viewer. Without
    /// `render.camera_path` it makes the display interactive: the page's
    /// keys move the camera, and the run goes on until Ctrl-C.
    #[serde(default)]
    pub web: Option<String>,
    /// Directory for PNG frames and the metrics CSV; none: not written.
    #[serde(default)]
    pub output: Option<PathBuf>,
    /// Write every frame as a PNG under `output` (else only the metrics).
    #[serde(default = "yes")]
    pub save_frames: bool,
    /// Frames in flight: the display sends the camera of frame k+n while
    /// frame k is not yet complete (double buffering at 2).
    #[serde(default = "default_frames_ahead")]
    pub frames_ahead: u32,
    /// Interactive: samples per pixel a still view is refined to (each
    /// frame adds one jittered sample; any move starts again at one).
    #[serde(default = "default_max_samples")]
    pub max_samples: u32,
}

fn default_frames_ahead() -> u32 {
    2
}

fn default_max_samples() -> u32 {
    32
}

/// Most samples per pixel a view is refined to.
pub const MAX_SAMPLES: u32 = 1024;

/// What a client does when a packet needs a voxel it does not have.
#[derive(Clone, Copy, Debug, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum MissMode {
    /// Suspend the packet, fetch asynchronously, go on with other packets.
    Suspend,
    /// Stall the render thread until the voxel arrives (the baseline).
    Block,
}

/// What a run does with a voxel that no store serves intact (every store
/// serving it sent a corrupt blob or refused it, as often as a client tries).
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq, Eq)]
#[serde(rename_all = "lowercase")]
pub enum CorruptVoxel {
    /// End the run with an error naming the voxel and the store.
    #[default]
    Fail,
    /// Render on with the voxel treated as empty; each such voxel is logged
    /// once and counted in the run's summary.
    Skip,
}

/// The render clients.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct ClientsConfig {
    /// How many clients `dray cluster` starts.
    pub count: u32,
    /// Render threads per client.
    pub threads: u32,
    /// Voxel cache budget per client, MB (10^6 bytes; fractions allowed).
    pub cache_mb: f64,
    /// Miss mode (`on_miss` is accepted too).
    #[serde(default = "default_miss", alias = "on_miss")]
    pub miss_mode: MissMode,
    /// Most voxel fetches in flight (or being decoded) per client.
    #[serde(default = "default_inflight")]
    pub max_inflight_fetches: u32,
    /// Tiles a client asks for beyond those its threads are rendering, so
    /// it never idles waiting for the scheduler: at first, and at least.
    /// One (the default) is enough where a tile takes longer than a round
    /// trip to the scheduler; fast tiles (primary rays in 32-pixel tiles
    /// take a fraction of a millisecond) need 16 to 32, which the client
    /// finds by itself (up to `max_tiles_ahead`). Finished tiles leave in
    /// batches of half the tiles asked ahead
    /// (`experiments/efficiency.toml`).
    #[serde(default = "default_tiles_ahead")]
    pub tiles_ahead: u32,
    /// Most tiles a client asks for ahead. Above `tiles_ahead`, a client
    /// whose render threads run out of tiles before the next ones come
    /// (fast tiles, a slow round trip) asks for half as many again as
    /// before, up to this, and gives one back after a long stretch without
    /// running dry, down to `tiles_ahead` (in suspend mode; a blocked
    /// thread renders one tile at a time whatever its client holds).
    /// Unset, it is 32 (or `tiles_ahead`, if more); at most `tiles_ahead`
    /// fixes the number.
    #[serde(default)]
    pub max_tiles_ahead: Option<u32>,
    /// Fetch every voxel that fits the cache before asking for tiles: warm
    /// caches from the first frame, for a model that fits the clients'
    /// memory (the rest, if any, is fetched on demand).
    #[serde(default)]
    pub preload: bool,
    /// How finished tiles' pixels are compressed (where that makes them
    /// smaller) on their way to the display: `"lz4"` (the default: the
    /// least CPU, several times fewer bytes), `"zstd"` (its fastest level:
    /// about a fifth fewer bytes than LZ4 for more CPU, for slow links) or
    /// `"none"` (more CPU than LZ4 even over loopback: more packets).
    #[serde(default)]
    pub pixel_compression: Compression,
    /// IP the clients bind (they dial out; the port is picked). Default:
    /// every interface (`0.0.0.0`, or `::` where the scheduler's address
    /// is IPv6).
    #[serde(default)]
    pub bind: Option<String>,
    /// A voxel no store serves intact: `"fail"` ends the run, `"skip"`
    /// renders it as empty.
    #[serde(default)]
    pub corrupt_voxel: CorruptVoxel,
    /// How fast a client traces relative to the core the virtual
    /// engine's cost model was measured on (`dray sim --virtual`,
    /// `engine = "virtual"`): 2 is twice as fast. Real runs go as fast as
    /// their machines and ignore it. Default 1.
    #[serde(default = "default_speed")]
    pub speed: f64,
    /// The same for decoding voxels (which the paper found negligible on
    /// its clients while their tracing was slow). Default 1.
    #[serde(default = "default_speed")]
    pub decode_speed: f64,
}

/// The most tiles a client asks for ahead when the config does not say.
pub const DEFAULT_MAX_TILES_AHEAD: u32 = 32;

impl ClientsConfig {
    /// The most tiles a client asks for ahead: `max_tiles_ahead`, or
    /// [`DEFAULT_MAX_TILES_AHEAD`] (`tiles_ahead` if that is more).
    pub fn most_tiles_ahead(&self) -> u32 {
        self.max_tiles_ahead
            .unwrap_or(DEFAULT_MAX_TILES_AHEAD.max(self.tiles_ahead))
    }
}

fn default_miss() -> MissMode {
    MissMode::Suspend
}
fn default_inflight() -> u32 {
    64
}
fn default_speed() -> f64 {
    1.0
}
fn default_tiles_ahead() -> u32 {
    1
}

/// The slowest link or disk a config may model, Mbit/s: a QUIC datagram
/// then takes about 0.1 s, which handshakes and timeouts still allow.
pub const MIN_BANDWIDTH_MBPS: f64 = 0.1;

/// Shaping of one link class, each direction.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinkConfig {
    /// One-way latency, ms.
    #[serde(default)]
    pub latency_ms: f64,
    /// Uniform jitter added to the latency, ms.
    #[serde(default)]
    pub jitter_ms: f64,
    /// Bandwidth cap, Mbit/s; none: unlimited.
    #[serde(default)]
    pub bandwidth_mbps: Option<f64>,
    /// Loss probability in [0, 1).
    #[serde(default)]
    pub loss: f64,
}

impl LinkConfig {
    /// The latency as a duration.
    pub fn latency(&self) -> Duration {
        Duration::from_secs_f64(self.latency_ms / 1000.0)
    }

    /// The jitter as a duration.
    pub fn jitter(&self) -> Duration {
        Duration::from_secs_f64(self.jitter_ms / 1000.0)
    }

    /// The cap in bits per second.
    pub fn bandwidth_bps(&self) -> Option<u64> {
        self.bandwidth_mbps.map(|m| (m * 1e6).round() as u64)
    }

    /// Whether the link is shaped at all.
    pub fn is_shaped(&self) -> bool {
        *self != LinkConfig::default()
    }

    fn validate(&self, key: &str) -> Result<(), ConfigError> {
        let ms = |v: f64, k: &str| {
            if v.is_finite() && (0.0..=60_000.0).contains(&v) {
                Ok(())
            } else {
                Err(invalid(
                    format!("{key}.{k}"),
                    format!("{v} is not between 0 and 60000 ms"),
                ))
            }
        };
        ms(self.latency_ms, "latency_ms")?;
        ms(self.jitter_ms, "jitter_ms")?;
        if let Some(b) = self.bandwidth_mbps {
            if !(b.is_finite() && (MIN_BANDWIDTH_MBPS..=1e6).contains(&b)) {
                return Err(invalid(
                    format!("{key}.bandwidth_mbps"),
                    format!(
                        "{b} is not a bandwidth from {MIN_BANDWIDTH_MBPS} to 1000000 Mbit/s (slower, a link cannot carry the cluster's messages in time)"
                    ),
                ));
            }
        }
        if !(self.loss.is_finite() && (0.0..1.0).contains(&self.loss)) {
            return Err(invalid(
                format!("{key}.loss"),
                format!("{} is not a probability in [0, 1)", self.loss),
            ));
        }
        Ok(())
    }
}

/// Link shaping per link class.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct LinksConfig {
    /// Between clients and stores (voxel traffic).
    #[serde(default)]
    pub client_store: LinkConfig,
    /// Between clients and the scheduler (tiles), and between clients and
    /// the display (pixels).
    #[serde(default)]
    pub client_scheduler: LinkConfig,
    /// Between the display and the scheduler.
    #[serde(default)]
    pub display: LinkConfig,
    /// Each store's egress: one link shared by everything the store sends,
    /// to every client it serves (after each pair's own link).
    #[serde(default)]
    pub store_uplink: LinkConfig,
    /// Each client's ingress: one link shared by everything the client
    /// receives, from every store (after each pair's own link).
    #[serde(default)]
    pub client_downlink: LinkConfig,
    /// Each store's reads from its database.
    #[serde(default)]
    pub store_disk: DiskConfig,
}

/// A store's disk: each blob read occupies it for the access time plus the
/// blob's size over the bandwidth, one read after another. Jitter and loss
/// have no meaning for a disk, so they are unknown keys here.
#[derive(Clone, Copy, Debug, Default, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct DiskConfig {
    /// Access time per read, ms.
    #[serde(default)]
    pub latency_ms: f64,
    /// Read bandwidth, Mbit/s; none: unlimited.
    #[serde(default)]
    pub bandwidth_mbps: Option<f64>,
}

impl DiskConfig {
    /// The access time per read.
    pub fn access_time(&self) -> Duration {
        Duration::from_secs_f64(self.latency_ms / 1000.0)
    }

    /// The read bandwidth in bits per second.
    pub fn bandwidth_bps(&self) -> Option<u64> {
        self.as_link().bandwidth_bps()
    }

    /// The same numbers as a link, to validate them as links are.
    fn as_link(&self) -> LinkConfig {
        LinkConfig {
            latency_ms: self.latency_ms,
            bandwidth_mbps: self.bandwidth_mbps,
            ..LinkConfig::default()
        }
    }
}

/// The cluster certificates.
#[derive(Clone, Debug, Deserialize, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct CertsConfig {
    /// Directory made by `dray certs init`.
    pub dir: PathBuf,
}

fn parse_addr(key: &str, s: &str) -> Result<NodeAddress, ConfigError> {
    NodeAddress::parse(s).map_err(|m| invalid(key, m))
}

impl Config {
    /// Reads, parses and validates a config file; relative paths in it are
    /// made relative to the file's directory.
    pub fn load(path: &Path) -> Result<Config, ConfigError> {
        let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Io {
            path: path.to_owned(),
            source,
        })?;
        let mut cfg = Config::parse(&text).map_err(|e| match e {
            ConfigError::Parse { message, .. } => ConfigError::Parse {
                path: path.to_owned(),
                message,
            },
            other => other,
        })?;
        let base = path.parent().unwrap_or(Path::new("."));
        let rel = |p: &mut PathBuf| {
            if p.is_relative() {
                *p = base.join(&*p);
            }
        };
        rel(&mut cfg.scene.database);
        for s in &mut cfg.stores {
            if let Some(p) = s.database.as_mut() {
                rel(p);
            }
        }
        rel(&mut cfg.certs.dir);
        if let Some(p) = cfg.render.camera_path.as_mut() {
            rel(p);
        }
        if let Some(p) = cfg.display.output.as_mut() {
            rel(p);
        }
        Ok(cfg)
    }

    /// Parses and validates config text (paths stay as written).
    pub fn parse(text: &str) -> Result<Config, ConfigError> {
        let cfg: Config = toml::from_str(text).map_err(|e| ConfigError::Parse {
            path: PathBuf::from("<config>"),
            message: e.to_string(),
        })?;
        cfg.validate()?;
        Ok(cfg)
    }

    /// Checks every value; the error names the first bad key.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let r = &self.render;
        check_image_side("render.width", r.width)?;
        check_image_side("render.height", r.height)?;
        if r.tile_size == 0 || r.tile_size > MAX_TILE_SIZE {
            return Err(invalid(
                "render.tile_size",
                format!("{} is not in 1..={MAX_TILE_SIZE}", r.tile_size),
            ));
        }
        dray_protocol::check_reflection_depth(u32::from(r.reflection_depth))
            .map_err(|m| invalid("render.reflection_depth", m))?;
        let tiles =
            r.width.div_ceil(r.tile_size) as usize * r.height.div_ceil(r.tile_size) as usize;
        if tiles > dray_protocol::MAX_FRAME_TILES {
            return Err(invalid(
                "render.tile_size",
                format!(
                    "{} gives {tiles} tiles per frame, more than {}",
                    r.tile_size,
                    dray_protocol::MAX_FRAME_TILES
                ),
            ));
        }
        check_camera("render.camera", &r.camera)?;
        dray_protocol::check_light_dir(r.light_dir).map_err(|m| invalid("render.light_dir", m))?;
        dray_protocol::check_reflectance(r.reflectance)
            .map_err(|m| invalid("render.reflectance", m))?;
        if r.frames == 0 || r.frames > 1_000_000 {
            return Err(invalid(
                "render.frames",
                format!("{} is not in 1..=1000000", r.frames),
            ));
        }
        if r.loops == 0 || r.loops > 1000 {
            return Err(invalid(
                "render.loops",
                format!("{} is not in 1..=1000", r.loops),
            ));
        }
        dray_protocol::check_samples(r.samples).map_err(|m| invalid("render.samples", m))?;
        if self.display.frames_ahead == 0 || self.display.frames_ahead > 16 {
            return Err(invalid(
                "display.frames_ahead",
                format!("{} is not in 1..=16", self.display.frames_ahead),
            ));
        }
        if self.display.max_samples == 0 || self.display.max_samples > MAX_SAMPLES {
            return Err(invalid(
                "display.max_samples",
                format!("{} is not in 1..={MAX_SAMPLES}", self.display.max_samples),
            ));
        }
        let ahead = u64::from(self.display.frames_ahead);
        let bpp = display_bytes_per_pixel(r.depth_and_ids);
        let in_flight = u64::from(r.width) * u64::from(r.height) * ahead * bpp;
        if in_flight > MAX_FRAMES_IN_FLIGHT_BYTES {
            return Err(invalid(
                "display.frames_ahead",
                format!(
                    "{ahead} frames of {}x{} in flight hold {:.1} GiB of pixels ({bpp} bytes a pixel{}), more than {} GiB: lower display.frames_ahead, or render.width and render.height{}",
                    r.width,
                    r.height,
                    in_flight as f64 / (1u64 << 30) as f64,
                    if r.depth_and_ids { " with render.depth_and_ids" } else { "" },
                    MAX_FRAMES_IN_FLIGHT_BYTES >> 30,
                    if r.depth_and_ids { ", or turn off render.depth_and_ids" } else { "" },
                ),
            ));
        }
        if self.scheduler.tile_deadline_ms == 0 {
            return Err(invalid("scheduler.tile_deadline_ms", "must be at least 1"));
        }
        if self.scheduler.max_block_px > MAX_TILE_SIZE {
            return Err(invalid(
                "scheduler.max_block_px",
                format!(
                    "{} is more than {MAX_TILE_SIZE}, the largest tile a message carries",
                    self.scheduler.max_block_px
                ),
            ));
        }
        let p = &self.prefetch;
        if p.step == 0 || p.step > 256 {
            return Err(invalid(
                "prefetch.step",
                format!("{} is not in 1..=256", p.step),
            ));
        }
        if p.voxels_per_ray == 0 || p.voxels_per_ray > 64 {
            return Err(invalid(
                "prefetch.voxels_per_ray",
                format!("{} is not in 1..=64", p.voxels_per_ray),
            ));
        }

        if self.scene.database.as_os_str().is_empty() {
            return Err(invalid("scene.database", "is empty"));
        }
        if self.certs.dir.as_os_str().is_empty() {
            return Err(invalid("certs.dir", "is empty"));
        }

        let mut addrs: Vec<(Listener, NodeAddress)> = Vec::new();
        let mut check = |l: Listener| -> Result<(), ConfigError> {
            if let Some(text) = self.address_text(l) {
                addrs.push((l, parse_addr(&l.key(), text)?));
            }
            Ok(())
        };
        check(Listener::Scheduler)?;
        check(Listener::Display)?;
        check(Listener::Web)?;
        if self.stores.is_empty() {
            return Err(invalid("stores", "at least one store is needed"));
        }
        if self.stores.len() > MAX_STORES {
            return Err(invalid(
                "stores",
                format!("{} stores, at most {MAX_STORES}", self.stores.len()),
            ));
        }
        for (i, s) in self.stores.iter().enumerate() {
            check(Listener::Store(i))?;
            if s.max_concurrent == 0 {
                return Err(invalid(
                    format!("stores[{i}].max_concurrent"),
                    "must be at least 1",
                ));
            }
            if s.database
                .as_ref()
                .is_some_and(|d| d.as_os_str().is_empty())
            {
                return Err(invalid(format!("stores[{i}].database"), "is empty"));
            }
        }
        self.shards()?;
        for (i, h) in self.launch.hosts.iter().enumerate() {
            if h.parse::<IpAddr>().is_err() && !address::is_host_name(h) {
                return Err(invalid(
                    format!("launch.hosts[{i}]"),
                    format!("{h:?} is neither an IP nor a host name"),
                ));
            }
        }
        // Where the hosts are not known yet (the launcher gives them), two
        // addresses are the same only if their text is.
        let mut hosts_known = Vec::with_capacity(addrs.len());
        for (l, a) in &addrs {
            if a.port() == 0 {
                return Err(invalid(l.key(), "port 0: other nodes could not find it"));
            }
            let host = if self.launch.hosts.is_empty() {
                None
            } else {
                Some(
                    a.host(&self.launch.hosts, self.hosts_source())
                        .map_err(|m| invalid(l.key(), m))?,
                )
            };
            hosts_known.push(host);
        }
        for (i, (la, a)) in addrs.iter().enumerate() {
            let same = |j: usize| match (&hosts_known[i], &hosts_known[j]) {
                (Some(x), Some(y)) => x == y && a.port() == addrs[j].1.port(),
                _ => *a == addrs[j].1,
            };
            if let Some(j) = (0..i).find(|&j| same(j)) {
                let text = self.address_text(*la).unwrap_or_default();
                return Err(invalid(
                    la.key(),
                    format!("{text} is also {}", addrs[j].0.key()),
                ));
            }
        }
        if let Some(ranks) = &self.launch.ranks {
            launch::check_ranks(ranks, &self.node_names())
                .map_err(|m| invalid("launch.ranks", m))?;
        }

        let c = &self.clients;
        if c.count == 0 {
            return Err(invalid("clients.count", "at least one client is needed"));
        }
        // The frame statistics and tile owners name at most this many.
        if c.count as usize > dray_protocol::MAX_STATS_CLIENTS {
            return Err(invalid(
                "clients.count",
                format!(
                    "{} is more than {} clients",
                    c.count,
                    dray_protocol::MAX_STATS_CLIENTS
                ),
            ));
        }
        if c.threads == 0 || c.threads > 1024 {
            return Err(invalid(
                "clients.threads",
                format!("{} is not in 1..=1024", c.threads),
            ));
        }
        if !(c.cache_mb.is_finite() && c.cache_mb > 0.0) {
            return Err(invalid(
                "clients.cache_mb",
                format!("{}: a cache must hold at least one voxel", c.cache_mb),
            ));
        }
        if c.cache_mb > (1u64 << 20) as f64 {
            return Err(invalid(
                "clients.cache_mb",
                format!("{} MB is more than 1 TB", c.cache_mb),
            ));
        }
        if c.max_inflight_fetches == 0 {
            return Err(invalid(
                "clients.max_inflight_fetches",
                "must be at least 1",
            ));
        }
        if c.tiles_ahead > 64 {
            return Err(invalid(
                "clients.tiles_ahead",
                format!("{} is over 64", c.tiles_ahead),
            ));
        }
        if let Some(most) = c.max_tiles_ahead.filter(|&m| m > 64) {
            return Err(invalid(
                "clients.max_tiles_ahead",
                format!("{most} is over 64"),
            ));
        }
        for (key, speed) in [
            ("clients.speed", c.speed),
            ("clients.decode_speed", c.decode_speed),
        ] {
            if !(speed.is_finite() && (1e-3..=1e3).contains(&speed)) {
                return Err(invalid(key, format!("{speed} is not in 0.001..=1000")));
            }
        }
        if let Some(bind) = c.bind.as_ref().filter(|b| b.parse::<IpAddr>().is_err()) {
            return Err(invalid(
                "clients.bind",
                format!("{bind:?} is not an IP address"),
            ));
        }
        self.links.client_store.validate("links.client_store")?;
        self.links
            .client_scheduler
            .validate("links.client_scheduler")?;
        self.links.display.validate("links.display")?;
        self.links.store_uplink.validate("links.store_uplink")?;
        self.links
            .client_downlink
            .validate("links.client_downlink")?;
        self.links
            .store_disk
            .as_link()
            .validate("links.store_disk")?;
        Ok(())
    }

    /// The address `l` listens on, as written (none: no web viewer).
    fn address_text(&self, l: Listener) -> Option<&str> {
        match l {
            Listener::Scheduler => Some(&self.scheduler.address),
            Listener::Display => Some(&self.display.address),
            Listener::Web => self.display.web.as_deref(),
            Listener::Store(i) => self.stores.get(i).map(|s| s.address.as_str()),
        }
    }

    /// What `launch.hosts` came from, for errors: the launcher's variable
    /// or the key.
    fn hosts_source(&self) -> &'static str {
        self.launch.hosts_from.unwrap_or("launch.hosts")
    }

    /// Where `l` listens as host and port, host templates filled but a
    /// name not looked up (a dialer looks it up before each dial).
    pub fn host_port(&self, l: Listener) -> Result<(String, u16), ConfigError> {
        let key = l.key();
        let text = self
            .address_text(l)
            .ok_or_else(|| invalid(key.clone(), "is not set"))?;
        let a = parse_addr(&key, text)?;
        let host = a
            .host(&self.launch.hosts, self.hosts_source())
            .map_err(|m| invalid(key, m))?;
        Ok((host, a.port()))
    }

    /// The socket address `l` listens on: host templates filled from
    /// `launch.hosts`, a host name looked up.
    pub fn resolve(&self, l: Listener) -> Result<SocketAddr, ConfigError> {
        let key = l.key();
        let text = self
            .address_text(l)
            .ok_or_else(|| invalid(key.clone(), "is not set"))?;
        parse_addr(&key, text)?
            .resolve(&self.launch.hosts, self.hosts_source())
            .map_err(|m| invalid(key, m))
    }

    /// The scheduler's address.
    pub fn scheduler_addr(&self) -> Result<SocketAddr, ConfigError> {
        self.resolve(Listener::Scheduler)
    }

    /// The display's address.
    pub fn display_addr(&self) -> Result<SocketAddr, ConfigError> {
        self.resolve(Listener::Display)
    }

    /// The web viewer's address, if there is one.
    pub fn web_addr(&self) -> Result<Option<SocketAddr>, ConfigError> {
        self.display
            .web
            .as_ref()
            .map(|_| self.resolve(Listener::Web))
            .transpose()
    }

    /// Each store's address, in order.
    pub fn store_addrs(&self) -> Result<Vec<SocketAddr>, ConfigError> {
        (0..self.stores.len())
            .map(|i| self.resolve(Listener::Store(i)))
            .collect()
    }

    /// The IP clients bind: `clients.bind`, or every interface of the
    /// family of `scheduler` (the scheduler's address, looked up).
    pub fn client_bind(&self, scheduler: SocketAddr) -> Result<IpAddr, ConfigError> {
        match &self.clients.bind {
            Some(b) => b
                .parse()
                .map_err(|_| invalid("clients.bind", format!("{b:?} is not an IP address"))),
            None if scheduler.is_ipv6() => Ok(Ipv6Addr::UNSPECIFIED.into()),
            None => Ok(Ipv4Addr::UNSPECIFIED.into()),
        }
    }

    /// The database store `i` reads: its `database`, or `scene.database`.
    pub fn store_database(&self, i: usize) -> &Path {
        self.stores
            .get(i)
            .and_then(|s| s.database.as_deref())
            .unwrap_or(&self.scene.database)
    }

    /// The node each launcher rank runs: `launch.ranks`, or every node in
    /// [`Config::node_names`] order.
    pub fn rank_nodes(&self) -> Vec<String> {
        self.launch
            .ranks
            .clone()
            .unwrap_or_else(|| self.node_names())
    }

    /// Which node a launcher's process is (role and index), from its rank;
    /// fills `launch.hosts` from the launcher's host list when the config
    /// lists none. `env` reads the environment. The error says what is
    /// missing or inconsistent.
    pub fn node_from_launcher(
        &mut self,
        env: &dyn Fn(&str) -> Option<String>,
    ) -> Result<LaunchedNode, ConfigError> {
        let bad = |m: String| invalid("launch", m);
        let l = launch::detect(env)
            .map_err(bad)?
            .ok_or_else(|| bad(launch::NO_LAUNCHER.into()))?;
        let ranks = self.rank_nodes();
        if let Some((var, n)) = l.size.filter(|&(_, n)| n != ranks.len()) {
            return Err(bad(format!(
                "{} started {n} processes ({var}), but the config has {} ranks \
                 (launch.ranks, or every node): start exactly {}",
                l.launcher,
                ranks.len(),
                ranks.len()
            )));
        }
        let node = ranks.get(l.rank).ok_or_else(|| {
            bad(format!(
                "rank {} ({}) has no node: the config has {} ranks (launch.ranks, or every node)",
                l.rank,
                l.rank_from,
                ranks.len()
            ))
        })?;
        let (role, index) =
            node_role(node).ok_or_else(|| bad(format!("{node:?} is not a node name")))?;
        if self.launch.hosts.is_empty() {
            if let Some((var, hosts)) = launch::hosts(env).map_err(bad)? {
                self.launch.hosts = hosts;
                self.launch.hosts_from = Some(var);
                // The addresses' templates are checked against the list now.
                self.validate()?;
            }
        }
        Ok(LaunchedNode {
            role,
            index,
            launch: l,
        })
    }

    /// The client cache budget in bytes.
    pub fn cache_bytes(&self) -> u64 {
        (self.clients.cache_mb * 1e6) as u64
    }

    /// Each store's shard `(index, count)`, in order: as configured, or
    /// `i/n` for store i of n. Every voxel id must be served by some store.
    pub fn shards(&self) -> Result<Vec<(u32, u32)>, ConfigError> {
        let n = self.stores.len() as u32;
        let mut out = Vec::with_capacity(self.stores.len());
        for (i, s) in self.stores.iter().enumerate() {
            let key = format!("stores[{i}].shard");
            let shard = match &s.shard {
                None => (i as u32, n),
                Some(text) => {
                    let bad = || {
                        invalid(
                            key.clone(),
                            format!("{text:?} is not of the form I/N with I < N <= 1024"),
                        )
                    };
                    let (a, b) = text.split_once('/').ok_or_else(bad)?;
                    let (a, b): (u32, u32) = (
                        a.trim().parse().map_err(|_| bad())?,
                        b.trim().parse().map_err(|_| bad())?,
                    );
                    if b == 0 || a >= b || b > 1024 {
                        return Err(bad());
                    }
                    (a, b)
                }
            };
            out.push(shard);
        }
        check_shards(&out).map_err(|problem| invalid("stores", problem))?;
        Ok(out)
    }

    /// Every node's name: `scheduler`, `display`, `store-I`, `client-I`.
    pub fn node_names(&self) -> Vec<String> {
        let mut v = vec!["scheduler".to_string(), "display".to_string()];
        v.extend((0..self.stores.len()).map(|i| format!("store-{i}")));
        v.extend((0..self.clients.count).map(|i| format!("client-{i}")));
        v
    }
}

/// What listens on an address of the config.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Listener {
    /// `scheduler.address`.
    Scheduler,
    /// `display.address`.
    Display,
    /// `display.web`, the web viewer.
    Web,
    /// `stores[I].address`.
    Store(usize),
}

impl Listener {
    /// The dotted key of its address.
    pub fn key(self) -> String {
        match self {
            Listener::Scheduler => "scheduler.address".into(),
            Listener::Display => "display.address".into(),
            Listener::Web => "display.web".into(),
            Listener::Store(i) => format!("stores[{i}].address"),
        }
    }
}

/// A node a launcher started ([`Config::node_from_launcher`]).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct LaunchedNode {
    /// Its role.
    pub role: Role,
    /// Which store or client (0 for the scheduler and the display).
    pub index: usize,
    /// What the launcher said.
    pub launch: launch::Launch,
}

/// The role and index of a node name (`scheduler`, `display`, `store-I`,
/// `client-I`).
pub fn node_role(name: &str) -> Option<(Role, usize)> {
    match name {
        "scheduler" => return Some((Role::Scheduler, 0)),
        "display" => return Some((Role::Display, 0)),
        _ => {}
    }
    let (role, i) = name.rsplit_once('-')?;
    let role = match role {
        "store" => Role::Store,
        "client" => Role::Client,
        _ => return None,
    };
    // One spelling per node: no sign, no leading zeros.
    if i.is_empty() || (i.len() > 1 && i.starts_with('0')) || !i.bytes().all(|b| b.is_ascii_digit())
    {
        return None;
    }
    Some((role, i.parse().ok()?))
}

/// The dotted keys whose values are paths; [`Config::load`] takes each
/// relative one relative to the config file's directory. A program that
/// builds a config as a TOML table (the experiment runner) resolves these
/// keys itself, so that the table means what the file meant.
pub const PATH_KEYS: [&str; 4] = [
    "scene.database",
    "render.camera_path",
    "display.output",
    "certs.dir",
];

/// Whether a dotted key's value is a path: one of [`PATH_KEYS`] or a
/// store's `stores[I].database`.
pub fn is_path_key(key: &str) -> bool {
    PATH_KEYS.contains(&key)
        || key
            .strip_prefix("stores[")
            .and_then(|k| k.strip_suffix("].database"))
            .is_some_and(|i| i.parse::<usize>().is_ok())
}

/// Every path key of a config with `stores` stores.
pub fn path_keys(stores: usize) -> Vec<String> {
    let mut keys: Vec<String> = PATH_KEYS.iter().map(|k| k.to_string()).collect();
    keys.extend((0..stores).map(|i| format!("stores[{i}].database")));
    keys
}
