//! The live web viewer over a real loopback socket.

use dray_actors::display::{FrameImage, FrameMetrics, WebViewer};
use dray_protocol::FrameStats;
use std::net::SocketAddr;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;

/// Sends raw bytes, returns (status, headers, body).
async fn request(addr: SocketAddr, raw: &[u8]) -> (u16, String, Vec<u8>) {
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
    (status, head, out[end + 4..].to_vec())
}

async fn get(addr: SocketAddr, path: &str) -> (u16, String, Vec<u8>) {
    let req = format!("GET {path} HTTP/1.1\r\nHost: localhost\r\nUser-Agent: test\r\n\r\n");
    request(addr, req.as_bytes()).await
}

fn decode_png(png: &[u8]) -> (u32, u32, Vec<[u8; 4]>) {
    dray_trace::image::decode_png(png).expect("a valid PNG")
}

#[tokio::test]
async fn display_web_viewer_serves_page_frame_and_metrics() {
    let v = WebViewer::start("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let addr = v.local_addr();
    assert_ne!(addr.port(), 0);

    let (status, _, body) = get(addr, "/").await;
    assert_eq!(status, 200);
    let page = String::from_utf8(body).unwrap();
    assert!(page.contains("/frame.png?n="));
    assert!(page.contains("/metrics.json"));
    let (status, _, _) = get(addr, "/frame.png").await;
    assert_eq!(status, 503, "no frame yet");
    let (status, _, body) = get(addr, "/metrics.json").await;
    assert_eq!((status, body.as_slice()), (200, &b"null"[..]));

    // A frame wider than one stored block (65535 bytes).
    let (w, h) = (300u32, 70u32);
    let rgba: Vec<[u8; 4]> = (0..w * h)
        .map(|i| [(i % w) as u8, (i / w) as u8, (i % 251) as u8, 255])
        .collect();
    let image = FrameImage {
        frame: 12,
        rgba: rgba.clone(),
        depth: None,
        primid: None,
    };
    let m = FrameMetrics::compute(12, &FrameStats::default(), 40.0);
    v.publish(w, h, &image, &m);

    let (status, head, body) = get(addr, "/frame.png?n=12").await;
    assert_eq!(status, 200);
    assert!(head.contains("Content-Type: image/png"));
    assert!(head.contains(&format!("Content-Length: {}", body.len())));
    assert_eq!(decode_png(&body), (w, h, rgba));
    let (status, _, body) = get(addr, "/metrics.json").await;
    assert_eq!(status, 200);
    let j: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(j["frame"], 12);
    assert_eq!(j["fps"], 25.0);

    // HEAD: the headers only.
    let (status, _, png) = get(addr, "/frame.png").await;
    assert_eq!(status, 200);
    let (status, head, body) = request(addr, b"HEAD /frame.png HTTP/1.1\r\n\r\n").await;
    assert_eq!(status, 200);
    assert!(head.contains("Content-Length: "));
    // HEAD says the length GET sends.
    assert!(
        head.contains(&format!("Content-Length: {}", png.len())),
        "{head}"
    );
    assert!(body.is_empty());
}

#[tokio::test]
async fn display_web_viewer_refuses_bad_requests_and_keeps_serving() {
    let v = WebViewer::start("127.0.0.1:0".parse().unwrap())
        .await
        .unwrap();
    let addr = v.local_addr();
    let bad: [&[u8]; 7] = [
        b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03garbage\r\n\r\n",
        b"hello\r\n\r\n",
        b"GET\r\n\r\n",
        b"GET frame.png HTTP/1.1\r\n\r\n",
        b"GET / SPDY/3\r\n\r\n",
        b"GET / HTTP/1.1 extra\r\n\r\n",
        b"\r\n\r\n",
    ];
    for raw in bad {
        let (status, _, _) = request(addr, raw).await;
        assert_eq!(status, 400, "{:?}", String::from_utf8_lossy(raw));
    }
    let (status, _, _) = request(addr, b"POST / HTTP/1.1\r\nContent-Length: 0\r\n\r\n").await;
    assert_eq!(status, 405);
    let (status, _, _) = get(addr, "/nope").await;
    assert_eq!(status, 404);
    // A head that never ends: refused once over the limit.
    let mut huge = b"GET / HTTP/1.1\r\n".to_vec();
    while huge.len() < 20_000 {
        huge.extend_from_slice(b"X-Filler: aaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaaa\r\n");
    }
    let mut s = TcpStream::connect(addr).await.unwrap();
    // The server may close before all of it is written.
    let _ = s.write_all(&huge).await;
    let mut out = Vec::new();
    let _ = s.read_to_end(&mut out).await;
    assert!(
        String::from_utf8_lossy(&out).starts_with("HTTP/1.1 431"),
        "{:?}",
        String::from_utf8_lossy(&out[..out.len().min(80)])
    );
    // A client that connects and says nothing does not block the others.
    let _idle = TcpStream::connect(addr).await.unwrap();
    // Half a request, then the connection closes.
    {
        let mut s = TcpStream::connect(addr).await.unwrap();
        s.write_all(b"GET / HT").await.unwrap();
    }
    let (status, _, _) = get(addr, "/").await;
    assert_eq!(status, 200, "still serving");
}

#[tokio::test]
async fn display_web_viewer_shows_the_displays_latest_frame() {
    use dray_actors::display::{run_display, DisplayOptions};
    use dray_actors::names;
    use dray_protocol::{
        Camera, FrameDone, Message, Name, Role, Shutdown, TileDone, TilePixels, TileRect, TileStats,
    };
    use dray_runtime::{Delivery, InProcNet};

    // A free port (the display binds it itself).
    let addr = std::net::TcpListener::bind("127.0.0.1:0")
        .unwrap()
        .local_addr()
        .unwrap();
    let net = InProcNet::new();
    let sched = net
        .add_node(Name::new("scheduler").unwrap(), Role::Scheduler)
        .unwrap();
    let disp = net
        .add_node(Name::new("display").unwrap(), Role::Display)
        .unwrap();
    let mut assigner = sched
        .mailbox(Name::new(names::ASSIGNER).unwrap(), 16)
        .unwrap();
    let mb = disp
        .mailbox(Name::new(names::DISPLAY).unwrap(), 64)
        .unwrap();
    // Next to the display, on its node: what stops it.
    let control = disp.mailbox(Name::new("control").unwrap(), 4).unwrap();
    // Tiles come from a client (the only role that may send them).
    let client = net
        .add_node(names::client_node(0), Role::Client)
        .unwrap()
        .mailbox(Name::new(names::CLIENT).unwrap(), 4)
        .unwrap();
    let cam = Camera {
        eye: [0.0, 0.0, -5.0],
        look: [0.0; 3],
        up: [0.0, 1.0, 0.0],
        fov_y_deg: 45.0,
    };
    let display = tokio::spawn(run_display(
        mb,
        DisplayOptions {
            assigner: names::assigner(),
            scheduler: names::scheduler(),
            width: 8,
            height: 4,
            cameras: vec![cam; 3],
            interactive: false,
            frames_ahead: 1,
            output: None,
            save_frames: true,
            keep_frames: false,
            web: Some(addr),
            samples: 1,
        },
    ));
    let camera = |d: Option<Delivery>| match d {
        Some(Delivery::Message {
            msg: Message::CameraUpdate(c),
            ..
        }) => Some(c.seq),
        _ => None,
    };
    let mut seq = None;
    while seq.is_none() {
        seq = camera(assigner.recv().await);
    }
    assert_eq!(seq, Some(0));
    let rgba: Vec<[u8; 4]> = (0..32u8).map(|i| [i, 2 * i, 3 * i, 255]).collect();
    client
        .send(
            &names::display(),
            Message::TileDone(TileDone {
                frame: 0,
                tile: TileRect {
                    x: 0,
                    y: 0,
                    w: 8,
                    h: 4,
                },
                pixels: TilePixels::encode(&rgba),
                depth: None,
                prim_ids: None,
                stats: TileStats::default(),
                hits: Default::default(),
            }),
        )
        .await
        .unwrap();
    assigner
        .send(
            &names::display(),
            Message::FrameDone(FrameDone {
                frame: 0,
                stats: Default::default(),
            }),
        )
        .await
        .unwrap();
    // Frame 0 shown: the display asks for frame 1.
    let mut seq = None;
    while seq.is_none() {
        seq = camera(assigner.recv().await);
    }
    assert_eq!(seq, Some(1));
    let (status, _, body) = get(addr, "/frame.png").await;
    assert_eq!(status, 200);
    let (w, h, px) = decode_png(&body);
    assert_eq!((w, h), (8, 4));
    assert_eq!(px, rgba);
    let (_, _, body) = get(addr, "/metrics.json").await;
    let j: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(j["frame"], 0);
    control
        .send(
            &names::display(),
            Message::Shutdown(Shutdown {
                reason: "done".into(),
            }),
        )
        .await
        .unwrap();
    let s = display.await.unwrap().unwrap();
    assert_eq!(s.frames.len(), 1);
    assert!(s.images.is_empty(), "keep_frames off");
}
