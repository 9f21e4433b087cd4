//! `"fidelity": "auto"`: the calibration picks the finest level whose p99 step fits the
//! budget with a margin, cheaper ones for smaller budgets, reports its choice, and a
//! pinned scene rebuilds the same grid. The choice is tested with a deterministic cost
//! (the step time of a level is its element count in µs), so no test depends on this
//! machine's speed; the real timing is exercised for what it reports, not for its values.

use cutsim_sim::grid::BranchedGrid;
use cutsim_sim::grid::fidelity::{BUDGET_MARGIN, COARSEST_AUTO_LEVEL, FidelityChoice, build_auto, build_auto_multirate_with, build_auto_with, pin_choice};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::tissue::{ChosenFidelity, Tissue};

fn liver_auto(budget_ms: f64) -> Scene {
    liver_auto_with(&format!("\"step_budget_ms\": {budget_ms},"))
}

/// The liver from level 1, "fidelity": "auto", with `settings` added to its grid's.
fn liver_auto_with(settings: &str) -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/liver.json");
    let text = std::fs::read_to_string(&path).unwrap();
    let text = text.replace("\"level\": 2,", &format!("\"level\": 1, \"fidelity\": \"auto\", {settings}"));
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
    assert_eq!(Tissue::fidelity(&grid), Some(ChosenFidelity { level: choice.level, deformation_every_steps: None, summary: choice.summary() }), "the session sees the same report");
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
    let pinned = pin_choice(&value.to_string(), &ChosenFidelity { level: 2, deformation_every_steps: None, summary: String::new() }).unwrap();
    let scene = Scene::from_json_str(&pinned, "u-tube (pinned)", path.parent()).unwrap();
    let tissue = cutsim_sim::build_tissue(&scene).unwrap();
    assert!(tissue.fidelity().is_none(), "a pinned scene is fixed");
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    assert_eq!(spec.level.get(), 2);
    let chosen = ChosenFidelity { level: 1, deformation_every_steps: None, summary: String::new() };
    assert!(pin_choice("{\"model\": {\"msm\": {}}}", &chosen).unwrap_err().contains("not a branched-grid"));
    // A deformation rate pins the multirate schedule's steps, and needs one to pin.
    let chosen = ChosenFidelity { level: 2, deformation_every_steps: Some(12), summary: String::new() };
    assert!(pin_choice(&value.to_string(), &chosen).unwrap_err().contains("no multirate schedule"));
    value["model"]["branched-grid"]["schedule"] = serde_json::json!({ "multirate": { "deformation_every_steps": 33 } });
    value["model"]["branched-grid"]["solver"] = serde_json::json!({ "preconditioner": "multigrid" });
    let pinned: serde_json::Value = serde_json::from_str(&pin_choice(&value.to_string(), &chosen).unwrap()).unwrap();
    let grid = &pinned["model"]["branched-grid"];
    assert_eq!((grid["level"].as_u64(), grid["fidelity"].as_str(), grid["schedule"]["multirate"]["deformation_every_steps"].as_u64()), (Some(2), Some("fixed"), Some(12)));
    let tissue = cutsim_sim::build_tissue(&Scene::from_json_str(&pinned.to_string(), "u-tube (pinned)", path.parent()).unwrap()).unwrap();
    assert!(tissue.fidelity().is_none(), "a pinned scene is fixed");
    assert_eq!(tissue.deformation_rate_hz().map(f64::round), Some(83.0), "every 12 steps of 1 ms");
}

/// Under a multirate schedule (at most every 33 haptic steps of 1 ms here) the level is
/// fitted to the longest period, then the period shortened as far as that level fits.
#[test]
fn a_multirate_schedule_gets_the_shortest_period_its_level_fits() {
    // (Multigrid: block Jacobi needs too many iterations for steps of 8 ms or more.)
    let scene = liver_auto_with(r#""solver": { "preconditioner": "multigrid" },"#);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    // A level's deformation step takes its element count in µs: level 1 (5,475) fits
    // 33 ms less the margin (23,100 µs), and 8 ms (5,600 µs) still.
    let (grid, every) = build_auto_multirate_with(&scene, spec, 33, &mut |grid, _| elements_in_us(grid)).unwrap_or_else(|e| panic!("{e}"));
    let choice = grid.fidelity_choice().unwrap().clone();
    eprintln!("{}", choice.summary());
    assert_eq!((choice.level, every), (1, 8));
    let rate = choice.rate.clone().expect("a rate was fitted");
    assert_eq!(rate.tried, [(33, Some(5475.0)), (8, Some(5475.0))]);
    assert_eq!(grid.time_step_s(), 0.008, "the grid is built with the chosen period");
    assert!(choice.summary().contains("deformation every 8 haptic steps"), "{}", choice.summary());
    assert_eq!(Tissue::fidelity(&grid).and_then(|c| c.deformation_every_steps), Some(8));
    // A step that costs more at shorter periods (fewer steps to settle in): the first
    // estimate (13 steps) misses, the next (20) fits.
    let slower_when_shorter = &mut |grid: &mut BranchedGrid, period_s: f64| elements_in_us(grid) * (1.0 + 0.02 / period_s);
    let (grid, every) = build_auto_multirate_with(&scene, spec, 33, slower_when_shorter).unwrap();
    let tried: Vec<u32> = grid.fidelity_choice().unwrap().rate.as_ref().unwrap().tried.iter().map(|t| t.0).collect();
    assert_eq!((every, tried), (20, vec![33, 13, 20]));
    // Nothing fits: the scene's period is kept and the report says so.
    let (grid, every) = build_auto_multirate_with(&scene, spec, 33, &mut |_, _| 1e9).unwrap();
    assert_eq!((every, grid.fidelity_choice().unwrap().over_budget), (33, true));
}
