//! Recording a flight at the viewer as a camera path (the file `dray
//! cluster` and the viewer play back).
//!
//! The view's camera is sampled on a wall-clock grid: one keyframe every
//! [`KEY_INTERVAL`], a camera that stood still repeated, and a last
//! keyframe where the recording stops. Path files space keyframes evenly
//! in frames, so the path gets [`FRAMES_PER_KEY`] frames per keyframe:
//! played at [`PLAYBACK_FPS`] it takes as long as the flight did.

use super::path::{CameraPath, Keyframe, MAX_FRAMES};
use dray_protocol::Camera;
use std::time::Duration;
use tokio::time::Instant;

/// Time between keyframes.
pub const KEY_INTERVAL: Duration = Duration::from_millis(200);
/// Frames along the path per keyframe.
pub const FRAMES_PER_KEY: u32 = 6;
/// The frame rate at which a recorded path lasts as long as the flight.
pub const PLAYBACK_FPS: u32 = 30;
/// Most keyframes a recording keeps (the path's frames stay within
/// [`MAX_FRAMES`]); a recording that reaches it stops.
pub const MAX_KEYFRAMES: usize = ((MAX_FRAMES - 1) / FRAMES_PER_KEY) as usize + 1;

const _: () = assert!(KEY_INTERVAL.as_millis() as u32 * PLAYBACK_FPS == FRAMES_PER_KEY * 1000);

/// A recording in progress.
#[derive(Debug)]
pub struct Recorder {
    started: Instant,
    /// When the next keyframe is due.
    next_key: Instant,
    keyframes: Vec<Keyframe>,
}

/// A finished recording.
#[derive(Clone, Debug, PartialEq)]
pub struct Recording {
    pub path: CameraPath,
    /// How long the flight took.
    pub seconds: f32,
}

impl Recorder {
    /// Starts at `now` with the view's camera as the first keyframe.
    pub fn start(now: Instant, camera: Camera) -> Recorder {
        Recorder {
            started: now,
            next_key: now + KEY_INTERVAL,
            keyframes: vec![keyframe(camera)],
        }
    }

    /// The camera was `camera` from the last call until `now`: a keyframe
    /// for every grid point passed (the camera is about to change).
    pub fn held(&mut self, now: Instant, camera: Camera) {
        // One place is left for the keyframe where the recording stops.
        while self.next_key <= now && self.keyframes.len() < MAX_KEYFRAMES - 1 {
            self.keyframes.push(keyframe(camera));
            self.next_key += KEY_INTERVAL;
        }
    }

    /// Whether it holds as many keyframes as a recording may.
    pub fn full(&self) -> bool {
        self.keyframes.len() >= MAX_KEYFRAMES - 1
    }

    /// Stops at `now` with the view's camera, held since the last call.
    pub fn stop(mut self, now: Instant, camera: Camera) -> Result<Recording, String> {
        self.held(now, camera);
        self.keyframes.push(keyframe(camera));
        let frames = (self.keyframes.len() as u32 - 1) * FRAMES_PER_KEY + 1;
        let seconds = now.saturating_duration_since(self.started).as_secs_f32();
        let path = CameraPath::new(frames, self.keyframes)
            .map_err(|(key, why)| format!("the recorded path: {key}: {why}"))?;
        Ok(Recording { path, seconds })
    }
}

fn keyframe(c: Camera) -> Keyframe {
    Keyframe {
        eye: c.eye,
        look: c.look,
        up: c.up,
        fov_y_deg: c.fov_y_deg,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::Path;

    fn cam(z: f32) -> Camera {
        Camera {
            eye: [0.0, 1.0, z],
            look: [0.0, 1.0, z - 1.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        }
    }

    #[test]
    fn a_flight_becomes_a_path_in_its_own_time() {
        let t0 = Instant::now();
        let ms = |m: u64| t0 + Duration::from_millis(m);
        let mut r = Recorder::start(t0, cam(0.0));
        // Still until 450 ms: keyframes at 200 and 400 repeat the start.
        r.held(ms(450), cam(0.0));
        // Then at z = -1 until 650: the keyframe at 600 has it.
        r.held(ms(650), cam(-1.0));
        let rec = r.stop(ms(700), cam(-2.0)).unwrap();
        let zs: Vec<f32> = rec.path.keyframes.iter().map(|k| k.eye[2]).collect();
        assert_eq!(zs, [0.0, 0.0, 0.0, -1.0, -2.0]);
        assert_eq!(rec.path.frames, 4 * FRAMES_PER_KEY + 1);
        assert!((rec.seconds - 0.7).abs() < 1e-6);
        // The file reads back as the same path, and ends on the last camera.
        let again = CameraPath::parse(&rec.path.to_toml(), Path::new("rec.toml")).unwrap();
        assert_eq!(again, rec.path);
        assert_eq!(again.cameras().last(), Some(&cam(-2.0)));
    }

    #[test]
    fn a_short_recording_has_two_keyframes_and_a_long_one_stops_at_the_limit() {
        let t0 = Instant::now();
        let r = Recorder::start(t0, cam(0.0));
        let rec = r.stop(t0 + Duration::from_millis(5), cam(0.0)).unwrap();
        assert_eq!(rec.path.keyframes.len(), 2);
        let mut r = Recorder::start(t0, cam(0.0));
        r.held(t0 + Duration::from_secs(24 * 3600), cam(0.0));
        assert!(r.full());
        let rec = r
            .stop(t0 + Duration::from_secs(24 * 3600), cam(1.0))
            .unwrap();
        assert_eq!(rec.path.keyframes.len(), MAX_KEYFRAMES);
        assert!(rec.path.frames <= MAX_FRAMES);
    }
}
