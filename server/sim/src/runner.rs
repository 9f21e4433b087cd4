//! Lockstep runs: a tissue stepped as fast as the CPU allows, with tool commands from a
//! script by step index, ending with a report. No wall clock enters the physics, so the
//! same scene and script always give the same state hash.

use std::ops::ControlFlow;
use std::time::Instant;

use serde::{Deserialize, Serialize};

use crate::assessment::{Assessment, Assessor, Task, ToolSample, fill_samples};
use crate::hash::hash_hex;
use crate::script::{CompiledScript, ExpectationResult};
use crate::stats::LatencyHistogram;
use crate::tissue::{CutFallback, Tissue, TissueCounters};
use crate::tool::{ToolCommand, ToolFeedback};

/// What a lockstep run did, as printed by `cutsim-server run --json` and returned by
/// the gRPC script API.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct RunReport {
    pub scene: String,
    pub model: String,
    pub steps: u64,
    /// steps × time step, s.
    pub simulated_time_s: f64,
    pub cuts: u64,
    pub cut_updates: u64,
    pub removed_elements: u64,
    pub removed_triangles: u64,
    pub incision_length_m: f64,
    pub pieces: u64,
    pub reconstruction_fallbacks: u64,
    /// Each of those fallbacks: the step it happened in and why the wound could not be
    /// stitched.
    #[serde(default)]
    pub fallbacks: Vec<CutFallback>,
    /// Largest tool force over the run (after the tool's clamp), N.
    pub max_tool_force_n: f64,
    /// Each of the scene's tools, in the scene's order: its own largest force.
    #[serde(default)]
    pub tools: Vec<ToolReport>,
    pub step_time_p50_us: f64,
    pub step_time_p99_us: f64,
    pub step_time_max_us: f64,
    pub wall_time_s: f64,
    pub steps_per_second: f64,
    pub surface_vertices: u64,
    pub surface_triangles: u64,
    pub topology_version: u64,
    /// 16 hex digits; equal for equal scene + commands.
    pub state_hash: String,
    pub counters: TissueCounters,
    /// The trainee's metrics against the scene's task (docs/assessment.md).
    #[serde(default)]
    pub assessment: Assessment,
    pub expectations: Vec<ExpectationResult>,
    /// True when every expectation holds (and there are none that fail).
    pub passed: bool,
}

/// One tool's part in a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToolReport {
    /// The tool's name in the scene.
    pub name: String,
    /// The largest force on this tool over the run (after its clamp), N.
    pub max_force_n: f64,
    /// How long it grasped tissue over the run, s: forceps closing on tissue or holding
    /// it (its feedback's `grasping`, crate::tool::ToolFeedback); 0 for other tools.
    #[serde(default)]
    pub grasping_s: f64,
    /// Forceps: the hardest their jaws pinched what they held over the run, N (the
    /// feedback's `jaws_force_n`); 0 for other tools.
    #[serde(default)]
    pub max_jaws_force_n: f64,
}

/// Progress of a run, reported every few steps.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Progress {
    pub step: u64,
    pub total: u64,
    pub cuts: u64,
    pub max_tool_force_n: f64,
}

/// Steps `tissue` `steps` times with the script's commands (tools away without one),
/// assessing the steps against `task`, calling `on_progress` about every
/// `progress_every` steps and at the end.
pub fn run(
    tissue: &mut dyn Tissue,
    scene_name: &str,
    task: Task,
    script: Option<&CompiledScript>,
    steps: u64,
    progress_every: u64,
    on_progress: impl FnMut(&Progress),
) -> RunReport {
    match run_with_hook(tissue, scene_name, task, script, steps, progress_every, on_progress, |_, _, _| ControlFlow::Continue(())) {
        Ok(report) => report,
        Err(Stopped { .. }) => unreachable!("the hook never stops the run"),
    }
}

/// A run its hook stopped before the end (the client went away, the session closed).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Stopped {
    /// Steps taken.
    pub at_step: u64,
}

/// [`run`], calling `after_step(tissue, commands, feedback)` after every step (the
/// server publishes deltas and frames and records commands there; it is not timed); the
/// hook may stop the run.
#[allow(clippy::too_many_arguments)]
pub fn run_with_hook(
    tissue: &mut dyn Tissue,
    scene_name: &str,
    task: Task,
    script: Option<&CompiledScript>,
    steps: u64,
    progress_every: u64,
    mut on_progress: impl FnMut(&Progress),
    mut after_step: impl FnMut(&mut dyn Tissue, &[ToolCommand], &[ToolFeedback]) -> ControlFlow<()>,
) -> Result<RunReport, Stopped> {
    let tools = tissue.tools().len();
    let mut commands = vec![ToolCommand::default(); tools];
    let mut feedback = vec![ToolFeedback::default(); tools];
    let mut histogram = LatencyHistogram::new();
    let mut max_force: f64 = 0.0;
    let mut tool_max_force = vec![0.0_f64; tools];
    let mut tool_grasping_steps = vec![0_u64; tools];
    let mut tool_max_jaws_force = vec![0.0_f64; tools];
    let mut assessor = Assessor::new(task, tools, tissue.time_step_s());
    let mut samples = vec![ToolSample::default(); tools];
    let start = Instant::now();
    for step in 0..steps {
        if let Some(s) = script {
            s.commands_at(step, &mut commands);
        }
        let t0 = Instant::now();
        tissue.step(&commands, &mut feedback);
        histogram.record(t0.elapsed());
        if after_step(tissue, &commands, &feedback).is_break() {
            return Err(Stopped { at_step: step + 1 });
        }
        for (((most, grasping), hardest_pinch), fb) in tool_max_force.iter_mut().zip(tool_grasping_steps.iter_mut()).zip(tool_max_jaws_force.iter_mut()).zip(&feedback) {
            *most = most.max(fb.force_n.norm());
            max_force = max_force.max(*most);
            *grasping += u64::from(fb.grasping);
            *hardest_pinch = hardest_pinch.max(fb.jaws_force_n);
        }
        fill_samples(&mut samples, &commands, &feedback);
        assessor.observe(&samples);
        if progress_every > 0 && (step + 1) % progress_every == 0 && step + 1 < steps {
            on_progress(&Progress { step: step + 1, total: steps, cuts: tissue.counters().cuts, max_tool_force_n: max_force });
        }
    }
    let wall = start.elapsed().as_secs_f64();
    let counters = tissue.counters();
    on_progress(&Progress { step: steps, total: steps, cuts: counters.cuts, max_tool_force_n: max_force });
    let us = |ns: u64| ns as f64 / 1e3;
    let mut report = RunReport {
        scene: scene_name.to_owned(),
        model: tissue.model_name().to_owned(),
        steps,
        simulated_time_s: steps as f64 * tissue.time_step_s(),
        cuts: counters.cuts,
        cut_updates: counters.cut_updates,
        removed_elements: counters.removed_elements,
        removed_triangles: counters.removed_triangles,
        incision_length_m: counters.incision_length_m,
        pieces: tissue.pieces() as u64,
        reconstruction_fallbacks: counters.reconstruction_fallbacks,
        fallbacks: tissue.cut_fallbacks().to_vec(),
        max_tool_force_n: max_force,
        tools: tissue
            .tools()
            .iter()
            .zip(tool_max_force)
            .zip(tool_grasping_steps)
            .zip(tool_max_jaws_force)
            .map(|(((t, max_force_n), grasping), max_jaws_force_n)| ToolReport { name: t.name.clone(), max_force_n, grasping_s: grasping as f64 * tissue.time_step_s(), max_jaws_force_n })
            .collect(),
        step_time_p50_us: us(histogram.quantile_ns(0.5)),
        step_time_p99_us: us(histogram.quantile_ns(0.99)),
        step_time_max_us: us(histogram.max_ns()),
        wall_time_s: wall,
        steps_per_second: if wall > 0.0 { steps as f64 / wall } else { 0.0 },
        surface_vertices: counters.surface_vertices,
        surface_triangles: counters.surface_triangles,
        topology_version: tissue.topology_version(),
        state_hash: hash_hex(tissue.state_hash()),
        counters,
        assessment: assessor.assessment(),
        expectations: Vec::new(),
        passed: true,
    };
    if let Some(s) = script {
        report.expectations = s.expect.check(&report);
        report.passed = report.expectations.iter().all(|e| e.passed);
    }
    Ok(report)
}
