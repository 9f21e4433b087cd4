//! The branched grid's Cholesky preconditioner over time (crate::solver::cholesky).
//!
//! Schedule, fixed by step index so that a run reaches the same state hash in real
//! time, in lockstep and as a replay:
//! - the first factor is made with the model, from it at rest (`Dynamics::prime`), so
//!   that no step makes one on the physics thread;
//! - every [`REFACTOR_EVERY`] steps the step's system, once solved, is handed to a
//!   worker thread (its buffer swapped for a spare: nothing is copied), whose factor
//!   replaces the one in use at the step `delay` later (a step waits for a late worker;
//!   the waits are counted). `delay` grows with the factor's size and shrinks as the
//!   steps' own solves take longer (see [`delay_for`]) so that on this class of machine
//!   the worker is rarely late;
//! - after a cut the structure (pattern, ordering, symbolic factor) is made again on the
//!   worker with the first factor, due twice the last delay later; until it arrives the
//!   solve uses block Jacobi alone.
//!
//! The factor is of a system some steps old (other rotations, other contacts). Turned
//! node by node with the rotation each node made since (`solver::cholesky`'s warp) it
//! still leaves the conjugate gradient one to three iterations on the bundled scenes
//! (on the sagging level-0 cantilever of docs/fem-comparison.md a factor from step 0
//! leaves about 3 a step warped, 41 unwarped), and the solve's tolerance, not the
//! factor, decides the answer.

use std::sync::Arc;

use super::topology::Topology;
use crate::math::{Matrix3, Vec3};
use crate::solver::background::{Background, take_due};
use crate::solver::block_sparse::{Block, BlockMatrix, Pattern};
use crate::solver::cholesky::{Factor, FactorError, FactorPreconditioner, FactorMemory, FactorScratch, FactorSolve, Ordering, Structure};

/// A new factor is asked for this often (steps).
pub const REFACTOR_EVERY: u64 = 16;
/// The shortest delay between asking for a factor and using it (ms; at least one step).
pub const MIN_DELAY: u64 = 16;

/// Steps of `step_s` between asking for a factor with `factor_entries` entries in L over
/// `unknowns` unknowns and using it: twice the factorization's time at 3·10¹⁰ units of
/// entries² / unknowns per second; at least [`MIN_DELAY`] ms (and one step). Measured on
/// this project's 2-core Xeon (faer, one thread, single precision, 2026-11-26), that
/// rate is 3.0–4.4·10¹⁰ for factors of millions of entries: 28 ms for 2.99 M entries
/// over 9,720 unknowns (the level-0 cantilever), 23 ms for 2.54 M over 7,794, 88 ms for
/// 8.28 M over 17,781; small factors run slower per unit and are covered by the
/// minimum (4.9 ms for 0.51 M over 5,226). (In double precision it was 2.0–2.6·10¹⁰,
/// and this constant 2·10¹⁰.)
///
/// A step lasts `step_s` of wall time when the physics keeps pace with real time, and
/// longer when its own work takes longer: `work` is what the steps since the last
/// factor did with this one ([`StepWork::floor_s`], the least time that takes), so a
/// large factor whose steps cannot keep pace is not left waiting tens of its slow steps
/// (on the level-0 cantilever each step of delay leaves about 0.01 more iterations a
/// step). A function of the structure, the step and the iterations the steps took
/// (the same on every machine: the state decides them), so the schedule is the same
/// on every machine; a slower one waits (counted in `solver_waits`). The step counts
/// because a multirate schedule's deformation steps are tens of ms long.
pub fn delay_for(factor_entries: usize, unknowns: usize, step_s: f64, work: &StepWork) -> u64 {
    let entries2 = (factor_entries as f64).powi(2) / unknowns.max(1) as f64;
    let ms = 2.0 * entries2 / 3e10 * 1e3;
    let step_ms = step_s.max(work.floor_s(factor_entries)) * 1e3;
    let at_least = (MIN_DELAY as f64 / step_ms).ceil().max(1.0);
    (ms / step_ms).ceil().max(at_least) as u64
}

/// Factor applications a second (a forward and a backward pass over L's compact copy,
/// entries of L; `compact_factor`) and system products a second (3×3 blocks in f32,
/// scalar entries) on this project's Xeon, rounded up from what the level-0
/// cantilever's steps measured (perf, 2026-11-27: 1.1 ms an application of 2.99 M
/// entries in bfloat16, 0.23 ms a product of 0.72 M; the 8-bit copy since
/// 2026-11-28 made applications faster, so this bound is looser): a lower bound on a
/// step's time.
const APPLIED_ENTRIES_PER_S: f64 = 3e9;
const MULTIPLIED_ENTRIES_PER_S: f64 = 4e9;

/// What the conjugate gradient did with the factor in use over the steps since it came
/// (counted by [`Factorization::solved`]): how long a step takes at least.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StepWork {
    pub steps: u64,
    /// Factor applications (one an iteration) and solves (each multiplies by the system
    /// once more than it iterates).
    pub applications: u64,
    pub solves: u64,
    /// Scalar entries of the system's blocks.
    pub system_entries: usize,
}

impl StepWork {
    /// The least wall time a step takes for its solves alone (s): the mean applications
    /// and products a step made, at the rates above. Before any step (a first factor),
    /// one solve of one iteration.
    pub fn floor_s(&self, factor_entries: usize) -> f64 {
        let (applications, solves) = if self.steps == 0 { (1.0, 1.0) } else { (self.applications as f64 / self.steps as f64, self.solves as f64 / self.steps as f64) };
        let products = applications + solves;
        applications * factor_entries as f64 / APPLIED_ENTRIES_PER_S + products * self.system_entries as f64 / MULTIPLIED_ENTRIES_PER_S
    }
}

/// The largest factor a scene may ask for (entries of L; about 1 s to compute on this
/// project's machine): at 40 M the factors in use and in the making take about 40–55 MB
/// each (the compact copy the solves read: 8 bits an entry, the diagonal blocks'
/// triangles twice),
/// and the worker 160 MB for the single-precision values it computes them from, beside
/// its gathered system.
pub const MAX_FACTOR_ENTRIES: usize = 40_000_000;

/// The entries of the Cholesky factor of `topo`'s step system (its symbolic
/// factorization alone, no values): what a scene asking for the Cholesky preconditioner
/// is checked against at load, before any factor is computed.
pub fn factor_entries(topo: &Topology) -> Result<usize, FactorError> {
    let active: Vec<bool> = (0..topo.nodes.len()).map(|n| topo.nodes.alive[n] && !topo.nodes.fixed[n]).collect();
    Ok(Structure::new(&super::solver::system_pattern(topo), &active, Ordering::Fewest(&topo.nodes.rest))?.factor_entries)
}

/// What the worker is given: the system's blocks at the step it was asked for (the
/// buffer itself, handed over after that step's solve: nothing is copied on the physics
/// thread), the structure to factor them on (or, after a cut, the pattern and active
/// set to make one from), and the nodes' rotations at that step, for the warp.
#[derive(Default)]
struct Job {
    blocks: Vec<Block<f32>>,
    structure: Option<Arc<Structure>>,
    /// After a cut: the pattern, active set and nodes' rest positions (the ordering's) to
    /// make the structure from.
    new_structure: (Pattern, Vec<bool>, Vec<Vec3>),
    rotations: Vec<Matrix3<f64>>,
    /// A factor no longer in use, whose buffer the new one is written into.
    recycled: std::sync::Mutex<FactorMemory>,
}

fn run(job: &Job, scratch: &mut FactorScratch) -> Result<Factor, FactorError> {
    let out = std::mem::take(&mut *job.recycled.lock().unwrap_or_else(|e| e.into_inner()));
    let structure = match &job.structure {
        Some(structure) => structure.clone(),
        None => {
            let (pattern, active, positions) = &job.new_structure;
            Arc::new(Structure::new(pattern, active, Ordering::Fewest(positions))?)
        }
    };
    Factor::from_blocks(structure, &job.blocks, out, scratch)
}

/// A job out with the worker.
struct Pending {
    due: u64,
    generation: u64,
    job: Arc<Job>,
}

/// The Cholesky preconditioner's state (see the module docs).
#[derive(Default)]
pub struct Factorization {
    current: Option<Factor>,
    /// The nodes' rotations when the current factor's system was assembled.
    factored_rotations: Vec<Matrix3<f64>>,
    /// Per node: its rotation now times its rotation then, transposed (scratch).
    warp: Vec<Matrix3<f64>>,
    pending: Option<Pending>,
    /// A clone's copy of its original's pending result, computed when it was cloned.
    precomputed: Option<Result<Factor, FactorError>>,
    worker: Option<Background<Arc<Job>, Result<Factor, FactorError>>>,
    /// One more for every topology change: results for an older one are dropped.
    generation: u64,
    /// Steps from asking for a factor to using it: [`delay_for`] the last factor made.
    delay: u64,
    /// The model's step, s (set when it is primed).
    step_s: f64,
    /// The last job back from the worker, its allocation and buffers reused for the next
    /// (nothing is allocated on the physics thread once the first job is back), and the
    /// last factor retired, whose buffer the next one is written into.
    spare_job: Option<Arc<Job>>,
    retired: Option<FactorMemory>,
    /// This step's system goes to the worker once it is solved.
    hand_over: bool,
    /// The values changed more than drift (a cut that kept the pattern): a new factor
    /// is asked for as soon as none is pending.
    refresh_soon: bool,
    solve: FactorSolve,
    /// What the steps did with the factor in use since it came (for the next delay), and
    /// the last step counted.
    work: StepWork,
    last_counted: Option<u64>,
    /// Steps that waited for the worker; factorizations that failed (the solve then
    /// goes on with block Jacobi until the next one).
    pub waits: u64,
    pub failures: u64,
}

impl std::fmt::Debug for Factorization {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Factorization")
            .field("has_factor", &self.current.is_some())
            .field("due", &self.pending.as_ref().map(|p| p.due))
            .field("generation", &self.generation)
            .field("waits", &self.waits)
            .finish_non_exhaustive()
    }
}

impl Clone for Factorization {
    /// A copy that will do exactly what the original does: a factor the original has out
    /// is computed here at once, and taken at the same step.
    fn clone(&self) -> Self {
        let precomputed = self.pending.as_ref().map(|p| run(&p.job, &mut FactorScratch::default()));
        Factorization {
            current: self.current.clone(),
            factored_rotations: self.factored_rotations.clone(),
            warp: Vec::new(),
            pending: self.pending.as_ref().map(|p| Pending { due: p.due, generation: p.generation, job: p.job.clone() }),
            precomputed,
            worker: None,
            generation: self.generation,
            delay: self.delay,
            step_s: self.step_s,
            spare_job: None,
            retired: None,
            hand_over: self.hand_over,
            refresh_soon: self.refresh_soon,
            solve: FactorSolve::default(),
            work: self.work,
            last_counted: self.last_counted,
            waits: self.waits,
            failures: self.failures,
        }
    }
}

impl Factorization {
    pub fn new() -> Self {
        Factorization { delay: MIN_DELAY, step_s: 1e-3, ..Factorization::default() }
    }

    /// The topology changed (a cut): the structure no longer fits. Every change of the
    /// pattern or of the active set comes through here (held nodes are set at load,
    /// nodes and elements change only by cuts), so a factor in use always fits the
    /// system it preconditions.
    pub fn topology_changed(&mut self) {
        self.generation += 1;
        self.current = None;
    }

    /// Whether a factor is in use (none: block Jacobi alone).
    pub fn has_factor(&self) -> bool {
        self.current.is_some()
    }

    /// A cut changed the system's values but not its pattern or active set (voxels taken
    /// out of elements that live on): the factor in use still fits and stays a close
    /// preconditioner (dropping it left block Jacobi alone, 24 iterations instead of 2
    /// on the layered abdomen, until the next factor came); a new one is asked for at
    /// once.
    pub fn values_changed(&mut self) {
        self.refresh_soon = true;
    }

    /// Before step `step`'s solve of `system` over the `active` unknowns, whose nodes
    /// are turned by `rotations` now: takes a factor that is due, asks for the next one
    /// when it is time, and returns the preconditioner to solve with (None: block Jacobi
    /// alone).
    pub fn prepare(&mut self, step: u64, system: &BlockMatrix<f32>, active: &[bool], rotations: &[Matrix3<f64>]) -> Option<FactorPreconditioner<'_>> {
        if self.pending.as_ref().is_some_and(|p| p.due == step) {
            let pending = self.pending.take().expect("a pending factor");
            let result = take_due(&mut self.precomputed, self.worker.as_mut(), step, &mut self.waits);
            let mut job = pending.job;
            match result {
                Some(Ok(factor)) if pending.generation == self.generation => {
                    self.work.system_entries = 9 * system.values.len();
                    self.delay = delay_for(factor.structure.factor_entries, factor.structure.unknowns(), self.step_s, &self.work);
                    self.work = StepWork::default();
                    // The old factor's buffer goes to the next job, not to the allocator:
                    // freeing megabytes here would cost this step an unmap.
                    self.retired = self.current.replace(factor).map(Factor::into_memory);
                    match Arc::get_mut(&mut job) {
                        Some(back) => std::mem::swap(&mut self.factored_rotations, &mut back.rotations),
                        // A copy of this model shares the job: its rotations are copied.
                        None => self.factored_rotations.clone_from(&job.rotations),
                    }
                }
                Some(Err(_)) | None => self.failures += 1,
                Some(Ok(_)) => {}
            }
            if Arc::get_mut(&mut job).is_some() {
                self.spare_job = Some(job);
            }
        }
        if self.pending.is_none() && (self.current.is_none() || self.refresh_soon || step.is_multiple_of(REFACTOR_EVERY)) {
            // No factor (after a cut, or one that failed) or one of values a cut changed:
            // ask at once; else on schedule.
            self.hand_over = true;
            self.refresh_soon = false;
        }
        let factor = self.current.as_ref()?;
        debug_assert!(factor.structure.fits(&system.pattern, active), "a factor in use fits its system");
        self.warp.clear();
        self.warp.extend(rotations.iter().zip(&self.factored_rotations).map(|(now, then)| now * then.transpose()));
        self.solve.prepare(factor);
        Some(self.solve.with(factor, Some(&self.warp)))
    }

    /// Step `step`'s solve with the preconditioner [`Self::prepare`] returned took
    /// `iterations`: counted for the next factor's delay (see [`delay_for`]).
    pub fn solved(&mut self, step: u64, iterations: u32) {
        if self.last_counted.replace(step) != Some(step) {
            self.work.steps += 1;
        }
        // The first application comes before the first iteration; the last iteration's
        // is skipped when it converged.
        self.work.applications += u64::from(iterations.max(1));
        self.work.solves += 1;
    }

    /// Makes the first factor, of `system` (whose nodes are turned by `rotations` and
    /// rest at `positions`), at once: at load, from the model at rest, so that the first
    /// step does not make it.
    pub fn prime(&mut self, system: &BlockMatrix<f32>, active: &[bool], positions: &[Vec3], rotations: &[Matrix3<f64>], step_s: f64) {
        self.step_s = step_s;
        match Factor::of(system, active, Ordering::Fewest(positions)) {
            Ok(factor) => {
                self.work = StepWork { system_entries: 9 * system.values.len(), ..StepWork::default() };
                self.delay = delay_for(factor.structure.factor_entries, factor.structure.unknowns(), self.step_s, &self.work);
                self.current = Some(factor);
                self.factored_rotations.clear();
                self.factored_rotations.extend_from_slice(rotations);
            }
            Err(_) => self.failures += 1,
        }
    }

    /// After step `step`'s solve: when `prepare` chose this step, hands `system`'s values
    /// to the worker (swapped for a spare buffer, which the next step's assembly
    /// overwrites), due after the factor's delay; after a cut, with the nodes' rest
    /// `positions` to order the new structure by. Returns whether it took `system`'s
    /// values.
    pub fn after_solve(&mut self, step: u64, system: &mut BlockMatrix<f32>, active: &[bool], positions: &[Vec3], rotations: &[Matrix3<f64>]) -> bool {
        if !std::mem::take(&mut self.hand_over) {
            return false;
        }
        // The factor in use fits this system (see `topology_changed`); without one (after
        // a cut) the worker makes the structure first.
        let reusable = self.current.as_ref().map(|f| f.structure.clone());
        // A new structure (after a cut) is not known before it is made: twice the last
        // factor's delay covers the ordering and symbolic work too (a cut changes the
        // system's size little).
        let due = step + if reusable.is_some() { self.delay } else { 2 * self.delay };
        let mut job = self.spare_job.take().unwrap_or_default();
        let next = Arc::get_mut(&mut job).expect("a spare job is shared with no one");
        next.rotations.clear();
        next.rotations.extend_from_slice(rotations);
        // Sized to the system (allocates only when a cut changed its pattern, or the
        // first time).
        next.blocks.resize(system.values.len(), [0.0; 12]);
        std::mem::swap(&mut next.blocks, &mut system.values);
        if reusable.is_none() {
            // Into the spare job's buffers: the active set and the positions reuse their
            // allocation (the pattern is cloned whole, as before).
            let (pattern, was_active, rest) = &mut next.new_structure;
            *pattern = system.pattern.clone();
            was_active.clear();
            was_active.extend_from_slice(active);
            rest.clear();
            rest.extend_from_slice(positions);
        }
        next.structure = reusable;
        *next.recycled.get_mut().unwrap_or_else(|e| e.into_inner()) = self.retired.take().unwrap_or_default();
        if self.worker.is_none() {
            let mut scratch = FactorScratch::default();
            self.worker = Background::new("grid-cholesky", move |job: Arc<Job>| run(&job, &mut scratch)).ok();
        }
        let refused = match self.worker.as_mut() {
            Some(worker) => worker.submit(job.clone(), due).is_err(),
            None => true,
        };
        // No worker thread could be started: factor here, due as planned.
        if refused {
            self.precomputed = Some(run(&job, &mut FactorScratch::default()));
        }
        self.pending = Some(Pending { due, generation: self.generation, job });
        true
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The level-0 cantilever's factor and system (docs/fem-comparison.md).
    const ENTRIES: usize = 2_990_000;
    const UNKNOWNS: usize = 9_720;
    const SYSTEM: usize = 720_000;

    #[test]
    fn a_factor_comes_after_twice_its_factorization_counted_in_steps_as_long_as_their_solves() {
        // Twice 2.99 M² / 9,720 / 3·10¹⁰ s = 61.3 ms.
        let first = StepWork { system_entries: SYSTEM, ..StepWork::default() };
        // Before any step: one application (1.0 ms) and two products (0.36 ms) a step.
        assert_eq!(delay_for(ENTRIES, UNKNOWNS, 1e-3, &first), 46);
        // 2.3 applications and 1 solve a step: 2.3 ms + 0.59 ms.
        let busy = StepWork { steps: 10, applications: 23, solves: 10, system_entries: SYSTEM };
        assert_eq!(delay_for(ENTRIES, UNKNOWNS, 1e-3, &busy), 22);
        // Steps longer than their solves (a multirate schedule's) count as themselves.
        assert_eq!(delay_for(ENTRIES, UNKNOWNS, 20e-3, &busy), 4);
        // A small factor's steps keep pace: the minimum, 16 steps of 1 ms.
        let small = StepWork { steps: 10, applications: 20, solves: 10, system_entries: 50_000 };
        assert_eq!(delay_for(100_000, 3_000, 1e-3, &small), MIN_DELAY);
    }

    #[test]
    fn the_steps_work_counts_applications_solves_and_distinct_steps() {
        let mut f = Factorization::new();
        f.solved(5, 3);
        f.solved(5, 0);
        f.solved(6, 2);
        assert_eq!(f.work, StepWork { steps: 2, applications: 6, solves: 3, system_entries: 0 });
    }
}
