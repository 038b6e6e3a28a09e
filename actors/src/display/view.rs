//! The interactive view: what a person at the web viewer controls, and
//! which frame the display asks for next.
//!
//! A [`ViewInput`] comes from the page ([`super::web`] parses and bounds
//! it) and [`View::apply`] turns it into the next camera or frame format:
//!
//! - **fly**: translate by world-space distances along the view, right and
//!   up vectors, then turn about the eye (the page integrates held keys and
//!   mouse look over its frame time, with the speed it shows);
//! - **orbit**: rotate the camera about the pivot (the last picked point,
//!   else where the home camera looks), keeping its view of the pivot;
//!   **zoom** moves the eye towards the pivot by a factor per wheel step;
//! - **home**: back to the first camera (framed on the model);
//! - **pick**: the next frame also returns triangle ids and depths, and the
//!   pixel under the click answers with its triangle, distance and point
//!   ([`View::picked`]);
//! - **set**: shadows, reflections, the voxel view (the paper's Figure 5)
//!   and the resolution scale, without a restart;
//! - **play**: one frame per camera of a path, then the view rests on its
//!   last camera; a move, `home` or **stop** ends it early (the display's
//!   [`super::record`] makes paths of flights).
//!
//! Any change starts again at sample 0; a camera left still is refined one
//! jittered sample per frame up to [`View::max_samples`], and then the
//! display stops asking for frames until the next input.

use dray_protocol::{Camera, FrameFormat, RenderSettings};
use glam::Vec3;
use std::sync::Arc;

/// Resolution scales a user can choose, smallest first.
pub const SCALES: [f32; 3] = [0.5, 1.0, 2.0];
/// Most pixels a frame may have at a chosen scale (a larger scale is not
/// offered): 2× of 1920×1080 fits, and frames in flight stay a few
/// hundred megabytes.
pub const MAX_SCALED_PIXELS: u64 = 3840 * 2160;
/// Reflection depth when a user turns reflections on and the config has
/// none.
pub const DEFAULT_REFLECTION_DEPTH: u8 = 2;
/// Each wheel step brings the eye this factor closer to the pivot.
pub const ZOOM_PER_STEP: f32 = 0.85;
/// Largest translation one input may carry, in home distances (the home
/// camera's eye→look distance): a bound on a confused or hostile page.
pub const MAX_FLY_HOMES: f32 = 4.0;
/// Largest turn or orbit one input may carry, degrees.
pub const MAX_TURN_DEG: f32 = 360.0;
/// Largest zoom one input may carry, wheel steps either way.
pub const MAX_ZOOM_STEPS: f32 = 20.0;
/// Closest the view direction gets to the up vector, degrees.
const MIN_POLE_DEG: f32 = 2.0;

/// One thing a person did at the viewer.
#[derive(Clone, Debug, PartialEq)]
pub enum ViewInput {
    /// Translate by world distances along view, right and up, then turn
    /// (yaw positive: left; pitch positive: up), degrees.
    Fly {
        forward: f32,
        right: f32,
        up: f32,
        yaw_deg: f32,
        pitch_deg: f32,
    },
    /// Rotate about the pivot (yaw positive: the camera goes right, the
    /// model turns left; pitch positive: the camera goes up), degrees.
    Orbit { yaw_deg: f32, pitch_deg: f32 },
    /// Wheel steps towards the pivot (negative: away).
    Zoom { steps: f32 },
    /// Back to the first camera.
    Home,
    /// What lies under this point of the image, x right and y down in
    /// [0, 1]; with `pivot`, it also becomes the orbit's pivot.
    Pick { x: f32, y: f32, pivot: bool },
    /// Change what frames show; `None` leaves a choice as it is.
    Set {
        shadows: Option<bool>,
        reflections: Option<bool>,
        voxels: Option<bool>,
        scale: Option<f32>,
    },
    /// Show these cameras one frame each (a camera path's frames).
    Play(Arc<[Camera]>),
    /// End a path being played where it is.
    Stop,
    /// Start (`true`) or stop recording the flight: the display's
    /// recorder takes it, the view's camera and frames do not change.
    Record(bool),
}

/// What a pick found.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Picked {
    /// Where the page clicked, as sent.
    pub x: f32,
    pub y: f32,
    /// The triangle hit (its id in the model), if any.
    pub triangle: Option<u32>,
    /// Distance from the eye along the ray.
    pub distance: Option<f32>,
    /// The point hit.
    pub point: Option<[f32; 3]>,
}

/// A pick waiting for a frame with ids and depths.
#[derive(Clone, Copy, Debug, PartialEq)]
struct PickRequest {
    x: f32,
    y: f32,
    pivot: bool,
}

/// The next frame to ask the cluster for.
#[derive(Clone, Debug, PartialEq)]
pub struct NextFrame {
    pub camera: Camera,
    pub sample: u32,
    /// The frame's size and settings, when they differ from the last
    /// frame's.
    pub format: Option<FrameFormat>,
    /// Which view this frame shows: frames of one view are samples of the
    /// same image and accumulate.
    pub view: u64,
    /// The frame answers a pick.
    pub pick: bool,
    /// Playing a path: this frame's index in it, and its length.
    pub path: Option<(u32, u32)>,
}

/// The view's choices besides the camera, as the page shows them.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Choices {
    pub shadows: bool,
    pub reflections: bool,
    pub voxels: bool,
    pub scale: f32,
    pub width: u32,
    pub height: u32,
    /// The flight is being recorded (the display's recorder sets it).
    pub recording: bool,
}

/// The interactive view's state.
#[derive(Clone, Debug)]
pub struct View {
    home: Camera,
    camera: Camera,
    /// The home camera's eye→look distance: the model's scale.
    home_distance: f32,
    pivot: Vec3,
    base: FrameFormat,
    shadows: bool,
    reflections: bool,
    voxels: bool,
    scale: f32,
    /// The format of the last frame asked for (`None` before the first).
    sent_format: Option<FrameFormat>,
    /// Bumped on every change of camera or format.
    view: u64,
    /// The next sample of this view to ask for.
    sample: u32,
    max_samples: u32,
    pick: Option<PickRequest>,
    playing: Option<Playing>,
}

/// A path being played.
#[derive(Clone, Debug)]
struct Playing {
    cameras: Arc<[Camera]>,
    /// The index of the next frame.
    next: usize,
}

impl View {
    /// A view starting at `home` with the config's size and settings,
    /// refined up to `max_samples` (at least 1) when still.
    pub fn new(home: Camera, base: FrameFormat, max_samples: u32) -> View {
        let home_distance = (v(home.look) - v(home.eye)).length();
        let home_distance = if home_distance.is_finite() && home_distance > 0.0 {
            home_distance
        } else {
            1.0
        };
        View {
            home,
            camera: home,
            home_distance,
            pivot: v(home.look),
            shadows: base.settings.shadows,
            reflections: base.settings.reflection_depth > 0,
            voxels: base.settings.voxel_colors,
            scale: 1.0,
            base,
            sent_format: None,
            view: 0,
            sample: 0,
            max_samples: max_samples.max(1),
            pick: None,
            playing: None,
        }
    }

    pub fn camera(&self) -> Camera {
        self.camera
    }

    pub fn max_samples(&self) -> u32 {
        self.max_samples
    }

    /// Whether a path is being played.
    pub fn playing(&self) -> bool {
        self.playing.is_some()
    }

    /// The model's scale: the home camera's eye→look distance (the page
    /// sets its flying speed from it).
    pub fn home_distance(&self) -> f32 {
        self.home_distance
    }

    pub fn choices(&self) -> Choices {
        let f = self.format();
        Choices {
            shadows: self.shadows,
            reflections: self.reflections,
            voxels: self.voxels,
            scale: self.scale,
            width: f.width,
            height: f.height,
            recording: false,
        }
    }

    /// Applies an input; whether the image changes (a pick alone does
    /// not: it rides on the next sample).
    pub fn apply(&mut self, input: ViewInput) -> bool {
        let before = (self.camera, self.format());
        if matches!(
            input,
            ViewInput::Fly { .. }
                | ViewInput::Orbit { .. }
                | ViewInput::Zoom { .. }
                | ViewInput::Home
        ) {
            self.playing = None;
        }
        match input {
            ViewInput::Fly {
                forward,
                right,
                up,
                yaw_deg,
                pitch_deg,
            } => self.fly(forward, right, up, yaw_deg, pitch_deg),
            ViewInput::Orbit { yaw_deg, pitch_deg } => self.orbit(yaw_deg, pitch_deg),
            ViewInput::Zoom { steps } => self.zoom(steps),
            ViewInput::Home => {
                self.camera = self.home;
                self.pivot = v(self.home.look);
            }
            ViewInput::Pick { x, y, pivot } => {
                if (0.0..=1.0).contains(&x) && (0.0..=1.0).contains(&y) {
                    self.pick = Some(PickRequest { x, y, pivot });
                }
            }
            ViewInput::Set {
                shadows,
                reflections,
                voxels,
                scale,
            } => {
                self.shadows = shadows.unwrap_or(self.shadows);
                self.reflections = reflections.unwrap_or(self.reflections);
                self.voxels = voxels.unwrap_or(self.voxels);
                if let Some(s) = scale.filter(|&s| self.offers(s)) {
                    self.scale = s;
                }
            }
            ViewInput::Play(cameras) => {
                let valid = |c: &Camera| dray_protocol::check_camera(c).is_ok();
                if let Some(&first) = cameras.first().filter(|_| cameras.iter().all(valid)) {
                    self.camera = first;
                    self.playing = Some(Playing { cameras, next: 0 });
                    // Each frame of a path is a view of its own, even
                    // where the path starts at the camera already shown.
                    self.view += 1;
                    self.sample = 0;
                    return true;
                }
            }
            ViewInput::Stop => self.playing = None,
            ViewInput::Record(_) => {}
        }
        let changed = before != (self.camera, self.format());
        if changed {
            self.view += 1;
            self.sample = 0;
        }
        changed
    }

    /// The sample the next frame would be, if one is due: none when the
    /// view is refined as far as it goes and no pick waits (a pick after
    /// the last sample asks for the last one again).
    pub fn due(&self) -> Option<u32> {
        if self.playing.is_some() {
            Some(0)
        } else if self.pick.is_some() {
            Some(self.sample.min(self.max_samples - 1))
        } else {
            (self.sample < self.max_samples).then_some(self.sample)
        }
    }

    /// The frame to ask for next (see [`Self::due`]).
    pub fn next_frame(&mut self) -> Option<NextFrame> {
        let path = self.next_of_path();
        let sample = self.due()?;
        let pick = self.pick.is_some();
        let mut format = self.format();
        if pick {
            format.settings.want_depth = true;
            format.settings.want_prim_ids = true;
        }
        let changed = self.sent_format.as_ref() != Some(&format);
        self.sent_format = Some(format.clone());
        self.sample = sample + 1;
        Some(NextFrame {
            camera: self.camera,
            sample,
            format: changed.then_some(format),
            view: self.view,
            pick,
            path,
        })
    }

    /// Playing: moves to the path's next camera (a view of its own) and
    /// ends the path after its last; the frame's place in the path.
    fn next_of_path(&mut self) -> Option<(u32, u32)> {
        let p = self.playing.as_mut()?;
        let at = p.next;
        let len = p.cameras.len();
        let camera = p.cameras[at];
        p.next += 1;
        if p.next >= len {
            self.playing = None;
        }
        if at > 0 {
            self.camera = camera;
            self.view += 1;
            self.sample = 0;
        }
        Some((at as u32, len as u32))
    }

    /// A frame asked for with `pick` was shown: answers the pick from its
    /// ids and depths (`width` × `height`, rows top down), and moves the
    /// pivot there if asked. `camera` is the frame's camera.
    pub fn picked(
        &mut self,
        camera: &Camera,
        width: u32,
        height: u32,
        ids: Option<&[u32]>,
        depth: Option<&[f32]>,
    ) -> Option<Picked> {
        let req = self.pick.take()?;
        let px = ((req.x * width as f32) as u32).min(width.saturating_sub(1));
        let py = ((req.y * height as f32) as u32).min(height.saturating_sub(1));
        let at = (py as usize) * width as usize + px as usize;
        let id = ids.and_then(|ids| ids.get(at)).copied();
        let t = depth.and_then(|d| d.get(at)).copied();
        let hit = id.is_some_and(|id| id != u32::MAX) && t.is_some_and(|t| t.is_finite());
        if !hit {
            return Some(Picked {
                x: req.x,
                y: req.y,
                triangle: None,
                distance: None,
                point: None,
            });
        }
        let t = t.unwrap_or_default();
        let point = v(camera.eye) + ray_direction(camera, width, height, px, py) * t;
        if req.pivot && point.is_finite() {
            self.pivot = point;
        }
        Some(Picked {
            x: req.x,
            y: req.y,
            triangle: id,
            distance: Some(t),
            point: Some(point.to_array()),
        })
    }

    /// Whether `scale` is one of [`SCALES`] and its frames are not too big
    /// (1× always is).
    fn offers(&self, scale: f32) -> bool {
        let pixels = |s: u32| (s as f32 * scale).round() as u64;
        SCALES.contains(&scale)
            && (scale <= 1.0
                || pixels(self.base.width) * pixels(self.base.height) <= MAX_SCALED_PIXELS)
    }

    /// The size and settings frames have now (without a pick's extras).
    fn format(&self) -> FrameFormat {
        let side = |s: u32| {
            ((s as f32 * self.scale).round() as u32).clamp(1, dray_protocol::MAX_IMAGE_SIDE)
        };
        let mut settings: RenderSettings = self.base.settings.clone();
        settings.shadows = self.shadows;
        settings.voxel_colors = self.voxels;
        settings.reflection_depth = match (self.reflections, self.base.settings.reflection_depth) {
            (false, _) => 0,
            (true, 0) => DEFAULT_REFLECTION_DEPTH,
            (true, d) => d,
        };
        FrameFormat {
            width: side(self.base.width),
            height: side(self.base.height),
            settings,
        }
    }

    fn fly(&mut self, forward: f32, right: f32, up: f32, yaw: f32, pitch: f32) {
        let Some((f, r, u)) = frame_of(&self.camera) else {
            return;
        };
        let limit = MAX_FLY_HOMES * self.home_distance;
        let step = f * bounded(forward, limit) + r * bounded(right, limit) + u * bounded(up, limit);
        let (eye, look) = (v(self.camera.eye) + step, v(self.camera.look) + step);
        let dir = turned(
            look - eye,
            u,
            r,
            bounded(yaw, MAX_TURN_DEG),
            bounded(pitch, MAX_TURN_DEG),
        );
        self.set_camera(eye, eye + dir);
    }

    fn orbit(&mut self, yaw: f32, pitch: f32) {
        let Some((_, r, u)) = frame_of(&self.camera) else {
            return;
        };
        let (yaw, pitch) = (bounded(yaw, MAX_TURN_DEG), bounded(pitch, MAX_TURN_DEG));
        let (eye, look) = (v(self.camera.eye), v(self.camera.look));
        // The eye goes round the pivot: yaw about up, then pitch about the
        // (turned) right vector, stopping short of the poles.
        let arm = eye - self.pivot;
        let yawed = glam::Quat::from_axis_angle(u, yaw.to_radians());
        let arm = yawed * arm;
        let r = yawed * r;
        // The view tilts down as the eye goes up: a look down of `pitch`.
        let pitch = -clamp_pitch(-arm, u, -pitch);
        let q = glam::Quat::from_axis_angle(r, -pitch.to_radians()) * yawed;
        let eye2 = self.pivot + glam::Quat::from_axis_angle(r, -pitch.to_radians()) * arm;
        let look2 = self.pivot + q * (look - self.pivot);
        self.set_camera(eye2, look2);
    }

    fn zoom(&mut self, steps: f32) {
        let steps = bounded(steps, MAX_ZOOM_STEPS);
        let (eye, look) = (v(self.camera.eye), v(self.camera.look));
        let arm = eye - self.pivot;
        let min = self.home_distance * 1e-4;
        let length = (arm.length() * ZOOM_PER_STEP.powf(steps)).max(min);
        let Some(dir) = arm.try_normalize() else {
            return;
        };
        let eye2 = self.pivot + dir * length;
        self.set_camera(eye2, look + (eye2 - eye));
    }

    /// Takes a moved camera if it is still a camera (finite, eye off look).
    fn set_camera(&mut self, eye: Vec3, look: Vec3) {
        let cam = Camera {
            eye: eye.to_array(),
            look: look.to_array(),
            ..self.camera
        };
        if dray_protocol::check_camera(&cam).is_ok() {
            self.camera = cam;
        }
    }
}

fn v(a: [f32; 3]) -> Vec3 {
    Vec3::from_array(a)
}

/// `x` if finite, clamped to ±`limit`; 0 otherwise.
fn bounded(x: f32, limit: f32) -> f32 {
    if x.is_finite() {
        x.clamp(-limit, limit)
    } else {
        0.0
    }
}

/// The camera's unit view, right and up vectors (`None`: degenerate).
fn frame_of(c: &Camera) -> Option<(Vec3, Vec3, Vec3)> {
    let f = (v(c.look) - v(c.eye)).try_normalize()?;
    let up = v(c.up).try_normalize()?;
    let r = f.cross(up).try_normalize()?;
    Some((f, r, up))
}

/// How far a pitch may go before the direction `d` reaches within
/// [`MIN_POLE_DEG`] of ±`up`.
fn clamp_pitch(d: Vec3, up: Vec3, pitch: f32) -> f32 {
    let now = d
        .normalize_or_zero()
        .dot(up)
        .clamp(-1.0, 1.0)
        .acos()
        .to_degrees();
    let target = (now - pitch).clamp(MIN_POLE_DEG, 180.0 - MIN_POLE_DEG);
    now - target
}

/// `d` turned by `yaw` about `up` and by `pitch` about the turned right
/// vector, short of the poles; its length is kept.
fn turned(d: Vec3, up: Vec3, right: Vec3, yaw: f32, pitch: f32) -> Vec3 {
    let yawed = glam::Quat::from_axis_angle(up, yaw.to_radians());
    let d = yawed * d;
    let pitch = clamp_pitch(d, up, pitch);
    glam::Quat::from_axis_angle(yawed * right, pitch.to_radians()) * d
}

/// The unit direction of the ray through the centre of pixel (x, y) of a
/// `width` × `height` image, y down (the kernel's convention,
/// `dray_trace::camera`).
fn ray_direction(c: &Camera, width: u32, height: u32, x: u32, y: u32) -> Vec3 {
    let Some((f, r, _)) = frame_of(c) else {
        return Vec3::ZERO;
    };
    let up = r.cross(f);
    let th = (c.fov_y_deg.to_radians() / 2.0).tan();
    let aspect = width as f32 / height as f32;
    let sx = 2.0 * (x as f32 + 0.5) / width as f32 - 1.0;
    let sy = 1.0 - 2.0 * (y as f32 + 0.5) / height as f32;
    (f + r * (th * aspect * sx) + up * (th * sy)).normalize_or_zero()
}

#[cfg(test)]
mod tests {
    use super::*;
    use dray_protocol::Reflective;

    fn home() -> Camera {
        Camera {
            eye: [0.0, 0.0, -10.0],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 45.0,
        }
    }

    fn base() -> FrameFormat {
        FrameFormat {
            width: 64,
            height: 48,
            settings: RenderSettings {
                shade: true,
                shadows: false,
                reflection_depth: 0,
                light_dir: [1.0, 1.0, 1.0],
                reflective: Reflective::All,
                reflectance: 0.5,
                voxel_colors: false,
                want_depth: false,
                want_prim_ids: false,
            },
        }
    }

    fn close(a: [f32; 3], b: [f32; 3]) -> bool {
        (v(a) - v(b)).length() < 1e-3
    }

    #[test]
    fn a_path_plays_one_frame_per_camera_then_rests_on_its_last() {
        let mut view = View::new(home(), base(), 2);
        view.next_frame();
        let at = |z: f32| Camera {
            eye: [0.0, 0.0, z],
            ..home()
        };
        let path: Arc<[Camera]> = vec![home(), at(-9.0), at(-8.0)].into();
        assert!(view.apply(ViewInput::Play(path.clone())));
        assert!(view.playing());
        let frames: Vec<NextFrame> = std::iter::from_fn(|| view.next_frame()).collect();
        let got: Vec<_> = frames
            .iter()
            .map(|f| (f.camera, f.sample, f.path))
            .collect();
        assert_eq!(
            got,
            [
                (home(), 0, Some((0, 3))),
                (at(-9.0), 0, Some((1, 3))),
                (at(-8.0), 0, Some((2, 3))),
                (at(-8.0), 1, None),
            ]
        );
        let views: Vec<u64> = frames.iter().map(|f| f.view).collect();
        assert!(views.windows(2).take(2).all(|w| w[0] < w[1]) && views[2] == views[3]);
        assert!(!view.playing());
        // A move ends a path early; a bad camera refuses the whole path.
        view.apply(ViewInput::Play(path));
        view.next_frame();
        view.apply(ViewInput::Fly {
            forward: 1.0,
            right: 0.0,
            up: 0.0,
            yaw_deg: 0.0,
            pitch_deg: 0.0,
        });
        assert!(!view.playing());
        let bad = Camera {
            look: home().eye,
            ..home()
        };
        assert!(!view.apply(ViewInput::Play(vec![home(), bad].into())));
        assert!(!view.playing());
        assert!(!view.apply(ViewInput::Play(Vec::new().into())));
    }

    #[test]
    fn a_still_view_is_refined_up_to_its_samples_then_rests() {
        let mut view = View::new(home(), base(), 3);
        let first = view.next_frame().unwrap();
        assert_eq!((first.sample, first.view, first.pick), (0, 0, false));
        assert_eq!(
            first.format,
            Some(base()),
            "the first frame says its format"
        );
        let second = view.next_frame().unwrap();
        assert_eq!((second.sample, second.format), (1, None));
        assert_eq!(view.next_frame().unwrap().sample, 2);
        assert_eq!(view.next_frame(), None, "refined: no more frames");
        assert!(view.apply(ViewInput::Fly {
            forward: 1.0,
            right: 0.0,
            up: 0.0,
            yaw_deg: 0.0,
            pitch_deg: 0.0
        }));
        let moved = view.next_frame().unwrap();
        assert_eq!((moved.sample, moved.view), (0, 1), "a move starts again");
        assert!(close(moved.camera.eye, [0.0, 0.0, -9.0]));
    }

    #[test]
    fn home_brings_the_first_camera_back() {
        let mut view = View::new(home(), base(), 4);
        view.apply(ViewInput::Fly {
            forward: 3.0,
            right: 2.0,
            up: 1.0,
            yaw_deg: 30.0,
            pitch_deg: 10.0,
        });
        view.apply(ViewInput::Orbit {
            yaw_deg: 45.0,
            pitch_deg: 20.0,
        });
        assert_ne!(view.camera(), home());
        assert!(view.apply(ViewInput::Home));
        assert_eq!(view.camera(), home());
        assert!(
            !view.apply(ViewInput::Home),
            "already home: nothing changes"
        );
    }

    #[test]
    fn orbit_keeps_the_distance_to_the_pivot_and_looks_at_it() {
        let mut view = View::new(home(), base(), 4);
        view.apply(ViewInput::Orbit {
            yaw_deg: 90.0,
            pitch_deg: 0.0,
        });
        let c = view.camera();
        assert!((v(c.eye).length() - 10.0).abs() < 1e-3, "{:?}", c.eye);
        assert!(close(c.look, [0.0, 0.0, 0.0]), "{:?}", c.look);
        // A quarter turn about +y takes the eye from -z to the side.
        assert!(
            c.eye[2].abs() < 1e-3 && c.eye[0].abs() > 9.99,
            "{:?}",
            c.eye
        );
        // Pitching over the top stops short of the pole.
        view.apply(ViewInput::Orbit {
            yaw_deg: 0.0,
            pitch_deg: 300.0,
        });
        let c = view.camera();
        let d = (v(c.look) - v(c.eye)).normalize();
        assert!(d.dot(Vec3::Y).abs() < 1.0 && d.dot(Vec3::Y).abs() > 0.99);
        assert!(dray_protocol::check_camera(&c).is_ok());
    }

    #[test]
    fn zoom_moves_towards_the_pivot_and_never_through_it() {
        let mut view = View::new(home(), base(), 4);
        view.apply(ViewInput::Zoom { steps: 1.0 });
        assert!(close(view.camera().eye, [0.0, 0.0, -10.0 * ZOOM_PER_STEP]));
        for _ in 0..1000 {
            view.apply(ViewInput::Zoom { steps: 20.0 });
        }
        let c = view.camera();
        assert!(c.eye[2] < 0.0 && dray_protocol::check_camera(&c).is_ok());
        view.apply(ViewInput::Zoom { steps: -1.0 });
        assert!(view.camera().eye[2] < c.eye[2]);
    }

    #[test]
    fn wild_inputs_are_bounded_and_never_break_the_camera() {
        let mut view = View::new(home(), base(), 4);
        for x in [f32::NAN, f32::INFINITY, -f32::INFINITY, 1e30, -1e30] {
            view.apply(ViewInput::Fly {
                forward: x,
                right: x,
                up: x,
                yaw_deg: x,
                pitch_deg: x,
            });
            view.apply(ViewInput::Orbit {
                yaw_deg: x,
                pitch_deg: x,
            });
            view.apply(ViewInput::Zoom { steps: x });
            view.apply(ViewInput::Pick {
                x,
                y: x,
                pivot: true,
            });
            view.apply(ViewInput::Set {
                shadows: None,
                reflections: None,
                voxels: None,
                scale: Some(x),
            });
            let c = view.camera();
            assert!(dray_protocol::check_camera(&c).is_ok(), "{x}: {c:?}");
            assert!(v(c.eye).length() < 1e6, "{x}: {c:?}");
        }
        assert_eq!(view.choices().scale, 1.0);
    }

    #[test]
    fn choices_change_the_format_and_start_again() {
        let mut view = View::new(home(), base(), 4);
        view.next_frame();
        view.next_frame();
        assert!(view.apply(ViewInput::Set {
            shadows: Some(true),
            reflections: Some(true),
            voxels: Some(true),
            scale: Some(2.0),
        }));
        let f = view.next_frame().unwrap();
        assert_eq!(f.sample, 0);
        let format = f.format.expect("a changed format is sent");
        assert_eq!((format.width, format.height), (128, 96));
        assert!(format.settings.shadows && format.settings.voxel_colors);
        assert_eq!(format.settings.reflection_depth, DEFAULT_REFLECTION_DEPTH);
        assert!(!view.apply(ViewInput::Set {
            shadows: Some(true),
            reflections: None,
            voxels: None,
            scale: Some(3.0),
        }));
        assert_eq!(view.choices().scale, 2.0, "only the offered scales");
    }

    #[test]
    fn a_pick_rides_on_the_next_frame_and_answers_from_its_pixels() {
        let mut view = View::new(home(), base(), 2);
        view.next_frame();
        view.next_frame();
        assert_eq!(view.next_frame(), None);
        assert!(!view.apply(ViewInput::Pick {
            x: 0.5,
            y: 0.5,
            pivot: true
        }));
        let f = view.next_frame().expect("a pick asks for a frame");
        assert!(f.pick && f.sample == 1);
        let fmt = f.format.unwrap();
        assert!(fmt.settings.want_prim_ids && fmt.settings.want_depth);
        let (w, h) = (64u32, 48u32);
        let mut ids = vec![u32::MAX; (w * h) as usize];
        let mut depth = vec![f32::INFINITY; (w * h) as usize];
        let at = (24 * w + 32) as usize;
        ids[at] = 77;
        depth[at] = 10.0;
        let p = view
            .picked(&f.camera, w, h, Some(&ids), Some(&depth))
            .unwrap();
        assert_eq!((p.triangle, p.distance), (Some(77), Some(10.0)));
        let point = p.point.unwrap();
        assert!(close(point, [point[0], point[1], 0.0]) && v(point).length() < 0.5);
        // The next frame drops the extras again, and the view rests.
        assert_eq!(view.next_frame(), None);
        view.apply(ViewInput::Pick {
            x: 0.0,
            y: 0.0,
            pivot: false,
        });
        let f = view.next_frame().unwrap();
        let missed = view
            .picked(&f.camera, w, h, Some(&ids), Some(&depth))
            .unwrap();
        assert_eq!(missed.triangle, None);
    }
}
