//! A single spring–mass against its analytic solution.

use cutsim_sim::math::Vec3;
use cutsim_sim::msm::calibration::MembraneMaterial;
use cutsim_sim::msm::{IntegratorChoice, MassSpring, MsmParams};

const K: f64 = 40.0; // N/m
const M: f64 = 0.004; // kg  → ω = 100 rad/s, period 62.8 ms
const L0: f64 = 0.05; // m
const AMPLITUDE: f64 = 0.005; // m

fn oscillator(integrator: IntegratorChoice, damping_per_s: f64) -> MassSpring {
    let params = MsmParams {
        time_step_s: 0.001,
        material: MembraneMaterial { young_pa: 1.0, poisson: 0.3, thickness_m: 1e-3, density_kg_per_m3: 1000.0 },
        residual_strain: 0.0,
        mass_damping_per_s: damping_per_s,
        spring_damping_s: 0.0,
        gravity_m_per_s2: None,
        integrator,
        cutting: None,
        foundation: None,
        fracture_toughness_j_per_m2: 0.0,
        friction: None,
    };
    // Node 0 is held; node 1 starts stretched by AMPLITUDE and at rest.
    let positions = [Vec3::zeros(), Vec3::new(L0 + AMPLITUDE, 0.0, 0.0)];
    let free = vec![Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0)];
    MassSpring::from_parts(&positions, &[1.0, M], &[(0, 1, K, L0)], free, &params).unwrap()
}

/// Times of upward zero crossings of the displacement, s.
fn crossings(model: &mut MassSpring, steps: usize) -> Vec<f64> {
    let dt = 0.001;
    let mut out = Vec::new();
    let mut prev = model.positions()[1].x - L0;
    for step in 1..=steps {
        model.step(&[], &mut []);
        let u = model.positions()[1].x - L0;
        if prev < 0.0 && u >= 0.0 {
            // Linear interpolation inside the step.
            out.push(dt * ((step - 1) as f64 + prev / (prev - u)));
        }
        prev = u;
    }
    out
}

#[test]
fn oscillates_at_sqrt_k_over_m_within_one_percent() {
    let omega = (K / M).sqrt();
    let mut model = oscillator(IntegratorChoice::SymplecticEuler { substeps: 10 }, 0.0);
    let c = crossings(&mut model, 2000);
    assert!(c.len() >= 20, "expected many periods, got {}", c.len());
    let period = (c[c.len() - 1] - c[0]) / (c.len() - 1) as f64;
    let measured = 2.0 * std::f64::consts::PI / period;
    let error = (measured / omega - 1.0).abs();
    assert!(error < 0.01, "ω measured {measured:.4} rad/s vs √(k/m) = {omega:.4} rad/s ({:.3} %)", error * 100.0);
}

#[test]
fn symplectic_euler_keeps_energy_within_one_percent_over_10000_steps() {
    let mut model = oscillator(IntegratorChoice::SymplecticEuler { substeps: 10 }, 0.0);
    let e0 = model.kinetic_energy() + model.potential_energy();
    assert!((e0 - 0.5 * K * AMPLITUDE * AMPLITUDE).abs() < 1e-12);
    let mut worst: f64 = 0.0;
    for _ in 0..10_000 {
        model.step(&[], &mut []);
        let e = model.kinetic_energy() + model.potential_energy();
        worst = worst.max((e / e0 - 1.0).abs());
    }
    assert!(worst < 0.01, "energy drifted by {:.4} %", worst * 100.0);
    // It must actually have oscillated, not stood still.
    assert!(model.velocities()[1].norm() > 0.0);
}

#[test]
fn implicit_euler_is_stable_and_dissipates() {
    let mut model = oscillator(IntegratorChoice::ImplicitEuler { max_iterations: 50, tolerance: 1e-10 }, 0.0);
    let e0 = model.kinetic_energy() + model.potential_energy();
    let mut previous = e0;
    for _ in 0..2000 {
        model.step(&[], &mut []);
        let e = model.kinetic_energy() + model.potential_energy();
        assert!(e <= previous * (1.0 + 1e-9), "backward Euler never gains energy");
        previous = e;
    }
    assert!(previous < 0.5 * e0, "numerical damping of backward Euler at ωh = 0.1 is visible");
    let (iterations, residual) = model.last_solve().unwrap();
    assert!(iterations <= 50 && residual <= 1e-10, "CG converged: {iterations} iterations, residual {residual:e}");
}

#[test]
fn mass_damping_decays_at_alpha_over_two() {
    // With −α·m·v the amplitude decays as exp(−α t / 2): compare the peaks' decay rate.
    let alpha = 4.0;
    let dt = 0.001;
    let mut model = oscillator(IntegratorChoice::SymplecticEuler { substeps: 10 }, alpha);
    let mut peaks: Vec<(f64, f64)> = Vec::new();
    let (mut u_prev2, mut u_prev) = (0.0f64, (model.positions()[1].x - L0).abs());
    for step in 1..=2000 {
        model.step(&[], &mut []);
        let u = (model.positions()[1].x - L0).abs();
        if u_prev > u_prev2 && u_prev >= u && step > 2 {
            peaks.push(((step - 1) as f64 * dt, u_prev));
        }
        u_prev2 = u_prev;
        u_prev = u;
    }
    assert!(peaks.len() > 40, "{} peaks", peaks.len());
    let (t1, a1) = peaks[1];
    let (t2, a2) = *peaks.last().unwrap();
    let rate = (a1 / a2).ln() / (t2 - t1);
    assert!((rate / (alpha / 2.0) - 1.0).abs() < 0.03, "decay rate {rate} 1/s vs α/2 = {}", alpha / 2.0);
}
