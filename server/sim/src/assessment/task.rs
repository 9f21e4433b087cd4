//! A scene's training task: a planned incision and no-go regions, as written in the
//! scene file (`"task"`), checked and compiled into what the assessor measures against.

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use super::plan::Plan;
use crate::math::Vec3;
use crate::quantity::{CoordinateM, ForceN, LengthM};
use crate::scene::SceneError;
use crate::tool::{Section, ToolShape};

/// The most no-go regions a task may have (each is checked for every tool every step).
pub const MAX_NO_GO_REGIONS: usize = 100;

/// What the trainee is asked to do, and what they must not do.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct TaskSpec {
    /// One or two sentences shown to the trainee and the instructor.
    #[serde(default)]
    pub description: String,
    /// The planned incision. Absent: only motion, force and no-go metrics are computed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub incision: Option<IncisionSpec>,
    /// Regions that must not be cut or pressed.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub no_go: Vec<NoGoSpec>,
    /// Tool forces above this count as time above the force limit, N.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub force_limit_n: Option<ForceN>,
    /// Forceps pinching what they hold harder than this count as time above the grip
    /// limit, N (crushed tissue). Needs a tool with jaws.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub grip_limit_n: Option<ForceN>,
    /// Fraction of the planned incision that must be cut (within the band) for the task
    /// to be complete. Default 0.9.
    #[serde(default = "default_min_coverage")]
    pub min_coverage: f64,
}

fn default_min_coverage() -> f64 {
    0.9
}

/// A planned incision: a polyline on the tissue's surface.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct IncisionSpec {
    /// The plan's points on the surface, m (at least two, consecutive points distinct).
    pub points_m: Vec<[CoordinateM; 3]>,
    /// The surface's outward normal along the plan (default +z). Deviation is measured
    /// across it (in the surface), depth along it.
    #[serde(default = "up")]
    pub normal: [f64; 3],
    /// Half-width of the tolerance band around the plan, m.
    pub band_m: LengthM,
    /// The depth the cut should reach below the planned line (volumetric tissue).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub depth: Option<DepthSpec>,
    /// The tool whose cuts are measured. Default: the scene's first tool that can cut.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub tool: Option<String>,
}

fn up() -> [f64; 3] {
    [0.0, 0.0, 1.0]
}

/// A target depth with its tolerance.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DepthSpec {
    pub target_m: LengthM,
    pub tolerance_m: LengthM,
}

/// A region that must not be cut, nor pressed harder than `max_force_n`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct NoGoSpec {
    /// Shown in warnings ("muscle", "vessel").
    pub name: String,
    /// An axis-aligned box, m.
    pub min_m: [CoordinateM; 3],
    pub max_m: [CoordinateM; 3],
    /// A tool tip inside the box pressing harder than this is a violation, N. Default 0:
    /// any contact is. Cutting inside the box always is.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub max_force_n: Option<ForceN>,
}

/// A task checked against its scene's tools, ready to measure against.
#[derive(Debug, Clone, PartialEq)]
pub struct Task {
    pub plan: Option<Plan>,
    /// Index of the tool whose motion and cuts are measured (None: the scene has no tool).
    pub tool: Option<usize>,
    pub depth: Option<(f64, f64)>,
    pub no_go: Vec<NoGoRegion>,
    pub force_limit_n: Option<f64>,
    pub grip_limit_n: Option<f64>,
    pub min_coverage: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub struct NoGoRegion {
    pub name: String,
    pub min: Vec3,
    pub max: Vec3,
    pub max_force_n: f64,
}

impl NoGoRegion {
    pub fn contains(&self, p: &Vec3) -> bool {
        (0..3).all(|a| p[a] >= self.min[a] && p[a] <= self.max[a])
    }
}

impl Task {
    /// The task of a scene without one: motion and force metrics only, measured on the
    /// first tool that can cut (else the first tool).
    pub fn none(tools: &[ToolShape]) -> Task {
        Task {
            plan: None,
            tool: tools.iter().position(|t| t.can_cut).or(if tools.is_empty() { None } else { Some(0) }),
            depth: None,
            no_go: Vec::new(),
            force_limit_n: None,
            grip_limit_n: None,
            min_coverage: default_min_coverage(),
        }
    }
}

impl TaskSpec {
    /// Checks the task against the scene's tools; errors name the JSON path under `task`.
    pub fn compile(&self, tools: &[ToolShape], origin: &str) -> Result<Task, SceneError> {
        let err = |path: &str, message: String| SceneError::new(origin, format!("task{path}"), message);
        if !(self.min_coverage.is_finite() && self.min_coverage > 0.0 && self.min_coverage <= 1.0) {
            return Err(err(".min_coverage", format!("must be a fraction within (0, 1], got {}", self.min_coverage)));
        }
        let mut task = Task::none(tools);
        task.min_coverage = self.min_coverage;
        task.force_limit_n = self.force_limit_n.map(ForceN::get);
        if let Some(limit) = self.grip_limit_n {
            if !tools.iter().any(|t| matches!(t.section, Section::Jaws { .. })) {
                let names: Vec<&str> = tools.iter().map(|t| t.name.as_str()).collect();
                return Err(err(".grip_limit_n", format!("a grip limit needs forceps (a tool with \"jaws\"); the scene's tools are: {}", names.join(", "))));
            }
            task.grip_limit_n = Some(limit.get());
        }
        if let Some(incision) = &self.incision {
            if let Some(name) = &incision.tool {
                let Some(index) = tools.iter().position(|t| &t.name == name) else {
                    let names: Vec<&str> = tools.iter().map(|t| t.name.as_str()).collect();
                    return Err(err(".incision.tool", format!("no tool named {name:?} in the scene; its tools are: {}", names.join(", "))));
                };
                task.tool = Some(index);
            }
            if task.tool.is_none_or(|t| !tools[t].can_cut) {
                return Err(err(".incision", "a planned incision needs a tool that can cut (\"can_cut\": true)".into()));
            }
            let [x, y, z] = incision.normal;
            let normal = Vec3::new(x, y, z);
            let length = normal.norm();
            if !length.is_finite() || length < 1e-9 {
                return Err(err(".incision.normal", format!("must be a non-zero direction, got [{x}, {y}, {z}]")));
            }
            let points: Vec<Vec3> = incision.points_m.iter().map(|p| Vec3::new(p[0].get(), p[1].get(), p[2].get())).collect();
            task.plan = Some(Plan::new(&points, normal / length, incision.band_m.get()).map_err(|m| err(".incision.points_m", m))?);
            task.depth = incision.depth.map(|d| (d.target_m.get(), d.tolerance_m.get()));
        }
        if self.no_go.len() > MAX_NO_GO_REGIONS {
            return Err(err(".no_go", format!("{} regions; at most {MAX_NO_GO_REGIONS} are allowed", self.no_go.len())));
        }
        for (i, region) in self.no_go.iter().enumerate() {
            if region.name.trim().is_empty() {
                return Err(err(&format!(".no_go[{i}].name"), "a no-go region needs a name".into()));
            }
            let min = Vec3::new(region.min_m[0].get(), region.min_m[1].get(), region.min_m[2].get());
            let max = Vec3::new(region.max_m[0].get(), region.max_m[1].get(), region.max_m[2].get());
            if let Some(axis) = (0..3).find(|&a| min[a] > max[a]) {
                return Err(err(
                    &format!(".no_go[{i}]"),
                    format!("min_m[{axis}] = {} m is above max_m[{axis}] = {} m; a box needs min ≤ max on every axis", min[axis], max[axis]),
                ));
            }
            task.no_go.push(NoGoRegion { name: region.name.clone(), min, max, max_force_n: region.max_force_n.map_or(0.0, ForceN::get) });
        }
        Ok(task)
    }
}
