//! The README's picture of the viewer (`docs/images/viewer.png`), taken as
//! the viewer's test takes its own: `dray view` on a 300 000-triangle plant
//! at 960×540 with 2 clients, in headless Chromium (Debian's `chromium` and
//! `chromium-driver`), after a short flight, a pick, and refinement to the
//! most samples.
//!
//!     cargo build --release && cargo run --release --example viewer_screenshot

use dray_testkit::browser::{Browser, Viewer};
use std::path::PathBuf;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(120);
const SHOW: &str = "return JSON.stringify({drawn: dray.drawn, samples: dray.samples})";

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR"));
    let dray = root.join("target/release/dray");
    assert!(dray.exists(), "build dray first: cargo build --release");
    let plant = dray_testkit::plant_db(300_000, 1, 4096);
    let Some(browser) = Browser::start(1280, 760).await else {
        panic!("no chromium or chromedriver (Debian: chromium chromium-driver)");
    };
    let web = format!("127.0.0.1:{}", dray_testkit::browser::free_tcp_port());
    let args = dray_testkit::browser::view_args(&plant.path, 2, &web, (960, 540));
    let viewer = Viewer::start(&dray, &args, WAIT);
    let b = &browser;
    b.client.goto(&viewer.url).await.expect("the page loads");
    let refined = "return dray.still === true && dray.samples === dray.status.max_samples";
    b.wait_for("refined", refined, SHOW, WAIT).await;
    b.hold_key('w', 700).await;
    b.wait_for("refined", refined, SHOW, WAIT).await;
    b.eval(
        "const c = document.getElementById('view'); const r = c.getBoundingClientRect(); \
         const at = {clientX: r.left + r.width * 0.55, clientY: r.top + r.height * 0.55, \
         button: 0, bubbles: true}; \
         c.dispatchEvent(new MouseEvent('mousedown', at)); \
         window.dispatchEvent(new MouseEvent('mouseup', at)); return true;",
    )
    .await;
    b.wait_for("a pick", "return dray.picked !== null", SHOW, WAIT)
        .await;
    b.wait_for("refined", refined, SHOW, WAIT).await;
    // The overlay's displayed rate falls to 0 once the view rests.
    tokio::time::sleep(Duration::from_millis(1500)).await;
    let out = root.join("docs/images/viewer.png");
    std::fs::write(&out, b.screenshot().await).expect("writing the picture");
    println!("{}", out.display());
    drop(viewer);
    browser.close().await;
}
