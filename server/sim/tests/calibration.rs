//! The calibrated patch against the membrane it stands for: a uniaxial stretch test.
//!
//! The patch (5 mm equilateral mesh, 10 × 10 cm, no prestrain) is held on rollers at
//! its left side and pulled by a prescribed 1 % displacement of its right side; it may
//! contract sideways. After relaxing to equilibrium, the reaction force over the right
//! side gives the stress, the displacement of two interior columns the strain, and
//! their ratio the Young's modulus the mesh reproduces.

mod common;
use common::*;
use cutsim_sim::math::Vec3;

const E: f64 = 100_000.0;
const T: f64 = 0.002;

#[test]
fn uniaxial_stretch_reproduces_young_modulus_within_ten_percent() {
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
    let mut m = build(&scene(&text));
    let width = 2.0 * half;
    let strain_applied = 0.01;
    let right: Vec<u32> = (0..m.positions().len() as u32).filter(|&i| m.positions()[i as usize].x > 0.0499).collect();
    assert_eq!(right.len(), 24, "right side nodes");
    for &i in &right {
        let p = m.positions()[i as usize];
        m.set_node_position(i, p + Vec3::new(width * strain_applied, 0.0, 0.0));
    }
    let reference: Vec<Vec3> = m.positions().to_vec();
    step_with(&mut m, None, false, 3000);
    assert!(max_speed(&m) < 1e-9, "relaxed to equilibrium (max speed {:e})", max_speed(&m));

    // Reaction: the springs pull the right side back with −F.
    let force: f64 = -right.iter().map(|&i| m.spring_force_on(i).x).sum::<f64>();
    let stress = force / (width * T); // Pa
    // Strain from two interior columns, away from the ends.
    let column = |x0: f64| -> (f64, f64) {
        let ids: Vec<usize> = (0..reference.len()).filter(|&i| (reference[i].x - x0).abs() < 1e-6).collect();
        let mean = |f: &dyn Fn(usize) -> f64| ids.iter().map(|&i| f(i)).sum::<f64>() / ids.len() as f64;
        (mean(&|i| reference[i].x), mean(&|i| m.positions()[i].x))
    };
    let (a0, a1) = column(-0.025);
    let (b0, b1) = column(0.025);
    let strain = ((b1 - a1) - (b0 - a0)) / (b0 - a0);
    let measured = stress / strain;
    let error = measured / E - 1.0;
    println!("uniaxial stretch: σ = {stress:.2} Pa, ε = {strain:.5}, E_measured = {measured:.0} Pa ({:+.2} % of E)", error * 100.0);
    assert!(error.abs() < 0.10, "E measured {measured:.0} Pa vs {E} Pa");
    // The lattice is isotropic with ν = 1/3: lateral contraction in the middle.
    let mid: Vec<usize> = (0..reference.len()).filter(|&i| reference[i].x.abs() < 0.003 && reference[i].y.abs() > 0.04).collect();
    let height_before: f64 = mid.iter().map(|&i| reference[i].y.abs()).sum();
    let height_after: f64 = mid.iter().map(|&i| m.positions()[i].y.abs()).sum();
    let lateral = height_after / height_before - 1.0;
    let nu = -lateral / strain;
    println!("effective Poisson ratio ≈ {nu:.3}");
    assert!((nu - 1.0 / 3.0).abs() < 0.06, "effective ν {nu}");
}
