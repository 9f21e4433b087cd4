//! Multirate haptics (issue 18), in real time: the livers and the layered abdomen under a
//! multirate schedule, the haptic loop paced at 1 kHz on this thread and the
//! deformation on its worker thread, as a session runs them. Needs the shared data
//! (`$CUTSIM_DATA_DIR` or ../shared/data).
//!
//! Run: `cargo bench -p cutsim-sim --bench multirate` (add `-- --quick` for a short
//! run, e.g. `-- "liver L1"` for the cases whose name contains that text, and
//! `-- --preconditioner NAME` to override each case's).
//!
//! Per case, the script of `cutsim_sim::accuracy::schedule`: a probe pressed 4 mm into
//! the organ's broad top over 100 ms and held (1 s), then the scalpel drawn 4 cm through
//! that point 8 mm deep at 20 mm/s with the cut button held (2 s). Printed: the haptic
//! step's time (every step, the ones that swap a deformation result in included)
//! p50/p99/max; the deformation job's time (step, patch compliance, publishing) p50/p99
//! and the rate it sustains; steps that waited for a late job; the force on the probe
//! when held and the elements cut. The single-rate comparison at equal budget is
//! `cargo run --release -p cutsim-sim --bin accuracy-speed -- schedules`.

use cutsim_sim::accuracy::schedule::{Model, Script, run_real_time, scene_at};

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    let args: Vec<String> = std::env::args().skip(1).collect();
    let preconditioner = args.iter().position(|a| a == "--preconditioner").and_then(|i| args.get(i + 1).cloned());
    let filters: Vec<String> = args.iter().filter(|a| !a.starts_with("--") && Some(*a) != preconditioner.as_ref()).cloned().collect();
    println!("cutsim-sim multirate benchmark (real time: haptic loop at 1 kHz here, deformation on its worker thread)");
    println!("on {}", cutsim_sim::stats::machine_description());
    println!(
        "{:<44} | {:>8} {:>8} {:>8} | {:>9} {:>9} {:>7} | {:>6} | {:>7} {:>6}",
        "case", "haptic p50 ms", "p99", "max", "deform p50 ms", "p99", "rate Hz", "waits", "probe N", "cut"
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
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(scene);
        let mut model = match scene_at(&path, level, Some((every, preconditioner, cap))).and_then(|scene| Model::build(&scene)) {
            Ok(model) => model,
            Err(message) => {
                println!("{case:<44} refused at load: {message}");
                continue;
            }
        };
        let run = run_real_time(&mut model, if quick { Script::QUICK } else { Script::FULL });
        let stopped = if run.steps < run.planned { format!(" (stopped after {} of {} steps: {} late jobs)", run.steps, run.planned, run.late_jobs) } else { String::new() };
        println!(
            "{:<44} | {:>13.3} {:>8.3} {:>8.3} | {:>13.1} {:>9.1} {:>7.1} | {:>6} | {:>7.3} {:>6}{stopped}",
            case,
            run.step_p50_ms,
            run.step_p99_ms,
            run.step_max_ms,
            run.deformation_p50_ms.unwrap_or(f64::NAN),
            run.deformation_p99_ms.unwrap_or(f64::NAN),
            1000.0 / f64::from(every),
            run.late_jobs,
            run.held_force_n,
            run.removed_elements,
        );
        println!("{:<44}   {} deformation steps, {} at the CG cap", "", run.solves, run.cap_hits);
    }
}
