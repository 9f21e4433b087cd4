//! The fault cases: a viewer that stops reading, clients that send garbage, a haptic
//! client that vanishes mid-cut (watched here, caused in `haptic`), the server killed
//! with SIGKILL and restarted, and a full disk while recording.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::{Context, anyhow};
use cutsim_proto::v1 as pb;
use futures_util::SinkExt;
use serde::Serialize;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio_tungstenite::tungstenite;

use crate::haptic::{self, HapticTarget, Trajectory};
use crate::server::{self, Created, FullDisk, ServerProcess};

/// One fault case's outcome.
#[derive(Serialize, Debug, Clone)]
pub struct FaultOutcome {
    pub case: String,
    pub passed: bool,
    pub detail: String,
}

impl FaultOutcome {
    pub fn new(case: &str, passed: bool, detail: impl Into<String>) -> Self {
        Self { case: case.into(), passed, detail: detail.into() }
    }

    fn failed(case: &str, error: &anyhow::Error) -> Self {
        Self::new(case, false, format!("{error:#}"))
    }
}

/// Deterministic bytes that are nothing in particular (xorshift).
fn garbage(len: usize, mut seed: u64) -> Vec<u8> {
    (0..len)
        .map(|_| {
            seed ^= seed << 13;
            seed ^= seed >> 7;
            seed ^= seed << 17;
            seed as u8
        })
        .collect()
}

/// Polls the session until `done` holds or `within` passes; returns how long it took.
async fn wait_for(server: &ServerProcess, session: &Created, within: Duration, done: impl Fn(&pb::SessionInfo) -> bool) -> anyhow::Result<Option<Duration>> {
    let start = Instant::now();
    while start.elapsed() < within {
        if done(&server::info(server, &session.id, &session.observe, false).await?) {
            return Ok(Some(start.elapsed()));
        }
        tokio::time::sleep(Duration::from_millis(20)).await;
    }
    Ok(None)
}

/// A viewer that opens its WebSocket with a 4 KiB receive buffer, asks for the highest
/// frame rate and never reads: once the socket buffers are full, the server's sends time
/// out (10 s) and it must drop the viewer, without slowing the session or other viewers.
pub async fn stalled_viewer(server: &ServerProcess, session: &Created, regular_viewers: u32, within: Duration) -> FaultOutcome {
    const CASE: &str = "viewer that stops reading";
    let run = async {
        let socket = tokio::net::TcpSocket::new_v4()?;
        socket.set_recv_buffer_size(4096)?;
        let tcp = socket.connect(server.http.parse()?).await?;
        let url = format!("ws://{}/ws/sessions/{}?token={}&rate_hz=240", server.http, session.id, session.observe);
        let (stalled, _) = tokio_tungstenite::client_async(url, tcp).await?;
        wait_for(server, session, Duration::from_secs(5), |i| i.viewers > regular_viewers).await?.ok_or_else(|| anyhow!("the stalled viewer was never counted"))?;
        let before = server::info(server, &session.id, &session.observe, false).await?.step;
        let dropped = wait_for(server, session, within, |i| i.viewers <= regular_viewers).await?;
        let after = server::info(server, &session.id, &session.observe, false).await?.step;
        drop(stalled);
        Ok::<_, anyhow::Error>(match dropped {
            Some(t) => FaultOutcome::new(CASE, true, format!("dropped by the server {:.1} s after it stopped reading; the session stepped {} times meanwhile", t.as_secs_f64(), after - before)),
            None => FaultOutcome::new(CASE, false, format!("still connected after {} s", within.as_secs())),
        })
    };
    run.await.unwrap_or_else(|e| FaultOutcome::failed(CASE, &e))
}

/// Reads what the server answers to `bytes` on a fresh connection, until it closes.
async fn answer_to(addr: &str, bytes: &[u8]) -> anyhow::Result<(Vec<u8>, bool)> {
    let mut tcp = tokio::net::TcpStream::connect(addr).await?;
    let _ = tcp.write_all(bytes).await;
    let mut answer = Vec::new();
    let closed = tokio::time::timeout(Duration::from_secs(10), tcp.read_to_end(&mut answer)).await.is_ok();
    Ok((answer, closed))
}

/// Garbage at every door: random bytes on the gRPC and HTTP ports, a viewer sending
/// random binary, a haptic stream with a NaN pose. Each gets a clear refusal or a closed
/// connection; the session is untouched (checked by the caller's statistics).
pub async fn garbage_clients(server: &ServerProcess, session: &Created) -> Vec<FaultOutcome> {
    let mut outcomes = Vec::new();
    let noise = garbage(64 << 10, 0x9e37_79b9_7f4a_7c15);
    outcomes.push(match answer_to(&server.grpc, &noise).await {
        Ok((answer, true)) => FaultOutcome::new("garbage on the gRPC port", true, format!("connection closed by the server ({} bytes answered)", answer.len())),
        Ok((_, false)) => FaultOutcome::new("garbage on the gRPC port", false, "connection left open for 10 s"),
        Err(e) => FaultOutcome::failed("garbage on the gRPC port", &e),
    });
    outcomes.push(match answer_to(&server.http, &noise).await {
        Ok((answer, closed)) => {
            let status = String::from_utf8_lossy(&answer[..answer.len().min(12)]).into_owned();
            let ok = closed && (answer.is_empty() || status.starts_with("HTTP/1.1 4"));
            FaultOutcome::new("garbage on the HTTP port", ok, format!("answered {status:?}, connection {}", if closed { "closed" } else { "left open" }))
        }
        Err(e) => FaultOutcome::failed("garbage on the HTTP port", &e),
    });
    let ws = async {
        let url = format!("ws://{}/ws/sessions/{}?token={}", server.http, session.id, session.observe);
        let (mut socket, _) = tokio_tungstenite::connect_async(url).await?;
        socket.send(tungstenite::Message::Binary(garbage(512, 7).into())).await?;
        use futures_util::StreamExt;
        let close = tokio::time::timeout(Duration::from_secs(10), async {
            while let Some(message) = socket.next().await {
                if let Ok(tungstenite::Message::Close(frame)) = message {
                    return frame.map(|f| (u16::from(f.code), f.reason.to_string()));
                }
            }
            None
        })
        .await?;
        Ok::<_, anyhow::Error>(match close {
            Some((1007, reason)) => FaultOutcome::new("viewer sending garbage", true, format!("closed with 1007: {reason}")),
            other => FaultOutcome::new("viewer sending garbage", false, format!("expected a close with 1007, got {other:?}")),
        })
    };
    outcomes.push(ws.await.unwrap_or_else(|e| FaultOutcome::failed("viewer sending garbage", &e)));
    let nan = async {
        let channel = server.channel().await?;
        let mut request = tonic::Request::new(futures_util::stream::iter([pb::ToolCommand {
            tool: 0,
            pose: Some(pb::Pose { position_m: Some(pb::Vec3 { x: f64::NAN, y: 0.0, z: 0.0 }), orientation: Some(pb::Quaternion { w: 1.0, x: 0.0, y: 0.0, z: 0.0 }) }),
            active: true,
            cut: true,
            client_time_ns: 1,
            feedback_every_steps: 1,
            grip: None,
        }]));
        request.metadata_mut().insert("cutsim-session", session.id.parse()?);
        request.metadata_mut().insert("cutsim-token", session.control.parse()?);
        let mut feedback = cutsim_proto::v1::haptics_client::HapticsClient::new(channel).stream(request).await?.into_inner();
        let end = loop {
            match tokio::time::timeout(Duration::from_secs(10), feedback.message()).await? {
                Ok(Some(_)) => continue,
                Ok(None) => break None,
                Err(status) => break Some(status),
            }
        };
        Ok::<_, anyhow::Error>(match end {
            Some(s) if s.code() == tonic::Code::InvalidArgument => FaultOutcome::new("haptic stream with a NaN pose", true, format!("INVALID_ARGUMENT: {}", s.message())),
            other => FaultOutcome::new("haptic stream with a NaN pose", false, format!("expected INVALID_ARGUMENT, got {other:?}")),
        })
    };
    outcomes.push(nan.await.unwrap_or_else(|e| FaultOutcome::failed("haptic stream with a NaN pose", &e)));
    outcomes
}

/// Watches a session whose haptic client vanishes at `at` (see `haptic::run`): the server
/// must notice, take the tool out, and keep stepping.
pub async fn vanishing_haptic_client(server: &ServerProcess, session: &Created, at: Instant) -> FaultOutcome {
    const CASE: &str = "haptic client vanishing mid-cut";
    let run = async {
        tokio::time::sleep_until(at.into()).await;
        let gone = wait_for(server, session, Duration::from_millis(450), |i| i.haptic_clients == 0).await?;
        let before = server::info(server, &session.id, &session.observe, false).await?;
        tokio::time::sleep(Duration::from_millis(200)).await;
        let after = server::info(server, &session.id, &session.observe, false).await?;
        Ok::<_, anyhow::Error>(match gone {
            Some(t) => FaultOutcome::new(
                CASE,
                after.step > before.step,
                format!(
                    "the server let go of the stream within {:.0} ms of the connection dropping (the tool left the scene) and stepped on: {} steps in the next 200 ms; {} cuts so far",
                    t.as_secs_f64() * 1e3,
                    after.step - before.step,
                    after.counters.map_or(0, |c| c.cuts)
                ),
            ),
            None => FaultOutcome::new(CASE, false, "the server still counted the vanished client 450 ms later"),
        })
    };
    run.await.unwrap_or_else(|e| FaultOutcome::failed(CASE, &e))
}

/// Before the kill: each session's state hash at a step (also a checkpoint in its recording).
pub struct Checkpoint {
    pub session: String,
    pub step: u64,
    pub hash: String,
}

/// Steps between the state hashes a real-time session writes into its recording, in
/// the load's server (`server::write_config`): the SIGKILL case's session passes one.
pub const CHECKPOINT_EVERY_STEPS: u64 = 1_000;

/// The SIGKILL case's session: a real-time session of its own, driven by a haptic client
/// for its first seconds, once it is half an interval past its recording's first
/// checkpoint; returns its checkpoint (the state hash now). Not the load's sessions:
/// they have stepped for as long as the load took, and on a slow host with the bot
/// starved by them that was minutes (CI, 2026-11-28: about 500,000 steps), which the
/// offline replay and the restarted server's seek must step through again (both seeks
/// passed their 120 s).
pub async fn session_past_a_checkpoint(server: &ServerProcess, scene: &str) -> anyhow::Result<Vec<Checkpoint>> {
    let session = server::create(server, scene, pb::SessionMode::Realtime, "cutsim-load SIGKILL").await?;
    let target = HapticTarget { grpc: server.grpc.clone(), session: session.id.clone(), token: session.control.clone(), trajectory: Trajectory::from_info(&session.info) };
    let client = tokio::spawn(haptic::run(target, Instant::now() + Duration::from_secs(2), None));
    let target_step = CHECKPOINT_EVERY_STEPS * 3 / 2;
    let past = wait_for(server, &session, Duration::from_secs(120), |i| i.step >= target_step).await?;
    client.await?;
    past.with_context(|| format!("the SIGKILL case's session did not reach step {target_step} in 120 s"))?;
    checkpoints(server, std::slice::from_ref(&session)).await
}

pub async fn checkpoints(server: &ServerProcess, sessions: &[Created]) -> anyhow::Result<Vec<Checkpoint>> {
    let mut out = Vec::new();
    for s in sessions {
        let info = server::info(server, &s.id, &s.observe, true).await?;
        out.push(Checkpoint { session: s.id.clone(), step: info.state_hash_step, hash: info.state_hash });
    }
    Ok(out)
}

/// After SIGKILL: each recording replays offline (`cutsim-server replay`) with every
/// checkpoint verified, and a restarted server replays it to the same hash at the
/// checkpoint's step.
pub async fn replay_after_kill(binary: &Path, restarted: &ServerProcess, recordings: &Path, checkpoints: &[Checkpoint]) -> Vec<FaultOutcome> {
    let mut outcomes = Vec::new();
    for c in checkpoints {
        let case = format!("SIGKILL + restart: session {}", c.session);
        let run = async {
            let recording = recordings.join(format!("{}.jsonl", c.session));
            let mut command = std::process::Command::new(binary);
            command.arg("replay").arg("--json").arg(&recording);
            let out = tokio::task::spawn_blocking(move || command.output()).await??;
            let report: serde_json::Value = serde_json::from_slice(&out.stdout).with_context(|| format!("replay said: {}", String::from_utf8_lossy(&out.stderr)))?;
            let verified = report["checkpoints_verified"].as_u64().unwrap_or(0);
            let mismatches = report["checkpoint_mismatches"].as_array().map_or(0, Vec::len);
            let steps = report["steps"].as_u64().unwrap_or(0);
            let body = server::http(&restarted.http, "POST", &format!("/api/recordings/{}/replay", c.session), server::OPERATOR_TOKEN, "").await?;
            anyhow::ensure!(body.0 == 201, "the restarted server refused the replay: {} {}", body.0, body.1);
            let created: serde_json::Value = serde_json::from_str(&body.1)?;
            let (id, control, observe) = (created["session_id"].as_str().unwrap_or_default(), created["control_token"].as_str().unwrap_or_default(), created["observe_token"].as_str().unwrap_or_default());
            let seek = server::http(&restarted.http, "POST", &format!("/api/sessions/{id}/playback"), control, &format!(r#"{{"action": "seek", "step": {}}}"#, c.step)).await?;
            anyhow::ensure!(seek.0 == 204, "seek to {} refused: {} {}", c.step, seek.0, seek.1);
            let replayed = server::info(restarted, id, observe, true).await?;
            let same = replayed.state_hash == c.hash && replayed.state_hash_step == c.step;
            let passed = same && verified >= 1 && mismatches == 0 && steps >= c.step;
            Ok::<_, anyhow::Error>(FaultOutcome::new(
                &case,
                passed,
                format!(
                    "recording: {steps} steps, {verified} checkpoints verified, {mismatches} mismatched; restarted server's replay at step {}: {} (before the kill: {})",
                    c.step, replayed.state_hash, c.hash
                ),
            ))
        };
        outcomes.push(run.await.unwrap_or_else(|e| FaultOutcome::failed(&case, &e)));
    }
    outcomes
}

/// A server whose recordings cannot grow past `limit` bytes: the session keeps running
/// with its haptic client, and SessionInfo reports the loss. The disk is a real full
/// filesystem where this process may mount one (root), else a file-size limit.
pub async fn disk_full(binary: &Path, config: &Path, recordings: &Path, scene: &str, limit: u64) -> FaultOutcome {
    const CASE: &str = "disk full while recording";
    let run = async {
        let (server, disk) = match ServerProcess::start(binary, config, recordings, Some(FullDisk::Tmpfs(limit))) {
            Ok(server) => (server, format!("the recordings directory is a full filesystem (a {} KiB tmpfs: writes fail with ENOSPC)", limit >> 10)),
            Err(tmpfs) => (
                ServerProcess::start(binary, config, recordings, Some(FullDisk::FileSize(limit)))?,
                format!(
                    "recordings limited to {} KiB by a file-size limit (RLIMIT_FSIZE: writes fail with EFBIG where a full disk fails them with ENOSPC; no tmpfs: {})",
                    limit >> 10,
                    tmpfs.root_cause()
                ),
            ),
        };
        let session = server::create(&server, scene, pb::SessionMode::Realtime, "cutsim-load disk-full").await?;
        let target = HapticTarget { grpc: server.grpc.clone(), session: session.id.clone(), token: session.control.clone(), trajectory: Trajectory::from_info(&session.info) };
        // The client's commands fill the disk (about 2 s at 1 kHz); a loaded machine
        // steps slower, so the report is waited for up to 10 s (4 s was too short for
        // this 2-core host at 600 Hz once), then the session must step on for a second.
        let until = Instant::now() + Duration::from_secs(12);
        let client = tokio::spawn(haptic::run(target, until, None));
        let reported = wait_for(&server, &session, Duration::from_secs(10), |i| !i.recording_problem.is_empty()).await?;
        let before = server::info(&server, &session.id, &session.observe, false).await?;
        tokio::time::sleep(Duration::from_secs(1)).await;
        let after = server::info(&server, &session.id, &session.observe, false).await?;
        let stats = client.await?;
        let rate = after.stats.as_ref().map_or(0.0, |s| s.achieved_rate_hz);
        let stepping = after.step > before.step;
        let passed = reported.is_some() && stepping && stats.errors.is_empty() && stats.feedback > 0;
        Ok::<_, anyhow::Error>(FaultOutcome::new(
            CASE,
            passed,
            format!(
                "{disk}; reported {} after the session started: \"{}\"; the session kept stepping ({} steps in the last part, {rate:.0} Hz) and its haptic client got {} feedback messages{}",
                reported.map_or("never".into(), |t| format!("{:.1} s", t.as_secs_f64())),
                after.recording_problem,
                after.step - before.step,
                stats.feedback,
                if stats.errors.is_empty() { String::new() } else { format!(", errors: {:?}", stats.errors) }
            ),
        ))
    };
    run.await.unwrap_or_else(|e| FaultOutcome::failed(CASE, &e))
}
