//! Voxel format: build, codec round trip, BVH traversal against brute force,
//! decoder robustness, BVH quality and compression ratios.

use dray_scene::geometry::{closer, intersect_triangle, Aabb, Hit, Ray};
use dray_scene::mesh::{Triangle, DEFAULT_COLOR};
use dray_scene::voxel::{
    checksum, decode_normal, encode_normal, Voxel, VoxelError, HEADER_LEN, MAX_LEAF_TRIANGLES,
};
use glam::Vec3;
use proptest::prelude::*;
use std::collections::HashMap;
use std::f32::consts::TAU;

// ---------------------------------------------------------------- helpers

/// SplitMix64: small deterministic generator for the non-proptest tests.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn f(&mut self) -> f32 {
        (self.next() >> 40) as f32 / (1u64 << 24) as f32
    }
    fn range(&mut self, lo: f32, hi: f32) -> f32 {
        lo + (hi - lo) * self.f()
    }
    fn below(&mut self, n: u64) -> u64 {
        self.next() % n
    }
    fn unit(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(
                self.range(-1., 1.),
                self.range(-1., 1.),
                self.range(-1., 1.),
            );
            let l = v.length();
            if l > 0.05 && l <= 1.0 {
                return v / l;
            }
        }
    }
}

const PALETTE: [[u8; 4]; 5] = [
    [200, 200, 200, 255],
    [180, 40, 30, 255],
    [40, 90, 170, 255],
    [230, 200, 40, 255],
    [60, 140, 60, 255],
];

struct MeshBuilder {
    tris: Vec<Triangle>,
    next_id: u32,
}

impl MeshBuilder {
    fn tri(&mut self, p: [Vec3; 3], n: [Vec3; 3], c: [u8; 4]) {
        self.tris.push(Triangle {
            positions: p,
            normals: n,
            colors: [c; 3],
            id: self.next_id,
        });
        self.next_id += 1;
    }

    fn quad(&mut self, p: [Vec3; 4], n: Vec3, c: [u8; 4]) {
        self.tri([p[0], p[1], p[2]], [n; 3], c);
        self.tri([p[0], p[2], p[3]], [n; 3], c);
    }

    fn boxed(&mut self, lo: Vec3, hi: Vec3, c: [u8; 4]) {
        for axis in 0..3 {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            for side in [lo[axis], hi[axis]] {
                let corner = |a: f32, b: f32| {
                    let mut p = Vec3::ZERO;
                    p[axis] = side;
                    p[u] = a;
                    p[v] = b;
                    p
                };
                let mut n = Vec3::ZERO;
                n[axis] = if side == lo[axis] { -1.0 } else { 1.0 };
                self.quad(
                    [
                        corner(lo[u], lo[v]),
                        corner(hi[u], lo[v]),
                        corner(hi[u], hi[v]),
                        corner(lo[u], hi[v]),
                    ],
                    n,
                    c,
                );
            }
        }
    }

    fn cylinder(&mut self, base: Vec3, axis: usize, len: f32, r: f32, c: [u8; 4]) {
        const SEG: usize = 16;
        let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
        let ring = |k: usize, h: f32| {
            let a = k as f32 / SEG as f32 * TAU;
            let mut p = base;
            p[axis] += h;
            p[u] += r * a.cos();
            p[v] += r * a.sin();
            let mut n = Vec3::ZERO;
            n[u] = a.cos();
            n[v] = a.sin();
            (p, n.normalize())
        };
        for k in 0..SEG {
            let (a0, n0) = ring(k, 0.0);
            let (b0, n1) = ring(k + 1, 0.0);
            let (a1, _) = ring(k, len);
            let (b1, _) = ring(k + 1, len);
            self.tri([a0, b0, b1], [n0, n1, n1], c);
            self.tri([a0, b1, a1], [n0, n1, n0], c);
        }
        for (h, s) in [(0.0, -1.0), (len, 1.0)] {
            let mut n = Vec3::ZERO;
            n[axis] = s;
            let (p0, _) = ring(0, h);
            for k in 1..SEG - 1 {
                self.tri([p0, ring(k, h).0, ring(k + 1, h).0], [n; 3], c);
            }
        }
    }
}

/// A CAD-like piece of a power plant: grid-aligned boxes (beams, plates)
/// and cylinders (pipes) on a 0.25 grid, about `target` triangles.
fn cad_mesh(seed: u64, target: usize) -> (Aabb, Vec<Triangle>) {
    let mut r = Rng(seed);
    let mut m = MeshBuilder {
        tris: Vec::new(),
        next_id: 7_000_000 + (seed as u32 % 1000) * 10_000,
    };
    let grid = |r: &mut Rng, n: u64| r.below(n) as f32 * 0.25;
    while m.tris.len() < target {
        let c = PALETTE[r.below(PALETTE.len() as u64) as usize];
        let base = Vec3::new(grid(&mut r, 80), grid(&mut r, 80), grid(&mut r, 80));
        if r.below(3) == 0 {
            let axis = r.below(3) as usize;
            let len = 0.5 + grid(&mut r, 40);
            let radius = [0.125, 0.25, 0.5][r.below(3) as usize];
            m.cylinder(base, axis, len, radius, c);
        } else {
            let mut size = Vec3::splat(0.25);
            size[r.below(3) as usize] = 0.5 + grid(&mut r, 40);
            m.boxed(base, base + size, c);
        }
    }
    (Aabb::new(Vec3::ZERO, Vec3::splat(20.0)), m.tris)
}

/// The triangles of the Stanford bunny whose first corner lies in a box
/// around the head, with area-weighted vertex normals (minimal PLY parser).
fn bunny_piece(max_triangles: usize) -> (Aabb, Vec<Triangle>) {
    let path = concat!(
        env!("CARGO_MANIFEST_DIR"),
        "/../tests/data/stanford-bunny.ply.zst"
    );
    let packed = std::fs::read(path).expect("read bunny");
    let data = zstd::stream::decode_all(&packed[..]).expect("unzstd bunny");
    let end = b"end_header\n";
    let hdr_end = data.windows(end.len()).position(|w| w == end).unwrap() + end.len();
    let header = std::str::from_utf8(&data[..hdr_end]).unwrap();
    let count = |el: &str| -> usize {
        header
            .lines()
            .find_map(|l| l.strip_prefix(&format!("element {el} ")))
            .unwrap()
            .trim()
            .parse()
            .unwrap()
    };
    let (nv, nf) = (count("vertex"), count("face"));
    assert!(header.contains("property list uchar int vertex_indices"));
    let mut pos = hdr_end;
    let f32_at = |p: usize| f32::from_le_bytes(data[p..p + 4].try_into().unwrap());
    let mut verts = Vec::with_capacity(nv);
    for _ in 0..nv {
        verts.push(Vec3::new(f32_at(pos), f32_at(pos + 4), f32_at(pos + 8)));
        pos += 12;
    }
    let mut faces = Vec::with_capacity(nf);
    for _ in 0..nf {
        let k = data[pos] as usize;
        pos += 1;
        let idx: Vec<usize> = (0..k)
            .map(|j| {
                u32::from_le_bytes(data[pos + 4 * j..pos + 4 * j + 4].try_into().unwrap()) as usize
            })
            .collect();
        pos += 4 * k;
        for j in 1..k - 1 {
            faces.push([idx[0], idx[j], idx[j + 1]]);
        }
    }
    let mut normals = vec![Vec3::ZERO; nv];
    for f in &faces {
        let n = (verts[f[1]] - verts[f[0]]).cross(verts[f[2]] - verts[f[0]]);
        for &v in f {
            normals[v] += n;
        }
    }
    let all = Aabb::from_points(&verts);
    // A cell in the upper part of the model, grown until it is full enough.
    let c = all.lo() + all.extent() * Vec3::new(0.35, 0.75, 0.5);
    let mut half = all.extent() * 0.02;
    loop {
        let cell = Aabb::new(c - half, c + half);
        let inside = |p: Vec3| (0..3).all(|a| cell.min[a] <= p[a] && p[a] <= cell.max[a]);
        let tris: Vec<Triangle> = faces
            .iter()
            .enumerate()
            .filter(|(_, f)| inside(verts[f[0]]))
            .map(|(id, f)| Triangle {
                positions: f.map(|v| verts[v]),
                normals: f.map(|v| normals[v].normalize_or(Vec3::Z)),
                colors: [DEFAULT_COLOR; 3],
                id: id as u32,
            })
            .collect();
        if tris.len() >= max_triangles * 9 / 10 || half.x > all.extent().x {
            return (cell, tris.into_iter().take(max_triangles).collect());
        }
        half *= 1.1;
    }
}

fn brute_force(tris: &[Triangle], ray: &Ray, tmin: f32, tmax: f32) -> Option<Hit> {
    let mut best = None;
    for t in tris {
        if let Some(th) = intersect_triangle(ray, &t.positions, tmin, tmax) {
            best = closer(best, th, t.id);
        }
    }
    best
}

/// Checks everything a decoded voxel promises about its input.
fn check_against_input(v: &Voxel, input: &[Triangle]) {
    v.validate().expect("valid");
    let finite: Vec<&Triangle> = input
        .iter()
        .filter(|t| t.positions.iter().all(|p| p.is_finite()))
        .collect();
    assert_eq!(v.triangles.len(), finite.len());
    let by_id: HashMap<u32, &Triangle> = finite.iter().map(|t| (t.id, *t)).collect();
    assert_eq!(by_id.len(), finite.len(), "test input ids must be unique");
    let mut seen = HashMap::new();
    for i in 0..v.triangles.len() {
        let t = v.triangle(i);
        assert!(seen.insert(t.id, i).is_none(), "id {} twice", t.id);
        let orig = by_id.get(&t.id).expect("id from the input");
        for k in 0..3 {
            assert_eq!(
                t.positions[k].to_array().map(f32::to_bits),
                orig.positions[k].to_array().map(f32::to_bits),
                "triangle {} corner {k}",
                t.id
            );
            assert_eq!(t.colors[k], orig.colors[k]);
            assert_eq!(t.normals[k], decode_normal(encode_normal(orig.normals[k])));
        }
    }
    assert_eq!(seen.len(), finite.len());
    // Vertices are unique.
    let mut keys = std::collections::HashSet::new();
    for i in 0..v.positions.len() {
        assert!(keys.insert((v.positions[i].map(f32::to_bits), v.normals[i], v.colors[i])));
    }
    let s = v.bvh_stats();
    assert!(s.max_leaf_triangles <= MAX_LEAF_TRIANGLES, "{s:?}");
}

fn ratio(v: &Voxel, blob: &[u8]) -> f64 {
    v.raw_size() as f64 / blob.len() as f64
}

/// Ratio against the arrays without the BVH node bounds (which the blob
/// does not store): the honest measure of the filters.
fn ratio_without_bounds(v: &Voxel, blob: &[u8]) -> f64 {
    (v.raw_size() - v.bvh.len() * 24) as f64 / blob.len() as f64
}

// ---------------------------------------------------------------- round trip

fn arb_soup() -> impl Strategy<Value = (Aabb, Vec<Triangle>)> {
    let coord = prop_oneof![
        (-8i32..8).prop_map(|i| i as f32 * 0.5),
        -5.0f32..5.0,
        Just(-0.0f32),
        Just(1e-30f32),
    ];
    let vertex = (
        [coord.clone(), coord.clone(), coord],
        [-1.0f32..1.0, -1.0f32..1.0, -1.0f32..1.0],
        0usize..3,
    );
    (
        proptest::collection::vec(vertex, 1..40),
        proptest::collection::vec((any::<u16>(), any::<u16>(), any::<u16>()), 0..120),
        any::<u32>(),
        (-4.0f32..0.0, 0.0f32..4.0),
    )
        .prop_map(|(pool, tris, id_base, (lo, hi))| {
            let n = pool.len();
            let tris = tris
                .iter()
                .enumerate()
                .map(|(k, &(a, b, c))| {
                    let corner = |i: u16| pool[i as usize % n];
                    let cs = [corner(a), corner(b), corner(c)];
                    Triangle {
                        positions: cs.map(|c| Vec3::from_array(c.0)),
                        normals: cs.map(|c| Vec3::from_array(c.1)),
                        colors: cs.map(|c| PALETTE[c.2]),
                        // Unique, not sorted, wrapping around u32::MAX.
                        id: id_base.wrapping_add((k as u32).wrapping_mul(2_654_435_761)),
                    }
                })
                .collect();
            // Cell bounds smaller than the soup: triangles stick out.
            (Aabb::new(Vec3::splat(lo), Vec3::splat(hi)), tris)
        })
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 200,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    #[test]
    fn soup_round_trips(input in arb_soup(), level in 1i32..10) {
        let (bounds, tris) = input;
        let v = Voxel::build(bounds, &tris);
        check_against_input(&v, &tris);
        let blob = v.encode(level);
        let d = Voxel::decode(&blob).expect("decode");
        prop_assert!(d.validate().is_ok(), "{:?}", d.validate());
        prop_assert_eq!(&d, &v);
        prop_assert_eq!(d.bounds, bounds);
        check_against_input(&d, &tris);
        // Encoding is deterministic.
        prop_assert_eq!(d.encode(level), blob);
    }
}

proptest! {
    #![proptest_config(ProptestConfig {
        cases: 300,
        failure_persistence: None,
        ..ProptestConfig::default()
    })]

    /// Random edits of the arrays, re-encoded with a valid checksum: decode
    /// never panics, and whatever it accepts is valid and traces exactly
    /// like brute force over its own triangles.
    #[test]
    fn edited_voxels_never_panic(
        edits in proptest::collection::vec((0u8..5, any::<u32>(), any::<u32>()), 1..4),
        seed in any::<u64>(),
    ) {
        let (b, tris) = cad_mesh(seed % 50, 40);
        let mut v = Voxel::build(b, &tris);
        let (nv, nt, nn) = (v.positions.len() as u32, v.triangles.len() as u32, v.bvh.len() as u32);
        for (kind, x, y) in edits {
            match kind {
                0 => v.triangles[(x % nt) as usize][(y % 3) as usize] = y % (nv + 3),
                1 => v.bvh[(x % nn) as usize].first = y % (nn + nt + 3),
                2 => v.bvh[(x % nn) as usize].count = y % 6,
                3 => v.bvh.swap((x % nn) as usize, (y % nn) as usize),
                _ => v.triangles.swap((x % nt) as usize, (y % nt) as usize),
            }
        }
        if let Ok(d) = Voxel::decode(&v.encode(1)) {
            d.validate().expect("accepted voxel is valid");
            let own: Vec<Triangle> = (0..d.triangles.len()).map(|i| d.triangle(i)).collect();
            let mut r = Rng(seed);
            for _ in 0..50 {
                let ray = Ray {
                    origin: Vec3::new(r.range(-2., 22.), r.range(-2., 22.), r.range(-2., 22.)),
                    dir: r.unit(),
                };
                prop_assert_eq!(
                    d.intersect(&ray, 0.0, f32::INFINITY),
                    brute_force(&own, &ray, 0.0, f32::INFINITY)
                );
            }
        }
    }
}

#[test]
fn empty_voxel_round_trips() {
    let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
    let v = Voxel::build(b, &[]);
    assert!(v.bvh.is_empty() && v.positions.is_empty());
    let d = Voxel::decode(&v.encode(3)).unwrap();
    assert_eq!(d, v);
    let ray = Ray {
        origin: Vec3::splat(-1.0),
        dir: Vec3::ONE,
    };
    assert_eq!(d.intersect(&ray, 0.0, f32::INFINITY), None);
}

#[test]
fn non_finite_triangles_are_dropped() {
    let (b, mut tris) = cad_mesh(3, 50);
    tris[7].positions[1].x = f32::NAN;
    tris[9].positions[2].y = f32::INFINITY;
    let v = Voxel::build(b, &tris);
    assert_eq!(v.triangles.len(), tris.len() - 2);
    check_against_input(&v, &tris);
}

// ---------------------------------------------------------------- traversal

fn check_rays(tris: &[Triangle], bounds: Aabb, seed: u64, n: usize) {
    let v = Voxel::decode(&Voxel::build(bounds, tris).encode(3)).unwrap();
    let world = Aabb::from_points(&tris.iter().flat_map(|t| t.positions).collect::<Vec<_>>());
    let (lo, hi) = (
        world.lo() - world.extent() * 0.2,
        world.hi() + world.extent() * 0.2,
    );
    let mut r = Rng(seed);
    let mut hits = 0;
    for k in 0..n {
        let origin = Vec3::new(
            r.range(lo.x, hi.x),
            r.range(lo.y, hi.y),
            r.range(lo.z, hi.z),
        );
        let dir = match k % 4 {
            // Towards a vertex or an edge midpoint: shared edges and ties.
            0 => {
                let t = &tris[r.below(tris.len() as u64) as usize];
                let a = t.positions[r.below(3) as usize];
                let b = t.positions[r.below(3) as usize];
                (a + b) * 0.5 - origin
            }
            // Axis-aligned: rays along CAD faces and box slabs.
            1 => {
                let mut d = Vec3::ZERO;
                d[r.below(3) as usize] = if r.below(2) == 0 { 1.0 } else { -1.0 };
                d
            }
            _ => r.unit(),
        };
        if dir == Vec3::ZERO {
            continue;
        }
        let ray = Ray { origin, dir };
        let (tmin, tmax) = match k % 5 {
            0 => (0.0, f32::INFINITY),
            1 => (r.range(0.0, 2.0), r.range(2.0, 30.0)),
            _ => (1e-4, f32::INFINITY),
        };
        let expect = brute_force(tris, &ray, tmin, tmax);
        let got = v.intersect(&ray, tmin, tmax);
        assert_eq!(
            got.map(|h| (h.t.to_bits(), h.id)),
            expect.map(|h| (h.t.to_bits(), h.id)),
            "ray {k}: {ray:?} in ({tmin}, {tmax}): bvh {got:?}, brute force {expect:?}"
        );
        hits += expect.is_some() as usize;
    }
    assert!(hits > n / 10, "only {hits} of {n} rays hit: test too weak");
}

#[test]
fn intersect_matches_brute_force_cad() {
    let (b, tris) = cad_mesh(11, 4000);
    check_rays(&tris, b, 1, 4000);
}

#[test]
fn intersect_matches_brute_force_bunny() {
    let (b, tris) = bunny_piece(4000);
    check_rays(&tris, b, 2, 3000);
}

#[test]
fn intersect_matches_brute_force_soup() {
    // Overlapping random triangles with many duplicates: many ties in t.
    let mut r = Rng(5);
    let pool: Vec<Vec3> = (0..60)
        .map(|_| {
            Vec3::new(
                r.below(8) as f32 * 0.5,
                r.below(8) as f32 * 0.5,
                r.below(8) as f32 * 0.5,
            )
        })
        .collect();
    let tris: Vec<Triangle> = (0..600u32)
        .map(|id| {
            let p = [0, 1, 2].map(|_| pool[r.below(pool.len() as u64) as usize]);
            Triangle {
                positions: p,
                normals: [Vec3::Z; 3],
                colors: [DEFAULT_COLOR; 3],
                id: 1000 - id,
            }
        })
        .collect();
    check_rays(&tris, Aabb::new(Vec3::ZERO, Vec3::splat(2.0)), 3, 4000);
}

// ---------------------------------------------------------------- robustness

fn small_blob() -> (Voxel, Vec<u8>) {
    let (b, tris) = cad_mesh(21, 60);
    let v = Voxel::build(b, &tris);
    let blob = v.encode(3);
    (v, blob)
}

fn reseal(blob: &mut [u8]) {
    let sum = checksum(blob);
    blob[16..24].copy_from_slice(&sum.to_le_bytes());
}

#[test]
fn every_byte_flip_is_rejected() {
    let (_, blob) = small_blob();
    assert!(Voxel::decode(&blob).is_ok());
    for i in 0..blob.len() {
        for mask in [0x01u8, 0x80, 0xFF] {
            let mut b = blob.clone();
            b[i] ^= mask;
            let err = Voxel::decode(&b).expect_err("flipped byte accepted");
            if i >= 16 {
                assert!(
                    matches!(err, VoxelError::ChecksumMismatch { .. }),
                    "byte {i}: {err}"
                );
            }
        }
    }
}

#[test]
fn every_truncation_is_rejected() {
    let (_, blob) = small_blob();
    for len in 0..blob.len() {
        let err = Voxel::decode(&blob[..len]).expect_err("truncated blob accepted");
        let msg = err.to_string();
        assert!(
            msg.contains("truncated") || msg.contains("checksum mismatch"),
            "{len}: {msg}"
        );
    }
    // Trailing bytes change the checksum too.
    let mut longer = blob.clone();
    longer.push(0);
    assert!(Voxel::decode(&longer).is_err());
}

#[test]
fn garbage_is_rejected() {
    let (_, blob) = small_blob();
    let mut r = Rng(99);
    for n in 0..2000 {
        let len = r.below(300) as usize;
        let mut g: Vec<u8> = (0..len).map(|_| r.next() as u8).collect();
        if n % 2 == 1 && len >= HEADER_LEN {
            // A real header prefix with garbage after it, resealed: only the
            // size checks and the decompressor stand between it and a panic.
            let keep = (r.below(HEADER_LEN as u64) as usize).max(16);
            g[..keep].copy_from_slice(&blob[..keep]);
            reseal(&mut g);
        }
        assert!(Voxel::decode(&g).is_err(), "garbage {n} accepted");
    }
    let e = Voxel::decode(b"NOTAVOXELBLOB").unwrap_err().to_string();
    assert!(e.contains("bad magic"), "{e}");
    let mut b = blob.clone();
    b[8] = 9;
    let e = Voxel::decode(&b).unwrap_err().to_string();
    assert!(e.contains("version 9"), "{e}");
}

/// A thread decodes with one zstd context for all its voxels: a blob whose
/// compressed frame is damaged (resealed, so that the decompressor itself
/// sees it) leaves the next good blob on the same thread decoding exactly.
#[test]
fn a_failed_decompression_leaves_the_next_voxel_intact() {
    let (v, blob) = small_blob();
    let mut r = Rng(5);
    let mut decompressor_errors = 0;
    for _ in 0..200 {
        let mut bad = blob.clone();
        for _ in 0..4 {
            let i = HEADER_LEN + r.below((blob.len() - HEADER_LEN) as u64) as usize;
            bad[i] ^= 1 + r.below(255) as u8;
        }
        reseal(&mut bad);
        // Resealed, damage in the frame's literals can decode to another
        // well-formed voxel: only the decompressor's own failures count.
        let failed = matches!(Voxel::decode(&bad), Err(VoxelError::Decompress(_)));
        decompressor_errors += failed as u32;
        assert!(Voxel::decode(&blob).expect("the good blob") == v);
    }
    assert!(
        decompressor_errors > 20,
        "only {decompressor_errors} damaged frames failed in the decompressor"
    );
}

/// Edits a valid voxel, re-encodes it (valid checksum) and expects decode to
/// reject it with a message containing `expect`.
fn forged(edit: impl FnOnce(&mut Voxel), expect: &str) {
    let (v, _) = small_blob();
    let mut bad = v.clone();
    edit(&mut bad);
    let err = Voxel::decode(&bad.encode(3)).expect_err("forged voxel accepted");
    let msg = err.to_string();
    assert!(msg.contains(expect), "expected '{expect}' in '{msg}'");
    assert!(bad.validate().is_err());
}

#[test]
fn forged_blobs_fail_validation() {
    forged(
        |v| v.triangles[17][1] = 5000,
        "triangle 17 vertex index 5000 out of range",
    );
    forged(|v| v.triangles[3][0] = u32::MAX, "out of range");
    forged(|v| v.bvh[0].first = 0, "malformed BVH");
    forged(|v| v.bvh[0].first = v.bvh.len() as u32, "malformed BVH");
    forged(
        |v| {
            let last = v.bvh.len() - 1;
            v.bvh[last].count += 1;
        },
        "malformed BVH",
    );
    forged(
        |v| {
            // A leaf pointing at another leaf's triangles.
            let leaves: Vec<usize> = (0..v.bvh.len()).filter(|&i| v.bvh[i].is_leaf()).collect();
            let f = v.bvh[leaves[0]].first;
            v.bvh[leaves[1]].first = f;
        },
        "malformed BVH",
    );
    forged(
        |v| {
            // An interior node turned into a leaf: its subtree is orphaned.
            v.bvh[0].count = 1;
            v.bvh[0].first = 0;
        },
        "malformed BVH",
    );
    forged(|v| v.bvh.push(v.bvh[1]), "malformed BVH");
    forged(
        |v| {
            // One leaf of every triangle: the kernel's nodes name at most
            // MAX_LEAF_TRIANGLES.
            let bounds = v.bvh[0].bounds;
            let count = v.triangles.len() as u32;
            v.bvh = vec![dray_scene::voxel::BvhNode {
                bounds,
                first: 0,
                count,
            }];
        },
        "more than 4",
    );
    forged(|v| v.bvh.clear(), "malformed BVH");
    forged(|v| v.positions[2][1] = f32::NAN, "non-finite");
    forged(|v| v.positions[2][0] = f32::INFINITY, "non-finite");
    forged(|v| v.bounds.min[0] = f32::NAN, "non-finite");
    forged(
        |v| {
            v.normals.pop();
        },
        "size mismatch",
    );
    forged(
        |v| {
            v.triangle_ids.pop();
        },
        "size mismatch",
    );
}

#[test]
fn deep_chain_is_rejected() {
    // A degenerate but well-formed-looking tree deeper than the limit.
    let (b, tris) = cad_mesh(4, 200);
    let mut v = Voxel::build(b, &tris);
    let n = v.triangles.len();
    v.bvh.clear();
    for i in 0..n - 1 {
        let me = v.bvh.len() as u32;
        v.bvh.push(dray_scene::voxel::BvhNode {
            bounds: Aabb::EMPTY,
            first: me + 2,
            count: 0,
        });
        v.bvh.push(dray_scene::voxel::BvhNode {
            bounds: Aabb::EMPTY,
            first: i as u32,
            count: 1,
        });
    }
    v.bvh.push(dray_scene::voxel::BvhNode {
        bounds: Aabb::EMPTY,
        first: n as u32 - 1,
        count: 1,
    });
    let e = Voxel::decode(&v.encode(1)).unwrap_err().to_string();
    assert!(e.contains("deeper than"), "{e}");
}

#[test]
fn huge_counts_are_rejected_before_allocating() {
    let (_, blob) = small_blob();
    for (field, value) in [
        (24usize, u32::MAX),
        (28, u32::MAX),
        (32, u32::MAX),
        (24, 20_000_000),
    ] {
        let mut b = blob.clone();
        b[field..field + 4].copy_from_slice(&value.to_le_bytes());
        reseal(&mut b);
        let e = Voxel::decode(&b).unwrap_err().to_string();
        assert!(e.contains("too large"), "{e}");
    }
    // Counts within the limit, sizes consistent, checksum forged: the frame
    // does not decompress to what the header promises.
    let mut b = blob.clone();
    let nv = 1_000_000u64;
    let nt = u32::from_le_bytes(b[28..32].try_into().unwrap()) as u64;
    let nn = u32::from_le_bytes(b[32..36].try_into().unwrap()) as u64;
    b[24..28].copy_from_slice(&(nv as u32).to_le_bytes());
    b[40..48].copy_from_slice(&(nv * 20 + nt * 16 + nn * 32).to_le_bytes());
    b[48..56].copy_from_slice(&(nv * 20 + nt * 16 + nn * 8).to_le_bytes());
    reseal(&mut b);
    let e = Voxel::decode(&b).unwrap_err().to_string();
    assert!(e.contains("truncated") || e.contains("corrupt"), "{e}");
    // Raw size field that disagrees with the counts.
    let mut b = blob.clone();
    b[40] ^= 1;
    reseal(&mut b);
    let e = Voxel::decode(&b).unwrap_err().to_string();
    assert!(e.contains("size mismatch"), "{e}");
}

// ---------------------------------------------------------------- quality and ratio

#[test]
fn cad_bvh_quality() {
    let (b, tris) = cad_mesh(11, 4000);
    let v = Voxel::build(b, &tris);
    let s = v.bvh_stats();
    println!("CAD BVH: {s:?}");
    assert!(s.average_leaf_triangles <= 4.0, "{s:?}");
    assert!(s.max_leaf_triangles <= MAX_LEAF_TRIANGLES);
    assert!(s.sah_cost < 0.05 * s.single_leaf_cost, "{s:?}");
    assert!(s.max_depth < 40, "{s:?}");
}

#[test]
fn compression_ratios() {
    for seed in [11u64, 12, 13] {
        let (b, tris) = cad_mesh(seed, 4000);
        let v = Voxel::build(b, &tris);
        for level in [1, 3, 9, 19] {
            let blob = v.encode(level);
            println!(
                "CAD seed {seed}: {} tris, {} verts, raw {} B, level {level}: {} B, ratio {:.2} ({:.2} without node bounds)",
                v.triangles.len(),
                v.positions.len(),
                v.raw_size(),
                blob.len(),
                ratio(&v, &blob),
                ratio_without_bounds(&v, &blob)
            );
            if level >= 3 {
                assert!(
                    ratio(&v, &blob) >= 3.0,
                    "CAD ratio below 3:1 at level {level}"
                );
            }
        }
    }
    let (b, tris) = bunny_piece(4000);
    let v = Voxel::build(b, &tris);
    for level in [1, 3, 9, 19] {
        let blob = v.encode(level);
        println!(
            "bunny piece: {} tris, {} verts, raw {} B, level {level}: {} B, ratio {:.2} ({:.2} without node bounds)",
            v.triangles.len(),
            v.positions.len(),
            v.raw_size(),
            blob.len(),
            ratio(&v, &blob),
            ratio_without_bounds(&v, &blob)
        );
        assert!(ratio(&v, &blob) > 1.5);
    }
}

/// Throughput, meaningful in release:
/// `cargo test -p dray-scene --release --test voxel -- --ignored --nocapture`
#[test]
#[ignore]
fn codec_throughput() {
    let mut sets = vec![("CAD", cad_mesh(11, 4000)), ("bunny", bunny_piece(4000))];
    sets.push(("CAD-20k", cad_mesh(12, 20000)));
    // Best of N: the machine is shared, the minimum is the least disturbed.
    fn best_of<T>(n: usize, mut f: impl FnMut() -> T) -> (f64, T) {
        let mut best = f64::INFINITY;
        let mut out = f();
        for _ in 0..n {
            let t = std::time::Instant::now();
            out = f();
            best = best.min(t.elapsed().as_secs_f64());
        }
        (best, out)
    }
    for (name, (b, tris)) in sets {
        let (build_s, v) = best_of(10, || Voxel::build(b, &tris));
        let raw = v.raw_size() as f64 / 1e6;
        for level in [1, 3, 6, 9] {
            let (enc, blob) = best_of(30, || v.encode(level));
            let (dec, d) = best_of(30, || Voxel::decode(&blob));
            assert!(d.is_ok());
            println!(
                "{name}: {} tris, build {:.2} ms; level {level}: ratio {:.2}, encode {:.0} MB/s, decode {:.0} MB/s (raw)",
                v.triangles.len(),
                build_s * 1e3,
                ratio(&v, &blob),
                raw / enc,
                raw / dec
            );
        }
    }
}
