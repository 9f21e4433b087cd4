//! The simple preconditioners: none, and block Jacobi (the inverse of each node's 3×3
//! diagonal block). The multigrid and factorization ones have modules of their own.

use super::block_sparse::{BlockMatrix, Scalar};
use super::pcg::Preconditioner;
use crate::math::{Matrix3, Vec3};

/// z = r.
#[derive(Debug, Clone, Copy, Default)]
pub struct Identity;

impl Preconditioner for Identity {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]) {
        z.copy_from_slice(r);
    }
}

/// The inverse of each active node's 3×3 diagonal block (zero on inactive nodes).
#[derive(Debug, Clone, Default)]
pub struct BlockJacobi {
    pub inverse: Vec<Matrix3<f64>>,
}

impl BlockJacobi {
    pub fn new<T: Scalar>(a: &BlockMatrix<T>, active: &[bool]) -> Self {
        let mut j = BlockJacobi::default();
        j.update(a, active);
        j
    }

    /// Recomputes the inverses from `a` (allocates only when the system grew).
    pub fn update<T: Scalar>(&mut self, a: &BlockMatrix<T>, active: &[bool]) {
        let n = a.rows();
        self.inverse.resize(n, Matrix3::zeros());
        self.update_rows(a, active, 0..n);
    }

    /// Recomputes the inverses of `rows` only, when no other row's diagonal block (or
    /// active flag) changed since the last update.
    pub fn update_rows<T: Scalar>(&mut self, a: &BlockMatrix<T>, active: &[bool], rows: impl IntoIterator<Item = usize>) {
        for i in rows {
            self.inverse[i] = if active[i] { invert_spd(&a.block(a.pattern.diag[i] as usize)) } else { Matrix3::zeros() };
        }
    }

    /// The ℓ1 variant, a smoother for multigrid: each diagonal block plus, on its
    /// diagonal, the absolute row sums of the row's other blocks (over active columns).
    /// `I − D_ℓ1⁻¹ A` then contracts in A's energy norm for any symmetric positive
    /// definite A (Baker, Falgout, Kolev & Yang 2011), with no damping to tune — where
    /// plain Jacobi's damping must stay under 2/λmax(D⁻¹A), which superimposed and
    /// ghost-filled coarse elements push high.
    pub fn update_l1<T: Scalar>(&mut self, a: &BlockMatrix<T>, active: &[bool]) {
        let n = a.rows();
        self.inverse.resize(n, Matrix3::zeros());
        let p = &a.pattern;
        for i in 0..n {
            if !active[i] {
                self.inverse[i] = Matrix3::zeros();
                continue;
            }
            let mut extra = Vec3::zeros();
            for k in p.start[i] as usize..p.start[i + 1] as usize {
                let j = p.cols[k] as usize;
                if j == i || !active[j] {
                    continue;
                }
                let b = a.block(k);
                for r in 0..3 {
                    extra[r] += b[(r, 0)].abs() + b[(r, 1)].abs() + b[(r, 2)].abs();
                }
            }
            self.inverse[i] = invert_spd(&(a.block(p.diag[i] as usize) + Matrix3::from_diagonal(&extra)));
        }
    }
}

/// The inverse of a symmetric positive semi-definite block; where it is singular, the
/// inverse of its diagonal (zero where that is zero).
pub fn invert_spd(m: &Matrix3<f64>) -> Matrix3<f64> {
    let scale = m[(0, 0)].abs() + m[(1, 1)].abs() + m[(2, 2)].abs();
    if scale > 0.0 && m.determinant().abs() > 1e-12 * scale * scale * scale
        && let Some(inverse) = m.try_inverse()
    {
        return inverse;
    }
    let inv = |d: f64| if d > 0.0 { 1.0 / d } else { 0.0 };
    Matrix3::from_diagonal(&Vec3::new(inv(m[(0, 0)]), inv(m[(1, 1)]), inv(m[(2, 2)])))
}

impl Preconditioner for BlockJacobi {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]) {
        for ((z, r), inverse) in z.iter_mut().zip(r).zip(&self.inverse) {
            *z = inverse * r;
        }
    }
}
