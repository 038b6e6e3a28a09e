//! The kernel against brute force: every pixel's primitive id and depth,
//! for every instruction set this CPU has, with and without suspension.

mod common;

use common::{cameras, isas, plant, real_model, settings, Model};
use dray_scene::geometry::{closer, intersect_triangle, Hit, Ray};
use dray_scene::rng::Rng;
use dray_trace::accel::{ResidentSource, VoxelRef, VoxelSource};
use dray_trace::camera::Camera;
use dray_trace::packet::{Occluder, Packet, Step, Traversal};
use dray_trace::render::{render, render_sample, Frame, Isa, Packets, RenderSettings};
use glam::Vec3;
use std::collections::{HashSet, VecDeque};
use std::sync::Mutex;

fn brute_force(tris: &[[Vec3; 3]], ray: &Ray) -> Option<Hit> {
    let mut best: Option<Hit> = None;
    for (i, p) in tris.iter().enumerate() {
        let limit = best.map_or(f32::INFINITY, |h| f32::from_bits(h.t.to_bits() + 1));
        if let Some(t) = intersect_triangle(ray, p, 0.0, limit) {
            best = closer(best, t, i as u32);
        }
    }
    best
}

/// Every pixel equals brute force exactly: same id, same distance bits.
fn check_against_brute_force(m: &Model, camera: &Camera, frame: &Frame, what: &str) {
    check_sample_against_brute_force(m, camera, 0, frame, what)
}

/// [`check_against_brute_force`] for sample `sample`'s rays.
fn check_sample_against_brute_force(
    m: &Model,
    camera: &Camera,
    sample: u32,
    frame: &Frame,
    what: &str,
) {
    let basis = camera.sample_basis(sample);
    let mut hits = 0;
    for y in 0..camera.height {
        for x in 0..camera.width {
            let k = (y * camera.width + x) as usize;
            let expected = brute_force(&m.tris, &basis.ray(x, y));
            let got = (frame.primid[k] != u32::MAX).then(|| Hit {
                t: frame.depth[k],
                id: frame.primid[k],
            });
            assert_eq!(got, expected, "{what}: pixel ({x}, {y})");
            hits += got.is_some() as usize;
        }
    }
    let pixels = (camera.width * camera.height) as usize;
    assert!(
        hits > pixels / 10,
        "{what}: only {hits} of {pixels} pixels hit"
    );
}

#[test]
fn packets_of_every_width_equal_brute_force() {
    // 16 and 32 lanes with AVX-512 and AVX2, sparse 16 with AVX-512 (8
    // lanes in the portable kernel), and the per-tile choice between them,
    // on every ISA the CPU has.
    let m = plant(20_000);
    for isa in isas() {
        for packets in [
            Packets::Narrow,
            Packets::Wide,
            Packets::Sparse,
            Packets::Auto,
        ] {
            for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
                let s = RenderSettings {
                    packets,
                    ..settings(isa, &m)
                };
                let frame = render(&m.top, &m.source, cam, &s).unwrap();
                let what = format!("{isa:?} {packets:?} camera {k}");
                check_against_brute_force(&m, cam, &frame, &what);
                if packets == Packets::Wide && isa != Isa::Portable {
                    assert!(
                        frame.stats.wide_tiles > 0,
                        "{what}: no tile was traced wide"
                    );
                }
                if packets == Packets::Sparse && isa == Isa::Avx512 {
                    assert!(
                        frame.stats.sparse_tiles > 0,
                        "{what}: no tile was traced sparse"
                    );
                }
            }
        }
    }
}

#[test]
fn plant_pixels_equal_brute_force_on_every_isa() {
    let m = plant(20_000);
    for isa in isas() {
        for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
            let frame = render(&m.top, &m.source, cam, &settings(isa, &m)).unwrap();
            check_against_brute_force(&m, cam, &frame, &format!("{isa:?} camera {k}"));
        }
    }
}

/// Jittered samples move every ray of the frame and still equal brute
/// force through the moved rays, on every ISA and every packet width.
#[test]
fn jittered_samples_equal_brute_force_on_every_isa() {
    let m = plant(20_000);
    let mut runs: Vec<(Isa, Packets)> = isas().into_iter().map(|i| (i, Packets::Auto)).collect();
    for isa in isas() {
        if isa != Isa::Portable {
            runs.push((isa, Packets::Wide));
        }
    }
    if Isa::detect() == Isa::Avx512 {
        runs.push((Isa::Avx512, Packets::Sparse));
    }
    for (isa, packets) in runs {
        let s = RenderSettings {
            packets,
            ..settings(isa, &m)
        };
        for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
            let sample = 1 + 3 * k as u32;
            let frame = render_sample(&m.top, &m.source, cam, sample, &s).unwrap();
            let what = format!("{isa:?} {packets:?} camera {k} sample {sample}");
            check_sample_against_brute_force(&m, cam, sample, &frame, &what);
            let centre = render(&m.top, &m.source, cam, &s).unwrap();
            assert_ne!(frame.depth, centre.depth, "{what}: the rays did not move");
        }
    }
}

#[test]
fn bunny_pixels_equal_brute_force() {
    let m = real_model("stanford-bunny");
    let isa = Isa::detect();
    for (k, cam) in cameras(&m, 80, 60).iter().enumerate() {
        let frame = render(&m.top, &m.source, cam, &settings(isa, &m)).unwrap();
        check_against_brute_force(&m, cam, &frame, &format!("bunny camera {k}"));
    }
}

/// A source that holds only the voxels delivered so far and records what
/// was asked for.
struct Delayed<'a> {
    all: &'a ResidentSource,
    resident: Mutex<HashSet<u32>>,
}

impl VoxelSource for Delayed<'_> {
    fn voxel(&self, id: u32) -> Option<VoxelRef<'_>> {
        if self.resident.lock().unwrap().contains(&id) {
            self.all.voxel(id)
        } else {
            None
        }
    }
}

/// Packets suspended on missing voxels, resumed in random order as voxels
/// arrive one by one in random order, end with bit-identical hits.
#[test]
fn suspension_in_random_order_gives_identical_hits() {
    let m = plant(30_000);
    let cam = cameras(&m, 64, 48)[1];
    let reference = render(&m.top, &m.source, &cam, &settings(Isa::Portable, &m)).unwrap();
    let basis = cam.basis();
    let delayed = Delayed {
        all: &m.source,
        resident: Mutex::new(HashSet::new()),
    };
    let mut rng = Rng::new(77);
    // Every 4x2 block of the image as a packet.
    type Pixels = [(u32, u32); 8];
    let mut waiting: Vec<(u32, Traversal<8>, Packet<8>, Pixels)> = Vec::new();
    let mut done: Vec<(Packet<8>, Pixels)> = Vec::new();
    let mut ready: VecDeque<(Traversal<8>, Packet<8>, Pixels)> = VecDeque::new();
    for by in (0..cam.height).step_by(2) {
        for bx in (0..cam.width).step_by(4) {
            let mut px = [(0, 0); 8];
            let mut dirs = [Vec3::ZERO; 8];
            for i in 0..8 {
                px[i] = (bx + i as u32 % 4, by + i as u32 / 4);
                dirs[i] = basis.direction(px[i].0, px[i].1);
            }
            let packet = Packet::<8>::new(&[basis.eye; 8], &dirs, 0.0, f32::INFINITY);
            ready.push_back((Traversal::default(), packet, px));
        }
    }
    let mut suspensions = 0;
    let mut requested: Vec<u32> = Vec::new();
    loop {
        while let Some((mut trav, mut packet, px)) = ready.pop_front() {
            match trav.run(&mut packet, &m.top, &delayed) {
                Step::Done => done.push((packet, px)),
                Step::Missing(id) => {
                    suspensions += 1;
                    if !requested.contains(&id) {
                        requested.push(id);
                    }
                    waiting.push((id, trav, packet, px));
                }
            }
        }
        if requested.is_empty() {
            break;
        }
        // Deliver one requested voxel, chosen at random, and resume its
        // packets in random order.
        let id = requested.swap_remove(rng.below(requested.len() as u32) as usize);
        delayed.resident.lock().unwrap().insert(id);
        let mut resumed: Vec<_> = Vec::new();
        let mut k = 0;
        while k < waiting.len() {
            if waiting[k].0 == id {
                resumed.push(waiting.swap_remove(k));
            } else {
                k += 1;
            }
        }
        while !resumed.is_empty() {
            let (_, trav, packet, px) =
                resumed.swap_remove(rng.below(resumed.len() as u32) as usize);
            ready.push_back((trav, packet, px));
        }
    }
    assert!(waiting.is_empty());
    assert!(
        suspensions > 100,
        "only {suspensions} suspensions: the test is too easy"
    );
    for (packet, px) in done {
        for (i, &(x, y)) in px.iter().enumerate() {
            let k = (y * cam.width + x) as usize;
            assert_eq!(packet.id[i], reference.primid[k], "pixel ({x}, {y})");
            let t = if packet.hit(i) {
                packet.t[i]
            } else {
                f32::INFINITY
            };
            assert_eq!(
                t.to_bits(),
                reference.depth[k].to_bits(),
                "pixel ({x}, {y})"
            );
        }
    }
}

/// Whether some triangle of the model lies on `ray` beyond `tmin`.
fn blocked_by_brute_force(m: &Model, ray: &Ray, tmin: f32) -> bool {
    m.tris
        .iter()
        .any(|p| intersect_triangle(ray, p, tmin, f32::INFINITY).is_some())
}

/// Shadow (any-hit) packets agree with brute force: a lane is occluded
/// exactly when some triangle lies on its ray beyond `tmin`.
#[test]
fn any_hit_packets_equal_brute_force() {
    let m = plant(20_000);
    let b = m.db.manifest.model_bounds;
    let mut rng = Rng::new(3);
    let mut occluded = 0;
    for _ in 0..300 {
        let mut origins = [Vec3::ZERO; 8];
        let mut dirs = [Vec3::ZERO; 8];
        let base = Vec3::new(
            rng.range(b.min[0], b.max[0]),
            rng.range(b.min[1], b.max[1]),
            rng.range(b.min[2], b.max[2]),
        );
        let light = Vec3::new(rng.range(-1.0, 1.0), 1.0, rng.range(-1.0, 1.0)).normalize();
        for i in 0..8 {
            origins[i] = base + Vec3::new(rng.range(-1.0, 1.0), 0.0, rng.range(-1.0, 1.0));
            dirs[i] = light;
        }
        let tmin = 1e-4 * b.diagonal();
        let mut packet = Packet::<8>::new(&origins, &dirs, tmin, f32::INFINITY);
        packet.any_hit = true;
        let mut trav = Traversal::<8>::default();
        assert_eq!(trav.run(&mut packet, &m.top, &m.source), Step::Done);
        for i in 0..8 {
            let ray = Ray {
                origin: origins[i],
                dir: dirs[i],
            };
            let blocked = blocked_by_brute_force(&m, &ray, tmin);
            assert_eq!(packet.occluded(i), blocked, "lane {i} of {ray:?}");
            occluded += blocked as usize;
        }
    }
    assert!(
        occluded > 100 && occluded < 2300,
        "{occluded} of 2400 occluded"
    );
}

/// A shadow packet from `origins` along `dir`, traversed to the end, with
/// sparse subtrees handed over to groups of lanes in the code of `groups`
/// where there is one (and the CPU has what it needs).
fn traced_shadow_packet<const N: usize>(
    m: &Model,
    origins: &[Vec3; N],
    dir: Vec3,
    tmin: f32,
    groups: Option<Isa>,
) -> Packet<N> {
    let mut packet = Packet::<N>::new(origins, &[dir; N], tmin, f32::INFINITY);
    packet.any_hit = true;
    if let Some(isa) = groups {
        packet.hand_off_sparse_subtrees(isa);
    }
    let mut trav = Traversal::<N>::default();
    assert_eq!(trav.run(&mut packet, &m.top, &m.source), Step::Done);
    packet
}

/// A corner of a random triangle of the model.
fn random_vertex(m: &Model, rng: &mut Rng) -> Vec3 {
    m.tris[rng.below(m.tris.len() as u32) as usize][rng.below(3) as usize]
}

/// 16-lane shadow packets whose lanes part ways (origins all over the
/// model) hand their sparse subtrees over to groups of up to four lanes
/// with AVX-512 and with AVX2, where the CPU has them
/// ([`Packet::hand_off_sparse_subtrees`]): every lane still agrees with
/// brute force, as does the same packet traced without groups, alone and
/// twice over in a 32-lane packet. Two packets in three aim their lanes at
/// vertices of the model, so that lanes pass next to shared corners; half
/// of those along a light whose components are powers of two, which meets
/// a vertex exactly where the origin's subtraction is exact.
#[test]
fn shadow_packets_in_groups_equal_brute_force() {
    for isa in isas().into_iter().filter(|&i| i != Isa::Portable) {
        shadow_packets_in_groups(isa);
    }
}

fn shadow_packets_in_groups(isa: Isa) {
    let m = plant(20_000);
    let b = m.db.manifest.model_bounds;
    let tmin = 1e-4 * b.diagonal();
    let mut rng = Rng::new(19);
    let (mut occluded, mut handed_over) = (0, 0);
    for k in 0..300 {
        let mut origins = [Vec3::ZERO; 16];
        let light = if k % 3 == 2 {
            Vec3::new(0.25, 1.0, -0.125)
        } else {
            Vec3::new(rng.range(-1.0, 1.0), 1.0, rng.range(-1.0, 1.0)).normalize()
        };
        for o in &mut origins {
            *o = if k % 3 != 1 {
                // Below a vertex, towards the light through it.
                let s = if k % 3 == 2 {
                    2f32.powi(rng.below(3) as i32)
                } else {
                    rng.range(0.5, 5.0)
                };
                random_vertex(&m, &mut rng) - light * s
            } else {
                Vec3::new(
                    rng.range(b.min[0], b.max[0]),
                    rng.range(b.min[1], b.max[1]),
                    rng.range(b.min[2], b.max[2]),
                )
            };
        }
        let grouped = traced_shadow_packet(&m, &origins, light, tmin, Some(isa));
        let plain = traced_shadow_packet(&m, &origins, light, tmin, None);
        let twice: [Vec3; 32] = std::array::from_fn(|i| origins[i % 16]);
        let wide = traced_shadow_packet(&m, &twice, light, tmin, None);
        handed_over += grouped.group_searches;
        for (i, &origin) in origins.iter().enumerate() {
            let ray = Ray { origin, dir: light };
            let blocked = blocked_by_brute_force(&m, &ray, tmin);
            let what = format!("{isa:?} packet {k} lane {i} of {ray:?}");
            assert_eq!(grouped.occluded(i), blocked, "{what}");
            assert_eq!(plain.occluded(i), blocked, "{what}");
            assert_eq!(wide.occluded(i), blocked, "32 lanes, {what}");
            assert_eq!(wide.occluded(16 + i), blocked, "32 lanes, {what}");
            occluded += blocked as usize;
        }
    }
    assert!(
        occluded > 450 && occluded < 4500,
        "{isa:?}: {occluded} of 4800 occluded"
    );
    assert!(
        handed_over > 1500,
        "{isa:?}: only {handed_over} subtrees handed over"
    );
}

/// Shadow rays straight up the y axis from exactly below vertices of the
/// model (a light at `0,1,0`): each lies in the planes x = vertex.x and
/// z = vertex.z, which are often faces of the boxes around the triangles
/// through that vertex, and meets those triangles exactly on their shared
/// corner (edge functions exactly zero). Every lane agrees with brute
/// force, in packets of 8 and of 16 (with and without AVX-512 groups;
/// AVX2 groups need every direction component non-zero).
#[test]
fn axis_parallel_shadow_rays_through_vertices_equal_brute_force() {
    let m = plant(20_000);
    let b = m.db.manifest.model_bounds;
    let tmin = 1e-4 * b.diagonal();
    let mut rng = Rng::new(23);
    let (mut occluded, mut handed_over) = (0, 0);
    for k in 0..150 {
        let mut origins = [Vec3::ZERO; 16];
        for o in &mut origins {
            *o = random_vertex(&m, &mut rng) - Vec3::Y * rng.range(0.5, 5.0);
        }
        let grouped = k % 2 == 0;
        let p16 = traced_shadow_packet(&m, &origins, Vec3::Y, tmin, grouped.then_some(Isa::Avx512));
        handed_over += p16.group_searches;
        let eight: [Vec3; 8] = std::array::from_fn(|i| origins[i]);
        let p8 = traced_shadow_packet(&m, &eight, Vec3::Y, tmin, None);
        for (i, &origin) in origins.iter().enumerate() {
            let ray = Ray {
                origin,
                dir: Vec3::Y,
            };
            let blocked = blocked_by_brute_force(&m, &ray, tmin);
            let what = format!("packet {k} (groups {grouped}) lane {i} of {ray:?}");
            assert_eq!(p16.occluded(i), blocked, "16 lanes, {what}");
            if i < 8 {
                assert_eq!(p8.occluded(i), blocked, "8 lanes, {what}");
            }
            occluded += blocked as usize;
        }
    }
    assert!(occluded > 200, "{occluded} of 2400 occluded");
    if Isa::detect() == Isa::Avx512 {
        assert!(handed_over > 300, "only {handed_over} subtrees handed over");
    }
}

/// A shadow packet that first tries a triangle (`occlude_with`) and is
/// traversed only if lanes remain still agrees with brute force lane by
/// lane, whatever the triangle: the occluder of a neighbouring packet
/// (which may block every lane), or any triangle of the model (which
/// may lie behind the origins, or beside the rays).
#[test]
fn shadow_packets_trying_an_occluder_first_equal_brute_force() {
    let m = plant(20_000);
    let b = m.db.manifest.model_bounds;
    let tmin = 1e-4 * b.diagonal();
    let mut rng = Rng::new(11);
    let (mut occluded, mut skipped) = (0, 0);
    // Enough packets that some skip their traversal: shadow packets take
    // the top level's far child first, so the occluder they remember is
    // often a far one, which blocks fewer of the next packet's lanes.
    for _ in 0..300 {
        let base = Vec3::new(
            rng.range(b.min[0], b.max[0]),
            rng.range(b.min[1], b.max[1]),
            rng.range(b.min[2], b.max[2]),
        );
        let light = Vec3::new(rng.range(-1.0, 1.0), 1.0, rng.range(-1.0, 1.0)).normalize();
        let mut last: Option<Occluder> = None;
        // Two neighbouring packets: the second tries the first's occluder.
        for _ in 0..2 {
            let mut origins = [Vec3::ZERO; 8];
            for o in &mut origins {
                *o = base + Vec3::new(rng.range(-0.5, 0.5), 0.0, rng.range(-0.5, 0.5));
            }
            let mut packet = Packet::<8>::new(&origins, &[light; 8], tmin, f32::INFINITY);
            packet.any_hit = true;
            let any = rng.below(m.tris.len() as u32) as usize;
            let candidates = [
                last,
                Some(Occluder {
                    corners: m.tris[any].map(|c| c.to_array()),
                    id: any as u32,
                }),
            ];
            let mut all = false;
            for o in candidates.iter().flatten() {
                all |= packet.occlude_with(o);
            }
            if all {
                skipped += 1;
            } else {
                let mut trav = Traversal::<8>::default();
                assert_eq!(trav.run(&mut packet, &m.top, &m.source), Step::Done);
            }
            for (i, &origin) in origins.iter().enumerate() {
                let ray = Ray { origin, dir: light };
                let blocked = blocked_by_brute_force(&m, &ray, tmin);
                assert_eq!(packet.occluded(i), blocked, "lane {i} of {ray:?}");
                occluded += blocked as usize;
            }
            // The next packet tries what blocked this one's first blocked
            // lane (as the renderer does).
            if let Some(i) = (0..8).find(|&i| packet.occluded(i) && packet.voxel[i] != u32::MAX) {
                let vox = m.source.voxel(packet.voxel[i]).unwrap();
                last = Some(Occluder {
                    corners: vox.corners[packet.tri[i] as usize],
                    id: packet.id[i],
                });
            }
        }
    }
    assert!(occluded > 100, "{occluded} of 4800 occluded");
    assert!(
        skipped > 5,
        "only {skipped} packets blocked by an occluder alone"
    );
}

/// The recorded working set holds every voxel that holds a pixel's hit,
/// is the same when the frame is rendered again, is cleared by `take`, and
/// leaves out voxels the kernel only prefetched.
#[test]
fn recorded_working_set_holds_every_hit_voxel() {
    use dray_trace::accel::RecordingSource;
    let m = plant(20_000);
    let voxels = m.db.manifest.voxels.len();
    for (k, cam) in cameras(&m, 96, 72).iter().enumerate() {
        let mut rec = RecordingSource::new(&m.source, voxels);
        let frame = render(&m.top, &rec, cam, &settings(Isa::detect(), &m)).unwrap();
        let entered = rec.take();
        assert!(rec.take().is_empty(), "camera {k}: take clears");
        let again = render(&m.top, &rec, cam, &settings(Isa::detect(), &m)).unwrap();
        assert_eq!(again.primid, frame.primid);
        assert_eq!(rec.take(), entered, "camera {k}: same frame, same set");
        let holding: HashSet<u32> = entered
            .iter()
            .flat_map(|&id| m.source.voxel(id).unwrap().ids.clone())
            .collect();
        for (p, &id) in frame.primid.iter().enumerate() {
            assert!(
                id == u32::MAX || holding.contains(&id),
                "camera {k}: pixel {p} hit triangle {id} of no entered voxel"
            );
        }
        assert!(!entered.is_empty(), "camera {k}: nothing entered");
    }
    // The kernel's hint that it may enter a voxel soon is not an entry.
    let mut rec = RecordingSource::new(&m.source, voxels);
    for id in 0..voxels as u32 {
        rec.prefetch(id);
    }
    assert!(rec.take().is_empty(), "a prefetch was recorded as an entry");
}

/// Loading every voxel (on every core) of a database with two corrupt
/// voxels fails naming the first of them, as one pass in order did, each
/// time; the intact database loads every voxel, each under its own id.
#[test]
fn loading_names_the_first_corrupt_voxel() {
    let m = plant(20_000);
    let n = m.db.manifest.voxels.len();
    assert_eq!(m.source.voxel_count(), n);
    for id in 0..n as u32 {
        assert_eq!(m.source.voxel(id).map(|v| v.id), Some(id));
    }
    assert!(n > 20, "{n} voxels: too few to load in parallel");
    let dir = m.db.dir().to_path_buf();
    let path = dir.join("voxels.dray");
    let mut bytes = std::fs::read(&path).unwrap();
    let (first, second) = (n as u32 / 3, n as u32 - 2);
    for id in [second, first] {
        let e = &m.db.manifest.voxels[id as usize];
        bytes[(e.offset + e.compressed_bytes / 2) as usize] ^= 0x5A;
    }
    std::fs::write(&path, &bytes).unwrap();
    let db = dray_scene::db::Database::open(&dir).unwrap();
    for _ in 0..5 {
        let err = ResidentSource::load(&db)
            .err()
            .expect("corrupt voxels load");
        let text = err.to_string();
        assert!(text.contains(&format!("voxel {first}")), "{text}");
    }
}
