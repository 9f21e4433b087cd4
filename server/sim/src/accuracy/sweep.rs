//! Measuring settings: what a step costs (a probe pressed into the body, the workload of
//! an instructor-less haptic session) and what the setting gets (its static error
//! against the reference; on the cantilever also the first frequency as the dynamics
//! deliver it).

use super::problems::{Problem, sample_displacements};
use super::reference::{Weighting, field_error, solve_linear};
pub use crate::grid::fidelity::{StepTiming, time_probe};
use crate::grid::topology::Topology;
use crate::grid::{BranchedGrid, build_from_scene};
use crate::math::Vec3;
use crate::quantity::{AccelerationMPerS2, CgIterations, DampingPerS, SpringDampingS, TimeStepS};
use crate::scene::{MassSpec, ModelSpec, PreconditionerSpec, Scene};
use crate::tool::{ToolCommand, ToolFeedback};

/// One point of the sweep.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Setting {
    pub level: u32,
    pub mass: MassSpec,
    pub cg_max_iterations: u32,
    pub dt_s: f64,
    pub preconditioner: PreconditionerSpec,
}

impl Setting {
    /// Block Jacobi, the default preconditioner.
    pub fn new(level: u32, mass: MassSpec, cg_max_iterations: u32, dt_s: f64) -> Self {
        Setting { level, mass, cg_max_iterations, dt_s, preconditioner: PreconditionerSpec::Jacobi }
    }

    /// The same setting with the multigrid preconditioner.
    pub fn multigrid(self) -> Self {
        Setting { preconditioner: PreconditionerSpec::Multigrid, ..self }
    }

    pub fn label(&self) -> String {
        let mass = match self.mass {
            MassSpec::Lumped => "lumped",
            MassSpec::Consistent => "consistent",
        };
        let multigrid = if self.preconditioner == PreconditionerSpec::Multigrid { " multigrid" } else { "" };
        format!("L{} {mass} CG≤{}{multigrid} dt {} ms", self.level, self.cg_max_iterations, self.dt_s * 1e3)
    }

    /// The scene with this setting.
    pub fn apply(&self, scene: &Scene) -> Scene {
        let mut scene = scene.with_grid_level(self.level);
        scene.time_step_s = TimeStepS::new(self.dt_s).unwrap_or_else(|e| panic!("{e}"));
        if let ModelSpec::BranchedGrid(spec) = &mut scene.model {
            spec.mass = self.mass;
            spec.solver.cg_max_iterations = CgIterations::new(self.cg_max_iterations).unwrap_or_else(|e| panic!("{e}"));
            spec.solver.preconditioner = self.preconditioner;
        }
        scene
    }
}

/// Builds a scene's grid (errors as text: a refusal names its reason).
pub fn build_grid(scene: &Scene) -> Result<BranchedGrid, String> {
    let ModelSpec::BranchedGrid(spec) = &scene.model else { return Err("not a branched-grid scene".into()) };
    build_from_scene(scene, spec).map_err(|e| e.to_string())
}

/// A reference displacement field for a problem: the given one, or the linear static
/// solution at `level` of our own solver.
pub fn own_reference(problem: &Problem, level: u32, samples: &[(usize, usize)]) -> Result<Vec<Vec3>, String> {
    let (parts, _, residual) = solve_linear(problem, level, Weighting::Condensed, 1e-10)?;
    if residual > 1e-8 {
        return Err(format!("{}: the reference solve stopped at residual {residual:e}", problem.name));
    }
    Ok(sample_displacements(&parts.topo, samples))
}

/// The static error (relative rms) of the linear solution at `level` against `reference`.
pub fn static_error(problem: &Problem, level: u32, weighting: Weighting, samples: &[(usize, usize)], reference: &[Vec3]) -> Result<f64, String> {
    let (parts, _, _) = solve_linear(problem, level, weighting, 1e-10)?;
    Ok(field_error(&sample_displacements(&parts.topo, samples), reference).rms)
}

/// The session error is measured where the linear reference holds: gravity is scaled
/// down until the reference's largest displacement is at most this fraction of the
/// body's size. At full gravity a 6 kPa liver's linear solution moves 0.74 m — longer
/// than the liver — and what the corotational session computes is a different (large
/// rotation) answer, not an error of the solver.
pub const SESSION_LOAD_DISPLACEMENT_FRACTION: f64 = 0.005;

/// What a session computes for `problem` at `setting`: the grid built as a session
/// builds it (ghost material, the setting's cap, the scene's tolerance), settled under
/// the problem's gravity — scaled down to the small-displacement range
/// ([`SESSION_LOAD_DISPLACEMENT_FRACTION`]) — by its own dynamics (the mass damping set
/// to 30/s, near critical for soft organs; Rayleigh damping does not move the
/// equilibrium) until no node of a held piece moves faster than 10 µm/s times that scale or
/// `max_duration_s` has passed; its displacements scaled back up, against `reference`
/// at the sample points (relative rms). Returns the error and the load scale.
pub fn session_error(problem: &Problem, setting: &Setting, samples: &[(usize, usize)], reference: &[Vec3], max_duration_s: f64) -> Result<(f64, f64), String> {
    let mut scene = setting.apply(&problem.scene);
    if let ModelSpec::BranchedGrid(spec) = &mut scene.model {
        spec.damping.mass_per_s = DampingPerS::new(30.0).map_err(|e| e.to_string())?;
    }
    let size = {
        let grid = build_grid(&scene)?;
        let (lo, hi) = grid.topology().nodes.rest.iter().fold((Vec3::repeat(f64::INFINITY), Vec3::repeat(f64::NEG_INFINITY)), |(lo, hi), r| (lo.inf(r), hi.sup(r)));
        (hi - lo).norm()
    };
    let largest = reference.iter().map(|u| u.norm()).fold(0.0, f64::max);
    let scale = if largest > 0.0 { (SESSION_LOAD_DISPLACEMENT_FRACTION * size / largest).min(1.0) } else { 1.0 };
    if let Some(g) = &mut scene.gravity_m_per_s2 {
        for c in g.iter_mut() {
            *c = AccelerationMPerS2::new(c.get() * scale).map_err(|e| e.to_string())?;
        }
    }
    let mut grid = build_grid(&scene)?;
    // A free piece falls for ever; settled means the held pieces are.
    let held = crate::grid::support::held_pieces(grid.topology());
    let n = crate::tissue::Tissue::tools(&grid).len();
    let (commands, mut feedback) = (vec![Default::default(); n], vec![Default::default(); n]);
    let steps = (max_duration_s / setting.dt_s).round() as usize;
    let check_every = (0.05 / setting.dt_s).round().max(1.0) as usize;
    for step in 1..=steps {
        grid.step(&commands, &mut feedback);
        if step % check_every == 0 && step as f64 * setting.dt_s >= 0.5 {
            let topo = grid.topology();
            let fastest = (0..topo.nodes.len()).filter(|&i| held[i]).map(|i| topo.nodes.v[i].norm()).fold(0.0, f64::max);
            if fastest < 1e-5 * scale {
                break;
            }
        }
    }
    let computed: Vec<Vec3> = sample_displacements(grid.topology(), samples).iter().map(|u| u / scale).collect();
    Ok((field_error(&computed, reference).rms, scale))
}

/// The live nodes at the cantilever's free end (the largest rest x).
pub fn tip_nodes(topo: &Topology) -> Vec<usize> {
    let far = topo.nodes.rest.iter().map(|r| r.x).fold(f64::NEG_INFINITY, f64::max);
    (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n] && (topo.nodes.rest[n].x - far).abs() < 1e-9).collect()
}

/// The first frequency of the cantilever as the model's dynamics deliver it: released
/// from rest under gravity with no damping, the tip's vertical motion is timed between
/// its first and last turning points. None when fewer than three turning points show
/// within `duration_s`.
pub fn cantilever_frequency(scene: &Scene, duration_s: f64) -> Result<Option<f64>, String> {
    let mut scene = scene.clone();
    if let ModelSpec::BranchedGrid(spec) = &mut scene.model {
        spec.damping.mass_per_s = DampingPerS(0.0);
        spec.damping.stiffness_s = SpringDampingS(0.0);
    }
    let mut grid = build_grid(&scene)?;
    let dt = scene.time_step_s.get();
    let tip = tip_nodes(grid.topology());
    let mut trace = Vec::new();
    let steps = (duration_s / dt).round() as usize;
    let mut feedback = vec![ToolFeedback::default(); crate::tissue::Tissue::tools(&grid).len()];
    let commands = vec![ToolCommand::default(); feedback.len()];
    for _ in 0..steps {
        grid.step(&commands, &mut feedback);
        let t = grid.topology();
        trace.push(tip.iter().map(|&n| t.nodes.x[n].z - t.nodes.rest[n].z).sum::<f64>() / tip.len() as f64);
    }
    let mut turns = Vec::new();
    for i in 1..trace.len().saturating_sub(1) {
        if (trace[i] - trace[i - 1]) * (trace[i + 1] - trace[i]) < 0.0 {
            // The turning point, refined by a parabola through the three samples.
            let (a, b, c) = (trace[i - 1], trace[i], trace[i + 1]);
            let denominator = a - 2.0 * b + c;
            let shift = if denominator != 0.0 { 0.5 * (a - c) / denominator } else { 0.0 };
            turns.push((i as f64 + shift) * dt);
        }
    }
    if turns.len() < 3 {
        return Ok(None);
    }
    let half_period = (turns[turns.len() - 1] - turns[0]) / (turns.len() - 1) as f64;
    Ok(Some(1.0 / (2.0 * half_period)))
}
