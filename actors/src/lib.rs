//! dray-actors: the distributed renderer (docs/design.md, the paper's system).
//!
//! Every actor is an `async fn run_*(mailbox, options)` that talks only
//! through the [`dray_runtime::Bus`]: the same code runs over QUIC between
//! processes and over the in-process transport in tests and `dray sim`.
//!
//! | actor | node | module |
//! |---|---|---|
//! | VoxelStore | `store-I` | [`store`] |
//! | Client (cache, loader, render threads) | `client-I` | [`client`] |
//! | Scheduler, FrameAssigner, Prefetcher | `scheduler` | [`scheduler`] |
//! | Display (frames, metrics, camera path) | `display` | [`display`] |
//!
//! [`nodes`] wires them into nodes and whole runs; [`centre`] runs the
//! scheduler node and the display alone against stand-in clients, to
//! measure what they cost as clients grow.
//!
//! Message flow: the display sends one [`Message::CameraUpdate`] per frame to
//! the frame assigner, which releases frames to the scheduler
//! ([`Message::FrameStart`]) once the previous one is fully assigned
//! ([`Message::FrameAssigned`]). Clients ask the scheduler for tiles
//! ([`Message::RequestWork`]), fetch voxels from the store of each voxel's
//! shard and send the pixels to the display ([`Message::TileDone`]), which
//! reports each tile to the scheduler once it has its pixels
//! ([`Message::TileReport`]). The scheduler tells
//! the display when a frame is complete ([`Message::FrameDone`]) and the
//! prefetcher who rendered which tile ([`Message::TileOwners`]).
//!
//! Every actor's loop takes its `select!` branches in order (`biased`),
//! not at random, and blocking work on the virtual clock runs on the
//! virtual thread ([`spawn_blocking`]): so a run on the virtual clock
//! ([`nodes::sim_virtual`], [`costs`]) repeats exactly. Each branch
//! drains quickly, so none starves the others.
//!
//! [`Message::CameraUpdate`]: dray_protocol::Message::CameraUpdate
//! [`Message::FrameStart`]: dray_protocol::Message::FrameStart
//! [`Message::FrameAssigned`]: dray_protocol::Message::FrameAssigned
//! [`Message::RequestWork`]: dray_protocol::Message::RequestWork
//! [`Message::TileDone`]: dray_protocol::Message::TileDone
//! [`Message::TileReport`]: dray_protocol::Message::TileReport
//! [`Message::FrameDone`]: dray_protocol::Message::FrameDone
//! [`Message::TileOwners`]: dray_protocol::Message::TileOwners

pub mod centre;
pub mod client;
pub mod costs;
pub mod display;
pub mod names;
pub mod nodes;
pub mod scheduler;
pub mod settings;
mod signals;
pub mod store;
pub mod supervisor;

pub use names::Shard;

/// Why an actor stopped with an error.
#[derive(Debug, thiserror::Error)]
pub enum ActorError {
    /// A message could not be sent.
    #[error("{actor}: sending to {to} failed: {source}")]
    Send {
        /// The sending actor.
        actor: String,
        /// The destination.
        to: String,
        /// What the bus said.
        source: dray_runtime::SendError,
    },
    /// The voxel database could not be used.
    #[error("{actor}: database {path}: {message}")]
    Database {
        /// The actor.
        actor: String,
        /// The database directory.
        path: String,
        /// What is wrong.
        message: String,
    },
    /// A peer sent something unusable (a manifest that does not parse, a
    /// voxel that keeps failing its checksum).
    #[error("{actor}: {message}")]
    Peer {
        /// The actor.
        actor: String,
        /// What happened.
        message: String,
    },
    /// Files (frames, metrics) could not be written.
    #[error("{actor}: {path}: {source}")]
    Io {
        /// The actor.
        actor: String,
        /// The file.
        path: String,
        /// What happened.
        source: std::io::Error,
    },
    /// The bus was dropped before the actor was told to stop.
    #[error("{0}: the bus closed")]
    BusClosed(String),
}

thread_local! {
    /// Set on the thread that runs a virtual run ([`nodes::sim_virtual`]).
    static ON_VIRTUAL_CLOCK: std::cell::Cell<bool> = const { std::cell::Cell::new(false) };
}

/// Marks the calling thread as running a virtual run until the guard
/// drops.
pub(crate) fn on_virtual_clock() -> impl Drop {
    struct Guard;
    impl Drop for Guard {
        fn drop(&mut self) {
            ON_VIRTUAL_CLOCK.with(|v| v.set(false));
        }
    }
    ON_VIRTUAL_CLOCK.with(|v| v.set(true));
    Guard
}

/// Runs blocking `f` on tokio's blocking pool; on the virtual clock, right
/// here, so that when it finishes does not depend on another thread and a
/// virtual run repeats exactly (the clock stands still either way).
pub(crate) fn spawn_blocking<T: Send + 'static>(
    f: impl FnOnce() -> T + Send + 'static,
) -> tokio::task::JoinHandle<T> {
    if ON_VIRTUAL_CLOCK.with(std::cell::Cell::get) {
        let done = f();
        tokio::spawn(async move { done })
    } else {
        tokio::task::spawn_blocking(f)
    }
}

/// Sleeps until `deadline`, or forever without one (a `select!` branch
/// for an optional timer).
pub(crate) async fn sleep_until_opt(deadline: Option<tokio::time::Instant>) {
    match deadline {
        Some(t) => tokio::time::sleep_until(t).await,
        None => std::future::pending().await,
    }
}
