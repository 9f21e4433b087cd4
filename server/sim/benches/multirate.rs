//! Multirate haptics (issue 18), in real time: the livers and the layered abdomen under a
//! multirate schedule, the haptic loop paced at 1 kHz on this thread and the
//! deformation on its worker thread, as a session runs them. Needs the shared data
//! (`$CUTSIM_DATA_DIR` or ../shared/data).
//!
//! Run: `cargo bench -p cutsim-sim --bench multirate` (add `-- --quick` for a short
//! run, e.g. `-- "liver L1"` for the cases whose name contains that text, and
//! `-- --preconditioner NAME` to override each case's).
//!
//! Per case: a broad probe pressed 4 mm into the organ's broad top over 100 ms and held
//! (1 s), then the scalpel drawn 4 cm through that point 8 mm deep at 20 mm/s with the
//! cut button held (2 s). Printed: the haptic step's time (every step, the ones that
//! swap a deformation result in included) p50/p99/max; the deformation job's time
//! (step, patch compliance, publishing) p50/p99/max and the rate it sustains; steps
//! that waited for a late job; the force on the probe when held and the voxels cut.

use std::time::{Duration, Instant};

use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::multirate::Multirate;
use cutsim_sim::scene::{ModelSpec, MultirateSpec, Scene, ScheduleSpec};
use cutsim_sim::stats::LatencyHistogram;
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};

/// The scene at `level` with deformation every `every` ms, with `preconditioner` (block
/// Jacobi needs far more iterations than a scene's cap at a deformation step of tens of
/// ms) and CG cap `cap` (None: the scene's).
fn build(scene_file: &str, level: u32, every: u32, preconditioner: &str, cap: Option<u32>) -> Result<Multirate, String> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(scene_file);
    let text = std::fs::read_to_string(&path).unwrap();
    let mut json: serde_json::Value = serde_json::from_str(&text).unwrap();
    let spec = &mut json["model"]["branched-grid"];
    spec["level"] = level.into();
    spec["solver"]["preconditioner"] = preconditioner.into();
    if let Some(cap) = cap {
        spec["solver"]["cg_max_iterations"] = cap.into();
    }
    spec["schedule"] = serde_json::json!({ "multirate": { "deformation_every_steps": every } });
    let scene = Scene::from_json_str(&json.to_string(), &path.display().to_string(), path.parent()).map_err(|e| e.to_string())?;
    let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!("a branched-grid scene") };
    let ScheduleSpec::Multirate(schedule) = spec.schedule else { unreachable!("set above") };
    let schedule: MultirateSpec = schedule;
    cutsim_sim::multirate::build_from_scene(&scene, &schedule).map_err(|e| e.to_string())
}

fn command(tool: usize, position: Vec3, cut: bool) -> [ToolCommand; 2] {
    let mut c = [ToolCommand::default(); 2];
    c[tool] = ToolCommand { pose: Pose::new(position, Quat::identity()), active: true, cut };
    c
}

fn ms(ns: u64) -> f64 {
    ns as f64 / 1e6
}

/// Sleeps until `deadline`, spinning its last 0.2 ms (a sleep overshoots).
fn wait_until(deadline: Instant) {
    loop {
        let now = Instant::now();
        if now >= deadline {
            return;
        }
        let left = deadline - now;
        if left > Duration::from_micros(300) {
            std::thread::sleep(left - Duration::from_micros(200));
        } else {
            std::hint::spin_loop();
        }
    }
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let args: Vec<String> = std::env::args().skip(1).collect();
    let preconditioner = args.iter().position(|a| a == "--preconditioner").and_then(|i| args.get(i + 1).cloned());
    let filters: Vec<String> = args.iter().filter(|a| !a.starts_with("--") && Some(*a) != preconditioner.as_ref()).cloned().collect();
    println!("cutsim-sim multirate benchmark (real time: haptic loop at 1 kHz here, deformation on its worker thread)");
    println!(
        "{:<44} | {:>8} {:>8} {:>8} | {:>9} {:>9} {:>9} {:>7} | {:>6} | {:>7} {:>6}",
        "case", "haptic p50 ms", "p99", "max", "deform p50 ms", "p99", "max", "rate Hz", "waits", "probe N", "cut"
    );
    // (scene, label, level, deformation every N ms, preconditioner, CG cap if not the
    // scene's): the multigrid V-cycle is the cheaper on the liver at level 1 (1.5 ms an
    // iteration against the Cholesky factor's 5), the factor the only one that converges
    // within a cap on the layered abdomen's stiff layers at these steps.
    for (scene, label, level, every, default_preconditioner, cap) in [
        ("liver.json", "liver", 1, 33, "multigrid", None),
        ("liver.json", "liver", 1, 50, "multigrid", None),
        ("liver.json", "liver", 2, 10, "multigrid", None),
        ("liver.json", "liver", 2, 33, "multigrid", None),
        ("liver-smooth.json", "liver-smooth", 2, 33, "cholesky", None),
        ("liver-smooth.json", "liver-smooth", 1, 33, "multigrid", None),
        ("abdomen-layers.json", "abdomen-layers", 2, 33, "cholesky", Some(400)),
        ("abdomen-layers.json", "abdomen-layers", 3, 10, "cholesky", None),
        ("abdomen-layers.json", "abdomen-layers", 3, 20, "cholesky", Some(200)),
    ] {
        let preconditioner = preconditioner.as_deref().unwrap_or(default_preconditioner);
        let case = match cap {
            Some(cap) => format!("{label} L{level} every {every} ms {preconditioner} CG≤{cap}"),
            None => format!("{label} L{level} every {every} ms {preconditioner}"),
        };
        if !filters.is_empty() && !filters.iter().any(|f| case.contains(f.as_str())) {
            continue;
        }
        let mut model = match build(scene, level, every, preconditioner, cap) {
            Ok(model) => model,
            Err(message) => {
                println!("{case:<44} refused at load: {message}");
                continue;
            }
        };
        let top = model.with_grid(|g| g.broad_top()).expect("a broad top");
        let (hold_steps, cut_steps) = if quick { (300, 500) } else { (1000, 2000) };
        let mut feedback = [ToolFeedback::default(); 2];
        let (mut haptic, mut deformation) = (LatencyHistogram::new(), LatencyHistogram::new());
        let start = Instant::now();
        let mut held_force = 0.0;
        for step in 0..hold_steps + cut_steps {
            let c = if step < hold_steps {
                let depth = 0.004 * (step as f64 / 100.0).min(1.0);
                command(1, Vec3::new(top.x, top.y, top.z + 0.005 - depth), false)
            } else {
                let x = -0.02 + 0.04 * (step - hold_steps) as f64 / cut_steps as f64;
                command(0, Vec3::new(top.x + x, top.y, top.z - 0.008), true)
            };
            wait_until(start + Duration::from_millis(step as u64));
            let t = Instant::now();
            model.step(&c, &mut feedback);
            haptic.record(t.elapsed());
            if step % every as usize == 0 && step > 0 {
                deformation.record_ns(model.last_deformation_ns());
            }
            if step + 1 == hold_steps {
                held_force = feedback[1].force_n.norm();
            }
        }
        let rate = 1000.0 / f64::from(every);
        println!(
            "{:<44} | {:>13.3} {:>8.3} {:>8.3} | {:>13.1} {:>9.1} {:>9.1} {:>7.1} | {:>6} | {:>7.3} {:>6}",
            case,
            ms(haptic.quantile_ns(0.5)),
            ms(haptic.quantile_ns(0.99)),
            ms(haptic.max_ns()),
            ms(deformation.quantile_ns(0.5)),
            ms(deformation.quantile_ns(0.99)),
            ms(deformation.max_ns()),
            rate,
            model.deformation_waits(),
            held_force,
            model.counters().removed_elements,
        );
        let c = model.counters();
        println!("{:<44}   {} deformation steps: {:.1} CG iterations each, {} at the cap", "", c.solves, c.solver_iterations as f64 / c.solves.max(1) as f64, c.solver_cap_hits);
    }
}
