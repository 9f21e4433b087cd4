//! cutsim-proto: the gRPC services and WebSocket frames of cutsim, generated from
//! `proto/cutsim.proto` (package `cutsim.v1`). One schema serves both transports.

#![allow(clippy::all)]

pub mod v1 {
    tonic::include_proto!("cutsim.v1");
}

/// The encoded file descriptor set of cutsim.proto, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/cutsim_descriptor.bin"));
