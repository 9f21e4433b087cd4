//! End-to-end tests: the real `cutsim-server` binary on free loopback ports, driven by
//! real clients — the generated Rust gRPC client, a tokio-tungstenite WebSocket client,
//! and gRPC reflection and health clients as grpcurl would use them.

mod assessment;
mod bad_input;
mod deploy;
mod faults;
mod harness;
mod haptics;
mod recording;
mod replay;
mod scripts;
mod security;
mod sessions;
mod tls;
mod viewers;
