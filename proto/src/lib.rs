//! cutsim-proto: the gRPC and WebSocket message types generated from proto/cutsim.proto
//! (filled by the server issue).
