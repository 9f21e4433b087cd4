//! `cutsim-server run`: a scene in lockstep, optionally driven by a cut script.

use std::io::{IsTerminal, Write};
use std::path::PathBuf;
use std::process::ExitCode;

use clap::Args;
use cutsim_sim::runner::{self, Progress, RunReport};
use cutsim_sim::scene::{Scene, resolve_scene_path};
use cutsim_sim::script::CutScript;

#[derive(Args)]
pub struct RunArgs {
    /// Bundled scene name (e.g. skin-patch) or path to a scene file. Default: the
    /// script's scene.
    pub scene: Option<String>,
    /// Steps to run (default: the script's length, or 1000 without a script).
    #[arg(long)]
    pub steps: Option<u64>,
    /// Cut script (JSON) giving tool poses by step and expectations on the report.
    #[arg(long)]
    pub script: Option<PathBuf>,
    /// Print the report as one JSON object on stdout.
    #[arg(long)]
    pub json: bool,
}

/// Exit codes: 0 success, 1 an expectation failed, 2 bad input.
pub fn run(args: &RunArgs, scene_dirs: &[PathBuf]) -> ExitCode {
    match try_run(args, scene_dirs) {
        Ok(report) => {
            if args.json {
                println!("{}", serde_json::to_string(&report).expect("report is JSON"));
            } else {
                print_report(&report);
            }
            if report.passed { ExitCode::SUCCESS } else { ExitCode::from(1) }
        }
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::from(2)
        }
    }
}

fn try_run(args: &RunArgs, scene_dirs: &[PathBuf]) -> Result<RunReport, String> {
    let script = args.script.as_deref().map(CutScript::load).transpose().map_err(|e| e.to_string())?;
    let scene_name = args
        .scene
        .clone()
        .or_else(|| script.as_ref().and_then(|s| s.scene.clone()))
        .ok_or("give a scene (a bundled name or a path), or a script that names one")?;
    let scene_path = resolve_scene_path(&scene_name, scene_dirs).map_err(|e| e.to_string())?;
    let scene = Scene::load(&scene_path).map_err(|e| e.to_string())?;
    let mut tissue = cutsim_sim::build_tissue(&scene).map_err(|e| e.to_string())?;
    if let Some(chosen) = tissue.fidelity() {
        eprintln!("{}", chosen.summary);
    }
    let compiled = match (&script, &args.script) {
        (Some(s), Some(path)) => Some(
            s.compile(tissue.tools(), tissue.time_step_s(), &path.display().to_string()).map_err(|e| e.to_string())?,
        ),
        _ => None,
    };
    let steps = args.steps.or(compiled.as_ref().map(|c| c.steps)).unwrap_or(1000);
    let mut progress = ProgressPrinter::new(!args.json || std::io::stderr().is_terminal());
    let report = runner::run(tissue.as_mut(), &scene.name, scene.task(), compiled.as_ref(), steps, (steps / 20).max(1), |p| progress.show(p));
    progress.finish();
    Ok(report)
}

/// Progress on stderr: a bar redrawn in place on a terminal, plain lines otherwise.
struct ProgressPrinter {
    enabled: bool,
    terminal: bool,
}

impl ProgressPrinter {
    fn new(enabled: bool) -> Self {
        Self { enabled, terminal: std::io::stderr().is_terminal() }
    }

    fn show(&mut self, p: &Progress) {
        if !self.enabled {
            return;
        }
        let fraction = if p.total == 0 { 1.0 } else { p.step as f64 / p.total as f64 };
        if self.terminal {
            let filled = (fraction * 30.0).round() as usize;
            eprint!(
                "\r[{}{}] {:>3.0}%  step {}/{}  cuts {}  max force {:.3} N",
                "#".repeat(filled),
                " ".repeat(30 - filled),
                fraction * 100.0,
                p.step,
                p.total,
                p.cuts,
                p.max_tool_force_n
            );
            let _ = std::io::stderr().flush();
        } else {
            eprintln!("progress: step {}/{} ({:.0}%), cuts {}, max force {:.3} N", p.step, p.total, fraction * 100.0, p.cuts, p.max_tool_force_n);
        }
    }

    fn finish(&mut self) {
        if self.enabled && self.terminal {
            eprintln!();
        }
    }
}

fn print_report(r: &RunReport) {
    println!("scene            {} ({})", r.scene, r.model);
    println!("steps            {} ({:.3} s simulated, {:.3} s wall, {:.0} steps/s)", r.steps, r.simulated_time_s, r.wall_time_s, r.steps_per_second);
    println!("step time        p50 {:.1} µs, p99 {:.1} µs, max {:.1} µs", r.step_time_p50_us, r.step_time_p99_us, r.step_time_max_us);
    let c = &r.counters;
    if c.solves > 0 {
        println!(
            "solver           {:.1} iterations per solve, {} of {} solves at their cap, residual max {:.1e} (last {:.1e})",
            c.solver_iterations as f64 / c.solves as f64,
            c.solver_cap_hits,
            c.solves,
            c.solver_max_residual,
            c.solver_last_residual
        );
    }
    if c.solver_waits > 0 || c.solver_factor_failures > 0 {
        println!("solver work      {} steps waited for background work, {} factorizations failed", c.solver_waits, c.solver_factor_failures);
    }
    println!("cuts             {} ({} updates, {} fallbacks)", r.cuts, r.cut_updates, r.reconstruction_fallbacks);
    for f in &r.fallbacks {
        println!("  fallback at step {}: {}", f.step, f.reason);
    }
    if c.uncut_last_pieces > 0 {
        println!("  last pieces left uncut (the incision ends short of where the blade left): {}", c.uncut_last_pieces);
    }
    println!("removed elements {}", r.removed_elements);
    println!("incision length  {:.2} mm", r.incision_length_m * 1e3);
    println!("pieces           {}", r.pieces);
    println!("max tool force   {:.4} N", r.max_tool_force_n);
    println!("surface          {} vertices, {} triangles (topology version {})", r.surface_vertices, r.surface_triangles, r.topology_version);
    println!("state_hash       {}", r.state_hash);
    for e in &r.expectations {
        println!("expect {:<26} {}  expected {}, got {}", e.name, if e.passed { "PASS" } else { "FAIL" }, e.expected, e.actual);
    }
    if !r.expectations.is_empty() {
        println!("result           {}", if r.passed { "PASS" } else { "FAIL" });
    }
}

