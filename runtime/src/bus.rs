//! The bus: mailboxes, addresses, routing to local actors and remote peers.

use crate::inproc::InProcLink;
use crate::quic::QuicPeer;
use crate::traffic::{Traffic, TrafficCounters};
use dray_protocol::{Address, Envelope, Message, Name, ProtocolError, Role};
use std::collections::HashMap;
use std::sync::{Arc, Mutex, MutexGuard, Weak};
use tokio::sync::{mpsc, Notify};
use tracing::{debug, error, warn};

/// What an actor receives.
// Nearly every delivery is a message: boxing it to shrink the rare peer
// events would cost an allocation per message.
#[allow(clippy::large_enum_variant)]
#[derive(Clone, Debug, PartialEq)]
pub enum Delivery {
    /// A message from another actor.
    Message {
        /// The sender.
        from: Address,
        /// The message.
        msg: Message,
    },
    /// A connection to a node came up (or came back).
    PeerUp {
        /// The node.
        node: Name,
        /// Its role, as it announced it.
        role: Role,
    },
    /// The connection to a node was lost; messages to it fail until it is
    /// back (a dialed peer is redialed with backoff).
    PeerDown {
        /// The node.
        node: Name,
        /// Why, for logs.
        reason: String,
    },
}

/// Why a mailbox could not be created.
#[derive(Debug, thiserror::Error)]
pub enum BusError {
    /// The actor name is taken on this node.
    #[error("an actor named {0} already exists on this node")]
    Taken(Name),
    /// A mailbox needs room for at least one message.
    #[error("a mailbox needs a capacity of at least 1")]
    ZeroCapacity,
    /// A node of that name already exists (in-process network).
    #[error("a node named {0} already exists")]
    NodeExists(Name),
    /// The shape is unusable.
    #[error(transparent)]
    Shape(#[from] crate::shaping::ShapeError),
}

/// Why a message could not be sent.
#[derive(Debug, thiserror::Error)]
pub enum SendError {
    /// No actor of that name on its node (or it has stopped).
    #[error("no actor {0}")]
    NoSuchActor(Address),
    /// No connection to that node now.
    #[error("node {0} is not connected")]
    PeerUnavailable(Name),
    /// The message is invalid or over its size limit.
    #[error("cannot send: {0}")]
    Protocol(#[from] ProtocolError),
    /// The connection failed while sending.
    #[error("connection to {node} failed while sending: {reason}")]
    Connection {
        /// The node.
        node: Name,
        /// What happened.
        reason: String,
    },
}

#[derive(Clone)]
pub(crate) enum PeerLink {
    InProc(Arc<InProcLink>),
    Quic(Arc<QuicPeer>),
}

impl PeerLink {
    /// Sends `env`; returns the bytes of its encoding.
    async fn send(&self, env: Envelope) -> Result<usize, SendError> {
        match self {
            PeerLink::InProc(l) => l.send(env).await,
            PeerLink::Quic(p) => p.send(env).await,
        }
    }

    fn id(&self) -> usize {
        match self {
            PeerLink::InProc(l) => Arc::as_ptr(l) as *const () as usize,
            PeerLink::Quic(p) => Arc::as_ptr(p) as *const () as usize,
        }
    }

    /// Where the link leads, for logs.
    pub(crate) fn remote(&self) -> String {
        match self {
            PeerLink::InProc(_) => "in-process".into(),
            PeerLink::Quic(p) => p.remote().to_string(),
        }
    }
}

/// Why [`Inner::peer_up`] refused a link: the node already has a live one.
#[derive(Debug)]
pub(crate) struct AlreadyConnected {
    /// Where the live link leads.
    pub(crate) remote: String,
}

pub(crate) struct Inner {
    pub(crate) node: Name,
    pub(crate) role: Role,
    actors: Mutex<HashMap<Name, mpsc::Sender<Delivery>>>,
    peers: Mutex<HashMap<Name, (PeerLink, Role)>>,
    peers_changed: Notify,
    traffic: TrafficCounters,
}

fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    // A panic while holding these maps cannot leave them inconsistent (each
    // update is one insert or remove), so a poisoned lock is still usable.
    m.lock().unwrap_or_else(|p| p.into_inner())
}

impl Inner {
    /// Delivers an envelope that arrived for this node to its actor.
    pub(crate) async fn deliver_local(&self, env: Envelope) -> Result<(), SendError> {
        let tx = lock(&self.actors).get(&env.to.actor).cloned();
        let Some(tx) = tx else {
            return Err(SendError::NoSuchActor(env.to));
        };
        let to = env.to;
        tx.send(Delivery::Message {
            from: env.from,
            msg: env.msg,
        })
        .await
        .map_err(|_| SendError::NoSuchActor(to))
    }

    /// Delivers an envelope that came over a link from a node of role
    /// `from_role` (as its authenticated name gives it), if the sender rule
    /// allows it; a forbidden message is dropped with a warning and the
    /// link goes on.
    pub(crate) async fn deliver_remote(
        &self,
        from_role: Role,
        env: Envelope,
    ) -> Result<(), SendError> {
        let kind = env.msg.kind();
        if !kind.may_send(from_role, self.role) {
            warn!(
                sender = %env.from,
                sender_role = %from_role,
                kind = kind.name(),
                receiver = %env.to,
                receiver_role = %self.role,
                "refused a message the sender's role may not send (dropped)"
            );
            return Ok(());
        }
        self.deliver_local(env).await
    }

    fn broadcast(&self, d: Delivery) {
        let txs: Vec<_> = lock(&self.actors).values().cloned().collect();
        for tx in txs {
            match tx.try_send(d.clone()) {
                Ok(()) | Err(mpsc::error::TrySendError::Closed(_)) => {}
                Err(mpsc::error::TrySendError::Full(d)) => {
                    // Never lose a peer event: wait for room in the background.
                    tokio::spawn(async move {
                        let _ = tx.send(d).await;
                    });
                }
            }
        }
    }

    /// Registers `link` as the one to `node`. One identity, one link: while
    /// a link to `node` is up, another is refused (logged as an error naming
    /// both ends), so a second process under the same name (an impostor,
    /// or the same `--index` started twice) can neither take the node's
    /// traffic nor, by leaving, cut the node off; closing the first instead
    /// would let the two evict each other in turn. A restarted node gets
    /// in once its old link is down (QUIC's idle timeout).
    pub(crate) fn peer_up(
        &self,
        node: Name,
        role: Role,
        link: PeerLink,
    ) -> Result<(), AlreadyConnected> {
        {
            let mut peers = lock(&self.peers);
            if let Some((live, _)) = peers.get(&node) {
                let remote = live.remote();
                error!(
                    local = %self.node,
                    peer = %node,
                    live = %remote,
                    refused = %link.remote(),
                    "a second connection under a connected node's name was refused"
                );
                return Err(AlreadyConnected { remote });
            }
            peers.insert(node.clone(), (link, role));
        }
        debug!(local = %self.node, peer = %node, %role, "peer up");
        self.peers_changed.notify_waiters();
        self.broadcast(Delivery::PeerUp { node, role });
        Ok(())
    }

    /// Removes the link if it is still the one registered for `node`.
    pub(crate) fn peer_down(&self, node: &Name, link_id: usize, reason: String) {
        let removed = {
            let mut peers = lock(&self.peers);
            match peers.get(node) {
                Some((l, _)) if l.id() == link_id => peers.remove(node).is_some(),
                _ => false,
            }
        };
        if removed {
            // A connection closed on purpose (a node stopping) is routine.
            if reason.starts_with("closed") {
                debug!(local = %self.node, peer = %node, %reason, "peer down");
            } else {
                warn!(local = %self.node, peer = %node, %reason, "peer down");
            }
            self.peers_changed.notify_waiters();
            self.broadcast(Delivery::PeerDown {
                node: node.clone(),
                reason,
            });
        }
    }

    /// Counts `bytes` of an envelope that arrived from a node of `role`.
    pub(crate) fn count_received(&self, role: Role, bytes: usize) {
        self.traffic.received(role, bytes);
    }

    pub(crate) fn link_id(link: &PeerLink) -> usize {
        link.id()
    }
}

/// One node's message bus. Cheap to clone.
#[derive(Clone)]
pub struct Bus {
    pub(crate) inner: Arc<Inner>,
}

impl std::fmt::Debug for Bus {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Bus")
            .field("node", &self.inner.node)
            .finish()
    }
}

impl Bus {
    /// A bus for node `node` with no peers yet; attach it to an
    /// [`crate::InProcNet`] or a [`crate::quic::QuicTransport`] to reach others.
    pub fn new(node: Name, role: Role) -> Bus {
        Bus {
            inner: Arc::new(Inner {
                node,
                role,
                actors: Mutex::new(HashMap::new()),
                peers: Mutex::new(HashMap::new()),
                peers_changed: Notify::new(),
                traffic: TrafficCounters::default(),
            }),
        }
    }

    pub(crate) fn downgrade(&self) -> Weak<Inner> {
        Arc::downgrade(&self.inner)
    }

    /// This node's name.
    pub fn node(&self) -> &Name {
        &self.inner.node
    }

    /// This node's role.
    pub fn role(&self) -> Role {
        self.inner.role
    }

    /// The address of actor `actor` on this node.
    pub fn address(&self, actor: Name) -> Address {
        Address::new(self.inner.node.clone(), actor)
    }

    /// Creates the mailbox of actor `actor` on this node, holding at most
    /// `capacity` undelivered messages (senders wait when it is full).
    pub fn mailbox(&self, actor: Name, capacity: usize) -> Result<Mailbox, BusError> {
        if capacity == 0 {
            return Err(BusError::ZeroCapacity);
        }
        let (tx, rx) = mpsc::channel(capacity);
        {
            let mut actors = lock(&self.inner.actors);
            if let Some(old) = actors.get(&actor) {
                if !old.is_closed() {
                    return Err(BusError::Taken(actor));
                }
            }
            actors.insert(actor.clone(), tx);
        }
        Ok(Mailbox {
            me: ActorRef {
                bus: self.clone(),
                addr: self.address(actor),
            },
            rx,
        })
    }

    /// Sends `msg` from `from` to `to`, wherever `to` lives. Waits while the
    /// receiving mailbox (or the link) is full.
    pub async fn send(&self, from: &Address, to: &Address, msg: Message) -> Result<(), SendError> {
        let env = Envelope {
            msg,
            from: from.clone(),
            to: to.clone(),
        };
        if to.node == self.inner.node {
            env.msg.validate()?;
            return self.inner.deliver_local(env).await;
        }
        let link = lock(&self.inner.peers).get(&to.node).cloned();
        match link {
            Some((link, role)) => {
                let bytes = link.send(env).await?;
                self.inner.traffic.sent(role, bytes);
                Ok(())
            }
            None => Err(SendError::PeerUnavailable(to.node.clone())),
        }
    }

    /// Bytes this node's links have carried so far, by the other end's role.
    pub fn traffic(&self) -> Traffic {
        self.inner.traffic.snapshot()
    }

    /// Nodes connected now, with their roles.
    pub fn peers(&self) -> Vec<(Name, Role)> {
        let mut v: Vec<_> = lock(&self.inner.peers)
            .iter()
            .map(|(n, (_, r))| (n.clone(), *r))
            .collect();
        v.sort_by(|a, b| a.0.cmp(&b.0));
        v
    }

    /// Whether `node` is connected now.
    pub fn is_connected(&self, node: &Name) -> bool {
        lock(&self.inner.peers).contains_key(node)
    }

    /// Waits until `node` is connected.
    pub async fn wait_for_peer(&self, node: &Name) {
        loop {
            let notified = self.inner.peers_changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if self.is_connected(node) {
                return;
            }
            notified.await;
        }
    }

    /// Waits until `node` is not connected.
    pub async fn wait_for_peer_loss(&self, node: &Name) {
        loop {
            let notified = self.inner.peers_changed.notified();
            tokio::pin!(notified);
            notified.as_mut().enable();
            if !self.is_connected(node) {
                return;
            }
            notified.await;
        }
    }
}

/// A handle that sends as one actor. Cheap to clone; hand it to the tasks
/// of the actor.
#[derive(Clone, Debug)]
pub struct ActorRef {
    bus: Bus,
    addr: Address,
}

impl ActorRef {
    /// The actor's address.
    pub fn address(&self) -> &Address {
        &self.addr
    }

    /// The bus it sends through.
    pub fn bus(&self) -> &Bus {
        &self.bus
    }

    /// Sends `msg` to `to` as this actor.
    pub async fn send(&self, to: &Address, msg: Message) -> Result<(), SendError> {
        let span = tracing::trace_span!("send", kind = msg.kind().name(), to = %to);
        let _e = span.enter();
        self.bus.send(&self.addr, to, msg).await
    }
}

/// An actor's bounded mailbox. Dropping it removes the actor from its node.
#[derive(Debug)]
pub struct Mailbox {
    me: ActorRef,
    rx: mpsc::Receiver<Delivery>,
}

impl Mailbox {
    /// The actor's address.
    pub fn address(&self) -> &Address {
        &self.me.addr
    }

    /// A sending handle for this actor.
    pub fn handle(&self) -> ActorRef {
        self.me.clone()
    }

    /// Sends `msg` to `to` as this actor.
    pub async fn send(&self, to: &Address, msg: Message) -> Result<(), SendError> {
        self.me.send(to, msg).await
    }

    /// The next delivery; `None` once the bus is gone.
    pub async fn recv(&mut self) -> Option<Delivery> {
        self.rx.recv().await
    }

    /// The next delivery if one is waiting.
    pub fn try_recv(&mut self) -> Option<Delivery> {
        self.rx.try_recv().ok()
    }

    /// The next message, skipping peer events.
    pub async fn recv_message(&mut self) -> Option<(Address, Message)> {
        loop {
            match self.rx.recv().await? {
                Delivery::Message { from, msg } => return Some((from, msg)),
                other => debug!(actor = %self.me.addr, ?other, "skipped peer event"),
            }
        }
    }
}

impl Drop for Mailbox {
    fn drop(&mut self) {
        self.rx.close();
        let mut actors = lock(&self.me.bus.inner.actors);
        if actors
            .get(&self.me.addr.actor)
            .is_some_and(|tx| tx.is_closed())
        {
            actors.remove(&self.me.addr.actor);
        }
    }
}
