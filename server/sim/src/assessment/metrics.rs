//! The assessor: folds each step's tool samples into the trainee's metrics.
//!
//! It sees, per step, every tool's tip position, force, contacts and whether it cut (the
//! same inputs in a live session, a script and a replay, so the same commands give the
//! same metrics), and keeps running sums only: a step costs a few dozen flops, plus a
//! walk over the plan's segments when the measured tool cuts. Definitions and sources:
//! docs/assessment.md.

use serde::{Deserialize, Serialize};

use super::plan::Nearest;
use crate::math::across;
use super::score::{self, Score};
use super::task::Task;
use crate::math::Vec3;
use crate::tool::{ToolCommand, ToolFeedback};

/// A pause in cutting shorter than this continues the stroke; a longer one starts a new
/// one unless the blade stayed on the tissue with its cut button held all along (a
/// volumetric model removes a voxel only every few steps).
pub const STROKE_GAP_S: f64 = 0.05;
/// The tool path is sampled this often for its jerk (finer sampling amplifies the
/// rounding of the positions, not the motion).
pub const JERK_SAMPLE_S: f64 = 0.01;
/// Coverage of the plan is kept in bins of this length along it, m.
pub const COVERAGE_BIN_M: f64 = 0.000_25;
/// Events kept in a session's list (later ones are counted, not kept).
pub const MAX_EVENTS: usize = 200;
/// The cut path is kept as points at least this far apart, m (for the report's figure).
pub const PATH_SPACING_M: f64 = 0.000_25;
/// Points the history keeps of the cut path.
pub const MAX_PATH_POINTS: usize = 8_192;
/// The force history starts with one peak every this many seconds…
pub const FORCE_BIN_S: f64 = 0.02;
/// …and doubles its bins whenever it holds this many, so a long session still fits.
pub const MAX_FORCE_BINS: usize = 8_192;

/// What the report draws: the measured tool's cut path and the force over time.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct History {
    /// Cut path points (m) with the stroke each belongs to (from 1).
    pub cut_path: Vec<(u32, [f32; 3])>,
    /// The largest force on any tool in each bin, N, from step 0.
    pub force_peaks_n: Vec<f32>,
    /// The bins' length, s.
    pub force_bin_s: f64,
}

impl History {
    fn new() -> Self {
        Self { cut_path: Vec::new(), force_peaks_n: Vec::new(), force_bin_s: FORCE_BIN_S }
    }

    fn add_force(&mut self, step: u64, dt: f64, force: f64) {
        let bin = ((step as f64 + 0.5) * dt / self.force_bin_s) as usize;
        if bin >= self.force_peaks_n.len() {
            self.force_peaks_n.resize(bin + 1, 0.0);
        }
        let peak = &mut self.force_peaks_n[bin];
        *peak = peak.max(force as f32);
        if self.force_peaks_n.len() > MAX_FORCE_BINS {
            // Twice as long bins, each the larger of two.
            self.force_peaks_n = self.force_peaks_n.chunks(2).map(|p| p.iter().copied().fold(0.0, f32::max)).collect();
            self.force_bin_s *= 2.0;
        }
    }

    fn add_cut_point(&mut self, stroke: u32, p: &Vec3) {
        let point = [p.x as f32, p.y as f32, p.z as f32];
        let far = self.cut_path.last().is_none_or(|(s, q)| {
            *s != stroke || (0..3).map(|a| f64::from(q[a] - point[a]).powi(2)).sum::<f64>() >= PATH_SPACING_M * PATH_SPACING_M
        });
        if far && self.cut_path.len() < MAX_PATH_POINTS {
            self.cut_path.push((stroke, point));
        }
    }
}

/// One tool after one step, as the assessor sees it.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ToolSample {
    /// The tool tip, m.
    pub position_m: Vec3,
    /// Magnitude of the force on the tool, N.
    pub force_n: f64,
    pub contacts: u32,
    pub active: bool,
    /// The tool removed tissue this step.
    pub cutting: bool,
    /// The cut button is held (a blade engaged, whether or not it removed tissue).
    pub cut_held: bool,
    /// Forceps: how hard what the jaws hold pushes them apart (the grip they pinch it
    /// with), N; 0 for other tools and jaws holding nothing.
    pub grip_force_n: f64,
}

impl ToolSample {
    pub fn new(command: &ToolCommand, feedback: &ToolFeedback) -> Self {
        Self {
            position_m: command.pose.position_m,
            force_n: feedback.force_n.norm(),
            contacts: feedback.contacts,
            active: command.active,
            cutting: feedback.cutting,
            cut_held: command.cut,
            grip_force_n: feedback.jaws_force_n,
        }
    }
}

/// Fills `samples[i]` from tool i's command and feedback of one step.
pub fn fill_samples(samples: &mut [ToolSample], commands: &[ToolCommand], feedback: &[ToolFeedback]) {
    for ((sample, command), fb) in samples.iter_mut().zip(commands).zip(feedback) {
        *sample = ToolSample::new(command, fb);
    }
}

/// Something an instructor wants to know when it happens.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AssessmentEvent {
    /// Steps taken when it happened.
    pub step: u64,
    pub time_s: f64,
    /// "no_go", "force_limit", "grip_limit", "outside_band" or "completed".
    pub kind: String,
    pub message: String,
}

/// The metrics of a session so far. Lengths in mm, times in s, forces in N; a metric
/// that needs a part of the task the scene does not have is absent.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
pub struct Assessment {
    /// Steps assessed.
    pub steps: u64,
    /// The scene has a planned incision.
    pub has_plan: bool,
    /// When the task started (the first tool contact or cut), s.
    pub started_s: Option<f64>,
    /// The plan's coverage reached the task's minimum.
    pub completed: bool,
    /// From the start to completion, s.
    pub time_to_complete_s: Option<f64>,
    /// Length of the measured tool's cut path (across the normal), mm.
    pub incision_length_mm: f64,
    pub plan_length_mm: Option<f64>,
    /// Fraction of the plan's length cut within its band (0–1).
    pub coverage: Option<f64>,
    /// Deviation of the cut path from the plan, weighted by cut length: RMS and largest, mm.
    pub deviation_rms_mm: Option<f64>,
    pub deviation_max_mm: Option<f64>,
    /// Cut path outside the tolerance band, mm.
    pub outside_band_mm: Option<f64>,
    /// RMS of (depth reached − target depth) along the cut, mm (plans with a depth).
    pub depth_error_rms_mm: Option<f64>,
    /// Separate cutting strokes (pauses longer than 50 ms separate them).
    pub strokes: u64,
    /// Path of the measured tool's tip since the start, mm.
    pub path_length_mm: f64,
    /// Length of plan covered over the tip's path, until completion (1: no motion wasted).
    pub economy_of_motion: Option<f64>,
    /// Largest force on any tool, N, and the mean over steps in contact.
    pub peak_force_n: f64,
    pub mean_force_n: f64,
    /// Time any tool was above the task's force limit, s.
    pub time_above_force_limit_s: Option<f64>,
    /// The hardest any forceps pinched what they held, N (0: nothing grasped).
    #[serde(default)]
    pub peak_grip_force_n: f64,
    /// Time any forceps pinched harder than the task's grip limit, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_above_grip_limit_s: Option<f64>,
    /// RMS jerk of the measured tool's tip (sampled at 100 Hz), m/s³.
    pub jerk_rms_m_per_s3: f64,
    /// Log dimensionless jerk, −ln(T⁵/L²·∫|j|²dt): higher is smoother.
    pub log_dimensionless_jerk: Option<f64>,
    /// Entries into no-go regions (cutting there, or pressing above its force), and the
    /// time spent in violation, s.
    pub no_go_entries: u64,
    pub no_go_time_s: f64,
    /// 0–100 with the weights of docs/assessment.md (tasks with a plan).
    pub score: Option<f64>,
    /// Complete, inside the band, no no-go entry, depth and force within limits.
    pub passed: Option<bool>,
    /// What went wrong, in words (empty when nothing did).
    pub failures: Vec<String>,
    pub events: Vec<AssessmentEvent>,
    /// Events beyond the kept list.
    pub events_dropped: u64,
}

/// Running sums for a length-weighted mean square along the cut.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct AlongCut {
    weighted: f64,
    length: f64,
    samples_sum: f64,
    samples: u64,
}

impl AlongCut {
    /// Adds a segment from a value `a` to `b` over `length` (trapezoid rule), or a lone
    /// sample when the stroke just started.
    fn add(&mut self, a: Option<f64>, b: f64, length: f64) {
        if let Some(a) = a {
            self.weighted += 0.5 * (a * a + b * b) * length;
            self.length += length;
        }
        self.samples_sum += b * b;
        self.samples += 1;
    }

    fn rms(&self) -> Option<f64> {
        if self.length > 0.0 {
            Some((self.weighted / self.length).sqrt())
        } else if self.samples > 0 {
            Some((self.samples_sum / self.samples as f64).sqrt())
        } else {
            None
        }
    }
}

/// The steps spent above a limit, and whether the last one was (to tell a crossing).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct AboveLimit {
    steps: u64,
    above: bool,
}

impl AboveLimit {
    /// Counts a step whose value is `value`; true when it has just gone above `limit`.
    fn crossed(&mut self, value: f64, limit: f64) -> bool {
        let above = value > limit;
        let crossed = above && !self.above;
        self.steps += u64::from(above);
        self.above = above;
        crossed
    }
}

/// The last cutting sample of the measured tool.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CutPoint {
    step: u64,
    position: Vec3,
    nearest: Option<Nearest>,
}

/// Folds steps into an [`Assessment`]. Cheap to clone (replays keep copies).
#[derive(Debug, Clone, PartialEq)]
pub struct Assessor {
    task: Task,
    tools: usize,
    dt: f64,
    stroke_gap_steps: u64,
    jerk_every: u64,
    steps: u64,
    started_step: Option<u64>,
    completed_step: Option<u64>,
    last_cut: Option<CutPoint>,
    /// The blade left the tissue or let go of the cut button since the last cut.
    disengaged: bool,
    strokes: u64,
    incision_length_m: f64,
    deviation: AlongCut,
    deviation_max_m: f64,
    depth_error: AlongCut,
    outside_band_m: f64,
    covered: Vec<bool>,
    covered_count: usize,
    bin_m: f64,
    last_position: Option<Vec3>,
    path_length_m: f64,
    /// (path length, plan covered) when the task completed, m.
    at_completion: Option<(f64, f64)>,
    active_time_s: f64,
    jerk_window: [Vec3; 4],
    jerk_filled: usize,
    jerk_integral: f64,
    jerk_time_s: f64,
    peak_force_n: f64,
    /// The largest force on any active tool in the last step.
    step_force_n: f64,
    contact_force_sum: f64,
    contact_steps: u64,
    above_force_limit: AboveLimit,
    peak_grip_force_n: f64,
    above_grip_limit: AboveLimit,
    /// Per (tool, region): in violation at the last step.
    violating: Vec<bool>,
    no_go_entries: u64,
    no_go_steps: u64,
    events: Vec<AssessmentEvent>,
    events_dropped: u64,
    history: History,
}

impl Assessor {
    /// An assessor for `tools` tools stepped every `time_step_s`.
    pub fn new(task: Task, tools: usize, time_step_s: f64) -> Self {
        let (covered, bin_m) = match &task.plan {
            Some(plan) => {
                let bins = (plan.length_m() / COVERAGE_BIN_M).ceil().clamp(1.0, 1e6) as usize;
                (vec![false; bins], plan.length_m() / bins as f64)
            }
            None => (Vec::new(), 1.0),
        };
        let regions = task.no_go.len();
        Self {
            task,
            tools,
            dt: time_step_s,
            stroke_gap_steps: (STROKE_GAP_S / time_step_s).round().max(1.0) as u64,
            jerk_every: (JERK_SAMPLE_S / time_step_s).round().max(1.0) as u64,
            steps: 0,
            started_step: None,
            completed_step: None,
            last_cut: None,
            disengaged: true,
            strokes: 0,
            incision_length_m: 0.0,
            deviation: AlongCut::default(),
            deviation_max_m: 0.0,
            depth_error: AlongCut::default(),
            outside_band_m: 0.0,
            covered,
            covered_count: 0,
            bin_m,
            last_position: None,
            path_length_m: 0.0,
            at_completion: None,
            active_time_s: 0.0,
            jerk_window: [Vec3::zeros(); 4],
            jerk_filled: 0,
            jerk_integral: 0.0,
            jerk_time_s: 0.0,
            peak_force_n: 0.0,
            step_force_n: 0.0,
            contact_force_sum: 0.0,
            contact_steps: 0,
            above_force_limit: AboveLimit::default(),
            peak_grip_force_n: 0.0,
            above_grip_limit: AboveLimit::default(),
            violating: vec![false; tools * regions],
            no_go_entries: 0,
            no_go_steps: 0,
            events: Vec::new(),
            events_dropped: 0,
            history: History::new(),
        }
    }

    /// The cut path and the force over time, for the report's figures.
    pub fn history(&self) -> &History {
        &self.history
    }

    /// Starts again from no steps (the tissue was rebuilt).
    pub fn reset(&mut self) {
        *self = Assessor::new(self.task.clone(), self.tools, self.dt);
    }

    /// The task it measures against.
    pub fn task(&self) -> &Task {
        &self.task
    }

    /// Steps folded in so far.
    pub fn steps(&self) -> u64 {
        self.steps
    }

    /// The largest force on any active tool in the last step folded in, N (what the peak
    /// force and the force history are made of).
    pub fn step_force_n(&self) -> f64 {
        self.step_force_n
    }

    /// Folds in one step: `tools[i]` is tool i after it.
    pub fn observe(&mut self, tools: &[ToolSample]) {
        let step = self.steps;
        self.steps += 1;
        if self.started_step.is_none() && tools.iter().any(|t| t.active && (t.contacts > 0 || t.cutting)) {
            self.started_step = Some(step);
        }
        self.observe_forces(step, tools);
        self.observe_grip(step, tools);
        self.observe_no_go(step, tools);
        let Some(measured) = self.task.tool.and_then(|i| tools.get(i)) else { return };
        if self.started_step.is_some() {
            self.observe_motion(measured);
        }
        if measured.active && measured.cutting {
            self.observe_cut(step, measured.position_m);
            self.disengaged = false;
        } else if !(measured.active && measured.cut_held && measured.contacts > 0) {
            self.disengaged = true;
        }
    }

    fn observe_forces(&mut self, step: u64, tools: &[ToolSample]) {
        let mut largest: f64 = 0.0;
        for tool in tools.iter().filter(|t| t.active) {
            largest = largest.max(tool.force_n);
            if tool.contacts > 0 {
                self.contact_force_sum += tool.force_n;
                self.contact_steps += 1;
            }
        }
        self.step_force_n = largest;
        self.peak_force_n = self.peak_force_n.max(largest);
        self.history.add_force(step, self.dt, largest);
        if let Some(limit) = self.task.force_limit_n
            && self.above_force_limit.crossed(largest, limit)
        {
            self.event(step, "force_limit", format!("force {largest:.2} N is above the task's limit of {limit} N"));
        }
    }

    fn observe_grip(&mut self, step: u64, tools: &[ToolSample]) {
        let hardest = tools.iter().filter(|t| t.active).map(|t| t.grip_force_n).fold(0.0, f64::max);
        self.peak_grip_force_n = self.peak_grip_force_n.max(hardest);
        if let Some(limit) = self.task.grip_limit_n
            && self.above_grip_limit.crossed(hardest, limit)
        {
            self.event(step, "grip_limit", format!("forceps pinch with {hardest:.2} N, above the task's grip limit of {limit} N"));
        }
    }

    fn observe_no_go(&mut self, step: u64, tools: &[ToolSample]) {
        let regions = self.task.no_go.len();
        if regions == 0 {
            return;
        }
        let mut any = false;
        for (t, tool) in tools.iter().enumerate() {
            for r in 0..regions {
                let region = &self.task.no_go[r];
                let inside = tool.active && region.contains(&tool.position_m);
                let pressing = tool.contacts > 0 && tool.force_n > region.max_force_n;
                let violation = inside && (tool.cutting || pressing);
                let slot = t * regions + r;
                if violation && !self.violating.get(slot).copied().unwrap_or(true) {
                    self.no_go_entries += 1;
                    let what = if tool.cutting { "cut".to_owned() } else { format!("pressed with {:.2} N", tool.force_n) };
                    self.event(step, "no_go", format!("tool {t} {what} inside no-go region {:?}", region.name));
                }
                if let Some(v) = self.violating.get_mut(slot) {
                    *v = violation;
                }
                any |= violation;
            }
        }
        self.no_go_steps += u64::from(any);
    }

    fn observe_motion(&mut self, tool: &ToolSample) {
        if !tool.active {
            self.last_position = None;
            self.jerk_filled = 0;
            return;
        }
        let p = tool.position_m;
        if let Some(last) = self.last_position {
            self.path_length_m += (p - last).norm();
            self.active_time_s += self.dt;
        }
        self.last_position = Some(p);
        if self.steps.is_multiple_of(self.jerk_every) {
            self.jerk_window.rotate_left(1);
            self.jerk_window[3] = p;
            self.jerk_filled = (self.jerk_filled + 1).min(4);
            if self.jerk_filled == 4 {
                let h = self.dt * self.jerk_every as f64;
                let [p0, p1, p2, p3] = self.jerk_window;
                let jerk = (p3 - p2 * 3.0 + p1 * 3.0 - p0) / (h * h * h);
                self.jerk_integral += jerk.norm_squared() * h;
                self.jerk_time_s += h;
            }
        }
    }

    fn observe_cut(&mut self, step: u64, position: Vec3) {
        let nearest = self.task.plan.as_ref().map(|plan| plan.nearest(&position));
        let previous = self.last_cut.filter(|c| step - c.step <= self.stroke_gap_steps || !self.disengaged);
        if previous.is_none() {
            self.strokes += 1;
        }
        let normal = self.task.plan.as_ref().map_or(Vec3::z(), |p| p.normal);
        let length = previous.map_or(0.0, |c| across(&(position - c.position), &normal).norm());
        self.incision_length_m += length;
        if let (Some(plan), Some(n)) = (&self.task.plan, nearest) {
            let band = plan.band_m;
            let before = previous.and_then(|c| c.nearest);
            self.deviation.add(before.map(|b| b.deviation_m), n.deviation_m, length);
            self.deviation_max_m = self.deviation_max_m.max(n.deviation_m);
            if let Some((target, _)) = self.task.depth {
                self.depth_error.add(before.map(|b| b.depth_m - target), n.depth_m - target, length);
            }
            let outside_now = n.deviation_m > band;
            if let Some(b) = before {
                let outside_before = b.deviation_m > band;
                self.outside_band_m += length * 0.5 * (f64::from(u8::from(outside_before)) + f64::from(u8::from(outside_now)));
                if outside_now && !outside_before {
                    self.event(step, "outside_band", format!("the cut left the band: {:.1} mm from the plan (band ±{:.1} mm)", n.deviation_m * 1e3, band * 1e3));
                }
                if !outside_now && !outside_before {
                    self.cover(b.arc_m, n.arc_m);
                }
            } else if !outside_now {
                self.cover(n.arc_m, n.arc_m);
            }
        }
        self.history.add_cut_point(self.strokes as u32, &position);
        self.last_cut = Some(CutPoint { step, position, nearest });
        self.check_completion(step);
    }

    fn cover(&mut self, from_m: f64, to_m: f64) {
        let last = self.covered.len() - 1;
        let bin = |s: f64| ((s / self.bin_m) as usize).min(last);
        let (a, b) = (bin(from_m.min(to_m)), bin(from_m.max(to_m)));
        for covered in &mut self.covered[a..=b] {
            if !*covered {
                *covered = true;
                self.covered_count += 1;
            }
        }
    }

    /// Length of the plan covered, m.
    fn covered_m(&self) -> f64 {
        self.covered_count as f64 * self.bin_m
    }

    fn coverage(&self) -> Option<f64> {
        self.task.plan.as_ref().map(|_| self.covered_count as f64 / self.covered.len() as f64)
    }

    fn check_completion(&mut self, step: u64) {
        if self.completed_step.is_none() && self.coverage().is_some_and(|c| c >= self.task.min_coverage) {
            self.completed_step = Some(step);
            self.at_completion = Some((self.path_length_m, self.covered_m()));
            let started = self.started_step.unwrap_or(step);
            self.event(step, "completed", format!("the planned incision is complete after {:.2} s", (step - started) as f64 * self.dt));
        }
    }

    fn event(&mut self, step: u64, kind: &str, message: String) {
        if self.events.len() < MAX_EVENTS {
            self.events.push(AssessmentEvent { step, time_s: step as f64 * self.dt, kind: kind.to_owned(), message });
        } else {
            self.events_dropped += 1;
        }
    }

    /// The metrics so far.
    pub fn assessment(&self) -> Assessment {
        let mm = |m: f64| m * 1e3;
        let plan = self.task.plan.as_ref();
        let started = self.started_step;
        let economy = plan.and_then(|_| {
            let (path, covered) = self.at_completion.unwrap_or((self.path_length_m, self.covered_m()));
            (path > 0.0).then(|| (covered / path).min(1.0))
        });
        let log_dimensionless_jerk = (self.path_length_m > 0.0 && self.jerk_integral > 0.0).then(|| {
            let t = self.active_time_s;
            -(t.powi(5) / (self.path_length_m * self.path_length_m) * self.jerk_integral).ln()
        });
        let mut assessment = Assessment {
            steps: self.steps,
            has_plan: plan.is_some(),
            started_s: started.map(|s| s as f64 * self.dt),
            completed: self.completed_step.is_some(),
            time_to_complete_s: self.completed_step.map(|c| (c - started.unwrap_or(c)) as f64 * self.dt),
            incision_length_mm: mm(self.incision_length_m),
            plan_length_mm: plan.map(|p| mm(p.length_m())),
            coverage: self.coverage(),
            deviation_rms_mm: plan.and(self.deviation.rms()).map(mm),
            deviation_max_mm: plan.and((self.deviation.samples > 0).then_some(self.deviation_max_m)).map(mm),
            outside_band_mm: plan.map(|_| mm(self.outside_band_m)),
            depth_error_rms_mm: self.task.depth.and(self.depth_error.rms()).map(mm),
            strokes: self.strokes,
            path_length_mm: mm(self.path_length_m),
            economy_of_motion: economy,
            peak_force_n: self.peak_force_n,
            mean_force_n: if self.contact_steps > 0 { self.contact_force_sum / self.contact_steps as f64 } else { 0.0 },
            time_above_force_limit_s: self.task.force_limit_n.map(|_| self.above_force_limit.steps as f64 * self.dt),
            peak_grip_force_n: self.peak_grip_force_n,
            time_above_grip_limit_s: self.task.grip_limit_n.map(|_| self.above_grip_limit.steps as f64 * self.dt),
            jerk_rms_m_per_s3: if self.jerk_time_s > 0.0 { (self.jerk_integral / self.jerk_time_s).sqrt() } else { 0.0 },
            log_dimensionless_jerk,
            no_go_entries: self.no_go_entries,
            no_go_time_s: self.no_go_steps as f64 * self.dt,
            score: None,
            passed: None,
            failures: Vec::new(),
            events: self.events.clone(),
            events_dropped: self.events_dropped,
        };
        let Score { score, passed, failures } = score::score(&self.task, &assessment);
        assessment.score = score;
        assessment.passed = passed;
        assessment.failures = failures;
        assessment
    }
}
