//! A UDP relay that shapes a QUIC link: it sits in front of a node, and
//! delays, paces (bandwidth cap with a bounded queue, tail drop) and drops
//! datagrams in each direction, so QUIC's own congestion control and
//! retransmission are what copes (this machine's kernel has no netem).
//!
//! Each client source address gets its own upstream socket, so the node sees
//! one distinct peer per client, as without the relay. Each session's
//! datagrams cross a link of the session's own and then, where given, a
//! [`SharedShaper`] common to every session (and to every relay given the
//! same one): a node's shared uplink or downlink.

use crate::shaping::{shared, LinkShape, Path, Shaper, SharedShaper, Verdict};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;
use tokio::net::UdpSocket;
use tokio::sync::{mpsc, watch};
use tokio::time::Instant;
use tracing::{debug, info_span, trace, Instrument};

/// Largest datagram relayed.
const MAX_DATAGRAM: usize = 65_535;
/// Socket buffer the relay asks for, so a burst is not lost in the kernel
/// while the relay is busy (the kernel caps it at `net.core.rmem_max`).
const SOCKET_BUFFER: usize = 4 << 20;

/// Binds a UDP socket with large buffers.
fn bind_udp(addr: SocketAddr) -> std::io::Result<UdpSocket> {
    use socket2::{Domain, Protocol, Socket, Type};
    let s = Socket::new(Domain::for_address(addr), Type::DGRAM, Some(Protocol::UDP))?;
    // Best effort: a smaller buffer still works, it only drops sooner.
    let _ = s.set_recv_buffer_size(SOCKET_BUFFER);
    let _ = s.set_send_buffer_size(SOCKET_BUFFER);
    s.set_nonblocking(true)?;
    s.bind(&addr.into())?;
    UdpSocket::from_std(s.into())
}

/// Datagrams waiting per direction before more are dropped.
const QUEUE_DATAGRAMS: usize = 65_536;

/// How long the pacing queue of a capped direction may get (the router
/// buffer): 50 ms, or twice the latency when that is longer.
fn queue_limit(shape: &LinkShape) -> Duration {
    (2 * shape.latency).max(Duration::from_millis(50))
}

/// A link shared by several relays or sessions (a node's uplink or
/// downlink), with the relay's queue limit for `shape`.
pub fn shared_link(shape: LinkShape, seed: u64) -> SharedShaper {
    shared(Shaper::new(shape, seed, queue_limit(&shape)))
}

/// How a relay shapes its two directions.
#[derive(Clone, Debug, Default)]
pub struct RelayShaping {
    /// Towards the node, a link per session.
    pub to_upstream: LinkShape,
    /// Towards the client, a link per session.
    pub to_client: LinkShape,
    /// Towards the node, after the session's link: one shared link.
    pub shared_to_upstream: Option<SharedShaper>,
    /// Towards the client, after the session's link: one shared link.
    pub shared_to_client: Option<SharedShaper>,
}

impl RelayShaping {
    /// The hops of one new session's direction.
    fn session_path(own: LinkShape, shared_link: &Option<SharedShaper>, seed: u64) -> Path {
        let own = (!own.is_none()).then(|| shared(Shaper::new(own, seed, queue_limit(&own))));
        Path::new(own.into_iter().chain(shared_link.clone()).collect())
    }
}

/// Datagram counts of a relay, both directions together.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RelayStats {
    /// Datagrams sent on.
    pub forwarded: u64,
    /// Datagrams dropped by the loss probability.
    pub lost: u64,
    /// Datagrams dropped because the queue was full.
    pub overflowed: u64,
}

#[derive(Default)]
struct Counters {
    forwarded: AtomicU64,
    lost: AtomicU64,
    overflowed: AtomicU64,
    /// While set, every datagram is dropped (counted as lost).
    partitioned: AtomicBool,
}

/// A running relay. Dropping it stops it.
pub struct UdpRelay {
    local: SocketAddr,
    stop: watch::Sender<bool>,
    counters: Arc<Counters>,
}

impl UdpRelay {
    /// Listens on `listen` and forwards to `upstream`; `to_upstream` shapes
    /// datagrams towards the node, `to_client` the answers.
    pub async fn start(
        listen: SocketAddr,
        upstream: SocketAddr,
        to_upstream: LinkShape,
        to_client: LinkShape,
    ) -> std::io::Result<UdpRelay> {
        let shaping = RelayShaping {
            to_upstream,
            to_client,
            ..RelayShaping::default()
        };
        UdpRelay::start_shaped(listen, upstream, shaping).await
    }

    /// Listens on `listen` and forwards to `upstream`, shaped by `shaping`.
    pub async fn start_shaped(
        listen: SocketAddr,
        upstream: SocketAddr,
        shaping: RelayShaping,
    ) -> std::io::Result<UdpRelay> {
        let front = Arc::new(bind_udp(listen)?);
        let local = front.local_addr()?;
        let (stop, stop_rx) = watch::channel(false);
        let counters = Arc::new(Counters::default());
        let span = info_span!("udp_relay", %local, %upstream);
        tokio::spawn(
            front_loop(front, upstream, shaping, counters.clone(), stop_rx).instrument(span),
        );
        Ok(UdpRelay {
            local,
            stop,
            counters,
        })
    }

    /// Cuts (`true`) or heals (`false`) the link: while cut, every datagram
    /// in both directions is dropped, as by a network partition; QUIC then
    /// sees its peer vanish without a word.
    pub fn partition(&self, cut: bool) {
        self.counters.partitioned.store(cut, Relaxed);
    }

    /// What the relay did so far.
    pub fn stats(&self) -> RelayStats {
        RelayStats {
            forwarded: self.counters.forwarded.load(Relaxed),
            lost: self.counters.lost.load(Relaxed),
            overflowed: self.counters.overflowed.load(Relaxed),
        }
    }

    /// Where clients send to.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }
}

impl Drop for UdpRelay {
    fn drop(&mut self) {
        self.stop.send_replace(true);
    }
}

/// One shaped direction: decides each datagram's fate and hands it to a
/// task that sends it at its time.
struct Direction {
    path: Path,
    tx: mpsc::Sender<(Instant, Vec<u8>)>,
    counters: Arc<Counters>,
}

impl Direction {
    fn new(
        path: Path,
        sock: Arc<UdpSocket>,
        to: Option<SocketAddr>,
        counters: Arc<Counters>,
        mut stop: watch::Receiver<bool>,
    ) -> Direction {
        let (tx, mut rx) = mpsc::channel::<(Instant, Vec<u8>)>(QUEUE_DATAGRAMS);
        tokio::spawn(
            async move {
                loop {
                    let next = tokio::select! {
                        n = rx.recv() => n,
                        _ = stop.changed() => None,
                    };
                    let Some((at, pkt)) = next else { break };
                    if at > Instant::now() {
                        tokio::time::sleep_until(at).await;
                    }
                    let r = match to {
                        Some(addr) => sock.send_to(&pkt, addr).await,
                        None => sock.send(&pkt).await,
                    };
                    if let Err(e) = r {
                        trace!(error = %e, "relay send failed");
                    }
                }
            }
            .in_current_span(),
        );
        Direction { path, tx, counters }
    }

    fn push(&self, pkt: &[u8]) {
        if self.counters.partitioned.load(Relaxed) {
            self.counters.lost.fetch_add(1, Relaxed);
            return;
        }
        match self.path.datagram(pkt.len()) {
            Verdict::At(at) => {
                if self.tx.try_send((at, pkt.to_vec())).is_err() {
                    self.counters.overflowed.fetch_add(1, Relaxed);
                } else {
                    self.counters.forwarded.fetch_add(1, Relaxed);
                }
            }
            Verdict::Drop => {
                self.counters.lost.fetch_add(1, Relaxed);
            }
            Verdict::Overflow => {
                self.counters.overflowed.fetch_add(1, Relaxed);
            }
        }
    }
}

async fn front_loop(
    front: Arc<UdpSocket>,
    upstream: SocketAddr,
    shaping: RelayShaping,
    counters: Arc<Counters>,
    mut stop: watch::Receiver<bool>,
) {
    // Sessions live as long as the relay (one per client address).
    let mut sessions: HashMap<SocketAddr, Arc<Direction>> = HashMap::new();
    let mut buf = vec![0u8; MAX_DATAGRAM];
    let mut seed = 1u64;
    loop {
        let got = tokio::select! {
            r = front.recv_from(&mut buf) => r,
            _ = stop.changed() => break,
        };
        let (n, client) = match got {
            Ok(v) => v,
            Err(e) => {
                debug!(error = %e, "relay receive failed");
                continue;
            }
        };
        let dir = match sessions.get(&client) {
            Some(d) => d.clone(),
            None => {
                let Ok(back) = open_session(upstream).await else {
                    continue;
                };
                seed += 2;
                let up = Arc::new(Direction::new(
                    RelayShaping::session_path(
                        shaping.to_upstream,
                        &shaping.shared_to_upstream,
                        seed,
                    ),
                    back.clone(),
                    None,
                    counters.clone(),
                    stop.clone(),
                ));
                let down = Direction::new(
                    RelayShaping::session_path(
                        shaping.to_client,
                        &shaping.shared_to_client,
                        seed + 1,
                    ),
                    front.clone(),
                    Some(client),
                    counters.clone(),
                    stop.clone(),
                );
                tokio::spawn(back_loop(back, down, stop.clone()).in_current_span());
                debug!(%client, "relay session opened");
                sessions.insert(client, up.clone());
                up
            }
        };
        dir.push(&buf[..n]);
    }
}

async fn open_session(upstream: SocketAddr) -> std::io::Result<Arc<UdpSocket>> {
    let bind: SocketAddr = if upstream.is_ipv4() {
        SocketAddr::from(([127, 0, 0, 1], 0))
    } else {
        SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, 0))
    };
    let s = bind_udp(bind)?;
    s.connect(upstream).await?;
    Ok(Arc::new(s))
}

async fn back_loop(back: Arc<UdpSocket>, down: Direction, mut stop: watch::Receiver<bool>) {
    let mut buf = vec![0u8; MAX_DATAGRAM];
    loop {
        let got = tokio::select! {
            r = back.recv(&mut buf) => r,
            _ = stop.changed() => break,
        };
        match got {
            Ok(n) => down.push(&buf[..n]),
            Err(e) => trace!(error = %e, "relay upstream receive failed"),
        }
    }
}
