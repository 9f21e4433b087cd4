//! Single-rate against multirate at equal budget (docs/accuracy-speed.md, "Single-rate
//! against multirate"): a bundled volumetric scene at a level, run in real time by the
//! same script under each schedule, the haptic side paced at 1 kHz on the calling
//! thread.
//!
//! - Single-rate: the whole step (contact, deformation, cuts) every millisecond on one
//!   thread; it fits the budget when its p99 step is at most 1 ms.
//! - Multirate: the haptic loop every millisecond on the calling thread, the deformation
//!   every [`DEFORMATION_EVERY`] steps (30 Hz) on its worker thread (the second core);
//!   it fits when the haptic step's p99 is at most 1 ms (a late deformation job makes a
//!   haptic step wait for it, so jobs that do not keep up show there).
//!
//! The script: a probe pressed 4 mm into the body's broad top over 100 ms and held, then
//! a scalpel drawn 4 cm through that point 8 mm deep at 20 mm/s with its cut button held
//! (the benchmark `cargo bench -p cutsim-sim --bench multirate` runs the same script).

use std::path::Path;
use std::time::{Duration, Instant};

use crate::grid::BranchedGrid;
use crate::math::{Pose, Quat, Vec3};
use crate::multirate::Multirate;
use crate::scene::{ModelSpec, Scene, ScheduleSpec};
use crate::stats::LatencyHistogram;
use crate::tissue::Tissue;
use crate::tool::{ToolCommand, ToolFeedback, ToolShape};

/// The haptic step's budget: one millisecond (1 kHz).
pub const HAPTIC_BUDGET_MS: f64 = 1.0;
/// Haptic steps per deformation step in the comparison: 30 Hz at 1 kHz, the floor.
pub const DEFORMATION_EVERY: u32 = 33;

/// How long each phase of the script lasts, in 1 ms steps.
#[derive(Debug, Clone, Copy)]
pub struct Script {
    pub hold_steps: usize,
    pub cut_steps: usize,
    /// Stop early where the budget is clearly missed (the benchmark: a schedule that
    /// cannot keep up is reported as such, not timed to the end); false runs every
    /// step however late (a test of what the script does, on a machine of any speed).
    pub stop_when_late: bool,
}

impl Script {
    /// The benchmark's script: held 1 s, cut for 2 s.
    pub const FULL: Script = Script { hold_steps: 1000, cut_steps: 2000, stop_when_late: true };
    /// A shorter one (0.3 s held, 0.5 s cutting).
    pub const QUICK: Script = Script { hold_steps: 300, cut_steps: 500, stop_when_late: true };

    /// The tools' commands at `step` (0-based) into `commands`, for a body whose broad
    /// top is at `top` (world frame): while held, the first tool that cannot cut (the
    /// probe) pressed 4 mm in over the first 100 steps; then the first that can (the
    /// scalpel) drawn 4 cm along x through that point, 8 mm deep, its cut button held.
    /// Every other tool is inactive.
    pub fn commands(&self, step: usize, top: Vec3, tools: &[ToolShape], commands: &mut [ToolCommand]) {
        commands.iter_mut().for_each(|c| *c = ToolCommand::default());
        if step < self.hold_steps {
            if let Some(p) = tools.iter().position(|t| !t.can_cut) {
                let depth = 0.004 * (step as f64 / 100.0).min(1.0);
                let below_tip = crate::grid::hold::reach_below_tip(&tools[p]);
                commands[p] = ToolCommand { pose: Pose::new(Vec3::new(top.x, top.y, top.z + below_tip - depth), Quat::identity()), active: true, cut: false, grip: None };
            }
        } else if let Some(b) = tools.iter().position(|t| t.can_cut) {
            let x = -0.02 + 0.04 * (step - self.hold_steps) as f64 / self.cut_steps as f64;
            commands[b] = ToolCommand { pose: Pose::new(Vec3::new(top.x + x, top.y, top.z - 0.008), Quat::identity()), active: true, cut: true, grip: None };
        }
    }
}

/// A bundled scene's JSON at `level`, under a multirate schedule of `every` steps with
/// `preconditioner` and CG cap `cap` (None: the scene's), or single-rate as the scene is.
pub fn scene_at(path: &Path, level: u32, multirate: Option<(u32, &str, Option<u32>)>) -> Result<Scene, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut json: serde_json::Value = serde_json::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    let spec = json.pointer_mut("/model/branched-grid").ok_or_else(|| format!("{}: not a branched-grid scene", path.display()))?;
    spec["level"] = level.into();
    spec["fidelity"] = "fixed".into();
    if let Some((every, preconditioner, cap)) = multirate {
        spec["solver"]["preconditioner"] = preconditioner.into();
        if let Some(cap) = cap {
            spec["solver"]["cg_max_iterations"] = cap.into();
        }
        spec["schedule"] = serde_json::json!({ "multirate": { "deformation_every_steps": every } });
    }
    Scene::from_json_str(&json.to_string(), &path.display().to_string(), path.parent()).map_err(|e| e.to_string())
}

/// A model run by [`run_real_time`].
pub enum Model {
    SingleRate(Box<BranchedGrid>),
    Multirate(Box<Multirate>),
}

impl Model {
    /// Builds a scene from [`scene_at`] under its schedule.
    pub fn build(scene: &Scene) -> Result<Model, String> {
        let ModelSpec::BranchedGrid(spec) = &scene.model else { return Err(format!("{}: not a branched-grid scene", scene.origin)) };
        match &spec.schedule {
            ScheduleSpec::SingleRate => crate::grid::build_from_scene(scene, spec).map(|g| Model::SingleRate(Box::new(g))).map_err(|e| e.to_string()),
            ScheduleSpec::Multirate(schedule) => crate::multirate::build_from_scene(scene, schedule).map(|m| Model::Multirate(Box::new(m))).map_err(|e| e.to_string()),
        }
    }

    fn tissue(&mut self) -> &mut dyn Tissue {
        match self {
            Model::SingleRate(grid) => grid.as_mut(),
            Model::Multirate(model) => model.as_mut(),
        }
    }

    fn broad_top(&self) -> Option<Vec3> {
        match self {
            Model::SingleRate(grid) => grid.broad_top(),
            Model::Multirate(model) => model.with_grid(|g| g.broad_top()),
        }
    }
}

/// What a real-time run measured.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RealTime {
    /// Steps run, and planned (fewer run: stopped early, the budget clearly missed).
    pub steps: usize,
    pub planned: usize,
    /// The step on the paced thread (single-rate: the whole step; multirate: the
    /// haptic step, a wait for a late job included), ms.
    pub step_p50_ms: f64,
    pub step_p99_ms: f64,
    pub step_max_ms: f64,
    /// Steps longer than the budget.
    pub over_budget: u64,
    /// Multirate: the deformation jobs' time (step, patch compliance, publishing), ms,
    /// how many ran, and how many were late (a haptic step waited for them).
    pub deformation_p50_ms: Option<f64>,
    pub deformation_p99_ms: Option<f64>,
    pub jobs: u64,
    pub late_jobs: u64,
    /// The probe's force at the end of the hold, N; voxels' elements removed by the cut.
    pub held_force_n: f64,
    pub removed_elements: u64,
    /// Solves that stopped at the CG cap, of all solves.
    pub cap_hits: u64,
    pub solves: u64,
}

impl RealTime {
    /// The paced step fits the 1 kHz budget.
    pub fn fits(&self) -> bool {
        self.steps == self.planned && self.step_p99_ms <= HAPTIC_BUDGET_MS
    }
}

fn ms(ns: u64) -> f64 {
    ns as f64 / 1e6
}

/// Sleeps until `deadline`, spinning its last 0.2 ms (a sleep overshoots).
pub fn wait_until(deadline: Instant) {
    loop {
        let now = Instant::now();
        if now >= deadline {
            return;
        }
        let left = deadline - now;
        if left > Duration::from_micros(300) {
            std::thread::sleep(left - Duration::from_micros(200));
        } else {
            std::hint::spin_loop();
        }
    }
}

/// Runs the script in real time, one step per millisecond. Stops early where the budget
/// is clearly missed and the script says so (`stop_when_late`): a single-rate model whose
/// median step after 50 steps is over three budgets, a multirate one after its tenth late
/// job.
pub fn run_real_time(model: &mut Model, script: Script) -> RealTime {
    let top = model.broad_top().unwrap_or_else(Vec3::zeros);
    let tools = model.tissue().tools().to_vec();
    let probe = tools.iter().position(|t| !t.can_cut);
    let mut commands = vec![ToolCommand::default(); tools.len()];
    let mut feedback = vec![ToolFeedback::default(); tools.len()];
    let every = match model {
        Model::Multirate(m) => Some(m.deformation_every()),
        Model::SingleRate(_) => None,
    };
    let planned = script.hold_steps + script.cut_steps;
    let (mut paced, mut deformation) = (LatencyHistogram::new(), LatencyHistogram::new());
    let mut out = RealTime { planned, ..RealTime::default() };
    let start = Instant::now();
    for step in 0..planned {
        script.commands(step, top, &tools, &mut commands);
        wait_until(start + Duration::from_millis(step as u64));
        let t = Instant::now();
        model.tissue().step(&commands, &mut feedback);
        let took = t.elapsed();
        paced.record(took);
        out.steps = step + 1;
        if took.as_secs_f64() * 1e3 > HAPTIC_BUDGET_MS {
            out.over_budget += 1;
        }
        if step + 1 == script.hold_steps {
            out.held_force_n = probe.map_or(0.0, |p| feedback[p].force_n.norm());
        }
        match model {
            Model::Multirate(m) => {
                if step > 0 && (step as u64).is_multiple_of(u64::from(every.unwrap_or(1))) {
                    deformation.record_ns(m.last_deformation_ns());
                }
                if script.stop_when_late && m.deformation_waits() >= 10 {
                    break;
                }
            }
            Model::SingleRate(_) => {
                if script.stop_when_late && step >= 50 && ms(paced.quantile_ns(0.5)) > 3.0 * HAPTIC_BUDGET_MS {
                    break;
                }
            }
        }
    }
    out.step_p50_ms = ms(paced.quantile_ns(0.5));
    out.step_p99_ms = ms(paced.quantile_ns(0.99));
    out.step_max_ms = ms(paced.max_ns());
    if let Model::Multirate(m) = model {
        out.deformation_p50_ms = Some(ms(deformation.quantile_ns(0.5)));
        out.deformation_p99_ms = Some(ms(deformation.quantile_ns(0.99)));
        out.jobs = deformation.count();
        out.late_jobs = m.deformation_waits();
    }
    let counters = model.tissue().counters();
    out.removed_elements = counters.removed_elements;
    out.cap_hits = counters.solver_cap_hits;
    out.solves = counters.solves;
    out
}

/// One scene at one level under both schedules.
#[derive(Debug, Clone)]
pub struct Comparison {
    pub scene: String,
    pub level: u32,
    /// The speed–accuracy study's static error at this level (None: not measured).
    pub static_error: Option<f64>,
    /// The multirate run's solver settings, e.g. "multigrid" or "cholesky, CG ≤ 200".
    pub multirate_solver: String,
    pub single_rate: Result<RealTime, String>,
    pub multirate: Result<RealTime, String>,
}

/// The markers around the generated section in docs/accuracy-speed.md.
pub const SECTION_START: &str = "<!-- schedules: generated by accuracy-speed; do not edit by hand -->";
pub const SECTION_END: &str = "<!-- /schedules -->";

/// The section comparing the schedules, between [`SECTION_START`] and [`SECTION_END`].
pub fn markdown(comparisons: &[Comparison], command: &str, machine: &str, script: Script) -> String {
    use std::fmt::Write;
    let mut md = String::new();
    let _ = writeln!(md, "{SECTION_START}\n## Single-rate against multirate at equal budget\n");
    let _ = writeln!(
        md,
        "Generated by `{command}` on {machine}. Each scene at each level runs the same script in real time under both schedules: a probe pressed 4 mm into the body's broad top over 100 ms and held ({:.1} s), then the scalpel drawn 4 cm through that point 8 mm deep at 20 mm/s with its cut button held ({:.1} s). **Single-rate**: the whole step (contact, deformation, cuts) every millisecond on one thread, with the scene's own solver settings; it fits when its p99 step is at most {HAPTIC_BUDGET_MS} ms. **Multirate**: the haptic loop every millisecond on one thread and the deformation every {DEFORMATION_EVERY} steps ({:.0} Hz) on a second (docs/branched-grid.md, \"Multirate haptics\"), with the preconditioner a deformation step of {DEFORMATION_EVERY} ms needs; it fits when its haptic step's p99 is at most {HAPTIC_BUDGET_MS} ms (a late deformation job makes a haptic step wait for it). A run that clearly misses (a single-rate median over three budgets after 50 steps, ten late jobs) is stopped early. The budget is equal in what the device gets (a force every millisecond); the multirate schedule uses the second core. The static error is the study's above (the level's linear solution against the scene's reference): the multirate deformation at a level is that level's model, so the error a schedule delivers is that of the finest level it fits.\n",
        script.hold_steps as f64 / 1e3,
        script.cut_steps as f64 / 1e3,
        1e3 / f64::from(DEFORMATION_EVERY),
    );
    let _ = writeln!(md, "| scene | level | static error | single-rate step p50 / p99 / max | fits | multirate haptic step p50 / p99 / max | deformation p50 / p99 | late jobs | fits |");
    let _ = writeln!(md, "|---|---:|---:|---|---|---|---|---:|---|");
    let times = |r: &RealTime| {
        let stopped = if r.steps < r.planned { format!(" (stopped after {} of {} steps)", r.steps, r.planned) } else { String::new() };
        format!("{:.3} / {:.3} / {:.1} ms{stopped}", r.step_p50_ms, r.step_p99_ms, r.step_max_ms)
    };
    let yes = |r: &RealTime| if r.fits() { "yes" } else { "no" };
    for c in comparisons {
        let error = match c.static_error {
            None => "not measured".to_string(),
            Some(0.0) => "the reference".to_string(),
            Some(e) => format!("{:.1} %", 100.0 * e),
        };
        let (single, single_fits) = match &c.single_rate {
            Ok(r) => (times(r), yes(r).to_string()),
            Err(e) => (format!("refused at load: {}", first_clause(e)), "no".to_string()),
        };
        let (multi, deformation, late, multi_fits) = match &c.multirate {
            Ok(r) => (
                format!("{} ({})", times(r), c.multirate_solver),
                format!("{:.1} / {:.1} ms", r.deformation_p50_ms.unwrap_or(f64::NAN), r.deformation_p99_ms.unwrap_or(f64::NAN)),
                format!("{} of {}", r.late_jobs, r.jobs),
                yes(r).to_string(),
            ),
            Err(e) => (format!("refused at load ({}): {}", c.multirate_solver, first_clause(e)), String::new(), String::new(), "no".to_string()),
        };
        let _ = writeln!(md, "| {} | L{} | {error} | {single} | {single_fits} | {multi} | {deformation} | {late} | {multi_fits} |", c.scene, c.level);
    }
    let _ = writeln!(md, "\nIn short, the finest level each schedule fits, and its static error:\n");
    let _ = writeln!(md, "| scene | single-rate | multirate |");
    let _ = writeln!(md, "|---|---|---|");
    let mut scenes: Vec<&str> = comparisons.iter().map(|c| c.scene.as_str()).collect();
    scenes.dedup();
    for scene in scenes {
        let finest = |fits: &dyn Fn(&Comparison) -> bool| {
            comparisons.iter().filter(|c| c.scene == scene && fits(c)).min_by_key(|c| c.level).map_or("none".to_string(), |c| match c.static_error {
                Some(0.0) => format!("L{}: the reference", c.level),
                Some(e) => format!("L{}: {:.1} %", c.level, 100.0 * e),
                None => format!("L{} (error not measured)", c.level),
            })
        };
        let single = finest(&|c| c.single_rate.as_ref().is_ok_and(RealTime::fits));
        let multi = finest(&|c| c.multirate.as_ref().is_ok_and(RealTime::fits));
        let _ = writeln!(md, "| {scene} | {single} | {multi} |");
    }
    let _ = writeln!(md, "{SECTION_END}");
    md
}

/// A load-time refusal's first clause, without the scene and field it names (they are
/// long: "the implicit solve of this scene needs 70 conjugate-gradient iterations to
/// reach its tolerance 1e-5 (time step …), more than the 60 allowed, …").
fn first_clause(message: &str) -> String {
    let text = message.rsplit_once(".cg_max_iterations: ").map_or(message, |(_, rest)| rest);
    let text = match text.split_once(" (") {
        Some((head, rest)) => match rest.split_once("), ") {
            Some((_, tail)) => format!("{head}, {}", tail.split(", and ").next().unwrap_or(tail)),
            None => head.to_string(),
        },
        None => text.to_string(),
    };
    text.replace('|', "/").chars().take(200).collect()
}

/// `document` with its generated section replaced by `section` (appended when it has none).
pub fn splice(document: &str, section: &str) -> String {
    match (document.find(SECTION_START), document.find(SECTION_END)) {
        (Some(start), Some(end)) if end > start => format!("{}{}{}", &document[..start], section.trim_end(), &document[end + SECTION_END.len()..]),
        _ => format!("{}\n{}", document.trim_end_matches('\n').to_string() + "\n", section),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn splice_replaces_the_generated_section_or_appends_it() {
        let section = format!("{SECTION_START}\nnew\n{SECTION_END}\n");
        let document = format!("# Title\n\nbefore\n{SECTION_START}\nold\n{SECTION_END}\nafter\n");
        assert_eq!(splice(&document, &section), format!("# Title\n\nbefore\n{SECTION_START}\nnew\n{SECTION_END}\nafter\n"));
        assert_eq!(splice("# Title\n\ntext\n\n", &section), format!("# Title\n\ntext\n\n{section}"));
    }

    #[test]
    fn a_refusal_is_shortened_to_what_it_needs() {
        let message = "scene.json: model.branched-grid.solver.cg_max_iterations: the implicit solve of this scene needs 84 conjugate-gradient iterations to reach its tolerance 1e-5 (time step 1 ms, a probe pressed in under load), more than the 60 allowed, and a solve stopped short is less accurate";
        assert_eq!(first_clause(message), "the implicit solve of this scene needs 84 conjugate-gradient iterations to reach its tolerance 1e-5, more than the 60 allowed");
        assert_eq!(first_clause("no | such file"), "no / such file");
    }
}
