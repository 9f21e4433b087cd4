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
