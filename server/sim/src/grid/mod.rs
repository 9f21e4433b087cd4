//! `branched-grid`: the Dynamic Branched Grid (paper 004, ALGORITHMS.md part B).

pub mod condense;
pub mod hex;
pub mod marching;
pub mod solver;
pub mod surface;
pub mod topology;
