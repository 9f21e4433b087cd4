//! Who may do what, through the real binary: anonymous clients cannot create, list or
//! close sessions; operators can, and close anyone's; nothing anonymous leaks names or
//! paths; every page carries a strict CSP; WebSocket upgrades from foreign pages are
//! refused; development mode opens loopback only, and says so.

use std::process::Command;

use cutsim_proto::v1 as pb;
use tokio_tungstenite::tungstenite::client::IntoClientRequest;
use tonic::Code;

use crate::harness::*;

fn create_request(label: &str) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: pb::SessionMode::Lockstep as i32, label: label.into() }
}

#[tokio::test]
async fn anonymous_clients_cannot_create_list_or_close_and_operators_can() {
    let server = Server::start();
    let mut client = server.sessions().await;

    // gRPC: no token, or a session's token, is not an operator.
    let refused = client.create_session(create_request("anonymous")).await.unwrap_err();
    assert_eq!(refused.code(), Code::Unauthenticated, "{}", refused.message());
    assert!(refused.message().contains("operator token"), "{}", refused.message());
    assert_eq!(client.list_sessions(pb::ListSessionsRequest {}).await.unwrap_err().code(), Code::Unauthenticated);
    let a = client.create_session(operator(create_request("Dr. Trainee Alice"))).await.expect("an operator creates").into_inner();
    let a_id = a.session.as_ref().unwrap().id.clone();
    let b = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let close = |id: &str| pb::CloseSessionRequest { session_id: id.into() };
    assert_eq!(client.close_session(close(&a_id)).await.unwrap_err().code(), Code::Unauthenticated);
    assert_eq!(client.close_session(authed(close(&a_id), &b.control)).await.unwrap_err().code(), Code::Unauthenticated, "another session's token");
    assert_eq!(client.list_sessions(authed(pb::ListSessionsRequest {}, &b.control)).await.unwrap_err().code(), Code::Unauthenticated);
    // An operator watches any session without its tokens.
    client.get_session(operator(pb::GetSessionRequest { session_id: a_id.clone(), with_state_hash: false })).await.expect("an operator watches");

    // HTTP: the session list, one session, closing, recordings.
    let http = &server.http;
    assert_eq!(http_request(http, "GET", "/api/sessions", None).await.0, 401);
    assert_eq!(http_request(http, "GET", "/api/sessions", Some(&b.control)).await.0, 401);
    let (status, list) = http_request(http, "GET", "/api/sessions", Some(OPERATOR)).await;
    assert_eq!(status, 200);
    assert!(list.contains("Dr. Trainee Alice"), "operators see labels: {list}");
    assert_eq!(http_request(http, "GET", &format!("/api/sessions/{a_id}"), None).await.0, 401);
    assert_eq!(http_request(http, "GET", &format!("/api/sessions/{a_id}"), Some(&a.observe_token)).await.0, 200);
    assert_eq!(http_request(http, "GET", "/api/recordings", None).await.0, 401);
    assert_eq!(http_request(http, "GET", "/api/recordings", Some(OPERATOR)).await.0, 200);
    assert_eq!(http_request(http, "DELETE", &format!("/api/sessions/{a_id}"), None).await.0, 401);
    assert_eq!(http_request(http, "DELETE", &format!("/api/sessions/{a_id}"), Some(&a.observe_token)).await.0, 403);

    // Nothing anonymous names a trainee or a file.
    let (status, metrics) = http_request(http, "GET", "/metrics", None).await;
    assert_eq!(status, 200);
    assert!(!metrics.contains("Alice") && !metrics.contains("skin-patch") && !metrics.contains(".json") && !metrics.contains('/'), "{metrics}");
    let (_, health) = http_request(http, "GET", "/healthz", None).await;
    assert!(!health.contains("Alice"), "{health}");

    // An operator closes anyone's session (gRPC and HTTP); a session's control token closes its own.
    client.close_session(operator(close(&a_id))).await.expect("an operator closes any session");
    assert_eq!(http_request(http, "DELETE", &format!("/api/sessions/{}", b.id), Some(OPERATOR)).await.0, 204);
    let c = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    client.close_session(authed(close(&c.id), &c.control)).await.expect("its control token closes it");
    assert!(client.list_sessions(operator(pb::ListSessionsRequest {})).await.unwrap().into_inner().sessions.is_empty());
}

#[tokio::test]
async fn every_response_carries_a_strict_csp_and_security_headers() {
    let server = Server::start();
    let page = http_call(&server.http, "GET", "/", &[], "").await;
    assert_eq!(page.status, 200);
    let csp = page.header("content-security-policy").expect("a CSP on the page");
    assert!(csp.contains("default-src 'none'") && csp.contains("script-src 'self' 'sha256-") && csp.contains("frame-ancestors 'none'"), "{csp}");
    assert!(!csp.contains("unsafe-inline") && !csp.contains("unsafe-eval"), "{csp}");
    for (name, value) in [("x-content-type-options", "nosniff"), ("x-frame-options", "DENY"), ("referrer-policy", "no-referrer")] {
        assert_eq!(page.header(name), Some(value), "{name}");
    }
    // The import map's hash is the one the CSP allows: the page's only inline script.
    let html = std::fs::read_to_string(repo("web-viewer/index.html")).unwrap();
    assert_eq!(html.matches("<script").count() - html.matches("<script type=\"module\" src=").count(), 1, "one inline script (the import map)");
    // Errors and API answers carry them too, and the API is not cached.
    let api = http_call(&server.http, "GET", "/api/sessions", &[("cutsim-token", OPERATOR)], "").await;
    assert!(api.header("content-security-policy").is_some());
    assert_eq!(api.header("cache-control"), Some("no-store"));
    let missing = http_call(&server.http, "GET", "/no-such-page", &[], "").await;
    assert_eq!(missing.status, 404);
    assert!(missing.header("content-security-policy").is_some());
}

#[tokio::test]
async fn websocket_upgrades_from_foreign_pages_are_refused() {
    let server = Server::start();
    let s = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let upgrade = |origin: Option<String>| {
        let url = format!("ws://{}/ws/sessions/{}?token={}", server.http, s.id, s.observe);
        async move {
            let mut request = url.into_client_request().unwrap();
            if let Some(origin) = origin {
                request.headers_mut().insert("origin", origin.parse().unwrap());
            }
            tokio_tungstenite::connect_async(request).await.map(|_| ())
        }
    };
    match upgrade(Some("http://evil.example".into())).await {
        Err(tokio_tungstenite::tungstenite::Error::Http(response)) => assert_eq!(response.status(), 403),
        other => panic!("a foreign page's upgrade must be refused with 403, got {other:?}"),
    }
    upgrade(Some(format!("http://{}", server.http))).await.expect("the server's own page");
    upgrade(None).await.expect("a client that is not a browser sends no Origin");
}

#[test]
fn development_mode_opens_loopback_only_and_says_so() {
    // Off loopback it is refused before anything listens.
    let out = Command::new(server_binary()).args(["serve", "--dev", "--no-session", "--grpc-addr", "0.0.0.0:0", "--http-addr", "127.0.0.1:0"]).output().unwrap();
    assert_eq!(out.status.code(), Some(2));
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(stderr.contains("development mode needs both listeners on loopback"), "{stderr}");

    // On loopback, anonymous local callers are operators, with a loud warning.
    let server = Server::start_with(&["--no-session", "--dev"]);
    let runtime = tokio::runtime::Runtime::new().unwrap();
    runtime.block_on(async {
        let created = server.sessions().await.create_session(create_request("dev")).await.expect("loopback is an operator in development mode");
        assert!(created.into_inner().session.is_some());
    });
    let mut printed = Vec::new();
    while let Ok(line) = server._lines.recv_timeout(std::time::Duration::from_secs(5)) {
        let warned = line.starts_with("WARNING: DEVELOPMENT MODE");
        printed.push(line);
        if warned {
            return;
        }
    }
    panic!("no development-mode warning in {printed:?}");
}

#[test]
fn weak_operator_tokens_and_bad_policies_stop_the_server_naming_them() {
    let dir = TempDir::new("weak-token");
    for (config, expected) in [
        (r#"{"operator_tokens": {"lab": "short"}}"#, "operator token \"lab\" has 5 characters; at least 16"),
        (r#"{"recordings": {"sync_every_ms": 0}}"#, "recordings.sync_every_ms: must be within [5, 3600000], got 0"),
        (r#"{"limits": {"stale_command_ms": 1}}"#, "limits.stale_command_ms: must be within [5, 60000], got 1"),
    ] {
        let path = dir.0.join("server.json");
        std::fs::write(&path, config).unwrap();
        let out = Command::new(server_binary())
            .args(["serve", "--no-session", "--grpc-addr", "127.0.0.1:0", "--http-addr", "127.0.0.1:0", "--config"])
            .arg(&path)
            .env_remove("CUTSIM_OPERATOR_TOKEN")
            .output()
            .unwrap();
        assert_eq!(out.status.code(), Some(2), "{config}");
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert!(stderr.contains(expected), "{config}: {stderr}");
    }
}
