//! Forceps' jaws as bodies of their own.
//!
//! Both tissue models' contact (the skin's hold, tip-face hold, sweep between poses and
//! puncture test; the branched grid's vertex and triangle holds) works on one solid per
//! tool: a disc or a plate around its axis. Forceps have two jaws with a gap between
//! them, where the tissue may rise. So a model takes each jaw as a body of its own, a
//! plate on its side of the forceps' axis, its inner flat half the opening from the
//! axis; while the button closes them the first jaw is the two as one plate on the axis
//! and the second is away (two touching plates would leave a seam where the tissue
//! slips in between). A forceps' command is split into its jaws' commands, and the jaws'
//! feedback is summed back into the forceps' (the torque taken about the forceps' tip),
//! clamped at its limit. Every other tool is one body, passed through as it is.
//! Closing jaws stop where a model tells them: on the skin's fold (crate::msm::grasp),
//! or by force on the branched grid ([`Bodies::pinch`]: where what lies between them
//! pushes back with the grip).
//!
//! Nothing here allocates after the model is built: the split and the sum reuse the
//! buffers made at build time.

use crate::math::Vec3;
use crate::tool::{Section, ToolCommand, ToolFeedback, ToolShape};

/// How fast a jaw moves across its flat as the forceps open or close, m/s: the device's
/// jaw is a button, and real forceps open over tens of milliseconds (4 mm in 40 ms here).
/// A jaw that jumped its whole travel in one step would land under the skin beside it
/// instead of pushing it aside.
pub const JAW_SPEED_M_PER_S: f64 = 0.1;

/// How long jaws stopped on what they pinch may press nothing under either inner flat
/// before it counts as slipped out, s ([`Bodies::pinch`]): long enough for a contact
/// that passes from one vertex to the next (a step or two with none under one jaw while
/// a grasp holds), short against the 40 ms the jaws take to close.
pub const SLIPPED_OUT_AFTER_S: f64 = 0.01;

/// A jaw pinching what lies between the jaws ([`Bodies::pinched`]).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pinch {
    /// The direction its inner flat presses (towards the other jaw), in the tool's frame.
    pub inward_local: Vec3,
    /// The grip it presses with, N.
    pub grip_n: f64,
    /// How far from the tip along the axis it grips, m (the forceps' `grip_length_m`:
    /// tissue forceps grip with their serrated tips).
    pub grip_length_m: f64,
}

/// One of a forceps' jaws as a body.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Jaw {
    /// 0 or 1: the jaw on the −normal or the +normal side (the flat's normal: axis × edge).
    side: usize,
    half_width_m: f64,
    half_thickness_m: f64,
}

impl Jaw {
    /// This jaw's plate and its centre's offset along the flat's normal, m, with the
    /// jaws' inner flats `2 half_gap_m` apart; None for the second jaw of closed forceps
    /// (`half_gap_m` 0): closed, the first jaw is the two as one plate (the seam between
    /// two touching plates would let the skin in between them).
    fn placed(&self, half_gap_m: f64) -> Option<(Section, f64)> {
        let Jaw { side, half_width_m, half_thickness_m } = *self;
        if half_gap_m > 0.0 {
            let offset = (half_gap_m + half_thickness_m) * if side == 0 { -1.0 } else { 1.0 };
            Some((Section::Plate { half_width_m, half_thickness_m }, offset))
        } else {
            (side == 0).then_some((Section::Plate { half_width_m, half_thickness_m: 2.0 * half_thickness_m }, 0.0))
        }
    }
}

/// A body: its tool, and for a jaw which one.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Body {
    tool: usize,
    jaw: Option<Jaw>,
}

/// The bodies of a model whose tools include forceps.
#[derive(Debug, Clone)]
pub(crate) struct Bodies {
    of: Vec<Body>,
    /// Per tool: its jaws' half gap now and open, m (0, 0 for a tool without jaws).
    half_gap_m: Vec<(f64, f64)>,
    /// Per tool: how fast its jaws open and close, m/s ([`JAW_SPEED_M_PER_S`] unless a
    /// multirate schedule slows them: [`Bodies::pace_jaws_for`]).
    jaw_speed_m_per_s: Vec<f64>,
    /// Per tool: the half gap at which closing jaws stop, m (0: they close fully; the
    /// skin's grasp stops them on the fold between them, crate::msm::grasp, and the
    /// grid's pinch on what pushes them back, [`Bodies::pinch`]).
    closed_half_gap_m: Vec<f64>,
    /// Per tool: its button closes its jaws this step, and they have met something
    /// between them since it was pressed ([`Bodies::pinch`]).
    closing: Vec<bool>,
    met: Vec<bool>,
    /// Per tool: how long its jaws, stopped on what they pinch, have pressed nothing
    /// under either inner flat, s ([`Bodies::pinch`]: past [`SLIPPED_OUT_AFTER_S`] what
    /// they held has slipped out).
    empty_s: Vec<f64>,
    /// Per tool: the force the hand pinches its jaws with this step, N (its command's
    /// share of the forceps' `grip_force_n`: [`ToolCommand::grip_n`]).
    grip_n: Vec<f64>,
    /// Where [`Bodies::pinch`] stops jaws that have met something at the latest, m;
    /// None: it does not stop them ([`Bodies::pinch_no_closer_than`]).
    least_pinch_half_gap_m: Option<f64>,
    /// Per body: its centre's offset from its tool's tip this step (world frame); None
    /// while it is away (the second jaw of closed forceps).
    arm: Vec<Option<Vec3>>,
    pub commands: Vec<ToolCommand>,
    pub feedback: Vec<ToolFeedback>,
}

/// The bodies of `tools` (a forceps' two jaws, every other tool as itself): their
/// shapes (a jaw's section is set each step by [`Bodies::split`]), and the split between
/// them; None where no tool has jaws (the bodies are the tools). Forceps start open.
pub(crate) fn expand(tools: &[ToolShape]) -> (Vec<ToolShape>, Option<Bodies>) {
    if !tools.iter().any(|t| matches!(t.section, Section::Jaws { .. })) {
        return (tools.to_vec(), None);
    }
    let (mut shapes, mut of, mut half_gap_m) = (Vec::new(), Vec::new(), Vec::new());
    for (tool, shape) in tools.iter().enumerate() {
        let Section::Jaws { half_width_m, half_thickness_m, half_gap_m: open, .. } = shape.section else {
            shapes.push(shape.clone());
            of.push(Body { tool, jaw: None });
            half_gap_m.push((0.0, 0.0));
            continue;
        };
        half_gap_m.push((open, open));
        for side in 0..2 {
            let jaw = Jaw { side, half_width_m, half_thickness_m };
            let (section, _) = jaw.placed(open).expect("an open jaw is placed");
            // Bounds the jaw open and the closed plate.
            shapes.push(ToolShape { radius_m: half_width_m.hypot(2.0 * half_thickness_m), section, ..shape.clone() });
            of.push(Body { tool, jaw: Some(jaw) });
        }
    }
    let n = of.len();
    let jaw_speed_m_per_s = vec![JAW_SPEED_M_PER_S; tools.len()];
    let closed_half_gap_m = vec![0.0; tools.len()];
    let (closing, met, grip_n) = (vec![false; tools.len()], vec![false; tools.len()], vec![0.0; tools.len()]);
    let empty_s = vec![0.0; tools.len()];
    (shapes, Some(Bodies { of, half_gap_m, jaw_speed_m_per_s, closed_half_gap_m, closing, met, empty_s, grip_n, least_pinch_half_gap_m: None, arm: vec![None; n], commands: vec![ToolCommand::default(); n], feedback: vec![ToolFeedback::default(); n] }))
}

impl crate::hash::HashState for Bodies {
    /// The jaws' state and what the next step's pinch reads: each body's last feedback
    /// and where it was.
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        let Self { of: _, half_gap_m, jaw_speed_m_per_s: _, closed_half_gap_m, closing, met, empty_s, grip_n, least_pinch_half_gap_m: _, arm, commands: _, feedback } = self;
        (half_gap_m, closed_half_gap_m).hash_state(h);
        (closing, met).hash_state(h);
        // Only while a stopped grasp presses nothing (the grid's jaws), so that hashes
        // where that never happens (every skin session) stay as they were.
        for (tool, empty_s) in empty_s.iter().enumerate().filter(|(_, s)| **s != 0.0) {
            (tool, *empty_s).hash_state(h);
        }
        (grip_n, arm).hash_state(h);
        feedback.hash_state(h);
    }
}

impl Bodies {
    /// Slows every forceps' jaws so that they move at most `travel_m` in a deformation
    /// step of `period_s` (a multirate schedule's, crate::multirate): the deformation
    /// meets the jaws only at its steps, and jaws that moved far between two of them
    /// passed the tissue they were closing on instead of pushing it aside.
    pub fn pace_jaws_for(&mut self, period_s: f64, travel_m: f64) {
        for (speed, (open, _)) in self.jaw_speed_m_per_s.iter_mut().zip(&self.half_gap_m) {
            if *open > 0.0 {
                *speed = JAW_SPEED_M_PER_S.min(travel_m / period_s);
            }
        }
    }

    /// Makes [`Bodies::pinch`] stop closing jaws (it does nothing until then), at the
    /// latest with their inner flats `2 least_half_gap_m` apart once they have met
    /// something.
    pub fn pinch_no_closer_than(&mut self, least_half_gap_m: f64) {
        self.least_pinch_half_gap_m = Some(least_half_gap_m);
    }

    /// Tool `tool`'s jaws' half gap now, m (0 for a tool without jaws, and for closed
    /// forceps).
    pub fn half_gap_m(&self, tool: usize) -> f64 {
        self.half_gap_m[tool].0
    }

    /// Where tool `tool`'s jaws stop closing from the next step on: their inner flats
    /// `2 half_gap_m` apart (0: touching). Jaws already closer stay where they are.
    pub fn stop_closing_at(&mut self, tool: usize, half_gap_m: f64) {
        self.closed_half_gap_m[tool] = half_gap_m;
    }

    /// Jaws closed by force, not to a place (the branched grid's grasp): the hand pinches
    /// them with its grip (the forceps' `grip_force_n`, or the share of it the command
    /// squeezes with: [`ToolCommand::grip_n`]), so closing jaws stop where what lies
    /// between them pushes each jaw back as hard (its outward force in the last step's
    /// feedback, `self.feedback`), and no closer than [`Bodies::pinch_no_closer_than`]
    /// once they have met something between them (a model's contact cannot hold a layer
    /// thinner than its resolution: the grid's vertices pass the jaws' flats). They stay
    /// there until the button is released, or until what they pinched has slipped out
    /// from between them: by `inner_flat_contacts` (per body, the contacts its inner
    /// flat pressed in the model's last step where it pinched, None where unknown: the
    /// branched grid counts them), jaws stopped on tissue whose inner flats both press
    /// nothing for [`SLIPPED_OUT_AFTER_S`] forget the stop and close on, as when they
    /// met nothing. (Their outward force cannot
    /// tell: the tissue outside the jaws pushes them in, and stopped on a fold they felt
    /// no net outward force for up to 0.2 s while holding it.) Meeting nothing, they
    /// close fully, as ever. The skin's jaws stop at one thickness of it instead
    /// (crate::msm::grasp).
    pub fn pinch(&mut self, tools: &[ToolShape], inner_flat_contacts: &[Option<u32>], dt_s: f64) {
        let Some(least_half_gap_m) = self.least_pinch_half_gap_m else { return };
        for (tool, shape) in tools.iter().enumerate() {
            if !matches!(shape.section, Section::Jaws { .. }) {
                continue;
            }
            let now = self.half_gap_m[tool].0;
            if self.holding(tool) {
                // Nothing under either flat only where both counts are known.
                let (jaws, empty_flats) = self.of.iter().zip(inner_flat_contacts).filter(|(body, _)| body.tool == tool && body.jaw.is_some()).fold((0, 0), |(jaws, empty), (_, &n)| (jaws + 1, empty + usize::from(n == Some(0))));
                let empty = jaws > 0 && empty_flats == jaws;
                self.empty_s[tool] = if empty { self.empty_s[tool] + dt_s } else { 0.0 };
                if self.empty_s[tool] >= SLIPPED_OUT_AFTER_S - 1e-12 {
                    self.closed_half_gap_m[tool] = 0.0;
                    self.met[tool] = false;
                    self.empty_s[tool] = 0.0;
                }
                continue;
            }
            if !self.closing[tool] || self.closed_half_gap_m[tool] > 0.0 || now <= 0.0 {
                continue;
            }
            let squeeze = self.squeeze_n(tool);
            self.met[tool] |= squeeze > 0.0;
            if squeeze >= self.grip_n[tool] || self.met[tool] && now <= least_half_gap_m + 1e-9 {
                self.closed_half_gap_m[tool] = now;
            }
        }
    }

    /// Whether tool `tool`'s jaws are closing and have stopped on what lies between them
    /// (the skin's fold, crate::msm::grasp, or the grid's pinch, [`Bodies::pinch`]).
    fn holding(&self, tool: usize) -> bool {
        self.closing[tool] && self.closed_half_gap_m[tool] > 0.0 && self.half_gap_m[tool].0 <= self.closed_half_gap_m[tool]
    }

    /// Whether tool `tool`'s jaws are closing on something: from the step they meet what
    /// lies between them (the skin's fold taken, crate::msm::grasp, which sets where they
    /// stop; the grid's tissue pushing them back, [`Bodies::pinch`]) until the button is
    /// released. The closing counts: the coupling of a haptic device swung the proxy
    /// along the jaws' edge as they closed, and tore the fold out (docs/haptic-bridge.md).
    fn grasping(&self, tool: usize) -> bool {
        self.closing[tool] && (self.met[tool] || self.closed_half_gap_m[tool] > 0.0)
    }

    /// Body `body`'s pinch, if it is a jaw of forceps stopped on what they pinch
    /// ([`Bodies::pinch`]): the direction its inner flat presses (towards the other jaw,
    /// in the tool's frame) and the grip it presses with, N. The tissue's friction under
    /// the jaws takes its normal force from the grip, not from how far the jaws sank in.
    pub fn pinched(&self, body: usize, tools: &[ToolShape]) -> Option<Pinch> {
        let Body { tool, jaw } = self.of[body];
        let jaw = jaw?;
        let Section::Jaws { grip_length_m, .. } = tools[tool].section else { return None };
        if !self.holding(tool) {
            return None;
        }
        let inward = Vec3::z().cross(&tools[tool].edge_local) * if jaw.side == 0 { 1.0 } else { -1.0 };
        Some(Pinch { inward_local: inward, grip_n: self.grip_n[tool], grip_length_m })
    }

    /// Every body's pinch ([`Bodies::pinched`]) into `out`, one per body.
    pub fn pinches(&self, tools: &[ToolShape], out: &mut [Option<Pinch>]) {
        for (body, pinch) in out.iter_mut().enumerate() {
            *pinch = self.pinched(body, tools);
        }
    }

    /// How hard what lies between tool `tool`'s jaws pushes them apart, N: the lesser of
    /// the two jaws' outward forces in the last step's feedback (0 while closed).
    fn squeeze_n(&self, tool: usize) -> f64 {
        let outward = |(body, (feedback, arm)): (&Body, (&ToolFeedback, &Option<Vec3>))| {
            if body.tool != tool || body.jaw.is_none() {
                return None;
            }
            Some(arm.and_then(|a| a.try_normalize(1e-12)).map_or(0.0, |out| feedback.force_n.dot(&out)))
        };
        let least = self.of.iter().zip(self.feedback.iter().zip(&self.arm)).filter_map(outward).fold(f64::INFINITY, f64::min);
        if least.is_finite() { least.max(0.0) } else { 0.0 }
    }

    /// How hard what lies between tool `tool`'s jaws pushes them apart, N
    /// ([`ToolFeedback::jaws_force_n`]): jaws stopped on it are closed by force and pinch
    /// with the grip, which it pushes back with; jaws closing push it aside against the
    /// lesser of their outward forces in the last step ([`Bodies::squeeze_n`], none on
    /// the skin, whose jaws stop on its fold at once), never more than the grip.
    fn jaws_force_n(&self, tool: usize) -> f64 {
        if self.holding(tool) {
            self.grip_n[tool]
        } else if self.closing[tool] && self.met[tool] {
            self.squeeze_n(tool).min(self.grip_n[tool])
        } else {
            0.0
        }
    }

    /// Tool `tool`'s jaws' half gap now, m (None for a tool without jaws).
    pub fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        self.first_jaw(tool).map(|_| self.half_gap_m(tool))
    }

    /// The body of tool `tool`'s first jaw (the one that is the closed plate), if it
    /// has jaws.
    pub fn first_jaw(&self, tool: usize) -> Option<usize> {
        self.of.iter().position(|b| b.tool == tool && b.jaw.is_some_and(|j| j.side == 0))
    }

    /// The bodies' commands from the tools' (`tools`: the scene's shapes) for a step of
    /// `dt_s`, and the jaws' sections in `shapes` (the bodies' shapes): a forceps' jaws
    /// move towards closed (or the half gap they stop at: [`Bodies::stop_closing_at`])
    /// while its button is held with some squeeze ([`ToolCommand::closes_jaws`]), else
    /// towards open, at their speed
    /// ([`JAW_SPEED_M_PER_S`] unless paced: [`Bodies::pace_jaws_for`]).
    pub fn split(&mut self, commands: &[ToolCommand], tools: &[ToolShape], shapes: &mut [ToolShape], dt_s: f64) {
        for (tool, (((command, (now, open)), speed), closed)) in commands.iter().zip(self.half_gap_m.iter_mut()).zip(&self.jaw_speed_m_per_s).zip(self.closed_half_gap_m.iter_mut()).enumerate() {
            // Released, the jaws forget where they stopped ([`Bodies::pinch`]).
            let close = command.closes_jaws();
            self.closing[tool] = close && *open > 0.0;
            self.grip_n[tool] = match tools[tool].section {
                Section::Jaws { grip_force_n, .. } => command.grip_n(grip_force_n),
                _ => 0.0,
            };
            if !close {
                self.met[tool] = false;
                self.empty_s[tool] = 0.0;
                *closed = 0.0;
            }
            let target = match close {
                true if *now <= *closed => *now,
                true => closed.min(*open),
                false => *open,
            };
            let travel = speed * dt_s;
            // Snapped to the target within a nanometre (steps of the travel do not sum
            // exactly to it).
            *now = if (target - *now).abs() <= travel + 1e-9 { target } else { *now + travel.copysign(target - *now) };
        }
        for (k, body) in self.of.iter().enumerate() {
            let command = &commands[body.tool];
            let out = &mut self.commands[k];
            *out = *command;
            self.arm[k] = match body.jaw {
                None => Some(Vec3::zeros()),
                Some(jaw) => jaw.placed(self.half_gap_m[body.tool].0).map(|(section, along_normal)| {
                    shapes[k].section = section;
                    let normal_local = Vec3::z().cross(&tools[body.tool].edge_local);
                    command.pose.orientation * (normal_local * along_normal)
                }),
            };
            match self.arm[k] {
                Some(arm) => out.pose.position_m += arm,
                None => out.active = false,
            }
            // A jaw cuts nothing; its tool's button closes the jaws.
            if body.jaw.is_some() {
                out.cut = false;
            }
        }
    }

    /// The tools' feedback from the bodies': forces, resistance and contacts summed, the
    /// torque about the tool's tip, clamped at the tool's limit. Returns how many tools
    /// the sum clamped where no body of theirs was (each body's own clamp is counted where
    /// it is made).
    pub fn gather(&self, tools: &[ToolShape], feedback: &mut [ToolFeedback]) -> u64 {
        for fb in feedback.iter_mut() {
            *fb = ToolFeedback::default();
        }
        for ((body, part), arm) in self.of.iter().zip(&self.feedback).zip(&self.arm) {
            let Some(arm) = arm else { continue };
            let fb = &mut feedback[body.tool];
            fb.force_n += part.force_n;
            fb.torque_nm += part.torque_nm + arm.cross(&part.force_n);
            fb.resistance_n += part.resistance_n;
            fb.contacts += part.contacts;
            fb.cutting |= part.cutting;
            fb.force_clamped |= part.force_clamped;
        }
        for (tool, fb) in feedback.iter_mut().enumerate() {
            fb.grasping = self.grasping(tool);
            fb.jaws_force_n = self.jaws_force_n(tool);
        }
        let mut clamped = 0;
        for (fb, tool) in feedback.iter_mut().zip(tools) {
            let before = fb.force_clamped;
            fb.clamp_force(tool.max_force_n);
            clamped += u64::from(fb.force_clamped && !before);
        }
        clamped
    }

    /// Per body, the body whose state it takes when it comes back into the scene: the
    /// second jaw of forceps reopening takes the first's (through the skin or holding it,
    /// as the closed jaws were).
    pub fn twins(&self) -> Vec<Option<usize>> {
        self.of.iter().enumerate().map(|(k, b)| b.jaw.filter(|j| j.side == 1).map(|_| k - 1)).collect()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{Pose, Quat};
    use crate::tool::{Section, TipShape};

    fn forceps() -> ToolShape {
        ToolShape {
            name: "forceps".into(),
            radius_m: 1e-3_f64.hypot(4e-3 + 1e-3),
            length_m: 0.08,
            section: Section::Jaws { half_width_m: 1e-3, half_thickness_m: 5e-4, half_gap_m: 4e-3, grip_force_n: 3.0, grip_length_m: 0.01 },
            contact_stiffness_n_per_m: 300.0,
            can_cut: false,
            max_force_n: 3.0,
            cutting_shape: None,
            edge_local: Vec3::x(),
            tip_shape: TipShape::Flat,
        }
    }

    /// Paced for a multirate schedule, the jaws move the travel allowed per deformation
    /// step over each of its periods, and a tool without jaws is untouched.
    #[test]
    fn paced_jaws_move_the_allowed_travel_per_deformation_step() {
        let probe = ToolShape { name: "probe".into(), section: Section::Round, radius_m: 3e-3, ..forceps() };
        let tools = [probe, forceps()];
        let (mut shapes, bodies) = expand(&tools);
        let mut bodies = bodies.expect("forceps make bodies");
        bodies.pace_jaws_for(0.033, 2e-4);
        assert_eq!(bodies.jaw_speed_m_per_s[0], JAW_SPEED_M_PER_S, "a probe has no jaws");
        let close = ToolCommand { pose: Pose::new(Vec3::zeros(), Quat::identity()), active: true, cut: true, grip: None };
        for _ in 0..33 {
            bodies.split(&[close, close], &tools, &mut shapes, 1e-3);
        }
        assert!((bodies.half_gap_m[1].0 - (4e-3 - 2e-4)).abs() < 1e-12, "{:?}", bodies.half_gap_m[1]);
        // Slower than the jaws' own speed only: a long travel leaves them at it.
        bodies.pace_jaws_for(0.033, 1.0);
        assert_eq!(bodies.jaw_speed_m_per_s[1], JAW_SPEED_M_PER_S);
    }

    /// Jaws told to stop closing at a half gap (the skin's grasp: crate::msm::grasp) stop
    /// there, stay where they are if already closer, and open as ever when the button is
    /// released.
    #[test]
    fn closing_jaws_stop_where_they_are_told() {
        let tools = [forceps()];
        let (mut shapes, bodies) = expand(&tools);
        let mut bodies = bodies.unwrap();
        let close = ToolCommand { pose: Pose::new(Vec3::zeros(), Quat::identity()), active: true, cut: true, grip: None };
        bodies.stop_closing_at(0, 1e-3);
        for _ in 0..100 {
            bodies.split(&[close], &tools, &mut shapes, 1e-3);
        }
        assert!((bodies.half_gap_m(0) - 1e-3).abs() < 1e-12, "{}", bodies.half_gap_m(0));
        assert_eq!(shapes[0].section, Section::Plate { half_width_m: 1e-3, half_thickness_m: 5e-4 }, "two jaws, not the closed plate");
        assert!(bodies.commands[1].active);
        bodies.stop_closing_at(0, 2e-3);
        bodies.split(&[close], &tools, &mut shapes, 1e-3);
        assert!((bodies.half_gap_m(0) - 1e-3).abs() < 1e-12, "closer already: they stay");
        bodies.stop_closing_at(0, 0.0);
        bodies.split(&[close], &tools, &mut shapes, 1e-3);
        assert!((bodies.half_gap_m(0) - 9e-4).abs() < 1e-12, "let go: they close on");
        bodies.split(&[ToolCommand { cut: false, ..close }], &tools, &mut shapes, 1e-3);
        assert!((bodies.half_gap_m(0) - 1e-3).abs() < 1e-12, "released: they open");
        assert_eq!(bodies.first_jaw(0), Some(0));
    }

    /// Pinching (the branched grid's grasp), closing jaws stop where what is between
    /// them pushes both back with the grip, or at the floor once they have met
    /// something; they stay there while the button is held, and the jaw stopped presses
    /// towards the other with the grip. Meeting nothing, or not told to pinch, they close
    /// fully.
    #[test]
    fn pinching_jaws_stop_on_the_grip_or_at_the_floor_once_they_met_something() {
        let tools = [forceps()];
        let close = ToolCommand { pose: Pose::new(Vec3::zeros(), Quat::identity()), active: true, cut: true, grip: None };
        let open = ToolCommand { cut: false, ..close };
        // Each jaw pushed outward (its arm's way: −y for the first, +y for the second) with `n`.
        let push = |b: &mut Bodies, n: f64| {
            b.feedback[0].force_n = Vec3::new(0.0, -n, 0.1);
            b.feedback[1].force_n = Vec3::new(0.0, n, 0.1);
        };
        let run = |pinching: bool, squeeze_at: &dyn Fn(f64) -> f64| {
            let (mut shapes, bodies) = expand(&tools);
            let mut bodies = bodies.unwrap();
            if pinching {
                bodies.pinch_no_closer_than(5e-4);
            }
            for _ in 0..60 {
                bodies.split(&[close], &tools, &mut shapes, 1e-3);
                let n = squeeze_at(bodies.half_gap_m(0));
                push(&mut bodies, n);
                bodies.pinch(&tools, &[None, None], 1e-3);
            }
            bodies
        };
        // Squeezed 3 N (the grip) from 2 mm on: they stop there.
        let grip = |gap: f64| if gap <= 2e-3 + 1e-9 { 3.0 } else { 0.0 };
        let mut stopped = run(true, &grip);
        assert!((stopped.half_gap_m(0) - 2e-3).abs() < 1e-9, "{}", stopped.half_gap_m(0));
        assert_eq!(stopped.pinched(0, &tools), Some(Pinch { inward_local: Vec3::y(), grip_n: 3.0, grip_length_m: 0.01 }), "the first jaw (−y) presses +y");
        assert_eq!(stopped.pinched(1, &tools).map(|p| p.inward_local), Some(-Vec3::y()));
        // Met something softer: at the floor. Met nothing, or not pinching: closed.
        let soft = run(true, &|gap| if gap <= 2e-3 { 0.2 } else { 0.0 });
        assert!((soft.half_gap_m(0) - 5e-4).abs() < 1e-9, "{}", soft.half_gap_m(0));
        assert_eq!(run(true, &|_| 0.0).half_gap_m(0), 0.0);
        assert_eq!(run(false, &grip).half_gap_m(0), 0.0);
        // Released: they open, forget the stop and the pinch.
        stopped.split(&[open], &tools, &mut expand(&tools).0, 1e-3);
        assert!(stopped.half_gap_m(0) > 2e-3 && stopped.pinched(0, &tools).is_none());
    }

    /// Jaws stopped on what they pinch hold it while either inner flat presses a contact;
    /// once neither has for [`SLIPPED_OUT_AFTER_S`], it has slipped out: they forget the
    /// stop, no longer grasp, and close on.
    #[test]
    fn stopped_jaws_whose_inner_flats_press_nothing_have_lost_their_grasp_and_close() {
        let tools = [forceps()];
        let close = ToolCommand { pose: Pose::new(Vec3::zeros(), Quat::identity()), active: true, cut: true, grip: None };
        let (mut shapes, bodies) = expand(&tools);
        let mut bodies = bodies.unwrap();
        bodies.pinch_no_closer_than(5e-4);
        let mut step = |bodies: &mut Bodies, squeeze: f64, inner_flats: [Option<u32>; 2]| {
            bodies.split(&[close], &tools, &mut shapes, 1e-3);
            bodies.feedback[0].force_n = Vec3::new(0.0, -squeeze, 0.0);
            bodies.feedback[1].force_n = Vec3::new(0.0, squeeze, 0.0);
            bodies.pinch(&tools, &inner_flats, 1e-3);
        };
        // Stopped on the grip about 2 mm from the axis.
        while bodies.half_gap_m(0) > 2e-3 + 1e-9 {
            step(&mut bodies, 0.0, [Some(0), Some(0)]);
        }
        step(&mut bodies, 3.0, [Some(2), Some(1)]);
        let stopped = bodies.half_gap_m(0);
        assert!(stopped > 1e-3 && bodies.grasping(0) && bodies.pinched(0, &tools).is_some());
        // One flat pressing, neither for less than the time, or not known (a step that
        // did not pinch with them): still held (the tissue outside pushes the jaws in: no
        // outward force).
        let (none, one) = (Some(0), Some(1));
        for flats in [[none, one], [one, none], [none, none], [none, none], [Some(3), none], [None, None], [none, None]].into_iter().cycle().take(210) {
            step(&mut bodies, 0.0, flats);
        }
        assert!(bodies.half_gap_m(0) == stopped && bodies.grasping(0));
        // Neither for the time: let go, and close on.
        for _ in 0..(SLIPPED_OUT_AFTER_S / 1e-3).round() as usize {
            step(&mut bodies, 0.0, [Some(0), Some(0)]);
        }
        assert!(!bodies.grasping(0) && bodies.pinched(0, &tools).is_none(), "slipped out: no longer grasping");
        for _ in 0..30 {
            step(&mut bodies, 0.0, [Some(0), Some(0)]);
        }
        assert_eq!(bodies.half_gap_m(0), 0.0, "meeting nothing more, the jaws close fully");
    }

    #[test]
    fn forceps_are_two_plates_either_side_of_the_axis_that_close_on_the_button() {
        let probe = ToolShape { name: "probe".into(), section: Section::Round, radius_m: 3e-3, ..forceps() };
        let tools = [probe.clone(), forceps()];
        let (mut shapes, bodies) = expand(&tools);
        let mut bodies = bodies.expect("forceps make bodies");
        assert_eq!(shapes.len(), 3);
        assert_eq!(shapes[0], probe);
        assert_eq!(shapes[1].section, Section::Plate { half_width_m: 1e-3, half_thickness_m: 5e-4 });
        // Turned a quarter about its axis, the edge faces +y and the flats' normal −x.
        let pose = Pose::new(Vec3::new(0.01, 0.0, 0.0), Quat::from_axis_angle(&Vec3::z_axis(), std::f64::consts::FRAC_PI_2));
        let mut commands = [ToolCommand::default(), ToolCommand { pose, active: true, cut: false, grip: None }];
        let jaw_x = |b: &Bodies, k: usize| b.commands[k].pose.position_m.x;
        bodies.split(&commands, &tools, &mut shapes, 1e-3);
        assert!((jaw_x(&bodies, 1) - 0.0145).abs() < 1e-12 && (jaw_x(&bodies, 2) - 0.0055).abs() < 1e-12, "open: 4.5 mm either side");
        assert!(bodies.commands[1].active && bodies.commands[2].active);
        assert_eq!(bodies.commands[0], commands[0], "the probe as it is");
        // Closing: 0.1 mm a step per jaw, so 40 steps from 4 mm.
        commands[1].cut = true;
        bodies.split(&commands, &tools, &mut shapes, 1e-3);
        assert!((jaw_x(&bodies, 1) - 0.0144).abs() < 1e-12, "{}", jaw_x(&bodies, 1));
        assert!(!bodies.commands[1].cut, "the button closes the jaws, it does not cut");
        for _ in 0..39 {
            bodies.split(&commands, &tools, &mut shapes, 1e-3);
        }
        assert!((jaw_x(&bodies, 1) - 0.01).abs() < 1e-12 && !bodies.commands[2].active, "closed: one plate on the axis");
        assert_eq!(shapes[1].section, Section::Plate { half_width_m: 1e-3, half_thickness_m: 1e-3 });
        assert_eq!(bodies.twins(), vec![None, None, Some(1)]);
        // Reopening: both jaws beside the axis from the first step.
        commands[1].cut = false;
        bodies.split(&commands, &tools, &mut shapes, 1e-3);
        assert_eq!(shapes[1].section, Section::Plate { half_width_m: 1e-3, half_thickness_m: 5e-4 });
        assert!(bodies.commands[2].active && (jaw_x(&bodies, 2) - 0.0094).abs() < 1e-12, "{}", jaw_x(&bodies, 2));
    }

    #[test]
    fn the_jaws_feedback_sums_with_its_torque_about_the_forceps_tip_and_is_clamped() {
        let tools = [forceps()];
        let (mut shapes, bodies) = expand(&tools);
        let mut bodies = bodies.unwrap();
        let commands = [ToolCommand { pose: Pose::new(Vec3::zeros(), Quat::identity()), active: true, cut: false, grip: None }];
        bodies.split(&commands, &tools, &mut shapes, 1e-3);
        // The jaws at y = −4.5 and +4.5 mm pushed up by 1 N and 0.5 N.
        bodies.feedback[0] = ToolFeedback { force_n: Vec3::new(0.0, 0.0, 1.0), contacts: 2, ..Default::default() };
        bodies.feedback[1] = ToolFeedback { force_n: Vec3::new(0.0, 0.0, 0.5), contacts: 1, ..Default::default() };
        let mut feedback = [ToolFeedback::default()];
        bodies.gather(&tools, &mut feedback);
        assert_eq!((feedback[0].force_n, feedback[0].contacts), (Vec3::new(0.0, 0.0, 1.5), 3));
        // r × F: (0, −4.5 mm, 0) × 1 N z + (0, 4.5 mm, 0) × 0.5 N z = −2.25e-3 N·m about x.
        assert!((feedback[0].torque_nm - Vec3::new(-2.25e-3, 0.0, 0.0)).norm() < 1e-15, "{:?}", feedback[0].torque_nm);
        assert_eq!(bodies.gather(&tools, &mut feedback), 0, "nothing clamped");
        bodies.feedback[1].force_n.z = 2.5;
        assert_eq!(bodies.gather(&tools, &mut feedback), 1, "the sum clamped, counted");
        assert!((feedback[0].force_n.z - 3.0).abs() < 1e-12 && feedback[0].force_clamped, "3.5 N clamped at the forceps' 3 N");
    }
}
