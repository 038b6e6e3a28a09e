//! The in-process transport: every kind, routing errors, backpressure,
//! peer events, and shaping on tokio's paused clock.

mod common;

use common::*;
use dray_protocol::examples::one_of_each;
use dray_protocol::{encode_envelope, Address, Blob, Envelope, Message, Ping, Role, TilePixels};
use dray_runtime::{Bus, Delivery, InProcNet, LinkShape, SendError};
use std::time::Duration;
use tokio::time::Instant;

/// Two tools, which may send each other every kind.
fn pair() -> (InProcNet, Bus, Bus) {
    let net = InProcNet::new();
    let a = net.add_node(name("node-a"), Role::Tool).unwrap();
    let b = net.add_node(name("node-b"), Role::Tool).unwrap();
    (net, a, b)
}

#[tokio::test(start_paused = true)]
async fn every_kind_crosses_the_inproc_transport() {
    let (_net, a, b) = pair();
    exchange_every_kind(&a, &b).await;
}

#[tokio::test(start_paused = true)]
async fn every_kind_crosses_a_shaped_inproc_link() {
    let (net, a, b) = pair();
    let shape = LinkShape {
        latency: Duration::from_millis(5),
        jitter: Duration::from_millis(3),
        bandwidth_bps: Some(1_000_000_000),
        loss: 0.2,
    };
    net.set_shape(a.node(), b.node(), shape).unwrap();
    exchange_every_kind(&a, &b).await;
}

#[tokio::test(start_paused = true)]
async fn same_node_delivery_and_routing_errors() {
    let (net, a, _b) = pair();
    let mut m1 = a.mailbox(name("one"), 4).unwrap();
    let m2 = a.mailbox(name("two"), 4).unwrap();
    assert!(a.mailbox(name("two"), 4).is_err(), "names are unique");
    m2.send(m1.address(), Message::Ping(Ping { seq: 3 }))
        .await
        .unwrap();
    assert_eq!(
        next_message(&mut m1).await,
        (m2.address().clone(), Message::Ping(Ping { seq: 3 }))
    );
    let nobody = Address::new(name("node-b"), name("nobody"));
    assert!(matches!(
        m2.send(&nobody, Message::Ping(Ping { seq: 1 })).await,
        Err(SendError::NoSuchActor(_))
    ));
    let nowhere = Address::new(name("node-z"), name("x"));
    assert!(matches!(
        m2.send(&nowhere, Message::Ping(Ping { seq: 1 })).await,
        Err(SendError::PeerUnavailable(_))
    ));
    // A dropped mailbox frees its name and stops receiving.
    let addr = m1.address().clone();
    drop(m1);
    assert!(matches!(
        m2.send(&addr, Message::Ping(Ping { seq: 1 })).await,
        Err(SendError::NoSuchActor(_))
    ));
    assert!(a.mailbox(name("one"), 4).is_ok());
    drop(net);
}

#[tokio::test(start_paused = true)]
async fn invalid_messages_are_refused_to_the_sender() {
    let (_net, a, b) = pair();
    let m = a.mailbox(name("one"), 4).unwrap();
    let _r = b.mailbox(name("two"), 4).unwrap();
    let mut msgs = one_of_each(10);
    let Message::TileDone(mut t) = msgs.remove(2) else {
        unreachable!()
    };
    t.pixels = TilePixels::Rgba(Blob(vec![0; 3]));
    let to = Address::new(name("node-b"), name("two"));
    assert!(matches!(
        m.send(&to, Message::TileDone(t)).await,
        Err(SendError::Protocol(_))
    ));
}

#[tokio::test(start_paused = true)]
async fn a_full_mailbox_makes_senders_wait() {
    let (_net, a, b) = pair();
    let mut slow = b.mailbox(name("slow"), 1).unwrap();
    let fast = a.mailbox(name("fast"), 1).unwrap();
    let to = slow.address().clone();
    fast.send(&to, Message::Ping(Ping { seq: 1 }))
        .await
        .unwrap();
    // The second send cannot complete until the first is taken out.
    let second = tokio::time::timeout(
        Duration::from_secs(1),
        fast.send(&to, Message::Ping(Ping { seq: 2 })),
    )
    .await;
    assert!(second.is_err(), "send waited for room");
    assert_eq!(
        next_message(&mut slow).await.1,
        Message::Ping(Ping { seq: 1 })
    );
    fast.send(&to, Message::Ping(Ping { seq: 2 }))
        .await
        .unwrap();
    assert_eq!(
        next_message(&mut slow).await.1,
        Message::Ping(Ping { seq: 2 })
    );
}

#[tokio::test(start_paused = true)]
async fn peers_coming_and_going_are_typed_events() {
    let net = InProcNet::new();
    let a = net.add_node(name("node-a"), Role::Scheduler).unwrap();
    let mut ma = a.mailbox(name("sched"), 8).unwrap();
    let b = net.add_node(name("node-b"), Role::Client).unwrap();
    assert_eq!(
        ma.recv().await,
        Some(Delivery::PeerUp {
            node: name("node-b"),
            role: Role::Client
        })
    );
    assert!(net.add_node(name("node-b"), Role::Client).is_err());
    net.disconnect(a.node(), b.node());
    assert!(matches!(
        ma.recv().await,
        Some(Delivery::PeerDown { node, .. }) if node == name("node-b")
    ));
    assert!(matches!(
        ma.send(
            &Address::new(name("node-b"), name("x")),
            Message::Ping(Ping { seq: 0 })
        )
        .await,
        Err(SendError::PeerUnavailable(_))
    ));
    net.reconnect(a.node(), b.node());
    assert!(matches!(ma.recv().await, Some(Delivery::PeerUp { .. })));
    assert!(a.is_connected(b.node()));
    assert_eq!(a.peers(), vec![(name("node-b"), Role::Client)]);
}

/// The wire size of `msg` from `from` to `to`: what shaping charges.
fn wire_size(msg: &Message, from: &Address, to: &Address) -> usize {
    encode_envelope(&Envelope {
        msg: msg.clone(),
        from: from.clone(),
        to: to.clone(),
    })
    .unwrap()
    .len()
}

#[tokio::test(start_paused = true)]
async fn shaped_message_arrives_after_latency_plus_size_over_bandwidth() {
    let (net, a, b) = pair();
    let tx = a.mailbox(name("tx"), 4).unwrap();
    let mut rx = b.mailbox(name("rx"), 4).unwrap();
    let voxel = one_of_each(100_000).swap_remove(4);
    let size = wire_size(&voxel, tx.address(), rx.address());
    // A bandwidth at which this message takes exactly 8 ms to transmit.
    let bps = size as u64 * 8 * 1000 / 8;
    let shape = LinkShape {
        latency: Duration::from_millis(20),
        bandwidth_bps: Some(bps),
        ..LinkShape::none()
    };
    assert_eq!(shape.transmission_time(size), Duration::from_millis(8));
    net.set_shape(a.node(), b.node(), shape).unwrap();

    let t0 = Instant::now();
    tx.send(rx.address(), voxel.clone()).await.unwrap();
    tx.send(rx.address(), voxel.clone()).await.unwrap();
    let (_, got) = next_message(&mut rx).await;
    assert_eq!(got, voxel);
    assert_eq!(t0.elapsed(), Duration::from_millis(28));
    // The second one queued behind the first on the link.
    next_message(&mut rx).await;
    assert_eq!(t0.elapsed(), Duration::from_millis(36));

    // The other direction is shaped too, and a small message's time is its
    // latency plus its (sub-millisecond) transmission, to the timer's
    // millisecond resolution.
    let t1 = Instant::now();
    rx.send(tx.address(), Message::Ping(Ping { seq: 9 }))
        .await
        .unwrap();
    let mut tx = tx;
    next_message(&mut tx).await;
    let small = wire_size(&Message::Ping(Ping { seq: 9 }), rx.address(), tx.address());
    let exact = Duration::from_millis(20) + shape.transmission_time(small);
    let took = t1.elapsed();
    assert!(
        took >= exact && took < exact + Duration::from_millis(1),
        "{took:?}"
    );
}

#[tokio::test(start_paused = true)]
async fn jitter_never_reorders_messages() {
    let (net, a, b) = pair();
    net.set_shape(
        a.node(),
        b.node(),
        LinkShape {
            latency: Duration::from_millis(10),
            jitter: Duration::from_millis(30),
            ..LinkShape::none()
        },
    )
    .unwrap();
    let tx = a.mailbox(name("tx"), 4).unwrap();
    let mut rx = b.mailbox(name("rx"), 256).unwrap();
    for seq in 0..200 {
        tx.send(rx.address(), Message::Ping(Ping { seq }))
            .await
            .unwrap();
    }
    for seq in 0..200 {
        assert_eq!(next_message(&mut rx).await.1, Message::Ping(Ping { seq }));
    }
}

#[tokio::test(start_paused = true)]
async fn a_big_voxel_does_not_hold_back_a_control_message() {
    let (net, a, b) = pair();
    net.set_shape(
        a.node(),
        b.node(),
        LinkShape {
            latency: Duration::from_millis(1),
            bandwidth_bps: Some(10_000_000),
            ..LinkShape::none()
        },
    )
    .unwrap();
    let tx = a.mailbox(name("store"), 4).unwrap();
    let mut rx = b.mailbox(name("loader"), 4).unwrap();
    let voxel = one_of_each(1 << 20).swap_remove(4);
    tx.send(rx.address(), voxel.clone()).await.unwrap();
    tx.send(rx.address(), Message::Ping(Ping { seq: 1 }))
        .await
        .unwrap();
    assert_eq!(
        next_message(&mut rx).await.1,
        Message::Ping(Ping { seq: 1 })
    );
    assert_eq!(next_message(&mut rx).await.1, voxel);
}

#[tokio::test(start_paused = true)]
async fn a_message_the_senders_role_may_not_send_is_dropped_and_the_link_goes_on() {
    use dray_protocol::{FetchVoxel, Shutdown};
    let net = InProcNet::new();
    let client = net.add_node(name("client-0"), Role::Client).unwrap();
    let store = net.add_node(name("store-0"), Role::Store).unwrap();
    let sched = net.add_node(name("scheduler"), Role::Scheduler).unwrap();
    let display = net.add_node(name("display"), Role::Display).unwrap();
    let from_client = client.mailbox(name("client"), 4).unwrap();
    let from_display = display.mailbox(name("control"), 4).unwrap();
    let mut at_store = store.mailbox(name("store"), 4).unwrap();
    let mut at_sched = sched.mailbox(name("scheduler"), 4).unwrap();
    let stop = || {
        Message::Shutdown(Shutdown {
            reason: "a client says so".into(),
        })
    };
    // A client's Shutdown reaches neither the store nor the scheduler; what
    // it may send still does, in order behind the refused message.
    from_client.send(at_store.address(), stop()).await.unwrap();
    from_client.send(at_sched.address(), stop()).await.unwrap();
    let fetch = Message::FetchVoxel(FetchVoxel { id: 7 });
    from_client
        .send(at_store.address(), fetch.clone())
        .await
        .unwrap();
    assert_eq!(next_message(&mut at_store).await.1, fetch);
    from_client
        .send(at_sched.address(), Message::Ping(Ping { seq: 1 }))
        .await
        .unwrap();
    assert_eq!(
        next_message(&mut at_sched).await.1,
        Message::Ping(Ping { seq: 1 })
    );
    assert!(client.is_connected(store.node()) && store.is_connected(client.node()));
    // The display's node may end the run.
    from_display.send(at_store.address(), stop()).await.unwrap();
    assert_eq!(next_message(&mut at_store).await.1, stop());
}
