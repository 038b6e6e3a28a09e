//! `dray shard`: each shard holds exactly its voxels, byte for byte, with
//! the whole manifest; it refuses the others by name, verifies, and is
//! never written over; a damaged shard is named when opened.

use dray_scene::db::manifest::{MANIFEST_FILE, VOXELS_FILE};
use dray_scene::db::shard::{write_shards, ShardOf, SHARD_FILE};
use dray_scene::db::verify::verify;
use dray_scene::db::Database;
use dray_scene::generate::{generate_plant, PlantParams};
use dray_scene::preprocess::{preprocess, PreprocessOptions};
use dray_scene::progress::Progress;
use std::path::Path;

fn plant(dir: &Path) -> Database {
    let model = dir.join("plant.ply");
    let params = PlantParams {
        triangles: 20_000,
        seed: 5,
    };
    generate_plant(&params, &model, &mut |_| {}).unwrap();
    let opts = PreprocessOptions {
        max_triangles: 256,
        threads: 2,
        ..PreprocessOptions::new(vec![model], dir.join("db"))
    };
    preprocess(&opts, &Progress::hidden()).unwrap();
    Database::open(&dir.join("db")).unwrap()
}

#[test]
fn each_shard_holds_its_voxels_and_names_the_others() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant(dir.path());
    let voxels = db.manifest.voxels.len() as u32;
    assert!(voxels > 20, "{voxels} voxels");
    let out = dir.path().join("shards");
    let dirs = write_shards(&db, 3, &out, &Progress::hidden()).unwrap();
    assert_eq!(dirs.len(), 3);
    let whole_manifest = std::fs::read(db.dir().join(MANIFEST_FILE)).unwrap();
    let mut bytes = 0;
    for (i, d) in dirs.iter().enumerate() {
        assert_eq!(d, &out.join(format!("shard-{i}")));
        let s = Database::open(d).unwrap();
        assert_eq!(
            s.shard(),
            Some(ShardOf {
                index: i as u32,
                count: 3
            })
        );
        assert_eq!(
            std::fs::read(d.join(MANIFEST_FILE)).unwrap(),
            whole_manifest
        );
        bytes += std::fs::metadata(d.join(VOXELS_FILE)).unwrap().len();
        for id in 0..voxels {
            if id % 3 == i as u32 {
                assert!(s.holds(id));
                assert_eq!(
                    s.read_blob(id).unwrap(),
                    db.read_blob(id).unwrap(),
                    "voxel {id}"
                );
                assert_eq!(s.load_voxel(id).unwrap(), db.load_voxel(id).unwrap());
            } else {
                assert!(!s.holds(id));
                let e = s.read_blob(id).unwrap_err().to_string();
                assert!(
                    e.contains(&format!("voxel {id}: not in this database")),
                    "{e}"
                );
                assert!(e.contains(&format!("shard {i}/3")), "{e}");
            }
        }
        let report = verify(&s, &Progress::hidden());
        assert!(report.is_ok(), "{:?}", report.problems);
        assert_eq!(report.voxels, (i as u32..voxels).step_by(3).count());
    }
    // Together the shards hold the database's blobs once.
    assert_eq!(
        bytes,
        std::fs::metadata(db.dir().join(VOXELS_FILE)).unwrap().len()
    );
    // Nothing partial is left beside them.
    let mut names: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    assert_eq!(names, ["shard-0", "shard-1", "shard-2"]);
}

#[test]
fn shards_are_never_written_over_nor_cut_again() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant(dir.path());
    let out = dir.path().join("shards");
    write_shards(&db, 2, &out, &Progress::hidden()).unwrap();
    let before = std::fs::read(out.join("shard-1").join(VOXELS_FILE)).unwrap();
    let e = write_shards(&db, 2, &out, &Progress::hidden())
        .unwrap_err()
        .to_string();
    assert!(e.contains("shard-0 exists"), "{e}");
    assert_eq!(
        std::fs::read(out.join("shard-1").join(VOXELS_FILE)).unwrap(),
        before
    );
    let shard = Database::open(&out.join("shard-0")).unwrap();
    let e = write_shards(&shard, 2, &dir.path().join("again"), &Progress::hidden())
        .unwrap_err()
        .to_string();
    assert!(e.contains("already shard 0/2"), "{e}");
    for bad in [0, 5000] {
        let e = write_shards(&db, bad, &dir.path().join("x"), &Progress::hidden())
            .unwrap_err()
            .to_string();
        assert!(e.contains(&format!("--of {bad}")), "{e}");
    }
}

#[test]
fn a_damaged_shard_is_named_when_opened() {
    let dir = tempfile::tempdir().unwrap();
    let db = plant(dir.path());
    let out = dir.path().join("shards");
    write_shards(&db, 2, &out, &Progress::hidden()).unwrap();
    let s0 = out.join("shard-0");
    // A shard file that says another shard: the blobs no longer fit.
    std::fs::write(s0.join(SHARD_FILE), "dray shard 1/2\n").unwrap();
    let e = Database::open(&s0).err().unwrap().to_string();
    assert!(
        e.contains(VOXELS_FILE) && e.contains("for shard 1/2"),
        "{e}"
    );
    for junk in ["", "dray shard 2/2", "shard 0/2", "dray shard x/2"] {
        std::fs::write(s0.join(SHARD_FILE), junk).unwrap();
        let e = Database::open(&s0).err().unwrap().to_string();
        assert!(
            e.contains(SHARD_FILE) && e.contains("is not `dray shard I/N`"),
            "{junk}: {e}"
        );
    }
    // Truncated blobs.
    std::fs::write(s0.join(SHARD_FILE), "dray shard 0/2\n").unwrap();
    let blobs = std::fs::read(s0.join(VOXELS_FILE)).unwrap();
    std::fs::write(s0.join(VOXELS_FILE), &blobs[..blobs.len() - 1]).unwrap();
    let e = Database::open(&s0).err().unwrap().to_string();
    assert!(e.contains("the manifest expects"), "{e}");
    // A flipped byte is found by the checksum.
    let mut flipped = blobs.clone();
    flipped[blobs.len() / 2] ^= 0x40;
    std::fs::write(s0.join(VOXELS_FILE), &flipped).unwrap();
    let s = Database::open(&s0).unwrap();
    assert!(!verify(&s, &Progress::hidden()).is_ok());
}
