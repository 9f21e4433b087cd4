//! WebSocket viewers end with exactly the server's surface.

use std::time::Duration;

use cutsim_proto::v1 as pb;

use crate::harness::*;
use cutsim_load::viewer::Viewer;

async fn server_surface_hash(server: &Server, session: &Created) -> (String, usize) {
    let s = server.sessions().await.get_snapshot(authed(pb::GetSnapshotRequest { session_id: session.id.clone() }, &session.observe)).await.unwrap().into_inner();
    (s.surface_hash.clone(), s.triangle_ids.len())
}

#[tokio::test]
async fn viewers_before_and_after_a_cut_end_with_the_server_surface() {
    viewers_follow_a_scripted_cut("skin-patch", "skin-patch-straight.json").await;
}

/// The branched-grid model behind the same server: a scalpel slits the U-tube's base
/// (voxel removal) through gRPC while a viewer watches over WebSocket.
#[tokio::test]
async fn viewers_follow_a_voxel_removal_cut_of_the_branched_grid() {
    viewers_follow_a_scripted_cut("u-tube", "u-tube-slit-base.json").await;
}

/// Runs `script` on the session ([`run_script`]) while `viewer` takes in its frames,
/// `watch` seeing the viewer after each; returns the script's report.
async fn run_script_watched(server: &Server, session: &Created, script: &str, viewer: &mut Viewer, watch: impl Fn(&Viewer) -> bool) -> pb::ScriptReport {
    let run = run_script(server, session, script);
    tokio::pin!(run);
    loop {
        tokio::select! {
            report = &mut run => return report.expect("the script runs"),
            _ = viewer.pump_until(Duration::from_millis(50), &watch) => {}
        }
    }
}

async fn viewers_follow_a_scripted_cut(scene: &str, script_file: &str) {
    let server = Server::start();
    let session = create(&server, scene, pb::SessionMode::Lockstep).await;
    let mut before = Viewer::connect(&server.http, &session.id, &session.observe).await.unwrap();
    assert!(before.pump_until(Duration::from_secs(10), |v| v.replica.is_some()).await);
    let hello = before.hello.clone().unwrap();
    assert!(hello.observer);
    let triangles_before = before.triangles();

    // The cut runs while the first viewer watches.
    let report = run_script_watched(&server, &session, &example_script(script_file), &mut before, |_| false).await;
    assert!(report.passed, "the script's expectations hold: {report:?}");
    let (server_hash, server_triangles) = server_surface_hash(&server, &session).await;
    assert_ne!(server_triangles, triangles_before, "the cut changed the surface");

    let mut after = Viewer::connect(&server.http, &session.id, &session.observe).await.unwrap();
    for (name, viewer) in [("before", &mut before), ("after", &mut after)] {
        let matched = viewer.pump_until(Duration::from_secs(10), |v| v.surface_hash().as_deref() == Some(server_hash.as_str())).await;
        assert!(matched, "viewer {name} ends with the server's surface ({:?} vs {server_hash})", viewer.surface_hash());
        assert_eq!(viewer.triangles(), server_triangles);
    }
    assert!(before.deltas > 0, "the viewer that watched the cut got deltas");
    assert!(before.positions_frames > 0);
}

/// A viewer sees the forceps' jaws where they are: open (8 mm) before they close, and
/// stopped on the lip they grasp in the retract example, one skin thickness apart
/// (2 mm), with the grasp flagged; the other tools have no jaws.
#[tokio::test]
async fn viewers_see_the_forceps_jaws_stopped_on_what_they_grasp() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Lockstep).await;
    assert_eq!(session.info.tools[2].name, "forceps");
    let mut viewer = Viewer::connect(&server.http, &session.id, &session.observe).await.unwrap();
    assert!(viewer.pump_until(Duration::from_secs(10), |v| v.replica.is_some()).await);
    // (step, grasping, jaws' gap) of the forceps in every tool frame; the scalpel's gap.
    let seen = std::cell::RefCell::new(Vec::new());
    let scalpel_gap = std::cell::Cell::new(None);
    // (step, how hard the lip pushes the jaws apart) of the forceps; the scalpel's.
    let pushed = std::cell::RefCell::new(Vec::new());
    let scalpel_pushed = std::cell::Cell::new(None);
    let watch = |v: &Viewer| {
        if let Some(states) = &v.last_tools {
            if let Some(forceps) = states.tools.get(2).filter(|t| t.active) {
                seen.borrow_mut().push((states.step, forceps.grasping, forceps.jaws_gap_m));
                pushed.borrow_mut().push((states.step, forceps.jaws_force_n));
            }
            scalpel_gap.set(scalpel_gap.get().or(states.tools.first().map(|t| t.jaws_gap_m)));
            scalpel_pushed.set(scalpel_pushed.get().or(states.tools.first().map(|t| t.jaws_force_n)));
        }
        false
    };
    let report = run_script_watched(&server, &session, &example_script("skin-patch-retract.json"), &mut viewer, watch).await;
    let seen = seen.into_inner();
    let mut gaps: Vec<(u64, bool, f64)> = seen.iter().map(|&(step, grasping, gap)| (step, grasping, gap.map_or(f64::NAN, |g| g * 1e3))).collect();
    gaps.dedup_by_key(|g| g.0);
    println!("forceps in {} tool frames (step, grasping, jaws' gap mm), the first: {:?}", gaps.len(), &gaps[..gaps.len().min(12)]);
    assert_eq!(scalpel_gap.get(), Some(None), "a scalpel has no jaws");
    // The forceps come at step 900 open and closing, grasp the lip, draw it away (to step
    // 1500), hold it, and let go at 1700.
    assert!(gaps.iter().all(|g| (2.0 - 1e-9..=8.0 + 1e-9).contains(&g.2)), "the jaws never close past the lip they grasp: {gaps:?}");
    let held: Vec<&(u64, bool, f64)> = gaps.iter().filter(|g| (1200..1700).contains(&g.0)).collect();
    assert!(!held.is_empty() && held.iter().all(|g| g.1 && (g.2 - 2.0).abs() < 1e-9), "while they hold the lip, the jaws are stopped one skin thickness apart, grasping: {held:?}");
    // Stopped on it, the jaws are pushed apart as hard as they pinch: the whole 3 N grip
    // (the example squeezes with no analog gripper); let go of, by nothing.
    let pushed = pushed.into_inner();
    assert_eq!(scalpel_pushed.get(), Some(None), "a scalpel has no jaws to push apart");
    let pushed_while_held: Vec<_> = pushed.iter().filter(|p| (1200..1700).contains(&p.0)).collect();
    assert!(!pushed_while_held.is_empty() && pushed_while_held.iter().all(|p| p.1 == Some(3.0)), "while they hold the lip, the jaws are pushed apart with the grip: {pushed_while_held:?}");
    assert!(pushed.iter().filter(|p| p.0 >= 1800).all(|p| p.1 == Some(0.0)), "let go of, nothing pushes the jaws apart: {pushed:?}");
    // The run's report and the trainee's metrics keep the hardest pinch: the grip.
    let pinched: Vec<f64> = report.tools.iter().map(|t| t.max_jaws_force_n).collect();
    assert_eq!(pinched, [0.0, 0.0, 3.0], "only the forceps pinch, with their grip");
    assert_eq!(report.assessment.as_ref().map(|a| (a.peak_grip_force_n, a.time_above_grip_limit_s)), Some((3.0, None)), "the scene's task sets no grip limit");
    assert!(viewer.errors.is_empty(), "{:?}", viewer.errors);
}

#[tokio::test]
async fn a_real_time_session_streams_to_a_control_token_viewer() {
    let server = Server::start();
    let session = create(&server, "skin-patch", pb::SessionMode::Realtime).await;
    let mut viewer = Viewer::connect(&server.http, &session.id, &session.control).await.unwrap();
    assert!(viewer.pump_until(Duration::from_secs(10), |v| v.replica.is_some()).await);
    assert!(!viewer.hello.clone().unwrap().observer);
    // Closing the session closes the viewer with a reason.
    server.sessions().await.close_session(authed(pb::CloseSessionRequest { session_id: session.id.clone() }, &session.control)).await.unwrap();
    viewer.pump_until(Duration::from_secs(10), |v| v.closed.is_some()).await;
    assert_eq!(viewer.closed.as_deref(), Some("session closed"));
}
