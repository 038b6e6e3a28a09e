//! The live web viewer over a real loopback socket: the page, the token,
//! the WebSocket's frames and messages, and what it refuses.

use dray_actors::display::web::{wire, MAX_INPUT_BYTES, MAX_PATH_BYTES};
use dray_actors::display::{FrameMetrics, ShownFrame, WebOptions, WebViewer};
use dray_protocol::FrameStats;
use futures::{SinkExt, StreamExt};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tokio_tungstenite::tungstenite::Message as Ws;

const SOON: Duration = Duration::from_secs(5);

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
    let req = format!(
        "GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\nUser-Agent: test\r\n\r\n"
    );
    request(addr, req.as_bytes()).await
}

fn token_of(v: &WebViewer) -> String {
    v.url().split("token=").nth(1).unwrap().to_string()
}

fn frame(n: u64, (w, h): (u32, u32), samples: u32, still: bool) -> (ShownFrame, Vec<[u8; 4]>) {
    let rgba: Vec<[u8; 4]> = (0..w * h)
        .map(|i| [(i % w) as u8, (i / w) as u8, (i % 251) as u8, 255])
        .collect();
    let m = FrameMetrics::compute(n, &FrameStats::default(), 40.0);
    let f = ShownFrame::new(
        n,
        (w, h),
        Arc::new(rgba.clone()),
        (samples, 3, still, None),
        m,
    );
    (f, rgba)
}

type Socket = tokio_tungstenite::WebSocketStream<tokio_tungstenite::MaybeTlsStream<TcpStream>>;

async fn socket(addr: SocketAddr, token: &str, origin: Option<&str>) -> Result<Socket, String> {
    let mut req = format!("ws://{addr}/ws?token={token}")
        .into_client_request()
        .unwrap();
    if let Some(o) = origin {
        req.headers_mut().insert("Origin", o.parse().unwrap());
    }
    tokio_tungstenite::connect_async(req)
        .await
        .map(|(s, _)| s)
        .map_err(|e| e.to_string())
}

/// The next text message, as JSON.
async fn next_text(ws: &mut Socket) -> serde_json::Value {
    loop {
        let m = tokio::time::timeout(SOON, ws.next())
            .await
            .expect("a message in time")
            .expect("the socket open")
            .unwrap();
        if let Ws::Text(t) = m {
            return serde_json::from_str(&t).unwrap();
        }
    }
}

/// The next frame: its header and image bytes.
async fn next_frame(ws: &mut Socket) -> (serde_json::Value, Vec<u8>) {
    loop {
        let m = tokio::time::timeout(SOON, ws.next())
            .await
            .expect("a frame in time")
            .expect("the socket open")
            .unwrap();
        if let Ws::Binary(b) = m {
            let n = u32::from_le_bytes(b[..4].try_into().unwrap()) as usize;
            let head = serde_json::from_slice(&b[4..4 + n]).unwrap();
            return (head, b[4 + n..].to_vec());
        }
    }
}

#[tokio::test]
async fn display_web_viewer_serves_the_page_and_frames_only_with_the_token() {
    let opts = WebOptions {
        interactive: false,
        token: None,
    };
    let (v, inputs) = WebViewer::start("127.0.0.1:0".parse().unwrap(), opts)
        .await
        .unwrap();
    assert!(inputs.is_none(), "a path's viewer takes no inputs");
    let addr = v.local_addr();
    let token = token_of(&v);
    assert!(wire::valid_token(&token));

    let (status, _, body) = get(addr, "/").await;
    assert_eq!(status, 200);
    let page = String::from_utf8(body).unwrap();
    assert!(page.contains("/ws?token=") && page.contains("<canvas"));

    for path in [
        "/frame.png",
        "/metrics.json",
        "/frame.png?token=",
        "/metrics.json?token=abc",
    ] {
        assert_eq!(get(addr, path).await.0, 403, "{path}");
    }
    assert_eq!(
        get(addr, &format!("/frame.png?token={token}")).await.0,
        503,
        "no frame yet"
    );
    let (status, _, body) = get(addr, &format!("/metrics.json?token={token}")).await;
    assert_eq!((status, body.as_slice()), (200, &b"null"[..]));
    assert_eq!(get(addr, "/nope").await.0, 404);

    let (f, rgba) = frame(12, (300, 70), 1, false);
    v.publish(f);
    let (status, head, body) = get(addr, &format!("/frame.png?token={token}")).await;
    assert_eq!(status, 200);
    assert!(
        head.to_ascii_lowercase()
            .contains("content-type: image/png"),
        "{head}"
    );
    assert_eq!(
        dray_trace::image::decode_png(&body).unwrap(),
        (300, 70, rgba)
    );
    let (_, _, body) = get(addr, &format!("/metrics.json?token={token}")).await;
    let j: serde_json::Value = serde_json::from_slice(&body).unwrap();
    assert_eq!(
        (j["frame"].as_u64(), j["fps"].as_f64()),
        (Some(12), Some(25.0))
    );
}

#[tokio::test]
async fn display_web_viewer_pushes_frames_and_status_over_the_socket() {
    let opts = WebOptions {
        interactive: false,
        token: Some("abcdefghijklmnop0123".into()),
    };
    let (v, _) = WebViewer::start("127.0.0.1:0".parse().unwrap(), opts)
        .await
        .unwrap();
    let addr = v.local_addr();
    assert_eq!(
        v.url(),
        format!("http://{addr}/?token=abcdefghijklmnop0123")
    );
    assert!(socket(addr, "wrong", None).await.is_err(), "a wrong token");
    assert!(
        socket(addr, "abcdefghijklmnop0123", Some("http://evil.example"))
            .await
            .is_err(),
        "another site's page"
    );
    let origin = format!("http://{addr}");
    let mut ws = socket(addr, "abcdefghijklmnop0123", Some(&origin))
        .await
        .unwrap();
    let hello = next_text(&mut ws).await;
    assert_eq!(hello["type"], "status");
    assert_eq!(hello["interactive"], false);

    // A moving frame comes as JPEG, a still one as PNG, exactly.
    let (f, _) = frame(1, (64, 48), 1, false);
    v.publish(f);
    let (head, img) = next_frame(&mut ws).await;
    assert_eq!(
        (head["frame"].as_u64(), head["format"].as_str()),
        (Some(1), Some("jpeg"))
    );
    assert_eq!(&img[..2], &[0xFF, 0xD8], "a JPEG");
    let (f, rgba) = frame(2, (64, 48), 4, true);
    v.publish(f);
    let (head, img) = next_frame(&mut ws).await;
    assert_eq!(head["format"], "png");
    assert_eq!(
        (head["samples"].as_u64(), head["still"].as_bool()),
        (Some(4), Some(true))
    );
    assert_eq!(head["metrics"]["frame"], 2);
    assert_eq!(dray_trace::image::decode_png(&img).unwrap(), (64, 48, rgba));

    // Inputs to a path's viewer are answered with an error, not taken.
    ws.send(Ws::Text("\"home\"".into())).await.unwrap();
    let e = next_text(&mut ws).await;
    assert_eq!(e["type"], "error");

    // The run's end reaches the page.
    v.set_status(|s| s.ended = Some("every frame is shown".into()));
    let s = next_text(&mut ws).await;
    assert_eq!(s["ended"], "every frame is shown");
}

#[tokio::test]
async fn display_web_viewer_takes_inputs_refuses_garbage_and_keeps_serving() {
    let opts = WebOptions {
        interactive: true,
        token: None,
    };
    let (v, inputs) = WebViewer::start("127.0.0.1:0".parse().unwrap(), opts)
        .await
        .unwrap();
    let mut inputs = inputs.expect("an interactive viewer's inputs");
    let addr = v.local_addr();
    let token = token_of(&v);
    let mut ws = socket(addr, &token, None).await.unwrap();
    assert_eq!(next_text(&mut ws).await["interactive"], true);
    for bad in [
        "",
        "{}",
        "\"away\"",
        r#"{"fly":{"sideways":1}}"#,
        "[1]",
        "{\"zoom\":",
    ] {
        ws.send(Ws::Text(bad.into())).await.unwrap();
        let e = next_text(&mut ws).await;
        assert_eq!(e["type"], "error", "{bad:?}");
    }
    // An input longer than an input may be is refused; a message longer
    // than a path to play closes the socket; the server goes on.
    let long = format!(r#"{{"zoom":{{"steps":1{}}}}}"#, " ".repeat(MAX_INPUT_BYTES));
    ws.send(Ws::Text(long.into())).await.unwrap();
    let e = next_text(&mut ws).await;
    assert!(
        e["message"].as_str().unwrap().starts_with("an input of"),
        "{e}"
    );
    ws.send(Ws::Text("x".repeat(MAX_PATH_BYTES + 1).into()))
        .await
        .ok();
    let closed = tokio::time::timeout(SOON, async {
        while let Some(Ok(m)) = ws.next().await {
            if let Ws::Close(_) = m {
                break;
            }
        }
    })
    .await;
    assert!(closed.is_ok(), "an oversized message ends the socket");
    assert!(inputs.try_recv().is_err(), "nothing taken");

    let mut ws = socket(addr, &token, None).await.unwrap();
    next_text(&mut ws).await;
    ws.send(Ws::Text(r#"{"fly":{"forward":2,"yaw":5}}"#.into()))
        .await
        .unwrap();
    ws.send(Ws::Text("\"home\"".into())).await.unwrap();
    let got = tokio::time::timeout(SOON, inputs.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(
        got,
        dray_actors::display::ViewInput::Fly {
            forward: 2.0,
            right: 0.0,
            up: 0.0,
            yaw_deg: 5.0,
            pitch_deg: 0.0
        }
    );
    let got = tokio::time::timeout(SOON, inputs.recv())
        .await
        .unwrap()
        .unwrap();
    assert_eq!(got, dray_actors::display::ViewInput::Home);

    // Raw garbage on the HTTP port does not stop it.
    for raw in [
        &b"hello\r\n\r\n"[..],
        b"\x16\x03\x01garbage\r\n\r\n",
        b"GET\r\n\r\n",
    ] {
        let mut s = TcpStream::connect(addr).await.unwrap();
        let _ = s.write_all(raw).await;
        let mut out = Vec::new();
        let _ = tokio::time::timeout(SOON, s.read_to_end(&mut out)).await;
    }
    assert_eq!(get(addr, "/").await.0, 200, "still serving");
}
