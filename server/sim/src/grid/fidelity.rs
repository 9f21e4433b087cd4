//! `"fidelity": "auto"`: at load, a short calibration on this machine picks the finest
//! level whose p99 step time fits the scene's budget with a margin, and the grid keeps
//! a report of the choice and of its error class (measured by the speed–accuracy study,
//! docs/accuracy-speed.json).
//!
//! Under a multirate schedule the level is fitted to the deformation's period, and the
//! period then shortened as far as that level allows ([`build_auto_multirate`]).
//!
//! The choice depends on the machine, so a recording must pin it: [`pin_choice`] rewrites
//! a scene's JSON to the chosen level (and deformation rate) with `"fidelity": "fixed"`,
//! and replays of that recording build the same grid.

use std::time::Instant;

use super::build::build_fixed;
use super::model::BranchedGrid;
use crate::accuracy::report::{ErrorTable, error_class};
use crate::math::{Pose, Quat, Vec3};
use crate::scene::{BranchedGridSpec, Scene, SceneError};
use crate::stats::LatencyHistogram;
use crate::tissue::ChosenFidelity;
use crate::tool::{ToolCommand, ToolFeedback};

/// The coarsest level the calibration tries.
pub const COARSEST_AUTO_LEVEL: u32 = 4;
/// The share of the budget kept free: the server's own work per step and the machine's
/// variation between hours (up to 40 % here) need room.
pub const BUDGET_MARGIN: f64 = 0.3;
/// Timed steps per level (after a warm-up of 30).
const CALIBRATION_STEPS: usize = 150;

/// What the calibration measured and chose.
#[derive(Debug, Clone, PartialEq)]
pub struct FidelityChoice {
    pub level: u32,
    pub budget_us: f64,
    /// Per level tried, coarsest first: its p99 step time, µs (None: refused at load).
    pub tried: Vec<(u32, Option<f64>)>,
    /// No level fitted: the coarsest buildable one was taken.
    pub over_budget: bool,
    /// The study's static error for this scene at this level, and its reference.
    pub error: Option<(f64, String)>,
    /// Under a multirate schedule: the deformation rate fitted to the chosen level.
    pub rate: Option<RateChoice>,
}

/// The deformation rate `"fidelity": "auto"` fitted under a multirate schedule.
#[derive(Debug, Clone, PartialEq)]
pub struct RateChoice {
    /// Haptic steps per deformation step, chosen.
    pub every: u32,
    /// The scene's `deformation_every_steps`: the longest period allowed.
    pub longest: u32,
    /// Per period tried, the longest first: its haptic steps and the chosen level's p99
    /// deformation step, µs (None: the grid could not be built with that step).
    pub tried: Vec<(u32, Option<f64>)>,
}

impl FidelityChoice {
    /// One line for logs and session info.
    pub fn summary(&self) -> String {
        let tried = tried_list(&self.tried, |level| format!("L{level}"));
        let fit = if self.over_budget { "no level fits" } else { "fits" };
        let error = match &self.error {
            Some((e, reference)) => format!("error class {}: {:.1} % static displacement error at this level against {reference}", error_class(*e), 100.0 * e),
            None => "error class not measured for this scene (docs/accuracy-speed.md measures the bundled scenes)".to_string(),
        };
        let rate = match &self.rate {
            Some(rate) => format!(
                "; deformation every {} haptic steps, the shortest period this level fits with the margin, at most the scene's {} (tried {})",
                rate.every,
                rate.longest,
                tried_list(&rate.tried, |every| format!("every {every} steps"))
            ),
            None => String::new(),
        };
        format!(
            "fidelity auto: level {} ({fit} a p99 budget of {:.0} µs with {:.0} % margin; tried {tried}){rate}; {error}",
            self.level,
            self.budget_us,
            BUDGET_MARGIN * 100.0,
        )
    }
}

/// "L4 p99 95 µs, L3 refused at load, …": what a calibration timed, each named by `name`.
fn tried_list(tried: &[(u32, Option<f64>)], name: impl Fn(u32) -> String) -> String {
    let tried: Vec<String> = tried
        .iter()
        .map(|&(what, p99)| match p99 {
            Some(p99) => format!("{} p99 {p99:.0} µs", name(what)),
            None => format!("{} refused at load", name(what)),
        })
        .collect();
    tried.join(", ")
}

/// Step-time quantiles, µs, and the mean CG iterations per step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepTiming {
    pub p50_us: f64,
    pub p99_us: f64,
    pub mean_cg: f64,
}

/// Times `steps` steps (after `warmup` untimed ones) with the scene's first non-cutting
/// tool (else its first tool, cut off) pressed 4 mm into the body's broad top over the
/// first 100 steps and held there; no tool when the body has no broad top. Stops early
/// once the median of 20 or more steps exceeds `stop_above_us`.
pub fn time_probe(grid: &mut BranchedGrid, warmup: usize, steps: usize, stop_above_us: Option<f64>) -> StepTiming {
    time_probe_with(grid, warmup, steps, stop_above_us, &mut |grid, commands, feedback| grid.step(commands, feedback))
}

/// A step of the grid as a caller takes it (commands and feedback, one per tool).
pub type StepWith<'a> = dyn FnMut(&mut BranchedGrid, &[ToolCommand], &mut [ToolFeedback]) + 'a;

/// [`time_probe`], each step taken by `step` (a multirate schedule's deformation step
/// does more than [`BranchedGrid::step`]).
pub fn time_probe_with(grid: &mut BranchedGrid, warmup: usize, steps: usize, stop_above_us: Option<f64>, step: &mut StepWith<'_>) -> StepTiming {
    let tools = crate::tissue::Tissue::tools(grid).to_vec();
    let probe = tools.iter().position(|t| !t.can_cut).or(if tools.is_empty() { None } else { Some(0) });
    let top = grid.broad_top();
    let mut commands = vec![ToolCommand::default(); tools.len()];
    let mut feedback = vec![ToolFeedback::default(); tools.len()];
    let below_tip = probe.map_or(0.0, |p| super::hold::reach_below_tip(&tools[p]));
    let mut histogram = LatencyHistogram::new();
    let mut iterations = 0u64;
    for index in 0..warmup + steps {
        if let (Some(p), Some(top)) = (probe, top) {
            let depth = 0.004 * (index as f64 / 100.0).min(1.0);
            let tip = Vec3::new(top.x, top.y, top.z + below_tip - depth);
            commands[p] = ToolCommand { pose: Pose::new(tip, Quat::identity()), active: true, cut: false, grip: None };
        }
        let started = Instant::now();
        step(grid, &commands, &mut feedback);
        let elapsed = started.elapsed();
        if index >= warmup {
            histogram.record(elapsed);
            iterations += u64::from(grid.last_solve().0);
        }
        if let Some(limit) = stop_above_us
            && index >= warmup + 20 && histogram.quantile_ns(0.5) as f64 / 1e3 > limit
        {
            break;
        }
    }
    let n = histogram.count().max(1) as f64;
    StepTiming { p50_us: histogram.quantile_ns(0.5) as f64 / 1e3, p99_us: histogram.quantile_ns(0.99) as f64 / 1e3, mean_cg: iterations as f64 / n }
}

/// The study's error table (docs/accuracy-speed.json, written by `accuracy-speed`).
pub fn error_table() -> ErrorTable {
    serde_json::from_str(include_str!("../../../../docs/accuracy-speed.json")).unwrap_or_default()
}

/// Builds the grid at the finest level from [`COARSEST_AUTO_LEVEL`] down to the scene's
/// `level` whose p99 step, timed on this machine with [`time_probe`], fits the budget
/// less the margin (the coarsest buildable one when none fits); the grid reports the
/// choice ([`BranchedGrid::fidelity_choice`]).
pub fn build_auto(scene: &Scene, spec: &BranchedGridSpec) -> Result<BranchedGrid, SceneError> {
    let budget_us = spec.step_budget_ms.get() * 1e3;
    build_auto_with(scene, spec, &mut |grid| time_probe(grid, 30, CALIBRATION_STEPS, Some(budget_us)).p99_us)
}

/// `"fidelity": "auto"` under a multirate schedule of at most `longest` haptic steps
/// (the scene's `time_step_s`) per deformation step: the finest level whose deformation
/// step, timed as a deformation job takes it (its contact patches' compliance
/// included), fits that period less the margin; then the shortest period, down to 2
/// haptic steps, that this level still fits, so that the deformation (and the patches
/// the haptic loop renders against) is as fresh as the machine allows. Returns the grid,
/// built with that step, and its haptic steps per deformation step; the grid's
/// [`FidelityChoice`] reports both choices.
pub fn build_auto_multirate(scene: &Scene, spec: &BranchedGridSpec, longest: u32) -> Result<(BranchedGrid, u32), SceneError> {
    let mut patches = Vec::new();
    build_auto_multirate_with(scene, spec, longest, &mut |grid, period_s| {
        let margin_m = crate::multirate::patch_margin_m(grid, period_s);
        patches.resize(grid.body_count(), crate::multirate::patch::ContactPatch::default());
        let step = &mut |grid: &mut BranchedGrid, commands: &[ToolCommand], feedback: &mut [ToolFeedback]| grid.deformation_step_of_tools(commands, &mut patches, margin_m, feedback);
        time_probe_with(grid, 10, CALIBRATION_STEPS / 3, Some(period_s * 1e6), step).p99_us
    })
}

/// [`build_auto_multirate`] with each candidate's p99 deformation step, µs, measured by
/// `p99_us(grid, deformation step in s)` on a copy of the candidate.
pub fn build_auto_multirate_with(scene: &Scene, spec: &BranchedGridSpec, longest: u32, p99_us: &mut dyn FnMut(&mut BranchedGrid, f64) -> f64) -> Result<(BranchedGrid, u32), SceneError> {
    let field = "model.branched-grid.schedule.multirate.deformation_every_steps";
    let haptic_dt = scene.time_step_s.get();
    let period_s = |every: u32| haptic_dt * f64::from(every);
    let usable_us = |every: u32| period_s(every) * 1e6 * (1.0 - BUDGET_MARGIN);
    // The fewest haptic steps whose period fits a step of `p99` µs.
    let needed = |p99: f64| ((p99 / usable_us(1)).ceil() as u32).clamp(2, longest);
    let deformation_scene = |every: u32| -> Result<Scene, SceneError> {
        let mut deformation = scene.clone();
        deformation.time_step_s = crate::quantity::TimeStepS::new(period_s(every)).map_err(|e| SceneError::new(&scene.origin, field, e))?;
        Ok(deformation)
    };

    let mut at_longest = spec.clone();
    at_longest.step_budget_ms = crate::quantity::StepBudgetMs::new(period_s(longest) * 1e3).map_err(|e| SceneError::new(&scene.origin, field, e))?;
    let mut grid = build_auto_with(&deformation_scene(longest)?, &at_longest, &mut |grid| p99_us(grid, period_s(longest)))?;
    let mut choice = grid.fidelity_choice().cloned().expect("build_auto_with reports its choice");
    let p99_longest = choice.tried.iter().find(|(level, _)| *level == choice.level).and_then(|(_, p99)| *p99).unwrap_or(f64::INFINITY);
    let mut rate = RateChoice { every: longest, longest, tried: vec![(longest, Some(p99_longest))] };
    if !choice.over_budget {
        let mut at_level = spec.clone();
        at_level.level = crate::quantity::GridLevel::new(choice.level).map_err(|e| SceneError::new(&scene.origin, "model.branched-grid.level", e))?;
        let mut every = needed(p99_longest);
        // A shorter step is cheaper (fewer CG iterations) but not by a known amount:
        // each candidate is built and timed; three tries at most.
        for _ in 0..3 {
            if every >= longest {
                break;
            }
            let Ok(candidate) = build_fixed(&deformation_scene(every)?, &at_level) else {
                rate.tried.push((every, None));
                break;
            };
            let p99 = p99_us(&mut candidate.clone(), period_s(every));
            rate.tried.push((every, Some(p99)));
            if p99 <= usable_us(every) {
                grid = candidate;
                rate.every = every;
                break;
            }
            every = needed(p99).max(every + 1);
        }
    }
    let every = rate.every;
    choice.rate = Some(rate);
    grid.set_fidelity(choice);
    Ok((grid, every))
}

/// [`build_auto`] with each candidate's p99 step time, µs, measured by `p99_us` (on a
/// copy of the candidate: the grid kept is untouched).
pub fn build_auto_with(scene: &Scene, spec: &BranchedGridSpec, p99_us: &mut dyn FnMut(&mut BranchedGrid) -> f64) -> Result<BranchedGrid, SceneError> {
    let budget_us = spec.step_budget_ms.get() * 1e3;
    let finest = spec.level.get();
    let mut tried = Vec::new();
    let mut chosen: Option<(u32, BranchedGrid)> = None;
    let mut over_budget = false;
    let mut last_error = None;
    for level in (finest..=COARSEST_AUTO_LEVEL.max(finest)).rev() {
        let mut candidate = spec.clone();
        candidate.level = crate::quantity::GridLevel::new(level).map_err(|e| SceneError::new(&scene.origin, "model.branched-grid.level", e))?;
        let grid = match build_fixed(scene, &candidate) {
            Ok(grid) => grid,
            Err(e) => {
                tried.push((level, None));
                last_error = Some(e);
                continue;
            }
        };
        let p99 = p99_us(&mut grid.clone());
        tried.push((level, Some(p99)));
        if p99 <= budget_us * (1.0 - BUDGET_MARGIN) {
            chosen = Some((level, grid));
            continue;
        }
        if chosen.is_none() {
            chosen = Some((level, grid));
            over_budget = true;
        }
        // Finer levels are slower still.
        break;
    }
    let Some((level, mut grid)) = chosen else {
        return Err(last_error.unwrap_or_else(|| SceneError::new(&scene.origin, "model.branched-grid.fidelity", "no level could be built")));
    };
    let error = error_table().lookup(&scene.name, level).map(|(e, reference)| (e, reference.to_string()));
    grid.set_fidelity(FidelityChoice { level, budget_us, tried, over_budget, error, rate: None });
    Ok(grid)
}

/// A scene's JSON with what `"fidelity": "auto"` chose pinned: the branched grid's
/// level, its fidelity "fixed" and, under a multirate schedule, the haptic steps per
/// deformation step (what a recording of an auto session must hold to replay the same
/// grid).
pub fn pin_choice(scene_json: &str, chosen: &ChosenFidelity) -> Result<String, String> {
    let mut value: serde_json::Value = serde_json::from_str(scene_json).map_err(|e| format!("the scene is not JSON: {e}"))?;
    let grid = value.pointer_mut("/model/branched-grid").and_then(|g| g.as_object_mut()).ok_or("not a branched-grid scene")?;
    grid.insert("level".into(), chosen.level.into());
    grid.insert("fidelity".into(), "fixed".into());
    if let Some(every) = chosen.deformation_every_steps {
        let multirate = grid.get_mut("schedule").and_then(|s| s.get_mut("multirate")).and_then(|m| m.as_object_mut()).ok_or("the choice has a deformation rate but the scene no multirate schedule")?;
        multirate.insert("deformation_every_steps".into(), every.into());
    }
    Ok(value.to_string())
}

/// The scene with what `"fidelity": "auto"` chose pinned, as [`pin_choice`] (what a
/// reset of an auto session rebuilds, so that it does not calibrate again).
pub fn pin_scene(scene: &Scene, chosen: &ChosenFidelity) -> Scene {
    let mut scene = scene.with_grid_level(chosen.level);
    if let crate::scene::ModelSpec::BranchedGrid(spec) = &mut scene.model {
        spec.fidelity = crate::scene::FidelitySpec::Fixed;
        if let (Some(every), crate::scene::ScheduleSpec::Multirate(multirate)) = (chosen.deformation_every_steps, &mut spec.schedule) {
            multirate.deformation_every_steps = crate::quantity::DeformationEvery::new(every).unwrap_or_else(|e| panic!("a chosen rate is in range: {e}"));
        }
    }
    scene
}
