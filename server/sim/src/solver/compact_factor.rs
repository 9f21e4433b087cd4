//! A supernodal Cholesky factor kept in bfloat16, and its triangular solves.
//!
//! As a preconditioner the factor is applied once per conjugate-gradient iteration,
//! and each application reads the whole factor twice (`L y = b`, then `Lᵀ x = y`): on
//! the level-0 cantilever of docs/fem-comparison.md, 2.99 M entries, 12 MB in single
//! precision, faer's solves took 40 % of the physics thread (perf), about 1 ms an
//! application on this project's Xeon. Kept in bfloat16 (the upper half of an f32: its
//! range, 8 significant bits) the factor is half the bytes.
//!
//! The precision costs nothing measurable: the factor is of a system tens of steps old
//! (other rotations, other contacts), so it preconditions to that age's accuracy, not
//! to its digits. On that cantilever (600 sagging steps, the factor's values rounded to
//! 10, 8 and 7 stored mantissa bits against f32's 23) the conjugate gradient took 2.32,
//! 2.35 and 2.36 iterations a step against 2.34. The solve's tolerance, checked on the
//! true residual, decides the answer.
//!
//! The solves are this module's own (faer's read f32 or f64): for each supernode, its
//! dense diagonal block's triangle and its dense rectangle below, column-major as faer
//! lays them out, with the rectangle's rows gathered from and scattered to the
//! supernode's row indices; the backward solve reads each diagonal block from a
//! transposed copy (see [`backward`] for why). Each output is a sum in one fixed order
//! (per element in both solves' triangles and the forward one's rectangle; the
//! backward one's dot products in 32 lanes, then a fixed tree), so the AVX2 code gives
//! the baseline's bits (see `super::kernels`). Measured on the cantilever against
//! faer's f32 solves (600 steps, three runs alternating the builds, perf samples of
//! the physics thread): the solves 22 % less time, the thread 11 % less.

use faer::sparse::linalg::cholesky::supernodal::SymbolicSupernodalCholesky;

use super::kernels::dispatch;

/// `x` in bfloat16, rounded to nearest, ties to even (finite `x`).
#[inline(always)]
pub fn to_bf16(x: f32) -> u16 {
    let bits = x.to_bits();
    ((bits + 0x7fff + ((bits >> 16) & 1)) >> 16) as u16
}

/// The f32 a bfloat16 stands for (exact).
#[inline(always)]
pub fn from_bf16(h: u16) -> f32 {
    f32::from_bits(u32::from(h) << 16)
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
    /// Per supernode: where its values (rows × columns, column-major) start; one more.
    values_at: Vec<usize>,
    /// Per supernode: where its diagonal block's transpose starts in the compact copy
    /// (after all the values); one more.
    transposed_at: Vec<usize>,
    /// The most rows any rectangle has, and the most columns any supernode has: the
    /// solves' scratch.
    widest: usize,
    most_columns: usize,
}

impl Supernodes {
    pub fn of(symbolic: &SymbolicSupernodalCholesky<u32>) -> Supernodes {
        let n = symbolic.n_supernodes();
        let mut begin = symbolic.supernode_begin().to_vec();
        begin.push(symbolic.supernode_end()[n - 1]);
        let values_at: Vec<usize> = symbolic.col_ptr_for_val().iter().map(|&v| v as usize).collect();
        let mut rows_at = Vec::with_capacity(n + 1);
        let mut transposed_at = Vec::with_capacity(n + 1);
        let mut rows = Vec::new();
        let (mut widest, mut most_columns) = (0, 0);
        let mut transposed = values_at[n];
        for s in 0..n {
            let columns = (begin[s + 1] - begin[s]) as usize;
            let below = (values_at[s + 1] - values_at[s]) / columns - columns;
            let at = symbolic.col_ptr_for_row_idx()[s] as usize;
            rows_at.push(rows.len() as u32);
            rows.extend_from_slice(&symbolic.row_idx()[at..at + below]);
            transposed_at.push(transposed);
            transposed += columns * columns;
            widest = widest.max(below);
            most_columns = most_columns.max(columns);
        }
        rows_at.push(rows.len() as u32);
        transposed_at.push(transposed);
        Supernodes { begin, rows_at, rows, values_at, transposed_at, widest, most_columns }
    }

    /// The compact copy of a factor's `values` (faer's supernodal layout) into `out`:
    /// the values in bfloat16, then each diagonal block transposed (row-major), which
    /// the backward solve reads a row at a time.
    pub fn compact(&self, values: &[f32], out: &mut Vec<u16>) {
        out.clear();
        out.extend(values.iter().map(|&v| to_bf16(v)));
        for s in 0..self.begin.len() - 1 {
            let (columns, height) = self.shape(s);
            for e in 0..columns * columns {
                let entry = out[self.values_at[s] + (e % columns) * height + e / columns];
                out.push(entry);
            }
        }
    }

    /// Scratch the solves need (f32 values).
    pub fn scratch_len(&self) -> usize {
        self.widest + self.most_columns
    }

    /// Solves `L Lᵀ x = b` in place (`x` holds `b`, in the factor's elimination order),
    /// with `l` the factor's [`Self::compact`] copy and `scratch` at least
    /// [`Self::scratch_len`] long.
    pub fn solve(&self, l: &[u16], x: &mut [f32], scratch: &mut [f32]) {
        for s in 0..self.begin.len() - 1 {
            let (first, columns, rows, values) = self.supernode(s, l);
            let t = &mut scratch[..rows.len()];
            forward_supernode(values, columns, &mut x[first..first + columns], t);
            for (&row, &sum) in rows.iter().zip(t.iter()) {
                x[row as usize] -= sum;
            }
        }
        for s in (0..self.begin.len() - 1).rev() {
            let (first, columns, rows, values) = self.supernode(s, l);
            let transposed = &l[self.transposed_at[s]..self.transposed_at[s + 1]];
            let (g, below) = scratch.split_at_mut(rows.len());
            for (g, &row) in g.iter_mut().zip(rows) {
                *g = x[row as usize];
            }
            backward_supernode(values, transposed, &mut x[first..first + columns], g, &mut below[..columns]);
        }
    }

    /// Supernode `s`'s columns and rows (its diagonal block's and its rectangle's).
    fn shape(&self, s: usize) -> (usize, usize) {
        let columns = (self.begin[s + 1] - self.begin[s]) as usize;
        (columns, (self.values_at[s + 1] - self.values_at[s]) / columns)
    }

    /// Supernode `s`: its first column, its columns, its rectangle's rows, its values.
    fn supernode<'a>(&'a self, s: usize, l: &'a [u16]) -> (usize, usize, &'a [u32], &'a [u16]) {
        let first = self.begin[s] as usize;
        let columns = self.shape(s).0;
        let rows = &self.rows[self.rows_at[s] as usize..self.rows_at[s + 1] as usize];
        (first, columns, rows, &l[self.values_at[s]..self.values_at[s + 1]])
    }
}

/// One supernode of `L y = b`: its diagonal block's triangle solved in place in
/// `x` (its columns' entries), and `t = (rectangle) · x` (what the rows below take
/// off). `values`: the supernode's (columns + t's rows) × columns, column-major.
#[inline(always)]
fn forward(values: &[u16], columns: usize, x: &mut [f32], t: &mut [f32]) {
    let height = columns + t.len();
    for j in 0..columns {
        let column = &values[j * height..(j + 1) * height];
        let xj = x[j] / from_bf16(column[j]);
        x[j] = xj;
        for (xi, &l) in x[j + 1..].iter_mut().zip(&column[j + 1..columns]) {
            *xi = from_bf16(l).mul_add(-xj, *xi);
        }
    }
    // The rectangle, four columns at a time (each t[k] summed in column order).
    t.fill(0.0);
    let mut j = 0;
    while j + 4 <= columns {
        let c: [&[u16]; 4] = std::array::from_fn(|q| &values[(j + q) * height + columns..(j + q + 1) * height]);
        let (x0, x1, x2, x3) = (x[j], x[j + 1], x[j + 2], x[j + 3]);
        for (k, tk) in t.iter_mut().enumerate() {
            let sum = from_bf16(c[0][k]).mul_add(x0, *tk);
            let sum = from_bf16(c[1][k]).mul_add(x1, sum);
            let sum = from_bf16(c[2][k]).mul_add(x2, sum);
            *tk = from_bf16(c[3][k]).mul_add(x3, sum);
        }
        j += 4;
    }
    for j in j..columns {
        let column = &values[j * height + columns..(j + 1) * height];
        for (tk, &l) in t.iter_mut().zip(column) {
            *tk = from_bf16(l).mul_add(x[j], *tk);
        }
    }
}

/// One supernode of `Lᵀ x = y`: `x` holds its columns' entries of y, solved in place;
/// `g` the rows below, already solved; `transposed` its diagonal block transposed
/// (row-major: its row j is row j of L's block); `below` (as long as `x`) scratch.
///
/// The rows below go first: each column's dot product with `g` (none waits for
/// another). Then the triangle last column first, each solved entry taken off the
/// entries before it (a row of L, contiguous in `transposed`): one division and one
/// multiply-add between an entry and the next, where a dot product per column (the
/// first version) put a whole reduction on that path and took 1.6 times the forward
/// solve's time (now about the same).
///
/// `WIDE`: with AVX2 and FMA (only from a function compiled for them, on a CPU that
/// has them).
#[inline(always)]
fn backward<const WIDE: bool>(values: &[u16], transposed: &[u16], x: &mut [f32], g: &[f32], below: &mut [f32]) {
    let columns = x.len();
    let height = columns + g.len();
    for (j, below) in below.iter_mut().enumerate() {
        *below = dot::<WIDE>(&values[j * height + columns..(j + 1) * height], g);
    }
    for j in (0..columns).rev() {
        let row = &transposed[j * columns..j * columns + j + 1];
        let xj = (x[j] - below[j]) / from_bf16(row[j]);
        x[j] = xj;
        for (xi, &l) in x[..j].iter_mut().zip(&row[..j]) {
            *xi = from_bf16(l).mul_add(-xj, *xi);
        }
    }
}

dispatch! {
    /// [`forward`], vectorized where the CPU allows.
    pub fn forward_supernode(values: &[u16], columns: usize, x: &mut [f32], t: &mut [f32]) {
        forward(values, columns, x, t)
    }
}

/// [`backward`], vectorized where the CPU allows. (Not by `dispatch!`: its dot
/// products are written in intrinsics for AVX2, since the compiler's own vectorization
/// of them came and went with the code around them, 2.5 times slower when it went.)
pub fn backward_supernode(values: &[u16], transposed: &[u16], x: &mut [f32], g: &[f32], below: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2,fma")]
    unsafe fn wide(values: &[u16], transposed: &[u16], x: &mut [f32], g: &[f32], below: &mut [f32]) {
        backward::<true>(values, transposed, x, g, below)
    }
    #[cfg(target_arch = "x86_64")]
    if super::kernels::has_avx2() {
        // SAFETY: the CPU was checked to have AVX2 and FMA.
        return unsafe { wide(values, transposed, x, g, below) };
    }
    backward::<false>(values, transposed, x, g, below)
}

/// `Σ lₖ gₖ` in 32 lanes (four vectors, so that four multiply-adds are in flight
/// rather than one waiting for the last), the remainder's whole eights in the first
/// eight lanes, the rest one by one; then the lanes added in a fixed tree. `WIDE`: the
/// lanes in AVX2 and FMA intrinsics (see [`backward`]), the same operations.
#[inline(always)]
fn dot<const WIDE: bool>(l: &[u16], g: &[f32]) -> f32 {
    let n = l.len().min(g.len());
    let (by32, by8) = (n / 32 * 32, n / 8 * 8);
    let lanes = if WIDE { lanes_wide(l, g, by32, by8) } else { lanes_portable(l, g, by32, by8) };
    let mut tail = 0f32;
    for (&lk, &gk) in l[by8..n].iter().zip(&g[by8..n]) {
        tail = from_bf16(lk).mul_add(gk, tail);
    }
    let v: [f32; 8] = std::array::from_fn(|q| (lanes[q] + lanes[8 + q]) + (lanes[16 + q] + lanes[24 + q]));
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7])) + tail
}

/// The lanes of [`dot`] over `l` and `g`'s first `by8` entries (`by32` of them by 32).
#[inline(always)]
fn lanes_portable(l: &[u16], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    let mut lanes = [0f32; 32];
    for (lc, gc) in l[..by32].chunks_exact(32).zip(g[..by32].chunks_exact(32)) {
        for q in 0..32 {
            lanes[q] = from_bf16(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    for (lc, gc) in l[by32..by8].chunks_exact(8).zip(g[by32..by8].chunks_exact(8)) {
        for q in 0..8 {
            lanes[q] = from_bf16(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    lanes
}

#[inline(always)]
fn lanes_wide(l: &[u16], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    #[cfg(target_arch = "x86_64")]
    // SAFETY: only `backward::<true>` calls this, and only `backward_supernode`'s
    // `wide` runs that, where the CPU was checked to have AVX2 and FMA.
    return unsafe { lanes_avx2(l, g, by32, by8) };
    #[cfg(not(target_arch = "x86_64"))]
    lanes_portable(l, g, by32, by8)
}

/// [`lanes_portable`] in AVX2 and FMA intrinsics: lane by lane the same operations (a
/// bfloat16 widened by a shift, one fused multiply-add), so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
#[inline]
unsafe fn lanes_avx2(l: &[u16], g: &[f32], by32: usize, by8: usize) -> [f32; 32] {
    use std::arch::x86_64::*;
    assert!(by32 <= by8 && by8 <= l.len() && by8 <= g.len());
    let mut sums = [_mm256_setzero_ps(); 4];
    // SAFETY (every load): k + 8 ≤ by8, within l and g (asserted above).
    for k in (0..by32).step_by(32) {
        for (q, sum) in sums.iter_mut().enumerate() {
            let at = k + 8 * q;
            let half = unsafe { _mm_loadu_si128(l.as_ptr().add(at).cast::<__m128i>()) };
            let widened = _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(half)));
            *sum = _mm256_fmadd_ps(widened, unsafe { _mm256_loadu_ps(g.as_ptr().add(at)) }, *sum);
        }
    }
    for k in (by32..by8).step_by(8) {
        let half = unsafe { _mm_loadu_si128(l.as_ptr().add(k).cast::<__m128i>()) };
        let widened = _mm256_castsi256_ps(_mm256_slli_epi32::<16>(_mm256_cvtepu16_epi32(half)));
        sums[0] = _mm256_fmadd_ps(widened, unsafe { _mm256_loadu_ps(g.as_ptr().add(k)) }, sums[0]);
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
    fn bfloat16_rounds_to_nearest_even_and_back_exactly() {
        assert_eq!(from_bf16(to_bf16(1.0)), 1.0);
        assert_eq!(from_bf16(to_bf16(-2.5)), -2.5);
        // 1 + 2⁻⁸ lies halfway between 1 and 1 + 2⁻⁷: to the even one, 1.
        assert_eq!(from_bf16(to_bf16(1.0 + 2f32.powi(-8))), 1.0);
        // 1 + 3·2⁻⁸ lies halfway between 1 + 2⁻⁷ and 1 + 2⁻⁶: to the even one.
        assert_eq!(from_bf16(to_bf16(1.0 + 3.0 * 2f32.powi(-8))), 1.0 + 2f32.powi(-6));
        for x in [0.1f32, 3.3e-7, -1234.5, 7.0e12] {
            let back = from_bf16(to_bf16(x));
            assert!(((back - x) / x).abs() <= 2f32.powi(-8), "{x} -> {back}");
        }
    }

    /// A supernode of 11 columns over 37 rows below: the solves compiled for the
    /// baseline and for AVX2 and FMA give the same bits, and solve its block.
    #[test]
    fn a_supernode_solves_to_the_same_bits_with_and_without_avx2() {
        let (columns, below) = (11, 37);
        let height = columns + below;
        let entry = |i: usize, j: usize| if i == j { 2.0 + j as f32 * 0.1 } else if i < j { 0.0 } else { ((i * 7 + j * 3) % 11) as f32 * 0.05 - 0.2 };
        let values: Vec<u16> = (0..columns * height).map(|e| to_bf16(entry(e % height, e / height))).collect();
        let transposed: Vec<u16> = (0..columns * columns).map(|e| values[(e % columns) * height + e / columns]).collect();
        let x0: Vec<f32> = (0..columns).map(|j| (j as f32 * 0.7).sin()).collect();
        let g: Vec<f32> = (0..below).map(|k| (k as f32 * 0.3).cos()).collect();
        let run = |forward_fn: &dyn Fn(&mut [f32], &mut [f32]), backward_fn: &dyn Fn(&mut [f32], &[f32], &mut [f32])| {
            let (mut y, mut t) = (x0.clone(), vec![0f32; below]);
            forward_fn(&mut y, &mut t);
            let mut x = y.clone();
            backward_fn(&mut x, &g, &mut vec![0f32; columns]);
            (y, t, x)
        };
        let baseline = run(&|x, t| forward(&values, columns, x, t), &|x, g, b| backward::<false>(&values, &transposed, x, g, b));
        // What each solve solves: L₁₁ y = x0 and t = L₂₁ y; L₁₁ᵀ x + L₂₁ᵀ g = y.
        let l = |i: usize, j: usize| f64::from(from_bf16(values[j * height + i]));
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
            unsafe fn forward_wide(values: &[u16], columns: usize, x: &mut [f32], t: &mut [f32]) {
                forward(values, columns, x, t)
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn backward_wide(values: &[u16], transposed: &[u16], x: &mut [f32], g: &[f32], below: &mut [f32]) {
                backward::<true>(values, transposed, x, g, below)
            }
            // SAFETY: the CPU was checked to have AVX2 and FMA.
            let wide = run(&|x, t| unsafe { forward_wide(&values, columns, x, t) }, &|x, g, b| unsafe { backward_wide(&values, &transposed, x, g, b) });
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
            let l: Vec<u16> = (0..n).map(|k| to_bf16(k as f32 * 0.5 - 3.0)).collect();
            let g: Vec<f32> = (0..n).map(|k| 1.0 / (k as f32 + 1.0)).collect();
            let exact: f64 = l.iter().zip(&g).map(|(&l, &g)| f64::from(from_bf16(l)) * f64::from(g)).sum();
            let sum = dot::<false>(&l, &g);
            assert!((f64::from(sum) - exact).abs() < 1e-5 * exact.abs().max(1.0), "{n}");
            #[cfg(target_arch = "x86_64")]
            if crate::solver::kernels::has_avx2() {
                #[target_feature(enable = "avx2,fma")]
                unsafe fn wide(l: &[u16], g: &[f32]) -> f32 {
                    dot::<true>(l, g)
                }
                // SAFETY: the CPU was checked to have AVX2 and FMA.
                assert_eq!(unsafe { wide(&l, &g) }.to_bits(), sum.to_bits(), "{n}");
            }
        }
    }
}
