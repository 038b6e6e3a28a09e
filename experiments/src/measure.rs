//! What a run measured: the columns of `points.csv`, computed from the
//! display's per-frame metrics (the same figures as its `metrics.csv`),
//! and the per-frame columns of `frames.csv` that plots can draw.

use serde::Deserialize;

/// The figures of one shown frame that the measures use (a subset of the
/// display's `FrameMetrics`, read from its summary).
#[derive(Clone, Debug, Deserialize)]
pub(crate) struct Frame {
    pub frame_ms: f64,
    pub rays: u64,
    pub stall_ms: f64,
    pub bytes_fetched: u64,
    pub bytes_raw: u64,
    pub misses: u64,
    pub voxels_touched: u64,
    pub reassigned: u32,
    pub link_client_store: u64,
    pub link_client_scheduler: u64,
    pub link_display: u64,
    pub link_store_uplink: u64,
    pub link_client_downlink: u64,
}

/// One run's figures, from which each measure is computed.
pub(crate) struct RunFigures<'a> {
    /// The measured frames: all, or with a warm walk the last loop's.
    pub measured: &'a [Frame],
    /// Wall time of the run, start-up included, seconds.
    pub wall_s: f64,
}

impl RunFigures<'_> {
    fn frame_ms(&self) -> Vec<f64> {
        let mut ms: Vec<f64> = self.measured.iter().map(|f| f.frame_ms).collect();
        ms.sort_by(f64::total_cmp);
        ms
    }

    fn seconds(&self) -> f64 {
        self.measured.iter().map(|f| f.frame_ms).sum::<f64>() / 1e3
    }

    fn sum(&self, of: impl Fn(&Frame) -> f64) -> f64 {
        self.measured.iter().map(of).sum()
    }
}

/// A measured column: its name in `points.csv`, unit, meaning, and how it
/// is computed.
pub struct Measure {
    /// The column's name.
    pub name: &'static str,
    /// Its unit, for axis labels.
    pub unit: &'static str,
    /// What it is, for the documentation and the summary.
    pub meaning: &'static str,
    value: fn(&RunFigures) -> Option<f64>,
}

impl Measure {
    pub(crate) fn of(&self, run: &RunFigures) -> Option<f64> {
        (self.value)(run).filter(|v| v.is_finite())
    }
}

/// The measured columns of `points.csv`, in order.
pub const MEASURES: &[Measure] = &[
    Measure {
        name: "fps",
        unit: "frames/s",
        meaning: "measured frames / their wall time (the sum of their frame times)",
        value: |r| Some(r.measured.len() as f64 / r.seconds()),
    },
    Measure {
        name: "frame_ms_p50",
        unit: "ms",
        meaning: "median frame time of the measured frames",
        value: |r| percentile(&r.frame_ms(), 0.5),
    },
    Measure {
        name: "frame_ms_p95",
        unit: "ms",
        meaning: "95th percentile frame time (nearest rank)",
        value: |r| percentile(&r.frame_ms(), 0.95),
    },
    Measure {
        name: "frame_ms_max",
        unit: "ms",
        meaning: "longest frame time",
        value: |r| r.frame_ms().last().copied(),
    },
    Measure {
        name: "mrays_per_s",
        unit: "Mrays/s",
        meaning: "rays traced (primary, shadow, reflection) / wall time, millions",
        value: |r| Some(r.sum(|f| f.rays as f64) / r.seconds() / 1e6),
    },
    Measure {
        name: "stall_ms",
        unit: "ms",
        meaning: "tiles' time waiting for voxels, summed over tiles and frames",
        value: |r| Some(r.sum(|f| f.stall_ms)),
    },
    Measure {
        name: "voxel_mb",
        unit: "MB",
        meaning: "voxel data fetched, compressed, 10^6 bytes (prefetches included)",
        value: |r| Some(r.sum(|f| f.bytes_fetched as f64) / 1e6),
    },
    Measure {
        name: "voxel_mb_raw",
        unit: "MB",
        meaning: "the same voxels after decompression, 10^6 bytes (the paper's Figure 3 measure)",
        value: |r| Some(r.sum(|f| f.bytes_raw as f64) / 1e6),
    },
    Measure {
        name: "link_mb_client_store",
        unit: "MB",
        meaning: "bytes the client-store links carried, both ways, 10^6 bytes (`[links.client_store]`)",
        value: |r| Some(r.sum(|f| f.link_client_store as f64) / 1e6),
    },
    Measure {
        name: "link_mb_client_scheduler",
        unit: "MB",
        meaning: "bytes between clients and the scheduler or the display, both ways (`[links.client_scheduler]`: tiles, pixels)",
        value: |r| Some(r.sum(|f| f.link_client_scheduler as f64) / 1e6),
    },
    Measure {
        name: "link_mb_display",
        unit: "MB",
        meaning: "bytes between the display and the scheduler, both ways (`[links.display]`)",
        value: |r| Some(r.sum(|f| f.link_display as f64) / 1e6),
    },
    Measure {
        name: "link_mb_store_uplink",
        unit: "MB",
        meaning: "bytes from the stores into the clients, what crossed the stores' uplinks (`[links.store_uplink]`)",
        value: |r| Some(r.sum(|f| f.link_store_uplink as f64) / 1e6),
    },
    Measure {
        name: "link_mb_client_downlink",
        unit: "MB",
        meaning: "bytes into the clients from any node, what crossed the clients' downlinks (`[links.client_downlink]`)",
        value: |r| Some(r.sum(|f| f.link_client_downlink as f64) / 1e6),
    },
    Measure {
        name: "cache_hit_rate",
        unit: "fraction",
        meaning: "1 - misses / voxels entered, over the measured frames (1 when none was entered)",
        value: |r| {
            let touched = r.sum(|f| f.voxels_touched as f64);
            Some(if touched == 0.0 {
                1.0
            } else {
                (1.0 - r.sum(|f| f.misses as f64) / touched).clamp(0.0, 1.0)
            })
        },
    },
    Measure {
        name: "tiles_reassigned",
        unit: "tiles",
        meaning: "tiles given to a second client (the first was lost or too slow)",
        value: |r| Some(r.sum(|f| f64::from(f.reassigned))),
    },
    Measure {
        name: "wall_s",
        unit: "s",
        meaning: "wall time of the whole run, start-up and every loop included",
        value: |r| Some(r.wall_s),
    },
];

/// The measure called `name`.
pub fn measure(name: &str) -> Option<&'static Measure> {
    MEASURES.iter().find(|m| m.name == name)
}

/// A column of `frames.csv` that a plot over the frames can draw: its
/// name and unit.
pub struct FrameColumn {
    /// The column's name.
    pub name: &'static str,
    /// Its unit, for axis labels.
    pub unit: &'static str,
}

/// The x of a plot over the frames: `frames.csv`'s frame number.
pub const FRAME: &str = "frame";

/// The numeric columns of `frames.csv`: the display's (`metrics.csv`),
/// then those the runner derives from them (`DERIVED`).
pub const FRAME_COLUMNS: &[FrameColumn] = &[
    FrameColumn {
        name: "frame_ms",
        unit: "ms",
    },
    FrameColumn {
        name: "fps",
        unit: "frames/s",
    },
    FrameColumn {
        name: "rays",
        unit: "rays",
    },
    FrameColumn {
        name: "mrays_per_s",
        unit: "Mrays/s",
    },
    FrameColumn {
        name: "tiles",
        unit: "tiles",
    },
    FrameColumn {
        name: "reassigned",
        unit: "tiles",
    },
    FrameColumn {
        name: "bytes_fetched",
        unit: "bytes",
    },
    FrameColumn {
        name: "bytes_raw",
        unit: "bytes",
    },
    FrameColumn {
        name: "misses",
        unit: "misses",
    },
    FrameColumn {
        name: "voxels_touched",
        unit: "voxels",
    },
    FrameColumn {
        name: "cache_hit_rate",
        unit: "fraction",
    },
    FrameColumn {
        name: "stall_ms",
        unit: "ms",
    },
    FrameColumn {
        name: "link_client_store",
        unit: "bytes",
    },
    FrameColumn {
        name: "link_client_scheduler",
        unit: "bytes",
    },
    FrameColumn {
        name: "link_display",
        unit: "bytes",
    },
    FrameColumn {
        name: "link_store_uplink",
        unit: "bytes",
    },
    FrameColumn {
        name: "link_client_downlink",
        unit: "bytes",
    },
    FrameColumn {
        name: "frame_ms_window",
        unit: "ms",
    },
    FrameColumn {
        name: "fps_window",
        unit: "frames/s",
    },
    FrameColumn {
        name: "voxel_mb_per_s",
        unit: "MB/s",
    },
    FrameColumn {
        name: "voxel_mb_raw_per_s",
        unit: "MB/s",
    },
];

/// The columns the runner derives per frame and adds to `frames.csv`, in
/// the order of [`derived`]'s values.
pub(crate) const DERIVED: [&str; 4] = [
    "frame_ms_window",
    "fps_window",
    "voxel_mb_per_s",
    "voxel_mb_raw_per_s",
];

/// Frames each derived rate is taken over, centred on its frame: frames
/// are pipelined, so several are often shown within a millisecond of each
/// other and a single frame's time says little about the rate.
pub(crate) const WINDOW: usize = 5;

/// Per frame of a run, the [`DERIVED`] columns over the [`WINDOW`] frames
/// around it (fewer at the ends): their mean frame time, 1000 over it, and
/// their voxel MB (10^6 bytes) over their time, compressed and after
/// decompression.
pub(crate) fn derived(frames: &[Frame]) -> Vec<[f64; 4]> {
    let half = WINDOW / 2;
    (0..frames.len())
        .map(|i| {
            let around = &frames[i.saturating_sub(half)..(i + half + 1).min(frames.len())];
            let ms = around.iter().map(|f| f.frame_ms).sum::<f64>().max(1e-3);
            let mb = |bytes: fn(&Frame) -> u64| {
                around.iter().map(|f| bytes(f) as f64).sum::<f64>() / 1e6
            };
            [
                ms / around.len() as f64,
                1e3 * around.len() as f64 / ms,
                mb(|f| f.bytes_fetched) / (ms / 1e3),
                mb(|f| f.bytes_raw) / (ms / 1e3),
            ]
        })
        .collect()
}

/// The `frames.csv` column called `name`.
pub fn frame_column(name: &str) -> Option<&'static FrameColumn> {
    FRAME_COLUMNS.iter().find(|c| c.name == name)
}

/// Nearest-rank percentile of sorted values.
fn percentile(sorted: &[f64], q: f64) -> Option<f64> {
    if sorted.is_empty() {
        return None;
    }
    let rank = (q * sorted.len() as f64).ceil() as usize;
    Some(sorted[rank.clamp(1, sorted.len()) - 1])
}

/// A measured value as a CSV cell: empty when unknown, else at most six
/// decimals without trailing zeros.
pub(crate) fn format_value(v: Option<f64>) -> String {
    match v {
        None => String::new(),
        Some(v) => {
            let s = format!("{v:.6}");
            let s = s.trim_end_matches('0').trim_end_matches('.');
            if s == "-0" {
                "0".into()
            } else {
                s.to_string()
            }
        }
    }
}

/// The median, smallest and largest of some values (None when empty).
pub(crate) fn spread(values: &[f64]) -> Option<(f64, f64, f64)> {
    let mut v: Vec<f64> = values.iter().copied().filter(|x| x.is_finite()).collect();
    if v.is_empty() {
        return None;
    }
    v.sort_by(f64::total_cmp);
    let n = v.len();
    let median = if n % 2 == 1 {
        v[n / 2]
    } else {
        (v[n / 2 - 1] + v[n / 2]) / 2.0
    };
    Some((median, v[0], v[n - 1]))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn frame(ms: f64) -> Frame {
        Frame {
            frame_ms: ms,
            rays: 1_000_000,
            stall_ms: 1.0,
            bytes_fetched: 500_000,
            bytes_raw: 750_000,
            misses: 1,
            voxels_touched: 4,
            reassigned: 0,
            link_client_store: 520_000,
            link_client_scheduler: 90_000,
            link_display: 2_000,
            link_store_uplink: 510_000,
            link_client_downlink: 530_000,
        }
    }

    #[test]
    fn measures_of_a_run() {
        let frames: Vec<Frame> = [100.0, 200.0, 300.0, 400.0].map(frame).to_vec();
        let run = RunFigures {
            measured: &frames,
            wall_s: 2.5,
        };
        let v = |name: &str| measure(name).unwrap().of(&run);
        assert_eq!(v("fps"), Some(4.0));
        assert_eq!(v("frame_ms_p50"), Some(200.0));
        assert_eq!(v("frame_ms_p95"), Some(400.0));
        assert_eq!(v("frame_ms_max"), Some(400.0));
        assert_eq!(v("mrays_per_s"), Some(4.0));
        assert_eq!(v("stall_ms"), Some(4.0));
        assert_eq!(v("voxel_mb"), Some(2.0));
        assert_eq!(v("voxel_mb_raw"), Some(3.0));
        assert_eq!(v("link_mb_client_store"), Some(2.08));
        assert_eq!(v("link_mb_display"), Some(0.008));
        assert_eq!(v("link_mb_client_downlink"), Some(2.12));
        assert_eq!(v("cache_hit_rate"), Some(0.75));
        assert_eq!(v("wall_s"), Some(2.5));
        // The last loop of a warm walk: its frames only.
        let warm = RunFigures {
            measured: &frames[2..],
            ..run
        };
        assert_eq!(measure("voxel_mb_raw").unwrap().of(&warm), Some(1.5));
        assert_eq!(derived(&frames[..1]), [[100.0, 10.0, 5.0, 7.5]]);
        // A frame shown with the one before: the window's mean time.
        let together = [frame(300.0), frame(0.0), frame(100.0)];
        let window: Vec<f64> = derived(&together).iter().map(|c| c[1]).collect();
        assert_eq!(window, [7.5, 7.5, 7.5]);
        assert_eq!(format_value(Some(0.5)), "0.5");
        assert_eq!(format_value(Some(12.0)), "12");
        assert_eq!(format_value(None), "");
        assert_eq!(spread(&[3.0, 1.0, 2.0, 10.0]), Some((2.5, 1.0, 10.0)));
    }

    #[test]
    fn every_frames_column_has_a_unit() {
        let display = dray_actors::display::CSV_HEADER
            .split(',')
            .filter(|c| *c != FRAME && *c != "tiles_per_client");
        let columns: Vec<&str> = display.chain(DERIVED).collect();
        let with_units: Vec<&str> = FRAME_COLUMNS.iter().map(|c| c.name).collect();
        assert_eq!(columns, with_units);
    }
}
