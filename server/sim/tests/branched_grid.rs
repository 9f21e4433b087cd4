//! The branched-grid model through its scene and the tissue interface: a cut that
//! separates a bar, nested tool shapes (a blade cuts where a probe pressed as hard does
//! not), locality of a voxel removal, determinism, and procedural scenes without data.

mod common;
use common::build_grid;

use std::collections::BTreeSet;

use cutsim_sim::grid::BranchedGrid;
use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::surface::SurfaceReplica;
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};


/// A 40 × 8 × 8 mm bar of 1 mm voxels at level 2, held at its −x end.
fn bar(gravity: bool) -> String {
    format!(
        r#"{{ "name": "bar", {}
        "model": {{ "branched-grid": {{
            "volume": {{ "box": {{ "size_m": [0.04, 0.008, 0.008], "voxel_size_m": 0.001 }} }},
            "centre": true,
            "materials": [ {{ "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 }} ],
            "level": 2,
            "fixed": [ {{ "side": {{ "side": "-x" }} }} ],
            "cutting": {{}} }} }},
        "tools": [] }}"#,
        if gravity { r#""gravity_m_per_s2": [0, 0, -9.81],"# } else { "" }
    )
}

/// Each directed edge once and its twin once: closed, oriented surface.
fn assert_closed(g: &BranchedGrid) {
    let mut directed: Vec<(u32, u32)> = g.surface().live_triangles().flat_map(|(_, t)| (0..3).map(move |k| (t[k], t[(k + 1) % 3]))).collect();
    directed.sort_unstable();
    assert!(directed.windows(2).all(|w| w[0] != w[1]), "a directed edge is used twice");
    for &(a, b) in &directed {
        assert!(directed.binary_search(&(b, a)).is_ok(), "edge {a}→{b} has no twin: the surface is open");
    }
}

/// Connected components of the surface (triangles joined through shared vertices).
fn surface_pieces(g: &BranchedGrid) -> usize {
    let mut sets = cutsim_sim::union_find::UnionFind::new(g.surface().vertex_count());
    for (_, t) in g.surface().live_triangles() {
        sets.union(t[0] as usize, t[1] as usize);
        sets.union(t[0] as usize, t[2] as usize);
    }
    let roots: BTreeSet<usize> = g.surface().live_triangles().map(|(_, t)| sets.find(t[0] as usize)).collect();
    roots.len()
}

#[test]
fn a_cut_through_a_bar_separates_two_bodies_that_fall_apart() {
    let mut g = build_grid(&bar(true));
    let (mut commands, mut feedback) = (vec![], vec![]);
    for _ in 0..200 {
        g.step(&commands, &mut feedback);
    }
    assert_eq!(g.pieces(), 1);
    let before = g.piece_centres()[0];
    // Remove the slab of voxels x = 20..=21 across the whole section.
    let t = g.topology();
    let slab: Vec<usize> = (0..8).flat_map(|j| (0..8).flat_map(move |k| [20usize, 21].map(|i| [i, j, k]))).map(|v| t.layout.voxel_index(v)).collect();
    let mut replica = SurfaceReplica::from_snapshot(&g.snapshot());
    g.apply_removal(&slab);
    let mut deltas = Vec::new();
    g.drain_deltas(&mut deltas);
    assert_eq!(deltas.len(), 1);
    replica.apply(&deltas[0]).unwrap();
    assert_eq!(replica.topology_hash(), g.snapshot().topology_hash(), "the delta takes a viewer to the new surface");
    assert_eq!(g.pieces(), 2, "two bodies");
    assert_closed(&g);
    assert_eq!(surface_pieces(&g), 2, "each side's surface is closed on its own");
    let volume_lost = g.removed_volume_m3();
    assert!((volume_lost - 128e-9).abs() < 1e-15, "{volume_lost}");
    // Let them fall: the free half drops, the held half stays.
    for _ in 0..300 {
        g.step(&commands, &mut feedback);
        commands.clear();
        feedback.clear();
    }
    let centres = g.piece_centres();
    assert_eq!(centres.len(), 2);
    let (held, free) = if centres[0].x < centres[1].x { (centres[0], centres[1]) } else { (centres[1], centres[0]) };
    let fallen = before.z - free.z;
    // Free fall under the scene's mass-proportional (Rayleigh α) damping, integrated as
    // the solver does (implicit Euler): v ← (v + h g)/(1 + h α), z ← z + h v.
    let (h, alpha) = (0.001, 5.0);
    let (mut v, mut expected) = (0.0, 0.0);
    for _ in 0..300 {
        v = (v + h * 9.81) / (1.0 + h * alpha);
        expected += h * v;
    }
    assert!((fallen / expected - 1.0).abs() < 0.1, "the free half fell {fallen} m; a damped free fall drops {expected} m");
    assert!(before.z - held.z < 0.01, "the held half hangs on: {} m", before.z - held.z);
    assert!(free.x > held.x + 0.015);
}

fn block_with_tools() -> String {
    r#"{ "name": "block",
        "model": { "branched-grid": {
            "volume": { "box": { "size_m": [0.032, 0.032, 0.016], "voxel_size_m": 0.002 } },
            "centre": true,
            "materials": [ { "label": 1, "young_pa": 20000, "density_kg_per_m3": 1000 } ],
            "level": 1,
            "damping": { "mass_per_s": 20, "stiffness_s": 0.002 },
            "fixed": [ { "side": { "side": "-z" } } ],
            "cutting": {} } },
        "tools": [
            { "name": "blade", "shape": { "cylinder": { "radius_m": 0.0014, "length_m": 0.05 } }, "cutting_shape": { "cylinder": { "radius_m": 0.0011, "length_m": 0.05 } }, "can_cut": true, "contact_stiffness_n_per_m": 400, "max_force_n": 100 },
            { "name": "probe", "shape": { "cylinder": { "radius_m": 0.006, "length_m": 0.05 } }, "cutting_shape": { "cylinder": { "radius_m": 0.003, "length_m": 0.05 } }, "can_cut": true, "contact_stiffness_n_per_m": 400, "max_force_n": 100 }
        ] }"#
        .into()
}

/// Lowers tool `tool` onto the block's top (z = +8 mm) at 5 mm/s with the cut button
/// held until it cuts or pushes with `stop_force` N; returns (force reached, cut?).
fn press(tool: usize, stop_force: f64) -> (f64, bool) {
    let mut g = build_grid(&block_with_tools());
    let mut feedback = vec![ToolFeedback::default(); 2];
    let mut commands = vec![ToolCommand::default(); 2];
    let mut z = 0.0085;
    let mut force: f64 = 0.0;
    for _ in 0..4000 {
        z -= 5e-6;
        commands[tool] = ToolCommand { pose: Pose::new(Vec3::new(0.0011, 0.0013, z), Quat::identity()), active: true, cut: true, grip: None };
        g.step(&commands, &mut feedback);
        force = force.max(feedback[tool].force_n.norm());
        if g.counters().removed_elements > 0 {
            return (force, true);
        }
        if force >= stop_force {
            return (force, false);
        }
    }
    (force, false)
}

#[test]
fn a_blade_cuts_where_a_broad_probe_pressed_as_hard_does_not() {
    let (blade_force, blade_cut) = press(0, 50.0);
    assert!(blade_cut, "the blade cuts (force reached {blade_force} N)");
    let (probe_force, probe_cut) = press(1, blade_force);
    eprintln!("blade cut at {blade_force} N; probe reached {probe_force} N without cutting");
    assert!(!probe_cut, "the probe must not cut at the blade's force {blade_force} N (it reached {probe_force} N)");
    assert!(probe_force >= blade_force);
}

#[test]
fn a_voxel_removal_changes_only_the_cells_that_hold_or_touch_it() {
    let mut g = build_grid(&bar(false));
    let t = g.topology().clone();
    let voxel = t.layout.voxel_index([13, 3, 7]);
    g.apply_removal(&[voxel]);
    let after = g.topology();
    let cell = t.layout.cell_of_voxel([13, 3, 7]);
    let near = |e: usize| {
        let c = t.layout.cell_coords(t.elements.cell[e] as usize);
        (0..3).all(|a| (c[a] as i64 - cell[a] as i64).abs() <= 1)
    };
    for e in 0..t.elements.len() {
        let changed = !after.elements.alive[e] || after.elements.nodes[e] != t.elements.nodes[e] || after.elements.stiffness[e] != t.elements.stiffness[e];
        assert!(!changed || near(e), "element {e} far from the removed voxel changed");
    }
    let changed_stiffness = (0..t.elements.len()).filter(|&e| after.elements.stiffness[e] != t.elements.stiffness[e]).count();
    assert_eq!(changed_stiffness, 1, "only the element holding the voxel loses stiffness");
}

fn u_tube_cut_run() -> (u64, u64) {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/u-tube.json")).unwrap();
    let mut g = build_grid(&text);
    let mut feedback = vec![ToolFeedback::default(); 2];
    let mut commands = vec![ToolCommand::default(); 2];
    // The scalpel presses down into the top of the left arm (x from −8 to −2 mm, top at
    // z = +32 mm) while moving along it.
    let down = Quat::identity();
    for step in 0..1500u32 {
        let s = f64::from(step) / 1500.0;
        let pose = Pose::new(Vec3::new(-0.007 + 0.004 * s, 0.0, 0.034 - 0.014 * s), down);
        commands[0] = ToolCommand { pose, active: true, cut: true, grip: None };
        g.step(&commands, &mut feedback);
        assert!(feedback.iter().all(|f| f.force_n.iter().all(|c| c.is_finite())));
    }
    (g.state_hash(), g.counters().removed_elements)
}

#[test]
fn the_same_cuts_give_the_same_state() {
    let (a, removed) = u_tube_cut_run();
    let (b, _) = u_tube_cut_run();
    assert_eq!(a, b);
    assert!(removed > 0, "the scalpel removed tissue");
}

#[test]
fn procedural_scenes_need_no_data_files() {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/u-tube.json")).unwrap();
    assert!(!text.contains("data:"), "the procedural scene reads no shared data");
    let scene = Scene::from_json_str(&text, "u-tube", None).unwrap();
    let mut tissue = cutsim_sim::build_tissue(&scene).unwrap();
    let mut feedback = vec![ToolFeedback::default(); 2];
    let commands = vec![ToolCommand::default(); 2];
    for _ in 0..100 {
        tissue.step(&commands, &mut feedback);
    }
    assert_eq!(tissue.model_name(), "branched-grid");
    assert!(tissue.counters().elements >= 4);
}

/// An element holding a single voxel has corners with almost no stiffness or mass; the
/// ghost material keeps them with the body. A 16 mm cube with one voxel sticking out
/// into the next level-3 cell, pressed by a probe next to it, must not throw any node
/// away.
#[test]
fn a_single_voxel_element_stays_with_the_body() {
    use cutsim_sim::volume::{LabelVolume, nifti};
    let mut volume = LabelVolume::new([24, 16, 16], [0.001; 3], Vec3::zeros());
    for k in 0..16 {
        for j in 0..16 {
            for i in 0..16 {
                volume.set(i, j, k, 1);
            }
        }
    }
    volume.set(16, 8, 15, 1);
    let dir = std::env::temp_dir().join(format!("cutsim-single-voxel-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("cube.nii");
    nifti::write_nifti(&volume, &path).unwrap();
    let json = format!(
        r#"{{ "name": "cube",
        "model": {{ "branched-grid": {{
            "volume": {{ "nifti": {{ "path": "{}" }} }},
            "materials": [ {{ "label": 1, "young_pa": 5000, "density_kg_per_m3": 1000 }} ],
            "level": 3,
            "fixed": [ {{ "side": {{ "side": "-x" }} }} ] }} }},
        "tools": [ {{ "name": "probe", "shape": {{ "cylinder": {{ "radius_m": 0.004, "length_m": 0.05 }} }}, "contact_stiffness_n_per_m": 300 }} ] }}"#,
        path.display()
    );
    let mut g = build_grid(&json);
    std::fs::remove_dir_all(&dir).ok();
    let single = (0..g.topology().elements.len()).filter(|&e| g.topology().elements.voxel_count[e] == 1).count();
    assert_eq!(single, 1, "the protruding voxel is an element of its own");
    let mut feedback = vec![ToolFeedback::default()];
    for step in 0..1500 {
        let depth = 0.003 * (f64::from(step) / 300.0).min(1.0);
        let pose = Pose::new(Vec3::new(0.013, 0.008, 0.016 + 0.0045 - depth), Quat::identity());
        g.step(&[ToolCommand { pose, active: true, cut: false, grip: None }], &mut feedback);
    }
    let n = &g.topology().nodes;
    let largest = (0..n.len()).filter(|&i| n.alive[i]).map(|i| (n.x[i] - n.rest[i]).norm()).fold(0.0, f64::max);
    assert!(largest < 0.01, "a node moved {} mm", largest * 1e3);
    assert!(feedback[0].contacts > 0, "the probe pressed the body");
}

/// Stability at the extremes (the reduced sweep of `cutsim_sim::accuracy::stability`;
/// `accuracy-speed stability` runs the full one into docs/stability.md): E from 1e2 to
/// 1e7 Pa, ν from 0 to 0.499, dt from 0.1 to 10 ms, damping off or on, a probe and a
/// blade at 2 m/s, fragments one voxel thick, a blade squeezed in a cut, a mass ratio of
/// 1e4. Every case is either refused at load with a reason and a stable setting, or stays
/// finite with its kinetic energy below the work put in and a bounded tool force, without
/// a blow-up contained; every scenario has cases that run and cases that cut.
#[test]
fn the_grid_stays_bounded_at_extreme_settings() {
    use cutsim_sim::accuracy::stability::{Outcome, Scenario, cases, run};
    let mut failures: Vec<String> = Vec::new();
    let mut ran = std::collections::BTreeMap::new();
    let mut cut = std::collections::BTreeMap::new();
    for case in cases(false) {
        let outcome = run(&case).unwrap_or_else(|e| panic!("{}: {e}", case.label()));
        eprintln!("{}: {}", case.label(), outcome.describe());
        if !outcome.acceptable() {
            failures.push(format!("{}: {}", case.label(), outcome.describe()));
        }
        if let Outcome::Ran { removed_voxels, .. } = outcome {
            *ran.entry(case.scenario.name()).or_insert(0) += 1;
            // Very soft tissue is pushed aside by the blade's outer shape rather than cut.
            if removed_voxels > 0 {
                *cut.entry(case.scenario.name()).or_insert(0) += 1;
            }
        }
    }
    assert!(failures.is_empty(), "unbounded runs or refusals without a reason:\n{}", failures.join("\n"));
    for scenario in Scenario::ALL {
        assert!(ran.get(scenario.name()).copied().unwrap_or(0) > 0, "no case of {} ran (all refused)", scenario.name());
        assert!(cut.get(scenario.name()).copied().unwrap_or(0) > 0, "no case of {} cut anything", scenario.name());
    }
}

#[test]
fn the_grid_feeds_back_the_contact_force_of_the_solved_state() {
    // The probe (6 mm, 400 N/m) pushed into the block's top at 0.1 m/s: its force is
    // the penalty at the end of each step, as the implicit step solved it, not the
    // penalty before the step (one step late). The penalty is the grid's own rule
    // (`penalty_now`: each vertex pushed along the normal it touched the tool with).
    let mut g = build_grid(&block_with_tools());
    let mut feedback = vec![ToolFeedback::default(); 2];
    let mut commands = vec![ToolCommand::default(); 2];
    let (speed, dt) = (0.1, 1e-3);
    let (mut worst_after, mut worst_before, mut contact_steps) = (0.0f64, 0.0f64, 0);
    // The capsule's rounded end first touches the top (z = 8 mm) from 14 mm.
    for step in 0..80 {
        let tip = Vec3::new(0.0011, 0.0013, 0.0145 - speed * dt * f64::from(step));
        commands[1] = ToolCommand { pose: Pose::new(tip, Quat::identity()), active: true, cut: false, grip: None };
        let before = g.penalty_now(1, &commands[1]);
        g.step(&commands, &mut feedback);
        let after = g.penalty_now(1, &commands[1]);
        if after.z < 0.3 {
            continue;
        }
        contact_steps += 1;
        let felt = feedback[1].force_n;
        worst_after = worst_after.max((felt - after).norm() / after.norm());
        worst_before = worst_before.max((before - after).norm() / after.norm());
    }
    println!("over {contact_steps} steps in contact: fed back within {:.1} % of the solved state's penalty (the penalty before the step: {:.1} %)", worst_after * 100.0, worst_before * 100.0);
    assert!(contact_steps >= 20);
    assert!(worst_after < 0.05, "fed back {:.1} % off the solved state's force", worst_after * 100.0);
    assert!(worst_after < 0.5 * worst_before, "closer than the penalty before the step ({:.1} % against {:.1} %)", worst_after * 100.0, worst_before * 100.0);
}

/// The bar held by a box 2 mm long that starts 0.5 mm inside its −x end: at level 2
/// (4 mm cells) no node lies in it. (Level 0 needs more CG iterations than the bar's
/// default cap.)
fn bar_held_inside(support: &str, level: u32) -> Result<BranchedGrid, cutsim_sim::scene::SceneError> {
    let json = bar(true).replace(r#""fixed": [ { "side": { "side": "-x" } } ],"#, &format!(r#""fixed": [ {{ "box": {{ "min_m": [-0.0195, -1, -1], "max_m": [-0.0175, 1, 1] }} }} ], "support": "{support}","#)).replace(r#""level": 2"#, &format!(r#""level": {level}, "solver": {{ "cg_max_iterations": 400 }}"#));
    let scene = Scene::from_json_str(&json, "held bar", None).unwrap_or_else(|e| panic!("{e}"));
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
    cutsim_sim::grid::build_from_scene(&scene, spec)
}

/// Solves the grid's linear static problem under gravity; returns the largest
/// displacement and the largest displacement of a held level-0 point (a fixed node or
/// an embedded point), m.
fn sag_and_held_motion(mut g: BranchedGrid) -> (f64, f64) {
    let topo = g.topology_mut();
    let loads: Vec<Vec3> = topo.nodes.mass.iter().map(|m| Vec3::new(0.0, 0.0, -9.81 * m)).collect();
    let (_, residual) = cutsim_sim::grid::solver::solve_static(topo, &loads, 1e-10, 100_000);
    assert!(residual < 1e-8, "converged: {residual:e}");
    largest_and_held_motion(g.topology())
}

/// The largest displacement from rest and the largest of a held level-0 point, m.
fn largest_and_held_motion(topo: &cutsim_sim::grid::topology::Topology) -> (f64, f64) {
    let moved = |n: usize| (topo.nodes.x[n] - topo.nodes.rest[n]).norm();
    let sag = (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n]).map(moved).fold(0.0, f64::max);
    let mut held = (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n] && topo.nodes.fixed[n]).map(moved).fold(0.0, f64::max);
    for (e, p) in topo.supports.live(topo) {
        let at: Vec3 = (0..8).map(|k| topo.nodes.x[topo.elements.nodes[e][k] as usize] * p.weights[k]).sum();
        held = held.max((at - p.rest).norm());
    }
    (sag, held)
}

#[test]
fn an_embedded_support_holds_level_0_points_where_a_coarse_level_has_no_node() {
    // By the level's nodes, the region holds nothing at level 2, and the error says so
    // and names the rule that holds it.
    let refused = bar_held_inside("coarse-nodes", 2).expect_err("no node in the region at level 2");
    assert_eq!(refused.path, "model.branched-grid.fixed[0]");
    assert!(refused.message.contains("\"support\": \"embedded\""), "{}", refused.message);
    // Embedded, the same region holds the level-0 points in it: springs only (none is a
    // cell corner), and they barely move while the free end sags.
    let embedded = bar_held_inside("embedded", 2).unwrap();
    let topo = embedded.topology();
    assert!(topo.supports.live(topo).count() > 0 && !topo.nodes.fixed.iter().any(|&f| f));
    let (sag, held) = sag_and_held_motion(embedded);
    println!("level 2, embedded: free end sags {:.3} mm, held points move {:.4} mm", sag * 1e3, held * 1e3);
    assert!(sag > 1e-4 && held < 0.01 * sag, "sag {sag:e} m, held points {held:e} m");
    // The dynamics hold them too (the springs in the implicit step): settling under
    // gravity, the bar swings while its held points stay put.
    let mut swinging = bar_held_inside("embedded", 2).unwrap();
    for _ in 0..300 {
        swinging.step(&[], &mut []);
    }
    let (swing, held) = largest_and_held_motion(swinging.topology());
    println!("level 2, embedded, after 0.3 s: largest displacement {:.3} mm, held points {:.4} mm", swing * 1e3, held * 1e3);
    assert!(swing > 1e-3 && held < 0.01 * swing, "moved {swing:e} m, held points {held:e} m");
    // At level 0 every held point is a node: both rules hold the same nodes, exactly.
    let (a, b) = (bar_held_inside("coarse-nodes", 0).unwrap(), bar_held_inside("embedded", 0).unwrap());
    assert_eq!(a.topology().nodes.fixed, b.topology().nodes.fixed);
    assert!(b.topology().supports.points.is_empty());
    let ((sag_a, held_a), (sag_b, held_b)) = (sag_and_held_motion(a), sag_and_held_motion(b));
    assert_eq!((sag_a, held_a), (sag_b, held_b));
    assert_eq!(held_b, 0.0);
}

/// What the block's probe, pressed 2 mm into the top and drawn 1 mm along +x at 10 mm/s
/// (the cut button off), feels and drags: (how far the surface vertex under the probe's
/// lowest point moved along x, the force along x, the force along z), m and N.
fn press_and_draw_on_block(friction: Option<(f64, f64)>) -> (f64, f64, f64) {
    let mut json: serde_json::Value = serde_json::from_str(&block_with_tools()).unwrap();
    if let Some((mu_s, mu_d)) = friction {
        json["model"]["branched-grid"]["materials"][0]["friction"] = serde_json::json!({ "static_coefficient": mu_s, "dynamic_coefficient": mu_d });
    }
    let mut g = build_grid(&json.to_string());
    let (mut commands, mut feedback) = (vec![ToolCommand::default(); 2], vec![ToolFeedback::default(); 2]);
    let mut at = |x: f64, z: f64, g: &mut BranchedGrid| {
        commands[1] = ToolCommand { pose: Pose::new(Vec3::new(x, 0.0, z), Quat::identity()), active: true, cut: false, grip: None };
        g.step(&commands, &mut feedback);
        feedback[1]
    };
    // The capsule's round end reaches its radius (6 mm) below its tip: from 0.5 mm above
    // the top (z = 8 mm) down to 2 mm into it.
    let (start, depth, radius) = (0.0145, 0.012, 0.006);
    for step in 0..700 {
        at(0.0, (start - 1e-5 * f64::from(step)).max(depth), &mut g);
    }
    let position = |g: &BranchedGrid, id| g.snapshot().vertices.iter().find(|v| v.id == id).map(|v| Vec3::new(v.position_m[0].into(), v.position_m[1].into(), v.position_m[2].into())).unwrap();
    let lowest = Vec3::new(0.0, 0.0, depth - radius);
    let under = g.snapshot().vertices.iter().min_by(|a, b| {
        let d = |v: &cutsim_sim::surface::SurfaceVertex| (Vec3::new(v.position_m[0].into(), v.position_m[1].into(), v.position_m[2].into()) - lowest).norm();
        d(a).total_cmp(&d(b))
    }).unwrap().id;
    let before = position(&g, under).x;
    let mut last = ToolFeedback::default();
    for step in 1..=100 {
        last = at(1e-5 * f64::from(step), depth, &mut g);
    }
    (position(&g, under).x - before, last.force_n.x, last.force_n.z)
}

#[test]
fn friction_drags_the_grids_surface_under_a_probe_drawn_sideways() {
    let mu_s = 0.5;
    let (held, along, normal) = press_and_draw_on_block(Some((mu_s, 0.4)));
    let (free, free_along, free_normal) = press_and_draw_on_block(None);
    println!("with friction the surface under the probe moved {:.3} mm of 1 mm ({along:.3} N along, {normal:.3} N normal); without {:.3} mm ({free_along:.3} N along, {free_normal:.3} N normal)", held * 1e3, free * 1e3);
    assert!(normal > 0.05, "the probe presses: {normal:.3} N");
    assert!(held > 0.8e-3, "within the static cone the surface sticks to the probe: {:.3} mm", held * 1e3);
    assert!(held < 1.02e-3, "never ahead of the probe: {:.3} mm", held * 1e3);
    assert!(free < 0.5 * held, "without friction the probe slides over it: {:.3} mm", free * 1e3);
    assert!(along < free_along - 0.01, "dragging the surface resists the draw: {along:.3} N, frictionless {free_along:.3} N");
    assert!(free_along - along <= mu_s * normal * 1.05, "within the static cone: {:.3} N for {:.3} N normal", free_along - along, normal);
}

/// The preconditioner changes how a solve gets to its answer, not the answer: the bar
/// sagging under gravity for 80 steps (so that the Cholesky factor in use is up to 32
/// steps old, and a fresh one from the worker is swapped in twice) ends where it does
/// with block Jacobi, to the solves' tolerance, in fewer iterations (the factor in a
/// fraction of them; the multigrid has few levels below this small bar's).
#[test]
fn cholesky_and_multigrid_preconditioning_reach_jacobis_answer_in_fewer_iterations() {
    let run = |preconditioner: &str| {
        let text = bar(true).replace(r#""cutting": {}"#, &format!(r#""cutting": {{}}, "solver": {{ "preconditioner": "{preconditioner}", "cg_tolerance": 1e-8, "cg_max_iterations": 1000 }}"#));
        let mut g = build_grid(&text);
        let mut feedback: [ToolFeedback; 0] = [];
        let mut iterations = 0;
        for _ in 0..80 {
            g.step(&[], &mut feedback);
            iterations += g.last_solve().0;
        }
        assert_eq!(g.counters().solver_cap_hits, 0, "{preconditioner}");
        (g.topology().nodes.x.clone(), iterations)
    };
    let (jacobi, jacobi_iterations) = run("jacobi");
    for preconditioner in ["multigrid", "cholesky"] {
        let (x, iterations) = run(preconditioner);
        let sag = jacobi.iter().map(|p| p.z).fold(f64::INFINITY, f64::min);
        assert!(sag < -0.0005, "the bar sags ({sag} m)");
        let differs = x.iter().zip(&jacobi).map(|(a, b)| (a - b).amax()).fold(0.0, f64::max);
        assert!(differs < 1e-7, "{preconditioner}: {differs} m from Jacobi's answer");
        assert!(iterations < jacobi_iterations, "{preconditioner}: {iterations} iterations against Jacobi's {jacobi_iterations}");
        if preconditioner == "cholesky" {
            assert!(iterations * 4 < jacobi_iterations, "a factor of a system at most 32 steps old: {iterations} iterations against Jacobi's {jacobi_iterations}");
        }
    }
}
