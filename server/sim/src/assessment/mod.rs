//! Assessment: a scene's training task (a planned incision, no-go regions, a force
//! limit) and the trainee's objective metrics against it.
//!
//! - [`task`]: the task as written in a scene and checked against its tools.
//! - [`plan`]: the planned incision's geometry (deviation, depth, arc length).
//! - [`metrics`]: the [`Assessor`] that folds each step into an [`Assessment`].
//! - [`score`]: the documented score and the pass/fail verdict.
//! - [`report`]: a printable HTML report of a session's task, metrics and figures.
//! - [`timeline`]: a recording's force and metric curves for the replay's timeline.
//!
//! The assessor sees the same inputs in a live session, a script and a replay (each
//! step's tool commands and feedback), so equal commands give equal metrics. The server
//! runs it off the physics thread; definitions, sources and weights: docs/assessment.md.

pub mod metrics;
pub mod plan;
pub mod report;
pub mod score;
pub mod task;
pub mod timeline;

pub use metrics::{Assessment, AssessmentEvent, Assessor, History, ToolSample, fill_samples};
pub use task::{Task, TaskSpec};
pub use timeline::Timeline;

#[cfg(test)]
mod tests;
