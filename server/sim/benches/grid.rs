//! The branched grid (issue 3): build time, one physics step and the cut update for the
//! liver scene (13k… here 38.6k voxels of 3 mm), the ~100k-voxel smooth liver and the
//! layered abdomen (157k voxels of seven tissues), at levels 1, 2 and 3, with the number of coarse elements, fine voxels and surface
//! triangles. Needs the shared data (`$CUTSIM_DATA_DIR` or ../shared/data).
//!
//! Run: `cargo bench -p cutsim-sim --bench grid` (add `-- --quick` for a short run, and
//! e.g. `-- "liver 3 mm L3"` for the cases whose name contains that text, and
//! `-- --preconditioner cholesky` to override the scenes' preconditioner).
//!
//! Per case: "probe" steps with a broad probe pressed into the top of the organ (where
//! it is broad: see `BranchedGrid::broad_top`)
//! (contacts every step, no cut); "cutting" steps with the scalpel drawn 4 cm along x
//! through that point, 8 mm deep, with the cut button held. For the cutting run the
//! steps that removed voxels (each holds one incremental topology and surface update)
//! are reported apart from the others, with the voxels removed per update. Last, how
//! the case's solves ended: those stopped at the iteration cap above the tolerance, and
//! the largest final relative residual.

use std::time::Instant;

use cutsim_sim::grid::{BranchedGrid, build_from_scene};
use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::stats::LatencyHistogram;
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};

/// The scene at `level`, built, and the build time; Err: the level is refused at load
/// (its message, e.g. a solve that needs more iterations than the scene allows).
fn build(scene_file: &str, level: u32, preconditioner: Option<&str>) -> Result<(BranchedGrid, f64), String> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(scene_file);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let spec = &mut json["model"]["branched-grid"];
    spec["level"] = level.into();
    if let Some(name) = preconditioner {
        spec["solver"]["preconditioner"] = name.into();
    }
    let text = json.to_string();
    let scene = Scene::from_json_str(&text, &path.display().to_string(), path.parent()).unwrap_or_else(|e| panic!("{e}"));
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!("a branched-grid scene") };
    let start = Instant::now();
    let grid = build_from_scene(&scene, spec).map_err(|e| e.to_string())?;
    Ok((grid, start.elapsed().as_secs_f64()))
}

fn command(tool: usize, position: Vec3, cut: bool) -> [ToolCommand; 2] {
    let mut c = [ToolCommand::default(); 2];
    c[tool] = ToolCommand { pose: Pose::new(position, Quat::identity()), active: true, cut, grip: None };
    c
}

fn micros(ns: u64) -> f64 {
    ns as f64 / 1e3
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // Any other argument (not cargo's --bench) picks the cases whose name contains it.
    // `--preconditioner NAME` overrides the scenes' (jacobi, multigrid or cholesky).
    let args: Vec<String> = std::env::args().skip(1).collect();
    let preconditioner = args.iter().position(|a| a == "--preconditioner").and_then(|i| args.get(i + 1).cloned());
    let filters: Vec<String> = args.iter().filter(|a| !a.starts_with("--") && Some(*a) != preconditioner.as_ref()).cloned().collect();
    println!("cutsim-sim branched-grid benchmark (release, one core)");
    println!("on {}", cutsim_sim::stats::machine_description());
    println!(
        "{:<22} {:>8} {:>8} {:>7} {:>8} {:>7} | {:>8} {:>8} {:>8} {:>5} | {:>8} {:>8} {:>8} {:>7} {:>8}",
        "scene", "voxels", "elements", "nodes", "tris", "build s", "probe p50", "p99", "max", "CG", "cut p50", "p99", "max", "updates", "vox/upd"
    );
    for (scene, label) in [("liver.json", "liver 3 mm"), ("liver-smooth.json", "liver-smooth 2.2 mm"), ("abdomen-layers.json", "abdomen-layers 3 mm")] {
        for level in [1, 2, 3] {
            let case = format!("{label} L{level}");
            if !filters.is_empty() && !filters.iter().any(|f| case.contains(f.as_str())) {
                continue;
            }
            let (mut grid, build_s) = match build(scene, level, preconditioner.as_deref()) {
                Ok(built) => built,
                Err(message) => {
                    println!("{case:<22} refused at load: {message}");
                    continue;
                }
            };
            let top = grid.broad_top().expect("a broad top");
            let mut feedback = [ToolFeedback::default(); 2];
            let (elements, nodes) = (grid.topology().elements.alive_count(), grid.topology().nodes.alive_count());
            let triangles = grid.surface().live_triangles().count();
            let voxels = grid.voxel_count();

            // A broad probe pressed 4 mm into the top, then held there.
            let probe_steps = if quick { 200 } else { 1500 };
            let mut probe = LatencyHistogram::new();
            let mut iterations = 0u64;
            let mut largest_residual = 0.0f64;
            let cap_hits_before_probe = grid.counters().solver_cap_hits;
            for step in 0..probe_steps {
                let depth = 0.004 * (step as f64 / 100.0).min(1.0);
                let c = command(1, Vec3::new(top.x, top.y, top.z + 0.005 - depth), false);
                let t = Instant::now();
                grid.step(&c, &mut feedback);
                probe.record(t.elapsed());
                iterations += u64::from(grid.last_solve().0);
                largest_residual = largest_residual.max(grid.last_solve().1);
            }
            let cap_hits_probing = grid.counters().solver_cap_hits - cap_hits_before_probe;

            // The scalpel across the top, 8 mm deep, at 0.1 m/s.
            let cut_steps = if quick { 200 } else { 600 };
            let (mut plain, mut updating) = (LatencyHistogram::new(), LatencyHistogram::new());
            let removed_before = grid.counters().removed_elements;
            let mut parts = [0u64; 3];
            let mut worst_update = 0u64;
            for step in 0..cut_steps {
                let x = -0.02 + 0.04 * step as f64 / cut_steps as f64;
                let c = command(0, Vec3::new(top.x + x, top.y, top.z - 0.008), true);
                let updates = grid.counters().cut_updates;
                let t = Instant::now();
                grid.step(&c, &mut feedback);
                let elapsed = t.elapsed();
                largest_residual = largest_residual.max(grid.last_solve().1);
                if grid.counters().cut_updates > updates {
                    updating.record(elapsed);
                    let u = grid.last_update().unwrap();
                    parts[0] += u.topology_ns;
                    parts[1] += u.surface_ns;
                    parts[2] += u.other_ns;
                    worst_update = worst_update.max(u.topology_ns + u.surface_ns + u.other_ns);
                } else {
                    plain.record(elapsed);
                }
            }
            let removed = grid.counters().removed_elements - removed_before;
            let cap_hits_cutting = grid.counters().solver_cap_hits - cap_hits_before_probe - cap_hits_probing;
            println!(
                "{:<22} {:>8} {:>8} {:>7} {:>8} {:>7.2} | {:>8.0} {:>8.0} {:>8.0} {:>5.1} | {:>8.0} {:>8.0} {:>8.0} {:>7} {:>8.1}",
                case,
                voxels,
                elements,
                nodes,
                triangles,
                build_s,
                micros(probe.quantile_ns(0.5)),
                micros(probe.quantile_ns(0.99)),
                micros(probe.max_ns()),
                iterations as f64 / probe_steps as f64,
                micros(updating.quantile_ns(0.5)),
                micros(updating.quantile_ns(0.99)),
                micros(updating.max_ns()),
                updating.count(),
                removed as f64 / updating.count().max(1) as f64,
            );
            let n = updating.count().max(1) as f64;
            println!(
                "{:<22} update itself: mean {:.0} µs (topology {:.0} + surface {:.0} + other {:.0}), max {:.0} µs; steps without an update while cutting: p50 {:.0}, p99 {:.0}, max {:.0} µs",
                "",
                (parts.iter().sum::<u64>()) as f64 / n / 1e3,
                parts[0] as f64 / n / 1e3,
                parts[1] as f64 / n / 1e3,
                parts[2] as f64 / n / 1e3,
                micros(worst_update),
                micros(plain.quantile_ns(0.5)),
                micros(plain.quantile_ns(0.99)),
                micros(plain.max_ns())
            );
            println!(
                "{:<22} solves stopped at the iteration cap above the tolerance: {cap_hits_probing} of {probe_steps} probing, {cap_hits_cutting} of {cut_steps} cutting; largest final relative residual {largest_residual:.1e}",
                ""
            );
        }
    }
}
