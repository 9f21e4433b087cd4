//! Accuracy against an independent finite-element reference, the speed each setting
//! costs, and stability at the extremes (docs/accuracy-speed.md).
//!
//! - [`problems`]: the reference problems (voxel meshes, loads, sample points) and their
//!   export for `tools/reference/solve.py` (scikit-fem).
//! - [`reference`]: reading its results, field errors, the linear static solve.
//! - [`schedule`]: single-rate against multirate at equal budget, in real time.

pub mod cut_force;
pub mod membrane;
pub mod problems;
pub mod reference;
pub mod report;
pub mod schedule;
pub mod stability;
pub mod sweep;
