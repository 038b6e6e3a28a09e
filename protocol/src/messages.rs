//! The actor messages and their limits.

use crate::{
    Blob, BoundedVec, Name, PackedF32, PackedU32, ProtocolError, Role, TilePixels, VoxelId,
    BULK_FRAME_MAX, ENVELOPE_OVERHEAD, MAX_PREFETCH_IDS, MAX_STATS_CLIENTS, MAX_TEXT_LEN,
    MAX_TILE_SIDE,
};
use serde::{Deserialize, Serialize};

/// A rectangle of pixels of a frame; `x, y` is its top left corner, y down.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct TileRect {
    /// Left column.
    pub x: u32,
    /// Top row.
    pub y: u32,
    /// Width in pixels.
    pub w: u32,
    /// Height in pixels.
    pub h: u32,
}

impl TileRect {
    /// Number of pixels.
    pub fn area(&self) -> usize {
        self.w as usize * self.h as usize
    }
}

/// A pinhole camera (docs/design.md, "Conventions"): vertical field of view in degrees.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Camera {
    /// Eye position.
    pub eye: [f32; 3],
    /// Point looked at.
    pub look: [f32; 3],
    /// Up hint.
    pub up: [f32; 3],
    /// Vertical field of view, degrees, in (0, 180).
    pub fov_y_deg: f32,
}

/// Which surfaces are mirrors (models carry no materials).
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Reflective {
    /// Every surface.
    All,
    /// Triangles whose ORIGINAL id is in `start..end`.
    Ids {
        /// First id.
        start: u32,
        /// One past the last id.
        end: u32,
    },
    /// Surfaces of this vertex color (within a few units per channel).
    Color([u8; 3]),
}

impl std::str::FromStr for Reflective {
    type Err = String;

    /// `all`, `ids:A-B` (B exclusive, A < B) or `color:R,G,B`.
    fn from_str(s: &str) -> Result<Self, String> {
        let bad = || format!("{s:?} is not a reflection rule (all, ids:A-B or color:R,G,B)");
        if s == "all" {
            return Ok(Reflective::All);
        }
        if let Some(r) = s.strip_prefix("ids:") {
            let (a, b) = r.split_once('-').ok_or_else(bad)?;
            let (start, end) = (
                a.trim().parse().map_err(|_| bad())?,
                b.trim().parse().map_err(|_| bad())?,
            );
            return if start < end {
                Ok(Reflective::Ids { start, end })
            } else {
                Err(bad())
            };
        }
        if let Some(c) = s.strip_prefix("color:") {
            let v: Vec<u8> = c
                .split(',')
                .map(|x| x.trim().parse())
                .collect::<Result<_, _>>()
                .map_err(|_| bad())?;
            if let [r, g, b] = v[..] {
                return Ok(Reflective::Color([r, g, b]));
            }
        }
        Err(bad())
    }
}

/// How a tile is shaded: exactly what `dray render` takes, so that a frame
/// rendered by the cluster equals the one rendered in one process.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    /// Shade (vertex normals and colors, one distant light); otherwise the
    /// pixels are a grey depth image.
    pub shade: bool,
    /// Trace shadow rays to the light.
    pub shadows: bool,
    /// Reflection recursion depth (0: none).
    pub reflection_depth: u8,
    /// Direction towards the distant light (need not be normalized).
    pub light_dir: [f32; 3],
    /// Which surfaces reflect.
    pub reflective: Reflective,
    /// Share of the light a reflective surface mirrors, in [0, 1].
    pub reflectance: f32,
    /// Color each voxel differently (the paper's Figure 5).
    pub voxel_colors: bool,
    /// Also return per-pixel depth.
    pub want_depth: bool,
    /// Also return per-pixel primitive ids.
    pub want_prim_ids: bool,
}

/// A client asks the scheduler for up to `slots` more tiles.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct RequestWork {
    /// How many more tiles the client can take now.
    pub slots: u16,
    /// Whether the client's cache holds every voxel of the model (a
    /// preloaded client whose budget fits it): it renders any tile
    /// without a miss, so the scheduler may send it blocks of tiles that
    /// nothing says are warm.
    pub holds_model: bool,
}

/// The scheduler gives a client one tile of a frame to render.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct AssignTile {
    /// Frame number.
    pub frame: u64,
    /// The tile.
    pub tile: TileRect,
    /// The frame's camera.
    pub camera: Camera,
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Shading settings.
    pub settings: RenderSettings,
    /// Which sample of the camera the frame is: its rays pass through
    /// each pixel at the sample's offset from the centre (0: the centre;
    /// `dray_trace::camera::sample_offset`).
    pub sample: u32,
}

/// Bytes links carried, by link class (the config's `[links.*]`), both
/// directions; counted as the transports encode and decode messages.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct LinkBytes {
    /// Between clients and stores.
    pub client_store: u64,
    /// Between clients and the scheduler or the display.
    pub client_scheduler: u64,
    /// Between the display and the scheduler.
    pub display: u64,
    /// From stores into clients: what crossed the stores' uplinks.
    pub store_uplink: u64,
    /// Into clients from any node: what crossed the clients' downlinks.
    pub client_downlink: u64,
}

impl LinkBytes {
    /// Both counts added, saturating (a peer may report anything).
    pub fn saturating_add(self, o: LinkBytes) -> LinkBytes {
        LinkBytes {
            client_store: self.client_store.saturating_add(o.client_store),
            client_scheduler: self.client_scheduler.saturating_add(o.client_scheduler),
            display: self.display.saturating_add(o.display),
            store_uplink: self.store_uplink.saturating_add(o.store_uplink),
            client_downlink: self.client_downlink.saturating_add(o.client_downlink),
        }
    }
}

/// What rendering one tile cost.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct TileStats {
    /// Rays traced (primary, shadow, reflection).
    pub rays: u64,
    /// Wall time from assignment to completion, microseconds.
    pub time_us: u64,
    /// Distinct voxels the tile's rays entered.
    pub voxels_touched: u32,
    /// Voxel cache misses: distinct voxels the tile had to wait for (a
    /// subset of those it touched).
    pub misses: u32,
    /// Bytes of voxels fetched for this tile.
    pub bytes_fetched: u64,
    /// The same voxels' bytes after decompression.
    pub bytes_raw: u64,
    /// Render thread stall charged to this tile, microseconds: the time
    /// its thread waited while every tile it had in progress waited for
    /// voxels, since the thread's previous tile finished (so the sum over
    /// tiles is the threads' stall time).
    pub stall_us: u64,
    /// What the client's links carried since its previous finished tile.
    pub link: LinkBytes,
}

/// A client returns a rendered tile.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileDone {
    /// Frame number.
    pub frame: u64,
    /// The tile.
    pub tile: TileRect,
    /// The colors, rows top to bottom: RGB when opaque, perhaps compressed.
    pub pixels: TilePixels,
    /// Per-pixel hit distance (+inf on a miss), when asked for.
    pub depth: Option<PackedF32>,
    /// Per-pixel original triangle index (0xFFFFFFFF on a miss), when asked for.
    pub prim_ids: Option<PackedU32>,
    /// Costs.
    pub stats: TileStats,
    /// World positions of the tile's primary hits at a few pixels spread
    /// over it (misses left out), which the display passes on to the
    /// scheduler in the tile's [`TileReport`].
    pub hits: BoundedVec<[f32; 3], MAX_REPORT_HITS>,
}

/// A client asks a store for a voxel.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FetchVoxel {
    /// The voxel.
    pub id: VoxelId,
}

/// A store answers with a voxel's compressed, checksummed blob.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoxelLoaded {
    /// The voxel.
    pub id: VoxelId,
    /// The blob exactly as stored in the database.
    pub data: Blob,
}

/// A store cannot serve a voxel.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoxelError {
    /// The voxel.
    pub id: VoxelId,
    /// Why (at most [`MAX_TEXT_LEN`] bytes).
    pub message: String,
}

/// A client gives up on a voxel: every store serving it failed to send it
/// intact (a checksum mismatch, a read error) as often as the client tries.
/// The display ends the run naming the voxel and the store, or, when the
/// client renders it as empty (`skipped`), counts it.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct VoxelLost {
    /// The voxel.
    pub id: VoxelId,
    /// The store that failed it last.
    pub store: Name,
    /// Why (at most [`MAX_TEXT_LEN`] bytes).
    pub reason: String,
    /// Whether the client renders on with the voxel treated as empty.
    pub skipped: bool,
}

/// A frame's size and shading.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameFormat {
    /// Image width in pixels, 1 to [`crate::MAX_IMAGE_SIDE`].
    pub width: u32,
    /// Image height in pixels, 1 to [`crate::MAX_IMAGE_SIDE`].
    pub height: u32,
    /// Shading.
    pub settings: RenderSettings,
}

/// The display asks for a frame: it moves the camera, or renders another
/// sample of the same camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraUpdate {
    /// Increases with each update; older ones are ignored. The frame
    /// number.
    pub seq: u64,
    /// The new camera.
    pub camera: Camera,
    /// Which sample of this camera the frame is (0: every ray through its
    /// pixel's centre; see [`AssignTile::sample`]).
    pub sample: u32,
    /// From this update on, frames have this size and shading; `None`
    /// keeps the current ones (at first, the frame assigner's).
    pub format: Option<FrameFormat>,
}

/// One client's share of a frame.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ClientFrameStats {
    /// The client node.
    pub node: Name,
    /// Tiles it rendered.
    pub tiles: u32,
    /// Rays it traced.
    pub rays: u64,
    /// Its cache misses.
    pub misses: u64,
    /// Voxel bytes it fetched.
    pub bytes_fetched: u64,
    /// Its render threads' stall time, microseconds.
    pub stall_us: u64,
}

/// Statistics of a finished frame.
#[derive(Clone, Debug, PartialEq, Default, Serialize, Deserialize)]
pub struct FrameStats {
    /// Tiles in the frame.
    pub tiles: u32,
    /// Tiles that had to be reassigned (a client was lost or too slow).
    pub reassigned: u32,
    /// Rays traced.
    pub rays: u64,
    /// Wall time from the first assignment to the last tile, microseconds.
    pub time_us: u64,
    /// Voxel cache misses.
    pub misses: u64,
    /// Voxel bytes fetched.
    pub bytes_fetched: u64,
    /// The same voxels' bytes after decompression.
    pub bytes_raw: u64,
    /// Distinct voxels entered, summed over tiles (for the cache hit rate).
    pub voxels_touched: u64,
    /// Render threads' stall time, summed over clients, microseconds.
    pub stall_us: u64,
    /// What the links carried (clients' links, summed from their tiles;
    /// the display's own link added by the display).
    pub link: LinkBytes,
    /// Per client.
    pub clients: BoundedVec<ClientFrameStats, MAX_STATS_CLIENTS>,
}

/// The scheduler reports that every tile of a frame is in.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameDone {
    /// Frame number.
    pub frame: u64,
    /// Its statistics.
    pub stats: FrameStats,
}

/// Voxels a client will probably need soon.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct PrefetchHint {
    /// The frame the hint is for.
    pub frame: u64,
    /// The voxels, most urgent first (at most [`MAX_PREFETCH_IDS`]).
    pub voxels: PackedU32,
}

/// Liveness probe; answered with [`Message::Pong`] carrying the same value.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Ping {
    /// Echoed back.
    pub seq: u64,
}

/// Asks the receiving actor to stop.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Shutdown {
    /// Why (at most [`MAX_TEXT_LEN`] bytes).
    pub reason: String,
}

/// A client (or the scheduler's prefetcher) asks a store for the
/// database's manifest (the high-level BSP and the voxel table), so that
/// neither needs a copy of the database.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FetchManifest {}

/// A store answers with the manifest file's bytes exactly as stored.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct ManifestData {
    /// The manifest file.
    pub data: Blob,
}

/// The display tells the scheduler that a tile's pixels arrived (in a
/// [`TileDone`]): a tile counts as done only once the display has it, so a
/// client that dies with pixels still on their way loses no tile. (A
/// client may also report its own tiles.)
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileReport {
    /// The client that rendered the tile.
    pub client: Name,
    /// Frame number.
    pub frame: u64,
    /// The tile.
    pub tile: TileRect,
    /// Costs.
    pub stats: TileStats,
    /// World positions of the tile's primary hits at a few pixels spread
    /// over it (misses left out): where its content lies, so that the
    /// scheduler can give the tiles that show it in the next frame to the
    /// client whose cache holds it (reprojection affinity).
    pub hits: BoundedVec<[f32; 3], MAX_REPORT_HITS>,
}

/// Most hit positions the scheduler keeps, and a [`TileOwners`] carries,
/// per tile of the frame's grid (a 4 × 4 grid of them).
pub const MAX_TILE_HITS: usize = 16;
/// Most hit positions one [`TileDone`] or [`TileReport`] carries: a
/// block of 4 × 4 tiles sampled as densely as one tile (16 × 16).
pub const MAX_REPORT_HITS: usize = 256;

/// The frame assigner releases a frame to the scheduler.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct FrameStart {
    /// Frame number (increasing).
    pub frame: u64,
    /// Its camera.
    pub camera: Camera,
    /// Image width in pixels.
    pub width: u32,
    /// Image height in pixels.
    pub height: u32,
    /// Shading.
    pub settings: RenderSettings,
    /// Which sample of the camera the frame is ([`AssignTile::sample`]).
    pub sample: u32,
}

/// The scheduler has handed out every tile of a frame at least once.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct FrameAssigned {
    /// Frame number.
    pub frame: u64,
}

/// Which client rendered each tile of a frame, and where the tile's content
/// lies (for the prefetcher, which sends each client hints for the tiles it
/// will probably get next: those its content moves to, as the scheduler
/// assigns them).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileOwners {
    /// Frame number.
    pub frame: u64,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Tile side.
    pub tile_size: u32,
    /// Per tile, row-major, an index into `clients` (u32::MAX: none).
    pub owners: PackedU32,
    /// The client nodes.
    pub clients: BoundedVec<Name, MAX_STATS_CLIENTS>,
    /// Per tile, row-major, how many of its hit positions `hits` holds
    /// (at most [`MAX_TILE_HITS`]).
    pub hit_counts: Blob,
    /// The tiles' hit positions (x, y, z), tile after tile, as their
    /// [`TileReport`]s gave them.
    pub hits: PackedF32,
    /// Times the frame's packets met a voxel their client did not hold
    /// (the sum of the tiles' `misses`): the prefetcher plans less while
    /// frames have none.
    pub misses: u64,
    /// The clients whose caches hold every voxel of the model, as their
    /// last [`RequestWork`] said: hints to them would fetch nothing, and
    /// the prefetcher plans none for them.
    pub holds_model: BoundedVec<Name, MAX_STATS_CLIENTS>,
}

/// Declares the message set once: each line is a doc, a `Message`
/// variant with its payload type, and the kind's short name. From it follow
/// [`Message`], [`MessageKind`] (plus `Handshake`), [`MessageKind::ALL`],
/// [`Message::kind`] and [`MessageKind::name`]. The line order is the wire
/// tag: append only.
macro_rules! message_set {
    ($($(#[doc = $doc:literal])+ $variant:ident($payload:ty) = $name:literal,)+) => {
        /// Every actor message. The variant order is the wire tag: append
        /// only. Who may send which kind to whom: [`MessageKind::may_send`].
        #[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
        pub enum Message {
            $($(#[doc = $doc])+ $variant($payload),)+
        }

        /// The kind of a message, without its contents.
        #[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
        pub enum MessageKind {
            $(#[doc = concat!("[`Message::", stringify!($variant), "`].")] $variant,)+
            /// Not an actor message: the connection handshake.
            Handshake,
        }

        impl MessageKind {
            /// Every actor message kind, in wire tag order.
            pub const ALL: [MessageKind; [$(stringify!($variant)),+].len()] =
                [$(MessageKind::$variant,)+];

            /// A short lowercase name, for logs and spans.
            pub fn name(self) -> &'static str {
                match self {
                    $(MessageKind::$variant => $name,)+
                    MessageKind::Handshake => "handshake",
                }
            }
        }

        impl Message {
            /// This message's kind.
            pub fn kind(&self) -> MessageKind {
                match self {
                    $(Message::$variant(_) => MessageKind::$variant,)+
                }
            }
        }
    };
}

message_set! {
    /// Client → scheduler.
    RequestWork(RequestWork) = "request_work",
    /// Scheduler → client.
    AssignTile(AssignTile) = "assign_tile",
    /// Client → display (the pixels; the display reports the tile on).
    TileDone(TileDone) = "tile_done",
    /// Client → store.
    FetchVoxel(FetchVoxel) = "fetch_voxel",
    /// Store → client.
    VoxelLoaded(VoxelLoaded) = "voxel_loaded",
    /// Store → client.
    VoxelError(VoxelError) = "voxel_error",
    /// Display → frame assigner, which passes a copy to the prefetcher.
    CameraUpdate(CameraUpdate) = "camera_update",
    /// Scheduler → display.
    FrameDone(FrameDone) = "frame_done",
    /// Prefetcher → client.
    PrefetchHint(PrefetchHint) = "prefetch_hint",
    /// Any → any.
    Ping(Ping) = "ping",
    /// Answer to a ping.
    Pong(Ping) = "pong",
    /// Display's node → scheduler, stores, clients.
    Shutdown(Shutdown) = "shutdown",
    /// Client or prefetcher → store.
    FetchManifest(FetchManifest) = "fetch_manifest",
    /// Store → client or prefetcher.
    ManifestData(ManifestData) = "manifest_data",
    /// Display → scheduler, once the tile's pixels are on the display (the
    /// scheduler also takes a client's report on its own tile).
    TileReport(TileReport) = "tile_report",
    /// Frame assigner → scheduler.
    FrameStart(FrameStart) = "frame_start",
    /// Scheduler → frame assigner.
    FrameAssigned(FrameAssigned) = "frame_assigned",
    /// Scheduler → prefetcher.
    TileOwners(TileOwners) = "tile_owners",
    /// Client → display.
    VoxelLost(VoxelLost) = "voxel_lost",
}

impl MessageKind {
    /// The kind whose wire tag (first body byte) is `tag`.
    pub fn from_tag(tag: u8) -> Option<MessageKind> {
        MessageKind::ALL.get(tag as usize).copied()
    }

    /// Largest encoded envelope of this kind, in bytes.
    pub fn max_wire_size(self) -> usize {
        let tile_px = (MAX_TILE_SIDE * MAX_TILE_SIDE) as usize;
        let text = MAX_TEXT_LEN + 4;
        match self {
            MessageKind::RequestWork
            | MessageKind::AssignTile
            | MessageKind::FetchVoxel
            | MessageKind::CameraUpdate
            | MessageKind::Ping
            | MessageKind::Pong
            | MessageKind::FetchManifest
            | MessageKind::FrameStart
            | MessageKind::FrameAssigned => ENVELOPE_OVERHEAD,
            MessageKind::TileReport => {
                ENVELOPE_OVERHEAD + crate::MAX_NAME_LEN + 2 + MAX_REPORT_HITS * 12
                    // the stats' bytes_raw and link bytes: u64 varints
                    + 6 * 10
            }
            MessageKind::ManifestData => BULK_FRAME_MAX,
            MessageKind::TileOwners => {
                ENVELOPE_OVERHEAD
                    + crate::MAX_FRAME_TILES * 4
                    + 4
                    + MAX_STATS_CLIENTS * (crate::MAX_NAME_LEN + 1)
                    + crate::MAX_FRAME_TILES * (1 + MAX_TILE_HITS * 12)
                    + 2 * 5
                    // misses: a u64 varint
                    + 10
                    // holds_model: names, as `clients`
                    + 4
                    + MAX_STATS_CLIENTS * (crate::MAX_NAME_LEN + 1)
            }
            MessageKind::VoxelError | MessageKind::Shutdown => ENVELOPE_OVERHEAD + text,
            MessageKind::VoxelLost => ENVELOPE_OVERHEAD + crate::MAX_NAME_LEN + 2 + text + 1,
            MessageKind::TileDone => {
                ENVELOPE_OVERHEAD + 3 * (tile_px * 4 + 4) + MAX_REPORT_HITS * 12 + 2
                    // the stats' bytes_raw and link bytes: u64 varints
                    + 6 * 10
            }
            MessageKind::VoxelLoaded => BULK_FRAME_MAX,
            MessageKind::FrameDone => {
                ENVELOPE_OVERHEAD + MAX_STATS_CLIENTS * (crate::MAX_NAME_LEN + 1 + 5 * 10) + 2 * 10
                    // the stats' bytes_raw and link bytes: u64 varints
                    + 6 * 10
            }
            MessageKind::PrefetchHint => ENVELOPE_OVERHEAD + MAX_PREFETCH_IDS * 4 + 4,
            MessageKind::Handshake => crate::HANDSHAKE_FRAME_MAX,
        }
    }

    /// Whether a message of this kind `encoded` bytes long travels on a
    /// stream of its own: large bulk messages do (see
    /// [`crate::SMALL_BULK_MAX`], tiles [`crate::SMALL_TILE_MAX`]);
    /// everything else goes in order on the control stream.
    pub fn own_stream(self, encoded: usize) -> bool {
        let small = match self {
            MessageKind::TileDone => crate::SMALL_TILE_MAX,
            _ => crate::SMALL_BULK_MAX,
        };
        self.is_bulk() && encoded > small
    }

    /// Whether this kind may be large (a voxel, a tile's pixels), so that
    /// it goes on a stream of its own when it is (see [`Self::own_stream`])
    /// and never delays the small control messages behind it.
    pub fn is_bulk(self) -> bool {
        matches!(
            self,
            MessageKind::TileDone
                | MessageKind::VoxelLoaded
                | MessageKind::ManifestData
                | MessageKind::TileOwners
        )
    }

    /// The sender rule: whether a node of role `from` may send a message
    /// of this kind to a node of role `to`. This is the one place the rule
    /// lives (docs/design.md's message table is checked against it); the
    /// receiving node applies it to every message from another node, with
    /// the sender's role taken from its authenticated name
    /// ([`Role::of_node`]), and drops what it forbids. Tools (tests,
    /// benchmarks) may ping anyone and send each other anything; no
    /// cluster node is a tool.
    pub fn may_send(self, from: Role, to: Role) -> bool {
        use Role::{Client, Display, Scheduler, Store, Tool};
        if from == Tool && to == Tool {
            return self != MessageKind::Handshake;
        }
        match self {
            MessageKind::RequestWork => from == Client && to == Scheduler,
            MessageKind::AssignTile | MessageKind::PrefetchHint => {
                from == Scheduler && to == Client
            }
            MessageKind::TileDone | MessageKind::VoxelLost => from == Client && to == Display,
            MessageKind::FetchVoxel => from == Client && to == Store,
            MessageKind::VoxelLoaded | MessageKind::VoxelError => from == Store && to == Client,
            // The display's camera to the assigner; the assigner's copy to
            // the prefetcher, on the same node.
            MessageKind::CameraUpdate => matches!(from, Display | Scheduler) && to == Scheduler,
            MessageKind::FrameDone => from == Scheduler && to == Display,
            MessageKind::Ping | MessageKind::Pong => true,
            // Only the display's node ends a run.
            MessageKind::Shutdown => from == Display && matches!(to, Scheduler | Store | Client),
            // Clients and the scheduler's prefetcher read the manifest.
            MessageKind::FetchManifest => matches!(from, Client | Scheduler) && to == Store,
            MessageKind::ManifestData => from == Store && matches!(to, Client | Scheduler),
            // The display reports tiles whose pixels it has; a client may
            // report its own (the scheduler checks that it is its own).
            MessageKind::TileReport => matches!(from, Display | Client) && to == Scheduler,
            // Between the scheduler node's own actors.
            MessageKind::FrameStart | MessageKind::FrameAssigned | MessageKind::TileOwners => {
                from == Scheduler && to == Scheduler
            }
            MessageKind::Handshake => false,
        }
    }

    /// The sender rule in words, over the cluster's roles, as
    /// docs/design.md's message table shows it: `any → any`, or per
    /// sender `from → to, to`, senders separated by `; `.
    pub fn rule_text(self) -> String {
        let pairs = |from: Role| -> Vec<Role> {
            Role::CLUSTER
                .into_iter()
                .filter(|&to| self.may_send(from, to))
                .collect()
        };
        if Role::CLUSTER
            .iter()
            .all(|&f| pairs(f).len() == Role::CLUSTER.len())
        {
            return "any → any".into();
        }
        let parts: Vec<String> = Role::CLUSTER
            .into_iter()
            .filter_map(|from| {
                let to = pairs(from);
                (!to.is_empty()).then(|| {
                    let to: Vec<String> = to.iter().map(Role::to_string).collect();
                    format!("{from} → {}", to.join(", "))
                })
            })
            .collect();
        if parts.is_empty() {
            "nobody".into()
        } else {
            parts.join("; ")
        }
    }
}

impl Role {
    /// Whether nodes of roles `self` and `other` are connected: one may
    /// send the other something beyond a ping (by the sender rule,
    /// [`MessageKind::may_send`]), or either is a tool. A cluster's
    /// clients never talk to each other, nor its stores, so they are not
    /// connected: a network of N clients has O(N) links, not O(N²).
    pub fn connects_to(self, other: Role) -> bool {
        self == Role::Tool
            || other == Role::Tool
            || MessageKind::ALL.iter().any(|k| {
                !matches!(k, MessageKind::Ping | MessageKind::Pong)
                    && (k.may_send(self, other) || k.may_send(other, self))
            })
    }
}

fn check_camera(c: &Camera) -> Result<(), String> {
    crate::check_camera(c).map_err(|e| format!("camera {e}"))
}

fn check_tile(t: &TileRect, width: u32, height: u32) -> Result<(), String> {
    if t.w == 0 || t.h == 0 || t.w > MAX_TILE_SIDE || t.h > MAX_TILE_SIDE {
        return Err(format!(
            "tile of {}x{} is empty or larger than {MAX_TILE_SIDE}",
            t.w, t.h
        ));
    }
    if u64::from(t.x) + u64::from(t.w) > u64::from(width)
        || u64::from(t.y) + u64::from(t.h) > u64::from(height)
    {
        return Err(format!(
            "tile {}x{} at ({}, {}) is outside the {}x{} image",
            t.w, t.h, t.x, t.y, width, height
        ));
    }
    Ok(())
}

fn check_frame(width: u32, height: u32, s: &RenderSettings) -> Result<(), String> {
    crate::check_image_side(width).map_err(|e| format!("image width {e}"))?;
    crate::check_image_side(height).map_err(|e| format!("image height {e}"))?;
    crate::check_reflection_depth(u32::from(s.reflection_depth))
        .map_err(|e| format!("reflection depth {e}"))?;
    crate::check_light_dir(s.light_dir).map_err(|e| format!("light direction {e}"))?;
    crate::check_reflectance(s.reflectance).map_err(|e| format!("reflectance {e}"))?;
    if let Reflective::Ids { start, end } = s.reflective {
        if start >= end {
            return Err(format!("reflective id range {start}..{end} is empty"));
        }
    }
    Ok(())
}

fn check_owners(o: &TileOwners) -> Result<(), String> {
    if o.tile_size == 0 || o.tile_size > MAX_TILE_SIDE {
        return Err(format!(
            "tile size {} is not in 1..={MAX_TILE_SIDE}",
            o.tile_size
        ));
    }
    crate::check_image_side(o.width).map_err(|e| format!("image width {e}"))?;
    crate::check_image_side(o.height).map_err(|e| format!("image height {e}"))?;
    let tiles = o.width.div_ceil(o.tile_size) as usize * o.height.div_ceil(o.tile_size) as usize;
    if tiles > crate::MAX_FRAME_TILES {
        return Err(format!(
            "{tiles} tiles, more than {}",
            crate::MAX_FRAME_TILES
        ));
    }
    if o.owners.0.len() != tiles {
        return Err(format!(
            "{} owners for a frame of {tiles} tiles",
            o.owners.0.len()
        ));
    }
    let n = o.clients.as_slice().len() as u32;
    if let Some(bad) = o.owners.0.iter().find(|&&c| c != u32::MAX && c >= n) {
        return Err(format!("owner {bad} but only {n} clients"));
    }
    if o.hit_counts.0.len() != tiles {
        return Err(format!(
            "{} hit counts for a frame of {tiles} tiles",
            o.hit_counts.0.len()
        ));
    }
    if let Some(bad) = o.hit_counts.0.iter().find(|&&c| c as usize > MAX_TILE_HITS) {
        return Err(format!("{bad} hits in a tile, more than {MAX_TILE_HITS}"));
    }
    let total: usize = o.hit_counts.0.iter().map(|&c| c as usize).sum();
    if o.hits.0.len() != 3 * total {
        return Err(format!(
            "{} hit coordinates for {total} hits",
            o.hits.0.len()
        ));
    }
    Ok(())
}

impl Message {
    /// Bytes of the message's large arrays (pixels, depths, ids, voxel and
    /// manifest data, hits), about its encoded size less a few fields.
    pub fn payload_len(&self) -> usize {
        match self {
            Message::TileDone(t) => {
                t.pixels.bytes().len()
                    + t.depth.as_ref().map_or(0, |d| d.0.len() * 4)
                    + t.prim_ids.as_ref().map_or(0, |p| p.0.len() * 4)
                    + t.hits.as_slice().len() * 12
            }
            Message::VoxelLoaded(v) => v.data.0.len(),
            Message::ManifestData(m) => m.data.0.len(),
            Message::TileReport(r) => r.hits.as_slice().len() * 12,
            Message::PrefetchHint(h) => h.voxels.0.len() * 4,
            Message::TileOwners(o) => o.hits.0.len() * 4 + o.hit_counts.0.len(),
            _ => 0,
        }
    }

    /// Checks what types cannot: sizes agree, values are finite and in range.
    pub fn validate(&self) -> Result<(), ProtocolError> {
        let kind = self.kind();
        let r = match self {
            Message::AssignTile(a) => check_frame(a.width, a.height, &a.settings)
                .and_then(|_| check_tile(&a.tile, a.width, a.height))
                .and_then(|_| check_camera(&a.camera)),
            Message::FrameStart(f) => {
                check_frame(f.width, f.height, &f.settings).and_then(|_| check_camera(&f.camera))
            }
            Message::TileReport(r) => check_tile(&r.tile, u32::MAX, u32::MAX),
            Message::TileOwners(o) => check_owners(o),
            Message::ManifestData(m) if m.data.0.len() > crate::MAX_VOXEL_BYTES => Err(format!(
                "manifest of {} bytes is over {}",
                m.data.0.len(),
                crate::MAX_VOXEL_BYTES
            )),
            Message::TileDone(t) => {
                let n = t.tile.area();
                check_tile(&t.tile, u32::MAX, u32::MAX).and_then(|_| {
                    if let Err(e) = t.pixels.check_size(n) {
                        Err(format!("a {}x{} tile: {e}", t.tile.w, t.tile.h))
                    } else if t.depth.as_ref().is_some_and(|d| d.0.len() != n) {
                        Err("depth length differs from the tile's pixel count".into())
                    } else if t.prim_ids.as_ref().is_some_and(|p| p.0.len() != n) {
                        Err("primitive id length differs from the tile's pixel count".into())
                    } else {
                        Ok(())
                    }
                })
            }
            Message::VoxelError(e) if e.message.len() > MAX_TEXT_LEN => {
                Err(format!("message of {} bytes is too long", e.message.len()))
            }
            Message::VoxelLost(l) if l.reason.len() > MAX_TEXT_LEN => {
                Err(format!("reason of {} bytes is too long", l.reason.len()))
            }
            Message::Shutdown(s) if s.reason.len() > MAX_TEXT_LEN => {
                Err(format!("reason of {} bytes is too long", s.reason.len()))
            }
            Message::CameraUpdate(c) => check_camera(&c.camera).and_then(|_| match &c.format {
                Some(f) => check_frame(f.width, f.height, &f.settings),
                None => Ok(()),
            }),
            Message::PrefetchHint(p) if p.voxels.0.len() > MAX_PREFETCH_IDS => Err(format!(
                "{} voxel ids, more than {MAX_PREFETCH_IDS}",
                p.voxels.0.len()
            )),
            Message::VoxelLoaded(v) if v.data.0.len() > crate::MAX_VOXEL_BYTES => Err(format!(
                "voxel of {} bytes is over {}",
                v.data.0.len(),
                crate::MAX_VOXEL_BYTES
            )),
            _ => Ok(()),
        };
        r.map_err(|reason| ProtocolError::Invalid { kind, reason })
    }
}
