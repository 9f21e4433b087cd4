//! Cut-script JSON (RunScriptRequest.script_json), parsed and validated.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(text) = std::str::from_utf8(data) {
        let _ = cutsim_sim::script::CutScript::from_json_str(text, "fuzz");
    }
});
