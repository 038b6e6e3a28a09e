//! dray's ray tracing kernel against Embree 3, pixel by pixel.
//!
//! Builds `bench/embree` (a C benchmark of Debian's Embree 3.13.5) into the
//! target directory, renders the models of `tests/data` with the same camera
//! in both programs, and compares depth (grey PFM) and primitive ids (raw
//! u32), the formats `bench/embree/README.md` describes.
//!
//! The camera is embree-bench's default one, computed here in float32 exactly
//! as its C code does and passed explicitly to both; the living room also gets
//! a view from inside (its default view only sees the outside of its walls).
//!
//! Agreement: primitive ids on at least 99.9 % of the pixels (Embree's triangle
//! test is not watertight, so a few pixels on triangle edges may differ), and
//! where both hit the same triangle, a relative depth difference of at most
//! 1e-4. Pixels where both hit but different triangles are among the 0.1 %,
//! except ties: when the pixel's ray (recomputed in f64) hits both triangles
//! at the same distance, both answers are right and the pixel agrees. The
//! living room has overlapping coplanar triangles, where Embree and dray pick
//! different ones on about 1.5 % of the pixels of its default view.
//!
//! Shaded frames: embree-bench's frame modes, which `scripts/bench-kernel`
//! sets against dray's shaded frames, must do dray's shading. Where both hit
//! the same triangle (or both missed), at least 98.9 % of the pixels of
//! Embree's last shaded frame are within 2 of dray's `--shadows` image in
//! every channel (rounding, and shadow edges where the two kernels answer a
//! grazing shadow ray differently).
//!
//! Needs Embree 3 and gcc (`apt-get install -y libembree-dev gcc`). Without
//! Embree the tests pass after printing that they skipped the comparison,
//! unless `DRAY_REQUIRE_EMBREE=1` (set by `.ci/run`) makes that a failure.

use std::fs::File;
use std::io::Write;
use std::path::{Path, PathBuf};
use std::process::{Command, Output};
use std::sync::OnceLock;

const WIDTH: usize = 320;
const HEIGHT: usize = 240;
const FOV_DEG: f64 = 50.0;
const UP: &str = "0,1,0";
const MISS: u32 = u32::MAX;
const MIN_PRIMID_AGREEMENT: f64 = 0.999;
const MAX_DEPTH_REL_ERR: f64 = 1e-4;
const RTCORE_H: &str = "/usr/include/embree3/rtcore.h";

fn repo() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

fn run(cmd: &mut Command) -> Output {
    let out = cmd
        .output()
        .unwrap_or_else(|e| panic!("cannot run {cmd:?}: {e}"));
    assert!(out.status.success(), "{cmd:?} failed:\n{}", text(&out));
    out
}

/// The last stdout line, as JSON.
fn last_json(out: &Output, what: &str) -> serde_json::Value {
    let stdout = String::from_utf8_lossy(&out.stdout);
    let line = stdout.lines().last().unwrap_or("");
    serde_json::from_str(line)
        .unwrap_or_else(|e| panic!("the last line of {what} is not JSON ({e}):\n{stdout}"))
}

/// Whether a missing Embree fails the tests instead of skipping them.
fn embree_required() -> bool {
    std::env::var_os("DRAY_REQUIRE_EMBREE").is_some_and(|v| !v.is_empty() && v != "0")
}

/// embree_bench, built once per test process into the target directory; or
/// `None`, after saying so, where Embree is not installed and not required.
fn embree_bench() -> Option<&'static Path> {
    static BIN: OnceLock<Option<PathBuf>> = OnceLock::new();
    BIN.get_or_init(|| {
        if !Path::new(RTCORE_H).exists() {
            let why = format!("Embree 3 is not installed (no {RTCORE_H})");
            assert!(
                !embree_required(),
                "{why}, and DRAY_REQUIRE_EMBREE is set: install it with \
                 `apt-get install -y libembree-dev gcc`"
            );
            // Straight to the process's stderr: the test harness captures
            // `eprintln!` of passing tests, and this note must be seen.
            let _ = writeln!(
                std::io::stderr(),
                "tests/embree.rs: SKIPPED the comparisons with Embree: {why}. To run them: \
                 `apt-get install -y libembree-dev gcc`; DRAY_REQUIRE_EMBREE=1 makes a missing \
                 Embree fail these tests (.ci/run sets it)."
            );
            return None;
        }
        let script = repo().join("bench/embree/build.sh");
        let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("embree");
        std::fs::create_dir_all(&dir).expect("create the embree_bench directory");
        // Build under a name of our own and rename: concurrent test processes
        // never see a half-written binary.
        let partial = dir.join(format!("embree_bench.{}", std::process::id()));
        run(Command::new("sh").arg(&script).arg(&partial));
        let bin = dir.join("embree_bench");
        std::fs::rename(&partial, &bin).expect("move embree_bench into place");
        Some(bin)
    })
    .as_deref()
}

/// Unpacks `tests/data/NAME.ply.zst` into `dir`.
fn unpack(name: &str, dir: &Path) -> PathBuf {
    let src = repo().join(format!("tests/data/{name}.ply.zst"));
    let input = File::open(&src).unwrap_or_else(|e| panic!("cannot open {}: {e}", src.display()));
    let dst = dir.join(format!("{name}.ply"));
    let output = File::create(&dst).expect("create the unpacked PLY");
    zstd::stream::copy_decode(input, output)
        .unwrap_or_else(|e| panic!("cannot unpack {}: {e}", src.display()));
    dst
}

/// Reads one little-endian PLY scalar from the start of a slice.
type ReadScalar = fn(&[u8]) -> f64;

/// The byte size and reader of a PLY scalar type.
fn scalar(ty: &str) -> Option<(usize, ReadScalar)> {
    fn arr<const N: usize>(b: &[u8]) -> [u8; N] {
        b[..N].try_into().expect("slice of the type's size")
    }
    Some(match ty {
        "char" | "int8" => (1, |b| f64::from(b[0] as i8)),
        "uchar" | "uint8" => (1, |b| f64::from(b[0])),
        "short" | "int16" => (2, |b| f64::from(i16::from_le_bytes(arr(b)))),
        "ushort" | "uint16" => (2, |b| f64::from(u16::from_le_bytes(arr(b)))),
        "int" | "int32" => (4, |b| f64::from(i32::from_le_bytes(arr(b)))),
        "uint" | "uint32" => (4, |b| f64::from(u32::from_le_bytes(arr(b)))),
        "float" | "float32" => (4, |b| f64::from(f32::from_le_bytes(arr(b)))),
        "double" | "float64" => (8, |b| f64::from_le_bytes(arr(b))),
        _ => return None,
    })
}

/// A PLY property: a scalar, or a list (count type, item type).
enum Prop {
    Scalar(String, usize, ReadScalar),
    List((usize, ReadScalar), (usize, ReadScalar)),
}

/// The vertices and triangles of a binary little-endian PLY, read the way
/// embree-bench reads them: every vertex (unused ones included), the faces'
/// first list property, each face a triangle, ids in file order.
struct Mesh {
    vertices: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
}

impl Mesh {
    fn read(ply: &Path) -> Mesh {
        let bytes = std::fs::read(ply).expect("read the PLY");
        let fail = |what: &str| -> ! { panic!("{}: {what}", ply.display()) };
        let end = b"end_header\n";
        let body = bytes
            .windows(end.len())
            .position(|w| w == end)
            .map(|p| p + end.len())
            .unwrap_or_else(|| fail("no end_header"));
        let header = std::str::from_utf8(&bytes[..body]).unwrap_or_else(|_| fail("not ASCII"));
        if !header.contains("\nformat binary_little_endian ") {
            fail("only binary little-endian PLY is read here");
        }
        let ty = |t: &str| scalar(t).unwrap_or_else(|| fail(&format!("unknown PLY type {t}")));
        let mut elements: Vec<(String, usize, Vec<Prop>)> = Vec::new();
        for line in header.lines() {
            let w: Vec<&str> = line.split_whitespace().collect();
            let el = elements.last_mut();
            match (w.as_slice(), el) {
                (["element", name, count], _) => {
                    let count = count.parse().unwrap_or_else(|_| fail("bad element count"));
                    elements.push((name.to_string(), count, Vec::new()));
                }
                (["property", "list", count, item, _], Some(el)) => {
                    el.2.push(Prop::List(ty(count), ty(item)));
                }
                (["property", t, name], Some(el)) => {
                    let (size, read) = ty(t);
                    el.2.push(Prop::Scalar(name.to_string(), size, read));
                }
                _ => {}
            }
        }
        let mut mesh = Mesh {
            vertices: Vec::new(),
            triangles: Vec::new(),
        };
        let mut at = body;
        let mut take = |n: usize| -> &[u8] {
            let s = bytes
                .get(at..at + n)
                .unwrap_or_else(|| fail("truncated data"));
            at += n;
            s
        };
        for (name, count, props) in &elements {
            for _ in 0..*count {
                let mut xyz = [0f32; 3];
                let mut first_list = true;
                for prop in props {
                    match prop {
                        Prop::Scalar(pname, size, read) => {
                            let v = read(take(*size)) as f32;
                            if let Some(k) = ["x", "y", "z"].iter().position(|a| a == pname) {
                                xyz[k] = v;
                            }
                        }
                        Prop::List((csize, cread), (isize, iread)) => {
                            let n = cread(take(*csize)) as usize;
                            let items: Vec<f64> = (0..n).map(|_| iread(take(*isize))).collect();
                            if name == "face" && first_list {
                                if n != 3 {
                                    fail("a face is not a triangle");
                                }
                                let idx = std::array::from_fn(|k| items[k] as u32);
                                mesh.triangles.push(idx);
                            }
                            first_list = false;
                        }
                    }
                }
                if name == "vertex" {
                    mesh.vertices.push(xyz);
                }
            }
        }
        let nv = mesh.vertices.len();
        if nv == 0 || mesh.triangles.iter().flatten().any(|&i| i as usize >= nv) {
            fail("no vertices, or a vertex index out of range");
        }
        mesh
    }

    /// Min and max of x, y, z over every vertex, as embree-bench computes them.
    fn bounds(&self) -> ([f32; 3], [f32; 3]) {
        let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
        for v in &self.vertices {
            for k in 0..3 {
                lo[k] = lo[k].min(v[k]);
                hi[k] = hi[k].max(v[k]);
            }
        }
        (lo, hi)
    }

    /// Distance along the ray at which it hits triangle `id` (f64, with a
    /// little slack on the edges), if it does.
    fn hit(&self, id: u32, origin: [f64; 3], dir: [f64; 3]) -> Option<f64> {
        let tri = self.triangles.get(id as usize)?;
        let p = tri.map(|i| self.vertices[i as usize].map(f64::from));
        let (e1, e2) = (sub(p[1], p[0]), sub(p[2], p[0]));
        let q = cross(dir, e2);
        let det = dot(e1, q);
        if det.abs() < 1e-300 {
            return None;
        }
        let s = sub(origin, p[0]);
        let u = dot(s, q) / det;
        let r = cross(s, e1);
        let v = dot(dir, r) / det;
        let t = dot(e2, r) / det;
        let slack = 1e-4;
        (u >= -slack && v >= -slack && u + v <= 1.0 + slack && t > 0.0).then_some(t)
    }
}

fn sub(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|k| a[k] - b[k])
}

fn dot(a: [f64; 3], b: [f64; 3]) -> f64 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}

fn cross(a: [f64; 3], b: [f64; 3]) -> [f64; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}

fn normalized(a: [f64; 3]) -> [f64; 3] {
    let l = dot(a, a).sqrt();
    a.map(|x| x / l)
}

/// The primary ray direction of pixel (x, y), the camera of `bench/embree/README.md`, in f64.
fn ray_dir(eye: [f64; 3], look: [f64; 3], x: usize, y: usize) -> [f64; 3] {
    let w = normalized(sub(look, eye));
    let u = normalized(cross(w, [0.0, 1.0, 0.0]));
    let v = cross(u, w);
    let th = (FOV_DEG.to_radians() / 2.0).tan();
    let sx = ((x as f64 + 0.5) / WIDTH as f64 * 2.0 - 1.0) * th * WIDTH as f64 / HEIGHT as f64;
    let sy = (1.0 - (y as f64 + 0.5) / HEIGHT as f64 * 2.0) * th;
    normalized(std::array::from_fn(|k| w[k] + sx * u[k] + sy * v[k]))
}

fn length(a: [f32; 3]) -> f32 {
    (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt()
}

/// embree-bench's default camera (eye, look), float32 as in its C code:
/// look = bounds centre, eye = centre + normalize(0.3, 0.4, 1) * 0.9 * diagonal.
fn default_camera(lo: [f32; 3], hi: [f32; 3]) -> ([f32; 3], [f32; 3]) {
    let c: [f32; 3] = std::array::from_fn(|k| 0.5 * (lo[k] + hi[k]));
    let diag = length(std::array::from_fn(|k| hi[k] - lo[k]));
    let off = [0.3f32, 0.4, 1.0];
    let l = length(off);
    let eye = std::array::from_fn(|k| c[k] + off[k] / l * 0.9 * diag);
    (eye, c)
}

/// `x,y,z`, each the shortest decimal that reads back as the same f32.
fn vec3(v: [f32; 3]) -> String {
    format!("{},{},{}", v[0], v[1], v[2])
}

fn json_vec3(v: &serde_json::Value) -> [f32; 3] {
    let a = v.as_array().expect("a JSON array of 3 numbers");
    std::array::from_fn(|k| a[k].as_f64().expect("a number") as f32)
}

/// The camera options. `joined` writes `--eye=-1,2,3`, which dray's command
/// line needs for values that start with '-' (embree_bench only takes them
/// as separate words).
fn camera_args(eye: [f32; 3], look: [f32; 3], joined: bool) -> Vec<String> {
    let mut args: Vec<String> = Vec::new();
    for (k, v) in [
        ("--eye", vec3(eye)),
        ("--look", vec3(look)),
        ("--up", UP.to_string()),
        ("--fov", FOV_DEG.to_string()),
        ("--width", WIDTH.to_string()),
        ("--height", HEIGHT.to_string()),
    ] {
        if joined {
            args.push(format!("{k}={v}"));
        } else {
            args.push(k.to_string());
            args.push(v);
        }
    }
    args
}

/// A grey little-endian PFM, returned in top-to-bottom row order.
fn read_pfm(path: &Path) -> Vec<f32> {
    let bytes =
        std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    let header = format!("Pf\n{WIDTH} {HEIGHT}\n-1.0\n");
    assert!(
        bytes.starts_with(header.as_bytes()),
        "{}: the header is not {header:?} but starts {:?}",
        path.display(),
        String::from_utf8_lossy(&bytes[..bytes.len().min(header.len())])
    );
    let body = &bytes[header.len()..];
    assert_eq!(
        body.len(),
        4 * WIDTH * HEIGHT,
        "{}: wrong pixel data size",
        path.display()
    );
    let bottom_up: Vec<f32> = body
        .chunks_exact(4)
        .map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect();
    bottom_up
        .chunks_exact(WIDTH)
        .rev()
        .flatten()
        .copied()
        .collect()
}

fn read_u32(path: &Path) -> Vec<u32> {
    let bytes =
        std::fs::read(path).unwrap_or_else(|e| panic!("cannot read {}: {e}", path.display()));
    assert_eq!(
        bytes.len(),
        4 * WIDTH * HEIGHT,
        "{}: wrong size for {WIDTH}x{HEIGHT} u32",
        path.display()
    );
    bytes
        .chunks_exact(4)
        .map(|b| u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
        .collect()
}

/// A binary PPM (P6, 8 bits) as embree-bench writes it: RGB, top row first.
fn read_ppm(path: &Path) -> Vec<[u8; 3]> {
    let bytes = std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let header = format!("P6\n{WIDTH} {HEIGHT}\n255\n");
    assert!(
        bytes.starts_with(header.as_bytes()),
        "{}: not a {WIDTH}x{HEIGHT} PPM",
        path.display()
    );
    let body = &bytes[header.len()..];
    assert_eq!(body.len(), WIDTH * HEIGHT * 3, "{}: size", path.display());
    body.chunks_exact(3).map(|p| [p[0], p[1], p[2]]).collect()
}

/// Depth and primitive ids of one rendering, top-to-bottom rows.
struct Image {
    depth: Vec<f32>,
    ids: Vec<u32>,
}

impl Image {
    fn read(dir: &Path, stem: &str) -> Image {
        let depth = read_pfm(&dir.join(format!("{stem}.pfm")));
        let ids = read_u32(&dir.join(format!("{stem}.u32")));
        let inconsistent = depth
            .iter()
            .zip(&ids)
            .filter(|(t, id)| t.is_finite() != (**id != MISS))
            .count();
        assert_eq!(
            inconsistent, 0,
            "{stem}: pixels where the depth and the primitive id disagree about hit or miss"
        );
        Image { depth, ids }
    }
}

/// Renders `ply` with Embree and dray from the same camera and compares.
struct View<'a> {
    embree_bench: &'a Path,
    name: &'a str,
    view: &'a str,
    ply: &'a Path,
    db: &'a Path,
    mesh: &'a Mesh,
}

fn compare(v: &View, eye: [f32; 3], look: [f32; 3]) {
    let View {
        embree_bench,
        name,
        view,
        ply,
        db,
        mesh,
    } = *v;
    let dir = ply.parent().expect("the PLY's directory");
    let stem = |who: &str| dir.join(format!("{name}-{view}.{who}"));
    let path = |who: &str, ext: &str| format!("{}.{ext}", stem(who).display());

    let out = run(Command::new(embree_bench)
        .arg(ply)
        .args(camera_args(eye, look, false))
        .args(["--threads", "1", "--repeat", "1"])
        .args(["--depth-out", &path("embree", "pfm")])
        .args(["--primid-out", &path("embree", "u32")])
        .args(["--rgb-out", &path("embree", "ppm")]));
    let e = last_json(&out, "embree_bench");
    assert_eq!(json_vec3(&e["eye"]), eye, "Embree read another eye");
    assert_eq!(json_vec3(&e["look"]), look, "Embree read another look");

    let out = run(Command::new(env!("CARGO_BIN_EXE_dray"))
        .arg("render")
        .arg(db)
        .args(camera_args(eye, look, true))
        .args(["--threads", "2", "--repeat", "1", "--json", "--shadows"])
        .args(["--depth-out", &path("dray", "pfm")])
        .args(["--primid-out", &path("dray", "u32")])
        .args(["--out", &path("dray", "png")])
        .env("RUST_LOG", "warn"));
    let d = last_json(&out, "dray render --json");
    assert_eq!(d["width"], WIDTH, "{d}");
    assert_eq!(d["height"], HEIGHT, "{d}");

    let a = Image::read(dir, &format!("{name}-{view}.embree"));
    let b = Image::read(dir, &format!("{name}-{view}.dray"));
    let n = WIDTH * HEIGHT;
    let count_hits = |im: &Image| im.ids.iter().filter(|&&id| id != MISS).count();
    let hits = count_hits(&a);
    assert!(
        hits * 20 > n,
        "{name}/{view}: Embree hits only {hits} of {n} pixels: the camera shows too little"
    );
    // A pixel agrees when both found the same triangle, or when both found
    // one at the same distance along the ray: a tie between overlapping
    // coplanar triangles (the living room has some) or on a shared edge.
    let (eye64, look64) = (eye.map(f64::from), look.map(f64::from));
    let tie = |i: usize| {
        let (ia, ib) = (a.ids[i], b.ids[i]);
        if ia == MISS || ib == MISS {
            return false;
        }
        let dir = ray_dir(eye64, look64, i % WIDTH, i / WIDTH);
        match (mesh.hit(ia, eye64, dir), mesh.hit(ib, eye64, dir)) {
            (Some(ta), Some(tb)) => (ta - tb).abs() <= 1e-6 * ta,
            _ => false,
        }
    };
    let (mut same_id, mut ties, mut both, mut over, mut over_other) = (0, 0, 0, 0, 0);
    let (mut worst, mut worst_at) = (0.0f64, 0);
    for i in 0..n {
        let same = a.ids[i] == b.ids[i];
        let tied = !same && tie(i);
        same_id += usize::from(same);
        ties += usize::from(tied);
        let (ta, tb) = (f64::from(a.depth[i]), f64::from(b.depth[i]));
        if !(ta.is_finite() && tb.is_finite()) {
            continue;
        }
        both += 1;
        let rel = (ta - tb).abs() / ta;
        if !(same || tied) {
            over_other += usize::from(rel > MAX_DEPTH_REL_ERR);
            continue;
        }
        over += usize::from(rel > MAX_DEPTH_REL_ERR);
        if rel > worst {
            (worst, worst_at) = (rel, i);
        }
    }
    let agreement = (same_id + ties) as f64 / n as f64;
    let summary = format!(
        "{name}/{view} {WIDTH}x{HEIGHT}, eye {} look {}: Embree hits {hits}, dray {} \
         ({both} both); primitive ids agree on {:.4} % of the pixels ({:.4} % the same id, \
         {ties} ties at equal distance, {} differ); same triangle or tie: max relative depth \
         error {worst:.3e} at pixel ({}, {}), {over} pixels over {MAX_DEPTH_REL_ERR:e}; \
         different triangles: {over_other} over",
        vec3(eye),
        vec3(look),
        count_hits(&b),
        100.0 * agreement,
        100.0 * same_id as f64 / n as f64,
        n - same_id - ties,
        worst_at % WIDTH,
        worst_at / WIDTH,
    );
    println!("{summary}");
    // Embree's shaded frame (its `frame` modes, which the benchmark sets
    // against dray's shaded frames) does dray's shading: the same colors,
    // up to rounding and shadow edges, wherever both found the same triangle.
    let rgb = read_ppm(Path::new(&path("embree", "ppm")));
    let png = std::fs::read(path("dray", "png")).expect("dray's shaded frame");
    let (_, _, rgba) = dray_trace::image::decode_png(&png).expect("dray's PNG");
    let same: Vec<usize> = (0..n).filter(|&i| a.ids[i] == b.ids[i]).collect();
    let close = same
        .iter()
        .filter(|&&i| (0..3).all(|c| rgb[i][c].abs_diff(rgba[i][c]) <= 2))
        .count();
    let shaded_agreement = close as f64 / same.len() as f64;
    println!(
        "{name}/{view}: shaded colors within 2 of 255 on {:.3} % of the {} pixels with the same triangle",
        100.0 * shaded_agreement,
        same.len()
    );
    assert!(
        shaded_agreement >= MIN_PRIMID_AGREEMENT - 0.01,
        "{name}/{view}: Embree's shaded frame differs from dray's on {} of {} pixels",
        same.len() - close,
        same.len()
    );
    let ok = agreement >= MIN_PRIMID_AGREEMENT && over == 0;
    if !ok {
        // Keep the images for a look at the failure.
        let keep = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join(format!("embree-{name}-{view}"));
        let _ = std::fs::create_dir_all(&keep);
        for who in ["embree", "dray"] {
            for ext in ["pfm", "u32"] {
                let from = path(who, ext);
                let _ = std::fs::copy(&from, keep.join(format!("{who}.{ext}")));
            }
        }
        panic!(
            "dray disagrees with Embree (at least {:.1} % of the ids must agree, and the depth \
             within {MAX_DEPTH_REL_ERR:e} where both hit the same triangle or tie): {summary}; \
             the images are kept in {}",
            100.0 * MIN_PRIMID_AGREEMENT,
            keep.display()
        );
    }
}

/// Unpacks a model of `tests/data`, preprocesses it, and compares its views.
fn check_model(name: &str, inside: Option<[f32; 3]>) {
    let Some(embree_bench) = embree_bench() else {
        return;
    };
    let dir = tempfile::tempdir().expect("temporary directory");
    let ply = unpack(name, dir.path());
    let db = dir.path().join(format!("{name}.db"));
    run(Command::new(env!("CARGO_BIN_EXE_dray"))
        .arg("preprocess")
        .arg(&ply)
        .arg("--out")
        .arg(&db)
        .env("RUST_LOG", "warn"));
    let mesh = Mesh::read(&ply);
    let (lo, hi) = mesh.bounds();
    let (eye, look) = default_camera(lo, hi);
    let mut v = View {
        embree_bench,
        name,
        view: "default",
        ply: &ply,
        db: &db,
        mesh: &mesh,
    };
    compare(&v, eye, look);
    if let Some(f) = inside {
        v.view = "inside";
        let eye = std::array::from_fn(|k| lo[k] + (hi[k] - lo[k]) * f[k]);
        compare(&v, eye, look);
    }
}

#[test]
fn bunny_matches_embree() {
    check_model("stanford-bunny", None);
}

#[test]
fn igea_matches_embree() {
    check_model("igea", None);
}

/// The living room from outside (its walls) and from its back corner, facing
/// the sofa (the same view as `scripts/bench-kernel`'s "inside").
#[test]
fn living_room_matches_embree() {
    check_model("bitterli-living-room-3", Some([0.2, 0.5, 0.2]));
}

/// The camera computed here is embree-bench's own default camera, bit for bit:
/// Embree given no camera reports the same eye and look.
#[test]
fn default_camera_is_embrees() {
    let Some(embree_bench) = embree_bench() else {
        return;
    };
    let dir = tempfile::tempdir().expect("temporary directory");
    let ply = unpack("stanford-bunny", dir.path());
    let (lo, hi) = Mesh::read(&ply).bounds();
    let (eye, look) = default_camera(lo, hi);
    let out = run(Command::new(embree_bench).arg(&ply).args([
        "--width",
        "64",
        "--height",
        "48",
        "--threads",
        "1",
        "--repeat",
        "1",
    ]));
    let e = last_json(&out, "embree_bench");
    assert_eq!(json_vec3(&e["eye"]), eye);
    assert_eq!(json_vec3(&e["look"]), look);
}
