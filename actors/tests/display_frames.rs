//! The display against a fake assigner, scheduler and clients on an
//! in-process network: frames assembled from tiles out of order and from
//! several clients, duplicates ignored, frames in order, frames_ahead
//! respected, files written, hostile tiles ignored.

use dray_actors::display::{run_display, DisplayOptions, DisplaySummary, CSV_HEADER};
use dray_actors::{names, ActorError};
use dray_protocol::{
    BoundedVec, Camera, ClientFrameStats, FrameDone, FrameStats, LinkBytes, Message, Name,
    PackedF32, PackedU32, Role, Shutdown, TileDone, TilePixels, TileRect, TileStats,
};
use dray_runtime::{Delivery, InProcNet, Mailbox};
use std::time::Duration;
use tokio::task::JoinHandle;

const W: u32 = 40;
const H: u32 = 24;
const T: u32 = 16;

fn pixel(frame: u64, x: u32, y: u32) -> [u8; 4] {
    [x as u8 * 3, y as u8 * 5, frame as u8 * 40 + 1, 255]
}

fn depth(frame: u64, x: u32, y: u32) -> f32 {
    if (x + y).is_multiple_of(7) {
        f32::INFINITY
    } else {
        frame as f32 + x as f32 * 0.5 + y as f32
    }
}

fn primid(frame: u64, x: u32, y: u32) -> u32 {
    if (x + y).is_multiple_of(7) {
        u32::MAX
    } else {
        ((frame as u32) << 16) | (y * W + x)
    }
}

fn tiles() -> Vec<TileRect> {
    let mut v = Vec::new();
    for y in (0..H).step_by(T as usize) {
        for x in (0..W).step_by(T as usize) {
            v.push(TileRect {
                x,
                y,
                w: T.min(W - x),
                h: T.min(H - y),
            });
        }
    }
    v
}

fn tile_done(frame: u64, r: TileRect, garbage: bool) -> TileDone {
    let mut px = Vec::new();
    let mut d = Vec::new();
    let mut ids = Vec::new();
    for y in r.y..r.y + r.h {
        for x in r.x..r.x + r.w {
            px.push(if garbage {
                [0xEE; 4]
            } else {
                pixel(frame, x, y)
            });
            d.push(if garbage { -1.0 } else { depth(frame, x, y) });
            ids.push(if garbage { 7 } else { primid(frame, x, y) });
        }
    }
    TileDone {
        frame,
        tile: r,
        pixels: TilePixels::encode(&px),
        depth: Some(PackedF32(d)),
        prim_ids: Some(PackedU32(ids)),
        stats: TileStats {
            rays: r.area() as u64,
            ..TileStats::default()
        },
        hits: Default::default(),
    }
}

fn camera(i: usize) -> Camera {
    Camera {
        eye: [i as f32, 1.0, -10.0],
        look: [0.0, 0.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 45.0,
    }
}

fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

struct Cluster {
    _net: InProcNet,
    assigner: Mailbox,
    /// Next to the display, on its node: what stops it.
    control: Mailbox,
    /// Gets the display's tile reports.
    scheduler: Mailbox,
    clients: Vec<Mailbox>,
    display: Option<JoinHandle<Result<DisplaySummary, ActorError>>>,
}

fn start(frames: usize, ahead: usize, output: Option<std::path::PathBuf>) -> Cluster {
    let net = InProcNet::new();
    let sched = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let disp = net.add_node(name("display"), Role::Display).unwrap();
    let assigner = sched.mailbox(name(names::ASSIGNER), 256).unwrap();
    let control = disp.mailbox(name("control"), 4).unwrap();
    let scheduler = sched.mailbox(name(names::SCHEDULER), 4096).unwrap();
    let clients = (0..2)
        .map(|i| {
            net.add_node(names::client_node(i), Role::Client)
                .unwrap()
                .mailbox(name(names::CLIENT), 16)
                .unwrap()
        })
        .collect();
    let mb = disp.mailbox(name(names::DISPLAY), 1024).unwrap();
    let opts = DisplayOptions {
        assigner: names::assigner(),
        scheduler: names::scheduler(),
        width: W,
        height: H,
        cameras: (0..frames).map(camera).collect(),
        interactive: false,
        frames_ahead: ahead,
        output,
        save_frames: true,
        keep_frames: true,
        keep_metrics: true,
        web: None,
        samples: 1,
        settings: dray_protocol::RenderSettings {
            shade: true,
            shadows: false,
            reflection_depth: 0,
            light_dir: [0.3, 1.0, 0.2],
            reflective: dray_protocol::Reflective::All,
            reflectance: 0.5,
            voxel_colors: false,
            want_depth: false,
            want_prim_ids: false,
        },
        max_samples: 1,
        web_token: None,
    };
    Cluster {
        _net: net,
        assigner,
        control,
        scheduler,
        clients,
        display: Some(tokio::spawn(run_display(mb, opts))),
    }
}

impl Cluster {
    /// The next camera update the assigner gets (other deliveries skipped).
    async fn camera(&mut self) -> u64 {
        loop {
            match self.assigner.recv().await.expect("bus") {
                Delivery::Message {
                    msg: Message::CameraUpdate(c),
                    ..
                } => return c.seq,
                _ => continue,
            }
        }
    }

    /// Whether a camera update comes within a second (paused clock).
    async fn camera_soon(&mut self) -> Option<u64> {
        tokio::time::timeout(Duration::from_secs(1), self.camera())
            .await
            .ok()
    }

    /// Sends every tile of `frame`, out of order, alternating clients, one
    /// tile twice (the second copy garbage: first wins), then FrameDone.
    async fn deliver(&mut self, frame: u64, done_first: bool) {
        if done_first {
            self.frame_done(frame).await;
        }
        let mut ts = tiles();
        // Deterministic shuffle, different per frame.
        ts.reverse();
        let n = ts.len();
        ts.rotate_left(frame as usize % n);
        let dup = ts[1];
        for (i, r) in ts.iter().enumerate() {
            let c = &self.clients[i % 2];
            c.send(
                &names::display(),
                Message::TileDone(tile_done(frame, *r, false)),
            )
            .await
            .unwrap();
            if i == 3 {
                // A reassigned tile rendered again by the other client.
                self.clients[1 - i % 2]
                    .send(
                        &names::display(),
                        Message::TileDone(tile_done(frame, dup, true)),
                    )
                    .await
                    .unwrap();
            }
        }
        if !done_first {
            self.frame_done(frame).await;
        }
    }

    async fn frame_done(&mut self, frame: u64) {
        let n = tiles().len() as u32;
        let clients = (0..2)
            .map(|i| ClientFrameStats {
                node: names::client_node(i),
                tiles: n / 2,
                rays: 100,
                misses: 1,
                bytes_fetched: 1000,
                stall_us: 10,
            })
            .collect();
        let stats = FrameStats {
            tiles: n,
            reassigned: 1,
            rays: (W * H) as u64,
            time_us: 1000,
            misses: 2,
            bytes_fetched: 2000,
            bytes_raw: 6000,
            voxels_touched: 8,
            stall_us: 20,
            link: LinkBytes {
                client_store: 5000,
                client_scheduler: 700,
                display: 0,
                store_uplink: 4900,
                client_downlink: 5100,
            },
            clients: BoundedVec::new(clients).unwrap(),
        };
        self.assigner
            .send(
                &names::display(),
                Message::FrameDone(FrameDone { frame, stats }),
            )
            .await
            .unwrap();
    }

    async fn summary(&mut self) -> DisplaySummary {
        self.display.take().unwrap().await.unwrap().unwrap()
    }
}

fn check_image(s: &DisplaySummary, frame: u64) {
    let img = &s.images[frame as usize];
    assert_eq!(img.frame, frame);
    assert_eq!(img.rgba.len(), (W * H) as usize);
    let d = img.depth.as_ref().expect("depth kept");
    let ids = img.primid.as_ref().expect("ids kept");
    for y in 0..H {
        for x in 0..W {
            let i = (y * W + x) as usize;
            assert_eq!(img.rgba[i], pixel(frame, x, y), "frame {frame} ({x}, {y})");
            assert_eq!(d[i], depth(frame, x, y));
            assert_eq!(ids[i], primid(frame, x, y));
        }
    }
}

#[tokio::test(start_paused = true)]
async fn display_assembles_frames_from_out_of_order_tiles_and_writes_files() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let mut c = start(4, 2, Some(out.clone()));
    let ahead = 2u64;
    let mut received = 0u64;
    let mut delivered = 0u64;
    while delivered < 4 {
        // Take every camera the display sends now; never more than
        // `ahead` beyond the frames it can have completed.
        while let Some(seq) = c.camera_soon().await {
            assert_eq!(seq, received, "cameras in order");
            received += 1;
            assert!(
                received <= delivered + ahead,
                "{received} cameras with {delivered} frames delivered"
            );
        }
        assert_eq!(
            received,
            (delivered + ahead).min(4),
            "display keeps {ahead} ahead"
        );
        c.deliver(delivered, delivered % 2 == 1).await;
        delivered += 1;
    }
    let s = c.summary().await;
    assert!(s.complete);
    assert_eq!(s.frames.len(), 4);
    assert_eq!(s.images.len(), 4);
    for f in 0..4 {
        check_image(&s, f);
        assert_eq!(s.frames[f as usize].frame, f);
    }
    assert_eq!(s.tiles_ignored, 0);
    assert_eq!(s.duplicate_tiles, 4);
    // The scheduler heard of each tile once, when its first copy came,
    // naming the client that sent that copy.
    let mut reported = std::collections::HashMap::new();
    while let Some(d) = c.scheduler.try_recv() {
        let Delivery::Message { from, msg } = d else {
            continue;
        };
        assert_eq!(from, names::display());
        let Message::TileReport(r) = msg else {
            panic!("the scheduler got {msg:?}");
        };
        assert!(r.stats.rays > 0, "the client's costs passed on");
        let first = reported.insert((r.frame, r.tile), r.client.clone());
        assert!(
            first.is_none(),
            "{:?} of frame {} reported twice",
            r.tile,
            r.frame
        );
    }
    assert_eq!(reported.len(), 4 * tiles().len());
    for f in 0..4u64 {
        let mut ts = tiles();
        ts.reverse();
        let n = ts.len();
        ts.rotate_left(f as usize % n);
        for (i, t) in ts.iter().enumerate() {
            assert_eq!(
                reported[&(f, *t)],
                names::client_node(i % 2),
                "frame {f} tile {t:?}"
            );
        }
    }
    assert_eq!(s.total_rays, 4 * (W * H) as u64);
    assert_eq!(s.frames[0].cache_hit_rate, 0.75);
    assert_eq!(s.frames[0].tiles_per_client, "client-0:3 client-1:3");

    // Files: a PNG (and depth, ids) per frame, and metrics.csv.
    for f in 0..4 {
        let png = std::fs::read(out.join(format!("frames/frame-{f:05}.png"))).unwrap();
        assert_eq!(&png[..8], b"\x89PNG\r\n\x1a\n");
        assert_eq!(&png[12..16], b"IHDR");
        assert_eq!(u32::from_be_bytes(png[16..20].try_into().unwrap()), W);
        assert_eq!(u32::from_be_bytes(png[20..24].try_into().unwrap()), H);
        let ids = std::fs::read(out.join(format!("frames/frame-{f:05}.primid"))).unwrap();
        assert_eq!(ids.len(), (W * H * 4) as usize);
        assert!(out.join(format!("frames/frame-{f:05}.pfm")).exists());
    }
    let csv = std::fs::read_to_string(out.join("metrics.csv")).unwrap();
    let mut lines = csv.lines();
    let header: Vec<&str> = lines.next().unwrap().split(',').collect();
    assert_eq!(header, CSV_HEADER.split(',').collect::<Vec<_>>());
    assert_eq!(header[0], "frame");
    let rows: Vec<Vec<&str>> = lines.map(|l| l.split(',').collect()).collect();
    assert_eq!(rows.len(), 4, "one row per frame");
    let col = |n: &str| header.iter().position(|h| *h == n).unwrap();
    for (f, row) in rows.iter().enumerate() {
        assert_eq!(row.len(), header.len());
        assert_eq!(row[col("frame")], f.to_string());
        assert_eq!(row[col("rays")], (W * H).to_string());
        assert_eq!(row[col("tiles")], "6");
        assert_eq!(row[col("reassigned")], "1");
        assert_eq!(row[col("bytes_fetched")], "2000");
        assert_eq!(row[col("bytes_raw")], "6000");
        assert_eq!(row[col("misses")], "2");
        assert_eq!(row[col("voxels_touched")], "8");
        assert_eq!(row[col("cache_hit_rate")].parse::<f64>().unwrap(), 0.75);
        assert_eq!(row[col("stall_ms")].parse::<f64>().unwrap(), 0.02);
        assert_eq!(row[col("link_client_store")], "5000");
        assert_eq!(row[col("link_client_downlink")], "5100");
        // The display's own link to the scheduler: the frame's camera out
        // and its FrameDone in, counted by the display's transport.
        assert!(row[col("link_display")].parse::<u64>().unwrap() > 0);
        assert_eq!(row[col("tiles_per_client")], "client-0:3 client-1:3");
        assert!(row[col("frame_ms")].parse::<f64>().unwrap() >= 0.0);
        // The row is the summary's frame, to the CSV's three decimals.
        let ms: f64 = row[col("frame_ms")].parse().unwrap();
        assert!((ms - s.frames[f].frame_ms).abs() <= 0.0005 + 1e-9, "{ms}");
        assert!(row[col("fps")].parse::<f64>().unwrap() > 0.0);
    }
    let json = s.to_json();
    assert_eq!(json["frames_shown"], 4);
    assert_eq!(json["frames"].as_array().unwrap().len(), 4);
    assert!(s.print_text().contains("4 of 4 frames"));
}

#[tokio::test(start_paused = true)]
async fn display_shows_frames_in_order_when_a_later_one_finishes_first() {
    let mut c = start(3, 2, None);
    assert_eq!(c.camera().await, 0);
    assert_eq!(c.camera().await, 1);
    assert_eq!(c.camera_soon().await, None, "only two ahead");
    // Frame 1 complete first: it must wait for frame 0, and no camera for
    // frame 2 may go out yet.
    tokio::time::advance(Duration::from_millis(5)).await;
    c.deliver(1, false).await;
    assert_eq!(c.camera_soon().await, None, "frame 0 is still outstanding");
    c.deliver(0, true).await;
    assert_eq!(c.camera().await, 2);
    assert_eq!(c.camera_soon().await, None);
    c.deliver(2, false).await;
    let s = c.summary().await;
    assert!(s.complete);
    let order: Vec<u64> = s.frames.iter().map(|m| m.frame).collect();
    assert_eq!(order, [0, 1, 2]);
    for f in 0..3 {
        check_image(&s, f);
    }
    // Frame 1 was ready before frame 0: both are shown together, and share
    // the time since the first camera (no frame of zero time, no fps of a
    // million).
    assert!(s.frames[0].frame_ms > 0.0, "{:?}", s.frames[0]);
    assert_eq!(s.frames[0].frame_ms, s.frames[1].frame_ms);
    assert_eq!(s.frames[0].fps, s.frames[1].fps);
    assert!(s.frames[1].fps < 1000.0, "{:?}", s.frames[1]);
}

#[tokio::test(start_paused = true)]
async fn display_ignores_hostile_tiles() {
    let mut c = start(1, 1, None);
    assert_eq!(c.camera().await, 0);
    let hostile = [
        // A frame never asked for, and the largest frame number.
        tile_done(7, tiles()[0], true),
        tile_done(u64::MAX, tiles()[0], true),
        // Rectangles leaving the image (right, bottom, far away).
        tile_done(
            0,
            TileRect {
                x: W - 8,
                y: 0,
                w: 16,
                h: 16,
            },
            true,
        ),
        tile_done(
            0,
            TileRect {
                x: 0,
                y: H - 1,
                w: 4,
                h: 2,
            },
            true,
        ),
        tile_done(
            0,
            TileRect {
                x: 1_000_000,
                y: u32::MAX - 8,
                w: 4,
                h: 4,
            },
            true,
        ),
    ];
    for t in hostile {
        c.clients[0]
            .send(&names::display(), Message::TileDone(t))
            .await
            .unwrap();
    }
    // A report for a frame that does not exist.
    c.frame_done(3).await;
    c.deliver(0, false).await;
    let s = c.summary().await;
    assert!(s.complete);
    assert_eq!(s.tiles_ignored, 5);
    check_image(&s, 0);
}

#[tokio::test(start_paused = true)]
async fn display_returns_what_it_has_on_shutdown() {
    let mut c = start(5, 2, None);
    assert_eq!(c.camera().await, 0);
    assert_eq!(c.camera().await, 1);
    c.deliver(0, false).await;
    assert_eq!(c.camera().await, 2);
    c.control
        .send(
            &names::display(),
            Message::Shutdown(Shutdown {
                reason: "test over".into(),
            }),
        )
        .await
        .unwrap();
    let s = c.summary().await;
    assert!(!s.complete);
    assert_eq!(s.frames.len(), 1);
    check_image(&s, 0);
    assert!(s.stopped_early.as_deref().unwrap().contains("test over"));
}

#[tokio::test(start_paused = true)]
async fn display_shows_a_frame_with_a_lost_tile_after_the_grace_time() {
    let mut c = start(1, 1, None);
    assert_eq!(c.camera().await, 0);
    for r in tiles().into_iter().skip(1) {
        c.clients[0]
            .send(&names::display(), Message::TileDone(tile_done(0, r, false)))
            .await
            .unwrap();
    }
    c.frame_done(0).await;
    let s = c.summary().await;
    assert!(s.complete);
    assert_eq!(s.missing_pixels, tiles()[0].area() as u64);
}
