//! Scene JSON as a network client sends it (CreateSessionRequest.scene_json): parsed,
//! validated, and checked for file references the network may not make.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        if let Ok(scene) = cutsim_sim::scene::Scene::from_json_str(text, "fuzz", None) {
            let _ = scene.check_network_file_references("fuzz");
        }
    }
});
