//! The affinity policy (the default): each tile preferably to the client
//! whose voxel cache already holds what it shows.
//!
//! Its prediction ([`Affinity::predict`]) goes, in this order: after a cut
//! (the camera turned by more than half the field of view, or moved beyond
//! everything the last frame showed; [`reproject::continues`]) each tile to
//! its last client; while the image streams from a point in view (the
//! camera travels the way it looks) by sectors around the image's centre
//! ([`sectors::assign`]); else to the client whose content of the last
//! frame lands in the tile most ([`reproject::votes`]); else to the tile's
//! last client.
//!
//! Its queues ([`ClientQueues`]) hold per predicted client its fresh tiles,
//! costliest first by the last frame's times (`costliest_first`), and the
//! tiles nobody is predicted for. A client out of its own takes nobody's
//! tiles nearest its region, then another client's that shows most of its
//! content or borders its region. Early in a frame a tile of its own goes
//! out with the rest of its aligned block (up to `max_block_px` a side)
//! where the last frame rendered those tiles without a miss.

use super::{reproject, sectors, FrameView, LastFrame, Policy, Prediction, Previous, Queues};
use crate::scheduler::tiles::TileGrid;
use crate::scheduler::tiles_in_flight::{SchedulerOptions, State};
use crate::settings::kernel_camera;
use dray_protocol::Name;
use dray_scene::rng::Rng;
use dray_trace::camera::CameraBasis;
use std::collections::{BTreeMap, BTreeSet, HashMap};

/// A block of n tiles goes out as one assignment only while the frame
/// has at least `n × clients × BLOCK_GUIDE` fresh tiles left (guided
/// self-scheduling: a block is at most half of each client's share of
/// what is left).
const BLOCK_GUIDE: usize = 2;

/// The affinity policy.
pub(super) struct Affinity;

impl Policy for Affinity {
    /// The paper's reprojection affinity, with sectors while the camera
    /// travels and each tile's last client after a cut (see the module
    /// docs for the order).
    fn predict(&self, grid: &TileGrid, now: &CameraBasis, last: &LastFrame<'_>) -> Prediction {
        let n = grid.count();
        let hits = || last.hits.iter().flatten().copied();
        // After a cut the last frame's content is mostly out of view: its
        // hits land in the wrong tiles, and each client keeps its part of
        // the screen, so that the clients stay on the sides of the image
        // whose content they cached as the path goes on; regions grown
        // afresh fetch far more (`experiments/affinity-inside.toml`).
        if let Some(then) = &last.camera {
            if !reproject::continues(then, now, hits()) {
                return Prediction {
                    owners: (0..n).map(|i| last.owner_on(grid, i).cloned()).collect(),
                    ..Prediction::none(n)
                };
            }
        }
        let samples = last
            .hits
            .iter()
            .zip(last.owners)
            .filter_map(|(hits, owner)| Some((hits, owner.as_ref()?)))
            .flat_map(|(hits, owner)| hits.iter().map(move |&h| (owner, h)));
        let votes = reproject::votes(grid, now, samples);
        // Where nothing lands (sky, or content just come into view), the
        // tile's last client.
        let mut owners: Vec<Option<Name>> = votes
            .iter()
            .enumerate()
            .map(|(i, v)| match reproject::most(v) {
                Some(n) => Some((*n).clone()),
                None => last.owner_on(grid, i).cloned(),
            })
            .collect();
        // While the image streams from a point in view, the clients'
        // sectors around the image's centre instead. A client out of tiles
        // still takes by the votes.
        if let Some(then) = &last.camera {
            let before: Vec<Option<&Name>> = (0..n).map(|i| last.owner_on(grid, i)).collect();
            if let Some(by) = sectors::assign(grid, then, now, hits(), &before) {
                owners = by.into_iter().map(|n| Some(n.clone())).collect();
            }
        }
        let votes = votes
            .into_iter()
            .map(|v| v.into_iter().map(|(n, c)| (n.clone(), c)).collect())
            .collect();
        Prediction {
            owners,
            votes,
            guides: true,
        }
    }

    fn claims_tiles(&self) -> bool {
        true
    }

    fn queues(&self, grid: &TileGrid) -> Box<dyn Queues> {
        Box::new(ClientQueues::of(grid))
    }
}

/// A frame's fresh tiles, queued per predicted client.
pub(super) struct ClientQueues {
    /// Per predicted client, its fresh tiles, `pop()` giving the next one.
    groups: Vec<Vec<usize>>,
    group_of: HashMap<Name, usize>,
    /// The fresh tiles nobody is predicted for, by curve position.
    unowned: BTreeMap<u32, usize>,
    /// The curve position of the tile each client got last (its region's
    /// growing edge).
    last: HashMap<Name, u32>,
    /// Each tile's position along the grid's space-filling curve.
    ranks: Vec<u32>,
    /// Per client, the curve positions of the tiles it owned in the last
    /// frame and of those it was given in this one: the screen region its
    /// cache holds, which tiles it takes beyond its own should border.
    region: HashMap<Name, BTreeSet<u32>>,
    /// Per tile, the client predicted to render it.
    affine: Vec<Option<Name>>,
    /// Per tile, how many of the last frame's hit samples of each client
    /// land in it.
    votes: Vec<BTreeMap<Name, u32>>,
    /// Per client, the tiles with some of its votes.
    voted: HashMap<Name, Vec<usize>>,
    /// The tiles in `groups`, by curve position: a client out of tiles
    /// finds the one nearest its region here rather than by measuring
    /// every queued tile (a cost per steal that grows with the tiles, and
    /// steals grow with the clients). Made at a frame's first steal, and
    /// kept from then on.
    queued: Option<BTreeMap<u32, usize>>,
    /// Per tile, whether the last frame rendered it without a miss (on the
    /// same grid): only such tiles go out in blocks, except to a client
    /// that holds the whole model.
    warm: Vec<bool>,
}

impl Queues for ClientQueues {
    /// Without a last frame (or its guide) every tile is nobody's, and
    /// clients take them by their regions (see [`ClientQueues::take_for`]).
    fn sort(&mut self, frame: &FrameView<'_>, prev: Option<&Previous>, opts: &SchedulerOptions) {
        let n = frame.tiles.len();
        let prediction = match (prev, frame.first_guide) {
            (Some(p), _) => {
                let now = kernel_camera(frame.camera, frame.grid.width, frame.grid.height).basis();
                Affinity.predict(frame.grid, &now, &p.last_frame())
            }
            // No frame has completed, but one is in flight: its clients,
            // so that the first frames' regions agree (each grown on its
            // own, the second frame's would disagree with the first's by
            // chance and, with cold caches, fetch far more:
            // `experiments/latency-hiding.toml`).
            (None, Some(guide)) => Prediction {
                owners: guide.to_vec(),
                ..Prediction::none(n)
            },
            (None, None) => Prediction::none(n),
        };
        // After a cut the last frame's misses and costs say nothing about
        // the new tiles.
        let guide = prev.filter(|p| prediction.guides && p.grid == *frame.grid);
        self.warm = match guide {
            Some(p) => p.missed.iter().map(|&m| !m).collect(),
            None => vec![false; n],
        };
        self.affine = prediction.owners;
        self.votes = prediction.votes;
        self.voted.clear();
        for (i, v) in self.votes.iter().enumerate() {
            for (c, _) in v.iter().filter(|(_, &k)| k > 0) {
                match self.voted.get_mut(c) {
                    Some(tiles) => tiles.push(i),
                    None => {
                        self.voted.insert(c.clone(), vec![i]);
                    }
                }
            }
        }
        let costs = guide.map(|p| &p.costs);
        self.groups.clear();
        self.group_of.clear();
        self.region.clear();
        for i in 0..n {
            // Whoever has it in this frame, else its predicted client.
            let owner = frame.owners[i]
                .as_ref()
                .or(frame.tiles[i].outstanding.first().map(|h| &h.client))
                .or(self.affine[i].as_ref());
            if let Some(o) = owner {
                self.region
                    .entry(o.clone())
                    .or_default()
                    .insert(self.ranks[i]);
            }
        }
        self.unowned.clear();
        for i in (0..n).filter(|&i| frame.tiles[i].state == State::Fresh) {
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
        self.queued = None;
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

    fn pick(&mut self, c: &Name, _: &mut Rng) -> Option<usize> {
        if let Some(&g) = self.group_of.get(c) {
            if let Some(i) = self.groups[g].pop() {
                if let Some(q) = &mut self.queued {
                    q.remove(&self.ranks[i]);
                }
                return Some(i);
            }
        }
        // Beyond its own tiles: first those nobody had, else any other
        // client's; of those the one showing most of what this client
        // rendered before, then the one nearest to its region, so that
        // regions stay compact and only their borders move.
        self.take_for(c)
    }

    fn has_own(&self, c: &Name) -> bool {
        !self.unowned.is_empty()
            || self
                .group_of
                .get(c)
                .is_some_and(|&g| !self.groups[g].is_empty())
    }

    /// While the frame has many fresh tiles left (see [`BLOCK_GUIDE`]),
    /// the fresh tiles of `i`'s aligned block that sit in the same queue
    /// go with it: one assignment, one message each way, for what would
    /// otherwise be up to 16. The block shrinks as the frame's fresh tiles
    /// run out, so that the last tiles still balance the clients' loads
    /// one by one. Blocks are made of tiles that the last frame rendered
    /// without a miss, unless the camera cut since, or of any tiles for a
    /// client that holds the whole model (`holds_model`), which misses
    /// nothing: there a tile is quick and its messages weigh; where voxels
    /// were missing, tiles are slow and uneven, and they go one by one so
    /// that the clients share them evenly (in blocks, a cold walk's first
    /// frames would go out before any hit told where each client's content
    /// lies, and fetch more: `experiments/latency-hiding.toml`). Only a
    /// tile of `c`'s own queue or of nobody's comes with a block: a tile
    /// taken from another client's queue comes alone, as that client's
    /// cache holds what it shows.
    fn block(
        &mut self,
        i: usize,
        c: &Name,
        frame: &FrameView<'_>,
        clients: usize,
        opts: &SchedulerOptions,
        holds_model: bool,
    ) -> Vec<usize> {
        if frame.tiles[i].state != State::Fresh
            || !(holds_model || self.warm[i])
            || self.affine[i].as_ref().is_some_and(|o| o != c)
        {
            return vec![i];
        }
        let ts = frame.grid.tile_size;
        let mut side = 1;
        while side * 2 * ts <= opts.max_block_px {
            side *= 2;
        }
        while side > 1 {
            let n = (side * side) as usize;
            if frame.fresh_left >= n * clients.max(1) * BLOCK_GUIDE {
                let block = frame.grid.block_of(i, side);
                let queue = &self.affine[i];
                if block.iter().all(|&j| {
                    j == i
                        || (frame.tiles[j].state == State::Fresh
                            && (holds_model || self.warm[j])
                            && self.affine[j] == *queue)
                }) {
                    // Out of the queue they share with `i`: `c`'s group, or
                    // nobody's.
                    let group = queue.as_ref().and_then(|o| self.group_of.get(o)).copied();
                    for &j in block.iter().filter(|&&j| j != i) {
                        match group {
                            Some(g) => {
                                self.groups[g].retain(|&k| k != j);
                                if let Some(q) = &mut self.queued {
                                    q.remove(&self.ranks[j]);
                                }
                            }
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

    fn handed_out(&mut self, c: &Name, i: usize) {
        let rank = self.ranks[i];
        self.region.entry(c.clone()).or_default().insert(rank);
        self.last.insert(c.clone(), rank);
    }

    fn predicted(&self) -> &[Option<Name>] {
        &self.affine
    }
}

impl ClientQueues {
    /// The empty queues of a frame on `grid`.
    fn of(grid: &TileGrid) -> ClientQueues {
        let n = grid.count();
        ClientQueues {
            groups: Vec::new(),
            group_of: HashMap::new(),
            unowned: BTreeMap::new(),
            last: HashMap::new(),
            ranks: grid.curve_ranks(),
            region: HashMap::new(),
            affine: vec![None; n],
            votes: vec![BTreeMap::new(); n],
            voted: HashMap::new(),
            queued: None,
            warm: vec![false; n],
        }
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
        let (groups, ranks) = (&self.groups, &self.ranks);
        let queued = self
            .queued
            .get_or_insert_with(|| groups.iter().flatten().map(|&i| (ranks[i], i)).collect());
        let votes = |i: usize| self.votes[i].get(c).copied().unwrap_or(0);
        // The queued tile that shows most of what `c` rendered before,
        // else the one nearest its region; ties to the lowest curve
        // position.
        let i = match own {
            Some(own) => {
                let voted = (self.voted.get(c).into_iter().flatten().copied())
                    .filter(|&i| queued.contains_key(&self.ranks[i]))
                    .min_by_key(|&i| {
                        let r = self.ranks[i];
                        (std::cmp::Reverse(votes(i)), distance(own, r), r)
                    });
                match voted {
                    Some(i) => i,
                    None => {
                        // Nearest to the region is nearest to one of its
                        // tiles, on one side or the other.
                        let (_, r) = own
                            .iter()
                            .flat_map(|&o| {
                                let below = queued.range(..=o).next_back();
                                let above = queued.range(o..).next();
                                below
                                    .into_iter()
                                    .chain(above)
                                    .map(move |(&r, _)| (r.abs_diff(o), r))
                            })
                            .min()?;
                        queued[&r]
                    }
                }
            }
            None => {
                let others = others();
                *queued.values().min_by_key(|&&i| {
                    let r = self.ranks[i];
                    (u32::MAX - distance(&others, r), r)
                })?
            }
        };
        queued.remove(&self.ranks[i]);
        let g = *self.group_of.get(self.affine[i].as_ref()?)?;
        let k = self.groups[g].iter().position(|&j| j == i)?;
        Some(self.groups[g].remove(k))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::policy::tests::{fresh_tiles, options, view, walk_camera};
    use dray_protocol::Camera;

    fn names() -> [Name; 2] {
        [
            Name::new("client-b").unwrap(),
            Name::new("client-a").unwrap(),
        ]
    }

    /// The last frame on `grid` through `camera`, every tile rendered
    /// without a miss, its owners alternating in an order no region grown
    /// along the curve would give, its costs rising with the tile index,
    /// its hits on the plane z = 0 at each tile's centre.
    fn previous(grid: TileGrid, camera: Camera) -> Previous {
        let n = grid.count();
        let basis = kernel_camera(&camera, grid.width, grid.height).basis();
        let names = names();
        Previous {
            number: 0,
            camera,
            grid,
            costs: (0..n as u64).map(|i| 100 + i).collect(),
            owners: (0..n).map(|i| Some(names[i % 2].clone())).collect(),
            hits: (0..n)
                .map(|i| {
                    let r = grid.rect(i);
                    let d = basis.direction(r.x + r.w / 2, r.y + r.h / 2);
                    vec![basis.eye + d * (basis.eye.z / -d.z)]
                })
                .collect(),
            missed: vec![false; n],
        }
    }

    fn basis(c: &Camera, grid: &TileGrid) -> CameraBasis {
        kernel_camera(c, grid.width, grid.height).basis()
    }

    #[test]
    fn walking_forward_the_tiles_go_by_sectors() {
        let grid = TileGrid::new(256, 128, 32);
        let prev = previous(grid, walk_camera(6.0));
        let now = basis(&walk_camera(5.0), &grid);
        let p = Affinity.predict(&grid, &now, &prev.last_frame());
        assert!(p.guides);
        let then = basis(&prev.camera, &grid);
        let before: Vec<Option<&Name>> = prev.owners.iter().map(Option::as_ref).collect();
        let hits = prev.hits.iter().flatten().copied();
        let by = sectors::assign(&grid, &then, &now, hits, &before).expect("sectors");
        let by: Vec<Option<Name>> = by.into_iter().map(|n| Some(n.clone())).collect();
        assert_eq!(p.owners, by);
        // Two sectors: the left and right halves.
        let left = p.owners[0].clone();
        assert!(
            (0..grid.count()).all(|i| (p.owners[i] == left) == (grid.rect(i).x < grid.width / 2))
        );
    }

    #[test]
    fn content_moving_across_the_screen_keeps_its_client() {
        let grid = TileGrid::new(256, 128, 32);
        let prev = previous(grid, walk_camera(5.0));
        // Sliding right along the wall by a tile's worth of the view: the
        // content shifts left as a whole, so no sectors, but votes.
        let b = basis(&prev.camera, &grid);
        let shift = (b.eye + b.direction(160, 64) * 5.0).x;
        let slid = Camera {
            eye: [shift, 0.0, 5.0],
            look: [shift, 0.0, 0.0],
            ..prev.camera
        };
        let now = basis(&slid, &grid);
        let p = Affinity.predict(&grid, &now, &prev.last_frame());
        assert!(p.guides);
        let cols = grid.cols as usize;
        for i in 0..grid.count() {
            let (col, row) = (i % cols, i / cols);
            let expected = if col + 1 < cols {
                // Tile i shows what tile i + 1 showed before.
                prev.owners[row * cols + col + 1].clone()
            } else {
                // Nothing landed in the last column: its last client.
                prev.owners[i].clone()
            };
            assert_eq!(p.owners[i], expected, "tile {i}");
        }
        assert!(p.votes.iter().any(|v| !v.is_empty()));
    }

    #[test]
    fn after_a_cut_each_tile_keeps_its_last_client_on_the_same_grid_only() {
        let grid = TileGrid::new(256, 128, 32);
        let prev = previous(grid, walk_camera(5.0));
        let turned = Camera {
            look: [10.0, 0.0, 5.0],
            ..prev.camera
        };
        let p = Affinity.predict(&grid, &basis(&turned, &grid), &prev.last_frame());
        assert!(!p.guides);
        assert_eq!(p.owners, prev.owners);
        assert!(p.votes.iter().all(BTreeMap::is_empty));
        let other = TileGrid::new(256, 128, 16);
        let p = Affinity.predict(&other, &basis(&turned, &other), &prev.last_frame());
        assert!(p.owners.iter().all(Option::is_none));
    }

    #[test]
    fn queues_are_costliest_first_while_guided_and_in_index_order_after_a_cut() {
        let grid = TileGrid::new(128, 64, 32);
        let ahead = walk_camera(5.0);
        let tiles = fresh_tiles(grid.count());
        let owners = vec![None; grid.count()];
        let opts = options();
        let mut q = ClientQueues::of(&grid);
        // The same view: the last frame guides this one. Its tiles are
        // warm (blocks may go out) and each queue gives its costliest first.
        let v = view(&grid, &ahead, &tiles, &owners);
        q.sort(&v, Some(&previous(grid, ahead)), &opts);
        assert!(q.warm.iter().all(|&w| w));
        for g in &q.groups {
            assert_eq!(g.last().copied(), g.iter().copied().max(), "{g:?}");
        }
        // The last frame looked a quarter turn away.
        let aside = Camera {
            look: [10.0, 0.0, 5.0],
            ..ahead
        };
        let prev = previous(grid, aside);
        q.sort(&v, Some(&prev), &opts);
        assert_eq!(q.affine, prev.owners, "each tile with its last client");
        assert!(q.warm.iter().all(|&w| !w), "no blocks");
        for g in &q.groups {
            assert_eq!(
                g.last().copied(),
                g.iter().copied().min(),
                "index order: {g:?}"
            );
        }
        assert_eq!(q.groups.iter().map(Vec::len).sum::<usize>(), grid.count());
        // Without costliest first, index order even while guided.
        let plain = SchedulerOptions {
            costliest_first: false,
            ..options()
        };
        let mut costs_reversed = previous(grid, ahead);
        costs_reversed.costs.reverse();
        q.sort(&v, Some(&costs_reversed), &plain);
        for g in &q.groups {
            assert_eq!(g.last().copied(), g.iter().copied().min(), "{g:?}");
        }
    }

    #[test]
    fn a_client_takes_the_queued_tile_that_every_queued_tile_was_measured_for() {
        // take_for's indexes against the rule measured over every queued
        // tile: most of the client's votes, then nearest its region, then
        // the lowest curve position; the farthest from the others for a
        // client with no region.
        fn distance(set: &BTreeSet<u32>, r: u32) -> u32 {
            set.iter().map(|&o| o.abs_diff(r)).min().unwrap_or(u32::MAX)
        }
        let grid = TileGrid::new(256, 128, 16);
        let camera = walk_camera(5.0);
        let tiles = fresh_tiles(grid.count());
        let owners = vec![None; grid.count()];
        let v = view(&grid, &camera, &tiles, &owners);
        let [b, a] = names();
        let z = Name::new("client-z").unwrap();
        for seed in 0..20u32 {
            let mut q = ClientQueues::of(&grid);
            q.sort(&v, Some(&previous(grid, camera)), &options());
            let mut x = seed.wrapping_mul(2_654_435_761).wrapping_add(1);
            let mut next = |m: u32| {
                x = x.wrapping_mul(1_103_515_245).wrapping_add(12_345);
                (x >> 8) % m
            };
            // z's region starts anywhere (after the first seeds, where it
            // has none).
            if seed > 2 {
                q.handed_out(&z, next(grid.count() as u32) as usize);
            }
            loop {
                let c = [&a, &b, &z][next(3) as usize].clone();
                let own = q.region.get(&c).filter(|r| !r.is_empty()).cloned();
                let others: BTreeSet<u32> = (q.region.iter())
                    .filter(|(n, _)| **n != c)
                    .flat_map(|(_, r)| r.iter().copied())
                    .collect();
                let votes = |i: usize| q.votes[i].get(&c).copied().unwrap_or(0);
                let want = q.groups.iter().flatten().copied().min_by_key(|&i| {
                    let r = q.ranks[i];
                    match &own {
                        Some(own) => (std::cmp::Reverse(votes(i)), distance(own, r), r),
                        None => (std::cmp::Reverse(0), u32::MAX - distance(&others, r), r),
                    }
                });
                let got = q.take_for(&c);
                assert_eq!(got, want, "seed {seed}, {c}");
                let Some(i) = got else { break };
                assert!(!q.groups.iter().flatten().any(|&j| j == i), "taken out");
                q.handed_out(&c, i);
            }
            assert!(
                q.queued.is_some_and(|q| q.is_empty()),
                "every queued tile taken"
            );
        }
    }

    #[test]
    fn a_client_takes_its_own_tiles_then_nobodys_then_anothers() {
        let grid = TileGrid::new(128, 64, 32);
        let camera = walk_camera(5.0);
        let tiles = fresh_tiles(grid.count());
        let owners = vec![None; grid.count()];
        let [b, a] = names();
        let mut q = ClientQueues::of(&grid);
        // Only the first frame in flight guides: b has tiles 0 and 1,
        // a none, and the rest are nobody's.
        let mut guide = vec![None; grid.count()];
        guide[0] = Some(b.clone());
        guide[1] = Some(b.clone());
        let v = FrameView {
            first_guide: Some(&guide),
            ..view(&grid, &camera, &tiles, &owners)
        };
        q.sort(&v, None, &options());
        assert!(q.warm.iter().all(|&w| !w), "nothing known warm yet");
        let mut rng = Rng::new(1);
        assert!(q.has_own(&a), "nobody's tiles count as its own");
        let mut got = Vec::new();
        while let Some(i) = q.pick(&b, &mut rng) {
            assert_eq!(q.block(i, &b, &v, 2, &options(), false), vec![i]);
            q.handed_out(&b, i);
            got.push(i);
        }
        assert_eq!(&got[..2], &[0, 1], "its own first, in index order");
        assert_eq!(got.len(), grid.count(), "then everyone else's");
        assert!(!q.has_own(&a) && !q.has_own(&b));
    }
}
