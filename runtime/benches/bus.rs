//! Figures of the message bus: `cargo bench -p dray-runtime --bench bus`.
//!
//! Prints, for the in-process transport and for QUIC on loopback:
//! round-trip latency of a small message, throughput of 256 KB payloads,
//! shaped throughput against the cap (100 Mbit/s and 1 Gbit/s; QUIC through
//! the UDP relay), and the rate of small control messages from 64 concurrent
//! senders to one actor. `DRAY_BENCH_QUICK=1` runs a shorter version.

use dray_protocol::{Blob, Message, Name, Ping, RequestWork, Role, VoxelLoaded};
use dray_runtime::certs::ClusterCa;
use dray_runtime::quic::QuicTransport;
use dray_runtime::relay::UdpRelay;
use dray_runtime::{Bus, Delivery, InProcNet, LinkShape, Mailbox};
use std::net::SocketAddr;
use std::sync::Arc;
use std::time::{Duration, Instant};

const PAYLOAD: usize = 256 << 10;

fn name(s: &str) -> Name {
    Name::new(s).expect("bench names are valid")
}

async fn next(mb: &mut Mailbox) -> Message {
    loop {
        match mb.recv().await.expect("mailbox open") {
            Delivery::Message { msg, .. } => return msg,
            _ => continue,
        }
    }
}

struct Pair {
    a: Bus,
    b: Bus,
    _keep: Vec<Arc<QuicTransport>>,
    _relay: Option<UdpRelay>,
}

fn inproc(shape: Option<LinkShape>) -> Pair {
    let net = InProcNet::new();
    let a = net.add_node(name("node-a"), Role::Tool).expect("node");
    let b = net.add_node(name("node-b"), Role::Tool).expect("node");
    if let Some(s) = shape {
        net.set_shape(a.node(), b.node(), s).expect("shape");
    }
    Pair {
        a,
        b,
        _keep: vec![],
        _relay: None,
    }
}

async fn quic(shape: Option<LinkShape>) -> Pair {
    let ca = ClusterCa::generate().expect("ca");
    let lo: SocketAddr = "127.0.0.1:0".parse().expect("addr");
    let a = Bus::new(name("node-a"), Role::Tool);
    let b = Bus::new(name("node-b"), Role::Tool);
    let ta = QuicTransport::start(&a, &ca.issue(a.node()).expect("cert"), lo)
        .await
        .expect("quic a");
    let tb = QuicTransport::start(&b, &ca.issue(b.node()).expect("cert"), lo)
        .await
        .expect("quic b");
    let b_addr = tb.local_addr().expect("addr");
    let relay = match shape {
        Some(s) => Some(UdpRelay::start(lo, b_addr, s, s).await.expect("relay")),
        None => None,
    };
    ta.connect(
        name("node-b"),
        relay.as_ref().map(|r| r.local_addr()).unwrap_or(b_addr),
    );
    a.wait_for_peer(b.node()).await;
    b.wait_for_peer(a.node()).await;
    Pair {
        a,
        b,
        _keep: vec![ta, tb],
        _relay: relay,
    }
}

/// Median and 99th percentile round trip of a ping, microseconds.
async fn rtt(p: &Pair, n: usize) -> (f64, f64) {
    let mut ma = p.a.mailbox(name("pinger"), 16).expect("mb");
    let mut mb = p.b.mailbox(name("ponger"), 16).expect("mb");
    let to = mb.address().clone();
    let back = ma.address().clone();
    let echo = tokio::spawn(async move {
        for _ in 0..n + 100 {
            if let Message::Ping(x) = next(&mut mb).await {
                mb.send(&back, Message::Pong(x)).await.expect("pong");
            }
        }
    });
    let mut times = Vec::with_capacity(n);
    for seq in 0..(n + 100) as u64 {
        let t0 = Instant::now();
        ma.send(&to, Message::Ping(Ping { seq }))
            .await
            .expect("ping");
        next(&mut ma).await;
        if seq >= 100 {
            times.push(t0.elapsed().as_secs_f64() * 1e6);
        }
    }
    let _ = echo.await;
    times.sort_by(|a, b| a.total_cmp(b));
    (times[n / 2], times[n * 99 / 100])
}

/// Payload goodput of `count` 256 KB voxels from a to b, Mbit/s.
async fn throughput(p: &Pair, count: usize, tag: &str) -> f64 {
    let ma = p.a.mailbox(name(&format!("tx-{tag}")), 16).expect("mb");
    let mut mb = p.b.mailbox(name(&format!("rx-{tag}")), 64).expect("mb");
    let to = mb.address().clone();
    let data = Blob(vec![0x5a; PAYLOAD]);
    let t0 = Instant::now();
    let sender = tokio::spawn(async move {
        for id in 0..count as u32 {
            ma.send(
                &to,
                Message::VoxelLoaded(VoxelLoaded {
                    id,
                    data: data.clone(),
                }),
            )
            .await
            .expect("send");
        }
        ma
    });
    for _ in 0..count {
        next(&mut mb).await;
    }
    let secs = t0.elapsed().as_secs_f64();
    let _ = sender.await;
    (count * PAYLOAD * 8) as f64 / secs / 1e6
}

/// Small messages per second from 64 concurrent senders to one actor.
async fn fan_in(p: &Pair, per_sender: usize, tag: &str) -> f64 {
    let mut rx = p.b.mailbox(name(&format!("sink-{tag}")), 4096).expect("mb");
    let to = rx.address().clone();
    let mut senders = Vec::new();
    let t0 = Instant::now();
    for i in 0..64 {
        let mb = p.a.mailbox(name(&format!("s{i}-{tag}")), 4).expect("mb");
        let to = to.clone();
        senders.push(tokio::spawn(async move {
            for _ in 0..per_sender {
                mb.send(
                    &to,
                    Message::RequestWork(RequestWork {
                        slots: 1,
                        holds_model: false,
                    }),
                )
                .await
                .expect("send");
            }
        }));
    }
    for _ in 0..64 * per_sender {
        next(&mut rx).await;
    }
    let rate = (64 * per_sender) as f64 / t0.elapsed().as_secs_f64();
    for s in senders {
        let _ = s.await;
    }
    rate
}

fn capped(bps: u64) -> LinkShape {
    LinkShape {
        bandwidth_bps: Some(bps),
        ..LinkShape::none()
    }
}

fn main() {
    dray_runtime::logging::init("warn");
    let quick = std::env::var_os("DRAY_BENCH_QUICK").is_some();
    let (pings, voxels, per_sender) = if quick {
        (200, 40, 200)
    } else {
        (2000, 400, 2000)
    };
    let rt = tokio::runtime::Builder::new_multi_thread()
        .enable_all()
        .build()
        .expect("runtime");
    rt.block_on(async {
        println!(
            "dray bus figures ({} CPUs, {} build)",
            std::thread::available_parallelism().map_or(0, |n| n.get()),
            if cfg!(debug_assertions) {
                "debug"
            } else {
                "release"
            }
        );
        println!(
            "{:<44} {:>14} {:>14}",
            "figure", "in-process", "QUIC loopback"
        );

        let ip = inproc(None);
        let q = quic(None).await;
        let (ip50, ip99) = rtt(&ip, pings).await;
        let (q50, q99) = rtt(&q, pings).await;
        println!(
            "{:<44} {:>11.1} us {:>11.1} us",
            "small message round trip, median", ip50, q50
        );
        println!(
            "{:<44} {:>11.1} us {:>11.1} us",
            "small message round trip, p99", ip99, q99
        );

        let ipt = throughput(&ip, voxels, "free").await;
        let qt = throughput(&q, voxels, "free").await;
        println!(
            "{:<44} {:>9.0} Mb/s {:>9.0} Mb/s",
            "256 KB payloads, unshaped", ipt, qt
        );

        let ipr = fan_in(&ip, per_sender, "x").await;
        let qr = fan_in(&q, per_sender, "x").await;
        println!(
            "{:<44} {:>10.0} /s {:>10.0} /s",
            "small messages, 64 concurrent senders", ipr, qr
        );

        for (cap, label) in [(100_000_000u64, "100 Mbit/s"), (1_000_000_000, "1 Gbit/s")] {
            // About 1.5 s of traffic at the cap (less when quick).
            let secs = if quick { 0.5 } else { 1.5 };
            let n = ((cap as f64 * secs) / (PAYLOAD * 8) as f64).ceil() as usize;
            let ips = inproc(Some(capped(cap)));
            let qs = quic(Some(capped(cap))).await;
            // Warm up the QUIC congestion window, then measure.
            throughput(&qs, n / 4 + 1, "warm").await;
            let a = throughput(&ips, n, "cap").await;
            let b = throughput(&qs, n, "cap").await;
            let cap_m = cap as f64 / 1e6;
            if let Some(r) = &qs._relay {
                let st = r.stats();
                eprintln!(
                    "  relay at {label}: {} datagrams forwarded, {} dropped at the full queue",
                    st.forwarded, st.overflowed
                );
            }
            println!(
                "{:<44} {:>6.0} ({:>3.0}%) {:>6.0} ({:>3.0}%)",
                format!("256 KB payloads capped at {label}, Mb/s"),
                a,
                100.0 * a / cap_m,
                b,
                100.0 * b / cap_m
            );
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    });
}
