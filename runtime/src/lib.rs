//! dray-runtime: the message bus (transports, mailboxes) and process setup.
//!
//! Actors get a [`Mailbox`] (a bounded tokio channel) under an [`Address`]
//! from a [`Bus`], and send typed [`Message`]s to any address through it.
//! Where the receiving actor lives decides the path:
//!
//! - same node: straight into its mailbox;
//! - another node of an [`InProcNet`]: encoded (so the wire limits hold),
//!   optionally shaped (latency, jitter, bandwidth, loss) on tokio's clock
//!   per pair of nodes and per node's shared uplink and downlink, then
//!   delivered;
//! - another node over QUIC ([`quic::QuicTransport`]): mutual TLS with the
//!   cluster CA ([`certs`]), a control stream per direction, a stream of its
//!   own for each bulk message; a UDP relay ([`relay`]) shapes such links.
//!
//! Peers coming and going reach every local mailbox as [`Delivery::PeerUp`]
//! and [`Delivery::PeerDown`].

mod bus;
pub mod certs;
mod inproc;
pub mod logging;
pub mod process;
pub mod quic;
pub mod relay;
pub mod shaping;
mod traffic;

pub use bus::{ActorRef, Bus, BusError, Delivery, Mailbox, SendError};
pub use dray_protocol::{Address, Message, Name, Role};
pub use inproc::{InProcNet, NodeLink};
pub use shaping::LinkShape;
pub use traffic::{LinkMeter, Traffic};
