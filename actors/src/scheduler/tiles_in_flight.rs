//! The Scheduler actor's frames in flight: it cuts the frames the assigner
//! releases into tiles and hands them to clients on demand, in the order
//! of the configured tile policy ([`super::policy`]), keeps each tile's
//! holders until one reports it, gives the tiles of lost or silent clients
//! to others, and sums each complete frame's statistics. The state is a
//! plain struct with handlers that return the messages to send ([`Out`]);
//! [`run_scheduler`] is the thin loop around them.

use super::policy::{self, FrameView, Policy, Previous, Queues, TilePolicy};
use super::tiles::TileGrid;
use crate::settings::kernel_camera;
use crate::ActorError;
use dray_protocol::{
    Address, AssignTile, Blob, BoundedVec, Camera, ClientFrameStats, FrameAssigned, FrameDone,
    FrameStart, FrameStats, Message, Name, PackedF32, PackedU32, RenderSettings, RequestWork,
    TileOwners, TileReport, MAX_STATS_CLIENTS, MAX_TILE_HITS,
};
use dray_runtime::{Delivery, Mailbox};
use dray_scene::rng::Rng;
use glam::Vec3;
use std::collections::{BTreeMap, BTreeSet, HashMap, VecDeque};
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// How the scheduler hands out tiles.
#[derive(Clone, Debug)]
pub struct SchedulerOptions {
    /// Tile side, pixels.
    pub tile_size: u32,
    /// Which policy hands out the tiles (see `scheduler::policy`).
    pub policy: TilePolicy,
    /// A knob of the affinity policy: a client's tiles (and tiles taken
    /// from others) go out costliest first, by the last frame's measured
    /// time of each tile.
    pub costliest_first: bool,
    /// A knob of the affinity policy: early in a frame the tiles go out in
    /// aligned blocks of at most this many pixels a side; under twice
    /// `tile_size`, one tile at a time.
    pub max_block_px: u32,
    /// A tile outstanding longer than this (and than 8 × the median tile
    /// time of its frame so far) is given to another client too.
    pub tile_deadline: Duration,
    /// Where [`FrameDone`] goes.
    pub display: Address,
    /// Where [`FrameAssigned`] goes.
    pub assigner: Address,
    /// Where [`TileOwners`] goes, if there is a prefetcher.
    pub prefetcher: Option<Address>,
    /// Seed of the random policy's choices.
    pub seed: u64,
}

/// What the scheduler did, returned when it stops.
#[derive(Clone, Debug, Default)]
pub struct SchedulerSummary {
    /// Frames completed.
    pub frames: u64,
    /// Tiles completed.
    pub tiles: u64,
    /// Tiles reassigned (client lost or past the deadline).
    pub reassigned: u64,
}

/// How often outstanding tiles are checked against the deadline.
const DEADLINE_CHECK: Duration = Duration::from_millis(20);
/// Most credits one client may hold.
const MAX_CREDITS: u32 = 4096;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(super) enum State {
    /// Never assigned: in its policy's queues.
    Fresh,
    /// Assigned, not reported.
    Out,
    /// Waiting in the retry queue for another client (it may still be
    /// outstanding at a silent client: first report wins).
    Retry,
    /// Reported.
    Done,
}

/// A client that has a tile to render.
pub(super) struct Holder {
    /// Who holds it.
    pub client: Name,
    /// When it was assigned.
    since: Instant,
    /// Tiles in the block it came in (1: alone), which the deadline
    /// allows for.
    block: u32,
}

/// A tile of a frame in flight.
pub(super) struct Tile {
    /// Where it is in its life.
    pub state: State,
    /// Assignments not reported yet.
    pub outstanding: Vec<Holder>,
}

struct Frame {
    number: u64,
    camera: Camera,
    settings: RenderSettings,
    /// Which sample of the camera the frame is (its tiles carry it).
    sample: u32,
    grid: TileGrid,
    tiles: Vec<Tile>,
    /// The fresh tiles, queued by the policy.
    queues: Box<dyn Queues>,
    /// Tiles to give to another client before any fresh one.
    retry: VecDeque<usize>,
    /// Tiles never assigned yet.
    fresh_left: usize,
    /// The assigner was told this frame is assigned (it then releases the
    /// next): every tile handed out, or a client ran out of its own.
    announced: bool,
    done: usize,
    first_assign: Option<Instant>,
    last_report: Option<Instant>,
    stats: FrameStats,
    clients: BTreeMap<Name, ClientFrameStats>,
    costs: Vec<u64>,
    owners: Vec<Option<Name>>,
    /// Per tile, the world positions of some of its hits, as reported.
    hits: Vec<Vec<Vec3>>,
    /// Per tile, whether its packets met a voxel their client lacked, as
    /// reported (for a block: any of its tiles).
    missed: Vec<bool>,
    /// Time of each tile done so far, for the deadline's median.
    times: Vec<u64>,
    median: (usize, u64),
    /// Per client, the tiles it holds (outstanding at it): kept with the
    /// tiles' holders, as the scheduler asks after every message.
    held: HashMap<Name, usize>,
    /// While no frame has completed yet: per tile, its client in the
    /// frame in flight when this one started (see
    /// [`Frame::clients_so_far`]).
    first_guide: Option<Vec<Option<Name>>>,
}

impl Frame {
    fn new(f: FrameStart, tile_size: u32, policy: &dyn Policy) -> Frame {
        let grid = TileGrid::new(f.width, f.height, tile_size);
        let n = grid.count();
        Frame {
            number: f.frame,
            camera: f.camera,
            settings: f.settings,
            sample: f.sample,
            grid,
            tiles: (0..n)
                .map(|_| Tile {
                    state: State::Fresh,
                    outstanding: Vec::new(),
                })
                .collect(),
            queues: policy.queues(&grid),
            retry: VecDeque::new(),
            fresh_left: n,
            announced: false,
            done: 0,
            first_assign: None,
            last_report: None,
            stats: FrameStats {
                tiles: n as u32,
                ..FrameStats::default()
            },
            clients: BTreeMap::new(),
            costs: vec![0; n],
            owners: vec![None; n],
            hits: vec![Vec::new(); n],
            missed: vec![false; n],
            times: Vec::new(),
            median: (0, 0),
            held: HashMap::new(),
            first_guide: None,
        }
    }

    /// Per tile, the client that rendered it or holds it so far.
    fn clients_so_far(&self) -> Vec<Option<Name>> {
        self.owners
            .iter()
            .zip(&self.tiles)
            .map(|(o, t)| {
                o.as_ref()
                    .or(t.outstanding.first().map(|h| &h.client))
                    .cloned()
            })
            .collect()
    }

    /// Sorts the fresh tiles into the policy's queues, judged from the
    /// last completed frame (`prev`).
    fn sort_fresh(&mut self, prev: Option<&Previous>, opts: &SchedulerOptions) {
        let view = FrameView {
            grid: &self.grid,
            camera: &self.camera,
            tiles: &self.tiles,
            owners: &self.owners,
            fresh_left: self.fresh_left,
            first_guide: self.first_guide.as_deref(),
        };
        self.queues.sort(&view, prev, opts);
    }
    fn retry_for(&self, c: &Name) -> Option<usize> {
        self.retry.iter().position(|&i| {
            self.tiles[i].state == State::Retry
                && !self.tiles[i].outstanding.iter().any(|h| h.client == *c)
        })
    }

    /// Tiles of this frame out at client `c`.
    fn held_by(&self, c: &Name) -> usize {
        let n = self.held.get(c).copied().unwrap_or(0);
        debug_assert_eq!(n, self.holding(c), "held count of {c}");
        n
    }

    /// Tiles with `c` among their holders, counted over every tile: what
    /// `held` keeps (checked in debug builds and tests).
    fn holding(&self, c: &Name) -> usize {
        self.tiles
            .iter()
            .filter(|t| t.outstanding.iter().any(|h| h.client == *c))
            .count()
    }

    /// Tile `i` goes out to `h.client`.
    fn hold(&mut self, i: usize, h: Holder) {
        *self.held.entry(h.client.clone()).or_default() += 1;
        self.tiles[i].outstanding.push(h);
    }

    /// Client `c` no longer holds tile `i` (it reported it, or is lost).
    /// Returns whether it did.
    fn release(&mut self, i: usize, c: &Name) -> bool {
        let t = &mut self.tiles[i];
        let before = t.outstanding.len();
        t.outstanding.retain(|h| h.client != *c);
        let released = t.outstanding.len() < before;
        if released {
            if let Some(n) = self.held.get_mut(c) {
                *n = n.saturating_sub(before - t.outstanding.len());
            }
        }
        released
    }

    /// Tile `i` is done: nobody holds it any more. A reassigned tile's
    /// other holders send pixels the display takes as duplicates and
    /// reports to no one, so without this they would count as holding it
    /// until the frame ends, and a client that seems to hold more than
    /// one tile never takes another client's (those of a lost client).
    /// Returns whether it had any.
    fn drop_holders(&mut self, i: usize) -> bool {
        let holders = std::mem::take(&mut self.tiles[i].outstanding);
        for h in &holders {
            if let Some(n) = self.held.get_mut(&h.client) {
                *n = n.saturating_sub(1);
            }
        }
        !holders.is_empty()
    }

    fn has_work_for(&self, c: &Name) -> bool {
        self.fresh_left > 0 || self.retry_for(c).is_some()
    }

    /// Whether client `c` has work here that is not another client's:
    /// a tile to retry, one of its own, or one nobody has.
    fn has_own_work_for(&self, c: &Name) -> bool {
        self.retry_for(c).is_some() || self.queues.has_own(c)
    }

    /// The tile client `c` should render next, taken out of its queue:
    /// a tile to retry first, else a fresh one by the policy.
    fn pick(&mut self, c: &Name, rng: &mut Rng) -> Option<usize> {
        while let Some(&i) = self.retry.front() {
            if self.tiles[i].state == State::Retry {
                break;
            }
            self.retry.pop_front();
        }
        if let Some(p) = self.retry_for(c) {
            return self.retry.remove(p);
        }
        if self.fresh_left == 0 {
            return None;
        }
        self.queues.pick(c, rng)
    }

    /// Tile `i`, just picked for client `c`, with the tiles the policy
    /// sends along in the same assignment, row by row.
    fn block(
        &mut self,
        i: usize,
        c: &Name,
        clients: usize,
        opts: &SchedulerOptions,
        holds_model: bool,
    ) -> Vec<usize> {
        let view = FrameView {
            grid: &self.grid,
            camera: &self.camera,
            tiles: &self.tiles,
            owners: &self.owners,
            fresh_left: self.fresh_left,
            first_guide: self.first_guide.as_deref(),
        };
        self.queues.block(i, c, &view, clients, opts, holds_model)
    }

    fn median_time(&mut self) -> u64 {
        if self.median.0 != self.times.len() && !self.times.is_empty() {
            let mut t = self.times.clone();
            let mid = t.len() / 2;
            let (_, m, _) = t.select_nth_unstable(mid);
            self.median = (self.times.len(), *m);
        }
        self.median.1
    }

    fn summary_messages(&self) -> (FrameStats, TileOwners) {
        let mut stats = self.stats.clone();
        stats.time_us = match (self.first_assign, self.last_report) {
            (Some(a), Some(b)) => b.saturating_duration_since(a).as_micros() as u64,
            _ => 0,
        };
        let mut clients: Vec<ClientFrameStats> = self.clients.values().cloned().collect();
        clients.truncate(MAX_STATS_CLIENTS);
        stats.clients = BoundedVec::new(clients).unwrap_or_default();
        let mut names: Vec<Name> = Vec::new();
        let mut index: HashMap<&Name, u32> = HashMap::new();
        // Tiles of clients past the message's limit count as unowned.
        let owners = self
            .owners
            .iter()
            .map(|o| match o {
                None => u32::MAX,
                Some(n) => match index.get(n) {
                    Some(&i) => i,
                    None if names.len() < MAX_STATS_CLIENTS => {
                        names.push(n.clone());
                        index.insert(n, names.len() as u32 - 1);
                        names.len() as u32 - 1
                    }
                    None => u32::MAX,
                },
            })
            .collect();
        let owners = TileOwners {
            frame: self.number,
            width: self.grid.width,
            height: self.grid.height,
            tile_size: self.grid.tile_size,
            owners: PackedU32(owners),
            clients: BoundedVec::new(names).unwrap_or_default(),
            // At most MAX_TILE_HITS each: they came in TileReports.
            hit_counts: Blob(self.hits.iter().map(|h| h.len() as u8).collect()),
            hits: PackedF32(
                self.hits
                    .iter()
                    .flatten()
                    .flat_map(|h| h.to_array())
                    .collect(),
            ),
            misses: stats.misses,
            // The scheduler's to fill in: it knows the clients.
            holds_model: BoundedVec::default(),
        };
        (stats, owners)
    }
}

struct ClientState {
    addr: Address,
    credits: u32,
    /// Its cache holds every voxel (as its last request said).
    holds_model: bool,
}

/// Something to send once the state is updated.
enum Out {
    Assign {
        node: Name,
        to: Address,
        msg: AssignTile,
    },
    Assigned(u64),
    Done(FrameDone, TileOwners),
}

struct Scheduler {
    opts: SchedulerOptions,
    policy: &'static dyn Policy,
    rng: Rng,
    /// Clients in the order they first asked for work.
    clients: Vec<(Name, ClientState)>,
    /// Where each client is in `clients`.
    client_index: HashMap<Name, usize>,
    /// The clients (their places in `clients`) with credits that
    /// [`Scheduler::dispatch`] visits, so that a message costs the same
    /// whether ten clients wait or a thousand.
    ready: BTreeSet<usize>,
    /// Clients with credits that got nothing when last visited, left out
    /// of the visits until something changes that could give them a tile
    /// ([`Scheduler::wake_all`], [`Scheduler::wake`]).
    waiting: BTreeSet<usize>,
    /// The clients of one pass of [`Scheduler::dispatch`] (kept to spare
    /// an allocation a message).
    pass: Vec<usize>,
    frames: BTreeMap<u64, Frame>,
    prev: Option<Previous>,
    summary: SchedulerSummary,
    /// Where the next round-robin pass starts.
    rr: usize,
}

impl Scheduler {
    fn new(opts: SchedulerOptions) -> Scheduler {
        Scheduler {
            rng: Rng::new(opts.seed),
            policy: policy::of(opts.policy),
            opts,
            clients: Vec::new(),
            client_index: HashMap::new(),
            ready: BTreeSet::new(),
            waiting: BTreeSet::new(),
            pass: Vec::new(),
            frames: BTreeMap::new(),
            prev: None,
            summary: SchedulerSummary::default(),
            rr: 0,
        }
    }

    fn request_work(&mut self, from: Address, r: RequestWork) {
        let at = match self.client_index.get(&from.node) {
            Some(&at) => {
                let c = &mut self.clients[at].1;
                c.credits = (c.credits + u32::from(r.slots)).min(MAX_CREDITS);
                c.holds_model = r.holds_model;
                c.addr = from;
                at
            }
            None => {
                let at = self.clients.len();
                self.client_index.insert(from.node.clone(), at);
                self.clients.push((
                    from.node.clone(),
                    ClientState {
                        addr: from,
                        credits: u32::from(r.slots).min(MAX_CREDITS),
                        holds_model: r.holds_model,
                    },
                ));
                at
            }
        };
        if self.clients[at].1.credits > 0 {
            self.waiting.remove(&at);
            self.ready.insert(at);
        }
    }

    /// Every waiting client is visited again: the frames changed (one
    /// started or ended, a tile went back for another client).
    fn wake_all(&mut self) {
        self.ready.append(&mut self.waiting);
    }

    /// Client `node` is visited again: the tiles it holds changed.
    fn wake(&mut self, node: &Name) {
        if let Some(&at) = self.client_index.get(node) {
            if self.waiting.remove(&at) {
                self.ready.insert(at);
            }
        }
    }

    fn frame_start(&mut self, f: FrameStart, out: &mut Vec<Out>) {
        let active = self.frames.get(&f.frame).map(|fr| fr.announced);
        if active.is_some() || self.prev.as_ref().is_some_and(|p| p.number >= f.frame) {
            debug!(frame = f.frame, "frame start for a known frame ignored");
            // The assigner waits for this frame to be assigned: if it is
            // (or is older than the last one done), say so again.
            if active != Some(false) {
                out.push(Out::Assigned(f.frame));
            }
            return;
        }
        let mut frame = Frame::new(f, self.opts.tile_size, self.policy);
        if self.prev.is_none() {
            frame.first_guide = self
                .frames
                .values()
                .next_back()
                .filter(|o| o.grid == frame.grid)
                .map(Frame::clients_so_far);
        }
        frame.sort_fresh(self.prev.as_ref(), &self.opts);
        debug!(
            frame = frame.number,
            tiles = frame.tiles.len(),
            "frame started"
        );
        self.frames.insert(frame.number, frame);
        self.wake_all();
    }

    /// Hands out tiles while some client has credits and some frame has
    /// work: one tile per client per pass, oldest frame first.
    fn dispatch(&mut self, out: &mut Vec<Out>) {
        let now = Instant::now();
        let n = self.clients.len();
        if n == 0 || self.ready.is_empty() {
            return;
        }
        // Between frames nobody gets anything: not worth a visit per client.
        if self
            .frames
            .values()
            .all(|f| f.fresh_left == 0 && f.retry.is_empty())
        {
            return;
        }
        loop {
            let mut progress = false;
            // The clients visited, from `rr` on round the circle; those
            // that get nothing wait (nothing else in this call gives them
            // work: other clients' tiles only take it).
            let mut pass = std::mem::take(&mut self.pass);
            pass.clear();
            pass.extend(
                self.ready
                    .range(self.rr..)
                    .chain(self.ready.range(..self.rr)),
            );
            let mut nothing = Vec::new();
            for &ci in &pass {
                let (node, state) = &mut self.clients[ci];
                if state.credits == 0 {
                    continue;
                }
                // Where tiles belong to clients (the affinity policy), a
                // client's own tiles come first, in the oldest frame that
                // has some, before another client's in an
                // older frame: taking another's tile fetches what its cache
                // lacks. A client with no tiles of its own in any open frame
                // releases the next frame early, so that it works ahead on
                // its own region rather than finish the others' (it still
                // takes one of theirs now, and theirs again once it has run
                // through its own in the next frame too).
                let claims = self.policy.claims_tiles();
                let own = if claims {
                    self.frames.values().position(|f| f.has_own_work_for(node))
                } else {
                    None
                };
                let at = match own {
                    Some(at) => at,
                    None => {
                        // Another client's tile only for a client about to
                        // run dry, with at most one tile left: a client with
                        // a queue of its own does not need it, and a tile
                        // taken from another's region fetches what its cache
                        // lacks, the more so the more tiles clients hold
                        // ahead (`experiments/affinity-inside.toml`).
                        if claims {
                            let held: usize = self.frames.values().map(|f| f.held_by(node)).sum();
                            if held > 1 {
                                nothing.push(ci);
                                continue;
                            }
                        }
                        match self.frames.values().position(|f| f.has_work_for(node)) {
                            Some(at) => at,
                            None => {
                                nothing.push(ci);
                                continue;
                            }
                        }
                    }
                };
                let open = self.frames.len();
                let Some(frame) = self.frames.values_mut().nth(at) else {
                    continue;
                };
                if claims
                    && own.is_none()
                    && at + 1 == open
                    && !frame.announced
                    && frame.fresh_left > 0
                {
                    frame.announced = true;
                    out.push(Out::Assigned(frame.number));
                }
                let Some(i) = frame.pick(node, &mut self.rng) else {
                    nothing.push(ci);
                    continue;
                };
                state.credits -= 1;
                progress = true;
                let tiles = frame.block(i, node, n, &self.opts, state.holds_model);
                for &i in &tiles {
                    frame.queues.handed_out(node, i);
                    let t = &mut frame.tiles[i];
                    if t.state == State::Fresh {
                        frame.fresh_left -= 1;
                    }
                    t.state = State::Out;
                    frame.hold(
                        i,
                        Holder {
                            client: node.clone(),
                            since: now,
                            block: tiles.len() as u32,
                        },
                    );
                }
                frame.first_assign.get_or_insert(now);
                out.push(Out::Assign {
                    node: node.clone(),
                    to: state.addr.clone(),
                    msg: AssignTile {
                        frame: frame.number,
                        tile: frame.grid.span(tiles[0], tiles[tiles.len() - 1]),
                        camera: frame.camera,
                        width: frame.grid.width,
                        height: frame.grid.height,
                        settings: frame.settings.clone(),
                        sample: frame.sample,
                    },
                });
                if frame.fresh_left == 0 && !frame.announced {
                    frame.announced = true;
                    out.push(Out::Assigned(frame.number));
                }
            }
            self.pass = pass;
            for ci in nothing {
                self.ready.remove(&ci);
                self.waiting.insert(ci);
            }
            self.ready.retain(|&ci| self.clients[ci].1.credits > 0);
            self.rr = (self.rr + 1) % n;
            if !progress {
                return;
            }
        }
    }

    fn report(&mut self, node: &Name, r: TileReport, out: &mut Vec<Out>) {
        // It holds fewer tiles now: it may take another client's.
        self.wake(node);
        let Some(frame) = self.frames.get_mut(&r.frame) else {
            debug!(frame = r.frame, client = %node, "report for an unknown or finished frame ignored");
            return;
        };
        let Some(tiles) = frame.grid.tiles_of(&r.tile) else {
            warn!(frame = r.frame, client = %node, tile = ?r.tile, "report for a tile that is not one of the frame's ignored");
            return;
        };
        let s = r.stats;
        let area: u64 = r.tile.area() as u64;
        let hits: Vec<Vec3> = r
            .hits
            .as_slice()
            .iter()
            .map(|&h| Vec3::from_array(h))
            // A peer's floats: only finite ones can be projected.
            .filter(|h| h.is_finite())
            .collect();
        // A block's hits go to the tile each shows in (its first tile if
        // it cannot be placed): per hit, the position of that tile in
        // `tiles`.
        let place: Vec<usize> = if tiles.len() == 1 {
            vec![0; hits.len()]
        } else {
            let cam = kernel_camera(&frame.camera, frame.grid.width, frame.grid.height).basis();
            hits.iter()
                .map(|&h| {
                    cam.project(h)
                        .filter(|&(x, y)| x >= 0.0 && y >= 0.0)
                        .and_then(|(x, y)| frame.grid.tile_at(x as u32, y as u32))
                        .and_then(|t| tiles.iter().position(|&i| i == t))
                        .unwrap_or(0)
                })
                .collect()
        };
        let mut done = 0u32;
        let mut others_released = false;
        for (k, &i) in tiles.iter().enumerate() {
            frame.release(i, node);
            let t = &mut frame.tiles[i];
            match t.state {
                State::Done => continue,
                State::Fresh => {
                    warn!(frame = r.frame, client = %node, tile = i, "report for a tile never assigned ignored");
                    continue;
                }
                State::Out | State::Retry => {}
            }
            t.state = State::Done;
            others_released |= frame.drop_holders(i);
            done += 1;
            frame.done += 1;
            // The block's time, shared by area.
            let share = (u128::from(s.time_us) * frame.grid.rect(i).area() as u128
                / u128::from(area.max(1))) as u64;
            frame.costs[i] = share;
            frame.times.push(share);
            frame.owners[i] = Some(node.clone());
            frame.missed[i] = s.misses > 0;
            let mine: Vec<Vec3> = hits
                .iter()
                .zip(&place)
                .filter(|&(_, &p)| p == k)
                .map(|(&h, _)| h)
                .collect();
            frame.hits[i] = spread(mine, MAX_TILE_HITS);
        }
        if done == 0 {
            return;
        }
        frame.last_report = Some(Instant::now());
        let fs = &mut frame.stats;
        // Sums of what a peer reports: saturating, as a hostile or broken
        // client may report anything.
        fs.rays = fs.rays.saturating_add(s.rays);
        fs.misses = fs.misses.saturating_add(u64::from(s.misses));
        fs.bytes_fetched = fs.bytes_fetched.saturating_add(s.bytes_fetched);
        fs.bytes_raw = fs.bytes_raw.saturating_add(s.bytes_raw);
        fs.link = fs.link.saturating_add(s.link);
        fs.voxels_touched = fs
            .voxels_touched
            .saturating_add(u64::from(s.voxels_touched));
        fs.stall_us = fs.stall_us.saturating_add(s.stall_us);
        let c = frame
            .clients
            .entry(node.clone())
            .or_insert_with(|| ClientFrameStats {
                node: node.clone(),
                tiles: 0,
                rays: 0,
                misses: 0,
                bytes_fetched: 0,
                stall_us: 0,
            });
        c.tiles += done;
        c.rays = c.rays.saturating_add(s.rays);
        c.misses = c.misses.saturating_add(u64::from(s.misses));
        c.bytes_fetched = c.bytes_fetched.saturating_add(s.bytes_fetched);
        c.stall_us = c.stall_us.saturating_add(s.stall_us);
        if frame.done == frame.tiles.len() {
            let number = frame.number;
            self.complete(number, out);
        }
        if others_released {
            self.wake_all();
        }
    }

    fn complete(&mut self, number: u64, out: &mut Vec<Out>) {
        let Some(frame) = self.frames.remove(&number) else {
            return;
        };
        if !frame.announced {
            out.push(Out::Assigned(number));
        }
        let (stats, mut owners) = frame.summary_messages();
        let whole: Vec<Name> = self
            .clients
            .iter()
            .filter(|(_, c)| c.holds_model)
            .map(|(n, _)| n.clone())
            .collect();
        owners.holds_model = BoundedVec::new(whole).unwrap_or_default();
        // The policy at work: how many tiles their predicted client
        // rendered.
        let kept = frame
            .queues
            .predicted()
            .iter()
            .zip(&frame.owners)
            .filter(|(a, b)| a.is_some() && a == b)
            .count();
        info!(
            frame = number,
            tiles = stats.tiles,
            kept,
            reassigned = stats.reassigned,
            rays = stats.rays,
            time_ms = stats.time_us as f64 / 1000.0,
            misses = stats.misses,
            "frame done"
        );
        self.summary.frames += 1;
        self.summary.tiles += u64::from(stats.tiles);
        self.summary.reassigned += u64::from(stats.reassigned);
        out.push(Out::Done(
            FrameDone {
                frame: number,
                stats,
            },
            owners,
        ));
        if self.prev.as_ref().is_none_or(|p| p.number < number) {
            self.prev = Some(Previous {
                number,
                camera: frame.camera,
                grid: frame.grid,
                costs: frame.costs,
                owners: frame.owners,
                hits: frame.hits,
                missed: frame.missed,
            });
            // Frames still being assigned go by the newest costs and owners.
            for f in self.frames.values_mut() {
                if f.fresh_left > 0 {
                    f.sort_fresh(self.prev.as_ref(), &self.opts);
                }
            }
        }
        // Its holders hold less, and the queues were sorted again.
        self.wake_all();
    }

    /// Puts tile `i` of `frame` back for another client.
    fn requeue(frame: &mut Frame, i: usize, why: &str, client: &Name) {
        frame.tiles[i].state = State::Retry;
        frame.retry.push_back(i);
        frame.stats.reassigned += 1;
        let r = frame.grid.rect(i);
        warn!(frame = frame.number, tile = i, x = r.x, y = r.y, %client, "tile reassigned: {why}");
    }

    fn client_lost(&mut self, node: &Name, why: &str) {
        let had = self.clients.len();
        self.clients.retain(|(n, _)| n != node);
        if had != self.clients.len() {
            // Places shift: index them again.
            self.client_index = (self.clients.iter().enumerate())
                .map(|(i, (n, _))| (n.clone(), i))
                .collect();
            self.ready = (0..self.clients.len())
                .filter(|&i| self.clients[i].1.credits > 0)
                .collect();
            self.waiting.clear();
            self.rr %= self.clients.len().max(1);
        }
        let mut returned = 0;
        for frame in self.frames.values_mut() {
            for i in 0..frame.tiles.len() {
                if frame.release(i, node)
                    && frame.tiles[i].outstanding.is_empty()
                    && frame.tiles[i].state == State::Out
                {
                    Self::requeue(frame, i, why, node);
                    returned += 1;
                }
            }
        }
        if had != self.clients.len() || returned > 0 {
            warn!(client = %node, tiles = returned, "client lost: {why}");
        }
        self.wake_all();
    }

    fn check_deadlines(&mut self) {
        // Also what keeps a waiting client from waiting past a change that
        // did not wake it.
        self.wake_all();
        let now = Instant::now();
        for frame in self.frames.values_mut() {
            if frame.tiles.len() - frame.fresh_left == frame.done {
                continue;
            }
            let median = frame.median_time().saturating_mul(8);
            for i in 0..frame.tiles.len() {
                let t = &frame.tiles[i];
                if t.state != State::Out {
                    continue;
                }
                let Some(h) = t.outstanding.iter().max_by_key(|h| h.since) else {
                    continue;
                };
                // A block takes as long as its tiles together.
                let median = Duration::from_micros(median.saturating_mul(u64::from(h.block)));
                let limit = self.opts.tile_deadline.max(median);
                if now.saturating_duration_since(h.since) > limit {
                    let who = h.client.clone();
                    let why = format!("not done after {} ms", limit.as_millis());
                    Self::requeue(frame, i, &why, &who);
                }
            }
        }
    }
}

/// At most `max` of `v`, spread evenly over it.
fn spread<T: Copy>(v: Vec<T>, max: usize) -> Vec<T> {
    if v.len() <= max {
        return v;
    }
    (0..max).map(|k| v[k * v.len() / max]).collect()
}

/// Runs the scheduler until [`Message::Shutdown`] (or the mailbox closes).
pub async fn run_scheduler(
    mut mb: Mailbox,
    opts: SchedulerOptions,
) -> Result<SchedulerSummary, ActorError> {
    let mut s = Scheduler::new(opts);
    let mut tick = tokio::time::interval(DEADLINE_CHECK);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    let mut out = Vec::new();
    loop {
        tokio::select! {
            biased;
            d = mb.recv() => match d {
                None => {
                    debug!("scheduler mailbox closed");
                    return Ok(s.summary);
                }
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::RequestWork(r) => s.request_work(from, r),
                    Message::FrameStart(f) => s.frame_start(f, &mut out),
                    // From the display, which has the pixels, or from the
                    // client itself; nobody else speaks for a client.
                    Message::TileReport(r)
                        if from.node == s.opts.display.node || from.node == r.client =>
                    {
                        let client = r.client.clone();
                        s.report(&client, r, &mut out)
                    }
                    Message::TileReport(r) => {
                        warn!(%from, client = %r.client, "tile report about another client ignored")
                    }
                    Message::Shutdown(r) => {
                        info!(reason = %r.reason, frames = s.summary.frames, "scheduler stops");
                        return Ok(s.summary);
                    }
                    other => debug!(kind = other.kind().name(), %from, "scheduler ignores"),
                },
                Some(Delivery::PeerDown { node, reason }) => {
                    s.client_lost(&node, &format!("connection lost ({reason})"))
                }
                Some(Delivery::PeerUp { .. }) => {}
            },
            _ = tick.tick() => s.check_deadlines(),
        }
        // Send what the state change produced; a client that cannot be
        // reached is lost, and its tiles go to the others.
        loop {
            s.dispatch(&mut out);
            if out.is_empty() {
                break;
            }
            for o in std::mem::take(&mut out) {
                send(&mut s, &mb, o).await;
            }
        }
    }
}

async fn send(s: &mut Scheduler, mb: &Mailbox, o: Out) {
    match o {
        Out::Assign { node, to, msg } => {
            if let Err(e) = mb.send(&to, Message::AssignTile(msg)).await {
                s.client_lost(&node, &format!("cannot send it a tile: {e}"));
            }
        }
        Out::Assigned(frame) => {
            let to = s.opts.assigner.clone();
            if let Err(e) = mb
                .send(&to, Message::FrameAssigned(FrameAssigned { frame }))
                .await
            {
                warn!(frame, %to, "cannot tell the frame assigner: {e}");
            }
        }
        Out::Done(done, owners) => {
            let to = s.opts.display.clone();
            let frame = done.frame;
            if let Err(e) = mb.send(&to, Message::FrameDone(done)).await {
                warn!(frame, %to, "cannot tell the display the frame is done: {e}");
            }
            if let Some(p) = s.opts.prefetcher.clone() {
                if let Err(e) = mb.send(&p, Message::TileOwners(owners)).await {
                    warn!(frame, to = %p, "cannot send the tile owners: {e}");
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::policy::tests::{options, walk_camera};
    use crate::scheduler::prefetch::recipients;
    use dray_protocol::examples::one_of_each;
    use dray_protocol::TileStats;

    /// The start of a frame of 4 × 2 tiles: the protocol's example.
    fn start() -> FrameStart {
        let start = one_of_each(16)
            .into_iter()
            .find_map(|m| match m {
                Message::FrameStart(f) => Some(f),
                _ => None,
            })
            .expect("the examples hold a frame start");
        FrameStart {
            width: 128,
            height: 64,
            ..start
        }
    }

    fn frame() -> Frame {
        Frame::new(start(), 32, policy::of(TilePolicy::Affinity))
    }

    #[test]
    fn before_any_frame_completes_the_next_follows_the_one_in_flight() {
        let opts = options();
        let mut s = Scheduler::new(opts.clone());
        let mut out = Vec::new();
        s.frame_start(
            FrameStart {
                frame: 0,
                ..start()
            },
            &mut out,
        );
        // Frame 0's tiles out to two clients, alternating (no region grown
        // along the curve looks so), one of them already rendered.
        let names = [
            Name::new("client-b").unwrap(),
            Name::new("client-a").unwrap(),
        ];
        let f0 = s.frames.get_mut(&0).expect("frame 0 open");
        let n = f0.tiles.len();
        for i in 0..n {
            let holder = Holder {
                client: names[i % 2].clone(),
                since: Instant::now(),
                block: 1,
            };
            f0.hold(i, holder);
        }
        f0.release(0, &names[0]);
        f0.owners[0] = Some(names[0].clone());
        let expected: Vec<Option<Name>> = (0..n).map(|i| Some(names[i % 2].clone())).collect();
        s.frame_start(
            FrameStart {
                frame: 1,
                ..start()
            },
            &mut out,
        );
        let f1 = s.frames.get_mut(&1).expect("frame 1 open");
        assert_eq!(
            f1.queues.predicted(),
            expected,
            "each tile to its client in frame 0"
        );
        let stranger = Name::new("client-z").unwrap();
        assert!(!f1.has_own_work_for(&stranger), "no tile is nobody's");
        for (i, c) in expected.iter().enumerate() {
            let c = c.as_ref().expect("every tile has a client");
            assert_eq!(
                f1.block(i, c, 2, &opts, false),
                vec![i],
                "nothing known warm yet: no blocks"
            );
        }
        // The very first frame had nothing to go by.
        assert!(s.frames[&0].queues.predicted().iter().all(Option::is_none));
    }

    /// Drives `s` through frame `number` seen through `camera` on a
    /// 256 × 128 image: every tile handed out to the clients that asked,
    /// then reported with hits on the plane z = 0 (a wall the camera looks
    /// at). Returns each tile's client in its first assignment and what
    /// the scheduler sent the prefetcher when the frame completed.
    fn run_frame(s: &mut Scheduler, number: u64, camera: Camera) -> (Vec<Name>, TileOwners) {
        let mut out = Vec::new();
        let f = FrameStart {
            frame: number,
            camera,
            width: 256,
            height: 128,
            ..start()
        };
        let grid = TileGrid::new(f.width, f.height, s.opts.tile_size);
        let basis = kernel_camera(&camera, f.width, f.height).basis();
        s.frame_start(f, &mut out);
        s.dispatch(&mut out);
        let mut first: Vec<Option<Name>> = vec![None; grid.count()];
        let mut owners = None;
        for o in std::mem::take(&mut out) {
            let Out::Assign { node, msg, .. } = o else {
                continue;
            };
            let tiles = grid.tiles_of(&msg.tile).expect("the frame's tiles");
            assert_eq!(
                (msg.frame, msg.sample),
                (number, start().sample),
                "the frame's sample"
            );
            for &i in &tiles {
                first[i].get_or_insert_with(|| node.clone());
            }
            // Hits at the centres of the assignment's tiles.
            let hits: Vec<[f32; 3]> = tiles
                .iter()
                .map(|&i| {
                    let r = grid.rect(i);
                    let d = basis.direction(r.x + r.w / 2, r.y + r.h / 2);
                    (basis.eye + d * (basis.eye.z / -d.z)).to_array()
                })
                .collect();
            let report = TileReport {
                client: node.clone(),
                frame: number,
                tile: msg.tile,
                stats: TileStats {
                    time_us: 100 * tiles.len() as u64,
                    ..TileStats::default()
                },
                hits: BoundedVec::new(hits).expect("few hits"),
            };
            s.report(&node, report, &mut out);
            for o in std::mem::take(&mut out) {
                if let Out::Done(_, o) = o {
                    owners = Some(o);
                }
            }
        }
        let first = first
            .into_iter()
            .map(|c| c.expect("every tile handed out"))
            .collect();
        (first, owners.expect("the frame completed"))
    }

    #[test]
    fn the_prefetchers_recipients_are_the_clients_the_scheduler_assigns() {
        let mut s = Scheduler::new(SchedulerOptions {
            max_block_px: 64,
            ..options()
        });
        for i in 0..3 {
            s.request_work(
                crate::names::client(i),
                RequestWork {
                    slots: 1000,
                    holds_model: false,
                },
            );
        }
        // Walking towards the wall (sectors), sliding along it
        // (reprojection), then a quarter turn (a cut: each tile stays with
        // its client).
        let slide = Camera {
            eye: [1.0, 0.0, 5.0],
            look: [1.0, 0.0, 0.0],
            ..walk_camera(5.0)
        };
        let turned = Camera {
            look: [11.0, 0.0, 5.0],
            ..slide
        };
        let path = [walk_camera(6.0), walk_camera(5.0), slide, turned];
        let (_, mut owners) = run_frame(&mut s, 0, path[0]);
        let grid = TileGrid::new(256, 128, 32);
        let mut rules = Vec::new();
        for (k, pair) in path.windows(2).enumerate() {
            let (then, now) = (pair[0], pair[1]);
            let hinted: Vec<Option<Name>> =
                recipients(&owners, Some(&then), &now, &grid, TilePolicy::Affinity)
                    .into_iter()
                    .map(|c| owners.clients.as_slice().get(c as usize).cloned())
                    .collect();
            let prev = s.prev.as_ref().expect("a frame completed");
            let basis = kernel_camera(&now, 256, 128).basis();
            let last = prev.last_frame();
            let p = policy::predict_owners(TilePolicy::Affinity, &grid, &basis, &last);
            let before: Vec<Option<&Name>> = prev.owners.iter().map(Option::as_ref).collect();
            let then_basis = last.camera.expect("the scheduler knows its cameras");
            let hits = prev.hits.iter().flatten().copied();
            let by_sectors =
                policy::sectors::assign(&grid, &then_basis, &basis, hits, &before).is_some();
            rules.push((p.guides, by_sectors));
            let (assigned, next) = run_frame(&mut s, k as u64 + 1, now);
            let assigned: Vec<Option<Name>> = assigned.into_iter().map(Some).collect();
            assert_eq!(hinted, assigned, "frame {}", k + 1);
            owners = next;
        }
        // Which rule decided each step: (no cut, by sectors).
        assert_eq!(rules, [(true, true), (true, false), (false, false)]);
    }

    #[test]
    fn a_reassigned_tile_done_by_one_holder_is_held_by_none() {
        // One tile per assignment.
        let mut s = Scheduler::new(SchedulerOptions {
            max_block_px: 0,
            ..options()
        });
        let clients: Vec<Address> = (0..3).map(crate::names::client).collect();
        for c in &clients {
            let slots = 1000;
            let holds_model = false;
            s.request_work(c.clone(), RequestWork { slots, holds_model });
        }
        run_frame(&mut s, 0, walk_camera(6.0));
        for (_, c) in &mut s.clients {
            c.credits = 0;
        }
        let mut out = Vec::new();
        let f1 = FrameStart {
            frame: 1,
            camera: walk_camera(5.0),
            width: 256,
            height: 128,
            ..start()
        };
        s.frame_start(f1, &mut out);
        let (a, b) = (&clients[0], &clients[1]);
        // Two tiles out to a, which goes silent: past the deadline they go
        // to b as well, and b renders them first.
        let slots = 2;
        s.request_work(
            a.clone(),
            RequestWork {
                slots,
                holds_model: false,
            },
        );
        s.dispatch(&mut out);
        let frame = s.frames.get_mut(&1).unwrap();
        let late: Vec<usize> = (0..frame.tiles.len())
            .filter(|&i| frame.tiles[i].state == State::Out)
            .collect();
        assert_eq!(late.len(), 2, "a's two tiles out");
        for &i in &late {
            Scheduler::requeue(frame, i, "late", &a.node);
        }
        s.request_work(
            b.clone(),
            RequestWork {
                slots,
                holds_model: false,
            },
        );
        out.clear();
        s.dispatch(&mut out);
        let mut to_b = Vec::new();
        for o in out.drain(..) {
            if let Out::Assign { node, msg, .. } = o {
                assert_eq!(node, b.node, "only b asked");
                to_b.push(msg.tile);
            }
        }
        let grid = TileGrid::new(256, 128, s.opts.tile_size);
        let retried: Vec<usize> = to_b
            .iter()
            .flat_map(|t| grid.tiles_of(t).unwrap())
            .collect();
        assert_eq!(retried, late, "the late tiles go to b first");
        assert_eq!(s.frames[&1].held_by(&a.node), 2);
        for tile in to_b {
            let stats = TileStats::default();
            let hits = BoundedVec::default();
            let (client, frame) = (b.node.clone(), 1);
            s.report(
                &b.node,
                TileReport {
                    client,
                    frame,
                    tile,
                    stats,
                    hits,
                },
                &mut out,
            );
        }
        let frame = &s.frames[&1];
        // a's copies are duplicates the display reports to no one.
        assert_eq!(
            frame.held_by(&a.node),
            0,
            "a holds nothing once b's are done"
        );
        assert_eq!(frame.held_by(&b.node), 0);
        assert!(late.iter().all(|&i| frame.tiles[i].outstanding.is_empty()));
    }

    #[test]
    fn held_counts_follow_the_tiles_holders() {
        // Tiles going out (a tile held by two clients once reassigned)
        // and coming back, in a scrambled order: the kept count of each
        // client is the count over the tiles after every step.
        let mut f = frame();
        let clients: Vec<Name> = ["client-0", "client-1", "client-2"]
            .iter()
            .map(|n| Name::new(n).unwrap())
            .collect();
        let n = f.tiles.len();
        let mut x = 7u32;
        for step in 0..400 {
            x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
            let i = (x >> 8) as usize % n;
            let c = &clients[(x >> 20) as usize % clients.len()];
            let holds = f.tiles[i].outstanding.iter().any(|h| h.client == *c);
            if holds {
                assert!(f.release(i, c), "step {step}");
            } else if x.is_multiple_of(3) {
                assert!(!f.release(i, c), "step {step}: {c} did not hold tile {i}");
            } else {
                f.hold(
                    i,
                    Holder {
                        client: c.clone(),
                        since: Instant::now(),
                        block: 1,
                    },
                );
            }
            for c in &clients {
                assert_eq!(f.held_by(c), f.holding(c), "step {step}, {c}");
            }
        }
        assert!(clients.iter().any(|c| f.held_by(c) > 0));
    }
}
