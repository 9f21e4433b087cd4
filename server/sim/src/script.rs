//! Cut scripts: timed tool poses and expectations on the result, run in lockstep.
//!
//! A script lists, per tool, keyframes at a step index (or a time, converted with the
//! scene's step). Between keyframes the position is interpolated linearly and the
//! orientation by slerp; the cut button, the forceps' grip and presence hold the earlier
//! keyframe's value.
//! Before its first keyframe a tool is away. The format is documented in
//! docs/cut-script.md and shared by `cutsim-server run`, the gRPC API and `cut-bot`.

use std::collections::BTreeMap;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::math::{Pose, Vec3, quat_from_wxyz, quat_from_wxyz_exact};
use crate::quantity::CoordinateM;
use crate::scene::SceneError;
use crate::tool::{ToolCommand, ToolShape};

/// The most steps a script may ask for (about 2.8 h at 1 kHz).
pub const MAX_SCRIPT_STEPS: u64 = 10_000_000;
/// The most keyframes a script may hold over all tools.
pub const MAX_KEYFRAMES: usize = 1_000_000;

#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema, Default)]
#[serde(deny_unknown_fields)]
pub struct CutScript {
    /// Scene to run (bundled name or path) when the caller does not give one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub scene: Option<String>,
    /// Steps to run. Default: up to and including the last keyframe.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub steps: Option<u64>,
    #[serde(default)]
    pub tools: Vec<ToolTrack>,
    #[serde(default)]
    pub expect: Expectations,
}

/// The keyframes of one tool.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ToolTrack {
    /// Name of the tool in the scene.
    pub tool: String,
    pub keyframes: Vec<Keyframe>,
}

#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Keyframe {
    /// Step index of this pose (give either `step` or `time_s`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub step: Option<u64>,
    /// Time of this pose, s from the start (rounded to the nearest step).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_s: Option<f64>,
    /// Position of the tool tip, m.
    pub position_m: [CoordinateM; 3],
    /// Orientation as a unit quaternion (w, x, y, z); the tool's axis is its local +z.
    /// Default: identity (axis along +z).
    #[serde(default = "identity_wxyz")]
    pub orientation_wxyz: [f64; 4],
    /// Cut button held (from this keyframe to the next).
    #[serde(default)]
    pub cut: bool,
    /// Tool present (from this keyframe to the next).
    #[serde(default = "yes")]
    pub active: bool,
    /// Forceps only: how hard the hand squeezes the handles while `cut` closes the jaws,
    /// as a fraction (0–1) of the tool's `grip_force_n` (from this keyframe to the next).
    /// Default: the whole grip, as a device whose jaw is a button gives.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grip: Option<f64>,
}

fn identity_wxyz() -> [f64; 4] {
    [1.0, 0.0, 0.0, 0.0]
}

fn yes() -> bool {
    true
}

/// Expectations on the run's report; each one that is given is checked.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema, Default)]
#[serde(deny_unknown_fields)]
pub struct Expectations {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cuts: Option<Bound>,
    /// Surface elements removed by cuts (triangles for msm, voxels for the branched grid).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub removed_elements: Option<Bound>,
    /// Connected pieces of tissue at the end.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub pieces: Option<Bound>,
    /// Total incision length, m.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incision_length_m: Option<Bound>,
    /// Largest tool force over the run, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_force_n: Option<Bound>,
    /// Cut updates the model could not stitch.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub reconstruction_fallbacks: Option<Bound>,
    /// Strokes whose last piece could not be stitched and was left uncut.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub uncut_last_pieces: Option<Bound>,
    /// Final state hash (16 hex digits).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_hash: Option<String>,
    /// Assessment: Time from the first contact to completing the planned incision, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_to_complete_s: Option<Bound>,
    /// Assessment: Fraction of the planned incision cut within its band (0–1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub coverage: Option<Bound>,
    /// Assessment: RMS deviation of the cut from the plan, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation_rms_mm: Option<Bound>,
    /// Assessment: Largest deviation of the cut from the plan, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub deviation_max_mm: Option<Bound>,
    /// Assessment: Length cut outside the plan's band, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub outside_band_mm: Option<Bound>,
    /// Assessment: RMS error of the cut's depth against the plan's target, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth_error_rms_mm: Option<Bound>,
    /// Assessment: Separate cutting strokes.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub strokes: Option<Bound>,
    /// Assessment: Path of the measured tool's tip from the first contact, mm.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub path_length_mm: Option<Bound>,
    /// Assessment: Plan length over the tip's path until completion (0–1).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub economy_of_motion: Option<Bound>,
    /// Assessment: Mean force on the tools while in contact, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub mean_force_n: Option<Bound>,
    /// Assessment: Time above the task's force limit, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_above_force_limit_s: Option<Bound>,
    /// Assessment: The hardest any forceps pinched what they held, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub peak_grip_force_n: Option<Bound>,
    /// Assessment: Time any forceps pinched harder than the task's grip limit, s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub time_above_grip_limit_s: Option<Bound>,
    /// Assessment: Smoothness of the tool path (higher is smoother).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub log_dimensionless_jerk: Option<Bound>,
    /// Assessment: Entries into no-go regions.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub no_go_entries: Option<Bound>,
    /// Assessment: The task's score, 0–100.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub score: Option<Bound>,
    /// Assessment: the task passed (true) or failed (false).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task_passed: Option<bool>,
    /// Per tool, by its name in the scene: expectations on that tool alone (say, that
    /// forceps pulled on what they held while a scalpel's cut is checked by `max_force_n`).
    #[serde(default, skip_serializing_if = "BTreeMap::is_empty")]
    pub tools: BTreeMap<String, ToolExpectations>,
}

/// Expectations on one tool's part in the run.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema, Default)]
#[serde(deny_unknown_fields)]
pub struct ToolExpectations {
    /// The largest force on this tool over the run, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_force_n: Option<Bound>,
    /// How long this tool grasped tissue over the run, s (forceps closing on it or
    /// holding it: the feedback's `grasping`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grasping_s: Option<Bound>,
    /// Forceps: the hardest their jaws pinched what they held over the run, N (the grip
    /// they were squeezed with, once stopped on the tissue).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_jaws_force_n: Option<Bound>,
}

impl ToolExpectations {
    /// Each expectation given: its name, its bound, and the value of the tool's report
    /// it bounds.
    fn bounds(&self) -> impl Iterator<Item = (&'static str, &Bound, fn(&crate::runner::ToolReport) -> f64)> {
        let max_force_n: fn(&crate::runner::ToolReport) -> f64 = |t| t.max_force_n;
        let grasping_s: fn(&crate::runner::ToolReport) -> f64 = |t| t.grasping_s;
        let max_jaws_force_n: fn(&crate::runner::ToolReport) -> f64 = |t| t.max_jaws_force_n;
        [("max_force_n", &self.max_force_n, max_force_n), ("grasping_s", &self.grasping_s, grasping_s), ("max_jaws_force_n", &self.max_jaws_force_n, max_jaws_force_n)]
            .into_iter()
            .filter_map(|(name, bound, value)| bound.as_ref().map(|b| (name, b, value)))
    }
}

/// A numeric expectation: any of min, max, equals, or approx with tolerance.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, JsonSchema, Default, PartialEq)]
#[serde(deny_unknown_fields)]
pub struct Bound {
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub min: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub equals: Option<f64>,
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub approx: Option<f64>,
    /// Absolute tolerance of `approx` (default: 1 % of it).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
}

impl Bound {
    pub fn holds(&self, value: f64) -> bool {
        self.min.is_none_or(|m| value >= m)
            && self.max.is_none_or(|m| value <= m)
            && self.equals.is_none_or(|e| value == e)
            && self.approx.is_none_or(|a| (value - a).abs() <= self.tolerance.unwrap_or(0.01 * a.abs()))
    }

    pub fn describe(&self) -> String {
        let mut parts = Vec::new();
        if let Some(v) = self.equals {
            parts.push(format!("= {v}"));
        }
        if let Some(v) = self.min {
            parts.push(format!("≥ {v}"));
        }
        if let Some(v) = self.max {
            parts.push(format!("≤ {v}"));
        }
        if let Some(v) = self.approx {
            parts.push(format!("≈ {v} ± {}", self.tolerance.unwrap_or(0.01 * v.abs())));
        }
        parts.join(" and ")
    }

    fn is_empty(&self) -> bool {
        self.min.is_none() && self.max.is_none() && self.equals.is_none() && self.approx.is_none()
    }
}

impl CutScript {
    /// Parses a script; errors name the JSON path.
    pub fn from_json_str(text: &str, origin: &str) -> Result<CutScript, SceneError> {
        let de = &mut serde_json::Deserializer::from_str(text);
        serde_path_to_error::deserialize(de)
            .map_err(|e| SceneError::new(origin, e.path().to_string().trim_start_matches('.'), e.into_inner().to_string()))
    }

    pub fn load(path: &std::path::Path) -> Result<CutScript, SceneError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| SceneError::new(&origin, "", format!("cannot read the script: {e}")))?;
        Self::from_json_str(&text, &origin)
    }

    /// Checks the script against a scene's tools and step, and prepares it for playing.
    pub fn compile(&self, tools: &[ToolShape], time_step_s: f64, origin: &str) -> Result<CompiledScript, SceneError> {
        let err = |path: String, message: String| SceneError::new(origin, path, message);
        let total_keyframes: usize = self.tools.iter().map(|t| t.keyframes.len()).sum();
        if total_keyframes > MAX_KEYFRAMES {
            return Err(err("tools".into(), format!("{total_keyframes} keyframes; at most {MAX_KEYFRAMES} are allowed")));
        }
        let mut tracks: Vec<Vec<CompiledKey>> = vec![Vec::new(); tools.len()];
        for (ti, track) in self.tools.iter().enumerate() {
            let tool = tool_named(tools, &track.tool).map_err(|message| err(format!("tools[{ti}].tool"), message))?;
            if !tracks[tool].is_empty() {
                return Err(err(format!("tools[{ti}].tool"), format!("tool {:?} has two tracks; give one", track.tool)));
            }
            let mut keys = Vec::with_capacity(track.keyframes.len());
            for (ki, k) in track.keyframes.iter().enumerate() {
                let path = |field: &str| format!("tools[{ti}].keyframes[{ki}]{field}");
                let step = match (k.step, k.time_s) {
                    (Some(s), None) => s,
                    (None, Some(t)) if t.is_finite() && t >= 0.0 => (t / time_step_s).round() as u64,
                    (None, Some(t)) => return Err(err(path(".time_s"), format!("time must be a finite number of seconds ≥ 0, got {t}"))),
                    _ => return Err(err(path(""), "give exactly one of step and time_s".into())),
                };
                if step > MAX_SCRIPT_STEPS {
                    return Err(err(path(""), format!("step {step} is beyond the limit of {MAX_SCRIPT_STEPS} steps")));
                }
                if let Some(prev) = keys.last().map(|p: &CompiledKey| p.step)
                    && step <= prev
                {
                    return Err(err(path(""), format!("keyframes must be in increasing step order; step {step} follows step {prev}")));
                }
                let [w, x, y, z] = k.orientation_wxyz;
                let norm = (w * w + x * x + y * y + z * z).sqrt();
                if !norm.is_finite() || (norm - 1.0).abs() > 1e-3 {
                    return Err(err(path(".orientation_wxyz"), format!("must be a unit quaternion (w, x, y, z), got norm {norm}")));
                }
                // Already unit (as every recorded pose is): taken bit for bit, so a script
                // made from a recording replays it exactly.
                let orientation = if (norm - 1.0).abs() <= 1e-12 { quat_from_wxyz_exact(w, x, y, z) } else { quat_from_wxyz(w, x, y, z) };
                let position = Vec3::new(k.position_m[0].get(), k.position_m[1].get(), k.position_m[2].get());
                if let Some(message) = k.grip.and_then(crate::tool::grip_error) {
                    return Err(err(path(".grip"), message));
                }
                keys.push(CompiledKey { step, pose: Pose::new(position, orientation), cut: k.cut, active: k.active, grip: k.grip });
            }
            tracks[tool] = keys;
        }
        let last_key = tracks.iter().filter_map(|t| t.last()).map(|k| k.step).max();
        let steps = match self.steps {
            Some(s) if s > MAX_SCRIPT_STEPS => {
                return Err(err("steps".into(), format!("{s} steps is beyond the limit of {MAX_SCRIPT_STEPS}")));
            }
            Some(s) => s,
            None => last_key.map_or(0, |s| s + 1),
        };
        for (name, bound) in self.expect.bounds() {
            if bound.is_empty() {
                return Err(err(format!("expect.{name}"), "give at least one of min, max, equals, approx".into()));
            }
        }
        for (name, expect) in &self.expect.tools {
            tool_named(tools, name).map_err(|message| err(format!("expect.tools.{name}"), message))?;
            if expect.bounds().next().is_none() {
                return Err(err(format!("expect.tools.{name}"), "expects nothing: give max_force_n, grasping_s or max_jaws_force_n".into()));
            }
            if let Some((key, ..)) = expect.bounds().find(|(_, bound, _)| bound.is_empty()) {
                return Err(err(format!("expect.tools.{name}.{key}"), "give at least one of min, max, equals, approx".into()));
            }
        }
        if let Some(h) = &self.expect.state_hash
            && (h.len() != 16 || !h.chars().all(|c| c.is_ascii_hexdigit()))
        {
            return Err(err("expect.state_hash".into(), format!("a state hash is 16 hexadecimal digits, got {h:?}")));
        }
        Ok(CompiledScript { tracks, steps, expect: self.expect.clone() })
    }
}

/// The index of the scene's tool called `name`, or a message listing the tools there are.
fn tool_named(tools: &[ToolShape], name: &str) -> Result<usize, String> {
    tools.iter().position(|t| t.name == name).ok_or_else(|| {
        let names: Vec<&str> = tools.iter().map(|t| t.name.as_str()).collect();
        format!("no tool named {name:?} in the scene; its tools are: {}", if names.is_empty() { "(none)".into() } else { names.join(", ") })
    })
}

impl Expectations {
    fn bounds(&self) -> Vec<(&'static str, &Bound)> {
        [
            ("cuts", &self.cuts),
            ("removed_elements", &self.removed_elements),
            ("pieces", &self.pieces),
            ("incision_length_m", &self.incision_length_m),
            ("max_force_n", &self.max_force_n),
            ("reconstruction_fallbacks", &self.reconstruction_fallbacks),
            ("uncut_last_pieces", &self.uncut_last_pieces),
            ("time_to_complete_s", &self.time_to_complete_s),
            ("coverage", &self.coverage),
            ("deviation_rms_mm", &self.deviation_rms_mm),
            ("deviation_max_mm", &self.deviation_max_mm),
            ("outside_band_mm", &self.outside_band_mm),
            ("depth_error_rms_mm", &self.depth_error_rms_mm),
            ("strokes", &self.strokes),
            ("path_length_mm", &self.path_length_mm),
            ("economy_of_motion", &self.economy_of_motion),
            ("mean_force_n", &self.mean_force_n),
            ("time_above_force_limit_s", &self.time_above_force_limit_s),
            ("peak_grip_force_n", &self.peak_grip_force_n),
            ("time_above_grip_limit_s", &self.time_above_grip_limit_s),
            ("log_dimensionless_jerk", &self.log_dimensionless_jerk),
            ("no_go_entries", &self.no_go_entries),
            ("score", &self.score),
        ]
        .into_iter()
        .filter_map(|(n, b)| b.as_ref().map(|b| (n, b)))
        .collect()
    }

    /// Checks every given expectation against the report's values.
    pub fn check(&self, report: &crate::runner::RunReport) -> Vec<ExpectationResult> {
        let mut out = Vec::new();
        let a = &report.assessment;
        for (name, bound) in self.bounds() {
            let actual = match name {
                "cuts" => Some(report.cuts as f64),
                "removed_elements" => Some(report.removed_elements as f64),
                "pieces" => Some(report.pieces as f64),
                "incision_length_m" => Some(report.incision_length_m),
                "max_force_n" => Some(report.max_tool_force_n),
                "reconstruction_fallbacks" => Some(report.reconstruction_fallbacks as f64),
                "uncut_last_pieces" => Some(report.counters.uncut_last_pieces as f64),
                "time_to_complete_s" => a.time_to_complete_s,
                "coverage" => a.coverage,
                "deviation_rms_mm" => a.deviation_rms_mm,
                "deviation_max_mm" => a.deviation_max_mm,
                "outside_band_mm" => a.outside_band_mm,
                "depth_error_rms_mm" => a.depth_error_rms_mm,
                "strokes" => Some(a.strokes as f64),
                "path_length_mm" => Some(a.path_length_mm),
                "economy_of_motion" => a.economy_of_motion,
                "mean_force_n" => Some(a.mean_force_n),
                "time_above_force_limit_s" => a.time_above_force_limit_s,
                "peak_grip_force_n" => Some(a.peak_grip_force_n),
                "time_above_grip_limit_s" => a.time_above_grip_limit_s,
                "log_dimensionless_jerk" => a.log_dimensionless_jerk,
                "no_go_entries" => Some(a.no_go_entries as f64),
                "score" => a.score,
                other => unreachable!("expectation {other} has no value"),
            };
            out.push(match actual {
                Some(actual) => ExpectationResult { name: name.to_owned(), expected: bound.describe(), actual: format!("{actual}"), passed: bound.holds(actual) },
                None => ExpectationResult {
                    name: name.to_owned(),
                    expected: bound.describe(),
                    actual: "absent (the scene's task does not define it, or nothing was cut or completed)".into(),
                    passed: false,
                },
            });
        }
        for (tool, expect) in &self.tools {
            for (key, bound, value) in expect.bounds() {
                let name = format!("tools.{tool}.{key}");
                out.push(match report.tools.iter().find(|t| &t.name == tool).map(value) {
                    Some(actual) => ExpectationResult { name, expected: bound.describe(), actual: format!("{actual}"), passed: bound.holds(actual) },
                    None => ExpectationResult { name, expected: bound.describe(), actual: "absent (the scene has no such tool)".into(), passed: false },
                });
            }
        }
        if let Some(expected) = self.task_passed {
            let actual = a.passed;
            out.push(ExpectationResult {
                name: "task_passed".into(),
                expected: expected.to_string(),
                actual: match actual {
                    Some(p) if a.failures.is_empty() => p.to_string(),
                    Some(p) => format!("{p} ({})", a.failures.join("; ")),
                    None => "absent (the scene has no task)".into(),
                },
                passed: actual == Some(expected),
            });
        }
        if let Some(hash) = &self.state_hash {
            out.push(ExpectationResult {
                name: "state_hash".into(),
                expected: hash.to_lowercase(),
                actual: report.state_hash.clone(),
                passed: hash.eq_ignore_ascii_case(&report.state_hash),
            });
        }
        out
    }
}

/// One expectation's outcome.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ExpectationResult {
    pub name: String,
    pub expected: String,
    pub actual: String,
    pub passed: bool,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct CompiledKey {
    step: u64,
    pose: Pose,
    cut: bool,
    active: bool,
    grip: Option<f64>,
}

/// A script checked against a scene, ready to give tool commands per step.
#[derive(Debug, Clone)]
pub struct CompiledScript {
    tracks: Vec<Vec<CompiledKey>>,
    pub steps: u64,
    pub expect: Expectations,
}

impl CompiledScript {
    /// The commands for step `step`, one per tool.
    pub fn commands_at(&self, step: u64, out: &mut [ToolCommand]) {
        for (track, command) in self.tracks.iter().zip(out.iter_mut()) {
            *command = command_at(track, step);
        }
    }
}

fn command_at(keys: &[CompiledKey], step: u64) -> ToolCommand {
    let after = keys.partition_point(|k| k.step <= step);
    if after == 0 {
        return ToolCommand::default();
    }
    let k0 = keys[after - 1];
    let pose = match keys.get(after) {
        // On a keyframe: its pose exactly (no interpolation rounding).
        _ if step == k0.step => k0.pose,
        Some(k1) => {
            let s = (step - k0.step) as f64 / (k1.step - k0.step) as f64;
            // p0 + (p1 − p0)·s rather than p0·(1 − s) + p1·s: a held pose (two equal
            // keyframes, as `cut-bot record` writes them) then stays exact bit for bit.
            let position = k0.pose.position_m + (k1.pose.position_m - k0.pose.position_m) * s;
            let orientation = if k0.pose.orientation == k1.pose.orientation {
                k0.pose.orientation
            } else {
                k0.pose.orientation.try_slerp(&k1.pose.orientation, s, 1e-9).unwrap_or(k0.pose.orientation)
            };
            Pose::new(position, orientation)
        }
        None => k0.pose,
    };
    ToolCommand { pose, active: k0.active, cut: k0.cut, grip: k0.grip }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn blade() -> Vec<ToolShape> {
        vec![ToolShape { name: "scalpel".into(), radius_m: 5e-4, length_m: 0.03, section: crate::tool::Section::Round, contact_stiffness_n_per_m: 100.0, can_cut: true, max_force_n: 10.0, cutting_shape: None, edge_local: crate::math::Vec3::x(), tip_shape: crate::tool::TipShape::Flat }]
    }

    #[test]
    fn interpolates_between_keyframes_and_holds_buttons() {
        let text = r#"{"tools":[{"tool":"scalpel","keyframes":[
            {"step":10,"position_m":[0,0,0],"cut":true},
            {"time_s":0.02,"position_m":[0.01,0,0]}]}]}"#;
        let script = CutScript::from_json_str(text, "t").unwrap().compile(&blade(), 0.001, "t").unwrap();
        assert_eq!(script.steps, 21);
        let mut c = [ToolCommand::default()];
        script.commands_at(5, &mut c);
        assert!(!c[0].active);
        script.commands_at(15, &mut c);
        assert!(c[0].active && c[0].cut);
        assert!((c[0].pose.position_m.x - 0.005).abs() < 1e-15);
        script.commands_at(30, &mut c);
        assert!(!c[0].cut && (c[0].pose.position_m.x - 0.01).abs() < 1e-15);
    }

    #[test]
    fn a_keyframes_grip_holds_until_the_next_and_must_be_a_fraction() {
        let text = r#"{"tools":[{"tool":"scalpel","keyframes":[
            {"step":0,"position_m":[0,0,0],"cut":true},
            {"step":10,"position_m":[0,0,0],"cut":true,"grip":0.25},
            {"step":20,"position_m":[0,0,0],"cut":true,"grip":0}]}]}"#;
        let script = CutScript::from_json_str(text, "t").unwrap().compile(&blade(), 0.001, "t").unwrap();
        let mut c = [ToolCommand::default()];
        let mut at = |step| {
            script.commands_at(step, &mut c);
            (c[0].grip, c[0].closes_jaws(), c[0].grip_n(3.0))
        };
        assert_eq!(at(5), (None, true, 3.0), "no grip given: the whole grip");
        assert_eq!(at(15), (Some(0.25), true, 0.75));
        assert_eq!(at(20), (Some(0.0), false, 0.0), "no squeeze closes nothing");
        for bad in ["1.5", "-0.1"] {
            let text = format!(r#"{{"tools":[{{"tool":"scalpel","keyframes":[{{"step":0,"position_m":[0,0,0],"grip":{bad}}}]}}]}}"#);
            let e = CutScript::from_json_str(&text, "t").unwrap().compile(&blade(), 0.001, "t").unwrap_err().to_string();
            assert!(e.contains("tools[0].keyframes[0].grip") && e.contains("from 0 to 1") && e.contains(bad), "{e}");
        }
    }

    #[test]
    fn a_held_pose_stays_exact_between_equal_keyframes() {
        // Values whose p·(1 − s) + p·s rounds away from p for some s: a recorded session
        // holds such poses for many steps while the trainee pauses.
        let (x, y, z) = (-0.013_374_999_999_999_998_f64, 0.004_912_345_678_901_234_f64, -0.005_f64);
        let q = [0.923_879_532_511_286_7_f64, 0.0, 0.382_683_432_365_089_8, 0.0];
        let n = (q.iter().map(|v| v * v).sum::<f64>()).sqrt();
        let q = q.map(|v| v / n);
        let key = |step: u64| format!(r#"{{"step":{step},"position_m":[{x:?},{y:?},{z:?}],"orientation_wxyz":[{:?},{:?},{:?},{:?}]}}"#, q[0], q[1], q[2], q[3]);
        let text = format!(r#"{{"tools":[{{"tool":"scalpel","keyframes":[{},{}]}}]}}"#, key(3), key(1000));
        let script = CutScript::from_json_str(&text, "t").unwrap().compile(&blade(), 0.001, "t").unwrap();
        let mut c = [ToolCommand::default()];
        script.commands_at(3, &mut c);
        let held = c[0].pose;
        for step in 4..=1000 {
            script.commands_at(step, &mut c);
            assert_eq!(c[0].pose.position_m, held.position_m, "step {step}");
            assert_eq!(c[0].pose.orientation, held.orientation, "step {step}");
        }
    }

    #[test]
    fn bad_scripts_name_the_path() {
        let unknown = r#"{"tools":[{"tool":"laser","keyframes":[]}]}"#;
        let e = CutScript::from_json_str(unknown, "s").unwrap().compile(&blade(), 0.001, "s").unwrap_err();
        assert_eq!(e.path, "tools[0].tool");
        assert!(e.message.contains("scalpel"));
        let order = r#"{"tools":[{"tool":"scalpel","keyframes":[{"step":5,"position_m":[0,0,0]},{"step":5,"position_m":[0,0,0]}]}]}"#;
        let e = CutScript::from_json_str(order, "s").unwrap().compile(&blade(), 0.001, "s").unwrap_err();
        assert_eq!(e.path, "tools[0].keyframes[1]");
        let quat = r#"{"tools":[{"tool":"scalpel","keyframes":[{"step":5,"position_m":[0,0,0],"orientation_wxyz":[2,0,0,0]}]}]}"#;
        let e = CutScript::from_json_str(quat, "s").unwrap().compile(&blade(), 0.001, "s").unwrap_err();
        assert_eq!(e.path, "tools[0].keyframes[0].orientation_wxyz");
        let typo = r#"{"tool":[]}"#;
        let e = CutScript::from_json_str(typo, "s").unwrap_err();
        assert_eq!(e.path, "tool");
        // One tool's expectations: a tool of the scene, and something to expect of it.
        for (expect, path) in [(r#"{"knife":{"max_force_n":{"min":1}}}"#, "expect.tools.knife"), (r#"{"scalpel":{}}"#, "expect.tools.scalpel"), (r#"{"scalpel":{"max_force_n":{}}}"#, "expect.tools.scalpel.max_force_n"), (r#"{"scalpel":{"max_force_n":{"min":1},"grasping_s":{}}}"#, "expect.tools.scalpel.grasping_s")] {
            let text = format!(r#"{{"tools":[],"expect":{{"tools":{expect}}}}}"#);
            let e = CutScript::from_json_str(&text, "s").unwrap().compile(&blade(), 0.001, "s").unwrap_err();
            assert_eq!(e.path, path, "{expect}: {}", e.message);
        }
        let far = r#"{"tools":[{"tool":"scalpel","keyframes":[{"step":5,"position_m":[0,0,1e9]}]}]}"#;
        let e = CutScript::from_json_str(far, "s").unwrap_err();
        assert_eq!(e.path, "tools[0].keyframes[0].position_m[2]");
    }

    #[test]
    fn bounds_check_and_describe() {
        let b = Bound { min: Some(1.0), max: Some(3.0), ..Default::default() };
        assert!(b.holds(2.0) && !b.holds(3.5));
        assert_eq!(b.describe(), "≥ 1 and ≤ 3");
        let a = Bound { approx: Some(0.04), tolerance: Some(0.004), ..Default::default() };
        assert!(a.holds(0.043) && !a.holds(0.045));
    }
}
