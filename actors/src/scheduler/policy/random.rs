//! The random policy, the baseline the affinity policy is measured
//! against: a uniformly random fresh tile to whichever client asks, one
//! at a time. It predicts no owners, so the prefetcher sends no hints.

use super::{FrameView, LastFrame, Policy, Prediction, Queues};
use crate::scheduler::tiles::TileGrid;
use crate::scheduler::tiles_in_flight::{SchedulerOptions, State};
use dray_protocol::Name;
use dray_scene::rng::Rng;
use dray_trace::camera::CameraBasis;

/// The random policy.
pub(super) struct Random;

impl Policy for Random {
    fn predict(&self, grid: &TileGrid, _: &CameraBasis, _: &LastFrame<'_>) -> Prediction {
        Prediction::none(grid.count())
    }

    fn claims_tiles(&self) -> bool {
        false
    }

    fn queues(&self, _: &TileGrid) -> Box<dyn Queues> {
        Box::new(Pool { fresh: Vec::new() })
    }
}

/// A frame's fresh tiles, in no order that matters.
struct Pool {
    fresh: Vec<usize>,
}

impl Queues for Pool {
    fn sort(&mut self, frame: &FrameView<'_>, _: Option<&super::Previous>, _: &SchedulerOptions) {
        self.fresh = (0..frame.tiles.len())
            .filter(|&i| frame.tiles[i].state == State::Fresh)
            .collect();
    }

    fn pick(&mut self, _: &Name, rng: &mut Rng) -> Option<usize> {
        if self.fresh.is_empty() {
            return None;
        }
        let k = rng.below(self.fresh.len() as u32) as usize;
        Some(self.fresh.swap_remove(k))
    }

    fn has_own(&self, _: &Name) -> bool {
        false
    }

    fn block(
        &mut self,
        i: usize,
        _: &Name,
        _: &FrameView<'_>,
        _: usize,
        _: &SchedulerOptions,
        _: bool,
    ) -> Vec<usize> {
        vec![i]
    }

    fn handed_out(&mut self, _: &Name, _: usize) {}

    fn predicted(&self) -> &[Option<Name>] {
        &[]
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scheduler::policy::of;
    use crate::scheduler::policy::tests::{fresh_tiles, options, view, walk_camera};
    use dray_config::TilePolicy;

    #[test]
    fn every_fresh_tile_goes_out_once_in_a_seeded_order_and_alone() {
        let grid = TileGrid::new(128, 64, 32);
        let camera = walk_camera(5.0);
        let mut tiles = fresh_tiles(grid.count());
        tiles[3].state = State::Out;
        let owners = vec![None; grid.count()];
        let policy = of(TilePolicy::Random);
        assert!(!policy.claims_tiles());
        let c = Name::new("client-0").unwrap();
        let order = |seed: u64| {
            let mut q = policy.queues(&grid);
            q.sort(&view(&grid, &camera, &tiles, &owners), None, &options());
            let mut rng = Rng::new(seed);
            let mut got = Vec::new();
            while let Some(i) = q.pick(&c, &mut rng) {
                let v = view(&grid, &camera, &tiles, &owners);
                assert_eq!(q.block(i, &c, &v, 2, &options(), true), vec![i]);
                assert!(!q.has_own(&c));
                got.push(i);
            }
            got
        };
        let first = order(1);
        let mut sorted = first.clone();
        sorted.sort_unstable();
        assert_eq!(sorted, [0, 1, 2, 4, 5, 6, 7], "each fresh tile once");
        assert_eq!(order(1), first, "the same seed, the same order");
        assert_ne!(order(2), first, "another seed, another order");
    }

    #[test]
    fn it_predicts_no_owner_so_the_prefetcher_hints_nothing() {
        let grid = TileGrid::new(128, 64, 32);
        let c = Name::new("client-0").unwrap();
        let owners = vec![Some(c); grid.count()];
        let hits = vec![Vec::new(); grid.count()];
        let now = kernel_basis(&walk_camera(5.0), &grid);
        let last = LastFrame {
            camera: Some(kernel_basis(&walk_camera(6.0), &grid)),
            grid,
            owners: &owners,
            hits: &hits,
        };
        let p = of(TilePolicy::Random).predict(&grid, &now, &last);
        assert!(p.owners.iter().all(Option::is_none));
        assert!(!p.guides);
    }

    fn kernel_basis(c: &dray_protocol::Camera, grid: &TileGrid) -> CameraBasis {
        crate::settings::kernel_camera(c, grid.width, grid.height).basis()
    }
}
