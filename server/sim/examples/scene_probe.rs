//! Probe timing of a branched-grid scene at a level: `scene_probe SCENE LEVEL [STEPS]`.
use cutsim_sim::grid::fidelity::time_probe;
use cutsim_sim::scene::{ModelSpec, Scene};
fn main() {
    let args: Vec<String> = std::env::args().collect();
    let path = if args[1].ends_with(".json") { std::path::PathBuf::from(&args[1]) } else { std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(format!("{}.json", args[1])) };
    let level: u32 = args[2].parse().unwrap();
    let steps: usize = args.get(3).map_or(1000, |s| s.parse().unwrap());
    let scene = Scene::load(&path).unwrap().with_grid_level(level);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { panic!() };
    let t = std::time::Instant::now();
    let mut grid = cutsim_sim::grid::build_from_scene(&scene, spec).unwrap_or_else(|e| panic!("{e}"));
    let build = t.elapsed();
    let timing = time_probe(&mut grid, 100, steps, None);
    println!("{} L{level}: nodes {} elements {} build {:.2} s: p50 {:.0} µs p99 {:.0} µs CG {:.1}", args[1], grid.topology().nodes.alive_count(), grid.topology().elements.alive_count(), build.as_secs_f64(), timing.p50_us, timing.p99_us, timing.mean_cg);
}
