//! Preprocessing end to end: model files in, a database out, checked against
//! the input triangles (placement, ray queries) and against corruption.

mod common;

use common::{brute_force, read_positions, test_rays, unpack_model, write_ply, Rng};
use dray_scene::db::manifest::MANIFEST_FILE;
use dray_scene::db::verify::verify;
use dray_scene::db::{intersect, Database};
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::geometry::triangle_touches_box;
use dray_scene::preprocess::{building_prefix, preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use dray_scene::voxel::Voxel;
use glam::Vec3;
use proptest::prelude::*;
use std::path::{Path, PathBuf};

fn build(inputs: Vec<PathBuf>, out: &Path, max_triangles: u32, chunk: Option<u64>) -> Database {
    let opts = PreprocessOptions {
        max_triangles,
        chunk_triangles: chunk,
        threads: 2,
        ..PreprocessOptions::new(inputs, out.to_path_buf())
    };
    preprocess(&opts, &Progress::hidden()).unwrap();
    Database::open(out).unwrap()
}

/// Every input triangle is in at least one voxel whose bounds it touches,
/// and every stored triangle touches its voxel and is bit-identical to the
/// input.
fn check_placement(db: &Database, input: &[[Vec3; 3]]) {
    let mut found = vec![false; input.len()];
    for v in db.load_all().unwrap() {
        for i in 0..v.triangles.len() {
            let t = v.triangle(i);
            let id = t.id as usize;
            assert_eq!(t.positions, input[id], "triangle {id} changed on the way");
            assert!(
                triangle_touches_box(&t.positions, &v.bounds, 1e-5 * v.bounds.diagonal()),
                "triangle {id} does not touch voxel {:?}",
                v.bounds
            );
            found[id] = true;
        }
    }
    if let Some(lost) = found.iter().position(|f| !f) {
        panic!("triangle {lost} is stored in no voxel");
    }
}

/// The database's nearest hit equals brute force for `rays` rays.
fn check_rays(db: &Database, input: &[[Vec3; 3]], rays: usize, seed: u64) {
    let voxels: Vec<Voxel> = db.load_all().unwrap();
    let mut hits = 0;
    for ray in test_rays(input, &db.manifest.model_bounds, rays, seed) {
        let expected = brute_force(input, 0, &ray);
        let got = intersect(&db.manifest, &ray, f32::INFINITY, &mut |id| {
            &voxels[id as usize]
        });
        assert_eq!(got, expected, "ray {ray:?}");
        hits += got.is_some() as usize;
    }
    assert!(
        hits > rays / 4,
        "only {hits} of {rays} rays hit: the test is too easy"
    );
}

fn random_soup(rng: &mut Rng, n: usize) -> Vec<[Vec3; 3]> {
    let mut tris = Vec::with_capacity(n);
    for _ in 0..n {
        let c = Vec3::new(
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
            rng.range(-10.0, 10.0),
        );
        let size = if rng.unit() < 0.05 { 8.0 } else { 0.5 };
        let mut corner = || {
            c + Vec3::new(
                rng.range(-size, size),
                rng.range(-size, size),
                rng.range(-size, size),
            )
        };
        let t = [corner(), corner(), corner()];
        // Some degenerate ones: a repeated corner.
        tris.push(if rng.unit() < 0.03 {
            [t[0], t[0], t[2]]
        } else {
            t
        });
    }
    tris
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 12, ..ProptestConfig::default() })]

    #[test]
    fn random_meshes_are_placed_exactly(seed in any::<u64>(), n in 1usize..3000, max_tris in 4u32..200, chunk in 50u64..2000) {
        let dir = tempfile::tempdir().unwrap();
        let tris = random_soup(&mut Rng::new(seed), n);
        let model = dir.path().join("soup.ply");
        write_ply(&model, &tris);
        let db = build(vec![model], &dir.path().join("db"), max_tris, Some(chunk));
        prop_assert_eq!(db.manifest.input_triangles, n as u64);
        check_placement(&db, &tris);
        prop_assert!(verify(&db, &Progress::hidden()).is_ok());
    }
}

#[test]
fn random_soup_rays_match_brute_force_out_of_core() {
    let dir = tempfile::tempdir().unwrap();
    let tris = random_soup(&mut Rng::new(7), 20_000);
    let model = dir.path().join("soup.ply");
    write_ply(&model, &tris);
    let db = build(vec![model], &dir.path().join("db"), 64, Some(3000));
    assert!(db.manifest.voxels.len() > 100);
    check_rays(&db, &tris, 3000, 1);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 4, ..ProptestConfig::default() })]

    /// Over the generator's output: exact placement, rays equal brute force,
    /// and `verify` agrees.
    #[test]
    fn generated_plants_are_placed_exactly_and_rays_match(
        seed in any::<u64>(),
        triangles in 10_000u64..80_000,
        max_tris in 128u32..2048,
    ) {
        let dir = tempfile::tempdir().unwrap();
        let model = dir.path().join("plant.ply");
        generate_plant(&PlantParams { triangles, seed }, &model, &mut |_| {}).unwrap();
        let tris = read_positions(&model);
        prop_assert_eq!(tris.len() as u64, triangles);
        let db = build(vec![model], &dir.path().join("db"), max_tris, Some(triangles / 3));
        check_placement(&db, &tris);
        check_rays(&db, &tris, 2000, seed);
        let report = verify(&db, &Progress::hidden());
        prop_assert!(report.is_ok(), "{:?}", report.problems);
    }
}

/// The quality target at the default voxel size: replication under
/// 1.3 on the plant (small voxels replicate more, docs/benchmarks.md has the table).
#[test]
fn default_settings_replicate_little() {
    let dir = tempfile::tempdir().unwrap();
    let model = dir.path().join("plant.ply");
    generate_plant(
        &PlantParams {
            triangles: 300_000,
            seed: 1,
        },
        &model,
        &mut |_| {},
    )
    .unwrap();
    let db = build(
        vec![model],
        &dir.path().join("db"),
        dray_scene::preprocess::DEFAULT_MAX_TRIANGLES,
        None,
    );
    let replication = db.manifest.stored_triangles as f64 / 300_000.0;
    assert!(replication < 1.3, "replication {replication}");
}

#[test]
fn several_inputs_and_copies_continue_ids() {
    let dir = tempfile::tempdir().unwrap();
    let mut rng = Rng::new(11);
    let a = random_soup(&mut rng, 500);
    let b = random_soup(&mut rng, 700);
    write_ply(&dir.path().join("a.ply"), &a);
    write_ply(&dir.path().join("b.ply"), &b);
    let opts = PreprocessOptions {
        max_triangles: 32,
        copies: [2, 1, 2],
        spacing: 1.5,
        chunk_triangles: Some(1000),
        ..PreprocessOptions::new(
            vec![dir.path().join("a.ply"), dir.path().join("b.ply")],
            dir.path().join("db"),
        )
    };
    preprocess(&opts, &Progress::hidden()).unwrap();
    let db = Database::open(&dir.path().join("db")).unwrap();
    // The input as the database must see it: a then b, then the copies in
    // x-fastest order, each shifted by 1.5 extents.
    let one: Vec<[Vec3; 3]> = a.iter().chain(&b).copied().collect();
    let bounds = one.iter().fold(dray_scene::Aabb::EMPTY, |acc, t| {
        acc.union(&dray_scene::Aabb::from_points(t))
    });
    let step = bounds.extent() * 1.5;
    let mut all = Vec::new();
    for (x, z) in [(0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)] {
        let shift = Vec3::new(x, 0.0, z) * step;
        all.extend(one.iter().map(|t| t.map(|p| p + shift)));
    }
    assert_eq!(db.manifest.input_triangles, 4800);
    check_placement(&db, &all);
    check_rays(&db, &all, 2000, 3);
}

fn real_model(name: &str, max_triangles: u32, rays: usize) {
    let dir = tempfile::tempdir().unwrap();
    let model = unpack_model(name, dir.path());
    let tris = read_positions(&model);
    let db = build(vec![model], &dir.path().join("db"), max_triangles, None);
    check_placement(&db, &tris);
    check_rays(&db, &tris, rays, 4);
}

#[test]
fn bunny_rays_match_brute_force() {
    real_model("stanford-bunny", 1024, 2000);
}

#[test]
fn igea_rays_match_brute_force() {
    real_model("igea", 4096, 1000);
}

#[test]
fn living_room_rays_match_brute_force() {
    real_model("bitterli-living-room-3", 4096, 1000);
}

fn small_db(dir: &Path) -> PathBuf {
    let tris = random_soup(&mut Rng::new(5), 3000);
    write_ply(&dir.join("m.ply"), &tris);
    build(vec![dir.join("m.ply")], &dir.join("db"), 100, None);
    dir.join("db")
}

#[test]
fn flipping_a_voxel_byte_fails_verify_naming_that_voxel() {
    let dir = tempfile::tempdir().unwrap();
    let path = small_db(dir.path());
    let db = Database::open(&path).unwrap();
    assert!(verify(&db, &Progress::hidden()).is_ok());
    let victim = (db.manifest.voxels.len() / 2) as u32;
    let entry = *db.entry(victim).unwrap();
    drop(db);
    let file = path.join("voxels.dray");
    let mut bytes = std::fs::read(&file).unwrap();
    bytes[(entry.offset + entry.compressed_bytes / 2) as usize] ^= 0x10;
    std::fs::write(&file, bytes).unwrap();
    let report = verify(&Database::open(&path).unwrap(), &Progress::hidden());
    assert_eq!(report.problems.len(), 1, "{:?}", report.problems);
    assert!(
        report.problems[0].starts_with(&format!("voxel {victim}: ")),
        "{:?}",
        report.problems
    );
}

#[test]
fn truncated_or_corrupt_manifest_is_a_clear_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = small_db(dir.path());
    let manifest = path.join(MANIFEST_FILE);
    let good = std::fs::read(&manifest).unwrap();

    std::fs::write(&manifest, &good[..good.len() - 10]).unwrap();
    let err = Database::open(&path)
        .err()
        .expect("truncated manifest")
        .to_string();
    assert!(
        err.contains("manifest.dray") && err.contains("truncated"),
        "{err}"
    );

    std::fs::write(&manifest, &good[..10]).unwrap();
    let err = Database::open(&path)
        .err()
        .expect("short manifest")
        .to_string();
    assert!(err.contains("truncated"), "{err}");

    let mut flipped = good.clone();
    let last = flipped.len() - 1;
    flipped[last] ^= 1;
    std::fs::write(&manifest, &flipped).unwrap();
    let err = Database::open(&path)
        .err()
        .expect("corrupt manifest")
        .to_string();
    assert!(err.contains("checksum"), "{err}");

    std::fs::write(&manifest, b"hello, not a manifest at all, really").unwrap();
    let err = Database::open(&path).err().expect("bad magic").to_string();
    assert!(err.contains("not a dray manifest"), "{err}");

    std::fs::write(&manifest, &good).unwrap();
    let voxels = path.join("voxels.dray");
    let v = std::fs::read(&voxels).unwrap();
    std::fs::write(&voxels, &v[..v.len() - 1]).unwrap();
    let err = Database::open(&path)
        .err()
        .expect("short voxels")
        .to_string();
    assert!(err.contains("voxels.dray"), "{err}");
}

#[test]
fn a_failed_run_leaves_nothing_and_keeps_the_old_database() {
    let dir = tempfile::tempdir().unwrap();
    let path = small_db(dir.path());
    let before = std::fs::read(path.join(MANIFEST_FILE)).unwrap();
    let bad = dir.path().join("bad.ply");
    std::fs::write(&bad, b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n").unwrap();
    let err = preprocess(
        &PreprocessOptions::new(vec![bad], path.clone()),
        &Progress::hidden(),
    );
    assert!(err.is_err());
    assert_eq!(std::fs::read(path.join(MANIFEST_FILE)).unwrap(), before);
    let leftovers: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .filter(|n| n.starts_with('.'))
        .collect();
    assert!(leftovers.is_empty(), "{leftovers:?}");

    // A directory that is not a database is never replaced.
    let other = dir.path().join("photos");
    std::fs::create_dir(&other).unwrap();
    let err = preprocess(
        &PreprocessOptions::new(vec![dir.path().join("m.ply")], other.clone()),
        &Progress::hidden(),
    )
    .unwrap_err()
    .to_string();
    assert!(err.contains("not a dray database"), "{err}");

    // A good run replaces the old database atomically.
    let again = preprocess(
        &PreprocessOptions {
            max_triangles: 50,
            ..PreprocessOptions::new(vec![dir.path().join("m.ply")], path.clone())
        },
        &Progress::hidden(),
    )
    .unwrap();
    assert_eq!(Database::open(&path).unwrap().manifest, again.manifest);
    assert_eq!(again.manifest.build.max_triangles, 50);
}

#[test]
fn a_cancelled_run_cleans_up() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(
        &dir.path().join("m.ply"),
        &random_soup(&mut Rng::new(9), 5000),
    );
    let progress = Progress::hidden();
    progress
        .cancel_flag()
        .store(true, std::sync::atomic::Ordering::Relaxed);
    let result = preprocess(
        &PreprocessOptions::new(vec![dir.path().join("m.ply")], dir.path().join("db")),
        &progress,
    );
    assert!(
        matches!(
            result,
            Err(dray_scene::preprocess::PreprocessError::Cancelled)
        ),
        "{result:?}"
    );
    let names: Vec<_> = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().file_name())
        .collect();
    assert_eq!(names, vec![std::ffi::OsString::from("m.ply")]);
}

/// A killed run's hidden build folder is removed by the next run into the
/// same parent; a live run's, and one that names no builder, are kept.
#[test]
fn stale_build_folders_of_killed_runs_are_removed() {
    let dir = tempfile::tempdir().unwrap();
    write_ply(
        &dir.path().join("m.ply"),
        &random_soup(&mut Rng::new(11), 2000),
    );
    // A process that has exited (and been reaped): its pid runs nothing.
    let mut gone = std::process::Command::new("true").spawn().unwrap();
    let dead = gone.id();
    gone.wait().unwrap();
    let folder = |name: String| {
        let p = dir.path().join(name);
        std::fs::create_dir_all(p.join("spill")).unwrap();
        std::fs::write(p.join("spill").join("input.spill"), vec![7u8; 4096]).unwrap();
        p
    };
    let stale = folder(format!("{}abc123", building_prefix("db", dead)));
    let stale_other_db = folder(format!("{}xyz789", building_prefix("other.vdb", dead)));
    let live = folder(format!(
        "{}def456",
        building_prefix("db", std::process::id())
    ));
    let unnamed = folder(".db.building-Qw3rTy".to_string());
    preprocess(
        &PreprocessOptions::new(vec![dir.path().join("m.ply")], dir.path().join("db")),
        &Progress::hidden(),
    )
    .unwrap();
    assert!(!stale.exists(), "a killed run's folder is left");
    assert!(!stale_other_db.exists(), "a killed run's folder is left");
    assert!(live.exists(), "a live run's folder was removed");
    assert!(unnamed.exists(), "a folder naming no builder was removed");
    Database::open(&dir.path().join("db")).unwrap();
}
