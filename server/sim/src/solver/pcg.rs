//! Preconditioned conjugate gradient on 3-vectors per node, with honest convergence
//! figures: every solve reports its iterations, the relative residual it reached and
//! whether it stopped at its iteration cap short of its tolerance.
//!
//! The residual is measured in the metric of the matrix's diagonal,
//! `‖r‖_D⁻¹ / ‖b‖_D⁻¹` with `‖r‖²_D⁻¹ = Σ r²/d`: every node counts by its own scale (a
//! node of tiny mass and stiffness — the far corner of an element holding one voxel — is
//! solved as accurately as the others instead of being lost in the sum), and the figure
//! does not depend on the preconditioner, so solvers are compared on the same scale.

use super::kernels::{self, flat, flat_mut};
use crate::math::Vec3;

/// `y = A x` on the active rows; returns `xᵀ y`.
pub trait LinearOperator {
    fn apply(&self, x: &[Vec3], y: &mut [Vec3]) -> f64;
}

/// `z ≈ A⁻¹ r` (symmetric positive definite, zero on inactive rows).
pub trait Preconditioner {
    fn apply(&self, r: &[Vec3], z: &mut [Vec3]);
}

/// When a solve stops.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PcgSettings {
    pub max_iterations: u32,
    /// Relative residual (in the diagonal metric) to reach.
    pub tolerance: f64,
    /// Also stop when the largest change the remaining residual would make to an unknown
    /// (estimated by its diagonal) is below this (0: never): a body at rest has round-off
    /// forces, not work to do.
    pub floor: f64,
    /// Also stop when the residual has not halved for this many iterations (0: never):
    /// a problem without a solution (a loaded piece free to turn) stalls, where a
    /// solvable one halves it every few dozen V-cycles. A stalled solve reports its
    /// residual, above the tolerance, without `cap_hit`.
    pub stalled_after: u32,
}

/// How a solve went.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Convergence {
    pub iterations: u32,
    /// Relative residual reached (diagonal metric).
    pub residual: f64,
    /// Stopped at the iteration cap above the tolerance (and above the floor).
    pub cap_hit: bool,
}

/// Scratch space of the solver (sized once per topology: solving allocates nothing).
#[derive(Debug, Clone, Default)]
pub struct Pcg {
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
    /// `1/d` per axis of the diagonal (0 where d ≤ 0): the residual's metric as
    /// multiplications (six divisions per node and iteration were a tenth of a step).
    metric: Vec<Vec3>,
}

fn safe_div(a: f64, b: f64) -> f64 {
    if b > 0.0 { a / b } else { 0.0 }
}

/// `Σ r²/d` per axis, with `w = 1/d`.
fn weighted_norm2(r: &Vec3, w: &Vec3) -> f64 {
    r.x * r.x * w.x + r.y * r.y * w.y + r.z * r.z * w.z
}

/// `max |r|/d` over the axes, with `w = 1/d`.
fn weighted_max(r: &Vec3, w: &Vec3) -> f64 {
    (r.x.abs() * w.x).max(r.y.abs() * w.y).max(r.z.abs() * w.z)
}

impl Pcg {
    pub fn resize(&mut self, n: usize) {
        for v in [&mut self.r, &mut self.z, &mut self.p, &mut self.q, &mut self.metric] {
            v.resize(n, Vec3::zeros());
        }
    }

    /// Solves `A x = b` on the active rows from the initial `x` (a warm start; inactive
    /// rows of x are zeroed). `diagonal` is A's diagonal (the residual's metric; ones
    /// measure it in the Euclidean norm).
    #[allow(clippy::too_many_arguments)]
    pub fn solve(
        &mut self,
        a: &impl LinearOperator,
        m: &impl Preconditioner,
        b: &[Vec3],
        x: &mut [Vec3],
        active: &[bool],
        diagonal: &[Vec3],
        settings: &PcgSettings,
    ) -> Convergence {
        let n = b.len();
        self.resize(n);
        let mut b_norm2 = 0.0;
        for i in 0..n {
            let d = &diagonal[i];
            self.metric[i] = Vec3::new(safe_div(1.0, d.x), safe_div(1.0, d.y), safe_div(1.0, d.z));
            if !active[i] || !x[i].iter().all(|c| c.is_finite()) {
                x[i] = Vec3::zeros();
            }
            if active[i] {
                b_norm2 += weighted_norm2(&b[i], &self.metric[i]);
            }
        }
        if !(b_norm2 > 0.0) {
            x.iter_mut().for_each(|v| *v = Vec3::zeros());
            return Convergence::default();
        }
        a.apply(x, &mut self.q);
        let mut r_norm2 = 0.0;
        let mut largest: f64 = 0.0;
        for i in 0..n {
            self.r[i] = if active[i] { b[i] - self.q[i] } else { Vec3::zeros() };
            r_norm2 += weighted_norm2(&self.r[i], &self.metric[i]);
            largest = largest.max(weighted_max(&self.r[i], &self.metric[i]));
        }
        m.apply(&self.r, &mut self.z);
        self.p.copy_from_slice(&self.z);
        let mut rz = kernels::dot(flat(&self.r), flat(&self.z));
        let target2 = settings.tolerance * settings.tolerance * b_norm2;
        let mut iterations = 0;
        let done = |r_norm2: f64, largest: f64| r_norm2 <= target2 || largest <= settings.floor;
        // The last iteration at which the residual fell below half the least before it.
        let (mut least_r_norm2, mut fell_at) = (r_norm2, 0);
        let stalled = |iterations: u32, fell_at: u32| settings.stalled_after > 0 && iterations - fell_at >= settings.stalled_after;
        while iterations < settings.max_iterations && !done(r_norm2, largest) && !stalled(iterations, fell_at) {
            let pq = a.apply(&self.p, &mut self.q);
            if !(pq > 0.0) || !(rz > 0.0) {
                break;
            }
            let alpha = rz / pq;
            (r_norm2, largest) = kernels::cg_update(flat_mut(x), flat(&self.p), flat_mut(&mut self.r), flat(&self.q), flat(&self.metric), alpha);
            iterations += 1;
            if r_norm2 < 0.25 * least_r_norm2 {
                (least_r_norm2, fell_at) = (r_norm2, iterations);
            }
            if done(r_norm2, largest) {
                break;
            }
            m.apply(&self.r, &mut self.z);
            let rz_next = kernels::dot(flat(&self.r), flat(&self.z));
            let beta = rz_next / rz;
            rz = rz_next;
            kernels::cg_direction(flat_mut(&mut self.p), flat(&self.z), beta);
        }
        let residual = (r_norm2 / b_norm2).sqrt();
        Convergence { iterations, residual, cap_hit: !done(r_norm2, largest) && iterations >= settings.max_iterations }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::solver::block_sparse::{BlockMatrix, Pattern};
    use crate::solver::preconditioner::{BlockJacobi, Identity};

    struct Op<'a>(&'a BlockMatrix, &'a [bool]);

    impl LinearOperator for Op<'_> {
        fn apply(&self, x: &[Vec3], y: &mut [Vec3]) -> f64 {
            self.0.multiply(x, y, self.1)
        }
    }

    /// A chain of springs between 3-vectors (a 1D Laplacian per axis, coupled across axes),
    /// plus a mass on the diagonal: symmetric positive definite.
    fn chain(n: usize) -> BlockMatrix {
        let elements: Vec<Vec<u32>> = (0..n as u32 - 1).map(|i| vec![i, i + 1]).collect();
        let mut a = BlockMatrix::<f64>::zeros(Pattern::from_elements(n, elements.iter().map(|e| e.as_slice())));
        let k = nalgebra::Matrix3::new(2.0, 0.5, 0.0, 0.5, 1.5, 0.2, 0.0, 0.2, 1.0);
        for i in 0..n - 1 {
            for (r, c, s) in [(i, i, 1.0), (i + 1, i + 1, 1.0), (i, i + 1, -1.0), (i + 1, i, -1.0)] {
                let at = a.pattern.find(r, c).unwrap();
                a.add(at, &(k * s));
            }
        }
        for i in 0..n {
            let at = a.pattern.diag[i] as usize;
            a.add_diagonal(at, Vec3::repeat(1e-3 * (1.0 + i as f64)));
        }
        a
    }

    #[test]
    fn pcg_solves_to_its_tolerance_and_reports_a_cap_it_hits() {
        let n = 60;
        let a = chain(n);
        let mut active = vec![true; n];
        active[0] = false; // a held node
        let b: Vec<Vec3> = (0..n).map(|i| if i == 0 { Vec3::zeros() } else { Vec3::new(1.0, -0.5, (i as f64).sin()) }).collect();
        let diagonal: Vec<Vec3> = (0..n).map(|i| { let d = a.block(a.pattern.diag[i] as usize); Vec3::new(d[(0, 0)], d[(1, 1)], d[(2, 2)]) }).collect();
        let jacobi = BlockJacobi::new(&a, &active);
        let mut pcg = Pcg::default();
        let mut x = vec![Vec3::zeros(); n];
        let settings = PcgSettings { max_iterations: 1000, tolerance: 1e-10, floor: 0.0, stalled_after: 0 };
        let done = pcg.solve(&Op(&a, &active), &jacobi, &b, &mut x, &active, &diagonal, &settings);
        assert!(!done.cap_hit && done.residual <= 1e-10, "{done:?}");
        // The true residual agrees.
        let mut ax = vec![Vec3::zeros(); n];
        a.multiply(&x, &mut ax, &active);
        let error: f64 = (1..n).map(|i| (ax[i] - b[i]).norm()).fold(0.0, f64::max);
        assert!(error < 1e-8, "{error}");
        assert_eq!(x[0], Vec3::zeros(), "held rows stay zero");
        // Capped at 3 iterations, it says so and reports where it stopped.
        let mut y = vec![Vec3::zeros(); n];
        let capped = pcg.solve(&Op(&a, &active), &Identity, &b, &mut y, &active, &diagonal, &PcgSettings { max_iterations: 3, ..settings });
        assert!(capped.cap_hit && capped.iterations == 3 && capped.residual > 1e-3, "{capped:?}");
        // Warm-started from the solution, nothing is left to do.
        let again = pcg.solve(&Op(&a, &active), &jacobi, &b, &mut x, &active, &diagonal, &settings);
        assert_eq!(again.iterations, 0);
    }
}
