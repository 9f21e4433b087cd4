//! `"fidelity": "auto"`: the calibration picks the finest level whose p99 step fits the
//! budget with a margin, cheaper ones for smaller budgets, reports its choice, and a
//! pinned scene rebuilds the same grid. The choice is tested with a deterministic cost
//! (the step time of a level is its element count in µs), so no test depends on this
//! machine's speed; the real timing is exercised for what it reports, not for its values.

use cutsim_sim::grid::BranchedGrid;
use cutsim_sim::grid::fidelity::{BUDGET_MARGIN, COARSEST_AUTO_LEVEL, FidelityChoice, build_auto, build_auto_with, pin_level};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::tissue::Tissue;

fn liver_auto(budget_ms: f64) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/liver.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let text = text.replace("\"level\": 2,", &format!("\"level\": 1, \"fidelity\": \"auto\", \"step_budget_ms\": {budget_ms},"));
    assert!(text.contains("\"auto\""), "the liver scene changed shape");
    Scene::from_json_str(&text, "liver (auto)", path.parent()).unwrap_or_else(|e| panic!("{e}"))
}

/// The grid auto builds for `budget_ms` when a level's p99 step is `cost(grid)` µs.
fn choose(budget_ms: f64, cost: &mut dyn FnMut(&mut BranchedGrid) -> f64) -> (BranchedGrid, FidelityChoice) {
    let scene = liver_auto(budget_ms);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    let grid = build_auto_with(&scene, spec, cost).unwrap_or_else(|e| panic!("{e}"));
    let choice = grid.fidelity_choice().expect("an auto grid reports its choice").clone();
    assert_eq!(grid.topology().layout.levels, choice.level, "the grid is built at the chosen level");
    assert_eq!(Tissue::fidelity(&grid), Some((choice.level, choice.summary())), "the session sees the same report");
    (grid, choice)
}

fn elements_in_us(grid: &mut BranchedGrid) -> f64 {
    grid.topology().elements.alive_count() as f64
}

#[test]
fn a_smaller_budget_gets_a_cheaper_level() {
    // The liver has 5,475 / 917 / 160 elements at levels 1 / 2 / 3: with 30 % margin a
    // 2 ms budget (1,400 µs usable) fits level 2, 0.5 ms (350 µs) only level 3.
    let levels: Vec<u32> = [1000.0, 2.0, 0.5].iter().map(|&b| choose(b, &mut elements_in_us).1.level).collect();
    assert_eq!(levels, [1, 2, 3], "finer levels for larger budgets");
    let (_, report) = choose(2.0, &mut elements_in_us);
    eprintln!("{}", report.summary());
    assert!(!report.over_budget);
    let tried: Vec<u32> = report.tried.iter().map(|t| t.0).collect();
    assert_eq!(tried, [COARSEST_AUTO_LEVEL, 3, 2, 1], "tried from the coarsest level down, stopping at the first over budget");
    assert!(report.tried.iter().all(|(_, p99)| p99.is_some()));
    assert_eq!(report.budget_us * (1.0 - BUDGET_MARGIN), 1400.0);
    // The error class comes from the study (docs/accuracy-speed.json) for a bundled scene.
    let (error, reference) = report.error.clone().expect("the study measured the liver at level 2");
    assert!(error > 0.0 && reference.contains("scikit-fem"), "{reference}");
    assert!(report.summary().starts_with("fidelity auto: level 2 (fits") && report.summary().contains("error class"), "{}", report.summary());
    // Nothing fits 10 µs: the coarsest level is taken and the report says so.
    let (_, report) = choose(0.01, &mut elements_in_us);
    assert_eq!((report.level, report.over_budget), (COARSEST_AUTO_LEVEL, true));
    assert!(report.summary().contains("no level fits"));
    assert_eq!(report.tried.len(), 1, "the calibration stops at the first level over budget");
}

/// The real calibration (a probe pressed in, timed on this machine) reports a level in
/// range with the step times it measured; which level depends on the machine.
#[test]
fn the_timed_calibration_reports_what_it_measured() {
    let scene = liver_auto(1.0);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    let grid = build_auto(&scene, spec).unwrap_or_else(|e| panic!("{e}"));
    let choice = grid.fidelity_choice().unwrap();
    eprintln!("{}", choice.summary());
    assert!((1..=COARSEST_AUTO_LEVEL).contains(&choice.level));
    assert_eq!(choice.tried[0].0, COARSEST_AUTO_LEVEL);
    assert!(choice.tried.iter().all(|(_, p99)| p99.is_some_and(|t| t.is_finite() && t > 0.0)), "{:?}", choice.tried);
    assert_eq!(grid.topology().layout.levels, choice.level);
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
