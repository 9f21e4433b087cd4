//! NIfTI-1 label images (.nii, and .nii.gz by their gzip magic).
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    if let Ok(volume) = cutsim_sim::volume::nifti::parse_nifti(data) {
        let _ = volume.check();
    }
});
