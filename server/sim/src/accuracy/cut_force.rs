//! The force of a scripted scalpel cut (docs/tool-tissue.md): a script run step by step
//! with the blade's force recorded, and the steady part of that force. The `cut-force`
//! report (docs/cut-force.md) and the tool–tissue tests read the same numbers from here.

use crate::math::Quat;
use crate::scene::Scene;
use crate::script::CutScript;
use crate::tool::{ToolCommand, ToolFeedback};

/// One scripted cut, step by step.
#[derive(Debug, Clone)]
pub struct CutTrace {
    /// Per step: (time s, force magnitude on the blade N, whether the skin was cut).
    pub samples: Vec<(f64, f64, bool)>,
    /// Incision updates over the run.
    pub cut_updates: u64,
    pub incision_length_m: f64,
}

/// The steady part of a cut's force: over the middle half of the steps between the first
/// and the last that cut.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SteadyForce {
    pub mean_n: f64,
    pub min_n: f64,
    pub max_n: f64,
}

impl CutTrace {
    /// None when the script never cut.
    pub fn steady(&self) -> Option<SteadyForce> {
        let first = self.samples.iter().position(|s| s.2)?;
        let last = self.samples.iter().rposition(|s| s.2)?;
        let window = &self.samples[first + (last - first) / 4..=first + 3 * (last - first) / 4];
        let mean_n = window.iter().map(|s| s.1).sum::<f64>() / window.len() as f64;
        let (min_n, max_n) = window.iter().fold((f64::INFINITY, 0.0f64), |(lo, hi), s| (lo.min(s.1), hi.max(s.1)));
        Some(SteadyForce { mean_n, min_n, max_n })
    }

    /// The largest force over the whole run, N.
    pub fn peak_n(&self) -> f64 {
        self.samples.iter().map(|s| s.1).fold(0.0, f64::max)
    }
}

/// Runs `script` on `scene` with the tool named `blade` turned by `turn` about its own
/// axis (identity: as scripted), recording that tool's force every step.
pub fn scripted_cut(scene: &Scene, script: &CutScript, blade: &str, turn: Quat) -> Result<CutTrace, String> {
    let mut tissue = crate::build_tissue(scene).map_err(|e| e.to_string())?;
    let dt = scene.time_step_s.get();
    let compiled = script.compile(tissue.tools(), dt, &scene.name).map_err(|e| e.to_string())?;
    let n = tissue.tools().len();
    let tool = tissue.tools().iter().position(|t| t.name == blade).ok_or_else(|| format!("the scene has no tool named {blade:?}"))?;
    let (mut commands, mut feedback) = (vec![ToolCommand::default(); n], vec![ToolFeedback::default(); n]);
    let mut samples = Vec::with_capacity(compiled.steps as usize);
    for step in 0..compiled.steps {
        compiled.commands_at(step, &mut commands);
        commands[tool].pose.orientation *= turn;
        tissue.step(&commands, &mut feedback);
        samples.push((step as f64 * dt, feedback[tool].force_n.norm(), feedback[tool].cutting));
    }
    let counters = tissue.counters();
    Ok(CutTrace { samples, cut_updates: counters.cut_updates, incision_length_m: counters.incision_length_m })
}
