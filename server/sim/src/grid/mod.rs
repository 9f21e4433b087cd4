//! `branched-grid`: the Dynamic Branched Grid (paper 004, ALGORITHMS.md part B).

mod build;
pub mod condense;
pub mod cut_resistance;
pub mod factorization;
pub mod fidelity;
pub mod friction;
pub mod hold;
pub mod hierarchy;
pub mod hex;
pub mod marching;
pub mod preconditioning;
mod model;
pub mod shared_stiffness;
pub mod solver;
mod statics;
pub mod support;
pub mod surface;
pub mod topology;

pub use build::{GridParts, MAX_MATERIAL_VOXELS, MAX_POISSON, MAX_POISSON_FULL, build_from_scene, build_parts, load_volume};
pub use model::{BranchedGrid, Frame, GridMaterial};
