//! Reprojection affinity (the paper's): where the content of the previous
//! frame lands in a new camera, and so which client's cache holds what each
//! tile of the new frame shows. The scheduler assigns tiles by it and the
//! prefetcher sends its hints by it.

use super::tiles::TileGrid;
use dray_trace::camera::CameraBasis;
use glam::Vec3;
use std::collections::BTreeMap;

/// Per tile of `grid` seen through `camera`, how many of the `samples`
/// (hit positions, each with the client that rendered it) land in it.
pub fn votes<K: Ord>(
    grid: &TileGrid,
    camera: &CameraBasis,
    samples: impl IntoIterator<Item = (K, Vec3)>,
) -> Vec<BTreeMap<K, u32>> {
    let mut votes: Vec<BTreeMap<K, u32>> = (0..grid.count()).map(|_| BTreeMap::new()).collect();
    for (client, p) in samples {
        let Some((x, y)) = camera.project(p) else {
            continue;
        };
        if x < 0.0 || y < 0.0 {
            continue;
        }
        // Huge coordinates saturate, then miss the grid.
        if let Some(t) = grid.tile_at(x as u32, y as u32) {
            *votes[t].entry(client).or_default() += 1;
        }
    }
    votes
}

/// The client with the most samples in a tile; the first among equals, so
/// that the same frames give the same assignment.
pub fn most<K: Ord>(votes: &BTreeMap<K, u32>) -> Option<&K> {
    votes
        .iter()
        .max_by_key(|&(k, c)| (*c, std::cmp::Reverse(k)))
        .map(|(k, _)| k)
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_trace::camera::Camera;

    #[test]
    fn samples_vote_for_the_tile_they_land_in() {
        let cam = Camera {
            eye: Vec3::new(0.0, 0.0, 5.0),
            look: Vec3::ZERO,
            up: Vec3::Y,
            fov_degrees: 50.0,
            width: 64,
            height: 64,
        };
        let b = cam.basis();
        let grid = TileGrid::new(64, 64, 16);
        let at = |x: u32, y: u32| b.eye + b.direction(x, y) * 5.0;
        let v = votes(
            &grid,
            &b,
            [
                ("b", at(3, 3)),
                ("a", at(5, 9)),
                ("b", at(40, 50)),
                ("a", at(41, 51)),
                ("c", b.eye - b.forward), // behind the eye
            ],
        );
        assert_eq!(v[0].len(), 2);
        assert_eq!(most(&v[0]), Some(&"a"), "equal votes: the first name");
        assert_eq!(most(&v[3 * 4 + 2]), Some(&"a"));
        assert_eq!(v.iter().map(|t| t.values().sum::<u32>()).sum::<u32>(), 4);
        assert_eq!(most(&v[5]), None);
    }
}
