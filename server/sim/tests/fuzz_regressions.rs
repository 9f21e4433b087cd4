//! Inputs the fuzzers (fuzz/, docs/fuzzing.md) found to crash a reader, each kept in
//! tests/fuzz-regressions/ and checked to give a clear error instead.

fn input(name: &str) -> Vec<u8> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/fuzz-regressions").join(name);
    std::fs::read(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// A vox_offset of ~1e30: the cast to an index saturated and `start + needed` wrapped past
/// the length check, and slicing panicked.
#[test]
fn a_nifti_with_a_huge_vox_offset_is_refused_as_truncated() {
    let err = cutsim_sim::volume::nifti::parse_nifti(&input("nifti-vox-offset-overflow.nii")).unwrap_err();
    assert!(err.contains("truncated") || err.contains("vox_offset"), "{err}");
}
