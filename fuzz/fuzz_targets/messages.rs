//! Every message the server decodes from a client: the gRPC requests and the haptic
//! stream's ToolCommand, the WebSocket's ViewerRequest, and the JSON they carry (an
//! inline scene, a cut script).
#![no_main]
use cutsim_proto::v1 as pb;
use libfuzzer_sys::fuzz_target;
use prost::Message;

fuzz_target!(|data: &[u8]| {
    if let Ok(request) = pb::CreateSessionRequest::decode(data) {
        if let Some(pb::create_session_request::Scene::SceneJson(json)) = request.scene {
            if let Ok(scene) = cutsim_sim::scene::Scene::from_json_str(&json, "fuzz", None) {
                let _ = scene.check_network_file_references("fuzz");
            }
        }
    }
    let _ = pb::ListSessionsRequest::decode(data);
    let _ = pb::GetSessionRequest::decode(data);
    let _ = pb::CloseSessionRequest::decode(data);
    let _ = pb::GetSnapshotRequest::decode(data);
    // The haptic stream's commands: decoding only (the server's pose checks live in its
    // binary crate, out of this fuzz crate's reach).
    let _ = pb::ToolCommand::decode(data);
    if let Ok(request) = pb::RunScriptRequest::decode(data) {
        let _ = cutsim_sim::script::CutScript::from_json_str(&request.script_json, "fuzz");
    }
    let _ = pb::ViewerRequest::decode(data);
});
