//! VTK ImageData (.vti) label images: every encoding, zlib and appended data.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(volume) = cutsim_sim::volume::vti::parse_vti(data, None, 1e-3) {
        let _ = volume.check();
    }
});
