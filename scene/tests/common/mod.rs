//! Helpers shared by the preprocessing tests: model writers, a PRNG, rays,
//! brute force, the real models.
#![allow(dead_code)]

use dray_scene::geometry::{closer, intersect_triangle, Hit, Ray};
use dray_scene::Aabb;
use glam::Vec3;
use std::io::Write;
use std::path::{Path, PathBuf};

pub use dray_scene::rng::Rng;

/// Random points and directions for the tests.
pub trait RngExt {
    fn in_box(&mut self, b: &Aabb) -> Vec3;
    fn direction(&mut self) -> Vec3;
    fn index(&mut self, n: usize) -> usize;
}

impl RngExt for Rng {
    fn in_box(&mut self, b: &Aabb) -> Vec3 {
        Vec3::new(
            self.range(b.min[0], b.max[0]),
            self.range(b.min[1], b.max[1]),
            self.range(b.min[2], b.max[2]),
        )
    }

    fn direction(&mut self) -> Vec3 {
        loop {
            let v = Vec3::new(
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
                self.range(-1.0, 1.0),
            );
            if v.length_squared() > 1e-4 && v.length_squared() <= 1.0 {
                return v.normalize();
            }
        }
    }

    fn index(&mut self, n: usize) -> usize {
        self.below(n as u32) as usize
    }
}

/// Writes triangles as a binary little-endian PLY (positions only, no
/// shared vertices).
pub fn write_ply(path: &Path, tris: &[[Vec3; 3]]) {
    let mut f = std::io::BufWriter::new(std::fs::File::create(path).unwrap());
    write!(
        f,
        "ply\nformat binary_little_endian 1.0\nelement vertex {}\nproperty float x\nproperty float y\nproperty float z\nelement face {}\nproperty list uchar int vertex_indices\nend_header\n",
        tris.len() * 3,
        tris.len()
    )
    .unwrap();
    for t in tris {
        for p in t {
            for c in p.to_array() {
                f.write_all(&c.to_le_bytes()).unwrap();
            }
        }
    }
    for i in 0..tris.len() as i32 {
        f.write_all(&[3]).unwrap();
        for k in 0..3 {
            f.write_all(&(3 * i + k).to_le_bytes()).unwrap();
        }
    }
    f.flush().unwrap();
}

/// Reads every triangle's positions back through the real importer.
pub fn read_positions(path: &Path) -> Vec<[Vec3; 3]> {
    let mut out = Vec::new();
    dray_scene::import::import_model(
        path,
        0,
        &dray_scene::import::ImportOptions::default(),
        &mut |t| {
            out.push(t.positions);
            Ok(())
        },
    )
    .unwrap();
    out
}

pub fn brute_force(tris: &[[Vec3; 3]], id_base: u32, ray: &Ray) -> Option<Hit> {
    let mut best = None;
    for (i, p) in tris.iter().enumerate() {
        let limit = best.map_or(f32::INFINITY, |h: Hit| h.t.next_up_f32());
        if let Some(t) = intersect_triangle(ray, p, 0.0, limit) {
            best = closer(best, t, id_base + i as u32);
        }
    }
    best
}

trait NextUp {
    fn next_up_f32(self) -> f32;
}
impl NextUp for f32 {
    fn next_up_f32(self) -> f32 {
        f32::from_bits(self.to_bits() + 1)
    }
}

/// Rays of three kinds: from outside the model towards a random point of
/// it, from inside in a random direction, and aimed at a random triangle.
pub fn test_rays(tris: &[[Vec3; 3]], bounds: &Aabb, n: usize, seed: u64) -> Vec<Ray> {
    let mut rng = Rng::new(seed);
    let grown = bounds.expanded(bounds.diagonal() * 0.5);
    (0..n)
        .map(|i| match i % 3 {
            0 => {
                let origin = rng.in_box(&grown);
                let target = rng.in_box(bounds);
                Ray {
                    origin,
                    dir: (target - origin).normalize_or(Vec3::X),
                }
            }
            1 => Ray {
                origin: rng.in_box(bounds),
                dir: rng.direction(),
            },
            _ => {
                let t = tris[rng.index(tris.len())];
                let (a, b) = (rng.unit(), rng.unit());
                let (a, b) = if a + b > 1.0 {
                    (1.0 - a, 1.0 - b)
                } else {
                    (a, b)
                };
                let target = t[0] + (t[1] - t[0]) * a + (t[2] - t[0]) * b;
                let origin = rng.in_box(&grown);
                Ray {
                    origin,
                    dir: (target - origin).normalize_or(Vec3::X),
                }
            }
        })
        .collect()
}

/// The real models shipped with the repository for tests (`tests/data/`,
/// origins and licences in its `SOURCES.md`).
pub fn test_data() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../tests/data")
}

/// Unpacks `tests/data/NAME.ply.zst` into `dir`.
pub fn unpack_model(name: &str, dir: &Path) -> PathBuf {
    let src = test_data().join(format!("{name}.ply.zst"));
    let out = dir.join(format!("{name}.ply"));
    let input = std::fs::File::open(&src).unwrap_or_else(|e| panic!("{}: {e}", src.display()));
    let mut output = std::fs::File::create(&out).unwrap();
    zstd::stream::copy_decode(input, &mut output).unwrap();
    out
}
