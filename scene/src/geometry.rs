//! Geometric primitives shared by preprocessing, verification and the
//! reference ray queries: boxes, rays, the watertight ray-triangle test and
//! triangle clipping against boxes.

use glam::Vec3;
use serde::{Deserialize, Serialize};

/// An axis-aligned box. An empty box has `min > max` on every axis.
#[derive(Clone, Copy, Debug, PartialEq, Serialize, Deserialize)]
pub struct Aabb {
    pub min: [f32; 3],
    pub max: [f32; 3],
}

impl Default for Aabb {
    fn default() -> Self {
        Self::EMPTY
    }
}

impl Aabb {
    pub const EMPTY: Aabb = Aabb {
        min: [f32::INFINITY; 3],
        max: [f32::NEG_INFINITY; 3],
    };

    pub fn new(min: Vec3, max: Vec3) -> Aabb {
        Aabb {
            min: min.to_array(),
            max: max.to_array(),
        }
    }

    pub fn from_points(points: &[Vec3]) -> Aabb {
        let mut b = Aabb::EMPTY;
        for &p in points {
            b.grow(p);
        }
        b
    }

    #[inline]
    pub fn lo(&self) -> Vec3 {
        Vec3::from_array(self.min)
    }

    #[inline]
    pub fn hi(&self) -> Vec3 {
        Vec3::from_array(self.max)
    }

    #[inline]
    pub fn is_empty(&self) -> bool {
        (0..3).any(|a| self.min[a] > self.max[a])
    }

    #[inline]
    pub fn grow(&mut self, p: Vec3) {
        *self = Aabb::new(self.lo().min(p), self.hi().max(p));
    }

    #[inline]
    pub fn union(&self, other: &Aabb) -> Aabb {
        Aabb::new(self.lo().min(other.lo()), self.hi().max(other.hi()))
    }

    pub fn intersection(&self, other: &Aabb) -> Aabb {
        Aabb::new(self.lo().max(other.lo()), self.hi().min(other.hi()))
    }

    pub fn extent(&self) -> Vec3 {
        if self.is_empty() {
            Vec3::ZERO
        } else {
            self.hi() - self.lo()
        }
    }

    #[inline]
    pub fn center(&self) -> Vec3 {
        (self.lo() + self.hi()) * 0.5
    }

    pub fn diagonal(&self) -> f32 {
        self.extent().length()
    }

    /// Surface area (0 for an empty box).
    #[inline]
    pub fn area(&self) -> f32 {
        let e = self.extent();
        2.0 * (e.x * e.y + e.y * e.z + e.z * e.x)
    }

    pub fn contains_box(&self, other: &Aabb) -> bool {
        (0..3).all(|a| self.min[a] <= other.min[a] && other.max[a] <= self.max[a])
    }

    /// The box grown by `eps` on every side.
    pub fn expanded(&self, eps: f32) -> Aabb {
        Aabb::new(self.lo() - Vec3::splat(eps), self.hi() + Vec3::splat(eps))
    }

    /// Splits the box at `pos` on `axis` into (below, above).
    pub fn split(&self, axis: usize, pos: f32) -> (Aabb, Aabb) {
        let mut left = *self;
        let mut right = *self;
        left.max[axis] = pos;
        right.min[axis] = pos;
        (left, right)
    }

    /// The parametric interval `[t0, t1]` in which `ray` is inside the box,
    /// clamped to `[tmin, tmax]`, or `None` when it misses.
    pub fn ray_interval(&self, ray: &Ray, tmin: f32, tmax: f32) -> Option<(f32, f32)> {
        let mut t0 = tmin;
        let mut t1 = tmax;
        for a in 0..3 {
            let inv = 1.0 / ray.dir[a];
            let mut near = (self.min[a] - ray.origin[a]) * inv;
            let mut far = (self.max[a] - ray.origin[a]) * inv;
            if near > far {
                std::mem::swap(&mut near, &mut far);
            }
            // NaN (0 * inf when the origin lies on a slab and the ray is
            // parallel to it) must not shrink the interval: max/min ignore NaN.
            t0 = t0.max(near);
            t1 = t1.min(far * (1.0 + 2.0 * f32::EPSILON * 2.0));
            if t0 > t1 {
                return None;
            }
        }
        Some((t0, t1))
    }
}

/// A ray `origin + t * dir`.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Ray {
    pub origin: Vec3,
    pub dir: Vec3,
}

/// The nearest hit found so far: the distance along the ray and the ORIGINAL
/// triangle id. Ties in `t` are broken towards the smaller id, so every
/// traversal order gives the same answer as brute force.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Hit {
    pub t: f32,
    pub id: u32,
}

impl Hit {
    /// Whether a candidate at (`t`, `id`) is better than this hit.
    pub fn is_beaten_by(&self, t: f32, id: u32) -> bool {
        t < self.t || (t == self.t && id < self.id)
    }
}

/// Keeps the better of `best` and the candidate.
pub fn closer(best: Option<Hit>, t: f32, id: u32) -> Option<Hit> {
    match best {
        Some(h) if !h.is_beaten_by(t, id) => Some(h),
        _ => Some(Hit { t, id }),
    }
}

/// Watertight ray-triangle intersection (Woop, Benthin and Wald, JCGT 2013):
/// rays through shared edges and vertices hit exactly one of the triangles
/// that share them (never none), whatever the winding. Both sides are hit.
/// Returns the distance `t` when it lies in `(tmin, tmax)`.
pub fn intersect_triangle(ray: &Ray, p: &[Vec3; 3], tmin: f32, tmax: f32) -> Option<f32> {
    let d = ray.dir;
    // Axis of the largest direction component becomes z.
    let ad = d.abs();
    let kz = if ad.x >= ad.y && ad.x >= ad.z {
        0
    } else if ad.y >= ad.z {
        1
    } else {
        2
    };
    let mut kx = (kz + 1) % 3;
    let mut ky = (kx + 1) % 3;
    if d[kz] < 0.0 {
        std::mem::swap(&mut kx, &mut ky);
    }
    let sz = 1.0 / d[kz];
    let sx = d[kx] * sz;
    let sy = d[ky] * sz;

    let a = p[0] - ray.origin;
    let b = p[1] - ray.origin;
    let c = p[2] - ray.origin;
    let ax = a[kx] - sx * a[kz];
    let ay = a[ky] - sy * a[kz];
    let bx = b[kx] - sx * b[kz];
    let by = b[ky] - sy * b[kz];
    let cx = c[kx] - sx * c[kz];
    let cy = c[ky] - sy * c[kz];

    let mut u = cx * by - cy * bx;
    let mut v = ax * cy - ay * cx;
    let mut w = bx * ay - by * ax;
    if u == 0.0 || v == 0.0 || w == 0.0 {
        // Fall back to double precision on edges so the test stays exact.
        let (ax, ay, bx, by, cx, cy) = (
            ax as f64, ay as f64, bx as f64, by as f64, cx as f64, cy as f64,
        );
        u = (cx * by - cy * bx) as f32;
        v = (ax * cy - ay * cx) as f32;
        w = (bx * ay - by * ax) as f32;
    }
    if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
        return None;
    }
    let det = u + v + w;
    if det == 0.0 {
        return None;
    }
    let az = sz * a[kz];
    let bz = sz * b[kz];
    let cz = sz * c[kz];
    let t_scaled = u * az + v * bz + w * cz;
    let t = t_scaled / det;
    if t > tmin && t < tmax && t.is_finite() {
        Some(t)
    } else {
        None
    }
}

/// The bounds of the part of triangle `p` that lies inside `bounds`
/// (Sutherland–Hodgman clipping against the six planes), or `None` when the
/// triangle does not reach into the box. Used to decide exactly which BSP
/// cells a triangle touches, so replicated triangles go only where they are.
pub fn clipped_bounds(p: &[Vec3; 3], bounds: &Aabb) -> Option<Aabb> {
    let tb = Aabb::from_points(p);
    if bounds.contains_box(&tb) {
        return Some(tb);
    }
    if tb.intersection(bounds).is_empty() {
        return None;
    }
    // A triangle clipped by 6 planes has at most 9 corners.
    let mut poly = [Vec3::ZERO; 12];
    let mut scratch = [Vec3::ZERO; 12];
    poly[..3].copy_from_slice(p);
    let mut n = 3;
    for axis in 0..3 {
        for (plane, keep_above) in [(bounds.min[axis], true), (bounds.max[axis], false)] {
            let inside = |q: Vec3| {
                if keep_above {
                    q[axis] >= plane
                } else {
                    q[axis] <= plane
                }
            };
            let mut m = 0;
            for i in 0..n {
                let cur = poly[i];
                let next = poly[(i + 1) % n];
                let (ci, ni) = (inside(cur), inside(next));
                if ci {
                    scratch[m] = cur;
                    m += 1;
                }
                if ci != ni {
                    let s = (plane - cur[axis]) / (next[axis] - cur[axis]);
                    let mut q = cur + (next - cur) * s;
                    q[axis] = plane; // exactly on the plane despite rounding
                    scratch[m] = q;
                    m += 1;
                }
            }
            n = m;
            if n == 0 {
                return None;
            }
            poly[..n].copy_from_slice(&scratch[..n]);
        }
    }
    let mut out = Aabb::from_points(&poly[..n]);
    // Rounding in the interpolation may push a corner a hair outside.
    out = out.intersection(bounds);
    if out.is_empty() {
        None
    } else {
        Some(out)
    }
}

/// Whether triangle `p` touches `bounds` grown by `eps` (separating axis test
/// in double precision). This is the independent check that `dray verify` and
/// the tests use against preprocessing, which decides with clipping.
pub fn triangle_touches_box(p: &[Vec3; 3], bounds: &Aabb, eps: f32) -> bool {
    let b = bounds.expanded(eps);
    let c = (b.lo().as_dvec3() + b.hi().as_dvec3()) * 0.5;
    let h = (b.hi().as_dvec3() - b.lo().as_dvec3()) * 0.5;
    let v = [
        p[0].as_dvec3() - c,
        p[1].as_dvec3() - c,
        p[2].as_dvec3() - c,
    ];
    // Box face normals.
    for a in 0..3 {
        let lo = v[0][a].min(v[1][a]).min(v[2][a]);
        let hi = v[0][a].max(v[1][a]).max(v[2][a]);
        if lo > h[a] || hi < -h[a] {
            return false;
        }
    }
    let e = [v[1] - v[0], v[2] - v[1], v[0] - v[2]];
    let mut axes: Vec<glam::DVec3> = Vec::with_capacity(10);
    axes.push(e[0].cross(e[1]));
    for edge in e {
        for unit in [glam::DVec3::X, glam::DVec3::Y, glam::DVec3::Z] {
            axes.push(unit.cross(edge));
        }
    }
    for axis in axes {
        if axis.length_squared() < 1e-30 {
            continue;
        }
        let p0 = v[0].dot(axis);
        let p1 = v[1].dot(axis);
        let p2 = v[2].dot(axis);
        let r = h.x * axis.x.abs() + h.y * axis.y.abs() + h.z * axis.z.abs();
        if p0.min(p1).min(p2) > r || p0.max(p1).max(p2) < -r {
            return false;
        }
    }
    true
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tri() -> [Vec3; 3] {
        [
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ]
    }

    #[test]
    fn ray_hits_triangle_from_both_sides() {
        let front = Ray {
            origin: Vec3::new(0.2, 0.2, 1.0),
            dir: Vec3::new(0.0, 0.0, -1.0),
        };
        let back = Ray {
            origin: Vec3::new(0.2, 0.2, -2.0),
            dir: Vec3::new(0.0, 0.0, 1.0),
        };
        assert_eq!(
            intersect_triangle(&front, &tri(), 0.0, f32::INFINITY),
            Some(1.0)
        );
        assert_eq!(
            intersect_triangle(&back, &tri(), 0.0, f32::INFINITY),
            Some(2.0)
        );
        assert_eq!(intersect_triangle(&back, &tri(), 0.0, 1.5), None);
    }

    #[test]
    fn shared_edge_is_hit_by_exactly_one_side() {
        // Two triangles sharing the diagonal of the unit square.
        let a = [
            Vec3::ZERO,
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
        ];
        let b = [
            Vec3::ZERO,
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(0.0, 1.0, 0.0),
        ];
        for i in 0..100 {
            let s = i as f32 / 100.0;
            let ray = Ray {
                origin: Vec3::new(s, s, 1.0),
                dir: Vec3::new(0.0, 0.0, -1.0),
            };
            let ha = intersect_triangle(&ray, &a, 0.0, f32::INFINITY).is_some();
            let hb = intersect_triangle(&ray, &b, 0.0, f32::INFINITY).is_some();
            assert!(ha || hb, "leak at {s}");
        }
    }

    #[test]
    fn clipping_shrinks_to_the_box() {
        let big = [
            Vec3::new(-10.0, -10.0, 0.5),
            Vec3::new(10.0, -10.0, 0.5),
            Vec3::new(0.0, 10.0, 0.5),
        ];
        let cell = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let c = clipped_bounds(&big, &cell).unwrap();
        assert_eq!(c.min, [0.0, 0.0, 0.5]);
        assert_eq!(c.max, [1.0, 1.0, 0.5]);
        let far = Aabb::new(Vec3::splat(20.0), Vec3::splat(21.0));
        assert!(clipped_bounds(&big, &far).is_none());
        // A triangle whose bounding box overlaps the cell but which does not.
        let diag = [
            Vec3::new(2.0, 0.5, 0.5),
            Vec3::new(0.5, 2.0, 0.5),
            Vec3::new(2.0, 2.0, 0.5),
        ];
        assert!(clipped_bounds(&diag, &cell).is_none());
        assert!(!triangle_touches_box(&diag, &cell, 0.0));
        assert!(triangle_touches_box(&big, &cell, 0.0));
    }

    #[test]
    fn ray_box_interval() {
        let b = Aabb::new(Vec3::ZERO, Vec3::ONE);
        let r = Ray {
            origin: Vec3::new(-1.0, 0.5, 0.5),
            dir: Vec3::X,
        };
        let (t0, t1) = b.ray_interval(&r, 0.0, f32::INFINITY).unwrap();
        assert_eq!(t0, 1.0);
        assert!((t1 - 2.0).abs() < 1e-5);
        let miss = Ray {
            origin: Vec3::new(-1.0, 2.0, 0.5),
            dir: Vec3::X,
        };
        assert!(b.ray_interval(&miss, 0.0, f32::INFINITY).is_none());
    }
}
