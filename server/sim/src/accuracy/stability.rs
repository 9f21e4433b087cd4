//! Stability at the extremes: a 40 × 8 × 8 mm bar of 1 mm voxels at level 2 under
//! gravity, swept over Young's modulus, Poisson ratio, time step and damping, in four
//! scenarios (a probe pressing and a blade drawn through at 2 m/s; cuts that leave
//! fragments one voxel thick; a blade squeezed between the two cut parts; neighbouring
//! materials whose densities differ 1e4 times). Every case is either refused at load
//! with a message that says why and what would be stable, or runs with finite state,
//! kinetic energy bounded by the work put in, bounded tool force, and no blow-up
//! contained. Force clamps are counted and reported, never silent.
//!
//! `tests/branched_grid.rs` runs the reduced sweep; `accuracy-speed stability` runs the
//! full one and writes docs/stability.md.

use std::fmt::Write as _;

use super::problems::G;
use crate::grid::{BranchedGrid, build_from_scene};
use crate::math::{Pose, Quat, Vec3};
use crate::scene::{ModelSpec, Scene};
use crate::tissue::Tissue;
use crate::tool::{ToolCommand, ToolFeedback};
use crate::volume::LabelVolume;

/// What a case does.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Scenario {
    /// A blade drawn across the bar at 2 m/s (cut held), then a probe pressing 3 mm.
    ProbeAndBlade,
    /// Four cuts across and three along the free end: pieces one voxel thick, falling.
    Fragments,
    /// Held at both ends, cut through the middle; the blade stays in the slit (both
    /// faces press on it) while a probe pushes one half towards it.
    SqueezedBlade,
    /// Layers of 8 voxels alternating between densities 10 and 100,000 kg/m³, probed and cut.
    MassRatio,
}

impl Scenario {
    pub const ALL: [Scenario; 4] = [Scenario::ProbeAndBlade, Scenario::Fragments, Scenario::SqueezedBlade, Scenario::MassRatio];

    pub fn name(self) -> &'static str {
        match self {
            Scenario::ProbeAndBlade => "probe + blade at 2 m/s",
            Scenario::Fragments => "one-voxel fragments",
            Scenario::SqueezedBlade => "blade squeezed in a cut",
            Scenario::MassRatio => "mass ratio 1e4",
        }
    }
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Case {
    pub scenario: Scenario,
    pub young_pa: f64,
    pub poisson: f64,
    pub dt_s: f64,
    pub damped: bool,
}

impl Case {
    pub fn label(&self) -> String {
        format!(
            "{}: E {:.0e} Pa, ν {}, dt {} ms, damping {}",
            self.scenario.name(),
            self.young_pa,
            self.poisson,
            self.dt_s * 1e3,
            if self.damped { "on" } else { "off" }
        )
    }
}

/// How a case ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Outcome {
    /// Refused at load; the message says why and which setting would be stable.
    Refused(String),
    /// It ran; `bounded` says whether it stayed within the bounds.
    Ran { bounded: bool, farthest_m: f64, max_speed_m_per_s: f64, max_kinetic_j: f64, energy_in_j: f64, max_force_n: f64, force_clamps: u64, removed_voxels: u64, blowups: u64 },
}

impl Outcome {
    /// Whether the case met the contract (refused with a reason, or bounded).
    pub fn acceptable(&self) -> bool {
        match self {
            Outcome::Refused(message) => message.contains("raise cg_max_iterations to at least") || message.contains("use a shorter time_step_s") || message.contains(&format!("use at most {}", crate::grid::MAX_POISSON)),
            Outcome::Ran { bounded, .. } => *bounded,
        }
    }

    pub fn describe(&self) -> String {
        match self {
            Outcome::Refused(message) => format!("refused at load: {message}"),
            Outcome::Ran { bounded, farthest_m, max_speed_m_per_s, max_kinetic_j, energy_in_j, max_force_n, force_clamps, removed_voxels, blowups } => format!(
                "{}: farthest node {:.1} mm, fastest {:.2} m/s, kinetic energy ≤ {:.2e} J of {:.2e} J put in, tool force ≤ {:.2} N ({force_clamps} clamps), {removed_voxels} voxels removed, {blowups} blow-ups",
                if *bounded { "bounded" } else { "UNBOUNDED" },
                farthest_m * 1e3,
                max_speed_m_per_s,
                max_kinetic_j,
                energy_in_j,
                max_force_n
            ),
        }
    }
}

const MAX_TOOL_FORCE_N: f64 = 20.0;
const RUN_S: f64 = 0.3;

/// The sweep: reduced (the test command) or full (the benchmark command).
pub fn cases(full: bool) -> Vec<Case> {
    let mut out = Vec::new();
    let grid = |scenario: Scenario, young: &[f64], poisson: &[f64], dt: &[f64], damping: &[bool], out: &mut Vec<Case>| {
        for &young_pa in young {
            for &poisson in poisson {
                for &dt_s in dt {
                    for &damped in damping {
                        out.push(Case { scenario, young_pa, poisson, dt_s, damped });
                    }
                }
            }
        }
    };
    if full {
        for scenario in Scenario::ALL {
            grid(scenario, &[1e2, 1e3, 1e4, 1e5, 1e6, 1e7], &[0.0, 0.3, 0.45, 0.49, 0.499], &[1e-4, 1e-3, 1e-2], &[false, true], &mut out);
        }
    } else {
        grid(Scenario::ProbeAndBlade, &[1e2, 1e4, 1e7], &[0.0, 0.3, 0.45, 0.49, 0.499], &[1e-4, 1e-3, 1e-2], &[false, true], &mut out);
        for scenario in [Scenario::Fragments, Scenario::SqueezedBlade, Scenario::MassRatio] {
            grid(scenario, &[1e2, 1e4, 1e7], &[0.3, 0.49], &[1e-4, 1e-3, 1e-2], &[false], &mut out);
        }
    }
    out
}

/// The scene of a case.
pub fn scene(case: &Case) -> Result<Scene, String> {
    let damping = if case.damped { r#"{ "mass_per_s": 5, "stiffness_s": 0.001 }"# } else { r#"{ "mass_per_s": 0, "stiffness_s": 0 }"# };
    let fixed = if case.scenario == Scenario::SqueezedBlade { r#"[ { "side": { "side": "-x" } }, { "side": { "side": "+x" } } ]"# } else { r#"[ { "side": { "side": "-x" } } ]"# };
    let (volume, materials) = if case.scenario == Scenario::MassRatio {
        let path = mass_ratio_volume()?;
        (
            format!(r#"{{ "vti": {{ "path": {} }} }}"#, serde_json::Value::from(path.display().to_string())),
            format!(
                r#"[ {{ "label": 1, "young_pa": {0}, "poisson": {1}, "density_kg_per_m3": 10 }}, {{ "label": 2, "young_pa": {0}, "poisson": {1}, "density_kg_per_m3": 100000 }} ]"#,
                case.young_pa, case.poisson
            ),
        )
    } else {
        (
            r#"{ "box": { "size_m": [0.04, 0.008, 0.008], "voxel_size_m": 0.001 } }"#.to_string(),
            format!(r#"[ {{ "label": 1, "young_pa": {}, "poisson": {}, "density_kg_per_m3": 1000 }} ]"#, case.young_pa, case.poisson),
        )
    };
    let json = format!(
        r#"{{ "name": "extreme", "time_step_s": {}, "gravity_m_per_s2": [0, 0, -{G}],
        "model": {{ "branched-grid": {{
            "volume": {volume}, "centre": true, "materials": {materials}, "level": 2,
            "damping": {damping}, "fixed": {fixed}, "cutting": {{ "max_voxels_per_step": 400 }} }} }},
        "tools": [
            {{ "name": "blade", "shape": {{ "cylinder": {{ "radius_m": 0.0008, "length_m": 0.05 }} }}, "cutting_shape": {{ "cylinder": {{ "radius_m": 0.0007, "length_m": 0.05 }} }}, "can_cut": true, "contact_stiffness_n_per_m": 60, "max_force_n": {MAX_TOOL_FORCE_N} }},
            {{ "name": "probe", "shape": {{ "cylinder": {{ "radius_m": 0.004, "length_m": 0.05 }} }}, "contact_stiffness_n_per_m": 300, "max_force_n": {MAX_TOOL_FORCE_N} }}
        ] }}"#,
        case.dt_s
    );
    Scene::from_json_str(&json, "stability case", None).map_err(|e| e.to_string())
}

/// The layered bar of the mass-ratio case, written once per process as a VTK image.
fn mass_ratio_volume() -> Result<std::path::PathBuf, String> {
    let path = std::env::temp_dir().join(format!("cutsim-stability-layers-{}.vti", std::process::id()));
    if !path.is_file() {
        let mut volume = LabelVolume::new([40, 8, 8], [0.001; 3], Vec3::zeros());
        for k in 0..8 {
            for j in 0..8 {
                for i in 0..40 {
                    volume.set(i, j, k, if (i / 8) % 2 == 0 { 1 } else { 2 });
                }
            }
        }
        crate::volume::vti::write_vti(&volume, &path, crate::volume::vti::VtiEncoding::Ascii)?;
    }
    Ok(path)
}

/// The tools' commands at time t.
fn commands(scenario: Scenario, t: f64) -> [ToolCommand; 2] {
    let at = |p: Vec3, active: bool, cut: bool| ToolCommand { pose: Pose::new(p, Quat::identity()), active, cut, grip: None };
    // The blade is vertical (+z from its tip): a tip 2 mm under the bar puts it through.
    match scenario {
        Scenario::ProbeAndBlade | Scenario::MassRatio => {
            // Across the bar at x = +10 mm at 2 m/s during t ∈ [0.05, 0.07] s.
            let blade_y = -0.02 + 2.0 * (t - 0.05).clamp(0.0, 0.02);
            let depth = 0.003 * ((t - 0.1) / 0.05).clamp(0.0, 1.0);
            [at(Vec3::new(0.01, blade_y, -0.006), (0.05..0.08).contains(&t), true), at(Vec3::new(-0.005, 0.0, 0.008 - depth), t >= 0.1, false)]
        }
        Scenario::Fragments => {
            // Seven 20 ms passes at 1 m/s: across at x = 12, 14, 16, 18 mm, then along at
            // y = −2, 0, 2 mm over x ∈ [10, 20] mm.
            let pass = (t / 0.02) as usize;
            let s = (t - pass as f64 * 0.02) / 0.02;
            let blade = match pass {
                0..=3 => Some(Vec3::new(0.012 + 0.002 * pass as f64, -0.01 + 0.02 * s, -0.006)),
                4..=6 => Some(Vec3::new(0.01 + 0.01 * s, -0.002 + 0.002 * (pass - 4) as f64, -0.006)),
                _ => None,
            };
            [at(blade.unwrap_or_else(Vec3::zeros), blade.is_some() && s < 0.95, true), at(Vec3::zeros(), false, false)]
        }
        Scenario::SqueezedBlade => {
            // Through the middle along y at 1 m/s, cutting (t ∈ [0.04, 0.06] s); back to
            // y = 0 along the slit with the cut off; then it stays there while the probe
            // presses 3 mm into the +x half beside it, pushing the cut face onto it.
            let blade_y = if t < 0.04 {
                -0.01
            } else if t < 0.06 {
                -0.01 + (t - 0.04)
            } else if t < 0.08 {
                0.01 - 0.5 * (t - 0.06)
            } else {
                0.0
            };
            let depth = 0.003 * ((t - 0.1) / 0.05).clamp(0.0, 1.0);
            [at(Vec3::new(0.0, blade_y, -0.006), t >= 0.02, t < 0.06), at(Vec3::new(0.005, 0.0, 0.008 - depth), t >= 0.1, false)]
        }
    }
}

/// Runs one case for 0.3 s.
pub fn run(case: &Case) -> Result<Outcome, String> {
    let scene = scene(case)?;
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!("a branched-grid scene") };
    let mut grid: BranchedGrid = match build_from_scene(&scene, spec) {
        Ok(g) => g,
        Err(e) => return Ok(Outcome::Refused(e.message)),
    };
    let mut feedback = [ToolFeedback::default(); 2];
    let steps = (RUN_S / case.dt_s).round() as usize;
    let (mut max_force, mut max_speed, mut max_kinetic) = (0.0f64, 0.0f64, 0.0f64);
    let mut finite = true;
    // Energy put in: the tools' work (an upper bound: |F| times the distance moved) and
    // gravity's (the most Σ m g Δz the body has released so far).
    let mut tool_work = 0.0;
    let mut tool_speed: f64 = 0.0;
    let mut gravity_work: f64 = 0.0;
    let mut previous: Option<[ToolCommand; 2]> = None;
    let mass: f64 = {
        let n = &grid.topology().nodes;
        (0..n.len()).filter(|&i| n.alive[i]).map(|i| n.mass[i]).sum()
    };
    for step in 0..steps {
        let t = step as f64 * case.dt_s;
        let now = commands(case.scenario, t);
        grid.step(&now, &mut feedback);
        if let Some(before) = previous {
            for k in 0..2 {
                if now[k].active && before[k].active {
                    let moved = (now[k].pose.position_m - before[k].pose.position_m).norm();
                    tool_work += feedback[k].force_n.norm() * moved;
                    tool_speed = tool_speed.max(moved / case.dt_s);
                }
            }
        }
        previous = Some(now);
        max_force = max_force.max(feedback.iter().map(|f| f.force_n.norm()).fold(0.0, f64::max));
        let n = &grid.topology().nodes;
        let mut released = 0.0;
        for i in (0..n.len()).filter(|&i| n.alive[i]) {
            released += n.mass[i] * G * (n.rest[i].z - n.x[i].z);
            let speed = n.v[i].norm();
            finite &= speed.is_finite() && n.x[i].iter().all(|c| c.is_finite());
            max_speed = max_speed.max(speed);
        }
        max_kinetic = max_kinetic.max(grid.kinetic_energy());
        gravity_work = gravity_work.max(released);
    }
    let n = &grid.topology().nodes;
    let farthest = (0..n.len()).filter(|&i| n.alive[i]).map(|i| (n.x[i] - n.rest[i]).norm()).fold(0.0, f64::max);
    let counters = grid.counters();
    // A rigid tool moving at v gives a free mass at most 2v (an elastic bounce): the
    // contacts' work beyond what the reported forces account for is below 2 M v².
    let energy_in = gravity_work + tool_work + 2.0 * mass * tool_speed * tool_speed;
    // Implicit Euler only loses energy: kinetic energy above what was put in was made by
    // the integrator (10 % allowance).
    let bounded = finite && max_kinetic <= 1.1 * energy_in + 1e-9 && max_force <= MAX_TOOL_FORCE_N && counters.blowups_contained == 0;
    Ok(Outcome::Ran {
        bounded,
        farthest_m: farthest,
        max_speed_m_per_s: max_speed,
        max_kinetic_j: max_kinetic,
        energy_in_j: energy_in,
        max_force_n: max_force,
        force_clamps: counters.force_clamps,
        removed_voxels: counters.removed_elements,
        blowups: counters.blowups_contained,
    })
}

/// The Markdown report of a sweep.
pub fn markdown(results: &[(Case, Outcome)], command: &str) -> String {
    let mut md = String::new();
    let refused = results.iter().filter(|(_, o)| matches!(o, Outcome::Refused(_))).count();
    let failed: Vec<&(Case, Outcome)> = results.iter().filter(|(_, o)| !o.acceptable()).collect();
    let _ = writeln!(md, "# Stability at the extremes\n");
    let _ = writeln!(md, "Generated by `{command}`; do not edit by hand.\n");
    let _ = writeln!(
        md,
        "A 40 × 8 × 8 mm bar of 1 mm voxels at level 2 under gravity, 0.3 s per case. The farthest any node moved is reported, not bounded: a free fall for the whole run is 0.44 m, and the far corners of a one-voxel fragment, held only by the ghost material, can be flung farther without carrying energy. Scenarios: a blade drawn across at 2 m/s and a probe pressing 3 mm; seven cuts leaving pieces one voxel thick; held at both ends and cut through the middle with the blade left in the slit while a probe pushes one half onto it; layers of 8 voxels alternating between densities 10 and 100,000 kg/m³ (a mass ratio of 1e4), probed and cut. Bounds: finite state, kinetic energy never above the energy put in (the most potential energy gravity has released, Σ m g Δz, plus the tools' work: |force| × distance, and at most 2 M v² for a tool at speed v that bounces mass M; 10 % allowance), tool force ≤ {MAX_TOOL_FORCE_N} N, no blow-up contained. A setting the solver cannot hold is refused at load with the CG iterations it needs or a shorter time step; force clamps are counted.\n"
    );
    let _ = writeln!(md, "**{} cases: {} refused at load with a reason, {} ran bounded, {} failed.**\n", results.len(), refused, results.len() - refused - failed.len(), failed.len());
    let _ = writeln!(md, "| case | outcome |");
    let _ = writeln!(md, "|---|---|");
    for (case, outcome) in results {
        let _ = writeln!(md, "| {} | {} |", case.label(), outcome.describe().replace('|', "/"));
    }
    md
}
