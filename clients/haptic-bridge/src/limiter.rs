//! What a device may receive: never a NaN, never more than its rated force, never a step
//! bigger than its force-rate limit allows in one millisecond; and a force that ramps to
//! zero when the server's answers are stale or the link is down.

use crate::vec::V3;

#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct Limits {
    /// The device's rated force, N.
    pub max_force_n: f64,
    /// The largest change of force per second, N/s.
    pub max_force_rate_n_per_s: f64,
    /// An answer older than this is stale, ms.
    pub stale_ms: f64,
    /// How long the force takes to fade to zero once answers are stale, ms.
    pub ramp_ms: f64,
    /// An analog gripper's rated force, N (the force the forceps' jaws are pushed apart
    /// with, rendered against the squeeze, is limited to it, at the same rate limit).
    pub max_grip_force_n: f64,
}

impl Default for Limits {
    fn default() -> Self {
        // A PHANToM Omni class device: 3.3 N rated. A gripper rendering force: 8 N (a
        // Force Dimension omega.7's, the vendor's figure).
        Self { max_force_n: 3.3, max_force_rate_n_per_s: 100.0, stale_ms: 20.0, ramp_ms: 50.0, max_grip_force_n: 8.0 }
    }
}

impl Limits {
    /// The limits of an analog gripper's force: its own rated force, the rest alike.
    pub fn of_gripper(&self) -> Limits {
        Limits { max_force_n: self.max_grip_force_n, ..*self }
    }

    pub fn check(&self) -> Result<(), String> {
        for (name, v) in [("max_force_n", self.max_force_n), ("max_force_rate_n_per_s", self.max_force_rate_n_per_s), ("stale_ms", self.stale_ms), ("ramp_ms", self.ramp_ms), ("max_grip_force_n", self.max_grip_force_n)] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a positive number, got {v}"));
            }
        }
        Ok(())
    }
}

#[derive(Debug, Clone)]
pub struct Limiter {
    limits: Limits,
    last: V3,
    /// 1 while answers are fresh, falling to 0 over `ramp_ms` while they are stale.
    gain: f64,
    pub clamped: u64,
    pub rate_limited: u64,
    pub non_finite: u64,
}

impl Limiter {
    pub fn new(limits: Limits) -> Self {
        Self { limits, last: V3::default(), gain: 1.0, clamped: 0, rate_limited: 0, non_finite: 0 }
    }

    /// The force to send the device this millisecond (`dt_s` after the last).
    pub fn apply(&mut self, wanted: V3, fresh: bool, dt_s: f64) -> V3 {
        let l = &self.limits;
        let step = dt_s * 1e3 / l.ramp_ms;
        self.gain = if fresh { (self.gain + step).min(1.0) } else { (self.gain - step).max(0.0) };
        let mut f = if wanted.is_finite() {
            wanted * self.gain
        } else {
            self.non_finite += 1;
            V3::default()
        };
        let magnitude = f.norm();
        if magnitude > l.max_force_n {
            f = f * (l.max_force_n / magnitude);
            self.clamped += 1;
        }
        // While fading out, the force never grows (the coupling may still swing).
        let last = self.last.norm();
        if !fresh && f.norm() > last {
            f = if last > 0.0 { f * (last / f.norm()) } else { V3::default() };
        }
        let max_change = l.max_force_rate_n_per_s * dt_s;
        let change = f - self.last;
        let c = change.norm();
        if c > max_change {
            f = self.last + change * (max_change / c);
            self.rate_limited += 1;
        }
        self.last = f;
        f
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn clamps_limits_rate_and_ramps() {
        let limits = Limits { max_force_n: 1.0, max_force_rate_n_per_s: 100.0, stale_ms: 20.0, ramp_ms: 50.0, max_grip_force_n: 8.0 };
        let mut l = Limiter::new(limits);
        let mut prev = V3::default();
        for _ in 0..100 {
            let f = l.apply(V3(0.0, 0.0, 5.0), true, 0.001);
            assert!(f.norm() <= 1.0 + 1e-12 && (f - prev).norm() <= 0.1 + 1e-12);
            prev = f;
        }
        assert!((prev.norm() - 1.0).abs() < 1e-12);
        assert!(l.apply(V3(f64::NAN, 0.0, 0.0), true, 0.001).is_finite());
        // Stale: down to zero within the ramp (plus what the rate limit needs), never
        // growing even when more is asked for.
        let mut steps = 0;
        let mut last = l.apply(V3(0.0, 0.0, 5.0), false, 0.001).norm();
        while last > 0.0 {
            let now = l.apply(V3(0.0, 0.0, 5.0 + steps as f64), false, 0.001).norm();
            assert!(now <= last);
            last = now;
            steps += 1;
            assert!(steps < 100);
        }
        // The ramp (50 ms) plus what the rate limit needs to go from the limit to zero.
        assert!(steps <= 50 + 10, "{steps}");
    }
}
