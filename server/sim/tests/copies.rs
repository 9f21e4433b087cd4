//! A copy of a tissue steps exactly as the original: replays keep copies to seek, and a
//! replay must reach the recorded state hash from any of them.

mod common;
use common::*;
use cutsim_sim::math::Vec3;
use cutsim_sim::tissue::Tissue;

/// A scalpel pressed down into the skin until it punctures it (about 7 mm of
/// indentation), along the plan at 0.1 m/s 5 mm deep, and out.
fn cut_step(model: &mut dyn Tissue, i: u32) {
    let (x, z) = match i {
        0..50 => (-0.024, 0.005 - 0.015 * f64::from(i) / 50.0),
        50..505 => (-0.024 + 0.0455 * f64::from(i - 50) / 455.0, -0.005),
        _ => (0.0215, -0.005 + 0.015 * f64::from(i - 505) / 95.0),
    };
    let command = cutsim_sim::tool::ToolCommand { pose: pose(Vec3::new(x, 0.0, z), Vec3::z()), active: i < 600, cut: true, grip: None };
    // The scene's other tools (a probe, forceps) stay away.
    let mut commands = vec![cutsim_sim::tool::ToolCommand { active: false, ..command }; model.tools().len()];
    commands[0] = command;
    let mut feedback = vec![cutsim_sim::tool::ToolFeedback::default(); commands.len()];
    model.step(&commands, &mut feedback);
}

/// Steps a skin built from `scene` through [`cut_step`] `steps` times, and copies made at
/// the start and at step `midway` the same steps: each copy's state hash must be the
/// original's after every step.
fn skin_copies_step_as_the_original(scene: &cutsim_sim::scene::Scene, steps: u32, midway: u32) {
    let mut original: Box<dyn Tissue> = Box::new(build(scene));
    let mut at_start = original.clone_box();
    let (mut hashes, mut from_midway) = (Vec::new(), None);
    for i in 0..steps {
        if i == midway {
            from_midway = Some(original.clone_box());
        }
        cut_step(original.as_mut(), i);
        hashes.push(original.state_hash());
    }
    assert!(original.counters().cuts > 0, "the blade cut");
    for (copy, from) in [(at_start.as_mut(), 0), (from_midway.as_deref_mut().unwrap(), midway)] {
        for i in from..steps {
            cut_step(copy, i);
            assert_eq!(copy.state_hash(), hashes[i as usize], "the copy from step {from} after step {i}");
        }
    }
}

#[test]
fn a_copy_made_at_the_start_or_midway_steps_as_the_original() {
    skin_copies_step_as_the_original(&load_scene(&scenes_dir().join("skin-patch.json")), 700, 300);
}

/// The same on the implicit skin at 10k nodes, whose blade makes its contacts through the
/// tip face and the side (each bounded by the room made for contacts: a copy used to
/// make fewer than its original, whose list had that room as its capacity, and left its
/// state hash from the step the blade met the skin), and whose solve sweeps a region
/// chosen each step round the blade (msm::implicit::region).
#[test]
fn a_copy_of_the_implicit_10k_skin_cutting_steps_as_the_original() {
    let text = std::fs::read_to_string(scenes_dir().join("skin-patch.json"))
        .unwrap()
        .replace(r#"{ "symplectic-euler": { "substeps": 10 } }"#, r#"{ "implicit-euler": { "cg_max_iterations": 20, "cg_tolerance": 1e-4 } }"#)
        .replace(r#""resolution": [40, 37]"#, r#""resolution": [124, 115]"#);
    assert!(text.contains("implicit-euler") && text.contains("[124, 115]"), "skin-patch.json's integrator or resolution changed");
    let scene = cutsim_sim::scene::Scene::from_json_str(&text, "implicit 10k", None).unwrap();
    skin_copies_step_as_the_original(&scene, 150, 75);
}

/// A 40 × 20 × 10 mm block of 1 mm voxels at level 1 on its −z side, solved with the
/// multigrid or the Cholesky factor (whose copies redo work the original has out on its
/// worker), and a scalpel.
const BLOCK: &str = r#"{ "name": "block", "gravity_m_per_s2": [0, 0, -9.81],
    "model": { "branched-grid": {
        "volume": { "box": { "size_m": [0.04, 0.02, 0.01], "voxel_size_m": 0.001 } },
        "centre": true,
        "materials": [ { "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 } ],
        "level": 1,
        "fixed": [ { "side": { "side": "-z" } } ],
        "solver": { "preconditioner": "multigrid" },
        "cutting": {} } },
    "tools": [ { "name": "scalpel", "shape": { "cylinder": { "radius_m": 0.0015, "length_m": 0.06 } },
                 "can_cut": true, "contact_stiffness_n_per_m": 60, "max_force_n": 10 } ] }"#;

#[test]
fn a_copy_of_a_branched_grid_cutting_steps_as_the_original() {
    for preconditioner in ["multigrid", "cholesky"] {
        copy_steps_as_the_original(&BLOCK.replace("multigrid", preconditioner));
    }
}

fn copy_steps_as_the_original(text: &str) {
    let scene = scene(text);
    let mut original = cutsim_sim::build_tissue(&scene).unwrap_or_else(|e| panic!("{e}"));
    let blade = |i: u32| {
        let x = -0.015 + 0.03 * f64::from(i.min(240)) / 240.0;
        let command = cutsim_sim::tool::ToolCommand { pose: pose(Vec3::new(x, 0.0, 0.001), Vec3::z()), active: true, cut: i > 20, grip: None };
        [command]
    };
    let mut feedback = [cutsim_sim::tool::ToolFeedback::default()];
    let (mut hashes, mut copies) = (Vec::new(), Vec::new());
    for i in 0..240 {
        if i % 80 == 0 {
            copies.push((i, original.clone_box()));
        }
        original.step(&blade(i), &mut feedback);
        hashes.push(original.state_hash());
    }
    assert!(original.counters().cuts > 0, "the blade removed voxels");
    for (from, mut copy) in copies {
        for i in from..240 {
            copy.step(&blade(i), &mut feedback);
            assert_eq!(copy.state_hash(), hashes[i as usize], "the copy from step {from} after step {i}");
        }
    }
}
