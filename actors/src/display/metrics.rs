//! Per-frame metrics, the `metrics.csv` file and the run's summary.

use super::FrameImage;
use dray_protocol::{FrameStats, LinkBytes};
use serde::Serialize;
use std::fs::File;
use std::io::{self, Write};
use std::path::{Path, PathBuf};

/// The figures of one displayed frame.
#[derive(Clone, Debug, Serialize)]
pub struct FrameMetrics {
    /// Frame number.
    pub frame: u64,
    /// Time since the previous frame was shown (the first frame: since the
    /// first camera was sent), milliseconds.
    pub frame_ms: f64,
    /// `1000 / frame_ms` (a frame time under 1 µs counts as 1 µs).
    pub fps: f64,
    /// Rays traced for the frame.
    pub rays: u64,
    /// Rays per frame time, millions per second.
    pub mrays_per_s: f64,
    /// Tiles in the frame.
    pub tiles: u32,
    /// Tiles reassigned (a client lost or too slow).
    pub reassigned: u32,
    /// Voxel bytes fetched, compressed.
    pub bytes_fetched: u64,
    /// The same voxels' bytes after decompression.
    pub bytes_raw: u64,
    /// Voxel cache misses.
    pub misses: u64,
    /// Voxels entered, summed over tiles.
    pub voxels_touched: u64,
    /// `1 - misses / voxels_touched` (1 when none was touched).
    pub cache_hit_rate: f64,
    /// Tiles' stall time waiting for voxels, summed, milliseconds.
    pub stall_ms: f64,
    /// Bytes the links between clients and stores carried for the frame.
    pub link_client_store: u64,
    /// Bytes between clients and the scheduler or the display.
    pub link_client_scheduler: u64,
    /// Bytes between the display and the scheduler.
    pub link_display: u64,
    /// Bytes from stores into clients (the stores' uplinks).
    pub link_store_uplink: u64,
    /// Bytes into clients from any node (the clients' downlinks).
    pub link_client_downlink: u64,
    /// Tiles per client, e.g. `client-0:150 client-1:150`.
    pub tiles_per_client: String,
}

/// The CSV columns, in order.
pub const CSV_HEADER: &str = "frame,frame_ms,fps,rays,mrays_per_s,tiles,reassigned,bytes_fetched,bytes_raw,misses,voxels_touched,cache_hit_rate,stall_ms,link_client_store,link_client_scheduler,link_display,link_store_uplink,link_client_downlink,tiles_per_client";

impl FrameMetrics {
    /// The metrics of `frame` with `stats`, shown `frame_ms` after the
    /// previous one.
    pub fn compute(frame: u64, stats: &FrameStats, frame_ms: f64) -> FrameMetrics {
        let frame_ms = frame_ms.max(0.0);
        let ms = frame_ms.max(1e-3);
        let cache_hit_rate = if stats.voxels_touched == 0 {
            1.0
        } else {
            (1.0 - stats.misses as f64 / stats.voxels_touched as f64).clamp(0.0, 1.0)
        };
        let tiles_per_client = stats
            .clients
            .as_slice()
            .iter()
            .map(|c| format!("{}:{}", c.node, c.tiles))
            .collect::<Vec<_>>()
            .join(" ");
        FrameMetrics {
            frame,
            frame_ms,
            fps: 1000.0 / ms,
            rays: stats.rays,
            mrays_per_s: stats.rays as f64 / (ms * 1e3),
            tiles: stats.tiles,
            reassigned: stats.reassigned,
            bytes_fetched: stats.bytes_fetched,
            bytes_raw: stats.bytes_raw,
            misses: stats.misses,
            voxels_touched: stats.voxels_touched,
            cache_hit_rate,
            stall_ms: stats.stall_us as f64 / 1e3,
            link_client_store: stats.link.client_store,
            link_client_scheduler: stats.link.client_scheduler,
            link_display: stats.link.display,
            link_store_uplink: stats.link.store_uplink,
            link_client_downlink: stats.link.client_downlink,
            tiles_per_client,
        }
    }

    /// The bytes each link class carried for the frame.
    pub fn link(&self) -> LinkBytes {
        LinkBytes {
            client_store: self.link_client_store,
            client_scheduler: self.link_client_scheduler,
            display: self.link_display,
            store_uplink: self.link_store_uplink,
            client_downlink: self.link_client_downlink,
        }
    }

    /// One CSV row (no newline), columns as [`CSV_HEADER`].
    pub fn csv_row(&self) -> String {
        format!(
            "{},{:.3},{:.3},{},{:.3},{},{},{},{},{},{},{:.6},{:.3},{},{},{},{},{},{}",
            self.frame,
            self.frame_ms,
            self.fps,
            self.rays,
            self.mrays_per_s,
            self.tiles,
            self.reassigned,
            self.bytes_fetched,
            self.bytes_raw,
            self.misses,
            self.voxels_touched,
            self.cache_hit_rate,
            self.stall_ms,
            self.link_client_store,
            self.link_client_scheduler,
            self.link_display,
            self.link_store_uplink,
            self.link_client_downlink,
            csv_field(&self.tiles_per_client)
        )
    }
}

fn csv_field(s: &str) -> String {
    if s.contains([',', '"', '\n', '\r']) {
        format!("\"{}\"", s.replace('"', "\"\""))
    } else {
        s.to_string()
    }
}

/// `metrics.csv`: the header when created, then one row per frame, each
/// flushed, so a run that is killed keeps the rows written so far.
pub(crate) struct CsvLog {
    path: PathBuf,
    file: File,
}

impl CsvLog {
    pub fn create(path: &Path) -> io::Result<CsvLog> {
        let mut file = File::create(path)?;
        writeln!(file, "{CSV_HEADER}")?;
        file.flush()?;
        Ok(CsvLog {
            path: path.to_path_buf(),
            file,
        })
    }

    pub fn path(&self) -> &Path {
        &self.path
    }

    pub fn append(&mut self, m: &FrameMetrics) -> io::Result<()> {
        // One write per row: a killed run never leaves half a row behind
        // a complete one.
        let line = format!("{}\n", m.csv_row());
        self.file.write_all(line.as_bytes())?;
        self.file.flush()
    }
}

/// What a display run showed.
#[derive(Clone, Debug)]
pub struct DisplaySummary {
    /// Per frame, in order (only when `keep_metrics`; otherwise empty, and
    /// only `metrics.csv` has them, when there is an output).
    pub frames: Vec<FrameMetrics>,
    /// Frames shown.
    pub frames_shown: usize,
    /// The images (only when `keep_frames`).
    pub images: Vec<FrameImage>,
    /// Image width.
    pub width: u32,
    /// Image height.
    pub height: u32,
    /// Frames asked for (cameras in the options).
    pub frames_requested: usize,
    /// Whether every frame asked for was shown (false after a Shutdown).
    pub complete: bool,
    /// Why the run stopped early, if it did.
    pub stopped_early: Option<String>,
    /// From the first camera sent to the last frame shown, seconds.
    pub seconds: f64,
    /// Frames shown per second over `seconds`.
    pub mean_fps: f64,
    /// Mean frame time, milliseconds.
    pub mean_frame_ms: f64,
    /// Longest frame time, milliseconds.
    pub max_frame_ms: f64,
    /// Rays traced in all.
    pub total_rays: u64,
    /// Rays per second over the run, millions.
    pub mrays_per_s: f64,
    /// Voxel bytes fetched in all.
    pub total_bytes_fetched: u64,
    /// The same voxels' bytes after decompression.
    pub total_bytes_raw: u64,
    /// Cache misses in all.
    pub total_misses: u64,
    /// Voxels touched in all.
    pub total_voxels_touched: u64,
    /// Over the run, `1 - misses / voxels_touched`.
    pub cache_hit_rate: f64,
    /// Tiles reassigned in all.
    pub total_reassigned: u64,
    /// Stall time summed over tiles, milliseconds.
    pub total_stall_ms: f64,
    /// Frame times summed, milliseconds.
    total_frame_ms: f64,
    /// Tiles ignored (unknown frame, outside the image, bad sizes).
    pub tiles_ignored: u64,
    /// Tiles that brought no new pixel (reassignment duplicates).
    pub duplicate_tiles: u64,
    /// Pixels that never arrived in frames shown anyway (a lost tile).
    pub missing_pixels: u64,
    /// Bytes each link class carried, summed over the frames.
    pub total_link: LinkBytes,
    /// Voxels no store served intact, rendered as empty
    /// (`clients.corrupt_voxel = "skip"`).
    pub voxels_missing: std::collections::BTreeSet<u32>,
}

impl DisplaySummary {
    pub(crate) fn new(width: u32, height: u32, frames_requested: usize) -> DisplaySummary {
        DisplaySummary {
            frames: Vec::new(),
            frames_shown: 0,
            images: Vec::new(),
            width,
            height,
            frames_requested,
            complete: frames_requested == 0,
            stopped_early: None,
            seconds: 0.0,
            mean_fps: 0.0,
            mean_frame_ms: 0.0,
            max_frame_ms: 0.0,
            total_rays: 0,
            mrays_per_s: 0.0,
            total_bytes_fetched: 0,
            total_bytes_raw: 0,
            total_misses: 0,
            total_voxels_touched: 0,
            cache_hit_rate: 1.0,
            total_reassigned: 0,
            total_stall_ms: 0.0,
            total_frame_ms: 0.0,
            tiles_ignored: 0,
            duplicate_tiles: 0,
            missing_pixels: 0,
            total_link: LinkBytes::default(),
            voxels_missing: Default::default(),
        }
    }

    /// Counts voxel `id` as rendered empty; whether it is new.
    pub(crate) fn voxel_missing(&mut self, id: u32) -> bool {
        self.voxels_missing.insert(id)
    }

    /// Adds a shown frame's metrics to the run's figures, and keeps them
    /// if `keep`: a run that goes on for hours keeps only its sums.
    pub(crate) fn push(&mut self, m: FrameMetrics, keep: bool) {
        // The figures come from a peer (the scheduler): saturating sums.
        self.total_rays = self.total_rays.saturating_add(m.rays);
        self.total_bytes_fetched = self.total_bytes_fetched.saturating_add(m.bytes_fetched);
        self.total_bytes_raw = self.total_bytes_raw.saturating_add(m.bytes_raw);
        self.total_misses = self.total_misses.saturating_add(m.misses);
        self.total_voxels_touched = self.total_voxels_touched.saturating_add(m.voxels_touched);
        self.total_reassigned = self
            .total_reassigned
            .saturating_add(u64::from(m.reassigned));
        self.total_stall_ms += m.stall_ms;
        self.total_link = self.total_link.saturating_add(m.link());
        self.max_frame_ms = self.max_frame_ms.max(m.frame_ms);
        self.total_frame_ms += m.frame_ms;
        self.frames_shown += 1;
        if keep {
            self.frames.push(m);
        }
    }

    /// Fills the run-wide figures; `seconds` from the first camera to the
    /// last frame shown.
    pub(crate) fn finish(&mut self, seconds: f64) {
        let n = self.frames_shown;
        self.seconds = seconds;
        if n > 0 {
            self.mean_frame_ms = self.total_frame_ms / n as f64;
        }
        if seconds > 0.0 {
            self.mean_fps = n as f64 / seconds;
            self.mrays_per_s = self.total_rays as f64 / seconds / 1e6;
        }
        self.cache_hit_rate = if self.total_voxels_touched == 0 {
            1.0
        } else {
            (1.0 - self.total_misses as f64 / self.total_voxels_touched as f64).clamp(0.0, 1.0)
        };
    }

    /// A few lines for people.
    pub fn print_text(&self) -> String {
        let mut s = format!(
            "{} of {} frames of {}x{} in {:.2} s: {:.2} fps (frame time mean {:.1} ms, max {:.1} ms)\n",
            self.frames_shown,
            self.frames_requested,
            self.width,
            self.height,
            self.seconds,
            self.mean_fps,
            self.mean_frame_ms,
            self.max_frame_ms
        );
        s += &format!(
            "rays {} ({:.2} Mrays/s), voxels fetched {} ({} decompressed, {} misses, cache hit rate {:.1} %), stall {:.1} ms, tiles reassigned {}\n",
            self.total_rays,
            self.mrays_per_s,
            human_bytes(self.total_bytes_fetched),
            human_bytes(self.total_bytes_raw),
            self.total_misses,
            self.cache_hit_rate * 100.0,
            self.total_stall_ms,
            self.total_reassigned
        );
        let l = &self.total_link;
        s += &format!(
            "links carried: client-store {}, client-scheduler/display {}, display-scheduler {}\n",
            human_bytes(l.client_store),
            human_bytes(l.client_scheduler),
            human_bytes(l.display)
        );
        if self.tiles_ignored > 0 || self.missing_pixels > 0 {
            s += &format!(
                "tiles ignored {}, pixels missing {}\n",
                self.tiles_ignored, self.missing_pixels
            );
        }
        if !self.voxels_missing.is_empty() {
            let ids: Vec<String> = self.voxels_missing.iter().map(u32::to_string).collect();
            s += &format!(
                "voxels missing (no store served them intact; rendered as empty): {} (ids {})\n",
                self.voxels_missing.len(),
                ids.join(", ")
            );
        }
        if let Some(why) = &self.stopped_early {
            s += &format!("stopped early: {why}\n");
        }
        s
    }

    /// The summary (without images) as JSON, with `print_text` as
    /// `text`.
    pub fn to_json(&self) -> serde_json::Value {
        serde_json::json!({
            "text": self.print_text(),
            "width": self.width,
            "height": self.height,
            "frames_requested": self.frames_requested,
            "frames_shown": self.frames_shown,
            "complete": self.complete,
            "stopped_early": self.stopped_early,
            "seconds": finite(self.seconds),
            "mean_fps": finite(self.mean_fps),
            "mean_frame_ms": finite(self.mean_frame_ms),
            "max_frame_ms": finite(self.max_frame_ms),
            "total_rays": self.total_rays,
            "mrays_per_s": finite(self.mrays_per_s),
            "total_bytes_fetched": self.total_bytes_fetched,
            "total_bytes_raw": self.total_bytes_raw,
            "total_misses": self.total_misses,
            "total_voxels_touched": self.total_voxels_touched,
            "cache_hit_rate": finite(self.cache_hit_rate),
            "total_reassigned": self.total_reassigned,
            "total_stall_ms": finite(self.total_stall_ms),
            "tiles_ignored": self.tiles_ignored,
            "duplicate_tiles": self.duplicate_tiles,
            "missing_pixels": self.missing_pixels,
            "total_link": self.total_link,
            "voxels_missing": self.voxels_missing,
            "frames": self.frames,
        })
    }
}

fn finite(x: f64) -> f64 {
    if x.is_finite() {
        x
    } else {
        0.0
    }
}

fn human_bytes(b: u64) -> String {
    const UNITS: [&str; 5] = ["B", "KiB", "MiB", "GiB", "TiB"];
    let mut v = b as f64;
    let mut u = 0;
    while v >= 1024.0 && u + 1 < UNITS.len() {
        v /= 1024.0;
        u += 1;
    }
    if u == 0 {
        format!("{b} B")
    } else {
        format!("{v:.1} {}", UNITS[u])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn metrics_from_stats() {
        let stats = FrameStats {
            tiles: 4,
            rays: 2_000_000,
            misses: 5,
            voxels_touched: 20,
            stall_us: 1500,
            bytes_fetched: 1000,
            bytes_raw: 3000,
            ..FrameStats::default()
        };
        let m = FrameMetrics::compute(3, &stats, 100.0);
        assert_eq!((m.bytes_fetched, m.bytes_raw), (1000, 3000));
        assert_eq!(m.fps, 10.0);
        assert_eq!(m.mrays_per_s, 20.0);
        assert_eq!(m.cache_hit_rate, 0.75);
        assert_eq!(m.stall_ms, 1.5);
        assert_eq!(
            m.csv_row().split(',').count(),
            CSV_HEADER.split(',').count()
        );
        let none = FrameMetrics::compute(0, &FrameStats::default(), 0.0);
        assert_eq!(none.cache_hit_rate, 1.0);
        assert!(none.fps.is_finite());
    }

    #[test]
    fn a_summary_without_rows_has_the_same_figures() {
        let stats = FrameStats {
            tiles: 2,
            rays: 1000,
            misses: 1,
            voxels_touched: 4,
            ..FrameStats::default()
        };
        let mut kept = DisplaySummary::new(8, 8, 3);
        let mut sums = DisplaySummary::new(8, 8, 3);
        for (frame, ms) in [(0, 10.0), (1, 30.0), (2, 20.0)] {
            kept.push(FrameMetrics::compute(frame, &stats, ms), true);
            sums.push(FrameMetrics::compute(frame, &stats, ms), false);
        }
        kept.finish(0.06);
        sums.finish(0.06);
        assert_eq!((kept.frames.len(), sums.frames.len()), (3, 0));
        assert_eq!((kept.frames_shown, sums.frames_shown), (3, 3));
        assert_eq!(kept.mean_frame_ms, 20.0);
        assert_eq!(kept.print_text(), sums.print_text());
        assert_eq!(sums.to_json()["frames_shown"], 3);
        assert_eq!(sums.to_json()["mean_frame_ms"], 20.0);
    }
}
