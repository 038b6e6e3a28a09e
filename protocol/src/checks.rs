//! Checks of values that reach the renderer from several places (a config
//! file, a command-line flag, a received message): each is written once
//! here, and every place calls it and puts its own key or flag before the
//! message.

use crate::{Camera, MAX_IMAGE_SIDE, MAX_REFLECTION_DEPTH, MAX_SAMPLES};
use std::fmt;

/// The value of a [`Camera`] that a check refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum CameraField {
    /// The eye position.
    Eye,
    /// The point looked at.
    Look,
    /// The up hint.
    Up,
    /// The vertical field of view.
    FovYDeg,
}

impl CameraField {
    /// The field's name, as the config and the wire spell it.
    pub fn name(self) -> &'static str {
        match self {
            CameraField::Eye => "eye",
            CameraField::Look => "look",
            CameraField::Up => "up",
            CameraField::FovYDeg => "fov_y_deg",
        }
    }
}

/// Why [`check_camera`] refused a camera: the field, and what is wrong with
/// it (a phrase that reads after the field's name or flag).
#[derive(Clone, Debug, PartialEq)]
pub struct CameraError {
    /// The refused field.
    pub field: CameraField,
    /// What is wrong, e.g. "is the zero vector".
    pub message: String,
}

impl fmt::Display for CameraError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}: {}", self.field.name(), self.message)
    }
}

impl std::error::Error for CameraError {}

/// Checks that a camera makes an image: finite coordinates, a field of view
/// in (0, 180) degrees, a look point apart from the eye, and an up hint that
/// is neither zero nor parallel to the view direction: what the kernel's
/// camera basis needs. The one camera check: the config, the command line,
/// received messages and the prefetcher's predicted cameras all call it.
pub fn check_camera(c: &Camera) -> Result<(), CameraError> {
    let err = |field, message: String| Err(CameraError { field, message });
    for (field, v) in [
        (CameraField::Eye, c.eye),
        (CameraField::Look, c.look),
        (CameraField::Up, c.up),
    ] {
        if !v.iter().all(|x| x.is_finite()) {
            return err(field, "holds a non-finite number".into());
        }
    }
    if !(c.fov_y_deg > 0.0 && c.fov_y_deg < 180.0) {
        return err(
            CameraField::FovYDeg,
            format!("{} is not in (0, 180) degrees", c.fov_y_deg),
        );
    }
    if c.eye == c.look {
        return err(CameraField::Look, "equals the eye position".into());
    }
    let w = std::array::from_fn::<f32, 3, _>(|k| c.look[k] - c.eye[k]);
    let u = c.up;
    let cross = [
        w[1] * u[2] - w[2] * u[1],
        w[2] * u[0] - w[0] * u[2],
        w[0] * u[1] - w[1] * u[0],
    ];
    let len2 = |v: [f32; 3]| v.iter().map(|x| x * x).sum::<f32>();
    if len2(u) == 0.0 {
        return err(CameraField::Up, "is the zero vector".into());
    }
    if len2(cross) <= 1e-12 * len2(w) * len2(u) {
        return err(
            CameraField::Up,
            "is parallel to the view direction (look - eye)".into(),
        );
    }
    Ok(())
}

/// Checks an image's width or height: 1 to [`MAX_IMAGE_SIDE`] pixels.
pub fn check_image_side(side: u32) -> Result<(), String> {
    if side == 0 || side > MAX_IMAGE_SIDE {
        return Err(format!("{side} is not in 1..={MAX_IMAGE_SIDE}"));
    }
    Ok(())
}

/// Checks a number of samples per pixel: 1 to [`MAX_SAMPLES`].
pub fn check_samples(samples: u32) -> Result<(), String> {
    if samples == 0 || samples > MAX_SAMPLES {
        return Err(format!("{samples} is not in 1..={MAX_SAMPLES}"));
    }
    Ok(())
}

/// Checks the share of the light a mirror reflects: within [0, 1].
pub fn check_reflectance(reflectance: f32) -> Result<(), String> {
    if !(0.0..=1.0).contains(&reflectance) {
        return Err(format!("{reflectance} is not in [0, 1]"));
    }
    Ok(())
}

/// Checks a number of mirror bounces: at most [`MAX_REFLECTION_DEPTH`].
pub fn check_reflection_depth(depth: u32) -> Result<(), String> {
    if depth > u32::from(MAX_REFLECTION_DEPTH) {
        return Err(format!("{depth} is over {MAX_REFLECTION_DEPTH}"));
    }
    Ok(())
}

/// Checks the direction towards the light: finite and not zero.
pub fn check_light_dir(dir: [f32; 3]) -> Result<(), String> {
    if !dir.iter().all(|x| x.is_finite()) || dir == [0.0; 3] {
        return Err(format!("{dir:?} is not a finite, non-zero direction"));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn camera() -> Camera {
        Camera {
            eye: [0.0, 0.0, -5.0],
            look: [0.0, 0.0, 0.0],
            up: [0.0, 1.0, 0.0],
            fov_y_deg: 50.0,
        }
    }

    fn refused(c: Camera) -> String {
        check_camera(&c).unwrap_err().to_string()
    }

    #[test]
    fn a_camera_is_refused_naming_the_field() {
        assert_eq!(check_camera(&camera()), Ok(()));
        let nan = Camera {
            up: [0.0, f32::NAN, 0.0],
            ..camera()
        };
        assert_eq!(refused(nan), "up: holds a non-finite number");
        let wide = Camera {
            fov_y_deg: 180.0,
            ..camera()
        };
        assert_eq!(refused(wide), "fov_y_deg: 180 is not in (0, 180) degrees");
        let nowhere = Camera {
            look: [0.0, 0.0, -5.0],
            ..camera()
        };
        assert_eq!(refused(nowhere), "look: equals the eye position");
        let zero = Camera {
            up: [0.0; 3],
            ..camera()
        };
        assert_eq!(refused(zero), "up: is the zero vector");
        let along = Camera {
            up: [0.0, 0.0, 2.0],
            ..camera()
        };
        assert_eq!(
            refused(along),
            "up: is parallel to the view direction (look - eye)"
        );
    }

    #[test]
    fn ranges_include_their_ends() {
        assert!(check_image_side(1).is_ok());
        assert!(check_image_side(MAX_IMAGE_SIDE).is_ok());
        assert_eq!(check_image_side(0).unwrap_err(), "0 is not in 1..=16384");
        assert!(check_image_side(MAX_IMAGE_SIDE + 1).is_err());
        assert!(check_reflectance(0.0).is_ok() && check_reflectance(1.0).is_ok());
        assert_eq!(check_reflectance(1.5).unwrap_err(), "1.5 is not in [0, 1]");
        assert!(check_reflectance(f32::NAN).is_err());
        assert!(check_reflection_depth(16).is_ok());
        assert_eq!(check_reflection_depth(17).unwrap_err(), "17 is over 16");
        assert!(check_light_dir([0.0, 1.0, 0.0]).is_ok());
        assert!(check_light_dir([0.0; 3]).is_err());
        assert!(check_light_dir([f32::INFINITY, 0.0, 0.0]).is_err());
        assert!(check_samples(1).is_ok() && check_samples(MAX_SAMPLES).is_ok());
        assert_eq!(check_samples(0).unwrap_err(), "0 is not in 1..=1024");
        assert!(check_samples(MAX_SAMPLES + 1).is_err());
    }
}
