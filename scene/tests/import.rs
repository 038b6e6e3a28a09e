//! Tests of the PLY and OBJ importers: exact triangles for tiny hand-written
//! models, one test per kind of bad input (the error must name the file, the
//! place and the problem), a fuzz-style robustness test and the real bunny.

mod common;

use dray_scene::import::{
    import_model, probe_model, ImportError, ImportOptions, ImportSummary, ModelFormat,
};
use dray_scene::mesh::{Triangle, DEFAULT_COLOR};
use glam::Vec3;
use std::path::{Path, PathBuf};

fn write(dir: &Path, name: &str, bytes: &[u8]) -> PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn import_with(
    path: &Path,
    first_id: u32,
    opts: &ImportOptions,
) -> Result<(Vec<Triangle>, ImportSummary), ImportError> {
    let mut tris = Vec::new();
    let s = import_model(path, first_id, opts, &mut |t: &Triangle| {
        tris.push(*t);
        Ok(())
    })?;
    assert_eq!(s.triangles, tris.len() as u64);
    Ok((tris, s))
}

fn import(path: &Path) -> Result<(Vec<Triangle>, ImportSummary), ImportError> {
    import_with(path, 0, &ImportOptions::default())
}

/// Asserts the import fails with a message naming the file, `place` (e.g.
/// "byte 123:" or "line 4:"; empty for none) and containing `what`.
#[track_caller]
fn expect_err(path: &Path, place: &str, what: &str) -> String {
    let e = match import(path) {
        Ok((t, _)) => panic!(
            "{}: expected an error, got {} triangles",
            path.display(),
            t.len()
        ),
        Err(e) => e.to_string(),
    };
    let prefix = format!("{}: ", path.display());
    assert!(e.starts_with(&prefix), "error does not name the file: {e}");
    assert!(
        e.contains(place),
        "error does not name the place '{place}': {e}"
    );
    assert!(e.contains(what), "error does not say '{what}': {e}");
    e
}

fn close(a: Vec3, b: Vec3) -> bool {
    (a - b).length() < 1e-5
}

#[track_caller]
fn assert_tri(t: &Triangle, id: u32, p: [Vec3; 3], n: [Vec3; 3], c: [[u8; 4]; 3]) {
    assert_eq!(t.id, id);
    assert_eq!(t.positions, p, "positions of triangle {id}");
    for (k, (got, want)) in t.normals.iter().zip(n).enumerate() {
        assert!(
            close(*got, want),
            "normal {k} of triangle {id}: {got:?} vs {want:?}"
        );
    }
    assert_eq!(t.colors, c, "colors of triangle {id}");
}

// ---------------------------------------------------------------- the model M
//
// Vertices 0..=4 form two triangles sharing vertex 0 with different areas
// (area weighting: the normal of vertex 0 is (0,1,4)/sqrt(17)), vertex 5 is
// unused and 6..=9 form a quad at z = 3.

const POS: [[f32; 3]; 10] = [
    [0.0, 0.0, 0.0],
    [2.0, 0.0, 0.0],
    [0.0, 2.0, 0.0],
    [0.0, 0.0, 1.0],
    [1.0, 0.0, 0.0],
    [5.0, 5.0, 5.0],
    [0.0, 0.0, 3.0],
    [1.0, 0.0, 3.0],
    [1.0, 1.0, 3.0],
    [0.0, 1.0, 3.0],
];
const COL: [[u8; 3]; 10] = [
    [255, 0, 0],
    [0, 255, 0],
    [0, 0, 255],
    [10, 20, 30],
    [40, 50, 60],
    [1, 2, 3],
    [7, 8, 9],
    [11, 12, 13],
    [14, 15, 16],
    [17, 18, 19],
];
const FACES: [&[u32]; 3] = [&[0, 1, 2], &[0, 3, 4], &[6, 7, 8, 9]];

fn v(i: usize) -> Vec3 {
    Vec3::from_array(POS[i])
}

fn rgba(i: usize, colors: bool) -> [u8; 4] {
    if colors {
        [COL[i][0], COL[i][1], COL[i][2], 255]
    } else {
        DEFAULT_COLOR
    }
}

/// The exact triangles of M (computed normals).
fn check_model_m(tris: &[Triangle], first_id: u32, colors: bool) {
    assert_eq!(tris.len(), 4);
    let n0 = Vec3::new(0.0, 1.0, 4.0) / 17f32.sqrt();
    let (z, y) = (Vec3::Z, Vec3::Y);
    let c = |a: usize, b: usize, d: usize| [rgba(a, colors), rgba(b, colors), rgba(d, colors)];
    assert_tri(
        &tris[0],
        first_id,
        [v(0), v(1), v(2)],
        [n0, z, z],
        c(0, 1, 2),
    );
    assert_tri(
        &tris[1],
        first_id + 1,
        [v(0), v(3), v(4)],
        [n0, y, y],
        c(0, 3, 4),
    );
    assert_tri(
        &tris[2],
        first_id + 2,
        [v(6), v(7), v(8)],
        [z, z, z],
        c(6, 7, 8),
    );
    assert_tri(
        &tris[3],
        first_id + 3,
        [v(6), v(8), v(9)],
        [z, z, z],
        c(6, 8, 9),
    );
}

#[derive(Clone, Copy, PartialEq)]
enum Enc {
    Ascii,
    Le,
    Be,
}

#[derive(Clone, Copy)]
enum T {
    I8,
    U8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

impl T {
    fn name(self) -> &'static str {
        match self {
            T::I8 => "int8",
            T::U8 => "uchar",
            T::I16 => "short",
            T::U16 => "uint16",
            T::I32 => "int",
            T::U32 => "uint32",
            T::F32 => "float",
            T::F64 => "float64",
        }
    }

    fn put(self, x: f64, enc: Enc, out: &mut Vec<u8>) {
        macro_rules! p {
            ($v:expr) => {{
                let v = $v;
                match enc {
                    Enc::Ascii => out.extend_from_slice(format!("{} ", v).as_bytes()),
                    Enc::Le => out.extend_from_slice(&v.to_le_bytes()),
                    Enc::Be => out.extend_from_slice(&v.to_be_bytes()),
                }
            }};
        }
        match self {
            T::I8 => p!(x as i8),
            T::U8 => p!(x as u8),
            T::I16 => p!(x as i16),
            T::U16 => p!(x as u16),
            T::I32 => p!(x as i32),
            T::U32 => p!(x as u32),
            T::F32 => p!(x as f32),
            T::F64 => p!(x),
        }
    }
}

/// Writes M as PLY with the given encoding and types.
fn ply_m(enc: Enc, coord: T, count: T, index: T, faces_first: bool, colors: bool) -> Vec<u8> {
    let format = match enc {
        Enc::Ascii => "ascii",
        Enc::Le => "binary_little_endian",
        Enc::Be => "binary_big_endian",
    };
    let mut vh = format!(
        "element vertex 10\nproperty {c} x\nproperty {c} y\nproperty {c} z\n",
        c = coord.name()
    );
    if colors {
        vh += "property uchar red\nproperty uint8 green\nproperty uchar blue\n";
    }
    let fh = format!(
        "element face 3\nproperty list {} {} vertex_indices\n",
        count.name(),
        index.name()
    );
    let mut out = format!(
        "ply\nformat {format} 1.0\ncomment made by a test\n{}{}end_header\n",
        if faces_first { &fh } else { &vh },
        if faces_first { &vh } else { &fh }
    )
    .into_bytes();
    let mut vd = Vec::new();
    for i in 0..10 {
        for x in POS[i] {
            coord.put(x as f64, enc, &mut vd);
        }
        if colors {
            for x in COL[i] {
                T::U8.put(x as f64, enc, &mut vd);
            }
        }
        if enc == Enc::Ascii {
            vd.push(b'\n');
        }
    }
    let mut fd = Vec::new();
    for f in FACES {
        count.put(f.len() as f64, enc, &mut fd);
        for &i in f {
            index.put(i as f64, enc, &mut fd);
        }
        if enc == Enc::Ascii {
            fd.push(b'\n');
        }
    }
    if faces_first {
        out.extend(fd);
        out.extend(vd);
    } else {
        out.extend(vd);
        out.extend(fd);
    }
    out
}

// ------------------------------------------------------------ positive tests

#[test]
fn ascii_ply_hand_written() {
    let dir = tempfile::tempdir().unwrap();
    // M with unknown elements and properties (scalar and list) to skip.
    let text = "ply\r\nformat ascii 1.0\r\ncomment hello\nobj_info scanned by nobody\n\
element material 1\nproperty float shine\nproperty list uchar float spectrum\n\
element vertex 10\nproperty float x\nproperty float y\nproperty float z\n\
property float confidence\nproperty uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar alpha\n\
element face 3\nproperty list uchar float texcoord\nproperty list uchar int vertex_index\nproperty uchar flags\n\
element edge 1\nproperty int vertex1\nproperty int vertex2\nend_header\n\
0.5 3 1 2 3\n\
0 0 0 0.9 255 0 0 7\n2 0 0 0.9 0 255 0 7\n0 2 0 0.9 0 0 255 7\n0 0 1 1 10 20 30 7\n\
1 0 0 1 40 50 60 7\n5 5 5 1 1 2 3 7\n0 0 3 1 7 8 9 7\n1 0 3 1 11 12 13 7\n\
1 1 3 1 14 15 16 7\n0 1 3 1 17 18 19 7\n\
2 0.5 0.5 3 0 1 2 1\n0 3 0 3 4 0\n6 0 0 1 0 1 1 4 6 7 8 9 0\n\
0 1\n";
    let p = write(dir.path(), "m.ply", text.as_bytes());
    let (tris, s) = import(&p).unwrap();
    check_model_m(&tris, 0, true);
    assert_eq!(
        s,
        ImportSummary {
            vertices: 10,
            triangles: 4,
            has_normals: false,
            has_colors: true
        }
    );
}

#[test]
fn generated_ply_in_every_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let cases = [
        (Enc::Ascii, T::F32, T::U8, T::I32, false),
        (Enc::Le, T::F32, T::U8, T::I32, false),
        (Enc::Le, T::F32, T::U8, T::U32, true),
        (Enc::Le, T::F64, T::U16, T::U16, false),
        (Enc::Be, T::F64, T::U8, T::U16, false),
        (Enc::Be, T::F64, T::U32, T::U32, true),
        (Enc::Be, T::F32, T::I8, T::I16, false),
        (Enc::Le, T::I16, T::I32, T::U8, true),
        (Enc::Ascii, T::F64, T::U16, T::U32, true),
    ];
    for (k, (enc, coord, count, index, faces_first)) in cases.into_iter().enumerate() {
        for colors in [false, true] {
            let p = write(
                dir.path(),
                &format!("m{k}{colors}.ply"),
                &ply_m(enc, coord, count, index, faces_first, colors),
            );
            let (tris, s) = import_with(&p, 100, &ImportOptions::default())
                .unwrap_or_else(|e| panic!("case {k}: {e}"));
            check_model_m(&tris, 100, colors);
            assert_eq!(s.vertices, 10);
            assert_eq!(s.has_colors, colors);
            assert!(!s.has_normals);
        }
    }
}

#[test]
fn big_and_little_endian_give_identical_triangles() {
    let dir = tempfile::tempdir().unwrap();
    let be = write(
        dir.path(),
        "be.ply",
        &ply_m(Enc::Be, T::F64, T::U8, T::U32, false, true),
    );
    let le = write(
        dir.path(),
        "le.ply",
        &ply_m(Enc::Le, T::F64, T::U8, T::U32, false, true),
    );
    let le_fast = write(
        dir.path(),
        "lef.ply",
        &ply_m(Enc::Le, T::F32, T::U8, T::I32, false, true),
    );
    let a = import(&be).unwrap().0;
    assert_eq!(a, import(&le).unwrap().0);
    assert_eq!(a, import(&le_fast).unwrap().0);
}

#[test]
fn ply_input_normals_and_float_colors() {
    let dir = tempfile::tempdir().unwrap();
    let text = "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\n\
property float nx\nproperty float ny\nproperty float nz\nproperty float red\nproperty double green\nproperty float blue\n\
element face 2\nproperty list uchar uint vertex_indices\nend_header\n\
0 0 0 0 0 2 1 0.5 0\n1 0 0 0 0 0 0 0 1.5\n0 1 0 0 3 4 0.25 1 -1\n1 1 0 0 0 1 0 0 0\n\
3 0 1 2\n3 1 3 2\n";
    let p = write(dir.path(), "n.ply", text.as_bytes());
    let (t, s) = import(&p).unwrap();
    assert!(s.has_normals && s.has_colors);
    // vertex 1 has a zero normal: the triangle's own geometric normal (+Z) is used.
    let z = Vec3::Z;
    let n2 = Vec3::new(0.0, 0.6, 0.8);
    assert_tri(
        &t[0],
        0,
        [Vec3::ZERO, Vec3::X, Vec3::Y],
        [z, z, n2],
        [[255, 128, 0, 255], [0, 0, 255, 255], [64, 255, 0, 255]],
    );
    assert_tri(
        &t[1],
        1,
        [Vec3::X, Vec3::new(1.0, 1.0, 0.0), Vec3::Y],
        [z, z, n2],
        [[0, 0, 255, 255], [0, 0, 0, 255], [64, 255, 0, 255]],
    );
}

#[test]
fn obj_all_face_forms() {
    let dir = tempfile::tempdir().unwrap();
    // M again, with comments, groups, materials, texture coordinates,
    // vertex colors, a w coordinate, CRLF and every face form.
    let mut text = String::from("# a comment\r\nmtllib m.mtl\r\no thing\r\ng group\r\n\r\n");
    for i in 0..10 {
        let [x, y, z] = POS[i];
        let [r, g, b] = COL[i].map(|c| c as f32 / 255.0);
        text += &format!("v {x} {y} {z} {r} {g} {b}\r\n");
    }
    text += "vt 0 0\nvt 1 0\nvt 1 1\nusemtl red\ns 1\n";
    text += "f 1 2 3\n"; // v
    text += "f -10/1 -7/2 -6/3\n"; // v/vt, negative
    text += "vn 0 0 2\n";
    text += "f 7//1 -3/2/-1 9/3/1 -1//1\n"; // v//vn, v/vt/vn, quad
    let p = write(dir.path(), "m.obj", text.as_bytes());
    let (tris, s) = import_with(&p, 7, &ImportOptions::default()).unwrap();
    check_model_m(&tris, 7, true);
    assert_eq!(
        s,
        ImportSummary {
            vertices: 10,
            triangles: 4,
            has_normals: true,
            has_colors: true
        }
    );

    // Per-corner normals come from vn; corners without vn are computed.
    let text = "v 0 0 0\nv 1 0 0\nv 0 1 0 1\nvn 1 0 0\nvn 0 0 0\nf 1//1 2 3//2\n";
    let p = write(dir.path(), "n.obj", text.as_bytes());
    let (t, s) = import(&p).unwrap();
    assert!(s.has_normals && !s.has_colors);
    assert_tri(
        &t[0],
        0,
        [Vec3::ZERO, Vec3::X, Vec3::Y],
        [Vec3::X, Vec3::Z, Vec3::Z],
        [DEFAULT_COLOR; 3],
    );
}

#[test]
fn zero_area_triangles_are_kept() {
    let dir = tempfile::tempdir().unwrap();
    let text = "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\n\
element face 3\nproperty list uchar int vertex_indices\nend_header\n\
0 0 0\n1 1 1\n2 2 2\n3 0 1 2\n3 0 0 0\n3 2 1 1\n";
    let p = write(dir.path(), "z.ply", text.as_bytes());
    let (t, _) = import(&p).unwrap();
    assert_eq!(t.len(), 3);
    for (i, t) in t.iter().enumerate() {
        assert_eq!(t.id, i as u32);
        assert_eq!(t.normals, [Vec3::Z; 3]);
        assert_eq!(t.geometric_normal(), Vec3::ZERO);
        assert!(!t.bounds().is_empty() || t.positions[0] == t.positions[1]);
    }
    let p = write(
        dir.path(),
        "z.obj",
        b"v 0 0 0\nv 1 1 1\nf 1 2 2\nf 1 1 1 1\n",
    );
    let (t, _) = import(&p).unwrap();
    assert_eq!(t.len(), 3);
    assert!(t.iter().all(|t| t.normals == [Vec3::Z; 3]));
}

#[test]
fn probe_reports_declared_counts() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "m.ply",
        &ply_m(Enc::Le, T::F32, T::U8, T::I32, true, false),
    );
    let pr = probe_model(&p).unwrap();
    assert_eq!(
        (pr.format, pr.vertices, pr.faces),
        (ModelFormat::Ply, 10, 3)
    );
    let p = write(
        dir.path(),
        "m.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\n# f 1 2 3\nf 1 2 3\nf 3 2 1\n",
    );
    let pr = probe_model(&p).unwrap();
    assert_eq!((pr.format, pr.vertices, pr.faces), (ModelFormat::Obj, 3, 2));
}

#[test]
fn ids_continue_from_first_id_and_refuse_overflow() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "m.ply",
        &ply_m(Enc::Le, T::F32, T::U8, T::I32, false, false),
    );
    let (t, _) = import_with(&p, u32::MAX - 3, &ImportOptions::default()).unwrap();
    assert_eq!(t.last().unwrap().id, u32::MAX);
    let e = import_with(&p, u32::MAX - 2, &ImportOptions::default()).unwrap_err();
    assert!(e.to_string().contains("overflow u32"), "{e}");
    let o = write(
        dir.path(),
        "m.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2 3\n",
    );
    let e = import_with(&o, u32::MAX, &ImportOptions::default()).unwrap_err();
    assert!(e.to_string().contains("overflow u32"), "{e}");
}

#[test]
fn sink_errors_stop_the_import() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "m.ply",
        &ply_m(Enc::Le, T::F32, T::U8, T::I32, false, false),
    );
    let mut n = 0;
    let e = import_model(&p, 0, &ImportOptions::default(), &mut |_| {
        n += 1;
        Err(std::io::Error::other("disk full"))
    })
    .unwrap_err();
    assert_eq!(n, 1);
    assert!(e.to_string().contains("disk full"), "{e}");
}

// --------------------------------------------------------------- bad input

/// Byte offset of the data of a PLY file (just after `end_header\n`).
fn data_start(bytes: &[u8]) -> usize {
    let k = bytes
        .windows(11)
        .position(|w| w == b"end_header\n")
        .unwrap();
    k + 11
}

fn m_le() -> Vec<u8> {
    ply_m(Enc::Le, T::F32, T::U8, T::I32, false, false)
}

fn replace(b: &[u8], from: &str, to: &str) -> Vec<u8> {
    let k = b
        .windows(from.len())
        .position(|w| w == from.as_bytes())
        .unwrap();
    let mut out = b[..k].to_vec();
    out.extend_from_slice(to.as_bytes());
    out.extend_from_slice(&b[k + from.len()..]);
    out
}

const XYZ: &str = "property float x\nproperty float y\nproperty float z\n";

#[test]
fn error_truncated_binary_vertex_data() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = m_le();
    let h = data_start(&b);
    b.truncate(h + 50);
    let p = write(dir.path(), "tv.ply", &b);
    expect_err(&p, &format!("byte {}:", h + 50), "truncated");
    // A vertex element with a list property (no up-front size bound).
    let mut b = format!(
        "ply\nformat binary_little_endian 1.0\nelement vertex 2\n{XYZ}property list uchar float extra\n\
         element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    let h = b.len();
    for x in [1f32, 2.0, 3.0] {
        b.extend(x.to_le_bytes());
    }
    b.push(3);
    for x in [4f32, 5.0, 6.0] {
        b.extend(x.to_le_bytes());
    }
    b.extend(1f32.to_le_bytes()); // vertex 1: x, then the file ends
    let p = write(dir.path(), "tv2.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 29),
        "unexpected end of file in element 'vertex' record 1",
    );
}

#[test]
fn error_truncated_binary_face_data() {
    let dir = tempfile::tempdir().unwrap();
    // Fast path (list uchar int, little-endian): face 2 is a quad.
    let mut b = m_le();
    let h = data_start(&b);
    b.truncate(b.len() - 2);
    let p = write(dir.path(), "tf.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 120 + 13 + 13),
        "runs past the end of the file",
    );
    // General path (big-endian, ushort indices): cut inside face 1.
    let mut b = ply_m(Enc::Be, T::F64, T::U8, T::U16, false, false);
    let h = data_start(&b);
    b.truncate(h + 240 + 7 + 3);
    let p = write(dir.path(), "tf2.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 240 + 7),
        "list of 3 items runs past the end of the file",
    );
}

#[test]
fn error_header_counts_exceed_data() {
    let dir = tempfile::tempdir().unwrap();
    let b = m_le();
    let more_faces = replace(&b, "element face 3", "element face 5");
    let p = write(dir.path(), "f5.ply", &more_faces);
    expect_err(
        &p,
        &format!("byte {}:", more_faces.len()),
        "unexpected end of file in element 'face' record 3",
    );
    let more_vertices = replace(&b, "element vertex 10", "element vertex 1000");
    let p = write(dir.path(), "v1000.ply", &more_vertices);
    expect_err(
        &p,
        &format!("byte {}:", more_vertices.len()),
        "declares 1000 records",
    );
    // ASCII: the file ends early.
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("element face 3", "element face 4", 1);
    let p = write(dir.path(), "a4.ply", a.as_bytes());
    expect_err(
        &p,
        "line 24:",
        "unexpected end of file in element 'face' record 3",
    );
}

#[test]
fn error_count_too_large_for_memory() {
    let dir = tempfile::tempdir().unwrap();
    let b = m_le();
    let huge = replace(&b, "element vertex 10", "element vertex 4000000000");
    let p = write(dir.path(), "huge.ply", &huge);
    expect_err(
        &p,
        &format!("byte {}:", huge.len()),
        "declares 4000000000 records",
    );
    let huge = replace(&b, "element face 3", "element face 18446744073709551615");
    let p = write(dir.path(), "hugef.ply", &huge);
    expect_err(&p, "byte ", "declares 18446744073709551615 records");
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("element vertex 10", "element vertex 4000000000", 1);
    let p = write(dir.path(), "hugea.ply", a.as_bytes());
    expect_err(&p, "line 4:", "declares 4000000000 records");
    // Over the caller's memory budget.
    let p = write(dir.path(), "budget.ply", &m_le());
    let e = import_with(
        &p,
        0,
        &ImportOptions {
            max_vertex_bytes: 100,
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with(&format!("{}: line 4: ", p.display())), "{e}");
    assert!(e.contains("memory budget of 100 bytes"), "{e}");
    let o = write(
        dir.path(),
        "budget.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nv 1 1 1\nv 2 2 2\nf 1 2 3\n",
    );
    let e = import_with(
        &o,
        0,
        &ImportOptions {
            max_vertex_bytes: 100,
        },
    )
    .unwrap_err()
    .to_string();
    assert!(e.starts_with(&format!("{}: line 5: ", o.display())), "{e}");
    assert!(e.contains("memory budget"), "{e}");
}

#[test]
fn error_unknown_format_line() {
    let dir = tempfile::tempdir().unwrap();
    let b = replace(&m_le(), "binary_little_endian", "binary_middle_endian");
    let p = write(dir.path(), "fmt.ply", &b);
    expect_err(&p, "line 2:", "unknown format 'binary_middle_endian'");
}

#[test]
fn error_unknown_property_type() {
    let dir = tempfile::tempdir().unwrap();
    let b = replace(&m_le(), "property float y", "property float128 y");
    let p = write(dir.path(), "ty.ply", &b);
    expect_err(&p, "line 6:", "unknown property type 'float128'");
    let b = replace(&m_le(), "list uchar int", "list uchar quad");
    let p = write(dir.path(), "ty2.ply", &b);
    expect_err(&p, "line 9:", "unknown property type 'quad'");
    let b = replace(&m_le(), "list uchar int", "list float int");
    let p = write(dir.path(), "ty3.ply", &b);
    expect_err(
        &p,
        "line 9:",
        "list count type 'float' is not an integer type",
    );
}

#[test]
fn error_missing_xyz() {
    let dir = tempfile::tempdir().unwrap();
    for axis in ["x", "y", "z"] {
        let b = replace(
            &m_le(),
            &format!("property float {axis}\n"),
            "property float w\n",
        );
        let p = write(dir.path(), &format!("no{axis}.ply"), &b);
        expect_err(
            &p,
            "line 4:",
            &format!("vertex element has no '{axis}' property"),
        );
    }
    let b = "ply\nformat ascii 1.0\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n3 0 1 2\n";
    let p = write(dir.path(), "nov.ply", b.as_bytes());
    expect_err(&p, "", "no vertex element");
}

#[test]
fn error_no_end_header() {
    let dir = tempfile::tempdir().unwrap();
    let b = format!("ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}");
    let p = write(dir.path(), "noend.ply", b.as_bytes());
    expect_err(&p, "line 6:", "the file ends before end_header");
    // Data where the header should end.
    let b = format!("ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}0 0 0\n");
    let p = write(dir.path(), "noend2.ply", b.as_bytes());
    expect_err(&p, "line 7:", "unknown header keyword '0'");
}

#[test]
fn error_vertex_index_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    // Fast path: face 1 = [0, 3, 4]; its second index becomes 10.
    let mut b = m_le();
    let h = data_start(&b);
    let at = h + 120 + 13 + 1 + 4;
    b[at..at + 4].copy_from_slice(&10i32.to_le_bytes());
    let p = write(dir.path(), "oor.ply", &b);
    expect_err(
        &p,
        &format!("byte {at}:"),
        "face 1: vertex index 10 out of range (the model has 10 vertices)",
    );
    // General path, big-endian uint.
    let mut b = ply_m(Enc::Be, T::F64, T::U8, T::U32, false, false);
    let h = data_start(&b);
    let at = h + 240 + 13 + 1 + 8;
    b[at..at + 4].copy_from_slice(&4000000000u32.to_be_bytes());
    let p = write(dir.path(), "oor2.ply", &b);
    expect_err(
        &p,
        &format!("byte {at}:"),
        "face 1: vertex index 4000000000 out of range",
    );
    // ASCII.
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("3 0 3 4", "3 0 3 11", 1);
    let p = write(dir.path(), "oor.ply", a.as_bytes());
    expect_err(&p, "line 22:", "face 1: vertex index 11 out of range");
}

#[test]
fn error_negative_index() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = m_le();
    let h = data_start(&b);
    let at = h + 120 + 1 + 8;
    b[at..at + 4].copy_from_slice(&(-1i32).to_le_bytes());
    let p = write(dir.path(), "neg.ply", &b);
    expect_err(
        &p,
        &format!("byte {at}:"),
        "face 0: negative vertex index -1",
    );
    let mut b = ply_m(Enc::Be, T::F32, T::U8, T::I16, false, false);
    let h = data_start(&b);
    let at = h + 120 + 7 + 1;
    b[at..at + 2].copy_from_slice(&(-3i16).to_be_bytes());
    let p = write(dir.path(), "neg2.ply", &b);
    expect_err(
        &p,
        &format!("byte {at}:"),
        "face 1: negative vertex index -3",
    );
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("3 0 3 4", "3 0 -3 4", 1);
    let p = write(dir.path(), "neg.ply", a.as_bytes());
    expect_err(&p, "line 22:", "face 1: negative vertex index -3");
}

#[test]
fn error_nan_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = m_le();
    let h = data_start(&b);
    let at = h + 2 * 12 + 4;
    b[at..at + 4].copy_from_slice(&f32::NAN.to_le_bytes());
    let p = write(dir.path(), "nan.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 24),
        "vertex 2 has a NaN coordinate",
    );
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("0 2 0", "0 nan 0", 1);
    let p = write(dir.path(), "nan.ply", a.as_bytes());
    expect_err(&p, "line 13:", "vertex 2 has a NaN coordinate");
    let p = write(
        dir.path(),
        "nan.obj",
        b"v 0 0 0\nv 1 NaN 0\nv 0 1 0\nf 1 2 3\n",
    );
    expect_err(&p, "line 2:", "NaN");
}

#[test]
fn error_infinite_coordinates() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = ply_m(Enc::Be, T::F64, T::U8, T::U32, false, false);
    let h = data_start(&b);
    let at = h + 3 * 24 + 16;
    b[at..at + 8].copy_from_slice(&f64::NEG_INFINITY.to_be_bytes());
    let p = write(dir.path(), "inf.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 72),
        "vertex 3 has an infinite coordinate",
    );
    // Finite as a double, infinite as f32.
    b[at..at + 8].copy_from_slice(&1e300f64.to_be_bytes());
    let p = write(dir.path(), "inf2.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 72),
        "vertex 3 has an infinite coordinate",
    );
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("0 2 0", "0 inf 0", 1);
    let p = write(dir.path(), "inf.ply", a.as_bytes());
    expect_err(&p, "line 13:", "vertex 2 has an infinite coordinate");
    let p = write(
        dir.path(),
        "inf.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 -inf\nf 1 2 3\n",
    );
    expect_err(&p, "line 3:", "infinite");
}

#[test]
fn error_faces_with_fewer_than_3_vertices() {
    let dir = tempfile::tempdir().unwrap();
    let mut b = m_le();
    let h = data_start(&b);
    b[h + 120 + 13] = 2;
    let p = write(dir.path(), "f2.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 133),
        "face 1 has 2 vertices; a face needs at least 3",
    );
    let mut b = ply_m(Enc::Le, T::F32, T::U16, T::U32, false, false);
    let h = data_start(&b);
    b[h + 120] = 0;
    let p = write(dir.path(), "f0.ply", &b);
    expect_err(&p, &format!("byte {}:", h + 120), "face 0 has 0 vertices");
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("3 0 3 4", "2 0 3", 1);
    let p = write(dir.path(), "f2.ply", a.as_bytes());
    expect_err(&p, "line 22:", "face 1 has 2 vertices");
    let p = write(
        dir.path(),
        "f2.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 1 2\n",
    );
    expect_err(
        &p,
        "line 5:",
        "face has 2 vertices; a face needs at least 3",
    );
}

#[test]
fn error_list_counts_overrun_the_file() {
    let dir = tempfile::tempdir().unwrap();
    // The last face's count says 255 (fast path) ...
    let mut b = m_le();
    let h = data_start(&b);
    b[h + 146] = 255;
    let p = write(dir.path(), "l255.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 146),
        "list of 255 items runs past the end of the file",
    );
    // ... or 4e9 (uint counts, general path).
    let mut b = ply_m(Enc::Le, T::F32, T::U32, T::I32, false, false);
    let h = data_start(&b);
    b[h + 120..h + 124].copy_from_slice(&4_000_000_000u32.to_le_bytes());
    let p = write(dir.path(), "l4e9.ply", &b);
    expect_err(
        &p,
        &format!("byte {}:", h + 120),
        "list of 4000000000 items runs past the end of the file",
    );
    // In a skipped property of an unknown element.
    let mut b = format!(
        "ply\nformat binary_big_endian 1.0\nelement junk 1\nproperty list int double stuff\n\
         element vertex 3\n{XYZ}element face 1\nproperty list uchar int vertex_indices\nend_header\n"
    )
    .into_bytes();
    let h = b.len();
    b.extend(1_000_000i32.to_be_bytes());
    b.extend([0u8; 49]);
    let p = write(dir.path(), "junk.ply", &b);
    expect_err(
        &p,
        &format!("byte {h}:"),
        "element 'junk' record 0: list of 1000000 items runs past the end",
    );
    // ASCII.
    let a = String::from_utf8(ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, false)).unwrap();
    let a = a.replacen("4 6 7 8 9", "200 6 7 8 9", 1);
    let p = write(dir.path(), "l200.ply", a.as_bytes());
    expect_err(
        &p,
        "line 23:",
        "list of 200 items runs past the end of the file",
    );
}

#[test]
fn error_empty_file() {
    let dir = tempfile::tempdir().unwrap();
    for name in ["e.ply", "e.obj", "e.xyz"] {
        let p = write(dir.path(), name, b"");
        let e = expect_err(&p, "", "empty file");
        assert_eq!(e, format!("{}: empty file", p.display()));
    }
}

#[test]
fn error_vertices_but_no_faces() {
    let dir = tempfile::tempdir().unwrap();
    let b =
        format!("ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}end_header\n0 0 0\n1 0 0\n0 1 0\n");
    let p = write(dir.path(), "nf.ply", b.as_bytes());
    expect_err(&p, "", "no faces");
    let b = format!(
        "ply\nformat ascii 1.0\nelement vertex 3\n{XYZ}element face 0\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n0 1 0\n"
    );
    let p = write(dir.path(), "nf0.ply", b.as_bytes());
    expect_err(&p, "", "no faces");
    let p = write(dir.path(), "nf.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\n");
    let e = expect_err(&p, "", "no faces");
    assert_eq!(e, format!("{}: no faces", p.display()));
}

#[test]
fn error_obj_index_zero() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "z.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\nf 0 1 2\n",
    );
    expect_err(&p, "line 5:", "vertex index 0 is invalid");
    let p = write(
        dir.path(),
        "zn.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//0 2//1 3//1\n",
    );
    expect_err(&p, "line 5:", "normal index 0 is invalid");
}

#[test]
fn error_obj_index_out_of_range() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(dir.path(), "r.obj", b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 4\n");
    expect_err(
        &p,
        "line 4:",
        "vertex index 4 out of range (3 defined so far)",
    );
    let p = write(
        dir.path(),
        "rn.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 -4\n",
    );
    expect_err(&p, "line 4:", "vertex index -4 out of range");
    let p = write(
        dir.path(),
        "rvn.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//2 3//1\n",
    );
    expect_err(&p, "line 5:", "normal index 2 out of range");
    // Forward references are not allowed either.
    let p = write(
        dir.path(),
        "fw.obj",
        b"v 0 0 0\nv 1 0 0\nf 1 2 3\nv 0 1 0\n",
    );
    expect_err(&p, "line 3:", "vertex index 3 out of range");
}

#[test]
fn error_obj_garbage_numbers() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "g.obj",
        b"v 0 0 0\n\nv 1.0 abc 2\nv 0 1 0\nf 1 2 3\n",
    );
    expect_err(&p, "line 3:", "invalid number 'abc' in 'v' statement");
    let p = write(
        dir.path(),
        "g2.obj",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 x3\n",
    );
    expect_err(&p, "line 4:", "invalid vertex index 'x3'");
    let p = write(dir.path(), "g3.obj", b"v 0 0\n");
    expect_err(&p, "line 1:", "'v' statement needs 3 numbers");
}

#[test]
fn error_binary_file_given_as_obj() {
    let dir = tempfile::tempdir().unwrap();
    let p = write(
        dir.path(),
        "bin.obj",
        b"v 0 0 0\nv 1 0 0\x00\x01\x02\n\x7fELF",
    );
    expect_err(&p, "byte 15:", "not a text OBJ file (NUL byte)");
    let p = write(
        dir.path(),
        "utf.obj",
        b"v 0 0 0\nv 1 0 0\xff\xfe\nv 0 1 0\nf 1 2 3\n",
    );
    expect_err(&p, "byte 15:", "not a text OBJ file (invalid UTF-8)");
}

#[test]
fn error_directory_missing_file_unknown_extension() {
    let dir = tempfile::tempdir().unwrap();
    let sub = dir.path().join("models.obj");
    std::fs::create_dir(&sub).unwrap();
    expect_err(&sub, "", "is a directory");
    expect_err(&dir.path().join("missing.ply"), "", "cannot open");
    let p = write(dir.path(), "model.stl", b"solid x\nendsolid x\n");
    expect_err(&p, "", "unknown model format");
    let p = write(
        dir.path(),
        "model.ply",
        b"v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n",
    );
    expect_err(&p, "byte 0:", "not a PLY file");
    // Detection is by content: a PLY named .obj (or anything) is PLY.
    let p = write(dir.path(), "really-ply.obj", &m_le());
    check_model_m(&import(&p).unwrap().0, 0, false);
    let p = write(dir.path(), "noext", &m_le());
    assert_eq!(probe_model(&p).unwrap().format, ModelFormat::Ply);
}

// ------------------------------------------------------------------ fuzzing

/// xorshift64*: a tiny deterministic PRNG.
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }

    fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            (self.next() % n as u64) as usize
        }
    }
}

fn mutate(rng: &mut Rng, base: &[u8]) -> Vec<u8> {
    let mut b = base.to_vec();
    for _ in 0..1 + rng.below(3) {
        // Half the mutations hit the header / first lines.
        let span = if rng.below(2) == 0 {
            b.len().min(300)
        } else {
            b.len()
        };
        let pos = rng.below(span);
        match rng.below(7) {
            0 if !b.is_empty() => b[pos] ^= 1 << rng.below(8),
            1 if !b.is_empty() => b[pos] = rng.next() as u8,
            2 => b.truncate(rng.below(b.len() + 1)),
            3 => {
                const TEXT: &[u8] = b"0123456789 -.\n/e";
                for _ in 0..1 + rng.below(8) {
                    let c = if rng.below(2) == 0 {
                        TEXT[rng.below(TEXT.len())]
                    } else {
                        rng.next() as u8
                    };
                    b.insert(pos.min(b.len()), c);
                }
            }
            4 => {
                let end = (pos + 1 + rng.below(16)).min(b.len());
                b.drain(pos.min(end)..end);
            }
            5 if b.len() >= pos + 4 => {
                let v: [u8; 4] = match rng.below(4) {
                    0 => [0xFF; 4],
                    1 => [0, 0, 0, 0x80],
                    2 => *b"9999",
                    _ => [0x7F, 0xFF, 0xFF, 0xFF],
                };
                b[pos..pos + 4].copy_from_slice(&v);
            }
            _ => {
                // Duplicate a chunk.
                let end = (pos + 1 + rng.below(32)).min(b.len());
                let chunk = b[pos.min(end)..end].to_vec();
                let at = rng.below(b.len() + 1);
                b.splice(at..at, chunk);
            }
        }
    }
    b
}

#[test]
fn fuzz_mutated_files_never_panic() {
    let dir = tempfile::tempdir().unwrap();
    let mut obj = String::new();
    for (i, p) in POS.iter().enumerate() {
        obj += &format!(
            "v {} {} {}{}\n",
            p[0],
            p[1],
            p[2],
            if i % 2 == 0 { " 0.5 0.25 1" } else { "" }
        );
    }
    obj += "vn 0 0 1\nvt 0 0\nf 1 2 3\nf -10/1 -7/1/1 -6//1\nf 7 8 9 10\n";
    let bases: Vec<(&str, Vec<u8>)> = vec![
        ("le.ply", ply_m(Enc::Le, T::F32, T::U8, T::I32, false, true)),
        (
            "le2.ply",
            ply_m(Enc::Le, T::F32, T::U16, T::U32, true, false),
        ),
        ("be.ply", ply_m(Enc::Be, T::F64, T::U8, T::U16, false, true)),
        (
            "a.ply",
            ply_m(Enc::Ascii, T::F32, T::U8, T::I32, false, true),
        ),
        (
            "a2.ply",
            ply_m(Enc::Ascii, T::F64, T::U16, T::U32, true, false),
        ),
        ("m.obj", obj.into_bytes()),
    ];
    let opts = ImportOptions {
        max_vertex_bytes: 1 << 20,
    };
    let mut rng = Rng(0x9E37_79B9_7F4A_7C15);
    let (mut ok, mut err) = (0, 0);
    for (name, base) in &bases {
        // The unmutated file imports.
        let p = write(dir.path(), name, base);
        import(&p).unwrap_or_else(|e| panic!("{e}"));
        for k in 0..2000 {
            let b = mutate(&mut rng, base);
            let p = write(dir.path(), name, &b);
            let _ = probe_model(&p);
            match import_with(&p, 0, &opts) {
                Ok((tris, _)) => {
                    ok += 1;
                    for (i, t) in tris.iter().enumerate() {
                        assert_eq!(t.id, i as u32);
                        assert!(t.positions.iter().all(|p| p.is_finite()), "{name} #{k}");
                        for n in t.normals {
                            assert!((n.length() - 1.0).abs() < 1e-3, "{name} #{k}: {n:?}");
                        }
                    }
                }
                Err(e) => {
                    err += 1;
                    let e = e.to_string();
                    assert!(e.starts_with(&format!("{}: ", p.display())), "{e}");
                }
            }
        }
    }
    eprintln!("fuzz: {ok} Ok, {err} Err");
    assert!(ok > 100 && err > 1000, "{ok} Ok, {err} Err");
}

// ------------------------------------------------------------- real models

fn check_real(
    name: &str,
    triangles: u64,
    vertices: u64,
    lo: [f32; 3],
    hi: [f32; 3],
) -> Vec<Triangle> {
    let dir = tempfile::tempdir().unwrap();
    let p = common::unpack_model(name, dir.path());
    let pr = probe_model(&p).unwrap();
    assert_eq!(
        (pr.format, pr.vertices, pr.faces),
        (ModelFormat::Ply, vertices, triangles)
    );
    let (tris, s) = import(&p).unwrap();
    assert_eq!(
        s,
        ImportSummary {
            vertices,
            triangles,
            has_normals: false,
            has_colors: false
        }
    );
    let (mut min, mut max) = (Vec3::INFINITY, Vec3::NEG_INFINITY);
    for (i, t) in tris.iter().enumerate() {
        assert_eq!(t.id, i as u32);
        assert_eq!(t.colors, [DEFAULT_COLOR; 3]);
        for n in t.normals {
            assert!((n.length() - 1.0).abs() < 1e-4, "triangle {i}: {n:?}");
        }
        for p in t.positions {
            min = min.min(p);
            max = max.max(p);
        }
    }
    assert!(
        (min - Vec3::from_array(lo)).abs().max_element() < 1e-3,
        "{min:?}"
    );
    assert!(
        (max - Vec3::from_array(hi)).abs().max_element() < 1e-3,
        "{max:?}"
    );
    tris
}

#[test]
fn real_stanford_bunny() {
    check_real(
        "stanford-bunny",
        69_451,
        35_947,
        [-0.0947, 0.0330, -0.0619],
        [0.0610, 0.1873, 0.0588],
    );
}

#[test]
fn real_igea() {
    check_real(
        "igea",
        268_686,
        134_345,
        [-0.0346, -0.0497, -0.0495],
        [0.0346, 0.0497, 0.0495],
    );
}

#[test]
fn real_living_room_with_zero_area_triangles() {
    let tris = check_real(
        "bitterli-living-room-3",
        787_232,
        394_190,
        [-6.022, -0.003, -6.679],
        [0.317, 2.722, 0.000],
    );
    if !tris.is_empty() {
        let degenerate = tris
            .iter()
            .filter(|t| {
                let p = t.positions;
                p[0] == p[1] || p[1] == p[2] || p[0] == p[2]
            })
            .count();
        assert!(degenerate >= 288, "{degenerate}");
    }
}

// -------------------------------------------------------------- throughput

/// Writes a binary little-endian PLY grid of about `target` triangles (with
/// constant vertex normals if asked); returns (vertices, triangles).
fn write_grid(path: &Path, target: u64, with_normals: bool) -> (u64, u64) {
    use std::io::Write;
    let side = ((target / 2) as f64).sqrt().ceil() as u32 + 1;
    let nv = side as u64 * side as u64;
    let nt = 2 * (side as u64 - 1) * (side as u64 - 1);
    let mut w = std::io::BufWriter::with_capacity(1 << 20, std::fs::File::create(path).unwrap());
    let normals = if with_normals {
        "property float nx\nproperty float ny\nproperty float nz\n"
    } else {
        ""
    };
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\nelement vertex {nv}\n{XYZ}{normals}\
         element face {nt}\nproperty list uchar int vertex_indices\nend_header\n"
    )
    .unwrap();
    for y in 0..side {
        for x in 0..side {
            let z = ((x ^ y) % 7) as f32 * 0.01;
            for c in [x as f32, y as f32, z] {
                w.write_all(&c.to_le_bytes()).unwrap();
            }
            if with_normals {
                for c in [0.1f32, 0.2, 1.0] {
                    w.write_all(&c.to_le_bytes()).unwrap();
                }
            }
        }
    }
    for y in 0..side - 1 {
        for x in 0..side - 1 {
            let i = (y * side + x) as i32;
            let s = side as i32;
            for f in [[i, i + 1, i + s + 1], [i, i + s + 1, i + s]] {
                w.write_all(&[3]).unwrap();
                for k in f {
                    w.write_all(&k.to_le_bytes()).unwrap();
                }
            }
        }
    }
    w.flush().unwrap();
    (nv, nt)
}

/// Import speed on a large binary little-endian PLY (a grid of triangles).
/// `DRAY_IMPORT_BENCH_TRIS=10000000 cargo test --release -p dray-scene
/// --test import -- --ignored --nocapture bench`
#[test]
#[ignore]
fn bench_binary_ply_import() {
    let target: u64 = std::env::var("DRAY_IMPORT_BENCH_TRIS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(10_000_000);
    let dir = tempfile::tempdir().unwrap();
    for with_normals in [false, true] {
        let path = dir.path().join(format!("grid-{with_normals}.ply"));
        let (nv, nt) = write_grid(&path, target, with_normals);
        eprintln!("{nt} triangles, {nv} vertices, normals in the file: {with_normals}");
        for round in 0..3 {
            let t0 = std::time::Instant::now();
            let mut acc = 0f32;
            let opts = ImportOptions {
                max_vertex_bytes: 8 << 30,
            };
            let s = import_model(&path, 0, &opts, &mut |t| {
                acc += t.normals[0].z + t.positions[2].x;
                Ok(())
            })
            .unwrap();
            let dt = t0.elapsed().as_secs_f64();
            assert_eq!(s.triangles, nt);
            eprintln!(
                "  round {round}: {dt:.3} s, {:.1} M triangles/s [{acc}]",
                nt as f64 / dt / 1e6
            );
        }
    }
}
