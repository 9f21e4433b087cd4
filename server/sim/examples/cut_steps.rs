//! Where a single-rate step's time goes around cuts: the schedule study's script
//! (`cutsim_sim::accuracy::schedule`: a probe pressed 4 mm into the body's broad top and
//! held for 1 s, then the scalpel drawn 4 cm through that point 8 mm deep with its cut
//! button held for 2 s) run unpaced on one thread, as fast as it steps, so that a
//! profiler sees only the physics. Prints the step-time percentiles of the holding and
//! the cutting phases, the conjugate-gradient iterations of each, every step that
//! removed voxels (with its grid and surface update times) and the steps over 1 ms
//! (each with its conjugate-gradient iterations).
//!
//! Run: `cargo run --release -p cutsim-sim --example cut_steps -- [SCENE] [LEVEL]`
//! (default `abdomen-layers.json` at level 3; the bundled scenes' file names). Needs the
//! shared data for the CT scenes (`$CUTSIM_DATA_DIR` or ../shared/data). The paced,
//! real-time measure of the same script under both schedules is
//! `cargo run --release -p cutsim-sim --bin accuracy-speed -- schedules`.

use cutsim_sim::accuracy::schedule::{Model, Script, scene_at};
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};
use std::time::Instant;

const SCRIPT: Script = Script::FULL;
const HOLD_STEPS: usize = SCRIPT.hold_steps;
const CUT_STEPS: usize = SCRIPT.cut_steps;

fn main() -> Result<(), String> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let scene = args.first().map_or("abdomen-layers.json", String::as_str);
    let level: u32 = args.get(1).map_or(Ok(3), |l| l.parse().map_err(|_| format!("level {l:?}: expected 0-4")))?;
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(scene);
    let Model::SingleRate(mut grid) = Model::build(&scene_at(&path, level, None)?)? else {
        return Err(format!("{scene}: expected a single-rate branched-grid scene"));
    };
    let top = grid.broad_top().ok_or("the body has no broad top to probe")?;
    let tools = grid.tools().to_vec();
    let mut commands = vec![ToolCommand::default(); tools.len()];
    let mut feedback = vec![ToolFeedback::default(); tools.len()];
    let mut times_us = Vec::with_capacity(HOLD_STEPS + CUT_STEPS);
    let mut iterations = [0u64; 2];
    let mut step_iterations = Vec::with_capacity(HOLD_STEPS + CUT_STEPS);
    let mut removal_steps = Vec::new();
    println!("{scene} at level {level}, single-rate, unpaced");
    for step in 0..HOLD_STEPS + CUT_STEPS {
        SCRIPT.commands(step, top, &tools, &mut commands);
        let before = grid.counters();
        let start = Instant::now();
        grid.step(&commands, &mut feedback);
        let us = start.elapsed().as_secs_f64() * 1e6;
        times_us.push(us);
        let after = grid.counters();
        iterations[usize::from(step >= HOLD_STEPS)] += after.solver_iterations - before.solver_iterations;
        step_iterations.push(after.solver_iterations - before.solver_iterations);
        if after.cut_updates != before.cut_updates {
            removal_steps.push(step);
            if let Some(u) = grid.last_update() {
                println!("step {step} removed {} voxels: {us:.0} µs (grid update {} µs, surface {} µs)", after.removed_elements - before.removed_elements, u.topology_ns / 1000, u.surface_ns / 1000);
            }
        }
    }
    let quantile = |range: std::ops::Range<usize>, q: f64| {
        let mut v = times_us[range].to_vec();
        v.sort_by(f64::total_cmp);
        v[((v.len() - 1) as f64 * q).round() as usize]
    };
    let all = 0..times_us.len();
    println!("holding: p50 {:.0} µs, p99 {:.0} µs, {:.2} CG iterations a step", quantile(0..HOLD_STEPS, 0.5), quantile(0..HOLD_STEPS, 0.99), iterations[0] as f64 / HOLD_STEPS as f64);
    println!("cutting: p50 {:.0} µs, p99 {:.0} µs, {:.2} CG iterations a step", quantile(HOLD_STEPS..times_us.len(), 0.5), quantile(HOLD_STEPS..times_us.len(), 0.99), iterations[1] as f64 / CUT_STEPS as f64);
    println!("whole run: p50 {:.0} µs, p99 {:.0} µs, max {:.0} µs", quantile(all.clone(), 0.5), quantile(all.clone(), 0.99), quantile(all, 1.0));
    let over: Vec<usize> = (0..times_us.len()).filter(|&s| times_us[s] > 1000.0).collect();
    let removals_over = over.iter().filter(|s| removal_steps.contains(s)).count();
    let listed: Vec<String> = over.iter().map(|&s| format!("{s}{}: {:.0} ({} it)", if removal_steps.contains(&s) { " (removal)" } else { "" }, times_us[s], step_iterations[s])).collect();
    println!("{} steps over 1 ms ({removals_over} of them removed voxels): {}", over.len(), listed.join(", "));
    Ok(())
}
