//! Scripts over gRPC: lockstep, deterministic, with expectations.

use cutsim_proto::v1 as pb;

use crate::harness::*;

#[tokio::test]
async fn script_run_twice_gives_the_same_hash_and_its_expectations() {
    let server = Server::start();
    let script = example_script("skin-patch-straight.json");
    let session = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let first = run_script(&server, &session, &script).await.unwrap();
    let second = run_script(&server, &session, &script).await.unwrap();
    assert!(first.passed, "{:?}", first.expectations);
    assert_eq!(first.expectations.len(), 5);
    assert_eq!((first.steps, first.cuts, first.pieces), (1500, 1, 1));
    assert!(first.removed_elements > 50 && first.incision_length_m > 0.034);
    assert_eq!(first.state_hash.len(), 16);
    assert_eq!(first.state_hash, second.state_hash, "same scene + same script = same hash");

    // On another session, even a real-time one (the script resets it), and through the
    // headless runner: the same hash again.
    let realtime = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    tokio::time::sleep(std::time::Duration::from_millis(200)).await;
    let third = run_script(&server, &realtime, &script).await.unwrap();
    assert_eq!(first.state_hash, third.state_hash);
    let headless = std::process::Command::new(server_binary())
        .args(["run", "skin-patch", "--json", "--script"])
        .arg(repo("clients/cut-bot/examples/skin-patch-straight.json"))
        .output()
        .unwrap();
    let report: serde_json::Value = serde_json::from_slice(&headless.stdout).unwrap();
    assert_eq!(report["state_hash"].as_str().unwrap(), first.state_hash);

    // A failed expectation is reported as such.
    let tampered = script.replace(r#""cuts": { "equals": 1 }"#, r#""cuts": { "equals": 2 }"#);
    let failed = run_script(&server, &session, &tampered).await.unwrap();
    assert!(!failed.passed);
    let cuts = failed.expectations.iter().find(|e| e.name == "cuts").unwrap();
    assert_eq!((cuts.passed, cuts.expected.as_str(), cuts.actual.as_str()), (false, "= 2", "1"));
    assert_eq!(failed.state_hash, first.state_hash);
}

/// Work the solver does on another thread (the multigrid hierarchy rebuilt after each cut,
/// swapped in at a step fixed in advance) keeps runs deterministic: a cut script on a
/// branched grid with the multigrid preconditioner reaches the same state hash in a
/// lockstep session, in a real-time session (its script on a background thread) and
/// headless, and the real-time session's recording replays to it.
#[tokio::test]
async fn a_grid_script_with_multigrid_gives_the_same_hash_in_real_time_and_lockstep() {
    same_hash_in_real_time_and_lockstep("multigrid", None).await;
}

/// The same with the Cholesky preconditioner: factors of recent systems made on a worker
/// every 32 steps and after each cut, each swapped in at its due step.
#[tokio::test]
async fn a_grid_script_with_cholesky_gives_the_same_hash_in_real_time_and_lockstep() {
    same_hash_in_real_time_and_lockstep("cholesky", None).await;
}

/// And under a multirate schedule: the haptic loop every step on the session's thread,
/// the deformation every 10 steps on its own, its results swapped in at their due steps.
#[tokio::test]
async fn a_multirate_grid_script_gives_the_same_hash_in_real_time_and_lockstep() {
    same_hash_in_real_time_and_lockstep("cholesky", Some(serde_json::json!({ "multirate": { "deformation_every_steps": 10 } }))).await;
}

async fn same_hash_in_real_time_and_lockstep(preconditioner: &str, schedule: Option<serde_json::Value>) {
    let server = Server::start();
    let scene = inline("u-tube", |s| {
        s["model"]["branched-grid"]["solver"] = serde_json::json!({ "preconditioner": preconditioner });
        if let Some(schedule) = &schedule {
            s["model"]["branched-grid"]["schedule"] = schedule.clone();
        }
    });
    let script = example_script("u-tube-slit-base.json");
    let lockstep = create_inline(&server, scene.clone(), pb::SessionMode::Lockstep).await.unwrap();
    let first = run_script(&server, &lockstep, &script).await.unwrap();
    assert!(first.passed, "{:?}", first.expectations);
    assert!(first.cuts > 0 && first.removed_elements > 0, "the script cuts (work redone on the worker)");
    let realtime = create_inline(&server, scene.clone(), pb::SessionMode::Realtime).await.unwrap();
    let info = server.sessions().await.get_session(authed(pb::GetSessionRequest { session_id: realtime.id.clone(), with_state_hash: false }, &realtime.observe)).await.unwrap().into_inner();
    let every = schedule.as_ref().map(|s| s["multirate"]["deformation_every_steps"].as_f64().unwrap());
    assert_eq!(info.deformation_rate_hz, every.map_or(0.0, |n| 1000.0 / n), "the session reports its deformation rate");
    tokio::time::sleep(std::time::Duration::from_millis(300)).await;
    let second = run_script(&server, &realtime, &script).await.unwrap();
    assert_eq!(second.state_hash, first.state_hash, "real time and lockstep agree");
    let again = run_script(&server, &lockstep, &script).await.unwrap();
    assert_eq!(again.state_hash, first.state_hash);
    assert_eq!(first.counters.as_ref().unwrap().solver_cap_hits, 0, "{:?}", first.counters);

    // The real-time session's recording (its real-time steps, the script, real-time steps
    // again) replays, verifying the script's end and the session's end.
    server.sessions().await.close_session(authed(pb::CloseSessionRequest { session_id: realtime.id.clone() }, &realtime.control)).await.unwrap();
    let recording = server.recordings.0.join(format!("{}.jsonl", realtime.id));
    let out = std::process::Command::new(server_binary()).args(["replay", "--json"]).arg(&recording).output().unwrap();
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert!(out.status.success(), "{report}");
    assert!(report["checkpoints_verified"].as_u64().unwrap() >= 2, "{report}");
    assert!(recording_holds(&recording, &first.state_hash), "the script's end hash is among the verified checkpoints");
}

fn recording_holds(path: &std::path::Path, hash: &str) -> bool {
    std::fs::read_to_string(path).unwrap().lines().any(|l| l.contains("\"t\":\"check\"") && l.contains(hash))
}

/// A cut update left as an open hole is named in the session's info, as in the script's
/// report: its step and why (an instructor asks GetSession while the session runs, or
/// the REST API's session summary).
#[tokio::test]
async fn the_session_info_lists_each_fallback_with_its_step_and_reason() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let sessions = || async { server.sessions().await };
    let get = || authed(pb::GetSessionRequest { session_id: session.id.clone(), with_state_hash: false }, &session.observe);
    let before = sessions().await.get_session(get()).await.unwrap().into_inner();
    assert!(before.fallbacks.is_empty(), "{:?}", before.fallbacks);

    // A cut one of whose updates falls back (the script expects it to).
    let script = std::fs::read_to_string(repo("server/sim/tests/data/skin-patch-falls-back.json")).unwrap();
    let report = run_script(&server, &session, &script).await.unwrap();
    assert!(report.passed && !report.fallbacks.is_empty(), "this cut no longer falls back: {:?}", report.expectations);

    let info = sessions().await.get_session(get()).await.unwrap().into_inner();
    assert_eq!(info.fallbacks, report.fallbacks);
    assert_eq!(info.counters.unwrap().reconstruction_fallbacks, info.fallbacks.len() as u64);
    assert!(info.fallbacks.iter().all(|f| f.step > 0 && f.step < 650 && !f.reason.is_empty()), "{:?}", info.fallbacks);

    let (status, body) = http_request(&server.http, "GET", &format!("/api/sessions/{}", session.id), Some(&session.observe)).await;
    assert_eq!(status, 200, "{body}");
    let summary: serde_json::Value = serde_json::from_str(&body).unwrap();
    assert_eq!(summary["reconstruction_fallbacks"], info.fallbacks.len());
    let listed: Vec<(u64, String)> = summary["fallbacks"].as_array().unwrap().iter().map(|f| (f["step"].as_u64().unwrap(), f["reason"].as_str().unwrap().to_owned())).collect();
    assert_eq!(listed, info.fallbacks.iter().map(|f| (f.step, f.reason.clone())).collect::<Vec<_>>());
}

/// A stroke's last piece that could not be stitched and was left uncut is counted, in
/// the script's report (its own expectation, its counters and its JSON) and in the
/// session's counters.
#[tokio::test]
async fn a_last_piece_left_uncut_is_counted_in_the_report_and_the_session() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    let script = std::fs::read_to_string(repo("server/sim/tests/data/skin-patch-last-piece-uncut.json")).unwrap();
    let report = run_script(&server, &session, &script).await.unwrap();
    assert!(report.passed, "{:?}", report.expectations);
    assert!(report.expectations.iter().any(|e| e.name == "uncut_last_pieces" && e.actual == "1"), "{:?}", report.expectations);
    assert_eq!(report.counters.unwrap().uncut_last_pieces, 1);
    let json: serde_json::Value = serde_json::from_str(&report.report_json).unwrap();
    assert_eq!(json["counters"]["uncut_last_pieces"], 1);

    let get = authed(pb::GetSessionRequest { session_id: session.id.clone(), with_state_hash: false }, &session.observe);
    let info = server.sessions().await.get_session(get).await.unwrap().into_inner();
    assert_eq!(info.counters.unwrap().uncut_last_pieces, 1);
    let (status, body) = http_request(&server.http, "GET", &format!("/api/sessions/{}", session.id), Some(&session.observe)).await;
    assert_eq!(status, 200, "{body}");
    assert_eq!(serde_json::from_str::<serde_json::Value>(&body).unwrap()["uncut_last_pieces"], 1);
}
