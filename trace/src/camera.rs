//! The pinhole camera of docs/design.md's conventions, in f32 exactly as the
//! comparison tools compute it.

use dray_scene::{Aabb, Ray};
use glam::Vec3;

#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Camera {
    pub eye: Vec3,
    pub look: Vec3,
    pub up: Vec3,
    /// Vertical field of view in degrees.
    pub fov_degrees: f32,
    pub width: u32,
    pub height: u32,
}

impl Camera {
    /// The default view of a model: from the front, above and to the side,
    /// at 0.9 of the diagonal from the centre (the same as the Embree
    /// yardstick's default, so both render the same image).
    pub fn default_for(bounds: &Aabb, width: u32, height: u32) -> Camera {
        let c = (bounds.lo() + bounds.hi()) * 0.5;
        let diag = (bounds.hi() - bounds.lo()).length();
        Camera {
            eye: c + normalize(Vec3::new(0.3, 0.4, 1.0)) * 0.9 * diag,
            look: c,
            up: Vec3::Y,
            fov_degrees: 50.0,
            width,
            height,
        }
    }

    /// The per-image constants of the ray generation.
    pub fn basis(&self) -> CameraBasis {
        let w = normalize(self.look - self.eye);
        let u = normalize(w.cross(self.up));
        let v = u.cross(w);
        let th = (self.fov_degrees * std::f32::consts::PI / 360.0).tan();
        let aspect = self.width as f32 / self.height as f32;
        CameraBasis {
            eye: self.eye,
            forward: w,
            right: u * (th * aspect),
            up: v * th,
            width: self.width as f32,
            height: self.height as f32,
        }
    }
}

/// `a / |a|` with a division (not a reciprocal multiply), so rays are
/// bit-identical to the C yardstick's.
#[inline(always)]
pub fn normalize(a: Vec3) -> Vec3 {
    a / (a.x * a.x + a.y * a.y + a.z * a.z).sqrt()
}

/// Precomputed camera frame: `right` and `up` are scaled by the image
/// plane's half extents.
#[derive(Clone, Copy, Debug)]
pub struct CameraBasis {
    pub eye: Vec3,
    pub forward: Vec3,
    pub right: Vec3,
    pub up: Vec3,
    pub width: f32,
    pub height: f32,
}

impl CameraBasis {
    /// The unit direction through the centre of pixel (x, y), y down.
    #[inline(always)]
    pub fn direction(&self, x: u32, y: u32) -> Vec3 {
        let sx = 2.0 * (x as f32 + 0.5) / self.width - 1.0;
        let sy = 1.0 - 2.0 * (y as f32 + 0.5) / self.height;
        normalize(self.forward + self.right * sx + self.up * sy)
    }

    pub fn ray(&self, x: u32, y: u32) -> Ray {
        Ray {
            origin: self.eye,
            dir: self.direction(x, y),
        }
    }

    /// Where world point `p` falls in the image, in continuous pixel
    /// coordinates (pixel (x, y) covers [x, x+1) × [y, y+1)), if it is in
    /// front of the eye; the inverse of [`Self::direction`]. It may fall
    /// outside the image.
    pub fn project(&self, p: Vec3) -> Option<(f32, f32)> {
        let d = p - self.eye;
        let z = d.dot(self.forward);
        // Also refuses NaN (a degenerate camera).
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        // d = z (forward + sx right + sy up), the three orthogonal.
        let sx = d.dot(self.right) / (z * self.right.length_squared());
        let sy = d.dot(self.up) / (z * self.up.length_squared());
        let xy = (
            (sx + 1.0) * 0.5 * self.width,
            (1.0 - sy) * 0.5 * self.height,
        );
        (xy.0.is_finite() && xy.1.is_finite()).then_some(xy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_on_a_pixel_ray_projects_into_that_pixel() {
        let cam = Camera {
            eye: Vec3::new(1.0, 2.0, 3.0),
            look: Vec3::new(-4.0, 0.5, -7.0),
            up: Vec3::Y,
            fov_degrees: 50.0,
            width: 640,
            height: 480,
        };
        let b = cam.basis();
        for (x, y) in [(0, 0), (639, 479), (320, 240), (17, 400), (600, 3)] {
            for t in [0.1, 3.0, 250.0] {
                let (px, py) = b.project(b.eye + b.direction(x, y) * t).unwrap();
                assert_eq!((px.floor() as u32, py.floor() as u32), (x, y), "t {t}");
                assert!((px - x as f32 - 0.5).abs() < 1e-3 && (py - y as f32 - 0.5).abs() < 1e-3);
            }
        }
        assert_eq!(b.project(b.eye - b.forward), None, "behind the eye");
        assert_eq!(b.project(b.eye), None);
    }

    #[test]
    fn centre_pixel_looks_forward_and_corners_span_the_fov() {
        let cam = Camera {
            eye: Vec3::ZERO,
            look: Vec3::new(0.0, 0.0, -1.0),
            up: Vec3::Y,
            fov_degrees: 90.0,
            width: 3,
            height: 3,
        };
        let b = cam.basis();
        let d = b.direction(1, 1);
        assert!((d - Vec3::new(0.0, 0.0, -1.0)).length() < 1e-6);
        // Pixel (0, 0) is top left: x negative, y positive.
        let tl = b.direction(0, 0);
        assert!(tl.x < 0.0 && tl.y > 0.0);
        // The top row's centre is 2/3 of the way to the top edge at 45°.
        let top = b.direction(1, 0);
        assert!((top.y / -top.z - 2.0 / 3.0).abs() < 1e-6);
    }
}
