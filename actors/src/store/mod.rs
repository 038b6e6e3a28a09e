//! The VoxelStore actor: serves compressed voxel blobs by id from a database
//! on disk (one shard of it).
//!
//! The database is never loaded whole: each [`FetchVoxel`] reads one blob
//! (on tokio's blocking pool), at most [`StoreOptions::max_concurrent`]
//! read or being sent at once (which bounds the store's memory), and the
//! answer is sent from a task of its own so that the mailbox loop never
//! waits on a slow peer. A [`StoreDisk`] models a slower disk on tokio's
//! clock (so both engines and paused-clock tests honour it).
//!
//! Shape: `state::Store` owns what the store decides (refusals, the read
//! slots and the reads waiting for one, the counts); its handlers push
//! effects (`state::Out`: read and send a voxel, refuse, send the
//! manifest, answer a ping); [`run_store`] receives, calls the handler,
//! and carries the effects out on tasks, which report back when a blob is
//! read (`Store::blob_read`) and when its answer has left
//! (`Store::answer_sent`).

mod state;

use crate::{ActorError, Shard};
use dray_protocol::{
    Address, Blob, FetchVoxel, ManifestData, Message, VoxelError, VoxelLoaded, MAX_TEXT_LEN,
};
use dray_runtime::{ActorRef, Delivery, LinkShape, Mailbox};
use dray_scene::db::manifest::MANIFEST_FILE;
use dray_scene::db::Database;
use state::{Out, ReadOutcome, Store};
use std::path::PathBuf;
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// How a store runs.
#[derive(Clone, Debug)]
pub struct StoreOptions {
    /// The database directory.
    pub database: PathBuf,
    /// The voxels it serves.
    pub shard: Shard,
    /// Most blobs read or being sent at once.
    pub max_concurrent: usize,
    /// The disk as modelled; the default: reads take what the real disk takes.
    pub disk: StoreDisk,
}

/// The disk a store reads its blobs from, as modelled: one read after
/// another, each taking the access time plus its bytes over the bandwidth.
/// The default is no model: reads take what the real disk takes.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct StoreDisk {
    /// Time per read before its bytes flow (a seek).
    pub access_time: Duration,
    /// Read bandwidth in bits per second; `None`: unlimited.
    pub bandwidth_bps: Option<u64>,
}

impl StoreDisk {
    /// How long the disk is busy reading `bytes`.
    fn read_time(&self, bytes: u64) -> Duration {
        let stream = LinkShape {
            bandwidth_bps: self.bandwidth_bps,
            ..LinkShape::none()
        };
        self.access_time + stream.transmission_time(usize::try_from(bytes).unwrap_or(usize::MAX))
    }
}

/// A modelled disk's queue: when it is free for the next read.
struct DiskQueue {
    disk: StoreDisk,
    free_at: Mutex<Instant>,
}

impl DiskQueue {
    fn new(disk: StoreDisk) -> Option<Arc<DiskQueue>> {
        (disk != StoreDisk::default()).then(|| {
            Arc::new(DiskQueue {
                disk,
                free_at: Mutex::new(Instant::now()),
            })
        })
    }

    /// Books a read of `bytes` asked for now; returns when it completes.
    fn book(&self, bytes: u64) -> Instant {
        let mut free_at = self.free_at.lock().unwrap_or_else(|p| p.into_inner());
        *free_at = (*free_at).max(Instant::now()) + self.disk.read_time(bytes);
        *free_at
    }
}

/// What a store did, returned when it stops.
#[derive(Clone, Debug, Default)]
pub struct StoreSummary {
    /// Voxels served.
    pub served: u64,
    /// Compressed bytes served.
    pub bytes_served: u64,
    /// Requests answered with a [`VoxelError`].
    pub refused: u64,
    /// Manifests served.
    pub manifests: u64,
}

/// Text cut to the wire's limit (on a character boundary).
pub(crate) fn clip(mut s: String) -> String {
    if s.len() > MAX_TEXT_LEN {
        let mut end = MAX_TEXT_LEN;
        while !s.is_char_boundary(end) {
            end -= 1;
        }
        s.truncate(end);
    }
    s
}

/// Opens the database a store serves `shard` from: a whole database, or
/// a shard of one (`dray shard`) that holds every voxel of `shard`.
fn open_database(path: &std::path::Path, shard: Shard) -> Result<Database, String> {
    let db = Database::open(path).map_err(|e| e.to_string())?;
    check_holds(&db, shard)?;
    Ok(db)
}

/// Whether `db` holds every voxel of `shard`; the problem in words if not.
pub fn check_holds(db: &Database, shard: Shard) -> Result<(), String> {
    let path = db.dir();
    match db.shard() {
        Some(s) if !s.covers(shard.index, shard.count) => Err(format!(
            "{} is shard {s} of a database, which does not hold the voxels of shard {shard} \
             that this store serves (a store serving I/N needs the shard I/N, or one of \
             M shards where M divides N and I mod M is its index)",
            path.display()
        )),
        _ => Ok(()),
    }
}

/// Runs a store until it gets [`Message::Shutdown`] or its mailbox closes;
/// each blob read takes at least what `opts.disk` says (the real read
/// overlaps the modelled time).
pub async fn run_store(mut mb: Mailbox, opts: StoreOptions) -> Result<StoreSummary, ActorError> {
    let actor = mb.address().to_string();
    let db_err = |message: String| ActorError::Database {
        actor: actor.clone(),
        path: opts.database.display().to_string(),
        message,
    };
    let path = opts.database.clone();
    let shard = opts.shard;
    let (db, manifest) = crate::spawn_blocking(move || {
        let db = open_database(&path, shard)?;
        let manifest_path = db.dir().join(MANIFEST_FILE);
        let bytes = std::fs::read(&manifest_path)
            .map_err(|e| format!("{}: {e}", manifest_path.display()))?;
        Ok::<_, String>((db, bytes))
    })
    .await
    .map_err(|e| db_err(format!("opening failed: {e}")))?
    .map_err(db_err)?;
    let voxels = db.manifest.voxels.len() as u64;
    info!(%actor, database = %opts.database.display(), shard = %opts.shard, voxels, "store ready");
    let mut store = Store::new(actor.clone(), opts.shard, voxels, opts.max_concurrent);
    let db = Arc::new(db);
    let manifest = Arc::new(manifest);
    let disk = DiskQueue::new(opts.disk);
    let me = mb.handle();
    // Every answer leaves from a task of its own. A read's task reports the
    // read as soon as it ends (counted even if the answer never leaves) and
    // its end, however it ends, frees a read slot.
    let mut reads: JoinSet<()> = JoinSet::new();
    let mut others: JoinSet<()> = JoinSet::new();
    let (read_tx, mut read_rx) = mpsc::unbounded_channel();
    let mut out = Vec::new();
    loop {
        while others.try_join_next().is_some() {}
        tokio::select! {
            biased;
            d = mb.recv() => match d {
                None => break,
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::FetchVoxel(FetchVoxel { id }) => store.fetch_voxel(from, id, &mut out),
                    Message::FetchManifest(_) => store.fetch_manifest(from, &mut out),
                    Message::Ping(p) => store.ping(from, p, &mut out),
                    Message::Shutdown(s) => {
                        info!(%actor, reason = %s.reason, "store stopping");
                        break;
                    }
                    other => debug!(%actor, kind = other.kind().name(), %from, "ignored"),
                },
                Some(_) => {}
            },
            Some(outcome) = read_rx.recv() => store.blob_read(outcome),
            Some(_) = reads.join_next() => store.answer_sent(&mut out),
        }
        for o in out.drain(..) {
            let me = me.clone();
            match o {
                Out::Read { to, id } => {
                    let (db, disk, read) = (db.clone(), disk.clone(), read_tx.clone());
                    reads.spawn(async move { read_and_send(&me, db, disk, read, to, id).await });
                }
                Out::Refuse { to, id, why } => {
                    others.spawn(async move {
                        let msg = Message::VoxelError(VoxelError {
                            id,
                            message: clip(why),
                        });
                        if let Err(e) = me.send(&to, msg).await {
                            debug!(voxel = id, %to, error = %e, "could not send a refusal");
                        }
                    });
                }
                Out::Manifest { to } => {
                    let manifest = manifest.clone();
                    others.spawn(async move {
                        let msg = Message::ManifestData(ManifestData {
                            data: Blob(manifest.as_ref().clone()),
                        });
                        if let Err(e) = me.send(&to, msg).await {
                            debug!(%to, error = %e, "could not send the manifest");
                        }
                    });
                }
                Out::Pong { to, ping } => {
                    others.spawn(async move {
                        let _ = me.send(&to, Message::Pong(ping)).await;
                    });
                }
            }
        }
    }
    // Answers still under way are dropped; reads that ended are counted.
    reads.shutdown().await;
    others.shutdown().await;
    while let Ok(outcome) = read_rx.try_recv() {
        store.blob_read(outcome);
    }
    Ok(store.summary().clone())
}

/// Reads voxel `id` (taking at least what the modelled disk says), reports
/// how the read ended on `read`, and sends the blob, or why it could not be
/// read, to `to`.
async fn read_and_send(
    me: &ActorRef,
    db: Arc<Database>,
    disk: Option<Arc<DiskQueue>>,
    read: mpsc::UnboundedSender<ReadOutcome>,
    to: Address,
    id: u32,
) {
    let bytes = db
        .manifest
        .voxels
        .get(id as usize)
        .map_or(0, |v| v.compressed_bytes);
    let done = disk.map(|d| d.book(bytes));
    let blob = crate::spawn_blocking(move || db.read_blob(id))
        .await
        .map_err(|e| format!("read task failed: {e}"))
        .and_then(|r| r.map_err(|e| e.to_string()));
    if let Some(done) = done {
        tokio::time::sleep_until(done).await;
    }
    let (msg, outcome) = match blob {
        Ok(blob) => {
            let bytes = blob.len() as u64;
            let msg = Message::VoxelLoaded(VoxelLoaded {
                id,
                data: Blob(blob),
            });
            (msg, ReadOutcome::Served { bytes })
        }
        Err(why) => {
            warn!(voxel = id, error = %why, "cannot read a voxel");
            let msg = Message::VoxelError(VoxelError {
                id,
                message: clip(why),
            });
            (msg, ReadOutcome::Failed)
        }
    };
    let _ = read.send(outcome);
    if let Err(e) = me.send(&to, msg).await {
        debug!(voxel = id, %to, error = %e, "could not answer");
    }
}
