//! The web viewer in a real browser: `dray view` on a small plant, its page
//! in headless Chromium (Debian's `chromium` and `chromium-driver`; skipped
//! where they are missing unless `DRAY_REQUIRE_CHROMIUM` is set, as on CI).
//!
//! The page loads and draws frames; a held key moves the camera and changes
//! the canvas; standing still raises the samples per pixel to the most and
//! the last frame is lossless; `Home` brings the first view back exactly;
//! a click picks a triangle; keys toggle shadows and the resolution; a
//! recorded flight comes back as a camera path and plays back to its last
//! view; a bad path file is refused by name; a screenshot is a PNG; the
//! overlay's numbers update; when the cluster stops the page says so. The
//! test leaves a screenshot in the target directory (`viewer.png`).

use dray_testkit::browser::{view_args, Browser, Viewer, HOME_KEY};
use serde_json::Value;
use std::path::Path;
use std::time::Duration;

const WAIT: Duration = Duration::from_secs(60);

/// What the page shows, for a failure's message.
const SHOW: &str =
    "return JSON.stringify({drawn: dray.drawn, view: dray.view, samples: dray.samples, \
    status: dray.status, connected: dray.connected, errors: dray.errors, \
    banner: document.getElementById('banner').textContent})";

/// A digest of the canvas's pixels.
const CANVAS_HASH: &str = "const c = document.getElementById('view'); \
    const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
    let h = 2166136261 >>> 0; \
    for (let i = 0; i < d.length; i += 1) { h = Math.imul(h ^ d[i], 16777619) >>> 0; } \
    return h + ':' + c.width + 'x' + c.height;";

fn num(v: &Value) -> f64 {
    v.as_f64().unwrap_or_else(|| panic!("not a number: {v}"))
}

/// Waits until the canvas's digest is `want`; panics saying `what` did not
/// happen.
async fn wait_for_pixels(b: &Browser, want: &Value, what: &str) {
    let deadline = std::time::Instant::now() + WAIT;
    while b.eval(CANVAS_HASH).await != *want {
        assert!(std::time::Instant::now() < deadline, "{what}");
        tokio::time::sleep(Duration::from_millis(50)).await;
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_flies_refines_picks_and_says_when_the_cluster_stops() {
    let Some(browser) = Browser::start(1200, 800).await else {
        return;
    };
    let plant = dray_testkit::plant_db(60_000, 3, 2048);
    let web = format!("127.0.0.1:{}", dray_testkit::browser::free_tcp_port());
    let dray = Path::new(env!("CARGO_BIN_EXE_dray"));
    let args = view_args(&plant.path, 2, &web, (240, 160));
    let mut viewer = Viewer::start(dray, &args, WAIT);
    assert!(
        viewer.url.starts_with(&format!("http://{web}/?token=")),
        "{}",
        viewer.url
    );

    browser
        .client
        .goto(&viewer.url)
        .await
        .expect("the page loads");
    let b = &browser;
    b.wait_for("a first frame", "return dray.drawn > 0", SHOW, WAIT)
        .await;
    let distinct = b
        .eval(
            "const c = document.getElementById('view'); \
             const d = c.getContext('2d').getImageData(0, 0, c.width, c.height).data; \
             const seen = new Set(); \
             for (let i = 0; i < d.length; i += 4) seen.add(d[i] << 16 | d[i+1] << 8 | d[i+2]); \
             return seen.size;",
        )
        .await;
    assert!(
        num(&distinct) > 20.0,
        "the frame is not a picture: {distinct} colours"
    );

    // Standing still: the samples rise to the most, the last frame lossless.
    let max = num(&b.eval("return dray.status.max_samples").await);
    assert!(max > 1.0);
    b.wait_for(
        "refined to the most samples",
        "return dray.samples === dray.status.max_samples && dray.still === true",
        SHOW,
        WAIT,
    )
    .await;
    let home = b.eval(CANVAS_HASH).await;
    let overlay = b
        .eval("return document.getElementById('s-spp').textContent")
        .await;
    assert_eq!(overlay, Value::String(format!("{max} / {max}")));
    let cluster_fps = b
        .eval("return document.getElementById('s-cluster').textContent")
        .await;
    assert_ne!(
        cluster_fps,
        Value::String("–".into()),
        "the overlay's numbers update"
    );

    // A held key moves the camera: a new view, other pixels.
    let before = b.eval("return dray.view").await;
    b.hold_key('w', 400).await;
    b.wait_for(
        "a frame of the moved camera",
        &format!("return dray.view !== {before} && dray.lastLatencyMs !== null"),
        SHOW,
        WAIT,
    )
    .await;
    b.wait_for(
        "the moved view refined",
        "return dray.still === true",
        SHOW,
        WAIT,
    )
    .await;
    let moved = b.eval(CANVAS_HASH).await;
    assert_ne!(moved, home, "the canvas did not change");

    // Home brings the first view back, pixel for pixel once refined.
    b.press(HOME_KEY).await;
    b.wait_for(
        "home, refined",
        &format!("return dray.still === true && dray.samples === {max} && dray.view !== null"),
        SHOW,
        WAIT,
    )
    .await;
    wait_for_pixels(b, &home, "home did not bring the first view back").await;

    // A click in the middle picks the model there.
    b.eval(
        "const c = document.getElementById('view'); const r = c.getBoundingClientRect(); \
         const at = {clientX: r.left + r.width / 2, clientY: r.top + r.height / 2, button: 0, bubbles: true}; \
         c.dispatchEvent(new MouseEvent('mousedown', at)); \
         window.dispatchEvent(new MouseEvent('mouseup', at)); return true;",
    )
    .await;
    b.wait_for("a pick's answer", "return dray.picked !== null", SHOW, WAIT)
        .await;
    let picked = b.eval("return dray.picked").await;
    assert!(picked["triangle"].is_u64(), "nothing picked: {picked}");
    assert!(num(&picked["distance"]) > 0.0, "{picked}");
    let text = b
        .eval("return document.getElementById('pick').textContent")
        .await;
    assert!(text.as_str().unwrap().starts_with("triangle "), "{text}");

    // Keys toggle shadows and change the resolution, without a restart.
    let shadows = b.eval("return dray.status.choices.shadows").await;
    b.press('1').await;
    b.wait_for(
        "shadows toggled",
        &format!(
            "return dray.status.choices.shadows === {}",
            !shadows.as_bool().unwrap()
        ),
        SHOW,
        WAIT,
    )
    .await;
    b.press('-').await;
    b.wait_for(
        "half the resolution",
        "const c = document.getElementById('view'); return c.width === 120 && c.height === 80",
        SHOW,
        WAIT,
    )
    .await;
    b.press('=').await;
    b.wait_for(
        "the resolution back",
        "const c = document.getElementById('view'); return c.width === 240 && dray.still === true",
        SHOW,
        WAIT,
    )
    .await;

    // A recorded flight downloads as a camera path, and playing it back
    // ends on the flight's last view, pixel for pixel.
    let start = b.eval(CANVAS_HASH).await;
    b.press('r').await;
    b.wait_for(
        "recording",
        "return dray.status.choices.recording === true",
        SHOW,
        WAIT,
    )
    .await;
    b.hold_key('w', 300).await;
    b.hold_key('d', 300).await;
    b.wait_for(
        "the flight refined",
        &format!("return dray.still === true && dray.samples === {max}"),
        SHOW,
        WAIT,
    )
    .await;
    let end = b.eval(CANVAS_HASH).await;
    assert_ne!(end, start, "the flight went nowhere");
    b.press('r').await;
    b.wait_for("a recording", "return dray.recorded !== null", SHOW, WAIT)
        .await;
    let toml = b.eval("return dray.recorded.toml").await;
    let path = dray_actors::display::path::CameraPath::parse(
        toml.as_str().expect("the path's text"),
        Path::new("recorded.toml"),
    )
    .expect("the recording is a camera path");
    assert!(path.keyframes.len() >= 3, "{path:?}");
    // The status (a watch) and the recording (an event) come separately.
    b.wait_for(
        "the page hears the recording stopped",
        "return dray.status.choices.recording === false",
        SHOW,
        WAIT,
    )
    .await;
    b.press(HOME_KEY).await;
    b.wait_for(
        "home again",
        &format!("return dray.still === true && dray.samples === {max}"),
        SHOW,
        WAIT,
    )
    .await;
    wait_for_pixels(
        b,
        &start,
        "home again did not show the view the flight began at",
    )
    .await;
    let before = b.eval("return dray.view").await;
    b.press('p').await;
    b.wait_for(
        "the path played and refined",
        &format!(
            "return dray.pathFrames > 0 && dray.playing === null && dray.view !== {before} \
             && dray.still === true && dray.samples === {max}"
        ),
        SHOW,
        WAIT,
    )
    .await;
    wait_for_pixels(b, &end, "playing the flight did not end where it did").await;
    // A path file that is not one is refused with its name and key.
    let bad = tempfile::Builder::new().suffix(".toml").tempfile().unwrap();
    std::fs::write(bad.path(), "frames = 0\n").unwrap();
    b.choose_file("open", bad.path()).await;
    let name = bad.path().file_name().unwrap().to_str().unwrap();
    b.wait_for(
        "the bad path refused",
        &format!("return dray.errors.some((e) => e.includes('{name}: frames: 0 is not'))"),
        SHOW,
        WAIT,
    )
    .await;
    // A screenshot is the display's image, lossless.
    b.press('c').await;
    b.wait_for(
        "a screenshot",
        "return dray.screenshot !== null",
        SHOW,
        WAIT,
    )
    .await;
    let shot = b.eval("return dray.screenshot").await;
    assert_eq!(shot["type"], Value::from("image/png"), "{shot}");
    assert!(num(&shot["bytes"]) > 1000.0, "{shot}");

    let shot = b.screenshot().await;
    let out = Path::new(env!("CARGO_TARGET_TMPDIR")).join("viewer.png");
    std::fs::write(&out, shot).expect("writing the screenshot");

    // The cluster stops: the page says so.
    let status = viewer.interrupt(WAIT);
    assert!(
        status.is_some_and(|s| s.success()),
        "dray view did not stop cleanly on SIGINT: {status:?}"
    );
    b.wait_for(
        "the page says the cluster stopped",
        "const b = document.getElementById('banner'); \
         return b.style.display === 'block' && /ended|stopped/.test(b.textContent)",
        SHOW,
        WAIT,
    )
    .await;
    browser.close().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn the_viewer_refuses_a_page_without_the_token_and_other_sites() {
    let Some(browser) = Browser::start(800, 600).await else {
        return;
    };
    let plant = dray_testkit::plant_db(20_000, 4, 2048);
    let web = format!("127.0.0.1:{}", dray_testkit::browser::free_tcp_port());
    let dray = Path::new(env!("CARGO_BIN_EXE_dray"));
    let args = view_args(&plant.path, 1, &web, (64, 48));
    let viewer = Viewer::start(dray, &args, WAIT);
    let bare = viewer.url.split('?').next().unwrap().to_string();
    browser.client.goto(&bare).await.expect("the page loads");
    let b = &browser;
    b.wait_for(
        "the page says it cannot connect",
        "return document.getElementById('banner').style.display === 'block'",
        SHOW,
        WAIT,
    )
    .await;
    assert_eq!(b.eval("return dray.drawn").await, Value::from(0));
    let refused = b
        .eval("return fetch('/metrics.json?token=wrongwrongwrongwrong').then(r => r.status)")
        .await;
    assert_eq!(refused, Value::from(403));
    drop(viewer);
    browser.close().await;
}
