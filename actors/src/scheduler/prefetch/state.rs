//! The prefetcher's state and handlers: which store to ask for the manifest
//! and when, the recent cameras and the last frame's tile owners, which
//! frame to plan hints for (or skip, while the caches are warm), and what
//! it counts. Nothing here samples rays, sends or sleeps: the handlers push
//! [`Out`] effects that [`super::run_prefetcher`] carries out.

use super::{plan_hints, plans_frame, predict_camera, PrefetcherOptions, PrefetcherSummary};
use crate::names::CLIENT;
use crate::scheduler::policy::TilePolicy;
use dray_protocol::{Address, Camera, CameraUpdate, Name, PackedU32, PrefetchHint, TileOwners};
use dray_scene::db::manifest::Manifest;
use dray_trace::accel::TopLevel;
use std::collections::VecDeque;
use std::sync::Arc;
use std::time::Duration;
use tokio::time::Instant;
use tracing::{debug, info, warn};

/// How long a store has to answer a `FetchManifest` before the next is asked.
pub(super) const MANIFEST_TIMEOUT: Duration = Duration::from_secs(2);

/// Cameras kept to find the one of the frame whose tile owners arrive
/// (the display runs a few frames ahead of the last completed one).
pub(super) const RECENT_CAMERAS: usize = 16;

/// What the prefetcher's handlers ask the run loop to do, in order.
#[derive(Debug)]
pub(super) enum Out {
    /// Ask this store for the manifest.
    FetchManifest(Address),
    /// Sample the plan's rays, off the actor's thread, and hand the result
    /// to [`Prefetcher::planned`].
    Plan(Box<Plan>),
    /// Send a client a hint; the loop calls [`Prefetcher::hint_sent`] once
    /// it has left.
    Hint(Address, PrefetchHint),
}

/// Everything [`plan_hints`] needs for one frame, owned so that it can run
/// on another thread.
#[derive(Debug)]
pub(super) struct Plan {
    /// The frame the hints are for.
    pub frame: u64,
    /// Its predicted camera.
    pub camera: Camera,
    top: Arc<TopLevel>,
    owners: TileOwners,
    /// The camera of the `owners` frame, if known.
    owners_camera: Option<Camera>,
    policy: TilePolicy,
    size: (u32, u32),
    step: u32,
    voxels_per_ray: u32,
}

impl Plan {
    /// Per client node, the voxels to hint, most urgent first.
    pub fn run(&self) -> Vec<(Name, Vec<u32>)> {
        plan_hints(
            self.policy,
            &self.top,
            (&self.owners, self.owners_camera.as_ref()),
            &self.camera,
            self.size,
            self.step,
            self.voxels_per_ray,
        )
    }
}

/// The prefetcher's state.
pub(super) struct Prefetcher {
    opts: PrefetcherOptions,
    /// Every store, in the order they are asked for the manifest.
    stores: Vec<Address>,
    /// Manifest requests sent; the next goes to `stores[asked % len]`.
    asked: usize,
    /// When to ask (again) for the manifest; `None` once it is here.
    ask_at: Option<Instant>,
    /// The high-level BSP, from the manifest.
    top: Option<Arc<TopLevel>>,
    /// The newest frame's tile owners.
    owners: Option<TileOwners>,
    /// The camera of the `owners` frame, if it is among the recent ones.
    owners_camera: Option<Camera>,
    /// The last two cameras, oldest first.
    cams: Vec<(u64, Camera)>,
    /// The recent cameras, oldest first, at most [`RECENT_CAMERAS`].
    recent: VecDeque<(u64, Camera)>,
    /// The last frame planned or skipped.
    hinted_for: Option<u64>,
    /// Completed frames in a row without a miss.
    quiet: u32,
    summary: PrefetcherSummary,
}

impl Prefetcher {
    /// A prefetcher that asks the first store for the manifest at `now`.
    pub fn new(opts: PrefetcherOptions, now: Instant) -> Prefetcher {
        Prefetcher {
            stores: opts.stores.all().cloned().collect(),
            opts,
            asked: 0,
            ask_at: Some(now),
            top: None,
            owners: None,
            owners_camera: None,
            cams: Vec::new(),
            recent: VecDeque::new(),
            hinted_for: None,
            quiet: 0,
            summary: PrefetcherSummary::default(),
        }
    }

    /// When the loop is to call [`Prefetcher::ask_due`]; `None` once the
    /// manifest is here.
    pub fn deadline(&self) -> Option<Instant> {
        self.ask_at
    }

    /// What the prefetcher did so far.
    pub fn summary(&self) -> &PrefetcherSummary {
        &self.summary
    }

    /// Time to ask for the manifest: the next store in turn, and the one
    /// after it if no answer comes within [`MANIFEST_TIMEOUT`].
    pub fn ask_due(&mut self, now: Instant, out: &mut Vec<Out>) {
        if let Some(to) = self.stores.get(self.asked % self.stores.len().max(1)) {
            out.push(Out::FetchManifest(to.clone()));
        }
        self.asked += 1;
        self.ask_at = Some(now + MANIFEST_TIMEOUT);
    }

    /// A node came (back) up: if it is a store and the manifest is still
    /// missing, it is asked now.
    pub fn peer_up(&mut self, node: &Name, now: Instant) {
        if self.top.is_some() {
            return;
        }
        if let Some(i) = self.stores.iter().position(|s| s.node == *node) {
            self.asked = i;
            self.ask_at = Some(now);
        }
    }

    /// A store sent the manifest's bytes: the first usable one gives the
    /// BSP to plan with; an unusable one makes the next store be asked
    /// soon.
    pub fn manifest_data(
        &mut self,
        from: &Address,
        bytes: &[u8],
        now: Instant,
        out: &mut Vec<Out>,
    ) {
        if self.top.is_some() {
            debug!(%from, "prefetcher ignores a second manifest");
            return;
        }
        match Manifest::decode(bytes) {
            Ok(manifest) => {
                self.top = Some(Arc::new(TopLevel::from_manifest(&manifest)));
                self.ask_at = None;
                info!(voxels = manifest.voxels.len(), %from, "prefetcher has the manifest");
                self.plan_next(out);
            }
            Err(e) => {
                warn!(%from, "unusable manifest, asking another store: {e}");
                self.ask_at = Some(now + MANIFEST_TIMEOUT / 4);
            }
        }
    }

    /// The scheduler completed a frame: its owners replace older ones, and
    /// its misses decide whether the caches count as warm.
    pub fn tile_owners(&mut self, o: TileOwners, out: &mut Vec<Out>) {
        if self.owners.as_ref().is_some_and(|old| old.frame >= o.frame) {
            debug!(frame = o.frame, "old tile owners ignored");
            return;
        }
        self.quiet = if o.misses == 0 {
            self.quiet.saturating_add(1)
        } else {
            0
        };
        self.owners_camera = self
            .recent
            .iter()
            .find(|(s, _)| *s == o.frame)
            .map(|(_, c)| *c);
        self.owners = Some(o);
        self.plan_next(out);
    }

    /// The assigner forwarded a camera update: kept if newer than the last,
    /// with the oldest beyond [`RECENT_CAMERAS`] dropped.
    pub fn camera_update(&mut self, u: CameraUpdate, out: &mut Vec<Out>) {
        if self.cams.last().is_some_and(|(s, _)| *s >= u.seq) {
            debug!(seq = u.seq, "old camera update ignored");
            return;
        }
        self.recent.push_back((u.seq, u.camera));
        if self.recent.len() > RECENT_CAMERAS {
            self.recent.pop_front();
        }
        self.cams.push((u.seq, u.camera));
        if self.cams.len() > 2 {
            self.cams.remove(0);
        }
        self.plan_next(out);
    }

    /// The hints of `frame` are planned: one per client node.
    pub fn planned(&mut self, frame: u64, plan: Vec<(Name, Vec<u32>)>, out: &mut Vec<Out>) {
        for (node, voxels) in plan {
            let to = Address::new(node, Name::new(CLIENT).expect("valid actor name"));
            out.push(Out::Hint(
                to,
                PrefetchHint {
                    frame,
                    voxels: PackedU32(voxels),
                },
            ));
        }
    }

    /// A hint of `voxels` ids has left.
    pub fn hint_sent(&mut self, voxels: usize) {
        self.summary.hints += 1;
        self.summary.voxels_hinted += voxels as u64;
    }

    /// Plans the frame after the newest camera, once, when the manifest,
    /// tile owners and a camera are at hand, unless the caches are warm
    /// (see [`plans_frame`]) or every client holds the whole model.
    fn plan_next(&mut self, out: &mut Vec<Out>) {
        let (Some(top), Some(owners), Some(&(seq, last))) =
            (&self.top, &self.owners, self.cams.last())
        else {
            return;
        };
        let next = seq + 1;
        if self.hinted_for == Some(next) {
            return;
        }
        self.hinted_for = Some(next);
        if !plans_frame(self.quiet, next) {
            self.summary.frames_skipped += 1;
            debug!(frame = next, quiet = self.quiet, "caches warm: no plan");
            return;
        }
        let whole = owners.holds_model.as_slice();
        if owners.clients.as_slice().iter().all(|c| whole.contains(c)) {
            self.summary.frames_skipped += 1;
            debug!(frame = next, "every client holds the model: no plan");
            return;
        }
        let prev = (self.cams.len() == 2).then(|| (self.cams[0].0, &self.cams[0].1));
        let camera = predict_camera(prev, (seq, &last), next);
        if dray_protocol::check_camera(&camera).is_err() {
            debug!(frame = next, "no usable camera to predict from");
            return;
        }
        let o = &self.opts;
        out.push(Out::Plan(Box::new(Plan {
            frame: next,
            camera,
            top: top.clone(),
            owners: owners.clone(),
            owners_camera: self.owners_camera,
            policy: o.policy,
            size: (o.width, o.height),
            step: o.step,
            voxels_per_ray: o.voxels_per_ray,
        })));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::names::{self, Shard, StoreRoutes};
    use crate::scheduler::prefetch::{WARM_AFTER, WARM_STRIDE};
    use dray_protocol::{Blob, BoundedVec, PackedF32};
    use dray_scene::db::manifest::{BspNode, BuildParams, VoxelEntry, FORMAT_VERSION};
    use dray_scene::Aabb;
    use glam::Vec3;

    fn prefetcher(now: Instant) -> Prefetcher {
        let stores = StoreRoutes::new(vec![
            (Shard::ALL, names::store(0)),
            (Shard::ALL, names::store(1)),
        ])
        .unwrap();
        Prefetcher::new(
            PrefetcherOptions {
                stores,
                step: 8,
                voxels_per_ray: 2,
                width: 64,
                height: 64,
                policy: TilePolicy::Affinity,
            },
            now,
        )
    }

    /// A manifest of two voxels split at x = 0, each holding content in a
    /// box beside the plane: voxel 0 left of it, voxel 1 right of it.
    fn two_voxels() -> Vec<u8> {
        let voxel = |i: u64, x0: f32, x1: f32| VoxelEntry {
            bounds: Aabb::new(
                Vec3::new(x0.min(0.0), -1.0, -1.0),
                Vec3::new(x1.max(0.0), 1.0, 1.0),
            ),
            content: Aabb::new(Vec3::new(x0, -1.0, -1.0), Vec3::new(x1, 1.0, 1.0)),
            triangles: 1,
            vertices: 3,
            raw_bytes: 100,
            compressed_bytes: 10,
            offset: 10 * i,
            checksum: 0,
            depth: 1,
        };
        let bounds = Aabb::new(Vec3::new(-2.0, -1.0, -1.0), Vec3::new(2.0, 1.0, 1.0));
        Manifest {
            format_version: FORMAT_VERSION,
            model_bounds: bounds,
            root_bounds: bounds,
            input_triangles: 2,
            stored_triangles: 2,
            build: BuildParams {
                inputs: Vec::new(),
                max_triangles: 1,
                max_depth: 1,
                copies: [1, 1, 1],
                spacing: 0.0,
                zstd_level: 3,
            },
            nodes: vec![
                BspNode::Split {
                    axis: 0,
                    pos: 0.0,
                    left: 1,
                    right: 2,
                },
                BspNode::Leaf { voxel: Some(0) },
                BspNode::Leaf { voxel: Some(1) },
            ],
            voxels: vec![voxel(0, -2.0, -0.5), voxel(1, 0.5, 2.0)],
        }
        .encode()
    }

    /// A camera 5 units up the z axis, `x` to the side, looking down it.
    fn camera_at(x: f32) -> Camera {
        Camera {
            eye: [x, 0.0, 5.0],
            look: [x, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        }
    }

    fn update(seq: u64) -> CameraUpdate {
        CameraUpdate {
            seq,
            camera: camera_at(0.0),
            sample: 0,
            format: None,
        }
    }

    /// Frame `frame` of 64 × 64 pixels in four 32-pixel tiles: the left
    /// column rendered by `client-0`, the right one by `client-1`, no hits.
    fn owners(frame: u64, misses: u64, holds_model: &[usize]) -> TileOwners {
        TileOwners {
            frame,
            width: 64,
            height: 64,
            tile_size: 32,
            owners: PackedU32(vec![0, 1, 0, 1]),
            clients: BoundedVec::new(vec![names::client_node(0), names::client_node(1)]).unwrap(),
            hit_counts: Blob(vec![0; 4]),
            hits: PackedF32(Vec::new()),
            misses,
            holds_model: BoundedVec::new(
                holds_model.iter().map(|&i| names::client_node(i)).collect(),
            )
            .unwrap(),
        }
    }

    /// The frames of the plans among `out`, which is emptied.
    fn plans(out: &mut Vec<Out>) -> Vec<u64> {
        out.drain(..)
            .filter_map(|o| match o {
                Out::Plan(p) => Some(p.frame),
                _ => None,
            })
            .collect()
    }

    /// A prefetcher with the manifest, having seen camera 1 and the owners
    /// of frame 1 (no misses, none holding the model): frame 2 planned.
    fn ready(now: Instant) -> Prefetcher {
        let mut p = prefetcher(now);
        let mut out = Vec::new();
        p.manifest_data(&names::store(0), &two_voxels(), now, &mut out);
        p.camera_update(update(1), &mut out);
        p.tile_owners(owners(1, 1, &[]), &mut out);
        assert_eq!(plans(&mut out), [2]);
        p
    }

    #[test]
    fn no_hints_before_the_manifest() {
        let now = Instant::now();
        let mut p = prefetcher(now);
        let mut out = Vec::new();
        p.camera_update(update(1), &mut out);
        p.tile_owners(owners(1, 1, &[]), &mut out);
        p.camera_update(update(2), &mut out);
        assert!(out.is_empty(), "{out:?}");
        p.manifest_data(&names::store(1), &two_voxels(), now, &mut out);
        assert_eq!(plans(&mut out), [3], "the frame after the newest camera");
        assert_eq!(p.deadline(), None, "no more asking");
    }

    #[test]
    fn no_hints_without_tile_owners_or_a_camera() {
        let now = Instant::now();
        let mut p = prefetcher(now);
        let mut out = Vec::new();
        p.manifest_data(&names::store(0), &two_voxels(), now, &mut out);
        p.camera_update(update(1), &mut out);
        assert!(out.is_empty(), "{out:?}");

        let mut p = prefetcher(now);
        p.manifest_data(&names::store(0), &two_voxels(), now, &mut out);
        p.tile_owners(owners(1, 1, &[]), &mut out);
        assert!(out.is_empty(), "{out:?}");
        p.camera_update(update(1), &mut out);
        assert_eq!(plans(&mut out), [2]);
    }

    #[test]
    fn the_manifest_is_asked_of_each_store_in_turn_until_one_answers() {
        let now = Instant::now();
        let mut p = prefetcher(now);
        let mut out = Vec::new();
        assert_eq!(p.deadline(), Some(now), "asked at once");
        let asked = |out: &mut Vec<Out>| -> Vec<Address> {
            out.drain(..)
                .filter_map(|o| match o {
                    Out::FetchManifest(to) => Some(to),
                    _ => None,
                })
                .collect()
        };
        p.ask_due(now, &mut out);
        assert_eq!(asked(&mut out), [names::store(0)]);
        assert_eq!(p.deadline(), Some(now + MANIFEST_TIMEOUT));
        p.ask_due(now, &mut out);
        p.ask_due(now, &mut out);
        assert_eq!(asked(&mut out), [names::store(1), names::store(0)]);
        // Store 1 comes back up: asked now, and next.
        let later = now + Duration::from_secs(1);
        p.peer_up(&names::store_node(1), later);
        assert_eq!(p.deadline(), Some(later));
        p.peer_up(&names::client_node(0), now);
        assert_eq!(p.deadline(), Some(later), "not a store");
        p.ask_due(later, &mut out);
        assert_eq!(asked(&mut out), [names::store(1)]);
        // An unusable manifest: the next store soon.
        p.manifest_data(&names::store(1), b"not a manifest", later, &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(p.deadline(), Some(later + MANIFEST_TIMEOUT / 4));
        p.manifest_data(&names::store(0), &two_voxels(), later, &mut out);
        assert_eq!(p.deadline(), None);
        p.peer_up(&names::store_node(0), later);
        assert_eq!(p.deadline(), None, "nothing more to ask");
    }

    #[test]
    fn hints_planned_on_tile_owners_go_to_the_predicted_clients() {
        let now = Instant::now();
        let mut p = prefetcher(now);
        let mut out = Vec::new();
        p.manifest_data(&names::store(0), &two_voxels(), now, &mut out);
        p.camera_update(update(1), &mut out);
        p.tile_owners(owners(1, 1, &[]), &mut out);
        let [Out::Plan(plan)] = &out[..] else {
            panic!("one plan: {out:?}");
        };
        assert_eq!((plan.frame, plan.camera), (2, camera_at(0.0)));
        assert_eq!(plan.owners_camera, Some(camera_at(0.0)), "frame 1's");
        // Each column keeps its client; each sees the voxel on its side.
        let hints = plan.run();
        assert_eq!(
            hints,
            [
                (names::client_node(0), vec![0]),
                (names::client_node(1), vec![1])
            ]
        );
        out.clear();
        p.planned(2, hints, &mut out);
        let sent: Vec<(Address, u64, Vec<u32>)> = out
            .drain(..)
            .map(|o| match o {
                Out::Hint(to, h) => (to, h.frame, h.voxels.0),
                other => panic!("not a hint: {other:?}"),
            })
            .collect();
        assert_eq!(
            sent,
            [
                (names::client(0), 2, vec![0]),
                (names::client(1), 2, vec![1])
            ]
        );
        p.hint_sent(1);
        p.hint_sent(1);
        assert_eq!((p.summary().hints, p.summary().voxels_hinted), (2, 2));
        // Each frame is planned once.
        p.tile_owners(owners(2, 1, &[]), &mut out);
        assert!(out.is_empty(), "{out:?}");
    }

    #[test]
    fn clients_that_hold_the_whole_model_get_no_hints() {
        let now = Instant::now();
        let mut p = ready(now);
        let mut out = Vec::new();
        p.tile_owners(owners(2, 1, &[1]), &mut out);
        p.camera_update(update(2), &mut out);
        let [Out::Plan(plan)] = &out[..] else {
            panic!("one plan: {out:?}");
        };
        assert_eq!(plan.run(), [(names::client_node(0), vec![0])]);
        out.clear();
        p.tile_owners(owners(3, 1, &[0, 1]), &mut out);
        p.camera_update(update(3), &mut out);
        assert!(out.is_empty(), "every client holds it: no plan");
        assert_eq!(p.summary().frames_skipped, 1);
    }

    #[test]
    fn warm_caches_plan_every_fourth_frame_until_a_miss() {
        let now = Instant::now();
        let mut p = ready(now);
        let mut out = Vec::new();
        for frame in 2..2 + u64::from(WARM_AFTER) {
            p.tile_owners(owners(frame, 0, &[]), &mut out);
        }
        out.clear();
        let mut planned = Vec::new();
        for seq in 2..12 {
            p.camera_update(update(seq), &mut out);
            planned.extend(plans(&mut out));
        }
        assert_eq!(planned, [4, 8, 12], "every {WARM_STRIDE}th");
        assert_eq!(p.summary().frames_skipped, 10 - 3);
        // A frame with a miss: every frame again.
        p.tile_owners(owners(2 + u64::from(WARM_AFTER), 3, &[]), &mut out);
        p.camera_update(update(12), &mut out);
        p.camera_update(update(13), &mut out);
        assert_eq!(plans(&mut out), [13, 14]);
    }

    #[test]
    fn old_tile_owners_change_nothing() {
        let now = Instant::now();
        let mut p = ready(now);
        let mut out = Vec::new();
        for frame in 2..2 + u64::from(WARM_AFTER) {
            p.tile_owners(owners(frame, 0, &[]), &mut out);
        }
        // An older frame with misses would have ended the warm run.
        p.tile_owners(owners(3, 5, &[]), &mut out);
        p.tile_owners(owners(1 + u64::from(WARM_AFTER), 5, &[]), &mut out);
        assert_eq!(p.quiet, WARM_AFTER);
        assert_eq!(
            p.owners.as_ref().map(|o| o.frame),
            Some(1 + u64::from(WARM_AFTER))
        );
    }

    #[test]
    fn old_camera_updates_are_dropped_and_the_state_stays_bounded() {
        let now = Instant::now();
        let mut p = ready(now);
        let mut out = Vec::new();
        let last = 3 * RECENT_CAMERAS as u64;
        for seq in 2..=last {
            p.camera_update(
                CameraUpdate {
                    seq,
                    camera: camera_at(seq as f32 * 0.01),
                    sample: 0,
                    format: None,
                },
                &mut out,
            );
        }
        assert_eq!(p.recent.len(), RECENT_CAMERAS);
        assert_eq!(
            p.recent.front().map(|r| r.0),
            Some(last + 1 - RECENT_CAMERAS as u64)
        );
        assert_eq!(
            p.cams.iter().map(|c| c.0).collect::<Vec<_>>(),
            [last - 1, last]
        );
        // Not newer than the last: ignored.
        out.clear();
        p.camera_update(update(last), &mut out);
        p.camera_update(update(5), &mut out);
        assert!(out.is_empty(), "{out:?}");
        assert_eq!(p.cams.last().map(|c| c.0), Some(last));
        // Owners of a frame whose camera was dropped: no camera for them.
        p.tile_owners(owners(5, 1, &[]), &mut out);
        assert_eq!(p.owners_camera, None);
        // Owners of a recent frame: its camera.
        p.tile_owners(owners(last - 2, 1, &[]), &mut out);
        assert_eq!(p.owners_camera, Some(camera_at((last - 2) as f32 * 0.01)));
    }
}
