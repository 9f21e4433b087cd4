//! The speed–accuracy study (docs/accuracy-speed.md).
//!
//! ```text
//! accuracy-speed [--quick] [--out DIR]    sweep the settings on the reference cantilever and
//!                                         the bundled scenes; write DIR/accuracy-speed.{md,svg,json}
//!                                         (DIR: docs)
//! accuracy-speed schedules [--quick] [--out DIR]
//!                                         single-rate against multirate at equal budget on
//!                                         the bundled volumetric scenes, in real time; rewrite
//!                                         that section of DIR/accuracy-speed.md (the sweep
//!                                         writes it too)
//! accuracy-speed stability [--reduced] [--out DIR]
//!                                         the stability sweep (full, or the test's reduced one);
//!                                         write DIR/stability.md
//! accuracy-speed static SCENE             a bundled scene's reference and the linear static
//!                                         error of each level against it, printed
//! accuracy-speed export-problems DIR      write the reference problems' meshes for tools/reference
//! ```
//! Run it in release: `cargo run --release -p cutsim-sim --bin accuracy-speed`.

use std::path::{Path, PathBuf};
use std::process::ExitCode;

use cutsim_sim::accuracy::problems::{G, Load, Problem, held_samples, in_held_piece, problems, sample_displacements, with_gravity_down};
use cutsim_sim::accuracy::reference::{Weighting, field_error, load_reference, solve_linear};
use cutsim_sim::accuracy::report::{ErrorTable, LoadRow, Measured, MembraneStudy, Row, SceneStudy, markdown, svg};
use cutsim_sim::accuracy::sweep::{Setting, build_grid, cantilever_frequency, own_reference, session_error, static_error, time_probe, tip_nodes};
use cutsim_sim::quantity::DampingPerS;
use cutsim_sim::grid::support::held_pieces;
use cutsim_sim::grid::topology::NONE;
use cutsim_sim::math::Vec3;
use cutsim_sim::scene::{MassSpec, ModelSpec, Scene, SupportSpec, VolumetricSpec};

const USAGE: &str = "usage: accuracy-speed [--quick] [--out DIR] | accuracy-speed schedules [--quick] [--out DIR] | accuracy-speed stability [--reduced] [--out DIR] | accuracy-speed supports [--out DIR] | accuracy-speed static SCENE | accuracy-speed export-problems DIR";

fn main() -> ExitCode {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.first().map(String::as_str) {
        Some("export-problems") => match args.get(1) {
            Some(dir) => export_problems(Path::new(dir)),
            None => Err("export-problems needs the directory to write into".to_string()),
        },
        Some("stability") => {
            let rest: Vec<String> = args[1..].iter().filter(|a| *a != "--reduced").cloned().collect();
            parse_sweep_args(&rest).and_then(|(_, out)| stability(args.iter().any(|a| a == "--reduced"), &out))
        }
        Some("schedules") => parse_sweep_args(&args[1..]).and_then(|(quick, out)| schedules(quick, &out)),
        Some("supports") => parse_sweep_args(&args[1..]).and_then(|(_, out)| supports(&out)),
        Some("static") => match args.get(1) {
            Some(scene) => static_errors(scene),
            None => Err("static needs a bundled scene's name (server/scenes/NAME.json)".to_string()),
        },
        Some("-h" | "--help") => {
            println!("{USAGE}");
            Ok(())
        }
        _ => parse_sweep_args(&args).and_then(|(quick, out)| sweep(quick, &out)),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

fn parse_sweep_args(args: &[String]) -> Result<(bool, PathBuf), String> {
    let (mut quick, mut out) = (false, Path::new(env!("CARGO_MANIFEST_DIR")).join("../../docs"));
    let mut i = 0;
    while i < args.len() {
        match args[i].as_str() {
            "--quick" => quick = true,
            "--out" => {
                i += 1;
                out = PathBuf::from(args.get(i).ok_or("--out needs a directory")?);
            }
            other => return Err(format!("unknown argument {other:?}\n{USAGE}")),
        }
        i += 1;
    }
    Ok((quick, out))
}

fn export_problems(dir: &Path) -> Result<(), String> {
    std::fs::create_dir_all(dir).map_err(|e| format!("{}: {e}", dir.display()))?;
    for problem in problems().map_err(|e| e.to_string())? {
        let export = problem.export().map_err(|e| e.to_string())?;
        let path = dir.join(format!("{}.json", problem.name));
        std::fs::write(&path, export.to_string()).map_err(|e| format!("{}: {e}", path.display()))?;
        eprintln!("wrote {} ({} nodes, {} hexahedra)", path.display(), export["nodes"].as_array().map_or(0, |a| a.len()), export["hexes"].as_array().map_or(0, |a| a.len()));
    }
    Ok(())
}

/// A bundled scene as a gravity problem (the scene's own gravity, else 9.81 m/s² down).
fn bundled_problem(name: &'static str) -> Result<Problem, String> {
    let mut scene = bundled_scene(name)?;
    if scene.gravity_m_per_s2.is_none() {
        scene = with_gravity_down(&scene, G);
    }
    Ok(Problem { name, summary: "", scene, load: Load::Gravity, frequency: false, quadratic: false, mixed: false, sample_stride: 16 })
}

fn bundled_scene(name: &str) -> Result<Scene, String> {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(format!("{name}.json"));
    Scene::load(&path).map_err(|e| e.to_string())
}

/// What a scene's errors are measured against.
struct SceneReference {
    samples: Vec<(usize, usize)>,
    /// None: the static problem has no solution (parts of the body are not held).
    field: Option<Vec<Vec3>>,
    label: String,
    frequency_hz: Option<f64>,
    /// The level whose mesh the reference was solved on (0 for scikit-fem's, which are
    /// on the level-0 mesh).
    level: u32,
}

/// The scikit-fem reference where there is one (its finest solution), else our linear
/// static solution at level 0 (level 1 above 200,000 voxels).
fn scene_reference(problem: &Problem) -> Result<SceneReference, String> {
    if let Ok(reference) = load_reference(problem) {
        let (label, finest) = reference.finest();
        return Ok(SceneReference {
            field: Some(finest.displacements()),
            label: format!("{label} on the level-0 mesh ({})", reference.generator),
            frequency_hz: finest.first_frequency_hz,
            samples: reference.samples,
            level: 0,
        });
    }
    let level0 = problem.parts(0).map_err(|e| e.to_string())?;
    let voxels = level0.topo.material.iter().filter(|&&m| m != 0).count();
    // Level 1 merges layers thinner than its elements (the abdomen's skin, 1–2 voxels,
    // 50 times stiffer than the fat beneath: its level 1 is 49 % off its level 0), so it is
    // no reference for them: level 0 up to 200,000 voxels (a few minutes' solve).
    let level = if voxels <= 200_000 { 0 } else { 1 };
    let parts = if level == 0 { level0 } else { problem.parts(1).map_err(|e| e.to_string())? };
    // Pieces not connected to a hold have no static answer: left out (and said so).
    let held = held_pieces(&parts.topo);
    let free_voxels = (0..parts.topo.material.len()).filter(|&v| parts.topo.material[v] != 0 && parts.topo.voxel_element[v] != NONE && !in_held_piece(&parts.topo, &held, v)).count();
    let samples = held_samples(&parts.topo, &problem.samples(&parts));
    let free = if free_voxels == 0 {
        String::new()
    } else {
        format!(
            "; {free_voxels} of the {voxels} voxels ({:.1} %) lie in pieces that touch no held region (organs the label map does not join to the held body), which have no static equilibrium under gravity: they carry no load in the static problems, and the errors are over the {} sample points of the held pieces",
            100.0 * free_voxels as f64 / voxels as f64,
            samples.len()
        )
    };
    let (field, label) = match own_reference(problem, level, &samples) {
        Ok(field) => (
            Some(field),
            format!(
                "our linear static solution at level {level} ({}), the finest solved here; level 0 equals scikit-fem Hex1–P0 on the reference problems to 1e-11{free}",
                if level == 0 { format!("{voxels} voxels") } else { format!("{voxels} voxels are too many for a level-0 solve here") }
            ),
        ),
        Err(e) => (None, format!("none: the static problem of the held pieces has no solution here ({e}){free}")),
    };
    Ok(SceneReference { samples, field, label, frequency_hz: None, level })
}

/// The bundled volumetric scenes the study covers.
const STUDIED_SCENES: [&str; 4] = ["liver", "u-tube", "liver-smooth", "abdomen-layers"];

/// The gravity problem the study measures a bundled scene by: the liver's is the
/// reference problem scikit-fem solved (`liver-gravity`), the others' their scene under
/// gravity.
fn study_problem(name: &str) -> Result<Problem, String> {
    let name = *STUDIED_SCENES.iter().find(|s| **s == name).ok_or_else(|| format!("{name:?} is not a bundled volumetric scene; one of {}", STUDIED_SCENES.join(", ")))?;
    if name == "liver" {
        return problems().map_err(|e| e.to_string())?.into_iter().find(|p| p.name == "liver-gravity").ok_or_else(|| "the liver-gravity problem".to_string());
    }
    bundled_problem(name)
}

/// One scene's reference and the static error of each of its levels from 1 (no timing,
/// no session), printed: what the sweep measures them against, in minutes.
fn static_errors(name: &str) -> Result<(), String> {
    let problem = study_problem(name)?;
    let started = std::time::Instant::now();
    let SceneReference { samples, field, label, .. } = scene_reference(&problem)?;
    println!("{}: reference {label} ({} samples, {:.1} s)", problem.name, samples.len(), started.elapsed().as_secs_f64());
    let field = field.ok_or("no reference: no errors to measure")?;
    for level in 1..=4 {
        match static_error(&problem, level, Weighting::Condensed, &samples, &field) {
            Ok(e) => println!("level {level}: static error {:.2} % ({:.1} s)", 100.0 * e, started.elapsed().as_secs_f64()),
            Err(e) => println!("level {level}: {e}"),
        }
    }
    Ok(())
}

struct Progress {
    done: usize,
    total: usize,
    started: std::time::Instant,
}

impl Progress {
    fn tick(&mut self, what: &str) {
        self.done += 1;
        eprintln!("[{:>3}/{}] {:>6.1} s  {what}", self.done, self.total, self.started.elapsed().as_secs_f64());
    }
}

/// A study: its name, its problem (the scene under gravity), the scene as users run it
/// (timed), its settings, and the levels of its weighting comparison.
type Plan = (String, Problem, Scene, Vec<Setting>, Vec<u32>);

fn sweep(quick: bool, out: &Path) -> Result<(), String> {
    let (warmup, steps) = if quick { (20, 80) } else { (50, 300) };
    let all = problems().map_err(|e| e.to_string())?;
    let cantilever = all.iter().find(|p| p.name == "cantilever-gravity").expect("the cantilever problem").clone();
    let liver = all.iter().find(|p| p.name == "liver-gravity").expect("the liver problem").clone();

    let dt = 0.001;
    // (study, problem (its scene under gravity), the scene as users run it (timed), settings,
    // levels for the weighting comparison).
    let mut plans: Vec<Plan> = Vec::new();
    let mut cantilever_settings = Vec::new();
    for level in 0..=3 {
        for mass in [MassSpec::Lumped, MassSpec::Consistent] {
            for cg in [100, 400] {
                cantilever_settings.push(Setting::new(level, mass, cg, dt));
            }
        }
        cantilever_settings.push(Setting::new(level, MassSpec::Consistent, 400, 0.00025));
        if level <= 1 {
            cantilever_settings.push(Setting::new(level, MassSpec::Lumped, 400, dt).multigrid());
        }
    }
    plans.push(("cantilever".into(), cantilever.clone(), cantilever.scene.clone(), cantilever_settings, vec![]));
    let scene_settings = |levels: &[u32], cg_default: u32| {
        let mut v = Vec::new();
        for &level in levels {
            for mass in [MassSpec::Lumped, MassSpec::Consistent] {
                v.push(Setting::new(level, mass, cg_default, dt));
            }
            v.push(Setting::new(level, MassSpec::Lumped, cg_default, dt).multigrid());
            v.push(Setting::new(level, MassSpec::Lumped, 10, dt));
        }
        v
    };
    plans.push(("liver".into(), liver.clone(), bundled_scene("liver")?, scene_settings(&[0, 1, 2, 3], 60), vec![1, 2, 3]));
    for name in ["u-tube", "liver-smooth", "abdomen-layers"] {
        let levels: &[u32] = if name == "u-tube" { &[0, 1, 2] } else { &[1, 2, 3] };
        let weighting = if name == "u-tube" { vec![1, 2] } else { vec![2, 3] };
        plans.push((name.into(), study_problem(name)?, bundled_scene(name)?, scene_settings(levels, 60), weighting));
    }
    let mut progress = Progress { done: 0, total: plans.iter().map(|p| p.3.len() + p.4.len() + 1).sum::<usize>() + all.len() + 2, started: std::time::Instant::now() };

    // The level-0 model against scikit-fem, as the test checks it.
    let mut reference_check = Vec::new();
    for problem in &all {
        let reference = load_reference(problem)?;
        let mut worst = 0.0f64;
        for (volumetric, solution, label) in [(VolumetricSpec::Full, &reference.hex1, "Hex1"), (VolumetricSpec::MeanDilatation, &reference.hex1p0, "Hex1–P0")] {
            let (parts, iterations, _) = solve_linear(&problem.with_volumetric(volumetric), 0, Weighting::Condensed, 1e-12)?;
            let e = field_error(&sample_displacements(&parts.topo, &reference.samples), &solution.displacements());
            worst = worst.max(e.max);
            let (finest_label, finest) = reference.finest();
            let discretization = field_error(&solution.displacements(), &finest.displacements()).rms;
            reference_check.push(format!(
                "{} against {label} ({}; {} hexahedra, {} samples): max difference {:.1e}, rms {:.1e} ({iterations} CG iterations){}",
                problem.name,
                reference.generator.split(" with ").nth(1).unwrap_or(&reference.generator),
                parts.topo.elements.alive_count(),
                reference.samples.len(),
                e.max,
                e.rms,
                if std::ptr::eq(solution, finest) { String::new() } else { format!("; {label} itself is {:.2} % off {}", 100.0 * discretization, finest_label.trim_start_matches("scikit-fem ")) }
            ));
        }
        progress.tick(&format!("{} level 0 vs scikit-fem Hex1 and Hex1–P0: max {worst:.1e}", problem.name));
    }

    let mut studies = Vec::new();
    for (name, problem, timed_scene, settings, weighting_levels) in &plans {
        let SceneReference { samples, field: reference_field, label: reference_label, frequency_hz: frequency_ref, .. } = scene_reference(problem)?;
        progress.tick(&format!("{name}: reference ready ({} samples)", samples.len()));
        let mut static_by_level = std::collections::BTreeMap::new();
        let mut rows = Vec::new();
        for setting in settings {
            let scene = setting.apply(timed_scene);
            let outcome = build_grid(&scene).and_then(|mut grid| {
                let timing = time_probe(&mut grid, warmup, steps, Some(20_000.0));
                let static_error = match (&reference_field, static_by_level.get(&setting.level)) {
                    (None, _) => None,
                    (Some(_), Some(&e)) => Some(e),
                    (Some(field), None) => {
                        let e = static_error(problem, setting.level, Weighting::Condensed, &samples, field)?;
                        static_by_level.insert(setting.level, e);
                        Some(e)
                    }
                };
                let session_error = match &reference_field {
                    Some(field) if timing.p50_us < 30_000.0 => Some(session_error(problem, setting, &samples, field, if quick { 1.0 } else { 4.0 })?.0),
                    _ => None,
                };
                let frequency_error = match frequency_ref {
                    Some(f_ref) => cantilever_frequency(&scene, if quick { 0.12 } else { 0.25 })?.map(|f| (f / f_ref - 1.0).abs()),
                    None => None,
                };
                Ok(Measured {
                    timing,
                    static_error,
                    session_error,
                    frequency_error,
                    elements: grid.topology().elements.alive_count(),
                    voxels: grid.voxel_count(),
                    triangles: grid.surface().live_triangles().count(),
                    held_nodes: cutsim_sim::grid::support::held_count(grid.topology()),
                })
            });
            progress.tick(&match &outcome {
                Ok(m) => format!("{name} {}: p99 {:.0} µs, error {:.2} %", setting.label(), m.timing.p99_us, 100.0 * m.error().unwrap_or(f64::NAN)),
                Err(e) => format!("{name} {}: refused ({})", setting.label(), e.chars().take(100).collect::<String>()),
            });
            rows.push(Row { setting: *setting, outcome });
        }
        let mut weighting = Vec::new();
        for &level in weighting_levels.iter().filter(|_| reference_field.is_some()) {
            let field = reference_field.as_ref().expect("filtered");
            let condensed = match static_by_level.get(&level) {
                Some(&e) => e,
                None => static_error(problem, level, Weighting::Condensed, &samples, field)?,
            };
            let full = problem.with_volumetric(VolumetricSpec::Full);
            let fully_integrated = static_error(&full, level, Weighting::Condensed, &samples, field)?;
            let fill = static_error(&full, level, Weighting::FillRatio, &samples, field)?;
            progress.tick(&format!(
                "{name} level {level}: mean dilatation {:.2} %, fully integrated {:.2} %, fill ratio {:.2} %",
                100.0 * condensed,
                100.0 * fully_integrated,
                100.0 * fill
            ));
            weighting.push((level, condensed, fully_integrated, fill));
        }
        let description = if problem.summary.is_empty() { problem.scene.description.clone() } else { problem.summary.to_string() };
        studies.push(SceneStudy { scene: name.clone(), description, reference: reference_label, rows, weighting });
    }

    let loads = growing_loads(&cantilever, quick)?;
    progress.tick("cantilever at growing loads");
    let membrane = membrane_study(quick)?;
    progress.tick(&format!("mass-spring skin: E measured {:.0} Pa", membrane.stretch.young_measured_pa));

    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let command = format!("cargo run --release -p cutsim-sim --bin accuracy-speed{}", if quick { " -- --quick" } else { "" });
    let machine = cutsim_sim::stats::machine_description();
    let files = [
        ("accuracy-speed.md", markdown(&studies, &loads, &membrane, &reference_check, &command, &machine)),
        ("accuracy-speed.svg", svg(&studies)),
        ("accuracy-speed.json", serde_json::to_string_pretty(&ErrorTable::from_studies(&studies)).expect("serialises") + "\n"),
    ];
    for (file, text) in files {
        let path = out.join(file);
        std::fs::write(&path, text).map_err(|e| format!("{}: {e}", path.display()))?;
        eprintln!("wrote {}", path.display());
    }
    schedules(quick, out)
}

/// A level of a scene in the schedules' comparison: the level, the multirate deformation's
/// preconditioner and its CG cap (None: the scene's).
type LevelPlan = (u32, &'static str, Option<u32>);

/// Single-rate against multirate at equal budget (`cutsim_sim::accuracy::schedule`): each
/// bundled volumetric scene from its coarsest level finer while either schedule fits;
/// rewrites that section of `out/accuracy-speed.md`.
fn schedules(quick: bool, out: &Path) -> Result<(), String> {
    use cutsim_sim::accuracy::schedule::{Comparison, DEFORMATION_EVERY, Model, Script, markdown, run_real_time, scene_at, splice};
    // Per scene, its levels from coarse to fine and the multirate deformation's solver
    // (block Jacobi needs far more iterations than a scene's cap at a 33 ms step): the
    // multigrid V-cycle where it converges within the cap (the U-tube's thin walls need up
    // to 153 iterations at 33 ms), the Cholesky factor on the smooth liver's levels 2–3 and
    // the layered abdomen's stiff layers (there with a larger cap), as measured by `cargo bench -p cutsim-sim --bench multirate`.
    let plans: [(&str, &[LevelPlan]); 4] = [
        ("liver", &[(3, "multigrid", None), (2, "multigrid", None), (1, "multigrid", None)]),
        ("liver-smooth", &[(3, "cholesky", None), (2, "cholesky", None), (1, "multigrid", None)]),
        ("abdomen-layers", &[(3, "cholesky", Some(200)), (2, "cholesky", Some(400))]),
        ("u-tube", &[(2, "multigrid", Some(200)), (1, "multigrid", Some(200)), (0, "multigrid", Some(200))]),
    ];
    let script = if quick { Script::QUICK } else { Script::FULL };
    // The study's errors as this run's sweep wrote them, else as built in.
    let errors = std::fs::read_to_string(out.join("accuracy-speed.json")).ok().and_then(|t| serde_json::from_str(&t).ok()).unwrap_or_else(cutsim_sim::grid::fidelity::error_table);
    let total: usize = plans.iter().map(|p| p.1.len()).sum();
    let mut progress = Progress { done: 0, total, started: std::time::Instant::now() };
    let mut comparisons = Vec::new();
    for (name, levels) in plans {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(format!("{name}.json"));
        for &(level, preconditioner, cap) in levels {
            let run = |multirate: Option<(u32, &str, Option<u32>)>| scene_at(&path, level, multirate).and_then(|scene| Model::build(&scene)).map(|mut model| run_real_time(&mut model, script));
            let single_rate = run(None);
            let multirate = run(Some((DEFORMATION_EVERY, preconditioner, cap)));
            let fits = |r: &Result<cutsim_sim::accuracy::schedule::RealTime, String>| r.as_ref().is_ok_and(|r| r.fits());
            let any_fits = fits(&single_rate) || fits(&multirate);
            progress.tick(&format!(
                "{name} L{level}: single-rate p99 {}, multirate haptic p99 {}",
                single_rate.as_ref().map_or("refused".to_string(), |r| format!("{:.3} ms", r.step_p99_ms)),
                multirate.as_ref().map_or("refused".to_string(), |r| format!("{:.3} ms ({} late jobs)", r.step_p99_ms, r.late_jobs)),
            ));
            comparisons.push(Comparison {
                scene: name.to_string(),
                level,
                static_error: errors.lookup(name, level).map(|(e, _)| e),
                multirate_solver: match cap {
                    Some(cap) => format!("{preconditioner}, CG ≤ {cap}"),
                    None => preconditioner.to_string(),
                },
                single_rate,
                multirate,
            });
            // Finer levels are slower still.
            if !any_fits {
                break;
            }
        }
    }
    let command = format!("cargo run --release -p cutsim-sim --bin accuracy-speed -- schedules{}", if quick { " --quick" } else { "" });
    let machine = cutsim_sim::stats::machine_description();
    let path = out.join("accuracy-speed.md");
    let document = std::fs::read_to_string(&path).unwrap_or_default();
    std::fs::write(&path, splice(&document, &markdown(&comparisons, &command, &machine, script))).map_err(|e| format!("{}: {e}", path.display()))?;
    eprintln!("wrote the schedules' section of {}", path.display());
    Ok(())
}

/// The rms of `u` over that of `reference` at the same points: how far the body deflects
/// against how far it should (below 1 too stiff). The point counts cancel, so the ratio
/// of the fields' norms.
fn deflection_ratio(u: &[Vec3], reference: &[Vec3]) -> f64 {
    let norm = |f: &[Vec3]| f.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt();
    norm(u) / norm(reference)
}

/// The two support rules side by side: each bundled volumetric scene's linear static
/// error per level with its fixed regions held by the level's nodes (`coarse-nodes`)
/// and by level 0's points (`embedded`), written to `supports.md`.
fn supports(out: &Path) -> Result<(), String> {
    let all = problems().map_err(|e| e.to_string())?;
    let mut studied: Vec<(&str, Problem, Vec<u32>)> = Vec::new();
    for name in ["cantilever-gravity", "liver-gravity"] {
        studied.push((name, all.iter().find(|p| p.name == name).expect("a bundled problem").clone(), vec![0, 1, 2, 3]));
    }
    for name in ["u-tube", "liver-smooth", "abdomen-layers"] {
        studied.push((name, bundled_problem(name)?, if name == "u-tube" { vec![0, 1, 2] } else { vec![1, 2, 3] }));
    }
    let started = std::time::Instant::now();
    let mut table = String::from("| scene | level | coarse-nodes: held | static error | deflection | embedded: held (nodes + springs) | static error | deflection |\n|---|---:|---:|---:|---:|---:|---:|---:|\n");
    for (name, problem, levels) in &studied {
        // Level 0 is the same under both rules: the reference must be finer than the
        // levels compared, so our own level-0 solution where scikit-fem has none.
        let (samples, field, label) = match scene_reference(problem)? {
            SceneReference { samples, field: Some(field), label, level: 0, .. } => (samples, field, label),
            SceneReference { field: None, label, .. } => {
                table.push_str(&format!("| {name} | | reference {label} | | | | | |\n"));
                continue;
            }
            SceneReference { level, .. } => {
                table.push_str(&format!("| {name} | | no reference: the body is too large for a level-0 solve here (its reference is level {level}, one of the levels compared) | | | | | |\n"));
                continue;
            }
        };
        for &level in levels {
            let mut cells = Vec::new();
            for rule in [SupportSpec::CoarseNodes, SupportSpec::Embedded] {
                let mut problem = problem.clone();
                if let ModelSpec::BranchedGrid(spec) = &mut problem.scene.model {
                    spec.support = rule;
                }
                let (parts, iterations, residual) = solve_linear(&problem, level, Weighting::Condensed, 1e-10)?;
                let springs = parts.topo.supports.live(&parts.topo).count();
                let held = cutsim_sim::grid::support::held_count(&parts.topo);
                cells.push(if rule == SupportSpec::Embedded { format!("{} + {springs}", held - springs) } else { held.to_string() });
                // The static problem may have no solution (a piece held at one point or
                // along a line, say, can turn about it); then the CG's answer is no error.
                if residual > 1e-8 {
                    cells.push(format!("no solution (CG stopped at residual {residual:.1e} after {iterations} iterations)"));
                    cells.push("–".into());
                } else {
                    let u = sample_displacements(&parts.topo, &samples);
                    cells.push(format!("{:.2} %", 100.0 * field_error(&u, &field).rms));
                    cells.push(format!("{:.2}", deflection_ratio(&u, &field)));
                }
            }
            table.push_str(&format!("| {name} | {level} | {} |\n", cells.join(" | ")));
            eprintln!("{:>6.1} s  {name} level {level}: {}", started.elapsed().as_secs_f64(), cells.join(", "));
        }
        table.push_str(&format!("| | | reference: {label} | | | | | |\n"));
    }
    let text = format!(
        "# Supports at coarse levels\n\nGenerated by `cargo run --release -p cutsim-sim --bin accuracy-speed -- supports`; do not edit by hand.\n\n\
         The linear static error under gravity (relative rms at the sample points, as in [accuracy-speed.md](accuracy-speed.md)) of each bundled volumetric scene, its fixed regions held by the two rules of `model.branched-grid.support` ([branched-grid.md](branched-grid.md), \"Supports\"): `coarse-nodes` holds the level's nodes inside a region; `embedded` holds level 0's points at every level — a node where a held point is a cell corner, else a stiff spring ({} × E of its voxel × voxel side) on the point embedded in its coarse element, where the region meets material it does not hold and at every held point of a piece the region holds wholly. Level 0 is the same under both. **Deflection** is the level's rms displacement over the reference's at the same points: below 1 the level is held too stiffly (or its elements are too stiff), above 1 too softly; the error left beside it is the shape.\n\n{table}",
        cutsim_sim::grid::support::SUPPORT_STIFFNESS_PER_VOXEL
    );
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let path = out.join("supports.md");
    std::fs::write(&path, text).map_err(|e| format!("{}: {e}", path.display()))?;
    eprintln!("wrote {}", path.display());
    Ok(())
}

/// The cantilever at level 1 under growing multiples of gravity, settled, against the
/// linear Hex2 reference scaled by the multiple.
fn growing_loads(problem: &Problem, quick: bool) -> Result<Vec<LoadRow>, String> {
    let reference = load_reference(problem)?;
    let (_, hex2) = reference.finest();
    let linear = hex2.displacements();
    let mut rows = Vec::new();
    for multiple in [1.0, 10.0, 30.0, 100.0] {
        let mut scene = Setting::new(1, MassSpec::Lumped, 200, 0.001).apply(&with_gravity_down(&problem.scene, G * multiple));
        if let ModelSpec::BranchedGrid(spec) = &mut scene.model {
            spec.damping.mass_per_s = DampingPerS(300.0);
        }
        let mut grid = build_grid(&scene)?;
        let n = cutsim_sim::tissue::Tissue::tools(&grid).len();
        let (commands, mut feedback) = (vec![Default::default(); n], vec![Default::default(); n]);
        for _ in 0..if quick { 600 } else { 1500 } {
            grid.step(&commands, &mut feedback);
        }
        let topo = grid.topology();
        let scaled: Vec<Vec3> = linear.iter().map(|d| d * multiple).collect();
        let error = field_error(&sample_displacements(topo, &reference.samples), &scaled).rms;
        let tip = tip_nodes(topo);
        let deflection = tip.iter().map(|&i| topo.nodes.rest[i].z - topo.nodes.x[i].z).sum::<f64>() / tip.len() as f64;
        rows.push(LoadRow { gravity_multiple: multiple, tip_deflection_over_length: deflection / topo.nodes.rest[tip[0]].x, error });
    }
    Ok(rows)
}

fn stability(reduced: bool, out: &Path) -> Result<(), String> {
    use cutsim_sim::accuracy::stability::{cases, markdown, run};
    let cases = cases(!reduced);
    let started = std::time::Instant::now();
    let mut results = Vec::new();
    for (i, case) in cases.iter().enumerate() {
        let outcome = run(case)?;
        eprintln!("[{:>3}/{}] {:>6.1} s  {}: {}", i + 1, cases.len(), started.elapsed().as_secs_f64(), case.label(), outcome.describe());
        results.push((*case, outcome));
    }
    let command = format!("cargo run --release -p cutsim-sim --bin accuracy-speed -- stability{}", if reduced { " --reduced" } else { "" });
    std::fs::create_dir_all(out).map_err(|e| format!("{}: {e}", out.display()))?;
    let path = out.join("stability.md");
    std::fs::write(&path, markdown(&results, &command)).map_err(|e| format!("{}: {e}", path.display()))?;
    eprintln!("wrote {}", path.display());
    let failed = results.iter().filter(|(_, o)| !o.acceptable()).count();
    if failed > 0 {
        return Err(format!("{failed} cases were unbounded or refused without a reason (see {})", path.display()));
    }
    Ok(())
}

/// The mass-spring skin: the stretch test and the shrinking curve against εr.
fn membrane_study(quick: bool) -> Result<MembraneStudy, String> {
    use cutsim_sim::accuracy::membrane::{peak_and_plateau, shrinking_gap_curve, uniaxial_stretch};
    let stretch = uniaxial_stretch()?;
    let mut shrinking = Vec::new();
    for eps in [0.0, 0.05, 0.1, 0.2] {
        let curve = shrinking_gap_curve(eps, if quick { 600 } else { 1200 })?;
        let ((at, peak), plateau) = peak_and_plateau(&curve);
        shrinking.push((eps, peak, at, plateau));
    }
    Ok(MembraneStudy { stretch, shrinking })
}
