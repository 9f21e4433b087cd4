//! Training cues (off by default, `--cues`): a short force pulse when the trainee enters
//! a no-go region of the session's task or goes above its force limit or its grip limit.
//!
//! A watcher thread asks the server for the session's assessment (`GetAssessment`) ten
//! times a second and counts the warnings it lists; the device loop starts a pulse for
//! each new one. The pulse rises and falls within the bridge's force-rate limit (it is
//! added before the limiter, which would flatten anything steeper), pushes the hand back
//! out along the scene's +z (or the tissue's force, when there is one) and lasts
//! `PULSE_MS`: a cue felt in the hand, not a force of the tissue. Cues arrive up to
//! 100 ms after the event (the metrics are computed off the server's physics thread).

use std::sync::Arc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::Duration;

use cutsim_proto::v1 as pb;
use cutsim_proto::v1::sessions_client::SessionsClient;

use crate::vec::V3;

/// How long a pulse lasts, ms (rise, hold and fall).
pub const PULSE_MS: f64 = 60.0;
/// Its peak, N (lower when the force-rate limit cannot reach it within a fifth of the pulse).
pub const PULSE_PEAK_N: f64 = 0.8;
/// How often the watcher asks for the assessment.
const POLL: Duration = Duration::from_millis(100);

/// Warnings seen so far, shared between the watcher and the device loop.
pub struct Watcher {
    pub warnings: Arc<AtomicU64>,
    stop: Arc<AtomicBool>,
    thread: Option<std::thread::JoinHandle<()>>,
}

/// The warnings of an assessment that deserve a cue.
pub fn warnings(a: &pb::Assessment) -> u64 {
    let listed = a.events.iter().filter(|e| matches!(e.kind.as_str(), "no_go" | "force_limit" | "grip_limit")).count() as u64;
    // Events past the kept list are only counted; no-go entries always are.
    listed.max(a.no_go_entries) + a.events_dropped
}

impl Watcher {
    pub fn start(server: tonic::transport::Endpoint, session: String, token: String) -> Self {
        let warnings = Arc::new(AtomicU64::new(0));
        let stop = Arc::new(AtomicBool::new(false));
        let thread = {
            let (warnings, stop) = (warnings.clone(), stop.clone());
            std::thread::Builder::new()
                .name("bridge-cues".into())
                .spawn(move || {
                    let runtime = tokio::runtime::Builder::new_current_thread().enable_all().build().expect("a tokio runtime");
                    runtime.block_on(async move {
                        let mut client = None;
                        while !stop.load(Ordering::Acquire) {
                            if client.is_none() {
                                client = server.connect().await.ok().map(SessionsClient::new);
                            }
                            if let Some(c) = client.as_mut() {
                                let mut request = tonic::Request::new(pb::GetAssessmentRequest { session_id: session.clone() });
                                if let Ok(token) = token.parse() {
                                    request.metadata_mut().insert("cutsim-token", token);
                                }
                                match c.get_assessment(request).await {
                                    // A script resets the metrics: only ever count up.
                                    Ok(a) => {
                                        warnings.fetch_max(self::warnings(a.get_ref()), Ordering::AcqRel);
                                    }
                                    Err(_) => client = None,
                                }
                            }
                            tokio::time::sleep(POLL).await;
                        }
                    });
                })
                .expect("the cue thread starts")
        };
        Self { warnings, stop, thread: Some(thread) }
    }

    pub fn stop(&mut self) {
        self.stop.store(true, Ordering::Release);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
    }
}

/// The pulse being played, in the device loop.
#[derive(Debug, Clone, Copy, Default)]
pub struct Pulse {
    seen: u64,
    played: u64,
    /// Time into the current pulse, s (None: none playing).
    elapsed_s: Option<f64>,
    peak_n: f64,
    ramp_s: f64,
}

impl Pulse {
    /// A pulse player for a device whose force may change by at most `max_rate_n_per_s`.
    pub fn new(max_rate_n_per_s: f64) -> Self {
        let ramp_s = PULSE_MS / 1e3 / 5.0;
        Self { seen: 0, played: 0, elapsed_s: None, peak_n: PULSE_PEAK_N.min(0.9 * max_rate_n_per_s * ramp_s), ramp_s }
    }

    /// Pulses started so far.
    pub fn played(&self) -> u64 {
        self.played
    }

    /// The cue force for this millisecond: starts a pulse when `warnings` grew, pushing
    /// along `away` (the tissue's force on the tool; +z when there is none).
    pub fn step(&mut self, dt_s: f64, warnings: u64, away: V3) -> V3 {
        if warnings > self.seen {
            self.seen = warnings;
            self.played += 1;
            self.elapsed_s = Some(0.0);
        }
        let Some(t) = self.elapsed_s else { return V3::default() };
        let total = PULSE_MS / 1e3;
        if t >= total {
            self.elapsed_s = None;
            return V3::default();
        }
        self.elapsed_s = Some(t + dt_s);
        let level = (t / self.ramp_s).min(1.0).min((total - t) / self.ramp_s).max(0.0);
        let norm = away.norm();
        let direction = if norm > 1e-9 { away * (1.0 / norm) } else { V3(0.0, 0.0, 1.0) };
        direction * (self.peak_n * level)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_new_warning_plays_one_pulse_within_the_force_rate_limit() {
        // A device slower than the default limit (100 N/s), so that the limit sets the peak.
        let rate = 50.0;
        let mut pulse = Pulse::new(rate);
        let dt = 0.001;
        let mut forces = Vec::new();
        for ms in 0..200 {
            let warnings = if ms >= 10 { 1 } else { 0 };
            forces.push(pulse.step(dt, warnings, V3::default()));
        }
        let peak = forces.iter().map(|f| f.norm()).fold(0.0, f64::max);
        assert!((peak - 0.9 * rate * 0.012).abs() < 1e-9, "the peak is what the rate limit allows in 12 ms: {peak}");
        assert!(forces.iter().all(|f| f.0 == 0.0 && f.1 == 0.0 && f.2 >= 0.0), "pushes along +z without a tissue force");
        let steepest = forces.windows(2).map(|w| (w[1] - w[0]).norm() / dt).fold(0.0, f64::max);
        assert!(steepest <= rate, "never steeper than the limiter allows: {steepest} N/s");
        let on = forces.iter().filter(|f| f.norm() > 0.0).count();
        assert!((55..=60).contains(&on), "lasts about {PULSE_MS} ms: {on} ms");
        assert!(forces[..10].iter().all(|f| f.norm() == 0.0) && forces[80..].iter().all(|f| f.norm() == 0.0), "one pulse, when the warning came");
    }

    #[test]
    fn the_pulse_pushes_along_the_tissue_force_and_repeats_for_each_warning() {
        let mut pulse = Pulse::new(1000.0);
        let mut peaks = Vec::new();
        for ms in 0..300u64 {
            let f = pulse.step(0.001, ms / 100 + 1, V3(3.0, 0.0, 0.0));
            assert!(f.1 == 0.0 && f.2 == 0.0 && f.0 >= 0.0);
            if ms % 100 == 30 {
                peaks.push(f.0);
            }
        }
        assert_eq!(peaks, vec![PULSE_PEAK_N; 3], "full peak when the rate allows it, once per warning");
    }

    #[test]
    fn warnings_count_no_go_entries_and_force_and_grip_limit_crossings() {
        let event = |kind: &str| pb::AssessmentEvent { kind: kind.into(), ..Default::default() };
        let a = pb::Assessment { no_go_entries: 1, events: vec![event("no_go"), event("completed"), event("force_limit"), event("outside_band"), event("grip_limit")], ..Default::default() };
        assert_eq!(warnings(&a), 3);
    }
}
