//! cut-bot against a real server: the example scripts pass, a tampered expectation fails
//! with exit status 1 and a readable diff, the JUnit file is valid XML, errors are clear,
//! and a recorded haptic session turns into a script that reproduces it exactly.

#[path = "../e2e/harness.rs"]
mod harness;

use std::process::{Command, Output};
use std::time::Duration;

use cutsim_proto::v1 as pb;
use harness::*;

const CUT_BOT: &str = env!("CARGO_BIN_EXE_cut-bot");

fn cut_bot(args: &[&str]) -> Output {
    Command::new(CUT_BOT).args(args).env("CUTSIM_OPERATOR_TOKEN", OPERATOR).output().expect("cut-bot runs")
}

fn text(o: &Output) -> String {
    format!("{}{}", String::from_utf8_lossy(&o.stdout), String::from_utf8_lossy(&o.stderr))
}

/// Parses an XML file with a real XML parser (Python's standard library).
fn assert_valid_xml(path: &std::path::Path) {
    let out = Command::new("python3")
        .args(["-c", "import sys, xml.dom.minidom as m; d = m.parse(sys.argv[1]); print(len(d.getElementsByTagName('testcase')))"])
        .arg(path)
        .output()
        .expect("python3 runs");
    assert!(out.status.success(), "{} is not valid XML: {}", path.display(), String::from_utf8_lossy(&out.stderr));
}

#[test]
fn example_scripts_pass_and_a_tampered_one_fails_readably() {
    let server = Server::start();
    let url = format!("http://{}", server.grpc);
    let dir = TempDir::new("cut-bot");
    let examples = repo("clients/cut-bot/examples");
    let mut names: Vec<_> = std::fs::read_dir(&examples).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|e| e == "json")).collect();
    names.sort();
    assert_eq!(names.len(), 15, "a straight, a curved and a separating cut for each skin scene, a wound's lip retracted with forceps, a slit of the U-tube's base (branched grid), and a good and a bad cut of each bundled task");
    for script in &names {
        let junit = dir.0.join("junit.xml");
        let report = dir.0.join("report.json");
        let out = cut_bot(&["run", script.to_str().unwrap(), "--server", &url, "--junit", junit.to_str().unwrap(), "--report", report.to_str().unwrap()]);
        assert!(out.status.success(), "{}: {}", script.display(), text(&out));
        assert!(text(&out).contains("result           PASS"), "{}", text(&out));
        assert_valid_xml(&junit);
        let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&report).unwrap()).unwrap();
        assert_eq!(report["passed"], true);
        if script.ends_with("skin-patch-retract.json") {
            // Each tool's own largest force, how long the forceps grasped and how hard they
            // pinched: printed, in the JUnit properties, and checked.
            for expectation in ["max_force_n", "grasping_s", "max_jaws_force_n"] {
                assert!(text(&out).contains(&format!("PASS tools.forceps.{expectation}")), "{}", text(&out));
            }
            assert!(text(&out).lines().any(|l| l.trim_start().starts_with("forceps ") && l.contains(" N, grasping ") && l.ends_with(", pinching at most 3.00 N")), "{}", text(&out));
            assert!(text(&out).lines().any(|l| l.trim() == "peak grip 3.00 N"), "the assessment's hardest pinch: {}", text(&out));
            assert!(text(&out).lines().any(|l| l.trim_start().starts_with("scalpel ") && l.ends_with(" N")), "{}", text(&out));
            let xml = std::fs::read_to_string(&junit).unwrap();
            assert!(xml.contains("<property name=\"max_force_n.forceps\"") && xml.contains("<property name=\"grasping_s.forceps\" value=\"0.8"), "{xml}");
            assert!(xml.contains("<property name=\"max_jaws_force_n.forceps\" value=\"3\"/>") && xml.contains("<property name=\"assessment.peak_grip_force_n\" value=\"3\"/>"), "{xml}");
        }
    }

    // A tampered expectation: exit 1, a readable diff, a JUnit failure.
    let original = std::fs::read_to_string(examples.join("skin-patch-straight.json")).unwrap();
    let tampered = dir.0.join("tampered.json");
    std::fs::write(&tampered, original.replace("\"cuts\": {\n      \"equals\": 1\n    }", "\"cuts\": {\n      \"equals\": 2\n    }").replace(r#""cuts": { "equals": 1 }"#, r#""cuts": { "equals": 2 }"#)).unwrap();
    let junit = dir.0.join("tampered.xml");
    let out = cut_bot(&["run", tampered.to_str().unwrap(), "--server", &url, "--scene", "skin-patch", "--junit", junit.to_str().unwrap()]);
    assert_eq!(out.status.code(), Some(1), "{}", text(&out));
    assert!(text(&out).contains("FAIL cuts                       expected = 2, got 1"), "{}", text(&out));
    assert_valid_xml(&junit);
    let xml = std::fs::read_to_string(&junit).unwrap();
    assert!(xml.contains("failures=\"1\"") && xml.contains("<failure message=\"expected = 2, got 1\""), "{xml}");
}

#[test]
fn errors_are_clear_and_exit_with_status_2() {
    let server = Server::start();
    let url = format!("http://{}", server.grpc);
    let dir = TempDir::new("cut-bot-errors");
    let example = repo("clients/cut-bot/examples/skin-patch-straight.json");
    let example = example.to_str().unwrap();

    let out = cut_bot(&["run", example, "--server", &url, "--scene", "no-such-scene"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out).contains("no-such-scene") && text(&out).contains("bundled scenes are"), "{}", text(&out));

    let out = cut_bot(&["run", example, "--server", "http://127.0.0.1:1"]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out).contains("cannot reach the server at http://127.0.0.1:1"), "{}", text(&out));

    let bad = dir.0.join("bad.json");
    std::fs::write(&bad, std::fs::read_to_string(example).unwrap().replace("\"position_m\"", "\"positon_m\"")).unwrap();
    let out = cut_bot(&["run", bad.to_str().unwrap(), "--server", &url]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out).contains("tools[0].keyframes[0].positon_m"), "the JSON path of the mistake: {}", text(&out));

    let out = cut_bot(&["run", dir.0.join("missing.json").to_str().unwrap(), "--server", &url]);
    assert_eq!(out.status.code(), Some(2));
    assert!(text(&out).contains("cannot read the script"), "{}", text(&out));
}

#[tokio::test(flavor = "multi_thread")]
async fn a_recorded_haptic_session_becomes_a_regression_script() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    // A trainee cuts through the haptic stream for about a second.
    let mut client = cutsim_proto::v1::haptics_client::HapticsClient::new(server.channel().await);
    let (tx, rx) = tokio::sync::mpsc::channel(16);
    let mut request = tonic::Request::new(futures_stream(rx));
    request.metadata_mut().insert("cutsim-session", session.id.parse().unwrap());
    request.metadata_mut().insert("cutsim-token", session.control.parse().unwrap());
    let mut feedback = client.stream(request).await.unwrap().into_inner();
    let reader = tokio::spawn(async move { while let Ok(Some(_)) = feedback.message().await {} });
    let mut tick = tokio::time::interval(Duration::from_millis(1));
    for i in 0..800u32 {
        tick.tick().await;
        if (400..450).contains(&i) {
            continue; // the trainee's device pauses: the server holds the last pose
        }
        let x = -0.02 + 0.03 * f64::from(i) / 800.0;
        let command = pb::ToolCommand { tool: 0, pose: Some(pose(x, 0.005 * (f64::from(i) / 100.0).sin(), -0.005)), active: true, cut: true, client_time_ns: u64::from(i) + 1, feedback_every_steps: 1, grip: None };
        tx.send(command).await.unwrap();
        // Meanwhile the other hand's forceps (an analog gripper) press into the skin
        // beside the incision, squeeze a fold at 40 % of their grip, and lift it.
        let z = 0.002 - 0.008 * (f64::from(i) / 300.0).min(1.0) + 0.006 * (f64::from(i.max(500) - 500) / 300.0);
        let forceps = pb::ToolCommand { tool: 2, pose: Some(pose(0.01, 0.015, z)), active: true, cut: i >= 350, client_time_ns: u64::from(i) + 1, feedback_every_steps: 1, grip: Some(0.4) };
        tx.send(forceps).await.unwrap();
    }
    drop(tx);
    let _ = reader.await;
    // A checkpoint, then the recording becomes a script.
    let info = server.sessions().await.get_session(authed(pb::GetSessionRequest { session_id: session.id.clone(), with_state_hash: true }, &session.observe)).await.unwrap().into_inner();
    assert!(info.counters.unwrap().cuts >= 1);
    let recording = server.recordings.0.join(format!("{}.jsonl", session.id));
    let dir = TempDir::new("record");
    let script = dir.0.join("trainee.json");
    wait_for_checkpoint(&recording, info.state_hash_step).await;
    let out = cut_bot(&["record", recording.to_str().unwrap(), "-o", script.to_str().unwrap()]);
    assert!(out.status.success(), "{}", text(&out));
    let parsed: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&script).unwrap()).unwrap();
    assert_eq!(parsed["expect"]["state_hash"], info.state_hash.as_str(), "the script checks the recorded state");
    assert_eq!(parsed["steps"], info.state_hash_step);
    let forceps = parsed["tools"].as_array().unwrap().iter().find(|t| t["tool"] == "forceps").expect("a track for the forceps");
    assert!(forceps["keyframes"].as_array().unwrap().iter().all(|k| k["grip"] == 0.4), "the forceps' keyframes keep the gripper's squeeze");
    // Run in lockstep on a fresh session: the same state, bit for bit.
    let out = cut_bot(&["run", script.to_str().unwrap(), "--server", &format!("http://{}", server.grpc)]);
    assert!(out.status.success(), "the trainee's session reproduces: {}", text(&out));
    assert!(text(&out).contains(&format!("state_hash       {}", info.state_hash)), "{}", text(&out));
}

fn futures_stream<T: Send + 'static>(mut rx: tokio::sync::mpsc::Receiver<T>) -> impl futures_util::Stream<Item = T> + Send {
    futures_util::stream::poll_fn(move |cx| rx.poll_recv(cx))
}
