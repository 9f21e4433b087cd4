//! The branched grid against an independent finite-element code (scikit-fem, run by
//! `tools/reference/run.sh` in the test command; its results are committed in
//! tools/reference/results, or read from `$CUTSIM_REFERENCE_DIR`).

use cutsim_sim::accuracy::problems::{problems, sample_displacements};
use cutsim_sim::accuracy::reference::{Weighting, field_error, load_reference, solve_linear};
use cutsim_sim::math::Vec3;
use cutsim_sim::scene::VolumetricSpec;

/// Same mesh, same trilinear elements: only round-off and the solvers' tolerances differ
/// — fully integrated against scikit-fem's Hex1, mean dilatation against its Hex1 with a
/// constant pressure per hexahedron (a mixed form, the pressure eliminated).
#[test]
fn level_0_matches_scikit_fem_hex1_and_hex1_p0_to_1e_6() {
    for problem in problems().expect("the reference problems build") {
        let reference = load_reference(&problem).unwrap_or_else(|e| panic!("{e}"));
        for (volumetric, solution, label) in [(VolumetricSpec::Full, &reference.hex1, "Hex1"), (VolumetricSpec::MeanDilatation, &reference.hex1p0, "Hex1–P0")] {
            let (parts, iterations, residual) = solve_linear(&problem.with_volumetric(volumetric), 0, Weighting::Condensed, 1e-12).expect("the problem builds");
            assert!(residual <= 1e-12, "{}: CG stopped at residual {residual:e} after {iterations} iterations", problem.name);
            let error = field_error(&sample_displacements(&parts.topo, &reference.samples), &solution.displacements());
            eprintln!("{}: {} samples, {iterations} CG iterations, error vs {label} rms {:.2e}, max {:.2e}", problem.name, reference.samples.len(), error.rms, error.max);
            assert!(error.max < 1e-6, "{}: level 0 differs from scikit-fem {label} by {:.2e} (relative, max over samples)", problem.name, error.max);
        }
    }
}

/// At ν = 0.49 the fully integrated trilinear hexahedron locks; the mean-dilatation one
/// comes within 5 % of Taylor–Hood hexahedra (which do not lock) on the same mesh.
#[test]
fn at_nu_0_49_mean_dilatation_is_within_5_percent_of_taylor_hood_and_full_integration_locks() {
    let problem = problems().expect("the reference problems build").into_iter().find(|p| p.name == "cantilever-incompressible").expect("the problem");
    let reference = load_reference(&problem).unwrap_or_else(|e| panic!("{e}"));
    let taylor_hood = reference.mixed.as_ref().expect("the Taylor–Hood solution").displacements();
    let error = |volumetric| {
        let (parts, _, _) = solve_linear(&problem.with_volumetric(volumetric), 0, Weighting::Condensed, 1e-12).expect("the problem builds");
        field_error(&sample_displacements(&parts.topo, &reference.samples), &taylor_hood).rms
    };
    let (free, locked) = (error(VolumetricSpec::MeanDilatation), error(VolumetricSpec::Full));
    eprintln!("ν = 0.49 at level 0 against Taylor–Hood: mean dilatation {:.2} %, fully integrated {:.2} %", 100.0 * free, 100.0 * locked);
    assert!(free < 0.05, "mean dilatation is {:.2} % off Taylor–Hood", 100.0 * free);
    assert!(locked > 2.0 * free, "full integration ({:.2} %) should lock visibly", 100.0 * locked);
}

/// Coarse levels against the finest reference. Fully integrated (the paper's element):
/// coarser elements are stiffer, the error grows with the level, and on a body with
/// partly filled cells (the liver) the condensed stiffness beats the simpler fill-ratio
/// weighting. Mean dilatation (the default): coarse levels much closer than the fully
/// integrated ones, the coarse elements no longer inheriting every voxel's volume
/// constraint.
#[test]
fn coarse_levels_approach_the_reference_and_condensation_beats_fill_ratio_where_cells_are_partial() {
    for problem in problems().expect("the reference problems build") {
        let reference = load_reference(&problem).unwrap_or_else(|e| panic!("{e}"));
        let bbar = problem.with_volumetric(VolumetricSpec::MeanDilatation);
        let problem = problem.with_volumetric(VolumetricSpec::Full);
        let (label, finest) = reference.finest();
        let finest = finest.displacements();
        let hex1 = field_error(&reference.hex1.displacements(), &finest);
        let mut previous = hex1.rms;
        for level in 1..=3 {
            let error = |weighting| {
                let (parts, _, _) = solve_linear(&problem, level, weighting, 1e-10).expect("the problem builds");
                field_error(&sample_displacements(&parts.topo, &reference.samples), &finest)
            };
            let (condensed, fill_ratio) = (error(Weighting::Condensed), error(Weighting::FillRatio));
            let (parts, _, _) = solve_linear(&bbar, level, Weighting::Condensed, 1e-10).expect("the problem builds");
            let mean_dilatation = field_error(&sample_displacements(&parts.topo, &reference.samples), &finest);
            eprintln!(
                "{} level {level} vs {label}: condensed rms {:.4}, fill ratio rms {:.4}, mean dilatation {:.4}",
                problem.name, condensed.rms, fill_ratio.rms, mean_dilatation.rms
            );
            // Where full integration is already close (the liver at level 1, 2.6 %), one
            // pressure per coarse element is a little softer than the voxels' (4.9 %).
            assert!(
                mean_dilatation.rms < condensed.rms.max(0.05),
                "{} level {level}: mean dilatation {:.4} should beat full integration {:.4}",
                problem.name,
                mean_dilatation.rms,
                condensed.rms
            );
            assert!(condensed.rms > previous, "{}: level {level} ({:.4}) should be further from {label} than the finer level ({previous:.4})", problem.name, condensed.rms);
            // Level 3 of the cantilevers is 4 elements, one through the thickness: bending
            // then has parasitic shear that one pressure per element does not remove.
            assert!(mean_dilatation.rms < if level < 3 { 0.1 } else { 0.45 }, "{}: level {level} is {:.1} % off {label}", problem.name, 100.0 * mean_dilatation.rms);
            if problem.name == "liver-gravity" && level >= 2 {
                assert!(condensed.rms < 0.6 * fill_ratio.rms, "liver level {level}: condensed {:.4} vs fill ratio {:.4}", condensed.rms, fill_ratio.rms);
            }
            if problem.name != "liver-gravity" {
                // Full cells: both weightings give the full cell's matrix.
                assert!((condensed.rms - fill_ratio.rms).abs() < 1e-9, "{}: full cells should weigh alike", problem.name);
            }
            previous = condensed.rms;
        }
    }
}

/// A label map's organs need not touch the held region: a piece joined to no hold has no
/// static equilibrium under gravity. The accuracy study's static problems leave it
/// unloaded (it stays at rest) and solve the held body as if the piece were not there.
#[test]
fn a_free_piece_carries_no_load_and_the_held_body_solves_as_if_alone() {
    use cutsim_sim::accuracy::problems::{Load, Problem, held_samples, with_gravity_down};
    use cutsim_sim::grid::support::held_pieces;
    use cutsim_sim::volume::{LabelVolume, nifti};
    let dir = std::env::temp_dir().join(format!("cutsim-free-piece-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    // A 6 × 4 × 4 block held at its −x side, and (in one of the two maps) a 4 × 4 × 4
    // block beyond a two-voxel gap.
    let problem = |with_free_piece: bool| {
        let mut volume = LabelVolume::new([12, 4, 4], [0.002; 3], Vec3::zeros());
        for (i, j, k) in (0..12).flat_map(|i| (0..4).flat_map(move |j| (0..4).map(move |k| (i, j, k)))) {
            if i < 6 || (with_free_piece && i >= 8) {
                volume.set(i, j, k, 1);
            }
        }
        let path = dir.join(format!("pieces-{with_free_piece}.nii"));
        nifti::write_nifti(&volume, &path).unwrap();
        let json = format!(
            r#"{{ "name": "pieces", "time_step_s": 0.001,
            "model": {{ "branched-grid": {{
                "volume": {{ "nifti": {{ "path": "{}" }} }},
                "materials": [ {{ "label": 1, "young_pa": 20000, "poisson": 0.4, "density_kg_per_m3": 1000 }} ],
                "level": 0,
                "fixed": [ {{ "side": {{ "side": "-x" }} }} ] }} }} }}"#,
            path.display()
        );
        let scene = cutsim_sim::scene::Scene::from_json_str(&json, "two pieces", None).expect("the scene is valid");
        Problem { name: "pieces", summary: "", scene: with_gravity_down(&scene, 9.81), load: Load::Gravity, frequency: false, quadratic: false, mixed: false, sample_stride: 1 }
    };
    let (both, alone) = (problem(true), problem(false));
    let (parts, iterations, residual) = solve_linear(&both, 0, Weighting::Condensed, 1e-10).expect("the problem builds");
    let (alone_parts, _, _) = solve_linear(&alone, 0, Weighting::Condensed, 1e-10).expect("the problem builds");
    std::fs::remove_dir_all(&dir).ok();
    assert!(residual <= 1e-10, "CG stopped at residual {residual:e} after {iterations} iterations");
    let topo = &parts.topo;
    let held = held_pieces(topo);
    let alive = (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n]).count();
    assert_eq!((held.iter().filter(|&&h| h).count(), alive), (7 * 5 * 5, 7 * 5 * 5 + 5 * 5 * 5), "the held block's nodes, of both blocks'");
    let displacement = |topo: &cutsim_sim::grid::topology::Topology, n: usize| topo.nodes.x[n] - topo.nodes.rest[n];
    let mut largest = 0.0f64;
    for n in (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n]) {
        if !held[n] {
            assert_eq!(displacement(topo, n), Vec3::zeros(), "the free piece stays at rest");
            continue;
        }
        let twin = (0..alone_parts.topo.nodes.len()).find(|&m| (alone_parts.topo.nodes.rest[m] - topo.nodes.rest[n]).norm() < 1e-9).expect("the held node exists alone too");
        let (u, alone_u) = (displacement(topo, n), displacement(&alone_parts.topo, twin));
        assert!((u - alone_u).norm() <= 1e-8 * alone_u.norm().max(1e-9), "node {n}: {u:?} beside the free piece, {alone_u:?} alone");
        largest = largest.max(u.norm());
    }
    assert!(largest > 1e-6, "gravity bends the held block ({largest:e} m)");
    // Only the held block's sample points are compared.
    let samples = both.samples(&parts);
    let kept = held_samples(topo, &samples);
    assert_eq!((kept.len(), samples.len()), (7 * 5 * 5, 7 * 5 * 5 + 5 * 5 * 5), "a sample per node: the held block's kept");
}
