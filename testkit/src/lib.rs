//! Test fixtures shared by every crate's tests (a dev-dependency only):
//!
//! - [`plant_db`] and [`plant_db_in`]: a generated plant preprocessed into
//!   a database, through [`dray_scene::preprocess::plant_database`], the
//!   way the demo's and the experiments' models are made;
//! - [`preprocess_into`]: any model file into a database;
//! - [`real_model`]: a real model shipped in `tests/data/`, decompressed;
//! - [`free_ports`]: loopback ports for QUIC nodes;
//! - [`browser`]: a headless Chromium over WebDriver, and a `dray view`
//!   process whose viewer it opens;
//! - [`skip_unless_required`]: a test whose tool this machine lacks skips,
//!   unless CI says the tool must be there.
//!
//! Panics on failure: a fixture that cannot be made fails the test.

pub mod browser;

use dray_scene::db::Database;
use dray_scene::generate::PlantParams;
use dray_scene::preprocess::{plant_database, preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use std::path::{Path, PathBuf};

/// For a test that cannot run here because `why` (a tool or permission
/// is missing): it says so and the test returns, unless the variable
/// `require` is "1" (`.ci/run` sets it where the tool must be there),
/// where it fails naming both.
pub fn skip_unless_required(require: &str, why: &str) {
    if std::env::var(require).as_deref() == Ok("1") {
        panic!("{require}=1 but {why}");
    }
    eprintln!("skipped: {why}");
}

/// A plant and its database in a temporary directory, removed on drop.
pub struct TestDb {
    /// The directory holding both; kept alive by this struct.
    pub dir: tempfile::TempDir,
    /// The generated model, `plant.ply`.
    pub model: PathBuf,
    /// The database, `plant.vdb`.
    pub path: PathBuf,
    /// The database, opened.
    pub db: Database,
}

/// A plant of `triangles` triangles from `seed`, preprocessed with at most
/// `max_triangles` per voxel into a temporary directory.
pub fn plant_db(triangles: u64, seed: u64, max_triangles: u32) -> TestDb {
    let dir = tempfile::tempdir().expect("creating a temporary directory");
    let path = plant_db_in(dir.path(), triangles, seed, max_triangles);
    TestDb {
        model: dir.path().join(PLANT_MODEL),
        db: Database::open(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display())),
        path,
        dir,
    }
}

/// Like [`plant_db`], in `dir` (as `plant.ply` and `plant.vdb`), which the
/// caller keeps; returns the database's path.
pub fn plant_db_in(dir: &Path, triangles: u64, seed: u64, max_triangles: u32) -> PathBuf {
    let path = dir.join("plant.vdb");
    plant_database(
        &PlantParams { triangles, seed },
        &dir.join(PLANT_MODEL),
        &options(Vec::new(), &path, max_triangles),
        &Progress::hidden(),
    )
    .unwrap_or_else(|e| panic!("making the test plant in {}: {e}", dir.display()));
    path
}

const PLANT_MODEL: &str = "plant.ply";

/// Preprocesses `model` into the database `db` with at most
/// `max_triangles` per voxel, and opens it.
pub fn preprocess_into(model: &Path, db: &Path, max_triangles: u32) -> Database {
    preprocess(
        &options(vec![model.to_path_buf()], db, max_triangles),
        &Progress::hidden(),
    )
    .unwrap_or_else(|e| panic!("preprocessing {}: {e}", model.display()));
    Database::open(db).unwrap_or_else(|e| panic!("{}: {e}", db.display()))
}

fn options(inputs: Vec<PathBuf>, db: &Path, max_triangles: u32) -> PreprocessOptions {
    PreprocessOptions {
        max_triangles,
        // Tests run side by side on small machines.
        threads: 2,
        ..PreprocessOptions::new(inputs, db.to_path_buf())
    }
}

/// The real model `tests/data/NAME.ply.zst` (origins in its `SOURCES.md`),
/// decompressed into `dir`; returns the PLY's path.
pub fn real_model(name: &str, dir: &Path) -> PathBuf {
    let src = PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("../tests/data")
        .join(format!("{name}.ply.zst"));
    let out = dir.join(format!("{name}.ply"));
    let input = std::fs::File::open(&src).unwrap_or_else(|e| panic!("{}: {e}", src.display()));
    let output = std::fs::File::create(&out).unwrap_or_else(|e| panic!("{}: {e}", out.display()));
    zstd::stream::copy_decode(input, output).unwrap_or_else(|e| panic!("{}: {e}", src.display()));
    out
}

/// `N` distinct free UDP ports on 127.0.0.1 (QUIC listens on UDP). The
/// sockets are held until all are chosen: binding and dropping one at a
/// time can hand out the same port twice.
pub fn free_ports<const N: usize>() -> [u16; N] {
    let sockets: Vec<std::net::UdpSocket> = (0..N)
        .map(|_| std::net::UdpSocket::bind("127.0.0.1:0").expect("binding a loopback port"))
        .collect();
    std::array::from_fn(|i| sockets[i].local_addr().expect("a bound port").port())
}
