//! Geometric multigrid as a preconditioner for CG: a V-cycle over a hierarchy of
//! coarser systems, so that the iterations a solve needs do not grow as the fine level
//! gets finer.
//!
//! The model gives the levels: a prolongation `P` per coarser level (each fine unknown
//! interpolated from a few coarse ones; for the branched grid, the trilinear weights of
//! the condensation itself) and each coarse level's own matrix, which it re-assembles as
//! it likes (for the branched grid, the coarser grid's own corotational system: the
//! condensation is a Galerkin projection, so this is the fine operator projected, with
//! each coarse element's own rotation). The fine level always smooths with the current
//! system.
//!
//! Smoothing is block Gauss–Seidel: a forward sweep on the way down, a backward one on
//! the way up, which makes the V-cycle symmetric — a valid CG preconditioner — and
//! contracts for any symmetric positive definite operator, with nothing to tune. The
//! coarsest level gets [`COARSEST_SWEEPS`] symmetric sweeps (also a symmetric operator):
//! no factorization, so refreshing a level never makes a step wait. A static problem
//! (no mass: its slowest modes are what a few sweeps leave alone) instead takes its
//! coarse operators as Galerkin products of its held fine one ([`Hierarchy::galerkin`])
//! and solves its coarsest level exactly ([`Hierarchy::factor_coarsest`]).

use super::block_sparse::BlockMatrix;
use super::kernels::{self, RowProduct};
#[cfg(test)]
use super::block_sparse::Pattern;
use super::pcg::Preconditioner;
use super::preconditioner::BlockJacobi;
use crate::math::{Matrix3, Vec3};

/// Symmetric Gauss–Seidel sweep pairs on the coarsest level.
pub const COARSEST_SWEEPS: usize = 4;

/// Interpolation of a fine level's unknowns from a coarser level's: fine row `i` is
/// `Σ weight · coarse[col]` over its entries.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Prolongation {
    pub coarse_rows: usize,
    pub start: Vec<u32>,
    pub cols: Vec<u32>,
    pub weights: Vec<f64>,
}

impl Prolongation {
    /// From per-fine-row (coarse, weight) lists; zero weights are dropped.
    pub fn from_rows(coarse_rows: usize, rows: &[Vec<(u32, f64)>]) -> Self {
        let mut p = Prolongation { coarse_rows, start: vec![0], ..Default::default() };
        for row in rows {
            for &(c, w) in row {
                if w != 0.0 {
                    p.cols.push(c);
                    p.weights.push(w);
                }
            }
            p.start.push(p.cols.len() as u32);
        }
        p
    }

    pub fn fine_rows(&self) -> usize {
        self.start.len() - 1
    }

    fn row(&self, i: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
        (self.start[i] as usize..self.start[i + 1] as usize).map(|k| (self.cols[k] as usize, self.weights[k]))
    }

    /// `fine += P coarse` on the active fine rows (the others stay zero: the matrix
    /// products that follow take inactive unknowns as zero).
    fn prolong_add(&self, coarse: &[Vec3], fine: &mut [Vec3], active: &[bool]) {
        for (i, f) in fine.iter_mut().enumerate() {
            if active[i] {
                for (c, w) in self.row(i) {
                    *f += coarse[c] * w;
                }
            }
        }
    }

    /// `coarse = Pᵀ fine`.
    fn restrict(&self, fine: &[Vec3], coarse: &mut [Vec3]) {
        coarse.iter_mut().for_each(|c| *c = Vec3::zeros());
        for (i, f) in fine.iter().enumerate() {
            for (c, w) in self.row(i) {
                coarse[c] += f * w;
            }
        }
    }

    /// The coarse unknowns that feed an `active` fine one.
    fn fed(&self, active: &[bool]) -> Vec<bool> {
        let mut fed = vec![false; self.coarse_rows];
        for i in (0..self.fine_rows()).filter(|&i| active[i]) {
            for (c, _) in self.row(i) {
                fed[c] = true;
            }
        }
        fed
    }

    /// `Pᵀ A P` over `a`'s active rows and columns: the coarse operator of a fine one
    /// whose inactive (held) unknowns are zero. Where the fine level holds unknowns that
    /// no coarse unknown coincides with, this is the only coarse operator that knows the
    /// hold: a coarse level assembled from whole elements would let the body move there.
    fn galerkin(&self, a: &BlockMatrix<f64>, active: &[bool]) -> BlockMatrix<f64> {
        let n = self.coarse_rows;
        // Pᵀ by rows: the active fine rows each coarse unknown feeds, with the weight.
        let mut feeds: Vec<Vec<(u32, f64)>> = vec![Vec::new(); n];
        for i in (0..self.fine_rows()).filter(|&i| active[i]) {
            for (c, w) in self.row(i) {
                feeds[c].push((i as u32, w));
            }
        }
        // Row I sums w_iI w_jJ A_ij into block (I, J) over the fine couplings (i, j) of
        // the rows I feeds: `sums[J]` is that block while `seen[J] == I`.
        let (mut seen, mut sums) = (vec![u32::MAX; n], vec![Matrix3::zeros(); n]);
        let (mut start, mut cols, mut diag, mut values) = (vec![0u32], Vec::new(), Vec::with_capacity(n), Vec::new());
        for (row, fed) in feeds.iter().enumerate() {
            let first = cols.len();
            (seen[row], sums[row]) = (row as u32, Matrix3::zeros());
            cols.push(row as u32);
            for &(i, wi) in fed {
                for k in a.pattern.start[i as usize] as usize..a.pattern.start[i as usize + 1] as usize {
                    let j = a.pattern.cols[k] as usize;
                    if !active[j] {
                        continue;
                    }
                    let block = a.block(k);
                    for (col, wj) in self.row(j) {
                        if seen[col] != row as u32 {
                            (seen[col], sums[col]) = (row as u32, Matrix3::zeros());
                            cols.push(col as u32);
                        }
                        sums[col] += block * (wi * wj);
                    }
                }
            }
            cols[first..].sort_unstable();
            diag.push((first + cols[first..].binary_search(&(row as u32)).expect("the diagonal block")) as u32);
            values.extend(cols[first..].iter().map(|&col| sums[col as usize]));
            start.push(cols.len() as u32);
        }
        let mut coarse = BlockMatrix::<f64>::zeros(super::block_sparse::Pattern { start, cols, diag });
        for (k, value) in values.iter().enumerate() {
            coarse.add(k, value);
        }
        coarse
    }

}

/// One coarser level: its operator, the inverses of its diagonal blocks, and scratch.
#[derive(Debug, Clone)]
struct Level {
    /// From the level above (finer) to this one.
    prolongation: Prolongation,
    matrix: BlockMatrix<f64>,
    active: Vec<bool>,
    smoother: BlockJacobi,
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    t: Vec<Vec3>,
}

impl Level {
    fn new(prolongation: Prolongation, matrix: BlockMatrix<f64>, active: Vec<bool>) -> Self {
        let n = prolongation.coarse_rows;
        Level { prolongation, matrix, active, smoother: BlockJacobi::default(), r: vec![Vec3::zeros(); n], z: vec![Vec3::zeros(); n], t: vec![Vec3::zeros(); n] }
    }
}

/// Transfer operators and coarse operators of a hierarchy.
#[derive(Debug, Clone)]
pub struct Hierarchy {
    levels: Vec<Level>,
    /// The coarsest level solved exactly, where [`Hierarchy::factor_coarsest`] made it so.
    coarsest: Option<DenseSolve>,
}

/// A pivot below this share of the largest diagonal entry makes a matrix singular for
/// [`DenseSolve`] (round-off leaves about 1e-16 where a body is free to move).
const SINGULAR_PIVOT: f64 = 1e-13;

/// A dense Cholesky factor of a block matrix's active unknowns: a small system solved
/// exactly.
#[derive(Debug, Clone)]
pub struct DenseSolve {
    /// The active unknowns, in the factor's order.
    unknowns: Vec<usize>,
    factor: nalgebra::Cholesky<f64, nalgebra::Dyn>,
}

impl DenseSolve {
    /// None where `matrix` has more than `max_unknowns` active scalar unknowns or is not
    /// positive definite on them (to round-off: [`SINGULAR_PIVOT`]).
    pub fn new<T: super::block_sparse::Scalar>(matrix: &BlockMatrix<T>, active: &[bool], max_unknowns: usize) -> Option<Self> {
        let unknowns: Vec<usize> = (0..active.len()).filter(|&i| active[i]).collect();
        if 3 * unknowns.len() > max_unknowns {
            return None;
        }
        // The active rows' blocks at the active columns (not the whole matrix made dense:
        // the active part may be a small share of it).
        let mut position = vec![usize::MAX; active.len()];
        for (k, &i) in unknowns.iter().enumerate() {
            position[i] = k;
        }
        let mut a = nalgebra::DMatrix::zeros(3 * unknowns.len(), 3 * unknowns.len());
        for (k, &i) in unknowns.iter().enumerate() {
            for b in matrix.pattern.start[i] as usize..matrix.pattern.start[i + 1] as usize {
                let l = position[matrix.pattern.cols[b] as usize];
                if l != usize::MAX {
                    a.fixed_view_mut::<3, 3>(3 * k, 3 * l).copy_from(&matrix.block(b));
                }
            }
        }
        // Singular to round-off (a piece free to move), a factor may still come out, of
        // pivots near zero, and its solve is noise: refused.
        let largest = (0..a.nrows()).map(|i| a[(i, i)]).fold(0.0, f64::max);
        let factor = nalgebra::Cholesky::new(a)?;
        let l = factor.l_dirty();
        let smallest = (0..l.nrows()).map(|i| l[(i, i)] * l[(i, i)]).fold(f64::INFINITY, f64::min);
        (smallest > SINGULAR_PIVOT * largest).then_some(DenseSolve { unknowns, factor })
    }

    /// `z = A⁻¹ r` on the active unknowns (the others of `z` are left as they are).
    pub fn solve(&self, r: &[Vec3], z: &mut [Vec3]) {
        let b = nalgebra::DVector::from_fn(3 * self.unknowns.len(), |k, _| r[self.unknowns[k / 3]][k % 3]);
        let x = self.factor.solve(&b);
        for (k, &i) in self.unknowns.iter().enumerate() {
            z[i] = Vec3::new(x[3 * k], x[3 * k + 1], x[3 * k + 2]);
        }
    }
}

impl Hierarchy {
    /// A hierarchy of the given prolongations (finest first) and coarse matrices (one
    /// per prolongation, of its coarse size), each coarse unknown active when it feeds an
    /// active fine one.
    pub fn new(prolongations: Vec<Prolongation>, matrices: Vec<BlockMatrix<f64>>, fine_active: &[bool]) -> Self {
        let mut levels: Vec<Level> = Vec::with_capacity(prolongations.len());
        for (prolongation, matrix) in prolongations.into_iter().zip(matrices) {
            assert_eq!(matrix.rows(), prolongation.coarse_rows, "a coarse matrix of the prolongation's size");
            let active = prolongation.fed(levels.last().map_or(fine_active, |above| &above.active));
            levels.push(Level::new(prolongation, matrix, active));
        }
        let mut h = Hierarchy { levels, coarsest: None };
        h.update();
        h
    }

    /// A hierarchy of the given prolongations whose coarse operators are the Galerkin
    /// products of the level above (`Pᵀ A P` over its active unknowns, from the fine
    /// level's `a`), coarse unknowns active as in [`Hierarchy::new`]. For a static
    /// problem: a coarse operator of the whole body with no mass is singular, its rigid
    /// motions being what the fine level's support forbids, and a hold the coarse nodes
    /// do not coincide with (a support thinner than a cell, points of it inside coarse
    /// cells) is carried down exactly only by the product. A clamped bar of 3,321
    /// nodes: 40 iterations to 1e-12 (`grid::statics`), against 56 with the coarse
    /// grids' own operators and the coarse nodes on held fine ones held, 123 with
    /// neither that hold nor an exact coarsest solve.
    pub fn galerkin(prolongations: Vec<Prolongation>, a: &BlockMatrix<f64>, fine_active: &[bool]) -> Self {
        let mut levels: Vec<Level> = Vec::with_capacity(prolongations.len());
        for prolongation in prolongations {
            let (above, above_active) = levels.last().map_or((a, fine_active), |l| (&l.matrix, &l.active));
            let (matrix, active) = (prolongation.galerkin(above, above_active), prolongation.fed(above_active));
            levels.push(Level::new(prolongation, matrix, active));
        }
        let mut h = Hierarchy { levels, coarsest: None };
        h.update();
        h
    }

    /// Level `l`'s matrix, to re-assemble (then call [`Hierarchy::update`]).
    pub fn matrix_mut(&mut self, l: usize) -> &mut BlockMatrix<f64> {
        &mut self.levels[l].matrix
    }

    /// Level `l`'s active unknowns.
    pub fn active(&self, l: usize) -> &[bool] {
        &self.levels[l].active
    }

    /// Recomputes the smoothers (3×3 inverses of the diagonal blocks) from the levels'
    /// matrices.
    pub fn update(&mut self) {
        for level in &mut self.levels {
            level.smoother.update(&level.matrix, &level.active);
        }
    }

    /// Solves the coarsest level exactly from now on (a dense Cholesky factor of its
    /// matrix as it stands: call again after re-assembling it) instead of by
    /// [`COARSEST_SWEEPS`]; for a static problem, whose slowest modes a few sweeps leave
    /// as they are. False, and sweeps kept, where the coarsest level has more than
    /// `max_unknowns` active unknowns or its matrix is not positive definite (a piece no
    /// support holds).
    pub fn factor_coarsest(&mut self, max_unknowns: usize) -> bool {
        self.coarsest = self.levels.last().and_then(|level| DenseSolve::new(&level.matrix, &level.active, max_unknowns));
        self.coarsest.is_some()
    }

    pub fn depth(&self) -> usize {
        self.levels.len()
    }

    /// Unknowns per level, finest coarse level first.
    pub fn sizes(&self) -> Vec<usize> {
        self.levels.iter().map(|l| l.matrix.rows()).collect()
    }

    /// `z = M⁻¹ r`: one V-cycle below a fine level of matrix `a` whose diagonal blocks'
    /// inverses are `fine`.
    pub fn apply<T: RowProduct>(&mut self, a: &BlockMatrix<T>, fine: &BlockJacobi, active: &[bool], r: &[Vec3], z: &mut [Vec3], scratch: &mut [Vec3]) {
        z.iter_mut().for_each(|v| *v = Vec3::zeros());
        forward_sweep(a, fine, active, r, z);
        if self.levels.is_empty() {
            backward_sweep(a, fine, active, r, z);
            return;
        }
        // Residual, restricted, solved below, prolonged back.
        a.multiply(z, scratch, active);
        for i in 0..r.len() {
            scratch[i] = if active[i] { r[i] - scratch[i] } else { Vec3::zeros() };
        }
        self.descend(0, scratch);
        let (first, coarse) = (&self.levels[0], &self.levels[0].z);
        first.prolongation.prolong_add(coarse, z, active);
        backward_sweep(a, fine, active, r, z);
    }

    /// Solves level `l` approximately for the residual `fine_residual` of the level
    /// above, leaving the correction in `levels[l].z`.
    fn descend(&mut self, l: usize, fine_residual: &[Vec3]) {
        let (head, tail) = self.levels.split_at_mut(l + 1);
        let level = &mut head[l];
        level.prolongation.restrict(fine_residual, &mut level.r);
        level.z.iter_mut().for_each(|v| *v = Vec3::zeros());
        if tail.is_empty() {
            if let Some(exact) = &self.coarsest {
                exact.solve(&level.r, &mut level.z);
                return;
            }
            for _ in 0..COARSEST_SWEEPS {
                forward_sweep(&level.matrix, &level.smoother, &level.active, &level.r, &mut level.z);
                backward_sweep(&level.matrix, &level.smoother, &level.active, &level.r, &mut level.z);
            }
            return;
        }
        let n = level.r.len();
        forward_sweep(&level.matrix, &level.smoother, &level.active, &level.r, &mut level.z);
        level.matrix.multiply(&level.z, &mut level.t, &level.active);
        for i in 0..n {
            level.t[i] = if level.active[i] { level.r[i] - level.t[i] } else { Vec3::zeros() };
        }
        let residual = std::mem::take(&mut level.t);
        self.descend(l + 1, &residual);
        let (head, tail) = self.levels.split_at_mut(l + 1);
        let level = &mut head[l];
        level.t = residual;
        tail[0].prolongation.prolong_add(&tail[0].z, &mut level.z, &level.active);
        backward_sweep(&level.matrix, &level.smoother, &level.active, &level.r, &mut level.z);
    }
}

/// One block Gauss–Seidel sweep over the rows in order: `z_i = D_i⁻¹ (r_i − Σ_{j≠i}
/// A_ij z_j)` with the newest `z_j` (inactive rows stay zero).
fn forward_sweep<T: RowProduct>(a: &BlockMatrix<T>, inverse: &BlockJacobi, active: &[bool], r: &[Vec3], z: &mut [Vec3]) {
    kernels::gauss_seidel(&a.pattern, &a.values, &inverse.inverse, active, r, z, true);
}

/// The same, rows in reverse order.
fn backward_sweep<T: RowProduct>(a: &BlockMatrix<T>, inverse: &BlockJacobi, active: &[bool], r: &[Vec3], z: &mut [Vec3]) {
    kernels::gauss_seidel(&a.pattern, &a.values, &inverse.inverse, active, r, z, false);
}

/// A V-cycle below a fine matrix, as a CG preconditioner (it needs scratch space, kept
/// in a cell: CG's preconditioner is applied through a shared reference).
pub struct VCycle<'a, T: RowProduct> {
    pub hierarchy: std::cell::RefCell<&'a mut Hierarchy>,
    pub matrix: &'a BlockMatrix<T>,
    pub smoother: &'a BlockJacobi,
    pub active: &'a [bool],
    pub scratch: std::cell::RefCell<&'a mut Vec<Vec3>>,
}

impl<T: RowProduct> Preconditioner for VCycle<'_, T> {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]) {
        let mut scratch = self.scratch.borrow_mut();
        scratch.resize(r.len(), Vec3::zeros());
        self.hierarchy.borrow_mut().apply(self.matrix, self.smoother, self.active, r, z, &mut scratch);
    }
}

impl Preconditioner for DenseSolve {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]) {
        self.solve(r, z);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::pcg::{LinearOperator, Pcg, PcgSettings};

    struct Op<'a>(&'a BlockMatrix<f64>, &'a [bool]);

    impl LinearOperator for Op<'_> {
        fn apply(&self, x: &[Vec3], y: &mut [Vec3]) -> f64 {
            self.0.multiply(x, y, self.1)
        }
    }

    /// A 1D chain of `n` nodes (springs of stiffness `k`, little mass): hard for Jacobi,
    /// easy for multigrid.
    fn chain(n: usize, k: f64) -> BlockMatrix<f64> {
        let elements: Vec<Vec<u32>> = (0..n as u32 - 1).map(|i| vec![i, i + 1]).collect();
        let mut a = BlockMatrix::<f64>::zeros(Pattern::from_elements(n, elements.iter().map(|e| e.as_slice())));
        for i in 0..n - 1 {
            for (r, c, s) in [(i, i, 1.0), (i + 1, i + 1, 1.0), (i, i + 1, -1.0), (i + 1, i, -1.0)] {
                let at = a.pattern.find(r, c).unwrap();
                a.add(at, &(Matrix3::identity() * (s * k)));
            }
        }
        for i in 0..n {
            let at = a.pattern.diag[i] as usize;
            a.add_diagonal(at, Vec3::repeat(1e-6));
        }
        a
    }

    /// Linear interpolation from every second node.
    fn halving(fine: usize) -> Prolongation {
        let coarse = fine.div_ceil(2);
        let rows: Vec<Vec<(u32, f64)>> = (0..fine)
            .map(|i| if i % 2 == 0 { vec![((i / 2) as u32, 1.0)] } else { vec![((i / 2) as u32, 0.5), ((i / 2 + 1).min(coarse - 1) as u32, 0.5)] })
            .collect();
        Prolongation::from_rows(coarse, &rows)
    }

    #[test]
    fn the_galerkin_product_is_pt_a_p_over_the_active_unknowns() {
        let (n, held) = (9, 3);
        let a = chain(n, 2.0);
        let p = halving(n);
        let active: Vec<bool> = (0..n).map(|i| i != held).collect();
        let coarse = p.galerkin(&a, &active).to_dense();
        // The same product in dense form, the held row and column of A zeroed.
        let mut dense_p = nalgebra::DMatrix::<f64>::zeros(3 * n, 3 * p.coarse_rows);
        for i in 0..n {
            for (c, w) in p.row(i) {
                for d in 0..3 {
                    dense_p[(3 * i + d, 3 * c + d)] = w;
                }
            }
        }
        let mut dense_a = a.to_dense();
        for d in 0..3 {
            dense_a.row_mut(3 * held + d).fill(0.0);
            dense_a.column_mut(3 * held + d).fill(0.0);
        }
        let expected = dense_p.transpose() * dense_a * &dense_p;
        assert!((coarse - &expected).abs().max() < 1e-12 * expected.abs().max(), "{expected}");
    }

    #[test]
    fn a_v_cycle_keeps_the_iterations_flat_as_the_chain_grows() {
        let mut counts = Vec::new();
        for n in [65usize, 257, 1025] {
            let a = chain(n, 1.0);
            let mut active = vec![true; n];
            active[0] = false;
            let mut prolongations = Vec::new();
            let mut size = n;
            while size > 20 {
                prolongations.push(halving(size));
                size = size.div_ceil(2);
            }
            // Coarse operators: the chain rediscretized at each size (as a model would).
            // (Linear interpolation halves a 1D Laplacian's springs at each coarser level.)
            let matrices: Vec<BlockMatrix<f64>> = prolongations.iter().enumerate().map(|(l, p)| chain(p.coarse_rows, 0.5f64.powi(l as i32 + 1))).collect();
            let mut hierarchy = Hierarchy::new(prolongations, matrices, &active);
            let jacobi = BlockJacobi::new(&a, &active);
            let diagonal: Vec<Vec3> = (0..n).map(|i| a.diagonal(i)).collect();
            let b: Vec<Vec3> = (0..n).map(|i| if i == 0 { Vec3::zeros() } else { Vec3::new(1.0, (i as f64 * 0.1).sin(), -0.5) }).collect();
            let settings = PcgSettings { max_iterations: 500, tolerance: 1e-8, floor: 0.0, stalled_after: 0 };
            let mut pcg = Pcg::default();
            let mut scratch = Vec::new();
            let mut x = vec![Vec3::zeros(); n];
            let vcycle = VCycle { hierarchy: std::cell::RefCell::new(&mut hierarchy), matrix: &a, smoother: &jacobi, active: &active, scratch: std::cell::RefCell::new(&mut scratch) };
            let done = pcg.solve(&Op(&a, &active), &vcycle, &b, &mut x, &active, &diagonal, &settings);
            assert!(!done.cap_hit, "{n}: {done:?}");
            let mut y = vec![Vec3::zeros(); n];
            let plain = pcg.solve(&Op(&a, &active), &jacobi, &b, &mut y, &active, &diagonal, &settings);
            counts.push((done.iterations, plain.iterations));
        }
        // Jacobi's iterations grow with the chain; the V-cycle's stay nearly flat.
        assert!(counts[2].1 > 4 * counts[0].1, "{counts:?}");
        assert!(counts[2].0 <= counts[0].0 + 4, "{counts:?}");
    }
}
