//! A recorded session replays to the same state hash after the server is SIGKILLed.

use std::time::Duration;

use cutsim_proto::v1 as pb;

use crate::harness::*;
use crate::haptics::open;

#[tokio::test]
async fn recording_replays_to_the_same_hash_after_sigkill() {
    let mut server = Server::start();
    let s = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    // A trainee cuts for about a second through the haptic stream.
    let (tx, response) = open(&server, &s.id, &s.control).await;
    let mut feedback = response.unwrap();
    let reader = tokio::spawn(async move { while let Ok(Some(_)) = feedback.message().await {} });
    let mut tick = tokio::time::interval(Duration::from_millis(1));
    for i in 0..1000u32 {
        tick.tick().await;
        let x = -0.02 + 0.04 * (f64::from(i) / 1000.0);
        let command = pb::ToolCommand { tool: 0, pose: Some(pose(x, 0.0, -0.005)), active: true, cut: true, client_time_ns: u64::from(i) + 1, feedback_every_steps: 1, grip: None };
        tx.send(command).await.unwrap();
    }
    drop(tx);
    let _ = reader.await;
    // A checkpoint: the state hash at a step, also written to the recording.
    let info = server
        .sessions()
        .await
        .get_session(authed(pb::GetSessionRequest { session_id: s.id.clone(), with_state_hash: true }, &s.observe))
        .await
        .unwrap()
        .into_inner();
    assert!(info.counters.unwrap().cuts >= 1, "the trainee cut");
    assert_eq!(info.state_hash.len(), 16);
    // The checkpoint in the recording, then the server killed without any cleanup.
    let recording = server.recordings.0.join(format!("{}.jsonl", s.id));
    wait_for_checkpoint(&recording, info.state_hash_step).await;
    server.kill();

    let out = std::process::Command::new(server_binary()).args(["replay", "--json"]).arg(&recording).output().unwrap();
    assert!(out.status.success(), "replay failed: {}\n{}", String::from_utf8_lossy(&out.stdout), String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(report["ended_cleanly"], false, "the server was killed");
    assert!(report["checkpoints_verified"].as_u64().unwrap() >= 1);
    assert_eq!(report["checkpoint_mismatches"].as_array().unwrap().len(), 0);
    // One command is recorded for each step that saw a new pose: a thousand on a machine
    // that steps at 1 kHz, fewer where the session steps slower than the poses come (a
    // loaded CI machine stepped such sessions at well under half that rate).
    assert!(report["commands"].as_u64().unwrap() > 100, "the recording holds the trainee's commands: {report}");
    assert!(report["steps"].as_u64().unwrap() >= info.state_hash_step);
}
