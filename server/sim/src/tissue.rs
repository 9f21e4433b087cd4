//! The one interface the session uses for every tissue model.
//!
//! A model steps with tool commands, reports tool forces and contacts, applies cuts
//! (as a result of the commands), exposes its surface with stable ids and drains the
//! topology deltas its cuts produced. Everything else about a model stays inside it.

use crate::surface::{SurfaceSnapshot, TopologyDelta};
use crate::tool::{ToolCommand, ToolFeedback, ToolShape};

/// What `"fidelity": "auto"` chose on this machine at load: the scene with these pinned
/// (`grid::fidelity::pin_level`) builds the same model.
#[derive(Debug, Clone, PartialEq)]
pub struct ChosenFidelity {
    /// The branched grid's level.
    pub level: u32,
    /// Under a multirate schedule: haptic steps per deformation step.
    pub deformation_every_steps: Option<u32>,
    /// One line for logs and session info: what was tried, what fits, the error class.
    pub summary: String,
}

/// A cut update whose wound could not be stitched and was left as an open hole.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct CutFallback {
    /// The step it happened in (0-based: the step index before that step).
    pub step: u64,
    /// Why the wound could not be stitched (node matching's reason).
    pub reason: String,
}

/// Running totals a model keeps, for reports and the viewer's panel.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(default)]
pub struct TissueCounters {
    /// Simulation nodes (mass points or grid nodes) alive now.
    pub nodes: u64,
    /// Force elements alive now (springs or hexahedra).
    pub elements: u64,
    pub surface_vertices: u64,
    pub surface_triangles: u64,
    /// Separate cut strokes that removed tissue.
    pub cuts: u64,
    /// Topology updates made by those strokes (one per cutting step).
    pub cut_updates: u64,
    /// Surface triangles removed by cuts (for the branched grid: voxels removed).
    pub removed_elements: u64,
    pub removed_triangles: u64,
    pub added_triangles: u64,
    /// Total length of the incisions' centre curves, m.
    pub incision_length_m: f64,
    /// Cut updates where the wound could not be stitched and was left as an open hole.
    pub reconstruction_fallbacks: u64,
    /// Strokes whose last piece (from the incision's stitched tip to where the blade left
    /// the skin inside it, shorter than one update) could not be stitched and was left
    /// uncut: that incision ends a millimetre or two short of where the blade left.
    pub uncut_last_pieces: u64,
    /// Steps in which a non-finite state was detected and contained.
    pub blowups_contained: u64,
    /// Times the model raised its substep count to stay stable after a cut.
    pub stability_adjustments: u64,
    /// Tool forces that were above the tool's limit and were clamped.
    pub force_clamps: u64,
    /// Tool commands ignored because their pose was not finite.
    pub rejected_poses: u64,
    /// Implicit solves taken (one per step of an implicit model), and the
    /// conjugate-gradient iterations they used in all.
    pub solves: u64,
    pub solver_iterations: u64,
    /// Solves that stopped at their iteration cap above their tolerance: their step is
    /// less accurate than the scene asks (and, far off, not stable).
    pub solver_cap_hits: u64,
    /// The largest relative residual a solve ended with, and the last one's (in the
    /// metric of the system's diagonal: see `solver::pcg`).
    pub solver_max_residual: f64,
    pub solver_last_residual: f64,
    /// Steps that waited for the solver's background work (a preconditioner rebuilt
    /// after a cut) to arrive at its appointed step.
    pub solver_waits: u64,
    /// Cholesky factorizations that failed (a system not positive definite): the solve
    /// went on with block Jacobi until the next factor.
    pub solver_factor_failures: u64,
}

impl TissueCounters {
    /// Counts one solve.
    pub fn count_solve(&mut self, convergence: &crate::solver::pcg::Convergence) {
        self.solves += 1;
        self.solver_iterations += u64::from(convergence.iterations);
        self.solver_cap_hits += u64::from(convergence.cap_hit);
        self.solver_max_residual = self.solver_max_residual.max(convergence.residual);
        self.solver_last_residual = convergence.residual;
    }
}

/// A tissue model behind the session: mass-spring skin or branched grid.
pub trait Tissue: Send {
    /// "msm" or "branched-grid".
    fn model_name(&self) -> &'static str;

    /// What `"fidelity": "auto"` chose at load (None: the scene's own settings). A
    /// recording must pin it to replay.
    fn fidelity(&self) -> Option<ChosenFidelity> {
        None
    }

    /// The fixed physics step, s.
    fn time_step_s(&self) -> f64;

    /// Under a multirate schedule (crate::multirate): the deformation's rate, Hz (the
    /// tools' contact runs every `time_step_s`). None: single-rate.
    fn deformation_rate_hz(&self) -> Option<f64> {
        None
    }

    /// The tools, in the scene's order; `step` takes one command and one feedback per tool.
    fn tools(&self) -> &[ToolShape];

    /// Advances one step of `time_step_s`. `commands` and `feedback` have one entry per tool.
    /// Allocation-free unless a cut changes the topology.
    fn step(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]);

    /// Steps taken since the scene was built.
    fn step_index(&self) -> u64;

    /// The whole surface now.
    fn snapshot(&self) -> SurfaceSnapshot;

    /// Current topology version (0 before any cut; +1 per delta).
    fn topology_version(&self) -> u64;

    /// Moves the deltas produced since the last call into `out`, oldest first.
    fn drain_deltas(&mut self, out: &mut Vec<TopologyDelta>);

    /// Number of vertex id slots: every live vertex id is below it.
    fn vertex_capacity(&self) -> usize;

    /// Writes the position (m) of every vertex slot into `out[id]`; `out.len()` must be
    /// at least `vertex_capacity()`. Dead slots are left unspecified.
    fn write_positions(&self, out: &mut [[f32; 3]]);

    /// True for a live surface vertex id.
    fn vertex_alive(&self, id: u32) -> bool;

    /// Hash of the full simulation state (bit-exact).
    fn state_hash(&self) -> u64;

    fn counters(&self) -> TissueCounters;

    /// Connected pieces of tissue (1 for an intact body).
    fn pieces(&self) -> usize;

    /// A full copy of the state (replays keep a few to scrub backwards quickly).
    fn clone_box(&self) -> Box<dyn Tissue>;

    /// Scene tool `tool`'s jaws' half gap now, m: half the distance between their inner
    /// flats (0 closed; None for a tool without jaws). Viewers draw the jaws where they
    /// are: stopped on what they grasp, or open where a gripper does not squeeze.
    fn jaws_half_gap_m(&self, _tool: usize) -> Option<f64> {
        None
    }

    /// Every cut update since the scene was built that fell back to an open hole
    /// (`TissueCounters::reconstruction_fallbacks` of them), with its step and reason;
    /// empty for a model whose cuts never fall back (the branched grid removes voxels).
    fn cut_fallbacks(&self) -> &[CutFallback] {
        &[]
    }
}
