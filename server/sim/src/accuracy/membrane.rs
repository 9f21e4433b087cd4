//! The mass-spring skin against what it stands for: a uniaxial stretch test of the
//! calibrated patch against the membrane's Young's modulus, and the shrinking effect
//! (paper Section 2.1, Fig. 6) as the gap of a fresh incision against the residual strain.
//! `tests/calibration.rs` and `tests/shrinking.rs` assert on these; the speed–accuracy
//! report prints them.

use crate::math::{Pose, Quat, Vec3};
use crate::msm::{MassSpring, build_from_scene};
use crate::scene::{ModelSpec, Scene};
use crate::tissue::Tissue;

fn build(json: &str) -> Result<MassSpring, String> {
    let scene = Scene::from_json_str(json, "membrane study", None).map_err(|e| e.to_string())?;
    let ModelSpec::Msm(spec) = &scene.model else { return Err("not a mass-spring scene".into()) };
    build_from_scene(&scene, spec).map_err(|e| e.to_string())
}

/// A skin patch scene (E 100 kPa, 2 mm thick, edges held, explicit integrator) with a
/// scalpel; `msm_extra` is spliced into the msm object. The shrinking study and the
/// tests use it.
pub fn patch_scene(size_m: [f64; 2], resolution: [u32; 2], residual_strain: f64, msm_extra: &str) -> String {
    format!(
        r#"{{
        "name": "test-patch",
        "model": {{ "msm": {{
            "geometry": {{ "patch": {{ "size_m": [{}, {}], "resolution": [{}, {}] }} }},
            "material": {{ "young_pa": 100000, "thickness_m": 0.002, "density_kg_per_m3": 1100 }},
            "residual_strain": {residual_strain},
            "damping": {{ "mass_per_s": 20 }},
            "fixed": [ {{ "boundary": {{}} }} ],
            "integrator": {{ "symplectic-euler": {{ "substeps": 12 }} }},
            "cutting": {{}}
            {msm_extra}
        }} }},
        "tools": [ {{ "name": "scalpel", "shape": {{ "cylinder": {{ "radius_m": 0.0005, "length_m": 0.04 }} }}, "can_cut": true }} ]
    }}"#,
        size_m[0], size_m[1], resolution[0], resolution[1]
    )
}

/// What the stretch test measured.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Stretch {
    pub young_target_pa: f64,
    pub young_measured_pa: f64,
    /// The lateral contraction over the strain (an equilateral spring lattice has 1/3).
    pub poisson: f64,
    /// The largest node speed left after relaxing, m/s.
    pub residual_speed: f64,
}

/// The patch (5 mm equilateral mesh, 10 × 10 cm, E = 100 kPa, 2 mm thick, no prestrain)
/// on rollers at its left side, its right side moved 1 % to the right; it may contract
/// sideways. After relaxing, the reaction over the right side gives the stress, two
/// interior columns the strain, their ratio the modulus the lattice reproduces.
pub fn uniaxial_stretch() -> Result<Stretch, String> {
    const E: f64 = 100_000.0;
    const T: f64 = 0.002;
    let half = 0.05;
    let text = format!(
        r#"{{
        "name": "stretch",
        "model": {{ "msm": {{
            "geometry": {{ "patch": {{ "size_m": [0.1, 0.1], "resolution": [20, 23] }} }},
            "material": {{ "young_pa": {E}, "thickness_m": {T}, "density_kg_per_m3": 1100 }},
            "residual_strain": 0.0,
            "damping": {{ "mass_per_s": 300 }},
            "fixed": [
                {{ "box": {{ "min_m": [-1, -1, -1], "max_m": [1, 1, 1], "axes": "z" }} }},
                {{ "box": {{ "min_m": [-{half}, -1, -1], "max_m": [-0.0499, 1, 1], "axes": "x" }} }},
                {{ "box": {{ "min_m": [-{half}, -{half}, -1], "max_m": [-0.0499, -0.0499, 1], "axes": "y" }} }},
                {{ "box": {{ "min_m": [0.0499, -1, -1], "max_m": [{half}, 1, 1], "axes": "x" }} }}
            ],
            "integrator": {{ "implicit-euler": {{ "cg_max_iterations": 500, "cg_tolerance": 1e-10 }} }}
        }} }}
    }}"#
    );
    let mut m = build(&text)?;
    let width = 2.0 * half;
    let strain_applied = 0.01;
    let right: Vec<u32> = (0..m.positions().len() as u32).filter(|&i| m.positions()[i as usize].x > 0.0499).collect();
    for &i in &right {
        let p = m.positions()[i as usize];
        m.set_node_position(i, p + Vec3::new(width * strain_applied, 0.0, 0.0));
    }
    let reference: Vec<Vec3> = m.positions().to_vec();
    m.step_holding(None, false, 3000);
    let residual_speed = m.velocities().iter().map(|v| v.norm()).fold(0.0, f64::max);
    // Reaction: the springs pull the right side back with −F.
    let force: f64 = -right.iter().map(|&i| m.spring_force_on(i).x).sum::<f64>();
    let stress = force / (width * T);
    // Strain from two interior columns, away from the ends.
    let column = |x0: f64| -> (f64, f64) {
        let ids: Vec<usize> = (0..reference.len()).filter(|&i| (reference[i].x - x0).abs() < 1e-6).collect();
        let mean = |f: &dyn Fn(usize) -> f64| ids.iter().map(|&i| f(i)).sum::<f64>() / ids.len() as f64;
        (mean(&|i| reference[i].x), mean(&|i| m.positions()[i].x))
    };
    let (a0, a1) = column(-0.025);
    let (b0, b1) = column(0.025);
    let strain = ((b1 - a1) - (b0 - a0)) / (b0 - a0);
    let mid: Vec<usize> = (0..reference.len()).filter(|&i| reference[i].x.abs() < 0.003 && reference[i].y.abs() > 0.04).collect();
    let height_before: f64 = mid.iter().map(|&i| reference[i].y.abs()).sum();
    let height_after: f64 = mid.iter().map(|&i| m.positions()[i].y.abs()).sum();
    let lateral = height_after / height_before - 1.0;
    Ok(Stretch { young_target_pa: E, young_measured_pa: stress / strain, poisson: -lateral / strain, residual_speed })
}

/// The gap (m) between the middle lip vertices of a 4 cm incision cut in one stroke
/// update into a 10 × 8 cm patch with residual strain `residual_strain`, sampled every
/// step for `steps` steps from the moment the lips are made.
pub fn shrinking_gap_curve(residual_strain: f64, steps: usize) -> Result<Vec<f64>, String> {
    shrinking_gap_curve_with(residual_strain, steps, "")
}

/// [`shrinking_gap_curve`] with more keys in the patch's `msm` object (`msm_extra`
/// starts with a comma), e.g. a foundation under the skin.
pub fn shrinking_gap_curve_with(residual_strain: f64, steps: usize, msm_extra: &str) -> Result<Vec<f64>, String> {
    let text = patch_scene([0.1, 0.08], [40, 37], residual_strain, msm_extra);
    let mut m = build(&text)?;
    let (from, to) = (Vec3::new(-0.02, 0.0, 0.0), Vec3::new(0.02, 0.0, 0.0));
    // A vertical blade 5 mm deep, in at one end and across in one step.
    m.step_holding(Some(Pose::new(from - Vec3::z() * 0.005, Quat::identity())), true, 1);
    m.step_holding(Some(Pose::new(to - Vec3::z() * 0.005, Quat::identity())), true, 1);
    if m.counters().cut_updates != 1 {
        return Err(format!("the incision took {} updates, not one", m.counters().cut_updates));
    }
    let incision = m.incisions().first().ok_or("no incision")?.clone();
    let mid = incision.lips[0].len() / 2;
    let (Some(&a), Some(&b)) = (incision.lips[0].get(mid), incision.lips[1].get(mid)) else {
        return Err("the incision has tissue on one side only".into());
    };
    let (a, b) = (a as usize, b as usize);
    if a == b {
        return Err("the lips are not split".into());
    }
    let mut curve = vec![(m.positions()[a] - m.positions()[b]).norm()];
    for _ in 1..steps {
        m.step_holding(None, false, 1);
        curve.push((m.positions()[a] - m.positions()[b]).norm());
    }
    Ok(curve)
}

/// The gap curve's peak (m, at step) and plateau (mean of its last 100 steps, m).
pub fn peak_and_plateau(curve: &[f64]) -> ((usize, f64), f64) {
    let peak = curve.iter().copied().enumerate().fold((0, 0.0), |best, (i, v)| if v > best.1 { (i, v) } else { best });
    let tail = &curve[curve.len().saturating_sub(100)..];
    (peak, tail.iter().sum::<f64>() / tail.len().max(1) as f64)
}
