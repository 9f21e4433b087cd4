//! A supernodal Cholesky factor kept in bfloat16, and its triangular solves.
//!
//! As a preconditioner the factor is applied once per conjugate-gradient iteration,
//! and each application streams the whole factor from memory twice (`L y = b`, then
//! `Lᵀ x = y`): on the level-0 cantilever of docs/fem-comparison.md, 2.99 M entries,
//! 12 MB in single precision, about 1.9 ms an application on this project's Xeon, a
//! third of the step, bound by memory bandwidth, not arithmetic. Kept in bfloat16 (the
//! upper half of an f32: its range, 8 significant bits) it is half the bytes.
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
//! supernode's row indices. Each output is a sum in one fixed order (per element in
//! the forward solve; in the backward one's dot products, 32 lanes, then a fixed
//! tree), so the vectorized clone gives the baseline's bits (see `super::kernels`).

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
    /// The most rows any rectangle has: the solves' scratch.
    widest: usize,
}

impl Supernodes {
    pub fn of(symbolic: &SymbolicSupernodalCholesky<u32>) -> Supernodes {
        let n = symbolic.n_supernodes();
        let mut begin = symbolic.supernode_begin().to_vec();
        begin.push(symbolic.supernode_end()[n - 1]);
        let values_at: Vec<usize> = symbolic.col_ptr_for_val().iter().map(|&v| v as usize).collect();
        let mut rows_at = Vec::with_capacity(n + 1);
        let mut rows = Vec::new();
        let mut widest = 0;
        for s in 0..n {
            let columns = (begin[s + 1] - begin[s]) as usize;
            let below = (values_at[s + 1] - values_at[s]) / columns - columns;
            let at = symbolic.col_ptr_for_row_idx()[s] as usize;
            rows_at.push(rows.len() as u32);
            rows.extend_from_slice(&symbolic.row_idx()[at..at + below]);
            widest = widest.max(below);
        }
        rows_at.push(rows.len() as u32);
        Supernodes { begin, rows_at, rows, values_at, widest }
    }

    /// Scratch the solves need (f32 values).
    pub fn scratch_len(&self) -> usize {
        self.widest
    }

    /// Solves `L Lᵀ x = b` in place (`x` holds `b`, in the factor's elimination order),
    /// with `l` the factor's values in bfloat16 and `scratch` at least
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
            let g = &mut scratch[..rows.len()];
            for (g, &row) in g.iter_mut().zip(rows) {
                *g = x[row as usize];
            }
            backward_supernode(values, columns, &mut x[first..first + columns], g);
        }
    }

    /// Supernode `s`: its first column, its columns, its rectangle's rows, its values.
    fn supernode<'a>(&'a self, s: usize, l: &'a [u16]) -> (usize, usize, &'a [u32], &'a [u16]) {
        let first = self.begin[s] as usize;
        let columns = self.begin[s + 1] as usize - first;
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

/// One supernode of `Lᵀ x = y`, last column first: `x` holds its columns' entries
/// of y, solved in place; `g` the rows below, already solved.
#[inline(always)]
fn backward(values: &[u16], columns: usize, x: &mut [f32], g: &[f32]) {
    let height = columns + g.len();
    for j in (0..columns).rev() {
        let column = &values[j * height..(j + 1) * height];
        let below = dot(&column[columns..], g);
        let inside = dot(&column[j + 1..columns], &x[j + 1..columns]);
        x[j] = (x[j] - below - inside) / from_bf16(column[j]);
    }
}

dispatch! {
    /// [`forward`], vectorized where the CPU allows.
    pub fn forward_supernode(values: &[u16], columns: usize, x: &mut [f32], t: &mut [f32]) {
        forward(values, columns, x, t)
    }
}

dispatch! {
    /// [`backward`], vectorized where the CPU allows.
    pub fn backward_supernode(values: &[u16], columns: usize, x: &mut [f32], g: &[f32]) {
        backward(values, columns, x, g)
    }
}

/// `Σ lₖ gₖ` in 32 lanes (four vectors, so that four multiply-adds are in flight
/// rather than one waiting for the last), the remainder's whole eights in the first
/// eight lanes, the rest one by one; then the lanes added in a fixed tree.
#[inline(always)]
fn dot(l: &[u16], g: &[f32]) -> f32 {
    let mut lanes = [0f32; 32];
    let by32 = l.len() / 32 * 32;
    for (lc, gc) in l[..by32].chunks_exact(32).zip(g[..by32].chunks_exact(32)) {
        for q in 0..32 {
            lanes[q] = from_bf16(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    let by8 = l.len() / 8 * 8;
    for (lc, gc) in l[by32..by8].chunks_exact(8).zip(g[by32..by8].chunks_exact(8)) {
        for q in 0..8 {
            lanes[q] = from_bf16(lc[q]).mul_add(gc[q], lanes[q]);
        }
    }
    let mut tail = 0f32;
    for (&lk, &gk) in l[by8..].iter().zip(&g[by8..]) {
        tail = from_bf16(lk).mul_add(gk, tail);
    }
    let v: [f32; 8] = std::array::from_fn(|q| (lanes[q] + lanes[8 + q]) + (lanes[16 + q] + lanes[24 + q]));
    ((v[0] + v[1]) + (v[2] + v[3])) + ((v[4] + v[5]) + (v[6] + v[7])) + tail
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
    /// baseline and for AVX2 and FMA give the same bits.
    #[test]
    fn a_supernode_solves_to_the_same_bits_with_and_without_avx2() {
        let (columns, below) = (11, 37);
        let height = columns + below;
        let values: Vec<u16> = (0..columns * height)
            .map(|e| {
                let (i, j) = (e % height, e / height);
                to_bf16(if i == j { 2.0 + j as f32 * 0.1 } else { ((i * 7 + j * 3) % 11) as f32 * 0.05 - 0.2 })
            })
            .collect();
        let x0: Vec<f32> = (0..columns).map(|j| (j as f32 * 0.7).sin()).collect();
        let g: Vec<f32> = (0..below).map(|k| (k as f32 * 0.3).cos()).collect();
        let run = |forward_fn: &dyn Fn(&mut [f32], &mut [f32]), backward_fn: &dyn Fn(&mut [f32], &[f32])| {
            let (mut x, mut t) = (x0.clone(), vec![0f32; below]);
            forward_fn(&mut x, &mut t);
            backward_fn(&mut x, &g);
            (x, t)
        };
        let baseline = run(&|x, t| forward(&values, columns, x, t), &|x, g| backward(&values, columns, x, g));
        assert!(baseline.0.iter().chain(&baseline.1).all(|v| v.is_finite()));
        #[cfg(target_arch = "x86_64")]
        if crate::solver::kernels::has_avx2() {
            #[target_feature(enable = "avx2,fma")]
            unsafe fn forward_wide(values: &[u16], columns: usize, x: &mut [f32], t: &mut [f32]) {
                forward(values, columns, x, t)
            }
            #[target_feature(enable = "avx2,fma")]
            unsafe fn backward_wide(values: &[u16], columns: usize, x: &mut [f32], g: &[f32]) {
                backward(values, columns, x, g)
            }
            // SAFETY: the CPU was checked to have AVX2 and FMA.
            let wide = run(&|x, t| unsafe { forward_wide(&values, columns, x, t) }, &|x, g| unsafe { backward_wide(&values, columns, x, g) });
            assert_eq!(baseline.0.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), wide.0.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
            assert_eq!(baseline.1.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), wide.1.iter().map(|v| v.to_bits()).collect::<Vec<_>>());
        }
    }

    #[test]
    fn a_dot_product_sums_its_lanes_in_a_fixed_order() {
        // Lengths with and without whole 32s, whole 8s and a tail.
        for n in [0, 5, 8, 19, 32, 45, 77] {
            let l: Vec<u16> = (0..n).map(|k| to_bf16(k as f32 * 0.5 - 3.0)).collect();
            let g: Vec<f32> = (0..n).map(|k| 1.0 / (k as f32 + 1.0)).collect();
            let exact: f64 = l.iter().zip(&g).map(|(&l, &g)| f64::from(from_bf16(l)) * f64::from(g)).sum();
            assert!((f64::from(dot(&l, &g)) - exact).abs() < 1e-5 * exact.abs().max(1.0), "{n}");
        }
    }
}
