//! The command and feedback records that cross between networking and the physics
//! thread, and their fixed-size word encodings for [`super::slots::SeqSlot`].

use cutsim_sim::math::{Pose, Vec3, quat_from_wxyz_exact};
use cutsim_sim::tool::{ToolCommand, ToolFeedback};

/// A tool command with its timing: what a haptic client last sent for one tool.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StampedCommand {
    pub command: ToolCommand,
    /// The client's clock when it sent the command, ns (echoed back).
    pub client_time_ns: u64,
    /// The session clock when the server received it, ns since the session started.
    pub received_ns: u64,
    /// Feedback every this many steps (≥ 1).
    pub feedback_every: u32,
}

pub const COMMAND_WORDS: usize = 11;

impl StampedCommand {
    pub fn to_words(&self) -> [u64; COMMAND_WORDS] {
        let p = self.command.pose.position_m;
        let q = self.command.pose.orientation.quaternion();
        let flags = u64::from(self.command.active) | (u64::from(self.command.cut) << 1) | (u64::from(self.command.grip.is_some()) << 2) | (u64::from(self.feedback_every) << 32);
        [
            p.x.to_bits(),
            p.y.to_bits(),
            p.z.to_bits(),
            q.w.to_bits(),
            q.i.to_bits(),
            q.j.to_bits(),
            q.k.to_bits(),
            flags,
            self.client_time_ns,
            self.received_ns,
            self.command.grip.unwrap_or(0.0).to_bits(),
        ]
    }

    pub fn from_words(w: &[u64; COMMAND_WORDS]) -> Self {
        let f = |i: usize| f64::from_bits(w[i]);
        let position = Vec3::new(f(0), f(1), f(2));
        let orientation = quat_from_wxyz_exact(f(3), f(4), f(5), f(6));
        Self {
            command: ToolCommand { pose: Pose::new(position, orientation), active: w[7] & 1 == 1, cut: w[7] & 2 == 2, grip: (w[7] & 4 == 4).then(|| f(10)) },
            client_time_ns: w[8],
            received_ns: w[9],
            feedback_every: ((w[7] >> 32) as u32).max(1),
        }
    }
}

/// One step's feedback for one tool.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct FeedbackRecord {
    pub step: u64,
    pub feedback: ToolFeedback,
    pub echo_client_time_ns: u64,
    /// From receiving the command the step used to the end of the step, ns.
    pub server_latency_ns: u64,
    pub step_time_ns: u64,
}

pub const FEEDBACK_WORDS: usize = 15;

impl FeedbackRecord {
    pub fn to_words(&self) -> [u64; FEEDBACK_WORDS] {
        let f = self.feedback.force_n;
        let t = self.feedback.torque_nm;
        let r = self.feedback.resistance_n;
        let flags = u64::from(self.feedback.contacts)
            | (u64::from(self.feedback.cutting) << 32)
            | (u64::from(self.feedback.force_clamped) << 33)
            | (u64::from(self.feedback.grasping) << 34);
        [
            self.step,
            f.x.to_bits(),
            f.y.to_bits(),
            f.z.to_bits(),
            t.x.to_bits(),
            t.y.to_bits(),
            t.z.to_bits(),
            flags,
            self.echo_client_time_ns,
            self.server_latency_ns,
            self.step_time_ns,
            r.x.to_bits(),
            r.y.to_bits(),
            r.z.to_bits(),
            self.feedback.jaws_force_n.to_bits(),
        ]
    }

    pub fn from_words(w: &[u64; FEEDBACK_WORDS]) -> Self {
        let f = |i: usize| f64::from_bits(w[i]);
        Self {
            step: w[0],
            feedback: ToolFeedback {
                force_n: Vec3::new(f(1), f(2), f(3)),
                torque_nm: Vec3::new(f(4), f(5), f(6)),
                contacts: w[7] as u32,
                cutting: (w[7] >> 32) & 1 == 1,
                force_clamped: (w[7] >> 33) & 1 == 1,
                grasping: (w[7] >> 34) & 1 == 1,
                resistance_n: Vec3::new(f(11), f(12), f(13)),
                jaws_force_n: f(14),
            },
            echo_client_time_ns: w[8],
            server_latency_ns: w[9],
            step_time_ns: w[10],
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn command_round_trips_through_words() {
        let c = StampedCommand {
            command: ToolCommand {
                pose: Pose::new(Vec3::new(0.1, -0.2, 0.3), cutsim_sim::math::Quat::from_euler_angles(0.1, 0.2, 0.3)),
                active: true,
                cut: true,
                grip: None,
            },
            client_time_ns: 123,
            received_ns: 456,
            feedback_every: 3,
        };
        assert_eq!(StampedCommand::from_words(&c.to_words()), c);
        // A squeeze of 0 is not the absent one (the whole grip).
        for grip in [Some(0.0), Some(0.35), Some(1.0)] {
            let squeezed = StampedCommand { command: ToolCommand { grip, ..c.command }, ..c };
            assert_eq!(StampedCommand::from_words(&squeezed.to_words()), squeezed);
        }
    }

    #[test]
    fn feedback_round_trips_through_words() {
        let r = FeedbackRecord {
            step: 9,
            feedback: ToolFeedback {
                force_n: Vec3::new(1.0, 2.0, 3.0),
                torque_nm: Vec3::new(-1.0, 0.5, 0.0),
                contacts: 7,
                cutting: true,
                force_clamped: false,
                resistance_n: Vec3::new(-0.5, 0.25, 0.0),
                grasping: true,
                jaws_force_n: 2.5,
            },
            echo_client_time_ns: 11,
            server_latency_ns: 12,
            step_time_ns: 13,
        };
        assert_eq!(FeedbackRecord::from_words(&r.to_words()), r);
    }
}
