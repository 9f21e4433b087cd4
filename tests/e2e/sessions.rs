//! Session lifecycle, reflection, health and the HTTP session list.

use cutsim_proto::v1 as pb;
use tonic_health::pb::health_check_response::ServingStatus;
use tonic_health::pb::health_client::HealthClient;
use tonic_reflection::pb::v1::server_reflection_client::ServerReflectionClient;
use tonic_reflection::pb::v1::server_reflection_request::MessageRequest;
use tonic_reflection::pb::v1::server_reflection_response::MessageResponse;

use crate::harness::*;

#[tokio::test]
async fn create_list_get_close() {
    let server = Server::start();
    let mut client = server.sessions().await;
    let a = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    assert_eq!(a.control.len(), 32);
    assert_ne!(a.control, a.observe);
    assert_eq!(a.info.scene, "skin-patch");
    assert_eq!(a.info.model, "msm");
    assert_eq!(a.info.rate_hz, 1000.0);
    assert_eq!(a.info.tools.iter().map(|t| t.name.as_str()).collect::<Vec<_>>(), ["scalpel", "probe", "forceps"]);
    assert_eq!((a.info.tools[0].radius_m, a.info.tools[0].width_m), (0.0005, 0.0), "a cylinder has no plate");
    // A blade's plate is described to clients: width, thickness, the way its edge faces.
    let plate = create_inline(&server, inline("skin-patch", |s| s["tools"][0]["shape"] = serde_json::json!({ "blade": { "width_m": 0.003, "thickness_m": 0.0004, "length_m": 0.04 } })), pb::SessionMode::Lockstep).await.unwrap();
    let blade = &plate.info.tools[0];
    assert_eq!((blade.width_m, blade.thickness_m, blade.edge.as_ref().map(|e| (e.x, e.y, e.z))), (0.003, 0.0004, Some((1.0, 0.0, 0.0))));
    assert!((blade.radius_m - 0.0015f64.hypot(0.0002)).abs() < 1e-12, "bounded by its corners: {}", blade.radius_m);
    client.close_session(operator(pb::CloseSessionRequest { session_id: plate.id.clone() })).await.unwrap();

    // An inline scene works too.
    let text = std::fs::read_to_string(repo("server/scenes/skin-patch.json")).unwrap().replace("\"skin-patch\"", "\"inline-patch\"");
    let b = client
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(text)), mode: pb::SessionMode::Lockstep as i32, label: "b".into() }))
        .await
        .unwrap()
        .into_inner();
    let b_info = b.session.unwrap();
    assert_eq!(b_info.scene, "inline-patch");

    let list = client.list_sessions(operator(pb::ListSessionsRequest {})).await.unwrap().into_inner();
    let ids: Vec<_> = list.sessions.iter().map(|s| s.id.clone()).collect();
    assert!(ids.contains(&a.id) && ids.contains(&b_info.id));

    // The realtime session steps; the lockstep one waits.
    wait_for_step_past(&server, &a, 100).await;
    let got = client.get_session(authed(pb::GetSessionRequest { session_id: a.id.clone(), with_state_hash: false }, &a.observe)).await.unwrap().into_inner();
    assert_eq!(got.status, pb::SessionStatus::Running as i32);
    let idle = client.get_session(authed(pb::GetSessionRequest { session_id: b_info.id.clone(), with_state_hash: false }, &b.observe_token)).await.unwrap().into_inner();
    assert_eq!((idle.step, idle.status), (0, pb::SessionStatus::Idle as i32));

    // The JSON list shows both to an operator.
    let (status, json) = http_request(&server.http, "GET", "/api/sessions", Some(OPERATOR)).await;
    assert_eq!(status, 200, "{json}");
    assert!(json.contains(&a.id) && json.contains(&b_info.id), "{json}");
    let metrics = reqwest_like_get(&server.http, "/metrics").await;
    assert!(metrics.contains(&format!("cutsim_steps_total{{session=\"{}\"}}", a.id)), "{metrics}");
    // The solver's background work is accounted per session (zero on the skin).
    for family in ["cutsim_solver_waits_total", "cutsim_solver_factor_failures_total"] {
        assert!(metrics.contains(&format!("{family}{{session=\"{}\"}} 0", a.id)), "{family}: {metrics}");
    }

    // Observers cannot close; controllers can.
    let denied = client.close_session(authed(pb::CloseSessionRequest { session_id: a.id.clone() }, &a.observe)).await.unwrap_err();
    assert_eq!(denied.code(), tonic::Code::PermissionDenied);
    client.close_session(authed(pb::CloseSessionRequest { session_id: a.id.clone() }, &a.control)).await.unwrap();
    let list = client.list_sessions(operator(pb::ListSessionsRequest {})).await.unwrap().into_inner();
    assert_eq!(list.sessions.len(), 1);
    let gone = client.get_session(authed(pb::GetSessionRequest { session_id: a.id.clone(), with_state_hash: false }, &a.observe)).await.unwrap_err();
    assert_eq!(gone.code(), tonic::Code::NotFound);
}

/// A plain HTTP/1.1 GET over a TCP socket (no HTTP client dependency needed).
pub async fn reqwest_like_get(addr: &str, path: &str) -> String {
    let (status, body) = http_get(addr, path).await;
    assert_eq!(status, 200, "GET {path}: {body}");
    body
}

pub async fn http_get(addr: &str, path: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream.write_all(format!("GET {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\n\r\n").as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8_lossy(&buf).into_owned();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    let body = text.split("\r\n\r\n").skip(1).collect::<Vec<_>>().join("\r\n\r\n");
    (status, body)
}

#[tokio::test]
async fn reflection_lists_services_and_health_reports_serving() {
    let server = Server::start();
    let mut reflection = ServerReflectionClient::new(server.channel().await);
    let request = tonic_reflection::pb::v1::ServerReflectionRequest { host: String::new(), message_request: Some(MessageRequest::ListServices(String::new())) };
    let mut responses = reflection.server_reflection_info(tokio_stream_once(request)).await.unwrap().into_inner();
    let response = responses.message().await.unwrap().unwrap();
    let Some(MessageResponse::ListServicesResponse(list)) = response.message_response else { panic!("a service list") };
    let names: Vec<String> = list.service.into_iter().map(|s| s.name).collect();
    for expected in ["cutsim.v1.Sessions", "cutsim.v1.Haptics", "cutsim.v1.Scripts", "grpc.health.v1.Health"] {
        assert!(names.iter().any(|n| n == expected), "{expected} in {names:?}");
    }
    let mut health = HealthClient::new(server.channel().await);
    for service in ["", "cutsim.v1.Sessions", "cutsim.v1.Haptics", "cutsim.v1.Scripts"] {
        let status = health.check(tonic_health::pb::HealthCheckRequest { service: service.into() }).await.unwrap().into_inner().status;
        assert_eq!(status, ServingStatus::Serving as i32, "{service:?}");
    }
}

fn tokio_stream_once<T: Send + 'static>(item: T) -> impl futures_util::Stream<Item = T> + Send {
    futures_util::stream::iter(std::iter::once(item))
}

/// `"fidelity": "auto"`: the session reports the level (and, under a multirate schedule,
/// the deformation rate) its calibration chose, and its recording pins them so that a
/// replay builds the same grid.
#[tokio::test]
async fn an_auto_fidelity_session_reports_and_records_its_level() {
    let server = Server::start();
    let mut client = server.sessions().await;
    let text = std::fs::read_to_string(repo("server/scenes/u-tube.json")).unwrap();
    let auto = text.replace("\"level\": 3,", "\"level\": 1, \"fidelity\": \"auto\", \"step_budget_ms\": 1000,");
    assert_ne!(auto, text, "the u-tube scene changed shape");
    let created = client
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(auto)), mode: pb::SessionMode::Lockstep as i32, label: String::new() }))
        .await
        .unwrap()
        .into_inner();
    let info = created.session.unwrap();
    // Which level fits depends on this machine; the session says which it took.
    let level: u32 = info
        .fidelity
        .strip_prefix("fidelity auto: level ")
        .and_then(|rest| rest.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no level in {:?}", info.fidelity));
    assert!(info.fidelity.contains("error class"), "{}", info.fidelity);
    // The recording holds the scene pinned to that level.
    let recording = std::fs::read_to_string(server.recordings.0.join(format!("{}.jsonl", info.id))).unwrap();
    let header: serde_json::Value = serde_json::from_str(recording.lines().next().unwrap()).unwrap();
    let grid = &header["scene"]["model"]["branched-grid"];
    assert_eq!((grid["fidelity"].as_str(), grid["level"].as_u64()), (Some("fixed"), Some(u64::from(level))), "the recording pins the level: {header}");
    // Under a multirate schedule the deformation's rate is chosen too (at most every 20
    // haptic steps here), reported, and pinned beside the level.
    let multirate = text.replace("\"level\": 3,", r#""level": 1, "fidelity": "auto", "solver": { "preconditioner": "multigrid" }, "schedule": { "multirate": { "deformation_every_steps": 20 } },"#);
    let created = client
        .create_session(operator(pb::CreateSessionRequest { scene: Some(pb::create_session_request::Scene::SceneJson(multirate)), mode: pb::SessionMode::Lockstep as i32, label: String::new() }))
        .await
        .unwrap()
        .into_inner();
    let info = created.session.unwrap();
    assert!(info.fidelity.contains("haptic steps, the shortest period this level fits"), "{}", info.fidelity);
    let recording = std::fs::read_to_string(server.recordings.0.join(format!("{}.jsonl", info.id))).unwrap();
    let header: serde_json::Value = serde_json::from_str(recording.lines().next().unwrap()).unwrap();
    let grid = &header["scene"]["model"]["branched-grid"];
    let every = grid["schedule"]["multirate"]["deformation_every_steps"].as_u64().unwrap_or_else(|| panic!("no rate pinned: {header}"));
    assert!((2..=20).contains(&every), "{header}");
    assert_eq!(grid["fidelity"].as_str(), Some("fixed"), "{header}");
    assert!(info.fidelity.contains(&format!("deformation every {every} haptic steps")), "{}", info.fidelity);
    assert!((info.deformation_rate_hz - 1e3 / every as f64).abs() < 0.01, "{} Hz, every {every} steps", info.deformation_rate_hz);
    // A fixed scene reports nothing.
    let fixed = create(&server, "u-tube", pb::SessionMode::Lockstep).await;
    assert_eq!(fixed.info.fidelity, "");
}
