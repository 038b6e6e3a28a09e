//! The sender rules (`MessageKind::may_send`): what each role may send, and
//! docs/design.md's message table, which must show the same rule.

use dray_protocol::{MessageKind, Name, Role};

#[test]
fn roles_follow_from_node_names() {
    let role = |s: &str| Role::of_node(&Name::new(s).unwrap());
    assert_eq!(role("scheduler"), Role::Scheduler);
    assert_eq!(role("display"), Role::Display);
    assert_eq!(role("store-0"), Role::Store);
    assert_eq!(role("store-12"), Role::Store);
    assert_eq!(role("client-3"), Role::Client);
    for other in [
        "client",
        "client-",
        "client-x",
        "client-1a",
        "stores-1",
        "node-a",
        "sched",
    ] {
        assert_eq!(role(other), Role::Tool, "{other}");
    }
}

#[test]
fn each_role_sends_only_what_its_actors_send() {
    use MessageKind as K;
    use Role::*;
    // A client may not stop anyone, nor speak for the scheduler or a store.
    for to in Role::ALL {
        assert!(!K::Shutdown.may_send(Client, to), "client → {to}");
        assert!(!K::Shutdown.may_send(Store, to), "store → {to}");
        assert!(!K::Shutdown.may_send(Scheduler, to), "scheduler → {to}");
        assert!(!K::Shutdown.may_send(Tool, to) || to == Tool, "tool → {to}");
        assert!(!K::AssignTile.may_send(Client, to));
        assert!(!K::VoxelLoaded.may_send(Client, to));
        assert!(!K::FrameDone.may_send(Client, to));
    }
    for to in [Scheduler, Store, Client] {
        assert!(K::Shutdown.may_send(Display, to), "display → {to}");
    }
    assert!(!K::Shutdown.may_send(Display, Display));
    assert!(K::RequestWork.may_send(Client, Scheduler));
    assert!(!K::RequestWork.may_send(Display, Scheduler));
    assert!(K::FetchVoxel.may_send(Client, Store));
    assert!(!K::FetchVoxel.may_send(Scheduler, Store));
    assert!(K::TileReport.may_send(Display, Scheduler));
    assert!(K::TileReport.may_send(Client, Scheduler));
    assert!(!K::TileReport.may_send(Store, Scheduler));
    assert!(!K::FrameStart.may_send(Display, Scheduler));
    // Liveness probes go anywhere; tools talk to each other freely, and
    // to the cluster only with probes.
    for from in Role::ALL {
        for to in Role::ALL {
            assert!(K::Ping.may_send(from, to) && K::Pong.may_send(from, to));
            assert!(!K::Handshake.may_send(from, to));
        }
    }
    for kind in MessageKind::ALL {
        assert!(kind.may_send(Tool, Tool), "{kind:?}");
        for r in Role::CLUSTER {
            let probe = matches!(kind, K::Ping | K::Pong);
            assert_eq!(kind.may_send(Tool, r), probe, "{kind:?} tool → {r}");
            assert_eq!(kind.may_send(r, Tool), probe, "{kind:?} {r} → tool");
        }
    }
}

#[test]
fn every_kind_has_a_sender_and_a_receiver_in_the_cluster() {
    for kind in MessageKind::ALL {
        let used = Role::CLUSTER
            .iter()
            .any(|&f| Role::CLUSTER.iter().any(|&t| kind.may_send(f, t)));
        assert!(used, "{kind:?} has no sender in the cluster");
    }
}

/// The second column of each row of docs/design.md's message table.
fn design_table() -> Vec<(String, String)> {
    let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../docs/design.md");
    let text = std::fs::read_to_string(path).unwrap();
    text.lines()
        .filter_map(|l| {
            let cells: Vec<&str> = l.split('|').map(str::trim).collect();
            // | `Kind` | rule | actors | carries |
            let kind = cells.get(1)?.strip_prefix('`')?.strip_suffix('`')?;
            let rule = cells.get(2)?;
            MessageKind::ALL
                .iter()
                .any(|k| format!("{k:?}") == kind)
                .then(|| (kind.to_string(), rule.to_string()))
        })
        .collect()
}

#[test]
fn the_design_documents_the_rule_of_every_kind() {
    let table = design_table();
    for kind in MessageKind::ALL {
        let name = format!("{kind:?}");
        let rows: Vec<_> = table.iter().filter(|(k, _)| *k == name).collect();
        assert_eq!(rows.len(), 1, "docs/design.md: {name} needs one table row");
        assert_eq!(
            rows[0].1,
            kind.rule_text(),
            "docs/design.md: the row of {name} differs from MessageKind::may_send"
        );
    }
    assert_eq!(table.len(), MessageKind::ALL.len());
}
