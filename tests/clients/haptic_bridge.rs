//! The haptic bridge against a real server, with the simulated device: over 5 s of
//! contact the force never exceeds its limit nor jumps by more than the rate limit; when
//! the server is killed the force ramps to zero.

#[path = "../e2e/harness.rs"]
mod harness;

use std::process::{Command, Stdio};
use std::time::Duration;

use cutsim_proto::v1 as pb;
use harness::*;

const BRIDGE: &str = env!("CARGO_BIN_EXE_haptic-bridge");
const MAX_FORCE_N: f64 = 0.08;
const MAX_RATE_N_PER_S: f64 = 20.0;
const STALE_MS: f64 = 20.0;
const RAMP_MS: f64 = 50.0;

fn bridge(server: &Server, session: &Created, seconds: f64, dir: &TempDir) -> Command {
    let mut c = Command::new(BRIDGE);
    c.args(["--server", &format!("http://{}", server.grpc), "--session", &session.id, "--token", &session.control, "--tool", "1", "--device", "sim:press"])
        .args(["--duration-s", &seconds.to_string(), "--max-force-n", &MAX_FORCE_N.to_string(), "--max-force-rate-n-per-s", &MAX_RATE_N_PER_S.to_string()])
        .args(["--stale-ms", &STALE_MS.to_string(), "--ramp-ms", &RAMP_MS.to_string()])
        .arg("--report")
        .arg(dir.0.join("report.json"))
        .arg("--trace")
        .arg(dir.0.join("trace.csv"))
        .stdout(Stdio::piped())
        .stderr(Stdio::piped());
    c
}

/// (t_s, |F| N, fresh, connected) per millisecond.
fn trace(dir: &TempDir) -> Vec<(f64, f64, bool, bool)> {
    std::fs::read_to_string(dir.0.join("trace.csv"))
        .unwrap()
        .lines()
        .skip(1)
        .map(|l| {
            let c: Vec<&str> = l.split(',').collect();
            (c[0].parse().unwrap(), c[4].parse().unwrap(), c[5] == "1", c[6] == "1")
        })
        .collect()
}

#[tokio::test(flavor = "multi_thread")]
async fn five_seconds_of_contact_stay_within_the_force_and_rate_limits() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    let dir = TempDir::new("bridge");
    let out = bridge(&server, &session, 5.0, &dir).output().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(dir.0.join("report.json")).unwrap()).unwrap();
    let max_force = report["max_force_n"].as_f64().unwrap();
    let max_step = report["max_force_step_n"].as_f64().unwrap();
    assert!(max_force <= MAX_FORCE_N + 1e-12, "force {max_force} N above the {MAX_FORCE_N} N limit");
    assert!(max_step <= MAX_RATE_N_PER_S * 0.001 + 1e-12, "a {max_step} N jump in one millisecond");
    assert!(report["clamped"].as_u64().unwrap() > 100, "pressing 3 mm in asks for more than the limit, which held");
    assert!(report["device_steps"].as_u64().unwrap() >= 4900);
    assert_eq!(report["non_finite"], 0);
    assert!(report["rtt_samples"].as_u64().unwrap() > 1000, "{report}");
    // In contact for most of the press: at the limit, and the tool feels it from 1.5 s on.
    let rows = trace(&dir);
    let pressing: Vec<_> = rows.iter().filter(|r| r.0 > 1.5 && r.0 < 5.0).collect();
    let at_limit = pressing.iter().filter(|r| (r.1 - MAX_FORCE_N).abs() < 1e-9).count();
    assert!(at_limit as f64 > 0.8 * pressing.len() as f64, "{at_limit} of {} ms at the limit", pressing.len());
    // And the force ended at zero (the bridge fades out before it exits).
    assert_eq!(rows.last().unwrap().1, 0.0);
}

#[tokio::test(flavor = "multi_thread")]
async fn killing_the_server_ramps_the_force_to_zero() {
    let mut server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    let dir = TempDir::new("bridge-kill");
    let child = bridge(&server, &session, 4.0, &dir).spawn().unwrap();
    tokio::time::sleep(Duration::from_millis(2500)).await;
    server.kill();
    let out = tokio::task::spawn_blocking(move || child.wait_with_output()).await.unwrap().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let rows = trace(&dir);
    let last_fresh = rows.iter().rposition(|r| r.2).expect("fresh answers before the kill");
    assert!(rows[last_fresh].0 > 2.0 && rows[last_fresh].0 < 3.0, "answers stopped at the kill ({} s)", rows[last_fresh].0);
    assert!(rows[last_fresh].1 > 0.5 * MAX_FORCE_N, "in contact when the server died");
    // From then on the force only falls, never by more than the rate limit, and is zero
    // within the stale time plus the ramp (plus what the rate limit needs).
    let after = &rows[last_fresh..];
    for w in after.windows(2) {
        assert!(w[1].1 <= w[0].1 + 1e-12, "the force rose after the server died: {w:?}");
        assert!((w[0].1 - w[1].1) <= MAX_RATE_N_PER_S * 0.001 + 1e-9, "a jump: {w:?}");
    }
    let zero = after.iter().position(|r| r.1 == 0.0).expect("the force reaches zero");
    let ms = (after[zero].0 - after[0].0) * 1e3;
    let bound = STALE_MS + RAMP_MS + MAX_FORCE_N / MAX_RATE_N_PER_S * 1e3 + 10.0;
    assert!(ms <= bound, "zero after {ms:.0} ms (bound {bound:.0} ms)");
    assert!(after[zero..].iter().all(|r| r.1 == 0.0), "and stays zero");
}
