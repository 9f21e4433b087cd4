//! The per-step kernels, written for the CPU's vector units.
//!
//! Every kernel here is a sequence of independent lane operations — each output value
//! is accumulated in one fixed order, never reassociated across lanes — so the
//! compiler's vectorized code gives the same bits at any vector width. Each kernel is
//! compiled twice, for the baseline x86-64 (SSE2, 4 f32 lanes) and with AVX2 and FMA
//! (8 lanes, fused multiply-adds), and the wider one is chosen at run time where the CPU
//! has it. Multiply-adds are IEEE fused ones (`mul_add`: one rounding), which the FMA
//! clone does in hardware and the baseline in software, to the same bits: a recording
//! replays to the same state hash on any x86-64 machine, only slower without FMA.

use super::block_sparse::{NO_BLOCK, Pattern, Scalar};
use crate::math::{Matrix3, Vec3};

/// 24 × 24 in single precision: an element's stiffness.
pub type Block24 = [f32; 576];

/// Whether the CPU runs the AVX2 and FMA clones (checked once).
#[inline]
pub fn has_avx2() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::sync::OnceLock;
        static AVX2: OnceLock<bool> = OnceLock::new();
        *AVX2.get_or_init(|| std::is_x86_feature_detected!("avx2") && std::is_x86_feature_detected!("fma"))
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        false
    }
}

/// Declares `$name` running `$body` compiled for the baseline and, on x86-64, for AVX2,
/// dispatching at run time.
macro_rules! dispatch {
    ($(#[$meta:meta])* pub fn $name:ident($($arg:ident: $ty:ty),*) $(-> $ret:ty)? $body:block) => {
        $(#[$meta])*
        pub fn $name($($arg: $ty),*) $(-> $ret)? {
            #[inline(always)]
            fn body($($arg: $ty),*) $(-> $ret)? $body
            #[cfg(target_arch = "x86_64")]
            #[target_feature(enable = "avx2,fma")]
            unsafe fn wide($($arg: $ty),*) $(-> $ret)? {
                body($($arg),*)
            }
            #[cfg(target_arch = "x86_64")]
            if $crate::solver::kernels::has_avx2() {
                // SAFETY: the CPU was checked to have AVX2.
                return unsafe { wide($($arg),*) };
            }
            body($($arg),*)
        }
    };
}
/// The skin's implicit solve uses it too (`msm::implicit`).
pub(crate) use dispatch;

/// Eight f32 lanes: one AVX register (two SSE ones). Its operations are lane by lane.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
#[repr(C, align(32))]
pub struct F8(pub [f32; 8]);

impl F8 {
    /// `self + a · x`, lane by lane, with one rounding (a fused multiply-add: IEEE's,
    /// the same bits whether the CPU does it or the library does).
    #[inline(always)]
    fn plus(self, a: f32, x: F8) -> F8 {
        let mut out = self.0;
        for l in 0..8 {
            out[l] = x.0[l].mul_add(a, out[l]);
        }
        F8(out)
    }
}

/// An element matrix in planar layout: row r, plane l, lane b holds entry
/// (r, 3b + l) of the 24 × 24 matrix.
pub type Planar24 = [[F8; 3]; 24];

/// A 24 × 24 matrix (column-major, as nalgebra stores it) in planar layout.
pub fn to_planar(column_major: &[f32]) -> Planar24 {
    let mut out = [[F8::default(); 3]; 24];
    for c in 0..24 {
        for r in 0..24 {
            out[r][c % 3].0[c / 3] = column_major[24 * c + r];
        }
    }
    out
}

dispatch! {
    /// The element stiffness in the world frame, `K_R = (I₈ ⊗ R) K (I₈ ⊗ Rᵀ)`, both in
    /// planar layout, and from it while it is in the cache `f = K_R d` (d and f corner-
    /// major). Left-multiplying by I ⊗ R combines whole rows; right-multiplying by I ⊗ Rᵀ
    /// combines a row's planes; `f` takes K_R's rows as its columns (K_R is symmetric):
    /// all of it 8-lane operations, each output accumulated in one fixed order.
    pub fn rotate_and_multiply(k: &Planar24, r: &[[f32; 3]; 3], d: &[f32; 24], out: &mut Planar24, f: &mut [f32; 24]) {
        for a in 0..8 {
            // V = (I ⊗ R) K for this corner's three rows: row p = Σ_k R[p][k] · row k.
            let mut v = [[F8::default(); 3]; 3];
            for (p, vp) in v.iter_mut().enumerate() {
                for (kk, source) in k[3 * a..3 * a + 3].iter().enumerate() {
                    for l in 0..3 {
                        vp[l] = vp[l].plus(r[p][kk], source[l]);
                    }
                }
            }
            // K_R = V (I ⊗ Rᵀ): plane q of each row = Σ_l R[q][l] · plane l.
            for (p, vp) in v.iter().enumerate() {
                for q in 0..3 {
                    let mut plane = F8::default();
                    for l in 0..3 {
                        plane = plane.plus(r[q][l], vp[l]);
                    }
                    out[3 * a + p][q] = plane;
                }
            }
        }
        // f = K_R d over the planes, then back to corner-major.
        let mut fp = [F8::default(); 3];
        for (c, row) in out.iter().enumerate() {
            for l in 0..3 {
                fp[l] = fp[l].plus(d[c], row[l]);
            }
        }
        for b in 0..8 {
            for l in 0..3 {
                f[3 * b + l] = fp[l].0[b];
            }
        }
    }
}

dispatch! {
    /// `f = (I₈ ⊗ R) K (I₈ ⊗ Rᵀ) d` without forming the rotated matrix (d and f corner-
    /// major, K in planar layout): for an element whose blocks in the system are kept
    /// from an earlier step (see `grid::solver`), a fifth of [`rotate_and_multiply`]'s
    /// work. K is symmetric, so `K u` sums K's rows as its columns, eight lanes at a time.
    pub fn rotated_multiply(k: &Planar24, r: &[[f32; 3]; 3], d: &[f32; 24], f: &mut [f32; 24]) {
        // u = (I ⊗ Rᵀ) d: corner c's u_q = Σ_p R[p][q] d_p.
        let mut u = [0f32; 24];
        for c in 0..8 {
            for q in 0..3 {
                let mut sum = 0f32;
                for p in 0..3 {
                    sum = d[3 * c + p].mul_add(r[p][q], sum);
                }
                u[3 * c + q] = sum;
            }
        }
        let mut fp = [F8::default(); 3];
        for (row, &weight) in k.iter().zip(&u) {
            for l in 0..3 {
                fp[l] = fp[l].plus(weight, row[l]);
            }
        }
        // f = (I ⊗ R) K u: corner b's f_p = Σ_l R[p][l] (K u)_{3b + l}.
        for b in 0..8 {
            for p in 0..3 {
                let mut sum = 0f32;
                for l in 0..3 {
                    sum = fp[l].0[b].mul_add(r[p][l], sum);
                }
                f[3 * b + p] = sum;
            }
        }
    }
}

/// `values[blocks[8 i + j]] += scale · (block (i, j) of m)` for the 64 corner pairs of
/// an element matrix in planar layout (pairs with no block, `NO_BLOCK`, skipped); the
/// pairs whose bit `8 i + j` is set in `first` are stored instead of added (the
/// element is the first to write that block: see `Scatter::first`, which spares
/// zeroing the whole matrix before assembling it). Plane c of corner i's three rows
/// holds column c of its eight blocks in its lanes; each block's column is gathered
/// into four lanes (the fourth zero, as every block's padding) and added as one
/// vector. With AVX2 the gathering is a transposition in registers
/// ([`scatter_element_avx2`]), the same operations on the same values: the same bits.
pub fn scatter_element(values: &mut [[f32; 12]], blocks: &[u32; 64], m: &Planar24, scale: f32, first: u64) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        // SAFETY: the CPU was checked to have AVX2.
        return unsafe { scatter_element_avx2(values, blocks, m, scale, first) };
    }
    scatter_element_portable(values, blocks, m, scale, first)
}

/// [`scatter_element`] column by column, lane by lane.
fn scatter_element_portable(values: &mut [[f32; 12]], blocks: &[u32; 64], m: &Planar24, scale: f32, first: u64) {
    for i in 0..8 {
        let rows = [&m[3 * i], &m[3 * i + 1], &m[3 * i + 2]];
        for j in 0..8 {
            if blocks[8 * i + j] == NO_BLOCK {
                continue;
            }
            let v = &mut values[blocks[8 * i + j] as usize];
            // Zero plus the element's part: the bits of zeroing and then adding,
            // whatever the block held (a NaN of a contained blow-up included, which
            // multiplying it by zero would keep).
            let before = if (first >> (8 * i + j)) & 1 == 1 { [0.0; 12] } else { *v };
            for c in 0..3 {
                let column = [rows[0][c].0[j], rows[1][c].0[j], rows[2][c].0[j], 0.0];
                for r in 0..4 {
                    v[4 * c + r] = before[4 * c + r] + scale * column[r];
                }
            }
        }
    }
}

/// [`scatter_element_portable`] with the columns gathered by transposing corner i's
/// rows in registers: for each plane, its three rows and a zero row (4 × 8) become
/// eight columns of four — the blocks (i, j) and (i, j + 4) in the low and high halves
/// of one register — by two rounds of interleaving. Gathering each entry on its own was
/// 10 % of a level-0 step (perf: nine inserts per block column).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn scatter_element_avx2(values: &mut [[f32; 12]], blocks: &[u32; 64], m: &Planar24, scale: f32, first: u64) {
    use std::arch::x86_64::*;
    let (zero, scale) = (_mm256_setzero_ps(), _mm_set1_ps(scale));
    for i in 0..8 {
        // columns[c][j % 4]: column c of block (i, j), for j < 4 in the low half.
        let mut columns = [[zero; 4]; 3];
        for (c, column) in columns.iter_mut().enumerate() {
            // SAFETY: each plane is eight f32 (an F8).
            let [a, b, d] = [0, 1, 2].map(|p| unsafe { _mm256_loadu_ps(m[3 * i + p][c].0.as_ptr()) });
            let (ab_low, ab_high) = (_mm256_unpacklo_ps(a, b), _mm256_unpackhi_ps(a, b));
            let (d_low, d_high) = (_mm256_unpacklo_ps(d, zero), _mm256_unpackhi_ps(d, zero));
            *column = [
                _mm256_shuffle_ps::<0x44>(ab_low, d_low),
                _mm256_shuffle_ps::<0xEE>(ab_low, d_low),
                _mm256_shuffle_ps::<0x44>(ab_high, d_high),
                _mm256_shuffle_ps::<0xEE>(ab_high, d_high),
            ];
        }
        for j in 0..8 {
            if blocks[8 * i + j] == NO_BLOCK {
                continue;
            }
            let v = &mut values[blocks[8 * i + j] as usize];
            let store = (first >> (8 * i + j)) & 1 == 1;
            for (c, column) in columns.iter().enumerate() {
                let column = if j < 4 { _mm256_castps256_ps128(column[j]) } else { _mm256_extractf128_ps::<1>(column[j - 4]) };
                // SAFETY: four f32 at 4c..4c + 4 of the block's twelve.
                let before = if store { _mm_setzero_ps() } else { unsafe { _mm_loadu_ps(v.as_ptr().add(4 * c)) } };
                unsafe { _mm_storeu_ps(v.as_mut_ptr().add(4 * c), _mm_add_ps(before, _mm_mul_ps(scale, column))) };
            }
        }
    }
}

// A slice of 3-vectors is a slice of 3n f64 (nalgebra's `Vector3<f64>` is `[f64; 3]`,
// `repr(C)`): the solver's vector updates run over it flat, four lanes at a time.
const _: () = assert!(std::mem::size_of::<Vec3>() == 24 && std::mem::align_of::<Vec3>() == 8);

/// The 3n coordinates of `v`.
pub fn flat(v: &[Vec3]) -> &[f64] {
    // SAFETY: Vec3 is three contiguous f64 (checked above), so n of them are 3n f64.
    unsafe { std::slice::from_raw_parts(v.as_ptr().cast::<f64>(), 3 * v.len()) }
}

/// The 3n coordinates of `v`, mutable.
pub fn flat_mut(v: &mut [Vec3]) -> &mut [f64] {
    // SAFETY: as in `flat`; the borrow is unique.
    unsafe { std::slice::from_raw_parts_mut(v.as_mut_ptr().cast::<f64>(), 3 * v.len()) }
}

/// Four partial sums (entry k into lane k mod 4) added in one fixed order.
#[inline(always)]
fn lanes_total(s: [f64; 4]) -> f64 {
    (s[0] + s[1]) + (s[2] + s[3])
}

dispatch! {
    /// The conjugate-gradient update `x += α p`, `r −= α q` over every coordinate, with
    /// the new residual's weighted measures: `(Σ r² w, max |r| w)` (`w` = 1/diagonal).
    /// The sum runs in four lanes added at the end, so the loop vectorizes and its bits
    /// do not depend on the vector width.
    pub fn cg_update(x: &mut [f64], p: &[f64], r: &mut [f64], q: &[f64], w: &[f64], alpha: f64) -> (f64, f64) {
        let n = x.len().min(p.len()).min(r.len()).min(q.len()).min(w.len());
        let (mut sum, mut largest) = ([0f64; 4], [0f64; 4]);
        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn lane(x: &mut f64, p: f64, r: &mut f64, q: f64, w: f64, alpha: f64, sum: &mut f64, largest: &mut f64) {
            *x += p * alpha;
            *r -= q * alpha;
            *sum += *r * *r * w;
            let m = r.abs() * w;
            *largest = if m > *largest { m } else { *largest };
        }
        let whole = n - n % 4;
        let (x, p, r, q, w) = (&mut x[..n], &p[..n], &mut r[..n], &q[..n], &w[..n]);
        let (xs, ps, rs, qs, ws) = (x[..whole].chunks_exact_mut(4), p[..whole].chunks_exact(4), r[..whole].chunks_exact_mut(4), q[..whole].chunks_exact(4), w[..whole].chunks_exact(4));
        for ((((xc, pc), rc), qc), wc) in xs.zip(ps).zip(rs).zip(qs).zip(ws) {
            for l in 0..4 {
                lane(&mut xc[l], pc[l], &mut rc[l], qc[l], wc[l], alpha, &mut sum[l], &mut largest[l]);
            }
        }
        for k in whole..n {
            lane(&mut x[k], p[k], &mut r[k], q[k], w[k], alpha, &mut sum[k % 4], &mut largest[k % 4]);
        }
        (lanes_total(sum), largest[0].max(largest[1]).max(largest[2].max(largest[3])))
    }
}

dispatch! {
    /// The conjugate-gradient update `x += α p`, `r −= α q` over every coordinate, and
    /// the Jacobi-preconditioned residual `z = r w` (`w` = 1/diagonal, zero on fixed
    /// axes) with `(Σ r z, Σ r²)`, each summed in four lanes (see [`cg_update`]).
    pub fn cg_update_jacobi(x: &mut [f64], p: &[f64], r: &mut [f64], q: &[f64], w: &[f64], z: &mut [f64], alpha: f64) -> (f64, f64) {
        let n = x.len().min(p.len()).min(r.len()).min(q.len()).min(w.len()).min(z.len());
        let (mut rz, mut rr) = ([0f64; 4], [0f64; 4]);
        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn lane(x: &mut f64, p: f64, r: &mut f64, q: f64, w: f64, z: &mut f64, alpha: f64, rz: &mut f64, rr: &mut f64) {
            *x += p * alpha;
            *r -= q * alpha;
            *z = *r * w;
            *rz += *r * *z;
            *rr += *r * *r;
        }
        let whole = n - n % 4;
        let (x, p, r, q, w, z) = (&mut x[..n], &p[..n], &mut r[..n], &q[..n], &w[..n], &mut z[..n]);
        let chunks = x[..whole].chunks_exact_mut(4).zip(p[..whole].chunks_exact(4)).zip(r[..whole].chunks_exact_mut(4)).zip(q[..whole].chunks_exact(4)).zip(w[..whole].chunks_exact(4)).zip(z[..whole].chunks_exact_mut(4));
        for (((((xc, pc), rc), qc), wc), zc) in chunks {
            for l in 0..4 {
                lane(&mut xc[l], pc[l], &mut rc[l], qc[l], wc[l], &mut zc[l], alpha, &mut rz[l], &mut rr[l]);
            }
        }
        for k in whole..n {
            lane(&mut x[k], p[k], &mut r[k], q[k], w[k], &mut z[k], alpha, &mut rz[k % 4], &mut rr[k % 4]);
        }
        (lanes_total(rz), lanes_total(rr))
    }
}

dispatch! {
    /// `Σ a b` over every coordinate, in four lanes (see [`cg_update`]).
    pub fn dot(a: &[f64], b: &[f64]) -> f64 {
        let n = a.len().min(b.len());
        let mut sum = [0f64; 4];
        let whole = n - n % 4;
        for (ac, bc) in a[..whole].chunks_exact(4).zip(b[..whole].chunks_exact(4)) {
            for lane in 0..4 {
                sum[lane] += ac[lane] * bc[lane];
            }
        }
        for k in whole..n {
            sum[k % 4] += a[k] * b[k];
        }
        lanes_total(sum)
    }
}

dispatch! {
    /// The new search direction `p = z + β p`.
    pub fn cg_direction(p: &mut [f64], z: &[f64], beta: f64) {
        for (p, z) in p.iter_mut().zip(z) {
            *p = z + *p * beta;
        }
    }
}

/// `Σ_k A_k x_{cols[k]}` over blocks `range` of a block row, skipping column `skip`
/// (`usize::MAX`: none), accumulated in f64: lane `r` of the result is row `r` (lane 3
/// is zero). Six independent sums — one per block column, for the blocks at even and
/// at odd positions in the range — are added at the end in one fixed order
/// (`((e₀ + o₀) + (e₁ + o₁)) + (e₂ + o₂)`): a single running sum made every block wait
/// for the previous multiply-add's latency (three times per block); six keep the vector
/// units busy. `FUSED`: with fused multiply-adds (the f32 system's path, matching its
/// AVX2 clone bit for bit); else a multiply and an add (f64 coarse levels, where a
/// software fused multiply-add would only be slow).
#[inline(always)]
fn row_generic<T: Scalar, const FUSED: bool>(values: &[[T; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4] {
    let mut s = [[[0f64; 4]; 3]; 2];
    let start = range.start;
    for k in range {
        let j = cols[k] as usize;
        if j == skip {
            continue;
        }
        let a = &values[k];
        let xj = x[j];
        let chains = &mut s[(k - start) & 1];
        for (c, xc) in [xj.x, xj.y, xj.z].into_iter().enumerate() {
            for lane in 0..4 {
                let sum = &mut chains[c][lane];
                *sum = if FUSED { a[4 * c + lane].to_f64().mul_add(xc, *sum) } else { *sum + a[4 * c + lane].to_f64() * xc };
            }
        }
    }
    std::array::from_fn(|lane| ((s[0][0][lane] + s[1][0][lane]) + (s[0][1][lane] + s[1][1][lane])) + (s[0][2][lane] + s[1][2][lane]))
}

/// [`row_generic`] for single-precision blocks with AVX2 and FMA: each padded column is
/// one register, widened to f64; the same six sums, the same fused operations in the
/// same order, so the same bits. The sum is left in a register; only callers compiled
/// for AVX2 may call it (it is inlined there). (Its twin for f64 blocks below differs
/// in the block's product; a shared driver taking the product as a closure lost the
/// inlining of the intrinsics, a tenfold slowdown.)
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn row_f32_avx_sum(values: &[[f32; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> std::arch::x86_64::__m256d {
    use std::arch::x86_64::*;
    // Block k's product added into one set of three sums (kept in registers: the two
    // sets are named, not indexed, and the loop takes the blocks two at a time).
    #[inline(always)]
    fn add(values: &[[f32; 12]], cols: &[u32], x: &[Vec3], skip: usize, k: usize, sums: &mut [__m256d; 3]) {
        let j = cols[k] as usize;
        if j == skip {
            return;
        }
        let a = values[k].as_ptr();
        let xj = x[j];
        // SAFETY: a block holds 12 floats: three loads of four (the caller runs with AVX2).
        unsafe {
            let (c0, c1, c2) = (_mm256_cvtps_pd(_mm_loadu_ps(a)), _mm256_cvtps_pd(_mm_loadu_ps(a.add(4))), _mm256_cvtps_pd(_mm_loadu_ps(a.add(8))));
            sums[0] = _mm256_fmadd_pd(c0, _mm256_set1_pd(xj.x), sums[0]);
            sums[1] = _mm256_fmadd_pd(c1, _mm256_set1_pd(xj.y), sums[1]);
            sums[2] = _mm256_fmadd_pd(c2, _mm256_set1_pd(xj.z), sums[2]);
        }
    }
    // SAFETY: the caller runs with AVX2 enabled.
    let (mut even, mut odd) = unsafe { ([_mm256_setzero_pd(); 3], [_mm256_setzero_pd(); 3]) };
    let mut k = range.start;
    while k + 1 < range.end {
        add(values, cols, x, skip, k, &mut even);
        add(values, cols, x, skip, k + 1, &mut odd);
        k += 2;
    }
    if k < range.end {
        add(values, cols, x, skip, k, &mut even);
    }
    // SAFETY: the caller runs with AVX2 enabled.
    unsafe { _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(even[0], odd[0]), _mm256_add_pd(even[1], odd[1])), _mm256_add_pd(even[2], odd[2])) }
}

/// [`row_generic`] for double-precision blocks (the coarse levels) with AVX2: each
/// padded column is one register; the same six sums with a multiply and an add (no
/// fused operation, as the generic f64 path), so the same bits. Only callers compiled
/// for AVX2 may call it.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
unsafe fn row_f64_avx_sum(values: &[[f64; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> std::arch::x86_64::__m256d {
    use std::arch::x86_64::*;
    #[inline(always)]
    fn add(values: &[[f64; 12]], cols: &[u32], x: &[Vec3], skip: usize, k: usize, sums: &mut [__m256d; 3]) {
        let j = cols[k] as usize;
        if j == skip {
            return;
        }
        let a = values[k].as_ptr();
        let xj = x[j];
        // SAFETY: a block holds 12 doubles: three loads of four (the caller runs with AVX2).
        unsafe {
            sums[0] = _mm256_add_pd(sums[0], _mm256_mul_pd(_mm256_loadu_pd(a), _mm256_set1_pd(xj.x)));
            sums[1] = _mm256_add_pd(sums[1], _mm256_mul_pd(_mm256_loadu_pd(a.add(4)), _mm256_set1_pd(xj.y)));
            sums[2] = _mm256_add_pd(sums[2], _mm256_mul_pd(_mm256_loadu_pd(a.add(8)), _mm256_set1_pd(xj.z)));
        }
    }
    // SAFETY: the caller runs with AVX2 enabled.
    let (mut even, mut odd) = unsafe { ([_mm256_setzero_pd(); 3], [_mm256_setzero_pd(); 3]) };
    let mut k = range.start;
    while k + 1 < range.end {
        add(values, cols, x, skip, k, &mut even);
        add(values, cols, x, skip, k + 1, &mut odd);
        k += 2;
    }
    if k < range.end {
        add(values, cols, x, skip, k, &mut even);
    }
    // SAFETY: as above.
    unsafe { _mm256_add_pd(_mm256_add_pd(_mm256_add_pd(even[0], odd[0]), _mm256_add_pd(even[1], odd[1])), _mm256_add_pd(even[2], odd[2])) }
}

/// Block-row products for a matrix value type: the portable row sum and, on x86-64,
/// its AVX2 clone (the same bits).
pub trait RowProduct: Scalar {
    /// See [`row_generic`]: fused multiply-adds for the f32 system, a multiply and an
    /// add for the f64 coarse levels.
    fn row(values: &[[Self; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4];

    /// The same sum with AVX2, left in a register.
    ///
    /// # Safety
    /// Only code compiled for AVX2 and FMA may call it (it is inlined there).
    #[cfg(target_arch = "x86_64")]
    unsafe fn row_avx2(values: &[[Self; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> std::arch::x86_64::__m256d;
}

impl RowProduct for f64 {
    #[inline(always)]
    fn row(values: &[[f64; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4] {
        row_generic::<f64, false>(values, cols, range, x, skip)
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn row_avx2(values: &[[f64; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> std::arch::x86_64::__m256d {
        // SAFETY: the caller runs with AVX2 enabled.
        unsafe { row_f64_avx_sum(values, cols, range, x, skip) }
    }
}

impl RowProduct for f32 {
    #[inline(always)]
    fn row(values: &[[f32; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4] {
        row_generic::<f32, true>(values, cols, range, x, skip)
    }

    #[cfg(target_arch = "x86_64")]
    #[inline(always)]
    unsafe fn row_avx2(values: &[[f32; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> std::arch::x86_64::__m256d {
        // SAFETY: the caller runs with AVX2 enabled.
        unsafe { row_f32_avx_sum(values, cols, range, x, skip) }
    }
}

/// `y = A x` over the active rows of a block-sparse matrix (see
/// `BlockMatrix::multiply`); returns `xᵀ y`. With AVX2 the whole product is compiled
/// for it, so that each row's kernel is inlined (a call per block row was a third of
/// the product's time).
pub fn block_multiply<T: RowProduct>(pattern: &Pattern, values: &[[T; 12]], x: &[Vec3], y: &mut [Vec3], active: &[bool]) -> f64 {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        #[target_feature(enable = "avx2,fma")]
        unsafe fn wide<T: RowProduct>(pattern: &Pattern, values: &[[T; 12]], x: &[Vec3], y: &mut [Vec3], active: &[bool]) -> f64 {
            // SAFETY: this function runs with AVX2 enabled.
            rows_with(pattern, x, y, active, |range| store(unsafe { T::row_avx2(values, &pattern.cols, range, x, usize::MAX) }))
        }
        // SAFETY: the CPU was checked to have AVX2 and FMA.
        return unsafe { wide(pattern, values, x, y, active) };
    }
    rows_with(pattern, x, y, active, |range| T::row(values, &pattern.cols, range, x, usize::MAX))
}

/// `y_i = row(i)` over the active rows (zero on the others); returns `xᵀ y`.
#[inline(always)]
fn rows_with(pattern: &Pattern, x: &[Vec3], y: &mut [Vec3], active: &[bool], row: impl Fn(std::ops::Range<usize>) -> [f64; 4]) -> f64 {
    let mut xy = 0.0;
    for i in 0..pattern.rows() {
        if !active[i] {
            y[i] = Vec3::zeros();
            continue;
        }
        let s = row(pattern.start[i] as usize..pattern.start[i + 1] as usize);
        let yi = Vec3::new(s[0], s[1], s[2]);
        xy += x[i].dot(&yi);
        y[i] = yi;
    }
    xy
}

/// A register's four doubles.
#[cfg(target_arch = "x86_64")]
#[inline(always)]
fn store(v: std::arch::x86_64::__m256d) -> [f64; 4] {
    let mut s = [0f64; 4];
    // SAFETY: four doubles into four doubles; `_mm256_storeu_pd` needs AVX, which every
    // caller of this (inlined into code compiled for AVX2) has.
    unsafe { std::arch::x86_64::_mm256_storeu_pd(s.as_mut_ptr(), v) };
    s
}

/// One block Gauss–Seidel sweep over the active rows, in order (`forward`) or in reverse:
/// `z_i = D_i⁻¹ (r_i − Σ_{j≠i} A_ij z_j)` with the newest `z_j`; `inverse` holds the
/// `D_i⁻¹`. Inactive rows are left as they are.
/// With AVX2 the whole sweep is compiled for it, each row's kernel inlined (as in
/// [`block_multiply`]).
pub fn gauss_seidel<T: RowProduct>(pattern: &Pattern, values: &[[T; 12]], inverse: &[Matrix3<f64>], active: &[bool], r: &[Vec3], z: &mut [Vec3], forward: bool) {
    #[cfg(target_arch = "x86_64")]
    if has_avx2() {
        #[target_feature(enable = "avx2,fma")]
        unsafe fn wide<T: RowProduct>(pattern: &Pattern, values: &[[T; 12]], inverse: &[Matrix3<f64>], active: &[bool], r: &[Vec3], z: &mut [Vec3], forward: bool) {
            // SAFETY: this function runs with AVX2 enabled.
            sweep_rows(pattern, inverse, active, r, z, forward, |range, z, i| store(unsafe { T::row_avx2(values, &pattern.cols, range, z, i) }));
        }
        // SAFETY: the CPU was checked to have AVX2 and FMA.
        return unsafe { wide(pattern, values, inverse, active, r, z, forward) };
    }
    sweep_rows(pattern, inverse, active, r, z, forward, |range, z, i| T::row(values, &pattern.cols, range, z, i));
}

#[inline(always)]
fn sweep_rows(pattern: &Pattern, inverse: &[Matrix3<f64>], active: &[bool], r: &[Vec3], z: &mut [Vec3], forward: bool, row: impl Fn(std::ops::Range<usize>, &[Vec3], usize) -> [f64; 4]) {
    let n = pattern.rows();
    for step in 0..n {
        let i = if forward { step } else { n - 1 - step };
        if active[i] {
            let s = row(pattern.start[i] as usize..pattern.start[i + 1] as usize, z, i);
            z[i] = inverse[i] * Vec3::new(r[i].x - s[0], r[i].y - s[1], r[i].z - s[2]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_rotated_product_is_the_rotated_matrix_times_the_displacement() {
        // A symmetric 24 × 24 matrix, a rotation, a displacement.
        let mut dense = [0f32; 576];
        for r in 0..24 {
            for c in 0..=r {
                let v = ((r * 31 + c * 17) as f32 * 0.37).sin() + if r == c { 4.0 } else { 0.0 };
                dense[24 * c + r] = v;
                dense[24 * r + c] = v;
            }
        }
        let k = to_planar(&dense);
        let rot = nalgebra::Rotation3::from_euler_angles(0.3, -0.7, 1.1);
        let r: [[f32; 3]; 3] = std::array::from_fn(|p| std::array::from_fn(|q| rot[(p, q)] as f32));
        let d: [f32; 24] = std::array::from_fn(|i| (i as f32 * 0.61).cos());
        let (mut rotated, mut expected, mut f) = ([[F8::default(); 3]; 24], [0f32; 24], [0f32; 24]);
        rotate_and_multiply(&k, &r, &d, &mut rotated, &mut expected);
        rotated_multiply(&k, &r, &d, &mut f);
        let scale = expected.iter().fold(0f32, |m, v| m.max(v.abs()));
        for i in 0..24 {
            assert!((f[i] - expected[i]).abs() < 1e-5 * scale, "entry {i}: {} against {}", f[i], expected[i]);
        }
    }
    use crate::math::Matrix3;

    #[test]
    fn the_conjugate_gradient_updates_match_their_formulas() {
        // 3 × 7 coordinates: five whole groups of four and a remainder of one.
        let n = 21;
        let f = |k: usize, a: f64| ((k as f64 + a) * 0.917).sin();
        let (p, q, w): (Vec<f64>, Vec<f64>, Vec<f64>) = ((0..n).map(|k| f(k, 0.1)).collect(), (0..n).map(|k| f(k, 0.7)).collect(), (0..n).map(|k| 1.0 + f(k, 2.0).abs()).collect());
        let (mut x, mut r): (Vec<f64>, Vec<f64>) = ((0..n).map(|k| f(k, 3.0)).collect(), (0..n).map(|k| f(k, 5.0)).collect());
        let (x0, r0) = (x.clone(), r.clone());
        let (norm2, largest) = cg_update(&mut x, &p, &mut r, &q, &w, 0.37);
        let mut expected = (0.0, 0.0f64);
        for k in 0..n {
            assert_eq!(x[k], x0[k] + p[k] * 0.37);
            assert_eq!(r[k], r0[k] - q[k] * 0.37);
            expected.0 += r[k] * r[k] * w[k];
            expected.1 = expected.1.max(r[k].abs() * w[k]);
        }
        assert!((norm2 - expected.0).abs() < 1e-14 * expected.0 && largest == expected.1);
        let plain: f64 = (0..n).map(|k| p[k] * q[k]).sum();
        assert!((dot(&p, &q) - plain).abs() < 1e-14);
        let mut direction = p.clone();
        cg_direction(&mut direction, &q, -1.5);
        assert!((0..n).all(|k| direction[k] == q[k] + p[k] * -1.5));
        // With the Jacobi-preconditioned residual (a fixed axis: w = 0).
        let (mut x, mut r, mut z) = (x0.clone(), r0.clone(), vec![f64::NAN; n]);
        let mut w = w.iter().map(|w| 1.0 / w).collect::<Vec<f64>>();
        w[4] = 0.0;
        let (rz, rr) = cg_update_jacobi(&mut x, &p, &mut r, &q, &w, &mut z, 0.37);
        let mut expected = (0.0, 0.0);
        for k in 0..n {
            assert_eq!(x[k], x0[k] + p[k] * 0.37);
            assert_eq!(r[k], r0[k] - q[k] * 0.37);
            assert_eq!(z[k], r[k] * w[k]);
            expected.0 += r[k] * z[k];
            expected.1 += r[k] * r[k];
        }
        assert!((rz - expected.0).abs() < 1e-14 * expected.0 && (rr - expected.1).abs() < 1e-14 * expected.1);
    }

    #[test]
    fn a_block_row_sums_to_the_same_bits_with_and_without_avx2() {
        // Odd and even row lengths, a skipped column, values of mixed sign and size.
        let values: Vec<[f32; 12]> = (0..23).map(|k| std::array::from_fn(|i| if i % 4 == 3 { 0.0 } else { ((k * 12 + i) as f32 * 0.731).sin() * 10f32.powi((k % 5) as i32 - 2) })).collect();
        let cols: Vec<u32> = (0..23).map(|k| (k * 7 % 23) as u32).collect();
        let x: Vec<Vec3> = (0..23).map(|j| Vec3::new((j as f64 * 1.3).cos(), (j as f64 * 0.4).sin() * 1e-3, j as f64 - 11.5)).collect();
        for (range, skip) in [(0..23, usize::MAX), (3..20, 7), (5..6, usize::MAX), (0..0, usize::MAX)] {
            let generic = row_generic::<f32, true>(&values, &cols, range.clone(), &x, skip);
            let dense: [f64; 4] = std::array::from_fn(|lane| range.clone().filter(|&k| cols[k] as usize != skip).map(|k| (0..3).map(|c| f64::from(values[k][4 * c + lane]) * x[cols[k] as usize][c]).sum::<f64>()).sum());
            for lane in 0..4 {
                assert!((generic[lane] - dense[lane]).abs() <= 1e-12 * dense.iter().map(|v| v.abs()).fold(1.0, f64::max), "lane {lane}");
            }
            #[cfg(target_arch = "x86_64")]
            if has_avx2() {
                // SAFETY: the CPU has AVX2 and FMA.
                #[target_feature(enable = "avx2,fma")]
                unsafe fn f32_wide(values: &[[f32; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4] {
                    // SAFETY: this function runs with AVX2 enabled.
                    store(unsafe { row_f32_avx_sum(values, cols, range, x, skip) })
                }
                let wide = unsafe { f32_wide(&values, &cols, range.clone(), &x, skip) };
                assert_eq!(wide.map(f64::to_bits), generic.map(f64::to_bits), "{range:?} skipping {skip}");
                // The coarse levels' double blocks, multiply and add without fusing.
                let doubles: Vec<[f64; 12]> = values.iter().map(|b| b.map(|v| f64::from(v) * (1.0 + 1e-9))).collect();
                #[target_feature(enable = "avx2,fma")]
                unsafe fn f64_wide(values: &[[f64; 12]], cols: &[u32], range: std::ops::Range<usize>, x: &[Vec3], skip: usize) -> [f64; 4] {
                    // SAFETY: this function runs with AVX2 enabled.
                    store(unsafe { row_f64_avx_sum(values, cols, range, x, skip) })
                }
                let wide = unsafe { f64_wide(&doubles, &cols, range.clone(), &x, skip) };
                let generic = row_generic::<f64, false>(&doubles, &cols, range.clone(), &x, skip);
                assert_eq!(wide.map(f64::to_bits), generic.map(f64::to_bits), "f64 {range:?} skipping {skip}");
            }
        }
    }

    #[test]
    fn a_first_write_stores_what_zeroing_and_adding_would_whatever_the_block_held() {
        let k24 = crate::grid::hex::box_stiffness([0.003, 0.002, 0.004], 5e3, 0.4);
        let m = to_planar(&k24.as_slice().iter().map(|&v| v as f32).collect::<Vec<f32>>());
        // Corner pairs onto 64 blocks, two of them left out.
        let mut blocks: [u32; 64] = std::array::from_fn(|k| k as u32);
        blocks[9] = NO_BLOCK;
        blocks[40] = NO_BLOCK;
        let first = 0x00FF_0F0F_F0F0_FF01u64;
        let mut zeroed = vec![[0f32; 12]; 64];
        for (k, v) in zeroed.iter_mut().enumerate() {
            if (first >> k) & 1 == 0 {
                *v = [0.25 * k as f32; 12];
            }
        }
        let mut stale = zeroed.clone();
        for (k, v) in stale.iter_mut().enumerate() {
            if (first >> k) & 1 == 1 {
                *v = [f32::NAN; 12];
            }
        }
        scatter_element(&mut zeroed, &blocks, &m, 0.5, 0);
        scatter_element(&mut stale, &blocks, &m, 0.5, first);
        for k in (0..64).filter(|&k| blocks[k] != NO_BLOCK) {
            let bits = |v: &[f32; 12]| v.map(f32::to_bits);
            assert_eq!(bits(&stale[k]), bits(&zeroed[k]), "block {k}");
        }
    }

    #[test]
    fn the_scatter_gives_the_same_bits_with_and_without_avx2() {
        let k24 = crate::grid::hex::box_stiffness([0.003, 0.002, 0.004], 5e3, 0.4);
        let m = to_planar(&k24.as_slice().iter().map(|&v| v as f32).collect::<Vec<f32>>());
        // Corner pairs onto 40 blocks (some shared, as neighbouring corners share them),
        // a few left out; blocks holding values of mixed sign; a removal (negative scale).
        let blocks: [u32; 64] = std::array::from_fn(|k| if k % 13 == 5 { NO_BLOCK } else { (k * 7 % 40) as u32 });
        let held: Vec<[f32; 12]> = (0..40).map(|b| std::array::from_fn(|e| if e % 4 == 3 { 0.0 } else { ((b * 12 + e) as f32 * 0.37).sin() * 1e3 })).collect();
        for (scale, first) in [(0.5f32, 0u64), (-0.25, 0), (1e-3, 0x00FF_0F0F_F0F0_FF01)] {
            let mut portable = held.clone();
            scatter_element_portable(&mut portable, &blocks, &m, scale, first);
            assert_ne!(portable, held, "the scatter wrote");
            #[cfg(target_arch = "x86_64")]
            if has_avx2() {
                let mut wide = held.clone();
                // SAFETY: the CPU has AVX2.
                unsafe { scatter_element_avx2(&mut wide, &blocks, &m, scale, first) };
                for b in 0..40 {
                    assert_eq!(wide[b].map(f32::to_bits), portable[b].map(f32::to_bits), "block {b}, scale {scale}");
                }
            }
        }
    }

    #[test]
    fn the_rotated_stiffness_is_r_k_r_transposed_and_the_force_its_product() {
        let k24 = crate::grid::hex::box_stiffness([0.003, 0.002, 0.004], 5e3, 0.4);
        let k = to_planar(&k24.as_slice().iter().map(|&v| v as f32).collect::<Vec<f32>>());
        let r = nalgebra::Rotation3::from_euler_angles(0.3, -0.7, 1.1).into_inner();
        let rf: [[f32; 3]; 3] = std::array::from_fn(|p| std::array::from_fn(|q| r[(p, q)] as f32));
        let d: [f32; 24] = std::array::from_fn(|i| (i as f32 * 0.37).sin() * 1e-3);
        let (mut out, mut f) = ([[F8::default(); 3]; 24], [0f32; 24]);
        rotate_and_multiply(&k, &rf, &d, &mut out, &mut f);
        let rotated = {
            let mut m = crate::grid::hex::Mat24::zeros();
            for a in 0..8 {
                for b in 0..8 {
                    let kab = Matrix3::from_fn(|i, j| k24[(3 * a + i, 3 * b + j)]);
                    m.fixed_view_mut::<3, 3>(3 * a, 3 * b).copy_from(&(r * kab * r.transpose()));
                }
            }
            m
        };
        for row in 0..24 {
            for column in 0..24 {
                let got = f64::from(out[row][column % 3].0[column / 3]);
                assert!((got - rotated[(row, column)]).abs() < 1e-4 * k24.amax(), "({row}, {column})");
            }
        }
        let expected = rotated * nalgebra::SVector::<f64, 24>::from_fn(|i, _| f64::from(d[i]));
        for i in 0..24 {
            assert!((f64::from(f[i]) - expected[i]).abs() < 1e-4 * expected.amax(), "f[{i}]");
        }
    }
}
