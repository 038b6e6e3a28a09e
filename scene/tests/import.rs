//! Tests of the PLY and OBJ importers: exact triangles for tiny hand-written
//! models, one test per kind of bad input (the error must name the file, the
//! place and the problem), a fuzz-style robustness test and the real bunny.

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
    for k in 0..3 {
        assert!(
            close(t.normals[k], n[k]),
            "normal {k} of triangle {id}: {:?} vs {:?}",
            t.normals[k],
            n[k]
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
