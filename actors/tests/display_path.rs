//! Camera paths: files, interpolation, errors, the built-in walkthrough.

use dray_actors::display::{CameraPath, PathError};
use dray_scene::Aabb;
use glam::Vec3;
use std::path::Path;

const THREE: &str = r#"
frames = 61
[[keyframe]]
eye = [0.0, 2.0, -20.0]
look = [0.0, 0.0, 0.0]
fov_y_deg = 50.0

[[keyframe]]
eye = [10, 3, -5]          # integers are numbers too
look = [0.0, 1.0, 0.0]
up = [0.0, 1.0, 0.1]

[[keyframe]]
eye = [12.0, 1.7, 6.0]
look = [20.0, 1.7, 12.0]
fov_y_deg = 70.0

[[keyframe]]
eye = [5.0, 1.7, 15.0]
look = [0.0, 1.7, 30.0]
"#;

fn write(dir: &Path, name: &str, text: &str) -> std::path::PathBuf {
    let p = dir.join(name);
    std::fs::write(&p, text).unwrap();
    p
}

#[test]
fn display_path_passes_through_keyframes_smoothly() {
    let dir = tempfile::tempdir().unwrap();
    let file = write(dir.path(), "path.toml", THREE);
    let path = CameraPath::load(&file).unwrap();
    assert_eq!(path.frames, 61);
    assert_eq!(path.keyframes.len(), 4);
    assert_eq!(path.keyframes[1].eye, [10.0, 3.0, -5.0]);
    assert_eq!(path.keyframes[1].fov_y_deg, 45.0, "default field of view");
    assert_eq!(path.keyframes[0].up, [0.0, 1.0, 0.0], "default up");
    let cams = path.cameras();
    assert_eq!(cams.len(), 61);
    // Exactly at their frames: 0, 20, 40, 60.
    for (j, k) in path.keyframes.iter().enumerate() {
        let f = path.keyframe_frame(j) as usize;
        assert_eq!(f, j * 20);
        let c = &cams[f];
        assert_eq!((c.eye, c.look, c.fov_y_deg), (k.eye, k.look, k.fov_y_deg));
    }
    assert_eq!(cams[0].eye, path.keyframes[0].eye);
    assert_eq!(cams[60].eye, path.keyframes[3].eye);
    // Smooth: no step much longer than the mean, no sharp turn of velocity.
    let eyes: Vec<Vec3> = cams.iter().map(|c| Vec3::from(c.eye)).collect();
    let steps: Vec<Vec3> = eyes.windows(2).map(|w| w[1] - w[0]).collect();
    let mean = steps.iter().map(|s| s.length()).sum::<f32>() / steps.len() as f32;
    for (i, s) in steps.iter().enumerate() {
        assert!(
            s.length() < 3.0 * mean,
            "step {i}: {} vs mean {mean}",
            s.length()
        );
    }
    for (i, w) in steps.windows(2).enumerate() {
        assert!(
            (w[1] - w[0]).length() < 0.5 * mean,
            "velocity jumps at frame {}: {:?} then {:?}",
            i + 1,
            w[0],
            w[1]
        );
    }
    for c in &cams {
        assert!(c.fov_y_deg >= 45.0 && c.fov_y_deg <= 70.0);
        assert!(c.eye != c.look);
        assert!(c
            .eye
            .iter()
            .chain(&c.look)
            .chain(&c.up)
            .all(|x| x.is_finite()));
    }
    // A path with fewer frames than keyframes still starts and ends right.
    let short = CameraPath {
        frames: 2,
        ..path.clone()
    };
    let cams = short.cameras();
    assert_eq!(cams.len(), 2);
    assert_eq!(cams[0].eye, path.keyframes[0].eye);
    assert_eq!(cams[1].eye, path.keyframes[3].eye);
}

fn error_of(text: &str) -> String {
    let e: PathError = CameraPath::parse(text, Path::new("walk.toml")).unwrap_err();
    e.to_string()
}

#[test]
fn display_path_errors_name_file_and_key() {
    let key = |eye: &str, look: &str| format!("[[keyframe]]\neye = {eye}\nlook = {look}\n");
    let two = format!(
        "{}{}",
        key("[0.0, 0.0, 0.0]", "[1.0, 0.0, 0.0]"),
        key("[1.0, 0.0, 0.0]", "[2.0, 0.0, 0.0]")
    );
    let cases: Vec<(String, &str)> = vec![
        (two.clone(), "frames: missing"),
        (format!("frames = 0\n{two}"), "frames: 0 is not in"),
        (
            format!("frames = 100001\n{two}"),
            "frames: 100001 is not in",
        ),
        (
            format!("frames = \"ten\"\n{two}"),
            "frames: expected an integer",
        ),
        ("frames = 10\n".into(), "keyframe: missing"),
        (
            format!("frames = 10\n{}", key("[0.0, 0.0, 0.0]", "[1.0, 0.0, 0.0]")),
            "keyframe: 1 keyframe(s)",
        ),
        (
            format!("frames = 10\n{two}[[keyframe]]\neye = [0.0, 1.0, 2.0]\n"),
            "keyframe[2].look: missing",
        ),
        (
            format!("frames = 10\n{two}{}", key("[0.0, 1.0]", "[1.0, 0.0, 0.0]")),
            "keyframe[2].eye: expected an array of three numbers",
        ),
        (
            format!(
                "frames = 10\n{two}{}",
                key("[0.0, nan, 0.0]", "[1.0, 0.0, 0.0]")
            ),
            "keyframe[2].eye: [0.0, NaN, 0.0] has a non-finite number",
        ),
        (
            format!(
                "frames = 10\n{two}{}",
                key("[0.0, 0.0, 0.0]", "[1.0, inf, 0.0]")
            ),
            "keyframe[2].look: [1.0, inf, 0.0] has a non-finite number",
        ),
        (
            format!(
                "frames = 10\n{two}{}",
                key("[1.0, 2.0, 3.0]", "[1.0, 2.0, 3.0]")
            ),
            "keyframe[2].look: equals eye",
        ),
        (
            format!("frames = 10\n{two}fov_y_deg = 180.0\n"),
            "keyframe[1].fov_y_deg: 180 is not in (0, 180)",
        ),
        (
            format!("frames = 10\n{two}up = [1.0, 0.0, 0.0]\n"),
            "keyframe[1].up: is parallel",
        ),
        (
            format!("frames = 10\n{two}fov = 50.0\n"),
            "keyframe[1].fov: unknown key",
        ),
        (format!("frame = 10\n{two}"), "frame: unknown key"),
        ("frames = [".into(), "not valid TOML"),
    ];
    for (text, want) in cases {
        let msg = error_of(&text);
        assert!(msg.starts_with("walk.toml: "), "{msg}");
        assert!(msg.contains(want), "{msg:?} should contain {want:?}");
    }
    let missing = CameraPath::load(Path::new("/nonexistent/dir/p.toml")).unwrap_err();
    assert!(missing.to_string().contains("/nonexistent/dir/p.toml"));
}

fn inside(b: &Aabb, p: [f32; 3]) -> bool {
    (0..3).all(|a| b.min[a] <= p[a] && p[a] <= b.max[a])
}

#[test]
fn display_path_walkthrough_flies_from_outside_to_inside() {
    for b in [
        Aabb::new(Vec3::new(0.0, 0.0, 0.0), Vec3::new(60.0, 25.0, 60.0)),
        Aabb::new(
            Vec3::new(-300.0, -2.0, -290.0),
            Vec3::new(280.0, 40.0, 290.0),
        ),
        Aabb::new(Vec3::new(5.0, 0.0, 5.0), Vec3::new(20.0, 4.0, 30.0)),
    ] {
        let path = CameraPath::walkthrough(&b, 300);
        assert_eq!(path.frames, 300);
        let cams = path.cameras();
        assert_eq!(cams.len(), 300);
        let first = cams[0];
        let last = cams[299];
        assert!(!inside(&b, first.eye), "starts outside: {:?}", first.eye);
        assert!(inside(&b, last.eye), "ends inside: {:?} in {b:?}", last.eye);
        // At eye height, looking ahead rather than up or down.
        assert!(last.eye[1] - b.min[1] <= 2.0, "eye height: {:?}", last.eye);
        for c in &cams {
            let f = (Vec3::from(c.look) - Vec3::from(c.eye)).normalize();
            assert!(f.is_finite());
            assert!(f.y.abs() < 0.9, "looking forward-ish: {f:?}");
        }
        // The start sees the whole model: the centre is ahead.
        let f = (Vec3::from(first.look) - Vec3::from(first.eye)).normalize();
        let to_c = (b.center() - Vec3::from(first.eye)).normalize();
        assert!(f.dot(to_c) > 0.95);
        // The TOML round-trips exactly.
        let text = path.to_toml();
        let back = CameraPath::parse(&text, Path::new("walk.toml")).unwrap();
        assert_eq!(back, path);
    }
}
