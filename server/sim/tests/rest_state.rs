//! The intact prestressed skin, held at its border, stays at rest: the in-vivo shape is
//! an equilibrium (residual stress balanced by the border and the underlying tissue).

mod common;
use common::*;

/// The stated bound: after 1 s no node moves faster than this, m/s.
const REST_SPEED_BOUND: f64 = 1e-6;

#[test]
fn intact_regular_patch_stays_at_rest() {
    let mut m = build(&load_scene(&scenes_dir().join("skin-patch.json")));
    let start: Vec<_> = m.positions().to_vec();
    step_with(&mut m, None, false, 1000);
    assert!(max_speed(&m) < REST_SPEED_BOUND, "max speed {:e} m/s", max_speed(&m));
    let drift = start.iter().zip(m.positions()).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
    assert!(drift < 1e-9, "nodes drifted by {drift:e} m");
}

#[test]
fn intact_jittered_patch_stays_at_rest() {
    let text = patch_scene([0.1, 0.08], [30, 28], 0.1, "")
        .replace(r#""resolution": [30, 28]"#, r#""resolution": [30, 28], "jitter": 0.25, "seed": 11"#);
    let mut m = build(&scene(&text));
    step_with(&mut m, None, false, 1000);
    assert!(max_speed(&m) < REST_SPEED_BOUND, "max speed {:e} m/s", max_speed(&m));
}

#[test]
fn intact_real_skin_stays_at_rest() {
    let mut m = build(&load_scene(&scenes_dir().join("skin-real.json")));
    step_with(&mut m, None, false, 1000);
    assert!(max_speed(&m) < REST_SPEED_BOUND, "max speed {:e} m/s", max_speed(&m));
}

#[test]
fn prestress_is_real_tension_that_a_free_patch_releases() {
    // Without its border held, the same prestressed patch shrinks: the prestress is not
    // a bookkeeping artefact.
    let text = patch_scene([0.1, 0.08], [30, 28], 0.1, "").replace(r#""fixed": [ { "boundary": {} } ],"#, r#""fixed": [],"#);
    let mut m = build(&scene(&text));
    let width = |m: &cutsim_sim::msm::MassSpring| {
        let xs = m.positions().iter().map(|p| p.x);
        xs.clone().fold(f64::MIN, f64::max) - xs.fold(f64::MAX, f64::min)
    };
    let before = width(&m);
    step_with(&mut m, None, false, 300);
    assert!(width(&m) < before, "a free prestressed patch contracts: {} → {}", before, width(&m));
}
