//! Building a [`BranchedGrid`] from a scene: read or make the label volume, crop it,
//! keep the labels that have a material, build the coarse grid, fix nodes, extract the
//! surface. Errors name the scene path and say what was found and what is allowed.

use super::condense::{Volumetric, VoxelMatrices};
use super::model::{BranchedGrid, Frame, GridMaterial};
use super::solver::{MassModel, Preconditioning, SolverSettings};
use super::surface::GridSurface;
use super::topology::{Layout, Topology};
use crate::math::Vec3;
use crate::scene::{BranchedGridSpec, FidelitySpec, MassSpec, PreconditionerSpec, Scene, SceneError, VolumeSource, VolumetricSpec};
use crate::volume::procedural::{UTube, ellipsoid, solid_box, u_tube};
use crate::volume::{LabelVolume, nifti, voxelize, vti};

/// The largest Poisson ratio a branched-grid material may have with fully integrated
/// elements. Nearer 0.5 they lock, and the corotated step, whose rotations are frozen
/// over the step, pumps energy into large deformations: in the stability sweep
/// (docs/stability.md) ν = 0.499 gained energy in every scenario without damping (and
/// some with), and ν = 0.49 in one-voxel fragments of soft tissue (100 Pa–1 kPa);
/// ν ≤ 0.45 never did.
pub const MAX_POISSON_FULL: f64 = 0.45;

/// The largest Poisson ratio with mean-dilatation elements (the default): they do not
/// lock, and the stability sweep stays bounded up to here (docs/stability.md).
pub const MAX_POISSON: f64 = 0.49;

/// Material voxels a scene may build (about 4 times the paper's largest scene).
pub const MAX_MATERIAL_VOXELS: usize = 2_000_000;

/// The void of each cell holds a ghost material this much stiffer than nothing: a
/// fraction of the softest material's Young's modulus (see `Topology::set_ghost`).
pub const GHOST_STIFFNESS: f64 = 1e-3;

/// Reads or makes the scene's label volume (before cropping and label selection).
pub fn load_volume(scene: &Scene, spec: &BranchedGridSpec) -> Result<LabelVolume, SceneError> {
    let err = |path: &str, message: String| SceneError::new(&scene.origin, format!("model.branched-grid.volume.{path}"), message);
    let volume = match &spec.volume {
        VolumeSource::Nifti { path } => nifti::read_nifti(&scene.resolve_path(path)).map_err(|e| err("nifti.path", e))?,
        VolumeSource::Vti { path, array, scale_m_per_unit } => {
            vti::read_vti(&scene.resolve_path(path), array.as_deref(), scale_m_per_unit.get()).map_err(|e| err("vti.path", e))?
        }
        VolumeSource::Mesh { path, scale_m_per_unit, voxel_size_m, label } => {
            let file = scene.resolve_path(path);
            let extension = file.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
            let mut mesh = match extension.as_str() {
                "obj" => crate::geometry::obj::read_obj_file(&file),
                "vtk" => crate::geometry::vtk::read_vtk_file(&file),
                other => Err(format!("{}: a mesh must be .obj or .vtk (legacy polydata), not .{other}", file.display())),
            }
            .map_err(|e| err("mesh.path", e))?;
            mesh.scale_and_offset(scale_m_per_unit.get(), Vec3::zeros());
            let (volume, _report) = voxelize::voxelize(&mesh, voxel_size_m.get(), label.get(), crate::volume::MAX_VOXELS).map_err(|e| err("mesh", e))?;
            volume
        }
        VolumeSource::Box { size_m, voxel_size_m, label } => solid_box(size_m.map(|s| s.get()), voxel_size_m.get(), label.get()),
        VolumeSource::Ellipsoid { radii_m, voxel_size_m, label } => ellipsoid(radii_m.map(|r| r.get()), voxel_size_m.get(), label.get()),
        VolumeSource::UTube { voxel_size_m, arm_voxels, gap_voxels, depth_voxels, base_voxels, arm_length_voxels, label } => u_tube(
            UTube {
                arm: arm_voxels.get() as usize,
                gap: gap_voxels.get() as usize,
                depth: depth_voxels.get() as usize,
                base: base_voxels.get() as usize,
                arm_length: arm_length_voxels.get() as usize,
            },
            voxel_size_m.get(),
            label.get(),
        ),
    };
    volume.check().map_err(|e| err("", e))?;
    Ok(volume)
}

/// What a scene's grid is made of before the solver check, the surface and the tools:
/// the topology with its fixed nodes, its frame, materials and solver settings, and
/// the label volume it was built from (cropped, selected, right-handed).
#[derive(Debug, Clone)]
pub struct GridParts {
    pub topo: Topology,
    pub frame: Frame,
    pub materials: Vec<GridMaterial>,
    pub settings: SolverSettings,
    pub volume: LabelVolume,
}

/// Builds the grid's topology, frame and settings from a scene (see [`GridParts`]).
pub fn build_parts(scene: &Scene, spec: &BranchedGridSpec) -> Result<GridParts, SceneError> {
    let at = |path: &str, message: String| SceneError::new(&scene.origin, format!("model.branched-grid{}{path}", if path.is_empty() { "" } else { "." }), message);
    let mut volume = load_volume(scene, spec)?;
    if let Some(crop) = &spec.crop_voxels {
        volume = volume.crop(crop.min.map(|i| i.get() as usize), crop.max.map(|i| i.get() as usize)).map_err(|e| at("crop_voxels", e))?;
    }
    let volume = volume.to_right_handed();
    let labels: Vec<u16> = spec.materials.iter().map(|m| m.label.get()).collect();
    let Some(volume) = volume.select(&labels, 0) else {
        let present: Vec<String> = volume.histogram().iter().take(40).map(|(l, n)| format!("{l} ({n} voxels)")).collect();
        return Err(at(
            "materials",
            format!(
                "none of the labels {labels:?} occurs in the volume; labels present: {}",
                if present.is_empty() { "none (the volume is empty)".into() } else { present.join(", ") }
            ),
        ));
    };
    let material: Vec<u16> = volume.labels.iter().map(|l| labels.iter().position(|m| m == l).map_or(0, |i| i as u16 + 1)).collect();
    let count = material.iter().filter(|&&m| m != 0).count();
    if count > MAX_MATERIAL_VOXELS {
        return Err(at("volume", format!("{count} voxels have a material; at most {MAX_MATERIAL_VOXELS} are allowed (crop, select fewer labels or use larger voxels)")));
    }
    let volumetric = match spec.volumetric {
        VolumetricSpec::MeanDilatation => Volumetric::MeanDilatation,
        VolumetricSpec::Full => Volumetric::Full,
    };
    let materials: Vec<GridMaterial> = spec
        .materials
        .iter()
        .map(|m| GridMaterial {
            label: m.label.get(),
            name: if m.name.is_empty() { format!("label {}", m.label.get()) } else { m.name.clone() },
            young_pa: m.young_pa.get(),
            poisson: m.poisson.get(),
            density_kg_per_m3: m.density_kg_per_m3.get(),
            friction: m.friction.map_or_else(Default::default, |f| super::friction::Friction { static_coefficient: f.static_coefficient.get(), dynamic_coefficient: f.dynamic_coefficient.get() }),
            fracture_toughness_j_per_m2: m.fracture_toughness_j_per_m2.get(),
        })
        .collect();
    let constants: Vec<(f64, f64, f64)> = materials.iter().map(|m| (m.young_pa, m.poisson, m.density_kg_per_m3)).collect();
    let layout = Layout::new(volume.dims, spec.level.get(), volume.spacing_m);
    let mut topo = Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &constants, volumetric));
    let softest = materials.iter().min_by(|a, b| a.young_pa.total_cmp(&b.young_pa)).expect("a material");
    let cell_m = topo.layout.cell_size_m();
    let cell = [cell_m.x, cell_m.y, cell_m.z];
    let (ghost_young, ghost_poisson) = (softest.young_pa * GHOST_STIFFNESS, softest.poisson);
    topo.set_ghost(match volumetric {
        Volumetric::Full => super::hex::box_stiffness(cell, ghost_young, ghost_poisson),
        Volumetric::MeanDilatation => super::hex::box_mean_dilatation_stiffness(cell, ghost_young, ghost_poisson),
    });

    // The grid's frame: voxel (0, 0, 0) spans [0, spacing] locally, its centre is the
    // volume's origin in the world.
    let half = Vec3::from(volume.spacing_m) * 0.5;
    let mut frame = Frame { rotation: volume.direction, translation: volume.origin_m - volume.direction * half };
    if spec.centre {
        let (lo, hi) = rest_bounds(&topo);
        frame.translation -= frame.to_world(&((lo + hi) * 0.5));
    }
    super::support::hold_regions(scene, spec, &mut topo, &frame)?;

    let settings = SolverSettings {
        dt_s: scene.time_step_s.get(),
        cg_max_iterations: spec.solver.cg_max_iterations.get(),
        cg_tolerance: spec.solver.cg_tolerance.get(),
        alpha_per_s: spec.damping.mass_per_s.get(),
        beta_s: spec.damping.stiffness_s.get(),
        mass: match spec.mass {
            MassSpec::Lumped => MassModel::Lumped,
            MassSpec::Consistent => MassModel::Consistent,
        },
        gravity: scene.gravity_m_per_s2.map(|g| frame.rotation.transpose() * Vec3::new(g[0].get(), g[1].get(), g[2].get())),
        preconditioner: match spec.solver.preconditioner {
            PreconditionerSpec::Multigrid => Preconditioning::Multigrid,
            PreconditionerSpec::Jacobi => Preconditioning::Jacobi,
            PreconditionerSpec::Cholesky => Preconditioning::Cholesky,
        },
    };
    Ok(GridParts { topo, frame, materials, settings, volume })
}

/// Builds the model a branched-grid scene describes (with `"fidelity": "auto"`, at the
/// level the calibration chooses: see [`super::fidelity`]).
pub fn build_from_scene(scene: &Scene, spec: &BranchedGridSpec) -> Result<BranchedGrid, SceneError> {
    match spec.fidelity {
        FidelitySpec::Fixed => build_fixed(scene, spec),
        FidelitySpec::Auto => super::fidelity::build_auto(scene, spec),
    }
}

/// Builds the model at the scene's `level`.
pub fn build_fixed(scene: &Scene, spec: &BranchedGridSpec) -> Result<BranchedGrid, SceneError> {
    check_poisson(scene, spec)?;
    let GridParts { topo, frame, materials, settings, volume } = build_parts(scene, spec)?;
    let surface = GridSurface::build(&topo, spec.surface.smoothing_iterations.get());
    let tools = crate::tool::tool_shapes(scene);
    if spec.cutting.is_some() {
        check_cutting_radii(scene, &tools, &volume)?;
    }
    let grid = BranchedGrid::assemble(
        scene.time_step_s.get(),
        frame,
        topo,
        settings,
        surface,
        materials,
        tools,
        spec.cutting.as_ref().map(|c| c.max_voxels_per_step.get() as usize),
    );
    if grid.settings.preconditioner == Preconditioning::Cholesky {
        check_factor_size(scene, &grid)?;
    }
    check_solver_converges(scene, &grid)?;
    Ok(grid)
}

/// A Cholesky factor grows faster than the grid (a 3D grid's fill): at level 0 of a
/// large volume it would take gigabytes and seconds a factorization. Its size is known
/// from the symbolic factorization alone, before any is computed.
fn check_factor_size(scene: &Scene, grid: &BranchedGrid) -> Result<(), SceneError> {
    let field = "model.branched-grid.solver.preconditioner";
    let entries = super::factorization::factor_entries(grid.topology()).map_err(|e| SceneError::new(&scene.origin, field, e.to_string()))?;
    if entries <= super::factorization::MAX_FACTOR_ENTRIES {
        return Ok(());
    }
    Err(SceneError::new(
        &scene.origin,
        field,
        format!(
            "the Cholesky factor of this scene's system would hold {entries} entries ({} MB in single precision), more than the {} allowed; use the multigrid preconditioner or a coarser level",
            entries * 4 / 1_000_000,
            super::factorization::MAX_FACTOR_ENTRIES
        ),
    ))
}

/// Steps the load-time check presses a probe in over, then holds it for as many.
const CHECK_STEPS: usize = 12;

/// An implicit step whose conjugate-gradient solve stops at its iteration cap far from
/// its solution is not a stable integrator: its Δv is partly garbage and energy grows
/// (a 1 MPa, ν = 0.49 bar of 1 mm voxels at 1 ms, capped at 30 iterations, stops at a
/// residual near 1 and blows up within 0.2 s). So at load the scene's own solver — its
/// tolerance and preconditioner — runs what a session does: a probe (the scene's first
/// tool that does not cut; gravity, or 10 m/s² when the scene has none) pressed 2 mm
/// into the body's broad top (its end: super::hold::reach_below_tip) and held, from
/// rest, with ten times the iteration cap; the scene is refused when a step needs more
/// than its cap to reach its tolerance, with the number it needs and the tool.
fn check_solver_converges(scene: &Scene, grid: &BranchedGrid) -> Result<(), SceneError> {
    let cap = grid.settings.cg_max_iterations;
    let tolerance = grid.settings.cg_tolerance;
    let mut probe = grid.clone();
    probe.settings.cg_max_iterations = (cap * 10).max(500);
    if probe.settings.gravity.is_none() {
        probe.settings.gravity = Some(Vec3::repeat(10.0 / 3f64.sqrt()));
    }
    let tools = crate::tissue::Tissue::tools(&probe).to_vec();
    let pressing = tools.iter().position(|t| !t.can_cut);
    let top = probe.broad_top();
    let mut commands = vec![crate::tool::ToolCommand::default(); tools.len()];
    let mut feedback = vec![crate::tool::ToolFeedback::default(); tools.len()];
    let (mut needed, mut unreached) = (0u32, None::<f64>);
    for step in 0..2 * CHECK_STEPS {
        if let (Some(p), Some(top)) = (pressing, top) {
            let depth = 0.002 * ((step + 1) as f64 / CHECK_STEPS as f64).min(1.0);
            let tip = Vec3::new(top.x, top.y, top.z + super::hold::reach_below_tip(&tools[p]) - depth);
            commands[p] = crate::tool::ToolCommand { pose: crate::math::Pose::new(tip, crate::math::Quat::identity()), active: true, cut: false, grip: None };
        }
        probe.step(&commands, &mut feedback);
        let done = probe.last_convergence();
        needed = needed.max(done.iterations);
        if done.cap_hit {
            unreached = Some(unreached.unwrap_or(0.0f64).max(done.residual));
        }
    }
    if needed <= cap && unreached.is_none() {
        return Ok(());
    }
    let dt_ms = grid.settings.dt_s * 1e3;
    let load = match (pressing, top) {
        (Some(p), Some(_)) => format!("tool {:?} pressed 2 mm into the body under load", tools[p].name),
        _ => "the body under load".to_owned(),
    };
    let message = if let Some(worst) = unreached {
        format!(
            "the implicit solve of this scene does not reach its tolerance {tolerance:e} (residual {worst:.1e} after {needed} conjugate-gradient iterations, time step {dt_ms} ms, {load}; {cap} are allowed), and a solve stopped further off is not stable: the system is too stiff for this step; use a shorter time_step_s, the multigrid preconditioner, a looser cg_tolerance or a softer material (or a Poisson ratio further from 0.5)"
        )
    } else {
        format!(
            "the implicit solve of this scene needs {needed} conjugate-gradient iterations to reach its tolerance {tolerance:e} (time step {dt_ms} ms, {load}), more than the {cap} allowed, and a solve stopped short is less accurate, and far off not stable; raise cg_max_iterations to at least {needed}, use the multigrid preconditioner, a shorter time_step_s or a softer material"
        )
    };
    Err(SceneError::new(&scene.origin, "model.branched-grid.solver.cg_max_iterations", message))
}

/// A cutting shape thinner than half a voxel would pass between the voxel centres and
/// cut nothing (or a dotted line): voxel removal cannot cut finer than its voxels.
fn check_cutting_radii(scene: &Scene, tools: &[crate::tool::ToolShape], volume: &LabelVolume) -> Result<(), SceneError> {
    let half_voxel = volume.spacing_m.iter().copied().fold(0.0, f64::max) * 0.5;
    for (i, tool) in tools.iter().enumerate().filter(|(_, t)| t.can_cut) {
        let (radius, explicit) = (tool.cutting_capsule().0, tool.cutting_shape.is_some());
        if radius < half_voxel * (1.0 - 1e-9) {
            let path = if explicit { format!("tools[{i}].cutting_shape") } else { format!("tools[{i}].shape") };
            let what = if explicit { "the cutting shape's radius" } else { "the default cutting radius (half the tool's radius)" };
            return Err(SceneError::new(
                &scene.origin,
                path,
                format!(
                    "{what} is {:.3} mm, less than half the voxel size ({:.3} mm): the blade would pass between voxel centres and cut nothing; give \"{}\" a cutting_shape of radius at least {:.3} mm, or use smaller voxels",
                    radius * 1e3,
                    half_voxel * 1e3,
                    tool.name,
                    half_voxel * 1e3
                ),
            ));
        }
    }
    Ok(())
}

/// Refuses Poisson ratios the dynamics cannot run with the scene's elements (a linear
/// static solve, as the accuracy study's, takes any below 0.5).
fn check_poisson(scene: &Scene, spec: &BranchedGridSpec) -> Result<(), SceneError> {
    let max_poisson = match spec.volumetric {
        VolumetricSpec::MeanDilatation => MAX_POISSON,
        VolumetricSpec::Full => MAX_POISSON_FULL,
    };
    for (i, m) in spec.materials.iter().enumerate() {
        if m.poisson.get() > max_poisson {
            let advice = match spec.volumetric {
                VolumetricSpec::Full => format!("with \"volumetric\": \"full\" use at most {MAX_POISSON_FULL}, or \"mean-dilatation\" (the default) up to {MAX_POISSON}"),
                VolumetricSpec::MeanDilatation => format!("use at most {MAX_POISSON} (10 % strain then changes the volume by 0.2 %)"),
            };
            return Err(SceneError::new(
                &scene.origin,
                format!("model.branched-grid.materials[{i}].poisson"),
                format!("a Poisson ratio of {} is too close to 0.5 for the branched grid: large deformations become unstable; {advice}", m.poisson.get()),
            ));
        }
    }
    Ok(())
}

/// The box around the live nodes' rest positions (grid frame).
pub(super) fn rest_bounds(topo: &Topology) -> (Vec3, Vec3) {
    let mut lo = Vec3::repeat(f64::INFINITY);
    let mut hi = Vec3::repeat(f64::NEG_INFINITY);
    for n in 0..topo.nodes.len() {
        if topo.nodes.alive[n] {
            lo = lo.inf(&topo.nodes.rest[n]);
            hi = hi.sup(&topo.nodes.rest[n]);
        }
    }
    (lo, hi)
}

