//! The virtual coupling between the device and the tool the server simulates.
//!
//! The tool is a light proxy joined to the device by a spring–damper (Colgate et al.,
//! "Issues in the haptic display of tool use", 1995). Every millisecond the proxy feels
//! the coupling and the newest tissue force from the server, and moves (semi-implicit
//! Euler); the server is sent the proxy's pose; the device renders the coupling force.
//! At rest the device feels exactly the tissue force; in motion the coupling filters the
//! server's delayed, stepwise answers into a smooth, passive force.

use crate::vec::V3;

#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct CouplingParams {
    /// Spring between device and proxy, N/m.
    pub stiffness_n_per_m: f64,
    /// Damper between device and proxy, N·s/m.
    pub damping_n_s_per_m: f64,
    /// Mass of the proxy, kg.
    pub proxy_mass_kg: f64,
}

impl Default for CouplingParams {
    fn default() -> Self {
        // ω = √(k/m) ≈ 173 rad/s (stable at 1 kHz: ω·dt = 0.17), ζ ≈ 0.6.
        Self { stiffness_n_per_m: 300.0, damping_n_s_per_m: 2.0, proxy_mass_kg: 0.01 }
    }
}

#[derive(Debug, Clone)]
pub struct Coupling {
    params: CouplingParams,
    pub proxy: V3,
    proxy_velocity: V3,
    started: bool,
}

impl Coupling {
    pub fn new(params: CouplingParams) -> Self {
        Self { params, proxy: V3::default(), proxy_velocity: V3::default(), started: false }
    }

    /// One step of `dt_s`: the device at `device` moving at `device_velocity` (scene
    /// frame), the tissue pushing the tool with `tissue_force`. Returns the force to
    /// render on the device (scene frame), N.
    pub fn step(&mut self, dt_s: f64, device: V3, device_velocity: V3, tissue_force: V3) -> V3 {
        if !self.started {
            self.proxy = device;
            self.started = true;
        }
        let p = &self.params;
        let coupling = (device - self.proxy) * p.stiffness_n_per_m + (device_velocity - self.proxy_velocity) * p.damping_n_s_per_m;
        self.proxy_velocity = self.proxy_velocity + (coupling + tissue_force) * (dt_s / p.proxy_mass_kg);
        self.proxy = self.proxy + self.proxy_velocity * dt_s;
        if !(self.proxy.is_finite() && self.proxy_velocity.is_finite()) {
            // Never let a broken state reach the device: start over at the device.
            self.proxy = device;
            self.proxy_velocity = V3::default();
            return V3::default();
        }
        -coupling
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn at_rest_the_device_feels_the_tissue_force() {
        let mut c = Coupling::new(CouplingParams::default());
        let tissue = V3(0.0, 0.0, 0.5);
        let mut f = V3::default();
        for _ in 0..3000 {
            f = c.step(0.001, V3(0.0, 0.0, -0.002), V3::default(), tissue);
        }
        assert!((f - tissue).norm() < 1e-6, "{f:?}");
    }

    #[test]
    fn free_motion_has_no_force_at_rest() {
        let mut c = Coupling::new(CouplingParams::default());
        let mut f = V3(1.0, 1.0, 1.0);
        for _ in 0..2000 {
            f = c.step(0.001, V3(0.01, 0.02, 0.03), V3::default(), V3::default());
        }
        assert!(f.norm() < 1e-9);
    }
}
