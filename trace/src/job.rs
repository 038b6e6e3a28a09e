//! One packet's whole life as a resumable state machine: primary
//! traversal, then for each bounce the shading of its hits, the shadow
//! packet and the reflection packet. Each stage keeps its [`Traversal`]
//! and [`Packet`] in the job, so a [`Step::Missing`] hands control back
//! and the next [`PacketJob::step`] resumes exactly there.
//!
//! [`crate::render::render`] (every voxel resident) and
//! [`crate::tile::render_tile`] (voxels arriving over time) both run this
//! code, which is what makes their pixels bit-identical: a lane's
//! arithmetic never depends on the other lanes of its packet, nor on when
//! its voxels arrived.

// Lane loops index several arrays in lockstep on purpose: that is the
// shape LLVM vectorizes.
#![allow(clippy::needless_range_loop)]

use crate::accel::{PreparedVoxel, TopLevel, VoxelRef, VoxelSource};
use crate::camera::CameraBasis;
use crate::clock;
use crate::packet::{Occluder, Packet, Step, Traversal};
use crate::render::{
    voxel_color, FrameStats, Isa, RenderSettings, AMBIENT, BACKGROUND, SHADOW_EPS,
};
use crate::tile::Rect;
use glam::Vec3;

/// One primary packet in this many (a power of two) counts its lanes at
/// child boxes.
const LANE_SAMPLE: u32 = 8;

/// What every packet of a frame reads.
pub(crate) struct Ctx<'a> {
    pub top: &'a TopLevel,
    pub basis: CameraBasis,
    pub settings: &'a RenderSettings,
    /// Unit direction towards the light.
    pub light: Vec3,
    /// Shadow and reflection rays start this far from their surface.
    pub eps: f32,
    /// Fill `rgba` with [`depth_grey`] when not shading.
    pub grey: bool,
    /// Whether 16-lane packets are sparse ([`crate::render::Packets`]):
    /// set only where the kernel runs its AVX-512 code and the CPU has
    /// AVX-512F and BMI2 (the callers clear it for other packets).
    pub quad: bool,
    /// Whether shadow packets hand sparse subtrees over to groups of lanes
    /// ([`Packet::hand_off_sparse_subtrees`]): where the kernel runs its
    /// AVX-512 or AVX2 code (`render` clears it for tiles whose rays stay
    /// together, [`crate::render::PacketChooser::scattered`]; the cluster's
    /// tiles, [`crate::tile`], keep it for AVX-512 only).
    pub groups: bool,
    /// Whether the tile's rays part ways, so that their hits lie far
    /// apart in memory: the surface stage then starts every lane's reads
    /// before it shades the first ([`PacketJob::prefetch_surfaces`]).
    /// `render` takes it from its packet chooser
    /// ([`crate::render::PacketChooser::scattered`]); the cluster's tiles
    /// ([`crate::tile`]), which have none, keep it on.
    pub scattered: bool,
}

impl<'a> Ctx<'a> {
    pub fn new(
        top: &'a TopLevel,
        basis: CameraBasis,
        settings: &'a RenderSettings,
        grey: bool,
    ) -> Ctx<'a> {
        Ctx {
            top,
            basis,
            settings,
            light: settings.light.normalize_or(Vec3::Y),
            eps: SHADOW_EPS * settings.scene_diagonal,
            grey,
            quad: settings.isa == Isa::Avx512 && crate::quad::available(),
            groups: settings.isa != Isa::Portable,
            scattered: true,
        }
    }
}

/// Where finished packets write their pixels: `width` pixels a row, rows
/// top to bottom.
pub(crate) struct Region<'a> {
    pub width: u32,
    pub depth: &'a mut [f32],
    pub primid: &'a mut [u32],
    /// Empty when nobody asked for colors.
    pub rgba: &'a mut [[u8; 4]],
}

/// The grey of a pixel at distance `depth` when the image is not shaded:
/// `1 - depth / scene_diagonal`, clamped; the background on a miss. Needs
/// nothing but the pixel itself, so tiles and frames agree.
pub fn depth_grey(depth: f32, scene_diagonal: f32) -> [u8; 4] {
    if depth.is_finite() {
        let g = to_u8(1.0 - depth / scene_diagonal);
        [g, g, g, 255]
    } else {
        rgba(BACKGROUND)
    }
}

#[inline(always)]
fn to_u8(v: f32) -> u8 {
    (v.clamp(0.0, 1.0) * 255.0 + 0.5) as u8
}

#[inline(always)]
fn rgba(c: Vec3) -> [u8; 4] {
    [to_u8(c.x), to_u8(c.y), to_u8(c.z), 255]
}

/// Three components of N lanes, axis by axis (`.0[axis][lane]`): the
/// shape in which lane loops vectorize.
#[derive(Clone, Copy)]
struct Axes<const N: usize>([[f32; N]; 3]);

impl<const N: usize> Axes<N> {
    #[inline(always)]
    fn splat(v: Vec3) -> Axes<N> {
        Axes([[v.x; N], [v.y; N], [v.z; N]])
    }

    #[inline(always)]
    fn lane(&self, i: usize) -> Vec3 {
        Vec3::new(self.0[0][i], self.0[1][i], self.0[2][i])
    }

    #[inline(always)]
    fn set(&mut self, i: usize, v: Vec3) {
        for a in 0..3 {
            self.0[a][i] = v[a];
        }
    }
}

#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Stage {
    /// Traversing the primary packet.
    Primary,
    /// Looking up the surfaces of the current hits (lanes before `lane`
    /// are done).
    Surface,
    /// Traversing the shadow packet of the current bounce.
    Shadow,
    /// Traversing the reflection packet of the current bounce.
    Reflect,
    Done,
}

/// How many of the last distinct occluders a job's shadow packets try
/// first: several rather than one block more whole packets from inside a
/// model and cost nothing measurable elsewhere (`scripts/bench-kernel`).
const OCCLUDERS: usize = 4;

/// One packet of N rays from a BW-pixel-wide block, through every stage.
pub(crate) struct PacketJob<const N: usize, const BW: u32> {
    /// Region-local pixel of each lane (lanes past the region's edge
    /// repeat its last pixel) and whether it is the lane's own.
    px: [(u32, u32); N],
    own: [bool; N],
    /// Whether every lane's pixel is its own (all blocks but those on the
    /// region's right and bottom edges).
    whole: bool,
    stage: Stage,
    trav: Traversal<N>,
    /// The packet being traversed: primary, shadow or reflection; once
    /// traversed, and until its surfaces are read, the hits being shaded.
    packet: Packet<N>,
    /// The rays of the hits being shaded.
    cur_dirs: Axes<N>,
    origins: Axes<N>,
    reflected: Axes<N>,
    bounce: u32,
    lane: usize,
    /// What the surface stage reads of each live lane's triangle: the
    /// normals and colors (RGBA bytes in one word) of its three corners.
    corner_normals: [Axes<N>; 3],
    corner_colors: [[u32; N]; 3],
    color: Axes<N>,
    weight: [f32; N],
    points: Axes<N>,
    normals: Axes<N>,
    albedo: Axes<N>,
    mirror: [f32; N],
    /// The last [`OCCLUDERS`] distinct triangles that blocked a lane of
    /// this job's shadow packets (kept from block to block; the next to
    /// replace at `next_occluder`), and whether the current shadow packet
    /// has yet to try them.
    last_occluders: [Option<Occluder>; OCCLUDERS],
    next_occluder: usize,
    try_occluder: bool,
}

impl<const N: usize, const BW: u32> PacketJob<N, BW> {
    /// A job for the block whose top left pixel is pixel (`bx`, `by`) of
    /// `rect` (relative to its corner).
    #[inline(always)]
    pub fn new(ctx: &Ctx, rect: Rect, bx: u32, by: u32) -> Self {
        let mut job = PacketJob {
            px: [(0, 0); N],
            own: [false; N],
            whole: false,
            stage: Stage::Primary,
            trav: Traversal::default(),
            packet: Packet::new(&[Vec3::ZERO; N], &[Vec3::X; N], 0.0, 0.0),
            cur_dirs: Axes::splat(Vec3::ZERO),
            origins: Axes::splat(Vec3::ZERO),
            reflected: Axes::splat(Vec3::ZERO),
            bounce: 0,
            lane: 0,
            corner_normals: [Axes::splat(Vec3::ZERO); 3],
            corner_colors: [[0; N]; 3],
            color: Axes::splat(Vec3::ZERO),
            weight: [1.0; N],
            points: Axes::splat(Vec3::ZERO),
            normals: Axes::splat(Vec3::Y),
            albedo: Axes::splat(Vec3::ZERO),
            mirror: [0.0; N],
            last_occluders: [None; OCCLUDERS],
            next_occluder: 0,
            try_occluder: false,
        };
        job.start(ctx, rect, bx, by);
        job
    }

    /// Reuses the job for the block at (`bx`, `by`) of `rect`.
    #[inline(always)]
    pub fn start(&mut self, ctx: &Ctx, rect: Rect, bx: u32, by: u32) {
        let (x0, y0, w, h) = (rect.x0, rect.y0, rect.width, rect.height);
        for i in 0..N {
            let (x, y) = (bx + i as u32 % BW, by + i as u32 / BW);
            let (cx, cy) = (x.min(w - 1), y.min(h - 1));
            self.px[i] = (cx, cy);
            self.own[i] = x == cx && y == cy;
            self.cur_dirs.set(i, ctx.basis.direction(x0 + cx, y0 + cy));
        }
        self.whole = self.own.iter().all(|&own| own);
        self.origins = Axes::splat(ctx.basis.eye);
        self.packet
            .aim(&self.origins.0, &self.cur_dirs.0, 0.0, f32::INFINITY);
        self.packet.quad = ctx.quad;
        // One primary packet in eight measures its coherence.
        self.packet.count_lanes = (bx / BW + by / (N as u32 / BW)) & (LANE_SAMPLE - 1) == 0;
        self.trav.reset();
        self.stage = Stage::Primary;
    }

    /// Runs the packet until it is done (its pixels written to `out`) or
    /// needs a voxel `source` lacks; then call again once it is resident.
    #[inline(always)]
    pub fn step(
        &mut self,
        ctx: &Ctx,
        source: &dyn VoxelSource,
        out: &mut Region,
        stats: &mut FrameStats,
    ) -> Step {
        loop {
            match self.stage {
                Stage::Primary | Stage::Shadow | Stage::Reflect => {
                    let shadow = self.stage == Stage::Shadow;
                    let started = shadow.then(clock::ticks);
                    // A new shadow packet first tries the triangles that
                    // blocked the ones before; where they block every
                    // lane, it needs no traversal.
                    let blocked =
                        std::mem::take(&mut self.try_occluder) && self.try_last_occluders();
                    let step = if blocked {
                        stats.occluder_skips += 1;
                        Step::Done
                    } else {
                        self.trav.run(&mut self.packet, ctx.top, source)
                    };
                    if let Some(s) = started {
                        stats.shadow_ticks += clock::ticks().saturating_sub(s);
                    }
                    if let Step::Missing(id) = step {
                        return Step::Missing(id);
                    }
                    match self.stage {
                        Stage::Primary => {
                            stats.voxels_visited += self.trav.voxels_visited as u64;
                            self.trav.reset();
                            self.primary_done(ctx, out, stats);
                        }
                        Stage::Shadow => {
                            stats.shadow_packets += 1;
                            if !blocked {
                                self.remember_occluder(source);
                            }
                            self.trav.reset();
                            self.shadow_done(ctx, out, stats);
                        }
                        _ => {
                            self.trav.reset();
                            self.origins = self.points;
                            self.cur_dirs = self.reflected;
                            self.bounce += 1;
                            self.lane = 0;
                            self.stage = Stage::Surface;
                        }
                    }
                }
                Stage::Surface => {
                    if let Some(id) = self.surfaces(ctx, source) {
                        return Step::Missing(id);
                    }
                    self.lane = 0;
                    // A block whose rays all left the model has no
                    // surface to light: no shadow packet at all. (From
                    // afar most blocks are sky, and building, trying and
                    // timing empty packets is not free.)
                    let lit_surfaces = self.weight.iter().any(|&w| w > 0.0);
                    if ctx.settings.shadows && lit_surfaces {
                        self.packet.aim(
                            &self.points.0,
                            &Axes::splat(ctx.light).0,
                            ctx.eps,
                            f32::INFINITY,
                        );
                        self.packet.any_hit = true;
                        self.packet.quad = ctx.quad;
                        if ctx.groups {
                            self.packet.hand_off_sparse_subtrees(ctx.settings.isa);
                        }
                        self.try_occluder = ctx.settings.occluder_cache;
                        for i in 0..N {
                            // Lanes without a surface to light take no part.
                            if self.weight[i] == 0.0 {
                                self.packet.t[i] = f32::NEG_INFINITY;
                            }
                        }
                        self.stage = Stage::Shadow;
                    } else {
                        self.light(ctx, &[true; N], out, stats);
                    }
                }
                Stage::Done => return Step::Done,
            }
        }
    }

    /// Blocks the shadow packet's lanes that the last occluders block;
    /// whether that blocked every lane. A try that blocks nothing costs
    /// about one triangle test an occluder, so every packet tries: resting
    /// a few packets after a try that blocks nothing gains nothing where it
    /// seldom blocks and loses where it often does (`scripts/bench-kernel`).
    #[inline(always)]
    fn try_last_occluders(&mut self) -> bool {
        for o in self.last_occluders.iter().flatten() {
            if self.packet.occlude_with(o) {
                return true;
            }
        }
        false
    }

    /// Keeps the triangle that blocked the first blocked lane of the shadow
    /// packet just traced, for the next ones to try first, in place of the
    /// oldest kept (unless it is kept already). Looked up here,
    /// once a packet, rather than recorded in the traversal's leaves: that
    /// would slow every packet's triangle loop, primary ones too.
    #[inline(always)]
    fn remember_occluder(&mut self, source: &dyn VoxelSource) {
        let p = &self.packet;
        let Some(i) = (0..N).find(|&i| p.occluded(i) && p.voxel[i] != u32::MAX) else {
            return;
        };
        if self
            .last_occluders
            .iter()
            .flatten()
            .any(|o| o.id == p.id[i])
        {
            return;
        }
        if let Some(vox) = source.voxel(p.voxel[i]) {
            self.last_occluders[self.next_occluder] = Some(Occluder {
                corners: vox.corners[p.tri[i] as usize],
                id: p.id[i],
            });
            self.next_occluder = (self.next_occluder + 1) % OCCLUDERS;
        }
    }

    /// Writes the primary hits; starts shading.
    #[inline(always)]
    fn primary_done(&mut self, ctx: &Ctx, out: &mut Region, stats: &mut FrameStats) {
        let p = &self.packet;
        stats.child_hits += u64::from(p.child_hits);
        stats.child_lanes += u64::from(p.child_lanes);
        // A lane that hit nothing still has the packet's far limit
        // (infinity) and no id: what the region holds where nothing is hit.
        self.write_own(out.depth, out.width, &p.t);
        self.write_own(out.primid, out.width, &p.id);
        let (mut rays, mut hits) = (0u64, 0u64);
        for i in 0..N {
            rays += self.own[i] as u64;
            hits += (self.own[i] & p.hit(i)) as u64;
        }
        stats.primary_rays += rays;
        stats.hits += hits;
        if !ctx.settings.shade && ctx.grey {
            let mut grey = [[0; 4]; N];
            for i in 0..N {
                grey[i] = depth_grey(p.t[i], ctx.settings.scene_diagonal);
            }
            self.write_own(out.rgba, out.width, &grey);
        }
        if !ctx.settings.shade {
            self.stage = Stage::Done;
            return;
        }
        // A block of sky takes the background without the shading stages
        // (from afar most blocks are sky).
        if !(0..N).any(|i| p.hit(i)) {
            self.write_own(out.rgba, out.width, &[rgba(BACKGROUND); N]);
            self.stage = Stage::Done;
            return;
        }
        self.color = Axes::splat(Vec3::ZERO);
        self.weight = [1.0; N];
        self.bounce = 0;
        self.lane = 0;
        self.stage = Stage::Surface;
    }

    /// Surface, color and mirror share of each live lane's hit (Lambert
    /// shading with the interpolated vertex normal and color); a lane that
    /// hit nothing takes the background. `Some(id)` when voxel `id` is
    /// missing: the corners of lanes before `self.lane` are read, call
    /// again to go on.
    ///
    /// In two passes: the corners' normals and colors of every live lane
    /// are copied out of the voxels first, lane by lane; then every lane is
    /// shaded at once in lane loops over axes, which LLVM vectorizes (lane
    /// by lane, the arithmetic cost more than the reads).
    #[inline(always)]
    fn surfaces(&mut self, ctx: &Ctx, source: &dyn VoxelSource) -> Option<u32> {
        if ctx.scattered {
            self.prefetch_surfaces(source);
        }
        if let Some(id) = self.read_corners(source) {
            return Some(id);
        }
        let s = ctx.settings;
        let mut live = [false; N];
        for i in 0..N {
            let alive = self.weight[i] != 0.0;
            let hit = self.packet.hit(i);
            live[i] = alive & hit;
            let miss = alive & !hit;
            for a in 0..3 {
                let background = self.color.0[a][i] + BACKGROUND[a] * self.weight[i];
                self.color.0[a][i] = if miss { background } else { self.color.0[a][i] };
            }
            self.weight[i] = if miss { 0.0 } else { self.weight[i] };
        }
        // No live lane (every reflected ray left the model, say): nothing
        // to shade.
        if !live.contains(&true) {
            return None;
        }
        let [na, nb, nc] = &self.corner_normals;
        let [ca, cb, cc] = &self.corner_colors;
        for i in 0..N {
            let (u, v) = (self.packet.u[i], self.packet.v[i]);
            let w = 1.0 - u - v;
            // The operations of `Vec3`, component by component, in its
            // order: the colors stay those of the reference renderer.
            let mut n = [0.0; 3];
            let mut color = [0.0; 3];
            for a in 0..3 {
                n[a] = na.0[a][i] * w + nb.0[a][i] * u + nc.0[a][i] * v;
                let channel = |c: u32| ((c >> (8 * a)) & 0xff) as f32 / 255.0;
                color[a] = channel(ca[i]) * w + channel(cb[i]) * u + channel(cc[i]) * v;
            }
            // `normalize_or(Vec3::Y)`.
            let rcp = 1.0 / (n[0] * n[0] + n[1] * n[1] + n[2] * n[2]).sqrt();
            let unit = rcp.is_finite() && rcp > 0.0;
            let n = if unit {
                n.map(|c| c * rcp)
            } else {
                Vec3::Y.to_array()
            };
            let d = self.cur_dirs.lane(i).to_array();
            let facing_away = n[0] * d[0] + n[1] * d[1] + n[2] * d[2] > 0.0;
            for a in 0..3 {
                let n = if facing_away { -n[a] } else { n[a] };
                let point = self.origins.0[a][i] + d[a] * self.packet.t[i];
                self.points.0[a][i] = if live[i] { point } else { 0.0 };
                self.normals.0[a][i] = if live[i] { n } else { Vec3::Y[a] };
                self.albedo.0[a][i] = if live[i] { color[a] } else { 0.0 };
            }
            self.mirror[i] = 0.0;
        }
        if self.bounce < s.reflections {
            for i in 0..N {
                if live[i] && s.reflective.matches(self.packet.id[i], self.albedo.lane(i)) {
                    self.mirror[i] = s.reflectance;
                }
            }
        }
        if s.voxel_colors {
            for i in 0..N {
                if live[i] {
                    // The voxel whose cell holds the point: the one the
                    // hit was found in depends on the traversal order
                    // when the triangle straddles cells.
                    let id = ctx.top.voxel_at(self.points.lane(i));
                    self.albedo
                        .set(i, voxel_color(id.unwrap_or(self.packet.voxel[i])));
                }
            }
        }
        None
    }

    /// Copies the corners' normals and colors of each live lane's hit,
    /// from lane `self.lane` on, into [`Self::corner_normals`] and
    /// [`Self::corner_colors`]; `Some(id)` when voxel `id` is missing
    /// (`self.lane` is then the lane that needs it).
    #[inline(always)]
    fn read_corners(&mut self, source: &dyn VoxelSource) -> Option<u32> {
        // The voxel of the last lane read: neighbouring lanes mostly hit
        // the same one.
        let mut last: Option<VoxelRef<'_>> = None;
        for i in self.lane..N {
            if self.weight[i] == 0.0 || !self.packet.hit(i) {
                continue;
            }
            let id = self.packet.voxel[i];
            if last.as_ref().is_none_or(|v| v.id != id) {
                match source.voxel(id) {
                    Some(v) => last = Some(v),
                    None => {
                        self.lane = i;
                        return Some(id);
                    }
                }
            }
            let vox = last.as_ref().expect("just set");
            let corners = vox.triangles[self.packet.tri[i] as usize];
            for (k, &c) in corners.iter().enumerate() {
                let n = vox.normals[c as usize];
                for a in 0..3 {
                    self.corner_normals[k].0[a][i] = n[a];
                }
                self.corner_colors[k][i] = u32::from_le_bytes(vox.colors[c as usize]);
            }
        }
        self.lane = N;
        None
    }

    /// Starts the reads of [`Self::surfaces`] for every live lane's hit,
    /// up to the first lane whose voxel is missing. Looked up one lane
    /// after another, each hit waits on a chain of misses of its own (its
    /// vertex indices, then their normals and colors, in arrays that
    /// traversal did not read); started together, they wait together.
    /// Where rays stay together their hits are mostly cached and the extra
    /// pass only costs, hence [`Ctx::scattered`] (`scripts/bench-kernel`).
    /// Every lane's vertex indices are requested before the first is read,
    /// so that no lane's read holds the next lanes' requests back.
    #[inline(always)]
    fn prefetch_surfaces(&self, source: &dyn VoxelSource) {
        self.each_live_hit(source, |vox, tri| vox.prefetch_indices(tri));
        self.each_live_hit(source, |vox, tri| vox.prefetch_surface(tri));
    }

    /// Calls `f` with the voxel and voxel-local triangle of each live
    /// lane's hit from lane `self.lane` on, up to the first lane whose
    /// voxel `source` lacks.
    #[inline(always)]
    fn each_live_hit(&self, source: &dyn VoxelSource, mut f: impl FnMut(&PreparedVoxel, u32)) {
        let hits = &self.packet;
        let mut last: Option<VoxelRef<'_>> = None;
        for i in self.lane..N {
            if self.weight[i] == 0.0 || !hits.hit(i) {
                continue;
            }
            let id = hits.voxel[i];
            if last.as_ref().is_none_or(|v| v.id != id) {
                last = source.voxel(id);
            }
            let Some(vox) = &last else {
                break;
            };
            f(vox, hits.tri[i]);
        }
    }

    /// Writes each lane's value to its own pixel of `dst` (a region
    /// `width` pixels a row): a whole block row by row, others lane by
    /// lane.
    #[inline(always)]
    fn write_own<T: Copy>(&self, dst: &mut [T], width: u32, values: &[T; N]) {
        if self.whole {
            let bw = BW as usize;
            for (r, row) in values.chunks_exact(bw).enumerate() {
                let (x, y) = self.px[r * bw];
                let at = (y * width + x) as usize;
                dst[at..at + bw].copy_from_slice(row);
            }
            return;
        }
        for i in 0..N {
            if self.own[i] {
                let (x, y) = self.px[i];
                dst[(y * width + x) as usize] = values[i];
            }
        }
    }

    #[inline(always)]
    fn shadow_done(&mut self, ctx: &Ctx, out: &mut Region, stats: &mut FrameStats) {
        let mut lit = [true; N];
        // Counted here and added once: increments of `stats` lane by lane
        // wait on one another through memory.
        let (mut rays, mut occluded) = (0u64, 0u64);
        for i in 0..N {
            let live = self.weight[i] > 0.0;
            lit[i] = !(live & self.packet.occluded(i));
            rays += (live & self.own[i]) as u64;
            occluded += (live & self.own[i] & !lit[i]) as u64;
        }
        stats.shadow_rays += rays;
        stats.occluded += occluded;
        self.light(ctx, &lit, out, stats);
    }

    /// Adds each lane's local light; starts the reflection packet, or
    /// writes the colors when no lane reflects.
    #[inline(always)]
    fn light(&mut self, ctx: &Ctx, lit: &[bool; N], out: &mut Region, stats: &mut FrameStats) {
        let l = ctx.light.to_array();
        let mut any_mirror = false;
        for i in 0..N {
            let alive = self.weight[i] != 0.0;
            let n = self.normals.lane(i).to_array();
            let diffuse = if lit[i] {
                (n[0] * l[0] + n[1] * l[1] + n[2] * l[2]).max(0.0)
            } else {
                0.0
            };
            let share = self.weight[i] * (1.0 - self.mirror[i]);
            for a in 0..3 {
                let local = self.albedo.0[a][i] * (AMBIENT + (1.0 - AMBIENT) * diffuse);
                let lit_color = self.color.0[a][i] + local * share;
                self.color.0[a][i] = if alive { lit_color } else { self.color.0[a][i] };
            }
            self.weight[i] = if alive {
                self.weight[i] * self.mirror[i]
            } else {
                self.weight[i]
            };
            any_mirror |= self.weight[i] > 0.0;
        }
        if !any_mirror {
            // A loop, not `array::from_fn`: its closure is compiled on its
            // own, without the kernel's target features.
            let mut pixels = [[0; 4]; N];
            for i in 0..N {
                pixels[i] = rgba(self.color.lane(i));
            }
            self.write_own(out.rgba, out.width, &pixels);
            self.stage = Stage::Done;
            return;
        }
        for i in 0..N {
            let d = self.cur_dirs.lane(i);
            let n = self.normals.lane(i);
            self.reflected
                .set(i, (d - n * (2.0 * d.dot(n))).normalize_or(n));
        }
        self.packet
            .aim(&self.points.0, &self.reflected.0, ctx.eps, f32::INFINITY);
        self.packet.quad = ctx.quad;
        for i in 0..N {
            if self.weight[i] == 0.0 {
                self.packet.t[i] = f32::NEG_INFINITY;
            } else if self.own[i] {
                stats.reflection_rays += 1;
            }
        }
        self.stage = Stage::Reflect;
    }
}
