//! cutsim-proto: the gRPC services and WebSocket frames of cutsim, generated from
//! `proto/cutsim.proto` (package `cutsim.v1`). One schema serves both transports.

#![allow(clippy::all)]

pub mod v1 {
    include!(concat!(env!("OUT_DIR"), "/cutsim.v1.rs"));
}

/// The encoded file descriptor set of cutsim.proto, for gRPC server reflection.
pub const FILE_DESCRIPTOR_SET: &[u8] = include_bytes!(concat!(env!("OUT_DIR"), "/cutsim_descriptor.bin"));

/// A gRPC endpoint for a server URL: `http://HOST:PORT` is plain TCP; `https://HOST:PORT`
/// is TLS, trusting the system's roots and, when given, the CA certificate in `ca_pem`
/// (a PEM file: a private CA or a self-signed server certificate).
#[cfg(feature = "grpc")]
pub fn endpoint(url: &str, ca_pem: Option<&std::path::Path>) -> Result<tonic::transport::Endpoint, String> {
    endpoint_for_name(url, ca_pem, None)
}

/// [`endpoint`], checking the server's certificate against `tls_name` instead of the
/// URL's host: for a probe that dials `127.0.0.1` on a server whose certificate names
/// its public host.
#[cfg(feature = "grpc")]
pub fn endpoint_for_name(url: &str, ca_pem: Option<&std::path::Path>, tls_name: Option<&str>) -> Result<tonic::transport::Endpoint, String> {
    let endpoint = tonic::transport::Endpoint::from_shared(url.to_owned())
        .map_err(|e| format!("{url:?} is not a server address ({e}); use e.g. http://127.0.0.1:50051 or https://host:50051"))?;
    let tls = url.starts_with("https://");
    if !tls {
        return match (ca_pem, tls_name) {
            (None, None) => Ok(endpoint),
            _ => Err(format!("TLS settings were given but {url:?} is not https://")),
        };
    }
    let mut config = tonic::transport::ClientTlsConfig::new().with_native_roots();
    if let Some(path) = ca_pem {
        let pem = std::fs::read(path).map_err(|e| format!("cannot read the TLS CA certificate {}: {e}", path.display()))?;
        config = config.ca_certificate(tonic::transport::Certificate::from_pem(pem));
    }
    if let Some(name) = tls_name {
        config = config.domain_name(name);
    }
    endpoint.tls_config(config).map_err(|e| format!("TLS set-up for {url}: {e}"))
}
