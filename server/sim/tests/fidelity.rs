//! `"fidelity": "auto"`: the calibration picks the finest level whose p99 step fits the
//! budget with a margin, cheaper ones for smaller budgets, reports its choice, and a
//! pinned scene rebuilds the same grid.

use cutsim_sim::grid::fidelity::{COARSEST_AUTO_LEVEL, build_auto, pin_level};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::tissue::Tissue;

fn liver_auto(budget_ms: f64) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/liver.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let text = text.replace("\"level\": 2,", &format!("\"level\": 1, \"fidelity\": \"auto\", \"step_budget_ms\": {budget_ms},"));
    assert!(text.contains("\"auto\""), "the liver scene changed shape");
    Scene::from_json_str(&text, "liver (auto)", path.parent()).unwrap_or_else(|e| panic!("{e}"))
}

fn choose(budget_ms: f64) -> (u32, cutsim_sim::grid::fidelity::FidelityChoice) {
    let scene = liver_auto(budget_ms);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    let (grid, choice) = build_auto(&scene, spec).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(grid.topology().layout.levels, choice.level, "the grid is built at the chosen level");
    assert_eq!(Tissue::fidelity(&grid).map(|(level, _)| level), Some(choice.level), "the grid reports its choice");
    (choice.level, choice)
}

#[test]
fn a_smaller_budget_gets_a_cheaper_level() {
    // 1 s per step: even level 1 of the liver (5,475 elements) fits with room to spare.
    let (generous, report) = choose(1000.0);
    eprintln!("{}", report.summary());
    assert_eq!(generous, 1, "the finest level allowed fits a 1 s budget");
    assert!(!report.over_budget);
    assert_eq!(report.tried.first().map(|t| t.0), Some(COARSEST_AUTO_LEVEL), "tried from the coarsest level down");
    // 10 µs per step: nothing fits; the coarsest level is taken and the report says so.
    let (tight, report) = choose(0.01);
    eprintln!("{}", report.summary());
    assert!(tight > generous, "a smaller budget picks a cheaper (coarser) level: {tight} vs {generous}");
    assert!(report.over_budget && report.summary().contains("no level fits"));
    assert_eq!(report.tried.len(), 1, "the calibration stops at the first level over budget");
    // The error class comes from the study (docs/accuracy-speed.json) for a bundled scene.
    let (_, report) = choose(1000.0);
    assert!(report.summary().contains("level 1"));
    assert!(report.error.is_some() && report.summary().contains("error class"), "{}", report.summary());
}

#[test]
fn a_pinned_scene_rebuilds_the_chosen_level_without_calibrating() {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/u-tube.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let mut value: serde_json::Value = serde_json::from_str(&text).unwrap();
    value["model"]["branched-grid"]["fidelity"] = "auto".into();
    let pinned = pin_level(&value.to_string(), 2).unwrap();
    let scene = Scene::from_json_str(&pinned, "u-tube (pinned)", path.parent()).unwrap();
    let tissue = cutsim_sim::build_tissue(&scene).unwrap();
    assert!(tissue.fidelity().is_none(), "a pinned scene is fixed");
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    assert_eq!(spec.level.get(), 2);
    assert!(pin_level("{\"model\": {\"msm\": {}}}", 1).unwrap_err().contains("not a branched-grid"));
}
