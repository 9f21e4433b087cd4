//! Legacy VTK polydata surface meshes.
#![no_main]
use libfuzzer_sys::fuzz_target;

fuzz_target!(|data: &[u8]| {
    let _ = cutsim_sim::geometry::vtk::parse_vtk(data);
});
