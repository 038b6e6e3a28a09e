//! One object's mesh, built in a reusable scratch buffer and then handed to
//! the [`Sink`](super::sink::Sink) as a whole (or not at all).
//!
//! Curved surfaces (cylinders, tori, domes) share their vertices between
//! neighbouring faces and carry analytic radial normals, so they shade
//! smoothly; flat faces (boxes, caps, plates) get their own vertices with the
//! face normal, so hard edges stay hard.

use glam::{Quat, Vec3};
use std::f32::consts::{FRAC_PI_2, TAU};

#[derive(Clone, Copy, Debug)]
pub(crate) struct Vertex {
    pub p: Vec3,
    pub n: Vec3,
    pub c: [u8; 3],
}

/// The scratch mesh of one object. Its buffers are reused from object to
/// object, so they never grow beyond the largest single object.
#[derive(Default)]
pub(crate) struct Part {
    pub verts: Vec<Vertex>,
    pub tris: Vec<[u32; 3]>,
    pub color: [u8; 3],
}

impl Part {
    pub fn begin(&mut self, color: [u8; 3]) {
        self.verts.clear();
        self.tris.clear();
        self.color = color;
    }

    /// Bytes held by the scratch buffers (for the memory test).
    pub fn capacity_bytes(&self) -> usize {
        self.verts.capacity() * std::mem::size_of::<Vertex>()
            + self.tris.capacity() * std::mem::size_of::<[u32; 3]>()
    }

    pub fn v(&mut self, p: Vec3, n: Vec3) -> u32 {
        self.verts.push(Vertex {
            p,
            n,
            c: self.color,
        });
        (self.verts.len() - 1) as u32
    }

    /// A triangle, wound so that its geometric normal agrees with its vertex
    /// normals (counter-clockwise seen from outside).
    pub fn tri(&mut self, a: u32, b: u32, c: u32) {
        let (va, vb, vc) = (
            self.verts[a as usize],
            self.verts[b as usize],
            self.verts[c as usize],
        );
        let g = (vb.p - va.p).cross(vc.p - va.p);
        if g.dot(va.n + vb.n + vc.n) < 0.0 {
            self.tris.push([a, c, b]);
        } else {
            self.tris.push([a, b, c]);
        }
    }

    pub fn quad(&mut self, a: u32, b: u32, c: u32, d: u32) {
        self.tri(a, b, c);
        self.tri(a, c, d);
    }

    /// A flat quad `center ± u ± v` (a plate, a sign), one-sided geometry.
    pub fn plate(&mut self, center: Vec3, u: Vec3, v: Vec3) {
        let n = u.cross(v).normalize();
        let a = self.v(center - u - v, n);
        let b = self.v(center + u - v, n);
        let c = self.v(center + u + v, n);
        let d = self.v(center - u + v, n);
        self.quad(a, b, c, d);
    }

    /// An oriented box: `center` plus three perpendicular half-extent vectors.
    /// 24 vertices (flat normals), 12 triangles.
    pub fn obox(&mut self, center: Vec3, h: [Vec3; 3]) {
        for k in 0..3 {
            let n = h[k].normalize();
            let u = h[(k + 1) % 3];
            let w = h[(k + 2) % 3];
            for s in [1.0f32, -1.0] {
                let fc = center + h[k] * s;
                let nn = n * s;
                let a = self.v(fc - u - w, nn);
                let b = self.v(fc + u - w, nn);
                let c = self.v(fc + u + w, nn);
                let d = self.v(fc - u + w, nn);
                self.quad(a, b, c, d);
            }
        }
    }

    /// An axis-aligned box from its corners.
    pub fn aabox(&mut self, lo: Vec3, hi: Vec3) {
        let c = (lo + hi) * 0.5;
        let e = ((hi - lo) * 0.5).max(Vec3::splat(0.002));
        self.obox(c, [Vec3::X * e.x, Vec3::Y * e.y, Vec3::Z * e.z]);
    }

    /// A box stretched from `a` to `b` with cross-section `w` (along `side`)
    /// by `h` (along `up`); `side` and `up` perpendicular to `b - a`.
    pub fn bar(&mut self, a: Vec3, b: Vec3, up: Vec3, w: f32, h: f32) {
        let d = (b - a) * 0.5;
        let up = up.normalize();
        let side = d.normalize().cross(up).normalize();
        self.obox((a + b) * 0.5, [d, up * (h * 0.5), side * (w * 0.5)]);
    }

    /// An I-beam from `a` to `b`, web along `up`: two flanges and a web.
    pub fn ibeam(&mut self, a: Vec3, b: Vec3, up: Vec3, h: f32, w: f32) {
        let d = (b - a) * 0.5;
        let c = (a + b) * 0.5;
        let up = up.normalize();
        let side = d.normalize().cross(up).normalize();
        let tf = (h * 0.08).max(0.01);
        let tw = (w * 0.08).max(0.008);
        for s in [1.0f32, -1.0] {
            self.obox(
                c + up * (s * (h * 0.5 - tf * 0.5)),
                [d, up * (tf * 0.5), side * (w * 0.5)],
            );
        }
        self.obox(c, [d, up * (h * 0.5 - tf), side * (tw * 0.5)]);
    }

    /// A ring of `segs` smooth vertices around `center` in the plane of the
    /// unit vectors `a`, `b`; returns the first index.
    fn ring(&mut self, center: Vec3, a: Vec3, b: Vec3, r: f32, segs: u32) -> u32 {
        let first = self.verts.len() as u32;
        for j in 0..segs {
            let (s, c) = (TAU * j as f32 / segs as f32).sin_cos();
            let dir = a * c + b * s;
            self.v(center + dir * r, dir);
        }
        first
    }

    fn connect(&mut self, r0: u32, r1: u32, segs: u32) {
        for j in 0..segs {
            let k = (j + 1) % segs;
            self.quad(r0 + j, r0 + k, r1 + k, r1 + j);
        }
    }

    /// A flat disk facing `n` (a cap), fan around its centre.
    pub fn disk(&mut self, center: Vec3, n: Vec3, a: Vec3, b: Vec3, r: f32, segs: u32) {
        let c = self.v(center, n);
        let first = self.verts.len() as u32;
        for j in 0..segs {
            let (s, co) = (TAU * j as f32 / segs as f32).sin_cos();
            self.v(center + (a * co + b * s) * r, n);
        }
        for j in 0..segs {
            self.tri(c, first + j, first + (j + 1) % segs);
        }
    }

    /// A cylinder from `p0` to `p1` of radius `r`, smooth sides, optional
    /// flat caps.
    pub fn cylinder(&mut self, p0: Vec3, p1: Vec3, r: f32, segs: u32, caps: bool) {
        let d = (p1 - p0).normalize();
        let (a, b) = d.any_orthonormal_pair();
        let r0 = self.ring(p0, a, b, r, segs);
        let r1 = self.ring(p1, a, b, r, segs);
        self.connect(r0, r1, segs);
        if caps {
            self.disk(p0, -d, a, b, r, segs);
            self.disk(p1, d, a, b, r, segs);
        }
    }

    /// A half-ellipsoid dome on the circle (`base`, `r`) bulging `h` along
    /// the unit `axis`, smooth normals, closed by a fan to the pole.
    pub fn dome(&mut self, base: Vec3, axis: Vec3, r: f32, h: f32, segs: u32, rings: u32) {
        let (a, b) = axis.any_orthonormal_pair();
        let mut prev = u32::MAX;
        for i in 0..rings {
            let phi = FRAC_PI_2 * i as f32 / rings as f32;
            let (sp, cp) = phi.sin_cos();
            let first = self.verts.len() as u32;
            for j in 0..segs {
                let (s, c) = (TAU * j as f32 / segs as f32).sin_cos();
                let dir = a * c + b * s;
                let p = base + axis * (h * sp) + dir * (r * cp);
                let n = (dir * (cp / r) + axis * (sp / h)).normalize();
                self.v(p, n);
            }
            if prev != u32::MAX {
                self.connect(prev, first, segs);
            }
            prev = first;
        }
        let pole = self.v(base + axis * h, axis);
        for j in 0..segs {
            self.tri(prev + j, prev + (j + 1) % segs, pole);
        }
    }

    /// A pipe run along an axis-aligned polyline: straight tubes joined by
    /// torus elbows of bend radius `bend`, one continuous smooth surface
    /// (the cross-section frame is carried through each bend), flat caps at
    /// both ends. Every leg must be longer than `2 * bend`.
    pub fn pipe_run(&mut self, pts: &[Vec3], r: f32, segs: u32, bend: f32, steps: u32) {
        let d0 = (pts[1] - pts[0]).normalize();
        let (mut a, mut b) = d0.any_orthonormal_pair();
        self.disk(pts[0], -d0, a, b, r, segs);
        let mut prev = self.ring(pts[0], a, b, r, segs);
        for i in 1..pts.len() - 1 {
            let din = (pts[i] - pts[i - 1]).normalize();
            let dout = (pts[i + 1] - pts[i]).normalize();
            let start = pts[i] - din * bend;
            let ring = self.ring(start, a, b, r, segs);
            self.connect(prev, ring, segs);
            prev = ring;
            let axis = din.cross(dout).normalize();
            let center = start + dout * bend;
            let (a0, b0) = (a, b);
            for s in 1..=steps {
                let q = Quat::from_axis_angle(axis, FRAC_PI_2 * s as f32 / steps as f32);
                let p = center + q * (start - center);
                a = (q * a0).normalize();
                b = (q * b0).normalize();
                let ring = self.ring(p, a, b, r, segs);
                self.connect(prev, ring, segs);
                prev = ring;
            }
        }
        let n = pts.len();
        let dl = (pts[n - 1] - pts[n - 2]).normalize();
        let end = self.ring(pts[n - 1], a, b, r, segs);
        self.connect(prev, end, segs);
        self.disk(pts[n - 1], dl, a, b, r, segs);
    }

    /// A flange (short wide disk) around a pipe at `p`, facing `d`.
    pub fn flange(&mut self, p: Vec3, d: Vec3, pipe_r: f32, segs: u32) {
        let t = pipe_r * 0.25 + 0.015;
        let r = pipe_r * 1.5 + 0.02;
        self.cylinder(p - d * t, p + d * t, r, segs, true);
    }
}
