//! Dev probe: a reference problem's linear static error per level against its finest
//! scikit-fem reference, and the ratio of displacement magnitudes (>1: softer).
//! `static_probe PROBLEM [LEVELS...]` (FULL=1: fully integrated elements)
use cutsim_sim::accuracy::problems::{problems, sample_displacements};
use cutsim_sim::accuracy::reference::{Weighting, field_error, load_reference, solve_linear};
use cutsim_sim::scene::VolumetricSpec;

struct Samples {
    samples: Vec<(usize, usize)>,
}

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let name = args.first().map(String::as_str).unwrap_or("liver-gravity");
    let bundled = || {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes").join(format!("{name}.json"));
        let scene = cutsim_sim::accuracy::problems::with_gravity_down(&cutsim_sim::scene::Scene::load(&path).unwrap(), 9.81);
        let name: &'static str = Box::leak(name.to_string().into_boxed_str());
        cutsim_sim::accuracy::problems::Problem { name, summary: "", scene, load: cutsim_sim::accuracy::problems::Load::Gravity, frequency: false, quadratic: false, mixed: false, sample_stride: 16 }
    };
    let mut problem = problems().unwrap().into_iter().find(|p| p.name == name).unwrap_or_else(bundled);
    if std::env::var("FULL").is_ok() {
        problem = problem.with_volumetric(VolumetricSpec::Full);
    }
    let (label, field, samples) = match load_reference(&problem) {
        Ok(reference) => {
            let (label, finest) = reference.finest();
            (label.to_string(), finest.displacements(), reference.samples.clone())
        }
        Err(_) => {
            let level: u32 = std::env::var("REF_LEVEL").ok().and_then(|v| v.parse().ok()).unwrap_or(1);
            let samples = problem.samples(&problem.parts(level).unwrap());
            (format!("own L{level}"), cutsim_sim::accuracy::sweep::own_reference(&problem, level, &samples).unwrap(), samples)
        }
    };
    let reference = Samples { samples };
    let levels: Vec<u32> = if args.len() > 1 { args[1..].iter().map(|a| a.parse().unwrap()).collect() } else { vec![1, 2, 3] };
    for level in levels {
        let (parts, _, _) = solve_linear(&problem, level, Weighting::Condensed, 1e-10).unwrap();
        let u = sample_displacements(&parts.topo, &reference.samples);
        let e = field_error(&u, &field);
        let ratio = (u.iter().map(|v| v.norm_squared()).sum::<f64>() / field.iter().map(|v| v.norm_squared()).sum::<f64>()).sqrt();
        println!("{name} L{level} vs {label}: rms {:.2} %, max {:.2} %, magnitude ratio {ratio:.3}", e.rms * 100.0, e.max * 100.0);
    }
}
