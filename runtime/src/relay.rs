//! A UDP relay that shapes a QUIC link: it sits in front of a node, and
//! delays, paces (bandwidth cap with a bounded queue, tail drop) and drops
//! datagrams in each direction, so QUIC's own congestion control and
//! retransmission are what copes (this machine's kernel has no netem).
//!
//! Each client source address gets its own upstream socket, so the node sees
//! one distinct peer per client, as without the relay.

use crate::shaping::{LinkShape, Shaper, Verdict};
use std::collections::HashMap;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;
use tokio::net::UdpSocket;
use tokio::sync::{mpsc, watch, Mutex};
use tokio::time::Instant;
use tracing::{debug, info_span, trace, Instrument};

/// Largest datagram relayed.
const MAX_DATAGRAM: usize = 65_535;
/// Datagrams waiting per direction before more are dropped.
const QUEUE_DATAGRAMS: usize = 65_536;

/// How long the pacing queue of a capped direction may get (the router
/// buffer): 50 ms, or twice the latency when that is longer.
fn queue_limit(shape: &LinkShape) -> Duration {
    (2 * shape.latency).max(Duration::from_millis(50))
}

/// A running relay. Dropping it stops it.
pub struct UdpRelay {
    local: SocketAddr,
    stop: watch::Sender<bool>,
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
        let front = Arc::new(UdpSocket::bind(listen).await?);
        let local = front.local_addr()?;
        let (stop, stop_rx) = watch::channel(false);
        let span = info_span!("udp_relay", %local, %upstream);
        tokio::spawn(front_loop(front, upstream, to_upstream, to_client, stop_rx).instrument(span));
        Ok(UdpRelay { local, stop })
    }

    /// Where clients send to.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }
}

impl Drop for UdpRelay {
    fn drop(&mut self) {
        let _ = self.stop.send(true);
    }
}

/// One shaped direction: decides each datagram's fate and hands it to a
/// task that sends it at its time.
struct Direction {
    shaper: std::sync::Mutex<Shaper>,
    tx: mpsc::Sender<(Instant, Vec<u8>)>,
}

impl Direction {
    fn new(
        shape: LinkShape,
        seed: u64,
        sock: Arc<UdpSocket>,
        to: Option<SocketAddr>,
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
                    tokio::time::sleep_until(at).await;
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
        Direction {
            shaper: std::sync::Mutex::new(Shaper::new(shape, seed, queue_limit(&shape))),
            tx,
        }
    }

    fn push(&self, pkt: &[u8]) {
        let verdict = self
            .shaper
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .datagram(pkt.len());
        match verdict {
            Verdict::At(at) => {
                if self.tx.try_send((at, pkt.to_vec())).is_err() {
                    trace!("relay queue full; datagram dropped");
                }
            }
            Verdict::Drop => trace!(bytes = pkt.len(), "datagram dropped"),
        }
    }
}

async fn front_loop(
    front: Arc<UdpSocket>,
    upstream: SocketAddr,
    to_upstream: LinkShape,
    to_client: LinkShape,
    mut stop: watch::Receiver<bool>,
) {
    let sessions: Mutex<HashMap<SocketAddr, Arc<Direction>>> = Mutex::new(HashMap::new());
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
        let mut map = sessions.lock().await;
        let dir = match map.get(&client) {
            Some(d) => d.clone(),
            None => {
                let Ok(back) = open_session(upstream).await else {
                    continue;
                };
                seed += 2;
                let up = Arc::new(Direction::new(
                    to_upstream,
                    seed,
                    back.clone(),
                    None,
                    stop.clone(),
                ));
                let down = Direction::new(
                    to_client,
                    seed + 1,
                    front.clone(),
                    Some(client),
                    stop.clone(),
                );
                tokio::spawn(back_loop(back, down, stop.clone()).in_current_span());
                debug!(%client, "relay session opened");
                map.insert(client, up.clone());
                up
            }
        };
        drop(map);
        dir.push(&buf[..n]);
    }
}

async fn open_session(upstream: SocketAddr) -> std::io::Result<Arc<UdpSocket>> {
    let bind: SocketAddr = if upstream.is_ipv4() {
        SocketAddr::from(([127, 0, 0, 1], 0))
    } else {
        SocketAddr::from((std::net::Ipv6Addr::LOCALHOST, 0))
    };
    let s = UdpSocket::bind(bind).await?;
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
