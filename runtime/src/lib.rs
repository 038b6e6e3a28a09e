//! dray-runtime: the message bus (transports, mailboxes) and process setup.

pub mod logging;
pub mod process;
