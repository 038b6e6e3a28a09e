//! The in-process transport: many nodes in one process, linked by channels,
//! with the same encoding, limits and (optionally) shaping as the wire.

use crate::bus::{Bus, BusError, Inner, PeerLink, SendError};
use crate::shaping::{shared, Lane, LinkShape, Path, Shaper, SharedShaper};
use dray_protocol::{decode_envelope, encode_envelope, Envelope, Name, Role};
use std::collections::{BTreeMap, HashMap};
use std::hash::{Hash, Hasher};
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use std::time::Duration;
use tokio::sync::mpsc;
use tokio::time::Instant;
use tracing::{trace, warn, Instrument};

/// Messages waiting in one shaped direction before senders wait.
const PIPE_CAPACITY: usize = 1024;

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}

struct Pipe {
    path: Path,
    /// One ordered queue per lane (control, bulk).
    tx: [mpsc::Sender<(Instant, Envelope)>; 2],
}

/// One direction between two in-process nodes.
pub(crate) struct InProcLink {
    /// The sending node's role: in one process, the role it was added with
    /// is its authenticated identity, checked against the sender rules.
    src_role: Role,
    dst_name: Name,
    dst: Weak<Inner>,
    pipe: Mutex<Option<Arc<Pipe>>>,
}

impl InProcLink {
    /// Sends `env`; returns the bytes of its encoding.
    pub(crate) async fn send(&self, env: Envelope) -> Result<usize, SendError> {
        let kind = env.msg.kind();
        // Encode exactly as the wire would: same validation, same limits, and
        // the size that shaping charges. The receiver decodes these bytes.
        let body = encode_envelope(&env)?;
        let dst = self
            .dst
            .upgrade()
            .ok_or_else(|| SendError::PeerUnavailable(self.dst_name.clone()))?;
        dst.count_received(self.src_role, body.len());
        let pipe = lock(&self.pipe).clone();
        match pipe {
            None => {
                let env = decode_envelope(&body)?;
                dst.deliver_remote(self.src_role, env)
                    .await
                    .map(|()| body.len())
            }
            Some(pipe) => {
                let lane = if kind.own_stream(body.len()) {
                    Lane::Bulk
                } else {
                    Lane::Control
                };
                let at = pipe.path.reliable(body.len(), lane);
                trace!(kind = kind.name(), bytes = body.len(), "shaped send");
                let env = decode_envelope(&body)?;
                drop(dst);
                pipe.tx[lane as usize]
                    .send((at, env))
                    .await
                    .map(|()| body.len())
                    .map_err(|_| SendError::PeerUnavailable(self.dst_name.clone()))
            }
        }
    }

    /// Starts the task that delivers one lane's messages at their times.
    fn spawn_lane(&self, lane: &'static str) -> mpsc::Sender<(Instant, Envelope)> {
        let (tx, mut rx) = mpsc::channel::<(Instant, Envelope)>(PIPE_CAPACITY);
        let dst = self.dst.clone();
        let src_role = self.src_role;
        let span = tracing::debug_span!("inproc_link", to = %self.dst_name, lane);
        tokio::spawn(
            async move {
                while let Some((at, env)) = rx.recv().await {
                    tokio::time::sleep_until(at).await;
                    let Some(dst) = dst.upgrade() else { break };
                    if let Err(e) = dst.deliver_remote(src_role, env).await {
                        warn!(error = %e, "shaped message not delivered");
                    }
                }
            }
            .instrument(span),
        );
        tx
    }

    fn set_path(&self, path: Path) {
        let mut pipe = lock(&self.pipe);
        if path.is_unshaped() {
            *pipe = None;
            return;
        }
        let tx = [self.spawn_lane("control"), self.spawn_lane("bulk")];
        *pipe = Some(Arc::new(Pipe { path, tx }));
    }
}

#[derive(Default)]
struct NetState {
    nodes: BTreeMap<Name, (Weak<Inner>, Role)>,
    links: HashMap<(Name, Name), Arc<InProcLink>>,
    shapes: HashMap<(Name, Name), LinkShape>,
    /// Each node's egress, shared by every link from it.
    uplinks: HashMap<Name, SharedShaper>,
    /// Each node's ingress, shared by every link to it.
    downlinks: HashMap<Name, SharedShaper>,
}

impl NetState {
    /// The hops of `from → to`: the sender's uplink, the pair's own link
    /// (a fresh shaper), the receiver's downlink, each where shaped.
    fn path(&self, from: &Name, to: &Name) -> Path {
        let pair = self
            .shapes
            .get(&(from.clone(), to.clone()))
            .map(|&shape| shared(Shaper::new(shape, seed((from, to)), Duration::ZERO)));
        let hops = [
            self.uplinks.get(from).cloned(),
            pair,
            self.downlinks.get(to).cloned(),
        ];
        Path::new(hops.into_iter().flatten().collect())
    }

    /// Gives every existing link that `touches` its current path.
    fn refresh(&self, touches: impl Fn(&Name, &Name) -> bool) {
        for ((from, to), link) in &self.links {
            if touches(from, to) {
                link.set_path(self.path(from, to));
            }
        }
    }
}

/// Which side of a node a [`InProcNet::set_node_link`] shapes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum NodeLink {
    /// Everything the node sends, to any node.
    Uplink,
    /// Everything the node receives, from any node.
    Downlink,
}

/// A network of in-process nodes: every node added is connected to every
/// other one. Shaping and partitions can be set per pair of nodes, and a
/// node's uplink and downlink, each shared by all of its links, can be
/// shaped too; a message crosses the sender's uplink, the pair's link and
/// the receiver's downlink in turn.
#[derive(Clone, Default)]
pub struct InProcNet {
    state: Arc<Mutex<NetState>>,
}

/// A shaper's random seed, derived from what it shapes.
fn seed(what: impl Hash) -> u64 {
    let mut h = std::collections::hash_map::DefaultHasher::new();
    what.hash(&mut h);
    h.finish()
}

impl InProcNet {
    /// An empty network.
    pub fn new() -> Self {
        InProcNet::default()
    }

    /// Adds node `name` and connects it to every node already there that
    /// its role talks to ([`Role::connects_to`]: not client to client);
    /// each side's actors get a [`crate::Delivery::PeerUp`]. Call within a
    /// tokio runtime.
    pub fn add_node(&self, name: Name, role: Role) -> Result<Bus, BusError> {
        let bus = Bus::new(name.clone(), role);
        let mut stale = Vec::new();
        let others: Vec<(Name, Arc<Inner>, Role)> = {
            let mut st = lock(&self.state);
            let before = st.nodes.len();
            st.nodes.retain(|_, (w, _)| w.strong_count() > 0);
            if st.nodes.contains_key(&name) {
                return Err(BusError::NodeExists(name));
            }
            // Links of nodes that are gone: a node of the same name may
            // come back, and gets links of its own. (Scanned only when a
            // node went: adding N nodes stays O(N) scans, not O(N) each.)
            let nodes = &st.nodes;
            let gone: Vec<(Name, Name)> = if nodes.len() < before {
                st.links
                    .keys()
                    .filter(|(f, t)| !nodes.contains_key(f) || !nodes.contains_key(t))
                    .cloned()
                    .collect()
            } else {
                Vec::new()
            };
            for key in gone {
                if let Some(link) = st.links.remove(&key) {
                    let from = st.nodes.get(&key.0).and_then(|(w, _)| w.upgrade());
                    stale.extend(from.map(|f| (f, key.1, link)));
                }
            }
            st.nodes.insert(name.clone(), (bus.downgrade(), role));
            st.nodes
                .iter()
                .filter(|(n, (_, r))| **n != name && role.connects_to(*r))
                .filter_map(|(n, (w, r))| w.upgrade().map(|i| (n.clone(), i, *r)))
                .collect()
        };
        for (from, to, link) in stale {
            from.peer_down(
                &to,
                Inner::link_id(&PeerLink::InProc(link)),
                "node gone".into(),
            );
        }
        for (_, inner, _) in others {
            self.link(&bus.inner, &inner);
            self.link(&inner, &bus.inner);
        }
        Ok(bus)
    }

    /// Creates the direction `from → to` and announces it to `from`,
    /// unless it exists already.
    fn link(&self, from: &Arc<Inner>, to: &Arc<Inner>) {
        let link = Arc::new(InProcLink {
            src_role: from.role,
            dst_name: to.node.clone(),
            dst: Arc::downgrade(to),
            pipe: Mutex::new(None),
        });
        {
            let mut st = lock(&self.state);
            let key = (from.node.clone(), to.node.clone());
            if st.links.contains_key(&key) {
                return;
            }
            st.links.insert(key, link.clone());
            link.set_path(st.path(&from.node, &to.node));
        }
        // The net makes one link per direction (above), so the bus never
        // holds another one to refuse it for.
        let _ = from.peer_up(to.node.clone(), to.role, PeerLink::InProc(link));
    }

    /// Shapes both directions between `a` and `b` (now and for links made
    /// later). Set it before traffic flows: messages already queued keep
    /// their old timing. Call within a tokio runtime.
    pub fn set_shape(&self, a: &Name, b: &Name, shape: LinkShape) -> Result<(), BusError> {
        shape.validate()?;
        let mut st = lock(&self.state);
        for key in [(a.clone(), b.clone()), (b.clone(), a.clone())] {
            st.shapes.insert(key, shape);
        }
        st.refresh(|from, to| (from == a && to == b) || (from == b && to == a));
        Ok(())
    }

    /// Shapes `node`'s uplink or downlink: one link shared by all of its
    /// connections (now and later ones), e.g. a server's egress that every
    /// client's traffic crosses. [`LinkShape::none`] removes it. Set it
    /// before traffic flows, as with [`InProcNet::set_shape`]. Call within a
    /// tokio runtime.
    pub fn set_node_link(
        &self,
        node: &Name,
        side: NodeLink,
        shape: LinkShape,
    ) -> Result<(), BusError> {
        shape.validate()?;
        let mut st = lock(&self.state);
        let (links, tag) = match side {
            NodeLink::Uplink => (&mut st.uplinks, "uplink"),
            NodeLink::Downlink => (&mut st.downlinks, "downlink"),
        };
        if shape.is_none() {
            links.remove(node);
        } else {
            let shaper = Shaper::new(shape, seed((node, tag)), Duration::ZERO);
            links.insert(node.clone(), shared(shaper));
        }
        st.refresh(|from, to| match side {
            NodeLink::Uplink => from == node,
            NodeLink::Downlink => to == node,
        });
        Ok(())
    }

    /// Cuts both directions between `a` and `b`; each side's actors get a
    /// [`crate::Delivery::PeerDown`].
    pub fn disconnect(&self, a: &Name, b: &Name) {
        let (links, nodes) = {
            let mut st = lock(&self.state);
            let l1 = st.links.remove(&(a.clone(), b.clone()));
            let l2 = st.links.remove(&(b.clone(), a.clone()));
            let na = st.nodes.get(a).and_then(|(w, _)| w.upgrade());
            let nb = st.nodes.get(b).and_then(|(w, _)| w.upgrade());
            ([l1, l2], [na, nb])
        };
        let [la, lb] = links;
        let [na, nb] = nodes;
        if let (Some(l), Some(n)) = (la, na) {
            n.peer_down(
                b,
                Inner::link_id(&PeerLink::InProc(l)),
                "disconnected".into(),
            );
        }
        if let (Some(l), Some(n)) = (lb, nb) {
            n.peer_down(
                a,
                Inner::link_id(&PeerLink::InProc(l)),
                "disconnected".into(),
            );
        }
    }

    /// Restores both directions between `a` and `b` after a
    /// [`InProcNet::disconnect`]; each side gets a [`crate::Delivery::PeerUp`].
    pub fn reconnect(&self, a: &Name, b: &Name) {
        let (na, nb) = {
            let st = lock(&self.state);
            (
                st.nodes.get(a).and_then(|(w, _)| w.upgrade()),
                st.nodes.get(b).and_then(|(w, _)| w.upgrade()),
            )
        };
        if let (Some(na), Some(nb)) = (na, nb) {
            self.link(&na, &nb);
            self.link(&nb, &na);
        }
    }
}
