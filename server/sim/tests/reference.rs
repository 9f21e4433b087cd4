//! The branched grid against an independent finite-element code (scikit-fem, run by
//! `tools/reference/run.sh` in the test command; its results are committed in
//! tools/reference/results, or read from `$CUTSIM_REFERENCE_DIR`).

use cutsim_sim::accuracy::problems::{problems, sample_displacements};
use cutsim_sim::accuracy::reference::{Weighting, field_error, load_reference, solve_linear};

/// Same mesh, same trilinear elements: only round-off and the solvers' tolerances differ.
#[test]
fn level_0_matches_scikit_fem_hex1_to_1e_6() {
    for problem in problems().expect("the reference problems build") {
        let reference = load_reference(&problem).unwrap_or_else(|e| panic!("{e}"));
        let (parts, iterations, residual) = solve_linear(&problem, 0, Weighting::Condensed, 1e-12).expect("the problem builds");
        assert!(residual <= 1e-12, "{}: CG stopped at residual {residual:e} after {iterations} iterations", problem.name);
        let error = field_error(&sample_displacements(&parts.topo, &reference.samples), &reference.hex1.displacements());
        eprintln!("{}: {} samples, {iterations} CG iterations, error vs Hex1 rms {:.2e}, max {:.2e}", problem.name, reference.samples.len(), error.rms, error.max);
        assert!(error.max < 1e-6, "{}: level 0 differs from scikit-fem Hex1 by {:.2e} (relative, max over samples)", problem.name, error.max);
    }
}

/// Coarser elements are stiffer: the error against the finest reference (Hex2 where
/// computed, else Hex1) grows with the level. And on a body with partly filled cells
/// (the liver), the condensed stiffness against the simpler fill-ratio weighting.
#[test]
fn coarse_levels_approach_the_reference_and_condensation_beats_fill_ratio_where_cells_are_partial() {
    for problem in problems().expect("the reference problems build") {
        let reference = load_reference(&problem).unwrap_or_else(|e| panic!("{e}"));
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
            eprintln!("{} level {level} vs {label}: condensed rms {:.4}, fill ratio rms {:.4}", problem.name, condensed.rms, fill_ratio.rms);
            assert!(condensed.rms > previous, "{}: level {level} ({:.4}) should be further from {label} than the finer level ({previous:.4})", problem.name, condensed.rms);
            assert!(condensed.rms < 0.4, "{}: level {level} is {:.1} % off {label}", problem.name, 100.0 * condensed.rms);
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
