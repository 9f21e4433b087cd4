//! Assessment over the real server: a script's report carries the task's metrics and the
//! session serves the same; a live cut through a haptic stream is assessed off the
//! physics thread, and its replay recomputes exactly the same metrics.

use std::time::Duration;

use cutsim_proto::v1 as pb;

use crate::harness::*;
use crate::haptics::open;

const ADMIN: &str = "0123456789abcdef0123456789abcdef";

async fn post(server: &Server, path: &str, token: &str, body: &str) -> HttpResponse {
    http_call(&server.http, "POST", path, &[("cutsim-token", token), ("content-type", "application/json")], body).await
}

/// The session's metrics once its assessor has published `steps` steps.
async fn settled(server: &Server, id: &str, token: &str, steps: u64) -> pb::Assessment {
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    loop {
        let a = assessment(server, id, token).await;
        if a.steps == steps || std::time::Instant::now() > deadline {
            return a;
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
}

async fn assessment(server: &Server, id: &str, token: &str) -> pb::Assessment {
    server.sessions().await.get_assessment(authed(pb::GetAssessmentRequest { session_id: id.into() }, token)).await.unwrap().into_inner()
}

#[tokio::test]
async fn a_good_and_a_bad_scripted_cut_are_scored_and_the_session_serves_the_same_metrics() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let good = run_script(&server, &session, &example_script("skin-patch-task-good.json")).await.unwrap();
    assert!(good.passed, "{:?}", good.expectations);
    let metrics = good.assessment.clone().expect("a script's report carries its assessment");
    assert_eq!(metrics.passed, Some(true), "{:?}", metrics.failures);
    assert!(metrics.task.contains("straight 40 mm incision"), "{}", metrics.task);
    assert!(metrics.events.iter().any(|e| e.kind == "completed"), "{:?}", metrics.events);
    // The session's own assessor (its thread, fed by the physics thread's ring) reaches
    // what the script's runner reported: same steps, same metrics.
    let served = settled(&server, &session.id, &session.observe, metrics.steps).await;
    assert_eq!(served, metrics);
    let info = server.sessions().await.get_session(authed(pb::GetSessionRequest { session_id: session.id.clone(), with_state_hash: false }, &session.observe)).await.unwrap().into_inner();
    assert_eq!(info.assessment.as_ref(), Some(&metrics));

    let bad = run_script(&server, &session, &example_script("skin-patch-task-bad.json")).await.unwrap();
    assert!(bad.passed, "the bad cut's script asserts that the task fails: {:?}", bad.expectations);
    let metrics = bad.assessment.unwrap();
    assert_eq!(metrics.passed, Some(false));
    assert!(metrics.failures.iter().any(|f| f.contains("coverage")) && metrics.failures.iter().any(|f| f.contains("from the plan")), "{:?}", metrics.failures);
    assert!(metrics.score.unwrap() < 60.0);

    // The printable report: for the session's tokens, an attachment of its own with no script.
    let path = format!("/api/sessions/{}/report", session.id);
    assert_eq!(http_call(&server.http, "GET", &path, &[], "").await.status, 401);
    assert_eq!(http_call(&server.http, "GET", &path, &[("cutsim-token", "wrong")], "").await.status, 401);
    let report = http_call(&server.http, "GET", &path, &[("cutsim-token", &session.observe)], "").await;
    assert_eq!(report.status, 200, "{}", report.body);
    assert!(report.header("content-disposition").is_some_and(|d| d.starts_with("attachment")), "{}", report.head);
    assert_eq!(report.header("content-security-policy"), Some("default-src 'none'; style-src 'unsafe-inline'"));
    assert!(report.body.contains("Verdict: <span class=\"fail\">failed</span>") && report.body.contains("coverage"), "the bad cut's report");
    assert!(!report.body.contains("<script"));

    // The observe token may read the metrics; a wrong token may not.
    let denied = server.sessions().await.get_assessment(authed(pb::GetAssessmentRequest { session_id: session.id.clone() }, "wrong")).await.unwrap_err();
    assert_eq!(denied.code(), tonic::Code::Unauthenticated);
}

#[tokio::test]
async fn a_live_cut_is_assessed_and_its_replay_recomputes_the_same_metrics() {
    let dir = TempDir::new("assessment");
    let config = dir.0.join("config.json");
    std::fs::write(&config, format!(r#"{{"admin_token": "{ADMIN}"}}"#)).unwrap();
    let server = Server::start_with(&["--no-session", "--config", config.to_str().unwrap()]);
    let live = create(&server, "skin-patch", pb::SessionMode::Realtime).await;

    // A trainee's scalpel: pressed down into the skin before the plan's start until it
    // punctures it (about 7 mm of indentation), along the plan at 0.1 m/s 5 mm deep,
    // out past its end, one pose a millisecond.
    let (tx, response) = open(&server, &live.id, &live.control).await;
    let mut feedback = response.expect("the stream opens");
    let reader = tokio::spawn(async move { while let Ok(Some(_)) = feedback.message().await {} });
    let mut tick = tokio::time::interval(Duration::from_millis(1));
    for i in 0..600u32 {
        tick.tick().await;
        let (x, z) = match i {
            0..50 => (-0.024, 0.005 - 0.015 * f64::from(i) / 50.0),
            50..505 => (-0.024 + 0.0455 * f64::from(i - 50) / 455.0, -0.005),
            _ => (0.0215, -0.005 + 0.015 * f64::from(i - 505) / 95.0),
        };
        let command = pb::ToolCommand { tool: 0, pose: Some(pose(x, 0.0, z)), active: true, cut: true, client_time_ns: u64::from(i) + 1, feedback_every_steps: 1, grip: None };
        tx.send(command).await.unwrap();
    }
    drop(tx);
    let _ = reader.await;
    tokio::time::sleep(Duration::from_millis(300)).await;

    let metrics = assessment(&server, &live.id, &live.observe).await;
    assert!(metrics.has_plan && metrics.problem.is_empty(), "{metrics:?}");
    // How much of it cut depends on how evenly this machine delivered the poses (a blade
    // held still by a late pose does not cut): loose bounds, the exact check is the replay's.
    assert!(metrics.strokes >= 1 && metrics.incision_length_mm > 5.0, "the live cut was assessed: {metrics:?}");
    assert!(metrics.coverage.unwrap() > 0.1 && metrics.deviation_max_mm.unwrap() < 2.0, "{metrics:?}");
    assert!(metrics.path_length_mm > 40.0 && metrics.peak_force_n > 0.5, "{metrics:?}");

    // The replay, shown at the step those metrics were of, computes the same metrics.
    let closed = server.sessions().await.close_session(authed(pb::CloseSessionRequest { session_id: live.id.clone() }, &live.control)).await;
    assert!(closed.is_ok(), "{closed:?}");
    let replay = post(&server, &format!("/api/recordings/{}/replay", live.id), ADMIN, "").await;
    assert_eq!(replay.status, 201, "{}", replay.body);
    let created: serde_json::Value = serde_json::from_str(&replay.body).unwrap();
    let (id, control, observe) = (created["session_id"].as_str().unwrap(), created["control_token"].as_str().unwrap(), created["observe_token"].as_str().unwrap());
    let playback = format!("/api/sessions/{id}/playback");
    let seek = post(&server, &playback, control, &format!(r#"{{"action": "seek", "step": {}}}"#, metrics.steps)).await;
    assert_eq!(seek.status, 204, "{}", seek.body);
    let replayed = assessment(&server, id, observe).await;
    assert_eq!(replayed, metrics, "the replay recomputes the live session's metrics");
    // Its timeline (built before the seek was answered) covers the whole recording and
    // ends where the live session did (the tool had left the tissue: no metric moved).
    let timeline = http_call(&server.http, "GET", &format!("/api/sessions/{id}/timeline"), &[("cutsim-token", observe)], "").await;
    assert_eq!(timeline.status, 200, "{}", timeline.body);
    let timeline: serde_json::Value = serde_json::from_str(&timeline.body).unwrap();
    assert_eq!(timeline["indexed_steps"], created["total_steps"], "{timeline}");
    assert_eq!(timeline["total_steps"], created["total_steps"]);
    let bins = timeline["force_peak_n"].as_array().unwrap();
    assert!(!bins.is_empty() && bins.len() <= 600 && timeline["score"].as_array().unwrap().len() == bins.len());
    let peak = bins.iter().map(|f| f.as_f64().unwrap()).fold(0.0, f64::max);
    // The curves are f32 (written in their shortest form).
    assert_eq!(peak as f32, metrics.peak_force_n as f32, "the curves' largest force is the metrics' peak");
    let last_score = timeline["score"].as_array().unwrap().last().unwrap().as_f64().unwrap();
    assert_eq!(last_score as f32, metrics.score.unwrap() as f32, "{timeline}");
    // Live sessions have no timeline.
    let other = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let refused = http_call(&server.http, "GET", &format!("/api/sessions/{}/timeline", other.id), &[("cutsim-token", &other.observe)], "").await;
    assert!(refused.status >= 400 && refused.body.contains("only replays have a timeline"), "{} {}", refused.status, refused.body);
    // And back to the start: nothing assessed yet.
    assert_eq!(post(&server, &playback, control, r#"{"action": "seek", "step": 0}"#).await.status, 204);
    let start = assessment(&server, id, observe).await;
    assert_eq!((start.steps, start.strokes, start.coverage), (0, 0, Some(0.0)));
}
