//! The plant's layout and its objects. See the module documentation of
//! [`generate`](super) for the overall picture.

use super::mesh::Part;
use super::sink::Sink;
use super::GenerateError;
use crate::rng::Rng;
use glam::Vec3;

/// Triangles a unit of average weight gets.
pub(crate) const UNIT_TRIANGLES: u64 = 200_000;
/// Distance between unit origins on the grid (metres).
pub(crate) const PITCH: f32 = 72.0;
/// Offset of a unit's frame inside its grid cell (the road and rack before it).
const INSET: f32 = 10.0;

const CONCRETE: [u8; 3] = [165, 160, 150];
const GROUND: [u8; 3] = [88, 90, 86];
const GRATING: [u8; 3] = [95, 97, 100];
const RAILING: [u8; 3] = [235, 190, 20];
const STEEL: [[u8; 3]; 4] = [
    [215, 175, 30],
    [120, 125, 132],
    [70, 95, 140],
    [160, 60, 40],
];
const PIPES: [[u8; 3]; 9] = [
    [200, 40, 30],
    [40, 90, 200],
    [230, 200, 40],
    [60, 150, 70],
    [215, 215, 210],
    [150, 100, 60],
    [240, 130, 30],
    [120, 120, 130],
    [180, 180, 185],
];
const TANKS: [[u8; 3]; 4] = [
    [70, 130, 80],
    [220, 220, 215],
    [185, 190, 195],
    [90, 110, 150],
];
const MACHINES: [[u8; 3]; 4] = [[50, 80, 160], [60, 130, 70], [235, 120, 30], [90, 95, 105]];

#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub(crate) enum Kind {
    /// A multi-storey steel frame with machinery and dense piping.
    Process,
    /// A taller, crowded frame around big vessels: the densest unit.
    Dense,
    /// A tall open hall with turbine sets, a crane and a mezzanine.
    Hall,
    /// A field of large tanks next to a pipe rack.
    TankFarm,
}

impl Kind {
    /// Relative triangle share (uneven density across the plant).
    fn weight(self) -> u64 {
        match self {
            Kind::Process => 10,
            Kind::Dense => 16,
            Kind::Hall => 6,
            Kind::TankFarm => 6,
        }
    }
}

/// Number of units for `n` triangles and the grid's column count.
pub(crate) fn grid(n: u64) -> (u64, u64) {
    let units = n.div_ceil(UNIT_TRIANGLES).max(1);
    let cols = (units as f64).sqrt().ceil() as u64;
    (units, cols)
}

fn kind_of(seed: u64, u: u64) -> Kind {
    if u == 0 {
        return Kind::Process;
    }
    let mut r = Rng::derive(seed, 0x4B49_4E44 ^ u);
    match r.below(10) {
        0..=3 => Kind::Process,
        4..=5 => Kind::Dense,
        6..=7 => Kind::Hall,
        _ => Kind::TankFarm,
    }
}

struct Ctx<'s, 'a> {
    sink: &'s mut Sink<'a>,
    part: Part,
}

impl Ctx<'_, '_> {
    /// Commits the object built in `part`; false when it did not fit.
    fn emit(&mut self) -> Result<bool, GenerateError> {
        self.sink.commit(&self.part)
    }
}

/// Builds the whole plant into `sink`, exactly `n` triangles.
pub(crate) fn build(sink: &mut Sink<'_>, n: u64, seed: u64) -> Result<(), GenerateError> {
    let (units, cols) = grid(n);
    let total: u64 = (0..units).map(|u| kind_of(seed, u).weight()).sum();
    let mut ctx = Ctx {
        sink,
        part: Part::default(),
    };
    let mut cum = 0u64;
    for u in 0..units {
        let kind = kind_of(seed, u);
        cum += kind.weight();
        let limit = if u + 1 == units {
            n
        } else {
            ((n as u128 * cum as u128) / total as u128) as u64
        };
        ctx.sink.limit = limit;
        let share = limit - ctx.sink.triangles;
        let mut rng = Rng::derive(seed, u);
        let cell = Vec3::new((u % cols) as f32 * PITCH, 0.0, (u / cols) as f32 * PITCH);
        let mut unit = Unit::plan(&mut rng, kind, cell + Vec3::new(INSET, 0.0, INSET), share);
        unit.build(&mut ctx, &mut rng, units > 1)?;
        fill(&mut ctx, &mut rng, &unit)?;
        debug_assert_eq!(ctx.sink.triangles, limit);
    }
    Ok(())
}

/// One building block: a steel frame of `bx` × `bz` bays and its contents.
struct Unit {
    kind: Kind,
    o: Vec3,
    bay: f32,
    bx: u32,
    bz: u32,
    /// Heights of the floor levels above ground (the last is the top).
    levels: Vec<f32>,
    steel: [u8; 3],
    /// Crowded corner (local coordinates) where pipes and machines cluster.
    hot: Vec3,
    share: u64,
    start: u64,
    stair: (u32, u32),
}

impl Unit {
    fn plan(rng: &mut Rng, kind: Kind, o: Vec3, share: u64) -> Unit {
        let (bay, storeys, storey_h, frac, est) = match kind {
            Kind::Process => (6.0, rng.int(3, 5), rng.range(4.5, 5.5), 0.35, 260.0),
            Kind::Dense => (6.0, rng.int(5, 7), rng.range(4.0, 4.8), 0.30, 280.0),
            Kind::Hall => (10.0, 2, 9.0, 0.2, 150.0),
            Kind::TankFarm => (6.0, 2, 4.0, 0.12, 200.0),
        };
        // Small plants (a lone building) get fewer storeys, so that the
        // frame leaves room for equipment and pipes.
        let storeys = storeys.min(2 + (share / 25_000) as u32);
        let bays = (frac * share as f32 / (est * storeys as f32)).max(1.0);
        let (max_x, max_z) = match kind {
            Kind::Hall => (6, 4),
            _ => (8, 7),
        };
        let mut bx = ((bays * 1.3).sqrt().round() as u32).clamp(1, max_x);
        let mut bz = ((bays / bx as f32).round() as u32).clamp(1, max_z);
        if kind == Kind::TankFarm {
            bx = (bays.round() as u32).clamp(2, 8);
            bz = 1;
        }
        let levels = match kind {
            Kind::Hall => vec![6.0, 18.0],
            _ => (1..=storeys).map(|l| l as f32 * storey_h).collect(),
        };
        let w = bx as f32 * bay;
        let d = bz as f32 * bay;
        let hot = Vec3::new(
            if rng.chance(0.5) { 0.15 } else { 0.85 } * w,
            0.0,
            if rng.chance(0.5) { 0.15 } else { 0.85 } * d,
        );
        let stair = (rng.below(bx), if rng.chance(0.5) { 0 } else { bz - 1 });
        Unit {
            kind,
            o,
            bay,
            bx,
            bz,
            levels,
            steel: rng.pick(&STEEL),
            hot,
            share,
            start: 0,
            stair,
        }
    }

    fn w(&self) -> f32 {
        self.bx as f32 * self.bay
    }
    fn d(&self) -> f32 {
        self.bz as f32 * self.bay
    }
    fn top(&self) -> f32 {
        *self.levels.last().unwrap_or(&4.0)
    }
    fn at(&self, x: f32, y: f32, z: f32) -> Vec3 {
        self.o + Vec3::new(x, y, z)
    }

    /// The volume pipes are routed in (local coordinates).
    fn pipe_box(&self) -> (Vec3, Vec3) {
        match self.kind {
            Kind::TankFarm => (
                Vec3::new(0.3, 0.4, 0.3),
                Vec3::new(48.0, self.top() + 1.0, self.d() + 44.0),
            ),
            _ => (
                Vec3::new(0.3, 0.4, 0.3),
                Vec3::new(self.w() - 0.3, self.top() - 0.3, self.d() - 0.3),
            ),
        }
    }

    fn used(&self, ctx: &Ctx) -> u64 {
        ctx.sink.triangles - self.start
    }

    fn build(&mut self, ctx: &mut Ctx, rng: &mut Rng, rack: bool) -> Result<(), GenerateError> {
        self.start = ctx.sink.triangles;
        let (w, d, top) = (self.w(), self.d(), self.top());
        // The cell's ground tile (roads), then the unit's slab.
        ctx.part.begin(GROUND);
        let (center, half) = if rack {
            let c = Vec3::new(PITCH * 0.5 - INSET, -0.1, PITCH * 0.5 - INSET);
            (self.o + c, PITCH * 0.5)
        } else {
            // A lone building stands on a yard of its own size.
            let c = Vec3::new(w * 0.5, -0.1, d * 0.5);
            (self.o + c, w.max(d) * 0.5 + 10.0)
        };
        ctx.part.plate(center, Vec3::X * half, Vec3::NEG_Z * half);
        ctx.emit()?;
        ctx.part.begin(CONCRETE);
        ctx.part
            .aabox(self.at(-1.0, -0.3, -1.0), self.at(w + 1.0, 0.0, d + 1.0));
        ctx.emit()?;
        self.frame(ctx, rng)?;
        if rack {
            self.rack(ctx, rng)?;
        }
        let eq_target = self.share as f32
            * match self.kind {
                Kind::Process => 0.5,
                Kind::Dense => 0.45,
                Kind::Hall => 0.6,
                Kind::TankFarm => 0.6,
            };
        match self.kind {
            Kind::TankFarm => self.tank_field(ctx, rng)?,
            Kind::Hall => {
                for k in 0..self.bz.div_ceil(2) {
                    let z = (2 * k + 1) as f32 * self.bay;
                    turbine(ctx, rng, self.at(3.0, 0.0, z.min(d - 2.0)), w - 6.0)?;
                }
                self.crane(ctx, rng)?;
            }
            _ => {}
        }
        let mut attempts = 0;
        while (self.used(ctx) as f32) < eq_target && attempts < 400 {
            attempts += 1;
            let placed = match rng.below(10) {
                0..=1 if self.kind != Kind::TankFarm => self.vertical_vessel(ctx, rng)?,
                2 => self.horizontal_vessel(ctx, rng)?,
                _ => {
                    let p = self.spot(rng, 3.0);
                    machine(ctx, rng, p)?
                }
            };
            if !placed && ctx.sink.remaining() < 2_000 {
                break;
            }
        }
        let _ = top;
        self.pipes(ctx, rng)
    }

    /// A random floor position (world), biased to the crowded corner, with
    /// `margin` metres clearance from the frame's outer edge.
    fn spot(&self, rng: &mut Rng, margin: f32) -> Vec3 {
        let (w, d) = (self.w(), self.d());
        let (mut x, mut z) = if rng.chance(0.6) {
            (
                self.hot.x + rng.range(-0.3, 0.3) * w,
                self.hot.z + rng.range(-0.3, 0.3) * d,
            )
        } else {
            (rng.range(0.0, w), rng.range(0.0, d))
        };
        let m = margin.min(w * 0.5 - 0.01).min(d * 0.5 - 0.01).max(0.0);
        x = x.clamp(m, w - m);
        z = z.clamp(m, d - m);
        let floors = if self.kind == Kind::Hall {
            1
        } else {
            self.levels.len()
        };
        let l = rng.below(floors as u32) as usize;
        let y = if l == 0 {
            0.0
        } else {
            self.levels[l - 1] + 0.04
        };
        self.at(x, y, z)
    }

    fn frame(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<(), GenerateError> {
        let (bay, top) = (self.bay, self.top());
        let hall = self.kind == Kind::Hall;
        for i in 0..=self.bx {
            for j in 0..=self.bz {
                let (x, z) = (i as f32 * bay, j as f32 * bay);
                ctx.part.begin(self.steel);
                if hall {
                    ctx.part.aabox(
                        self.at(x - 0.3, 0.0, z - 0.3),
                        self.at(x + 0.3, top, z + 0.3),
                    );
                } else {
                    ctx.part
                        .ibeam(self.at(x, 0.0, z), self.at(x, top, z), Vec3::X, 0.35, 0.3);
                }
                ctx.emit()?;
            }
        }
        for (l, &y) in self.levels.iter().enumerate() {
            let (h, wf) = if hall && l + 1 == self.levels.len() {
                (0.9, 0.35)
            } else {
                (0.4, 0.2)
            };
            let beam_y = y - h * 0.5;
            // Beams along x, then along z, one object per grid line.
            for j in 0..=self.bz {
                ctx.part.begin(self.steel);
                for i in 0..self.bx {
                    let z = j as f32 * bay;
                    ctx.part.ibeam(
                        self.at(i as f32 * bay + 0.18, beam_y, z),
                        self.at((i + 1) as f32 * bay - 0.18, beam_y, z),
                        Vec3::Y,
                        h,
                        wf,
                    );
                }
                ctx.emit()?;
            }
            for i in 0..=self.bx {
                ctx.part.begin(self.steel);
                for j in 0..self.bz {
                    let x = i as f32 * bay;
                    ctx.part.ibeam(
                        self.at(x, beam_y, j as f32 * bay + 0.18),
                        self.at(x, beam_y, (j + 1) as f32 * bay - 0.18),
                        Vec3::Y,
                        h,
                        wf,
                    );
                }
                ctx.emit()?;
            }
            // Floors: gratings on some bays, railings along open edges.
            let last = l + 1 == self.levels.len();
            let p = match self.kind {
                Kind::Process => 0.65,
                Kind::Dense => 0.8,
                Kind::Hall => 1.0,
                Kind::TankFarm => 1.0,
            };
            for i in 0..self.bx {
                for j in 0..self.bz {
                    let floor = match self.kind {
                        Kind::Hall => !last && j == 0,
                        Kind::TankFarm => last,
                        _ => (i, j) != self.stair && (!last || rng.chance(0.5)),
                    } && rng.chance(p);
                    if !floor {
                        continue;
                    }
                    self.grating(ctx, i, j, y)?;
                    let edges = [
                        (j == 0, (i, j), (i + 1, j)),
                        (j + 1 == self.bz, (i, j + 1), (i + 1, j + 1)),
                        (i == 0, (i, j), (i, j + 1)),
                        (i + 1 == self.bx, (i + 1, j), (i + 1, j + 1)),
                    ];
                    for (outer, a, b) in edges {
                        if outer {
                            let pa = self.at(a.0 as f32 * bay, y + 0.04, a.1 as f32 * bay);
                            let pb = self.at(b.0 as f32 * bay, y + 0.04, b.1 as f32 * bay);
                            railing(ctx, pa, pb)?;
                        }
                    }
                }
            }
            if !hall && self.kind != Kind::TankFarm {
                let y0 = if l == 0 { 0.0 } else { self.levels[l - 1] };
                self.stairs(ctx, y0, y, l % 2 == 1)?;
            }
        }
        Ok(())
    }

    fn grating(&self, ctx: &mut Ctx, i: u32, j: u32, y: f32) -> Result<bool, GenerateError> {
        let bay = self.bay;
        let (x0, x1) = (i as f32 * bay + 0.12, (i + 1) as f32 * bay - 0.12);
        let (z0, z1) = (j as f32 * bay + 0.12, (j + 1) as f32 * bay - 0.12);
        ctx.part.begin(GRATING);
        let bars = ((z1 - z0) / 0.4) as u32;
        for k in 0..=bars {
            let z = z0 + (z1 - z0) * k as f32 / bars as f32;
            ctx.part
                .aabox(self.at(x0, y, z - 0.015), self.at(x1, y + 0.04, z + 0.015));
        }
        for x in [x0, x1] {
            ctx.part
                .aabox(self.at(x - 0.03, y, z0), self.at(x + 0.03, y + 0.04, z1));
        }
        ctx.emit()
    }

    fn stairs(&self, ctx: &mut Ctx, y0: f32, y1: f32, flip: bool) -> Result<bool, GenerateError> {
        let bay = self.bay;
        let (i, j) = self.stair;
        let (xa, xb) = (i as f32 * bay + 0.6, (i + 1) as f32 * bay - 0.6);
        let (xs, xe) = if flip { (xb, xa) } else { (xa, xb) };
        let z0 = j as f32 * bay + if j == 0 { 0.5 } else { bay - 1.7 };
        let rise = y1 - y0;
        let steps = (rise / 0.22).ceil() as u32;
        ctx.part.begin(RAILING);
        let run = xe - xs;
        let dir = Vec3::new(run, rise, 0.0).normalize();
        let up = Vec3::Z.cross(dir).normalize();
        for dz in [0.0, 1.2] {
            ctx.part.bar(
                self.at(xs, y0, z0 + dz),
                self.at(xe, y1, z0 + dz),
                up,
                0.04,
                0.22,
            );
        }
        for k in 0..steps {
            let t = (k as f32 + 0.5) / steps as f32;
            let x = xs + run * t;
            let y = y0 + rise * t;
            let half = (run.abs() / steps as f32 * 0.5).max(0.1);
            ctx.part.aabox(
                self.at(x - half, y - 0.03, z0 + 0.02),
                self.at(x + half, y, z0 + 1.18),
            );
        }
        ctx.emit()
    }

    /// A pipe rack along the road in front of the unit, lining up with the
    /// neighbours' racks into long straight runs across the plant.
    fn rack(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<(), GenerateError> {
        let (x0, x1) = (-INSET, PITCH - INSET);
        let (za, zb) = (-7.0, -3.0);
        let y = 6.0;
        let mut x = x0 + 2.0;
        while x < x1 {
            ctx.part.begin(STEEL[1]);
            for z in [za, zb] {
                ctx.part.aabox(
                    self.at(x - 0.15, 0.0, z - 0.15),
                    self.at(x + 0.15, y, z + 0.15),
                );
            }
            ctx.part.ibeam(
                self.at(x, y - 0.15, za - 0.3),
                self.at(x, y - 0.15, zb + 0.3),
                Vec3::Y,
                0.3,
                0.15,
            );
            ctx.emit()?;
            x += 8.0;
        }
        let count = rng.int(4, 10);
        let mut z = za + 0.3;
        for _ in 0..count {
            let r = rng.pick(&[0.08, 0.12, 0.15, 0.2, 0.25, 0.3]);
            if z + r > zb - 0.1 {
                break;
            }
            let c = z + r;
            z += 2.0 * r + 0.15;
            let segs = segs_for(r);
            let py = y + r;
            ctx.part.begin(rng.pick(&PIPES));
            ctx.part
                .cylinder(self.at(x0, py, c), self.at(x1, py, c), r, segs, false);
            let mut fx = x0 + 6.0;
            while fx < x1 {
                ctx.part.flange(self.at(fx, py, c), Vec3::X, r, segs);
                fx += 12.0;
            }
            ctx.emit()?;
        }
        Ok(())
    }

    fn tank_field(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<(), GenerateError> {
        let z0 = self.d() + 4.0;
        for gx in 0..4 {
            for gz in 0..3 {
                if rng.chance(0.2) {
                    continue;
                }
                let r = rng.range(2.5, 5.2);
                let c = self.at(
                    6.0 + gx as f32 * 12.0 + rng.range(-0.5, 0.5),
                    0.0,
                    z0 + 6.0 + gz as f32 * 12.0,
                );
                let h = rng.range(5.0, 16.0);
                if !tank(ctx, rng, c, r, h, true)? {
                    return Ok(());
                }
            }
        }
        Ok(())
    }

    fn vertical_vessel(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<bool, GenerateError> {
        let i = rng.below(self.bx);
        let j = rng.below(self.bz);
        let r = rng.range(0.6, self.bay * 0.38);
        let levels = self.levels.len() as u32;
        let l = rng.below(levels.min(2));
        let y0 = if l == 0 {
            0.0
        } else {
            self.levels[l as usize - 1] + 0.04
        };
        let h = rng.range(2.0, (self.top() - y0 - r * 0.6).max(2.5));
        let c = self.at((i as f32 + 0.5) * self.bay, y0, (j as f32 + 0.5) * self.bay);
        tank(ctx, rng, c, r, h, false)
    }

    fn horizontal_vessel(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<bool, GenerateError> {
        let r = rng.range(0.4, 1.4);
        let len = rng.range(2.5, (self.w().max(self.d()) * 0.5).clamp(3.0, 9.0));
        let along_x = rng.chance(0.5);
        let p = self.spot(rng, len * 0.5 + r + 0.3);
        let axis = if along_x { Vec3::X } else { Vec3::Z };
        let c = p + Vec3::Y * (r + 0.5);
        let color = rng.pick(&TANKS);
        ctx.part.begin(color);
        let (a, b) = (c - axis * (len * 0.5), c + axis * (len * 0.5));
        ctx.part.cylinder(a, b, r, 24, false);
        let hd = r * rng.range(0.35, 0.6);
        ctx.part.dome(b, axis, r, hd, 24, 5);
        ctx.part.dome(a, -axis, r, hd, 24, 5);
        let side = Vec3::Y.cross(axis);
        for s in [-0.3f32, 0.3] {
            let q = c + axis * (len * s);
            ctx.part.obox(
                Vec3::new(q.x, p.y + (r + 0.5) * 0.5, q.z),
                [axis * 0.15, Vec3::Y * ((r + 0.5) * 0.5), side * (r * 0.8)],
            );
        }
        nozzles(ctx, rng, c + Vec3::Y * r, Vec3::Y, 0.1 + r * 0.1, 2);
        ctx.emit()
    }

    fn crane(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<bool, GenerateError> {
        let (w, d) = (self.w(), self.d());
        let y = 14.0;
        ctx.part.begin(STEEL[0]);
        for z in [0.6, d - 0.6] {
            ctx.part.ibeam(
                self.at(0.3, y, z),
                self.at(w - 0.3, y, z),
                Vec3::Y,
                0.7,
                0.35,
            );
        }
        let x = rng.range(0.2, 0.8) * w;
        ctx.part.aabox(
            self.at(x - 0.5, y + 0.35, 0.4),
            self.at(x + 0.5, y + 1.5, d - 0.4),
        );
        ctx.part.aabox(
            self.at(x - 1.0, y + 1.5, d * 0.4),
            self.at(x + 1.0, y + 2.4, d * 0.4 + 2.0),
        );
        ctx.emit()
    }

    fn pipes(&self, ctx: &mut Ctx, rng: &mut Rng) -> Result<(), GenerateError> {
        let (lo, hi) = self.pipe_box();
        let mut misses = 0;
        while misses < 6 && ctx.sink.remaining() > 0 {
            let legs = if misses == 0 {
                rng.int(3, 8)
            } else {
                rng.int(1, 3)
            };
            if pipe_run(ctx, rng, self, lo, hi, legs)? {
                misses = 0;
            } else {
                misses += 1;
            }
        }
        Ok(())
    }
}

fn segs_for(r: f32) -> u32 {
    if r < 0.07 {
        8
    } else if r < 0.2 {
        12
    } else {
        16
    }
}

const AXES: [Vec3; 6] = [
    Vec3::X,
    Vec3::NEG_X,
    Vec3::Z,
    Vec3::NEG_Z,
    Vec3::Y,
    Vec3::NEG_Y,
];

/// Length available from `p` along axis `d` inside `[lo, hi]`.
fn room(p: Vec3, d: Vec3, lo: Vec3, hi: Vec3) -> f32 {
    let mut m = f32::INFINITY;
    for a in 0..3 {
        if d[a] > 0.0 {
            m = m.min(hi[a] - p[a]);
        } else if d[a] < 0.0 {
            m = m.min(p[a] - lo[a]);
        }
    }
    m.max(0.0)
}

/// One routed pipe run with elbows and flanges; false when it did not fit.
fn pipe_run(
    ctx: &mut Ctx,
    rng: &mut Rng,
    unit: &Unit,
    lo: Vec3,
    hi: Vec3,
    legs: u32,
) -> Result<bool, GenerateError> {
    let r = rng.pick(&[0.03, 0.05, 0.05, 0.08, 0.08, 0.12, 0.15, 0.2, 0.3, 0.45]);
    let segs = segs_for(r);
    let bend = (3.0 * r).max(0.12);
    let min_leg = 2.0 * bend + 0.3;
    // Start: near the crowded corner or anywhere; hung under a level.
    let mut p = if rng.chance(0.55) {
        let h = unit.hot;
        Vec3::new(
            h.x + rng.range(-0.25, 0.25) * (hi.x - lo.x),
            0.0,
            h.z + rng.range(-0.25, 0.25) * (hi.z - lo.z),
        )
    } else {
        Vec3::new(rng.range(lo.x, hi.x), 0.0, rng.range(lo.z, hi.z))
    };
    p.y = if !unit.levels.is_empty() && rng.chance(0.7) {
        let l = unit.levels[rng.below(unit.levels.len() as u32) as usize];
        l - 0.6 - rng.below(4) as f32 * 0.35 - r
    } else {
        rng.range(lo.y + r + 0.3, hi.y)
    };
    p = p.clamp(lo + Vec3::splat(r), hi - Vec3::splat(r));
    let mut pts: [Vec3; 10] = [Vec3::ZERO; 10];
    pts[0] = p;
    let mut n = 1;
    let mut dir = Vec3::ZERO;
    for _ in 0..legs {
        let mut chosen = None;
        for _ in 0..8 {
            let d = if rng.chance(0.2) {
                AXES[4 + rng.below(2) as usize]
            } else {
                AXES[rng.below(4) as usize]
            };
            if d.dot(dir).abs() > 0.5 {
                continue;
            }
            let avail = room(p, d, lo, hi);
            if avail >= min_leg {
                let extra = rng.range(2.0, 14.0);
                let len = rng.range(min_leg, avail.min(min_leg + extra));
                chosen = Some((d, len));
                break;
            }
        }
        let Some((d, len)) = chosen else { break };
        p += d * len;
        pts[n] = p;
        n += 1;
        dir = d;
    }
    if n < 2 {
        return Ok(false);
    }
    ctx.part.begin(rng.pick(&PIPES));
    let steps = if segs <= 8 { 4 } else { 6 };
    let pts = &pts[..n];
    ctx.part.pipe_run(pts, r, segs, bend, steps);
    // Flanges at both ends and in the middle of some legs.
    let d0 = (pts[1] - pts[0]).normalize();
    let dl = (pts[n - 1] - pts[n - 2]).normalize();
    ctx.part.flange(pts[0] + d0 * 0.05, d0, r, segs);
    ctx.part.flange(pts[n - 1] - dl * 0.05, dl, r, segs);
    for k in 0..n - 1 {
        let len = pts[k].distance(pts[k + 1]);
        if len > 4.0 && rng.chance(0.5) {
            let d = (pts[k + 1] - pts[k]) / len;
            let m = pts[k] + d * (len * 0.5);
            ctx.part.flange(m - d * 0.04, d, r, segs);
            ctx.part.flange(m + d * 0.04, d, r, segs);
        }
    }
    let o = unit.o;
    for v in ctx.part.verts.iter_mut() {
        v.p += o;
    }
    ctx.emit()
}

/// A vertical tank or vessel on a base, domed top, nozzles, optional railing.
fn tank(
    ctx: &mut Ctx,
    rng: &mut Rng,
    base: Vec3,
    r: f32,
    h: f32,
    big: bool,
) -> Result<bool, GenerateError> {
    let segs = if r > 2.0 { 32 } else { 24 };
    ctx.part.begin(rng.pick(&TANKS));
    let plinth = 0.3;
    let b = base + Vec3::Y * plinth;
    let t = b + Vec3::Y * h;
    ctx.part.cylinder(b, t, r, segs, false);
    let (a, c) = Vec3::Y.any_orthonormal_pair();
    ctx.part.disk(b, Vec3::NEG_Y, a, c, r, segs);
    let hd = if big {
        r * rng.range(0.12, 0.3)
    } else {
        r * rng.range(0.4, 1.0)
    };
    ctx.part
        .dome(t, Vec3::Y, r, hd, segs, if big { 4 } else { 7 });
    let k = rng.int(1, 4);
    for s in 0..k {
        let ang = std::f32::consts::TAU * (s as f32 + rng.unit() * 0.5) / k as f32;
        let dir = Vec3::new(ang.cos(), 0.0, ang.sin());
        let y = rng.range(0.3, 0.9) * h;
        nozzles(ctx, rng, b + Vec3::Y * y + dir * r, dir, 0.08 + r * 0.04, 1);
    }
    let color = ctx.part.color;
    ctx.part.color = CONCRETE;
    ctx.part.cylinder(base, b, r + 0.3, segs, true);
    if big {
        // Roof railing: posts and a ring of rails.
        ctx.part.color = RAILING;
        let posts = 16;
        let ry = t.y + hd * 0.3;
        let rr = r * 0.92;
        for s in 0..posts {
            let a0 = std::f32::consts::TAU * s as f32 / posts as f32;
            let a1 = std::f32::consts::TAU * (s + 1) as f32 / posts as f32;
            let p0 = Vec3::new(base.x + rr * a0.cos(), ry, base.z + rr * a0.sin());
            let p1 = Vec3::new(base.x + rr * a1.cos(), ry, base.z + rr * a1.sin());
            ctx.part.bar(p0, p0 + Vec3::Y * 1.1, Vec3::X, 0.05, 0.05);
            let up = Vec3::Y;
            ctx.part.bar(p0 + up * 1.1, p1 + up * 1.1, up, 0.04, 0.04);
        }
    }
    ctx.part.color = color;
    ctx.emit()
}

/// Short pipe stubs with flanges sticking out of a vessel along `dir`.
fn nozzles(ctx: &mut Ctx, rng: &mut Rng, at: Vec3, dir: Vec3, r: f32, count: u32) {
    let (side, _) = dir.any_orthonormal_pair();
    for k in 0..count {
        let off = side * ((k as f32 - (count - 1) as f32 * 0.5) * (6.0 * r));
        let len = rng.range(0.3, 0.8);
        let p0 = at + off - dir * 0.2;
        let p1 = at + off + dir * len;
        ctx.part.cylinder(p0, p1, r, 12, false);
        ctx.part.flange(p1 - dir * 0.03, dir, r, 12);
    }
}

/// A pump set on a skid: motor with cooling fins and fan hood, coupling
/// guard, pump casing and its suction and discharge stubs.
fn machine(ctx: &mut Ctx, rng: &mut Rng, p: Vec3) -> Result<bool, GenerateError> {
    let s = rng.range(0.7, 1.6);
    let along = if rng.chance(0.5) { Vec3::X } else { Vec3::Z };
    let side = Vec3::Y.cross(along);
    ctx.part.begin(rng.pick(&MACHINES));
    ctx.part.obox(
        p + Vec3::Y * (0.12 * s),
        [along * (1.3 * s), Vec3::Y * (0.12 * s), side * (0.5 * s)],
    );
    let axis_y = p.y + 0.24 * s + 0.45 * s;
    let mc = Vec3::new(p.x, axis_y, p.z) - along * (0.5 * s);
    let mr = 0.4 * s;
    ctx.part
        .cylinder(mc - along * (0.6 * s), mc + along * (0.4 * s), mr, 16, true);
    for k in 0..4 {
        let a = std::f32::consts::FRAC_PI_4 + k as f32 * std::f32::consts::FRAC_PI_2;
        let out = (side * a.cos() + Vec3::Y * a.sin()) * (mr + 0.03 * s);
        ctx.part.obox(
            mc + out - along * (0.1 * s),
            [
                along * (0.45 * s),
                out.normalize() * (0.03 * s),
                out.normalize().cross(along) * (0.01 * s + 0.005),
            ],
        );
    }
    ctx.part
        .dome(mc - along * (0.6 * s), -along, mr * 0.95, 0.25 * s, 16, 3);
    let color = ctx.part.color;
    ctx.part.color = [230, 190, 30];
    ctx.part.obox(
        mc + along * (0.6 * s),
        [along * (0.2 * s), Vec3::Y * (0.25 * s), side * (0.25 * s)],
    );
    ctx.part.color = color;
    let pc = mc + along * (1.05 * s);
    ctx.part.cylinder(
        pc - along * (0.2 * s),
        pc + along * (0.2 * s),
        0.45 * s,
        16,
        true,
    );
    let pr = 0.1 * s;
    ctx.part.cylinder(
        pc + along * (0.2 * s),
        pc + along * (0.7 * s),
        pr,
        12,
        false,
    );
    ctx.part.flange(pc + along * (0.67 * s), along, pr, 12);
    ctx.part
        .cylinder(pc, pc + Vec3::Y * (0.8 * s), pr, 12, false);
    ctx.part.flange(pc + Vec3::Y * (0.77 * s), Vec3::Y, pr, 12);
    ctx.emit()
}

/// A turbine-generator set along x: pedestal, stepped casings, generator.
fn turbine(ctx: &mut Ctx, rng: &mut Rng, p: Vec3, len: f32) -> Result<bool, GenerateError> {
    let len = len.max(4.0);
    ctx.part.begin(CONCRETE);
    ctx.part
        .aabox(p + Vec3::new(0.0, 0.0, -2.5), p + Vec3::new(len, 5.0, 2.5));
    ctx.part.color = rng.pick(&MACHINES);
    let y = 5.0 + 2.2;
    let n = 4;
    let step = len / n as f32;
    for k in 0..n {
        let r = 1.2 + (k as f32 * 0.45).min(1.0) + rng.range(0.0, 0.3);
        let a = p + Vec3::new(k as f32 * step + 0.2, y, 0.0);
        let b = a + Vec3::X * (step - 0.4);
        ctx.part.cylinder(a, b, r, 32, true);
        ctx.part.flange(a + Vec3::X * 0.1, Vec3::X, r, 32);
    }
    ctx.emit()
}

/// A railing along one floor edge: posts, top and middle rails.
fn railing(ctx: &mut Ctx, a: Vec3, b: Vec3) -> Result<bool, GenerateError> {
    let len = a.distance(b);
    let posts = (len / 2.0).ceil() as u32;
    ctx.part.begin(RAILING);
    for k in 0..=posts {
        let p = a.lerp(b, k as f32 / posts as f32);
        ctx.part.bar(p, p + Vec3::Y * 1.1, Vec3::X, 0.05, 0.05);
    }
    for h in [0.55, 1.1] {
        ctx.part
            .bar(a + Vec3::Y * h, b + Vec3::Y * h, Vec3::Y, 0.04, 0.04);
    }
    ctx.emit()
}

/// Fills the unit's remaining budget exactly with small detail: junction
/// boxes on the columns, then signs (2 triangles), then a gusset plate.
fn fill(ctx: &mut Ctx, rng: &mut Rng, unit: &Unit) -> Result<(), GenerateError> {
    loop {
        let rem = ctx.sink.remaining();
        if rem == 0 {
            return Ok(());
        }
        let i = rng.below(unit.bx + 1) as f32 * unit.bay;
        let j = rng.below(unit.bz + 1) as f32 * unit.bay;
        let y = rng.range(0.8, unit.top() - 0.8).max(0.5);
        let c = unit.at(i, y, j);
        let side = if rng.chance(0.5) { 1.0 } else { -1.0 };
        ctx.part.begin(rng.pick(&MACHINES));
        if rem >= 12 {
            let c = c + Vec3::Z * (side * 0.35);
            ctx.part.aabox(
                c - Vec3::new(0.2, 0.25, 0.12),
                c + Vec3::new(0.2, 0.25, 0.12),
            );
        } else if rem >= 2 {
            ctx.part.color = [240, 240, 235];
            ctx.part.plate(
                c + Vec3::new(0.0, 0.0, side * 0.2),
                Vec3::X * 0.15,
                Vec3::Y * 0.1,
            );
        } else {
            ctx.part.color = unit.steel;
            let y = unit.levels.first().copied().unwrap_or(4.0) - 0.45;
            let b = unit.at(i, y, j);
            let n = Vec3::Z;
            let v0 = ctx.part.v(b, n);
            let v1 = ctx.part.v(b + Vec3::X * 0.35, n);
            let v2 = ctx.part.v(b - Vec3::Y * 0.35, n);
            ctx.part.tri(v0, v1, v2);
        }
        if !ctx.emit()? {
            unreachable!("filler never exceeds the remaining budget");
        }
    }
}
