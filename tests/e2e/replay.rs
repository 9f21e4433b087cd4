//! Replay sessions: a recording played back with play, pause and seek reaches exactly the
//! recorded state, and viewers follow it.

use std::time::Duration;

use cutsim_proto::v1 as pb;

use crate::harness::*;
use crate::sessions::http_get;
use cutsim_load::viewer::Viewer;

const ADMIN: &str = "0123456789abcdef0123456789abcdef";

async fn http_post(addr: &str, path: &str, token: &str, body: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    let request = format!(
        "POST {path} HTTP/1.1\r\nHost: {addr}\r\nConnection: close\r\ncutsim-token: {token}\r\ncontent-type: application/json\r\ncontent-length: {}\r\n\r\n{body}",
        body.len()
    );
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut buf = Vec::new();
    stream.read_to_end(&mut buf).await.unwrap();
    let text = String::from_utf8_lossy(&buf).into_owned();
    let status = text.split_whitespace().nth(1).and_then(|s| s.parse().ok()).unwrap_or(0);
    (status, text.split("\r\n\r\n").nth(1).unwrap_or_default().to_owned())
}

async fn state(server: &Server, id: &str, token: &str) -> pb::SessionInfo {
    server.sessions().await.get_session(authed(pb::GetSessionRequest { session_id: id.into(), with_state_hash: true }, token)).await.unwrap().into_inner()
}

#[tokio::test]
async fn a_replayed_script_reaches_the_recorded_state_and_viewers_follow() {
    let dir = TempDir::new("admin");
    let config = dir.0.join("config.json");
    std::fs::write(&config, format!(r#"{{"admin_token": "{ADMIN}"}}"#)).unwrap();
    let server = Server::start_with(&["--no-session", "--config", config.to_str().unwrap()]);
    let recorded = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let report = run_script(&server, &recorded, &example_script("skin-patch-straight.json")).await.unwrap();

    // Recordings need the admin token.
    assert_eq!(http_get(&server.http, "/api/recordings").await.0, 401);
    let (status, list) = http_post(&server.http, "/api/recordings", ADMIN, "").await;
    assert_eq!(status, 405, "listing is a GET: {list}");
    let (status, body) = http_post(&server.http, &format!("/api/recordings/{}/replay", recorded.id), "wrong", "").await;
    assert_eq!(status, 401, "{body}");
    let (status, body) = http_post(&server.http, &format!("/api/recordings/{}/replay", recorded.id), ADMIN, "").await;
    assert_eq!(status, 201, "{body}");
    let created: serde_json::Value = serde_json::from_str(&body).unwrap();
    let id = created["session_id"].as_str().unwrap().to_owned();
    let control = created["control_token"].as_str().unwrap().to_owned();
    let observe = created["observe_token"].as_str().unwrap().to_owned();
    assert_eq!(created["total_steps"], 1500, "the script's steps");

    let mut viewer = Viewer::connect(&server.http, &id, &observe).await.unwrap();
    assert!(viewer.pump_until(Duration::from_secs(10), |v| v.replica.is_some()).await);
    let playback = viewer.hello.clone().unwrap().session.unwrap().playback.unwrap();
    assert_eq!((playback.step, playback.total_steps, playback.playing), (0, 1500, false));

    let post = |body: &'static str| {
        let (server_http, id, control) = (server.http.clone(), id.clone(), control.clone());
        async move { http_post(&server_http, &format!("/api/sessions/{id}/playback"), &control, body).await }
    };
    // Play in real time for a moment (until it has played 50 steps: the replay's thread
    // runs in the background class, slower on a busy machine), then pause.
    assert_eq!(post(r#"{"action": "play"}"#).await.0, 204);
    let deadline = std::time::Instant::now() + Duration::from_secs(20);
    while state(&server, &id, &observe).await.playback.unwrap().step <= 50 {
        assert!(std::time::Instant::now() < deadline, "the replay plays");
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    assert_eq!(post(r#"{"action": "pause"}"#).await.0, 204);
    let paused = state(&server, &id, &observe).await.playback.unwrap();
    assert!(paused.step > 50 && paused.step < 1500 && !paused.playing, "{paused:?}");
    tokio::time::sleep(Duration::from_millis(100)).await;
    assert_eq!(state(&server, &id, &observe).await.playback.unwrap().step, paused.step, "paused means paused");

    // To the end: exactly the recorded state; back to the middle and to the end again
    // (through a kept copy of the state): the same.
    assert_eq!(post(r#"{"action": "seek", "step": 1500}"#).await.0, 204);
    let end = state(&server, &id, &observe).await;
    assert_eq!(end.state_hash, report.state_hash, "the replay reaches the recorded state");
    assert_eq!(end.counters.unwrap().cuts, 1);
    assert_eq!(post(r#"{"action": "seek", "step": 700}"#).await.0, 204);
    let middle = state(&server, &id, &observe).await;
    assert_ne!(middle.state_hash, report.state_hash);
    assert_eq!(post(r#"{"action": "seek", "step": 1500}"#).await.0, 204);
    assert_eq!(state(&server, &id, &observe).await.state_hash, report.state_hash);

    // The viewer followed every jump to the replay's surface.
    let snapshot = server.sessions().await.get_snapshot(authed(pb::GetSnapshotRequest { session_id: id.clone() }, &observe)).await.unwrap().into_inner();
    let followed = viewer.pump_until(Duration::from_secs(10), |v| v.surface_hash().as_deref() == Some(snapshot.surface_hash.as_str())).await;
    assert!(followed, "viewer {:?} vs server {}", viewer.surface_hash(), snapshot.surface_hash);
    assert!(viewer.snapshots >= 3, "each seek resynchronises the viewer: {}", viewer.snapshots);

    // Bad playback requests, and playback on a session that is not a replay.
    assert_eq!(post(r#"{"action": "rewind"}"#).await.0, 400);
    assert_eq!(post(r#"{"action": "speed", "speed": 500}"#).await.0, 400);
    let (status, _) = http_post(&server.http, &format!("/api/sessions/{id}/playback"), &observe, r#"{"action": "play"}"#).await;
    assert_eq!(status, 403, "observers cannot drive the playback");
    let (status, _) = http_post(&server.http, &format!("/api/sessions/{}/playback", recorded.id), &recorded.control, r#"{"action": "play"}"#).await;
    assert_eq!(status, 409);
}
