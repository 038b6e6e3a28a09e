//! The test body every transport must pass.

#![allow(dead_code)]

use dray_protocol::examples::one_of_each;
use dray_protocol::{Message, MessageKind, Name};
use dray_runtime::{Bus, Delivery, Mailbox};

pub fn name(s: &str) -> Name {
    Name::new(s).unwrap()
}

/// Receives the next message, skipping peer events.
pub async fn next_message(mb: &mut Mailbox) -> (dray_protocol::Address, Message) {
    loop {
        match mb.recv().await.expect("mailbox open") {
            Delivery::Message { from, msg } => return (from, msg),
            _ => continue,
        }
    }
}

/// Node `a` sends one message of every kind (with a 256 KB voxel) to an
/// actor on node `b`, which checks each and echoes it back; `a` checks the
/// echoes. Bulk and control messages may overtake each other, so both sides
/// match by kind; within the control stream order is kept.
pub async fn exchange_every_kind(a: &Bus, b: &Bus) {
    let mut ma = a.mailbox(name("alpha"), 64).unwrap();
    let mut mb = b.mailbox(name("beta"), 64).unwrap();
    let sent = one_of_each(256 << 10);
    let to_b = mb.address().clone();
    let to_a = ma.address().clone();

    let echo = tokio::spawn(async move {
        let mut got = Vec::new();
        for _ in 0..MessageKind::ALL.len() {
            let (from, msg) = next_message(&mut mb).await;
            assert_eq!(from, to_a);
            mb.send(&from, msg.clone()).await.unwrap();
            got.push(msg);
        }
        got
    });
    for msg in &sent {
        ma.send(&to_b, msg.clone()).await.unwrap();
    }
    let mut echoed = Vec::new();
    for _ in 0..MessageKind::ALL.len() {
        let (from, msg) = next_message(&mut ma).await;
        assert_eq!(from, to_b);
        echoed.push(msg);
    }
    let got = echo.await.unwrap();
    for received in [got, echoed] {
        let control: Vec<_> = received.iter().filter(|m| !m.kind().is_bulk()).collect();
        let sent_control: Vec<_> = sent.iter().filter(|m| !m.kind().is_bulk()).collect();
        assert_eq!(control, sent_control, "control messages arrive in order");
        for m in &sent {
            assert!(received.contains(m), "{:?} arrived unchanged", m.kind());
        }
    }
}
