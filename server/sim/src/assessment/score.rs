//! The score and the pass/fail verdict, from the metrics. The weights are documented in
//! docs/assessment.md; they sum to 100.

use super::metrics::Assessment;
use super::task::Task;

/// Points lost for leaving the plan uncut, at coverage 0.
pub const WEIGHT_COVERAGE: f64 = 35.0;
/// Points lost when the RMS deviation reaches the band's half-width.
pub const WEIGHT_DEVIATION: f64 = 25.0;
/// Points lost when the cut outside the band is as long as the plan.
pub const WEIGHT_OUTSIDE_BAND: f64 = 15.0;
/// Points lost when the RMS depth error reaches the depth tolerance (plans with a depth).
pub const WEIGHT_DEPTH: f64 = 10.0;
/// Points lost after one second above the force limit or the grip limit, the two times
/// added (tasks with a limit).
pub const WEIGHT_FORCE: f64 = 5.0;
/// Points lost for entering a no-go region (once is enough to lose them all).
pub const WEIGHT_NO_GO: f64 = 10.0;

pub struct Score {
    pub score: Option<f64>,
    pub passed: Option<bool>,
    pub failures: Vec<String>,
}

pub fn score(task: &Task, a: &Assessment) -> Score {
    let mut failures = Vec::new();
    let has_criteria = task.plan.is_some() || !task.no_go.is_empty() || task.force_limit_n.is_some() || task.grip_limit_n.is_some();
    if !has_criteria {
        return Score { score: None, passed: None, failures };
    }
    if let (Some(coverage), false) = (a.coverage, a.completed) {
        failures.push(format!("coverage {:.0} % of the plan is below the task's {:.0} %", coverage * 100.0, task.min_coverage * 100.0));
    }
    if let (Some(plan), Some(max)) = (&task.plan, a.deviation_max_mm)
        && max > plan.band_m * 1e3
    {
        failures.push(format!("the cut strayed {max:.1} mm from the plan, outside its band of ±{:.1} mm", plan.band_m * 1e3));
    }
    if let (Some((_, tolerance)), Some(rms)) = (task.depth, a.depth_error_rms_mm)
        && rms > tolerance * 1e3
    {
        failures.push(format!("the depth was off by {rms:.1} mm RMS, beyond the tolerance of {:.1} mm", tolerance * 1e3));
    }
    if let (Some(limit), Some(time)) = (task.force_limit_n, a.time_above_force_limit_s)
        && time > 0.0
    {
        failures.push(format!("{time:.3} s above the force limit of {limit} N"));
    }
    if let (Some(limit), Some(time)) = (task.grip_limit_n, a.time_above_grip_limit_s)
        && time > 0.0
    {
        failures.push(format!("{time:.3} s pinching harder than the grip limit of {limit} N"));
    }
    if a.no_go_entries > 0 {
        failures.push(format!("{} entr{} into no-go regions", a.no_go_entries, if a.no_go_entries == 1 { "y" } else { "ies" }));
    }
    let score = task.plan.as_ref().map(|plan| {
        let ratio = |x: f64, full: f64| if full > 0.0 { (x / full).clamp(0.0, 1.0) } else { 0.0 };
        let band_mm = plan.band_m * 1e3;
        let mut lost = WEIGHT_COVERAGE * (1.0 - a.coverage.unwrap_or(0.0));
        // A plan not cut at all has nothing to deviate: it loses these points too.
        lost += WEIGHT_DEVIATION * a.deviation_rms_mm.map_or(1.0, |d| ratio(d, band_mm));
        lost += WEIGHT_OUTSIDE_BAND * ratio(a.outside_band_mm.unwrap_or(0.0), plan.length_m() * 1e3);
        if let Some((_, tolerance)) = task.depth {
            lost += WEIGHT_DEPTH * a.depth_error_rms_mm.map_or(1.0, |d| ratio(d, tolerance * 1e3));
        }
        let above_limits = a.time_above_force_limit_s.unwrap_or(0.0) + a.time_above_grip_limit_s.unwrap_or(0.0);
        lost += WEIGHT_FORCE * ratio(above_limits, 1.0);
        lost += WEIGHT_NO_GO * ratio(a.no_go_entries as f64, 1.0);
        (100.0 - lost).max(0.0)
    });
    Score { score, passed: Some(failures.is_empty()), failures }
}
