//! Reprojection affinity (the paper's): where the content of the previous
//! frame lands in a new camera, and so which client's cache holds what each
//! tile of the new frame shows; and whether the new camera continues from
//! the old one at all. The affinity policy's prediction goes by it (see
//! [`super::affinity`]), and the prefetcher's camera extrapolation stops
//! at a cut.

use crate::scheduler::tiles::TileGrid;
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

/// Whether a frame seen through `then`, with hits at `hits`, is a guide to
/// one seen through `now`: whether the camera moved on from it rather than
/// cut to another view. After a cut (a jump along a camera path, a
/// teleport, a sharp turn) the old frame's content is mostly out of view,
/// and its owners, costs and misses say nothing about the new tiles. The
/// camera cut when it turned by more than half the field of view, or when
/// the eye moved farther than the old frame's farthest hit (everything it
/// showed is behind or beside the new eye, as when it passes through a
/// wall). The farthest hit, not a typical one: walking up to something,
/// most hits are nearer than a frame's step (half the median distance
/// would cut most frames of `experiments/affinity-inside.toml`'s walk).
pub fn continues(
    then: &CameraBasis,
    now: &CameraBasis,
    hits: impl IntoIterator<Item = Vec3>,
) -> bool {
    // `up` is scaled by the tangent of half the vertical field of view.
    let half_fov = now.up.length().atan().min(then.up.length().atan());
    if then.forward.dot(now.forward) < half_fov.cos() {
        return false;
    }
    let farthest = hits
        .into_iter()
        .map(|p| p.distance(then.eye))
        .filter(|d| d.is_finite())
        .fold(None, |m: Option<f32>, d| Some(m.map_or(d, |m| m.max(d))));
    // Only sky: turning decides alone.
    farthest.is_none_or(|f| now.eye.distance(then.eye) <= f)
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

    #[test]
    fn a_camera_that_turns_or_jumps_too_far_cuts() {
        let cam = |eye: Vec3, look: Vec3| {
            Camera {
                eye,
                look,
                up: Vec3::Y,
                fov_degrees: 50.0,
                width: 64,
                height: 48,
            }
            .basis()
        };
        let then = cam(Vec3::ZERO, Vec3::new(0.0, 0.0, -1.0));
        // Content 10 to 30 ahead.
        let hits: Vec<Vec3> = (10..=30)
            .map(|z| Vec3::new(1.0, 0.0, -(z as f32)))
            .collect();
        let h = || hits.iter().copied();
        // Walking on and turning a little.
        assert!(continues(
            &then,
            &cam(Vec3::new(0.0, 0.0, -2.0), Vec3::new(0.2, 0.0, -3.0)),
            h()
        ));
        // Turned by 30°, more than half the 50° field.
        let turned = Vec3::new(30f32.to_radians().sin(), 0.0, -30f32.to_radians().cos());
        assert!(!continues(&then, &cam(Vec3::ZERO, turned), h()));
        // 20° is less than half the field.
        let turned = Vec3::new(20f32.to_radians().sin(), 0.0, -20f32.to_radians().cos());
        assert!(continues(&then, &cam(Vec3::ZERO, turned), h()));
        // Moved farther than the farthest hit, looking the same way.
        let far = Vec3::new(31.0, 0.0, 0.0);
        assert!(!continues(
            &then,
            &cam(far, far + Vec3::new(0.0, 0.0, -1.0)),
            h()
        ));
        let near = Vec3::new(29.0, 0.0, 0.0);
        assert!(continues(
            &then,
            &cam(near, near + Vec3::new(0.0, 0.0, -1.0)),
            h()
        ));
        // Only sky: turning decides alone.
        assert!(continues(
            &then,
            &cam(far, far + Vec3::new(0.0, 0.0, -1.0)),
            std::iter::empty()
        ));
    }
}
