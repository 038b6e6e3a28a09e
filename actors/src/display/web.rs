//! The live web viewer: a tiny HTTP/1.1 server (GET and HEAD only, one
//! request per connection) on a tokio listener, without dependencies.
//!
//! - `/` a page that shows the latest complete frame and its figures and
//!   refreshes them (it polls `/metrics.json` and loads `/frame.png?n=N`
//!   when a new frame is there);
//! - `/frame.png` the latest frame (503 before the first one);
//! - `/metrics.json` the latest [`FrameMetrics`] (`null` before the first);
//! - `/move?k=KEY` (interactive mode, [`WebViewer::start_interactive`]) a
//!   camera move ([`Move::parse`] lists the keys), handed to the display
//!   through a bounded channel: 204 when taken, 400 for an unknown move,
//!   503 when the display is behind (the channel full) or gone, 404 when
//!   the viewer is not interactive. GET only: it is a local tool.
//!
//! Requests are bounded: the head must fit in [`MAX_HEAD`] bytes and arrive
//! within [`READ_TIMEOUT`], at most [`MAX_CONNECTIONS`] are served at once
//! (more are closed at once), and anything that is not a well-formed GET
//! gets a 4xx answer; nothing a client sends can stop the server.

use super::moves::Move;
use super::{FrameImage, FrameMetrics};
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard};
use std::time::Duration;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::{TcpListener, TcpStream};
use tokio::sync::{mpsc, Semaphore};
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};

/// Largest request head (request line and headers), bytes.
pub const MAX_HEAD: usize = 8 << 10;
/// Time a client has to send its request head.
pub const READ_TIMEOUT: Duration = Duration::from_secs(5);
/// Time a client has to take the answer.
pub const WRITE_TIMEOUT: Duration = Duration::from_secs(20);
/// Bytes read and dropped after refusing a request, before closing.
const LINGER_BYTES: usize = 64 << 10;
/// Time spent on that at most.
const LINGER_TIME: Duration = Duration::from_secs(1);
/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 64;
/// Moves waiting for the display; more are refused with 503.
pub const MOVE_QUEUE: usize = 64;

#[derive(Default)]
struct Latest {
    width: u32,
    height: u32,
    frame: Option<u64>,
    rgba: Arc<Vec<[u8; 4]>>,
    /// The PNG of `frame`, encoded on the first request for it.
    png: Option<(u64, Arc<Vec<u8>>)>,
    metrics_json: Option<String>,
}

fn lock(m: &Mutex<Latest>) -> MutexGuard<'_, Latest> {
    m.lock().unwrap_or_else(|e| e.into_inner())
}

/// What the connections share.
struct Shared {
    latest: Mutex<Latest>,
    /// Where `/move` requests go; `None`: not interactive.
    moves: Option<mpsc::Sender<Move>>,
}

/// A running viewer; stops when dropped.
pub struct WebViewer {
    addr: SocketAddr,
    shared: Arc<Shared>,
    task: JoinHandle<()>,
}

impl WebViewer {
    /// Listens on `addr` (port 0: any free port, see [`Self::local_addr`]);
    /// `/move` is refused (404).
    pub async fn start(addr: SocketAddr) -> io::Result<WebViewer> {
        Self::listen(addr, None).await
    }

    /// Like [`Self::start`], and takes camera moves on `/move`: they come
    /// out of the receiver, at most [`MOVE_QUEUE`] waiting.
    pub async fn start_interactive(
        addr: SocketAddr,
    ) -> io::Result<(WebViewer, mpsc::Receiver<Move>)> {
        let (tx, rx) = mpsc::channel(MOVE_QUEUE);
        Ok((Self::listen(addr, Some(tx)).await?, rx))
    }

    async fn listen(addr: SocketAddr, moves: Option<mpsc::Sender<Move>>) -> io::Result<WebViewer> {
        let listener = TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let interactive = moves.is_some();
        let shared = Arc::new(Shared {
            latest: Mutex::new(Latest::default()),
            moves,
        });
        let task = tokio::spawn(serve(listener, shared.clone()));
        if interactive {
            info!("web viewer on http://{addr}/ (interactive: w/s/a/d/q/e/r/f, arrows, drag)");
        } else {
            info!("web viewer on http://{addr}/");
        }
        Ok(WebViewer { addr, shared, task })
    }

    /// Where it listens.
    pub fn local_addr(&self) -> SocketAddr {
        self.addr
    }

    /// Shows `image` (of `width × height`) and its metrics from now on.
    pub fn publish(&self, width: u32, height: u32, image: &FrameImage, metrics: &FrameMetrics) {
        let json = serde_json::to_string(metrics).ok();
        let mut l = lock(&self.shared.latest);
        l.width = width;
        l.height = height;
        l.frame = Some(image.frame);
        l.rgba = Arc::new(image.rgba.clone());
        l.png = None;
        l.metrics_json = json;
    }
}

impl Drop for WebViewer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

async fn serve(listener: TcpListener, shared: Arc<Shared>) {
    let slots = Arc::new(Semaphore::new(MAX_CONNECTIONS));
    loop {
        let (stream, peer) = match listener.accept().await {
            Ok(c) => c,
            Err(e) => {
                // Out of file descriptors and the like: wait a little.
                warn!("web viewer: accept failed: {e}");
                tokio::time::sleep(Duration::from_millis(50)).await;
                continue;
            }
        };
        let Ok(permit) = slots.clone().try_acquire_owned() else {
            debug!("web viewer: too many connections, closing {peer}");
            continue;
        };
        let shared = shared.clone();
        tokio::spawn(async move {
            if let Err(e) = connection(stream, &shared).await {
                debug!("web viewer: {peer}: {e}");
            }
            drop(permit);
        });
    }
}

struct Response {
    status: u16,
    content_type: &'static str,
    body: Arc<Vec<u8>>,
    extra: &'static str,
}

impl Response {
    fn text(status: u16, body: &str) -> Response {
        Response {
            status,
            content_type: "text/plain; charset=utf-8",
            body: Arc::new(format!("{body}\n").into_bytes()),
            extra: "",
        }
    }
}

fn reason(status: u16) -> &'static str {
    match status {
        200 => "OK",
        204 => "No Content",
        400 => "Bad Request",
        404 => "Not Found",
        405 => "Method Not Allowed",
        408 => "Request Timeout",
        431 => "Request Header Fields Too Large",
        500 => "Internal Server Error",
        503 => "Service Unavailable",
        _ => "Error",
    }
}

/// Reads the request head: `Ok(Err(status))` for a request to refuse.
async fn read_head(stream: &mut TcpStream) -> io::Result<Result<Vec<u8>, u16>> {
    let mut buf = Vec::with_capacity(1024);
    let mut chunk = [0u8; 1024];
    let read = async {
        loop {
            if let Some(end) = head_end(&buf) {
                buf.truncate(end);
                return Ok(Ok(buf));
            }
            if buf.len() > MAX_HEAD {
                return Ok(Err(431));
            }
            let n = stream.read(&mut chunk).await?;
            if n == 0 {
                // Closed before the head ended.
                return if buf.is_empty() {
                    Err(io::Error::new(io::ErrorKind::UnexpectedEof, "closed"))
                } else {
                    Ok(Err(400))
                };
            }
            buf.extend_from_slice(&chunk[..n]);
        }
    };
    match tokio::time::timeout(READ_TIMEOUT, read).await {
        Ok(r) => r,
        Err(_) => Ok(Err(408)),
    }
}

fn head_end(buf: &[u8]) -> Option<usize> {
    let crlf = buf.windows(4).position(|w| w == b"\r\n\r\n");
    let lf = buf.windows(2).position(|w| w == b"\n\n");
    match (crlf, lf) {
        (Some(a), Some(b)) => Some(a.min(b)),
        (a, b) => a.or(b),
    }
}

async fn connection(mut stream: TcpStream, shared: &Shared) -> io::Result<()> {
    let (resp, head_only) = match read_head(&mut stream).await? {
        Err(status) => (Response::text(status, reason(status)), false),
        Ok(head) => match parse_request_line(&head) {
            Err(status) => (Response::text(status, reason(status)), false),
            // A move has an effect: not for HEAD.
            Ok((method, path, _)) if method == "HEAD" && path == "/move" => {
                (Response::text(405, reason(405)), false)
            }
            Ok((method, path, query)) => (route(&path, &query, shared).await, method == "HEAD"),
        },
    };
    let head = format!(
        "HTTP/1.1 {} {}\r\nContent-Type: {}\r\nContent-Length: {}\r\nCache-Control: no-store\r\nConnection: close\r\n{}\r\n",
        resp.status,
        reason(resp.status),
        resp.content_type,
        resp.body.len(),
        resp.extra
    );
    let write = async {
        stream.write_all(head.as_bytes()).await?;
        if !head_only {
            stream.write_all(&resp.body).await?;
        }
        stream.flush().await?;
        stream.shutdown().await
    };
    match tokio::time::timeout(WRITE_TIMEOUT, write).await {
        Ok(r) => r?,
        Err(_) => return Err(io::Error::new(io::ErrorKind::TimedOut, "write timed out")),
    }
    if resp.status >= 400 {
        // A refused request may have left bytes unread; closing on them
        // would reset the connection and lose the answer. Drain a bounded
        // amount for a bounded time first (a "lingering close").
        let mut sink = [0u8; 4096];
        let mut left = LINGER_BYTES;
        let drain = async {
            while left > 0 {
                match stream.read(&mut sink).await {
                    Ok(0) | Err(_) => break,
                    Ok(n) => left = left.saturating_sub(n),
                }
            }
        };
        let _ = tokio::time::timeout(LINGER_TIME, drain).await;
    }
    Ok(())
}

/// `(method, path, query)` of a GET or HEAD request (the query without
/// its `?`, empty when none), or the status to answer.
fn parse_request_line(head: &[u8]) -> Result<(String, String, String), u16> {
    let text = std::str::from_utf8(head).map_err(|_| 400u16)?;
    let line = text.lines().next().ok_or(400u16)?;
    let mut parts = line.split(' ');
    let (Some(method), Some(target), Some(version), None) =
        (parts.next(), parts.next(), parts.next(), parts.next())
    else {
        return Err(400);
    };
    if !version.starts_with("HTTP/1.") || !target.starts_with('/') {
        return Err(400);
    }
    if method.is_empty() || !method.bytes().all(|b| b.is_ascii_uppercase()) {
        return Err(400);
    }
    if method != "GET" && method != "HEAD" {
        return Err(405);
    }
    let target = target.split('#').next().unwrap_or("/");
    let (path, query) = target.split_once('?').unwrap_or((target, ""));
    Ok((method.to_string(), path.to_string(), query.to_string()))
}

/// Hands a `/move` request's move to the display.
fn take_move(query: &str, shared: &Shared) -> Response {
    let Some(tx) = &shared.moves else {
        return Response::text(404, "not interactive (the config has a camera path)");
    };
    let Some(m) = Move::parse(query) else {
        return Response::text(
            400,
            "unknown move: use k=w|s|a|d|q|e|r|f|left|right|up|down or k=look&dx=N&dy=N",
        );
    };
    match tx.try_send(m) {
        Ok(()) => Response {
            status: 204,
            content_type: "text/plain; charset=utf-8",
            body: Arc::new(Vec::new()),
            extra: "",
        },
        Err(mpsc::error::TrySendError::Full(_)) => Response {
            extra: "Retry-After: 1\r\n",
            ..Response::text(503, "too many moves waiting")
        },
        Err(mpsc::error::TrySendError::Closed(_)) => Response::text(503, "the display has stopped"),
    }
}

async fn route(path: &str, query: &str, shared: &Shared) -> Response {
    let latest = &shared.latest;
    match path {
        "/move" => take_move(query, shared),
        "/" | "/index.html" => Response {
            status: 200,
            content_type: "text/html; charset=utf-8",
            body: Arc::new(PAGE.as_bytes().to_vec()),
            extra: "",
        },
        "/frame.png" => {
            let (frame, w, h, rgba) = {
                let mut l = lock(latest);
                let Some(frame) = l.frame else {
                    return Response {
                        extra: "Retry-After: 1\r\n",
                        ..Response::text(503, "no frame yet")
                    };
                };
                if let Some((f, png)) = &l.png {
                    if *f == frame {
                        return png_response(png.clone());
                    }
                }
                l.png = None;
                (frame, l.width, l.height, l.rgba.clone())
            };
            // Encode outside the lock and off the display's thread (a
            // node runs one: its tiles and transport wait meanwhile); the
            // first request for a frame caches it for the others.
            let encoded =
                tokio::task::spawn_blocking(move || dray_trace::image::encode_png(w, h, &rgba))
                    .await;
            let png = match encoded {
                Ok(Ok(png)) => Arc::new(png),
                Ok(Err(e)) => {
                    warn!(error = %e, "encoding the frame failed");
                    return Response::text(500, "the frame could not be encoded");
                }
                Err(e) => {
                    warn!(error = %e, "the encoding task failed");
                    return Response::text(500, "the frame could not be encoded");
                }
            };
            let mut l = lock(latest);
            if l.frame == Some(frame) {
                l.png = Some((frame, png.clone()));
            }
            png_response(png)
        }
        "/metrics.json" => {
            let json = lock(latest)
                .metrics_json
                .clone()
                .unwrap_or_else(|| "null".into());
            Response {
                status: 200,
                content_type: "application/json",
                body: Arc::new(json.into_bytes()),
                extra: "",
            }
        }
        _ => Response::text(404, "not found"),
    }
}

fn png_response(png: Arc<Vec<u8>>) -> Response {
    Response {
        status: 200,
        content_type: "image/png",
        body: png,
        extra: "",
    }
}

const PAGE: &str = r#"<!doctype html>
<html><head><meta charset="utf-8"><title>dray</title>
<style>
body { background: #111; color: #ddd; font: 14px monospace; margin: 1em; }
img { image-rendering: pixelated; max-width: 100%; border: 1px solid #333; }
#m { white-space: pre; margin-top: .5em; }
#c { color: #888; margin-bottom: .5em; }
</style></head>
<body>
<div><b>dray</b> live view</div>
<div id="c">interactive: w/s forward/back, a/d strafe, q/e or &larr;/&rarr; turn,
&uarr;/&darr; look up/down, r/f up/down, drag the image to look around
<span id="k"></span></div>
<img id="f" alt="waiting for the first frame" draggable="false">
<div id="m">waiting for the first frame…</div>
<script>
// Camera moves: GET /move?k=KEY (404 when the display follows a path).
const keys = {w:'w', s:'s', a:'a', d:'d', q:'q', e:'e', r:'r', f:'f',
  ArrowLeft:'left', ArrowRight:'right', ArrowUp:'up', ArrowDown:'down'};
const k = document.getElementById('k'), c = document.getElementById('c');
async function send(q) {
  try {
    const r = await fetch('/move?' + q, {cache: 'no-store'});
    if (r.status === 404) { c.textContent = 'camera path: the view is read-only'; }
    else if (!r.ok) { k.textContent = ' (' + r.status + ')'; }
    else { k.textContent = ''; }
  } catch (e) { k.textContent = ' (display unreachable)'; }
}
document.addEventListener('keydown', (ev) => {
  const key = keys[ev.key] || keys[ev.key.toLowerCase()];
  if (!key || ev.ctrlKey || ev.metaKey || ev.altKey) return;
  ev.preventDefault();
  send('k=' + key);
});
let drag = null, dx = 0, dy = 0, pending = false;
const fimg = document.getElementById('f');
fimg.addEventListener('mousedown', (ev) => { drag = [ev.clientX, ev.clientY]; ev.preventDefault(); });
document.addEventListener('mouseup', () => { drag = null; });
document.addEventListener('mousemove', (ev) => {
  if (!drag) return;
  dx += ev.clientX - drag[0]; dy += ev.clientY - drag[1];
  drag = [ev.clientX, ev.clientY];
  if (!pending) {
    pending = true;
    // One drag move per 50 ms at most.
    setTimeout(() => { pending = false; if (dx || dy) { send('k=look&dx=' + dx + '&dy=' + dy); dx = dy = 0; } }, 50);
  }
});
let shown = -1, loading = false;
const img = document.getElementById('f'), m = document.getElementById('m');
async function poll() {
  try {
    const r = await fetch('/metrics.json', {cache: 'no-store'});
    const j = await r.json();
    if (j && j.frame !== shown && !loading) {
      loading = true;
      const next = new Image();
      next.onload = () => { img.src = next.src; shown = j.frame; loading = false; };
      next.onerror = () => { loading = false; };
      next.src = '/frame.png?n=' + j.frame;
      m.textContent = 'frame ' + j.frame + '   ' + j.frame_ms.toFixed(1) + ' ms   ' +
        j.fps.toFixed(2) + ' fps   ' + j.mrays_per_s.toFixed(2) + ' Mrays/s\n' +
        'tiles ' + j.tiles + ' (reassigned ' + j.reassigned + ')   fetched ' +
        (j.bytes_fetched / 1048576).toFixed(1) + ' MiB   misses ' + j.misses +
        '   hit rate ' + (100 * j.cache_hit_rate).toFixed(1) + ' %   stall ' +
        j.stall_ms.toFixed(1) + ' ms\n' + j.tiles_per_client;
    }
  } catch (e) { /* the display may have stopped; keep trying */ }
  setTimeout(poll, 200);
}
poll();
</script>
</body></html>
"#;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn request_lines() {
        assert_eq!(
            parse_request_line(b"GET /frame.png?n=3 HTTP/1.1\r\nHost: x"),
            Ok(("GET".into(), "/frame.png".into(), "n=3".into()))
        );
        assert_eq!(parse_request_line(b"POST / HTTP/1.1"), Err(405));
        assert_eq!(parse_request_line(b"\xff\xfe"), Err(400));
        assert_eq!(parse_request_line(b"GET /"), Err(400));
        assert_eq!(parse_request_line(b"GET x HTTP/1.1"), Err(400));
        assert_eq!(parse_request_line(b""), Err(400));
    }
}
