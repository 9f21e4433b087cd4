//! Helpers shared by the integration tests: scenes written inline, and tool drivers.
#![allow(dead_code)]

use cutsim_sim::geometry::TriMesh;
use cutsim_sim::math::{Pose, Quat, Vec3};
use cutsim_sim::msm::{MassSpring, build_from_scene};
use cutsim_sim::scene::{ModelSpec, Scene};
use cutsim_sim::tool::ToolFeedback;

/// A file in the shared data directory; fails loudly when the data is not there.
pub fn shared_data(relative: &str) -> std::path::PathBuf {
    let path = cutsim_sim::scene::data_dir().join(relative);
    assert!(path.exists(), "shared data {} not found; set CUTSIM_DATA_DIR to the shared data directory", path.display());
    path
}

pub fn scenes_dir() -> std::path::PathBuf {
    std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes")
}

#[allow(unused_imports)]
pub use cutsim_sim::accuracy::membrane::patch_scene;

pub fn scene(text: &str) -> Scene {
    Scene::from_json_str(text, "test scene", None).unwrap_or_else(|e| panic!("{e}"))
}

/// A branched grid from a scene written inline.
pub fn build_grid(json: &str) -> cutsim_sim::grid::BranchedGrid {
    let scene = scene(json);
    let ModelSpec::BranchedGrid(spec) = &scene.model else { panic!("{}: not a branched-grid scene", scene.name) };
    cutsim_sim::grid::build_from_scene(&scene, spec).unwrap_or_else(|e| panic!("{e}"))
}

pub fn build(scene: &Scene) -> MassSpring {
    let ModelSpec::Msm(spec) = &scene.model else { panic!("{}: not an msm scene", scene.name) };
    build_from_scene(scene, spec).unwrap_or_else(|e| panic!("{e}"))
}

pub fn load_scene(path: &std::path::Path) -> Scene {
    Scene::load(path).unwrap_or_else(|e| panic!("{e}"))
}

/// A pose with the tool's tip at `tip` and its axis along `axis`.
pub fn pose(tip: Vec3, axis: Vec3) -> Pose {
    let rotation = Quat::rotation_between(&Vec3::z(), &axis.normalize()).unwrap_or_else(Quat::identity);
    Pose::new(tip, rotation)
}

/// Steps the model with tool 0 held at `pose` (cut button `cut`), `steps` times.
pub fn step_with(model: &mut MassSpring, pose: Option<Pose>, cut: bool, steps: usize) -> ToolFeedback {
    model.step_holding(pose, cut, steps)
}

/// Cuts along a straight line in `steps` steps with a blade whose tip is `depth` below
/// the surface point (along −axis), then lifts it away.
pub fn straight_cut(model: &mut MassSpring, from: Vec3, to: Vec3, axis: Vec3, depth: f64, steps: usize) {
    for k in 0..=steps {
        let p = from + (to - from) * (k as f64 / steps as f64);
        step_with(model, Some(pose(p - axis.normalize() * depth, axis)), true, 1);
    }
    step_with(model, None, false, 1);
}

/// The live triangles as a compact mesh (for manifold checks).
pub fn live_mesh(model: &MassSpring) -> TriMesh {
    let mut map = vec![u32::MAX; model.positions().len()];
    let mut mesh = TriMesh::default();
    for (_, tri) in model.triangles() {
        let mut out = [0u32; 3];
        for (k, &v) in tri.iter().enumerate() {
            if map[v as usize] == u32::MAX {
                map[v as usize] = mesh.positions.len() as u32;
                mesh.positions.push(model.positions()[v as usize]);
            }
            out[k] = map[v as usize];
        }
        mesh.triangles.push(out);
    }
    mesh
}

pub fn max_speed(model: &MassSpring) -> f64 {
    model.velocities().iter().map(|v| v.norm()).fold(0.0, f64::max)
}
