//! The web viewer's rates, measured in headless Chromium (Debian's
//! `chromium` and `chromium-driver`):
//!
//! - **displayed / cluster**: while a key is held (the camera flying), the
//!   frames the page drew against the frames the cluster rendered, over
//!   the same seconds;
//! - **key to pixels**: from standing still (refined), the time from a key
//!   press to the first frame of the moved camera on the canvas, against
//!   the cluster's frame time; and to that frame's message arriving at
//!   the page (the rest is the browser decoding and drawing it).
//!
//!     cargo run --release --example bench_viewer [-- TRIANGLES CLIENTS SECONDS]
//!
//! Defaults: a 300 000-triangle plant, 2 clients × 1 thread, 5 s of flying,
//! at 640×480 and 1280×720. Prints a Markdown table.

use dray_testkit::browser::{Browser, Viewer};
use serde_json::Value;
use std::path::PathBuf;
use std::time::{Duration, Instant};

const WAIT: Duration = Duration::from_secs(120);
const PRESSES: usize = 15;

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or(f64::NAN)
}

fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    if v.is_empty() {
        f64::NAN
    } else {
        v[v.len() / 2]
    }
}

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let triangles: u64 = args
        .first()
        .map_or(300_000, |a| a.parse().expect("TRIANGLES"));
    let clients: u32 = args.get(1).map_or(2, |a| a.parse().expect("CLIENTS"));
    let seconds: f64 = args.get(2).map_or(5.0, |a| a.parse().expect("SECONDS"));
    let dray = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("target/release/dray");
    assert!(dray.exists(), "build dray first: cargo build --release");
    eprintln!("making a {triangles}-triangle plant");
    let plant = dray_testkit::plant_db(triangles, 1, 4096);
    let Some(browser) = Browser::start(1400, 900).await else {
        panic!("no chromium or chromedriver (Debian: chromium chromium-driver)");
    };
    println!(
        "| size | cluster fps | displayed fps | displayed / cluster | frame ms | key to arrival ms | key to pixels ms (median of {PRESSES}) | minus frame time |"
    );
    println!("|---|---:|---:|---:|---:|---:|---:|---:|");
    for (w, h) in [(640u32, 480u32), (1280, 720)] {
        let web = format!("127.0.0.1:{}", dray_testkit::browser::free_tcp_port());
        let args = dray_testkit::browser::view_args(&plant.path, clients, &web, (w, h));
        let viewer = Viewer::start(&dray, &args, WAIT);
        let b = &browser;
        b.client.goto(&viewer.url).await.expect("the page loads");
        b.wait_for(
            "refined",
            "return dray.still === true",
            "return dray.drawn",
            WAIT,
        )
        .await;

        // Flying: frames drawn against frames rendered, and frame times.
        let start = b.eval("return [dray.drawn, dray.frame]").await;
        let t0 = Instant::now();
        let hold = b.hold_key('w', (seconds * 1000.0) as u64);
        let sample = async {
            let mut ms = Vec::new();
            while t0.elapsed().as_secs_f64() < seconds * 0.95 {
                tokio::time::sleep(Duration::from_millis(200)).await;
                let m = b.eval("return dray.still ? null : dray.clusterFps").await;
                if let Some(fps) = m.as_f64().filter(|f| *f > 0.0) {
                    ms.push(1e3 / fps);
                }
            }
            ms
        };
        let ((), frame_ms) = tokio::join!(hold, sample);
        let end = b.eval("return [dray.drawn, dray.frame]").await;
        let secs = t0.elapsed().as_secs_f64();
        let drawn = num(&end[0]) - num(&start[0]);
        let rendered = num(&end[1]) - num(&start[1]);
        let frame_ms = median(frame_ms);

        // Key to pixels, from a refined view each time.
        let mut latencies = Vec::new();
        let mut arrivals = Vec::new();
        for _ in 0..PRESSES {
            b.wait_for(
                "refined",
                "return dray.still === true",
                "return dray.drawn",
                WAIT,
            )
            .await;
            tokio::time::sleep(Duration::from_millis(300)).await;
            let before = b.eval("return dray.latencies.length").await;
            b.hold_key('d', 60).await;
            let n = num(&before) as usize;
            b.wait_for(
                "a moved frame",
                &format!("return dray.latencies.length > {n}"),
                "return dray.drawn",
                WAIT,
            )
            .await;
            latencies.push(num(&b.eval(&format!("return dray.latencies[{n}]")).await));
            arrivals.push(num(&b.eval(&format!("return dray.arrivals[{n}]")).await));
        }
        let latency = median(latencies);
        println!(
            "| {w}×{h} | {:.1} | {:.1} | {:.2} | {:.1} | {:.1} | {:.1} | {:+.1} |",
            rendered / secs,
            drawn / secs,
            drawn / rendered.max(1.0),
            frame_ms,
            median(arrivals),
            latency,
            latency - frame_ms
        );
        drop(viewer);
    }
    browser.close().await;
}
