//! The figures `dray render` reports: one view's rays per second over timed
//! passes, and a camera path's frame rate and working sets, each as a line
//! of text and as a JSON object.

use crate::accel::{RecordingSource, ResidentSource, TopLevel, VoxelSource};
use crate::camera::Camera;
use crate::render::{render_sample, FrameStats, Isa, Passes, RenderSettings};
use serde_json::{json, Value};

/// One view rendered in timed passes ([`crate::render::render_repeated`]).
#[derive(Clone, Debug)]
pub struct ViewReport {
    pub width: u32,
    pub height: u32,
    /// Samples per pixel of each pass ([`crate::render::render_samples`]):
    /// the counts and times are of all of them.
    pub samples: u32,
    pub threads: usize,
    pub isa: Isa,
    /// Whether shadow or reflection rays were traced (the text names them).
    pub secondary: bool,
    /// The last pass's counts.
    pub stats: FrameStats,
    /// Each pass's wall-clock seconds, fastest first.
    pub seconds: Vec<f64>,
    /// Each pass's thread seconds in shadow packets, fewest first.
    pub shadow_seconds: Vec<f64>,
    /// Voxels of the database, and their bytes in the kernel's layout.
    pub voxels: usize,
    pub resident_bytes: usize,
    /// The process's memory in transparent huge pages, where known: large
    /// models trace faster in them, so a comparison names it.
    pub huge_pages_bytes: Option<u64>,
    /// Seconds to load every voxel.
    pub load_seconds: f64,
    pub camera: Camera,
}

impl ViewReport {
    /// The report of `passes` rendered with `settings` through `camera`;
    /// the database's size and load time are the caller's to fill in.
    pub fn new(passes: &Passes, settings: &RenderSettings, camera: &Camera) -> ViewReport {
        let mut seconds = passes.seconds.clone();
        seconds.sort_by(f64::total_cmp);
        let mut shadow_seconds = passes.shadow_seconds.clone();
        shadow_seconds.sort_by(f64::total_cmp);
        ViewReport {
            width: passes.frame.width,
            height: passes.frame.height,
            samples: passes.samples,
            threads: settings.threads,
            isa: settings.isa,
            secondary: settings.shadows || settings.reflections > 0,
            stats: passes.frame.stats,
            seconds,
            shadow_seconds,
            voxels: 0,
            resident_bytes: 0,
            huge_pages_bytes: None,
            load_seconds: 0.0,
            camera: *camera,
        }
    }

    /// Rays of one pass (all its samples): primary, shadow and reflection.
    pub fn rays(&self) -> u64 {
        let s = &self.stats;
        s.primary_rays + s.shadow_rays + s.reflection_rays
    }

    /// Millions of rays per second of the fastest pass.
    pub fn mrays_best(&self) -> f64 {
        self.rays() as f64 / self.seconds[0] / 1e6
    }

    /// Millions of rays per second of the median pass.
    pub fn mrays_median(&self) -> f64 {
        self.rays() as f64 / self.seconds[self.seconds.len() / 2] / 1e6
    }

    /// Millions of shadow rays per second of one thread's time, from
    /// `secs` thread seconds; none when no shadow ray was timed.
    fn shadow_rate(&self, secs: f64) -> Option<f64> {
        (secs > 0.0).then(|| self.stats.shadow_rays as f64 / (secs / self.threads as f64) / 1e6)
    }

    /// Share of the primary rays that hit a triangle.
    pub fn hit_fraction(&self) -> f64 {
        self.stats.hits as f64 / self.stats.primary_rays.max(1) as f64
    }

    /// Voxels entered per packet of primary rays.
    pub fn voxels_per_packet(&self) -> f64 {
        self.stats.voxels_visited as f64
            / (self.stats.primary_rays as f64 / self.isa.lanes() as f64)
    }

    /// The one line `dray render` prints.
    pub fn text(&self) -> String {
        let s = &self.stats;
        format!(
            "{}x{}{} on {} thread(s), {} packets of {} rays{}: {:.2} Mrays/s best, {:.2} median ({} rays{}), {:.1} % hit, {:.2} voxels entered per {} primary rays; loaded {} voxels ({} MiB) in {:.2} s",
            self.width,
            self.height,
            if self.samples > 1 {
                format!(" x {} samples", self.samples)
            } else {
                String::new()
            },
            self.threads,
            self.isa.name(),
            self.isa.lanes(),
            if self.isa == Isa::Avx512 {
                format!(" (32 in {} tiles, sparse in {})", s.wide_tiles, s.sparse_tiles)
            } else {
                String::new()
            },
            self.mrays_best(),
            self.mrays_median(),
            self.rays(),
            if self.secondary {
                format!(", {} shadow and {} reflection rays", s.shadow_rays, s.reflection_rays)
            } else {
                String::new()
            },
            100.0 * self.hit_fraction(),
            self.voxels_per_packet(),
            self.isa.lanes(),
            self.voxels,
            self.resident_bytes >> 20,
            self.load_seconds
        )
    }

    /// The JSON object `dray render --json` prints.
    pub fn to_json(&self) -> Value {
        let s = &self.stats;
        json!({
            "mrays_per_s": self.mrays_best(),
            "mrays_per_s_median": self.mrays_median(),
            "rays": self.rays(),
            "primary_rays": s.primary_rays,
            "shadow_rays": s.shadow_rays,
            "reflection_rays": s.reflection_rays,
            "shadow_mrays_per_s": self.shadow_rate(self.shadow_seconds[0]),
            "shadow_mrays_per_s_median":
                self.shadow_rate(self.shadow_seconds[self.shadow_seconds.len() / 2]),
            "occluded_fraction":
                (s.shadow_rays > 0).then(|| s.occluded as f64 / s.shadow_rays as f64),
            "shadow_packets": s.shadow_packets,
            "occluder_skips": s.occluder_skips,
            "threads": self.threads,
            "width": self.width,
            "height": self.height,
            "samples": self.samples,
            "hit_fraction": self.hit_fraction(),
            "isa": self.isa.name(),
            "lanes": self.isa.lanes(),
            "wide_tiles": s.wide_tiles,
            "sparse_tiles": s.sparse_tiles,
            "seconds": self.seconds,
            "voxels": self.voxels,
            "load_seconds": self.load_seconds,
            "huge_pages_mib": self.huge_pages_bytes.map(|b| b as f64 / 1048576.0),
            "eye": self.camera.eye.to_array(),
            "look": self.camera.look.to_array(),
        })
    }
}

/// A camera path rendered with every voxel resident, each camera
/// `samples` times (samples 0..samples, as a cluster with `render.samples`
/// renders them as frames of their own): the one-process figure the
/// cluster's frame rate is compared with.
#[derive(Clone, Debug, Default)]
pub struct PathReport {
    /// Frames rendered: cameras × samples.
    pub frames: usize,
    /// Samples per camera.
    pub samples: u32,
    pub width: u32,
    pub height: u32,
    pub threads: usize,
    /// Wall-clock seconds of the whole path.
    pub seconds: f64,
    /// Rays of every frame: primary, shadow and reflection.
    pub rays: u64,
    /// Each frame's seconds.
    pub frame_seconds: Vec<f64>,
    /// Per frame, the bytes of the voxels it entered (as a client's cache
    /// counts them); empty unless recorded.
    pub working_set_bytes: Vec<usize>,
    /// Bytes of every voxel, and the seconds it took to load them.
    pub resident_bytes: usize,
    pub load_seconds: f64,
}

/// Renders samples `0..samples` of every camera of a path, everything
/// resident; with `working_set`, records which voxels each frame enters.
/// `Err` is a voxel `source` lacks.
pub fn render_path(
    top: &TopLevel,
    source: &ResidentSource,
    cameras: &[Camera],
    samples: u32,
    settings: &RenderSettings,
    working_set: bool,
) -> Result<PathReport, u32> {
    let samples = samples.max(1);
    // Recording costs a flag test per voxel entered: only when asked.
    let mut recorder = working_set.then(|| RecordingSource::new(source, source.voxel_count()));
    let mut report = PathReport {
        frames: cameras.len() * samples as usize,
        samples,
        width: cameras.first().map_or(0, |c| c.width),
        height: cameras.first().map_or(0, |c| c.height),
        threads: settings.threads,
        resident_bytes: source.bytes(),
        ..PathReport::default()
    };
    let start = std::time::Instant::now();
    for (camera, sample) in cameras
        .iter()
        .flat_map(|c| (0..samples).map(move |k| (c, k)))
    {
        let frame = match &mut recorder {
            Some(r) => {
                let f = render_sample(top, r, camera, sample, settings)?;
                let bytes: usize = r
                    .take()
                    .iter()
                    .filter_map(|&id| source.voxel(id))
                    .map(|v| v.bytes)
                    .sum();
                report.working_set_bytes.push(bytes);
                f
            }
            None => render_sample(top, source, camera, sample, settings)?,
        };
        let s = &frame.stats;
        report.rays += s.primary_rays + s.shadow_rays + s.reflection_rays;
        report.frame_seconds.push(s.seconds);
    }
    report.seconds = start.elapsed().as_secs_f64();
    Ok(report)
}

impl PathReport {
    /// Frames per second over the whole path.
    pub fn fps(&self) -> f64 {
        self.frames as f64 / self.seconds
    }

    /// Millions of rays per second over the whole path.
    pub fn mrays_per_s(&self) -> f64 {
        self.rays as f64 / self.seconds / 1e6
    }

    /// Mean and largest working set in bytes; none unless recorded.
    pub fn working_set(&self) -> Option<(f64, usize)> {
        let max = *self.working_set_bytes.iter().max()?;
        let mean = self.working_set_bytes.iter().sum::<usize>() as f64
            / self.working_set_bytes.len() as f64;
        Some((mean, max))
    }

    /// The lines `dray render --path` prints.
    pub fn text(&self) -> String {
        let mut out = format!(
            "{} frames{} of {}x{} on {} thread(s) in {:.2} s: {:.2} frames/s, {:.2} Mrays/s (loaded in {:.2} s)\n",
            self.frames,
            if self.samples > 1 {
                format!(" ({} cameras x {} samples)", self.frames / self.samples as usize, self.samples)
            } else {
                String::new()
            },
            self.width,
            self.height,
            self.threads,
            self.seconds,
            self.fps(),
            self.mrays_per_s(),
            self.load_seconds
        );
        if let Some((mean, max)) = self.working_set() {
            out.push_str(&format!(
                "working set per frame: mean {:.1} MB, largest {:.1} MB (of {:.1} MB)\n",
                mean / 1e6,
                max as f64 / 1e6,
                self.resident_bytes as f64 / 1e6
            ));
        }
        out
    }

    /// The JSON object `dray render --path --json` prints.
    pub fn to_json(&self) -> Value {
        json!({
            "frames": self.frames,
            "samples": self.samples,
            "seconds": self.seconds,
            "fps": self.fps(),
            "rays": self.rays,
            "mrays_per_s": self.mrays_per_s(),
            "frame_seconds": self.frame_seconds,
            "threads": self.threads,
            "width": self.width,
            "height": self.height,
            "load_seconds": self.load_seconds,
            "working_set_bytes": self.working_set_bytes,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::render::Frame;
    use glam::Vec3;

    fn passes() -> Passes {
        let stats = FrameStats {
            primary_rays: 1000,
            shadow_rays: 500,
            occluded: 100,
            reflection_rays: 500,
            hits: 250,
            voxels_visited: 125,
            ..FrameStats::default()
        };
        Passes {
            frame: Frame {
                width: 40,
                height: 25,
                depth: Vec::new(),
                primid: Vec::new(),
                rgba: Vec::new(),
                stats,
            },
            samples: 1,
            seconds: vec![0.004, 0.001, 0.002],
            shadow_seconds: vec![0.0, 0.002, 0.001],
        }
    }

    fn settings() -> RenderSettings {
        RenderSettings {
            threads: 2,
            isa: Isa::Portable,
            shadows: true,
            ..RenderSettings::primary(1.0)
        }
    }

    fn camera() -> Camera {
        Camera {
            eye: Vec3::new(0.0, 0.0, -5.0),
            look: Vec3::ZERO,
            up: Vec3::Y,
            fov_degrees: 50.0,
            width: 40,
            height: 25,
        }
    }

    #[test]
    fn a_view_reports_its_best_and_median_pass() {
        let r = ViewReport::new(&passes(), &settings(), &camera());
        assert_eq!(r.rays(), 2000);
        assert_eq!(r.seconds, [0.001, 0.002, 0.004]);
        assert!((r.mrays_best() - 2.0).abs() < 1e-9);
        assert!((r.mrays_median() - 1.0).abs() < 1e-9);
        assert!((r.hit_fraction() - 0.25).abs() < 1e-12);
        let j = r.to_json();
        // No shadow time in the fastest pass: no rate rather than infinity.
        assert!(j["shadow_mrays_per_s"].is_null());
        // 500 shadow rays in 0.001 s over 2 threads: 1 M rays per thread-second.
        assert!((j["shadow_mrays_per_s_median"].as_f64().unwrap() - 1.0).abs() < 1e-9);
        assert_eq!(j["occluded_fraction"].as_f64(), Some(0.2));
        assert_eq!(j["eye"], json!([0.0, 0.0, -5.0]));
        let text = r.text();
        assert!(text.starts_with("40x25 on 2 thread(s), portable packets of "));
        assert!(text.contains(", 500 shadow and 500 reflection rays"));
        assert!(text.contains("25.0 % hit"));
        let four = ViewReport::new(
            &Passes {
                samples: 4,
                ..passes()
            },
            &settings(),
            &camera(),
        );
        assert!(four
            .text()
            .starts_with("40x25 x 4 samples on 2 thread(s), "));
        assert_eq!(four.to_json()["samples"], 4);
    }

    #[test]
    fn a_path_reports_its_frame_rate_and_working_sets() {
        let mut r = PathReport {
            frames: 4,
            samples: 1,
            width: 640,
            height: 480,
            threads: 2,
            seconds: 2.0,
            rays: 8_000_000,
            frame_seconds: vec![0.5; 4],
            working_set_bytes: Vec::new(),
            resident_bytes: 10_000_000,
            load_seconds: 0.25,
        };
        assert_eq!(r.fps(), 2.0);
        assert_eq!(r.mrays_per_s(), 4.0);
        assert_eq!(r.working_set(), None);
        assert_eq!(r.text().lines().count(), 1);
        r.working_set_bytes = vec![1_000_000, 3_000_000, 2_000_000, 2_000_000];
        assert_eq!(r.working_set(), Some((2_000_000.0, 3_000_000)));
        assert!(r
            .text()
            .ends_with("working set per frame: mean 2.0 MB, largest 3.0 MB (of 10.0 MB)\n"));
        let j = r.to_json();
        assert_eq!(j["fps"].as_f64(), Some(2.0));
        assert_eq!(
            j["working_set_bytes"],
            json!([1_000_000, 3_000_000, 2_000_000, 2_000_000])
        );
        r.samples = 2;
        assert!(r
            .text()
            .starts_with("4 frames (2 cameras x 2 samples) of 640x480 "));
    }
}
