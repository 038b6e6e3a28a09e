//! Interactive mode: camera moves sent to the web viewer over a real
//! loopback socket steer the display's cameras; a fake assigner completes
//! the frames.

use dray_actors::display::{
    moves, run_display_with_viewer, DisplayOptions, DisplaySummary, Move, WebViewer, IDLE_FRAMES,
};
use dray_actors::{names, ActorError};
use dray_protocol::{
    Camera, FrameDone, Message, Name, Role, Shutdown, TileDone, TilePixels, TileRect, TileStats,
};
use dray_runtime::{Delivery, InProcNet, Mailbox};
use std::net::SocketAddr;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio::task::JoinHandle;

const W: u32 = 8;
const H: u32 = 4;

/// Sends raw bytes, returns (status, body).
async fn request(addr: SocketAddr, raw: &[u8]) -> (u16, Vec<u8>) {
    let mut s = TcpStream::connect(addr).await.unwrap();
    s.write_all(raw).await.unwrap();
    let mut out = Vec::new();
    s.read_to_end(&mut out).await.unwrap();
    let end = out
        .windows(4)
        .position(|w| w == b"\r\n\r\n")
        .expect("a response head");
    let head = String::from_utf8(out[..end].to_vec()).unwrap();
    let status = head.split(' ').nth(1).unwrap().parse().unwrap();
    (status, out[end + 4..].to_vec())
}

async fn get(addr: SocketAddr, path: &str) -> u16 {
    let req = format!("GET {path} HTTP/1.1\r\nHost: localhost\r\n\r\n");
    request(addr, req.as_bytes()).await.0
}

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

struct Fixture {
    _net: InProcNet,
    assigner: Mailbox,
    /// Next to the display, on its node: what stops it.
    control: Mailbox,
    /// Sends the tiles (only a client may).
    client: Mailbox,
    web: SocketAddr,
    display: JoinHandle<Result<DisplaySummary, ActorError>>,
}

/// A display with an interactive viewer on a port the system picks (bound
/// before the display runs, so no other test can take it in between).
async fn start(stop: impl std::future::Future<Output = ()> + Send + 'static) -> Fixture {
    let (viewer, moves) = WebViewer::start_interactive("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let web = viewer.local_addr();
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
    let opts = DisplayOptions {
        assigner: names::assigner(),
        scheduler: names::scheduler(),
        width: W,
        height: H,
        cameras: vec![start_cam()],
        interactive: true,
        frames_ahead: 1,
        output: None,
        save_frames: false,
        keep_frames: false,
        web: Some(web),
        samples: 1,
    };
    Fixture {
        _net: net,
        assigner,
        control,
        client,
        web,
        display: tokio::spawn(run_display_with_viewer(
            mb,
            opts,
            Some((viewer, Some(moves))),
            stop,
        )),
    }
}

impl Fixture {
    async fn camera(&mut self) -> (u64, Camera) {
        loop {
            if let Delivery::Message {
                msg: Message::CameraUpdate(c),
                ..
            } = self.assigner.recv().await.expect("bus")
            {
                return (c.seq, c.camera);
            }
        }
    }

    async fn camera_within(&mut self, t: Duration) -> Option<(u64, Camera)> {
        tokio::time::timeout(t, self.camera()).await.ok()
    }

    /// Sends the whole frame as one tile, then its FrameDone.
    async fn complete(&mut self, frame: u64) {
        let rgba: Vec<[u8; 4]> = (0..W * H).map(|i| [i as u8, frame as u8, 0, 255]).collect();
        let tile = TileDone {
            frame,
            tile: TileRect {
                x: 0,
                y: 0,
                w: W,
                h: H,
            },
            pixels: TilePixels::encode(&rgba),
            depth: None,
            prim_ids: None,
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

    /// Sends a move over HTTP and gives the display time to take it.
    async fn user(&self, query: &str) {
        assert_eq!(
            get(self.web, &format!("/move?{query}")).await,
            204,
            "{query}"
        );
        tokio::time::sleep(Duration::from_millis(100)).await;
    }
}

fn sub(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    [a[0] - b[0], a[1] - b[1], a[2] - b[2]]
}

fn close(a: [f32; 3], b: [f32; 3]) -> bool {
    sub(a, b).iter().all(|x| x.abs() < 1e-4)
}

const SOON: Duration = Duration::from_secs(5);

#[tokio::test]
async fn display_interactive_follows_moves_from_the_web_viewer() {
    let mut f = start(std::future::pending()).await;
    let c0 = start_cam();
    let step = moves::step_for(&c0);
    let (seq, cam) = f.camera_within(SOON).await.expect("first camera");
    assert_eq!((seq, cam), (0, c0), "starts from the config's camera");

    // `w`: the next frame's eye is one step forward along the view.
    f.user("k=w").await;
    f.complete(0).await;
    let (seq, c1) = f.camera_within(SOON).await.expect("camera 1");
    assert_eq!(seq, 1);
    assert!(close(c1.eye, [0.0, 1.0, -10.0 + step]), "{:?}", c1.eye);
    assert!(close(c1.look, [0.0, 1.0, step]), "{:?}", c1.look);

    // `q`: the look point turns left about the up vector, the eye stays.
    f.user("k=q").await;
    f.complete(1).await;
    let (seq, c2) = f.camera_within(SOON).await.expect("camera 2");
    assert_eq!(seq, 2);
    assert!(close(c2.eye, c1.eye));
    let d = sub(c2.look, c2.eye);
    let a = moves::TURN_DEG.to_radians();
    // Looking along +z with up +y, left is +x.
    assert!(close(d, [10.0 * a.sin(), 0.0, 10.0 * a.cos()]), "{d:?}");

    // No more moves: the same camera a few more times, then the display
    // waits for a move.
    let mut seq = 2;
    for _ in 1..IDLE_FRAMES {
        f.complete(seq).await;
        let (s, c) = f.camera_within(SOON).await.expect("idle refresh");
        assert_eq!((s, c), (seq + 1, c2));
        seq = s;
    }
    f.complete(seq).await;
    assert_eq!(
        f.camera_within(Duration::from_millis(500)).await,
        None,
        "an idle viewer leaves the cluster idle"
    );
    // A move wakes it up: `d` strafes right (-x here).
    let resumed = std::time::Instant::now();
    f.user("k=d").await;
    let (s, c) = f.camera_within(SOON).await.expect("camera after the pause");
    assert_eq!(s, seq + 1);
    assert!(!close(c.look, c2.look) && (c.eye[1] - c2.eye[1]).abs() < 1e-4);
    let moved = sub(c.eye, c2.eye);
    let len = moved.iter().map(|x| x * x).sum::<f32>().sqrt();
    assert!((len - step).abs() < 1e-4 && moved[0] < 0.0, "{moved:?}");

    f.complete(s).await;
    let seq = s;
    tokio::time::sleep(Duration::from_millis(100)).await;

    // A Shutdown ends the run, with the frames shown so far.
    f.control
        .send(
            &names::display(),
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let s = f.display.await.unwrap().unwrap();
    let since_move = resumed.elapsed().as_secs_f64() * 1e3;
    assert_eq!(s.frames.len() as u64, seq + 1);
    assert_eq!(s.frames_requested, s.frames.len());
    assert!(s.complete && s.stopped_early.is_none());
    // The idle pause (500 ms and more before the move) is not frame
    // time: the last frame's clock started after the move.
    let last = s.frames.last().unwrap();
    assert!(
        last.frame_ms <= since_move,
        "{} ms, {since_move} ms since the move",
        last.frame_ms
    );
    // The viewer stopped with the display.
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert!(TcpStream::connect(f.web).await.is_err());
}

#[tokio::test]
async fn display_interactive_ends_on_the_stop_future() {
    let (tx, rx) = tokio::sync::oneshot::channel::<()>();
    let mut f = start(async {
        let _ = rx.await;
    })
    .await;
    f.camera_within(SOON).await.expect("first camera");
    f.complete(0).await;
    f.camera_within(SOON).await.expect("second camera");
    tokio::time::sleep(Duration::from_millis(100)).await;
    tx.send(()).unwrap();
    let s = tokio::time::timeout(SOON, f.display)
        .await
        .expect("stops")
        .unwrap()
        .unwrap();
    assert_eq!(s.frames.len(), 1);
    assert!(s.complete);
}

#[tokio::test]
async fn display_web_viewer_refuses_bad_moves_and_keeps_serving() {
    let (v, mut rx) = WebViewer::start_interactive("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let addr = v.local_addr();
    for bad in [
        "/move",
        "/move?",
        "/move?k=zz",
        "/move?k=w&k=s",
        "/move?k=w&x=1",
        "/move?k=look&dx=nan&dy=0",
        "/move?k=look&dx=1e30",
        "/move?k=%77",
    ] {
        assert_eq!(get(addr, bad).await, 400, "{bad}");
    }
    assert_eq!(
        request(addr, b"HEAD /move?k=w HTTP/1.1\r\n\r\n").await.0,
        405,
        "a move is not for HEAD"
    );
    assert_eq!(
        request(addr, b"POST /move HTTP/1.1\r\nContent-Length: 3\r\n\r\nk=w")
            .await
            .0,
        405
    );
    assert!(rx.try_recv().is_err(), "nothing taken");
    assert_eq!(get(addr, "/move?k=w").await, 204);
    assert_eq!(get(addr, "/move?k=look&dx=3&dy=-2").await, 204);
    assert_eq!(rx.try_recv().unwrap(), Move::Forward);
    assert_eq!(rx.try_recv().unwrap(), Move::Drag { dx: 3.0, dy: -2.0 });
    // A display that does not keep up: refused, not queued without bound.
    for _ in 0..dray_actors::display::web::MOVE_QUEUE {
        assert_eq!(get(addr, "/move?k=e").await, 204);
    }
    assert_eq!(get(addr, "/move?k=e").await, 503);
    // The page still comes, with the controls.
    let (status, page) = request(addr, b"GET / HTTP/1.1\r\n\r\n").await;
    assert_eq!(status, 200);
    let page = String::from_utf8(page).unwrap();
    assert!(page.contains("/move?") && page.contains("/metrics.json"));
    // The display gone: 503.
    drop(rx);
    assert_eq!(get(addr, "/move?k=w").await, 503);

    // A viewer that is not interactive has no /move.
    let ro = WebViewer::start("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    assert_eq!(get(ro.local_addr(), "/move?k=w").await, 404);
    assert_eq!(get(ro.local_addr(), "/").await, 200);
}
