//! Compiles proto/cutsim.proto with protox (pure Rust, no protoc needed) and generates
//! the prost messages and, with the "grpc" feature, the tonic clients/servers. The
//! encoded file descriptor set is written too, for gRPC server reflection.

use prost::Message;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    println!("cargo:rerun-if-changed=cutsim.proto");
    let fds = protox::compile(["cutsim.proto"], ["."])?;
    let out = std::path::PathBuf::from(std::env::var("OUT_DIR")?);
    std::fs::write(out.join("cutsim_descriptor.bin"), fds.encode_to_vec())?;
    // Without the "grpc" feature the messages alone (no tonic clients or servers).
    let grpc = std::env::var_os("CARGO_FEATURE_GRPC").is_some();
    tonic_prost_build::configure().build_client(grpc).build_server(grpc).compile_fds(fds)?;
    Ok(())
}
