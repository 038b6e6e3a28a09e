//! Camera paths: keyframes in a TOML file, sampled into one camera per
//! frame.
//!
//! ```toml
//! frames = 120            # frames sampled along the whole path
//! [[keyframe]]
//! eye = [x, y, z]
//! look = [x, y, z]
//! up = [0.0, 1.0, 0.0]    # optional
//! fov_y_deg = 50.0        # optional (default 45)
//! ```
//!
//! Keyframe `j` of `K` is shown exactly at frame `round(j (N-1) / (K-1))`;
//! in between, eye and look follow a Catmull-Rom spline through the
//! keyframes (uniform in the keyframe parameter, the end keyframes
//! repeated), the up vector and the field of view are linear.

use dray_protocol::Camera;
use dray_scene::Aabb;
use glam::Vec3;
use std::path::{Path, PathBuf};

/// Most frames a path may have.
pub const MAX_FRAMES: u32 = 100_000;
/// Field of view when a keyframe gives none, degrees.
pub const DEFAULT_FOV_Y_DEG: f32 = 45.0;

/// Why a camera path is unusable; names the file and the key.
#[derive(Debug, thiserror::Error)]
pub enum PathError {
    /// The file could not be read.
    #[error("{file}: {source}")]
    Io {
        /// The file.
        file: PathBuf,
        /// What happened.
        source: std::io::Error,
    },
    /// The file is not TOML.
    #[error("{file}: not valid TOML: {message}")]
    Toml {
        /// The file.
        file: PathBuf,
        /// The parser's message (with line and column).
        message: String,
    },
    /// A value is missing or wrong.
    #[error("{file}: {key}: {message}")]
    Invalid {
        /// The file.
        file: PathBuf,
        /// The key, e.g. `frames` or `keyframe[2].eye`.
        key: String,
        /// What is wrong.
        message: String,
    },
}

/// One keyframe.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Keyframe {
    /// Eye position.
    pub eye: [f32; 3],
    /// Point looked at.
    pub look: [f32; 3],
    /// Up hint.
    pub up: [f32; 3],
    /// Vertical field of view, degrees.
    pub fov_y_deg: f32,
}

impl Keyframe {
    fn camera(&self) -> Camera {
        Camera {
            eye: self.eye,
            look: self.look,
            up: self.up,
            fov_y_deg: self.fov_y_deg,
        }
    }
}

/// A camera path: keyframes and the number of frames along it.
#[derive(Clone, Debug, PartialEq)]
pub struct CameraPath {
    /// Frames sampled along the whole path.
    pub frames: u32,
    /// At least two keyframes.
    pub keyframes: Vec<Keyframe>,
}

impl CameraPath {
    /// Reads a path file.
    pub fn load(path: &Path) -> Result<CameraPath, PathError> {
        let text = std::fs::read_to_string(path).map_err(|source| PathError::Io {
            file: path.to_path_buf(),
            source,
        })?;
        CameraPath::parse(&text, path)
    }

    /// Parses a path file's text; `file` names it in errors.
    pub fn parse(text: &str, file: &Path) -> Result<CameraPath, PathError> {
        let invalid = |key: &str, message: String| PathError::Invalid {
            file: file.to_path_buf(),
            key: key.to_string(),
            message,
        };
        let table: toml::Table = text.parse().map_err(|e: toml::de::Error| PathError::Toml {
            file: file.to_path_buf(),
            message: e.to_string().trim().to_string(),
        })?;
        for k in table.keys() {
            if k != "frames" && k != "keyframe" {
                return Err(invalid(
                    k,
                    "unknown key (expected frames and [[keyframe]])".into(),
                ));
            }
        }
        let frames = match table.get("frames") {
            None => return Err(invalid("frames", "missing".into())),
            Some(toml::Value::Integer(n)) => *n,
            Some(v) => {
                return Err(invalid(
                    "frames",
                    format!("expected an integer, found a {}", v.type_str()),
                ))
            }
        };
        if frames < 1 || frames > i64::from(MAX_FRAMES) {
            return Err(invalid(
                "frames",
                format!("{frames} is not in 1..={MAX_FRAMES}"),
            ));
        }
        let list = match table.get("keyframe") {
            None => {
                return Err(invalid(
                    "keyframe",
                    "missing (at least two [[keyframe]] tables)".into(),
                ))
            }
            Some(toml::Value::Array(a)) => a,
            Some(v) => {
                return Err(invalid(
                    "keyframe",
                    format!("expected [[keyframe]] tables, found a {}", v.type_str()),
                ))
            }
        };
        let mut keyframes = Vec::with_capacity(list.len());
        for (i, v) in list.iter().enumerate() {
            let at = |key: &str| format!("keyframe[{i}].{key}");
            let Some(t) = v.as_table() else {
                return Err(invalid(
                    &format!("keyframe[{i}]"),
                    format!("expected a table, found a {}", v.type_str()),
                ));
            };
            for k in t.keys() {
                if !["eye", "look", "up", "fov_y_deg"].contains(&k.as_str()) {
                    return Err(invalid(
                        &at(k),
                        "unknown key (expected eye, look, up, fov_y_deg)".into(),
                    ));
                }
            }
            let vec3 = |key: &str, required: bool| -> Result<Option<[f32; 3]>, PathError> {
                let Some(v) = t.get(key) else {
                    return if required {
                        Err(invalid(&at(key), "missing".into()))
                    } else {
                        Ok(None)
                    };
                };
                let bad = || invalid(&at(key), "expected an array of three numbers".into());
                let a = v.as_array().ok_or_else(bad)?;
                if a.len() != 3 {
                    return Err(bad());
                }
                let mut out = [0.0f32; 3];
                for (o, x) in out.iter_mut().zip(a) {
                    *o = number(x).ok_or_else(bad)?;
                }
                Ok(Some(out))
            };
            let eye = vec3("eye", true)?.unwrap_or_default();
            let look = vec3("look", true)?.unwrap_or_default();
            let up = vec3("up", false)?.unwrap_or([0.0, 1.0, 0.0]);
            let fov_y_deg = match t.get("fov_y_deg") {
                None => DEFAULT_FOV_Y_DEG,
                Some(x) => number(x)
                    .ok_or_else(|| invalid(&at("fov_y_deg"), "expected a number".into()))?,
            };
            keyframes.push(Keyframe {
                eye,
                look,
                up,
                fov_y_deg,
            });
        }
        CameraPath::new(frames as u32, keyframes).map_err(|(key, message)| PathError::Invalid {
            file: file.to_path_buf(),
            key,
            message,
        })
    }

    /// Checks a path's number of frames (a file's `frames`, or the
    /// `--frames` of `dray walkthrough`).
    pub fn check_frames(frames: u32) -> Result<(), String> {
        if frames == 0 || frames > MAX_FRAMES {
            return Err(format!("{frames} is not in 1..={MAX_FRAMES}"));
        }
        Ok(())
    }

    /// A path from keyframes, checked: an error is `(key, message)`.
    pub fn new(frames: u32, keyframes: Vec<Keyframe>) -> Result<CameraPath, (String, String)> {
        CameraPath::check_frames(frames).map_err(|m| ("frames".to_string(), m))?;
        if keyframes.len() < 2 {
            return Err((
                "keyframe".into(),
                format!("{} keyframe(s); a path needs at least two", keyframes.len()),
            ));
        }
        for (i, k) in keyframes.iter().enumerate() {
            let at = |key: &str| format!("keyframe[{i}].{key}");
            for (key, v) in [("eye", k.eye), ("look", k.look), ("up", k.up)] {
                if !v.iter().all(|x| x.is_finite()) {
                    return Err((at(key), format!("{v:?} has a non-finite number")));
                }
            }
            if !k.fov_y_deg.is_finite() || k.fov_y_deg <= 0.0 || k.fov_y_deg >= 180.0 {
                return Err((
                    at("fov_y_deg"),
                    format!("{} is not in (0, 180) degrees", k.fov_y_deg),
                ));
            }
            let fwd = Vec3::from(k.look) - Vec3::from(k.eye);
            if fwd.length_squared() == 0.0 {
                return Err((at("look"), "equals eye (the camera looks nowhere)".into()));
            }
            let up = Vec3::from(k.up);
            if up.length_squared() == 0.0 {
                return Err((at("up"), "is the zero vector".into()));
            }
            if fwd.normalize().cross(up.normalize()).length() < 1e-4 {
                return Err((at("up"), "is parallel to the view direction".into()));
            }
        }
        Ok(CameraPath { frames, keyframes })
    }

    /// The frame at which keyframe `j` is shown exactly.
    pub fn keyframe_frame(&self, j: usize) -> u32 {
        let k = self.keyframes.len().max(2) as u64 - 1;
        let n = u64::from(self.frames.max(1)) - 1;
        ((j as u64 * n + k / 2) / k) as u32
    }

    /// One camera per frame.
    pub fn cameras(&self) -> Vec<Camera> {
        let k = &self.keyframes;
        if k.is_empty() {
            return Vec::new();
        }
        let last = k.len() - 1;
        let mut out = Vec::with_capacity(self.frames as usize);
        for f in 0..self.frames {
            // The segment [j, j+1] whose frames hold f.
            let mut j = 0;
            while j < last && self.keyframe_frame(j + 1) <= f {
                j += 1;
            }
            // The ends are the end keyframes even when several keyframes
            // share a frame (fewer frames than keyframes).
            if f == 0 {
                out.push(k[0].camera());
                continue;
            }
            if j == last || f == self.keyframe_frame(j) {
                out.push(k[j].camera());
                continue;
            }
            let (f0, f1) = (self.keyframe_frame(j), self.keyframe_frame(j + 1));
            let u = (f - f0) as f32 / (f1 - f0) as f32;
            let p = |i: isize| k[i.clamp(0, last as isize) as usize];
            let ji = j as isize;
            let (a, b, c, d) = (p(ji - 1), p(ji), p(ji + 1), p(ji + 2));
            let cr = |g: fn(&Keyframe) -> [f32; 3]| {
                catmull_rom(g(&a).into(), g(&b).into(), g(&c).into(), g(&d).into(), u)
            };
            let eye = cr(|k| k.eye);
            let mut look = cr(|k| k.look);
            if (look - eye).length_squared() < 1e-12 {
                // Degenerate between keyframes: keep the linear direction.
                let dir = Vec3::from(b.look) - Vec3::from(b.eye);
                let dir2 = Vec3::from(c.look) - Vec3::from(c.eye);
                let d = dir.lerp(dir2, u);
                look = eye + if d.length_squared() > 0.0 { d } else { dir };
            }
            let mut up = Vec3::from(b.up)
                .normalize()
                .lerp(Vec3::from(c.up).normalize(), u);
            let fwd = (look - eye).normalize_or_zero();
            if up.length_squared() < 1e-8 || fwd.cross(up.normalize()).length() < 1e-4 {
                up = if fwd.cross(Vec3::Y).length() > 1e-3 {
                    Vec3::Y
                } else {
                    Vec3::Z
                };
            }
            out.push(Camera {
                eye: eye.to_array(),
                look: look.to_array(),
                up: up.normalize().to_array(),
                fov_y_deg: b.fov_y_deg + (c.fov_y_deg - b.fov_y_deg) * u,
            });
        }
        out
    }

    /// A walkthrough of a generated plant with these bounds (the paper's
    /// Figure 3): from outside, high up, seeing the whole model, flying in
    /// along the first road and ending deep inside among the structures at
    /// eye height, looking ahead. The keyframes are
    /// [`dray_scene::generate::suggested_views`] but the last (which looks
    /// up), with the final eye kept inside the bounds.
    pub fn walkthrough(bounds: &Aabb, frames: u32) -> CameraPath {
        let frames = frames.clamp(1, MAX_FRAMES);
        let views = dray_scene::generate::suggested_views(bounds);
        let lo = bounds.lo();
        let hi = bounds.hi();
        let e = bounds.extent();
        let mut keyframes: Vec<Keyframe> = views
            .iter()
            .take(5)
            .map(|&(eye, look)| Keyframe {
                eye: eye.to_array(),
                look: look.to_array(),
                up: [0.0, 1.0, 0.0],
                fov_y_deg: 50.0,
            })
            .collect();
        // End at eye height (1.7 m, within the model), inside the bounds,
        // looking ahead across the plant and slightly down.
        let eye_h = (lo.y + 1.7).min(lo.y + 0.5 * e.y);
        let end_eye =
            Vec3::new(lo.x + 0.45 * e.x, eye_h, lo.z + 0.45 * e.z).clamp(lo.min(hi), hi.max(lo));
        let end_look = Vec3::new(lo.x + 0.95 * e.x, eye_h, lo.z + 0.9 * e.z);
        if let Some(last) = keyframes.last_mut() {
            last.eye = end_eye.to_array();
            last.look = end_look.to_array();
            last.fov_y_deg = 60.0;
        }
        // Drop keyframes made degenerate by flat or empty bounds.
        let mut keyframes: Vec<Keyframe> = keyframes
            .into_iter()
            .filter(|k| {
                let f = Vec3::from(k.look) - Vec3::from(k.eye);
                k.eye.iter().chain(&k.look).all(|x| x.is_finite())
                    && f.length_squared() > 0.0
                    && f.normalize().cross(Vec3::Y).length() > 1e-4
            })
            .collect();
        while keyframes.len() < 2 {
            // A degenerate box: a plain approach to its centre.
            let c = if bounds.is_empty() {
                Vec3::ZERO
            } else {
                bounds.center()
            };
            let r = bounds.diagonal().max(1.0);
            keyframes = vec![
                Keyframe {
                    eye: (c + Vec3::new(-r, 0.5 * r, -r)).to_array(),
                    look: c.to_array(),
                    up: [0.0, 1.0, 0.0],
                    fov_y_deg: 50.0,
                },
                Keyframe {
                    eye: c.to_array(),
                    look: (c + Vec3::new(r, 0.0, r)).to_array(),
                    up: [0.0, 1.0, 0.0],
                    fov_y_deg: 60.0,
                },
            ];
        }
        CameraPath { frames, keyframes }
    }

    /// Writes the path file to `out` through a temporary file renamed over
    /// it, so that no reader sees half a path.
    pub fn save(&self, out: &Path) -> std::io::Result<()> {
        let tmp = out.with_extension("toml.tmp");
        std::fs::write(&tmp, self.to_toml())?;
        std::fs::rename(&tmp, out)
    }

    /// The path as a path file (what [`CameraPath::load`] reads).
    pub fn to_toml(&self) -> String {
        let v = |a: [f32; 3]| format!("[{:?}, {:?}, {:?}]", a[0], a[1], a[2]);
        let mut s = format!(
            "# dray camera path: {} keyframes, Catmull-Rom through eye and look.\nframes = {}\n",
            self.keyframes.len(),
            self.frames
        );
        for (j, k) in self.keyframes.iter().enumerate() {
            s += &format!(
                "\n[[keyframe]]  # shown at frame {}\neye = {}\nlook = {}\nup = {}\nfov_y_deg = {:?}\n",
                self.keyframe_frame(j),
                v(k.eye),
                v(k.look),
                v(k.up),
                k.fov_y_deg
            );
        }
        s
    }
}

fn number(v: &toml::Value) -> Option<f32> {
    let x = match v {
        toml::Value::Float(f) => *f as f32,
        toml::Value::Integer(i) => *i as f32,
        _ => return None,
    };
    // Non-finite values are reported by `CameraPath::new` with the key.
    Some(x)
}

fn catmull_rom(p0: Vec3, p1: Vec3, p2: Vec3, p3: Vec3, t: f32) -> Vec3 {
    let t2 = t * t;
    let t3 = t2 * t;
    0.5 * (2.0 * p1
        + (p2 - p0) * t
        + (2.0 * p0 - 5.0 * p1 + 4.0 * p2 - p3) * t2
        + (3.0 * p1 - p0 - 3.0 * p2 + p3) * t3)
}
