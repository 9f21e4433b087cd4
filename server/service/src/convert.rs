//! Between the simulation's types and the wire's (cutsim.v1), and the validation of
//! what clients send: every message is checked into a domain value before it reaches a
//! session (no unchecked optional fields).

use cutsim_proto::v1 as pb;
use cutsim_sim::assessment::Assessment;
use cutsim_sim::hash::hash_hex;
use cutsim_sim::math::{Pose, Vec3, quat_from_wxyz};
use cutsim_sim::runner::{Progress, RunReport};
use cutsim_sim::surface::{SurfaceSnapshot, TopologyDelta};
use cutsim_sim::tissue::TissueCounters;
use cutsim_sim::tool::ToolCommand;

use crate::error::ApiError;
use crate::session::assessing::TaskInfo;
use crate::session::hub::{Frame, StepStats};
use crate::session::records::StampedCommand;
use crate::session::{Mode, Session, Status};

pub fn vec3(v: &Vec3) -> pb::Vec3 {
    pb::Vec3 { x: v.x, y: v.y, z: v.z }
}

pub fn pose(p: &Pose) -> pb::Pose {
    let q = p.orientation.quaternion();
    pb::Pose { position_m: Some(vec3(&p.position_m)), orientation: Some(pb::Quaternion { w: q.w, x: q.i, y: q.j, z: q.k }) }
}

pub fn status(s: Status) -> pb::SessionStatus {
    match s {
        Status::Running => pb::SessionStatus::Running,
        Status::Idle => pb::SessionStatus::Idle,
        Status::RunningScript => pb::SessionStatus::RunningScript,
        Status::Closed => pb::SessionStatus::Closed,
        Status::Degraded => pb::SessionStatus::Degraded,
        Status::Failed => pb::SessionStatus::Failed,
    }
}

pub fn mode(m: Mode) -> pb::SessionMode {
    match m {
        Mode::Realtime => pb::SessionMode::Realtime,
        Mode::Lockstep => pb::SessionMode::Lockstep,
        Mode::Replay => pb::SessionMode::Replay,
    }
}

pub fn playback(p: &Option<crate::session::hub::PlaybackState>, session: &Session) -> Option<pb::Playback> {
    p.map(|p| pb::Playback {
        step: p.step,
        total_steps: p.total_steps,
        playing: p.playing,
        speed: p.speed,
        recorded_session: session.label.strip_prefix("replay of ").unwrap_or_default().to_owned(),
    })
}

pub fn stats(s: &StepStats) -> pb::StepStats {
    pb::StepStats {
        p50_us: s.p50_us,
        p99_us: s.p99_us,
        max_us: s.max_us,
        steps: s.steps,
        missed_deadlines: s.missed_deadlines,
        achieved_rate_hz: s.achieved_rate_hz,
    }
}

pub fn counters(c: &TissueCounters, pieces: u64) -> pb::TissueCounters {
    pb::TissueCounters {
        nodes: c.nodes,
        elements: c.elements,
        surface_vertices: c.surface_vertices,
        surface_triangles: c.surface_triangles,
        cuts: c.cuts,
        cut_updates: c.cut_updates,
        removed_elements: c.removed_elements,
        incision_length_m: c.incision_length_m,
        reconstruction_fallbacks: c.reconstruction_fallbacks,
        uncut_last_pieces: c.uncut_last_pieces,
        blowups_contained: c.blowups_contained,
        stability_adjustments: c.stability_adjustments,
        force_clamps: c.force_clamps,
        rejected_poses: c.rejected_poses,
        pieces,
        solves: c.solves,
        solver_iterations: c.solver_iterations,
        solver_cap_hits: c.solver_cap_hits,
        solver_max_residual: c.solver_max_residual,
        solver_last_residual: c.solver_last_residual,
        solver_waits: c.solver_waits,
        solver_factor_failures: c.solver_factor_failures,
    }
}

pub fn cut_fallback(f: &cutsim_sim::tissue::CutFallback) -> pb::CutFallback {
    pb::CutFallback { step: f.step, reason: f.reason.clone() }
}

/// The metrics in the API's form; `problem`: what the assessor missed.
pub fn assessment(a: &Assessment, problem: String, task: &TaskInfo) -> pb::Assessment {
    pb::Assessment {
        steps: a.steps,
        has_plan: a.has_plan,
        started_s: a.started_s,
        completed: a.completed,
        time_to_complete_s: a.time_to_complete_s,
        incision_length_mm: a.incision_length_mm,
        plan_length_mm: a.plan_length_mm,
        coverage: a.coverage,
        deviation_rms_mm: a.deviation_rms_mm,
        deviation_max_mm: a.deviation_max_mm,
        outside_band_mm: a.outside_band_mm,
        depth_error_rms_mm: a.depth_error_rms_mm,
        strokes: a.strokes,
        path_length_mm: a.path_length_mm,
        economy_of_motion: a.economy_of_motion,
        peak_force_n: a.peak_force_n,
        mean_force_n: a.mean_force_n,
        time_above_force_limit_s: a.time_above_force_limit_s,
        peak_grip_force_n: a.peak_grip_force_n,
        time_above_grip_limit_s: a.time_above_grip_limit_s,
        jerk_rms_m_per_s3: a.jerk_rms_m_per_s3,
        log_dimensionless_jerk: a.log_dimensionless_jerk,
        no_go_entries: a.no_go_entries,
        no_go_time_s: a.no_go_time_s,
        score: a.score,
        passed: a.passed,
        failures: a.failures.clone(),
        events: a
            .events
            .iter()
            .map(|e| pb::AssessmentEvent { step: e.step, time_s: e.time_s, kind: e.kind.clone(), message: e.message.clone() })
            .collect(),
        events_dropped: a.events_dropped,
        problem,
        task: task.description.clone(),
        plan_points_m: task.plan_points_m.clone(),
        band_mm: task.band_mm,
    }
}

/// A session's newest published metrics.
pub fn session_assessment(s: &Session) -> pb::Assessment {
    assessment(&s.assessment.load(), s.assessment.problem(), &s.assessment.task)
}

/// A session as the API describes it (from its newest frame).
pub fn session_info(s: &Session) -> pb::SessionInfo {
    let frame = s.frame.load();
    pb::SessionInfo {
        assessment: Some(session_assessment(s)),
        id: s.id.clone(),
        label: s.label.clone(),
        scene: s.scene_name.clone(),
        model: s.model.to_owned(),
        fidelity: s.fidelity.clone(),
        deformation_rate_hz: s.deformation_rate_hz,
        recording_problem: s.recording_problem().unwrap_or_default(),
        mode: mode(s.mode) as i32,
        status: status(if s.failure().is_some() {
            Status::Failed
        } else if s.is_closed() {
            Status::Closed
        } else {
            frame.status
        }) as i32,
        failure: s.failure().unwrap_or_default().to_owned(),
        rate_hz: s.rate_hz,
        age_s: s.age_s(),
        step: frame.total_steps,
        stats: Some(stats(&frame.stats)),
        viewers: s.viewers.load(std::sync::atomic::Ordering::Relaxed),
        haptic_clients: s.subscribers.count() as u32,
        topology_version: frame.topology_version,
        counters: Some(counters(&frame.counters, frame.pieces)),
        fallbacks: frame.fallbacks.iter().map(cut_fallback).collect(),
        tools: s
            .tools
            .iter()
            .map(|t| {
                let (width_m, thickness_m, jaw_opening_m) = match t.section {
                    cutsim_sim::tool::Section::Round => (0.0, 0.0, 0.0),
                    cutsim_sim::tool::Section::Plate { half_width_m, half_thickness_m } => (2.0 * half_width_m, 2.0 * half_thickness_m, 0.0),
                    cutsim_sim::tool::Section::Jaws { half_width_m, half_thickness_m, half_gap_m, .. } => (2.0 * half_width_m, 2.0 * half_thickness_m, 2.0 * half_gap_m),
                };
                pb::ToolInfo {
                    name: t.name.clone(),
                    radius_m: t.radius_m,
                    length_m: t.length_m,
                    can_cut: t.can_cut,
                    max_force_n: t.max_force_n,
                    width_m,
                    thickness_m,
                    edge: Some(vec3(&t.edge_local)),
                    round_tip: t.tip_shape == cutsim_sim::tool::TipShape::Round,
                    jaw_opening_m,
                }
            })
            .collect(),
        state_hash: String::new(),
        state_hash_step: 0,
        bounds_min_m: Some(vec3(&s.bounds.0)),
        bounds_max_m: Some(vec3(&s.bounds.1)),
        playback: playback(&frame.playback, s),
    }
}

pub fn snapshot(s: &SurfaceSnapshot, session_id: &str, step: u64) -> pb::Snapshot {
    pb::Snapshot {
        session_id: session_id.to_owned(),
        version: s.version,
        step,
        vertex_ids: s.vertices.iter().map(|v| v.id).collect(),
        positions_m: s.vertices.iter().flat_map(|v| v.position_m).collect(),
        materials: s.vertices.iter().map(|v| u32::from(v.material)).collect(),
        triangle_ids: s.triangles.iter().map(|t| t.id).collect(),
        triangle_vertices: s.triangles.iter().flat_map(|t| t.vertices).collect(),
        surface_hash: hash_hex(s.surface_hash()),
    }
}

pub fn delta(d: &TopologyDelta, step: u64) -> pb::TopologyDelta {
    pb::TopologyDelta {
        version: d.version,
        step,
        removed_triangle_ids: d.removed_triangles.clone(),
        removed_vertex_ids: d.removed_vertices.clone(),
        added_vertex_ids: d.added_vertices.iter().map(|v| v.id).collect(),
        added_positions_m: d.added_vertices.iter().flat_map(|v| v.position_m).collect(),
        added_materials: d.added_vertices.iter().map(|v| u32::from(v.material)).collect(),
        added_triangle_ids: d.added_triangles.iter().map(|t| t.id).collect(),
        added_triangle_vertices: d.added_triangles.iter().flat_map(|t| t.vertices).collect(),
    }
}

pub fn delta_frame(d: &TopologyDelta, step: u64) -> pb::ViewerFrame {
    pb::ViewerFrame { frame: Some(pb::viewer_frame::Frame::Delta(delta(d, step))) }
}

pub fn tool_states(frame: &Frame) -> pb::ToolStates {
    pb::ToolStates {
        step: frame.total_steps,
        server_time_ns: frame.session_time_ns,
        tools: frame
            .tools
            .iter()
            .enumerate()
            .map(|(i, t)| pb::ToolState {
                tool: i as u32,
                active: t.command.active,
                cut: t.command.cut,
                pose: Some(pose(&t.command.pose)),
                force_n: Some(vec3(&t.feedback.force_n)),
                contacts: t.feedback.contacts,
                cutting: t.feedback.cutting,
                jaws_gap_m: t.jaws_half_gap_m.map(|h| 2.0 * h),
                grasping: t.feedback.grasping,
                jaws_force_n: t.jaws_half_gap_m.map(|_| t.feedback.jaws_force_n),
            })
            .collect(),
    }
}

pub fn progress(p: &Progress) -> pb::ScriptProgress {
    pb::ScriptProgress { step: p.step, total_steps: p.total, cuts: p.cuts, max_tool_force_n: p.max_tool_force_n }
}

/// A script's report, with the session's task.
pub fn report(r: &RunReport, task: &TaskInfo) -> pb::ScriptReport {
    pb::ScriptReport {
        scene: r.scene.clone(),
        model: r.model.clone(),
        steps: r.steps,
        simulated_time_s: r.simulated_time_s,
        cuts: r.cuts,
        cut_updates: r.cut_updates,
        removed_elements: r.removed_elements,
        removed_triangles: r.removed_triangles,
        incision_length_m: r.incision_length_m,
        pieces: r.pieces,
        reconstruction_fallbacks: r.reconstruction_fallbacks,
        max_tool_force_n: r.max_tool_force_n,
        step_time_p50_us: r.step_time_p50_us,
        step_time_p99_us: r.step_time_p99_us,
        step_time_max_us: r.step_time_max_us,
        wall_time_s: r.wall_time_s,
        steps_per_second: r.steps_per_second,
        surface_vertices: r.surface_vertices,
        surface_triangles: r.surface_triangles,
        topology_version: r.topology_version,
        state_hash: r.state_hash.clone(),
        expectations: r
            .expectations
            .iter()
            .map(|e| pb::ExpectationResult { name: e.name.clone(), expected: e.expected.clone(), actual: e.actual.clone(), passed: e.passed })
            .collect(),
        passed: r.passed,
        counters: Some(counters(&r.counters, r.pieces)),
        report_json: serde_json::to_string(r).unwrap_or_default(),
        assessment: Some(assessment(&r.assessment, String::new(), task)),
        tools: r.tools.iter().map(|t| pb::ToolForceReport { name: t.name.clone(), max_force_n: t.max_force_n, grasping_s: t.grasping_s, max_jaws_force_n: t.max_jaws_force_n }).collect(),
        fallbacks: r.fallbacks.iter().map(cut_fallback).collect(),
    }
}

/// Checks a client's tool command into a stamped command for the physics thread.
pub fn tool_command(c: &pb::ToolCommand, session: &Session, received_ns: u64, margin_m: f64) -> Result<(usize, StampedCommand), ApiError> {
    let tool = c.tool as usize;
    if tool >= session.tools.len() {
        return Err(ApiError::InvalidArgument(format!(
            "tool {} does not exist; the scene has tools 0 to {} ({})",
            c.tool,
            session.tools.len().saturating_sub(1),
            session.tools.iter().map(|t| t.name.as_str()).collect::<Vec<_>>().join(", ")
        )));
    }
    let pose = c.pose.as_ref().ok_or_else(|| ApiError::InvalidArgument("pose is required".into()))?;
    let p = pose.position_m.as_ref().ok_or_else(|| ApiError::InvalidArgument("pose.position_m is required".into()))?;
    let q = pose.orientation.as_ref().ok_or_else(|| ApiError::InvalidArgument("pose.orientation is required".into()))?;
    let position = Vec3::new(p.x, p.y, p.z);
    if !position.iter().all(|v| v.is_finite()) {
        return Err(ApiError::InvalidArgument(format!("pose.position_m must be finite, got ({}, {}, {})", p.x, p.y, p.z)));
    }
    let norm = (q.w * q.w + q.x * q.x + q.y * q.y + q.z * q.z).sqrt();
    if !norm.is_finite() || (norm - 1.0).abs() > 1e-3 {
        return Err(ApiError::InvalidArgument(format!(
            "pose.orientation must be a unit quaternion (w, x, y, z); its norm is {norm}"
        )));
    }
    let (lo, hi) = (session.bounds.0.add_scalar(-margin_m), session.bounds.1.add_scalar(margin_m));
    if (0..3).any(|k| position[k] < lo[k] || position[k] > hi[k]) {
        return Err(ApiError::InvalidArgument(format!(
            "pose.position_m ({:.3}, {:.3}, {:.3}) m is more than {margin_m} m outside the tissue, which spans ({:.3}, {:.3}, {:.3}) to ({:.3}, {:.3}, {:.3}) m",
            p.x, p.y, p.z, session.bounds.0.x, session.bounds.0.y, session.bounds.0.z, session.bounds.1.x, session.bounds.1.y, session.bounds.1.z
        )));
    }
    if let Some(message) = c.grip.and_then(cutsim_sim::tool::grip_error) {
        return Err(ApiError::InvalidArgument(format!("grip of tool {} ({}): {message}", c.tool, session.tools[tool].name)));
    }
    let command = ToolCommand { pose: Pose::new(position, quat_from_wxyz(q.w, q.x, q.y, q.z)), active: c.active, cut: c.cut, grip: c.grip };
    Ok((tool, StampedCommand { command, client_time_ns: c.client_time_ns, received_ns, feedback_every: c.feedback_every_steps.max(1) }))
}
