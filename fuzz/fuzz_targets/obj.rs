//! Wavefront OBJ surface meshes.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = cutsim_sim::geometry::obj::parse_obj(std::io::Cursor::new(data));
});
