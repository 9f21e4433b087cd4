//! The scikit-fem reference solutions (written by `tools/reference/solve.py`) and the
//! errors of our solutions against them.

use std::path::{Path, PathBuf};

use serde::Deserialize;

use super::problems::Problem;
use crate::grid::GridParts;
use crate::grid::solver::solve_static;
use crate::grid::support::held_pieces;
use crate::math::Vec3;
use crate::scene::SceneError;

/// One reference solution at the sample points.
#[derive(Debug, Clone, Deserialize)]
pub struct ReferenceSolution {
    /// Displacement at each sample point (grid frame), m.
    pub displacement_m: Vec<[f64; 3]>,
    /// The lowest eigenfrequency (consistent mass), when the problem asks for it.
    #[serde(default)]
    pub first_frequency_hz: Option<f64>,
    pub dofs: usize,
    pub seconds: f64,
}

impl ReferenceSolution {
    pub fn displacements(&self) -> Vec<Vec3> {
        self.displacement_m.iter().map(|d| Vec3::new(d[0], d[1], d[2])).collect()
    }
}

/// A problem's reference on the same mesh: trilinear hexahedra fully integrated (Hex1)
/// and with a constant pressure each (Hex1–P0, the mean-dilatation element), and for the
/// small bodies triquadratic (Hex2) or Taylor–Hood (Hex2–Hex1, non-locking) hexahedra.
#[derive(Debug, Clone, Deserialize)]
pub struct Reference {
    pub problem: String,
    pub digest: String,
    pub generator: String,
    pub samples: Vec<(usize, usize)>,
    pub hex1: ReferenceSolution,
    pub hex1p0: ReferenceSolution,
    #[serde(default)]
    pub hex2: Option<ReferenceSolution>,
    #[serde(default)]
    pub mixed: Option<ReferenceSolution>,
}

impl Reference {
    /// The finest solution there is: Taylor–Hood, else Hex2, else the mean-dilatation
    /// Hex1 (which does not lock; the fully integrated Hex1 does, a few per cent at
    /// ν = 0.45).
    pub fn finest(&self) -> (&'static str, &ReferenceSolution) {
        match (&self.mixed, &self.hex2) {
            (Some(mixed), _) => ("scikit-fem Taylor–Hood Hex2–Hex1", mixed),
            (None, Some(hex2)) => ("scikit-fem Hex2", hex2),
            (None, None) => ("scikit-fem Hex1 with a constant pressure per hexahedron", &self.hex1p0),
        }
    }
}

/// Where the reference results are read from: `$CUTSIM_REFERENCE_DIR`, else the
/// committed `tools/reference/results`.
pub fn results_dir() -> PathBuf {
    match std::env::var_os("CUTSIM_REFERENCE_DIR") {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tools/reference/results"),
    }
}

/// Reads a problem's reference and checks that it was made for this exact problem.
pub fn load_reference(problem: &Problem) -> Result<Reference, String> {
    let path = results_dir().join(format!("{}.json", problem.name));
    let text = std::fs::read_to_string(&path).map_err(|e| format!("{}: {e} (make it with tools/reference/run.sh)", path.display()))?;
    let reference: Reference = serde_json::from_str(&text).map_err(|e| format!("{}: not a reference result: {e}", path.display()))?;
    let export = problem.export().map_err(|e: SceneError| e.to_string())?;
    let digest = export["digest"].as_str().unwrap_or_default();
    if reference.digest != digest {
        return Err(format!(
            "{}: made for problem digest {}, but the problem now has digest {digest} (the mesh, loads or samples changed); regenerate it with tools/reference/run.sh",
            path.display(),
            reference.digest
        ));
    }
    let n = reference.samples.len();
    let solutions = [Some(&reference.hex1), Some(&reference.hex1p0), reference.hex2.as_ref(), reference.mixed.as_ref()];
    if solutions.iter().flatten().any(|s| s.displacement_m.len() != n) {
        return Err(format!("{}: {n} samples but a different number of displacements", path.display()));
    }
    Ok(reference)
}

/// A displacement field's error against a reference field.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FieldError {
    /// sqrt(Σ|u − u_ref|² / Σ|u_ref|²) over the sample points.
    pub rms: f64,
    /// max|u − u_ref| / max|u_ref|.
    pub max: f64,
}

pub fn field_error(u: &[Vec3], reference: &[Vec3]) -> FieldError {
    assert_eq!(u.len(), reference.len());
    let diff2: f64 = u.iter().zip(reference).map(|(a, b)| (a - b).norm_squared()).sum();
    let ref2: f64 = reference.iter().map(|r| r.norm_squared()).sum();
    let diff_max = u.iter().zip(reference).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
    let ref_max = reference.iter().map(|r| r.norm()).fold(0.0, f64::max);
    FieldError { rms: (diff2 / ref2).sqrt(), max: diff_max / ref_max }
}

/// How the coarse elements get their stiffness.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Weighting {
    /// Condensed from the voxels (the branched grid's own).
    Condensed,
    /// The full cell's, scaled by its fill fraction.
    FillRatio,
}

/// Iterations a linear static solve may take: ten times the most a solvable bundled
/// problem needed (the layered abdomen's level 3: 480 V-cycles; its level 0: 238); a
/// problem with no solution (a piece held at a point, free to turn) stops here or
/// stalls before (`grid::statics`), and its residual says so.
pub const LINEAR_SOLVE_CAP: u32 = 5_000;

/// The linear (small-strain) static solution of a problem at a level: K u = f by
/// conjugate gradient in double precision (`grid::statics`), to `tolerance`, at most
/// [`LINEAR_SOLVE_CAP`] iterations. A free
/// piece (one not connected to a hold, [`held_pieces`]) has no equilibrium under a load:
/// it carries none here and stays at rest, and the held pieces' solution is unchanged.
pub fn solve_linear(problem: &Problem, level: u32, weighting: Weighting, tolerance: f64) -> Result<(GridParts, u32, f64), String> {
    let mut parts = problem.parts(level).map_err(|e| e.to_string())?;
    if weighting == Weighting::FillRatio {
        super::problems::apply_fill_ratio_weighting(&mut parts);
    }
    let mut loads = problem.loads(&parts);
    for (load, held) in loads.iter_mut().zip(held_pieces(&parts.topo)) {
        if !held {
            *load = Vec3::zeros();
        }
    }
    let (iterations, residual) = solve_static(&mut parts.topo, &loads, tolerance, LINEAR_SOLVE_CAP);
    Ok((parts, iterations, residual))
}
