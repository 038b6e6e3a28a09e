//! dray-protocol: the typed messages nodes exchange (postcard encoded).
//!
//! Everything that crosses a process boundary is defined here: node and actor
//! names, the connection handshake ([`Handshake`]), the actor messages
//! ([`Message`]) wrapped in an [`Envelope`], and the wire size limit of each
//! message kind. This crate does no I/O.
//!
//! # Wire format
//!
//! A frame body is the postcard encoding of an [`Envelope`]. The message comes
//! first, so the first byte of a body is the variant index of [`Message`]
//! (there are fewer than 128 variants, so postcard writes it as one byte).
//! [`decode_envelope`] reads that byte, looks up the limit of the kind, and
//! refuses a body over it before decoding anything; the transports put a
//! length prefix in front of each body and cap it per stream class
//! ([`CONTROL_FRAME_MAX`], [`BULK_FRAME_MAX`]).
//!
//! Decoding never panics, and never allocates more than the kind's limit:
//! large arrays are carried as byte strings ([`Blob`], [`PackedU32`],
//! [`PackedF32`]) whose memory is at most their encoded size, and the few
//! lists of structures are [`BoundedVec`]s that refuse more than their bound.

mod bounded;
mod checks;
mod messages;
mod name;
mod pixels;

pub use bounded::{Blob, BoundedVec, PackedF32, PackedU32};
pub use checks::{
    check_camera, check_image_side, check_light_dir, check_reflectance, check_reflection_depth,
    check_samples, CameraError, CameraField,
};
pub use messages::*;
pub use name::{Name, NameError, MAX_NAME_LEN};
pub use pixels::{Compression, PixelError, Pixels, TilePixels};

use serde::{Deserialize, Serialize};

/// Identifies one voxel of a database: its index in the manifest.
pub type VoxelId = u32;

// The version number, written once for both `PROTOCOL_VERSION` and `ALPN`.
macro_rules! protocol_version {
    () => {
        7
    };
}

/// Version of the wire protocol; both ends of a connection must agree.
/// 2: the distributed renderer's messages (manifest, tile reports, frame
/// start and assignment, tile owners) and the shading render settings;
/// 3: tile reports carry hit positions (reprojection affinity);
/// 4: tile owners carry the frame's misses (the prefetcher's throttle);
/// 5: tile and frame statistics carry the voxel bytes after decompression;
/// 6: a client reports a voxel no store serves intact (`VoxelLost`), and
/// tile and frame statistics carry the bytes each link class carried;
/// 7: frames carry a sample index (jittered rays), and a camera update
/// may change the frames' size and shading (`FrameFormat`).
pub const PROTOCOL_VERSION: u32 = protocol_version!();

/// ALPN protocol id spoken over QUIC: `dray/` and [`PROTOCOL_VERSION`].
pub const ALPN: &[u8] = concat!("dray/", protocol_version!()).as_bytes();

/// Largest compressed voxel blob a store may send.
pub const MAX_VOXEL_BYTES: usize = 64 << 20;
/// Largest tile side, in pixels.
pub const MAX_TILE_SIDE: u32 = 256;
/// Largest image side, in pixels.
pub const MAX_IMAGE_SIDE: u32 = 16384;
/// Most tiles in one frame.
pub const MAX_FRAME_TILES: usize = 1 << 16;
/// Most voxel ids in one prefetch hint.
pub const MAX_PREFETCH_IDS: usize = 16384;
/// Most per-client entries in one frame's statistics.
pub const MAX_STATS_CLIENTS: usize = 1024;
/// Longest free text (error messages, reasons), in bytes.
pub const MAX_TEXT_LEN: usize = 1024;
/// Deepest reflection recursion a tile may ask for.
pub const MAX_REFLECTION_DEPTH: u8 = 16;
/// Most samples per pixel a camera of a walkthrough (`render.samples`) or
/// `dray render --spp` asks for.
pub const MAX_SAMPLES: u32 = 1024;

/// Room for an envelope's addresses and a message's fixed fields.
const ENVELOPE_OVERHEAD: usize = 4 * (MAX_NAME_LEN + 2) + 256;

/// Largest handshake frame.
pub const HANDSHAKE_FRAME_MAX: usize = 4096;
/// Largest frame on a control stream (every kind that is not bulk).
pub const CONTROL_FRAME_MAX: usize = 256 << 10;
/// A bulk message no longer than this (a 64 × 64 tile's colors, a small
/// voxel) goes on the control stream: opening a stream of its own costs
/// more than the little it can delay the control messages behind it
/// (32 KB take 2.6 ms at 100 Mbit/s, well under a millisecond on a LAN).
pub const SMALL_BULK_MAX: usize = 32 << 10;
/// A tile's pixels go on the control stream up to this size: a block of
/// 128 × 128 colors with its hits (the scheduler's largest block by
/// default), so that a block costs no more than the tiles it replaces.
/// Only the display's connections carry tiles, and nothing else waits
/// behind them there.
pub const SMALL_TILE_MAX: usize = 80 << 10;
/// Largest frame on a bulk stream (one voxel or one tile result).
pub const BULK_FRAME_MAX: usize = MAX_VOXEL_BYTES + ENVELOPE_OVERHEAD;

/// An actor's address: the node it runs on and its name there.
#[derive(Clone, Debug, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
pub struct Address {
    /// The node (process) the actor lives in.
    pub node: Name,
    /// The actor's name within its node.
    pub actor: Name,
}

impl Address {
    /// Builds an address from two already validated names.
    pub fn new(node: Name, actor: Name) -> Self {
        Address { node, actor }
    }

    /// Builds an address from two strings, validating both.
    pub fn parse(node: &str, actor: &str) -> Result<Self, NameError> {
        Ok(Address {
            node: Name::new(node)?,
            actor: Name::new(actor)?,
        })
    }
}

impl std::fmt::Display for Address {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}/{}", self.node, self.actor)
    }
}

/// A message in flight: what, from whom, to which actor of the receiving node.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize)]
pub struct Envelope {
    /// The message; first, so that a body's first byte names its kind.
    pub msg: Message,
    /// The sending actor.
    pub from: Address,
    /// The receiving actor.
    pub to: Address,
}

/// Why bytes could not be encoded or decoded.
#[derive(Debug, thiserror::Error, PartialEq, Eq)]
pub enum ProtocolError {
    /// The body is empty.
    #[error("empty frame")]
    Empty,
    /// The first byte names no message kind.
    #[error("unknown message kind tag {0}")]
    UnknownKind(u8),
    /// The body is larger than its kind allows.
    #[error("{kind:?} frame of {len} bytes is over its limit of {limit} bytes")]
    Oversized {
        /// The message kind.
        kind: MessageKind,
        /// The body's length.
        len: usize,
        /// The kind's limit.
        limit: usize,
    },
    /// postcard could not decode (or encode) the body.
    #[error("malformed {what}: {source}")]
    Malformed {
        /// What was being decoded.
        what: &'static str,
        /// postcard's error.
        source: postcard::Error,
    },
    /// Bytes were left over after the message.
    #[error("{0} trailing bytes after the message")]
    Trailing(usize),
    /// The message decoded but its contents make no sense.
    #[error("invalid {kind:?}: {reason}")]
    Invalid {
        /// The message kind.
        kind: MessageKind,
        /// What is wrong.
        reason: String,
    },
    /// The peer speaks another protocol version.
    #[error(
        "protocol version mismatch: we speak version {ours}, the peer speaks version {theirs}"
    )]
    VersionMismatch {
        /// Our version.
        ours: u32,
        /// The peer's version.
        theirs: u32,
    },
}

fn malformed(what: &'static str) -> impl FnOnce(postcard::Error) -> ProtocolError {
    move |source| ProtocolError::Malformed { what, source }
}

/// Reads the message kind of a body from its first byte, without decoding.
pub fn peek_kind(body: &[u8]) -> Result<MessageKind, ProtocolError> {
    let tag = *body.first().ok_or(ProtocolError::Empty)?;
    MessageKind::from_tag(tag).ok_or(ProtocolError::UnknownKind(tag))
}

/// Room for an envelope's names, fields and length prefixes beyond
/// [`Message::payload_len`]: the encoder allocates the two at once.
pub const ENVELOPE_SLACK: usize = 256;

/// postcard's output in a vector allocated once at about the encoded size:
/// grown from empty, it would copy a tile's pixels several times over.
struct Presized(Vec<u8>);

impl postcard::ser_flavors::Flavor for Presized {
    type Output = Vec<u8>;

    fn try_extend(&mut self, data: &[u8]) -> postcard::Result<()> {
        self.0.extend_from_slice(data);
        Ok(())
    }

    fn try_push(&mut self, data: u8) -> postcard::Result<()> {
        self.0.push(data);
        Ok(())
    }

    fn finalize(self) -> postcard::Result<Vec<u8>> {
        Ok(self.0)
    }
}

/// Encodes an envelope, refusing one whose message is invalid or over its
/// kind's limit (so a sender learns of it, not the receiver).
pub fn encode_envelope(env: &Envelope) -> Result<Vec<u8>, ProtocolError> {
    let kind = env.msg.kind();
    env.msg.validate()?;
    let out = Presized(Vec::with_capacity(env.msg.payload_len() + ENVELOPE_SLACK));
    let body = postcard::serialize_with_flavor(env, out).map_err(malformed("envelope"))?;
    let limit = kind.max_wire_size();
    if body.len() > limit {
        return Err(ProtocolError::Oversized {
            kind,
            len: body.len(),
            limit,
        });
    }
    Ok(body)
}

/// Decodes and validates an envelope from untrusted bytes.
///
/// The size is checked against the kind's limit before anything is decoded;
/// the whole body must be consumed.
pub fn decode_envelope(body: &[u8]) -> Result<Envelope, ProtocolError> {
    let kind = peek_kind(body)?;
    let limit = kind.max_wire_size();
    if body.len() > limit {
        return Err(ProtocolError::Oversized {
            kind,
            len: body.len(),
            limit,
        });
    }
    let (env, rest): (Envelope, _) =
        postcard::take_from_bytes(body).map_err(malformed("envelope"))?;
    if !rest.is_empty() {
        return Err(ProtocolError::Trailing(rest.len()));
    }
    env.msg.validate()?;
    Ok(env)
}

/// The role a node plays in the cluster.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Role {
    /// Splits frames into tiles and hands them out.
    Scheduler,
    /// Renders tiles.
    Client,
    /// Serves voxels.
    Store,
    /// Shows frames and sends camera moves.
    Display,
    /// A command line tool or benchmark.
    Tool,
}

impl Role {
    /// Every role.
    pub const ALL: [Role; 5] = [
        Role::Scheduler,
        Role::Client,
        Role::Store,
        Role::Display,
        Role::Tool,
    ];

    /// The roles of the cluster's nodes (every role but [`Role::Tool`]).
    pub const CLUSTER: [Role; 4] = [Role::Scheduler, Role::Client, Role::Store, Role::Display];

    /// The role a node's name gives it: `scheduler`, `display`, `store-I`
    /// and `client-I` (I a decimal number) are the cluster's nodes; any
    /// other name is a [`Role::Tool`]. A node's role is never taken from
    /// what it says about itself: its certificate names it, and the name
    /// fixes the role, so the sender rules
    /// ([`MessageKind::may_send`](crate::MessageKind::may_send)) hold
    /// against the authenticated identity.
    pub fn of_node(node: &Name) -> Role {
        let indexed = |prefix: &str| {
            node.as_str()
                .strip_prefix(prefix)
                .is_some_and(|i| !i.is_empty() && i.bytes().all(|b| b.is_ascii_digit()))
        };
        match node.as_str() {
            "scheduler" => Role::Scheduler,
            "display" => Role::Display,
            _ if indexed("store-") => Role::Store,
            _ if indexed("client-") => Role::Client,
            _ => Role::Tool,
        }
    }
}

impl std::fmt::Display for Role {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let s = match self {
            Role::Scheduler => "scheduler",
            Role::Client => "client",
            Role::Store => "store",
            Role::Display => "display",
            Role::Tool => "tool",
        };
        f.write_str(s)
    }
}

/// First message of a connection, from the dialing node.
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub struct Hello {
    /// Must stay the first field: it is read before the rest.
    pub version: u32,
    /// The dialer's role.
    pub role: Role,
    /// The dialer's node name (must match its certificate).
    pub node: Name,
}

/// The accepting node's answer to a [`Hello`].
#[derive(Clone, Debug, PartialEq, Eq, Serialize, Deserialize)]
pub enum Handshake {
    /// Sent by the dialer.
    Hello(Hello),
    /// The acceptor agrees; same fields as a hello.
    Welcome(Hello),
    /// The acceptor refuses, saying why.
    Refused {
        /// Our version, so the other side can report it.
        version: u32,
        /// Human readable reason.
        reason: String,
    },
}

impl Handshake {
    /// Encodes a handshake message.
    pub fn encode(&self) -> Result<Vec<u8>, ProtocolError> {
        postcard::to_stdvec(self).map_err(malformed("handshake"))
    }

    /// Decodes a handshake message from untrusted bytes. A hello or welcome
    /// of another protocol version is reported as
    /// [`ProtocolError::VersionMismatch`] even when the rest of it would not
    /// decode with this version's types.
    pub fn decode(body: &[u8]) -> Result<Handshake, ProtocolError> {
        if body.len() > HANDSHAKE_FRAME_MAX {
            return Err(ProtocolError::Oversized {
                kind: MessageKind::Handshake,
                len: body.len(),
                limit: HANDSHAKE_FRAME_MAX,
            });
        }
        let (tag, rest): (u32, _) =
            postcard::take_from_bytes(body).map_err(malformed("handshake"))?;
        if tag == 0 || tag == 1 {
            let (version, _): (u32, _) =
                postcard::take_from_bytes(rest).map_err(malformed("handshake"))?;
            if version != PROTOCOL_VERSION {
                return Err(ProtocolError::VersionMismatch {
                    ours: PROTOCOL_VERSION,
                    theirs: version,
                });
            }
        }
        let (hs, rest): (Handshake, _) =
            postcard::take_from_bytes(body).map_err(malformed("handshake"))?;
        if !rest.is_empty() {
            return Err(ProtocolError::Trailing(rest.len()));
        }
        if let Handshake::Refused { reason, .. } = &hs {
            if reason.len() > MAX_TEXT_LEN {
                return Err(ProtocolError::Invalid {
                    kind: MessageKind::Handshake,
                    reason: "refusal reason too long".into(),
                });
            }
        }
        Ok(hs)
    }
}

pub mod examples;
