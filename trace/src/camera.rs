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

    /// The per-image constants of the ray generation: sample 0, every
    /// ray through its pixel's centre.
    pub fn basis(&self) -> CameraBasis {
        self.sample_basis(0)
    }

    /// The per-image constants of sample `sample`'s rays: every ray of the
    /// image moved by the same [`sample_offset`], so packets stay as
    /// coherent as at the centres.
    pub fn sample_basis(&self, sample: u32) -> CameraBasis {
        let (jx, jy) = sample_offset(sample);
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
            centre_x: 0.5 + jx,
            centre_y: 0.5 + jy,
        }
    }
}

/// The sub-pixel offset of sample `sample`'s rays from the pixel centres,
/// (x right, y down), each in (-0.5, 0.5): (0, 0) for sample 0, then the
/// R2 sequence (Roberts' additive recurrence on the plastic number, a
/// low-discrepancy sequence in two dimensions), so that the first few
/// samples already spread over the pixel and every further one fills its
/// largest gaps. Computed in 32-bit fixed point and converted exactly, so
/// every machine and every path of the kernel gets the same floats.
pub fn sample_offset(sample: u32) -> (f32, f32) {
    // 2^32 / φ₂ and 2^32 / φ₂², φ₂ the plastic number (x³ = x + 1).
    const A1: u32 = 0xC13F_A9A9;
    const A2: u32 = 0x91E1_0DA5;
    // The fraction of sample × a, read as signed, is its offset from the
    // centre; 24 bits of it convert to f32 exactly, and the one value
    // that would be -0.5 is moved inside.
    let axis = |a: u32| {
        let q = (sample.wrapping_mul(a) as i32 >> 8).max(-(1 << 23) + 1);
        q as f32 * (1.0 / (1u32 << 24) as f32)
    };
    (axis(A1), axis(A2))
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
    /// Where within its pixel each ray passes, from the pixel's left and
    /// top edges: 0.5 at the centre (sample 0), else 0.5 plus the sample's
    /// [`sample_offset`].
    pub centre_x: f32,
    pub centre_y: f32,
}

impl CameraBasis {
    /// The unit direction of pixel (x, y)'s ray, y down: through its
    /// centre at sample 0, else moved by the sample's offset.
    #[inline(always)]
    pub fn direction(&self, x: u32, y: u32) -> Vec3 {
        let sx = 2.0 * (x as f32 + self.centre_x) / self.width - 1.0;
        let sy = 1.0 - 2.0 * (y as f32 + self.centre_y) / self.height;
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
    fn sample_zero_is_the_centre_and_the_others_spread_over_the_pixel() {
        assert_eq!(sample_offset(0), (0.0, 0.0));
        let cam = Camera {
            eye: Vec3::new(1.0, 2.0, 3.0),
            look: Vec3::new(-4.0, 0.5, -7.0),
            up: Vec3::Y,
            fov_degrees: 50.0,
            width: 64,
            height: 48,
        };
        let (b, b0) = (cam.basis(), cam.sample_basis(0));
        for (x, y) in [(0, 0), (63, 47), (17, 30)] {
            assert_eq!(b.direction(x, y), b0.direction(x, y));
        }
        let offsets: Vec<(f32, f32)> = (0..1024).map(sample_offset).collect();
        for (k, &(x, y)) in offsets.iter().enumerate() {
            assert!(x > -0.5 && x < 0.5 && y > -0.5 && y < 0.5, "sample {k}");
        }
        // The fraction that is exactly -0.5 is moved inside.
        assert_eq!(sample_offset(1 << 31).0, -0.5 + 1.0 / (1u32 << 24) as f32);
        // Samples 0..4 fall one in each quadrant of the pixel.
        let quadrant = |(x, y): (f32, f32)| (x >= 0.0, y >= 0.0);
        let mut q: Vec<_> = offsets[..4].iter().map(|&o| quadrant(o)).collect();
        q.sort();
        q.dedup();
        assert_eq!(q.len(), 4);
        // Evenly spread: the mean offset of 1024 samples is near the centre.
        let n = offsets.len() as f32;
        let mean = offsets
            .iter()
            .fold((0.0, 0.0), |m, o| (m.0 + o.0, m.1 + o.1));
        assert!(
            (mean.0 / n).abs() < 0.01 && (mean.1 / n).abs() < 0.01,
            "{mean:?}"
        );
        // A sample's rays pass through their own pixels, moved by its offset.
        for k in [1, 2, 3, 1023] {
            let (jx, jy) = sample_offset(k);
            let s = cam.sample_basis(k);
            let (px, py) = s.project(s.eye + s.direction(17, 30) * 10.0).unwrap();
            assert_eq!((px.floor(), py.floor()), (17.0, 30.0), "sample {k}");
            assert!((px - 17.5 - jx).abs() < 1e-3 && (py - 30.5 - jy).abs() < 1e-3);
        }
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
