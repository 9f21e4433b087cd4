//! cutsim-sim: soft-tissue models, collision and cutting for the cutsim surgical
//! training simulator. No async, no network: the server crate drives this one.
//!
//! - [`scene`]: scene files (JSON) and their validation.
//! - [`tissue::Tissue`]: the one interface every tissue model offers the session.
//! - [`msm`]: the surface mass-spring skin with residual stress and three-stage cutting.
//! - [`surface`]: the visible surface with stable ids, snapshots and topology deltas.
//! - [`script`] and [`runner`]: cut scripts run in lockstep, with a report.
//!
//! Units are SI everywhere: m, kg, s, Pa, N.

// Numerical kernels walk parallel arrays (positions, velocities, masses…) by one index:
// an iterator over one of them would hide that the others are indexed alike.
#![allow(clippy::needless_range_loop)]
// `!(x > 0.0)` is how the solvers and orderings treat NaN with the non-positive values
// (a `<=` would let NaN through).
#![allow(clippy::neg_cmp_op_on_partial_ord)]

pub mod accuracy;
pub mod assessment;
pub mod broad_phase;
pub mod geometry;
pub mod grid;
pub mod hash;
pub mod math;
pub mod msm;
pub mod multirate;
pub mod quantity;
pub mod runner;
pub mod scene;
pub mod solver;
pub mod script;
pub mod stats;
pub mod surface;
pub mod tissue;
pub mod tool;
pub mod union_find;
pub mod volume;

use scene::{ModelSpec, Scene, SceneError};
use tissue::Tissue;

/// Builds the tissue model a scene describes.
pub fn build_tissue(scene: &Scene) -> Result<Box<dyn Tissue>, SceneError> {
    match &scene.model {
        ModelSpec::Msm(spec) => Ok(Box::new(msm::build_from_scene(scene, spec)?)),
        ModelSpec::BranchedGrid(spec) => match &spec.schedule {
            scene::ScheduleSpec::SingleRate => Ok(Box::new(grid::build_from_scene(scene, spec)?)),
            scene::ScheduleSpec::Multirate(schedule) => Ok(Box::new(multirate::build_from_scene(scene, schedule)?)),
        },
    }
}
