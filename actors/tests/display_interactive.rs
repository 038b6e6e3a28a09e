//! Interactive mode: inputs sent over the viewer's WebSocket steer the
//! display's frames; a fake assigner completes them. A still view is
//! refined sample by sample and accumulated; a move starts again; choices
//! change the frames' format; a pick is answered from a frame's ids.

use dray_actors::display::{
    run_display_with_viewer, DisplayOptions, DisplaySummary, WebOptions, WebViewer,
};
use dray_actors::{names, ActorError};
use dray_protocol::{
    Blob, Camera, CameraUpdate, FrameDone, Message, Name, PackedF32, PackedU32, Reflective,
    RenderSettings, Role, Shutdown, TileDone, TilePixels, TileRect, TileStats,
};
use dray_runtime::{Delivery, InProcNet, Mailbox};
use futures::{SinkExt, StreamExt};
use std::time::Duration;
use tokio::net::TcpStream;
use tokio::task::JoinHandle;
use tokio_tungstenite::tungstenite::Message as Ws;

const W: u32 = 8;
const H: u32 = 4;
const MAX_SAMPLES: u32 = 3;
const SOON: Duration = Duration::from_secs(5);

fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

fn start_cam() -> Camera {
    Camera {
        eye: [0.0, 1.0, -10.0],
        look: [0.0, 1.0, 0.0],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 45.0,
    }
}

fn settings() -> RenderSettings {
    RenderSettings {
        shade: true,
        shadows: false,
        reflection_depth: 0,
        light_dir: [0.3, 1.0, 0.2],
        reflective: Reflective::All,
        reflectance: 0.5,
        voxel_colors: false,
        want_depth: false,
        want_prim_ids: false,
    }
}

type Socket = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<TcpStream>>;

struct Fixture {
    _net: InProcNet,
    assigner: Mailbox,
    /// Next to the display, on its node: what stops it.
    control: Mailbox,
    /// Sends the tiles (only a client may).
    client: Mailbox,
    ws: Socket,
    display: JoinHandle<Result<DisplaySummary, ActorError>>,
}

async fn start() -> Fixture {
    let opts = WebOptions {
        interactive: true,
        token: None,
    };
    let (viewer, inputs) = WebViewer::start("127.0.0.1:0".parse().unwrap(), opts)
        .await
        .unwrap();
    let url = viewer
        .url()
        .replace("http://", "ws://")
        .replace("/?", "/ws?");
    let net = InProcNet::new();
    let sched = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let disp = net.add_node(name("display"), Role::Display).unwrap();
    let assigner = sched.mailbox(name(names::ASSIGNER), 64).unwrap();
    let control = disp.mailbox(name("control"), 4).unwrap();
    let client = net
        .add_node(names::client_node(0), Role::Client)
        .unwrap()
        .mailbox(name(names::CLIENT), 4)
        .unwrap();
    let mb = disp.mailbox(name(names::DISPLAY), 64).unwrap();
    let web = viewer.local_addr();
    let opts = DisplayOptions {
        assigner: names::assigner(),
        scheduler: names::scheduler(),
        width: W,
        height: H,
        settings: settings(),
        max_samples: MAX_SAMPLES,
        web_token: None,
        cameras: vec![start_cam()],
        interactive: true,
        frames_ahead: 2,
        output: None,
        save_frames: false,
        keep_frames: false,
        keep_metrics: false,
        web: Some(web),
        samples: 1,
    };
    let display = tokio::spawn(run_display_with_viewer(
        mb,
        opts,
        Some((viewer, inputs)),
        std::future::pending(),
    ));
    let (ws, _) = tokio_tungstenite::connect_async(url).await.unwrap();
    Fixture {
        _net: net,
        assigner,
        control,
        client,
        ws,
        display,
    }
}

impl Fixture {
    async fn camera(&mut self) -> CameraUpdate {
        loop {
            if let Delivery::Message {
                msg: Message::CameraUpdate(c),
                ..
            } = self.assigner.recv().await.expect("bus")
            {
                return c;
            }
        }
    }

    async fn camera_within(&mut self, t: Duration) -> Option<CameraUpdate> {
        tokio::time::timeout(t, self.camera()).await.ok()
    }

    /// Sends frame `frame` of `w` × `h` as one tile (every pixel `v`), with
    /// ids and depths when asked, then its FrameDone.
    async fn complete(&mut self, frame: u64, (w, h): (u32, u32), v: u8, ids: bool) {
        let n = (w * h) as usize;
        let tile = TileDone {
            frame,
            tile: TileRect { x: 0, y: 0, w, h },
            pixels: TilePixels::Rgba(Blob(vec![v; n * 4])),
            depth: ids.then(|| PackedF32(vec![7.5; n])),
            prim_ids: ids.then(|| PackedU32((0..n as u32).collect())),
            stats: TileStats::default(),
            hits: Default::default(),
        };
        let d = names::display();
        self.client.send(&d, Message::TileDone(tile)).await.unwrap();
        let done = FrameDone {
            frame,
            stats: Default::default(),
        };
        self.assigner
            .send(&d, Message::FrameDone(done))
            .await
            .unwrap();
    }

    async fn input(&mut self, json: &str) {
        self.ws.send(Ws::Text(json.into())).await.unwrap();
    }

    /// The next message on the socket: text as JSON, or a frame's header.
    async fn next(&mut self) -> serde_json::Value {
        let m = tokio::time::timeout(SOON, self.ws.next())
            .await
            .expect("a message in time")
            .expect("the socket open")
            .unwrap();
        match m {
            Ws::Text(t) => serde_json::from_str(&t).unwrap(),
            Ws::Binary(b) => {
                let n = u32::from_le_bytes(b[..4].try_into().unwrap()) as usize;
                let mut head: serde_json::Value = serde_json::from_slice(&b[4..4 + n]).unwrap();
                head["type"] = "frame".into();
                if head["format"] == "png" {
                    let (_, _, px) = dray_trace::image::decode_png(&b[4 + n..]).unwrap();
                    head["pixel"] = px[0].to_vec().into();
                }
                head
            }
            other => panic!("unexpected {other:?}"),
        }
    }

    async fn next_of(&mut self, kind: &str) -> serde_json::Value {
        loop {
            let m = self.next().await;
            if m["type"] == kind {
                return m;
            }
        }
    }
}

#[tokio::test]
async fn display_interactive_refines_a_still_view_and_a_move_starts_again() {
    let mut f = start().await;
    let hello = f.next_of("status").await;
    assert_eq!(hello["max_samples"], MAX_SAMPLES);
    assert_eq!(hello["choices"]["width"], W);

    // Samples 0, 1, 2 of the first camera, the first saying its format.
    let c0 = f.camera_within(SOON).await.expect("first camera");
    assert_eq!((c0.seq, c0.sample, c0.camera), (0, 0, start_cam()));
    let format = c0.format.clone().expect("the first frame's format");
    assert_eq!((format.width, format.height), (W, H));
    assert!(
        f.camera_within(Duration::from_millis(200)).await.is_none(),
        "a refining sample waits for the frame before it"
    );
    // Pixels 30, 60, 90: the page sees their running mean.
    f.complete(0, (W, H), 30, false).await;
    let c1 = f.camera_within(SOON).await.expect("second camera");
    assert_eq!(
        (c1.seq, c1.sample, c1.camera, c1.format),
        (1, 1, start_cam(), None)
    );
    f.complete(1, (W, H), 60, false).await;
    let c2 = f.camera_within(SOON).await.expect("third camera");
    assert_eq!((c2.seq, c2.sample), (2, 2));
    f.complete(2, (W, H), 90, false).await;
    let mut last = serde_json::Value::Null;
    while last["samples"] != MAX_SAMPLES {
        last = f.next_of("frame").await;
    }
    assert_eq!(last["still"], true);
    assert_eq!(
        last["pixel"],
        serde_json::json!([60, 60, 60, 255]),
        "the mean of 30, 60, 90"
    );
    assert!(
        f.camera_within(Duration::from_millis(300)).await.is_none(),
        "a refined view leaves the cluster idle"
    );

    // A move: sample 0 of the moved camera.
    f.input(r#"{"fly":{"forward":1.5}}"#).await;
    let m = f
        .camera_within(SOON)
        .await
        .expect("a camera after the move");
    assert_eq!((m.seq, m.sample, m.format), (3, 0, None));
    assert!(
        (m.camera.eye[2] - (-8.5)).abs() < 1e-4,
        "{:?}",
        m.camera.eye
    );
    f.complete(3, (W, H), 200, false).await;
    let shown = f.next_of("frame").await;
    assert_eq!(
        (shown["samples"].as_u64(), shown["still"].as_bool()),
        (Some(1), Some(false))
    );

    // Half the resolution: the format says so, and its tiles fit.
    f.input(r#"{"set":{"scale":0.5,"shadows":true}}"#).await;
    let status = f.next_of("status").await;
    assert_eq!(
        (
            status["choices"]["width"].as_u64(),
            status["choices"]["shadows"].as_bool()
        ),
        (Some(4), Some(true))
    );
    let mut c = f
        .camera_within(SOON)
        .await
        .expect("a camera after the change");
    while c.format.is_none() {
        f.complete(c.seq, (W, H), 0, false).await;
        c = f.camera_within(SOON).await.expect("the changed format");
    }
    let fmt = c.format.clone().unwrap();
    assert_eq!(
        (fmt.width, fmt.height, fmt.settings.shadows, c.sample),
        (4, 2, true, 0)
    );
    f.complete(c.seq, (4, 2), 10, false).await;
    let shown = loop {
        let s = f.next_of("frame").await;
        if s["width"] == 4 {
            break s;
        }
    };
    assert_eq!(shown["height"], 2);

    // A pick rides on the next frame, with ids and depths, and is answered.
    f.input(r#"{"pick":{"x":0.6,"y":0.9,"pivot":true}}"#).await;
    let p = loop {
        let c = f.camera_within(SOON).await.expect("the pick's frame");
        let wants = c
            .format
            .as_ref()
            .is_some_and(|f| f.settings.want_prim_ids && f.settings.want_depth);
        f.complete(c.seq, (4, 2), 10, wants).await;
        if wants {
            break f.next_of("picked").await;
        }
    };
    // Pixel (2, 1) of 4 × 2: id 6, at the depth sent.
    assert_eq!(
        (p["triangle"].as_u64(), p["distance"].as_f64()),
        (Some(6), Some(7.5))
    );

    // A Shutdown ends the run; the page hears why.
    f.control
        .send(
            &names::display(),
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let ended = loop {
        let s = f.next_of("status").await;
        if !s["ended"].is_null() {
            break s;
        }
    };
    assert_eq!(ended["ended"], "shutdown: done");
    let s = tokio::time::timeout(SOON, f.display)
        .await
        .unwrap()
        .unwrap()
        .unwrap();
    assert!(s.complete && s.stopped_early.is_none());
    // An interactive run keeps its sums, not a row per frame.
    assert!(s.frames_shown >= 6 && s.frames.is_empty());
    assert_eq!(s.frames_requested, s.frames_shown);
}

#[tokio::test]
async fn display_interactive_ignores_wild_inputs() {
    let mut f = start().await;
    f.next_of("status").await;
    f.camera_within(SOON).await.expect("first camera");
    for bad in [
        r#"{"fly":{"forward":1e38,"yaw":1e38}}"#,
        r#"{"orbit":{"yaw":-1e38,"pitch":1e38}}"#,
        r#"{"zoom":{"steps":1e30}}"#,
        r#"{"set":{"scale":3}}"#,
        r#"{"pick":{"x":-1,"y":2}}"#,
    ] {
        f.input(bad).await;
    }
    let mut last = None;
    while let Some(c) = f.camera_within(Duration::from_millis(500)).await {
        assert!(dray_protocol::check_camera(&c.camera).is_ok(), "{c:?}");
        assert!(c.camera.eye.iter().all(|x| x.abs() < 1e3), "{c:?}");
        if let Some(fmt) = &c.format {
            assert_eq!((fmt.width, fmt.height), (W, H), "no such scale");
        }
        f.complete(c.seq, (W, H), 1, false).await;
        last = Some(c);
    }
    assert!(last.is_some(), "the display goes on");
}
