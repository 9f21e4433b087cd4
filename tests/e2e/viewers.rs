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

async fn viewers_follow_a_scripted_cut(scene: &str, script_file: &str) {
    let server = Server::start();
    let session = create(&server, scene, pb::SessionMode::Lockstep).await;
    let mut before = Viewer::connect(&server.http, &session.id, &session.observe).await.unwrap();
    assert!(before.pump_until(Duration::from_secs(10), |v| v.replica.is_some()).await);
    let hello = before.hello.clone().unwrap();
    assert!(hello.observer);
    let triangles_before = before.triangles();

    // The cut runs while the first viewer watches.
    let script = example_script(script_file);
    let run = {
        let (id, control, observe, info) = (session.id.clone(), session.control.clone(), session.observe.clone(), session.info.clone());
        let server_grpc = server.grpc.clone();
        tokio::spawn(async move {
            let channel = tonic::transport::Channel::from_shared(format!("http://{server_grpc}")).unwrap().connect().await.unwrap();
            let mut client = cutsim_proto::v1::scripts_client::ScriptsClient::new(channel);
            let request = authed(pb::RunScriptRequest { session_id: id.clone(), script_json: script, progress_every_steps: 0 }, &control);
            let mut events = client.run_script(request).await.unwrap().into_inner();
            let mut report = None;
            while let Some(event) = events.message().await.unwrap() {
                if let Some(pb::script_event::Event::Report(r)) = event.event {
                    report = Some(r);
                }
            }
            let report = report.expect("a report");
            assert!(report.passed, "the script's expectations hold: {report:?}");
            let _ = (observe, info);
        })
    };
    while !run.is_finished() {
        before.pump_until(Duration::from_millis(50), |_| false).await;
    }
    run.await.unwrap();
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
