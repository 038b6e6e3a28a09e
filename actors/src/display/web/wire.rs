//! What travels on the viewer's WebSocket, and the checks on what arrives.
//!
//! Server → page:
//! - a **frame**: a binary message, `u32` (little-endian) header length,
//!   the header (JSON: `frame`, `width`, `height`, `samples`, `view`,
//!   `still`, `path` = `[index, length]` while a path plays (else null),
//!   `format` = `"jpeg"` or `"png"`, `metrics`), then the image;
//! - text messages (JSON with `type`): `status` (interactive, choices,
//!   home distance, max samples, `ended`), `picked`, `recorded` (`toml`:
//!   the flight as a camera-path file, `keyframes`, `frames`, `seconds`),
//!   `error`.
//!
//! Page → server: one input per text message, at most
//! [`super::MAX_INPUT_BYTES`] (a path to play: [`super::MAX_PATH_BYTES`]):
//! `{"fly":{"forward":f,"right":f,"up":f,"yaw":deg,"pitch":deg}}`,
//! `{"orbit":{"yaw":deg,"pitch":deg}}`, `{"zoom":{"steps":f}}`, `"home"`,
//! `{"pick":{"x":f,"y":f,"pivot":bool}}`,
//! `{"set":{"shadows":bool,"reflections":bool,"voxels":bool,"scale":f}}`
//! (any of `set`'s keys may be left out), `{"record":bool}`,
//! `{"play":{"name":"file.toml","toml":"…"}}` (a camera-path file, see
//! [`super::super::path`]), `"stop"`. Unknown keys are refused.

use super::super::path::CameraPath;
use super::super::view::{Picked, ViewInput};
use super::{PageEvent, ShownFrame, ViewerStatus, JPEG_QUALITY};
use serde::Deserialize;
use serde_json::json;
use std::path::Path;

/// An input as the page writes it.
#[derive(Deserialize)]
#[serde(rename_all = "lowercase", deny_unknown_fields)]
enum Input {
    Fly {
        #[serde(default)]
        forward: f32,
        #[serde(default)]
        right: f32,
        #[serde(default)]
        up: f32,
        #[serde(default)]
        yaw: f32,
        #[serde(default)]
        pitch: f32,
    },
    Orbit {
        #[serde(default)]
        yaw: f32,
        #[serde(default)]
        pitch: f32,
    },
    Zoom {
        steps: f32,
    },
    Home,
    Pick {
        x: f32,
        y: f32,
        #[serde(default)]
        pivot: bool,
    },
    Set {
        #[serde(default)]
        shadows: Option<bool>,
        #[serde(default)]
        reflections: Option<bool>,
        #[serde(default)]
        voxels: Option<bool>,
        #[serde(default)]
        scale: Option<f32>,
    },
    Record(bool),
    Play {
        name: String,
        toml: String,
    },
    Stop,
}

/// A page's input, or why it is refused. Numbers are bounded later by
/// [`super::super::view::View::apply`]; here only the shape is checked.
pub fn parse_input(text: &str) -> Result<ViewInput, String> {
    let too_long = |most: usize| format!("an input of {} bytes (at most {most})", text.len());
    if text.len() > super::MAX_PATH_BYTES {
        return Err(too_long(super::MAX_PATH_BYTES));
    }
    let input: Input =
        serde_json::from_str(text).map_err(|e| format!("not an input the viewer knows: {e}"))?;
    if text.len() > super::MAX_INPUT_BYTES && !matches!(input, Input::Play { .. }) {
        return Err(too_long(super::MAX_INPUT_BYTES));
    }
    Ok(match input {
        Input::Fly {
            forward,
            right,
            up,
            yaw,
            pitch,
        } => ViewInput::Fly {
            forward,
            right,
            up,
            yaw_deg: yaw,
            pitch_deg: pitch,
        },
        Input::Orbit { yaw, pitch } => ViewInput::Orbit {
            yaw_deg: yaw,
            pitch_deg: pitch,
        },
        Input::Zoom { steps } => ViewInput::Zoom { steps },
        Input::Home => ViewInput::Home,
        Input::Pick { x, y, pivot } => ViewInput::Pick { x, y, pivot },
        Input::Set {
            shadows,
            reflections,
            voxels,
            scale,
        } => ViewInput::Set {
            shadows,
            reflections,
            voxels,
            scale,
        },
        Input::Record(on) => ViewInput::Record(on),
        Input::Play { name, toml } => {
            let name: String = name.chars().filter(|c| !c.is_control()).take(200).collect();
            let path = CameraPath::parse(&toml, Path::new(&name)).map_err(|e| e.to_string())?;
            ViewInput::Play(path.cameras().into())
        }
        Input::Stop => ViewInput::Stop,
    })
}

/// The binary message of a frame: JPEG unless it is still (then PNG).
pub(super) fn frame_message(f: &ShownFrame) -> Vec<u8> {
    let (format, image) = if f.still {
        ("png", encode_png(f))
    } else {
        match encode_jpeg(f) {
            Some(jpeg) => ("jpeg", jpeg),
            None => ("png", encode_png(f)),
        }
    };
    let header = json!({
        "frame": f.frame,
        "width": f.width,
        "height": f.height,
        "samples": f.samples,
        "view": f.view,
        "still": f.still,
        "path": f.path.map(|(at, len)| [at, len]),
        "format": format,
        "metrics": f.metrics,
    })
    .to_string();
    let mut out = Vec::with_capacity(4 + header.len() + image.len());
    out.extend_from_slice(&(header.len() as u32).to_le_bytes());
    out.extend_from_slice(header.as_bytes());
    out.extend_from_slice(&image);
    out
}

fn encode_png(f: &ShownFrame) -> Vec<u8> {
    dray_trace::image::encode_png(f.width, f.height, &f.rgba).unwrap_or_default()
}

/// `None` if the encoder refuses (a side over 65535: never, sides are
/// bounded by the protocol).
pub fn encode_jpeg(f: &ShownFrame) -> Option<Vec<u8>> {
    let (w, h) = (u16::try_from(f.width).ok()?, u16::try_from(f.height).ok()?);
    let mut out = Vec::new();
    let enc = jpeg_encoder::Encoder::new(&mut out, JPEG_QUALITY);
    enc.encode(f.rgba.as_flattened(), w, h, jpeg_encoder::ColorType::Rgba)
        .ok()?;
    Some(out)
}

pub(super) fn status_message(s: &ViewerStatus) -> String {
    let choices = s.choices.map(|c| {
        json!({
            "shadows": c.shadows,
            "reflections": c.reflections,
            "voxels": c.voxels,
            "scale": c.scale,
            "width": c.width,
            "height": c.height,
            "recording": c.recording,
        })
    });
    json!({
        "type": "status",
        "interactive": s.interactive,
        "choices": choices,
        "home_distance": s.home_distance,
        "max_samples": s.max_samples,
        "ended": s.ended,
    })
    .to_string()
}

pub(super) fn event_message(e: &PageEvent) -> String {
    match e {
        PageEvent::Picked(p) => picked_message(p),
        PageEvent::Recorded(Ok(r)) => json!({
            "type": "recorded",
            "toml": r.path.to_toml(),
            "keyframes": r.path.keyframes.len(),
            "frames": r.path.frames,
            "seconds": r.seconds,
        })
        .to_string(),
        PageEvent::Recorded(Err(why)) => error_message(&format!("recording the flight: {why}")),
    }
}

fn picked_message(p: &Picked) -> String {
    json!({
        "type": "picked",
        "x": p.x,
        "y": p.y,
        "triangle": p.triangle,
        "distance": p.distance,
        "point": p.point,
    })
    .to_string()
}

pub(super) fn error_message(why: &str) -> String {
    json!({"type": "error", "message": why}).to_string()
}

/// A fresh token: 128 random bits, in hex.
pub fn new_token() -> std::io::Result<String> {
    let mut bytes = [0u8; 16];
    getrandom::fill(&mut bytes).map_err(std::io::Error::other)?;
    Ok(bytes.iter().map(|b| format!("{b:02x}")).collect())
}

/// A token a user may choose: 16 to 128 ASCII letters and digits.
pub fn valid_token(t: &str) -> bool {
    (16..=128).contains(&t.len()) && t.bytes().all(|b| b.is_ascii_alphanumeric())
}

/// Token comparison in time independent of where they differ.
pub fn same_token(given: &str, token: &str) -> bool {
    given.len() == token.len()
        && given
            .bytes()
            .zip(token.bytes())
            .fold(0u8, |acc, (a, b)| acc | (a ^ b))
            == 0
}

/// Whether a socket's `Origin` names the host it connected to. No Origin:
/// not a browser page (a script), allowed with the token.
pub fn same_origin(origin: Option<&str>, host: Option<&str>) -> bool {
    let Some(origin) = origin else {
        return true;
    };
    let Some(host) = host else {
        return false;
    };
    let rest = origin
        .strip_prefix("http://")
        .or_else(|| origin.strip_prefix("https://"));
    rest.is_some_and(|r| r.eq_ignore_ascii_case(host))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn inputs_parse_and_garbage_is_refused() {
        assert_eq!(parse_input("\"home\""), Ok(ViewInput::Home));
        assert_eq!(
            parse_input(r#"{"fly":{"forward":1.5,"yaw":2}}"#),
            Ok(ViewInput::Fly {
                forward: 1.5,
                right: 0.0,
                up: 0.0,
                yaw_deg: 2.0,
                pitch_deg: 0.0
            })
        );
        assert_eq!(
            parse_input(r#"{"set":{"scale":0.5}}"#),
            Ok(ViewInput::Set {
                shadows: None,
                reflections: None,
                voxels: None,
                scale: Some(0.5)
            })
        );
        assert_eq!(
            parse_input(r#"{"pick":{"x":0.25,"y":0.75,"pivot":true}}"#),
            Ok(ViewInput::Pick {
                x: 0.25,
                y: 0.75,
                pivot: true
            })
        );
        assert_eq!(
            parse_input(r#"{"record":true}"#),
            Ok(ViewInput::Record(true))
        );
        assert_eq!(parse_input("\"stop\""), Ok(ViewInput::Stop));
        let keyframes = (0..60)
            .map(|i| super::super::super::path::Keyframe {
                eye: [i as f32 * 0.1, 1.0, 5.0],
                look: [0.0, 0.0, 0.0],
                up: [0.0, 1.0, 0.0],
                fov_y_deg: 45.0,
            })
            .collect();
        let path = CameraPath::new(300, keyframes).unwrap();
        let play = json!({"play": {"name": "w.toml", "toml": path.to_toml()}}).to_string();
        assert!(
            play.len() > super::super::MAX_INPUT_BYTES,
            "a path may be longer"
        );
        assert_eq!(
            parse_input(&play),
            Ok(ViewInput::Play(path.cameras().into()))
        );
        let bad = json!({"play": {"name": "w.toml", "toml": "frames = 0"}}).to_string();
        let e = parse_input(&bad).unwrap_err();
        assert!(e.starts_with("w.toml: frames:"), "{e}");
        let long = format!("{{\"zoom\":{{\"steps\":1{}}}}}", " ".repeat(5000));
        for bad in [
            "",
            "{}",
            "home",
            "\"away\"",
            r#"{"fly":{"forward":"x"}}"#,
            r#"{"fly":{"sideways":1}}"#,
            r#"{"zoom":{}}"#,
            r#"{"pick":{"x":1}}"#,
            r#"{"home":1,"fly":{}}"#,
            "[1,2,3]",
            "\u{0}",
            long.as_str(),
        ] {
            assert!(parse_input(bad).is_err(), "{bad:?}");
        }
    }

    #[test]
    fn arbitrary_bytes_never_panic_the_parser() {
        use proptest::prelude::*;
        proptest!(|(s in ".{0,300}")| {
            let _ = parse_input(&s);
        });
    }

    #[test]
    fn tokens_and_origins() {
        let t = new_token().unwrap();
        assert!(valid_token(&t) && t.len() == 32);
        assert_ne!(t, new_token().unwrap());
        assert!(same_token(&t, &t));
        assert!(!same_token(&t[..31], &t));
        assert!(!same_token("0".repeat(32).as_str(), &t) || t == "0".repeat(32));
        assert!(!valid_token("short") && !valid_token(&"a".repeat(129)));
        assert!(!valid_token("with space and more letters"));
        assert!(same_origin(None, Some("127.0.0.1:7480")));
        assert!(same_origin(
            Some("http://127.0.0.1:7480"),
            Some("127.0.0.1:7480")
        ));
        assert!(same_origin(Some("http://Box:7480"), Some("box:7480")));
        assert!(!same_origin(
            Some("http://evil.example"),
            Some("127.0.0.1:7480")
        ));
        assert!(!same_origin(
            Some("http://127.0.0.1:7481"),
            Some("127.0.0.1:7480")
        ));
        assert!(!same_origin(Some("null"), Some("127.0.0.1:7480")));
        assert!(!same_origin(Some("http://127.0.0.1:7480"), None));
    }
}
