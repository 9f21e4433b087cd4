//! Bad tokens, observers trying to control, NaN and far-away poses, oversized messages,
//! unknown sessions and bad scripts get the right status, and the session survives.

use std::time::Duration;

use cutsim_proto::v1 as pb;
use tonic::Code;

use crate::harness::*;
use crate::haptics::open;
use crate::sessions::http_get;

async fn step_of(server: &Server, s: &Created) -> u64 {
    server.sessions().await.get_session(authed(pb::GetSessionRequest { session_id: s.id.clone(), with_state_hash: false }, &s.observe)).await.unwrap().into_inner().step
}

/// Sends one command on a fresh haptic stream and returns how the stream ended.
async fn send_one(server: &Server, s: &Created, token: &str, command: pb::ToolCommand) -> Code {
    send_one_status(server, s, token, command).await.0
}

/// [`send_one`] with the status's message.
async fn send_one_status(server: &Server, s: &Created, token: &str, command: pb::ToolCommand) -> (Code, String) {
    let (tx, response) = open(server, &s.id, token).await;
    let mut stream = match response {
        Ok(stream) => stream,
        Err(status) => return (status.code(), status.message().into()),
    };
    tx.send(command).await.unwrap();
    loop {
        match tokio::time::timeout(Duration::from_secs(5), stream.message()).await {
            Ok(Ok(Some(_))) => continue,
            Ok(Ok(None)) => return (Code::Ok, String::new()),
            Ok(Err(status)) => return (status.code(), status.message().into()),
            Err(_) => return (Code::DeadlineExceeded, String::new()),
        }
    }
}

#[tokio::test]
async fn bad_requests_get_the_right_status_and_the_session_survives() {
    let server = Server::start();
    let s = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    let mut sessions = server.sessions().await;
    let get = |token: &str| authed(pb::GetSessionRequest { session_id: s.id.clone(), with_state_hash: false }, token);

    // Tokens.
    assert_eq!(sessions.get_session(get("0123456789abcdef0123456789abcdef")).await.unwrap_err().code(), Code::Unauthenticated);
    assert_eq!(sessions.get_session(pb::GetSessionRequest { session_id: s.id.clone(), with_state_hash: false }).await.unwrap_err().code(), Code::Unauthenticated);

    // Unknown session.
    let unknown = sessions.get_snapshot(authed(pb::GetSnapshotRequest { session_id: "nope".into() }, &s.observe)).await.unwrap_err();
    assert_eq!(unknown.code(), Code::NotFound);
    assert!(unknown.message().contains("nope"), "{}", unknown.message());
    let (_, response) = open(&server, "nope", &s.control).await;
    assert_eq!(response.unwrap_err().code(), Code::NotFound);

    // Observers cannot move a tool or run a script.
    let probe = |z: f64| pb::ToolCommand { tool: 1, pose: Some(pose(0.0, 0.0, z)), active: true, cut: false, client_time_ns: 1, feedback_every_steps: 1, grip: None };
    assert_eq!(send_one(&server, &s, &s.observe, probe(0.01)).await, Code::PermissionDenied);
    let script = example_script("skin-patch-straight.json");
    assert_eq!(run_script(&server, &Created { control: s.observe.clone(), ..clone_created(&s) }, &script).await.unwrap_err().code(), Code::PermissionDenied);

    // Bad poses end the stream with INVALID_ARGUMENT, and nothing else.
    let nan = pb::ToolCommand { pose: Some(pose(f64::NAN, 0.0, 0.0)), ..probe(0.0) };
    assert_eq!(send_one(&server, &s, &s.control, nan).await, Code::InvalidArgument);
    assert_eq!(send_one(&server, &s, &s.control, probe(25.0)).await, Code::InvalidArgument, "25 m away");
    let tilted = pb::ToolCommand { pose: Some(pb::Pose { orientation: Some(pb::Quaternion { w: 2.0, x: 0.0, y: 0.0, z: 0.0 }), ..pose(0.0, 0.0, 0.0) }), ..probe(0.0) };
    assert_eq!(send_one(&server, &s, &s.control, tilted).await, Code::InvalidArgument, "not a unit quaternion");
    assert_eq!(send_one(&server, &s, &s.control, pb::ToolCommand { tool: 7, ..probe(0.01) }).await, Code::InvalidArgument);
    // A gripper's squeeze is a fraction of the forceps' grip (tool 2).
    for grip in [1.5, -0.2, f64::NAN] {
        let (code, message) = send_one_status(&server, &s, &s.control, pb::ToolCommand { tool: 2, grip: Some(grip), ..probe(0.01) }).await;
        assert_eq!(code, Code::InvalidArgument, "grip {grip}: {message}");
        assert!(message.contains("grip of tool 2 (forceps)") && message.contains("from 0 to 1"), "{message}");
    }

    // Oversized messages: a scene above the scene limit, and a message above the gRPC limit.
    let big_scene = format!("{{\"name\": \"x\", \"description\": \"{}\"}}", "a".repeat(2 << 20));
    let e = sessions
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(big_scene)), mode: 0, label: String::new() }))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted, "{}", e.message());
    assert!(e.message().contains("at most 1048576"), "{}", e.message());
    let huge = "a".repeat(5 << 20);
    let e = sessions
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(huge)), mode: 0, label: String::new() }))
        .await
        .unwrap_err();
    assert!(matches!(e.code(), Code::ResourceExhausted | Code::OutOfRange), "{:?}: {}", e.code(), e.message());

    // Bad scenes and scripts name the JSON path.
    let e = sessions
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson("{\"name\": \"x\", \"model\": {\"msm\": {\"geometry\": 5}}}".into())), mode: 0, label: String::new() }))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("model.msm.geometry"), "{}", e.message());
    // No path traversal: a scene name is a name, and a scene sent inline reads only the
    // shared data directory — not a file of the server's, even one that exists.
    let existing = repo("server/scenes/skin-patch.json");
    for name in ["../secret", "../../server/scenes/skin-patch.json", existing.to_str().unwrap(), "skin-patch.json"] {
        let e = sessions
            .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName(name.into())), mode: 0, label: String::new() }))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{name}");
        assert!(e.message().contains("not a path") || e.message().contains("only letters"), "{name}: {}", e.message());
    }
    let mesh = repo("tests/e2e/data/does-not-matter.obj");
    for path in ["/etc/passwd".to_owned(), "data:../../etc/passwd".to_owned(), mesh.display().to_string(), "../server/scenes/x.obj".to_owned()] {
        let json = format!(
            r#"{{ "name": "probe", "model": {{ "branched-grid": {{ "volume": {{ "mesh": {{ "path": {path:?}, "voxel_size_m": 0.002 }} }}, "materials": [ {{ "label": 1, "young_pa": 1000, "density_kg_per_m3": 1000 }} ], "level": 1 }} }}, "tools": [] }}"#
        );
        let e = sessions
            .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(json)), mode: 0, label: String::new() }))
            .await
            .unwrap_err();
        assert_eq!(e.code(), Code::InvalidArgument, "{path}");
        assert!(e.message().contains("may read only the shared data directory"), "{path}: {}", e.message());
    }
    let bad_script = script.replace("\"tool\": \"scalpel\"", "\"tool\": \"laser\"");
    let e = run_script(&server, &s, &bad_script).await.unwrap_err();
    assert_eq!(e.code(), Code::InvalidArgument);
    assert!(e.message().contains("tools[0].tool"), "{}", e.message());

    // WebSocket handshakes: no token or a wrong one → 401, unknown session → 404, a bad
    // rate → 400.
    assert_eq!(ws_status(&format!("ws://{}/ws/sessions/{}", server.http, s.id)).await, 401);
    assert_eq!(ws_status(&format!("ws://{}/ws/sessions/{}?token=wrong", server.http, s.id)).await, 401);
    assert_eq!(ws_status(&format!("ws://{}/ws/sessions/nope?token={}", server.http, s.observe)).await, 404);
    assert_eq!(ws_status(&format!("ws://{}/ws/sessions/{}?token={}&rate_hz=5000", server.http, s.id, s.observe)).await, 400);
    // A plain GET that is not a WebSocket handshake is refused too.
    assert_eq!(http_get(&server.http, &format!("/ws/sessions/{}?token={}", s.id, s.observe)).await.0, 400);

    // The session kept running through all of it.
    let before = step_of(&server, &s).await;
    wait_for_step_past(&server, &s, before + 100).await;
    let info = sessions.get_session(get(&s.observe)).await.unwrap().into_inner();
    assert_eq!(info.status, pb::SessionStatus::Running as i32);
    assert_eq!(info.counters.unwrap().blowups_contained, 0);
}

/// The HTTP status a WebSocket handshake is refused with (101 if it is accepted).
async fn ws_status(url: &str) -> u16 {
    match tokio_tungstenite::connect_async(url).await {
        Ok(_) => 101,
        Err(tokio_tungstenite::tungstenite::Error::Http(response)) => response.status().as_u16(),
        Err(e) => panic!("handshake failed without a status: {e}"),
    }
}

fn clone_created(s: &Created) -> Created {
    Created { id: s.id.clone(), control: s.control.clone(), observe: s.observe.clone(), info: s.info.clone() }
}

#[tokio::test]
async fn the_session_limit_is_refused_clearly() {
    let dir = TempDir::new("config");
    let config = dir.0.join("config.json");
    std::fs::write(&config, r#"{"limits": {"max_sessions": 2}}"#).unwrap();
    let server = Server::start_with(&["--no-session", "--config", config.to_str().unwrap()]);
    create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let e = server
        .sessions()
        .await
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: 2, label: String::new() }))
        .await
        .unwrap_err();
    assert_eq!(e.code(), Code::ResourceExhausted);
    assert!(e.message().contains("maximum of 2 sessions"), "{}", e.message());
}

/// A gRPC channel whose connections come from `source` (another loopback address is
/// another client to the server).
async fn channel_from(server: &Server, source: &str) -> tonic::transport::Channel {
    tonic::transport::Endpoint::from_shared(format!("http://{}", server.grpc)).unwrap().local_address(Some(source.parse().unwrap())).connect().await.expect("gRPC connects")
}

async fn http_status_from(server: &Server, source: &str, path: &str) -> u16 {
    http_status_with(server, source, path, "").await
}

/// An HTTP GET of `path` from `source` with `headers` (each ending in CRLF): the status.
async fn http_status_with(server: &Server, source: &str, path: &str, headers: &str) -> u16 {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let socket = tokio::net::TcpSocket::new_v4().unwrap();
    socket.bind(format!("{source}:0").parse().unwrap()).unwrap();
    let mut stream = socket.connect(server.http.parse().unwrap()).await.unwrap();
    stream.write_all(format!("GET {path} HTTP/1.1\r\nHost: {}\r\n{headers}Connection: close\r\n\r\n", server.http).as_bytes()).await.unwrap();
    let mut text = String::new();
    stream.read_to_string(&mut text).await.unwrap();
    text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0)
}

#[tokio::test]
async fn a_client_over_its_rate_is_refused_and_others_are_not() {
    use cutsim_proto::v1::sessions_client::SessionsClient;
    let config = TempDir::new("rate-config");
    let path = config.0.join("server.json");
    let limits = r#"{"limits": {"requests_per_second_per_client": 1, "request_burst_per_client": 5, "tool_commands_per_second": 50}}"#;
    std::fs::write(&path, limits).unwrap();
    let server = Server::start_with(&["--no-session", "--config", path.to_str().unwrap()]);
    let (noisy, calm) = ("127.0.0.1", "127.0.0.2");

    let mut calm_sessions = SessionsClient::new(channel_from(&server, calm).await);
    let created = calm_sessions
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneName("skin-patch".into())), mode: pb::SessionMode::Realtime as i32, label: "rate".into() }))
        .await
        .unwrap()
        .into_inner();

    // The noisy client spends its burst of 5, then is refused (gRPC and HTTP alike).
    let mut noisy_sessions = SessionsClient::new(channel_from(&server, noisy).await);
    for _ in 0..5 {
        noisy_sessions.list_sessions(operator(pb::ListSessionsRequest {})).await.expect("within the burst");
    }
    let refused = noisy_sessions.list_sessions(operator(pb::ListSessionsRequest {})).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(refused.message().contains("rate limit: 127.0.0.1 sends more than 1 requests per second") && refused.message().contains("retry in"), "{}", refused.message());
    assert_eq!(http_status_from(&server, noisy, "/healthz").await, 429);
    // The limit stands in front of every gRPC service, health included.
    let mut noisy_health = tonic_health::pb::health_client::HealthClient::new(channel_from(&server, noisy).await);
    let refused = noisy_health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted, "{}", refused.message());

    // The other client is served.
    calm_sessions.list_sessions(operator(pb::ListSessionsRequest {})).await.expect("another client is not limited");
    let mut calm_health = tonic_health::pb::health_client::HealthClient::new(channel_from(&server, calm).await);
    calm_health.check(tonic_health::pb::HealthCheckRequest { service: String::new() }).await.expect("health answers the other client");
    assert_eq!(http_status_from(&server, calm, "/healthz").await, 200);

    // A haptic stream flooding commands (far over 50/s, past its 100 saved up) is ended
    // with RESOURCE_EXHAUSTED; the session keeps stepping.
    let id = created.session.as_ref().unwrap().id.clone();
    let (tx, feedback) = crate::haptics::open_on(channel_from(&server, calm).await, &id, &created.control_token).await;
    let mut feedback = feedback.expect("the stream opens");
    let probe = pb::ToolCommand { tool: 1, pose: Some(pose(0.0, 0.0, 0.05)), active: true, cut: false, client_time_ns: 1, feedback_every_steps: 1, grip: None };
    tokio::spawn(async move {
        for _ in 0..300 {
            if tx.send(probe).await.is_err() {
                break;
            }
        }
    });
    let ended = loop {
        match tokio::time::timeout(Duration::from_secs(10), feedback.message()).await.expect("the stream ends") {
            Ok(Some(_)) => continue,
            Ok(None) => panic!("the flood must be refused, not accepted"),
            Err(status) => break status,
        }
    };
    assert_eq!(ended.code(), Code::ResourceExhausted, "{}", ended.message());
    assert!(ended.message().contains("more than 50 tool commands per second"), "{}", ended.message());
    tokio::time::sleep(Duration::from_millis(1100)).await;
    let info = calm_sessions.get_session(authed(pb::GetSessionRequest { session_id: id, with_state_hash: false }, &created.observe_token)).await.unwrap().into_inner();
    assert!(info.step > 0);
}

async fn http_status_forwarded(server: &Server, source: &str, forwarded_for: &str) -> u16 {
    http_status_with(server, source, "/healthz", &format!("X-Forwarded-For: {forwarded_for}\r\n")).await
}

/// Behind a trusted proxy each forwarded client has its own rate; anyone else's
/// X-Forwarded-For is ignored (a client cannot dodge its limit by inventing addresses).
#[tokio::test]
async fn a_trusted_proxy_forwards_for_its_clients_and_others_cannot_pretend() {
    use cutsim_proto::v1::sessions_client::SessionsClient;
    let config = TempDir::new("proxy-config");
    let path = config.0.join("server.json");
    std::fs::write(&path, r#"{"limits": {"requests_per_second_per_client": 1, "request_burst_per_client": 3, "trusted_proxies": ["127.0.0.1/32", "fd00::/8"]}}"#).unwrap();
    let server = Server::start_with(&["--no-session", "--config", path.to_str().unwrap()]);
    let (proxy, stranger) = ("127.0.0.1", "127.0.0.2");

    // Through the proxy (HTTP): one forwarded client spends its burst; the next is served.
    for _ in 0..3 {
        assert_eq!(http_status_forwarded(&server, proxy, "203.0.113.1").await, 200);
    }
    assert_eq!(http_status_forwarded(&server, proxy, "203.0.113.1").await, 429);
    assert_eq!(http_status_forwarded(&server, proxy, "198.51.100.7, 203.0.113.2").await, 200, "the nearest hop is the client");

    // gRPC through the proxy: the metadata names the client, and the refusal names it too.
    let mut via_proxy = SessionsClient::new(channel_from(&server, proxy).await);
    let forwarded = |who: &str| {
        let mut request = operator(pb::ListSessionsRequest {});
        request.metadata_mut().insert("x-forwarded-for", who.parse().unwrap());
        request
    };
    for _ in 0..3 {
        via_proxy.list_sessions(forwarded("203.0.113.50")).await.expect("within the forwarded client's burst");
    }
    let refused = via_proxy.list_sessions(forwarded("203.0.113.50")).await.unwrap_err();
    assert_eq!(refused.code(), Code::ResourceExhausted);
    assert!(refused.message().contains("203.0.113.50"), "{}", refused.message());
    via_proxy.list_sessions(forwarded("203.0.113.51")).await.expect("another forwarded client");

    // A peer that is not a trusted proxy is its own client, whatever it claims.
    let mut statuses = Vec::new();
    for k in 0..4 {
        statuses.push(http_status_forwarded(&server, stranger, &format!("192.0.2.{k}")).await);
    }
    assert_eq!(statuses, [200, 200, 200, 429], "an untrusted peer's X-Forwarded-For is ignored");
}

#[test]
fn bad_limits_stop_the_server_naming_the_setting() {
    let dir = TempDir::new("bad-limits");
    for (limits, expected) in [
        (r#"{"trusted_proxies": ["10.0.0.0/8", "10.0.0/8"]}"#, "limits.trusted_proxies[1]: \"10.0.0/8\" is not an address or a CIDR block"),
        (r#"{"requests_per_second_per_client": 0}"#, "limits.requests_per_second_per_client: must be a finite number ≥ 1, got 0"),
    ] {
        let path = dir.0.join("server.json");
        std::fs::write(&path, format!(r#"{{"limits": {limits}}}"#)).unwrap();
        let out = std::process::Command::new(server_binary()).args(["serve", "--no-session", "--config", path.to_str().unwrap()]).output().unwrap();
        let stderr = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{stderr}");
        assert!(stderr.contains(expected) && stderr.contains("server.json"), "{stderr}");
    }
}
