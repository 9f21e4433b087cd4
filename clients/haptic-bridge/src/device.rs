//! Haptic devices: a simulated stylus (scripted trajectories, for demos and tests) and
//! any physical device whose vendor driver sends its pose over UDP (docs/haptic-bridge.md:
//! OpenHaptics, Force Dimension or libnifalcon plug in without being linked here).

use std::net::{SocketAddr, UdpSocket};
use std::time::Duration;

use crate::vec::{Quat, V3};

/// What a device reports each millisecond, in its own frame.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct DeviceState {
    /// False until the device has reported at all (the tool stays away).
    pub present: bool,
    pub position_m: V3,
    pub orientation: Quat,
    /// Bit 0: the cut button (or pedal); on forceps, it closes the jaws.
    pub buttons: u32,
    /// An analog gripper's squeeze, 0 (open) to 1 (the forceps' whole grip); None for a
    /// device whose jaw is a button (the whole grip while it is held).
    pub grip: Option<f64>,
}

/// Pose datagram flag (in `buttons`): the device has an analog gripper, whose squeeze
/// is the f32 at offset 76.
pub const HAS_GRIPPER: u32 = 1 << 1;

pub trait Device: Send {
    fn name(&self) -> String;
    /// The newest state, `t` after the bridge started.
    fn read(&mut self, t: Duration) -> DeviceState;
    /// Renders a force (device frame, N) and, on an analog gripper, `grip_n` against the
    /// squeeze (N: how hard the tissue between the forceps' jaws pushes them apart);
    /// `fresh` tells the device the link is healthy.
    fn write_force(&mut self, force: V3, grip_n: f64, fresh: bool);
}

/// A simulated stylus following a scripted trajectory in scene units (m).
pub struct SimDevice {
    trajectory: Trajectory,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Trajectory {
    /// A probe lowered onto the skin at (1 cm, 1 cm), 3 mm deep over a second, then held
    /// with a slow 0.5 mm wobble.
    Press,
    /// A scalpel cutting 4 cm along x over 4 s, 5 mm below the surface, button held.
    Cut,
    /// Forceps at (1 cm, 1 cm), tip first: lowered from 5 mm above the skin to 6 mm into
    /// it over the first second, jaws closed by the button from 1.2 s, lifted 10 mm at
    /// 20 mm/s from 1.6 s, held, and let go at 3 s.
    Grasp,
}

impl SimDevice {
    pub fn new(trajectory: Trajectory) -> Self {
        Self { trajectory }
    }
}

impl Device for SimDevice {
    fn name(&self) -> String {
        format!("simulated stylus ({:?})", self.trajectory).to_lowercase()
    }

    fn read(&mut self, t: Duration) -> DeviceState {
        let s = t.as_secs_f64();
        let (position_m, buttons) = match self.trajectory {
            Trajectory::Press => {
                let z = 0.005 - 0.008 * s.min(1.0) + 0.0005 * (2.0 * std::f64::consts::PI * 0.5 * s).sin() * f64::from(u8::from(s > 1.0));
                (V3(0.01, 0.01, z), 0)
            }
            Trajectory::Cut => (V3(-0.02 + 0.01 * s.min(4.0), 0.0, -0.005), 1),
            Trajectory::Grasp => {
                let z = 0.005 - 0.011 * s.min(1.0) + 0.02 * (s - 1.6).clamp(0.0, 0.5);
                (V3(0.01, 0.01, z), u32::from((1.2..3.0).contains(&s)))
            }
        };
        DeviceState { present: true, position_m, orientation: Quat::default(), buttons, grip: None }
    }

    fn write_force(&mut self, _force: V3, _grip_n: f64, _fresh: bool) {}
}

/// Datagram sizes of the UDP device protocol.
pub const POSE_DATAGRAM: usize = 80;
pub const FORCE_DATAGRAM: usize = 64;

/// A device whose driver sends `CSD1` pose datagrams and receives `CSF1` force
/// datagrams (little-endian; docs/haptic-bridge.md).
pub struct UdpDevice {
    socket: UdpSocket,
    peer: Option<SocketAddr>,
    last: DeviceState,
    sequence: u32,
    pub bad_datagrams: u64,
}

impl UdpDevice {
    pub fn bind(address: &str) -> std::io::Result<Self> {
        let socket = UdpSocket::bind(address)?;
        socket.set_nonblocking(true)?;
        Ok(Self { socket, peer: None, last: DeviceState::default(), sequence: 0, bad_datagrams: 0 })
    }

    pub fn local_addr(&self) -> std::io::Result<SocketAddr> {
        self.socket.local_addr()
    }
}

fn f64_at(b: &[u8], at: usize) -> f64 {
    f64::from_le_bytes(b[at..at + 8].try_into().expect("8 bytes"))
}

/// Decodes a pose datagram; None when it is not one (or holds non-finite values).
pub fn decode_pose(b: &[u8]) -> Option<(u32, DeviceState)> {
    if b.len() != POSE_DATAGRAM || &b[..4] != b"CSD1" {
        return None;
    }
    let sequence = u32::from_le_bytes(b[4..8].try_into().ok()?);
    let position_m = V3(f64_at(b, 16), f64_at(b, 24), f64_at(b, 32));
    let q = Quat(f64_at(b, 40), f64_at(b, 48), f64_at(b, 56), f64_at(b, 64));
    let buttons = u32::from_le_bytes(b[72..76].try_into().ok()?);
    // A gripper's sensor a little past its calibrated ends is clamped; a broken one
    // (not a number) spoils the datagram.
    let grip = (buttons & HAS_GRIPPER != 0).then(|| f64::from(f32::from_le_bytes(b[76..80].try_into().expect("4 bytes"))));
    let finite = position_m.is_finite() && [q.0, q.1, q.2, q.3].iter().all(|c| c.is_finite()) && grip.is_none_or(f64::is_finite);
    finite.then_some((sequence, DeviceState { present: true, position_m, orientation: q.normalized(), buttons, grip: grip.map(|g| g.clamp(0.0, 1.0)) }))
}

pub fn encode_force(sequence: u32, force: V3, grip_n: f64, fresh: bool) -> [u8; FORCE_DATAGRAM] {
    let mut b = [0u8; FORCE_DATAGRAM];
    b[..4].copy_from_slice(b"CSF1");
    b[4..8].copy_from_slice(&sequence.to_le_bytes());
    for (k, c) in [force.0, force.1, force.2].iter().enumerate() {
        b[8 + 8 * k..16 + 8 * k].copy_from_slice(&c.to_le_bytes());
    }
    b[56..60].copy_from_slice(&u32::from(fresh).to_le_bytes());
    b[60..64].copy_from_slice(&(grip_n as f32).to_le_bytes());
    b
}

impl Device for UdpDevice {
    fn name(&self) -> String {
        format!("UDP device on {}", self.socket.local_addr().map(|a| a.to_string()).unwrap_or_default())
    }

    fn read(&mut self, _t: Duration) -> DeviceState {
        let mut buf = [0u8; 256];
        // Drain what arrived; the newest pose wins.
        while let Ok((n, from)) = self.socket.recv_from(&mut buf) {
            match decode_pose(&buf[..n]) {
                Some((sequence, state)) => {
                    self.sequence = sequence;
                    self.last = state;
                    self.peer = Some(from);
                }
                None => self.bad_datagrams += 1,
            }
        }
        self.last
    }

    fn write_force(&mut self, force: V3, grip_n: f64, fresh: bool) {
        if let Some(peer) = self.peer {
            let _ = self.socket.send_to(&encode_force(self.sequence, force, grip_n, fresh), peer);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pose_datagram_round_trip() {
        let mut b = [0u8; POSE_DATAGRAM];
        b[..4].copy_from_slice(b"CSD1");
        b[4..8].copy_from_slice(&7u32.to_le_bytes());
        for (k, c) in [0.01, 0.02, 0.03, 1.0, 0.0, 0.0, 0.0].iter().enumerate() {
            b[16 + 8 * k..24 + 8 * k].copy_from_slice(&f64::to_le_bytes(*c));
        }
        b[72..76].copy_from_slice(&1u32.to_le_bytes());
        let (sequence, state) = decode_pose(&b).unwrap();
        assert_eq!((sequence, state.buttons, state.position_m), (7, 1, V3(0.01, 0.02, 0.03)));
        b[16..24].copy_from_slice(&f64::NAN.to_le_bytes());
        assert!(decode_pose(&b).is_none());
        assert!(decode_pose(&b[..10]).is_none());
        assert_eq!(state.grip, None, "no gripper flagged: a button");
        // A gripper: its squeeze at offset 76, clamped to 0–1; not a number spoils it.
        b[16..24].copy_from_slice(&0.01f64.to_le_bytes());
        b[72..76].copy_from_slice(&(1 | HAS_GRIPPER).to_le_bytes());
        for (squeeze, read) in [(0.25f32, Some(0.25)), (1.02, Some(1.0)), (-0.01, Some(0.0)), (f32::NAN, None)] {
            b[76..80].copy_from_slice(&squeeze.to_le_bytes());
            assert_eq!(decode_pose(&b).map(|(_, s)| s.grip.expect("a gripper")), read, "squeeze {squeeze}");
        }
        let f = encode_force(7, V3(1.0, 2.0, 3.0), 1.5, true);
        assert_eq!(&f[..4], b"CSF1");
        assert_eq!(f64::from_le_bytes(f[24..32].try_into().unwrap()), 3.0);
        assert_eq!(f32::from_le_bytes(f[60..64].try_into().unwrap()), 1.5, "the gripper's force at offset 60");
    }
}
