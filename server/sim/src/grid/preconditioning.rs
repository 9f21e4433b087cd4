//! The branched grid's multigrid preconditioner over time.
//!
//! The coarse levels are the same voxels condensed onto coarser cells
//! ([`super::hierarchy`]): each level's operator is that coarser grid's own corotational
//! system `(1 + hα) M + (h² + hβ) K_R`, its elements rotated like the fine element that
//! holds their first voxel. Condensation is a Galerkin projection, so this is the fine
//! operator projected down. The coarse operators are re-assembled every
//! [`REFRESH_EVERY`] steps, on the step itself: cheap (the coarse levels hold an eighth
//! of the elements, and fewer below) and scheduled by step index.
//!
//! A cut changes the voxels, and the coarse grids must be built again: that is done on a
//! worker thread and swapped in [`REBUILD_DELAY`] steps later, whatever the clock says
//! (a step waits for a late worker, and the waits are counted), so a run reaches the same
//! state hash in real time, in lockstep and as a replay. Until it arrives the solve uses
//! block Jacobi alone.

use std::sync::Arc;

use super::hierarchy::{COARSEST_NODES, Coarsening};
use super::topology::{NONE, Topology};
use crate::math::{Matrix3, Vec3};
use crate::solver::background::{Background, take_due};
use crate::solver::block_sparse::{BlockMatrix, Pattern, Scatter};
use crate::solver::kernels::{F8, rotate_and_multiply};
use crate::solver::multigrid::Hierarchy;

/// Coarse operators are re-assembled this often (steps).
pub const REFRESH_EVERY: u64 = 4;
/// A hierarchy rebuilt after a cut is due this long after it was asked for (ms; at
/// least one step: a multirate schedule's deformation steps are tens of ms long).
pub const REBUILD_DELAY: u64 = 32;

/// [`REBUILD_DELAY`] in steps of `step_s`.
fn rebuild_delay_steps(step_s: f64) -> u64 {
    (REBUILD_DELAY as f64 / (step_s * 1e3)).ceil().max(1.0) as u64
}

/// One coarser grid: its elements, where they go in its matrix, and whose rotation each
/// takes.
#[derive(Debug, Clone)]
struct CoarseGrid {
    topo: Topology,
    scatter: Scatter,
    /// Per coarse element: the fine element holding its first voxel.
    rotation_from: Vec<u32>,
}

/// The coarse grids of one topology and the hierarchy over them.
#[derive(Debug, Clone)]
pub struct Levels {
    grids: Vec<CoarseGrid>,
    hierarchy: Hierarchy,
}

/// Builds the coarse grids below `coarsening` (at most down to [`COARSEST_NODES`] nodes)
/// and their hierarchy (matrices empty until the first assembly). Their cells' void holds
/// the fine grid's ghost material, scaled to their size (a box's stiffness grows with
/// its side).
fn build(coarsening: &Coarsening, fine_active: &[bool]) -> Levels {
    let (prolongations, topologies) = coarsening.levels(COARSEST_NODES);
    let mut grids = Vec::with_capacity(topologies.len());
    let mut matrices = Vec::with_capacity(topologies.len());
    for mut topo in topologies {
        let scale = (topo.layout.side / coarsening.layout.side) as f64;
        topo.set_ghost(coarsening.ghost * scale);
        let live = (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]).map(|e| &topo.elements.nodes[e][..]);
        let pattern = Pattern::from_elements(topo.nodes.len(), live);
        let scatter = Scatter::new(&pattern, &topo.elements.nodes, &topo.elements.alive);
        let mut rotation_from = vec![NONE; topo.elements.len()];
        for (v, &e) in topo.voxel_element.iter().enumerate() {
            if e != NONE && rotation_from[e as usize] == NONE {
                rotation_from[e as usize] = coarsening.fine.voxel_element[v];
            }
        }
        matrices.push(BlockMatrix::<f64>::zeros(pattern));
        grids.push(CoarseGrid { topo, scatter, rotation_from });
    }
    let hierarchy = Hierarchy::new(prolongations, matrices, fine_active);
    Levels { grids, hierarchy }
}

impl Levels {
    /// Assembles every coarse level's operator from the fine rotations.
    fn assemble(&mut self, fine_rotations: &[Matrix3<f64>], a_mass: f64, a_stiff: f64, rotated: &mut [[F8; 3]; 24]) {
        for (l, grid) in self.grids.iter().enumerate() {
            let matrix = self.hierarchy.matrix_mut(l);
            matrix.clear();
            let topo = &grid.topo;
            let zero = [0f32; 24];
            let mut force = [0f32; 24];
            for e in 0..topo.elements.len() {
                if !topo.elements.alive[e] {
                    continue;
                }
                let source = grid.rotation_from[e];
                let r = if source == NONE { Matrix3::identity() } else { fine_rotations[source as usize] };
                let rf: [[f32; 3]; 3] = std::array::from_fn(|p| std::array::from_fn(|q| r[(p, q)] as f32));
                rotate_and_multiply(&topo.elements.stiffness_single[e], &rf, &zero, rotated, &mut force);
                let blocks = &grid.scatter.blocks[e];
                for i in 0..8 {
                    for j in 0..8 {
                        let block = Matrix3::from_fn(|p, q| f64::from(rotated[3 * i + p][q].0[j]) * a_stiff);
                        matrix.add(blocks[8 * i + j] as usize, &block);
                    }
                }
            }
            for n in 0..topo.nodes.len() {
                let at = matrix.pattern.diag[n] as usize;
                matrix.add_diagonal(at, Vec3::repeat(a_mass * topo.nodes.mass[n]));
            }
        }
    }
}

/// The coarse grids below `topo` with the operators of its linear static problem `k`
/// (the unrotated stiffness alone: no mass, no damping, on the unknowns `active`), for
/// a V-cycle that preconditions it (`grid::statics`): each coarse operator the Galerkin
/// product of the one above, so that the support reaches every level as it is (the
/// layered abdomen's level-0 reference: 105 s, against 10.5 min with the coarse grids'
/// own operators and only the coarse nodes on held fine ones held).
pub fn static_hierarchy(topo: &Topology, k: &BlockMatrix<f64>, active: &[bool]) -> Hierarchy {
    let (prolongations, _) = Coarsening::of(topo).levels(COARSEST_NODES);
    let mut hierarchy = Hierarchy::galerkin(prolongations, k, active);
    hierarchy.factor_coarsest(STATIC_COARSEST_UNKNOWNS);
    hierarchy
}

/// A static problem's coarsest level is solved exactly up to this many unknowns (a
/// dense factor of 3,000 unknowns: 72 MB, seconds to make).
pub const STATIC_COARSEST_UNKNOWNS: usize = 3_000;

/// What a rebuild of the hierarchy reads: the coarsening, and which fine unknowns are
/// active (not held).
type RebuildInput = (Arc<Coarsening>, Arc<Vec<bool>>);

/// A rebuild out with the worker: its due step, its topology generation, and its input.
type PendingRebuild = (u64, u64, Arc<Coarsening>, Arc<Vec<bool>>);

/// The multigrid preconditioner's state (see the module docs).
#[derive(Debug, Default)]
pub struct Multigrid {
    current: Option<Box<Levels>>,
    /// A rebuild out with the worker: its due step, the topology generation it is for,
    /// and what it reads (kept so that a clone can redo it).
    pending: Option<PendingRebuild>,
    /// A clone's copy of its original's pending result, computed when it was cloned.
    precomputed: Option<Box<Levels>>,
    worker: Option<Background<RebuildInput, Box<Levels>>>,
    /// One more for every topology change: results for an older one are dropped.
    generation: u64,
    /// A cut made the hierarchy stale: a new one is asked of the worker.
    rebuild: bool,
    /// Scratch for the element kernel.
    rotated: Box<[[F8; 3]; 24]>,
    /// Steps that waited for the worker.
    pub waits: u64,
    /// Steps from asking for a rebuild to using it (0 before `prime`: [`REBUILD_DELAY`]).
    rebuild_delay: u64,
    /// The step the coarse operators were last assembled at.
    assembled_at: Option<u64>,
}

impl Clone for Multigrid {
    /// A copy that will do exactly what the original does: a rebuild the original has out
    /// is redone here at once, and taken at the same step.
    fn clone(&self) -> Self {
        let precomputed = match &self.pending {
            Some((_, _, coarsening, active)) => Some(Box::new(build(coarsening, active))),
            None => self.precomputed.clone(),
        };
        Multigrid {
            current: self.current.clone(),
            pending: self.pending.clone(),
            precomputed,
            worker: None,
            generation: self.generation,
            rebuild: self.rebuild,
            rotated: self.rotated.clone(),
            waits: self.waits,
            rebuild_delay: self.rebuild_delay,
            assembled_at: self.assembled_at,
        }
    }
}

impl Multigrid {
    /// Builds the first coarse grids, with the model (so that no step builds them on
    /// the physics thread). The first step assembles their operators.
    pub fn prime(&mut self, topo: &Topology, active: &[bool], step_s: f64) {
        self.rebuild_delay = rebuild_delay_steps(step_s);
        self.current = Some(Box::new(build(&Coarsening::of(topo), active)));
        self.rebuild = false;
    }

    /// The topology changed (a cut): the coarse grids no longer fit; new ones are built
    /// on the worker.
    pub fn topology_changed(&mut self) {
        self.generation += 1;
        self.current = None;
        self.rebuild = true;
    }

    /// Before step `step`'s solve: takes a rebuilt hierarchy that is due, asks for one
    /// after a cut, re-assembles the coarse operators when it is their step, and returns
    /// the hierarchy to precondition with (None: block Jacobi alone).
    #[allow(clippy::too_many_arguments)]
    pub fn prepare(&mut self, step: u64, topo: &Topology, active: &[bool], rotations: &[Matrix3<f64>], a_mass: f64, a_stiff: f64) -> Option<&mut Hierarchy> {
        let mut fresh = false;
        if self.pending.as_ref().is_some_and(|p| p.0 == step) {
            let (_, generation, _, _) = self.pending.take().expect("a pending rebuild");
            let result = take_due(&mut self.precomputed, self.worker.as_mut(), step, &mut self.waits);
            if generation == self.generation {
                self.current = result;
                fresh = true;
            }
        }
        if self.rebuild && self.pending.is_none() {
            let coarsening = Arc::new(Coarsening::of(topo));
            let fine_active = Arc::new(active.to_vec());
            let due = step + if self.rebuild_delay == 0 { REBUILD_DELAY } else { self.rebuild_delay };
            self.pending = Some((due, self.generation, coarsening.clone(), fine_active.clone()));
            if self.worker.is_none() {
                self.worker = Background::new("grid-multigrid", |(c, a): (Arc<Coarsening>, Arc<Vec<bool>>)| Box::new(build(&c, &a))).ok();
            }
            let refused = match self.worker.as_mut() {
                Some(worker) => worker.submit((coarsening, fine_active), due).err(),
                None => Some((coarsening, fine_active)),
            };
            // No worker thread could be started: build here, due as planned.
            if let Some((c, a)) = refused {
                self.precomputed = Some(Box::new(build(&c, &a)));
            }
            self.rebuild = false;
        }
        let levels = self.current.as_deref_mut()?;
        // A step may ask more than once (a multirate deformation step's compliance
        // solves before its own): the coarse operators are assembled once.
        if fresh || (step.is_multiple_of(REFRESH_EVERY) && self.assembled_at != Some(step)) {
            levels.assemble(rotations, a_mass, a_stiff, &mut self.rotated);
            levels.hierarchy.update();
            self.assembled_at = Some(step);
        }
        Some(&mut levels.hierarchy)
    }
}
