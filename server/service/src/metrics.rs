//! Prometheus metrics at `/metrics` (text exposition format 0.0.4).

use std::fmt::Write;
use std::sync::atomic::{AtomicU64, Ordering};

use crate::session::Registry;

/// Server-wide counters.
#[derive(Debug, Default)]
pub struct Metrics {
    pub viewer_bytes: AtomicU64,
}

pub fn render(registry: &Registry, metrics: &Metrics) -> String {
    let sessions = registry.list();
    let mut out = String::new();
    let family = |name: &str, kind: &str, help: &str, out: &mut String| {
        let _ = writeln!(out, "# HELP {name} {help}\n# TYPE {name} {kind}");
    };
    family("cutsim_sessions", "gauge", "Sessions open.", &mut out);
    let _ = writeln!(out, "cutsim_sessions {}", sessions.len());
    family("cutsim_sessions_created_total", "counter", "Sessions created since the server started.", &mut out);
    let _ = writeln!(out, "cutsim_sessions_created_total {}", registry.created_total.load(Ordering::Relaxed));
    family("cutsim_sessions_failed_total", "counter", "Sessions whose physics failed (panicked) since the server started.", &mut out);
    let _ = writeln!(out, "cutsim_sessions_failed_total {}", registry.failed_total.load(Ordering::Relaxed));
    family("cutsim_sessions_expired_total", "counter", "Idle sessions closed since the server started.", &mut out);
    let _ = writeln!(out, "cutsim_sessions_expired_total {}", registry.expired_total.load(Ordering::Relaxed));
    let (admitted, realtime) = registry.admission.held();
    family("cutsim_sessions_admitted", "gauge", "Sessions holding room (being built or running), and real-time sessions holding a core.", &mut out);
    let _ = writeln!(out, "cutsim_sessions_admitted{{kind=\"all\"}} {admitted}");
    let _ = writeln!(out, "cutsim_sessions_admitted{{kind=\"realtime\"}} {realtime}");
    family("cutsim_bytes_sent_total", "counter", "Bytes sent to WebSocket viewers.", &mut out);
    let _ = writeln!(out, "cutsim_bytes_sent_total{{transport=\"websocket\"}} {}", metrics.viewer_bytes.load(Ordering::Relaxed));
    family("cutsim_step_time_microseconds", "summary", "Physics step computation time per session, µs.", &mut out);
    for s in &sessions {
        let f = s.frame.load();
        let _ = writeln!(out, "cutsim_step_time_microseconds{{session=\"{}\",quantile=\"0.5\"}} {}", s.id, f.stats.p50_us);
        let _ = writeln!(out, "cutsim_step_time_microseconds{{session=\"{}\",quantile=\"0.99\"}} {}", s.id, f.stats.p99_us);
        let _ = writeln!(out, "cutsim_step_time_microseconds_count{{session=\"{}\"}} {}", s.id, f.stats.steps);
    }
    let per_session: [(&str, &str, &str, fn(&crate::session::Session) -> f64); 14] = [
        ("cutsim_solver_iterations_total", "counter", "Conjugate-gradient iterations of the implicit solves.", |s| s.frame.load().counters.solver_iterations as f64),
        ("cutsim_solver_cap_hits_total", "counter", "Solves that stopped at their iteration cap above the scene's tolerance.", |s| s.frame.load().counters.solver_cap_hits as f64),
        ("cutsim_solver_max_residual", "gauge", "The largest relative residual a solve ended with.", |s| s.frame.load().counters.solver_max_residual),
        ("cutsim_solver_waits_total", "counter", "Steps that waited for the solver's background work at its appointed step.", |s| s.frame.load().counters.solver_waits as f64),
        ("cutsim_solver_factor_failures_total", "counter", "Background factorizations that failed (the solve went on with block Jacobi).", |s| s.frame.load().counters.solver_factor_failures as f64),
        ("cutsim_session_failed", "gauge", "1 when the session's physics failed.", |s| f64::from(u8::from(s.failure().is_some()))),
        ("cutsim_stale_tool_lifts_total", "counter", "Tools lifted because their haptic client went quiet.", |s| s.stale_lifts.load(Ordering::Relaxed) as f64),
        ("cutsim_steps_total", "counter", "Physics steps taken.", |s| s.frame.load().total_steps as f64),
        ("cutsim_missed_deadlines_total", "counter", "Steps that finished after their period.", |s| s.frame.load().stats.missed_deadlines as f64),
        ("cutsim_achieved_rate_hertz", "gauge", "Steps per second over the last second.", |s| s.frame.load().stats.achieved_rate_hz),
        ("cutsim_viewers", "gauge", "WebSocket viewers attached.", |s| f64::from(s.viewers.load(Ordering::Relaxed))),
        ("cutsim_haptic_clients", "gauge", "Haptic streams attached.", |s| s.subscribers.count() as f64),
        ("cutsim_session_bytes_sent_total", "counter", "Bytes sent to this session's viewers.", |s| s.bytes_sent.load(Ordering::Relaxed) as f64),
        ("cutsim_recording_lost_events_total", "counter", "Recording events lost (full ring or failed writes).", |s| {
            let (lost, errors) = s.recording_losses();
            (lost + errors) as f64
        }),
    ];
    for (name, kind, help, value) in per_session {
        family(name, kind, help, &mut out);
        for s in &sessions {
            let _ = writeln!(out, "{name}{{session=\"{}\"}} {}", s.id, value(s));
        }
    }
    out
}
