//! The Prefetcher actor: predicts the next camera from the last two, shoots
//! a coarse grid of rays through the high-level BSP, and tells each client
//! which voxels the tiles it will probably get next will enter, so that its
//! loader fetches them before the tiles arrive.
//!
//! Shape: [`state::Prefetcher`] owns the manifest's BSP, the recent cameras,
//! the last tile owners and the manifest requests; its handlers (a camera
//! update, tile owners, the manifest, a store up, the manifest timer, a
//! finished plan, a hint sent) change it and push effects ([`state::Out`]:
//! ask a store for the manifest, plan a frame's hints, send a hint);
//! [`run_prefetcher`] receives, calls the handler and carries the effects
//! out, planning on the blocking pool. The planning itself ([`plan_hints`],
//! [`recipients`], [`predict_camera`]) is pure and lives here.

mod state;

use super::policy::{self, LastFrame, TilePolicy};
use super::tiles::TileGrid;
use crate::names::StoreRoutes;
use crate::settings::kernel_camera;
use crate::ActorError;
use dray_protocol::{Camera, FetchManifest, Message, Name, TileOwners, MAX_PREFETCH_IDS};
use dray_runtime::{Delivery, Mailbox};
use dray_scene::Ray;
use dray_trace::accel::TopLevel;
use glam::Vec3;
use state::{Out, Prefetcher};
use std::collections::HashMap;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// What the prefetcher needs.
#[derive(Clone, Debug)]
pub struct PrefetcherOptions {
    /// The stores; the manifest is fetched from the first that answers.
    pub stores: StoreRoutes,
    /// One sample ray per `step` × `step` pixels (at least 1).
    pub step: u32,
    /// Voxels hinted along each sample ray, nearest first.
    pub voxels_per_ray: u32,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
    /// The scheduler's tile policy, whose prediction the hints follow.
    pub policy: TilePolicy,
}

/// What the prefetcher did, returned when it stops.
#[derive(Clone, Debug, Default)]
pub struct PrefetcherSummary {
    /// Hints sent.
    pub hints: u64,
    /// Voxel ids in them, summed.
    pub voxels_hinted: u64,
    /// Frames not planned because the caches were warm (see
    /// [`plans_frame`]).
    pub frames_skipped: u64,
}

/// Completed frames in a row without a miss after which the caches count as
/// warm.
pub const WARM_AFTER: u32 = 8;
/// While the caches are warm, only every this many frames is planned.
pub const WARM_STRIDE: u64 = 4;

/// Whether to plan the hints for frame `next`, after `quiet` completed
/// frames in a row whose packets met no missing voxel. Planning samples
/// thousands of rays through the BSP for every frame; while the clients'
/// caches already hold what the frames need, hints fetch nothing, so only
/// every fourth frame is planned, to notice new content. The first frame
/// with a miss plans every frame again.
pub fn plans_frame(quiet: u32, next: u64) -> bool {
    quiet < WARM_AFTER || next.is_multiple_of(WARM_STRIDE)
}

/// The camera of frame `next` predicted from the last one or two: eye and
/// look point extrapolated linearly (per frame number), the rest as the
/// latest. Falls back to the latest camera when the extrapolation is not a
/// usable view, and after a cut (the camera turned by more than half the
/// field of view from the one before, see [`policy::reproject::continues`]):
/// a jump is no motion to go on with (extrapolated across a jump back to
/// a path's start, it would predict a view as far beyond the start).
pub fn predict_camera(prev: Option<(u64, &Camera)>, last: (u64, &Camera), next: u64) -> Camera {
    let (s1, c1) = last;
    let Some((s0, c0)) = prev.filter(|(s0, _)| *s0 < s1) else {
        return *c1;
    };
    let basis = |c: &Camera| kernel_camera(c, 1, 1).basis();
    // No hits at hand: by the turn alone.
    if !policy::reproject::continues(&basis(c0), &basis(c1), std::iter::empty()) {
        return *c1;
    }
    let k = (next.saturating_sub(s1)) as f32 / (s1 - s0) as f32;
    let ext = |a: [f32; 3], b: [f32; 3]| {
        let (a, b) = (Vec3::from_array(a), Vec3::from_array(b));
        (b + (b - a) * k).to_array()
    };
    let p = Camera {
        eye: ext(c0.eye, c1.eye),
        look: ext(c0.look, c1.look),
        ..*c1
    };
    if dray_protocol::check_camera(&p).is_ok() {
        p
    } else {
        *c1
    }
}

/// Per tile of `grid` seen through `camera`, the index (in `owners`'
/// clients) of the client the scheduler will give it (u32::MAX: none):
/// `policy`'s prediction ([`policy::predict_owners`], the rule the
/// scheduler sorts its tiles by), judged from the `owners` frame, whose
/// camera `then` is known or not.
pub(super) fn recipients(
    owners: &TileOwners,
    then: Option<&Camera>,
    camera: &Camera,
    grid: &TileGrid,
    policy: TilePolicy,
) -> Vec<u32> {
    let clients = owners.clients.as_slice();
    let names: Vec<Option<Name>> = (0..grid.count())
        .map(|t| {
            let c = *owners.owners.0.get(t)?;
            clients.get(c as usize).cloned()
        })
        .collect();
    // Each tile's hits, as many as its count says.
    let mut hits: Vec<Vec<Vec3>> = vec![Vec::new(); grid.count()];
    let mut at = 0;
    for (t, &n) in owners.hit_counts.0.iter().enumerate() {
        let end = at + 3 * n as usize;
        if let (Some(xyz), Some(h)) = (owners.hits.0.get(at..end), hits.get_mut(t)) {
            h.extend(
                xyz.chunks_exact(3)
                    .map(|p| Vec3::new(p[0], p[1], p[2]))
                    .filter(|p| p.is_finite()),
            );
        }
        at = end;
    }
    let last = LastFrame {
        camera: then.map(|c| kernel_camera(c, owners.width, owners.height).basis()),
        grid: *grid,
        owners: &names,
        hits: &hits,
    };
    let now = kernel_camera(camera, owners.width, owners.height).basis();
    policy::predict_owners(policy, grid, &now, &last)
        .owners
        .iter()
        .map(|o| {
            o.as_ref()
                .and_then(|n| clients.iter().position(|c| c == n))
                .map_or(u32::MAX, |i| i as u32)
        })
        .collect()
}

/// Per client node, the voxels its tiles of `camera` will probably enter,
/// most urgent first (nearest along the rays, then most often), at most
/// [`MAX_PREFETCH_IDS`]. Sample pixels are the centre pixels of each
/// `step` × `step` block of a `width` × `height` image; each goes to the
/// client the scheduler will probably give its tile by `policy` (see
/// [`recipients`]; `owners_camera` is the `owners` frame's camera, if
/// known). Tiles of no client are skipped, and so are those of a client
/// that holds the whole model.
pub fn plan_hints(
    policy: TilePolicy,
    top: &TopLevel,
    (owners, owners_camera): (&TileOwners, Option<&Camera>),
    camera: &Camera,
    (width, height): (u32, u32),
    step: u32,
    voxels_per_ray: u32,
) -> Vec<(Name, Vec<u32>)> {
    let step = step.max(1);
    let basis = kernel_camera(camera, width, height).basis();
    let grid = TileGrid::new(owners.width, owners.height, owners.tile_size);
    let recipients = recipients(owners, owners_camera, camera, &grid, policy);
    let clients = owners.clients.as_slice();
    // No rays for the tiles of a client that holds the whole model.
    let whole: Vec<bool> = clients
        .iter()
        .map(|c| owners.holds_model.as_slice().contains(c))
        .collect();
    // Per client: voxel → (nearest rank along a ray, how many rays).
    let mut seen: Vec<HashMap<u32, (u32, u32)>> = vec![HashMap::new(); clients.len()];
    let (mut stack, mut hits) = (Vec::new(), Vec::new());
    for by in (0..height).step_by(step as usize) {
        for bx in (0..width).step_by(step as usize) {
            let x = bx + (step.min(width - bx)) / 2;
            let y = by + (step.min(height - by)) / 2;
            // The tile of the owners' image holding the same spot.
            let ox = (u64::from(x) * u64::from(owners.width) / u64::from(width)) as u32;
            let oy = (u64::from(y) * u64::from(owners.height) / u64::from(height)) as u32;
            let Some(tile) = grid.tile_at(ox, oy) else {
                continue;
            };
            let Some(&c) = recipients.get(tile) else {
                continue;
            };
            if whole.get(c as usize).copied().unwrap_or(false) {
                continue;
            }
            let Some(per) = seen.get_mut(c as usize) else {
                continue;
            };
            let ray = Ray {
                origin: basis.eye,
                dir: basis.direction(x, y),
            };
            hits.clear();
            top.voxels_along(&ray, voxels_per_ray as usize, &mut stack, &mut hits);
            for (rank, &v) in hits.iter().enumerate() {
                let e = per.entry(v).or_insert((u32::MAX, 0));
                e.0 = e.0.min(rank as u32);
                e.1 += 1;
            }
        }
    }
    clients
        .iter()
        .zip(seen)
        .filter(|(_, per)| !per.is_empty())
        .map(|(name, per)| {
            let mut v: Vec<(u32, (u32, u32))> = per.into_iter().collect();
            v.sort_unstable_by_key(|&(id, (rank, count))| (rank, std::cmp::Reverse(count), id));
            v.truncate(MAX_PREFETCH_IDS);
            (name.clone(), v.into_iter().map(|(id, _)| id).collect())
        })
        .collect()
}

/// Runs the prefetcher until [`Message::Shutdown`] (or the mailbox closes).
/// It sends nothing until it has the manifest, a frame's tile owners and a
/// camera.
pub async fn run_prefetcher(
    mut mb: Mailbox,
    opts: PrefetcherOptions,
) -> Result<PrefetcherSummary, ActorError> {
    let mut p = Prefetcher::new(opts, Instant::now());
    let mut out = Vec::new();
    loop {
        tokio::select! {
            biased;
            d = mb.recv() => match d {
                None => return Ok(p.summary().clone()),
                Some(Delivery::Message { from, msg }) => match msg {
                    Message::ManifestData(m) => {
                        p.manifest_data(&from, &m.data.0, Instant::now(), &mut out)
                    }
                    Message::TileOwners(o) => p.tile_owners(o, &mut out),
                    Message::CameraUpdate(u) => p.camera_update(u, &mut out),
                    Message::Shutdown(r) => {
                        let s = p.summary();
                        info!(reason = %r.reason, hints = s.hints,
                            skipped = s.frames_skipped, "prefetcher stops");
                        return Ok(s.clone());
                    }
                    other => debug!(kind = other.kind().name(), %from, "prefetcher ignores"),
                },
                Some(Delivery::PeerUp { node, .. }) => p.peer_up(&node, Instant::now()),
                Some(Delivery::PeerDown { .. }) => {}
            },
            _ = crate::sleep_until_opt(p.deadline()) => p.ask_due(Instant::now(), &mut out),
        }
        carry_out(&mut p, &mb, &mut out).await;
    }
}

/// Carries out the handlers' effects in order, then those that planning
/// adds.
async fn carry_out(p: &mut Prefetcher, mb: &Mailbox, out: &mut Vec<Out>) {
    while !out.is_empty() {
        for o in std::mem::take(out) {
            match o {
                Out::FetchManifest(to) => {
                    let ask = Message::FetchManifest(FetchManifest {});
                    if let Err(e) = mb.send(&to, ask).await {
                        debug!(%to, "cannot ask for the manifest: {e}");
                    }
                }
                Out::Plan(plan) => {
                    let frame = plan.frame;
                    // Thousands of rays through the BSP: on the blocking pool, not on
                    // the scheduler node's only thread, which hands out the tiles.
                    match crate::spawn_blocking(move || plan.run()).await {
                        Ok(hints) => p.planned(frame, hints, out),
                        Err(e) => warn!(frame, "planning the prefetch failed: {e}"),
                    }
                }
                Out::Hint(to, h) => {
                    let (frame, n) = (h.frame, h.voxels.0.len());
                    match mb.send(&to, Message::PrefetchHint(h)).await {
                        Ok(()) => {
                            p.hint_sent(n);
                            debug!(frame, %to, voxels = n, "prefetch hint");
                        }
                        Err(e) => debug!(frame, %to, "cannot send a prefetch hint: {e}"),
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_protocol::{Blob, BoundedVec, PackedF32, PackedU32};
    use dray_trace::camera::CameraBasis;

    #[test]
    fn warm_caches_plan_every_fourth_frame() {
        for next in 0..16 {
            // Until WARM_AFTER quiet frames, every frame.
            assert!(plans_frame(0, next));
            assert!(plans_frame(WARM_AFTER - 1, next));
            assert_eq!(
                plans_frame(WARM_AFTER, next),
                next.is_multiple_of(WARM_STRIDE)
            );
            assert_eq!(
                plans_frame(u32::MAX, next),
                next.is_multiple_of(WARM_STRIDE)
            );
        }
    }

    #[test]
    fn the_camera_goes_on_as_it_moved_but_not_across_a_cut() {
        let at = |x: f32, look: [f32; 3]| Camera {
            eye: [x, 0.0, 5.0],
            look,
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        };
        let (a, b) = (at(0.0, [0.0, 0.0, 0.0]), at(1.0, [1.0, 0.0, 0.0]));
        // Moving sideways by 1 a frame: two frames on, 2 further.
        let p = predict_camera(Some((4, &a)), (5, &b), 7);
        assert_eq!((p.eye, p.look), ([3.0, 0.0, 5.0], [3.0, 0.0, 0.0]));
        // Turned a quarter round since the frame before: the latest.
        let turned = at(1.0, [11.0, 0.0, 5.0]);
        assert_eq!(predict_camera(Some((4, &a)), (5, &turned), 6), turned);
        assert_eq!(predict_camera(None, (5, &b), 6), b);
    }

    /// The owners of a 64 × 64 frame of four 32-pixel tiles (row by row)
    /// rendered by `client-0` and `client-1`, with each tile's hits.
    fn owners_2x2(owners: [u32; 4], hit_counts: [u8; 4], hits: &[Vec3]) -> TileOwners {
        TileOwners {
            frame: 1,
            width: 64,
            height: 64,
            tile_size: 32,
            owners: PackedU32(owners.to_vec()),
            clients: BoundedVec::new(vec![
                Name::new("client-0").unwrap(),
                Name::new("client-1").unwrap(),
            ])
            .unwrap(),
            hit_counts: Blob(hit_counts.to_vec()),
            hits: PackedF32(hits.iter().flat_map(|p| p.to_array()).collect()),
            misses: 0,
            holds_model: BoundedVec::default(),
        }
    }

    /// Two points 5 units from the eye of `b` (a 64 × 64 view) that it
    /// sees in its tile 3 (bottom right).
    fn in_tile_3(b: &CameraBasis) -> [Vec3; 2] {
        [
            b.eye + b.direction(40, 50) * 5.0,
            b.eye + b.direction(60, 33) * 5.0,
        ]
    }

    /// A camera 5 units up the z axis, looking at the origin.
    fn towards_origin() -> Camera {
        Camera {
            eye: [0.0, 0.0, 5.0],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        }
    }

    #[test]
    fn hints_follow_the_content_that_moves_into_a_tile() {
        let camera = towards_origin();
        let b = kernel_camera(&camera, 64, 64).basis();
        // What client 0 rendered in tile 0 is now in tile 3 (bottom right).
        let owners = owners_2x2([0, u32::MAX, 1, 1], [2, 0, 0, 0], &in_tile_3(&b));
        let grid = TileGrid::new(64, 64, 32);
        // Tiles where nothing lands keep their owner (or none).
        assert_eq!(
            recipients(&owners, None, &camera, &grid, TilePolicy::Affinity),
            vec![0, u32::MAX, 1, 0]
        );
    }

    #[test]
    fn hints_go_to_each_tiles_last_client_after_a_cut() {
        let then = towards_origin();
        // A quarter turn.
        let now = Camera {
            look: [10.0, 0.0, 5.0],
            ..then
        };
        // What client 0 rendered in tile 0 lands in tile 3 of the new view
        // (so reprojection would give tile 3 to client 0).
        let b = kernel_camera(&now, 64, 64).basis();
        let owners = owners_2x2([0, u32::MAX, 1, 1], [2, 0, 0, 0], &in_tile_3(&b));
        let grid = TileGrid::new(64, 64, 32);
        assert_eq!(
            recipients(&owners, None, &now, &grid, TilePolicy::Affinity),
            vec![0, u32::MAX, 1, 0],
            "reprojected"
        );
        // Knowing the owners' camera, the cut shows: as the scheduler
        // assigns, each tile to its last client.
        assert_eq!(
            recipients(&owners, Some(&then), &now, &grid, TilePolicy::Affinity),
            vec![0, u32::MAX, 1, 1]
        );
    }

    #[test]
    fn hints_go_by_sectors_while_the_camera_walks_forward() {
        let at = |z: f32| Camera {
            eye: [0.0, 0.0, z],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        };
        let (then, now) = (at(6.0), at(5.0));
        let b = kernel_camera(&then, 64, 64).basis();
        // Points on the plane z = 0 seen all over the earlier image.
        let hits: Vec<Vec3> = [(8, 8), (56, 8), (8, 56), (56, 56), (20, 40), (44, 24)]
            .iter()
            .map(|&(x, y)| b.eye + b.direction(x, y) * 6.0 / b.direction(x, y).z.abs())
            .collect();
        // Left half client 1, right half client 0.
        let owners = owners_2x2([1, 0, 1, 0], [2, 2, 1, 1], &hits);
        let grid = TileGrid::new(64, 64, 32);
        // Two sectors around the centre, turned to keep the most tiles:
        // what the scheduler will assign.
        let before: Vec<Option<&Name>> = [1, 0, 1, 0]
            .iter()
            .map(|&c| owners.clients.as_slice().get(c))
            .collect();
        let tb = kernel_camera(&then, 64, 64).basis();
        let nb = kernel_camera(&now, 64, 64).basis();
        let points = owners
            .hits
            .0
            .chunks_exact(3)
            .map(|p| Vec3::new(p[0], p[1], p[2]));
        let expected = policy::sectors::assign(&grid, &tb, &nb, points, &before)
            .expect("walking forward: sectors");
        let expected: Vec<u32> = expected
            .iter()
            .map(|n| {
                owners
                    .clients
                    .as_slice()
                    .iter()
                    .position(|c| c == *n)
                    .unwrap() as u32
            })
            .collect();
        assert_eq!(expected.len(), grid.count());
        assert_eq!(
            recipients(&owners, Some(&then), &now, &grid, TilePolicy::Affinity),
            expected
        );
        // Without the earlier camera: reprojection, as before.
        assert_ne!(
            recipients(&owners, None, &now, &grid, TilePolicy::Affinity),
            expected
        );
    }

    #[test]
    fn no_hints_where_the_random_policy_assigns() {
        let then = towards_origin();
        let b = kernel_camera(&then, 64, 64).basis();
        let owners = owners_2x2([0, 1, 1, 0], [2, 0, 0, 0], &in_tile_3(&b));
        let grid = TileGrid::new(64, 64, 32);
        assert_eq!(
            recipients(&owners, Some(&then), &then, &grid, TilePolicy::Random),
            vec![u32::MAX; 4]
        );
    }
}
