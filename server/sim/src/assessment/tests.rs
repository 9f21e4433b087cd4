//! Metric definitions against hand-computed answers on synthetic tool paths.

use super::plan::Plan;
use super::task::{NoGoRegion, Task, TaskSpec};
use super::{Assessor, ToolSample};
use crate::math::Vec3;
use crate::tool::ToolShape;

const DT: f64 = 0.001;

fn straight_plan_task() -> Task {
    let plan = Plan::new(&[Vec3::new(-0.02, 0.0, 0.0), Vec3::new(0.02, 0.0, 0.0)], Vec3::z(), 0.002).unwrap();
    Task { plan: Some(plan), tool: Some(0), depth: None, no_go: Vec::new(), force_limit_n: None, grip_limit_n: None, min_coverage: 0.9 }
}

fn cutting_at(p: Vec3) -> ToolSample {
    ToolSample { position_m: p, force_n: 2.0, contacts: 3, active: true, cutting: true, cut_held: true, grip_force_n: 0.0 }
}

/// Cuts along x from `x0` to `x1` at `y` (m) at 0.1 m/s (0.1 mm a step).
fn cut(assessor: &mut Assessor, x0: f64, x1: f64, y: f64) {
    let steps = ((x1 - x0).abs() / 1e-4).round() as usize;
    for i in 0..=steps {
        let x = x0 + (x1 - x0) * i as f64 / steps as f64;
        assessor.observe(&[cutting_at(Vec3::new(x, y, -0.003))]);
    }
}

fn pause(assessor: &mut Assessor, steps: usize, p: Vec3) {
    for _ in 0..steps {
        assessor.observe(&[ToolSample { position_m: p, force_n: 0.0, contacts: 0, active: true, cutting: false, cut_held: true, grip_force_n: 0.0 }]);
    }
}

fn close(a: f64, b: f64, tolerance: f64) -> bool {
    (a - b).abs() <= tolerance
}

#[test]
fn a_straight_cut_offset_by_one_millimetre_deviates_by_one_millimetre() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, 0.02, 0.001);
    let a = assessor.assessment();
    assert!(close(a.deviation_rms_mm.unwrap(), 1.0, 1e-9), "{a:?}");
    assert!(close(a.deviation_max_mm.unwrap(), 1.0, 1e-9));
    assert!(close(a.incision_length_mm, 40.0, 1e-9));
    assert_eq!(a.plan_length_mm, Some(40.0));
    assert!(close(a.coverage.unwrap(), 1.0, 1e-12));
    assert_eq!(a.outside_band_mm, Some(0.0));
    assert_eq!(a.strokes, 1);
    assert!(a.completed);
    // 90 % of the plan's 160 bins of 0.25 mm is 144 bins, the last of which the blade
    // enters at 35.75 mm: step 358 at 0.1 mm a step.
    assert!(close(a.time_to_complete_s.unwrap(), 0.358, 1e-9), "{:?}", a.time_to_complete_s);
    assert_eq!(a.passed, Some(true), "{:?}", a.failures);
    // Only the deviation costs points: 25 × (1 mm / 2 mm).
    assert!(close(a.score.unwrap(), 87.5, 1e-9), "{:?}", a.score);
}

#[test]
fn a_cut_outside_the_band_covers_nothing_and_fails_with_the_reason() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, 0.02, 0.003);
    let a = assessor.assessment();
    assert!(close(a.deviation_rms_mm.unwrap(), 3.0, 1e-9));
    assert_eq!(a.coverage, Some(0.0));
    assert!(close(a.outside_band_mm.unwrap(), 40.0, 1e-9));
    assert!(!a.completed);
    assert_eq!(a.passed, Some(false));
    assert!(a.failures.iter().any(|f| f.contains("coverage 0 %")), "{:?}", a.failures);
    assert!(a.failures.iter().any(|f| f.contains("3.0 mm from the plan")), "{:?}", a.failures);
    // 35 (nothing covered) + 25 (RMS beyond the band) + 15 (all of it outside).
    assert!(close(a.score.unwrap(), 25.0, 1e-9));
    assert_eq!(a.events.iter().filter(|e| e.kind == "outside_band").count(), 0, "never inside, so never left");
}

#[test]
fn leaving_the_band_halfway_is_an_event_and_half_the_length_outside() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, 0.0, 0.0);
    // Jump sideways within one stroke to 3 mm off and carry on.
    cut(&mut assessor, 0.0, 0.02, 0.003);
    let a = assessor.assessment();
    assert_eq!(a.strokes, 1);
    assert!(close(a.coverage.unwrap(), 0.5, 0.01), "{:?}", a.coverage);
    // 20 mm outside, plus half the 3 mm sideways segment.
    assert!(close(a.outside_band_mm.unwrap(), 21.5, 1e-6), "{:?}", a.outside_band_mm);
    assert_eq!(a.events.iter().filter(|e| e.kind == "outside_band").count(), 1);
}

#[test]
fn pauses_longer_than_the_stroke_gap_start_a_new_stroke() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, -0.01, 0.0);
    pause(&mut assessor, 20, Vec3::new(-0.01, 0.0, -0.003));
    cut(&mut assessor, -0.01, 0.0, 0.0);
    pause(&mut assessor, 100, Vec3::new(0.0, 0.0, -0.003));
    cut(&mut assessor, 0.0, 0.02, 0.0);
    let a = assessor.assessment();
    assert_eq!(a.strokes, 2, "a 20 ms pause continues the stroke, a 100 ms one does not");
    assert!(close(a.coverage.unwrap(), 1.0, 1e-12));
    assert!(close(a.deviation_rms_mm.unwrap(), 0.0, 1e-12));
    assert!(close(a.score.unwrap(), 100.0, 1e-9));
}

#[test]
fn a_blade_held_in_the_tissue_continues_its_stroke_across_a_long_pause() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, 0.0, 0.0);
    // 200 ms on the tissue with the button held but nothing removed (a voxel model
    // removes tissue only every few steps), then on.
    for _ in 0..200 {
        assessor.observe(&[ToolSample { position_m: Vec3::new(0.0, 0.0, -0.003), force_n: 1.0, contacts: 2, active: true, cutting: false, cut_held: true, grip_force_n: 0.0 }]);
    }
    cut(&mut assessor, 0.0, 0.02, 0.0);
    let a = assessor.assessment();
    assert_eq!(a.strokes, 1);
    assert!(close(a.coverage.unwrap(), 1.0, 1e-12));
}

#[test]
fn path_length_and_economy_count_from_the_first_contact() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    // 10 mm of approach in the air: not part of the task.
    for i in 0..=100 {
        let p = Vec3::new(-0.02, 0.0, 0.01 - 1e-4 * i as f64);
        assessor.observe(&[ToolSample { position_m: p, active: true, ..Default::default() }]);
    }
    cut(&mut assessor, -0.02, 0.02, 0.0);
    // Back over the whole cut, in contact but not cutting: 40 mm more.
    for i in 0..=400 {
        let p = Vec3::new(0.02 - 1e-4 * i as f64, 0.0, -0.003);
        assessor.observe(&[ToolSample { position_m: p, force_n: 1.0, contacts: 1, active: true, ..Default::default() }]);
    }
    let a = assessor.assessment();
    assert!(close(a.path_length_mm, 80.0, 1e-6), "{}", a.path_length_mm);
    // Until completion (36 mm of plan covered) the path was 35.8 mm: no waste.
    assert_eq!(a.economy_of_motion, Some(1.0));
    assert!(close(a.started_s.unwrap(), 0.101, 1e-12));
}

#[test]
fn economy_of_motion_is_the_plan_over_the_path_when_motion_is_wasted() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    // Half the plan, back to the start in contact, then the whole plan again.
    cut(&mut assessor, -0.02, 0.0, 0.0);
    for i in 0..=200 {
        let p = Vec3::new(-1e-4 * i as f64, 0.0, -0.003);
        assessor.observe(&[ToolSample { position_m: p, force_n: 1.0, contacts: 1, active: true, ..Default::default() }]);
    }
    cut(&mut assessor, -0.02, 0.02, 0.0);
    let a = assessor.assessment();
    // Completion when coverage reaches 90 % (144 of 160 bins, the last entered at 35.75 mm
    // along the plan, so reached at the 0.1 mm step to 35.8 mm) comes 35.8 mm into the second
    // pass: 36 mm of plan covered for 20 + 20 + 35.8 mm of path.
    assert!(close(a.economy_of_motion.unwrap(), 36.0 / 75.8, 1e-9), "{:?}", a.economy_of_motion);
    assert!(close(a.incision_length_mm, 60.0, 1e-6));
}

#[test]
fn forces_peak_mean_and_time_above_the_limit() {
    let mut task = straight_plan_task();
    task.force_limit_n = Some(3.0);
    let mut assessor = Assessor::new(task, 1, DT);
    let p = Vec3::new(-0.02, 0.0, 0.0);
    for (force, steps) in [(1.0, 100), (4.0, 30), (2.0, 70)] {
        for _ in 0..steps {
            assessor.observe(&[ToolSample { position_m: p, force_n: force, contacts: 1, active: true, ..Default::default() }]);
        }
    }
    let a = assessor.assessment();
    assert_eq!(a.peak_force_n, 4.0);
    assert!(close(a.mean_force_n, (100.0 + 120.0 + 140.0) / 200.0, 1e-12));
    assert!(close(a.time_above_force_limit_s.unwrap(), 0.03, 1e-12));
    assert_eq!(a.events.iter().filter(|e| e.kind == "force_limit").count(), 1);
    assert!(a.failures.iter().any(|f| f.contains("above the force limit")), "{:?}", a.failures);
}

#[test]
fn the_hardest_pinch_and_the_time_above_the_grip_limit() {
    // Forceps (tool 1) beside a blade (tool 0): pinching with 2 N, then 5 N for 40 steps
    // twice over, against a 4 N limit; a pinch reported by an inactive tool is not one.
    let mut task = straight_plan_task();
    task.grip_limit_n = Some(4.0);
    let mut assessor = Assessor::new(task, 2, DT);
    let blade = ToolSample { position_m: Vec3::new(0.05, 0.0, 0.0), active: true, ..Default::default() };
    let forceps = |grip: f64, active: bool| ToolSample { position_m: Vec3::new(0.0, 0.01, 0.0), force_n: 1.0, contacts: 3, active, grip_force_n: grip, ..Default::default() };
    for (grip, steps, active) in [(2.0, 100, true), (5.0, 40, true), (0.0, 10, true), (5.0, 40, true), (9.0, 5, false)] {
        for _ in 0..steps {
            assessor.observe(&[blade, forceps(grip, active)]);
        }
    }
    let a = assessor.assessment();
    assert_eq!(a.peak_grip_force_n, 5.0);
    assert!(close(a.time_above_grip_limit_s.unwrap(), 0.08, 1e-12), "{:?}", a.time_above_grip_limit_s);
    let crossings: Vec<u64> = a.events.iter().filter(|e| e.kind == "grip_limit").map(|e| e.step).collect();
    assert_eq!(crossings, [100, 150], "{:?}", a.events);
    assert!(a.failures.iter().any(|f| f.contains("harder than the grip limit of 4 N")), "{:?}", a.failures);
    assert_eq!(a.time_above_force_limit_s, None, "the task sets no force limit");

    // Without a limit the hardest pinch is still measured, and fails nothing.
    let mut unlimited = Assessor::new(straight_plan_task(), 2, DT);
    unlimited.observe(&[blade, forceps(5.0, true)]);
    let a = unlimited.assessment();
    assert_eq!((a.peak_grip_force_n, a.time_above_grip_limit_s), (5.0, None));
    assert!(!a.failures.iter().any(|f| f.contains("grip")), "{:?}", a.failures);
}

#[test]
fn jerk_of_a_cubic_path_is_its_constant_third_derivative() {
    let task = Task { plan: None, tool: Some(0), depth: None, no_go: Vec::new(), force_limit_n: None, grip_limit_n: None, min_coverage: 0.9 };
    let mut assessor = Assessor::new(task, 1, DT);
    let jerk = 6.0; // m/s³: x = jerk t³ / 6
    for i in 0..1000 {
        let t = i as f64 * DT;
        let p = Vec3::new(jerk * t * t * t / 6.0, 0.0, 0.0);
        assessor.observe(&[ToolSample { position_m: p, contacts: 1, active: true, ..Default::default() }]);
    }
    let a = assessor.assessment();
    assert!(close(a.jerk_rms_m_per_s3, jerk, 1e-6), "{}", a.jerk_rms_m_per_s3);
    // T = 0.999 s of motion, L = x(T); 100 samples 10 ms apart, of which the first three
    // only fill the window: ∫j² dt = j² × 0.97 s.
    let (t, length): (f64, f64) = (0.999, jerk * 0.999f64.powi(3) / 6.0);
    let integral = jerk * jerk * 0.97;
    let expected = -(t.powi(5) / (length * length) * integral).ln();
    assert!(close(a.log_dimensionless_jerk.unwrap(), expected, 1e-6), "{:?} vs {expected}", a.log_dimensionless_jerk);
    assert_eq!(a.score, None, "no plan, no score");
    assert_eq!(a.passed, None, "no task, no verdict");
}

#[test]
fn no_go_entries_count_each_entry_and_the_time_inside() {
    let mut task = straight_plan_task();
    task.no_go.push(NoGoRegion { name: "vessel".into(), min: Vec3::new(0.0, -0.01, -0.01), max: Vec3::new(0.01, 0.01, 0.01), max_force_n: 1.0 });
    let mut assessor = Assessor::new(task, 1, DT);
    let inside = Vec3::new(0.005, 0.0, 0.0);
    let outside = Vec3::new(-0.005, 0.0, 0.0);
    let press = |p: Vec3, f: f64| ToolSample { position_m: p, force_n: f, contacts: 1, active: true, ..Default::default() };
    for (p, f, steps) in [(inside, 2.0, 30), (outside, 2.0, 10), (inside, 0.5, 10), (inside, 1.5, 20)] {
        for _ in 0..steps {
            assessor.observe(&[press(p, f)]);
        }
    }
    let a = assessor.assessment();
    assert_eq!(a.no_go_entries, 2, "pressing below the region's force is allowed");
    assert!(close(a.no_go_time_s, 0.05, 1e-12));
    assert_eq!(a.passed, Some(false));
    assert!(a.events.iter().any(|e| e.kind == "no_go" && e.message.contains("\"vessel\"")), "{:?}", a.events);
}

#[test]
fn depth_error_is_measured_below_the_plan_against_the_target() {
    let mut task = straight_plan_task();
    task.depth = Some((0.002, 0.0005));
    let mut assessor = Assessor::new(task, 1, DT);
    // The cut helper holds the tip 3 mm below the plan: 1 mm deeper than the target.
    cut(&mut assessor, -0.02, 0.02, 0.0);
    let a = assessor.assessment();
    assert!(close(a.depth_error_rms_mm.unwrap(), 1.0, 1e-9));
    assert!(a.failures.iter().any(|f| f.contains("depth")), "{:?}", a.failures);
    // 10 points for a depth error at (beyond) its tolerance; nothing else lost.
    assert!(close(a.score.unwrap(), 90.0, 1e-9));
}

#[test]
fn the_same_steps_give_the_same_metrics() {
    let run = || {
        let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
        cut(&mut assessor, -0.02, 0.013, 0.0007);
        pause(&mut assessor, 80, Vec3::zeros());
        cut(&mut assessor, 0.013, 0.02, -0.0004);
        assessor.assessment()
    };
    assert_eq!(run(), run());
}

fn tools() -> Vec<ToolShape> {
    let shape = |name: &str, can_cut| ToolShape {
        name: name.into(),
        radius_m: 0.001,
        length_m: 0.05,
        section: crate::tool::Section::Round,
        contact_stiffness_n_per_m: 100.0,
        can_cut,
        max_force_n: 10.0,
        cutting_shape: None,
        edge_local: Vec3::x(),
        tip_shape: crate::tool::TipShape::Flat,
    };
    vec![shape("probe", false), shape("scalpel", true)]
}

#[test]
fn a_grip_limit_is_kept_where_the_scene_has_forceps() {
    let mut with_forceps = tools();
    with_forceps[0].section = crate::tool::Section::Jaws { half_width_m: 1e-3, half_thickness_m: 5e-4, half_gap_m: 4e-3, grip_force_n: 3.0, grip_length_m: 0.01 };
    let spec: TaskSpec = serde_json::from_str(r#"{"grip_limit_n": 2.5}"#).unwrap();
    assert_eq!(spec.compile(&with_forceps, "test scene").unwrap().grip_limit_n, Some(2.5));
}

fn compile(json: &str) -> Result<Task, String> {
    let spec: TaskSpec = serde_json::from_str(json).map_err(|e| e.to_string())?;
    spec.compile(&tools(), "test scene").map_err(|e| e.to_string())
}

#[test]
fn a_task_measures_the_first_cutting_tool_unless_it_names_one() {
    let task = compile(r#"{"incision": {"points_m": [[0,0,0],[0.01,0,0]], "band_m": 0.002}}"#).unwrap();
    assert_eq!(task.tool, Some(1));
    let e = compile(r#"{"incision": {"points_m": [[0,0,0],[0.01,0,0]], "band_m": 0.002, "tool": "probe"}}"#).unwrap_err();
    assert!(e.contains("task.incision") && e.contains("can cut"), "{e}");
    let e = compile(r#"{"incision": {"points_m": [[0,0,0],[0.01,0,0]], "band_m": 0.002, "tool": "knife"}}"#).unwrap_err();
    assert!(e.contains("task.incision.tool") && e.contains("probe, scalpel"), "{e}");
}

#[test]
fn bad_tasks_are_refused_with_the_path_and_what_is_allowed() {
    let e = compile(r#"{"incision": {"points_m": [[0,0,0]], "band_m": 0.002}}"#).unwrap_err();
    assert!(e.contains("task.incision.points_m") && e.contains("at least two"), "{e}");
    let e = compile(r#"{"min_coverage": 1.5}"#).unwrap_err();
    assert!(e.contains("task.min_coverage") && e.contains("(0, 1]"), "{e}");
    let e = compile(r#"{"no_go": [{"name": "m", "min_m": [0,0,0.1], "max_m": [1,1,0]}]}"#).unwrap_err();
    assert!(e.contains("task.no_go[0]") && e.contains("min ≤ max"), "{e}");
    let e = compile(r#"{"incision": {"points_m": [[0,0,0],[0.01,0,0]], "band_m": 0.002, "normal": [0,0,0]}}"#).unwrap_err();
    assert!(e.contains("task.incision.normal"), "{e}");
    let many = format!(r#"{{"no_go": [{}]}}"#, vec![r#"{"name": "m", "min_m": [0,0,0], "max_m": [1,1,1]}"#; 101].join(","));
    let e = compile(&many).unwrap_err();
    assert!(e.contains("task.no_go") && e.contains("at most 100"), "{e}");
    let e = compile(r#"{"incision": {"points_m": [[0,0,0],[0.01,0,0]], "band_m": -1}}"#).unwrap_err();
    assert!(e.contains("length must be within"), "{e}");
    let e = compile(r#"{"grip_limit_n": 4}"#).unwrap_err();
    assert!(e.contains("task.grip_limit_n") && e.contains("needs forceps") && e.contains("probe, scalpel"), "{e}");
    let e = compile(r#"{"grip_limit_n": -4}"#).unwrap_err();
    assert!(e.contains("force must be within [0,"), "{e}");
}

#[test]
fn the_history_keeps_the_cut_path_by_stroke_and_force_peaks_in_bins() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    cut(&mut assessor, -0.02, 0.0, 0.0);
    pause(&mut assessor, 100, Vec3::new(0.0, 0.0, 0.01));
    cut(&mut assessor, 0.0, 0.02, 0.0);
    let h = assessor.history();
    // 20 mm at 0.1 mm a step, a point every 0.25 mm (every third sample, 0.3 mm): 67 a stroke.
    assert_eq!(h.cut_path.iter().filter(|(s, _)| *s == 1).count(), 67);
    assert_eq!(h.cut_path.iter().filter(|(s, _)| *s == 2).count(), 67);
    // 201 + 100 + 201 steps in 20 ms bins: 26 bins; 2 N while cutting, 0 in the pause.
    assert_eq!(h.force_peaks_n.len(), 26);
    assert_eq!(h.force_peaks_n[0], 2.0);
    assert_eq!(h.force_peaks_n[12], 0.0);
}

#[test]
fn a_long_session_doubles_its_force_bins_instead_of_growing() {
    let task = Task { plan: None, tool: Some(0), depth: None, no_go: Vec::new(), force_limit_n: None, grip_limit_n: None, min_coverage: 0.9 };
    let mut assessor = Assessor::new(task, 1, DT);
    let steps = 20 * 8_192 * 3; // three times what 20 ms bins hold
    for i in 0..steps {
        let force = if i == steps / 2 { 5.0 } else { 1.0 };
        assessor.observe(&[ToolSample { force_n: force, contacts: 1, active: true, ..Default::default() }]);
    }
    let h = assessor.history();
    assert!(h.force_peaks_n.len() <= super::metrics::MAX_FORCE_BINS);
    assert_eq!(h.force_bin_s, 0.08, "bins doubled twice");
    assert_eq!(h.force_peaks_n.iter().filter(|&&f| f == 5.0).count(), 1, "the peak survives the merges");
}

#[test]
fn a_timeline_bins_the_force_and_ends_with_the_final_metrics() {
    let mut assessor = Assessor::new(straight_plan_task(), 1, DT);
    // 401 cutting steps at 2 N with one of 7 N, then 99 steps of rest: 500 steps in 500 bins…
    let mut steps: Vec<ToolSample> = (0..=400).map(|i| cutting_at(Vec3::new(-0.02 + 1e-4 * i as f64, 0.0, -0.003))).collect();
    steps[250].force_n = 7.0;
    steps.extend((0..99).map(|_| ToolSample { position_m: Vec3::new(0.02, 0.0, 0.01), active: true, ..Default::default() }));
    let mut one_per_step = super::Timeline::new(500, DT);
    // …or, for a recording of 600,000 steps, 600 bins of 1,000 (watch only the first 2,000).
    let mut long = super::Timeline::new(600_000, DT);
    let mut long_assessor = assessor.clone();
    for s in &steps {
        assessor.observe(std::slice::from_ref(s));
        one_per_step.observe(&assessor);
    }
    assert!(one_per_step.complete());
    assert_eq!((one_per_step.bin_steps, one_per_step.force_peak_n.len(), one_per_step.score.len()), (1, 500, 500));
    assert_eq!(one_per_step.force_peak_n[250], 7.0);
    assert_eq!(one_per_step.force_peak_n[499], 0.0);
    let a = assessor.assessment();
    assert_eq!(one_per_step.score.last().copied().flatten(), a.score.map(|s| s as f32));
    assert_eq!(one_per_step.coverage_pct[499], Some(100.0));
    assert_eq!(one_per_step.coverage_pct[0], Some(100.0 / 160.0), "one step covers one 0.25 mm bin of 160");
    observe_all(&mut long, &mut long_assessor, &steps, 4);
    assert_eq!((long.bin_steps, long.indexed_steps, long.force_peak_n.len(), long.score.len()), (1000, 2000, 2, 2));
    assert_eq!(long.force_peak_n, vec![7.0, 7.0], "each bin keeps its largest force, not its last");
    long_assessor.observe(&steps[..1]);
    long.observe(&long_assessor);
    assert_eq!(long.force_peak_n.len(), 3, "a step past a bin's end opens the next");
    assert!(!long.complete());
}

/// Observes `steps` `times` over.
fn observe_all(timeline: &mut super::Timeline, assessor: &mut Assessor, steps: &[ToolSample], times: usize) {
    for _ in 0..times {
        for s in steps {
            assessor.observe(std::slice::from_ref(s));
            timeline.observe(assessor);
        }
    }
}
