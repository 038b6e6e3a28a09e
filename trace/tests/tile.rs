//! `render_tile` against `render`: every pixel's color, depth and
//! primitive id bit for bit, whatever the tile's size and origin, the
//! instruction set, and the order and timing in which voxels arrive.

mod common;

use common::{cameras, isas, plant, real_model, settings, Model};
use dray_scene::rng::Rng;
use dray_trace::accel::{PreparedVoxel, ResidentSource, VoxelRef, VoxelSource};
use dray_trace::camera::Camera;
use dray_trace::image::Accumulator;
use dray_trace::render::{
    render, render_sample, render_samples, Frame, Isa, Packets, ReflectRule, RenderSettings,
};
use dray_trace::tile::{
    render_tile, render_tile_sample, LoadError, MissMode, Rect, TileImage, VoxelLoader,
};
use futures::future::BoxFuture;
use std::collections::VecDeque;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// Every voxel resident: `load` is never needed.
struct Resident<'a>(&'a ResidentSource);

impl VoxelSource for Resident<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        self.0.voxel(id)
    }
}

impl VoxelLoader for Resident<'_> {
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>> {
        let v = self.0.shared(id).ok_or(LoadError {
            voxel: id,
            message: "no such voxel".into(),
        });
        Box::pin(async move { v })
    }
}

/// A cache of `capacity` voxels, least recently used evicted first, that
/// delivers each voxel after a random delay (so in random order).
struct TinyCache<'a> {
    all: &'a ResidentSource,
    capacity: usize,
    /// Most recently used at the back.
    lru: Mutex<VecDeque<Arc<PreparedVoxel>>>,
    rng: Mutex<Rng>,
    loads: Mutex<u64>,
}

impl<'a> TinyCache<'a> {
    fn new(all: &'a ResidentSource, capacity: usize, seed: u64) -> TinyCache<'a> {
        TinyCache {
            all,
            capacity,
            lru: Mutex::new(VecDeque::new()),
            rng: Mutex::new(Rng::new(seed)),
            loads: Mutex::new(0),
        }
    }
}

impl VoxelSource for TinyCache<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        let mut lru = self.lru.lock().unwrap();
        let k = lru.iter().position(|v| v.id == id)?;
        let v = lru.remove(k).unwrap();
        lru.push_back(v.clone());
        Some(VoxelRef::Shared(v))
    }
}

impl VoxelLoader for TinyCache<'_> {
    fn load(&self, id: u32) -> BoxFuture<'_, Result<Arc<PreparedVoxel>, LoadError>> {
        let delay = Duration::from_micros(self.rng.lock().unwrap().int(0, 20_000) as u64);
        *self.loads.lock().unwrap() += 1;
        Box::pin(async move {
            tokio::time::sleep(delay).await;
            let v = self.all.shared(id).ok_or(LoadError {
                voxel: id,
                message: "no such voxel".into(),
            })?;
            let mut lru = self.lru.lock().unwrap();
            lru.retain(|x| x.id != id);
            lru.push_back(v.clone());
            while lru.len() > self.capacity {
                lru.pop_front();
            }
            Ok(v)
        })
    }
}

/// Shading, shadows and two mirror bounces off every surface.
fn shaded(isa: Isa, m: &Model) -> RenderSettings {
    RenderSettings {
        shade: true,
        shadows: true,
        reflections: 2,
        reflective: ReflectRule::All,
        ..settings(isa, m)
    }
}

/// Every rect of a `tw`×`th` grid over the image, from origin (`ox`, `oy`)
/// (the strips left and above it too).
fn grid(cam: &Camera, tw: u32, th: u32, ox: u32, oy: u32) -> Vec<Rect> {
    let cuts = |size: u32, step: u32, origin: u32| {
        let mut v = vec![0];
        let mut c = origin % step;
        if c == 0 {
            c = step;
        }
        while c < size {
            v.push(c);
            c += step;
        }
        v.push(size);
        v
    };
    let xs = cuts(cam.width, tw, ox);
    let ys = cuts(cam.height, th, oy);
    let mut rects = Vec::new();
    for y in ys.windows(2) {
        for x in xs.windows(2) {
            rects.push(Rect {
                x0: x[0],
                y0: y[0],
                width: x[1] - x[0],
                height: y[1] - y[0],
            });
        }
    }
    rects
}

/// The tile's pixels equal the frame's, bit for bit.
fn check_tile(frame: &Frame, tile: &TileImage, what: &str) {
    let r = tile.rect;
    assert_eq!(tile.rgba.len(), (r.width * r.height) as usize);
    for y in 0..r.height {
        for x in 0..r.width {
            let k = (y * r.width + x) as usize;
            let f = ((r.y0 + y) * frame.width + r.x0 + x) as usize;
            let at = || format!("{what}: pixel ({}, {})", r.x0 + x, r.y0 + y);
            assert_eq!(tile.primid[k], frame.primid[f], "{}", at());
            assert_eq!(
                tile.depth[k].to_bits(),
                frame.depth[f].to_bits(),
                "{}",
                at()
            );
            assert_eq!(tile.rgba[k], frame.rgba[f], "{}", at());
        }
    }
}

/// Renders every rect with `loader` and checks each against `frame`;
/// returns the summed stats' misses.
#[allow(clippy::too_many_arguments)]
async fn check_rects(
    m: &Model,
    loader: &dyn VoxelLoader,
    cam: &Camera,
    s: &RenderSettings,
    frame: &Frame,
    rects: &[Rect],
    mode: MissMode,
    what: &str,
) -> u64 {
    let mut misses = 0;
    let mut rays = 0;
    for &rect in rects {
        let tile = render_tile(&m.top, loader, cam, rect, s, mode)
            .await
            .unwrap_or_else(|e| panic!("{what}: {rect:?}: {e}"));
        assert_eq!(tile.rect, rect);
        check_tile(frame, &tile, &format!("{what} {rect:?}"));
        misses += tile.stats.misses;
        rays += tile.stats.primary_rays;
    }
    let covered: u64 = rects.iter().map(|r| (r.width * r.height) as u64).sum();
    assert_eq!(rays, covered, "{what}: one primary ray per pixel");
    misses
}

/// The frame `render` gives, with the unshaded grey filled in.
fn reference(m: &Model, cam: &Camera, s: &RenderSettings) -> Frame {
    let mut frame = render(&m.top, &m.source, cam, s).unwrap();
    frame.fill_grey(s.scene_diagonal);
    frame
}

fn rect_grids(cam: &Camera) -> Vec<(String, Vec<Rect>)> {
    vec![
        ("32x32".into(), grid(cam, 32, 32, 0, 0)),
        ("16x8 from (5, 3)".into(), grid(cam, 16, 8, 5, 3)),
        ("7x13 from (2, 6)".into(), grid(cam, 7, 13, 2, 6)),
        ("20x7".into(), grid(cam, 20, 7, 0, 0)),
    ]
}

/// A few single pixels spread over the image.
fn pixels(cam: &Camera, seed: u64) -> Vec<Rect> {
    let mut rng = Rng::new(seed);
    (0..40)
        .map(|_| Rect {
            x0: rng.below(cam.width),
            y0: rng.below(cam.height),
            width: 1,
            height: 1,
        })
        .collect()
}

#[tokio::test]
async fn resident_tiles_equal_the_frame_on_every_isa() {
    let m = plant(20_000);
    let loader = Resident(&m.source);
    for isa in isas() {
        for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
            for (name, s) in [("shaded", shaded(isa, &m)), ("primary", settings(isa, &m))] {
                let frame = reference(&m, cam, &s);
                let mut grids = rect_grids(cam);
                grids.push(("1x1".into(), pixels(cam, k as u64)));
                for (g, rects) in grids {
                    let what = format!("{isa:?} camera {k} {name} {g}");
                    let misses = check_rects(
                        &m,
                        &loader,
                        cam,
                        &s,
                        &frame,
                        &rects,
                        MissMode::Suspend,
                        &what,
                    )
                    .await;
                    assert_eq!(misses, 0, "{what}");
                }
            }
        }
    }
}

#[tokio::test]
async fn voxel_colored_tiles_equal_the_frame() {
    let m = plant(20_000);
    let loader = Resident(&m.source);
    for isa in isas() {
        let s = RenderSettings {
            voxel_colors: true,
            ..shaded(isa, &m)
        };
        for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
            let frame = reference(&m, cam, &s);
            for (g, rects) in rect_grids(cam) {
                let what = format!("{isa:?} camera {k} voxel colors {g}");
                check_rects(
                    &m,
                    &loader,
                    cam,
                    &s,
                    &frame,
                    &rects,
                    MissMode::Suspend,
                    &what,
                )
                .await;
            }
        }
    }
}

#[tokio::test]
async fn bunny_tiles_equal_the_frame() {
    let m = real_model("stanford-bunny");
    let loader = Resident(&m.source);
    let isa = Isa::detect();
    for (k, cam) in cameras(&m, 80, 60).iter().enumerate() {
        for (name, s) in [("shaded", shaded(isa, &m)), ("primary", settings(isa, &m))] {
            let frame = reference(&m, cam, &s);
            for (g, rects) in rect_grids(cam) {
                let what = format!("bunny camera {k} {name} {g}");
                check_rects(
                    &m,
                    &loader,
                    cam,
                    &s,
                    &frame,
                    &rects,
                    MissMode::Suspend,
                    &what,
                )
                .await;
            }
        }
    }
}

/// A jittered sample's tiles equal that sample's frame, shaded and grey,
/// with voxels arriving in random order; `render_samples` is sample 0's
/// depth and ids with the samples' colours averaged.
#[tokio::test(start_paused = true)]
async fn sample_tiles_equal_the_sample_frame() {
    let m = plant(20_000);
    let cam = cameras(&m, 64, 48)[1];
    for isa in isas() {
        let s = shaded(isa, &m);
        let mut acc = Accumulator::new(cam.width, cam.height);
        for sample in 0..3 {
            let frame = render_sample(&m.top, &m.source, &cam, sample, &s).unwrap();
            acc.add(&frame.rgba).unwrap();
            let mut grey =
                render_sample(&m.top, &m.source, &cam, sample, &settings(isa, &m)).unwrap();
            grey.fill_grey(s.scene_diagonal);
            for (g, rects) in rect_grids(&cam).into_iter().take(2) {
                for (name, s, frame) in [
                    ("shaded", &s, &frame),
                    ("primary", &settings(isa, &m), &grey),
                ] {
                    let loader = TinyCache::new(&m.source, 3, 7 + u64::from(sample));
                    for &rect in &rects {
                        let what = format!("{isa:?} {name} sample {sample} {g} {rect:?}");
                        let tile = render_tile_sample(
                            &m.top,
                            &loader,
                            &cam,
                            sample,
                            rect,
                            s,
                            MissMode::Suspend,
                        )
                        .await
                        .unwrap_or_else(|e| panic!("{what}: {e}"));
                        check_tile(frame, &tile, &what);
                    }
                }
            }
        }
        let first = render(&m.top, &m.source, &cam, &s).unwrap();
        let one = render_samples(&m.top, &m.source, &cam, 1, &s).unwrap();
        assert!(
            one.rgba == first.rgba && one.primid == first.primid,
            "{isa:?}: one sample"
        );
        let three = render_samples(&m.top, &m.source, &cam, 3, &s).unwrap();
        assert!(
            three.rgba == acc.image(),
            "{isa:?}: the mean of the samples"
        );
        assert!(
            three.rgba != first.rgba,
            "{isa:?}: the samples changed nothing"
        );
        assert_eq!(three.primid, first.primid, "{isa:?}: sample 0's ids");
        assert!(
            three
                .depth
                .iter()
                .zip(&first.depth)
                .all(|(a, b)| a.to_bits() == b.to_bits()),
            "{isa:?}: sample 0's depth"
        );
        assert_eq!(three.stats.primary_rays, 3 * first.stats.primary_rays);
    }
}

/// A cache of three voxels, voxels delivered after random delays (so in
/// random order, and often evicted before the packets that waited for
/// them resume): every tile completes, bit-identical, in both modes.
#[tokio::test(start_paused = true)]
async fn tiny_cache_random_arrivals_give_identical_tiles() {
    let m = plant(20_000);
    let mut total_misses = 0;
    for isa in isas() {
        let s = shaded(isa, &m);
        for (k, cam) in cameras(&m, 64, 48).iter().enumerate() {
            let frame = reference(&m, cam, &s);
            for (mode, grids) in [
                (MissMode::Suspend, rect_grids(cam)),
                (
                    MissMode::Block,
                    vec![("16x16".into(), grid(cam, 16, 16, 3, 9))],
                ),
            ] {
                for (g, rects) in grids {
                    let loader = TinyCache::new(&m.source, 3, 11 + k as u64);
                    let what = format!("{isa:?} camera {k} {mode:?} tiny cache {g}");
                    let misses =
                        check_rects(&m, &loader, cam, &s, &frame, &rects, mode, &what).await;
                    assert!(misses > 0, "{what}: the cache never missed");
                    total_misses += misses;
                }
            }
            // Primary only, and single pixels.
            let p = settings(isa, &m);
            let frame = reference(&m, cam, &p);
            let loader = TinyCache::new(&m.source, 3, 5);
            let what = format!("{isa:?} camera {k} primary tiny cache");
            check_rects(
                &m,
                &loader,
                cam,
                &p,
                &frame,
                &grid(cam, 16, 8, 0, 0),
                MissMode::Suspend,
                &what,
            )
            .await;
            check_rects(
                &m,
                &loader,
                cam,
                &s,
                &reference(&m, cam, &s),
                &pixels(cam, 9),
                MissMode::Suspend,
                &what,
            )
            .await;
        }
    }
    assert!(
        total_misses > 500,
        "only {total_misses} misses: the test is too easy"
    );
}

/// Tiles of 32-lane packets and of sparse 16-lane ones, with voxels
/// arriving in random order, give the pixels of 16-lane packets (shaded,
/// shadows, reflections), and so do frames of sparse packets, with AVX-512
/// and AVX2 alike.
#[tokio::test(start_paused = true)]
async fn wide_and_sparse_packet_tiles_equal_the_narrow_frame() {
    let m = plant(20_000);
    for isa in isas().into_iter().filter(|&i| i != Isa::Portable) {
        wide_and_sparse_tiles(&m, isa).await;
    }
}

async fn wide_and_sparse_tiles(m: &Model, isa: Isa) {
    let narrow = RenderSettings {
        packets: Packets::Narrow,
        ..shaded(isa, m)
    };
    for packets in [Packets::Wide, Packets::Sparse] {
        let other = RenderSettings {
            packets,
            ..narrow.clone()
        };
        for (k, cam) in cameras(m, 64, 48).iter().enumerate() {
            let frame = reference(m, cam, &narrow);
            let whole = reference(m, cam, &other);
            assert_eq!(
                frame.rgba, whole.rgba,
                "{isa:?} camera {k} {packets:?} frame"
            );
            assert_eq!(
                frame.primid, whole.primid,
                "{isa:?} camera {k} {packets:?} frame"
            );
            for (g, rects) in rect_grids(cam) {
                let loader = TinyCache::new(&m.source, 3, 7 + k as u64);
                let what = format!("{isa:?} camera {k} {packets:?} tiles {g}");
                check_rects(
                    m,
                    &loader,
                    cam,
                    &other,
                    &frame,
                    &rects,
                    MissMode::Suspend,
                    &what,
                )
                .await;
            }
        }
    }
}

/// Shadow packets that first try the triangle that blocked the packet
/// before change no pixel: frames with and without it are identical for
/// every instruction set, and so are tiles traced with it while voxels
/// arrive in random order. The try does spare traversals.
#[tokio::test(start_paused = true)]
async fn trying_the_last_occluder_first_changes_no_pixel() {
    let m = plant(20_000);
    for isa in isas() {
        let with = shaded(isa, &m);
        let without = RenderSettings {
            occluder_cache: false,
            ..with.clone()
        };
        let mut skips = 0;
        for (k, cam) in cameras(&m, 64, 48).iter().enumerate() {
            let a = reference(&m, cam, &without);
            let b = reference(&m, cam, &with);
            let what = format!("{isa:?} camera {k}");
            assert_eq!(a.rgba, b.rgba, "{what}: colors");
            assert_eq!(a.stats.occluded, b.stats.occluded, "{what}");
            assert_eq!(a.stats.shadow_packets, b.stats.shadow_packets, "{what}");
            assert_eq!(a.stats.occluder_skips, 0, "{what}");
            skips += b.stats.occluder_skips;
            let rects = grid(cam, 16, 8, 5, 3);
            let loader = TinyCache::new(&m.source, 3, 5 + k as u64);
            check_rects(
                &m,
                &loader,
                cam,
                &with,
                &a,
                &rects,
                MissMode::Suspend,
                &format!("{what} tiles"),
            )
            .await;
        }
        assert!(skips > 0, "{isa:?}: no shadow packet skipped its traversal");
    }
}

/// Only blocks with a surface to light trace a shadow packet: the model
/// seen from outside traces some, the same camera turned round (nothing
/// but sky) none, for every instruction set.
#[test]
fn blocks_without_a_surface_trace_no_shadow_packet() {
    let m = plant(20_000);
    for isa in isas() {
        let s = shaded(isa, &m);
        let cam = cameras(&m, 64, 48)[0];
        let away = Camera {
            look: cam.eye + (cam.eye - cam.look),
            ..cam
        };
        let model = reference(&m, &cam, &s);
        assert!(
            model.stats.hits > 0 && model.stats.shadow_packets > 0,
            "{isa:?}"
        );
        let sky = reference(&m, &away, &s);
        assert_eq!(
            sky.stats.hits, 0,
            "{isa:?}: the turned camera sees the model"
        );
        assert_eq!(
            sky.stats.shadow_packets, 0,
            "{isa:?}: shadow packets under the sky"
        );
        assert_eq!(sky.stats.shadow_rays, 0, "{isa:?}");
    }
}

/// Tile statistics: rays counted once per pixel, one request per voxel
/// at a time, every voxel touched loaded.
#[tokio::test(start_paused = true)]
async fn tile_stats_count_rays_and_requests() {
    let m = plant(20_000);
    let cam = cameras(&m, 64, 48)[1];
    let s = shaded(Isa::detect(), &m);
    let rect = Rect {
        x0: 8,
        y0: 4,
        width: 32,
        height: 32,
    };
    let resident = render_tile(
        &m.top,
        &Resident(&m.source),
        &cam,
        rect,
        &s,
        MissMode::Suspend,
    )
    .await
    .unwrap();
    let st = &resident.stats;
    assert_eq!(st.primary_rays, 32 * 32);
    assert!(st.shadow_rays > 0 && st.reflection_rays > 0, "{st:?}");
    assert_eq!((st.misses, st.requested), (0, 0));
    assert_eq!(st.stall, Duration::ZERO);
    assert!(st.voxels_touched > 1);
    // A big cache: each voxel requested exactly once.
    let big = TinyCache::new(&m.source, 10_000, 1);
    let cold = render_tile(&m.top, &big, &cam, rect, &s, MissMode::Suspend)
        .await
        .unwrap();
    assert_eq!(cold.rgba, resident.rgba);
    let c = &cold.stats;
    assert_eq!(c.requested, c.voxels_touched as u64, "{c:?}");
    assert!(c.misses >= c.requested);
    assert_eq!(
        (c.primary_rays, c.shadow_rays, c.reflection_rays),
        (st.primary_rays, st.shadow_rays, st.reflection_rays)
    );
}

#[tokio::test]
async fn a_rect_outside_the_image_is_an_error() {
    let m = plant(10_000);
    let cam = cameras(&m, 64, 48)[0];
    let s = settings(Isa::Portable, &m);
    for rect in [
        Rect {
            x0: 60,
            y0: 0,
            width: 8,
            height: 8,
        },
        Rect {
            x0: 0,
            y0: 0,
            width: 0,
            height: 8,
        },
        Rect {
            x0: u32::MAX,
            y0: 0,
            width: 2,
            height: 2,
        },
    ] {
        let r = render_tile(
            &m.top,
            &Resident(&m.source),
            &cam,
            rect,
            &s,
            MissMode::Suspend,
        )
        .await;
        assert!(r.is_err(), "{rect:?}");
    }
}
