//! The VoxelStore actor: serves compressed voxel blobs by id from a database
//! on disk (one shard of it).
//!
//! The database is never loaded whole: each [`FetchVoxel`] reads one blob
//! (on tokio's blocking pool), at most [`StoreOptions::max_concurrent`]
//! read or being sent at once (which bounds the store's memory), and the
//! answer is sent from a task of its own so that the mailbox loop never
//! waits on a slow peer. A [`StoreDisk`] models a slower disk on tokio's
//! clock (so both engines and paused-clock tests honour it).

use crate::{ActorError, Shard};
use dray_protocol::{
    Address, Blob, FetchVoxel, ManifestData, Message, VoxelError, VoxelLoaded, MAX_TEXT_LEN,
};
use dray_runtime::{ActorRef, Delivery, LinkShape, Mailbox};
use dray_scene::db::manifest::MANIFEST_FILE;
use dray_scene::db::Database;
use std::path::PathBuf;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tokio::sync::Semaphore;
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

#[derive(Default)]
struct Counters {
    served: AtomicU64,
    bytes_served: AtomicU64,
    refused: AtomicU64,
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
    let (db, manifest) = tokio::task::spawn_blocking(move || {
        let db = Database::open(&path).map_err(|e| e.to_string())?;
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
    let db = Arc::new(db);
    let manifest = Arc::new(manifest);
    let disk = DiskQueue::new(opts.disk);
    let permits = Arc::new(Semaphore::new(opts.max_concurrent.max(1)));
    let counters = Arc::new(Counters::default());
    let me = mb.handle();
    let mut tasks = JoinSet::new();
    let mut summary = StoreSummary::default();

    let refuse = |tasks: &mut JoinSet<()>, me: &ActorRef, to: Address, id: u32, why: String| {
        counters.refused.fetch_add(1, Ordering::Relaxed);
        debug!(voxel = id, %to, %why, "refused");
        let me = me.clone();
        tasks.spawn(async move {
            let msg = Message::VoxelError(VoxelError {
                id,
                message: clip(why),
            });
            if let Err(e) = me.send(&to, msg).await {
                debug!(voxel = id, %to, error = %e, "could not send a refusal");
            }
        });
    };

    loop {
        while tasks.try_join_next().is_some() {}
        let Some(delivery) = mb.recv().await else {
            break;
        };
        let Delivery::Message { from, msg } = delivery else {
            continue;
        };
        match msg {
            Message::FetchVoxel(FetchVoxel { id }) => {
                if !opts.shard.owns(id) {
                    let why = format!(
                        "voxel {id} is not in shard {} served by {actor}",
                        opts.shard
                    );
                    refuse(&mut tasks, &me, from, id, why);
                } else if u64::from(id) >= voxels {
                    let why = format!("voxel {id}: no such voxel (the database has {voxels})");
                    refuse(&mut tasks, &me, from, id, why);
                } else {
                    let (db, permits, counters, me, disk) = (
                        db.clone(),
                        permits.clone(),
                        counters.clone(),
                        me.clone(),
                        disk.clone(),
                    );
                    tasks.spawn(async move {
                        // The permit is held until the answer is sent, so
                        // that at most `max_concurrent` blobs are in memory
                        // at once however slowly peers take them.
                        let (permit, read) = match permits.acquire_owned().await {
                            Ok(permit) => {
                                let bytes = db
                                    .manifest
                                    .voxels
                                    .get(id as usize)
                                    .map_or(0, |v| v.compressed_bytes);
                                let done = disk.map(|d| d.book(bytes));
                                let read = tokio::task::spawn_blocking(move || db.read_blob(id))
                                    .await
                                    .map_err(|e| format!("read task failed: {e}"))
                                    .and_then(|r| r.map_err(|e| e.to_string()));
                                if let Some(done) = done {
                                    tokio::time::sleep_until(done).await;
                                }
                                (Some(permit), read)
                            }
                            Err(_) => (None, Err("the store is stopping".into())),
                        };
                        let msg = match read {
                            Ok(blob) => {
                                counters.served.fetch_add(1, Ordering::Relaxed);
                                counters
                                    .bytes_served
                                    .fetch_add(blob.len() as u64, Ordering::Relaxed);
                                Message::VoxelLoaded(VoxelLoaded {
                                    id,
                                    data: Blob(blob),
                                })
                            }
                            Err(why) => {
                                warn!(voxel = id, error = %why, "cannot read a voxel");
                                counters.refused.fetch_add(1, Ordering::Relaxed);
                                Message::VoxelError(VoxelError {
                                    id,
                                    message: clip(why),
                                })
                            }
                        };
                        if let Err(e) = me.send(&from, msg).await {
                            debug!(voxel = id, to = %from, error = %e, "could not answer");
                        }
                        drop(permit);
                    });
                }
            }
            Message::FetchManifest(_) => {
                summary.manifests += 1;
                let (manifest, me) = (manifest.clone(), me.clone());
                tasks.spawn(async move {
                    let msg = Message::ManifestData(ManifestData {
                        data: Blob(manifest.as_ref().clone()),
                    });
                    if let Err(e) = me.send(&from, msg).await {
                        debug!(to = %from, error = %e, "could not send the manifest");
                    }
                });
            }
            Message::Ping(p) => {
                let me = me.clone();
                tasks.spawn(async move {
                    let _ = me.send(&from, Message::Pong(p)).await;
                });
            }
            Message::Shutdown(s) => {
                info!(%actor, reason = %s.reason, "store stopping");
                break;
            }
            other => debug!(%actor, kind = other.kind().name(), %from, "ignored"),
        }
    }
    permits.close();
    tasks.shutdown().await;
    summary.served = counters.served.load(Ordering::Relaxed);
    summary.bytes_served = counters.bytes_served.load(Ordering::Relaxed);
    summary.refused = counters.refused.load(Ordering::Relaxed);
    Ok(summary)
}
