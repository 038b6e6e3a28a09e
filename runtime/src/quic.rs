//! The QUIC transport: quinn with mutual TLS against the cluster CA.
//!
//! Per connection: a handshake on one bidirectional stream ([`Handshake`]:
//! protocol version, role, node name, which must be the name in the peer's
//! certificate), then one long-lived control stream per direction for small
//! messages and a fresh unidirectional stream for each bulk message
//! ([`MessageKind::is_bulk`]), so a large voxel never delays a control
//! message. Every stream starts with one byte naming its class, then carries
//! frames of a 4-byte big-endian length and a postcard body (tokio-util's
//! `LengthDelimitedCodec`). A malformed control frame closes the connection;
//! a malformed bulk stream is stopped alone. Other peers are not affected.

use crate::bus::{AlreadyConnected, Bus, Inner, PeerLink, SendError};
use crate::certs::{CertError, NodeIdentity};
use bytes::{Bytes, BytesMut};
use dray_protocol::{
    decode_envelope, encode_envelope, peek_kind, Envelope, Handshake, Hello, MessageKind, Name,
    ProtocolError, Role, BULK_FRAME_MAX, CONTROL_FRAME_MAX, HANDSHAKE_FRAME_MAX, PROTOCOL_VERSION,
};
use futures::{SinkExt, StreamExt};
use quinn::crypto::rustls::{QuicClientConfig, QuicServerConfig};
use quinn::{Connection, Endpoint, VarInt};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::Duration;
use tokio::sync::{mpsc, watch, Notify};
use tokio_util::codec::{FramedRead, FramedWrite, LengthDelimitedCodec};
use tracing::{debug, error, info, info_span, trace, warn, Instrument};

/// First byte of a control stream.
pub const STREAM_CONTROL: u8 = 0;
/// First byte of a bulk stream (one frame, then the end of the stream).
pub const STREAM_BULK: u8 = 1;

/// Application close and stop codes.
const CODE_SHUTDOWN: u32 = 0;
const CODE_PROTOCOL: u32 = 1;
const CODE_REFUSED: u32 = 2;

/// Control frames queued per connection before senders wait.
const CONTROL_QUEUE: usize = 1024;
/// How long an accepted connection may take to say hello.
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);
/// First and largest delay between redials.
const BACKOFF_MIN: Duration = Duration::from_millis(50);
const BACKOFF_MAX: Duration = Duration::from_secs(5);

/// Why the QUIC transport failed.
#[derive(Debug, thiserror::Error)]
pub enum QuicError {
    /// Certificates or TLS configuration.
    #[error(transparent)]
    Cert(#[from] CertError),
    /// Socket trouble.
    #[error("socket: {0}")]
    Io(#[from] std::io::Error),
    /// quinn refused the crypto configuration.
    #[error("QUIC crypto configuration: {0}")]
    Crypto(String),
    /// The identity is for another node than the bus.
    #[error("certificate is for node {cert} but the bus is node {bus}")]
    WrongIdentity {
        /// Name in the identity.
        cert: Name,
        /// Name of the bus.
        bus: Name,
    },
    /// Dialing failed.
    #[error("connect: {0}")]
    Connect(#[from] quinn::ConnectError),
    /// The connection failed (TLS refusal included).
    #[error("connection: {0}")]
    Connection(#[from] quinn::ConnectionError),
    /// A stream failed during the handshake.
    #[error("handshake stream: {0}")]
    Stream(String),
    /// The handshake message was bad (version mismatch included).
    #[error("handshake: {0}")]
    Handshake(#[from] ProtocolError),
    /// The peer refused us.
    #[error("refused by the peer: {0}")]
    Refused(String),
    /// The peer is not who it should be.
    #[error("expected node {expected}, the peer says it is {got}")]
    WrongPeer {
        /// Whom we dialed or whom the certificate names.
        expected: String,
        /// What the peer said.
        got: String,
    },
    /// The handshake took too long.
    #[error("handshake timed out")]
    Timeout,
    /// A peer's host name did not resolve.
    #[error("{0}")]
    Lookup(String),
    /// A node's announced role is not the one its name gives it.
    #[error("node {node} says it is a {announced}, but its name makes it a {role}")]
    WrongRole {
        /// The node (as its certificate names it).
        node: Name,
        /// The role it announced.
        announced: Role,
        /// The role its name gives it ([`Role::of_node`]).
        role: Role,
    },
    /// Another connection under the same node name is up.
    #[error("node {node} is already connected (from {live}); a second connection under its name is refused")]
    AlreadyConnected {
        /// The node.
        node: Name,
        /// Where its live connection comes from.
        live: String,
    },
    /// The TLS handshake failed over a certificate: retrying cannot help
    /// until the certificates are fixed.
    #[error("{0}")]
    Untrusted(String),
}

/// Explains a connection error that is a TLS refusal over certificates
/// (QUIC carries TLS alerts as crypto errors `0x100 + alert`), naming who
/// refused whom; `None` for any other error.
fn untrusted(e: &QuicError, local: &Name, peer: &Name) -> Option<String> {
    let (code, reason, by_peer) = match e {
        QuicError::Connection(quinn::ConnectionError::TransportError(t)) => {
            (u64::from(t.code), t.reason.clone(), false)
        }
        QuicError::Connection(quinn::ConnectionError::ConnectionClosed(c)) => (
            u64::from(c.error_code),
            String::from_utf8_lossy(&c.reason).into_owned(),
            true,
        ),
        _ => return None,
    };
    let alert = code.checked_sub(0x100).filter(|a| *a < 0x100)?;
    // bad_certificate .. certificate_unknown, unknown_ca, certificate_required
    let about_certs = matches!(alert, 42..=46 | 48 | 116) || reason.contains("certificate");
    if !about_certs {
        return None;
    }
    let other_ca = alert == 48 || reason.contains("UnknownIssuer");
    let (refuser, refused) = if by_peer {
        (peer.to_string(), format!("the certificate of {local}"))
    } else {
        (local.to_string(), format!("the certificate of {peer}"))
    };
    let detail = if reason.is_empty() {
        format!("TLS alert {alert}")
    } else {
        reason
    };
    Some(if other_ca {
        format!(
            "{refuser} refused {refused}: unknown issuer, it is signed by another CA than the \
             one {refuser} trusts ({detail}); every node needs its certificate and ca.pem \
             from the same CA (`dray certs bundle` / `dray certs add`)"
        )
    } else {
        format!("{refuser} refused {refused} in the TLS handshake ({detail})")
    })
}

/// Socket buffer asked for, so a burst of datagrams is not lost in the
/// kernel while the endpoint is busy (capped by `net.core.rmem_max`).
const SOCKET_BUFFER: usize = 4 << 20;

/// Binds the endpoint's UDP socket with large buffers.
fn bind_udp(addr: SocketAddr) -> std::io::Result<std::net::UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let s = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    // Best effort: a smaller buffer still works, it only drops sooner.
    let _ = s.set_recv_buffer_size(SOCKET_BUFFER);
    let _ = s.set_send_buffer_size(SOCKET_BUFFER);
    s.bind(&addr.into())?;
    Ok(s.into())
}

fn codec(max: usize) -> LengthDelimitedCodec {
    LengthDelimitedCodec::builder()
        .length_field_type::<u32>()
        .max_frame_length(max)
        .new_codec()
}

fn transport_config() -> quinn::TransportConfig {
    let mut t = quinn::TransportConfig::default();
    t.keep_alive_interval(Some(Duration::from_millis(500)));
    t.max_idle_timeout(Some(quinn::IdleTimeout::from(VarInt::from_u32(4_000))));
    t.max_concurrent_uni_streams(VarInt::from_u32(64));
    t.max_concurrent_bidi_streams(VarInt::from_u32(4));
    t.stream_receive_window(VarInt::from_u32(16 << 20));
    t.receive_window(VarInt::from_u32(64 << 20));
    t.send_window(64 << 20);
    t
}

/// A connected peer, as the bus sees it.
pub(crate) struct QuicPeer {
    node: Name,
    conn: Connection,
    control: mpsc::Sender<Bytes>,
}

impl QuicPeer {
    /// The peer's address.
    pub(crate) fn remote(&self) -> SocketAddr {
        self.conn.remote_address()
    }

    /// Sends `env`; returns the bytes of its encoding.
    pub(crate) async fn send(&self, env: Envelope) -> Result<usize, SendError> {
        let kind = env.msg.kind();
        let body = encode_envelope(&env)?;
        let bytes = body.len();
        let fail = |reason: String| SendError::Connection {
            node: self.node.clone(),
            reason,
        };
        if kind.own_stream(body.len()) {
            let mut s = self
                .conn
                .open_uni()
                .await
                .map_err(|e| fail(e.to_string()))?;
            let len = u32::try_from(body.len()).map_err(|_| fail("frame too large".into()))?;
            let mut head = [0u8; 5];
            head[0] = STREAM_BULK;
            head[1..].copy_from_slice(&len.to_be_bytes());
            let mut chunks = [Bytes::copy_from_slice(&head), Bytes::from(body)];
            s.write_all_chunks(&mut chunks)
                .await
                .map_err(|e| fail(e.to_string()))?;
            s.finish().map_err(|e| fail(e.to_string()))?;
            trace!(peer = %self.node, kind = kind.name(), "bulk stream sent");
            Ok(bytes)
        } else {
            self.control
                .send(Bytes::from(body))
                .await
                .map(|()| bytes)
                .map_err(|_| fail("control stream closed".into()))
        }
    }
}

/// Where a peer is dialed: an address, or a host name and port looked up
/// before every dial, so that a peer restarted at another address (a
/// rescheduled Kubernetes pod) is found again, and one whose name does not
/// resolve yet is waited for like one that is not up yet.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum DialTarget {
    /// A fixed address.
    Addr(SocketAddr),
    /// A host name and port.
    Host {
        /// The name.
        name: String,
        /// The port.
        port: u16,
    },
}

impl DialTarget {
    /// The target for `host` (an IP or a name) and `port`.
    pub fn new(host: &str, port: u16) -> DialTarget {
        match host.parse::<std::net::IpAddr>() {
            Ok(ip) => DialTarget::Addr(SocketAddr::new(ip, port)),
            Err(_) => DialTarget::Host {
                name: host.to_string(),
                port,
            },
        }
    }

    /// The address to dial now.
    pub async fn resolve(&self) -> Result<SocketAddr, QuicError> {
        match self {
            DialTarget::Addr(a) => Ok(*a),
            DialTarget::Host { name, port } => {
                let mut addrs = tokio::net::lookup_host((name.as_str(), *port))
                    .await
                    .map_err(|e| QuicError::Lookup(format!("cannot look up host {name:?}: {e}")))?;
                addrs
                    .next()
                    .ok_or_else(|| QuicError::Lookup(format!("host {name:?} has no address")))
            }
        }
    }
}

impl From<SocketAddr> for DialTarget {
    fn from(a: SocketAddr) -> DialTarget {
        DialTarget::Addr(a)
    }
}

impl std::fmt::Display for DialTarget {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            DialTarget::Addr(a) => write!(f, "{a}"),
            DialTarget::Host { name, port } => write!(f, "{name}:{port}"),
        }
    }
}

/// A node's QUIC endpoint: accepts peers, dials peers (redialing with
/// backoff), and attaches each connection to the bus.
pub struct QuicTransport {
    bus: Weak<Inner>,
    node: Name,
    role: Role,
    endpoint: Endpoint,
    shutdown: watch::Sender<bool>,
    /// Why the last dial to each peer failed (cleared once it connects),
    /// and whether retrying cannot help.
    dial_errors: Mutex<HashMap<Name, (String, bool)>>,
    dial_failed: Notify,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // Each update is one insert or remove, so a poisoned map is usable.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

/// A connection registered on the bus as the link to its peer.
struct Attached {
    conn: Connection,
    peer: Name,
    role: Role,
    link_id: usize,
    rx: mpsc::Receiver<Bytes>,
}

impl QuicTransport {
    /// Binds `listen` (port 0 picks one) and starts accepting peers for `bus`.
    pub async fn start(
        bus: &Bus,
        identity: &NodeIdentity,
        listen: SocketAddr,
    ) -> Result<Arc<QuicTransport>, QuicError> {
        if identity.node() != bus.node() {
            return Err(QuicError::WrongIdentity {
                cert: identity.node().clone(),
                bus: bus.node().clone(),
            });
        }
        let role = Role::of_node(bus.node());
        if bus.role() != role {
            return Err(QuicError::WrongRole {
                node: bus.node().clone(),
                announced: bus.role(),
                role,
            });
        }
        let transport = Arc::new(transport_config());
        let server_crypto = QuicServerConfig::try_from(identity.server_tls()?)
            .map_err(|e| QuicError::Crypto(e.to_string()))?;
        let mut server = quinn::ServerConfig::with_crypto(Arc::new(server_crypto));
        server.transport_config(transport.clone());
        let client_crypto = QuicClientConfig::try_from(identity.client_tls()?)
            .map_err(|e| QuicError::Crypto(e.to_string()))?;
        let mut client = quinn::ClientConfig::new(Arc::new(client_crypto));
        client.transport_config(transport);
        let socket = bind_udp(listen)?;
        let mut endpoint = Endpoint::new(
            quinn::EndpointConfig::default(),
            Some(server),
            socket,
            Arc::new(quinn::TokioRuntime),
        )?;
        endpoint.set_default_client_config(client);
        let (shutdown, _) = watch::channel(false);
        let this = Arc::new(QuicTransport {
            bus: bus.downgrade(),
            node: bus.node().clone(),
            role: bus.role(),
            endpoint,
            shutdown,
            dial_errors: Mutex::new(HashMap::new()),
            dial_failed: Notify::new(),
        });
        let acceptor = this.clone();
        let span = info_span!("quic_accept", node = %this.node);
        tokio::spawn(acceptor.accept_loop().instrument(span));
        info!(node = %this.node, addr = ?this.local_addr(), "QUIC transport listening");
        Ok(this)
    }

    /// The bound address.
    pub fn local_addr(&self) -> Result<SocketAddr, QuicError> {
        Ok(self.endpoint.local_addr()?)
    }

    /// Keeps a connection to node `peer` at `target`: dials now, and
    /// redials with backoff whenever the connection is lost, until
    /// shutdown. Use [`Bus::wait_for_peer`] to wait for it.
    pub fn connect(self: &Arc<Self>, peer: Name, target: impl Into<DialTarget>) {
        let target = target.into();
        let this = self.clone();
        let span = info_span!("quic_dial", node = %self.node, peer = %peer, addr = %target);
        tokio::spawn(this.dial_loop(peer, target).instrument(span));
    }

    /// Why the last dial to `peer` failed, while it is not connected.
    pub fn dial_error(&self, peer: &Name) -> Option<String> {
        lock(&self.dial_errors).get(peer).map(|(e, _)| e.clone())
    }

    /// Waits until `peer` (see [`QuicTransport::connect`]) is connected, or
    /// fails with [`QuicError::Untrusted`] once a dial to it failed over
    /// certificates (one side's certificate is from another CA, say),
    /// which no retry mends; the dialing goes on meanwhile.
    pub async fn wait_connected(&self, peer: &Name) -> Result<(), QuicError> {
        let Some(inner) = self.bus.upgrade() else {
            return Err(QuicError::Stream("the bus is gone".into()));
        };
        let bus = Bus { inner };
        loop {
            let failed = self.dial_failed.notified();
            tokio::pin!(failed);
            failed.as_mut().enable();
            if bus.is_connected(peer) {
                return Ok(());
            }
            if let Some((e, true)) = lock(&self.dial_errors).get(peer) {
                return Err(QuicError::Untrusted(e.clone()));
            }
            tokio::select! {
                _ = bus.wait_for_peer(peer) => return Ok(()),
                _ = &mut failed => {}
            }
        }
    }

    /// Closes every connection and stops accepting and redialing.
    pub async fn shutdown(&self) {
        self.shutdown.send_replace(true);
        self.endpoint
            .close(VarInt::from_u32(CODE_SHUTDOWN), b"shutdown");
        self.endpoint.wait_idle().await;
    }

    fn stopping(&self) -> bool {
        *self.shutdown.borrow()
    }

    async fn accept_loop(self: Arc<Self>) {
        while let Some(incoming) = self.endpoint.accept().await {
            let this = self.clone();
            let remote = incoming.remote_address();
            tokio::spawn(
                async move {
                    match this.accept_one(incoming).await {
                        Ok(()) => {}
                        Err(e) => warn!(error = %e, "refused incoming connection"),
                    }
                }
                .instrument(info_span!("quic_incoming", %remote)),
            );
        }
        debug!("endpoint closed; accept loop ends");
    }

    async fn accept_one(self: Arc<Self>, incoming: quinn::Incoming) -> Result<(), QuicError> {
        // TLS (mutual, against the cluster CA) completes here; a stranger
        // fails before any of its streams is read.
        let conn = incoming.await?;
        let hs = tokio::time::timeout(HANDSHAKE_TIMEOUT, self.answer_hello(&conn))
            .await
            .map_err(|_| QuicError::Timeout)
            .and_then(|r| r);
        let (hello, mut wr) = match hs {
            Ok(v) => v,
            Err(e) => {
                conn.close(VarInt::from_u32(CODE_REFUSED), e.to_string().as_bytes());
                return Err(e);
            }
        };
        let attached = match self.attach(&conn, hello.node.clone(), hello.role) {
            Ok(a) => a,
            Err(live) => {
                let e = QuicError::AlreadyConnected {
                    node: hello.node,
                    live: live.remote,
                };
                self.refuse(wr, e.to_string()).await;
                conn.close(VarInt::from_u32(CODE_REFUSED), e.to_string().as_bytes());
                return Err(e);
            }
        };
        let welcome = Handshake::Welcome(Hello {
            version: PROTOCOL_VERSION,
            role: self.role,
            node: self.node.clone(),
        });
        let sent = self.send_handshake(&mut wr, &welcome).await;
        if sent.is_ok() {
            let _ = wr.into_inner().finish();
        } else {
            conn.close(VarInt::from_u32(CODE_PROTOCOL), b"welcome not sent");
        }
        // Serving a closed connection only unregisters it.
        self.serve(attached).await;
        sent
    }

    /// Reads and checks the peer's hello; the caller answers it.
    async fn answer_hello(
        &self,
        conn: &Connection,
    ) -> Result<(Hello, FramedWrite<quinn::SendStream, LengthDelimitedCodec>), QuicError> {
        let (send, recv) = conn.accept_bi().await?;
        let mut rd = FramedRead::new(recv, codec(HANDSHAKE_FRAME_MAX));
        let wr = FramedWrite::new(send, codec(HANDSHAKE_FRAME_MAX));
        let frame = rd
            .next()
            .await
            .ok_or_else(|| QuicError::Stream("no hello".into()))?
            .map_err(|e| QuicError::Stream(e.to_string()))?;
        let hello = match Handshake::decode(&frame) {
            Ok(Handshake::Hello(h)) => h,
            Ok(_) => return Err(QuicError::Stream("expected a hello".into())),
            Err(e) => {
                self.refuse(wr, e.to_string()).await;
                return Err(QuicError::Handshake(e));
            }
        };
        if let Err(e) = check_cert_name(conn, &hello.node).and_then(|()| check_role(&hello)) {
            self.refuse(wr, e.to_string()).await;
            return Err(e);
        }
        Ok((hello, wr))
    }

    /// Tells the peer why it is refused, and waits (briefly) until it has
    /// the answer, so that closing the connection does not discard it.
    async fn refuse(
        &self,
        mut wr: FramedWrite<quinn::SendStream, LengthDelimitedCodec>,
        reason: String,
    ) {
        let refusal = Handshake::Refused {
            version: PROTOCOL_VERSION,
            reason,
        };
        if self.send_handshake(&mut wr, &refusal).await.is_ok() {
            let mut s = wr.into_inner();
            if s.finish().is_ok() {
                let _ = tokio::time::timeout(Duration::from_secs(2), s.stopped()).await;
            }
        }
    }

    async fn send_handshake(
        &self,
        wr: &mut FramedWrite<quinn::SendStream, LengthDelimitedCodec>,
        hs: &Handshake,
    ) -> Result<(), QuicError> {
        let bytes = hs.encode()?;
        wr.send(Bytes::from(bytes))
            .await
            .map_err(|e| QuicError::Stream(e.to_string()))
    }

    async fn dial(&self, peer: &Name, addr: SocketAddr) -> Result<(Connection, Role), QuicError> {
        let conn = self.endpoint.connect(addr, peer.as_str())?.await?;
        match self.greet(peer, &conn).await {
            Ok(role) => Ok((conn, role)),
            // The acceptor checks our certificate only after our side of
            // the TLS handshake is done: its refusal is the close reason.
            Err(e @ (QuicError::Stream(_) | QuicError::Connection(_))) => {
                Err(conn.close_reason().map_or(e, QuicError::Connection))
            }
            Err(e) => Err(e),
        }
    }

    /// Sends our hello on a dialed connection and reads the answer.
    async fn greet(&self, peer: &Name, conn: &Connection) -> Result<Role, QuicError> {
        let (send, recv) = conn.open_bi().await?;
        let mut wr = FramedWrite::new(send, codec(HANDSHAKE_FRAME_MAX));
        let mut rd = FramedRead::new(recv, codec(HANDSHAKE_FRAME_MAX));
        let hello = Handshake::Hello(Hello {
            version: PROTOCOL_VERSION,
            role: self.role,
            node: self.node.clone(),
        });
        self.send_handshake(&mut wr, &hello).await?;
        let answer = tokio::time::timeout(HANDSHAKE_TIMEOUT, rd.next())
            .await
            .map_err(|_| QuicError::Timeout)?;
        let frame = match answer {
            Some(Ok(f)) => f,
            Some(Err(e)) => return Err(QuicError::Stream(e.to_string())),
            None => {
                // The stream ended: the acceptor closed the connection.
                return Err(match conn.close_reason() {
                    Some(e) => QuicError::Connection(e),
                    None => QuicError::Stream("no welcome".into()),
                });
            }
        };
        let _ = wr.into_inner().finish();
        match Handshake::decode(&frame)? {
            Handshake::Welcome(w) if &w.node == peer => {
                check_role(&w)?;
                Ok(w.role)
            }
            Handshake::Welcome(w) => Err(QuicError::WrongPeer {
                expected: peer.to_string(),
                got: w.node.to_string(),
            }),
            Handshake::Refused { version, .. } if version != PROTOCOL_VERSION => {
                Err(QuicError::Handshake(ProtocolError::VersionMismatch {
                    ours: PROTOCOL_VERSION,
                    theirs: version,
                }))
            }
            Handshake::Refused { reason, .. } => Err(QuicError::Refused(reason)),
            Handshake::Hello(_) => Err(QuicError::Stream("expected a welcome".into())),
        }
    }

    async fn dial_loop(self: Arc<Self>, peer: Name, target: DialTarget) {
        let mut backoff = BACKOFF_MIN;
        let mut stop = self.shutdown.subscribe();
        while !self.stopping() {
            let dialed = match target.resolve().await {
                Ok(addr) => self.dial(&peer, addr).await,
                Err(e) => Err(e),
            };
            let dialed = dialed.and_then(|(conn, role)| {
                self.attach(&conn, peer.clone(), role).map_err(|live| {
                    let e = QuicError::AlreadyConnected {
                        node: peer.clone(),
                        live: live.remote,
                    };
                    conn.close(VarInt::from_u32(CODE_REFUSED), e.to_string().as_bytes());
                    e
                })
            });
            match dialed {
                Ok(attached) => {
                    backoff = BACKOFF_MIN;
                    lock(&self.dial_errors).remove(&peer);
                    self.serve(attached).await;
                }
                Err(QuicError::Handshake(e @ ProtocolError::VersionMismatch { .. })) => {
                    error!(error = %e, "giving up on this peer");
                    self.dial_failed(&peer, e.to_string(), true);
                    return;
                }
                Err(e) => match untrusted(&e, &self.node, &peer) {
                    // Certificates do not mend themselves: say why loudly
                    // (the node gives up if it is still starting).
                    Some(why) => {
                        error!(error = %why, retry_in = ?backoff, "dial failed");
                        self.dial_failed(&peer, why, true);
                    }
                    None => {
                        // A peer that is starting or stopping refuses for a
                        // moment; only a failure that lasts is worth a warning.
                        if backoff >= Duration::from_secs(1) {
                            warn!(error = %e, retry_in = ?backoff, "dial failed");
                        } else {
                            debug!(error = %e, retry_in = ?backoff, "dial failed");
                        }
                        self.dial_failed(&peer, e.to_string(), false);
                    }
                },
            }
            if self.stopping() {
                break;
            }
            tokio::select! {
                _ = tokio::time::sleep(backoff) => {}
                _ = stop.changed() => {}
            }
            backoff = (backoff * 2).min(BACKOFF_MAX);
        }
    }

    fn dial_failed(&self, peer: &Name, why: String, lasting: bool) {
        lock(&self.dial_errors).insert(peer.clone(), (why, lasting));
        self.dial_failed.notify_waiters();
    }

    /// Registers an established connection on the bus as the link to
    /// `peer`, unless another link to it is up (see `Inner::peer_up`).
    fn attach(
        &self,
        conn: &Connection,
        peer: Name,
        role: Role,
    ) -> Result<Attached, AlreadyConnected> {
        let Some(bus) = self.bus.upgrade() else {
            conn.close(VarInt::from_u32(CODE_SHUTDOWN), b"bus gone");
            return Err(AlreadyConnected {
                remote: "nowhere (this node is stopping)".into(),
            });
        };
        let (tx, rx) = mpsc::channel(CONTROL_QUEUE);
        let link = PeerLink::Quic(Arc::new(QuicPeer {
            node: peer.clone(),
            conn: conn.clone(),
            control: tx,
        }));
        let link_id = Inner::link_id(&link);
        bus.peer_up(peer.clone(), role, link)?;
        Ok(Attached {
            conn: conn.clone(),
            peer,
            role,
            link_id,
            rx,
        })
    }

    /// Serves an attached connection until it closes, then unregisters it.
    async fn serve(&self, attached: Attached) {
        let Attached {
            conn,
            peer,
            role,
            link_id,
            rx,
        } = attached;
        let span = info_span!("quic_conn", node = %self.node, peer = %peer, remote = %conn.remote_address());
        info!(parent: &span, %role, "peer connected");
        let writer = tokio::spawn(control_writer(conn.clone(), rx).instrument(span.clone()));
        let reader = tokio::spawn(
            accept_streams(
                conn.clone(),
                self.bus.clone(),
                self.node.clone(),
                (peer.clone(), role),
            )
            .instrument(span.clone()),
        );
        let reason = conn.closed().await;
        writer.abort();
        reader.abort();
        let path = conn.stats().path;
        info!(parent: &span, %reason, mtu = path.current_mtu, sent_packets = path.sent_packets,
            lost_packets = path.lost_packets, rtt = ?path.rtt, "peer disconnected");
        if let Some(bus) = self.bus.upgrade() {
            bus.peer_down(&peer, link_id, reason.to_string());
        }
    }
}

/// Checks that a hello's role is the one its node's name gives it.
fn check_role(h: &Hello) -> Result<(), QuicError> {
    let role = Role::of_node(&h.node);
    if h.role == role {
        Ok(())
    } else {
        Err(QuicError::WrongRole {
            node: h.node.clone(),
            announced: h.role,
            role,
        })
    }
}

/// Checks that the peer's certificate names `node`.
fn check_cert_name(conn: &Connection, node: &Name) -> Result<(), QuicError> {
    let certs = conn
        .peer_identity()
        .and_then(|id| {
            id.downcast::<Vec<rustls::pki_types::CertificateDer<'static>>>()
                .ok()
        })
        .ok_or_else(|| QuicError::Stream("peer presented no certificate".into()))?;
    let first = certs
        .first()
        .ok_or_else(|| QuicError::Stream("peer presented no certificate".into()))?;
    let wrong = || QuicError::WrongPeer {
        expected: "the name in its certificate".into(),
        got: node.to_string(),
    };
    let cert = webpki::EndEntityCert::try_from(first).map_err(|_| wrong())?;
    let name = rustls::pki_types::ServerName::try_from(node.as_str()).map_err(|_| wrong())?;
    cert.verify_is_valid_for_subject_name(&name)
        .map_err(|_| wrong())
}

async fn control_writer(conn: Connection, mut rx: mpsc::Receiver<Bytes>) {
    let result: Result<(), String> = async {
        let mut s = conn.open_uni().await.map_err(|e| e.to_string())?;
        s.write_all(&[STREAM_CONTROL])
            .await
            .map_err(|e| e.to_string())?;
        // Each frame goes to quinn as its length and its body, both handed
        // over without a copy (a length-delimited codec copied every body,
        // a tile's pixels included, into its buffer, and quinn copied that
        // again); the reader's codec sees the same bytes.
        let mut chunks: Vec<Bytes> = Vec::new();
        while let Some(frame) = rx.recv().await {
            chunks.clear();
            push_frame(&mut chunks, frame)?;
            // What is already queued goes in the same write.
            for _ in 0..64 {
                match rx.try_recv() {
                    Ok(f) => push_frame(&mut chunks, f)?,
                    Err(_) => break,
                }
            }
            s.write_all_chunks(&mut chunks)
                .await
                .map_err(|e| e.to_string())?;
        }
        Ok(())
    }
    .await;
    if let Err(e) = result {
        debug!(error = %e, "control writer stopped");
    }
}

/// Appends a control frame (as the reader's length-delimited codec takes
/// it: a big-endian u32 length, then the body) to `chunks`.
fn push_frame(chunks: &mut Vec<Bytes>, body: Bytes) -> Result<(), String> {
    let len = u32::try_from(body.len())
        .ok()
        .filter(|&n| n as usize <= CONTROL_FRAME_MAX)
        .ok_or_else(|| format!("control frame of {} bytes is over the limit", body.len()))?;
    chunks.push(Bytes::copy_from_slice(&len.to_be_bytes()));
    chunks.push(body);
    Ok(())
}

async fn accept_streams(conn: Connection, bus: Weak<Inner>, local: Name, peer: (Name, Role)) {
    loop {
        let recv = match conn.accept_uni().await {
            Ok(r) => r,
            Err(e) => {
                debug!(error = %e, "no more streams");
                return;
            }
        };
        let conn = conn.clone();
        let bus = bus.clone();
        let local = local.clone();
        let peer = peer.clone();
        tokio::spawn(
            async move { read_stream(conn, recv, bus, local, peer).await }.in_current_span(),
        );
    }
}

enum Bad {
    /// Close the whole connection (the control stream is unusable).
    Connection(String),
    /// Stop only this stream.
    Stream(String),
}

async fn read_stream(
    conn: Connection,
    mut recv: quinn::RecvStream,
    bus: Weak<Inner>,
    local: Name,
    peer: (Name, Role),
) {
    let mut class = [0u8; 1];
    if recv.read_exact(&mut class).await.is_err() {
        return;
    }
    let outcome = match class[0] {
        STREAM_CONTROL => {
            let mut rd = FramedRead::new(&mut recv, codec(CONTROL_FRAME_MAX));
            let mut out = Ok(());
            while let Some(frame) = rd.next().await {
                let r = match frame {
                    Ok(body) => deliver(&bus, &local, &peer, body, false).await,
                    // The codec reports a frame over the limit as invalid
                    // data; anything else is the stream or connection ending.
                    Err(e) if e.kind() == std::io::ErrorKind::InvalidData => Err(e.to_string()),
                    Err(e) => {
                        debug!(error = %e, "control stream ended");
                        break;
                    }
                };
                if let Err(e) = r {
                    out = Err(Bad::Connection(e));
                    break;
                }
            }
            out
        }
        STREAM_BULK => match read_bulk(&mut recv).await {
            Ok(body) => deliver(&bus, &local, &peer, body, true)
                .await
                .map_err(Bad::Stream),
            Err(e) => Err(Bad::Stream(e)),
        },
        other => Err(Bad::Stream(format!("unknown stream class {other}"))),
    };
    match outcome {
        Ok(()) => {}
        Err(Bad::Stream(e)) => {
            warn!(error = %e, "bad bulk stream; stopping it");
            let _ = recv.stop(VarInt::from_u32(CODE_PROTOCOL));
        }
        Err(Bad::Connection(e)) => {
            warn!(error = %e, "bad control frame; closing the connection");
            conn.close(VarInt::from_u32(CODE_PROTOCOL), e.as_bytes());
        }
    }
}

/// Reads the one frame of a bulk stream, refusing it by its kind's limit
/// before reading (or allocating for) the body.
async fn read_bulk(recv: &mut quinn::RecvStream) -> Result<BytesMut, String> {
    let mut head = [0u8; 5];
    recv.read_exact(&mut head)
        .await
        .map_err(|e| format!("bulk header: {e}"))?;
    let len = u32::from_be_bytes([head[0], head[1], head[2], head[3]]) as usize;
    if len == 0 || len > BULK_FRAME_MAX {
        return Err(format!("bulk frame of {len} bytes"));
    }
    let kind = peek_kind(&head[4..]).map_err(|e| e.to_string())?;
    if !kind.is_bulk() || len > kind.max_wire_size() {
        return Err(format!("{kind:?} frame of {len} bytes on a bulk stream"));
    }
    // read_to_end grows with the data that actually arrives.
    let rest = recv
        .read_to_end(len - 1)
        .await
        .map_err(|e| format!("bulk body: {e}"))?;
    if rest.len() != len - 1 {
        return Err(format!(
            "bulk stream ended after {} of {len} bytes",
            rest.len() + 1
        ));
    }
    let mut body = BytesMut::with_capacity(len);
    body.extend_from_slice(&head[4..]);
    body.extend_from_slice(&rest);
    Ok(body)
}

async fn deliver(
    bus: &Weak<Inner>,
    local: &Name,
    (peer, role): &(Name, Role),
    body: BytesMut,
    bulk: bool,
) -> Result<(), String> {
    let env = decode_envelope(&body).map_err(|e| e.to_string())?;
    let kind: MessageKind = env.msg.kind();
    // Small bulk messages come on the control stream too.
    if bulk && !kind.is_bulk() {
        return Err(format!("{kind:?} on a bulk stream"));
    }
    if &env.from.node != peer {
        return Err(format!(
            "peer {peer} sent a message claiming to be from {}",
            env.from
        ));
    }
    if &env.to.node != local {
        return Err(format!("message for {} arrived at node {local}", env.to));
    }
    let Some(bus) = bus.upgrade() else {
        return Ok(());
    };
    bus.count_received(*role, body.len());
    let span =
        tracing::trace_span!("recv", kind = kind.name(), from = %env.from, to = %env.to.actor);
    if let Err(e) = bus.deliver_remote(*role, env).instrument(span).await {
        // Not the peer's fault: the actor is gone. Drop the message.
        warn!(error = %e, "message dropped");
    }
    Ok(())
}
