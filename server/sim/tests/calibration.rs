//! The calibrated patch against the membrane it stands for: a uniaxial stretch test
//! (`cutsim_sim::accuracy::membrane::uniaxial_stretch`: a 10 × 10 cm patch of 5 mm
//! equilateral mesh on rollers, pulled 1 %, relaxed; stress from the reaction, strain
//! from two interior columns).

use cutsim_sim::accuracy::membrane::uniaxial_stretch;

#[test]
fn uniaxial_stretch_reproduces_young_modulus_within_ten_percent() {
    let s = uniaxial_stretch().unwrap();
    assert!(s.residual_speed < 1e-9, "relaxed to equilibrium (max speed {:e})", s.residual_speed);
    let error = s.young_measured_pa / s.young_target_pa - 1.0;
    println!("uniaxial stretch: E_measured = {:.0} Pa ({:+.2} % of E), effective Poisson ratio ≈ {:.3}", s.young_measured_pa, error * 100.0, s.poisson);
    assert!(error.abs() < 0.10, "E measured {:.0} Pa vs {} Pa", s.young_measured_pa, s.young_target_pa);
    // The lattice is isotropic with ν = 1/3: lateral contraction in the middle.
    assert!((s.poisson - 1.0 / 3.0).abs() < 0.06, "effective ν {}", s.poisson);
}
