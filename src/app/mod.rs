//! The application interface: wire protocol, socket server and client library.

pub mod client;
pub mod endpoint;
pub mod protocol;
pub mod server;
