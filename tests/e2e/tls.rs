//! TLS: the server started with a self-signed certificate made here (rcgen) serves gRPC,
//! HTTPS and WebSocket over TLS only, to clients that trust that certificate.

use std::process::Command;
use std::sync::Arc;
use std::time::Duration;

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::sessions_client::SessionsClient;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_rustls::rustls;

use crate::harness::{OPERATOR, Server, TempDir, operator, server_binary};
use cutsim_load::viewer::Viewer;

struct Certificate {
    dir: TempDir,
    der: Vec<u8>,
}

impl Certificate {
    /// A self-signed certificate for 127.0.0.1 and localhost, written as cert.pem/key.pem.
    fn make() -> Self {
        Self::make_for(&["127.0.0.1", "localhost"])
    }

    /// A self-signed certificate for `names` only.
    fn make_for(names: &[&str]) -> Self {
        let made = rcgen::generate_simple_self_signed(names.iter().map(|n| n.to_string()).collect::<Vec<_>>()).expect("rcgen makes a certificate");
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
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: pb::SessionMode::Realtime as i32, label: "tls".into() }))
        .await
        .expect("a session over TLS")
        .into_inner();
    let id = created.session.unwrap().id;

    // Plain gRPC to the TLS port gets nowhere.
    let plain = async { tonic::transport::Endpoint::from_shared(format!("http://{}", server.grpc)).unwrap().connect().await.map(SessionsClient::new)?.list_sessions(operator(pb::ListSessionsRequest {})).await.map_err(Into::into) };
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
    assert!(answer.contains("\r\n\r\nok\n"), "{answer}");

    // The WebSocket viewer over wss:// gets its snapshot.
    let mut viewer = Viewer::connect_tls(&server.http, &id, &created.observe_token, cert.client_config()).await.expect("wss connects");
    assert!(viewer.pump_until(Duration::from_secs(20), |v| v.snapshots > 0 && v.positions_frames > 0).await, "snapshot and positions over wss");
    assert!(viewer.triangles() > 0);

    // Plain ws:// on the TLS port fails.
    assert!(Viewer::connect(&server.http, &id, &created.observe_token).await.is_err(), "plain ws:// must not be served on a TLS listener");

    // The health probe speaks TLS when given the CA.
    let probe = |extra: &[&str]| Command::new(server_binary()).args(["health", "--grpc-addr", &server.grpc, "--tls-ca", &cert.path("cert.pem")]).args(extra).output().unwrap();
    let served = probe(&[]);
    assert!(served.status.success(), "{}", String::from_utf8_lossy(&served.stderr));
    // A probe inside a pod dials 127.0.0.1 and checks the certificate's own name
    // (docker/k8s/tls-patch.yaml); a name the certificate does not carry is refused.
    let by_name = probe(&["--tls-domain", "localhost"]);
    assert!(by_name.status.success(), "{}", String::from_utf8_lossy(&by_name.stderr));
    let wrong_name = probe(&["--tls-domain", "cutsim.example.org"]);
    assert_eq!(wrong_name.status.code(), Some(1), "a certificate without the name must not pass");
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

/// The JSON arrays (YAML flow sequences) on the lines of `yaml` that start with `key:`.
fn flow_lists(yaml: &str, key: &str) -> Vec<Vec<String>> {
    yaml.lines()
        .filter_map(|l| l.trim().strip_prefix(key)?.strip_prefix(':'))
        .filter_map(|rest| serde_json::from_str(rest.trim()).ok())
        .collect()
}

/// docker/k8s/tls-patch.yaml, run here: the server started with the patch's arguments
/// (its Secret's files made by rcgen for the probe's name only, not for 127.0.0.1), and
/// the patch's exec probes pass against it.
#[test]
fn the_kubernetes_tls_patch_serves_and_its_probes_pass() {
    let patch = std::fs::read_to_string(crate::harness::repo("docker/k8s/tls-patch.yaml")).unwrap();
    let args = flow_lists(&patch, "args").pop().expect("the patch gives the server's args");
    let probes = flow_lists(&patch, "command");
    assert_eq!(probes.len(), 2, "a readiness and a liveness probe");
    let probe = &probes[0];
    assert_eq!(&probes[1], probe);
    assert!(patch.matches("grpc: null").count() == 2, "the native gRPC probes are removed");
    let after = |list: &[String], flag: &str| list.iter().position(|a| a == flag).map(|i| list[i + 1].clone()).unwrap_or_else(|| panic!("{flag} in {list:?}"));
    let name = after(probe, "--tls-domain");

    // The Secret's files, mounted at /etc/cutsim/tls in the pod, are made here.
    let cert = Certificate::make_for(&[&name]);
    std::fs::copy(cert.path("cert.pem"), cert.dir.0.join("tls.crt")).unwrap();
    std::fs::copy(cert.path("key.pem"), cert.dir.0.join("tls.key")).unwrap();
    std::fs::copy(cert.path("cert.pem"), cert.dir.0.join("ca.crt")).unwrap();
    std::fs::write(cert.dir.0.join("server.json"), "{}").unwrap();
    let local = |a: &String| {
        let a = a.replace("/etc/cutsim/tls/", &format!("{}/", cert.dir.0.display()));
        a.replace("/etc/cutsim/server.json", &cert.path("server.json"))
    };
    assert_eq!(args[0], "serve");
    let serve: Vec<String> = args[1..].iter().map(local).collect();
    let server = Server::start_with(&serve.iter().map(String::as_str).collect::<Vec<_>>());

    assert_eq!(probe[0], "cutsim-server");
    assert_eq!(after(probe, "--grpc-addr"), "127.0.0.1:50051", "the probe dials the pod's own gRPC port");
    let run: Vec<String> = probe[1..].iter().map(local).map(|a| a.replace("127.0.0.1:50051", &server.grpc)).collect();
    let out = Command::new(server_binary()).args(&run).output().unwrap();
    assert!(out.status.success(), "the probe {run:?} fails: {}{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    // Without the name, the probe checks 127.0.0.1, which the certificate does not carry.
    let without_name: Vec<String> = run.iter().take_while(|a| *a != "--tls-domain").cloned().collect();
    let out = Command::new(server_binary()).args(&without_name).output().unwrap();
    assert_eq!(out.status.code(), Some(1), "a certificate for {name} only must not pass for 127.0.0.1");
}

/// Operators by client certificate (mTLS): a certificate the operators' CA signed makes
/// its holder an operator without a token; clients without one are still served as
/// before (trainees' browsers have none) but cannot manage sessions.
#[tokio::test(flavor = "multi_thread")]
async fn a_client_certificate_from_the_operators_ca_makes_an_operator() {
    use rcgen::{BasicConstraints, CertificateParams, IsCa, KeyPair};
    let dir = TempDir::new("mtls");
    let ca_key = KeyPair::generate().unwrap();
    let mut ca_params = CertificateParams::new(Vec::<String>::new()).unwrap();
    ca_params.is_ca = IsCa::Ca(BasicConstraints::Unconstrained);
    let ca = ca_params.self_signed(&ca_key).unwrap();
    let issuer = rcgen::Issuer::new(ca_params, ca_key);
    let server_key = KeyPair::generate().unwrap();
    let server_cert = CertificateParams::new(vec!["127.0.0.1".to_string(), "localhost".to_string()]).unwrap().signed_by(&server_key, &issuer).unwrap();
    let client_key = KeyPair::generate().unwrap();
    let client_cert = CertificateParams::new(vec!["operator.sim-lab".to_string()]).unwrap().signed_by(&client_key, &issuer).unwrap();
    let write = |name: &str, text: String| {
        std::fs::write(dir.0.join(name), text).unwrap();
        dir.0.join(name).display().to_string()
    };
    let (ca_pem, cert_pem, key_pem) = (write("ca.pem", ca.pem()), write("cert.pem", server_cert.pem()), write("key.pem", server_key.serialize_pem()));
    let server = Server::start_with(&["--no-session", "--tls-cert", &cert_pem, "--tls-key", &key_pem, "--tls-client-ca", &ca_pem]);

    let url = format!("https://{}", server.grpc);
    let tls = tonic::transport::ClientTlsConfig::new().ca_certificate(tonic::transport::Certificate::from_pem(ca.pem()));
    let with_cert = tls.clone().identity(tonic::transport::Identity::from_pem(client_cert.pem(), client_key.serialize_pem()));
    let connect = |config: tonic::transport::ClientTlsConfig| {
        let url = url.clone();
        async move { SessionsClient::new(tonic::transport::Endpoint::from_shared(url).unwrap().tls_config(config).unwrap().connect().await.expect("TLS connects")) }
    };
    let request = || pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: pb::SessionMode::Lockstep as i32, label: "mtls".into() };

    // Without a certificate: connected, but not an operator.
    let mut anonymous = connect(tls.clone()).await;
    let refused = anonymous.create_session(request()).await.unwrap_err();
    assert_eq!(refused.code(), tonic::Code::Unauthenticated, "{}", refused.message());
    // With the CA's certificate: an operator, no token needed.
    let mut certified = connect(with_cert).await;
    let created = certified.create_session(request()).await.expect("a certified operator creates").into_inner();
    let listed = certified.list_sessions(pb::ListSessionsRequest {}).await.expect("and lists").into_inner();
    assert_eq!(listed.sessions.len(), 1);
    // The token still works without a certificate.
    anonymous.list_sessions(operator(pb::ListSessionsRequest {})).await.expect("an operator token over TLS");
    assert_eq!(created.session.unwrap().scene, "skin-patch");
    let _ = OPERATOR;
}
