//! A recording's curves for the replay's timeline: the force and the metrics over the
//! whole recording, in a fixed number of bins, so an instructor sees where a trainee
//! pressed too hard or left the plan before scrubbing there.
//!
//! A replay builds it by playing its recording through once (see the server's
//! playback); each bin holds the largest force in it and the metrics at its end, as the
//! [`Assessor`] computed them from the same steps the live session assessed.

use serde::{Deserialize, Serialize};

use super::metrics::Assessor;

/// Bins a timeline holds at most (a recording longer than this many steps puts
/// several steps in a bin).
pub const MAX_TIMELINE_BINS: u64 = 600;

/// Curves over a recording. Bin i covers steps `[i·bin_steps, (i+1)·bin_steps)` of the
/// whole recording (all its resets); a metric the task does not have is `null`.
#[derive(Debug, Clone, PartialEq, Default, Serialize, Deserialize)]
pub struct Timeline {
    /// Steps in the recording, and how many of them the curves cover so far.
    pub total_steps: u64,
    pub indexed_steps: u64,
    /// Length of a step, s.
    pub step_s: f64,
    pub bin_steps: u64,
    /// Largest force on any active tool in the bin, N (as the metrics' peak).
    pub force_peak_n: Vec<f32>,
    /// At the bin's end: the score (0–100), deviation RMS (mm), coverage (%), no-go
    /// entries so far.
    pub score: Vec<Option<f32>>,
    pub deviation_rms_mm: Vec<Option<f32>>,
    pub coverage_pct: Vec<Option<f32>>,
    pub no_go_entries: Vec<u64>,
}

impl Timeline {
    pub fn new(total_steps: u64, step_s: f64) -> Self {
        let bin_steps = total_steps.div_ceil(MAX_TIMELINE_BINS).max(1);
        let bins = total_steps.div_ceil(bin_steps) as usize;
        Self {
            total_steps,
            indexed_steps: 0,
            step_s,
            bin_steps,
            force_peak_n: Vec::with_capacity(bins),
            score: Vec::with_capacity(bins),
            deviation_rms_mm: Vec::with_capacity(bins),
            coverage_pct: Vec::with_capacity(bins),
            no_go_entries: Vec::with_capacity(bins),
        }
    }

    /// The curves cover the whole recording.
    pub fn complete(&self) -> bool {
        self.indexed_steps >= self.total_steps
    }

    /// One more step, read from the assessor that has just folded it in.
    pub fn observe(&mut self, assessor: &Assessor) {
        if self.complete() {
            return;
        }
        let force = assessor.step_force_n() as f32;
        if self.indexed_steps.is_multiple_of(self.bin_steps) {
            self.force_peak_n.push(force);
        } else if let Some(peak) = self.force_peak_n.last_mut() {
            *peak = peak.max(force);
        }
        self.indexed_steps += 1;
        if self.indexed_steps.is_multiple_of(self.bin_steps) || self.complete() {
            let a = assessor.assessment();
            self.score.push(a.score.map(|s| s as f32));
            self.deviation_rms_mm.push(a.deviation_rms_mm.map(|d| d as f32));
            self.coverage_pct.push(a.coverage.map(|c| (100.0 * c) as f32));
            self.no_go_entries.push(a.no_go_entries);
        }
    }
}
