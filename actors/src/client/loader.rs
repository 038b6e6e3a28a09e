//! The client's voxel loader: render threads ask for voxels through a
//! channel (each request with a oneshot for the answer); the loader, part
//! of the client's state, asks for one fetch per voxel however many packets
//! wait for it, at most `max_inflight` at once, counting those still being
//! decoded (the rest queue: packets' requests first, then a preload of the
//! whole model if asked for, hints last), has what comes back verified and
//! decoded on tokio's blocking pool, puts it in the cache and answers every
//! waiter. Fetches, decodes and reports are effects ([`Out`]) that the
//! client's run loop carries out.
//!
//! Faults: a blob that fails its checksum (or does not decode) is logged
//! and fetched again; a [`VoxelError`] is retried after a short delay,
//! each try asking the next store serving the voxel. After [`MAX_TRIES`]
//! failures (and at least one per such store) the voxel is lost: the
//! display hears of it once ([`VoxelLost`]), and by the
//! `clients.corrupt_voxel` choice every request for it gets a
//! [`LoadError`] (the run ends) or an empty voxel (the frame renders
//! without it). Fetches go to stores that are up: a fetch whose store
//! goes down is sent at once to another store serving the voxel
//! ([`Loader::peer_down`]); where none is up it waits for one to come back
//! ([`Loader::peer_up`]) or for its time out ([`FETCH_TIMEOUT`]), and is
//! then asked of the next store that serves the voxel; a prefetch that
//! times out is dropped.

use super::cache::VoxelCache;
use super::state::Out;
use crate::names::StoreRoutes;
use dray_config::CorruptVoxel;
use dray_protocol::{Address, Message, Name, VoxelError, VoxelLost};
use dray_scene::db::manifest::{Manifest, VoxelEntry};
use dray_scene::geometry::Aabb;
use dray_scene::voxel::Voxel;
use dray_trace::accel::{PreparedVoxel, VoxelRef, VoxelSource};
use dray_trace::tile::{LoadError, VoxelLoader};
use futures::future::BoxFuture;
use std::collections::{HashMap, HashSet, VecDeque};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use tokio::sync::{mpsc, oneshot};
use tokio::time::{Duration, Instant};
use tracing::{debug, warn};

/// Failed attempts (bad checksum, store error) before giving up on a voxel.
pub const MAX_TRIES: u32 = 4;
/// A fetch unanswered this long is sent again.
pub const FETCH_TIMEOUT: Duration = Duration::from_secs(10);
/// Wait before asking again after a [`VoxelError`].
pub const RETRY_DELAY: Duration = Duration::from_millis(100);
/// Most hinted voxels waiting to be prefetched.
pub const MAX_PREFETCH_QUEUE: usize = 16384;

/// Voxel bytes fetched: as they travelled (compressed) and after
/// decompression.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub(crate) struct Fetched {
    pub compressed: u64,
    pub raw: u64,
}

impl std::ops::AddAssign for Fetched {
    fn add_assign(&mut self, other: Fetched) {
        self.compressed += other.compressed;
        self.raw += other.raw;
    }
}

/// A voxel and the bytes fetched for it on behalf of this request (only
/// the request that caused the fetch is charged).
pub(crate) type Answer = Result<(Arc<PreparedVoxel>, Fetched), LoadError>;

/// A render thread's request.
pub(crate) struct LoadRequest {
    pub id: u32,
    pub reply: oneshot::Sender<Answer>,
}

/// What the render threads share: the cache and the way to the loader.
pub(crate) struct Shared {
    pub cache: Arc<VoxelCache>,
    pub requests: mpsc::UnboundedSender<LoadRequest>,
}

/// One tile's view of the loader: counts the bytes fetched for it.
pub(crate) struct TileLoader<'a> {
    pub shared: &'a Shared,
    pub bytes: AtomicU64,
    /// The same voxels' bytes after decompression.
    pub bytes_raw: AtomicU64,
}

impl VoxelSource for TileLoader<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        self.shared.cache.get(id).map(VoxelRef::Shared)
    }
}

impl VoxelLoader for TileLoader<'_> {
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>> {
        if let Some(v) = self.shared.cache.get(id) {
            return Box::pin(std::future::ready(Ok(v)));
        }
        let (tx, rx) = oneshot::channel();
        let sent = self
            .shared
            .requests
            .send(LoadRequest { id, reply: tx })
            .is_ok();
        Box::pin(async move {
            let stopping = || LoadError {
                voxel: id,
                message: "the client is stopping".into(),
            };
            if !sent {
                return Err(stopping());
            }
            let (v, fetched) = rx.await.map_err(|_| stopping())??;
            self.bytes.fetch_add(fetched.compressed, Ordering::Relaxed);
            self.bytes_raw.fetch_add(fetched.raw, Ordering::Relaxed);
            Ok(v)
        })
    }
}

/// A decoded voxel (or why not), from the blocking pool.
pub(crate) struct Decoded {
    pub id: u32,
    pub store: Address,
    pub bytes: u64,
    pub result: Result<Arc<PreparedVoxel>, String>,
}

/// What happens to voxels no store serves intact, and who hears of them.
#[derive(Clone, Debug)]
pub(crate) struct LostPolicy {
    /// Fail the requests (the run ends) or answer them with an empty voxel.
    pub mode: CorruptVoxel,
    /// Where [`VoxelLost`] goes (the display), as a control message.
    pub report_to: Address,
}

/// A voxel no store served intact: why, and in skip mode what stands in
/// for it.
struct Lost {
    message: String,
    empty: Option<Arc<PreparedVoxel>>,
}

/// A voxel with no triangles in `bounds`: what a lost voxel renders as.
pub(super) fn empty_voxel(id: u32, bounds: Aabb) -> PreparedVoxel {
    PreparedVoxel::new(
        id,
        &Voxel {
            bounds,
            positions: Vec::new(),
            normals: Vec::new(),
            colors: Vec::new(),
            triangles: Vec::new(),
            triangle_ids: Vec::new(),
            bvh: Vec::new(),
        },
    )
}

/// Checks a blob against its manifest entry, decodes and prepares it.
pub(crate) fn decode(
    id: u32,
    entry: &VoxelEntry,
    blob: &[u8],
) -> Result<Arc<PreparedVoxel>, String> {
    if blob.len() as u64 != entry.compressed_bytes {
        return Err(format!(
            "{} bytes, the manifest says {}",
            blob.len(),
            entry.compressed_bytes
        ));
    }
    // The header's checksum must be the manifest's, and decoding checks
    // the content against the header: one hash of the blob, not two.
    if dray_scene::voxel::stored_checksum(blob) != Some(entry.checksum) {
        return Err("checksum mismatch".into());
    }
    let v = Voxel::decode(blob).map_err(|e| match e {
        dray_scene::voxel::VoxelError::ChecksumMismatch { .. } => "checksum mismatch".to_string(),
        e => format!("cannot decode: {e}"),
    })?;
    Ok(Arc::new(PreparedVoxel::new(id, &v)))
}

#[derive(Debug)]
enum State {
    /// In a queue, not sent.
    Queued,
    /// Asked of `store` at `sent`.
    InFlight { store: Address, sent: Instant },
    /// Failed; ask again at this instant.
    Retry(Instant),
    /// Arrived, being decoded.
    Decoding,
}

struct Pending {
    state: State,
    waiters: Vec<oneshot::Sender<Answer>>,
    failures: u32,
    /// Fetches sent so far (each asks the next store serving the voxel).
    sends: u32,
    /// Asked for by a hint only (so far).
    prefetch: bool,
}

/// Counters for the summary.
#[derive(Clone, Debug, Default)]
pub(crate) struct LoaderStats {
    pub fetched: u64,
    pub bytes_fetched: u64,
    /// Decompressed bytes of the voxels fetched (the blobs' raw sizes).
    pub bytes_raw: u64,
    pub refetched: u64,
    pub prefetched: u64,
    pub preloaded: u64,
    pub retries: u64,
    /// Voxels no store served intact (rendered as empty in skip mode).
    pub lost: u64,
}

/// The loader's state, driven by the client's actor task.
pub(crate) struct Loader {
    manifest: Arc<Manifest>,
    cache: Arc<VoxelCache>,
    routes: StoreRoutes,
    max_inflight: usize,
    inflight: usize,
    pending: HashMap<u32, Pending>,
    queue: VecDeque<u32>,
    hints: VecDeque<u32>,
    /// Voxels still to preload (every voxel, in id order, until the cache
    /// is full), fetched when no request waits, before any hint.
    preload: VecDeque<u32>,
    /// Decoded bytes (the manifest's sizes) of the preloads sent so far.
    preload_planned: u64,
    ever_loaded: Vec<bool>,
    pub stats: LoaderStats,
    /// Bytes fetched that no tile has been charged with yet.
    unattributed: Fetched,
    policy: LostPolicy,
    lost: HashMap<u32, Lost>,
    /// Store nodes whose connection is down.
    down: HashSet<Name>,
}

impl Loader {
    /// Bytes fetched that no tile asked for (prefetches), since the last
    /// call.
    pub fn take_unattributed(&mut self) -> Fetched {
        std::mem::take(&mut self.unattributed)
    }

    pub fn new(
        manifest: Arc<Manifest>,
        cache: Arc<VoxelCache>,
        routes: StoreRoutes,
        max_inflight: usize,
        policy: LostPolicy,
    ) -> Loader {
        let n = manifest.voxels.len();
        Loader {
            manifest,
            cache,
            routes,
            max_inflight: max_inflight.max(1),
            inflight: 0,
            pending: HashMap::new(),
            queue: VecDeque::new(),
            hints: VecDeque::new(),
            preload: VecDeque::new(),
            preload_planned: 0,
            ever_loaded: vec![false; n],
            stats: LoaderStats::default(),
            unattributed: Fetched::default(),
            policy,
            lost: HashMap::new(),
            down: HashSet::new(),
        }
    }

    /// Failures after which voxel `id` is lost: [`MAX_TRIES`], and at
    /// least one try at each store serving it.
    fn tries(&self, id: u32) -> u32 {
        MAX_TRIES.max(u32::try_from(self.routes.owners(id)).unwrap_or(u32::MAX))
    }

    /// The answer for a lost voxel: its empty stand-in (made resident
    /// again, should the cache have dropped it) or the error.
    fn lost_answer(&self, id: u32) -> Option<Answer> {
        let l = self.lost.get(&id)?;
        Some(match &l.empty {
            Some(v) => Ok((self.cache.insert(v.clone()).0, Fetched::default())),
            None => Err(LoadError {
                voxel: id,
                message: l.message.clone(),
            }),
        })
    }

    /// A render thread asks for a voxel.
    pub fn request(&mut self, req: LoadRequest, out: &mut Vec<Out>) {
        let id = req.id;
        if let Some(v) = self.cache.get(id) {
            let _ = req.reply.send(Ok((v, Fetched::default())));
            return;
        }
        if id as usize >= self.manifest.voxels.len() {
            let _ = req.reply.send(Err(LoadError {
                voxel: id,
                message: format!(
                    "no such voxel (the manifest has {})",
                    self.manifest.voxels.len()
                ),
            }));
            return;
        }
        if let Some(answer) = self.lost_answer(id) {
            let _ = req.reply.send(answer);
            return;
        }
        match self.pending.get_mut(&id) {
            Some(p) => {
                p.waiters.push(req.reply);
                p.prefetch = false;
            }
            None => {
                self.pending.insert(
                    id,
                    Pending {
                        state: State::Queued,
                        waiters: vec![req.reply],
                        failures: 0,
                        sends: 0,
                        prefetch: false,
                    },
                );
                self.queue.push_back(id);
            }
        }
        self.pump(out);
    }

    /// The prefetcher hints at voxels needed soon: the newest hint
    /// replaces older ones.
    pub fn hint(&mut self, ids: &[u32], out: &mut Vec<Out>) {
        self.hints.clear();
        let n = self.manifest.voxels.len();
        for &id in ids.iter().take(MAX_PREFETCH_QUEUE) {
            if (id as usize) < n
                && !self.pending.contains_key(&id)
                && !self.cache.contains(id)
                && !self.lost.contains_key(&id)
            {
                self.hints.push_back(id);
            }
        }
        self.pump(out);
    }

    /// Fetches every voxel of the model, in id order, while the cache has
    /// room for it (by the manifest's decoded sizes, and by what the cache
    /// holds): warm caches before the first tile, for a model that fits.
    /// Requests from packets go first.
    pub fn preload(&mut self, out: &mut Vec<Out>) {
        self.preload = (0..self.manifest.voxels.len() as u32).collect();
        self.preload_planned = 0;
        self.pump(out);
    }

    /// Whether a preload is still going on (queued, in flight or being
    /// decoded). A hinted prefetch in flight counts too: both are fetches
    /// no packet waits for, and the client asks for tiles once neither is
    /// left.
    pub fn preloading(&self) -> bool {
        !self.preload.is_empty() || self.pending.values().any(|p| p.prefetch)
    }

    /// The next voxel to preload, if the cache has room for it.
    fn next_preload(&mut self) -> Option<u32> {
        while let Some(&id) = self.preload.front() {
            let size = self.manifest.voxels[id as usize].raw_bytes;
            let planned = self.preload_planned + size;
            if planned > self.cache.budget()
                || self.cache.resident_bytes() + size > self.cache.budget()
            {
                debug!(
                    left = self.preload.len(),
                    "the cache is full: the other voxels are fetched on demand"
                );
                self.preload.clear();
                return None;
            }
            self.preload.pop_front();
            if self.pending.contains_key(&id)
                || self.cache.contains(id)
                || self.lost.contains_key(&id)
            {
                continue;
            }
            self.preload_planned = planned;
            self.stats.preloaded += 1;
            return Some(id);
        }
        None
    }

    /// Sends queued fetches while slots are free: requests first, then
    /// the preload, hints when nothing else waits.
    fn pump(&mut self, out: &mut Vec<Out>) {
        while self.inflight < self.max_inflight {
            if let Some(id) = self.queue.pop_front() {
                if matches!(self.pending.get(&id), Some(p) if matches!(p.state, State::Queued)) {
                    self.send(id, out);
                }
                continue;
            }
            let id = match self.next_preload() {
                Some(id) => id,
                None => {
                    let Some(id) = self.hints.pop_front() else {
                        break;
                    };
                    if self.pending.contains_key(&id) || self.cache.contains(id) {
                        continue;
                    }
                    self.stats.prefetched += 1;
                    id
                }
            };
            self.pending.insert(
                id,
                Pending {
                    state: State::Queued,
                    waiters: Vec::new(),
                    failures: 0,
                    sends: 0,
                    prefetch: true,
                },
            );
            self.send(id, out);
        }
    }

    fn send(&mut self, id: u32, out: &mut Vec<Out>) {
        if let Some(p) = self.pending.get_mut(&id) {
            // The next store serving the voxel that is up, if any is.
            let owners = u32::try_from(self.routes.owners(id))
                .unwrap_or(u32::MAX)
                .max(1);
            let attempt = (0..owners)
                .map(|k| p.sends.wrapping_add(k))
                .find(|&a| !self.down.contains(&self.routes.store_for(id, a).node))
                .unwrap_or(p.sends);
            let store = self.routes.store_for(id, attempt).clone();
            p.sends = attempt.wrapping_add(1);
            if !matches!(p.state, State::InFlight { .. }) {
                self.inflight += 1;
            }
            p.state = State::InFlight {
                store: store.clone(),
                sent: Instant::now(),
            };
            out.push(Out::Fetch { to: store, id });
        }
    }

    fn leave_flight(&mut self, id: u32) {
        if let Some(p) = self.pending.get(&id) {
            if matches!(p.state, State::InFlight { .. } | State::Decoding) {
                self.inflight -= 1;
            }
        }
    }

    /// A store sent a blob: it is decoded off the actor task.
    pub fn loaded(&mut self, from: Address, id: u32, blob: Vec<u8>, out: &mut Vec<Out>) {
        let Some(p) = self.pending.get(&id) else {
            debug!(voxel = id, %from, "voxel nobody waits for (a duplicate)");
            return;
        };
        if matches!(p.state, State::Decoding) {
            debug!(voxel = id, %from, "duplicate voxel while decoding");
            return;
        }
        // Its slot stays taken while it decodes: `max_inflight` bounds the
        // blobs in memory, not only those on the wire, so a store faster
        // than the decoders cannot pile blobs up on the blocking pool.
        if let Some(p) = self.pending.get_mut(&id) {
            if !matches!(p.state, State::InFlight { .. }) {
                self.inflight += 1;
            }
            p.state = State::Decoding;
        }
        out.push(Out::Decode {
            id,
            store: from,
            entry: self.manifest.voxels[id as usize],
            blob,
        });
        self.pump(out);
    }

    /// The blocking pool finished a voxel.
    pub fn decoded(&mut self, d: Decoded, out: &mut Vec<Out>) {
        let Some(mut p) = self.pending.remove(&d.id) else {
            return;
        };
        if matches!(p.state, State::Decoding) {
            self.inflight = self.inflight.saturating_sub(1);
        }
        match d.result {
            Ok(v) => {
                let (v, freed) = self.cache.insert(v);
                let _ = freed;
                self.stats.fetched += 1;
                let raw = self
                    .manifest
                    .voxels
                    .get(d.id as usize)
                    .map_or(0, |entry| entry.raw_bytes);
                self.stats.bytes_fetched += d.bytes;
                self.stats.bytes_raw += raw;
                if let Some(e) = self.ever_loaded.get_mut(d.id as usize) {
                    if std::mem::replace(e, true) {
                        self.stats.refetched += 1;
                    }
                }
                let mut fetched = Fetched {
                    compressed: d.bytes,
                    raw,
                };
                for w in p.waiters {
                    let _ = w.send(Ok((v.clone(), std::mem::take(&mut fetched))));
                }
                // Prefetched before any packet asked: the next tile to
                // finish carries these bytes, so frames count every byte.
                self.unattributed += fetched;
            }
            Err(why) => {
                p.failures += 1;
                warn!(voxel = d.id, store = %d.store, error = %why, tries = p.failures,
                    "voxel failed verification; fetching it again");
                if p.failures >= self.tries(d.id) {
                    let why = format!("{why} ({} tries)", p.failures);
                    self.lose(d.id, p, &d.store, why, out);
                } else {
                    self.stats.retries += 1;
                    p.state = State::Queued;
                    self.pending.insert(d.id, p);
                    self.queue.push_front(d.id);
                }
            }
        }
        self.pump(out);
    }

    /// A store refused a voxel.
    pub fn refused(&mut self, from: Address, e: VoxelError, out: &mut Vec<Out>) {
        let id = e.id;
        match self.pending.get(&id) {
            Some(p) if matches!(p.state, State::InFlight { .. }) => {}
            _ => return,
        }
        self.leave_flight(id);
        let Some(mut p) = self.pending.remove(&id) else {
            return;
        };
        p.failures += 1;
        warn!(voxel = id, store = %from, error = %e.message, tries = p.failures, "store refused a voxel");
        if p.failures >= self.tries(id) {
            let why = format!("refused: {} ({} tries)", e.message, p.failures);
            self.lose(id, p, &from, why, out);
        } else if p.prefetch {
            let why = format!("{from} refused it: {}", e.message);
            self.fail(id, p, why);
        } else {
            self.stats.retries += 1;
            p.state = State::Retry(Instant::now() + RETRY_DELAY);
            self.pending.insert(id, p);
        }
        self.pump(out);
    }

    /// No store serves voxel `id` intact (`store` failed it last, for
    /// `reason`): the display hears of it, and its waiters, like every
    /// later request, get what the policy says.
    fn lose(&mut self, id: u32, p: Pending, store: &Address, reason: String, out: &mut Vec<Out>) {
        let skip = self.policy.mode == CorruptVoxel::Skip;
        let empty = skip.then(|| {
            let bounds = self.manifest.voxels[id as usize].bounds;
            Arc::new(empty_voxel(id, bounds))
        });
        if skip {
            warn!(voxel = id, %store, error = %reason,
                "no store serves this voxel intact: rendering it as empty (clients.corrupt_voxel = \"skip\")");
        } else {
            warn!(voxel = id, %store, error = %reason, "no store serves this voxel intact");
        }
        self.stats.lost += 1;
        let report = Message::VoxelLost(VoxelLost {
            id,
            store: store.node.clone(),
            reason: crate::store::clip(reason.clone()),
            skipped: skip,
        });
        let message = format!("{}: {reason}", store.node);
        out.push(Out::Control(self.policy.report_to.clone(), report));
        self.lost.insert(id, Lost { message, empty });
        for w in p.waiters {
            if let Some(answer) = self.lost_answer(id) {
                let _ = w.send(answer);
            }
        }
    }

    fn fail(&mut self, id: u32, p: Pending, message: String) {
        for w in p.waiters {
            let _ = w.send(Err(LoadError {
                voxel: id,
                message: message.clone(),
            }));
        }
    }

    /// A store node went down: its unanswered fetches go at once to
    /// another store serving their voxels, where one is up.
    pub fn peer_down(&mut self, node: &Name, out: &mut Vec<Out>) {
        if !self.routes.all().any(|a| &a.node == node) {
            return;
        }
        self.down.insert(node.clone());
        let routes = &self.routes;
        let down = &self.down;
        let elsewhere: Vec<u32> = self
            .pending
            .iter()
            .filter(|(&id, p)| {
                matches!(&p.state, State::InFlight { store, .. } if &store.node == node)
                    && (0..routes.owners(id) as u32)
                        .any(|a| !down.contains(&routes.store_for(id, a).node))
            })
            .map(|(&id, _)| id)
            .collect();
        if !elsewhere.is_empty() {
            warn!(store = %node, fetches = elsewhere.len(), "store is down: asking the others serving its voxels");
        }
        for id in elsewhere {
            self.stats.retries += 1;
            self.send(id, out);
        }
    }

    /// A store node came (back) up: fetches it never answered go again.
    pub fn peer_up(&mut self, node: &Name, out: &mut Vec<Out>) {
        self.down.remove(node);
        let again: Vec<u32> = self
            .pending
            .iter()
            .filter(
                |(_, p)| matches!(&p.state, State::InFlight { store, .. } if &store.node == node),
            )
            .map(|(&id, _)| id)
            .collect();
        if !again.is_empty() {
            debug!(store = %node, fetches = again.len(), "store is back: asking again");
        }
        for id in again {
            self.send(id, out);
        }
    }

    /// Retries whose delay is over, fetches that timed out.
    pub fn tick(&mut self, out: &mut Vec<Out>) {
        let now = Instant::now();
        let (mut again, mut dropped) = (Vec::new(), Vec::new());
        for (&id, p) in &mut self.pending {
            match p.state {
                State::Retry(at) if at <= now => {
                    p.state = State::Queued;
                    self.queue.push_back(id);
                }
                State::InFlight { sent, ref store } if now - sent >= FETCH_TIMEOUT => {
                    if p.prefetch {
                        // Nobody waits for it: not worth a slot.
                        debug!(voxel = id, %store, "prefetch timed out: dropped");
                        dropped.push(id);
                    } else {
                        // Asked again for as long as packets wait: a store
                        // that died comes back (the supervisor restarts
                        // it), and another serving the voxel is tried.
                        warn!(voxel = id, %store, "fetch timed out: asking again");
                        again.push(id);
                    }
                }
                _ => {}
            }
        }
        for id in dropped {
            self.leave_flight(id);
            self.pending.remove(&id);
        }
        for id in again {
            self.stats.retries += 1;
            self.send(id, out);
        }
        self.pump(out);
    }

    /// Answers every waiter with an error (the client stops).
    pub fn stop(&mut self) {
        for (id, p) in std::mem::take(&mut self.pending) {
            self.fail(id, p, "the client is stopping".into());
        }
        self.queue.clear();
        self.hints.clear();
        self.preload.clear();
        self.inflight = 0;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Shard;

    fn fetched(out: &mut Vec<Out>) -> Vec<u32> {
        out.drain(..)
            .map(|o| match o {
                Out::Fetch { id, .. } => id,
                other => panic!("unexpected {other:?}"),
            })
            .collect()
    }

    #[test]
    fn a_fetch_from_a_store_that_goes_down_goes_to_its_replica_at_once() {
        let t = dray_testkit::plant_db(20_000, 3, 512);
        let manifest = Arc::new(t.db.manifest.clone());
        let cache = Arc::new(VoxelCache::new(manifest.voxels.len(), u64::MAX));
        let (a, b, c) = (
            crate::names::store(0),
            crate::names::store(1),
            crate::names::store(2),
        );
        let half = |index| Shard { index, count: 2 };
        // a and b both serve the even voxels; c the odd ones.
        let routes = StoreRoutes::new(vec![
            (half(0), a.clone()),
            (half(0), b.clone()),
            (half(1), c.clone()),
        ])
        .unwrap();
        let policy = LostPolicy {
            mode: CorruptVoxel::Fail,
            report_to: crate::names::display(),
        };
        let mut loader = Loader::new(manifest, cache, routes, 8, policy);
        let mut out = Vec::new();
        let ask = |loader: &mut Loader, id: u32, out: &mut Vec<Out>| {
            let (reply, answer) = oneshot::channel();
            loader.request(LoadRequest { id, reply }, out);
            answer
        };
        let to = |out: &mut Vec<Out>| -> Vec<(Address, u32)> {
            out.drain(..)
                .map(|o| match o {
                    Out::Fetch { to, id } => (to, id),
                    other => panic!("unexpected {other:?}"),
                })
                .collect()
        };
        // Voxels 0 and 4 go one to each replica; 1 to c.
        let _w: Vec<_> = [0, 4, 1].map(|id| ask(&mut loader, id, &mut out)).into();
        let first = to(&mut out);
        let on_a: Vec<u32> = first
            .iter()
            .filter(|(s, _)| s == &a)
            .map(|&(_, id)| id)
            .collect();
        assert_eq!(on_a.len(), 1, "{first:?}");
        // a goes down: its fetch goes to b now, not after a time out.
        loader.peer_down(&a.node, &mut out);
        assert_eq!(to(&mut out), [(b.clone(), on_a[0])]);
        // While a is down, new fetches of its voxels go to b.
        let _w2: Vec<_> = [2, 6, 8].map(|id| ask(&mut loader, id, &mut out)).into();
        assert!(to(&mut out).iter().all(|(s, _)| s == &b));
        // c goes down: no other store serves its voxel, which waits.
        loader.peer_down(&c.node, &mut out);
        assert!(out.is_empty(), "{out:?}");
        loader.peer_up(&c.node, &mut out);
        assert_eq!(to(&mut out), [(c.clone(), 1)]);
        // a back: fetches spread over both replicas again.
        loader.peer_up(&a.node, &mut out);
        let _w3: Vec<_> = [10, 12, 14, 16]
            .map(|id| ask(&mut loader, id, &mut out))
            .into();
        assert!(to(&mut out).iter().any(|(s, _)| s == &a));
    }

    #[test]
    fn a_voxel_being_decoded_keeps_its_fetch_slot() {
        let t = dray_testkit::plant_db(20_000, 3, 512);
        let db = &t.db;
        assert!(db.manifest.voxels.len() >= 2);
        let manifest = Arc::new(db.manifest.clone());
        let cache = Arc::new(VoxelCache::new(manifest.voxels.len(), u64::MAX));
        let store = crate::names::store(0);
        let routes = StoreRoutes::new(vec![(Shard::ALL, store.clone())]).unwrap();
        let policy = LostPolicy {
            mode: CorruptVoxel::Fail,
            report_to: crate::names::display(),
        };
        let mut loader = Loader::new(manifest, cache, routes, 1, policy);
        let mut out = Vec::new();
        let (reply, mut answer) = oneshot::channel();
        loader.request(LoadRequest { id: 0, reply }, &mut out);
        let (reply, _answer1) = oneshot::channel();
        loader.request(LoadRequest { id: 1, reply }, &mut out);
        assert_eq!(fetched(&mut out), [0], "one slot: one fetch");
        loader.loaded(store.clone(), 0, db.read_blob(0).unwrap(), &mut out);
        let Some(Out::Decode {
            id,
            store,
            entry,
            blob,
        }) = out.pop()
        else {
            panic!("no decode: {out:?}");
        };
        assert!(
            out.is_empty(),
            "nothing sent while voxel 0 decodes: {out:?}"
        );
        let result = decode(id, &entry, &blob);
        let bytes = blob.len() as u64;
        loader.decoded(
            Decoded {
                id,
                store,
                bytes,
                result,
            },
            &mut out,
        );
        assert!(matches!(answer.try_recv(), Ok(Ok(_))));
        assert_eq!(fetched(&mut out), [1], "the slot is free once decoded");
    }
}
