//! A sparse Cholesky factorization of an assembled system, kept as the conjugate
//! gradient's preconditioner for many steps after it was computed.
//!
//! The system changes every step (rotations, contacts), but slowly: the factor of a
//! recent one, `A_old = L Lᵀ`, makes `A_old⁻¹ A` close to the identity, so a solve takes
//! a few iterations at any resolution. Computing it is the expensive part, so it is split
//! the way SOFA's asynchronous LDLᵀ solver and Courtecuisse et al. (2014) split it:
//!
//! - [`Structure`]: the lower triangle's pattern over the active unknowns (three per
//!   active node, in node order) and its symbolic factorization (faer's, supernodal or
//!   simplicial as the fill decides), in the [`Ordering`] given: nested dissection by
//!   the nodes' positions (`super::ordering`) where they are known, else faer's
//!   approximate minimum degree; computed once per topology;
//! - [`Factor`]: the numeric factor of one system's values on that structure, computed
//!   on a worker thread (the models schedule it: see `grid::factorization`);
//! - [`FactorSolve`]: `z = A_old⁻¹ r` with buffers of its own: no allocation per solve;
//!   a supernodal factor from its compact copy (`super::compact_factor`: 8 bits an
//!   entry, a scale per column), a
//!   simplicial one (small) by faer's solves.
//!
//! Everything runs on one thread per call (faer's `Par::Seq`): the physics thread keeps
//! its core, the worker its own.

use std::cell::RefCell;
use std::sync::Arc;

use faer::dyn_stack::{MemBuffer, MemStack, StackReq};
use faer::linalg::cholesky::llt::factor::LltRegularization;
use faer::sparse::linalg::cholesky::{LltRef, SymbolicCholesky, SymbolicCholeskyRaw, SymmetricOrdering, factorize_symbolic_cholesky};
use faer::sparse::{SparseColMatRef, SymbolicSparseColMatRef};
use faer::perm::PermRef;
use faer::{Conj, MatMut, Par, Side};

use super::block_sparse::{Block, BlockMatrix, Pattern, Scalar, at};
use super::compact_factor::{Compact, Supernodes};
use super::ordering::nested_dissection;
use super::pcg::Preconditioner;
use crate::math::{Matrix3, Vec3};

/// A node without unknowns (held or dead).
const INACTIVE: u32 = u32::MAX;

/// Why no factor could be made.
#[derive(Debug, thiserror::Error)]
pub enum FactorError {
    #[error("the symbolic Cholesky factorization failed: {0:?}")]
    Symbolic(faer::sparse::FaerError),
    #[error("the system is not positive definite (Cholesky broke down): {0:?}")]
    NotPositiveDefinite(faer::linalg::cholesky::llt::factor::LltError),
}

/// The order in which a factorization eliminates the unknowns.
#[derive(Debug, Clone, Copy)]
pub enum Ordering<'a> {
    /// faer's approximate minimum degree, from the pattern alone.
    MinimumDegree,
    /// Nested dissection by the nodes' positions (one per node of the pattern; a mesh's
    /// rest positions): a third to a half fewer entries on box lattices
    /// (`super::ordering`).
    NestedDissection(&'a [Vec3]),
    /// Whichever of the two makes the smaller factor (both symbolic factorizations are
    /// computed: a few ms to a few hundred, once per topology). Neither wins everywhere:
    /// on the bundled scenes nested dissection saves 15–16 % of the entries on the
    /// cantilever, the smooth liver at level 2 and the CT liver at level 1, and costs
    /// 6–60 % on the CT liver at level 2 and the layered abdomen, whose branched nodes
    /// (several at one position, one per tissue piece) make its planes poor separators.
    Fewest(&'a [Vec3]),
}

/// The lower triangle's pattern over the active unknowns, where each of its entries is
/// read from in the block matrix, and the symbolic factorization.
#[derive(Debug)]
pub struct Structure {
    /// Per node: its first unknown (the next two follow), or [`INACTIVE`].
    first: Vec<u32>,
    unknowns: usize,
    col_ptr: Vec<u32>,
    row_idx: Vec<u32>,
    /// Per entry: the block it is read from, and the position in that block.
    source: Vec<(u32, u8)>,
    symbolic: SymbolicCholesky<u32>,
    /// A supernodal factorization's layout, for the solves from its compact copy
    /// (`super::compact_factor`); None for a simplicial one (small factors), which
    /// faer's solves apply in f32.
    supernodes: Option<Supernodes>,
    /// Entries of the factor L.
    pub factor_entries: usize,
}

impl Structure {
    /// The structure of a system with `pattern` whose unknowns are those of the nodes
    /// with `active` true, eliminated in `ordering`. The pattern must be symmetric
    /// (every assembled system is).
    pub fn new(pattern: &Pattern, active: &[bool], ordering: Ordering<'_>) -> Result<Structure, FactorError> {
        let n = pattern.rows();
        let mut first = vec![INACTIVE; n];
        let mut unknowns = 0u32;
        for (i, first) in first.iter_mut().enumerate() {
            if active[i] {
                *first = unknowns;
                unknowns += 3;
            }
        }
        // Column 3j + q of the lower triangle: rows 3i + p ≥ 3j + q over the blocks of
        // row j (the pattern is symmetric: block (i, j) is block (j, i) transposed). The
        // columns of a row are sorted, so each column's rows come out sorted.
        let mut col_ptr = Vec::with_capacity(unknowns as usize + 1);
        let mut row_idx = Vec::new();
        let mut source = Vec::new();
        col_ptr.push(0u32);
        for j in 0..n {
            if first[j] == INACTIVE {
                continue;
            }
            for q in 0..3 {
                let column = first[j] + q as u32;
                for k in pattern.start[j] as usize..pattern.start[j + 1] as usize {
                    let i = pattern.cols[k] as usize;
                    if first[i] == INACTIVE || first[i] < first[j] {
                        continue;
                    }
                    for p in 0..3 {
                        let row = first[i] + p as u32;
                        if row >= column {
                            row_idx.push(row);
                            source.push((k as u32, at(q, p) as u8));
                        }
                    }
                }
                col_ptr.push(row_idx.len() as u32);
            }
        }
        let size = unknowns as usize;
        let lower = SymbolicSparseColMatRef::new_checked(size, size, &col_ptr, None, &row_idx);
        let by_degree = || factorize_symbolic_cholesky(lower, Side::Lower, SymmetricOrdering::Amd, Default::default()).map_err(FactorError::Symbolic);
        let first_of = |i: u32| first[i as usize];
        let by_position = |positions: &[Vec3]| {
            // The nodes' order, three unknowns each: `forward[k]` is the unknown
            // eliminated k-th.
            let nodes: Vec<u32> = (0..n as u32).filter(|&i| first_of(i) != INACTIVE).collect();
            let forward: Vec<u32> = nested_dissection(positions, &nodes).iter().flat_map(|&i| (0..3).map(move |q| first_of(i) + q)).collect();
            let mut inverse = vec![0u32; size];
            for (k, &u) in forward.iter().enumerate() {
                inverse[u as usize] = k as u32;
            }
            let perm = PermRef::new_checked(&forward, &inverse, size);
            factorize_symbolic_cholesky(lower, Side::Lower, SymmetricOrdering::Custom(perm), Default::default()).map_err(FactorError::Symbolic)
        };
        let symbolic = match ordering {
            Ordering::MinimumDegree => by_degree()?,
            Ordering::NestedDissection(positions) => by_position(positions)?,
            Ordering::Fewest(positions) => {
                let (dissected, minimum) = (by_position(positions)?, by_degree()?);
                if dissected.len_val() <= minimum.len_val() { dissected } else { minimum }
            }
        };
        let factor_entries = symbolic.len_val();
        let supernodes = match symbolic.raw() {
            SymbolicCholeskyRaw::Supernodal(supernodal) => Some(Supernodes::of(supernodal)),
            SymbolicCholeskyRaw::Simplicial(_) => None,
        };
        Ok(Structure { first, unknowns: size, col_ptr, row_idx, source, symbolic, supernodes, factor_entries })
    }

    /// Unknowns of the factored system.
    pub fn unknowns(&self) -> usize {
        self.unknowns
    }

    /// Whether this structure is the one of a system with `pattern` and `active`
    /// (same rows and active set; the pattern itself is checked by its size).
    pub fn fits(&self, pattern: &Pattern, active: &[bool]) -> bool {
        self.first.len() == pattern.rows()
            && self.first.iter().zip(active).all(|(&f, &a)| (f != INACTIVE) == a)
    }
}

/// The numeric factor of one system on a [`Structure`].
#[derive(Debug, Clone)]
pub struct Factor {
    pub structure: Arc<Structure>,
    memory: FactorMemory,
}

/// A factor's values as its solves read them: a simplicial one's as computed (f32), a
/// supernodal one's compact copy (`super::compact_factor`; its f32 values stay in the
/// [`FactorScratch`] they were computed in). Recycled from a factor no longer in use
/// into the next factorization.
#[derive(Debug, Clone, Default)]
pub struct FactorMemory {
    values: Vec<f32>,
    compact: Compact,
}

impl Structure {
    /// The lower triangle's values of a system with block values `blocks` (laid out on
    /// the pattern this structure was made from), in the structure's order and single
    /// precision, into `out`:
    /// what a factorization reads (a seventh of the blocks' floats: one triangle, no
    /// padding).
    pub fn gather<T: Scalar>(&self, blocks: &[Block<T>], out: &mut Vec<f32>) {
        out.clear();
        out.extend(self.source.iter().map(|&(k, at)| blocks[k as usize][at as usize].to_f64() as f32));
    }
}

/// What a factorization works in, kept between factorizations by whoever makes them (a
/// worker thread): the gathered lower triangle, faer's scratch, and a supernodal
/// factor's f32 values (only their compact copy goes with the factor); grown, never
/// shrunk.
#[derive(Default)]
pub struct FactorScratch {
    lower: Vec<f32>,
    buffer: Option<(StackReq, MemBuffer)>,
    values: Vec<f32>,
}

impl Factor {
    /// Factors the system whose lower triangle is `lower` (from [`Structure::gather`]),
    /// in single precision, into `memory` (a factor no longer used, recycled: no
    /// allocation where it has the size); a supernodal one into the scratch's buffer,
    /// and from there into `memory` as the compact copy its solves read. The
    /// triangular solves stream the factor from memory every iteration, so it is kept
    /// in single precision (half their time), a supernodal one compact (8-bit
    /// integers with a scale per column: a quarter of f32's bytes). It is computed in
    /// single precision too, since 2026-11-26: 1.4–1.7×
    /// faster than in double precision and converted (the level-0 cantilever's 2.99 M
    /// entries in 28 ms against 40 ms, the CT liver's level 1 in 88 ms against 151 ms,
    /// on this project's Xeon), with half the worker's memory and the same iteration
    /// counts (the cantilever's 600 sagging steps: 2.64 a step either way). As a
    /// preconditioner its rounding is harmless; a system too ill-conditioned for it
    /// fails to factor and the solve goes on with block Jacobi (counted in
    /// `solver_factor_failures`).
    fn new(structure: Arc<Structure>, lower: &[f32], mut memory: FactorMemory, scratch: &mut FactorScratch) -> Result<Factor, FactorError> {
        let s = &*structure;
        // A supernodal factor is computed in the scratch's buffer and copied out; a
        // simplicial one in its own.
        let mut out = std::mem::take(if s.supernodes.is_some() { &mut scratch.values } else { &mut memory.values });
        let symbolic = SymbolicSparseColMatRef::new_checked(s.unknowns, s.unknowns, &s.col_ptr, None, &s.row_idx);
        let matrix = SparseColMatRef::new(symbolic, lower);
        out.resize(s.symbolic.len_val(), 0.0);
        let req = s.symbolic.factorize_numeric_llt_scratch::<f32>(Par::Seq, Default::default());
        let fits = scratch.buffer.as_ref().is_some_and(|(had, _)| had.size_bytes() >= req.size_bytes() && had.align_bytes() >= req.align_bytes());
        if !fits {
            scratch.buffer = Some((req, MemBuffer::new(req)));
        }
        let buffer = &mut scratch.buffer.as_mut().expect("sized above").1;
        let factored = s
            .symbolic
            .factorize_numeric_llt(&mut out, matrix, Side::Lower, LltRegularization::default(), Par::Seq, MemStack::new(buffer), Default::default())
            .map(|_| ())
            .map_err(FactorError::NotPositiveDefinite);
        match &s.supernodes {
            Some(supernodes) => {
                if factored.is_ok() {
                    supernodes.compact(&out, &mut memory.compact);
                }
                scratch.values = out;
                // Whatever f32 buffer came recycled (a simplicial factor's) is not needed.
                memory.values = Vec::new();
            }
            None => {
                memory.values = out;
                memory.compact = Compact::default();
            }
        }
        factored?;
        Ok(Factor { structure, memory })
    }

    /// Factors the system whose block values are `blocks` (on the pattern the structure
    /// was made from).
    pub fn from_blocks<T: Scalar>(structure: Arc<Structure>, blocks: &[Block<T>], out: FactorMemory, scratch: &mut FactorScratch) -> Result<Factor, FactorError> {
        let mut lower = std::mem::take(&mut scratch.lower);
        structure.gather(blocks, &mut lower);
        let factor = Factor::new(structure, &lower, out, scratch);
        scratch.lower = lower;
        factor
    }

    /// Factors a block matrix (at once, on this thread).
    pub fn of<T: Scalar>(a: &BlockMatrix<T>, active: &[bool], ordering: Ordering<'_>) -> Result<Factor, FactorError> {
        let structure = Arc::new(Structure::new(&a.pattern, active, ordering)?);
        Factor::from_blocks(structure, &a.values, FactorMemory::default(), &mut FactorScratch::default())
    }

    /// The factor's buffers, to recycle into the next factorization.
    pub fn into_memory(self) -> FactorMemory {
        self.memory
    }
}

/// Solves with a [`Factor`]: `z = A_old⁻¹ r` on the active nodes, zero elsewhere.
#[derive(Default)]
pub struct FactorSolve {
    rhs: RefCell<Vec<f32>>,
    /// faer's scratch (simplicial factors), or the supernodal solves' own.
    scratch: RefCell<Option<MemBuffer>>,
    work: RefCell<Vec<f32>>,
    /// The unknowns the scratch was sized for.
    sized_for: usize,
}

impl std::fmt::Debug for FactorSolve {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("FactorSolve").field("sized_for", &self.sized_for).finish_non_exhaustive()
    }
}

/// A copy has buffers of its own, sized at its first `prepare`.
impl Clone for FactorSolve {
    fn clone(&self) -> Self {
        FactorSolve::default()
    }
}

impl FactorSolve {
    /// Sizes the buffers for `factor` (allocates only when its structure grew).
    pub fn prepare(&mut self, factor: &Factor) {
        let s = &*factor.structure;
        let ready = match &s.supernodes {
            Some(supernodes) => self.work.get_mut().len() >= supernodes.scratch_len(),
            None => self.scratch.get_mut().is_some(),
        };
        if self.sized_for != s.unknowns || !ready {
            self.rhs.get_mut().resize(s.unknowns, 0.0);
            match &s.supernodes {
                Some(supernodes) => self.work.get_mut().resize(supernodes.scratch_len(), 0.0),
                None => *self.scratch.get_mut() = Some(MemBuffer::new(s.symbolic.solve_in_place_scratch::<f32>(1, Par::Seq))),
            }
            self.sized_for = s.unknowns;
        }
    }

    /// The preconditioner of one solve: the factor and these buffers (prepared for it),
    /// warped by a rotation per node (see [`FactorPreconditioner`]).
    pub fn with<'a>(&'a self, factor: &'a Factor, warp: Option<&'a [Matrix3<f64>]>) -> FactorPreconditioner<'a> {
        assert_eq!(self.sized_for, factor.structure.unknowns, "FactorSolve::prepare first");
        FactorPreconditioner { factor, solve: self, warp }
    }
}

/// A factor as the conjugate gradient's preconditioner: `z = W A_old⁻¹ Wᵀ r`, with `W`
/// block diagonal, a rotation per node (the identity when there is no warp). A
/// corotational system whose parts turned since it was factored is, to first order, the
/// old one turned with them (Saupin, Duriez & Cotin 2008 warp their preconditioner so):
/// turning the factor keeps it useful over more steps. `W` orthogonal keeps `z`
/// symmetric positive definite in `r`.
pub struct FactorPreconditioner<'a> {
    factor: &'a Factor,
    solve: &'a FactorSolve,
    warp: Option<&'a [Matrix3<f64>]>,
}

impl Preconditioner for FactorPreconditioner<'_> {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]) {
        let s = &*self.factor.structure;
        let mut rhs = self.solve.rhs.borrow_mut();
        // A supernodal factor's own solves work in the elimination order: each unknown
        // goes straight to its slot (the elimination order's inverse permutation, which
        // the symbolic factorization holds). faer's permute themselves.
        let order = s.supernodes.as_ref().and(s.symbolic.perm()).map(|perm| perm.arrays().1);
        let slot = |u: u32| order.map_or(u as usize, |inverse| inverse[u as usize] as usize);
        for (i, &f) in s.first.iter().enumerate() {
            if f != INACTIVE {
                let turned = match self.warp {
                    Some(w) => w[i].tr_mul(&r[i]),
                    None => r[i],
                };
                rhs[slot(f)] = turned.x as f32;
                rhs[slot(f + 1)] = turned.y as f32;
                rhs[slot(f + 2)] = turned.z as f32;
            }
        }
        match &s.supernodes {
            Some(supernodes) => supernodes.solve(&self.factor.memory.compact, &mut rhs, &mut self.solve.work.borrow_mut()),
            None => {
                let mut scratch = self.solve.scratch.borrow_mut();
                let scratch = scratch.as_mut().expect("prepared");
                let llt = LltRef::<u32, f32>::new(&s.symbolic, &self.factor.memory.values);
                llt.solve_in_place_with_conj(Conj::No, MatMut::from_column_major_slice_mut(&mut rhs[..], s.unknowns, 1), Par::Seq, MemStack::new(scratch));
            }
        }
        for (i, &f) in s.first.iter().enumerate() {
            z[i] = if f == INACTIVE {
                Vec3::zeros()
            } else {
                let x = Vec3::new(f64::from(rhs[slot(f)]), f64::from(rhs[slot(f + 1)]), f64::from(rhs[slot(f + 2)]));
                match self.warp {
                    Some(w) => w[i] * x,
                    None => x,
                }
            };
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A chain of `n` nodes, each coupled to the next: SPD, with a node held.
    fn chain(n: usize) -> (BlockMatrix<f64>, Vec<bool>) {
        let elements: Vec<[u32; 2]> = (0..n as u32 - 1).map(|i| [i, i + 1]).collect();
        let pattern = Pattern::from_elements(n, elements.iter().map(|e| &e[..]));
        let mut a = BlockMatrix::<f64>::zeros(pattern);
        for e in &elements {
            let (i, j) = (e[0] as usize, e[1] as usize);
            let k = Matrix3::new(2.0, 0.3, 0.1, 0.3, 1.5, 0.2, 0.1, 0.2, 1.0) * (1.0 + i as f64 * 0.1);
            a.add(a.pattern.find(i, i).unwrap(), &k);
            a.add(a.pattern.find(j, j).unwrap(), &k);
            a.add(a.pattern.find(i, j).unwrap(), &-k);
            a.add(a.pattern.find(j, i).unwrap(), &-k.transpose());
        }
        for i in 0..n {
            a.add_diagonal(a.pattern.diag[i] as usize, Vec3::repeat(0.5));
        }
        let mut active = vec![true; n];
        active[0] = false;
        (a, active)
    }

    #[test]
    fn the_factor_solves_the_system_on_the_active_nodes() {
        let (a, active) = chain(12);
        let factor = Factor::of(&a, &active, Ordering::MinimumDegree).unwrap();
        assert_eq!(factor.structure.unknowns(), 33);
        let mut solve = FactorSolve::default();
        solve.prepare(&factor);
        let x: Vec<Vec3> = (0..12).map(|i| if active[i] { Vec3::new(i as f64, 1.0 - i as f64, 0.5) } else { Vec3::zeros() }).collect();
        let mut b = vec![Vec3::zeros(); 12];
        a.multiply(&x, &mut b, &active);
        let mut z = vec![Vec3::repeat(7.0); 12];
        solve.with(&factor, None).apply(&b, &mut z);
        for i in 0..12 {
            assert!((z[i] - x[i]).amax() < 1e-5 * x[i].amax().max(1.0), "node {i}: {} against {}", z[i], x[i]);
        }
        assert_eq!(z[0], Vec3::zeros());
    }

    /// A 3D lattice of `m`³ nodes coupled to their 26 neighbours by non-symmetric
    /// blocks (symmetric as a whole): large enough for a supernodal factor.
    fn lattice(m: usize) -> (BlockMatrix<f64>, Vec<bool>) {
        let id = |x: usize, y: usize, z: usize| (x + m * (y + m * z)) as u32;
        let mut pairs = Vec::new();
        for z in 0..m {
            for y in 0..m {
                for x in 0..m {
                    for (dx, dy, dz) in [(1, 0, 0), (0, 1, 0), (0, 0, 1), (1, 1, 0), (1, 0, 1), (0, 1, 1), (1, 1, 1)] {
                        if x + dx < m && y + dy < m && z + dz < m {
                            pairs.push([id(x, y, z), id(x + dx, y + dy, z + dz)]);
                        }
                    }
                }
            }
        }
        let n = m * m * m;
        let mut a = BlockMatrix::<f64>::zeros(Pattern::from_elements(n, pairs.iter().map(|e| &e[..])));
        for (e, pair) in pairs.iter().enumerate() {
            let (i, j) = (pair[0] as usize, pair[1] as usize);
            let c = Matrix3::new(0.3, 0.1, 0.0, -0.05, 0.2, 0.07, 0.02, 0.0, 0.25) * (1.0 + (e % 7) as f64 * 0.1);
            // A coupling c between i and j: [cᵀc, −cᵀc; −cᵀc, cᵀc] is symmetric PSD, so
            // use the non-symmetric product c·M·cᵀ-free form: off-diagonal −c, diagonal
            // a dominant multiple of the identity.
            a.add(a.pattern.find(i, j).unwrap(), &-c);
            a.add(a.pattern.find(j, i).unwrap(), &-c.transpose());
            a.add_diagonal(a.pattern.diag[i] as usize, Vec3::repeat(0.6));
            a.add_diagonal(a.pattern.diag[j] as usize, Vec3::repeat(0.6));
        }
        let mut active = vec![true; n];
        for i in (0..n).step_by(17) {
            active[i] = false;
        }
        (a, active)
    }

    /// The nodes' positions of `lattice(m)`.
    fn lattice_positions(m: usize) -> Vec<Vec3> {
        (0..m * m * m).map(|i| Vec3::new((i % m) as f64, (i / m % m) as f64, (i / (m * m)) as f64)).collect()
    }

    #[test]
    fn nested_dissection_by_position_fills_in_less_than_minimum_degree() {
        let (a, active) = lattice(11);
        let positions = lattice_positions(11);
        let by_degree = Structure::new(&a.pattern, &active, Ordering::MinimumDegree).unwrap().factor_entries;
        let by_position = Structure::new(&a.pattern, &active, Ordering::NestedDissection(&positions)).unwrap().factor_entries;
        assert!(by_position < by_degree, "nested dissection {by_position} entries, minimum degree {by_degree}");
    }

    /// A supernodal factor is applied from its compact copy: its solve is that of the
    /// values the copy stands for (faer's, in f32) to single precision, and of the
    /// system itself to the precision of about 8 significant bits.
    #[test]
    fn a_large_factor_solves_as_its_compact_values_do() {
        let (a, active) = lattice(11);
        let n = a.rows();
        let positions = lattice_positions(11);
        let structure = Arc::new(Structure::new(&a.pattern, &active, Ordering::NestedDissection(&positions)).unwrap());
        let mut scratch = FactorScratch::default();
        let factor = Factor::from_blocks(structure, &a.values, FactorMemory::default(), &mut scratch).unwrap();
        let s = &*factor.structure;
        assert!(s.supernodes.is_some(), "large enough for a supernodal factor");
        assert!(factor.memory.values.is_empty(), "its f32 values stay in the scratch");
        let mut solve = FactorSolve::default();
        solve.prepare(&factor);
        let x: Vec<Vec3> = (0..n).map(|i| if active[i] { Vec3::new((i as f64).sin(), (i as f64 * 0.3).cos(), 0.1 * (i % 5) as f64) } else { Vec3::zeros() }).collect();
        let mut b = vec![Vec3::zeros(); n];
        a.multiply(&x, &mut b, &active);
        let mut z = vec![Vec3::zeros(); n];
        solve.with(&factor, None).apply(&b, &mut z);

        let supernodes = s.supernodes.as_ref().expect("supernodal");
        let rounded = supernodes.expand(&factor.memory.compact, scratch.values.len());
        let mut rhs = vec![0f32; s.unknowns];
        for (i, &f) in s.first.iter().enumerate() {
            if f != INACTIVE {
                for q in 0..3 {
                    rhs[f as usize + q] = b[i][q] as f32;
                }
            }
        }
        let mut buffer = MemBuffer::new(s.symbolic.solve_in_place_scratch::<f32>(1, Par::Seq));
        LltRef::<u32, f32>::new(&s.symbolic, &rounded).solve_in_place_with_conj(Conj::No, MatMut::from_column_major_slice_mut(&mut rhs[..], s.unknowns, 1), Par::Seq, MemStack::new(&mut buffer));
        let (mut from_faer, mut from_exact) = (0f64, 0f64);
        for (i, &f) in s.first.iter().enumerate() {
            if f != INACTIVE {
                for q in 0..3 {
                    from_faer = from_faer.max((z[i][q] - f64::from(rhs[f as usize + q])).abs());
                    from_exact = from_exact.max((z[i][q] - x[i][q]).abs());
                }
            } else {
                assert_eq!(z[i], Vec3::zeros());
            }
        }
        assert!(from_faer < 1e-5, "{from_faer}");
        assert!(from_exact > 1e-5 && from_exact < 2e-2, "{from_exact}");
    }

    /// A system turned node by node, `A' = W A Wᵀ`, is solved (to the factor's single
    /// precision) by the factor of `A` warped with `W`.
    #[test]
    fn a_warped_factor_solves_the_turned_system() {
        let (a, active) = lattice(5);
        let n = a.rows();
        let factor = Factor::of(&a, &active, Ordering::MinimumDegree).unwrap();
        let warp: Vec<Matrix3<f64>> = (0..n).map(|i| *nalgebra::Rotation3::from_scaled_axis(Vec3::new(0.1 * i as f64, -0.3, 0.02 * i as f64)).matrix()).collect();
        let mut turned = a.clone();
        for i in 0..n {
            for k in a.pattern.start[i] as usize..a.pattern.start[i + 1] as usize {
                let j = a.pattern.cols[k] as usize;
                let block = warp[i] * a.block(k) * warp[j].transpose();
                turned.values[k] = [0.0; 12];
                turned.add(k, &block);
            }
        }
        let mut solve = FactorSolve::default();
        solve.prepare(&factor);
        let x: Vec<Vec3> = (0..n).map(|i| if active[i] { Vec3::new(1.0, (i as f64).sin(), -0.5) } else { Vec3::zeros() }).collect();
        let mut b = vec![Vec3::zeros(); n];
        turned.multiply(&x, &mut b, &active);
        let mut z = vec![Vec3::zeros(); n];
        solve.with(&factor, Some(&warp)).apply(&b, &mut z);
        let error = (0..n).map(|i| (z[i] - x[i]).amax()).fold(0.0, f64::max);
        assert!(error < 1e-5, "{error}");
    }

    #[test]
    fn a_structure_fits_only_its_active_set() {
        let (a, active) = chain(5);
        let s = Structure::new(&a.pattern, &active, Ordering::MinimumDegree).unwrap();
        assert!(s.fits(&a.pattern, &active));
        assert!(!s.fits(&a.pattern, &[true; 5]));
    }

    #[test]
    fn an_indefinite_system_is_refused() {
        let (mut a, active) = chain(4);
        a.add_diagonal(a.pattern.diag[2] as usize, Vec3::repeat(-100.0));
        assert!(matches!(Factor::of(&a, &active, Ordering::MinimumDegree), Err(FactorError::NotPositiveDefinite(_))));
    }
}
