//! The QUIC transport on loopback: every kind, mutual TLS refusals, bad
//! frames, connection loss and redial, and the shaping relay.
//!
//! These run on the real clock (sockets); the timeouts only guard against a
//! hang, no test asserts how fast anything is, except the relay's lower
//! bound, which no speed of this machine can beat.

mod common;

use common::*;
use dray_protocol::{
    encode_envelope, Address, Blob, Envelope, FetchVoxel, Handshake, Hello, Message, Ping, Role,
    VoxelLoaded, PROTOCOL_VERSION,
};
use dray_runtime::certs::{
    add_nodes, bundle, init_cluster, init_cluster_in, CertError, ClusterCa, NodeIdentity,
};
use dray_runtime::quic::{DialTarget, QuicTransport, STREAM_BULK, STREAM_CONTROL};
use dray_runtime::relay::{shared_link, RelayShaping, UdpRelay};
use dray_runtime::{Bus, Delivery, LinkShape};
use quinn::crypto::rustls::QuicClientConfig;
use quinn::{Connection, Endpoint};
use std::future::Future;
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::Duration;

const GUARD: Duration = Duration::from_secs(20);

async fn guard<T>(f: impl Future<Output = T>) -> T {
    tokio::time::timeout(GUARD, f).await.expect("test hung")
}

/// Why `t`'s dial to `peer` failed, once one has.
async fn first_dial_error(t: &QuicTransport, peer: &str) -> String {
    guard(async {
        loop {
            if let Some(e) = t.dial_error(&name(peer)) {
                return e;
            }
            tokio::time::sleep(Duration::from_millis(10)).await;
        }
    })
    .await
}

fn loopback() -> SocketAddr {
    "127.0.0.1:0".parse().unwrap()
}

async fn node(id: &NodeIdentity, role: Role) -> (Bus, Arc<QuicTransport>) {
    let bus = Bus::new(id.node().clone(), role);
    let t = QuicTransport::start(&bus, id, loopback()).await.unwrap();
    (bus, t)
}

/// Two nodes, `node-a` dialing `node-b`, connected.
async fn connected_pair(ca: &ClusterCa) -> (Bus, Arc<QuicTransport>, Bus, Arc<QuicTransport>) {
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    ta.connect(name("node-b"), tb.local_addr().unwrap());
    guard(a.wait_for_peer(&name("node-b"))).await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    (a, ta, b, tb)
}

async fn ping_pong(a: &Bus, b: &Bus, seq: u64) {
    let ma = a.mailbox(name(&format!("pinger-{seq}")), 4).unwrap();
    let mut mb = b.mailbox(name(&format!("ponger-{seq}")), 4).unwrap();
    ma.send(mb.address(), Message::Ping(Ping { seq }))
        .await
        .unwrap();
    let (from, msg) = guard(next_message(&mut mb)).await;
    assert_eq!(from, *ma.address());
    assert_eq!(msg, Message::Ping(Ping { seq }));
}

/// A bare quinn client with `id`'s certificate, dialing `server_name`.
async fn raw_connect(
    id: &NodeIdentity,
    addr: SocketAddr,
    server_name: &str,
) -> Result<(Endpoint, Connection), String> {
    let mut ep = Endpoint::client(loopback()).map_err(|e| e.to_string())?;
    let crypto = QuicClientConfig::try_from(id.client_tls().unwrap()).unwrap();
    ep.set_default_client_config(quinn::ClientConfig::new(Arc::new(crypto)));
    let conn = ep
        .connect(addr, server_name)
        .map_err(|e| e.to_string())?
        .await
        .map_err(|e| e.to_string())?;
    Ok((ep, conn))
}

fn frame(body: &[u8]) -> Vec<u8> {
    let mut f = (body.len() as u32).to_be_bytes().to_vec();
    f.extend_from_slice(body);
    f
}

/// Sends a handshake message and reads the answer.
async fn raw_hello(conn: &Connection, hs: &Handshake) -> Result<Handshake, String> {
    let (mut send, mut recv) = conn.open_bi().await.map_err(|e| e.to_string())?;
    send.write_all(&frame(&hs.encode().unwrap()))
        .await
        .map_err(|e| e.to_string())?;
    let mut len = [0u8; 4];
    recv.read_exact(&mut len).await.map_err(|e| e.to_string())?;
    let mut body = vec![0u8; u32::from_be_bytes(len) as usize];
    recv.read_exact(&mut body)
        .await
        .map_err(|e| e.to_string())?;
    Handshake::decode(&body).map_err(|e| e.to_string())
}

fn hello(node: &str, version: u32) -> Handshake {
    Handshake::Hello(Hello {
        version,
        role: Role::Tool,
        node: name(node),
    })
}

#[tokio::test]
async fn every_kind_crosses_quic_with_certificates_from_disk() {
    let dir = tempfile::tempdir().unwrap();
    let written = init_cluster(dir.path(), &["node-a", "node-b"]).unwrap();
    assert_eq!(written.len(), 6);
    assert!(
        init_cluster(dir.path(), &["node-a"]).is_err(),
        "an existing CA is never replaced"
    );
    let ida = NodeIdentity::load(dir.path(), &name("node-a")).unwrap();
    let idb = NodeIdentity::load(dir.path(), &name("node-b")).unwrap();
    let err = NodeIdentity::load(dir.path(), &name("node-z")).unwrap_err();
    assert!(err.to_string().contains("node-z.pem"), "{err}");

    let (a, ta) = node(&ida, Role::Tool).await;
    let (b, tb) = node(&idb, Role::Tool).await;
    ta.connect(name("node-b"), tb.local_addr().unwrap());
    guard(a.wait_for_peer(&name("node-b"))).await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    assert_eq!(b.peers(), vec![(name("node-a"), Role::Tool)]);
    assert_eq!(a.peers(), vec![(name("node-b"), Role::Tool)]);
    guard(exchange_every_kind(&a, &b)).await;
    ta.shutdown().await;
    tb.shutdown().await;
}

#[tokio::test]
async fn strangers_are_refused_and_the_node_keeps_serving() {
    let ca = ClusterCa::generate().unwrap();
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    let mut watcher = b.mailbox(name("watcher"), 16).unwrap();
    let addr = tb.local_addr().unwrap();

    // A self-signed certificate, and one from another CA; both strangers
    // know (and trust) the cluster's public CA certificate.
    let self_signed = NodeIdentity::self_signed(&name("node-c"))
        .unwrap()
        .trusting(ca.cert_der());
    let other_ca = ClusterCa::generate()
        .unwrap()
        .issue(&name("node-c"))
        .unwrap()
        .trusting(ca.cert_der());
    for stranger in [self_signed, other_ca] {
        let outcome = guard(async {
            let (_ep, conn) = raw_connect(&stranger, addr, "node-b").await?;
            raw_hello(&conn, &hello("node-c", PROTOCOL_VERSION)).await
        })
        .await;
        assert!(outcome.is_err(), "stranger got {outcome:?}");
    }
    // A legitimate client refuses a server whose certificate is foreign.
    let rogue = ClusterCa::generate()
        .unwrap()
        .issue(&name("node-b"))
        .unwrap();
    let (_rogue_bus, rogue_t) = node(&rogue, Role::Tool).await;
    let legit = ca.issue(&name("node-a")).unwrap();
    let outcome = guard(raw_connect(&legit, rogue_t.local_addr().unwrap(), "node-b")).await;
    assert!(outcome.is_err());

    // Nothing from the strangers reached the node; a member still gets in.
    let (a, ta) = node(&legit, Role::Tool).await;
    ta.connect(name("node-b"), addr);
    guard(a.wait_for_peer(&name("node-b"))).await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    assert_eq!(
        guard(watcher.recv()).await,
        Some(Delivery::PeerUp {
            node: name("node-a"),
            role: Role::Tool
        }),
        "the first event is the member's arrival"
    );
    assert_eq!(b.peers().len(), 1);
    ping_pong(&a, &b, 1).await;
}

#[tokio::test]
async fn version_mismatch_and_impersonation_are_refused_clearly() {
    let ca = ClusterCa::generate().unwrap();
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    let addr = tb.local_addr().unwrap();
    let idc = ca.issue(&name("node-c")).unwrap();

    let (_ep, conn) = guard(raw_connect(&idc, addr, "node-b")).await.unwrap();
    let answer = guard(raw_hello(&conn, &hello("node-c", PROTOCOL_VERSION + 1))).await;
    match answer {
        Ok(Handshake::Refused { reason, version }) => {
            assert_eq!(version, PROTOCOL_VERSION);
            assert!(reason.contains("version mismatch"), "{reason}");
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    guard(conn.closed()).await;

    // A member whose certificate says node-c may not claim to be node-a.
    let (_ep, conn) = guard(raw_connect(&idc, addr, "node-b")).await.unwrap();
    let answer = guard(raw_hello(&conn, &hello("node-a", PROTOCOL_VERSION))).await;
    assert!(
        matches!(answer, Ok(Handshake::Refused { .. })),
        "{answer:?}"
    );
    guard(conn.closed()).await;
    assert!(b.peers().is_empty());
}

/// Connects a raw member client `node-c` to `addr` through the handshake.
async fn raw_member(ca: &ClusterCa, addr: SocketAddr) -> (Endpoint, Connection) {
    let idc = ca.issue(&name("node-c")).unwrap();
    let (ep, conn) = guard(raw_connect(&idc, addr, "node-b")).await.unwrap();
    let answer = guard(raw_hello(&conn, &hello("node-c", PROTOCOL_VERSION))).await;
    assert!(matches!(answer, Ok(Handshake::Welcome(_))), "{answer:?}");
    (ep, conn)
}

fn ping_from_c(seq: u64) -> Vec<u8> {
    encode_envelope(&Envelope {
        msg: Message::Ping(Ping { seq }),
        from: Address::new(name("node-c"), name("raw")),
        to: Address::new(name("node-b"), name("beta")),
    })
    .unwrap()
}

#[tokio::test]
async fn bad_frames_close_only_their_stream_or_connection() {
    let ca = ClusterCa::generate().unwrap();
    let (a, _ta, b, tb) = connected_pair(&ca).await;
    let addr = tb.local_addr().unwrap();
    let mut beta = b.mailbox(name("beta"), 16).unwrap();

    // A bulk stream claiming an oversized voxel is stopped; the connection
    // and its control stream go on.
    let (_ep, conn) = raw_member(&ca, addr).await;
    guard(b.wait_for_peer(&name("node-c"))).await;
    let mut bulk = conn.open_uni().await.unwrap();
    let mut head = vec![STREAM_BULK];
    head.extend_from_slice(&u32::MAX.to_be_bytes());
    head.push(4); // VoxelLoaded
    bulk.write_all(&head).await.unwrap();
    let stopped = guard(bulk.stopped()).await.unwrap();
    assert_eq!(stopped, Some(quinn::VarInt::from_u32(1)));
    // A bulk stream with a garbage body is stopped too.
    let mut bulk = conn.open_uni().await.unwrap();
    let mut junk = vec![STREAM_BULK];
    junk.extend_from_slice(&frame(&[4, 0xff, 0xff, 0xff, 0xff, 0xff, 0xff, 0x7f]));
    bulk.write_all(&junk).await.unwrap();
    bulk.finish().unwrap();
    // (The node read all of it before refusing it, so whether the stop or
    // the acknowledgement reaches us first is a race; what matters is that
    // nothing of it is delivered and the connection lives on.)

    let mut ctl = conn.open_uni().await.unwrap();
    let mut bytes = vec![STREAM_CONTROL];
    bytes.extend_from_slice(&frame(&ping_from_c(5)));
    ctl.write_all(&bytes).await.unwrap();
    let (from, msg) = guard(next_message(&mut beta)).await;
    assert_eq!(from, Address::new(name("node-c"), name("raw")));
    assert_eq!(msg, Message::Ping(Ping { seq: 5 }));

    // A malformed control frame closes that connection.
    ctl.write_all(&frame(&[0, 1, 2, 3, 4])).await.unwrap();
    let reason = guard(conn.closed()).await;
    assert!(
        matches!(reason, quinn::ConnectionError::ApplicationClosed(ref c) if c.error_code == quinn::VarInt::from_u32(1)),
        "{reason:?}"
    );
    guard(b.wait_for_peer_loss(&name("node-c"))).await;

    // An oversized control frame (and a sender impersonating another node)
    // closes the connection too.
    for bad in [
        {
            let mut v = vec![STREAM_CONTROL];
            v.extend_from_slice(&(64u32 << 20).to_be_bytes());
            v
        },
        {
            let mut v = vec![STREAM_CONTROL];
            let spoof = encode_envelope(&Envelope {
                msg: Message::Ping(Ping { seq: 1 }),
                from: Address::new(name("node-a"), name("x")),
                to: Address::new(name("node-b"), name("beta")),
            })
            .unwrap();
            v.extend_from_slice(&frame(&spoof));
            v
        },
    ] {
        let (_ep, conn) = raw_member(&ca, addr).await;
        let mut ctl = conn.open_uni().await.unwrap();
        ctl.write_all(&bad).await.unwrap();
        guard(conn.closed()).await;
    }

    // Meanwhile node-a was never disturbed.
    assert!(b.is_connected(&name("node-a")));
    ping_pong(&a, &b, 2).await;
    // No message from the bad streams reached the actor.
    assert!(matches!(
        beta.try_recv(),
        None | Some(Delivery::PeerUp { .. } | Delivery::PeerDown { .. })
    ));
}

#[tokio::test]
async fn connection_loss_is_an_event_and_the_dialer_reconnects() {
    let ca = ClusterCa::generate().unwrap();
    let idb = ca.issue(&name("node-b")).unwrap();
    let (a, ta, _b, tb) = connected_pair(&ca).await;
    let mut ma = a.mailbox(name("sched"), 16).unwrap();
    let addr = tb.local_addr().unwrap();

    tb.shutdown().await;
    drop(tb);
    let ev = guard(ma.recv()).await;
    assert!(
        matches!(ev, Some(Delivery::PeerDown { ref node, .. }) if *node == name("node-b")),
        "{ev:?}"
    );
    assert!(a
        .send(
            ma.address(),
            &Address::new(name("node-b"), name("x")),
            Message::Ping(Ping { seq: 0 })
        )
        .await
        .is_err());

    // node-b comes back on the same address; node-a redials by itself.
    let b2 = Bus::new(name("node-b"), Role::Tool);
    // The old endpoint lets go of its port once its last connection task
    // has ended; retry the bind until it has.
    let tb2 = guard(async {
        loop {
            match QuicTransport::start(&b2, &idb, addr).await {
                Ok(t) => break t,
                Err(_) => tokio::time::sleep(Duration::from_millis(10)).await,
            }
        }
    })
    .await;
    let ev = guard(ma.recv()).await;
    assert_eq!(
        ev,
        Some(Delivery::PeerUp {
            node: name("node-b"),
            role: Role::Tool
        })
    );
    ping_pong(&a, &b2, 3).await;
    ta.shutdown().await;
    tb2.shutdown().await;
}

#[tokio::test]
async fn relay_delay_shows_in_the_round_trip() {
    let ca = ClusterCa::generate().unwrap();
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    let shape = LinkShape {
        latency: Duration::from_millis(20),
        ..LinkShape::none()
    };
    let relay = UdpRelay::start(loopback(), tb.local_addr().unwrap(), shape, shape)
        .await
        .unwrap();
    ta.connect(name("node-b"), relay.local_addr());
    guard(a.wait_for_peer(&name("node-b"))).await;

    let mut ma = a.mailbox(name("pinger"), 4).unwrap();
    let mut mb = b.mailbox(name("ponger"), 4).unwrap();
    let to = mb.address().clone();
    let echo = tokio::spawn(async move {
        for _ in 0..3 {
            let (from, msg) = next_message(&mut mb).await;
            let Message::Ping(p) = msg else { continue };
            mb.send(&from, Message::Pong(p)).await.unwrap();
        }
    });
    for seq in 0..3 {
        let t0 = std::time::Instant::now();
        ma.send(&to, Message::Ping(Ping { seq })).await.unwrap();
        let (_, msg) = guard(next_message(&mut ma)).await;
        assert_eq!(msg, Message::Pong(Ping { seq }));
        let rtt = t0.elapsed();
        assert!(rtt >= Duration::from_millis(40), "round trip {rtt:?}");
    }
    guard(echo).await.unwrap();
}

#[tokio::test]
async fn every_kind_crosses_a_lossy_capped_relay() {
    let ca = ClusterCa::generate().unwrap();
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    // QUIC's retransmission and congestion control have to cope.
    let shape = LinkShape {
        latency: Duration::from_millis(2),
        jitter: Duration::from_millis(1),
        bandwidth_bps: Some(200_000_000),
        loss: 0.03,
    };
    let relay = UdpRelay::start(loopback(), tb.local_addr().unwrap(), shape, shape)
        .await
        .unwrap();
    ta.connect(name("node-b"), relay.local_addr());
    guard(a.wait_for_peer(&name("node-b"))).await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    guard(exchange_every_kind(&a, &b)).await;
    ta.shutdown().await;
    tb.shutdown().await;
}

#[tokio::test]
async fn a_big_voxel_does_not_hold_back_a_control_message() {
    use dray_protocol::{Blob, VoxelLoaded};
    let ca = ClusterCa::generate().unwrap();
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    // 4 MB at 50 Mbit/s takes most of a second on the wire.
    let shape = LinkShape {
        bandwidth_bps: Some(50_000_000),
        ..LinkShape::none()
    };
    let relay = UdpRelay::start(loopback(), tb.local_addr().unwrap(), shape, shape)
        .await
        .unwrap();
    ta.connect(name("node-b"), relay.local_addr());
    guard(a.wait_for_peer(&name("node-b"))).await;
    let ma = a.mailbox(name("store"), 4).unwrap();
    let mut mb = b.mailbox(name("loader"), 4).unwrap();
    let voxel = Message::VoxelLoaded(VoxelLoaded {
        id: 1,
        data: Blob(vec![7u8; 4 << 20]),
    });
    let to = mb.address().clone();
    let sender = tokio::spawn(async move {
        ma.send(&to, voxel).await.unwrap();
        ma.send(&to, Message::Ping(Ping { seq: 1 })).await.unwrap();
        ma
    });
    let (_, first) = guard(next_message(&mut mb)).await;
    assert_eq!(
        first,
        Message::Ping(Ping { seq: 1 }),
        "the ping overtook the voxel"
    );
    let (_, second) = guard(next_message(&mut mb)).await;
    assert!(matches!(second, Message::VoxelLoaded(v) if v.data.0.len() == 4 << 20));
    guard(sender).await.unwrap();
    ta.shutdown().await;
    tb.shutdown().await;
}

#[tokio::test]
async fn a_silent_partition_is_detected_and_healed() {
    let ca = ClusterCa::generate().unwrap();
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let (b, tb) = node(&ca.issue(&name("node-b")).unwrap(), Role::Tool).await;
    let relay = UdpRelay::start(
        loopback(),
        tb.local_addr().unwrap(),
        LinkShape::none(),
        LinkShape::none(),
    )
    .await
    .unwrap();
    ta.connect(name("node-b"), relay.local_addr());
    guard(a.wait_for_peer(&name("node-b"))).await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    let mut ma = a.mailbox(name("client"), 16).unwrap();
    let mut mb = b.mailbox(name("sched"), 16).unwrap();

    // No close frame gets through: both sides find out by the idle timeout.
    relay.partition(true);
    let down = |d: Option<Delivery>, who: &str| {
        assert!(
            matches!(d, Some(Delivery::PeerDown { ref node, .. }) if *node == name(who)),
            "{d:?}"
        )
    };
    down(guard(ma.recv()).await, "node-b");
    down(guard(mb.recv()).await, "node-a");
    assert!(relay.stats().lost > 0);

    // Healed, the dialer gets back in by itself.
    relay.partition(false);
    assert_eq!(
        guard(ma.recv()).await,
        Some(Delivery::PeerUp {
            node: name("node-b"),
            role: Role::Tool
        })
    );
    guard(b.wait_for_peer(&name("node-a"))).await;
    ping_pong(&a, &b, 4).await;
    ta.shutdown().await;
    tb.shutdown().await;
}

/// A store's uplink over QUIC: one relay in front of the store whose answers
/// cross one shared link, so four clients together get no more than that
/// link's bandwidth. Only the lower bound on the time is asserted (no
/// machine can beat it); without sharing it would take a quarter of it.
#[tokio::test]
async fn clients_share_a_store_uplink_through_its_relay() {
    const CLIENTS: usize = 4;
    const PER_CLIENT: u32 = 6;
    const VOXEL: usize = 64 << 10;
    const CAP_BPS: u64 = 20_000_000;
    let ca = ClusterCa::generate().unwrap();
    let (s, ts) = node(&ca.issue(&name("store-0")).unwrap(), Role::Store).await;
    let uplink = LinkShape {
        latency: Duration::from_millis(2),
        bandwidth_bps: Some(CAP_BPS),
        ..LinkShape::none()
    };
    let shaping = RelayShaping {
        shared_to_client: Some(shared_link(uplink, 1)),
        ..RelayShaping::default()
    };
    let relay = UdpRelay::start_shaped(loopback(), ts.local_addr().unwrap(), shaping)
        .await
        .unwrap();
    let mut store = s.mailbox(name("store"), 256).unwrap();
    let store_addr = store.address().clone();
    tokio::spawn(async move {
        while let Some((from, msg)) = store.recv_message().await {
            if let Message::FetchVoxel(FetchVoxel { id }) = msg {
                let data = Blob(vec![id as u8; VOXEL]);
                let _ = store
                    .send(&from, Message::VoxelLoaded(VoxelLoaded { id, data }))
                    .await;
            }
        }
    });
    let mut clients = Vec::new();
    for i in 0..CLIENTS {
        let id = ca.issue(&name(&format!("client-{i}"))).unwrap();
        let (c, tc) = node(&id, Role::Client).await;
        tc.connect(name("store-0"), relay.local_addr());
        guard(c.wait_for_peer(&name("store-0"))).await;
        clients.push((c, tc));
    }
    let t0 = std::time::Instant::now();
    let mut pulls = Vec::new();
    for (c, _) in &clients {
        let mut mb = c.mailbox(name("loader"), 64).unwrap();
        let to = store_addr.clone();
        pulls.push(tokio::spawn(async move {
            for id in 0..PER_CLIENT {
                let ask = Message::FetchVoxel(FetchVoxel { id });
                mb.send(&to, ask).await.unwrap();
            }
            for _ in 0..PER_CLIENT {
                let (_, msg) = next_message(&mut mb).await;
                assert!(matches!(msg, Message::VoxelLoaded(_)));
            }
        }));
    }
    for p in pulls {
        guard(p).await.unwrap();
    }
    let took = t0.elapsed();
    let payload_bits = (CLIENTS * PER_CLIENT as usize * VOXEL * 8) as f64;
    let least = Duration::from_secs_f64(payload_bits / CAP_BPS as f64);
    assert!(
        took >= least,
        "{took:?}: faster than one shared {CAP_BPS} bit/s uplink allows ({least:?})"
    );
    for (_, tc) in &clients {
        tc.shutdown().await;
    }
    ts.shutdown().await;
}

/// A store `store-0` and a client `client-0` of one CA, connected.
async fn store_and_client(ca: &ClusterCa) -> (Bus, Arc<QuicTransport>, Bus, Arc<QuicTransport>) {
    let (s, ts) = node(&ca.issue(&name("store-0")).unwrap(), Role::Store).await;
    let (c, tc) = node(&ca.issue(&name("client-0")).unwrap(), Role::Client).await;
    tc.connect(name("store-0"), ts.local_addr().unwrap());
    guard(tc.wait_connected(&name("store-0"))).await.unwrap();
    guard(s.wait_for_peer(&name("client-0"))).await;
    (s, ts, c, tc)
}

#[tokio::test]
async fn a_client_may_not_stop_a_store_and_may_not_claim_another_role() {
    use dray_protocol::Shutdown;
    let ca = ClusterCa::generate().unwrap();
    let (s, ts, c, _tc) = store_and_client(&ca).await;
    let mut store = s.mailbox(name("store"), 8).unwrap();
    let client = c.mailbox(name("client"), 8).unwrap();
    client
        .send(
            store.address(),
            Message::Shutdown(Shutdown {
                reason: "a client says so".into(),
            }),
        )
        .await
        .unwrap();
    let fetch = Message::FetchVoxel(FetchVoxel { id: 3 });
    client.send(store.address(), fetch.clone()).await.unwrap();
    // Same control stream, so the fetch comes after the refused shutdown.
    assert_eq!(guard(next_message(&mut store)).await.1, fetch);
    assert!(s.is_connected(&name("client-0")));

    // A client's certificate cannot make it a display (which may stop nodes).
    let idc = ca.issue(&name("client-1")).unwrap();
    let (_ep, conn) = guard(raw_connect(&idc, ts.local_addr().unwrap(), "store-0"))
        .await
        .unwrap();
    let claim = Handshake::Hello(Hello {
        version: PROTOCOL_VERSION,
        role: Role::Display,
        node: name("client-1"),
    });
    match guard(raw_hello(&conn, &claim)).await {
        Ok(Handshake::Refused { reason, .. }) => {
            assert!(reason.contains("makes it a client"), "{reason}")
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    assert_eq!(s.peers(), vec![(name("client-0"), Role::Client)]);
    // And a transport refuses to start under a role its name does not have.
    let bus = Bus::new(name("client-2"), Role::Display);
    let err = QuicTransport::start(&bus, &ca.issue(&name("client-2")).unwrap(), loopback())
        .await
        .err()
        .expect("a client may not run as a display");
    assert!(err.to_string().contains("makes it a client"), "{err}");
}

#[tokio::test]
async fn a_second_connection_under_a_connected_name_is_refused_and_the_first_goes_on() {
    let ca = ClusterCa::generate().unwrap();
    let (s, ts, c, tc) = store_and_client(&ca).await;
    let addr = ts.local_addr().unwrap();
    // Another process with client-0's identity (the same --index twice).
    let twin = ca.issue(&name("client-0")).unwrap();
    let (ep, conn) = guard(raw_connect(&twin, addr, "store-0")).await.unwrap();
    let claim = Handshake::Hello(Hello {
        version: PROTOCOL_VERSION,
        role: Role::Client,
        node: name("client-0"),
    });
    match guard(raw_hello(&conn, &claim)).await {
        Ok(Handshake::Refused { reason, .. }) => {
            assert!(reason.contains("already connected"), "{reason}")
        }
        other => panic!("expected a refusal, got {other:?}"),
    }
    // The same through a transport: its dial is refused, saying why.
    let (_twin_bus, twin_t) = node(&twin, Role::Client).await;
    twin_t.connect(name("store-0"), addr);
    let why = first_dial_error(&twin_t, "store-0").await;
    assert!(why.contains("already connected"), "{why}");
    // The twins leave; the first connection carries on.
    twin_t.shutdown().await;
    drop((conn, ep));
    assert!(s.is_connected(&name("client-0")));
    ping_pong(&c, &s, 7).await;
    ping_pong(&s, &c, 8).await;
    // Once the first is gone, the name is free again (a restarted node).
    tc.shutdown().await;
    guard(s.wait_for_peer_loss(&name("client-0"))).await;
    let (c2, tc2) = node(&ca.issue(&name("client-0")).unwrap(), Role::Client).await;
    tc2.connect(name("store-0"), addr);
    guard(tc2.wait_connected(&name("store-0"))).await.unwrap();
    ping_pong(&c2, &s, 9).await;
}

#[tokio::test]
async fn a_certificate_of_another_ca_is_refused_as_from_an_unknown_issuer() {
    let ca = ClusterCa::generate().unwrap();
    let other = ClusterCa::generate().unwrap();
    let (_s, ts) = node(&ca.issue(&name("store-0")).unwrap(), Role::Store).await;
    let addr = ts.local_addr().unwrap();
    // A node whose whole identity comes from another CA: it refuses the
    // store. One with another CA's certificate but the cluster's ca.pem:
    // the store refuses it. Either way the dialer says why at once.
    let foreign = other.issue(&name("client-0")).unwrap();
    let mixed = other
        .issue(&name("client-1"))
        .unwrap()
        .trusting(ca.cert_der());
    for (id, refuser) in [(foreign, "client-0 refused"), (mixed, "store-0 refused")] {
        let peer = id.node().clone();
        let (_b, t) = node(&id, Role::Client).await;
        t.connect(name("store-0"), addr);
        let err = guard(t.wait_connected(&name("store-0")))
            .await
            .expect_err("a foreign certificate got in");
        let text = err.to_string();
        assert!(text.contains("unknown issuer"), "{peer}: {text}");
        assert!(text.contains("another CA"), "{peer}: {text}");
        assert!(text.contains(refuser), "{peer}: {text}");
        t.shutdown().await;
    }
}

#[tokio::test]
async fn the_ca_key_stays_apart_bundles_hold_one_node_and_nodes_can_be_added() {
    let dir = tempfile::tempdir().unwrap();
    let certs = dir.path().join("certs");
    init_cluster(&certs, &["store-0", "client-0"]).unwrap();
    let ca_key = std::fs::read_to_string(certs.join("ca").join("ca.key")).unwrap();
    assert!(!certs.join("ca.key").exists());

    // A bundle has what one node needs and nothing else.
    let out = dir.path().join("client-0-bundle");
    bundle(&certs, "client-0", &out).unwrap();
    let mut files: Vec<String> = std::fs::read_dir(&out)
        .unwrap()
        .map(|e| e.unwrap().file_name().into_string().unwrap())
        .collect();
    files.sort();
    assert_eq!(files, ["ca.pem", "client-0.key", "client-0.pem"]);
    for f in &files {
        let text = std::fs::read_to_string(out.join(f)).unwrap();
        assert_ne!(text, ca_key, "{f} is the CA key");
    }
    let err = bundle(&certs, "client-0", &out).unwrap_err();
    assert!(err.to_string().contains("already exists"), "{err}");
    let err = bundle(&certs, "client-7", &dir.path().join("x")).unwrap_err();
    assert!(err.to_string().contains("client-7.pem"), "{err}");

    // A node added later, from the same CA; the others keep theirs.
    let before = std::fs::read(certs.join("client-0.pem")).unwrap();
    add_nodes(&certs, None, &["client-1"]).unwrap();
    assert_eq!(std::fs::read(certs.join("client-0.pem")).unwrap(), before);
    let err = add_nodes(&certs, None, &["client-0"]).unwrap_err();
    assert!(matches!(err, CertError::NodeExists(_)), "{err}");

    // The bundled node and the added one both reach the store.
    let store = NodeIdentity::load(&certs, &name("store-0")).unwrap();
    let (s, ts) = node(&store, Role::Store).await;
    for id in [
        NodeIdentity::load(&out, &name("client-0")).unwrap(),
        NodeIdentity::load(&certs, &name("client-1")).unwrap(),
    ] {
        let (c, tc) = node(&id, Role::Client).await;
        tc.connect(name("store-0"), ts.local_addr().unwrap());
        guard(tc.wait_connected(&name("store-0"))).await.unwrap();
        ping_pong(&c, &s, 1).await;
    }

    // Another CA's key cannot issue for this folder; a folder without its
    // CA key says where to look.
    let elsewhere = dir.path().join("other");
    let other_ca = dir.path().join("other-ca");
    init_cluster_in(&elsewhere, Some(&other_ca), &["store-0"]).unwrap();
    assert!(other_ca.join("ca.key").exists() && !elsewhere.join("ca").exists());
    let err = add_nodes(&certs, Some(&other_ca), &["client-2"]).unwrap_err();
    assert!(matches!(err, CertError::CaMismatch { .. }), "{err}");
    let err = add_nodes(&elsewhere, None, &["client-2"]).unwrap_err();
    assert!(err.to_string().contains("the CA key is missing"), "{err}");
    add_nodes(&elsewhere, Some(&other_ca), &["client-2"]).unwrap();
    assert!(
        init_cluster(&certs, &["x"]).is_err(),
        "a CA is never replaced"
    );
}

/// A peer dialed by host name is looked up before every dial: one whose
/// name does not resolve is waited for, saying why, and one that restarts
/// is found again by its name.
#[tokio::test]
async fn a_peer_dialed_by_name_is_looked_up_before_each_dial() {
    let ca = ClusterCa::generate().unwrap();
    let (a, ta) = node(&ca.issue(&name("node-a")).unwrap(), Role::Tool).await;
    let nowhere = DialTarget::new("no-such-peer.invalid", 7400);
    assert!(matches!(nowhere, DialTarget::Host { .. }));
    ta.connect(name("node-z"), nowhere);
    let why = first_dial_error(&ta, "node-z").await;
    assert!(
        why.contains("cannot look up host \"no-such-peer.invalid\""),
        "{why}"
    );

    // `localhost` resolves to the same first address for the listener and
    // the dialer, whichever family that is.
    let here = DialTarget::new("localhost", 0).resolve().await.unwrap();
    let idb = ca.issue(&name("node-b")).unwrap();
    let start_b = |port: u16| {
        let idb = idb.clone();
        async move {
            let bus = Bus::new(name("node-b"), Role::Tool);
            let t = QuicTransport::start(&bus, &idb, SocketAddr::new(here.ip(), port))
                .await
                .unwrap();
            (bus, t)
        }
    };
    let (b, tb) = start_b(0).await;
    let port = tb.local_addr().unwrap().port();
    assert_eq!(
        DialTarget::new("127.0.0.1", port),
        DialTarget::Addr(([127, 0, 0, 1], port).into())
    );
    ta.connect(name("node-b"), DialTarget::new("localhost", port));
    guard(a.wait_for_peer(&name("node-b"))).await;
    ping_pong(&a, &b, 1).await;
    // node-b stops and starts again on the same name and port.
    tb.shutdown().await;
    drop((b, tb));
    let (b, tb) = guard(async {
        loop {
            let bus = Bus::new(name("node-b"), Role::Tool);
            match QuicTransport::start(&bus, &idb, SocketAddr::new(here.ip(), port)).await {
                Ok(t) => return (bus, t),
                // The old socket may linger a moment.
                Err(_) => tokio::time::sleep(Duration::from_millis(50)).await,
            }
        }
    })
    .await;
    guard(b.wait_for_peer(&name("node-a"))).await;
    guard(a.wait_for_peer(&name("node-b"))).await;
    ping_pong(&a, &b, 2).await;
    ta.shutdown().await;
    tb.shutdown().await;
}
