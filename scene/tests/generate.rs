//! Tests of the synthetic plant generator, with a small PLY reader of their
//! own (independent of the importer) that checks the file byte for byte.

use dray_scene::generate::{
    generate_plant, last_peak_scratch_bytes, suggested_views, GenerateError, PlantParams,
};
use dray_scene::Aabb;
use glam::Vec3;
use std::path::Path;

/// What the independent reader found in a file.
struct Ply {
    positions: Vec<Vec3>,
    colors: Vec<[u8; 3]>,
    faces: Vec<[u32; 3]>,
}

fn read_ply(path: &Path) -> Ply {
    let bytes = std::fs::read(path).unwrap();
    let end = b"end_header\n";
    let header_len = bytes
        .windows(end.len())
        .position(|w| w == end)
        .expect("no end_header")
        + end.len();
    let header = std::str::from_utf8(&bytes[..header_len]).unwrap();
    let lines: Vec<&str> = header
        .lines()
        .filter(|l| !l.starts_with("comment"))
        .collect();
    let vcount: usize = lines[2]
        .strip_prefix("element vertex ")
        .unwrap()
        .parse()
        .unwrap();
    let fcount: usize = lines[12]
        .strip_prefix("element face ")
        .unwrap()
        .parse()
        .unwrap();
    let expected = [
        "ply",
        "format binary_little_endian 1.0",
        "",
        "property float x",
        "property float y",
        "property float z",
        "property float nx",
        "property float ny",
        "property float nz",
        "property uchar red",
        "property uchar green",
        "property uchar blue",
        "",
        "property list uchar uint vertex_indices",
        "end_header",
    ];
    assert_eq!(lines.len(), expected.len(), "header: {header}");
    for (l, e) in lines.iter().zip(expected) {
        if !e.is_empty() {
            assert_eq!(*l, e);
        }
    }
    assert_eq!(
        bytes.len(),
        header_len + vcount * 27 + fcount * 13,
        "file size does not match the header counts"
    );
    let f32_at = |o: usize| f32::from_le_bytes(bytes[o..o + 4].try_into().unwrap());
    let mut positions = Vec::with_capacity(vcount);
    let mut colors = Vec::with_capacity(vcount);
    for i in 0..vcount {
        let o = header_len + i * 27;
        let p = Vec3::new(f32_at(o), f32_at(o + 4), f32_at(o + 8));
        let n = Vec3::new(f32_at(o + 12), f32_at(o + 16), f32_at(o + 20));
        assert!(p.is_finite(), "vertex {i} not finite: {p}");
        assert!(
            (n.length() - 1.0).abs() < 1e-3,
            "vertex {i} normal not unit: {n}"
        );
        positions.push(p);
        colors.push([bytes[o + 24], bytes[o + 25], bytes[o + 26]]);
    }
    let fbase = header_len + vcount * 27;
    let mut faces = Vec::with_capacity(fcount);
    for i in 0..fcount {
        let o = fbase + i * 13;
        assert_eq!(bytes[o], 3, "face {i} is not a triangle");
        let idx =
            |k: usize| u32::from_le_bytes(bytes[o + 1 + 4 * k..o + 5 + 4 * k].try_into().unwrap());
        let f = [idx(0), idx(1), idx(2)];
        for &v in &f {
            assert!((v as usize) < vcount, "face {i} index {v} out of range");
        }
        faces.push(f);
    }
    Ply {
        positions,
        colors,
        faces,
    }
}

fn gen(
    dir: &Path,
    name: &str,
    triangles: u64,
    seed: u64,
) -> (dray_scene::generate::GenerateSummary, std::path::PathBuf) {
    let out = dir.join(name);
    let mut calls = Vec::new();
    let s = generate_plant(&PlantParams { triangles, seed }, &out, &mut |t| {
        calls.push(t)
    })
    .unwrap();
    assert!(calls.windows(2).all(|w| w[0] <= w[1]), "progress went back");
    assert_eq!(
        calls.last().copied(),
        Some(triangles),
        "last progress is the total"
    );
    (s, out)
}

fn check(triangles: u64, seed: u64) -> Ply {
    let dir = tempfile::tempdir().unwrap();
    let (s, out) = gen(dir.path(), "plant.ply", triangles, seed);
    let ply = read_ply(&out);
    assert_eq!(ply.faces.len() as u64, triangles);
    assert_eq!(s.triangles, triangles);
    assert_eq!(s.vertices, ply.positions.len() as u64);
    assert_eq!(s.bounds, Aabb::from_points(&ply.positions));
    // No zero-area triangles (tolerate a tiny fraction of slivers).
    let degenerate = ply
        .faces
        .iter()
        .filter(|f| {
            let [a, b, c] = f.map(|i| ply.positions[i as usize]);
            (b - a).cross(c - a).length() < 1e-9
        })
        .count();
    assert!(
        degenerate as f64 <= triangles as f64 * 1e-4,
        "{degenerate} zero-area triangles"
    );
    // Only the output is left in the directory: the temporaries are gone.
    let entries: Vec<_> = std::fs::read_dir(dir.path()).unwrap().collect();
    assert_eq!(entries.len(), 1);
    ply
}

#[test]
fn exact_triangle_counts_and_valid_files() {
    for n in [10_000, 12_345, 200_000] {
        check(n, 7);
    }
}

#[test]
fn a_bigger_plant_has_several_units_and_is_still_exact() {
    let ply = check(650_001, 3);
    let b = Aabb::from_points(&ply.positions);
    // 4 units on a 2 x 2 grid of 72 m cells.
    assert!(b.extent().x > 80.0 && b.extent().z > 80.0, "{:?}", b);
    assert!(b.extent().y > 8.0 && b.extent().y < 60.0, "{:?}", b);
}

#[test]
fn has_many_colors_and_mostly_shared_vertices_on_curves() {
    let ply = check(100_000, 11);
    let mut colors = ply.colors.clone();
    colors.sort();
    colors.dedup();
    assert!(colors.len() >= 8, "only {} colors", colors.len());
    // Boxes use 2 vertices per triangle, smooth tubes about 1: the mix must
    // be in between (pipes are present and share their vertices).
    let ratio = ply.positions.len() as f64 / ply.faces.len() as f64;
    assert!(ratio > 0.8 && ratio < 1.9, "vertices per triangle {ratio}");
}

#[test]
fn same_seed_same_bytes_different_seed_different_bytes() {
    let dir = tempfile::tempdir().unwrap();
    let (_, a) = gen(dir.path(), "a.ply", 30_000, 42);
    let (_, b) = gen(dir.path(), "b.ply", 30_000, 42);
    let (_, c) = gen(dir.path(), "c.ply", 30_000, 43);
    let (a, b, c) = (
        std::fs::read(a).unwrap(),
        std::fs::read(b).unwrap(),
        std::fs::read(c).unwrap(),
    );
    assert!(a == b, "same seed gave different bytes");
    assert!(a != c, "different seeds gave the same bytes");
}

#[test]
fn memory_does_not_grow_with_n() {
    let dir = tempfile::tempdir().unwrap();
    gen(dir.path(), "small.ply", 20_000, 5);
    let small = last_peak_scratch_bytes();
    gen(dir.path(), "big.ply", 1_200_000, 5);
    let big = last_peak_scratch_bytes();
    assert!(small > 0);
    // The scratch holds one object; 60x the triangles, same bound.
    assert!(big < 4 << 20, "scratch {big} bytes");
    assert!(big <= small * 4, "scratch grew from {small} to {big} bytes");
}

#[test]
fn out_of_range_counts_are_errors_and_write_nothing() {
    let dir = tempfile::tempdir().unwrap();
    for n in [0, 9_999, 100_000_001] {
        let out = dir.path().join("p.ply");
        let err = generate_plant(
            &PlantParams {
                triangles: n,
                seed: 1,
            },
            &out,
            &mut |_| {},
        )
        .unwrap_err();
        assert!(matches!(err, GenerateError::TriangleCount { .. }));
        assert!(err.to_string().contains(&n.to_string()), "{err}");
        assert!(!out.exists());
    }
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

#[test]
fn a_missing_directory_is_an_error_naming_the_path() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("no-such-dir").join("plant.ply");
    let err = generate_plant(
        &PlantParams {
            triangles: 10_000,
            seed: 1,
        },
        &out,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(matches!(err, GenerateError::Io { .. }));
    assert!(
        err.to_string().contains(&out.display().to_string()),
        "{err}"
    );
    assert!(!out.exists());
}

#[test]
fn a_failure_at_the_end_leaves_no_file_and_no_temporaries() {
    let dir = tempfile::tempdir().unwrap();
    // The output path is a directory: everything is written, the final
    // rename fails.
    let out = dir.path().join("plant.ply");
    std::fs::create_dir(&out).unwrap();
    let err = generate_plant(
        &PlantParams {
            triangles: 10_000,
            seed: 1,
        },
        &out,
        &mut |_| {},
    )
    .unwrap_err();
    assert!(
        err.to_string().contains(&out.display().to_string()),
        "{err}"
    );
    assert!(out.is_dir());
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 1);
}

#[test]
fn suggested_views_start_outside_and_go_inside() {
    let dir = tempfile::tempdir().unwrap();
    let (s, _) = gen(dir.path(), "p.ply", 900_000, 9);
    let views = suggested_views(&s.bounds);
    assert!(views.len() >= 4);
    let b = s.bounds;
    let inside = |p: Vec3| (0..3).all(|a| b.min[a] <= p[a] && p[a] <= b.max[a]);
    assert!(!inside(views[0].0), "the overview is taken from outside");
    assert!(inside(views[views.len() - 1].0), "the walk ends inside");
    assert!(views.iter().filter(|v| inside(v.0)).count() >= 3);
    for (eye, look) in views {
        assert!(eye.is_finite() && look.is_finite());
        assert!(eye.distance(look) > 1.0);
    }
}

/// The plant is open: rays from outside towards its centre often travel far
/// into it before they hit anything, yet most do hit something.
#[test]
fn from_outside_one_sees_deep_inside() {
    use dray_scene::geometry::intersect_triangle;
    use dray_scene::Ray;
    let ply = check(150_000, 21);
    let b = Aabb::from_points(&ply.positions);
    let tris: Vec<[Vec3; 3]> = ply
        .faces
        .iter()
        .map(|f| f.map(|i| ply.positions[i as usize]))
        .collect();
    let c = b.center();
    let e = b.extent();
    let rays = 64;
    let (mut deep, mut hit) = (0, 0);
    for k in 0..rays {
        let ang = std::f32::consts::TAU * k as f32 / rays as f32;
        let radius = e.x.max(e.z);
        let origin = Vec3::new(
            c.x + radius * ang.cos(),
            b.min[1] + 1.7 + (k % 4) as f32 * 0.2 * e.y,
            c.z + radius * ang.sin(),
        );
        let target = Vec3::new(
            c.x + ((k * 7) % 5) as f32 * 0.05 * e.x - 0.1 * e.x,
            b.min[1] + 1.0 + ((k * 3) % 4) as f32 * 0.2 * e.y,
            c.z + ((k * 11) % 5) as f32 * 0.05 * e.z - 0.1 * e.z,
        );
        let dir = (target - origin).normalize();
        let ray = Ray { origin, dir };
        let (t_in, _) = b.ray_interval(&ray, 0.0, f32::INFINITY).unwrap();
        let t_target = origin.distance(target);
        let mut best = f32::INFINITY;
        for t in &tris {
            if let Some(d) = intersect_triangle(&ray, t, 0.0, best) {
                best = d;
            }
        }
        if best < f32::INFINITY {
            hit += 1;
        }
        if best > t_in + 0.3 * (t_target - t_in) {
            deep += 1;
        }
    }
    println!("{deep} of {rays} rays travel over 30 % of the way in, {hit} hit");
    assert!(
        deep * 4 >= rays,
        "too closed: {deep} of {rays} rays get deep inside"
    );
    assert!(
        hit * 2 >= rays,
        "too empty: only {hit} of {rays} rays hit anything"
    );
}

/// Release timing: `cargo test --release -p dray-scene --test generate -- --ignored --nocapture`.
/// `DRAY_TIMING_N` changes the count, `DRAY_TIMING_OUT` keeps the file there.
#[test]
#[ignore]
fn timing_12_5_million() {
    let dir = tempfile::tempdir_in(".").unwrap();
    let out = std::env::var("DRAY_TIMING_OUT")
        .map(std::path::PathBuf::from)
        .unwrap_or_else(|_| dir.path().join("plant.ply"));
    let n = std::env::var("DRAY_TIMING_N")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(12_500_000);
    let t = std::time::Instant::now();
    let s = generate_plant(
        &PlantParams {
            triangles: n,
            seed: 1,
        },
        &out,
        &mut |_| {},
    )
    .unwrap();
    let secs = t.elapsed().as_secs_f64();
    let size = std::fs::metadata(&out).unwrap().len();
    println!(
        "generated {n} triangles, {} vertices in {secs:.2} s: {:.2} M triangles/s, {size} bytes ({:.1} bytes/triangle), bounds {:?}",
        s.vertices,
        n as f64 / secs / 1e6,
        size as f64 / n as f64,
        s.bounds
    );
}
