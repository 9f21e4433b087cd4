//! The multirate schedule (crate::multirate): contact every millisecond against the
//! patch a branched grid stepped every N milliseconds publishes. A held probe settles
//! to the single-rate model's force; the force has no step when a new patch arrives;
//! while pressing it follows the single-rate force closely; dragged over a surface with
//! friction it is held back as the single-rate probe is while stuck; the state hash is the same
//! whether the deformation runs on its thread or inline, and a copy goes on alike;
//! a schedule whose deformation step is out of range is refused naming the field.

mod common;
use common::build_grid;

use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::multirate::Multirate;
use cutsim_sim::scene::Scene;
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};

/// A 32 × 32 × 16 mm block of 2 mm voxels at level 1 held at its bottom, a blade and a
/// 6 mm probe; the model's step `dt` s (Cholesky-preconditioned: a step of 10 ms or more
/// needs too many block-Jacobi iterations).
fn block(dt: f64) -> String {
    format!(
        r#"{{ "name": "block", "time_step_s": {dt},
        "model": {{ "branched-grid": {{
            "volume": {{ "box": {{ "size_m": [0.032, 0.032, 0.016], "voxel_size_m": 0.002 }} }},
            "centre": true,
            "materials": [ {{ "label": 1, "young_pa": 20000, "density_kg_per_m3": 1000 }} ],
            "level": 1,
            "damping": {{ "mass_per_s": 20, "stiffness_s": 0.002 }},
            "solver": {{ "preconditioner": "cholesky" }},
            "fixed": [ {{ "side": {{ "side": "-z" }} }} ],
            "cutting": {{}} }} }},
        "tools": [
            {{ "name": "blade", "shape": {{ "cylinder": {{ "radius_m": 0.0014, "length_m": 0.05 }} }}, "cutting_shape": {{ "cylinder": {{ "radius_m": 0.0011, "length_m": 0.05 }} }}, "can_cut": true, "contact_stiffness_n_per_m": 400, "max_force_n": 100 }},
            {{ "name": "probe", "shape": {{ "cylinder": {{ "radius_m": 0.006, "length_m": 0.05 }} }}, "contact_stiffness_n_per_m": 400, "max_force_n": 100 }}
        ] }}"#
    )
}


/// The block under a multirate schedule: haptics at 1 kHz, deformation every `every` ms.
fn multirate(every: u32, inline: bool) -> Multirate {
    Multirate::new(build_grid(&block(1e-3 * f64::from(every))), 1e-3, every, inline)
}

fn probe_at(tip: Vec3) -> Vec<ToolCommand> {
    let mut commands = vec![ToolCommand::default(); 2];
    commands[1] = ToolCommand { pose: Pose::new(tip, Quat::identity()), active: true, cut: false, grip: None };
    commands
}

/// The block's top is at z = 8 mm; the probe's rounded end reaches 6 mm below its tip.
fn probe_depth(depth: f64) -> Vec3 {
    Vec3::new(0.0011, 0.0013, 0.014 - depth)
}

/// Lowers the probe into the block at 10 mm/s to `depth`, holds it there for `hold`
/// steps; returns each step's force on the probe.
fn press_and_hold(tissue: &mut dyn Tissue, depth: f64, hold: usize) -> Vec<Vec3> {
    let mut feedback = vec![ToolFeedback::default(); 2];
    let mut forces = Vec::new();
    let start = 0.0005;
    let steps = ((depth + start) / 1e-5).round() as usize;
    for step in 0..steps + hold {
        let d = (-start + 1e-5 * step as f64).min(depth);
        tissue.step(&probe_at(probe_depth(d)), &mut feedback);
        forces.push(feedback[1].force_n);
    }
    forces
}

#[test]
fn a_probe_held_in_the_block_settles_to_the_single_rate_force() {
    let mut single = build_grid(&block(1e-3));
    let settled_single = *press_and_hold(&mut single, 0.002, 800).last().unwrap();
    for every in [10, 33] {
        let mut model = multirate(every, false);
        let forces = press_and_hold(&mut model, 0.002, 800);
        let settled = *forces.last().unwrap();
        let off = (settled - settled_single).norm() / settled_single.norm();
        println!(
            "probe 2 mm deep, held: single-rate {:.4} N, multirate (deformation every {every} ms) {:.4} N: {:.2} % apart; patch of {} vertices, compliance {:.3} mm/N down",
            settled_single.z,
            settled.z,
            off * 100.0,
            model.patch(1).vertices.len(),
            model.patch(1).compliance[(2, 2)] * 1e3
        );
        assert!(settled_single.z > 0.1, "the probe is pushed back: {settled_single:?}");
        assert!(off < 0.03, "multirate every {every} ms settles {:.1} % off the single-rate force", off * 100.0);
    }
}

#[test]
fn the_force_has_no_step_when_a_new_patch_arrives() {
    // The haptic bridge limits the force's rate to 100 N/s: 0.1 N a millisecond. Pressed
    // at 10 mm/s to 3 mm and held, the force the multirate loop renders changes by less
    // than that at every step, the steps where a new patch arrives included.
    let every = 33;
    let mut model = multirate(every, false);
    let forces = press_and_hold(&mut model, 0.003, 400);
    let jumps: Vec<f64> = forces.windows(2).map(|w| (w[1] - w[0]).norm()).collect();
    let largest = jumps.iter().copied().fold(0.0, f64::max);
    let at_arrivals = jumps.iter().enumerate().filter(|(i, _)| (i + 1) % every as usize == 0).map(|(_, j)| *j).fold(0.0, f64::max);
    let peak = forces.iter().map(|f| f.norm()).fold(0.0, f64::max);
    println!("peak {peak:.3} N; largest change in a step {largest:.4} N, at a new patch {at_arrivals:.4} N");
    assert!(peak > 0.2, "the probe pressed: {peak} N");
    assert!(largest < 0.1, "the force changed by {largest:.3} N in one step");
}

#[test]
fn the_same_session_gives_the_same_state_on_the_deformation_thread_and_inline() {
    // A probe pressed and a blade drawn through the block with the cut button held:
    // contact, loads, cuts and patches all go through the schedule.
    let run = |inline: bool| {
        let mut model = multirate(10, inline);
        let mut feedback = vec![ToolFeedback::default(); 2];
        let mut hashes = Vec::new();
        for step in 0..600 {
            let t = step as f64 * 1e-3;
            let mut commands = probe_at(probe_depth(0.001 + 0.002 * (t * 5.0).sin().abs()));
            commands[1].pose.position_m.x = -0.008;
            commands[0] = ToolCommand { pose: Pose::new(Vec3::new(0.004, -0.012 + 0.04 * t, 0.004), Quat::identity()), active: true, cut: true, grip: None };
            model.step(&commands, &mut feedback);
            if step % 50 == 49 {
                hashes.push(model.state_hash());
            }
        }
        (hashes, model.counters(), model.topology_version())
    };
    let (threaded, counters, version) = run(false);
    let (inline, _, _) = run(true);
    println!("{} voxels removed in {} updates (topology version {version})", counters.removed_elements, counters.cut_updates);
    assert!(counters.removed_elements > 0, "the blade cut");
    assert_eq!(threaded, inline, "the same state at every checkpoint");
    assert_eq!(run(false).0, threaded, "and again");
}

/// Forceps with jaws thick for the block (4 × 3 mm: its vertices hold them) pressed in,
/// closed and reopened give the same state on the deformation thread and inline: each job
/// receives the jaws as the haptic loop split them at its step, and on tissue with
/// friction, where closing jaws stop on what they pinch, their pinches too
/// (tool::bodies::Bodies::pinch).
#[test]
fn forceps_give_the_same_state_on_the_deformation_thread_and_inline() {
    for friction in [false, true] {
        let mut scene: serde_json::Value = serde_json::from_str(&block(10e-3)).unwrap();
        scene["tools"] = serde_json::json!([{ "name": "forceps", "shape": { "forceps": { "width_m": 0.004, "thickness_m": 0.003, "length_m": 0.05, "opening_m": 0.006 } }, "contact_stiffness_n_per_m": 400, "max_force_n": 100 }]);
        if friction {
            scene["model"]["branched-grid"]["materials"][0]["friction"] = serde_json::json!({ "static_coefficient": 0.5, "dynamic_coefficient": 0.4 });
        }
        let run = |inline: bool| {
            let mut model = Multirate::new(build_grid(&scene.to_string()), 1e-3, 10, inline);
            let mut feedback = vec![ToolFeedback::default(); 1];
            let (mut hashes, mut pressed, mut closed_half_gap, mut grasping) = (Vec::new(), 0.0f64, 0.0, 0);
            for step in 0..900 {
                // Pressed 3 mm in at 10 mm/s, closed from 350 ms to 650 ms; on frictional
                // tissue by an analog gripper squeezing from 20 % of the grip to all of it.
                let tip = probe_depth(0.001 * (f64::from(step) * 0.01).min(3.0)) - Vec3::new(0.0, 0.0, 0.006);
                let grip = friction.then(|| 0.2 + 0.8 * (f64::from(step.max(350) - 350) / 300.0).min(1.0));
                let command = ToolCommand { pose: Pose::new(tip, Quat::identity()), active: true, cut: (350..650).contains(&step), grip };
                model.step(&[command], &mut feedback);
                pressed = pressed.max(feedback[0].force_n.z);
                grasping += u32::from(feedback[0].grasping);
                if step == 649 {
                    closed_half_gap = model.jaws_half_gap_m(0).unwrap();
                }
                if step % 50 == 49 {
                    hashes.push(model.state_hash());
                }
            }
            (hashes, pressed, closed_half_gap, grasping)
        };
        let (threaded, pressed, closed_half_gap, grasping) = run(false);
        println!("forceps (friction {friction}) pressed with up to {pressed:.2} N, closed to {:.2} mm apart, grasping for {grasping} ms", 2e3 * closed_half_gap);
        assert!(pressed > 0.1, "the forceps pressed the block: {pressed:.2} N");
        assert_eq!(closed_half_gap > 0.0, friction, "the jaws stop on what they pinch where the tissue has friction, else close fully");
        assert_eq!(grasping > 0, friction, "the haptic loop's feedback says when the jaws grasp");
        assert_eq!(run(true).0, threaded, "the same state at every checkpoint (friction {friction})");
    }
}

#[test]
fn a_blade_drawn_fast_cuts_between_deformation_steps_as_a_single_rate_model_does() {
    // The blade drawn 24 mm across the block at 0.1 m/s, 4 mm deep: 3.3 mm a deformation
    // step of 33 ms, more than its cutting capsule's 2.2 mm width. The deformation step
    // cuts along the haptic steps' poses since the last one, so the incision has no gaps.
    let draw = |tissue: &mut dyn Tissue| {
        let mut feedback = vec![ToolFeedback::default(); 2];
        for step in 0..300 {
            let y = -0.012 + 0.1 * 1e-3 * step.min(240) as f64;
            let mut commands = vec![ToolCommand::default(); 2];
            commands[0] = ToolCommand { pose: Pose::new(Vec3::new(0.001, y, 0.004), Quat::identity()), active: true, cut: true, grip: None };
            tissue.step(&commands, &mut feedback);
        }
        tissue.counters().removed_elements
    };
    let single = draw(&mut build_grid(&block(1e-3)));
    let multi = draw(&mut multirate(33, false));
    println!("voxels removed by the blade: single-rate {single}, multirate (deformation every 33 ms) {multi}");
    assert!(single > 20, "the blade cuts: {single}");
    // Cutting only at each deformation step's pose removed 22 (gaps between the capsule's
    // positions); along the path 39: a little more than single-rate, because between
    // deformation steps the blade does not push the tissue aside before it cuts.
    assert!(multi >= single && (multi as f64) < 1.5 * single as f64, "single-rate {single}, multirate {multi}");
}

#[test]
fn auto_fidelity_fits_the_deformation_level_and_rate_and_reports_the_schedule() {
    // The block from level 3 down to level 0 with its deformation at most every 20 ms:
    // the calibration times deformation steps against 20 ms (not the haptic step's
    // 1 ms), then shortens the period as far as the chosen level allows.
    let json = block(1e-3)
        .replace(r#""level": 1,"#, r#""level": 0, "fidelity": "auto","#)
        .replace(r#""cutting": {}"#, r#""cutting": {}, "schedule": { "multirate": { "deformation_every_steps": 20 } }"#);
    let tissue = cutsim_sim::build_tissue(&Scene::from_json_str(&json, "test scene", None).unwrap()).unwrap_or_else(|e| panic!("{e}"));
    // Which level and rate fit is this machine's business (a benchmark's); what they
    // were fitted against and the schedule are the calibration's report.
    let chosen = tissue.fidelity().expect("an auto level");
    println!("{}", chosen.summary);
    let every = chosen.deformation_every_steps.expect("a multirate choice pins its rate");
    assert!((2..=20).contains(&every), "{every}");
    assert!(chosen.summary.contains("budget of 20000 µs"), "{}", chosen.summary);
    assert!(chosen.summary.contains(&format!("deformation every {every} haptic steps")), "{}", chosen.summary);
    assert!(chosen.summary.contains(&format!("every {every} steps ({:.0} Hz)", 1e3 / f64::from(every))), "{}", chosen.summary);
    assert_eq!(tissue.deformation_rate_hz(), Some(1.0 / (1e-3 * f64::from(every))));
}

#[test]
fn a_copy_goes_on_as_the_original_does() {
    let mut model = multirate(10, false);
    let mut feedback = vec![ToolFeedback::default(); 2];
    for step in 0..255 {
        model.step(&probe_at(probe_depth(1e-5 * step as f64)), &mut feedback);
    }
    let mut copy = model.clone_box();
    for step in 255..400 {
        let commands = probe_at(probe_depth(1e-5 * step as f64));
        model.step(&commands, &mut feedback);
        copy.step(&commands, &mut feedback);
    }
    assert_eq!(model.state_hash(), copy.state_hash());
}

#[test]
fn a_deformation_step_out_of_range_is_refused_naming_the_field() {
    let json = block(1e-3).replace(r#""cutting": {}"#, r#""cutting": {}, "schedule": { "multirate": { "deformation_every_steps": 60 } }"#).replace(r#""time_step_s": 0.001"#, r#""time_step_s": 0.002"#);
    let scene = Scene::from_json_str(&json, "test scene", None).unwrap();
    let error = cutsim_sim::build_tissue(&scene).err().expect("refused").to_string();
    assert!(error.contains("schedule.multirate.deformation_every_steps") && error.contains("0.1"), "{error}");
    let fine = json.replace(r#""time_step_s": 0.002"#, r#""time_step_s": 0.001"#);
    let tissue = cutsim_sim::build_tissue(&Scene::from_json_str(&fine, "test scene", None).unwrap()).unwrap();
    assert_eq!(tissue.time_step_s(), 1e-3, "the session steps at the haptic rate");
}

#[test]
fn while_pressing_the_force_follows_the_single_rate_model() {
    // Pressed at 10 mm/s to 3 mm and held: the deformation lags the tool by one to two
    // deformation steps, and between them the patch moves as a whole; the force the
    // haptic loop renders stays close to the single-rate model's at every step.
    let mut single = build_grid(&block(1e-3));
    let reference = press_and_hold(&mut single, 0.003, 300);
    let peak = reference.iter().map(|f| f.norm()).fold(0.0, f64::max);
    for (every, allowed) in [(10, 0.05), (33, 0.2)] {
        let mut model = multirate(every, false);
        let forces = press_and_hold(&mut model, 0.003, 300);
        let worst = forces.iter().zip(&reference).map(|(a, b)| (a - b).norm()).fold(0.0, f64::max);
        println!("deformation every {every} ms: at most {worst:.4} N from the single-rate force ({:.1} % of its peak {peak:.3} N)", 100.0 * worst / peak);
        assert!(worst < allowed * peak, "every {every} ms: {worst:.3} N off");
    }
}

/// The script that compares the schedules at equal budget (accuracy-speed schedules, the
/// multirate benchmark) presses the probe in and cuts with the blade under both.
#[test]
fn the_schedule_comparison_presses_and_cuts_under_both_schedules() {
    use cutsim_sim::accuracy::schedule::{Model, Script, run_real_time, scene_at};
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/u-tube.json");
    for multirate in [None, Some((33, "multigrid", Some(200)))] {
        let mut model = Model::build(&scene_at(&path, 2, multirate).unwrap()).unwrap_or_else(|e| panic!("{e}"));
        // Every step run however late: on a loaded machine the benchmark's early stop
        // (ten late deformation jobs) cut this run short (CI building beside it).
        let run = run_real_time(&mut model, Script { hold_steps: 150, cut_steps: 300, stop_when_late: false });
        assert!(run.held_force_n > 0.01 && run.removed_elements > 0, "{multirate:?}: the probe pressed and the blade cut: {run:?}");
        assert_eq!(run.jobs > 0, multirate.is_some(), "deformation jobs only under the multirate schedule: {run:?}");
    }
}

/// The block with Coulomb friction (μs 0.5, μd 0.4) on its material.
fn with_friction(json: &str) -> String {
    let out = json.replace(r#""density_kg_per_m3": 1000 }"#, r#""density_kg_per_m3": 1000, "friction": { "static_coefficient": 0.5, "dynamic_coefficient": 0.4 } }"#);
    assert_ne!(out, json, "the block's material changed shape");
    out
}

/// Presses the probe 2 mm in (10 mm/s), holds it 100 ms, then drags it 4 mm along +x at
/// 10 mm/s; each step's force on the probe.
fn press_and_drag(tissue: &mut dyn Tissue) -> Vec<Vec3> {
    let mut forces = press_and_hold(tissue, 0.002, 100);
    let mut feedback = vec![ToolFeedback::default(); 2];
    for step in 1..=400 {
        tissue.step(&probe_at(probe_depth(0.002) + Vec3::new(1e-5 * step as f64, 0.0, 0.0)), &mut feedback);
        forces.push(feedback[1].force_n);
    }
    forces
}

/// The mean x force over steps `range` (the drag starts at step 351).
fn mean_x(forces: &[Vec3], range: std::ops::Range<usize>) -> f64 {
    let n = range.len() as f64;
    forces[range].iter().map(|f| f.x).sum::<f64>() / n
}

#[test]
fn a_probe_dragged_over_the_surface_feels_its_friction_between_deformation_steps() {
    // Single-rate, the drag meets the tissue's friction (against +x): stuck for the first
    // ~1.5 mm, then sliding. The multirate haptic loop renders it every step from the
    // anchors the deformation published, moved as its vertices slide: it follows the
    // single-rate force while stuck; sliding, it follows its deformation model, whose
    // friction is decided once per deformation step (a vertex dragged 0.1-0.33 mm in a
    // step slides where at 1 ms it would stick again), lower than the 1 ms model's. Its
    // force changes no faster than the haptic bridge's limit (0.1 N a step).
    let single = press_and_drag(&mut build_grid(&with_friction(&block(1e-3))));
    let frictionless = press_and_drag(&mut build_grid(&block(1e-3)));
    let (stuck, sliding) = (400..500, 550..750);
    let normal = single[500].z;
    println!("single-rate: drag {:.4} N stuck, {:.4} N sliding (frictionless {:.4} N), normal {normal:.4} N", mean_x(&single, stuck.clone()), mean_x(&single, sliding.clone()), mean_x(&frictionless, sliding.clone()));
    assert!(mean_x(&single, sliding.clone()) < -0.25 * normal && mean_x(&frictionless, sliding.clone()).abs() < 0.02 * normal);
    for every in [10, 33] {
        let mut model = Multirate::new(build_grid(&with_friction(&block(1e-3 * f64::from(every)))), 1e-3, every, false);
        let forces = press_and_drag(&mut model);
        let largest = forces.windows(2).map(|w| (w[1] - w[0]).norm()).fold(0.0, f64::max);
        let (drag_stuck, drag_sliding) = (mean_x(&forces, stuck.clone()), mean_x(&forces, sliding.clone()));
        let off_stuck = drag_stuck / mean_x(&single, stuck.clone()) - 1.0;
        println!(
            "multirate every {every} ms: drag {drag_stuck:.4} N stuck ({:+.1} % off single-rate), {drag_sliding:.4} N sliding ({:+.1} %); largest change in a step {largest:.4} N",
            100.0 * off_stuck,
            100.0 * (drag_sliding / mean_x(&single, sliding.clone()) - 1.0)
        );
        assert!(off_stuck.abs() < 0.15, "every {every} ms: stuck, the drag is {:.1} % off the single-rate one", 100.0 * off_stuck);
        assert!(drag_sliding < -0.25 * normal, "every {every} ms: sliding, the drag is resisted: {drag_sliding} N");
        assert!(largest < 0.1, "every {every} ms: the force changed by {largest} N in one step");
    }
}
