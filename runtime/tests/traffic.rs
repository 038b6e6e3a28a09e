//! What a node's links carried (`Bus::traffic`): the same count at both
//! ends, by the other end's role, on both transports; messages between
//! actors of one node are not counted.

mod common;

use common::*;
use dray_protocol::{encode_envelope, Address, Blob, Envelope, Message, Ping, Role, VoxelLoaded};
use dray_runtime::certs::ClusterCa;
use dray_runtime::quic::QuicTransport;
use dray_runtime::{Bus, InProcNet};
use std::time::Duration;

fn messages() -> Vec<Message> {
    vec![
        Message::Ping(Ping { seq: 7 }),
        Message::VoxelLoaded(VoxelLoaded {
            id: 3,
            data: Blob(vec![5; 100_000]),
        }),
    ]
}

fn encoded(from: &Address, to: &Address) -> u64 {
    messages()
        .into_iter()
        .map(|msg| {
            let env = Envelope {
                msg,
                from: from.clone(),
                to: to.clone(),
            };
            encode_envelope(&env).unwrap().len() as u64
        })
        .sum()
}

/// Sends [`messages`] from `store` to a mailbox on `client` and one to a
/// local actor, and checks both nodes' counts.
async fn check(store: &Bus, client: &Bus) {
    let tx = store.mailbox(name("store"), 4).unwrap();
    let local = store.mailbox(name("local"), 4).unwrap();
    let mut rx = client.mailbox(name("client"), 4).unwrap();
    for msg in messages() {
        tx.send(rx.address(), msg).await.unwrap();
    }
    tx.send(local.address(), Message::Ping(Ping { seq: 1 }))
        .await
        .unwrap();
    for _ in 0..2 {
        tokio::time::timeout(Duration::from_secs(20), next_message(&mut rx))
            .await
            .expect("message not delivered");
    }
    let bytes = encoded(tx.address(), rx.address());
    let sent = store.traffic();
    let got = client.traffic();
    assert_eq!(sent.sent_to(Role::Client), bytes);
    assert_eq!(sent.received(), 0);
    assert_eq!(got.received_from(Role::Store), bytes);
    assert_eq!(got.sent_to(Role::Store), 0);
    let link = got.link_bytes(Role::Client);
    assert_eq!((link.client_store, link.store_uplink), (bytes, bytes));
    assert_eq!((link.client_scheduler, link.client_downlink), (0, bytes));
}

#[tokio::test]
async fn in_process_links_count_what_they_carry() {
    let net = InProcNet::new();
    let store = net.add_node(name("store-0"), Role::Store).unwrap();
    let client = net.add_node(name("client-0"), Role::Client).unwrap();
    check(&store, &client).await;
}

#[tokio::test]
async fn quic_links_count_what_they_carry() {
    let ca = ClusterCa::generate().unwrap();
    let (s_id, c_id) = (
        ca.issue(&name("store-0")).unwrap(),
        ca.issue(&name("client-0")).unwrap(),
    );
    let any = "127.0.0.1:0".parse().unwrap();
    let store = Bus::new(name("store-0"), Role::Store);
    let ts = QuicTransport::start(&store, &s_id, any).await.unwrap();
    let client = Bus::new(name("client-0"), Role::Client);
    let tc = QuicTransport::start(&client, &c_id, any).await.unwrap();
    tc.connect(name("store-0"), ts.local_addr().unwrap());
    let up = async {
        client.wait_for_peer(&name("store-0")).await;
        store.wait_for_peer(&name("client-0")).await;
    };
    tokio::time::timeout(Duration::from_secs(20), up)
        .await
        .expect("no connection");
    check(&store, &client).await;
}
