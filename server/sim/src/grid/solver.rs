//! Dynamics of the branched grid: corotational hexahedra, implicit Euler on the assembled
//! block-sparse system (crate::solver; the elements' blocks kept while their rotations
//! stay put, and the step's system, its diagonal and block-Jacobi inverses made again
//! only where they changed) solved by preconditioned conjugate gradient from a guess extrapolated from
//! the last steps' solutions, Rayleigh damping, lumped or consistent mass, fixed nodes,
//! and penalty contacts whose stiffness enters the solve.
//!
//! Rotation: per element, the polar rotation of its deformation gradient at the centre
//! (the mean of its four x-, y- and z-edges over the cell's sides), by Newton's
//! iteration; inverted elements take the nearest proper rotation from the SVD. It is
//! exact for rigid motions (a rigidly rotated body feels no elastic force). The polar
//! rotation makes the elastic force the gradient of the corotated energy; the QR of the
//! edge frame used before does not, and it pumped energy into nearly incompressible
//! bodies at large deflection (an undamped ν = 0.499 bar sagging under gravity blew up
//! within 0.15 s; the stability sweep in tests/branched_grid.rs covers it).
//!
//! One step of h (linearised backward Euler, rotations frozen over the step):
//! `(M + hC + h²(K_R + K_c)) Δv = h (f(x) − C v − h K_R v − h K_c v)`, `v += Δv`,
//! `x += h v`, with `K_R = R K Rᵀ` per element, `C = αM + βK_R`, `K_c` the contacts'
//! normal stiffness and `f` the elastic, gravity and contact forces (the contacts' with
//! the tools already where they end the step).

use nalgebra::SVector;

use super::hex::Mat24;
use super::topology::Topology;
use crate::math::{Matrix3, Vec3};
use crate::solver::block_sparse::{Block, BlockMatrix, IndexSet, Pattern, Scatter};
use crate::solver::kernels::{Planar24, RowProduct, rotate_and_multiply, rotated_multiply, scatter_element};
use crate::solver::pcg::{Convergence, LinearOperator, Pcg, PcgSettings};
use crate::solver::predictor::Predictor;
use crate::solver::multigrid::VCycle;
use crate::solver::preconditioner::BlockJacobi;
use super::factorization::Factorization;
use super::preconditioning::Multigrid;
pub use super::statics::solve_static;

type Vec24 = SVector<f64, 24>;

/// Velocity change below which the solve has nothing left to do, m/s.
const VELOCITY_FLOOR: f64 = 1e-9;

/// How the mass matrix is used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MassModel {
    /// Row sums on the diagonal: cheaper, slightly more damped high modes.
    Lumped,
    /// The condensed consistent matrix, element by element.
    Consistent,
}

/// What preconditions the solve.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Preconditioning {
    /// The inverse of each node's 3×3 diagonal block: cheap, its iterations grow with
    /// resolution and stiffness.
    Jacobi,
    /// A V-cycle over the grid's coarser levels (see `grid::preconditioning`).
    Multigrid,
    /// A sparse Cholesky factor of a recent step's system (see `grid::factorization`).
    Cholesky,
}

/// Solver settings (scene knobs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverSettings {
    pub dt_s: f64,
    pub cg_max_iterations: u32,
    pub cg_tolerance: f64,
    /// Rayleigh damping: C = α M + β K.
    pub alpha_per_s: f64,
    pub beta_s: f64,
    pub mass: MassModel,
    /// In the grid's frame, m/s².
    pub gravity: Option<Vec3>,
    pub preconditioner: Preconditioning,
}

/// A penalty contact at a point embedded in an element: force `k (depth) n` pushes it
/// out along `n`; its stiffness `k n nᵀ` enters the implicit solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointContact {
    pub element: u32,
    pub weights: [f64; 8],
    pub normal: Vec3,
    pub stiffness: f64,
    /// The contact force, N (already `k · depth · n`, with the tool where it ends the
    /// step).
    pub force: Vec3,
    /// Friction's stick spring across the normal (super::friction): its stiffness, N/m
    /// (0: none, or sliding with a constant force), its force at the step's start, N,
    /// and the tool's velocity its anchor moves with, m/s.
    pub stick_stiffness: f64,
    pub stick_force: Vec3,
    pub tool_velocity: Vec3,
}

impl PointContact {
    /// The point's velocity, interpolated from its element's nodes.
    pub fn point_velocity(&self, topo: &Topology) -> Vec3 {
        embedded_velocity(topo, self.element, &self.weights)
    }

    /// The contact force at the end of a step of h whose velocities `topo` holds (the
    /// linearisation the implicit step solves with: the point moved by h v), N; zero
    /// once it has let go.
    pub fn force_after(&self, topo: &Topology, h: f64) -> Vec3 {
        let along = self.force.dot(&self.normal) - self.stiffness * h * self.point_velocity(topo).dot(&self.normal);
        self.normal * along.max(0.0)
    }
}

/// The velocity of a point embedded in `element` with trilinear `weights`.
pub fn embedded_velocity(topo: &Topology, element: u32, weights: &[f64; 8]) -> Vec3 {
    let nodes = &topo.elements.nodes[element as usize];
    (0..8).map(|i| topo.nodes.v[nodes[i] as usize] * weights[i]).sum()
}

/// Buffers and per-element state of the solver; sized to the topology (resized only when
/// a cut adds nodes or elements).
#[derive(Debug, Clone, Default)]
pub struct Dynamics {
    pub rotations: Vec<Matrix3<f64>>,
    force: Vec<Vec3>,
    b: Vec<Vec3>,
    q: Vec<Vec3>,
    /// The system's diagonal, per axis (the residual's metric).
    diagonal: Vec<Vec3>,
    /// Unknowns the solve moves: alive, not held.
    active: Vec<bool>,
    /// `A = (1 + hα) M + (h² + hβ) K_R + h² K_c`, assembled every step.
    system: BlockMatrix<f32>,
    /// `(h² + hβ) Σ_e K_R(e)`: the elements' part of `system`, kept across steps; element
    /// e's blocks in it were rotated by `scattered[e]` and are rotated again only once
    /// its rotation has moved on by more than [`ROTATION_KEPT`] (see `assemble`).
    stiffness: Vec<Block<f32>>,
    /// Per element: the rotation its blocks in `stiffness` were made with (None: not in).
    scattered: Vec<Option<Matrix3<f64>>>,
    /// `stiffness` holds the elements' part as `scattered` says. False after a step that
    /// assembled straight into `system` (most elements had moved in it and in the step
    /// before: keeping a copy would have cost a pass over the system for nothing); the
    /// next step that would keep blocks remakes the part first.
    stiffness_whole: bool,
    /// Most elements moved in the last step's assembly.
    most_moved_last: bool,
    /// Steps since `stiffness` was last made whole from nothing, and the factor it was
    /// made with.
    stiffness_age: u32,
    stiffness_scale: f64,
    /// `system` changed since `diagonal` and `jacobi` were taken from it: in every
    /// row's diagonal block (`diagonal_whole`) or only in `diagonal_rows`' (a touched-up
    /// assembly, the contacts).
    diagonal_stale: bool,
    diagonal_whole: bool,
    diagonal_rows: IndexSet,
    /// `system` holds the tissue's system for `stiffness` as it stands (the elements'
    /// part, then the mass and the supports at `system_scales`) plus the contacts added
    /// on the blocks in `contacted`: a step that changes few blocks of the elements'
    /// part refreshes only those and the contacted ones (see `assemble`).
    system_kept: bool,
    /// (mass factor, supports' factor) the kept system was made with.
    system_scales: (f64, f64),
    /// The blocks the last step's contacts were added to.
    contacted: IndexSet,
    /// The blocks this step's assembly refreshes (scratch).
    refresh: IndexSet,
    /// An element's stiffness in the world frame (scratch).
    rotated: Box<Planar24>,
    scatter: Scatter,
    /// A cut changed the topology: the next assembly checks the pattern (remade where
    /// the cut changed what it is made from) and makes every value again.
    stale_pattern: bool,
    /// What `system`'s pattern, `scatter` and `first_element` were made from.
    pattern_inputs: PatternInputs,
    /// The elements the pending cut takes voxels from, each with its stiffness before
    /// the cut ([`Self::before_cut`]): what a cut that keeps the pattern takes out of
    /// the kept elements' part before putting the new stiffness in.
    cut_elements: Vec<(u32, Planar24)>,
    jacobi: BlockJacobi,
    multigrid: Multigrid,
    factorization: Factorization,
    /// Each node's rotation (for the Cholesky preconditioner's warp), and the element
    /// it is taken from.
    node_rotations: Vec<Matrix3<f64>>,
    first_element: Vec<u32>,
    /// Scratch of the V-cycle.
    vcycle_scratch: Vec<Vec3>,
    pcg: Pcg,
    /// Δv of the last step; before the next solve, that solve's initial guess.
    pub dv: Vec<Vec3>,
    /// The guess: Δv extrapolated from the last steps' (crate::solver::predictor).
    predictor: Predictor,
    /// How the last solve went.
    pub last: Convergence,
}

impl Dynamics {
    pub fn new(topo: &Topology) -> Self {
        let mut d = Dynamics { stale_pattern: true, multigrid: Multigrid::default(), factorization: Factorization::new(), ..Dynamics::default() };
        d.resize(topo);
        d
    }

    /// Called before a cut takes voxels `removed` out of `topo`: keeps the stiffness
    /// of the elements that hold them, for [`Self::rebuild_pattern`]. Cuts before the
    /// next assembly add to the list, each element kept as it was before the first
    /// (as the kept elements' part still holds it).
    pub fn before_cut(&mut self, topo: &Topology, removed: &[usize]) {
        for &v in removed {
            let e = topo.voxel_element.get(v).copied().unwrap_or(super::topology::NONE);
            if e != super::topology::NONE && !self.cut_elements.iter().any(|(kept, _)| *kept == e) {
                self.cut_elements.push((e, topo.elements.stiffness_single[e as usize]));
            }
        }
    }

    /// Grows the buffers to the topology's node and element counts; the system's pattern
    /// is checked (and remade where the cut changed it) before the next step.
    pub fn resize(&mut self, topo: &Topology) {
        let n = topo.nodes.len();
        for buffer in [&mut self.force, &mut self.b, &mut self.q, &mut self.diagonal, &mut self.dv] {
            buffer.resize(n, Vec3::zeros());
        }
        self.active.resize(n, false);
        self.predictor.resize(n);
        self.rotations.resize(topo.elements.len(), Matrix3::identity());
        self.stale_pattern = true;
        self.multigrid.topology_changed();
    }

    /// Steps that waited for background work (the multigrid's rebuilt hierarchy, a
    /// Cholesky factor).
    pub fn waits(&self) -> u64 {
        self.multigrid.waits + self.factorization.waits
    }

    /// Cholesky factorizations that failed (see `grid::factorization`).
    pub fn factor_failures(&self) -> u64 {
        self.factorization.failures
    }

    /// Forgets the warm start (after a contained blow-up).
    pub fn reset_warm_start(&mut self) {
        self.dv.iter_mut().for_each(|v| *v = Vec3::zeros());
        self.predictor.forget();
    }

    /// Updates every element's rotation from its current corners.
    pub fn update_rotations(&mut self, topo: &Topology) {
        for e in 0..topo.elements.len() {
            if topo.elements.alive[e] {
                let nodes = &topo.elements.nodes[e];
                let x = |n: usize| topo.nodes.x[nodes[n] as usize];
                if let Some(r) = averaged_edge_rotation(&x, &topo.layout.cell_size_m()) {
                    self.rotations[e] = r;
                }
            }
        }
    }

    /// After a cut: the pattern, the scatter and each node's first element made anew
    /// where the cut changed what they are made from (`PatternInputs`), and every value
    /// made again from nothing either way. A cut that only takes voxels out of coarse
    /// elements (each lives on, condensed anew) leaves them as they were: remaking them
    /// took half a millisecond of the next step on the layered abdomen's level 3. The
    /// Cholesky factor in use is dropped with the pattern, kept (and a new one asked
    /// for) with it.
    fn rebuild_pattern(&mut self, topo: &Topology) {
        let cut_elements = std::mem::take(&mut self.cut_elements);
        if self.pattern_inputs.made_from(topo) {
            self.factorization.values_changed();
            if self.take_out_cut_elements(topo, &cut_elements) {
                self.stale_pattern = false;
                return;
            }
            self.system.clear();
        } else {
            self.factorization.topology_changed();
            let pattern = system_pattern(topo);
            self.scatter = Scatter::new(&pattern, &topo.elements.nodes, &topo.elements.alive);
            self.first_element = first_elements(topo);
            self.system = BlockMatrix::zeros(pattern);
            self.pattern_inputs.record(topo);
        }
        let blocks = self.system.pattern.blocks();
        self.stiffness.clear();
        self.stiffness.resize(blocks, [0.0; 12]);
        self.contacted.reset(blocks);
        self.refresh.reset(blocks);
        self.diagonal_rows.reset(topo.nodes.len());
        self.system_kept = false;
        self.diagonal_whole = true;
        self.scattered.clear();
        self.scattered.resize(topo.elements.len(), None);
        self.stiffness_whole = true;
        self.stale_pattern = false;
    }

    /// A cut that kept the pattern changed only the stiffness of the elements it took
    /// voxels from (and the masses at their corners): in a whole elements' part, each
    /// of those is taken out as it was and put back as it is, with the rotation its
    /// blocks were made with, as a re-rotated element is; the step's assembly then
    /// touches up their blocks (mass included) instead of making every value again
    /// (which cost about 0.14 ms on the layered abdomen's level 3, where a cut takes a
    /// voxel from one element of 991). False where that cannot be done: the part is not
    /// whole, or a cut element's blocks are not in it.
    fn take_out_cut_elements(&mut self, topo: &Topology, cut_elements: &[(u32, Planar24)]) -> bool {
        let in_part = |e: u32| topo.elements.alive.get(e as usize) == Some(&true) && self.scattered.get(e as usize).is_some_and(Option::is_some);
        if !self.stiffness_whole || cut_elements.is_empty() || !cut_elements.iter().all(|&(e, _)| in_part(e)) {
            return false;
        }
        let scale = self.stiffness_scale as f32;
        let (zero, mut unused) = ([0f32; 24], [0f32; 24]);
        for (e, before) in cut_elements {
            // The rotation its blocks in the part were made with (checked above).
            let r = self.scattered[*e as usize].expect("a cut element in the part");
            let (rf, blocks) = (single_rotation(&r), &self.scatter.blocks[*e as usize]);
            for (k, sign) in [(before, -1.0), (&topo.elements.stiffness_single[*e as usize], 1.0)] {
                rotate_and_multiply(k, &rf, &zero, &mut self.rotated, &mut unused);
                scatter_element(&mut self.stiffness, blocks, &self.rotated, sign * scale, 0);
            }
            if self.system_kept {
                blocks.iter().for_each(|&b| self.refresh.insert(b));
            }
        }
        true
    }

    /// The step's system without the tools (rotations, element blocks, mass, supports)
    /// into `system`, and the forces f_el − (β + h) K_R v, gravity and supports into
    /// `force`; which nodes are active.
    fn assemble(&mut self, topo: &mut Topology, settings: &SolverSettings) {
        if self.stale_pattern {
            self.rebuild_pattern(topo);
        }
        let h = settings.dt_s;
        let a_mass = 1.0 + h * settings.alpha_per_s;
        let a_stiff = h * settings.beta_s + h * h;
        let a_contact = h * h;
        let n = topo.nodes.len();
        for i in 0..n {
            self.force[i] = Vec3::zeros();
            self.active[i] = coupled(topo, i);
        }
        // The elements' blocks are kept from step to step: an element's are taken out
        // and put back rotated anew only once its rotation has moved by more than
        // ROTATION_KEPT since they were made (most of a body at rest or moving rigidly
        // in small steps keeps them). The whole part is made again from nothing every
        // STIFFNESS_REMADE steps (the f32 round-off of taking blocks out and putting
        // them back does not accumulate), and when over a third of the elements moved
        // (taking one out and putting it back costs twice making it, keeping one a fifth:
        // beyond about 0.44 keeping costs more). The forces take the rotation of now.
        let cell_m = topo.layout.cell_size_m();
        let (mut alive, mut moved) = (0usize, 0usize);
        for e in 0..topo.elements.len() {
            if !topo.elements.alive[e] {
                continue;
            }
            let nodes = &topo.elements.nodes[e];
            if let Some(r) = averaged_edge_rotation(&|n: usize| topo.nodes.x[nodes[n] as usize], &cell_m) {
                self.rotations[e] = r;
            }
            alive += 1;
            moved += usize::from(self.scattered[e].is_none_or(|before| (self.rotations[e] - before).amax() > ROTATION_KEPT));
        }
        let most_moved = 3 * moved > alive;
        let remake = !self.stiffness_whole || self.stiffness_age >= STIFFNESS_REMADE || self.stiffness_scale != a_stiff || most_moved;
        // When most elements moved in this step and the last (a body deforming or
        // turning throughout: the level-0 cantilever sagging), nothing is kept: their
        // blocks go straight into the step's system (the same sums in the same order as
        // into `stiffness` and a copy, so the same bits; the copy was 3–5 % of such a
        // step), and `stiffness` is remade when keeping pays again.
        let direct = remake && most_moved && self.most_moved_last;
        self.most_moved_last = most_moved;
        // When the elements' part is only touched up (not remade), the step's system is
        // the last one with the blocks that changed made again: those of the elements
        // re-rotated now and those the last contacts were added to. Each is made as the
        // whole assembly makes it (its part, its mass, its supports, in that order), so
        // the bits are those of the whole assembly. The consistent mass touches every
        // block: it takes the whole assembly.
        let consistent = settings.mass == MassModel::Consistent;
        let scales = (a_mass, a_contact);
        let touch_up = !remake && !consistent && self.system_kept && self.system_scales == scales;
        if remake {
            // Not zeroed whole: every live element stores the blocks it writes first
            // (`Scatter::first`), and only the blocks none of them writes are zeroed
            // here. The scatter was made for the live elements of now: elements die
            // only by cuts, which remake it (`resize`) before the next step.
            debug_assert!((0..topo.elements.len()).all(|e| topo.elements.alive[e] || self.scatter.first[e] == 0), "the scatter is of the live elements");
            let part = if direct { &mut self.system.values } else { &mut self.stiffness };
            for &b in &self.scatter.unwritten {
                part[b as usize] = [0.0; 12];
            }
            self.scattered.iter_mut().for_each(|r| *r = None);
            self.stiffness_age = 0;
            self.stiffness_scale = a_stiff;
            self.stiffness_whole = !direct;
        }
        self.stiffness_age += 1;
        // One pass over the elements: f_el − (β + h) K_R v, and the element's blocks of
        // the system where they moved.
        let damping = settings.beta_s + h;
        for e in 0..topo.elements.len() {
            if !topo.elements.alive[e] {
                continue;
            }
            let nodes = &topo.elements.nodes[e];
            let r = self.rotations[e];
            let k = &topo.elements.stiffness_single[e];
            let d = world_displacement(topo, e, &r, damping);
            let rf = single_rotation(&r);
            let mut f = [0f32; 24];
            let blocks = &self.scatter.blocks[e];
            match self.scattered[e] {
                Some(before) if (r - before).amax() <= ROTATION_KEPT => rotated_multiply(k, &rf, &d, &mut f),
                before => {
                    let rotated = &mut *self.rotated;
                    let part = if direct { &mut self.system.values } else { &mut self.stiffness };
                    if let Some(before) = before {
                        let mut unused = [0f32; 24];
                        rotate_and_multiply(k, &single_rotation(&before), &d, rotated, &mut unused);
                        scatter_element(part, blocks, rotated, -(a_stiff as f32), 0);
                    }
                    // On a remake, each element is scattered once, in order.
                    let first = if remake { self.scatter.first[e] } else { 0 };
                    rotate_and_multiply(k, &rf, &d, rotated, &mut f);
                    scatter_element(part, blocks, rotated, a_stiff as f32, first);
                    self.scattered[e] = Some(r);
                    if touch_up {
                        blocks.iter().for_each(|&b| self.refresh.insert(b));
                    }
                }
            }
            for c in 0..8 {
                self.force[nodes[c] as usize] -= Vec3::new(f64::from(f[3 * c]), f64::from(f[3 * c + 1]), f64::from(f[3 * c + 2]));
            }
        }
        // The step's system: the elements' part, then the mass, the supports and (later)
        // the contacts; touched up where few blocks changed (a quarter of the blocks
        // costs about what a whole copy does).
        if touch_up {
            let (refresh, contacted) = (&mut self.refresh, &self.contacted);
            contacted.iter().for_each(|b| refresh.insert(b));
        }
        let partial = touch_up && 4 * self.refresh.len() <= self.stiffness.len();
        self.diagonal_whole |= !partial;
        if partial {
            for b in self.refresh.iter() {
                self.system.values[b as usize] = self.stiffness[b as usize];
            }
        } else if !direct {
            self.system.values.copy_from_slice(&self.stiffness);
        }
        if consistent {
            for e in (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]) {
                let (blocks, m) = (&self.scatter.blocks[e], &topo.elements.mass[e]);
                for i in 0..8 {
                    for j in 0..8 {
                        self.system.add_diagonal(blocks[8 * i + j] as usize, Vec3::repeat(a_mass * m[(i, j)]));
                    }
                }
            }
        } else {
            for i in 0..n {
                let at = self.system.pattern.diag[i];
                if !partial || self.refresh.contains(at) {
                    self.system.add_diagonal(at as usize, Vec3::repeat(a_mass * topo.nodes.mass[i]));
                    if partial {
                        self.diagonal_rows.insert(i as u32);
                    }
                }
            }
        }
        if let Some(g) = settings.gravity {
            for i in 0..n {
                self.force[i] += g * topo.nodes.mass[i];
            }
        }
        // The supports' springs at coarse levels (super::support), linearised like the
        // contacts: their stiffness in the element's blocks, −h K_s v in the force.
        topo.supports.add_forces(topo, h, &mut self.force);
        let (system, scatter, refresh) = (&mut self.system, &self.scatter, &self.refresh);
        topo.supports.for_each_block(topo, a_contact, |e, i, j, block| {
            let b = scatter.blocks[e][8 * i + j];
            if !partial || refresh.contains(b) {
                system.add(b as usize, &block);
            }
        });
        self.refresh.clear();
        self.contacted.clear();
        self.system_kept = true;
        self.system_scales = scales;
    }

    /// The tools' contacts into the assembled system and force.
    fn add_contacts(&mut self, topo: &Topology, settings: &SolverSettings, contacts: &[PointContact]) {
        let h = settings.dt_s;
        let a_contact = h * h;
        for c in contacts {
            let nodes = &topo.elements.nodes[c.element as usize];
            let blocks = &self.scatter.blocks[c.element as usize];
            let across = super::friction::tangent_projection(&c.normal);
            let nn = (c.normal * c.normal.transpose() * c.stiffness + across * c.stick_stiffness) * a_contact;
            // The contact force at the step's end, linearised: f_c − h k ((v + Δv)·n) n (the
            // tool is already where it ends the step); the Δv term is the h² K_c in the
            // matrix, the v term goes on the right-hand side. Friction's stick spring
            // likewise, its anchor moving with the tool: f_t − h k_t P (v + Δv − u).
            let v = c.point_velocity(topo);
            let approach = -c.normal * (h * c.stiffness * v.dot(&c.normal)) + c.stick_force - across * (v - c.tool_velocity) * (h * c.stick_stiffness);
            for i in 0..8 {
                self.diagonal_rows.insert(nodes[i]);
                self.force[nodes[i] as usize] += (c.force + approach) * c.weights[i];
                for j in 0..8 {
                    self.system.add(blocks[8 * i + j] as usize, &(nn * (c.weights[i] * c.weights[j])));
                    self.contacted.insert(blocks[8 * i + j]);
                }
            }
        }
    }

    /// Does the preconditioner's first heavy work now, from the model as it stands (at
    /// load: at rest, no contacts), so that no step does it on the physics thread: the
    /// Cholesky preconditioner's first factor, the multigrid's coarse grids. Block
    /// Jacobi has none.
    pub fn prime(&mut self, topo: &mut Topology, settings: &SolverSettings) {
        match settings.preconditioner {
            Preconditioning::Jacobi => {}
            Preconditioning::Cholesky => {
                self.assemble(topo, settings);
                node_rotations_into(&self.first_element, &self.rotations, &mut self.node_rotations);
                self.factorization.prime(&self.system, &self.active, &topo.nodes.rest, &self.node_rotations, settings.dt_s);
            }
            Preconditioning::Multigrid => {
                self.assemble(topo, settings);
                self.multigrid.prime(topo, &self.active, settings.dt_s);
            }
        }
    }

    /// A step is taken in three parts: [`Self::assemble_tissue`], then
    /// [`Self::solve_with_contacts`] (Δv into `dv`, `last` says how the solve went), then
    /// [`Self::finish_step`] (the state moves). Between the first two the tissue's own
    /// system answers [`Self::compliance`] queries.
    ///
    /// The first part: the system of the tissue alone, the tools' contacts not in it yet.
    pub fn assemble_tissue(&mut self, topo: &mut Topology, settings: &SolverSettings) {
        self.assemble(topo, settings);
        self.diagonal_stale = true;
    }

    /// The second part of a step: the contacts into the system, then the solve.
    pub fn solve_with_contacts(&mut self, topo: &Topology, settings: &SolverSettings, contacts: &[PointContact], step: u64) {
        if !contacts.is_empty() {
            self.add_contacts(topo, settings, contacts);
            self.diagonal_stale = true;
        }
        let h = settings.dt_s;
        let n = topo.nodes.len();
        // b = h (f − αM v − (β + h) K_R v); the last term is already in `force`.
        mass_times(topo, settings.mass, &topo.nodes.v, &mut self.q);
        for i in 0..n {
            self.b[i] = if self.active[i] { (self.force[i] - self.q[i] * settings.alpha_per_s) * h } else { Vec3::zeros() };
        }
        let pcg_settings = PcgSettings { max_iterations: settings.cg_max_iterations, tolerance: settings.cg_tolerance, floor: VELOCITY_FLOOR, stalled_after: 0 };
        self.predictor.predict(&mut self.dv[..n]);
        self.last = self.solve_b(topo, settings, step, &pcg_settings, Unknown::VelocityChange);
    }

    /// How far constant nodal forces `f` (N) move the nodes over one step of the
    /// tissue's system as [`Self::assemble_tissue`] left it: `x = h² A⁻¹ f` (m; held and
    /// dead nodes do not move), solved with the step's preconditioner to its cap and a
    /// tolerance of at most [`COMPLIANCE_TOLERANCE`]. The compliance a multirate haptic
    /// loop renders contact against (crate::multirate).
    pub fn compliance(&mut self, topo: &Topology, settings: &SolverSettings, step: u64, f: &[Vec3], x: &mut [Vec3]) -> Convergence {
        let h = settings.dt_s;
        for (i, (b, q)) in self.b.iter_mut().zip(self.q.iter_mut()).enumerate().take(topo.nodes.len()) {
            *b = if self.active[i] { f[i] * h } else { Vec3::zeros() };
            *q = Vec3::zeros();
        }
        // A compliance the haptic loop renders against needs three digits, not the
        // state's tolerance; and no absolute floor: a unit force's velocity change may be
        // far below the state's.
        let pcg_settings = PcgSettings { max_iterations: settings.cg_max_iterations, tolerance: settings.cg_tolerance.max(COMPLIANCE_TOLERANCE), floor: 0.0, stalled_after: 0 };
        let convergence = self.solve_b(topo, settings, step, &pcg_settings, Unknown::Scratch);
        for (x, q) in x.iter_mut().zip(&self.q) {
            *x = q * h;
        }
        convergence
    }

    /// Solves the assembled system for `b` into `dv` (warm-started) or the scratch `q`
    /// (from zero), preconditioned as the settings say.
    fn solve_b(&mut self, topo: &Topology, settings: &SolverSettings, step: u64, pcg_settings: &PcgSettings, unknown: Unknown) -> Convergence {
        if std::mem::take(&mut self.diagonal_stale) {
            self.refresh_diagonal(topo);
        }
        let h = settings.dt_s;
        let a_mass = 1.0 + h * settings.alpha_per_s;
        let a_stiff = h * settings.beta_s + h * h;
        let Dynamics { system, active, jacobi, multigrid, factorization, node_rotations, first_element, rotations, vcycle_scratch, pcg, b, dv, q, diagonal, .. } = self;
        let x = match unknown {
            Unknown::VelocityChange => dv,
            Unknown::Scratch => q,
        };
        let operator = Assembled { matrix: system, active };
        let hierarchy = match settings.preconditioner {
            Preconditioning::Multigrid => multigrid.prepare(step, topo, active, rotations, a_mass, a_stiff),
            Preconditioning::Jacobi | Preconditioning::Cholesky => None,
        };
        let factor = match settings.preconditioner {
            Preconditioning::Cholesky => {
                node_rotations_into(first_element, rotations, node_rotations);
                factorization.prepare(step, system, active, node_rotations)
            }
            _ => None,
        };
        match (hierarchy, factor) {
            (_, Some(factor)) => {
                let convergence = pcg.solve(&operator, &factor, b, x, active, diagonal, pcg_settings);
                factorization.solved(step, convergence.iterations);
                convergence
            }
            (Some(hierarchy), None) => {
                let vcycle = VCycle {
                    hierarchy: std::cell::RefCell::new(hierarchy),
                    matrix: system,
                    smoother: jacobi,
                    active,
                    scratch: std::cell::RefCell::new(vcycle_scratch),
                };
                pcg.solve(&operator, &vcycle, b, x, active, diagonal, pcg_settings)
            }
            (None, None) => pcg.solve(&operator, jacobi, b, x, active, diagonal, pcg_settings),
        }
    }

    /// The system's diagonal (the residual's metric) and its block-Jacobi inverse, once
    /// per change of the system before a solve needs them.
    fn refresh_diagonal(&mut self, topo: &Topology) {
        if std::mem::take(&mut self.diagonal_whole) {
            for i in 0..topo.nodes.len() {
                self.diagonal[i] = self.system.diagonal(i);
            }
            self.jacobi.update(&self.system, &self.active);
        } else {
            for i in self.diagonal_rows.iter() {
                self.diagonal[i as usize] = self.system.diagonal(i as usize);
            }
            self.jacobi.update_rows(&self.system, &self.active, self.diagonal_rows.iter().map(|i| i as usize));
        }
        self.diagonal_rows.clear();
    }

    /// The third part of a step: hands the system to the Cholesky worker when it is due
    /// a factor, then moves the state by Δv. Returns the max |Δv| (not finite on a
    /// blow-up).
    pub fn finish_step(&mut self, topo: &mut Topology, settings: &SolverSettings, step: u64) -> f64 {
        if settings.preconditioner == Preconditioning::Cholesky {
            // A system handed to the worker leaves a spare buffer in its place.
            if self.factorization.after_solve(step, &mut self.system, &self.active, &topo.nodes.rest, &self.node_rotations) {
                self.system_kept = false;
            }
        }
        let h = settings.dt_s;
        let mut max_dv: f64 = 0.0;
        for i in 0..topo.nodes.len() {
            if !self.active[i] {
                topo.nodes.v[i] = Vec3::zeros();
                continue;
            }
            let dv = self.dv[i];
            max_dv = max_dv.max(dv.amax());
            if !dv.iter().all(|c| c.is_finite()) {
                max_dv = f64::NAN;
            }
            topo.nodes.v[i] += dv;
            topo.nodes.x[i] += topo.nodes.v[i] * h;
        }
        max_dv
    }
}

/// How far (largest entry of the difference) an element's rotation may move from the
/// one its blocks in the system were made with before they are made again: the step's
/// linearisation already freezes rotations over the step, and 1e-4 rad is a fraction of
/// what an element turns in a step of a body in motion.
pub const ROTATION_KEPT: f64 = 1e-4;

/// Steps after which the elements' part of the system is made whole again.
pub const STIFFNESS_REMADE: u32 = 256;

/// The relative residual a compliance query is solved to (see `Dynamics::compliance`).
pub const COMPLIANCE_TOLERANCE: f64 = 1e-3;

/// Which vector a solve of the assembled system fills.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Unknown {
    /// `dv`, from its warm start: the step's solve.
    VelocityChange,
    /// The scratch `q`, from zero: a compliance query.
    Scratch,
}

/// What the system's pattern is made from: every element's corners and whether it
/// lives, every node's coupling ([`coupled`]). A cut that leaves all three leaves the
/// pattern, the scatter and the first elements as they are.
#[derive(Debug, Clone, Default, PartialEq)]
struct PatternInputs {
    element_nodes: Vec<[u32; 8]>,
    element_alive: Vec<bool>,
    coupled: Vec<bool>,
}

impl PatternInputs {
    fn made_from(&self, topo: &Topology) -> bool {
        self.element_nodes == topo.elements.nodes && self.element_alive == topo.elements.alive && self.coupled.len() == topo.nodes.len() && (0..topo.nodes.len()).all(|n| self.coupled[n] == coupled(topo, n))
    }

    fn record(&mut self, topo: &Topology) {
        self.element_nodes.clone_from(&topo.elements.nodes);
        self.element_alive.clone_from(&topo.elements.alive);
        self.coupled.clear();
        self.coupled.extend((0..topo.nodes.len()).map(|n| coupled(topo, n)));
    }
}

/// Whether node `n` is coupled to its neighbours in the system: alive and not held (a
/// held node's unknown is zero).
fn coupled(topo: &Topology, n: usize) -> bool {
    topo.nodes.alive[n] && !topo.nodes.fixed[n]
}

/// The pattern of the step's system: every pair of nodes sharing a live element, except
/// that held nodes' unknowns are zero: their couplings would only multiply zeros (on the
/// layered abdomen a third of the nodes are held), so they keep their diagonal alone.
pub fn system_pattern(topo: &Topology) -> Pattern {
    let live = (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]).map(|e| &topo.elements.nodes[e][..]);
    Pattern::from_elements_coupling(topo.nodes.len(), live, |n| coupled(topo, n as usize))
}

/// A rotation in single precision, as the element kernels take it.
fn single_rotation(r: &Matrix3<f64>) -> [[f32; 3]; 3] {
    std::array::from_fn(|p| std::array::from_fn(|q| r[(p, q)] as f32))
}

/// An assembled system as the solver's operator, on its active rows: the step's (in
/// single precision) and the static problem's (`super::statics`, in double).
pub(super) struct Assembled<'a, T: RowProduct> {
    pub matrix: &'a BlockMatrix<T>,
    pub active: &'a [bool],
}

impl<T: RowProduct> LinearOperator for Assembled<'_, T> {
    fn apply(&self, x: &[Vec3], y: &mut [Vec3]) -> f64 {
        self.matrix.multiply(x, y, self.active)
    }
}

/// The rotation of an element: the polar rotation of its deformation gradient at the
/// centre, `F = [Σ x-edges / 4a, Σ y-edges / 4b, Σ z-edges / 4c]` for a cell of sides
/// (a, b, c); `x(n)` is corner n's position. See [`nearest_rotation`].
pub fn averaged_edge_rotation(x: &impl Fn(usize) -> Vec3, cell_m: &Vec3) -> Option<Matrix3<f64>> {
    // Each corner read once, not once for each of its three edges: a fifth of the
    // element rotations' time on the layered abdomen (the same sums, the same bits).
    let corners: [Vec3; 8] = std::array::from_fn(x);
    let mut edges = [Vec3::zeros(); 3];
    for (a, edge) in edges.iter_mut().enumerate() {
        for n in 0..8 {
            if (n >> a) & 1 == 0 {
                *edge += corners[n | (1 << a)] - corners[n];
            }
        }
        *edge /= 4.0 * cell_m[a];
    }
    nearest_rotation(&Matrix3::from_columns(&edges))
}

/// The polar rotation of `f`: Newton's iteration `R ← (R + R⁻ᵀ)/2` converges
/// quadratically; an inverted or collapsed `f` (det ≤ 1e-6) takes the proper rotation
/// nearest it from the SVD instead. None when that is undefined.
fn nearest_rotation(f: &Matrix3<f64>) -> Option<Matrix3<f64>> {
    if f.determinant() > 1e-6 {
        let mut r = *f;
        for _ in 0..20 {
            let Some(inverse) = r.try_inverse() else { break };
            let next = (r + inverse.transpose()) * 0.5;
            let change = (next - r).amax();
            r = next;
            // Quadratic convergence: the new iterate is off by about change²/2, so a
            // change below 1e-6 leaves it within 1e-12 (one iteration fewer than
            // waiting for the change itself to fall that low).
            if change < 1e-6 {
                break;
            }
        }
        if r.iter().all(|c| c.is_finite()) && (r.determinant() - 1.0).abs() < 1e-6 {
            return Some(r);
        }
    }
    // Inverted or collapsed: the rotation nearest F among proper rotations, from the
    // SVD with the smallest singular direction flipped (Irving et al. 2004), so the
    // element pushes back out of inversion instead of settling into it.
    let svd = f.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut smallest = 0;
    for k in 1..3 {
        if svd.singular_values[k] < svd.singular_values[smallest] {
            smallest = k;
        }
    }
    let mut flip = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        flip[(smallest, smallest)] = -1.0;
    }
    let r = u * flip * v_t;
    r.iter().all(|c| c.is_finite()).then_some(r)
}

/// Per node, the first live element holding it ([`super::topology::NONE`] for a node
/// without any): whose rotation the node takes for the Cholesky preconditioner's warp.
/// One element's rotation is as good for that as the mean of all of them (the same
/// iteration counts) and needs no polar decomposition per node. Made once per
/// topology, with the pattern.
fn first_elements(topo: &Topology) -> Vec<u32> {
    let mut first = vec![super::topology::NONE; topo.nodes.len()];
    for e in (0..topo.elements.len()).rev().filter(|&e| topo.elements.alive[e]) {
        for &n in &topo.elements.nodes[e] {
            first[n as usize] = e as u32;
        }
    }
    first
}

/// Each node's rotation, from the element [`first_elements`] gave it (the identity for
/// a node without one).
fn node_rotations_into(first_element: &[u32], element_rotations: &[Matrix3<f64>], out: &mut Vec<Matrix3<f64>>) {
    out.clear();
    out.extend(first_element.iter().map(|&e| if e == super::topology::NONE { Matrix3::identity() } else { element_rotations[e as usize] }));
}

/// Element `e`'s displacement in its rotated frame, `Rᵀ(x − x₀) − (X − X₀)` per corner
/// (corner 0 as the reference), plus `damping · Rᵀv` (the step's (β + h) K_R v term;
/// 0 for the elastic force alone). Rest offsets come from the nodes' own rest positions,
/// so a body at rest has exactly zero strain.
fn local_displacement(topo: &Topology, e: usize, r: &Matrix3<f64>, damping: f64) -> Vec24 {
    let nodes = &topo.elements.nodes[e];
    let rt = r.transpose();
    let (x0, rest0) = (topo.nodes.x[nodes[0] as usize], topo.nodes.rest[nodes[0] as usize]);
    let mut u = Vec24::zeros();
    for c in 0..8 {
        let node = nodes[c] as usize;
        let local = rt * (topo.nodes.x[node] - x0) - (topo.nodes.rest[node] - rest0) + rt * topo.nodes.v[node] * damping;
        u.fixed_rows_mut::<3>(3 * c).copy_from(&local);
    }
    u
}

/// Element `e`'s displacement in the world frame from its rotated rest shape,
/// `(x − x₀) − R(X − X₀)` per corner (corner 0 as the reference), plus `damping · v`
/// (the step's (β + h) K_R v term): `K_R` times it is the elastic force (and that term).
fn world_displacement(topo: &Topology, e: usize, r: &Matrix3<f64>, damping: f64) -> [f32; 24] {
    let nodes = &topo.elements.nodes[e];
    let (x0, rest0) = (topo.nodes.x[nodes[0] as usize], topo.nodes.rest[nodes[0] as usize]);
    let mut d = [0f32; 24];
    for c in 0..8 {
        let node = nodes[c] as usize;
        let w = (topo.nodes.x[node] - x0) - r * (topo.nodes.rest[node] - rest0) + topo.nodes.v[node] * damping;
        d[3 * c] = w.x as f32;
        d[3 * c + 1] = w.y as f32;
        d[3 * c + 2] = w.z as f32;
    }
    d
}

/// Adds −R K (Rᵀ(x − x₀) − (X − X₀)) of every element (corner 0 as the reference), with
/// the same kernel and rotations as the step.
pub fn add_elastic_forces(topo: &Topology, rotations: &[Matrix3<f64>], force: &mut [Vec3]) {
    for e in 0..topo.elements.len() {
        if !topo.elements.alive[e] {
            continue;
        }
        let nodes = &topo.elements.nodes[e];
        let r = &rotations[e];
        let f = mat_vec(&topo.elements.stiffness[e], &local_displacement(topo, e, r, 0.0));
        for c in 0..8 {
            force[nodes[c] as usize] -= r * f.fixed_rows::<3>(3 * c);
        }
    }
}

/// out = K_R x (out is overwritten).
pub fn stiffness_times(topo: &Topology, rotations: &[Matrix3<f64>], x: &[Vec3], out: &mut [Vec3]) {
    rotated_product(topo, rotations, x, out, |e, u| mat_vec(&topo.elements.stiffness[e], u));
}

/// `out = Σ_e R_e P_e(R_eᵀ x_e)` for a per-element product `P_e` (out is overwritten).
fn rotated_product(topo: &Topology, rotations: &[Matrix3<f64>], x: &[Vec3], out: &mut [Vec3], product: impl Fn(usize, &Vec24) -> Vec24) {
    out.iter_mut().for_each(|o| *o = Vec3::zeros());
    for e in 0..topo.elements.len() {
        if !topo.elements.alive[e] {
            continue;
        }
        let nodes = &topo.elements.nodes[e];
        let r = &rotations[e];
        let mut u = Vec24::zeros();
        for c in 0..8 {
            u.fixed_rows_mut::<3>(3 * c).copy_from(&(r.transpose() * x[nodes[c] as usize]));
        }
        let f = product(e, &u);
        for c in 0..8 {
            out[nodes[c] as usize] += r * f.fixed_rows::<3>(3 * c);
        }
    }
}

/// `K u`, column by column (axpy over contiguous columns vectorises; no reassociation).
fn mat_vec(k: &Mat24, u: &Vec24) -> Vec24 {
    let k = k.as_slice();
    let mut f = Vec24::zeros();
    for j in 0..24 {
        let uj = u[j];
        let column = &k[24 * j..24 * j + 24];
        for i in 0..24 {
            f[i] += column[i] * uj;
        }
    }
    f
}

/// out = M x (out is overwritten).
pub fn mass_times(topo: &Topology, model: MassModel, x: &[Vec3], out: &mut [Vec3]) {
    match model {
        MassModel::Lumped => {
            for n in 0..topo.nodes.len() {
                out[n] = x[n] * topo.nodes.mass[n];
            }
        }
        MassModel::Consistent => {
            out.iter_mut().for_each(|o| *o = Vec3::zeros());
            for e in 0..topo.elements.len() {
                if !topo.elements.alive[e] {
                    continue;
                }
                let nodes = &topo.elements.nodes[e];
                let m = &topo.elements.mass[e];
                for i in 0..8 {
                    let mut sum = Vec3::zeros();
                    for j in 0..8 {
                        sum += x[nodes[j] as usize] * m[(i, j)];
                    }
                    out[nodes[i] as usize] += sum;
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::condense::{Volumetric, VoxelMatrices};
    use crate::grid::topology::Layout;
    use crate::volume::procedural::solid_box;

    /// A 16 × 8 × 8 mm bar of 1 mm voxels at level 1 (2 mm elements), nothing held.
    fn bar() -> Topology {
        let volume = solid_box([0.016, 0.008, 0.008], 0.001, 1);
        let layout = Layout::new(volume.dims, 1, volume.spacing_m);
        let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
        Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(1e4, 0.4, 1000.0)], Volumetric::MeanDilatation))
    }

    fn settings() -> SolverSettings {
        SolverSettings { dt_s: 1e-3, cg_max_iterations: 100, cg_tolerance: 1e-8, alpha_per_s: 0.0, beta_s: 0.0, mass: MassModel::Lumped, gravity: None, preconditioner: Preconditioning::Jacobi }
    }

    /// Turns every node rigidly by `angle` about z through the bar's first node.
    fn turn(topo: &mut Topology, angle: f64) {
        let r = nalgebra::Rotation3::from_axis_angle(&Vec3::z_axis(), angle);
        let centre = topo.nodes.rest[0];
        for i in 0..topo.nodes.len() {
            topo.nodes.x[i] = centre + r * (topo.nodes.rest[i] - centre);
        }
    }

    /// A new solver that has assembled `topo`'s system once.
    fn new_assembled(topo: &mut Topology, settings: &SolverSettings) -> Dynamics {
        let mut d = Dynamics::new(topo);
        d.assemble(topo, settings);
        d
    }

    /// The largest difference between two systems' blocks over their largest entry.
    fn relative_difference(a: &BlockMatrix<f32>, b: &BlockMatrix<f32>) -> f64 {
        let largest = a.values.iter().flatten().fold(0f32, |m, v| m.max(v.abs()));
        let differs = a.values.iter().flatten().zip(b.values.iter().flatten()).fold(0f32, |m, (x, y)| m.max((x - y).abs()));
        f64::from(differs / largest)
    }

    #[test]
    fn element_blocks_are_kept_while_their_rotation_stays_within_its_tolerance_and_made_again_after() {
        let settings = settings();
        let mut topo = bar();
        let mut kept = Dynamics::new(&topo);
        kept.assemble(&mut topo, &settings);
        // Turned by a third of the tolerance: the blocks are the ones made at rest, a
        // fresh assembly differs by about the angle, and a rigid turn still feels no
        // elastic force (the forces take the rotation of now).
        turn(&mut topo, ROTATION_KEPT / 3.0);
        let at_rest = kept.system.clone();
        kept.assemble(&mut topo, &settings);
        assert_eq!(kept.system, at_rest, "the blocks made at rest are kept");
        let fresh = new_assembled(&mut topo, &settings);
        let off = relative_difference(&kept.system, &fresh.system);
        assert!(off > 0.0 && off < 2.0 * ROTATION_KEPT, "kept blocks {off:e} off a fresh assembly");
        let largest_force = kept.force.iter().map(|f| f.amax()).fold(0.0, f64::max);
        let scale = topo.elements.stiffness[0].amax() * 1e-3;
        assert!(largest_force < 1e-5 * scale, "a rigid turn makes {largest_force:e} N of elastic force");
        // Turned by three times the tolerance: every element's blocks are made again, the
        // same as a fresh assembly's to the single-precision round-off of taking the old
        // ones out.
        turn(&mut topo, 3.0 * ROTATION_KEPT);
        kept.assemble(&mut topo, &settings);
        let fresh = new_assembled(&mut topo, &settings);
        let off = relative_difference(&kept.system, &fresh.system);
        assert!(off < 1e-6, "blocks made again {off:e} off a fresh assembly");
    }

    #[test]
    fn the_kept_elements_part_is_made_whole_again_at_its_appointed_steps() {
        let settings = settings();
        let mut topo = bar();
        let mut kept = Dynamics::new(&topo);
        // Turning a quarter of the bar (its far end) a little further every step, by
        // more than the tolerance each time: its blocks taken out and put back every
        // step, then the whole part remade from nothing at the appointed step.
        let r_of = |angle: f64| nalgebra::Rotation3::from_axis_angle(&Vec3::z_axis(), angle);
        // (Nodes from x = 14 mm: the last two of eight element columns turn or bend.)
        let far = |x: f64| x > 0.014 - 1e-9;
        for step in 0..STIFFNESS_REMADE + 1 {
            let r = r_of(2.0 * ROTATION_KEPT * f64::from(step));
            for i in 0..topo.nodes.len() {
                let rest = topo.nodes.rest[i];
                topo.nodes.x[i] = if far(rest.x) { r * rest } else { rest };
            }
            kept.assemble(&mut topo, &settings);
            assert_eq!(kept.stiffness_age, if step == STIFFNESS_REMADE { 1 } else { step + 1 }, "step {step}");
            if step == 100 {
                // Taken out and put back a hundred times: within round-off of fresh.
                let fresh = new_assembled(&mut topo, &settings);
                let off = relative_difference(&kept.system, &fresh.system);
                assert!(off < 1e-5, "after 100 updates {off:e} off a fresh assembly");
            }
        }
        let fresh = new_assembled(&mut topo, &settings);
        assert_eq!(kept.system, fresh.system, "made from nothing, as a fresh assembly");
        // When most elements turned, the whole part is made from nothing at once.
        turn(&mut topo, 0.1);
        kept.assemble(&mut topo, &settings);
        assert_eq!(kept.stiffness_age, 1, "remade when most elements moved");
        assert!(kept.stiffness_whole, "kept: the first step in which most moved");
        // Most moved again: straight into the step's system, nothing kept; the next
        // step that would keep blocks makes the part whole again first, to the same bits.
        turn(&mut topo, 0.2);
        kept.assemble(&mut topo, &settings);
        assert!(!kept.stiffness_whole && kept.stiffness_age == 1, "assembled straight into the system");
        let direct = kept.system.clone();
        kept.assemble(&mut topo, &settings);
        assert!(kept.stiffness_whole && kept.stiffness_age == 1, "made whole again when keeping pays");
        assert_eq!(kept.system, direct, "the same bits either way");
        kept.assemble(&mut topo, &settings);
        assert_eq!((kept.stiffness_age, &kept.system), (2, &direct), "then kept");
    }

    #[test]
    fn after_a_cut_the_pattern_is_kept_where_its_inputs_are_and_the_system_is_that_of_a_new_solver() {
        let settings = settings();
        let mut topo = bar();
        turn(&mut topo, 0.3);
        let mut cut = Dynamics::new(&topo);
        cut.assemble(&mut topo, &settings);
        cut.assemble(&mut topo, &settings);
        // A cut that leaves every element and node (voxels taken out of elements that live
        // on): the pattern stays where it is, every value is made again.
        let values = cut.system.values.as_ptr();
        cut.resize(&topo);
        cut.assemble(&mut topo, &settings);
        assert_eq!(cut.system.values.as_ptr(), values, "the pattern's values kept, not made anew");
        let fresh = new_assembled(&mut topo, &settings);
        assert_eq!(cut.system, fresh.system, "the bits of a new solver's system");
        assert_eq!((&cut.scatter, &cut.first_element), (&fresh.scatter, &fresh.first_element));
        // A cut that takes an element away: the pattern, the scatter and the first
        // elements are made again from the topology of now.
        let blocks_before = cut.system.pattern.blocks();
        let last = topo.elements.len() - 1;
        topo.elements.alive[last] = false;
        cut.resize(&topo);
        cut.assemble(&mut topo, &settings);
        let fresh = new_assembled(&mut topo, &settings);
        assert_eq!(cut.system.pattern, system_pattern(&topo));
        assert!(cut.system.pattern.blocks() < blocks_before, "an element fewer, fewer blocks");
        assert_eq!(cut.system, fresh.system);
        assert_eq!((&cut.scatter, &cut.first_element), (&fresh.scatter, &fresh.first_element));
    }

    #[test]
    fn a_cut_that_keeps_the_pattern_touches_up_the_cut_element_to_a_new_solvers_system() {
        let settings = SolverSettings { alpha_per_s: 2.0, ..settings() };
        let mut topo = bar();
        turn(&mut topo, 0.3);
        let mut cut = Dynamics::new(&topo);
        cut.assemble(&mut topo, &settings);
        cut.assemble(&mut topo, &settings);
        let age = cut.stiffness_age;
        // One corner voxel of the first element (2 × 2 × 2 voxels): the element lives on
        // and still touches its neighbours across every face, so no node changes.
        let voxel = (0..topo.material.len()).find(|&v| topo.material[v] != 0).expect("a voxel");
        let element = topo.voxel_element[voxel] as usize;
        cut.before_cut(&topo, &[voxel]);
        assert_eq!(topo.remove_voxels(&[voxel]).voxels_removed, 1);
        cut.resize(&topo);
        // A second cut before the next assembly, of another voxel of the same element
        // and one of its neighbour along x: both elements taken out as they were before
        // the first.
        let same = (voxel + 1..topo.material.len()).find(|&v| topo.material[v] != 0 && topo.voxel_element[v] as usize == element).expect("another voxel of the element");
        let neighbour = (0..topo.material.len()).find(|&v| topo.material[v] != 0 && topo.voxel_element[v] as usize == element + 1).expect("a voxel of the next element");
        cut.before_cut(&topo, &[same, neighbour]);
        assert_eq!(topo.remove_voxels(&[same, neighbour]).voxels_removed, 2);
        cut.resize(&topo);
        assert_eq!(cut.cut_elements.iter().map(|(e, _)| *e as usize).collect::<Vec<_>>(), vec![element, element + 1]);
        // A block of an element the cut left alone, marked: the touch-up leaves it.
        let far = topo.elements.len() - 1;
        assert!(topo.elements.nodes[far].iter().all(|n| !topo.elements.nodes[element].contains(n)));
        let untouched = cut.scatter.blocks[far][0] as usize;
        let before = cut.system.values[untouched][0];
        cut.system.values[untouched][0] = -1.0;
        cut.assemble(&mut topo, &settings);
        assert_eq!(cut.system.values[untouched][0], -1.0, "only the cut element's blocks were written");
        cut.system.values[untouched][0] = before;
        assert_eq!(cut.stiffness_age, age + 1, "the elements' part was kept, not made whole again");
        let fresh = new_assembled(&mut topo, &settings);
        let difference = relative_difference(&cut.system, &fresh.system);
        assert!(difference < 1e-6, "a new solver's system to single precision's round-off: {difference:e}");
        // Without the stiffness from before the cut, the part is made whole again.
        let mut blind = new_assembled(&mut topo, &settings);
        blind.assemble(&mut topo, &settings);
        blind.resize(&topo);
        blind.assemble(&mut topo, &settings);
        assert_eq!((blind.stiffness_age, &blind.system), (1, &fresh.system));
    }

    #[test]
    fn a_cut_that_keeps_the_pattern_keeps_the_cholesky_factor_and_one_that_changes_it_drops_it() {
        let settings = SolverSettings { preconditioner: Preconditioning::Cholesky, ..settings() };
        let mut topo = bar();
        let mut d = Dynamics::new(&topo);
        d.prime(&mut topo, &settings);
        assert!(d.factorization.has_factor(), "the first factor is made at load");
        d.resize(&topo);
        d.assemble(&mut topo, &settings);
        assert!(d.factorization.has_factor(), "voxels taken out of live elements: the factor still fits and is kept");
        assert!(d.factorization.prepare(1, &d.system, &d.active, &d.node_rotations).is_some());
        let last = topo.elements.len() - 1;
        topo.elements.alive[last] = false;
        d.resize(&topo);
        d.assemble(&mut topo, &settings);
        assert!(!d.factorization.has_factor(), "an element fewer: the factor no longer fits");
    }

    #[test]
    fn a_touched_up_system_and_its_diagonal_have_the_bits_of_the_whole_and_write_only_what_changed() {
        let settings = SolverSettings { alpha_per_s: 2.0, ..settings() };
        let mut topo = bar();
        let mut kept = Dynamics::new(&topo);
        kept.assemble(&mut topo, &settings);
        kept.assemble(&mut topo, &settings);
        kept.refresh_diagonal(&topo);
        // A contact on the first element, then the far end turned past the tolerance: the
        // next assembly makes again the far elements' blocks and the contact's.
        let contact = PointContact { element: 0, weights: [0.125; 8], normal: Vec3::z(), stiffness: 50.0, force: Vec3::zeros(), stick_stiffness: 20.0, stick_force: Vec3::zeros(), tool_velocity: Vec3::zeros() };
        kept.add_contacts(&topo, &settings, &[contact]);
        let r = nalgebra::Rotation3::from_axis_angle(&Vec3::z_axis(), 3.0 * ROTATION_KEPT);
        for i in 0..topo.nodes.len() {
            if topo.nodes.rest[i].x > 0.016 - 1e-9 {
                topo.nodes.x[i] = r * topo.nodes.rest[i];
            }
        }
        let mut whole = kept.clone();
        whole.system_kept = false;
        whole.assemble(&mut topo, &settings);
        // A block neither the contact nor a turned element touches, marked: the touch-up
        // leaves it as it was.
        let middle = (0..topo.elements.len()).find(|&e| topo.elements.nodes[e].iter().all(|&n| (0.006..0.010).contains(&topo.nodes.rest[n as usize].x))).expect("an element mid-bar");
        let untouched = kept.scatter.blocks[middle][0] as usize;
        assert!(!kept.contacted.contains(untouched as u32));
        let before = kept.system.values[untouched][0];
        kept.system.values[untouched][0] = -1.0;
        kept.assemble(&mut topo, &settings);
        assert_eq!(kept.system.values[untouched][0], -1.0, "the touch-up wrote only the blocks that changed");
        kept.system.values[untouched][0] = before;
        assert_eq!(kept.system, whole.system, "the same bits as the whole assembly");
        // The diagonal and the block-Jacobi inverses, refreshed only in the rows that
        // changed, are those of the whole system.
        assert!(!kept.diagonal_whole && !kept.diagonal_rows.is_empty());
        kept.refresh_diagonal(&topo);
        whole.refresh_diagonal(&topo);
        assert_eq!((&kept.diagonal, &kept.jacobi.inverse), (&whole.diagonal, &whole.jacobi.inverse));
        // A system handed to the Cholesky worker is assembled whole the next step.
        kept.system_kept = false;
        kept.system.values.iter_mut().for_each(|b| *b = [9.0; 12]);
        kept.assemble(&mut topo, &settings);
        whole.assemble(&mut topo, &settings);
        assert_eq!(kept.system, whole.system);
    }
}
