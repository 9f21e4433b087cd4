//! Linear solves for the tissue models.
//!
//! Both models take linearised implicit steps `A Δv = b` with `A = M + hC + h²K` over
//! 3-vectors per node. This subsystem holds what they share:
//!
//! - [`block_sparse`]: the assembled system, a sparse matrix of 3×3 blocks whose pattern
//!   is built once per topology and whose values are refreshed every step;
//! - [`pcg`]: preconditioned conjugate gradient that reports, for every solve, its
//!   iterations, the residual it reached and whether it hit its cap;
//! - [`predictor`]: the solve's initial guess, extrapolated from the last steps';
//! - [`preconditioner`]: none and block Jacobi, the baselines;
//! - [`multigrid`]: a V-cycle over coarser Galerkin levels, the preconditioner whose
//!   iteration count does not grow with resolution;
//! - [`cholesky`]: a sparse Cholesky factor of a recent system (faer's), the other such
//!   preconditioner: computed on a worker, reused for many steps;
//! - [`compact_factor`]: its triangular solves, from a compact copy (8 bits an entry
//!   with a scale per column, diagonals in f32: a fifth of f32's memory traffic per
//!   application);
//! - [`ordering`]: the order its factorization eliminates the nodes in (nested
//!   dissection by position: a smaller factor than minimum degree);
//! - [`kernels`]: the per-step kernels — element rotation and scatter, block-row products
//!   and Gauss–Seidel sweeps, the conjugate gradient's vector updates — vectorized, each
//!   sum in a fixed order (the same bits at every vector width);
//! - [`background`]: a worker thread whose results are swapped in at steps fixed in
//!   advance (deterministic in real time, lockstep and replay).
//!
//! The models assemble their own matrices (they know their elements); this module knows
//! nothing of tissues.

pub mod background;
pub mod block_sparse;
pub mod cholesky;
pub mod compact_factor;
pub mod kernels;
pub mod multigrid;
pub mod ordering;
pub mod pcg;
pub mod preconditioner;
pub mod predictor;
