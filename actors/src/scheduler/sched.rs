//! The Scheduler actor: cuts the frames the assigner releases into tiles and
//! hands them to clients on demand, with tile affinity, costliest tiles
//! first, and reassignment of the tiles of lost or silent clients.

use super::reproject;
use super::sectors;
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
    /// Give each client first the tiles it rendered in the previous frame
    /// (its voxel cache holds what they need); otherwise a uniformly random
    /// unassigned tile (the baseline).
    pub affinity: bool,
    /// With affinity, hand out a client's tiles (and stolen tiles) costliest
    /// first, by the previous frame's measured time of each tile.
    pub costliest_first: bool,
    /// With affinity, early in a frame the tiles go out in aligned blocks
    /// of at most this many pixels a side (see [`Frame::block`]); under
    /// twice `tile_size`, one tile at a time.
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
    /// Seed of the random choice without affinity.
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
/// A block of n tiles goes out as one assignment only while the frame
/// has at least `n × clients × BLOCK_GUIDE` fresh tiles left (guided
/// self-scheduling: a block is at most half of each client's share of
/// what is left).
const BLOCK_GUIDE: usize = 2;
/// Most credits one client may hold.
const MAX_CREDITS: u32 = 4096;

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum State {
    /// Never assigned: in a group queue (affinity) or the pool (random).
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
struct Holder {
    client: Name,
    /// When it was assigned.
    since: Instant,
    /// Tiles in the block it came in (1: alone), which the deadline
    /// allows for.
    block: u32,
}

struct Tile {
    state: State,
    /// Assignments not reported yet.
    outstanding: Vec<Holder>,
}

/// The last completed frame: what affinity and costliest-first go by.
struct Previous {
    number: u64,
    camera: Camera,
    grid: TileGrid,
    costs: Vec<u64>,
    owners: Vec<Option<Name>>,
    /// Per tile, the world positions of some of its hits.
    hits: Vec<Vec<Vec3>>,
    /// Per tile, whether its packets met a voxel their client lacked.
    missed: Vec<bool>,
}

struct Frame {
    number: u64,
    camera: Camera,
    settings: RenderSettings,
    grid: TileGrid,
    tiles: Vec<Tile>,
    /// Affinity: per previous owner, the fresh tiles, `pop()` giving the
    /// next one.
    groups: Vec<Vec<usize>>,
    /// Affinity: the fresh tiles nobody owned, by curve position.
    unowned: BTreeMap<u32, usize>,
    /// Affinity: the curve position of the tile each client got last (its
    /// region's growing edge).
    last: HashMap<Name, u32>,
    group_of: HashMap<Name, usize>,
    /// Each tile's position along the grid's space-filling curve.
    ranks: Vec<u32>,
    /// Affinity: per client, the curve positions of the tiles it owned in
    /// the previous frame and of those it was given in this one: the
    /// screen region its cache holds, which tiles it takes beyond its own
    /// should border.
    region: HashMap<Name, BTreeSet<u32>>,
    /// Without affinity: the fresh tiles.
    pool: Vec<usize>,
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
    /// Per tile, whether the previous frame rendered it without a miss
    /// (on the same grid): only such tiles go out in blocks, except to a
    /// client that holds the whole model.
    warm: Vec<bool>,
    /// Affinity: per tile, the client whose cache should hold what it
    /// shows (see [`Frame::reprojection`]).
    affine: Vec<Option<Name>>,
    /// Affinity: per tile, how many of the previous frame's hit samples
    /// of each client land in it.
    votes: Vec<Vec<(Name, u32)>>,
    /// Time of each tile done so far, for the deadline's median.
    times: Vec<u64>,
    median: (usize, u64),
    /// Per client, the tiles it holds (outstanding at it): kept with the
    /// tiles' holders, as the scheduler asks after every message.
    held: HashMap<Name, usize>,
    /// Affinity while no frame has completed yet: per tile, its client in
    /// the frame in flight when this one started (see
    /// [`Frame::clients_so_far`]).
    first_guide: Option<Vec<Option<Name>>>,
}

impl Frame {
    fn new(f: FrameStart, tile_size: u32) -> Frame {
        let grid = TileGrid::new(f.width, f.height, tile_size);
        let n = grid.count();
        Frame {
            number: f.frame,
            camera: f.camera,
            settings: f.settings,
            grid,
            tiles: (0..n)
                .map(|_| Tile {
                    state: State::Fresh,
                    outstanding: Vec::new(),
                })
                .collect(),
            groups: Vec::new(),
            unowned: BTreeMap::new(),
            last: HashMap::new(),
            group_of: HashMap::new(),
            ranks: grid.curve_ranks(),
            region: HashMap::new(),
            pool: Vec::new(),
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
            warm: vec![false; n],
            affine: vec![None; n],
            votes: vec![Vec::new(); n],
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

    /// The paper's reprojection affinity: each tile goes preferably to the
    /// client that rendered most of the previous frame's content that
    /// lands in it (the previous frame's hit samples projected into this
    /// frame's camera), as that client's cache holds it; where nothing
    /// lands (sky, or content just come into view) to the tile's previous
    /// owner. Content that moves across the screen keeps its client.
    ///
    /// Returns each tile's client and the samples of each client that
    /// land in it.
    #[allow(clippy::type_complexity)]
    fn reprojection(&self, prev: &Previous) -> (Vec<Option<Name>>, Vec<Vec<(Name, u32)>>) {
        let camera = kernel_camera(&self.camera, self.grid.width, self.grid.height).basis();
        let samples = prev
            .hits
            .iter()
            .zip(&prev.owners)
            .filter_map(|(hits, owner)| Some((hits, owner.as_ref()?)))
            .flat_map(|(hits, owner)| hits.iter().map(move |&h| (owner, h)));
        let votes = reproject::votes(&self.grid, &camera, samples);
        let same_grid = prev.grid == self.grid;
        let owners = votes
            .iter()
            .enumerate()
            .map(|(i, v)| match reproject::most(v) {
                Some(n) => Some((*n).clone()),
                None if same_grid => prev.owners[i].clone(),
                None => None,
            })
            .collect();
        let votes = votes
            .into_iter()
            .map(|v| v.into_iter().map(|(n, c)| (n.clone(), c)).collect())
            .collect();
        (owners, votes)
    }

    /// Each tile's client by sectors around the image's centre, among the
    /// clients that rendered `prev`, while the image streams from a point
    /// in view between `prev` and this frame (the camera travels roughly
    /// the way it looks; see [`sectors::assign`]); `None` otherwise, and
    /// reprojection decides.
    fn sector_owners(&self, prev: &Previous) -> Option<Vec<Option<Name>>> {
        let now = kernel_camera(&self.camera, self.grid.width, self.grid.height).basis();
        let then = kernel_camera(&prev.camera, prev.grid.width, prev.grid.height).basis();
        // Who had each tile before, on the same grid.
        let before: Vec<Option<&Name>> = if prev.grid == self.grid {
            prev.owners.iter().map(Option::as_ref).collect()
        } else {
            vec![None; self.tiles.len()]
        };
        let hits = prev.hits.iter().flatten().copied();
        let owners = sectors::assign(&self.grid, &then, &now, hits, &before)?;
        Some(owners.into_iter().map(|n| Some(n.clone())).collect())
    }

    /// Whether this frame continues from `prev` (see
    /// [`reproject::continues`]).
    fn continues_from(&self, prev: &Previous) -> bool {
        let now = kernel_camera(&self.camera, self.grid.width, self.grid.height).basis();
        let then = kernel_camera(&prev.camera, prev.grid.width, prev.grid.height).basis();
        reproject::continues(&then, &now, prev.hits.iter().flatten().copied())
    }

    /// Sorts the fresh tiles into queues: per affinity client when
    /// `affinity` (costliest first, or in index order), else one pool.
    ///
    /// Without a previous frame every tile is in the "nobody's" group, and
    /// clients take from it by their regions (see [`Frame::take_for`]).
    fn sort_fresh(&mut self, prev: Option<&Previous>, opts: &SchedulerOptions) {
        let fresh: Vec<usize> = (0..self.tiles.len())
            .filter(|&i| self.tiles[i].state == State::Fresh)
            .collect();
        if !opts.affinity {
            self.pool = fresh;
            return;
        }
        // After a cut (see `reproject::continues`) the previous frame's
        // content is mostly out of view: its misses and costs say nothing
        // about the new tiles, and its hits land in the wrong ones. Each
        // client keeps its part of the screen (its previous tiles), so that
        // the clients stay on the sides of the image whose content they
        // cached as the path goes on; regions grown afresh fetch far more
        // (`experiments/affinity-inside.toml`).
        let cut = prev.filter(|p| !self.continues_from(p));
        let guide = prev.filter(|_| cut.is_none());
        self.warm = match guide.filter(|p| p.grid == self.grid) {
            Some(p) => p.missed.iter().map(|&m| !m).collect(),
            None => vec![false; self.tiles.len()],
        };
        (self.affine, self.votes) = match guide {
            Some(p) => self.reprojection(p),
            None => {
                let affine = match cut {
                    Some(p) if p.grid == self.grid => Some(p.owners.clone()),
                    Some(_) => None,
                    // No frame has completed, but one is in flight: its
                    // clients, so that the first frames' regions agree
                    // (each grown on its own, the second frame's would
                    // disagree with the first's by chance and, with cold
                    // caches, fetch far more: `experiments/latency-hiding.toml`).
                    None => self.first_guide.clone(),
                };
                let n = self.tiles.len();
                (affine.unwrap_or_else(|| vec![None; n]), vec![Vec::new(); n])
            }
        };
        // While the image streams from a point in view (the camera travels
        // the way it looks), the clients' sectors around the image's
        // centre instead (see `sectors`). A client out of tiles still
        // takes by the votes.
        if let Some(owners) = guide.and_then(|p| self.sector_owners(p)) {
            self.affine = owners;
        }
        let costs = guide.filter(|p| p.grid == self.grid).map(|p| &p.costs);
        self.groups.clear();
        self.group_of.clear();
        self.region.clear();
        for i in 0..self.tiles.len() {
            // Whoever has it in this frame, else its affinity client.
            let owner = self.owners[i]
                .as_ref()
                .or(self.tiles[i].outstanding.first().map(|h| &h.client))
                .or(self.affine[i].as_ref());
            if let Some(o) = owner {
                self.region
                    .entry(o.clone())
                    .or_default()
                    .insert(self.ranks[i]);
            }
        }
        self.unowned.clear();
        for i in fresh {
            let Some(owner) = &self.affine[i] else {
                self.unowned.insert(self.ranks[i], i);
                continue;
            };
            let next = self.groups.len();
            let g = *self.group_of.entry(owner.clone()).or_insert(next);
            if g == next {
                self.groups.push(Vec::new());
            }
            self.groups[g].push(i);
        }
        for q in &mut self.groups {
            match costs {
                // Ascending cost, ties by descending index: pop() gives the
                // costliest, the lowest index first among equals.
                Some(costs) if opts.costliest_first => {
                    q.sort_unstable_by_key(|&i| (costs[i], std::cmp::Reverse(i)))
                }
                _ => q.sort_unstable_by(|a, b| b.cmp(a)),
            }
        }
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

    fn has_work_for(&self, c: &Name) -> bool {
        self.fresh_left > 0 || self.retry_for(c).is_some()
    }

    /// Whether client `c` has work here that is not another client's:
    /// a tile to retry, one of its own, or one nobody has.
    fn has_own_work_for(&self, c: &Name) -> bool {
        self.retry_for(c).is_some()
            || !self.unowned.is_empty()
            || self
                .group_of
                .get(c)
                .is_some_and(|&g| !self.groups[g].is_empty())
    }

    /// The tile client `c` should render next, taken out of its queue.
    fn pick(&mut self, c: &Name, affinity: bool, rng: &mut Rng) -> Option<usize> {
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
        if !affinity {
            if self.pool.is_empty() {
                return None;
            }
            let k = rng.below(self.pool.len() as u32) as usize;
            return Some(self.pool.swap_remove(k));
        }
        if let Some(&g) = self.group_of.get(c) {
            if let Some(i) = self.groups[g].pop() {
                return Some(i);
            }
        }
        // Beyond its own tiles: first those nobody had, else any other
        // client's; of those the one showing most of what this client
        // rendered before, then the one nearest to its region, so that
        // regions stay compact and only their borders move.
        self.take_for(c)
    }

    /// The tile beyond its own that client `c` takes, taken out of its
    /// queue. A client without a region yet takes the tile farthest from
    /// every other client's region, so that clients starting together grow
    /// their regions from far apart.
    fn take_for(&mut self, c: &Name) -> Option<usize> {
        fn distance(set: &BTreeSet<u32>, r: u32) -> u32 {
            let below = set.range(..=r).next_back().map(|&b| r - b);
            let above = set.range(r..).next().map(|&a| a - r);
            below.into_iter().chain(above).min().unwrap_or(u32::MAX)
        }
        let own = self.region.get(c).filter(|r| !r.is_empty());
        let others = || -> BTreeSet<u32> {
            self.region
                .iter()
                .filter(|(n, _)| *n != c)
                .flat_map(|(_, r)| r.iter().copied())
                .collect()
        };
        if !self.unowned.is_empty() {
            // Nobody's tiles show nothing anyone rendered: by position
            // alone. Nearest to the client's newest tile, found in the
            // ordered set (the first frame takes every tile this way).
            let rank = match own {
                Some(own) => {
                    let at = self
                        .last
                        .get(c)
                        .copied()
                        .unwrap_or_else(|| own.iter().copied().next().unwrap_or(0));
                    let below = self.unowned.range(..=at).next_back().map(|(&r, _)| r);
                    let above = self.unowned.range(at..).next().map(|(&r, _)| r);
                    match (below, above) {
                        (Some(b), Some(a)) if a - at < at - b => a,
                        (Some(b), _) => b,
                        (None, a) => a?,
                    }
                }
                None => {
                    let others = others();
                    *self
                        .unowned
                        .keys()
                        .min_by_key(|&&r| (u32::MAX - distance(&others, r), r))?
                }
            };
            return self.unowned.remove(&rank);
        }
        let votes = |i: usize| {
            self.votes[i]
                .iter()
                .find(|(n, _)| n == c)
                .map_or(0, |&(_, v)| v)
        };
        let others = if own.is_none() {
            others()
        } else {
            BTreeSet::new()
        };
        let (g, k) = (0..self.groups.len())
            .flat_map(|g| (0..self.groups[g].len()).map(move |k| (g, k)))
            .min_by_key(|&(g, k)| {
                let i = self.groups[g][k];
                let r = self.ranks[i];
                // Ties go to the lowest curve position.
                match own {
                    Some(own) => (std::cmp::Reverse(votes(i)), distance(own, r), r),
                    None => (std::cmp::Reverse(0), u32::MAX - distance(&others, r), r),
                }
            })?;
        Some(self.groups[g].remove(k))
    }

    /// Tile `i`, just picked for client `c`, with the fresh tiles of its
    /// aligned block that sit in the same queue, while the frame has many
    /// fresh tiles left (see [`BLOCK_GUIDE`]): one assignment, one
    /// message each way, for what would otherwise be up to 16. The block
    /// shrinks as the frame's fresh tiles run out, so that the last tiles
    /// still balance the clients' loads one by one. Blocks are made of
    /// tiles that the previous frame rendered without a miss, unless the
    /// camera cut since (see [`Frame::sort_fresh`]), or of any tiles for a
    /// client that holds the whole model (`holds_model`), which misses
    /// nothing: there a tile is quick and its messages weigh; where voxels
    /// were missing, tiles are slow and uneven, and they go one by one so
    /// that the clients share them evenly (in blocks, a cold walk's first
    /// frames would go out before any hit told where each client's content
    /// lies, and fetch more: `experiments/latency-hiding.toml`). Only a tile
    /// of `c`'s own queue or of nobody's comes with a block: a tile taken
    /// from another client's queue comes alone, as that client's cache
    /// holds what it shows. Returns the tiles, row by row, taken out of
    /// their queues.
    fn block(
        &mut self,
        i: usize,
        c: &Name,
        clients: usize,
        max_px: u32,
        holds_model: bool,
    ) -> Vec<usize> {
        if self.tiles[i].state != State::Fresh
            || !(holds_model || self.warm[i])
            || self.affine[i].as_ref().is_some_and(|o| o != c)
        {
            return vec![i];
        }
        let ts = self.grid.tile_size;
        let mut side = 1;
        while side * 2 * ts <= max_px {
            side *= 2;
        }
        while side > 1 {
            let n = (side * side) as usize;
            if self.fresh_left >= n * clients.max(1) * BLOCK_GUIDE {
                let block = self.grid.block_of(i, side);
                let queue = &self.affine[i];
                if block.iter().all(|&j| {
                    j == i
                        || (self.tiles[j].state == State::Fresh
                            && (holds_model || self.warm[j])
                            && self.affine[j] == *queue)
                }) {
                    // Out of the queue they share with `i`: `c`'s group, or
                    // nobody's.
                    let group = queue.as_ref().and_then(|o| self.group_of.get(o)).copied();
                    for &j in block.iter().filter(|&&j| j != i) {
                        match group {
                            Some(g) => self.groups[g].retain(|&k| k != j),
                            None => {
                                self.unowned.remove(&self.ranks[j]);
                            }
                        }
                    }
                    return block;
                }
            }
            side /= 2;
        }
        vec![i]
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
    rng: Rng,
    /// Clients in the order they first asked for work.
    clients: Vec<(Name, ClientState)>,
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
            opts,
            clients: Vec::new(),
            frames: BTreeMap::new(),
            prev: None,
            summary: SchedulerSummary::default(),
            rr: 0,
        }
    }

    fn client(&mut self, node: &Name) -> Option<&mut ClientState> {
        self.clients
            .iter_mut()
            .find(|(n, _)| n == node)
            .map(|(_, c)| c)
    }

    fn request_work(&mut self, from: Address, r: RequestWork) {
        match self.client(&from.node) {
            Some(c) => {
                c.credits = (c.credits + u32::from(r.slots)).min(MAX_CREDITS);
                c.holds_model = r.holds_model;
                c.addr = from;
            }
            None => self.clients.push((
                from.node.clone(),
                ClientState {
                    addr: from,
                    credits: u32::from(r.slots).min(MAX_CREDITS),
                    holds_model: r.holds_model,
                },
            )),
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
        let mut frame = Frame::new(f, self.opts.tile_size);
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
    }

    /// Hands out tiles while some client has credits and some frame has
    /// work: one tile per client per pass, oldest frame first.
    fn dispatch(&mut self, out: &mut Vec<Out>) {
        let now = Instant::now();
        let n = self.clients.len();
        if n == 0 {
            return;
        }
        loop {
            let mut progress = false;
            for k in 0..n {
                let ci = (self.rr + k) % n;
                let (node, state) = &mut self.clients[ci];
                if state.credits == 0 {
                    continue;
                }
                // With affinity, a client's own tiles come first, in the
                // oldest frame that has some, before another client's in an
                // older frame: taking another's tile fetches what its cache
                // lacks. A client with no tiles of its own in any open frame
                // releases the next frame early, so that it works ahead on
                // its own region rather than finish the others' (it still
                // takes one of theirs now, and theirs again once it has run
                // through its own in the next frame too).
                let own = if self.opts.affinity {
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
                        if self.opts.affinity {
                            let held: usize = self.frames.values().map(|f| f.held_by(node)).sum();
                            if held > 1 {
                                continue;
                            }
                        }
                        match self.frames.values().position(|f| f.has_work_for(node)) {
                            Some(at) => at,
                            None => continue,
                        }
                    }
                };
                let open = self.frames.len();
                let Some(frame) = self.frames.values_mut().nth(at) else {
                    continue;
                };
                if self.opts.affinity
                    && own.is_none()
                    && at + 1 == open
                    && !frame.announced
                    && frame.fresh_left > 0
                {
                    frame.announced = true;
                    out.push(Out::Assigned(frame.number));
                }
                let Some(i) = frame.pick(node, self.opts.affinity, &mut self.rng) else {
                    continue;
                };
                state.credits -= 1;
                progress = true;
                let tiles = if self.opts.affinity {
                    frame.block(i, node, n, self.opts.max_block_px, state.holds_model)
                } else {
                    vec![i]
                };
                for &i in &tiles {
                    if self.opts.affinity {
                        let rank = frame.ranks[i];
                        frame.region.entry(node.clone()).or_default().insert(rank);
                        frame.last.insert(node.clone(), rank);
                    }
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
                    },
                });
                if frame.fresh_left == 0 && !frame.announced {
                    frame.announced = true;
                    out.push(Out::Assigned(frame.number));
                }
            }
            self.rr = (self.rr + 1) % n;
            if !progress {
                return;
            }
        }
    }

    fn report(&mut self, node: &Name, r: TileReport, out: &mut Vec<Out>) {
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
        // Affinity at work: how many tiles their affinity client rendered.
        let kept = frame
            .affine
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
    }

    fn check_deadlines(&mut self) {
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
    use dray_protocol::examples::one_of_each;

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
        Frame::new(start(), 32)
    }

    /// Affinity, costliest first, blocks of up to 4 × 4 tiles of 32.
    fn options() -> SchedulerOptions {
        SchedulerOptions {
            tile_size: 32,
            affinity: true,
            costliest_first: true,
            max_block_px: 128,
            tile_deadline: Duration::from_secs(10),
            display: crate::names::display(),
            assigner: crate::names::assigner(),
            prefetcher: None,
            seed: 1,
        }
    }

    #[test]
    fn before_any_frame_completes_the_next_follows_the_one_in_flight() {
        let mut s = Scheduler::new(options());
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
        let f1 = &s.frames[&1];
        assert_eq!(f1.affine, expected, "each tile to its client in frame 0");
        assert!(f1.unowned.is_empty());
        assert!(f1.warm.iter().all(|&w| !w), "nothing known warm yet");
        // The very first frame had nothing to go by.
        assert!(s.frames[&0].affine.iter().all(Option::is_none));
    }

    /// The last frame before `f`, through `camera`, every tile rendered
    /// without a miss, its owners alternating in an order no region grown
    /// along the curve would give, its costs rising with the tile index,
    /// its hits 5 units in front of `camera`.
    fn previous(f: &Frame, camera: Camera) -> Previous {
        let n = f.tiles.len();
        let basis = kernel_camera(&camera, f.grid.width, f.grid.height).basis();
        let names = [
            Name::new("client-b").unwrap(),
            Name::new("client-a").unwrap(),
        ];
        Previous {
            number: f.number - 1,
            camera,
            grid: f.grid,
            costs: (0..n as u64).map(|i| 100 + i).collect(),
            owners: (0..n).map(|i| Some(names[i % 2].clone())).collect(),
            hits: (0..n)
                .map(|i| {
                    let r = f.grid.rect(i);
                    let d = basis.direction(r.x + r.w / 2, r.y + r.h / 2);
                    vec![basis.eye + d * 5.0]
                })
                .collect(),
            missed: vec![false; n],
        }
    }

    #[test]
    fn after_a_cut_each_tile_stays_with_its_client_in_index_order_and_cold() {
        let ahead = Camera {
            eye: [0.0, 0.0, 5.0],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        };
        let opts = options();
        let mut f = frame();
        f.camera = ahead;
        // The same view: the last frame guides this one. Its tiles are
        // warm (blocks may go out) and each queue gives its costliest first.
        f.sort_fresh(Some(&previous(&f, ahead)), &opts);
        assert!(f.warm.iter().all(|&w| w));
        for q in &f.groups {
            let costliest = q.iter().copied().max();
            assert_eq!(q.last().copied(), costliest, "{q:?}");
        }
        // The last frame looked a quarter turn away.
        let aside = Camera {
            look: [10.0, 0.0, 5.0],
            ..ahead
        };
        let prev = previous(&f, aside);
        f.sort_fresh(Some(&prev), &opts);
        assert_eq!(f.affine, prev.owners, "each tile with its last client");
        assert!(f.warm.iter().all(|&w| !w), "no blocks");
        for q in &f.groups {
            let lowest = q.iter().copied().min();
            assert_eq!(q.last().copied(), lowest, "index order: {q:?}");
        }
        assert_eq!(f.groups.iter().map(Vec::len).sum::<usize>(), f.tiles.len());
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
