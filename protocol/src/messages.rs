//! The actor messages and their limits.

use crate::{
    Blob, BoundedVec, Name, PackedF32, PackedU32, ProtocolError, VoxelId, BULK_FRAME_MAX,
    ENVELOPE_OVERHEAD, MAX_IMAGE_SIDE, MAX_PREFETCH_IDS, MAX_REFLECTION_DEPTH, MAX_STATS_CLIENTS,
    MAX_TEXT_LEN, MAX_TILE_SIDE,
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

/// A pinhole camera (DESIGN.md conventions): vertical field of view in degrees.
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

/// A point light.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Light {
    /// Position in world space.
    pub position: [f32; 3],
    /// Linear RGB intensity.
    pub intensity: [f32; 3],
}

/// How a tile is shaded.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct RenderSettings {
    /// Trace shadow rays to the light.
    pub shadows: bool,
    /// Reflection recursion depth (0: none).
    pub reflection_depth: u8,
    /// The light.
    pub light: Light,
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
    /// Voxel cache misses.
    pub misses: u32,
    /// Bytes of voxels fetched for this tile.
    pub bytes_fetched: u64,
}

/// A client returns a rendered tile.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct TileDone {
    /// Frame number.
    pub frame: u64,
    /// The tile.
    pub tile: TileRect,
    /// RGBA8 pixels, rows top to bottom, `tile.w * tile.h * 4` bytes.
    pub pixels: Blob,
    /// Per-pixel hit distance (+inf on a miss), when asked for.
    pub depth: Option<PackedF32>,
    /// Per-pixel original triangle index (0xFFFFFFFF on a miss), when asked for.
    pub prim_ids: Option<PackedU32>,
    /// Costs.
    pub stats: TileStats,
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

/// The display moves the camera.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct CameraUpdate {
    /// Increases with each update; older ones are ignored.
    pub seq: u64,
    /// The new camera.
    pub camera: Camera,
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

/// Every actor message. The variant order is the wire tag: append only.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub enum Message {
    /// Client → scheduler.
    RequestWork(RequestWork),
    /// Scheduler → client.
    AssignTile(AssignTile),
    /// Client → scheduler (or display).
    TileDone(TileDone),
    /// Client → store.
    FetchVoxel(FetchVoxel),
    /// Store → client.
    VoxelLoaded(VoxelLoaded),
    /// Store → client.
    VoxelError(VoxelError),
    /// Display → scheduler.
    CameraUpdate(CameraUpdate),
    /// Scheduler → display.
    FrameDone(FrameDone),
    /// Prefetcher → client.
    PrefetchHint(PrefetchHint),
    /// Any → any.
    Ping(Ping),
    /// Answer to a ping.
    Pong(Ping),
    /// Any → any.
    Shutdown(Shutdown),
}

/// The kind of a message, without its contents.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash)]
pub enum MessageKind {
    /// [`Message::RequestWork`].
    RequestWork,
    /// [`Message::AssignTile`].
    AssignTile,
    /// [`Message::TileDone`].
    TileDone,
    /// [`Message::FetchVoxel`].
    FetchVoxel,
    /// [`Message::VoxelLoaded`].
    VoxelLoaded,
    /// [`Message::VoxelError`].
    VoxelError,
    /// [`Message::CameraUpdate`].
    CameraUpdate,
    /// [`Message::FrameDone`].
    FrameDone,
    /// [`Message::PrefetchHint`].
    PrefetchHint,
    /// [`Message::Ping`].
    Ping,
    /// [`Message::Pong`].
    Pong,
    /// [`Message::Shutdown`].
    Shutdown,
    /// Not an actor message: the connection handshake.
    Handshake,
}

impl MessageKind {
    /// Every actor message kind, in wire tag order.
    pub const ALL: [MessageKind; 12] = [
        MessageKind::RequestWork,
        MessageKind::AssignTile,
        MessageKind::TileDone,
        MessageKind::FetchVoxel,
        MessageKind::VoxelLoaded,
        MessageKind::VoxelError,
        MessageKind::CameraUpdate,
        MessageKind::FrameDone,
        MessageKind::PrefetchHint,
        MessageKind::Ping,
        MessageKind::Pong,
        MessageKind::Shutdown,
    ];

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
            | MessageKind::Pong => ENVELOPE_OVERHEAD,
            MessageKind::VoxelError | MessageKind::Shutdown => ENVELOPE_OVERHEAD + text,
            MessageKind::TileDone => ENVELOPE_OVERHEAD + 3 * (tile_px * 4 + 4),
            MessageKind::VoxelLoaded => BULK_FRAME_MAX,
            MessageKind::FrameDone => {
                ENVELOPE_OVERHEAD + MAX_STATS_CLIENTS * (crate::MAX_NAME_LEN + 1 + 4 * 10)
            }
            MessageKind::PrefetchHint => ENVELOPE_OVERHEAD + MAX_PREFETCH_IDS * 4 + 4,
            MessageKind::Handshake => crate::HANDSHAKE_FRAME_MAX,
        }
    }

    /// Whether this kind travels on its own stream, so that it never delays
    /// the small control messages behind it.
    pub fn is_bulk(self) -> bool {
        matches!(self, MessageKind::TileDone | MessageKind::VoxelLoaded)
    }

    /// A short lowercase name, for logs and spans.
    pub fn name(self) -> &'static str {
        match self {
            MessageKind::RequestWork => "request_work",
            MessageKind::AssignTile => "assign_tile",
            MessageKind::TileDone => "tile_done",
            MessageKind::FetchVoxel => "fetch_voxel",
            MessageKind::VoxelLoaded => "voxel_loaded",
            MessageKind::VoxelError => "voxel_error",
            MessageKind::CameraUpdate => "camera_update",
            MessageKind::FrameDone => "frame_done",
            MessageKind::PrefetchHint => "prefetch_hint",
            MessageKind::Ping => "ping",
            MessageKind::Pong => "pong",
            MessageKind::Shutdown => "shutdown",
            MessageKind::Handshake => "handshake",
        }
    }
}

fn finite(v: &[f32]) -> bool {
    v.iter().all(|x| x.is_finite())
}

fn check_camera(c: &Camera) -> Result<(), String> {
    if !(finite(&c.eye) && finite(&c.look) && finite(&c.up) && c.fov_y_deg.is_finite()) {
        return Err("camera has a non-finite value".into());
    }
    if !(c.fov_y_deg > 0.0 && c.fov_y_deg < 180.0) {
        return Err(format!(
            "field of view {} is outside (0, 180) degrees",
            c.fov_y_deg
        ));
    }
    if c.eye == c.look {
        return Err("camera eye and look point coincide".into());
    }
    Ok(())
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

impl Message {
    /// This message's kind.
    pub fn kind(&self) -> MessageKind {
        match self {
            Message::RequestWork(_) => MessageKind::RequestWork,
            Message::AssignTile(_) => MessageKind::AssignTile,
            Message::TileDone(_) => MessageKind::TileDone,
            Message::FetchVoxel(_) => MessageKind::FetchVoxel,
            Message::VoxelLoaded(_) => MessageKind::VoxelLoaded,
            Message::VoxelError(_) => MessageKind::VoxelError,
            Message::CameraUpdate(_) => MessageKind::CameraUpdate,
            Message::FrameDone(_) => MessageKind::FrameDone,
            Message::PrefetchHint(_) => MessageKind::PrefetchHint,
            Message::Ping(_) => MessageKind::Ping,
            Message::Pong(_) => MessageKind::Pong,
            Message::Shutdown(_) => MessageKind::Shutdown,
        }
    }

    /// Checks what types cannot: sizes agree, values are finite and in range.
    pub fn validate(&self) -> Result<(), ProtocolError> {
        let kind = self.kind();
        let r = match self {
            Message::AssignTile(a) => {
                if a.width == 0
                    || a.height == 0
                    || a.width > MAX_IMAGE_SIDE
                    || a.height > MAX_IMAGE_SIDE
                {
                    Err(format!(
                        "image of {}x{} is empty or larger than {MAX_IMAGE_SIDE}",
                        a.width, a.height
                    ))
                } else if a.settings.reflection_depth > MAX_REFLECTION_DEPTH {
                    Err(format!(
                        "reflection depth {} is over {MAX_REFLECTION_DEPTH}",
                        a.settings.reflection_depth
                    ))
                } else if !(finite(&a.settings.light.position)
                    && finite(&a.settings.light.intensity))
                {
                    Err("light has a non-finite value".into())
                } else {
                    check_tile(&a.tile, a.width, a.height).and_then(|_| check_camera(&a.camera))
                }
            }
            Message::TileDone(t) => {
                let n = t.tile.area();
                check_tile(&t.tile, u32::MAX, u32::MAX).and_then(|_| {
                    if t.pixels.0.len() != n * 4 {
                        Err(format!(
                            "{} pixel bytes for a {}x{} tile (want {})",
                            t.pixels.0.len(),
                            t.tile.w,
                            t.tile.h,
                            n * 4
                        ))
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
            Message::Shutdown(s) if s.reason.len() > MAX_TEXT_LEN => {
                Err(format!("reason of {} bytes is too long", s.reason.len()))
            }
            Message::CameraUpdate(c) => check_camera(&c.camera),
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
