//! A supernodal Cholesky factor kept compact, and its triangular solves.
//!
//! As a preconditioner the factor is applied once per conjugate-gradient iteration,
//! and each application reads the whole factor twice (`L y = b`, then `Lᵀ x = y`): on
//! the level-0 cantilever of docs/fem-comparison.md, 2.99 M entries, 12 MB in single
//! precision, faer's solves took 40 % of the physics thread (perf), about 1 ms an
//! application on this project's Xeon. The solves stream it from memory (this Xeon
//! streams 6–8 GB/s to one core), so every byte left out is time saved. The copy the
//! solves read keeps:
//!
//! - each column's diagonal entry in f32;
//! - the rest of each column (below the diagonal: within its supernode's diagonal block,
//!   then in the rectangle below it) in 8-bit integers with one scale per column (its
//!   largest magnitude over 127): a quarter of single precision's bytes;
//! - the diagonal blocks' strict lower triangles twice, packed by columns for the
//!   forward solve and by rows for the backward one (see [`backward`]), so that each
//!   solve reads its copy straight through.
//!
//! The precision costs little: the factor is of a system tens of steps old (other
//! rotations, other contacts), so it preconditions to that age's accuracy, not to its
//! digits. On that cantilever (600 sagging steps) the conjugate gradient took 2.32,
//! 2.35 and 2.36 iterations a step with 10, 8 and 7 stored mantissa bits against f32's
//! 23 (2.34); on 2026-11-28, 2.055 with the whole factor in bfloat16, 2.08 with the
//! rectangles in 8 bits, 2.085 with the diagonal blocks' too, while the bytes an
//! application reads fell from 10 MB to about 4 MB. The solve's tolerance, checked on
//! the true residual, decides the answer.
//!
//! The solves are this module's own (faer's read f32 or f64): for each supernode, its
//! dense diagonal block's triangle and its dense rectangle below, column-major, with
//! the rectangle's rows gathered from and scattered to the supernode's row indices.
//! Each output is a sum in one fixed order (per element in both solves' triangles and
//! the forward one's rectangle; the backward one's dot products in 32 lanes, then a
//! fixed tree), so the AVX2 code gives the baseline's bits (see `super::kernels`).

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use super::kernels::dispatch;

/// The largest magnitude an 8-bit entry holds (symmetric: -127..=127).
const LEVELS: f32 = 127.0;

/// The scale of a column's entries in 8 bits: the largest magnitude over [`LEVELS`]
/// (0 for a column of zeros).
fn scale_of(column: &[f32]) -> f32 {
    column.iter().fold(0f32, |m, v| m.max(v.abs())) / LEVELS
}

/// Entries of a column in 8 bits at `scale` (from [`scale_of`]) into `out`: each over
/// the scale, rounded to nearest, ties to even, by adding and taking off 1.5·2²³ (exact
/// for magnitudes under 2²²; `f32::round` is a library call on the baseline x86-64,
/// a fifth of the worker's copy).
fn quantize(column: &[f32], scale: f32, out: &mut Vec<i8>) {
    const ROUND: f32 = 12_582_912.0;
    if !(scale > 0.0) {
        out.extend(column.iter().map(|_| 0i8));
        return;
    }
    out.extend(column.iter().map(|&v| (((v / scale) + ROUND) - ROUND).clamp(-LEVELS, LEVELS) as i8));
}

/// A factor's values as the solves read them (see the module's doc).
#[derive(Debug, Clone, Default)]
pub struct Compact {
    /// Per supernode: its diagonal block's strict lower triangle in 8 bits, packed by
    /// columns (column j below the diagonal), then packed by rows (row i left of it).
    triangles: Vec<i8>,
    /// Per supernode: its rectangle (rows × columns, column-major) in 8 bits.
    rectangles: Vec<i8>,
    /// Per column of the factor: the scale of its 8-bit entries.
    scales: Vec<f32>,
    /// Per column of the factor: its diagonal entry.
    diagonal: Vec<f32>,
}

/// What the solves need of a supernodal symbolic factorization (faer's), copied once
/// per structure.
#[derive(Debug, Clone)]
pub struct Supernodes {
    /// Per supernode: its first column; one more entry, past the last column.
    begin: Vec<u32>,
    /// Per supernode: where its rectangle's row indices start in `rows`; one more entry.
    rows_at: Vec<u32>,
    /// The rectangles' row indices (the diagonal blocks' are the supernodes' columns).
    rows: Vec<u32>,
    /// Per supernode: where its values (rows × columns, column-major) start in faer's
    /// layout; one more.
    values_at: Vec<usize>,
    /// Per supernode: where its triangles start in [`Compact::triangles`]; one more.
    triangles_at: Vec<usize>,
    /// Per supernode: where its rectangle starts in [`Compact::rectangles`]; one more.
    rectangles_at: Vec<usize>,
    /// The most rows any rectangle has, and the most columns any supernode has: the
    /// solves' scratch.
    widest: usize,
    most_columns: usize,
}

/// Entries of a strict lower triangle of `columns` columns.
fn strict_triangle(columns: usize) -> usize {
    columns * (columns - 1) / 2
}

impl Supernodes {
    pub fn of(symbolic: &SymbolicSupernodalCholesky<u32>) -> Supernodes {
        let n = symbolic.n_supernodes();
        let mut begin = symbolic.supernode_begin().to_vec();
        begin.push(symbolic.supernode_end()[n - 1]);
        let values_at: Vec<usize> = symbolic.col_ptr_for_val().iter().map(|&v| v as usize).collect();
        let mut rows_at = Vec::with_capacity(n + 1);
        let mut triangles_at = Vec::with_capacity(n + 1);
        let mut rectangles_at = Vec::with_capacity(n + 1);
        let mut rows = Vec::new();
        let (mut widest, mut most_columns) = (0, 0);
        let (mut triangles, mut rectangles) = (0, 0);
        for s in 0..n {
            let columns = (begin[s + 1] - begin[s]) as usize;
            let below = (values_at[s + 1] - values_at[s]) / columns - columns;
            let at = symbolic.col_ptr_for_row_idx()[s] as usize;
            rows_at.push(rows.len() as u32);
            rows.extend_from_slice(&symbolic.row_idx()[at..at + below]);
            triangles_at.push(triangles);
            triangles += 2 * strict_triangle(columns);
            rectangles_at.push(rectangles);
            rectangles += below * columns;
            widest = widest.max(below);
            most_columns = most_columns.max(columns);
        }
        rows_at.push(rows.len() as u32);
        triangles_at.push(triangles);
        rectangles_at.push(rectangles);
        Supernodes { begin, rows_at, rows, values_at, triangles_at, rectangles_at, widest, most_columns }
    }

    /// The compact copy of a factor's `values` (faer's supernodal layout) into `out`.
    pub fn compact(&self, values: &[f32], out: &mut Compact) {
        out.triangles.clear();
        out.rectangles.clear();
        out.scales.clear();
        out.diagonal.clear();
        for s in 0..self.begin.len() - 1 {
            let (columns, height) = self.shape(s);
            let values = &values[self.values_at[s]..self.values_at[s + 1]];
            let by_columns = out.triangles.len();
            for j in 0..columns {
                let column = &values[j * height..(j + 1) * height];
                let scale = scale_of(&column[j + 1..]);
                out.diagonal.push(column[j]);
                out.scales.push(scale);
                quantize(&column[j + 1..columns], scale, &mut out.triangles);
                quantize(&column[columns..], scale, &mut out.rectangles);
            }
            // Row i's entries left of the diagonal, from the copy by columns (the same
            // 8-bit values: both solves apply one factor, so the preconditioner stays
            // symmetric).
            for i in 1..columns {
                for j in 0..i {
                    out.triangles.push(out.triangles[by_columns + triangle_at(columns, j) + (i - j - 1)]);
                }
            }
        }
    }

    /// The values (faer's layout, `len` of them) a compact copy stands for: what its
    /// solves solve with.
    #[cfg(test)]
    pub fn expand(&self, compact: &Compact, len: usize) -> Vec<f32> {
        let mut values = vec![0f32; len];
        for s in 0..self.begin.len() - 1 {
            let (columns, height) = self.shape(s);
            let (first, _, rows, triangles, rectangle) = self.supernode(s, compact);
            for j in 0..columns {
                let scale = compact.scales[first + j];
                let column = &mut values[self.values_at[s] + j * height..self.values_at[s] + (j + 1) * height];
                column[j] = compact.diagonal[first + j];
                for i in j + 1..columns {
                    column[i] = f32::from(triangles[triangle_at(columns, j) + (i - j - 1)]) * scale;
                }
                for k in 0..rows.len() {
                    column[columns + k] = f32::from(rectangle[j * rows.len() + k]) * scale;
                }
            }
        }
        values
    }

    /// Scratch the solves need (f32 values).
    pub fn scratch_len(&self) -> usize {
        self.widest + self.most_columns
    }

    /// Solves `L Lᵀ x = b` in place (`x` holds `b`, in the factor's elimination order),
    /// with `l` the factor's [`Self::compact`] copy and `scratch` at least
    /// [`Self::scratch_len`] long.
    pub fn solve(&self, l: &Compact, x: &mut [f32], scratch: &mut [f32]) {
        for s in 0..self.begin.len() - 1 {
            let (first, columns, rows, triangles, rectangle) = self.supernode(s, l);
            let t = &mut scratch[..rows.len()];
            let column = Column { diagonal: &l.diagonal[first..first + columns], scales: &l.scales[first..first + columns] };
            forward_supernode(column, &triangles[..triangles.len() / 2], rectangle, &mut x[first..first + columns], t);
            for (&row, &sum) in rows.iter().zip(t.iter()) {
                x[row as usize] -= sum;
            }
        }
        for s in (0..self.begin.len() - 1).rev() {
            let (first, columns, rows, triangles, rectangle) = self.supernode(s, l);
            let (g, below) = scratch.split_at_mut(rows.len());
            for (g, &row) in g.iter_mut().zip(rows) {
                *g = x[row as usize];
            }
            let column = Column { diagonal: &l.diagonal[first..first + columns], scales: &l.scales[first..first + columns] };
            backward_supernode(column, &triangles[triangles.len() / 2..], rectangle, &mut x[first..first + columns], g, &mut below[..columns]);
        }
    }

    /// Supernode `s`'s columns and its height in faer's layout (columns + rows below).
    fn shape(&self, s: usize) -> (usize, usize) {
        let columns = (self.begin[s + 1] - self.begin[s]) as usize;
        (columns, (self.values_at[s + 1] - self.values_at[s]) / columns)
    }

    /// Supernode `s`: its first column, its columns, its rectangle's rows, its diagonal
    /// block's strict triangles (by columns, then by rows), its rectangle.
    fn supernode<'a>(&'a self, s: usize, l: &'a Compact) -> (usize, usize, &'a [u32], &'a [i8], &'a [i8]) {
        let first = self.begin[s] as usize;
        let columns = self.shape(s).0;
        let rows = &self.rows[self.rows_at[s] as usize..self.rows_at[s + 1] as usize];
        (first, columns, rows, &l.triangles[self.triangles_at[s]..self.triangles_at[s + 1]], &l.rectangles[self.rectangles_at[s]..self.rectangles_at[s + 1]])
    }
}

/// Where column `j`'s entries below the diagonal start in a strict lower triangle of
/// `columns` columns packed by columns.
fn triangle_at(columns: usize, j: usize) -> usize {
    j * columns - j * (j + 1) / 2
}

/// A supernode's columns' diagonal entries and scales.
#[derive(Clone, Copy)]
pub struct Column<'a> {
    pub diagonal: &'a [f32],
    pub scales: &'a [f32],
}

/// One supernode of `L y = b`: its diagonal block's triangle solved in place in `x`
/// (its columns' entries), and `t = (rectangle) · x` (what the rows below take off).
/// `by_columns`: the block's strict lower triangle packed by columns; `rectangle`: t's
/// rows × x's columns, column-major; both in 8 bits, each column's scale taken into
/// its solved entry (so each update is one multiply-add).
#[inline(always)]
fn forward(column: Column<'_>, by_columns: &[i8], rectangle: &[i8], x: &mut [f32], t: &mut [f32]) {
    let columns = x.len();
    let rows = t.len();
    let mut at = 0;
    for j in 0..columns {
        let below = &by_columns[at..at + columns - 1 - j];
        at += columns - 1 - j;
        let xj = x[j] / column.diagonal[j];
        x[j] = xj;
        let s = xj * column.scales[j];
        for (xi, &l) in x[j + 1..].iter_mut().zip(below) {
            *xi = f32::from(l).mul_add(-s, *xi);
        }
    }
    // The rectangle, four columns at a time (each t[k] summed in column order).
    t.fill(0.0);
    let mut j = 0;
    while j + 4 <= columns {
        let c: [&[i8]; 4] = std::array::from_fn(|q| &rectangle[(j + q) * rows..(j + q + 1) * rows]);
        let s: [f32; 4] = std::array::from_fn(|q| x[j + q] * column.scales[j + q]);
        for (k, tk) in t.iter_mut().enumerate() {
            let sum = f32::from(c[0][k]).mul_add(s[0], *tk);
            let sum = f32::from(c[1][k]).mul_add(s[1], sum);
            let sum = f32::from(c[2][k]).mul_add(s[2], sum);
            *tk = f32::from(c[3][k]).mul_add(s[3], sum);
        }
        j += 4;
    }
    for j in j..columns {
        let c = &rectangle[j * rows..(j + 1) * rows];
        let s = x[j] * column.scales[j];
        for (tk, &l) in t.iter_mut().zip(c) {
            *tk = f32::from(l).mul_add(s, *tk);
        }
    }
}

/// One supernode of `Lᵀ x = y`: `x` holds its columns' entries of y, solved in place;
/// `g` the rows below, already solved; `by_rows` its diagonal block's strict lower
/// triangle packed by rows (row j: L's block's row j left of the diagonal);
/// `rectangle` as in [`forward`]; `below` (as long as `x`) scratch.
///
/// The rows below go first: each column's dot product with `g` (none waits for
/// another). Then the triangle last column first, each solved entry taken off the
/// entries before it (a row of L, contiguous in `by_rows`; each entry times its own
/// column's scale): one division and one multiply-add between an entry and the next,
/// where a dot product per column (the first version) put a whole reduction on that
/// path and took 1.6 times the forward solve's time (now about the same).
///
/// `WIDE`: with AVX2 and FMA (only from a function compiled for them, on a CPU that
/// has them).
#[inline(always)]
fn backward<const WIDE: bool>(column: Column<'_>, by_rows: &[i8], rectangle: &[i8], x: &mut [f32], g: &[f32], below: &mut [f32]) {
    let columns = x.len();
    let rows = g.len();
    for (j, below) in below.iter_mut().enumerate() {
        *below = column.scales[j] * dot::<WIDE>(&rectangle[j * rows..(j + 1) * rows], g);
    }
    for j in (0..columns).rev() {
        let row = &by_rows[j * j.saturating_sub(1) / 2..j * (j + 1) / 2];
        let xj = (x[j] - below[j]) / column.diagonal[j];
        x[j] = xj;
        for ((xi, &l), &scale) in x[..j].iter_mut().zip(row).zip(&column.scales[..j]) {
            *xi = (f32::from(l) * scale).mul_add(-xj, *xi);
        }
    }
}

dispatch! {
    /// [`forward`], vectorized where the CPU allows.
    pub fn forward_supernode(column: Column<'_>, by_columns: &[i8], rectangle: &[i8], x: &mut [f32], t: &mut [f32]) {
        forward(column, by_columns, rectangle, x, t)
    }
}

/// [`backward`], vectorized where the CPU allows. (Not by `dispatch!`: its dot
/// products are written in intrinsics for AVX2, since the compiler's own vectorization
/// of them came and went with the code around them, 2.5 times slower when it went.)
pub fn backward_supernode(column: Column<'_>, by_rows: &[i8], rectangle: &[i8], x: &mut [f32], g: &[f32], below: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn wide(column: Column<'_>, by_rows: &[i8], rectangle: &[i8], x: &mut [f32], g: &[f32], below: &mut [f32]) {
        backward::<true>(column, by_rows, rectangle, x, g, below)
    }
    #[cfg(target_arch = "x86_64")]
    if super::kernels::has_avx2() {
        // SAFETY: the CPU was checked to have AVX2 and FMA.
        return unsafe { wide(column, by_rows, rectangle, x, g, below) };
    }
    backward::<false>(column, by_rows, rectangle, x, g, below)
}

/// `Σ lₖ gₖ` in 32 lanes (four vectors, so that four multiply-adds are in flight
/// rather than one waiting for the last), the remainder's whole eights in the first
/// eight lanes, the rest one by one; then the lanes added in a fixed tree. `WIDE`: the
/// lanes in AVX2 and FMA intrinsics (see [`backward`]), the same operations.
#[inline(always)]
fn dot<const WIDE: bool>(l: &[i8], g: &[f32]) -> f32 {
    let n = l.len().min(g.len());
    let (by32, by8) = (n / 32 * 32, n / 8 * 8);
    let lanes = if WIDE { lanes_wide(l, g, by32, by8) } else { lanes_portable(l, g, by32, by8) };
    let mut tail = 0f32;
    for (&lk, &gk) in l[by8..n].iter().zip(&g[by8..n]) {
        tail = f32::from(lk).mul_add(gk, tail);
    }
    let v: [f32; 8] = std::array::from_fn(|q| (lanes[q] + lanes[8 + q]) + (lanes[16 + q] + lanes[24 + q]));
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7])) + tail
}

/// The lanes of [`dot`] over `l` and `g`'s first `by8` entries (`by32` of them by 32).
#[inline(always)]
fn lanes_portable(l: &[i8], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    let mut lanes = [0f32; 32];
    for (lc, gc) in l[..by32].chunks_exact(32).zip(g[..by32].chunks_exact(32)) {
        for q in 0..32 {
            lanes[q] = f32::from(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    for (lc, gc) in l[by32..by8].chunks_exact(8).zip(g[by32..by8].chunks_exact(8)) {
        for q in 0..8 {
            lanes[q] = f32::from(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    lanes
}

#[inline(always)]
fn lanes_wide(l: &[i8], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: only `backward::<true>` calls this, and only `backward_supernode`'s
    // `wide` runs that, where the CPU was checked to have AVX2 and FMA.
    return unsafe { lanes_avx2(l, g, by32, by8) };
    #[cfg(not(target_arch = "x86_64"))]
    lanes_portable(l, g, by32, by8)
}

/// [`lanes_portable`] in AVX2 and FMA intrinsics: lane by lane the same operations (an
/// 8-bit integer widened and converted, exactly, one fused multiply-add), so the same
/// bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn lanes_avx2(l: &[i8], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    use std::arch::x86_64::*;
    assert!(by32 <= by8 && by8 <= l.len() && by8 <= g.len());
    let widen = |at: usize| {
        // SAFETY: at + 8 ≤ by8, within l (asserted above).
        let eight = unsafe { _mm_loadl_epi64(l.as_ptr().add(at).cast::<__m128i>()) };
        _mm256_cvtepi32_ps(_mm256_cvtepi8_epi32(eight))
    };
    let mut sums = [_mm256_setzero_ps(); 4];
    // SAFETY (every load of g): k + 8 ≤ by8, within g (asserted above).
    for k in (0..by32).step_by(32) {
        for (q, sum) in sums.iter_mut().enumerate() {
            let at = k + 8 * q;
            *sum = _mm256_fmadd_ps(widen(at), unsafe { _mm256_loadu_ps(g.as_ptr().add(at)) }, *sum);
        }
    }
    for k in (by32..by8).step_by(8) {
        sums[0] = _mm256_fmadd_ps(widen(k), unsafe { _mm256_loadu_ps(g.as_ptr().add(k)) }, sums[0]);
    }
    let mut lanes = [0f32; 32];
    for (q, sum) in sums.iter().enumerate() {
        // SAFETY: eight f32 into lanes 8q..8q + 8 of 32.
        unsafe { _mm256_storeu_ps(lanes.as_mut_ptr().add(8 * q), *sum) };
    }
    lanes
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_column_in_eight_bits_keeps_its_largest_entry_and_rounds_the_rest_to_its_scale() {
        let column = [0.5f32, -2.54, 0.0, 1e-3, 2.54];
        let scale = scale_of(&column);
        assert_eq!(scale, 2.54 / 127.0);
        let mut q = Vec::new();
        quantize(&column, scale, &mut q);
        assert_eq!(q, vec![25, -127, 0, 0, 127]);
        for (&v, &q) in column.iter().zip(&q) {
            assert!((f32::from(q) * scale - v).abs() <= 0.5 * scale * 1.0001, "{v}");
        }
        // Ties go to the even neighbour: 1.5 and 2.5 units of the scale to 2.
        let mut ties = Vec::new();
        quantize(&[1.5, 2.5, -127.0], 1.0, &mut ties);
        assert_eq!(ties, vec![2, 2, -127]);
        let mut zeros = Vec::new();
        assert_eq!(scale_of(&[0.0, 0.0]), 0.0);
        quantize(&[0.0, 0.0], 0.0, &mut zeros);
        assert_eq!(zeros, vec![0, 0]);
    }

    /// A supernode of 11 columns over 37 rows below: the solves compiled for the
    /// baseline and for AVX2 and FMA give the same bits, and solve the block its compact
    /// copy stands for.
    #[test]
    fn a_supernode_solves_to_the_same_bits_with_and_without_avx2() {
        let (columns, below) = (11, 37);
        let entry = |i: usize, j: usize| if i == j { 2.0 + j as f32 * 0.1 } else if i < j { 0.0 } else { ((i * 7 + j * 3) % 11) as f32 * 0.05 - 0.2 };
        let (mut by_columns, mut rectangle, mut scales, mut diagonal) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for j in 0..columns {
            let column: Vec<f32> = (0..columns + below).map(|i| entry(i, j)).collect();
            let scale = scale_of(&column[j + 1..]);
            quantize(&column[j + 1..columns], scale, &mut by_columns);
            quantize(&column[columns..], scale, &mut rectangle);
            scales.push(scale);
            diagonal.push(column[j]);
        }
        let by_rows: Vec<i8> = (1..columns).flat_map(|i| (0..i).map(move |j| (i, j))).map(|(i, j)| by_columns[triangle_at(columns, j) + i - j - 1]).collect();
        let column = Column { diagonal: &diagonal, scales: &scales };
        let x0: Vec<f32> = (0..columns).map(|j| (j as f32 * 0.7).sin()).collect();
        let g: Vec<f32> = (0..below).map(|k| (k as f32 * 0.3).cos()).collect();
        let run = |forward_fn: &dyn Fn(&mut [f32], &mut [f32]), backward_fn: &dyn Fn(&mut [f32], &[f32], &mut [f32])| {
            let (mut y, mut t) = (x0.clone(), vec![0f32; below]);
            forward_fn(&mut y, &mut t);
            let mut x = y.clone();
            backward_fn(&mut x, &g, &mut vec![0f32; columns]);
            (y, t, x)
        };
        let baseline = run(&|x, t| forward(column, &by_columns, &rectangle, x, t), &|x, g, b| backward::<false>(column, &by_rows, &rectangle, x, g, b));
        // What each solve solves, with the values the compact copy stands for (close
        // to the block's own): L₁₁ y = x0 and t = L₂₁ y; L₁₁ᵀ x + L₂₁ᵀ g = y.
        let l = |i: usize, j: usize| match i {
            _ if i < j => 0.0,
            _ if i == j => f64::from(diagonal[j]),
            _ if i < columns => f64::from(by_columns[triangle_at(columns, j) + i - j - 1]) * f64::from(scales[j]),
            _ => f64::from(rectangle[j * below + i - columns]) * f64::from(scales[j]),
        };
        for i in 0..columns + below {
            for j in 0..columns {
                assert!((l(i, j) - f64::from(entry(i, j))).abs() <= 0.5 * f64::from(scales[j]) * 1.0001, "entry {i}, {j}");
            }
        }
        let (y, t, x) = &baseline;
        for i in 0..columns {
            let lower: f64 = (0..=i).map(|j| l(i, j) * f64::from(y[j])).sum();
            assert!((lower - f64::from(x0[i])).abs() < 1e-5, "forward row {i}");
            let upper: f64 = (i..columns).map(|j| l(j, i) * f64::from(x[j])).sum::<f64>() + (0..below).map(|k| l(columns + k, i) * f64::from(g[k])).sum::<f64>();
            assert!((upper - f64::from(y[i])).abs() < 1e-5, "backward row {i}");
        }
        for k in 0..below {
            let product: f64 = (0..columns).map(|j| l(columns + k, j) * f64::from(y[j])).sum();
            assert!((product - f64::from(t[k])).abs() < 1e-5, "rectangle row {k}");
        }
        #[cfg(target_arch = "x86_64")]
        if crate::solver::kernels::has_avx2() {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn forward_wide(column: Column<'_>, by_columns: &[i8], rectangle: &[i8], x: &mut [f32], t: &mut [f32]) {
                forward(column, by_columns, rectangle, x, t)
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn backward_wide(column: Column<'_>, by_rows: &[i8], rectangle: &[i8], x: &mut [f32], g: &[f32], below: &mut [f32]) {
                backward::<true>(column, by_rows, rectangle, x, g, below)
            }
            // SAFETY: the CPU was checked to have AVX2 and FMA.
            let wide = run(&|x, t| unsafe { forward_wide(column, &by_columns, &rectangle, x, t) }, &|x, g, b| unsafe { backward_wide(column, &by_rows, &rectangle, x, g, b) });
            let bits = |v: &[f32]| v.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
            assert_eq!(bits(&baseline.0), bits(&wide.0));
            assert_eq!(bits(&baseline.1), bits(&wide.1));
            assert_eq!(bits(&baseline.2), bits(&wide.2));
        }
    }

    #[test]
    fn a_dot_product_sums_its_lanes_in_a_fixed_order() {
        // Lengths with and without whole 32s, whole 8s and a tail.
        for n in [0, 5, 8, 19, 32, 45, 77, 200] {
            let l: Vec<i8> = (0..n).map(|k| ((k * 37) % 255) as i32 - 127).map(|v| v as i8).collect();
            let g: Vec<f32> = (0..n).map(|k| 1.0 / (k as f32 + 1.0)).collect();
            let exact: f64 = l.iter().zip(&g).map(|(&l, &g)| f64::from(l) * f64::from(g)).sum();
            let sum = dot::<false>(&l, &g);
            assert!((f64::from(sum) - exact).abs() < 1e-4 * exact.abs().max(1.0), "{n}");
            #[cfg(target_arch = "x86_64")]
            if crate::solver::kernels::has_avx2() {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide(l: &[i8], g: &[f32]) -> f32 {
                    dot::<true>(l, g)
                }
                // SAFETY: the CPU was checked to have AVX2 and FMA.
                assert_eq!(unsafe { wide(&l, &g) }.to_bits(), sum.to_bits(), "{n}");
            }
        }
    }
}
