//! The live web viewer: an axum server whose page draws the display's
//! frames on a canvas as they are shown, pushed over a WebSocket, and sends
//! a person's inputs back on the same socket.
//!
//! - `GET /` the page ([`PAGE`]: canvas, controls, stats overlay); it reads
//!   the token from its own address and opens the socket;
//! - `GET /ws?token=T` the WebSocket ([`wire`] has what travels on it):
//!   the server sends a `hello`, then every frame shown (a binary message:
//!   JPEG while the view changes, PNG once it is refined), the view's
//!   choices when they change, pick answers, recorded flights, and
//!   `ended` when the run ends; the page sends inputs
//!   ([`super::view::ViewInput`]), taken only in interactive mode;
//! - `GET /frame.png?token=T`, `GET /metrics.json?token=T` the latest frame
//!   and its metrics, for scripts.
//!
//! Every route but the page needs the run's token (printed with the URL);
//! a WebSocket whose `Origin` is not the address it asked for is refused
//! (another site's page cannot drive the viewer), and at most
//! [`MAX_CONNECTIONS`] are served at once. A page that cannot keep up is
//! sent the newest frame when it is ready for one: frames in between are
//! skipped, never queued.

pub mod wire;

use super::record::Recording;
use super::view::{Choices, Picked, ViewInput};
use super::FrameMetrics;
use axum::extract::ws::{Message as WsMessage, WebSocket, WebSocketUpgrade};
use axum::extract::{Query, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::response::{Html, IntoResponse, Response};
use axum::routing::get;
use axum::Router;
use std::io;
use std::net::SocketAddr;
use std::sync::{Arc, OnceLock};
use tokio::sync::{broadcast, mpsc, watch, Semaphore};
use tokio::task::JoinHandle;
use tracing::{debug, info, warn};

/// The page, with its script and style inline.
pub const PAGE: &str = include_str!("page.html");
/// Connections (page, socket or script) served at once.
pub const MAX_CONNECTIONS: usize = 64;
/// Inputs waiting for the display; more are dropped (the page sends the
/// next ones anyway).
pub const INPUT_QUEUE: usize = 256;
/// Largest input a page may send but a path to play, bytes.
pub const MAX_INPUT_BYTES: usize = 4096;
/// Largest path to play a page may send (its TOML), bytes: about 8,000
/// keyframes, a recorded flight of half an hour.
pub const MAX_PATH_BYTES: usize = 1 << 20;
/// JPEG quality of frames while the view changes.
pub const JPEG_QUALITY: u8 = 85;

/// A frame as the viewer shows it.
#[derive(Debug)]
pub struct ShownFrame {
    pub frame: u64,
    pub width: u32,
    pub height: u32,
    /// The image, rows top down.
    pub rgba: Arc<Vec<[u8; 4]>>,
    /// Samples per pixel in it.
    pub samples: u32,
    /// The view it shows ([`super::view::NextFrame::view`]); 0 for a
    /// camera path.
    pub view: u64,
    /// The last frame of its view for now (refined, or the path's end):
    /// sent lossless.
    pub still: bool,
    /// Playing a path: the frame's index in it and its length.
    pub path: Option<(u32, u32)>,
    pub metrics: FrameMetrics,
    encoded: OnceLock<Arc<Vec<u8>>>,
}

impl ShownFrame {
    pub fn new(
        frame: u64,
        (width, height): (u32, u32),
        rgba: Arc<Vec<[u8; 4]>>,
        (samples, view, still, path): (u32, u64, bool, Option<(u32, u32)>),
        metrics: FrameMetrics,
    ) -> ShownFrame {
        ShownFrame {
            frame,
            width,
            height,
            rgba,
            samples,
            view,
            still,
            path,
            metrics,
            encoded: OnceLock::new(),
        }
    }

    /// The WebSocket message of this frame, encoded once for every page.
    fn message(&self) -> Arc<Vec<u8>> {
        self.encoded
            .get_or_init(|| Arc::new(wire::frame_message(self)))
            .clone()
    }
}

/// What the page shows besides frames.
#[derive(Clone, Debug, PartialEq)]
pub struct ViewerStatus {
    pub interactive: bool,
    /// The view's choices (interactive).
    pub choices: Option<Choices>,
    /// The model's scale, for the page's flying speed.
    pub home_distance: f32,
    /// Samples a still view is refined to.
    pub max_samples: u32,
    /// Why the run ended, once it did.
    pub ended: Option<String>,
}

/// What every page hears of besides frames and status.
#[derive(Clone, Debug)]
pub enum PageEvent {
    /// A pick's answer.
    Picked(Picked),
    /// A recording stopped: the path, or why there is none.
    Recorded(Result<Recording, String>),
}

struct Shared {
    token: String,
    /// `host:port` the server listens on, which a page's Origin must name.
    addr: SocketAddr,
    frames: watch::Sender<Option<Arc<ShownFrame>>>,
    status: watch::Sender<ViewerStatus>,
    events: broadcast::Sender<PageEvent>,
    inputs: Option<mpsc::Sender<ViewInput>>,
    slots: Arc<Semaphore>,
}

/// Options of a viewer.
#[derive(Clone, Debug)]
pub struct WebOptions {
    /// Take inputs (a display without a camera path).
    pub interactive: bool,
    /// The token a page must show; `None`: a fresh random one.
    pub token: Option<String>,
}

/// A running viewer; stops when dropped.
pub struct WebViewer {
    shared: Arc<Shared>,
    task: JoinHandle<()>,
}

impl WebViewer {
    /// Listens on `addr` (port 0: any free port, see [`Self::url`]); in
    /// interactive mode also the receiver of the pages' inputs.
    pub async fn start(
        addr: SocketAddr,
        opts: WebOptions,
    ) -> io::Result<(WebViewer, Option<mpsc::Receiver<ViewInput>>)> {
        let listener = tokio::net::TcpListener::bind(addr).await?;
        let addr = listener.local_addr()?;
        let token = match opts.token {
            Some(t) if wire::valid_token(&t) => t,
            Some(_) => {
                return Err(io::Error::new(
                    io::ErrorKind::InvalidInput,
                    "the viewer's token must be 16 to 128 ASCII letters and digits",
                ))
            }
            None => wire::new_token()?,
        };
        let (tx, rx) = match opts.interactive {
            true => {
                let (tx, rx) = mpsc::channel(INPUT_QUEUE);
                (Some(tx), Some(rx))
            }
            false => (None, None),
        };
        let shared = Arc::new(Shared {
            token,
            addr,
            frames: watch::Sender::new(None),
            status: watch::Sender::new(ViewerStatus {
                interactive: opts.interactive,
                choices: None,
                home_distance: 1.0,
                max_samples: 1,
                ended: None,
            }),
            events: broadcast::Sender::new(16),
            inputs: tx,
            slots: Arc::new(Semaphore::new(MAX_CONNECTIONS)),
        });
        let app = Router::new()
            .route("/", get(page))
            .route("/ws", get(socket))
            .route("/frame.png", get(frame_png))
            .route("/metrics.json", get(metrics_json))
            .with_state(shared.clone());
        let task = tokio::spawn(async move {
            if let Err(e) = axum::serve(listener, app).await {
                warn!("web viewer stopped: {e}");
            }
        });
        let viewer = WebViewer { shared, task };
        info!("web viewer on {}", viewer.url());
        Ok((viewer, rx))
    }

    /// Where it listens.
    pub fn local_addr(&self) -> SocketAddr {
        self.shared.addr
    }

    /// The page's address, token included.
    pub fn url(&self) -> String {
        format!("http://{}/?token={}", self.shared.addr, self.shared.token)
    }

    /// Shows a frame from now on.
    pub fn publish(&self, frame: ShownFrame) {
        self.shared.frames.send_replace(Some(Arc::new(frame)));
    }

    /// The page's view of the run changed.
    pub fn set_status(&self, f: impl FnOnce(&mut ViewerStatus)) {
        self.shared.status.send_modify(f);
    }

    /// Tells every page.
    pub fn tell(&self, e: PageEvent) {
        let _ = self.shared.events.send(e);
    }
}

impl Drop for WebViewer {
    fn drop(&mut self) {
        self.task.abort();
    }
}

#[derive(serde::Deserialize)]
struct TokenQuery {
    token: Option<String>,
}

/// Whether a request shows the run's token.
fn authorized(shared: &Shared, q: &TokenQuery) -> bool {
    q.token
        .as_deref()
        .is_some_and(|t| wire::same_token(t, &shared.token))
}

fn refuse(status: StatusCode, why: &'static str) -> Response {
    (status, why).into_response()
}

async fn page() -> impl IntoResponse {
    ([(header::CACHE_CONTROL, "no-store")], Html(PAGE))
}

async fn frame_png(State(shared): State<Arc<Shared>>, Query(q): Query<TokenQuery>) -> Response {
    if !authorized(&shared, &q) {
        return refuse(
            StatusCode::FORBIDDEN,
            "a token is needed (see the URL dray printed)\n",
        );
    }
    let Some(f) = shared.frames.borrow().clone() else {
        return refuse(StatusCode::SERVICE_UNAVAILABLE, "no frame yet\n");
    };
    match tokio::task::spawn_blocking(move || {
        dray_trace::image::encode_png(f.width, f.height, &f.rgba)
    })
    .await
    {
        Ok(Ok(png)) => (
            [
                (header::CONTENT_TYPE, "image/png"),
                (header::CACHE_CONTROL, "no-store"),
            ],
            png,
        )
            .into_response(),
        _ => refuse(
            StatusCode::INTERNAL_SERVER_ERROR,
            "cannot encode the frame\n",
        ),
    }
}

async fn metrics_json(State(shared): State<Arc<Shared>>, Query(q): Query<TokenQuery>) -> Response {
    if !authorized(&shared, &q) {
        return refuse(
            StatusCode::FORBIDDEN,
            "a token is needed (see the URL dray printed)\n",
        );
    }
    let body = match shared.frames.borrow().as_ref() {
        Some(f) => serde_json::to_string(&f.metrics).unwrap_or_else(|_| "null".into()),
        None => "null".into(),
    };
    (
        [
            (header::CONTENT_TYPE, "application/json"),
            (header::CACHE_CONTROL, "no-store"),
        ],
        body,
    )
        .into_response()
}

async fn socket(
    State(shared): State<Arc<Shared>>,
    Query(q): Query<TokenQuery>,
    headers: HeaderMap,
    ws: WebSocketUpgrade,
) -> Response {
    if !authorized(&shared, &q) {
        return refuse(
            StatusCode::FORBIDDEN,
            "a token is needed (see the URL dray printed)\n",
        );
    }
    let host = headers.get(header::HOST).and_then(|h| h.to_str().ok());
    let origin = headers.get(header::ORIGIN).and_then(|h| h.to_str().ok());
    if !wire::same_origin(origin, host) {
        warn!(
            ?origin,
            ?host,
            "web viewer: a socket from another site refused"
        );
        return refuse(
            StatusCode::FORBIDDEN,
            "another site's page may not open the viewer\n",
        );
    }
    let Ok(permit) = shared.slots.clone().try_acquire_owned() else {
        return refuse(StatusCode::SERVICE_UNAVAILABLE, "too many viewers\n");
    };
    ws.max_message_size(MAX_PATH_BYTES)
        .on_upgrade(move |ws| async move {
            session(ws, &shared).await;
            drop(permit);
        })
}

/// One page's socket, until either side closes it.
async fn session(mut ws: WebSocket, shared: &Shared) {
    let mut frames = shared.frames.subscribe();
    let mut status = shared.status.subscribe();
    let mut events = shared.events.subscribe();
    // The newest frame counts as unseen: a page that joins late sees it.
    frames.mark_changed();
    let hello = wire::status_message(&status.borrow_and_update());
    if ws.send(WsMessage::Text(hello.into())).await.is_err() {
        return;
    }
    loop {
        tokio::select! {
            changed = frames.changed() => {
                if changed.is_err() {
                    break;
                }
                let Some(frame) = frames.borrow_and_update().clone() else {
                    continue;
                };
                // Encoding a big frame takes milliseconds: off the runtime.
                let bytes = match tokio::task::spawn_blocking(move || frame.message()).await {
                    Ok(b) => b,
                    Err(e) => {
                        warn!("web viewer: encoding a frame failed: {e}");
                        continue;
                    }
                };
                if ws.send(WsMessage::Binary(bytes.to_vec().into())).await.is_err() {
                    break;
                }
            }
            changed = status.changed() => {
                if changed.is_err() {
                    break;
                }
                let s = status.borrow_and_update().clone();
                let text = wire::status_message(&s);
                if ws.send(WsMessage::Text(text.into())).await.is_err() {
                    break;
                }
            }
            event = events.recv() => match event {
                Ok(e) => {
                    if ws.send(WsMessage::Text(wire::event_message(&e).into())).await.is_err() {
                        break;
                    }
                }
                Err(broadcast::error::RecvError::Lagged(_)) => {}
                Err(broadcast::error::RecvError::Closed) => break,
            },
            incoming = ws.recv() => match incoming {
                Some(Ok(WsMessage::Text(text))) => {
                    if let Err(why) = take_input(shared, text.as_str()) {
                        let msg = wire::error_message(&why);
                        if ws.send(WsMessage::Text(msg.into())).await.is_err() {
                            break;
                        }
                    }
                }
                Some(Ok(WsMessage::Close(_))) | None => break,
                Some(Ok(_)) => {}
                Some(Err(e)) => {
                    debug!("web viewer: socket: {e}");
                    break;
                }
            },
        }
    }
}

/// Hands a page's input to the display; why not, for the page.
fn take_input(shared: &Shared, text: &str) -> Result<(), String> {
    let Some(tx) = &shared.inputs else {
        return Err("this run follows a camera path: it takes no inputs".into());
    };
    let input = wire::parse_input(text)?;
    match tx.try_send(input) {
        Ok(()) => Ok(()),
        Err(mpsc::error::TrySendError::Full(_)) => {
            debug!("web viewer: the display is behind, an input dropped");
            Ok(())
        }
        Err(mpsc::error::TrySendError::Closed(_)) => Err("the display has stopped".into()),
    }
}
