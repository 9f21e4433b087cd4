//! TLS (rustls, ring) for both listeners from one PEM certificate chain and key named in
//! the config: tonic terminates it for gRPC; the HTTP/WebSocket side has its own accept
//! loop here because `axum::serve` speaks plain TCP only.

use std::net::SocketAddr;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Duration;

use axum::Router;
use axum::extract::ConnectInfo;
use hyper_util::rt::{TokioExecutor, TokioIo};
use hyper_util::service::TowerToHyperService;
use serde::Deserialize;
use tokio::net::TcpListener;
use tokio_rustls::TlsAcceptor;
use tokio_rustls::rustls;
use tokio_rustls::rustls::pki_types::pem::PemObject;
use tokio_rustls::rustls::pki_types::{CertificateDer, PrivateKeyDer};
use tower::ServiceExt;

/// `"tls": {"cert_path": …, "key_path": …}` in the config (or `--tls-cert`/`--tls-key`).
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TlsConfig {
    /// PEM: the server's certificate first, then any intermediates.
    pub cert_path: PathBuf,
    /// PEM: the private key (PKCS#8, PKCS#1 or SEC1).
    pub key_path: PathBuf,
    /// PEM: the operators' CA. A client presenting a certificate it signed is an
    /// operator (docs/server.md); clients without a certificate are still served.
    #[serde(default)]
    pub client_ca_path: Option<PathBuf>,
}

/// The certificate and key, read and checked once at start.
pub struct Tls {
    pub cert_pem: Vec<u8>,
    pub key_pem: Vec<u8>,
    pub client_ca_pem: Option<Vec<u8>>,
    /// For the HTTP/WebSocket listener.
    pub http_acceptor: TlsAcceptor,
}

fn read(path: &Path, what: &str) -> Result<Vec<u8>, String> {
    std::fs::read(path).map_err(|e| format!("cannot read the TLS {what} {}: {e}", path.display()))
}

impl Tls {
    /// Reads and checks the PEM files; every failure names the file and what was wrong.
    pub fn load(config: &TlsConfig) -> Result<Self, String> {
        let cert_pem = read(&config.cert_path, "certificate")?;
        let key_pem = read(&config.key_path, "private key")?;
        let chain: Vec<CertificateDer<'static>> = CertificateDer::pem_slice_iter(&cert_pem)
            .collect::<Result<_, _>>()
            .map_err(|e| format!("{}: not a PEM certificate chain: {e}", config.cert_path.display()))?;
        if chain.is_empty() {
            return Err(format!("{}: no CERTIFICATE block found (expected PEM)", config.cert_path.display()));
        }
        let key = PrivateKeyDer::from_pem_slice(&key_pem)
            .map_err(|e| format!("{}: no usable private key (expected a PEM PRIVATE KEY, RSA PRIVATE KEY or EC PRIVATE KEY block): {e}", config.key_path.display()))?;
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let builder = rustls::ServerConfig::builder_with_provider(provider.clone())
            .with_safe_default_protocol_versions()
            .map_err(|e| format!("TLS set-up: {e}"))?;
        let client_ca_pem = match &config.client_ca_path {
            Some(path) => Some(read(path, "client CA certificate")?),
            None => None,
        };
        let builder = match (&client_ca_pem, &config.client_ca_path) {
            (Some(pem), Some(path)) => {
                let mut roots = rustls::RootCertStore::empty();
                for cert in CertificateDer::pem_slice_iter(pem) {
                    let cert = cert.map_err(|e| format!("{}: not a PEM certificate: {e}", path.display()))?;
                    roots.add(cert).map_err(|e| format!("{}: not a usable CA certificate: {e}", path.display()))?;
                }
                if roots.is_empty() {
                    return Err(format!("{}: no CERTIFICATE block found (expected PEM)", path.display()));
                }
                // Optional: trainees' and instructors' browsers have no certificate.
                let verifier = rustls::server::WebPkiClientVerifier::builder_with_provider(Arc::new(roots), provider)
                    .allow_unauthenticated()
                    .build()
                    .map_err(|e| format!("{}: {e}", path.display()))?;
                builder.with_client_cert_verifier(verifier)
            }
            _ => builder.with_no_client_auth(),
        };
        let mut server = builder
            .with_single_cert(chain, key)
            .map_err(|e| format!("{} and {} do not make a usable identity: {e}", config.cert_path.display(), config.key_path.display()))?;
        // HTTP/1.1 only: browsers open WebSockets over HTTP/1.1 connections.
        server.alpn_protocols = vec![b"http/1.1".to_vec()];
        Ok(Self { cert_pem, key_pem, client_ca_pem, http_acceptor: TlsAcceptor::from(Arc::new(server)) })
    }

    /// tonic's view of the same identity (and the same optional client CA).
    pub fn grpc_config(&self) -> tonic::transport::ServerTlsConfig {
        let config = tonic::transport::ServerTlsConfig::new().identity(tonic::transport::Identity::from_pem(&self.cert_pem, &self.key_pem));
        match &self.client_ca_pem {
            Some(ca) => config.client_ca_root(tonic::transport::Certificate::from_pem(ca)).client_auth_optional(true),
            None => config,
        }
    }
}

/// Set on an HTTP request whose TLS client presented a certificate the operators' CA
/// signed (the handshake verified it).
#[derive(Debug, Clone, Copy)]
pub struct OperatorCertificate;

/// A handshake that takes longer than this is dropped (a client that opens a connection
/// and says nothing holds no task for long).
const HANDSHAKE_TIMEOUT: Duration = Duration::from_secs(10);

/// Serves `app` over TLS on `listener` until `stop` resolves: each connection is
/// handshaken and served on a task of its own, with WebSocket upgrades, and the peer's
/// address as `ConnectInfo` (as `axum::serve` gives it on plain TCP).
pub async fn serve_https(listener: TcpListener, acceptor: TlsAcceptor, app: Router, stop: impl std::future::Future<Output = ()>) {
    let http = hyper_util::server::conn::auto::Builder::new(TokioExecutor::new());
    tokio::pin!(stop);
    loop {
        let (tcp, peer) = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok(conn) => conn,
                Err(e) => {
                    // Out of descriptors and the like: back off instead of spinning.
                    tracing::warn!("accepting an HTTPS connection: {e}");
                    tokio::time::sleep(Duration::from_millis(50)).await;
                    continue;
                }
            },
            () = &mut stop => return,
        };
        let _ = tcp.set_nodelay(true);
        let (acceptor, app, http) = (acceptor.clone(), app.clone(), http.clone());
        tokio::spawn(async move {
            let stream = match tokio::time::timeout(HANDSHAKE_TIMEOUT, acceptor.accept(tcp)).await {
                Ok(Ok(stream)) => stream,
                Ok(Err(e)) => return tracing::debug!(%peer, "TLS handshake failed: {e}"),
                Err(_) => return tracing::debug!(%peer, "TLS handshake timed out"),
            };
            let certified = stream.get_ref().1.peer_certificates().is_some_and(|c| !c.is_empty());
            let app = app.map_request(move |mut request: axum::extract::Request<hyper::body::Incoming>| {
                request.extensions_mut().insert(ConnectInfo::<SocketAddr>(peer));
                if certified {
                    request.extensions_mut().insert(OperatorCertificate);
                }
                request
            });
            if let Err(e) = http.serve_connection_with_upgrades(TokioIo::new(stream), TowerToHyperService::new(app)).await {
                tracing::debug!(%peer, "HTTPS connection ended: {e}");
            }
        });
    }
}
