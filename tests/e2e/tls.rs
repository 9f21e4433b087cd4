//! TLS: the server started with a self-signed certificate made here (rcgen) serves gRPC,
//! HTTPS and WebSocket over TLS only, to clients that trust that certificate.

use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::sessions_client::SessionsClient;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_rustls::rustls;

use crate::harness::{Server, TempDir, server_binary};
use cutsim_load::viewer::Viewer;

struct Certificate {
    dir: TempDir,
    der: Vec<u8>,
}

impl Certificate {
    /// A self-signed certificate for 127.0.0.1 and localhost, written as cert.pem/key.pem.
    fn make() -> Self {
        let made = rcgen::generate_simple_self_signed(vec!["127.0.0.1".to_owned(), "localhost".to_owned()]).expect("rcgen makes a certificate");
        let dir = TempDir::new("tls");
        std::fs::write(dir.0.join("cert.pem"), made.cert.pem()).unwrap();
        std::fs::write(dir.0.join("key.pem"), made.signing_key.serialize_pem()).unwrap();
        Certificate { der: made.cert.der().to_vec(), dir }
    }

    fn path(&self, name: &str) -> String {
        self.dir.0.join(name).display().to_string()
    }

    fn client_config(&self) -> Arc<rustls::ClientConfig> {
        let mut roots = rustls::RootCertStore::empty();
        roots.add(self.der.clone().into()).unwrap();
        let provider = Arc::new(rustls::crypto::ring::default_provider());
        let config = rustls::ClientConfig::builder_with_provider(provider).with_safe_default_protocol_versions().unwrap().with_root_certificates(roots).with_no_client_auth();
        Arc::new(config)
    }
}

#[tokio::test(flavor = "multi_thread")]
async fn grpc_https_and_websocket_take_tls_with_the_configured_certificate() {
    let cert = Certificate::make();
    let server = Server::start_with(&["--no-session", "--tls-cert", &cert.path("cert.pem"), "--tls-key", &cert.path("key.pem")]);

    // gRPC over TLS, trusting the certificate as a CA: create a session.
    let channel = cutsim_proto::endpoint(&format!("https://{}", server.grpc), Some(&cert.dir.0.join("cert.pem"))).unwrap().connect().await.expect("gRPC over TLS connects");
    let created = SessionsClient::new(channel)
        .create_session(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: pb::SessionMode::Realtime as i32, label: "tls".into() })
        .await
        .expect("a session over TLS")
        .into_inner();
    let id = created.session.unwrap().id;

    // Plain gRPC to the TLS port gets nowhere.
    let plain = async { tonic::transport::Endpoint::from_shared(format!("http://{}", server.grpc)).unwrap().connect().await.map(SessionsClient::new)?.list_sessions(pb::ListSessionsRequest {}).await.map_err(Into::into) };
    let plain: Result<_, Box<dyn std::error::Error>> = tokio::time::timeout(Duration::from_secs(10), plain).await.expect("plain gRPC fails promptly");
    assert!(plain.is_err(), "plain-text gRPC must not be served on a TLS listener");

    // A client that does not trust the certificate is refused at the handshake.
    let untrusted = cutsim_proto::endpoint(&format!("https://{}", server.grpc), None).unwrap().connect().await;
    assert!(untrusted.is_err(), "a self-signed certificate must not be trusted without --tls-ca");

    // HTTPS: the health page.
    let connector = tokio_rustls::TlsConnector::from(cert.client_config());
    let tcp = tokio::net::TcpStream::connect(&server.http).await.unwrap();
    let mut tls = connector.connect("127.0.0.1".try_into().unwrap(), tcp).await.expect("HTTPS handshake");
    tls.write_all(b"GET /healthz HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n").await.unwrap();
    let mut answer = String::new();
    tls.read_to_string(&mut answer).await.unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");
    assert!(answer.ends_with("ok\n"), "{answer}");

    // The WebSocket viewer over wss:// gets its snapshot.
    let mut viewer = Viewer::connect_tls(&server.http, &id, &created.observe_token, cert.client_config()).await.expect("wss connects");
    assert!(viewer.pump_until(Duration::from_secs(20), |v| v.snapshots > 0 && v.positions_frames > 0).await, "snapshot and positions over wss");
    assert!(viewer.triangles() > 0);

    // Plain ws:// on the TLS port fails.
    assert!(Viewer::connect(&server.http, &id, &created.observe_token).await.is_err(), "plain ws:// must not be served on a TLS listener");

    // The health probe speaks TLS when given the CA.
    let probe = Command::new(server_binary()).args(["health", "--grpc-addr", &server.grpc, "--tls-ca", &cert.path("cert.pem")]).output().unwrap();
    assert!(probe.status.success(), "{}", String::from_utf8_lossy(&probe.stderr));
}

#[test]
fn a_missing_or_mismatched_key_stops_the_server_with_a_clear_error() {
    let cert = Certificate::make();
    let other = Certificate::make();
    let run = |cert_path: &str, key_path: &str| {
        let out = Command::new(server_binary())
            .args(["serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--tls-cert", cert_path, "--tls-key", key_path])
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2));
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let missing = run(&cert.path("cert.pem"), &cert.path("nope.pem"));
    assert!(missing.contains("cannot read the TLS private key") && missing.contains("nope.pem"), "{missing}");
    let not_pem = run(&cert.path("key.pem"), &cert.path("key.pem"));
    assert!(not_pem.contains("no CERTIFICATE block"), "{not_pem}");
    let mismatched = run(&cert.path("cert.pem"), &other.path("key.pem"));
    assert!(mismatched.contains("do not make a usable identity"), "{mismatched}");
}
