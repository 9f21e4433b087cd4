//! A sparse matrix of 3×3 blocks in block-compressed-row form (BSR): the system matrix
//! of a tissue whose unknowns are 3-vectors per node.
//!
//! The pattern (which blocks exist) is built once per topology from the elements'
//! node lists — every pair of nodes of an element is a block — and kept apart from the
//! values, which are refreshed every step. [`Scatter`] maps each element's 8 × 8 corner
//! pairs to their blocks once, so assembling an element is 64 block additions without
//! a search.

use crate::math::{Matrix3, Vec3};

/// Which 3×3 blocks exist: for block row `i`, columns `cols[start[i]..start[i+1]]`,
/// sorted, the diagonal among them.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Pattern {
    pub start: Vec<u32>,
    pub cols: Vec<u32>,
    /// Index (into `cols`) of each row's diagonal block.
    pub diag: Vec<u32>,
}

impl Pattern {
    /// The pattern of `n` block rows coupling every pair of nodes that share an element.
    /// Every row gets its diagonal block, coupled or not.
    pub fn from_elements<'a>(n: usize, elements: impl Iterator<Item = &'a [u32]> + Clone) -> Pattern {
        Self::from_elements_coupling(n, elements, |_| true)
    }

    /// As [`Pattern::from_elements`], coupling only nodes for which `coupled` is true: a
    /// node left out keeps its diagonal block alone (a held node, whose unknown is zero:
    /// its blocks would only multiply zeros).
    pub fn from_elements_coupling<'a>(n: usize, elements: impl Iterator<Item = &'a [u32]> + Clone, coupled: impl Fn(u32) -> bool) -> Pattern {
        // Count neighbours (with repeats), then fill, sort and deduplicate per row.
        let mut count = vec![1u32; n];
        for nodes in elements.clone() {
            for &a in nodes {
                if coupled(a) {
                    count[a as usize] += nodes.len() as u32;
                }
            }
        }
        let mut start = Vec::with_capacity(n + 1);
        start.push(0u32);
        for c in &count {
            start.push(start.last().copied().unwrap_or(0) + c);
        }
        let mut fill = start[..n].to_vec();
        let mut cols = vec![0u32; start[n] as usize];
        for (i, f) in fill.iter_mut().enumerate() {
            cols[*f as usize] = i as u32;
            *f += 1;
        }
        for nodes in elements {
            for &a in nodes.iter().filter(|&&a| coupled(a)) {
                for &b in nodes.iter().filter(|&&b| coupled(b)) {
                    cols[fill[a as usize] as usize] = b;
                    fill[a as usize] += 1;
                }
            }
        }
        // Compact each row in place: drop repeats (a table of the row that last took
        // each column), then sort what is left — a row holds each neighbour once per
        // shared element, eight times over in a hexahedral mesh, so sorting after the
        // repeats are gone is several times cheaper than before.
        let mut out_start = Vec::with_capacity(n + 1);
        out_start.push(0u32);
        let mut write = 0usize;
        let mut taken_by = vec![u32::MAX; n];
        for i in 0..n {
            let row_start = write;
            // Rows only move left (write ≤ start[i] ≤ j), so reading ahead is safe.
            for j in start[i] as usize..start[i + 1] as usize {
                let c = cols[j];
                if taken_by[c as usize] != i as u32 {
                    taken_by[c as usize] = i as u32;
                    cols[write] = c;
                    write += 1;
                }
            }
            cols[row_start..write].sort_unstable();
            out_start.push(write as u32);
        }
        cols.truncate(write);
        cols.shrink_to_fit();
        let diag = (0..n)
            .map(|i| {
                let row = &cols[out_start[i] as usize..out_start[i + 1] as usize];
                out_start[i] + row.binary_search(&(i as u32)).expect("every row has its diagonal") as u32
            })
            .collect();
        Pattern { start: out_start, cols, diag }
    }

    pub fn rows(&self) -> usize {
        self.start.len().saturating_sub(1)
    }

    pub fn blocks(&self) -> usize {
        self.cols.len()
    }

    /// The index of block (row, col), if it exists.
    pub fn find(&self, row: usize, col: usize) -> Option<usize> {
        let (s, e) = (self.start[row] as usize, self.start[row + 1] as usize);
        self.cols[s..e].binary_search(&(col as u32)).ok().map(|k| s + k)
    }
}

/// A corner pair with no block in the pattern (an element left out, or a held node's
/// coupling); adding to it adds nothing.
pub const NO_BLOCK: u32 = u32::MAX;

/// Where each element's corner pairs live in the matrix: `blocks[e][8 i + j]` is block
/// (node of corner i, node of corner j); [`NO_BLOCK`] for an element not in the pattern
/// and for a pair the pattern leaves out.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Scatter {
    pub blocks: Vec<[u32; 64]>,
    /// Per element, bit `8 i + j` set where pair (i, j)'s block is written by no element
    /// before it: assembling every included element in order, storing those blocks
    /// instead of adding to them, and zeroing [`Scatter::unwritten`] makes the matrix
    /// without first zeroing all of it (a pass over every block, 4 % of a level-0 step).
    pub first: Vec<u64>,
    /// The blocks no included element writes (a lone node's diagonal, a held node's).
    pub unwritten: Vec<u32>,
}

impl Scatter {
    /// For the elements whose `included` flag is set (the others map nowhere).
    ///
    /// Row by row: the row's columns are spread into a dense position table, every
    /// element corner on that row reads its eight blocks from it, and the table is
    /// cleared again. A binary search per corner pair (64 per element) took a third of
    /// a millisecond on the liver's level 2 after every cut; this takes a tenth.
    pub fn new(pattern: &Pattern, elements: &[[u32; 8]], included: &[bool]) -> Scatter {
        let n = pattern.rows();
        // The (element, corner) pairs on each node, in compressed rows.
        let mut start = vec![0u32; n + 1];
        for (nodes, _) in elements.iter().zip(included).filter(|(_, on)| **on) {
            for &a in nodes {
                start[a as usize + 1] += 1;
            }
        }
        for a in 0..n {
            start[a + 1] += start[a];
        }
        let mut fill = start.clone();
        let mut corners = vec![(0u32, 0u8); start[n] as usize];
        for (e, (nodes, _)) in elements.iter().zip(included).enumerate().filter(|(_, (_, on))| **on) {
            for (i, &a) in nodes.iter().enumerate() {
                corners[fill[a as usize] as usize] = (e as u32, i as u8);
                fill[a as usize] += 1;
            }
        }
        let mut blocks = vec![[NO_BLOCK; 64]; elements.len()];
        let mut position = vec![NO_BLOCK; n];
        for a in 0..n {
            let row = pattern.start[a] as usize..pattern.start[a + 1] as usize;
            for k in row.clone() {
                position[pattern.cols[k] as usize] = k as u32;
            }
            for &(e, i) in &corners[start[a] as usize..start[a + 1] as usize] {
                let (e, i) = (e as usize, i as usize);
                for j in 0..8 {
                    blocks[e][8 * i + j] = position[elements[e][j] as usize];
                }
            }
            for k in row {
                position[pattern.cols[k] as usize] = NO_BLOCK;
            }
        }
        // Which element writes each block first, in element order (what an assembly
        // that stores those blocks instead of adding to them needs; no block is written
        // twice as a first).
        let mut first = vec![0u64; elements.len()];
        let mut written = vec![false; pattern.blocks()];
        for (e, pairs) in blocks.iter().enumerate() {
            for (k, &b) in pairs.iter().enumerate().filter(|(_, b)| **b != NO_BLOCK) {
                if !std::mem::replace(&mut written[b as usize], true) {
                    first[e] |= 1 << k;
                }
            }
        }
        let unwritten = (0..pattern.blocks() as u32).filter(|&b| !written[b as usize]).collect();
        Scatter { blocks, first, unwritten }
    }
}

/// The number type of a matrix's values: f64 where precision matters (a factorization,
/// coarse operators), f32 for the per-step system (half the memory traffic; its
/// relative precision, 6e-8, is far below any solve's tolerance).
pub trait Scalar: Copy + Default + PartialEq + std::fmt::Debug + Send + Sync + 'static {
    fn to_f64(self) -> f64;
    fn from_f64(v: f64) -> Self;
}

impl Scalar for f64 {
    fn to_f64(self) -> f64 {
        self
    }
    fn from_f64(v: f64) -> Self {
        v
    }
}

impl Scalar for f32 {
    fn to_f64(self) -> f64 {
        f64::from(self)
    }
    fn from_f64(v: f64) -> Self {
        v as f32
    }
}

/// A set of indices below a bound (a pattern's blocks, a matrix's rows), for refreshing
/// only what changed: a flag per index and the list of those set, so clearing costs
/// what was marked. Inserting [`NO_BLOCK`] does nothing. Allocates only in `reset`
/// (room for every index), never when inserting.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct IndexSet {
    flags: Vec<bool>,
    list: Vec<u32>,
}

impl IndexSet {
    /// Empties the set and sizes it for indices below `bound`.
    pub fn reset(&mut self, bound: usize) {
        self.clear();
        self.flags.resize(bound, false);
        self.list.reserve(bound);
    }

    /// Makes room for indices below `bound` too, keeping what is in it.
    pub fn grow(&mut self, bound: usize) {
        if bound > self.flags.len() {
            self.flags.resize(bound, false);
            self.list.reserve(bound - self.list.len());
        }
    }

    pub fn insert(&mut self, index: u32) {
        if index != NO_BLOCK && !std::mem::replace(&mut self.flags[index as usize], true) {
            self.list.push(index);
        }
    }

    pub fn contains(&self, index: u32) -> bool {
        index != NO_BLOCK && self.flags[index as usize]
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    pub fn is_empty(&self) -> bool {
        self.list.is_empty()
    }

    /// The indices in the order they were first inserted.
    pub fn iter(&self) -> impl Iterator<Item = u32> + '_ {
        self.list.iter().copied()
    }

    pub fn clear(&mut self) {
        for &b in &self.list {
            self.flags[b as usize] = false;
        }
        self.list.clear();
    }
}

/// A block's 3×3 values, column-major, each column padded to 4 lanes (the fourth is
/// always zero): a column is one vector register, so a block times a 3-vector is three
/// vector multiply-adds.
pub type Block<T> = [T; 12];

/// The index of entry (row, column) in a [`Block`].
#[inline]
pub const fn at(row: usize, column: usize) -> usize {
    4 * column + row
}

/// A block-sparse matrix: a pattern and a 3×3 value per block.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BlockMatrix<T: Scalar = f64> {
    pub pattern: Pattern,
    pub values: Vec<Block<T>>,
}

impl<T: Scalar> BlockMatrix<T> {
    pub fn zeros(pattern: Pattern) -> Self {
        let values = vec![[T::default(); 12]; pattern.blocks()];
        BlockMatrix { pattern, values }
    }

    pub fn rows(&self) -> usize {
        self.pattern.rows()
    }

    pub fn clear(&mut self) {
        self.values.iter_mut().for_each(|v| *v = [T::default(); 12]);
    }

    pub fn block(&self, k: usize) -> Matrix3<f64> {
        Matrix3::from_fn(|r, c| self.values[k][at(r, c)].to_f64())
    }

    /// The diagonal of row `i`'s diagonal block.
    pub fn diagonal(&self, i: usize) -> Vec3 {
        let v = &self.values[self.pattern.diag[i] as usize];
        Vec3::new(v[at(0, 0)].to_f64(), v[at(1, 1)].to_f64(), v[at(2, 2)].to_f64())
    }

    /// Adds `m` to block `k` (nothing for [`NO_BLOCK`]).
    pub fn add(&mut self, k: usize, m: &Matrix3<f64>) {
        if k == NO_BLOCK as usize {
            return;
        }
        let v = &mut self.values[k];
        for r in 0..3 {
            for c in 0..3 {
                v[at(r, c)] = T::from_f64(v[at(r, c)].to_f64() + m[(r, c)]);
            }
        }
    }

    /// Adds `s` on block `k`'s diagonal.
    pub fn add_diagonal(&mut self, k: usize, s: Vec3) {
        if k == NO_BLOCK as usize {
            return;
        }
        let v = &mut self.values[k];
        for (a, d) in [at(0, 0), at(1, 1), at(2, 2)].into_iter().zip([s.x, s.y, s.z]) {
            v[a] = T::from_f64(v[a].to_f64() + d);
        }
    }

    /// `y = A x` over the rows where `active` is true (other rows of y are zero; columns
    /// of inactive nodes must hold zero in x). Returns `xᵀ y`. Values are widened to f64;
    /// each row accumulates in six fixed sums (vectorized, see kernels::row_generic).
    pub fn multiply(&self, x: &[Vec3], y: &mut [Vec3], active: &[bool]) -> f64
    where
        T: super::kernels::RowProduct,
    {
        super::kernels::block_multiply(&self.pattern, &self.values, x, y, active)
    }

    /// The dense matrix (tests and small coarse problems).
    pub fn to_dense(&self) -> nalgebra::DMatrix<f64> {
        let n = self.rows();
        let mut d = nalgebra::DMatrix::zeros(3 * n, 3 * n);
        for i in 0..n {
            for k in self.pattern.start[i] as usize..self.pattern.start[i + 1] as usize {
                let j = self.pattern.cols[k] as usize;
                for r in 0..3 {
                    for c in 0..3 {
                        d[(3 * i + r, 3 * j + c)] = self.values[k][at(r, c)].to_f64();
                    }
                }
            }
        }
        d
    }
}

impl BlockMatrix<f32> {
    /// Adds `scale ·` a 24 × 24 element matrix in planar layout (see
    /// `kernels::Planar24`) to the blocks its corners map to.
    pub fn add_element(&mut self, blocks: &[u32; 64], m: &super::kernels::Planar24, scale: f32) {
        super::kernels::scatter_element(&mut self.values, blocks, m, scale, 0);
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn an_index_set_keeps_each_index_once_ignores_no_block_and_clears_what_it_marked() {
        let mut set = IndexSet::default();
        set.reset(5);
        for b in [3, 1, 3, NO_BLOCK, 4] {
            set.insert(b);
        }
        assert_eq!(set.iter().collect::<Vec<_>>(), vec![3, 1, 4]);
        assert!(set.contains(1) && !set.contains(0) && !set.contains(NO_BLOCK));
        set.clear();
        assert!(set.is_empty() && (0..5).all(|b| !set.contains(b)));
        set.insert(0);
        assert_eq!(set.len(), 1);
    }

    use super::*;

    #[test]
    fn the_scatter_finds_every_corner_pairs_block_as_a_search_would() {
        // Overlapping hexahedra on a 4 × 3 × 3 lattice of nodes, one left out, and a
        // pattern that leaves node 5's couplings out.
        let node = |x: u32, y: u32, z: u32| x + 4 * (y + 3 * z);
        let mut elements = Vec::new();
        for (x, y, z) in [(0, 0, 0), (1, 0, 0), (2, 0, 0), (0, 1, 1), (1, 1, 0), (2, 1, 1)] {
            elements.push(std::array::from_fn::<u32, 8, _>(|c| node(x + (c as u32 & 1), y + ((c as u32 >> 1) & 1), z + ((c as u32 >> 2) & 1))));
        }
        let included = [true, true, false, true, true, true];
        let live = elements.iter().zip(&included).filter(|(_, on)| **on).map(|(e, _)| &e[..]);
        let pattern = Pattern::from_elements_coupling(36, live, |n| n != 5);
        let scatter = Scatter::new(&pattern, &elements, &included);
        for (e, nodes) in elements.iter().enumerate() {
            for k in 0..64 {
                let expected = if included[e] { pattern.find(nodes[k / 8] as usize, nodes[k % 8] as usize).map_or(NO_BLOCK, |b| b as u32) } else { NO_BLOCK };
                assert_eq!(scatter.blocks[e][k], expected, "element {e}, pair {k}");
            }
        }
        assert!(scatter.blocks[0].contains(&NO_BLOCK), "node 5's couplings are left out");
        // Each block is first written by exactly one element, the earliest holding it;
        // the unwritten ones by none.
        let mut firsts = vec![0; pattern.blocks()];
        for (e, pairs) in scatter.blocks.iter().enumerate() {
            for (k, &b) in pairs.iter().enumerate() {
                if (scatter.first[e] >> k) & 1 == 1 {
                    firsts[b as usize] += 1;
                    let earlier = scatter.blocks[..e].iter().any(|p| p.contains(&b)) || pairs[..k].contains(&b);
                    assert!(!earlier, "element {e} pair {k}: block {b} was written before");
                }
            }
        }
        for b in 0..pattern.blocks() {
            let held = scatter.blocks.iter().any(|p| p.contains(&(b as u32)));
            assert_eq!(firsts[b], usize::from(held), "block {b}");
            assert_eq!(scatter.unwritten.contains(&(b as u32)), !held, "block {b}");
        }
        assert!(!scatter.unwritten.is_empty(), "nodes no included element holds keep a diagonal block");
        // Adding at a left-out pair adds nothing (and does not index past the values).
        let mut a = BlockMatrix::<f64>::zeros(pattern);
        a.add(NO_BLOCK as usize, &Matrix3::identity());
        a.add_diagonal(NO_BLOCK as usize, Vec3::repeat(1.0));
        assert!(a.values.iter().all(|v| v.iter().all(|&x| x == 0.0)));
    }

    #[test]
    fn the_pattern_couples_the_nodes_of_each_element_and_products_match_dense() {
        // Two "elements" sharing node 2; node 5 belongs to none but still has a diagonal.
        let elements: Vec<Vec<u32>> = vec![vec![0, 1, 2], vec![2, 3, 4]];
        let pattern = Pattern::from_elements(6, elements.iter().map(|e| e.as_slice()));
        assert_eq!(pattern.cols[pattern.start[2] as usize..pattern.start[3] as usize], [0, 1, 2, 3, 4]);
        assert_eq!(pattern.cols[pattern.start[5] as usize..pattern.start[6] as usize], [5]);
        assert_eq!(pattern.find(0, 4), None);
        assert_eq!(pattern.blocks(), 3 * 3 * 2 - 1 + 1);
        let mut a = BlockMatrix::<f64>::zeros(pattern);
        for (k, v) in a.values.iter_mut().enumerate() {
            for r in 0..3 {
                for c in 0..3 {
                    v[at(r, c)] = (k * 9 + 3 * r + c) as f64 * 0.1 - 1.0;
                }
            }
        }
        let x: Vec<Vec3> = (0..6).map(|i| Vec3::new(i as f64, 1.0 - i as f64, 0.5)).collect();
        let mut y = vec![Vec3::zeros(); 6];
        let active = [true, true, true, false, true, true];
        let mut masked = x.clone();
        masked[3] = Vec3::zeros();
        let xy = a.multiply(&masked, &mut y, &active);
        let dense = a.to_dense() * nalgebra::DVector::from_iterator(18, masked.iter().flat_map(|v| [v.x, v.y, v.z]));
        for i in 0..6 {
            let expected = if active[i] { Vec3::new(dense[3 * i], dense[3 * i + 1], dense[3 * i + 2]) } else { Vec3::zeros() };
            assert!((y[i] - expected).norm() < 1e-12, "row {i}");
        }
        let expected_xy: f64 = (0..6).map(|i| masked[i].dot(&y[i])).sum();
        assert!((xy - expected_xy).abs() < 1e-12);
    }
}
