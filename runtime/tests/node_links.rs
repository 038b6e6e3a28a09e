//! Node links on the in-process transport, on tokio's paused clock: a
//! store's uplink is one bottleneck for every client it serves, a client's
//! downlink one for every store it fetches from, unlike per-pair links.

mod common;

use common::*;
use dray_protocol::{encode_envelope, Address, Blob, Envelope, FetchVoxel, Message, VoxelLoaded};
use dray_runtime::{Bus, InProcNet, LinkShape, NodeLink, Role};
use std::time::Duration;
use tokio::time::Instant;

/// A voxel's size, as the paper's plant gives them.
const VOXEL: usize = 24 << 10;
/// Fetches each client keeps in flight.
const WINDOW: u32 = 8;
/// Voxels each client pulls.
const PER_CLIENT: u32 = 60;

const MBIT_100: LinkShape = LinkShape {
    latency: Duration::ZERO,
    jitter: Duration::ZERO,
    bandwidth_bps: Some(100_000_000),
    loss: 0.0,
};

fn voxel(id: u32) -> Message {
    Message::VoxelLoaded(VoxelLoaded {
        id,
        data: Blob(vec![7; VOXEL]),
    })
}

/// What shaping charges for a voxel from `from` to `to`.
fn wire_size(from: &Address, to: &Address) -> u64 {
    let env = Envelope {
        msg: voxel(0),
        from: from.clone(),
        to: to.clone(),
    };
    encode_envelope(&env).unwrap().len() as u64
}

/// A network of `stores` stores and `clients` clients; every pair has a
/// 1 ms link of its own (unlimited bandwidth).
fn network(stores: usize, clients: usize) -> (InProcNet, Vec<Bus>, Vec<Bus>) {
    let net = InProcNet::new();
    let s: Vec<Bus> = (0..stores)
        .map(|i| {
            net.add_node(name(&format!("store-{i}")), Role::Store)
                .unwrap()
        })
        .collect();
    let c: Vec<Bus> = (0..clients)
        .map(|i| {
            net.add_node(name(&format!("client-{i}")), Role::Client)
                .unwrap()
        })
        .collect();
    let pair = LinkShape {
        latency: Duration::from_millis(1),
        ..LinkShape::none()
    };
    for a in &c {
        for b in &s {
            net.set_shape(a.node(), b.node(), pair).unwrap();
        }
    }
    (net, s, c)
}

/// Every client pulls [`PER_CLIENT`] voxels, [`WINDOW`] at a time, from the
/// stores in turn; returns the aggregate rate of the voxels' wire bytes in
/// Mbit/s over the virtual time it took.
async fn pull(stores: &[Bus], clients: &[Bus]) -> f64 {
    let store_addrs: Vec<Address> = stores.iter().map(|b| b.address(name("store"))).collect();
    for bus in stores {
        let mut mb = bus.mailbox(name("store"), 4096).unwrap();
        tokio::spawn(async move {
            while let Some((from, msg)) = mb.recv_message().await {
                if let Message::FetchVoxel(FetchVoxel { id }) = msg {
                    mb.send(&from, voxel(id)).await.unwrap();
                }
            }
        });
    }
    let t0 = Instant::now();
    let mut pulls = Vec::new();
    for bus in clients {
        let mut mb = bus.mailbox(name("loader"), 4096).unwrap();
        let stores = store_addrs.clone();
        pulls.push(tokio::spawn(async move {
            let mut bytes = 0;
            let fetch = |id: u32| Message::FetchVoxel(FetchVoxel { id });
            for id in 0..WINDOW {
                mb.send(&stores[id as usize % stores.len()], fetch(id))
                    .await
                    .unwrap();
            }
            for got in 0..PER_CLIENT {
                let (from, msg) = next_message(&mut mb).await;
                assert!(matches!(msg, Message::VoxelLoaded(_)), "{msg:?}");
                bytes += wire_size(&from, mb.address());
                let id = got + WINDOW;
                if id < PER_CLIENT {
                    mb.send(&stores[id as usize % stores.len()], fetch(id))
                        .await
                        .unwrap();
                }
            }
            bytes
        }));
    }
    let mut bytes = 0;
    for p in pulls {
        bytes += p.await.unwrap();
    }
    bytes as f64 * 8.0 / t0.elapsed().as_secs_f64() / 1e6
}

/// `rate` is within [80 %, 101 %] of `cap` Mbit/s.
fn assert_near_cap(rate: f64, cap: f64) {
    assert!(rate <= cap * 1.01, "{rate:.1} Mbit/s exceeds the {cap} cap");
    assert!(
        rate >= cap * 0.8,
        "{rate:.1} Mbit/s: the {cap} Mbit/s link is not kept busy"
    );
}

#[tokio::test(start_paused = true)]
async fn eight_clients_share_one_store_uplink() {
    let (net, stores, clients) = network(1, 8);
    net.set_node_link(stores[0].node(), NodeLink::Uplink, MBIT_100)
        .unwrap();
    assert_near_cap(pull(&stores, &clients).await, 100.0);
}

#[tokio::test(start_paused = true)]
async fn two_store_uplinks_deliver_twice_as_much() {
    let (net, stores, clients) = network(2, 8);
    for s in &stores {
        net.set_node_link(s.node(), NodeLink::Uplink, MBIT_100)
            .unwrap();
    }
    assert_near_cap(pull(&stores, &clients).await, 200.0);
}

#[tokio::test(start_paused = true)]
async fn per_pair_links_are_not_shared() {
    // The contrast: eight 100 Mbit/s pair links carry far more than one.
    let (net, stores, clients) = network(1, 8);
    for c in &clients {
        net.set_shape(c.node(), stores[0].node(), MBIT_100).unwrap();
    }
    let rate = pull(&stores, &clients).await;
    assert!(rate > 600.0, "{rate:.1} Mbit/s");
}

#[tokio::test(start_paused = true)]
async fn one_client_downlink_is_shared_by_every_store() {
    let (net, stores, clients) = network(4, 1);
    net.set_node_link(clients[0].node(), NodeLink::Downlink, MBIT_100)
        .unwrap();
    assert_near_cap(pull(&stores, &clients).await, 100.0);
}

#[tokio::test(start_paused = true)]
async fn an_uplink_adds_its_latency_and_removing_it_restores_the_link() {
    let (net, stores, clients) = network(1, 1);
    let tx = stores[0].mailbox(name("store"), 4).unwrap();
    let mut rx = clients[0].mailbox(name("loader"), 4).unwrap();
    let uplink = LinkShape {
        latency: Duration::from_millis(5),
        ..LinkShape::none()
    };
    net.set_node_link(stores[0].node(), NodeLink::Uplink, uplink)
        .unwrap();
    let t0 = Instant::now();
    tx.send(rx.address(), voxel(1)).await.unwrap();
    next_message(&mut rx).await;
    // The uplink's 5 ms, then the pair's own 1 ms.
    assert_eq!(t0.elapsed(), Duration::from_millis(6));

    net.set_node_link(stores[0].node(), NodeLink::Uplink, LinkShape::none())
        .unwrap();
    let t1 = Instant::now();
    tx.send(rx.address(), voxel(2)).await.unwrap();
    next_message(&mut rx).await;
    assert_eq!(t1.elapsed(), Duration::from_millis(1));
    let bad = LinkShape {
        loss: 1.0,
        ..LinkShape::none()
    };
    assert!(net
        .set_node_link(stores[0].node(), NodeLink::Uplink, bad)
        .is_err());
}
