//! Camera moves a user sends through the web viewer (interactive mode).
//!
//! A [`Move`] comes from `GET /move?k=KEY` (see [`Move::parse`]) and is
//! applied to the current camera with [`Move::apply`]:
//!
//! | key | move |
//! |-----|------|
//! | `w` / `s` | forward / back along the view direction |
//! | `a` / `d` | strafe left / right |
//! | `r` / `f` | up / down along the up vector |
//! | `q` / `e` (`left` / `right`) | turn left / right about the up vector |
//! | `up` / `down` | look up / down |
//! | `look` with `dx`, `dy` | turn by a mouse drag of that many pixels |
//!
//! Translations move `eye` and `look` together by the step: a fixed
//! fraction ([`STEP_FRACTION`]) of the first camera's eye→look distance,
//! which is the scene scale the config gives (moves keep that distance,
//! so the step stays the same). Turns rotate `look` around `eye` by
//! [`TURN_DEG`] (a drag: [`DRAG_DEG_PER_PIXEL`] per pixel); looking up or
//! down stops short of the up vector.

use dray_protocol::Camera;

/// Step of a translation, as a fraction of the first camera's eye→look
/// distance.
pub const STEP_FRACTION: f32 = 0.05;
/// Angle of one turn key, degrees.
pub const TURN_DEG: f32 = 5.0;
/// Angle per pixel of a mouse drag, degrees.
pub const DRAG_DEG_PER_PIXEL: f32 = 0.25;
/// Largest drag a request may carry, pixels per axis.
pub const MAX_DRAG: f32 = 4000.0;
/// Closest the view direction gets to the up vector, degrees.
const MIN_POLE_DEG: f32 = 2.0;

/// One user camera move.
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum Move {
    /// Forward along the view direction (`w`).
    Forward,
    /// Back (`s`).
    Back,
    /// Strafe left (`a`).
    Left,
    /// Strafe right (`d`).
    Right,
    /// Up along the up vector (`r`).
    Up,
    /// Down (`f`).
    Down,
    /// Turn left about the up vector (`q`, `left`).
    TurnLeft,
    /// Turn right (`e`, `right`).
    TurnRight,
    /// Look up (`up`).
    LookUp,
    /// Look down (`down`).
    LookDown,
    /// A mouse drag, pixels (right and down positive).
    Drag {
        /// Horizontal pixels.
        dx: f32,
        /// Vertical pixels.
        dy: f32,
    },
}

impl Move {
    /// The move of a `/move` query string (`k=w`, `k=look&dx=3&dy=-2`);
    /// `None` for anything else.
    pub fn parse(query: &str) -> Option<Move> {
        let mut key = None;
        let (mut dx, mut dy) = (None, None);
        for pair in query.split('&').filter(|p| !p.is_empty()) {
            let (k, v) = pair.split_once('=')?;
            let slot = match k {
                "k" | "key" => &mut key,
                "dx" => &mut dx,
                "dy" => &mut dy,
                _ => return None,
            };
            if slot.replace(v).is_some() {
                return None;
            }
        }
        let num = |v: Option<&str>| -> Option<f32> {
            let x: f32 = v.unwrap_or("0").parse().ok()?;
            (x.is_finite() && x.abs() <= MAX_DRAG).then_some(x)
        };
        let key = key?.to_ascii_lowercase();
        if key != "look" && (dx.is_some() || dy.is_some()) {
            return None;
        }
        Some(match key.as_str() {
            "w" => Move::Forward,
            "s" => Move::Back,
            "a" => Move::Left,
            "d" => Move::Right,
            "r" => Move::Up,
            "f" => Move::Down,
            "q" | "left" | "arrowleft" => Move::TurnLeft,
            "e" | "right" | "arrowright" => Move::TurnRight,
            "up" | "arrowup" => Move::LookUp,
            "down" | "arrowdown" => Move::LookDown,
            "look" => Move::Drag {
                dx: num(dx)?,
                dy: num(dy)?,
            },
            _ => return None,
        })
    }

    /// `cam` after the move, translations by `step`. A degenerate camera
    /// (eye on look, view along up) is returned unchanged.
    pub fn apply(self, cam: &Camera, step: f32) -> Camera {
        let (eye, look) = (cam.eye, cam.look);
        let view = sub(look, eye);
        let (Some(f), Some(up)) = (unit(view), unit(cam.up)) else {
            return *cam;
        };
        let Some(right) = unit(cross(f, up)) else {
            return *cam;
        };
        let moved = |d: [f32; 3], s: f32| Camera {
            eye: add(eye, scale(d, s)),
            look: add(look, scale(d, s)),
            ..*cam
        };
        match self {
            Move::Forward => moved(f, step),
            Move::Back => moved(f, -step),
            Move::Right => moved(right, step),
            Move::Left => moved(right, -step),
            Move::Up => moved(up, step),
            Move::Down => moved(up, -step),
            Move::TurnLeft => turn(cam, view, up, right, TURN_DEG, 0.0),
            Move::TurnRight => turn(cam, view, up, right, -TURN_DEG, 0.0),
            Move::LookUp => turn(cam, view, up, right, 0.0, TURN_DEG),
            Move::LookDown => turn(cam, view, up, right, 0.0, -TURN_DEG),
            Move::Drag { dx, dy } => turn(
                cam,
                view,
                up,
                right,
                -dx * DRAG_DEG_PER_PIXEL,
                -dy * DRAG_DEG_PER_PIXEL,
            ),
        }
    }
}

/// The step of translations for a first camera: [`STEP_FRACTION`] of its
/// eye→look distance (1 when that is zero or not finite).
pub fn step_for(cam: &Camera) -> f32 {
    let d = len(sub(cam.look, cam.eye));
    if d.is_finite() && d > 0.0 {
        d * STEP_FRACTION
    } else {
        1.0
    }
}

/// Rotates the view about `up` by `yaw` degrees (positive: left), then
/// about the right vector by `pitch` degrees (positive: up), stopping
/// [`MIN_POLE_DEG`] short of the up vector.
fn turn(
    cam: &Camera,
    view: [f32; 3],
    up: [f32; 3],
    right: [f32; 3],
    yaw: f32,
    pitch: f32,
) -> Camera {
    let mut d = rotate(view, up, yaw.to_radians());
    if pitch != 0.0 {
        let r = rotate(right, up, yaw.to_radians());
        let n = len(d);
        // Angle between the view and up now, and the allowed range.
        let now = (dot(d, up) / n).clamp(-1.0, 1.0).acos().to_degrees();
        let target = (now - pitch).clamp(MIN_POLE_DEG, 180.0 - MIN_POLE_DEG);
        d = rotate(d, r, (now - target).to_radians());
    }
    let eye = cam.eye;
    Camera {
        look: add(eye, d),
        ..*cam
    }
}

/// `x` rotated by `a` radians about the unit axis `k` (Rodrigues).
fn rotate(x: [f32; 3], k: [f32; 3], a: f32) -> [f32; 3] {
    let (s, c) = a.sin_cos();
    add(
        add(scale(x, c), scale(cross(k, x), s)),
        scale(k, dot(k, x) * (1.0 - c)),
    )
}

fn add(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] + b[0], a[1] + b[1], a[2] + b[2]]
}
fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}
fn scale(a: [f32; 3], s: f32) -> [f32; 3] {
    [a[0] * s, a[1] * s, a[2] * s]
}
fn dot(a: [f32; 3], b: [f32; 3]) -> f32 {
    a[0] * b[0] + a[1] * b[1] + a[2] * b[2]
}
fn cross(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [
        a[1] * b[2] - a[2] * b[1],
        a[2] * b[0] - a[0] * b[2],
        a[0] * b[1] - a[1] * b[0],
    ]
}
fn len(a: [f32; 3]) -> f32 {
    dot(a, a).sqrt()
}
fn unit(a: [f32; 3]) -> Option<[f32; 3]> {
    let n = len(a);
    (n.is_finite() && n > 1e-12).then(|| scale(a, 1.0 / n))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn cam() -> Camera {
        Camera {
            eye: [0.0, 0.0, -10.0],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 45.0,
        }
    }

    fn close(a: [f32; 3], b: [f32; 3]) -> bool {
        len(sub(a, b)) < 1e-4
    }

    #[test]
    fn parses_keys_and_refuses_garbage() {
        assert_eq!(Move::parse("k=w"), Some(Move::Forward));
        assert_eq!(Move::parse("k=ArrowLeft"), Some(Move::TurnLeft));
        assert_eq!(
            Move::parse("k=look&dx=4&dy=-2"),
            Some(Move::Drag { dx: 4.0, dy: -2.0 })
        );
        for bad in [
            "",
            "k=",
            "k=z",
            "w",
            "k=w&k=s",
            "k=w&dx=1",
            "k=look&dx=nan",
            "k=look&dx=1e9",
            "x=w",
            "k=look&dx=",
        ] {
            assert_eq!(Move::parse(bad), None, "{bad:?}");
        }
    }

    #[test]
    fn moves_and_turns() {
        let c = cam();
        let s = step_for(&c);
        assert_eq!(s, 0.5);
        let f = Move::Forward.apply(&c, s);
        assert!(close(f.eye, [0.0, 0.0, -9.5]) && close(f.look, [0.0, 0.0, 0.5]));
        // Looking along +z with up +y, right is -x (w × up).
        let r = Move::Right.apply(&c, s);
        assert!(close(r.eye, [-0.5, 0.0, -10.0]), "{:?}", r.eye);
        let l = Move::TurnLeft.apply(&c, s);
        assert!(close(l.eye, c.eye));
        let d = sub(l.look, l.eye);
        assert!((len(d) - 10.0).abs() < 1e-4);
        // Turned towards +x (the left), by TURN_DEG.
        assert!(d[0] > 0.0 && (d[0] / 10.0 - TURN_DEG.to_radians().sin()).abs() < 1e-4);
        let back = Move::TurnRight.apply(&l, s);
        assert!(close(back.look, c.look));
        // Looking up stops short of the pole.
        let mut u = c;
        for _ in 0..100 {
            u = Move::LookUp.apply(&u, s);
        }
        let d = sub(u.look, u.eye);
        assert!(d[1] > 0.99 * len(d) && d[1] < len(d));
        assert_eq!(Move::Up.apply(&u, s).up, c.up);
    }
}
