//! One physics step of the default scene (skin-patch) at three sizes — about 1k, 10k
//! and 40k nodes on the same 10 × 8 cm patch — with and without a cut in progress, for
//! both integrators.
//!
//! Run: `cargo bench -p cutsim-sim --bench step` (add `-- --quick` for a short run,
//! `-- 10k` for one size, `-- implicit` for one integrator).
//! Prints, per case, steps per second and the p50/p99/max step time measured over every
//! step, plus the time per stage; under each implicit case how its solves ended (those
//! stopped at the iteration cap above the tolerance, the largest final residual), and
//! under each cutting case what the cut did; then what assessing the steps costs (the physics thread
//! hands each step's tool samples to an assessor thread through a lock-free ring, as the
//! server does); then divan's statistics of the intact step.

use std::time::Instant;

use cutsim_sim::assessment::{Assessor, ToolSample};
use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::msm::{MassSpring, build_from_scene};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::stats::LatencyHistogram;
use cutsim_sim::tissue::Tissue;
use cutsim_sim::tool::{ToolCommand, ToolFeedback};

const SIZES: [(&str, u32, u32); 3] = [("1k", 40, 37), ("10k", 124, 115), ("40k", 248, 230)];

/// The default scene's tools: a scalpel, a probe and forceps (away unless a case moves them).
const TOOLS: usize = 3;

fn scene_text(cells_x: u32, cells_y: u32, integrator: &str) -> String {
    let base = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/skin-patch.json")).unwrap();
    base.replace(r#""resolution": [40, 37]"#, &format!(r#""resolution": [{cells_x}, {cells_y}]"#))
        .replace(r#"{ "symplectic-euler": { "substeps": 10 } }"#, integrator)
}

/// The default scene at a size, with the fewest stable substeps (explicit) or with CG.
fn build(cells_x: u32, cells_y: u32, explicit: bool) -> MassSpring {
    let make = |integrator: &str| {
        let scene = Scene::from_json_str(&scene_text(cells_x, cells_y, integrator), "bench", None).unwrap();
        let ModelSpec::Msm(spec) = &scene.model else { unreachable!("an msm scene") };
        build_from_scene(&scene, spec)
    };
    if !explicit {
        return make(r#"{ "implicit-euler": { "cg_max_iterations": 20, "cg_tolerance": 1e-4 } }"#).unwrap();
    }
    let probe = make(r#"{ "implicit-euler": {} }"#).unwrap();
    let substeps = (0.001 / probe.stability_bound().max_substep_s).ceil() as u32;
    make(&format!(r#"{{ "symplectic-euler": {{ "substeps": {substeps} }} }}"#)).unwrap()
}

fn blade_at(x: f64) -> [ToolCommand; TOOLS] {
    let mut commands = [ToolCommand::default(); TOOLS];
    commands[0] = ToolCommand { pose: Pose::new(Vec3::new(x, 0.0, -0.005), Quat::identity()), active: true, cut: true, grip: None };
    commands
}

fn probe_at(depth: f64) -> [ToolCommand; TOOLS] {
    let mut commands = [ToolCommand::default(); TOOLS];
    commands[1] = ToolCommand { pose: Pose::new(Vec3::new(0.01, 0.01, -depth), Quat::identity()), active: true, cut: false, grip: None };
    commands
}

struct Row {
    case: String,
    nodes: usize,
    substeps: String,
    histogram: LatencyHistogram,
    stages: cutsim_sim::msm::StageTimes,
    /// Mean CG iterations per step (implicit only).
    iterations: Option<f64>,
    /// How the solves ended (implicit only): what the mean iterations hide.
    convergence: Option<String>,
    /// What the cut did (cutting cases only): a change in it changes what the steps
    /// solve, so the times are comparable only where it is the same.
    cut: Option<String>,
}

/// Steps until `steps` are done, or (for `budget_s`) until the time budget is spent
/// after at least 50 steps.
fn measure(case: &str, model: &mut MassSpring, steps: usize, budget_s: Option<f64>, command: impl Fn(usize) -> [ToolCommand; TOOLS]) -> Row {
    let mut feedback = [ToolFeedback::default(); TOOLS];
    let mut histogram = LatencyHistogram::new();
    model.set_profiling(true);
    let start = Instant::now();
    let (mut iterations, mut solves, mut largest_residual) = (0u64, 0u64, 0.0f64);
    let cap_hits_before = model.counters().solver_cap_hits;
    for step in 0..steps {
        if budget_s.is_some_and(|b| step >= 50 && start.elapsed().as_secs_f64() > b) {
            break;
        }
        let c = command(step);
        let t = Instant::now();
        model.step(&c, &mut feedback);
        histogram.record(t.elapsed());
        if let Some((its, residual)) = model.last_solve() {
            largest_residual = largest_residual.max(residual);
            iterations += u64::from(its);
            solves += 1;
        }
    }
    let stages = model.stage_times().unwrap();
    let substeps = model.substeps().map_or_else(|| "CG".to_owned(), |s| s.to_string());
    let iterations = (solves > 0).then(|| iterations as f64 / solves as f64);
    let c = model.counters();
    let convergence = (solves > 0).then(|| format!("{} of {solves} solves stopped at the iteration cap; largest final relative residual {largest_residual:.1e}", c.solver_cap_hits - cap_hits_before));
    let cut = (c.cut_updates > 0).then(|| {
        format!(
            "{} updates, {:.1} mm of incision, {} left open, {} last piece{} uncut",
            c.cut_updates,
            c.incision_length_m * 1e3,
            c.reconstruction_fallbacks,
            c.uncut_last_pieces,
            if c.uncut_last_pieces == 1 { "" } else { "s" }
        )
    });
    Row { case: case.to_owned(), nodes: model.node_count(), substeps, histogram, stages, iterations, convergence, cut }
}

fn main() {
    let quick = std::env::args().any(|a| a == "--quick");
    // Sizes named on the command line (e.g. `10k`), else all.
    let only: Vec<String> = std::env::args().skip(1).filter(|a| SIZES.iter().any(|(label, ..)| label == a)).collect();
    // `explicit` or `implicit` on the command line: that integrator only.
    let integrators: Vec<bool> = [true, false].into_iter().filter(|&explicit| !std::env::args().any(|a| a == if explicit { "implicit" } else { "explicit" })).collect();
    println!("cutsim-sim step benchmark (release, one core): skin-patch 10 × 8 cm at three resolutions");
    println!("on {}", cutsim_sim::stats::machine_description());
    println!(
        "{:<34} {:>7} {:>6} {:>6} {:>10} {:>9} {:>9} {:>9}   stages per step (forces / contacts / integrate / cut)",
        "case", "nodes", "subst", "CG it", "steps/s", "p50 µs", "p99 µs", "max µs"
    );
    for (label, cx, cy) in SIZES.into_iter().filter(|(label, ..)| only.is_empty() || only.iter().any(|o| o == label)) {
        for &explicit in &integrators {
            let integrator = if explicit { "explicit" } else { "implicit" };
            let (steps, budget) = if quick { (200, Some(0.5)) } else { (5000, Some(3.0)) };
            let mut m = build(cx, cy, explicit);
            // Intact, with the probe lowered from 1 mm above onto the skin and pressing it
            // 1.5 mm deep (held at its tip face every step).
            let mut m2 = m.clone();
            for k in 0..50 {
                m2.step(&probe_at(-0.001 + 0.0025 * k as f64 / 50.0), &mut [ToolFeedback::default(); TOOLS]);
            }
            let rows = [
                measure(&format!("{label} {integrator} intact, probe in contact"), &mut m2, steps, budget, |_| probe_at(0.0015)),
                measure(&format!("{label} {integrator} cutting (4 cm at 0.1 m/s)"), &mut m, 400, None, |s| blade_at(-0.02 + 0.04 * s as f64 / 400.0)),
            ];
            for r in rows {
                let per = |ns: u64| ns as f64 / r.stages.steps.max(1) as f64 / 1e3;
                println!(
                    "{:<34} {:>7} {:>6} {:>6} {:>10.0} {:>9.1} {:>9.1} {:>9.1}   {:.1} / {:.1} / {:.1} / {:.1} µs",
                    r.case,
                    r.nodes,
                    r.substeps,
                    r.iterations.map_or_else(|| "-".to_owned(), |i| format!("{i:.1}")),
                    1e9 / r.histogram.mean_ns(),
                    r.histogram.quantile_ns(0.5) as f64 / 1e3,
                    r.histogram.quantile_ns(0.99) as f64 / 1e3,
                    r.histogram.max_ns() as f64 / 1e3,
                    per(r.stages.forces_ns),
                    per(r.stages.contacts_ns),
                    per(r.stages.integrate_ns),
                    per(r.stages.cut_ns),
                );
                if let Some(convergence) = &r.convergence {
                    println!("{:<34} the solves: {convergence}", "");
                }
                if let Some(cut) = &r.cut {
                    println!("{:<34} the cut: {cut}", "");
                }
            }
        }
    }
    assessment_cost();
    if !quick {
        divan::main();
    }
}

/// The 1k explicit cut again, each step's tool samples pushed into a ring that an
/// assessor thread drains and folds into the metrics (the server's arrangement): what
/// the push costs the physics thread, and what the assessor does per step on its own.
fn assessment_cost() {
    let scene = Scene::load(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/skin-patch.json"))).unwrap();
    let mut assessor = Assessor::new(scene.task(), TOOLS, 0.001);
    let mut model = build(40, 37, true);
    let (mut ring, mut drain) = rtrb::RingBuffer::<[ToolSample; TOOLS]>::new(1 << 12);
    let assessing = std::thread::spawn(move || {
        let mut observe = LatencyHistogram::new();
        loop {
            let done = drain.is_abandoned();
            while let Ok(samples) = drain.pop() {
                let t = Instant::now();
                assessor.observe(&samples);
                observe.record(t.elapsed());
            }
            if done {
                return (observe, assessor.assessment());
            }
            std::thread::sleep(std::time::Duration::from_millis(2));
        }
    });
    let (mut step_time, mut push_time) = (LatencyHistogram::new(), LatencyHistogram::new());
    let mut feedback = [ToolFeedback::default(); TOOLS];
    for step in 0..400 {
        let commands = blade_at(-0.02 + 0.04 * step as f64 / 400.0);
        let t = Instant::now();
        model.step(&commands, &mut feedback);
        step_time.record(t.elapsed());
        let t = Instant::now();
        let _ = ring.push(std::array::from_fn(|i| ToolSample::new(&commands[i], &feedback[i])));
        push_time.record(t.elapsed());
    }
    drop(ring);
    let (observe, assessment) = assessing.join().unwrap();
    let ns = |h: &LatencyHistogram, q: f64| h.quantile_ns(q) as f64;
    println!(
        "assessment, 1k explicit cutting: physics thread's push {:.0} ns mean, p99 {:.0} ns ({:.3} % of the mean step, {:.1} µs); assessor thread {:.0} ns mean, p99 {:.0} ns per step; score {:.1}, coverage {:.2}",
        push_time.mean_ns(),
        ns(&push_time, 0.99),
        100.0 * push_time.mean_ns() / step_time.mean_ns(),
        step_time.mean_ns() / 1e3,
        observe.mean_ns(),
        ns(&observe, 0.99),
        assessment.score.unwrap_or(f64::NAN),
        assessment.coverage.unwrap_or(f64::NAN),
    );
}

/// divan's view of one intact explicit step at each size.
#[divan::bench(args = ["1k", "10k", "40k"], sample_count = 20)]
fn intact_explicit_step(bencher: divan::Bencher, size: &str) {
    let (_, cx, cy) = SIZES.iter().copied().find(|s| s.0 == size).unwrap();
    let mut m = build(cx, cy, true);
    let c = probe_at(0.0);
    let mut fb = [ToolFeedback::default(); TOOLS];
    bencher.bench_local(|| m.step(&c, &mut fb));
}
