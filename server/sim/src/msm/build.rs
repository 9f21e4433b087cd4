//! Building a [`MassSpring`] from a scene or from parts.

use super::calibration::MembraneMaterial;
use super::cut::{CuttingParams, Cutter};
use super::explicit::{StabilityBound, bound_over};
use super::foundation::{Foundation, FoundationParams};
use super::implicit::ImplicitSolver;
use super::state::{Nodes, Spring, SpringSet, Topology};
use super::{Integrator, MassSpring};
use crate::broad_phase::PointGrid;
use crate::geometry::patch::{self, PatchParams};
use crate::geometry::{TriMesh, obj};
use crate::math::{Vec3, triangle_area};
use crate::scene::{FixedSpec, IntegratorSpec, MsmSpec, Scene, SceneError, SurfaceGeometry};
use crate::tissue::TissueCounters;
use crate::tool::{PlacedTool, ToolShape};

/// The largest mesh a scene may ask for.
pub const MAX_NODES: u64 = 2_000_000;

/// Time integration choice with its settings.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum IntegratorChoice {
    SymplecticEuler { substeps: u32 },
    ImplicitEuler { max_iterations: u32, tolerance: f64 },
}

/// Everything the model needs besides geometry, boundary conditions and tools.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MsmParams {
    pub time_step_s: f64,
    pub material: MembraneMaterial,
    /// εr: springs rest at their reference length / (1 + εr).
    pub residual_strain: f64,
    /// α, 1/s: damping force −α·m·v.
    pub mass_damping_per_s: f64,
    /// β, s: spring damping β·k·(rate of extension).
    pub spring_damping_s: f64,
    pub gravity_m_per_s2: Option<Vec3>,
    pub integrator: IntegratorChoice,
    /// `None`: the model cannot be cut. Inside, `None` values take their defaults.
    pub cutting: Option<(Option<f64>, Option<f64>)>,
    /// The tissue under the skin; `None`: the membrane spans empty space.
    pub foundation: Option<FoundationParams>,
    /// The work a cut needs per unit area, J/m² (0: cutting needs no force).
    pub fracture_toughness_j_per_m2: f64,
    /// Coulomb friction at the tools' tip faces: (static, dynamic) coefficients.
    pub friction: Option<(f64, f64)>,
}

/// Why a model could not be built.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum MsmBuildError {
    #[error("{0}")]
    Mesh(String),
    #[error(
        "the explicit substep dt/substeps = {substep_ms:.4} ms is above the stability bound {bound_ms:.4} ms \
         (highest natural frequency ≤ {omega:.3e} rad/s, at node {node}); use substeps ≥ {min_substeps}, \
         or the implicit-euler integrator"
    )]
    Unstable { substep_ms: f64, bound_ms: f64, omega: f64, node: u32, min_substeps: u64 },
}

impl MassSpring {
    /// Builds the model from a checked mesh. `free[i]` is 1.0 on the axes node i may move
    /// along and 0.0 on its fixed axes.
    pub fn new(mesh: TriMesh, free: Vec<Vec3>, params: &MsmParams, tools: Vec<ToolShape>) -> Result<Self, MsmBuildError> {
        mesh.check().map_err(MsmBuildError::Mesh)?;
        assert_eq!(free.len(), mesh.positions.len(), "one free-axes mask per node");
        let n = mesh.positions.len();
        let mut nodes = Nodes::default();
        let mut topo = Topology { node_tris: vec![Vec::new(); n], ..Default::default() };
        for p in &mesh.positions {
            nodes.push(*p, Vec3::zeros());
        }
        nodes.free = free;
        for tri in &mesh.triangles {
            let [a, b, c] = tri.map(|v| mesh.positions[v as usize]);
            topo.push_tri(*tri, triangle_area(&a, &b, &c));
        }
        let edges = mesh.edges();
        let mut springs = SpringSet::with_capacity(edges.len());
        for &(a, b) in &edges {
            let l_ref = (mesh.positions[a as usize] - mesh.positions[b as usize]).norm();
            let k = topo
                .edge_tris(a, b)
                .map(|t| params.material.edge_stiffness_share(topo.tri_area_ref[t as usize], l_ref))
                .sum();
            springs.insert(Spring { a, b, k, l0: l_ref / (1.0 + params.residual_strain), l_ref });
        }
        for i in 0..n as u32 {
            let m: f64 = topo.node_tris[i as usize]
                .iter()
                .map(|&t| params.material.vertex_mass_share(topo.tri_area_ref[t as usize]))
                .sum();
            nodes.set_mass(i, m);
        }
        let mean_edge_m = mesh.mean_edge_length();
        let max_edge_m = edges
            .iter()
            .map(|&(a, b)| (mesh.positions[a as usize] - mesh.positions[b as usize]).norm())
            .fold(0.0, f64::max);
        let interior: Vec<bool> = mesh.boundary_vertices().iter().map(|b| !b).collect();
        Self::assemble(nodes, springs, topo, params, tools, mean_edge_m, max_edge_m, Some(&interior))
    }

    /// Builds a bare model from nodes and springs, without triangles (no surface, no
    /// cutting, no support forces): for analytic checks such as a single oscillator.
    pub fn from_parts(
        positions: &[Vec3],
        masses: &[f64],
        springs: &[(u32, u32, f64, f64)],
        free: Vec<Vec3>,
        params: &MsmParams,
    ) -> Result<Self, MsmBuildError> {
        let mut nodes = Nodes::default();
        for (i, p) in positions.iter().enumerate() {
            nodes.push(*p, Vec3::zeros());
            nodes.set_mass(i as u32, masses[i]);
        }
        nodes.free = free;
        let mut set = SpringSet::with_capacity(springs.len());
        let mut lengths = Vec::new();
        for &(a, b, k, l0) in springs {
            let l_ref = (positions[a as usize] - positions[b as usize]).norm();
            lengths.push(l_ref);
            set.insert(Spring { a, b, k, l0, l_ref });
        }
        let topo = Topology { node_tris: vec![Vec::new(); positions.len()], ..Default::default() };
        let mean = if lengths.is_empty() { 1.0 } else { lengths.iter().sum::<f64>() / lengths.len() as f64 };
        let max = lengths.iter().copied().fold(0.0, f64::max);
        let params = MsmParams { cutting: None, ..*params };
        Self::assemble(nodes, set, topo, &params, Vec::new(), mean.max(1e-6), max, None)
    }

    #[allow(clippy::too_many_arguments)]
    fn assemble(
        mut nodes: Nodes,
        springs: SpringSet,
        topo: Topology,
        params: &MsmParams,
        tools: Vec<ToolShape>,
        mean_edge_m: f64,
        max_edge_m: f64,
        supported: Option<&[bool]>,
    ) -> Result<Self, MsmBuildError> {
        let n = nodes.len();
        for i in 0..n {
            if !nodes.alive[i] || nodes.mass[i] <= 0.0 {
                nodes.free[i] = Vec3::zeros();
            }
        }
        if let Some(supported) = supported {
            // The underlying tissue holds the imported (in-vivo) shape of the interior at
            // rest: a constant support force balances the prestressed springs at each
            // interior node. It vanishes inside a regular flat patch; it carries the
            // discretisation imbalance of irregular meshes and the membrane pressure of
            // curved ones. The border is held by the scene's fixed nodes, or not at all:
            // an unheld border pulls in, as excised skin shrinks.
            super::forces::accumulate(&mut nodes, &springs.list, None, 0.0, &mut Default::default(), None);
            for i in 0..n {
                if supported[i] {
                    nodes.support[i] = -nodes.f[i];
                }
            }
        }
        // The skin meets bodies: the tools, forceps as their two jaws.
        let (scene_tools, (tools, bodies)) = (tools.clone(), crate::tool::bodies::expand(&tools));
        let twins = bodies.as_ref().map_or_else(|| vec![None; tools.len()], crate::tool::bodies::Bodies::twins);
        // Grasp springs as stiff as the holds' under the implicit integrator; under the
        // explicit one, the contact's (what its substeps are stable for).
        let grasp_stiffness = match params.integrator {
            IntegratorChoice::ImplicitEuler { .. } => super::HELD_STIFFNESS_OVER_CONTACT,
            IntegratorChoice::SymplecticEuler { .. } => 1.0,
        };
        let grasps = super::grasp::Grasps::new(&scene_tools, bodies.as_ref(), params.material.thickness_m, mean_edge_m, grasp_stiffness);
        let foundation = params.foundation.map(|f| Foundation::new(f, &nodes, &topo));
        // A tool's contact and the foundation's spring may act on one node together.
        let max_contact_stiffness = tools.iter().map(|t| t.contact_stiffness_n_per_m).fold(0.0, f64::max)
            + foundation.as_ref().map_or(0.0, Foundation::max_node_stiffness);
        let stability = bound_over(&nodes, &springs.list, None, max_contact_stiffness, params.spring_damping_s);
        let integrator = match params.integrator {
            IntegratorChoice::SymplecticEuler { substeps } => {
                check_explicit(params.time_step_s, substeps, &stability)?;
                Integrator::SymplecticEuler { substeps }
            }
            IntegratorChoice::ImplicitEuler { max_iterations, tolerance } => {
                let mut solver = ImplicitSolver::new(max_iterations, tolerance);
                solver.reserve(n, springs.len());
                Integrator::ImplicitEuler(Box::new(solver))
            }
        };
        let cell = mean_edge_m.max(tools.iter().map(|t| t.radius_m).fold(0.0, f64::max));
        let mut grid = PointGrid::new(cell, n);
        for i in 0..n {
            if nodes.alive[i] {
                grid.insert(i as u32, &nodes.x[i]);
            }
        }
        let cutter = params.cutting.map(|(sweep, advance)| {
            // A blade's plate cuts a path as wide as it is thick, not as wide as it is.
            let blade_half_width = tools.iter().filter(|t| t.can_cut).map(|t| t.cut_half_width_m()).fold(0.0, f64::max);
            let cut = CuttingParams {
                sweep_radius_m: sweep.unwrap_or_else(|| blade_half_width.max(0.5 * mean_edge_m)),
                min_advance_m: advance.unwrap_or(1.5 * mean_edge_m),
                vertex_spacing_m: mean_edge_m,
            };
            Cutter::new(cut, tools.len())
        });
        let mut skin = Self {
            dt_s: params.time_step_s,
            material: params.material,
            residual_strain: params.residual_strain,
            mass_damping_per_s: params.mass_damping_per_s,
            spring_damping_s: params.spring_damping_s,
            gravity: params.gravity_m_per_s2,
            foundation,
            fracture_toughness_j_per_m2: params.fracture_toughness_j_per_m2,
            integrator,
            placed: vec![None::<PlacedTool>; tools.len()],
            previous_placed: vec![None::<PlacedTool>; tools.len()],
            swept: vec![None::<PlacedTool>; tools.len()],
            tool_velocity: vec![Vec3::zeros(); tools.len()],
            pierced: vec![false; tools.len()],
            holding: vec![false; tools.len()],
            side_holds: vec![false; tools.len()],
            blade_through: vec![false; tools.len()],
            holes: vec![None; tools.len()],
            holder: super::hold::Holder::new(tools.len(), params.friction, topo.tris.len()),
            side_memory: super::side_hold::SideMemory::with_room(n, topo.tris.len()),
            face_scratch: Vec::new(),
            blade_velocity: vec![Vec3::zeros(); tools.len()],
            cut_reactions: Vec::new(),
            contacts: Vec::new(),
            scene_tools,
            tools,
            bodies,
            twins,
            grasps,
            nodes,
            springs,
            topo,
            grid,
            cutter,
            deltas: Vec::new(),
            topology_version: 0,
            step_index: 0,
            counters: TissueCounters::default(),
            fallbacks: Vec::new(),
            mean_edge_m,
            max_edge_m,
            max_contact_stiffness,
            stability,
            spring_scratch: Default::default(),
            profile: None,
            last_cut_min_angle_deg: None,
            min_cut_angle_deg: None,
        };
        skin.reserve_step_room();
        Ok(skin)
    }

    /// The contact stiffness the stability bound assumes (the stiffest tool's), N/m.
    pub(crate) fn max_contact_stiffness(&self) -> f64 {
        self.max_contact_stiffness
    }
}

fn check_explicit(dt_s: f64, substeps: u32, bound: &StabilityBound) -> Result<(), MsmBuildError> {
    let h = dt_s / f64::from(substeps);
    if h <= bound.max_substep_s {
        return Ok(());
    }
    Err(MsmBuildError::Unstable {
        substep_ms: h * 1e3,
        bound_ms: bound.max_substep_s * 1e3,
        omega: bound.omega_max_rad_s,
        node: bound.stiffest_node,
        min_substeps: (dt_s / bound.max_substep_s).ceil() as u64,
    })
}

/// Builds the mass-spring model a scene describes; errors carry the scene's JSON path.
pub fn build_from_scene(scene: &Scene, spec: &MsmSpec) -> Result<MassSpring, SceneError> {
    let err = |path: &str, message: String| SceneError::new(&scene.origin, path, message);

    let mesh = match &spec.geometry {
        SurfaceGeometry::Patch(p) => {
            let params = PatchParams {
                width_m: p.size_m[0].get(),
                height_m: p.size_m[1].get(),
                cells_x: p.resolution[0].get(),
                cells_y: p.resolution[1].get(),
                jitter: p.jitter.get(),
                seed: p.seed,
            };
            let count = patch::node_count(&params);
            if count > MAX_NODES {
                return Err(err(
                    "model.msm.geometry.patch.resolution",
                    format!("the patch would have {count} nodes; at most {MAX_NODES} are allowed"),
                ));
            }
            patch::generate(&params)
        }
        SurfaceGeometry::Obj(o) => {
            let path = scene.resolve_path(&o.path);
            let mut mesh = obj::read_obj_file(&path).map_err(|e| err("model.msm.geometry.obj.path", e))?;
            mesh.drop_unreferenced_vertices();
            if mesh.positions.len() as u64 > MAX_NODES {
                return Err(err(
                    "model.msm.geometry.obj.path",
                    format!("the mesh has {} vertices; at most {MAX_NODES} are allowed", mesh.positions.len()),
                ));
            }
            let offset = o.offset_m.map_or(Vec3::zeros(), |c| Vec3::new(c[0].get(), c[1].get(), c[2].get()));
            mesh.scale_and_offset(o.scale_m_per_unit.get(), offset);
            mesh
        }
    };
    let geometry_path = match &spec.geometry {
        SurfaceGeometry::Patch(_) => "model.msm.geometry.patch",
        SurfaceGeometry::Obj(_) => "model.msm.geometry.obj",
    };
    mesh.check().map_err(|e| err(geometry_path, format!("the mesh cannot be simulated: {e}")))?;

    let n = mesh.positions.len();
    let mut free = vec![Vec3::repeat(1.0); n];
    let boundary = spec.fixed.iter().any(|f| matches!(f, FixedSpec::Boundary { .. })).then(|| mesh.boundary_vertices());
    for (i, fixed) in spec.fixed.iter().enumerate() {
        let (selected, axes): (Vec<u32>, _) = match fixed {
            FixedSpec::Boundary { axes } => {
                let on = boundary.as_ref().expect("computed above");
                ((0..n as u32).filter(|&v| on[v as usize]).collect(), axes)
            }
            FixedSpec::Box { min_m, max_m, axes } => {
                let lo = Vec3::new(min_m[0].get(), min_m[1].get(), min_m[2].get());
                let hi = Vec3::new(max_m[0].get(), max_m[1].get(), max_m[2].get());
                let inside: Vec<u32> = (0..n as u32)
                    .filter(|&v| (0..3).all(|k| mesh.positions[v as usize][k] >= lo[k] && mesh.positions[v as usize][k] <= hi[k]))
                    .collect();
                if inside.is_empty() {
                    return Err(err(&format!("model.msm.fixed[{i}].box"), "the box holds no node of the mesh".into()));
                }
                (inside, axes)
            }
            FixedSpec::Nodes { indices, axes } => {
                if let Some((j, bad)) = indices.iter().enumerate().find(|(_, v)| **v as usize >= n) {
                    return Err(err(
                        &format!("model.msm.fixed[{i}].nodes.indices[{j}]"),
                        format!("node {bad} does not exist; the mesh has nodes 0 to {}", n - 1),
                    ));
                }
                (indices.clone(), axes)
            }
        };
        for v in selected {
            let f = &mut free[v as usize];
            if axes.x {
                f.x = 0.0;
            }
            if axes.y {
                f.y = 0.0;
            }
            if axes.z {
                f.z = 0.0;
            }
        }
    }

    let tools = crate::tool::tool_shapes(scene);
    let params = MsmParams {
        time_step_s: scene.time_step_s.get(),
        material: MembraneMaterial {
            young_pa: spec.material.young_pa.get(),
            poisson: spec.material.poisson.get(),
            thickness_m: spec.material.thickness_m.get(),
            density_kg_per_m3: spec.material.density_kg_per_m3.get(),
        },
        residual_strain: spec.residual_strain.get(),
        mass_damping_per_s: spec.damping.mass_per_s.get(),
        spring_damping_s: spec.damping.spring_s.get(),
        gravity_m_per_s2: scene.gravity_m_per_s2.map(|g| Vec3::new(g[0].get(), g[1].get(), g[2].get())),
        integrator: match spec.integrator {
            IntegratorSpec::SymplecticEuler { substeps } => IntegratorChoice::SymplecticEuler { substeps: substeps.get() },
            IntegratorSpec::ImplicitEuler { cg_max_iterations, cg_tolerance } => IntegratorChoice::ImplicitEuler {
                max_iterations: cg_max_iterations.get(),
                tolerance: cg_tolerance.get(),
            },
        },
        cutting: spec.cutting.as_ref().map(|c| (c.sweep_radius_m.map(|r| r.get()), c.min_advance_m.map(|a| a.get()))),
        foundation: spec.foundation.as_ref().map(|f| FoundationParams {
            stiffness_pa_per_m: f.stiffness_pa_per_m.get(),
            shear_stiffness_pa_per_m: f.shear_stiffness_pa_per_m.get(),
            normal_damping_pa_s_per_m: f.normal_damping_pa_s_per_m.get(),
            shear_damping_pa_s_per_m: f.shear_damping_pa_s_per_m.get(),
        }),
        fracture_toughness_j_per_m2: spec.material.fracture_toughness_j_per_m2.get(),
        friction: spec.material.friction.map(|f| (f.static_coefficient.get(), f.dynamic_coefficient.get())),
    };
    MassSpring::new(mesh, free, &params, tools).map_err(|e| match e {
        MsmBuildError::Unstable { .. } => err("model.msm.integrator.symplectic-euler.substeps", e.to_string()),
        MsmBuildError::Mesh(m) => err(geometry_path, m),
    })
}

