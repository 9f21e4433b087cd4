//! Label volumes from the shared anatomical data: the NIfTI reader against the data's
//! documented counts, the same volume written as NIfTI and as VTI reads back the same,
//! and the SOFA liver surfaces voxelize to a liver-sized volume.

use cutsim_sim::geometry::{obj::read_obj_file, vtk::read_vtk_file};
use cutsim_sim::scene::data_dir;
use cutsim_sim::volume::nifti::{read_nifti, write_nifti};
use cutsim_sim::volume::voxelize::voxelize;
use cutsim_sim::volume::vti::{VtiEncoding, read_vti, write_vti};

fn temp_dir(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("cutsim-volumes-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

#[test]
fn the_totalsegmentator_labels_read_as_documented() {
    let v = read_nifti(&data_dir().join("totalsegmentator/example_seg.nii.gz")).unwrap();
    assert_eq!(v.dims, [122, 101, 30]);
    assert_eq!(v.count(5), 38_634, "liver voxels (data/README.md)");
    for s in v.spacing_m {
        assert!((s - 0.003).abs() < 1e-9);
    }
    // RAS, 3 mm: the sform is diagonal with the origin at (−177.96, 11.32, 94.30) mm.
    assert!((v.direction - cutsim_sim::math::Matrix3::identity()).norm() < 1e-9);
    assert!((v.origin_m.x + 0.177_956_329).abs() < 1e-6 && (v.origin_m.z - 0.094_301_757).abs() < 1e-6);
}

#[test]
fn nifti_and_vti_of_the_same_volume_read_back_the_same() {
    let original = read_nifti(&data_dir().join("totalsegmentator/abdomen_tissue_labels_derived.nii.gz")).unwrap();
    let dir = temp_dir("roundtrip");
    let nii = dir.join("labels.nii.gz");
    write_nifti(&original, &nii).unwrap();
    let from_nifti = read_nifti(&nii).unwrap();
    for (name, encoding) in [("raw-zlib", VtiEncoding::AppendedRaw { zlib: true }), ("base64", VtiEncoding::InlineBase64 { zlib: false })] {
        let vti = dir.join(format!("labels-{name}.vti"));
        write_vti(&original, &vti, encoding).unwrap();
        let from_vti = read_vti(&vti, None, 1e-3).unwrap();
        assert_eq!(from_vti.dims, from_nifti.dims);
        assert_eq!(from_vti.labels, from_nifti.labels, "{name}");
        for a in 0..3 {
            // NIfTI stores f32 millimetres.
            assert!((from_vti.spacing_m[a] - from_nifti.spacing_m[a]).abs() < 1e-9);
            assert!((from_vti.origin_m[a] - from_nifti.origin_m[a]).abs() < 1e-7);
        }
        assert!((from_vti.direction - from_nifti.direction).norm() < 1e-6);
    }
    // Truncated files fail clearly.
    let bytes = std::fs::read(&nii).unwrap();
    let cut = dir.join("cut.nii.gz");
    std::fs::write(&cut, &bytes[..bytes.len() / 2]).unwrap();
    let e = read_nifti(&cut).unwrap_err();
    assert!(e.contains("cut.nii.gz") && (e.contains("truncated") || e.contains("corrupt")), "{e}");
    let _ = std::fs::remove_dir_all(dir);
}

#[test]
fn the_sofa_livers_voxelize_to_a_liver() {
    // liver.vtk: mm, with three degenerate fragments that must be dropped.
    let mut mesh = read_vtk_file(&data_dir().join("sofa-liver/liver.vtk")).unwrap();
    mesh.scale_and_offset(1e-3, cutsim_sim::math::Vec3::zeros());
    let (v, report) = voxelize(&mesh, 0.004, 1, 1 << 24).unwrap();
    assert_eq!(report.parts_kept, 1);
    assert_eq!(report.parts_dropped.len(), 3, "{:?}", report.parts_dropped);
    let litres = report.voxels_inside as f64 * 0.004f64.powi(3) * 1e3;
    assert!((0.8..3.0).contains(&litres), "{litres} L");
    assert_eq!(v.count(1), report.voxels_inside);
    let smooth = read_obj_file(&data_dir().join("sofa-liver/liver-smooth.obj")).unwrap();
    let (_, report) = voxelize(&smooth, 0.1, 1, 1 << 24).unwrap();
    assert_eq!((report.parts_kept, report.parts_dropped.len()), (1, 0));
}
