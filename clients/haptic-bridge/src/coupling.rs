//! The virtual coupling between the device and the tool the server simulates.
//!
//! The tool is a light proxy joined to the device by a spring–damper (Colgate et al.,
//! "Issues in the haptic display of tool use", 1995). Every millisecond the proxy feels
//! the coupling and the newest tissue force from the server, and moves (semi-implicit
//! Euler); the server is sent the proxy's pose; the device renders the coupling force.
//! At rest the device feels exactly the tissue force; in motion the coupling filters the
//! server's delayed, stepwise answers into a smooth, passive force. Each answer is
//! carried from the pose it answered to the proxy's by a local model of the tissue's
//! stiffness (crate::local_model), so that a stiff load answered late does not swing
//! the proxy.

use crate::local_model::LocalModel;
use crate::vec::V3;

#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize, serde::Serialize)]
#[serde(deny_unknown_fields, default)]
pub struct CouplingParams {
    /// Spring between device and proxy, N/m.
    pub stiffness_n_per_m: f64,
    /// Damper between device and proxy, N·s/m.
    pub damping_n_s_per_m: f64,
    /// The damper while the server says the tool grasps tissue (forceps stopped on what
    /// they hold), N·s/m: see [`Coupling::set_grasping`].
    pub grasp_damping_n_s_per_m: f64,
    /// Mass of the proxy, kg.
    pub proxy_mass_kg: f64,
    /// The largest tissue stiffness the local model believes, N/m (0: no local model,
    /// each answer acts as it came): see crate::local_model.
    pub local_max_stiffness_n_per_m: f64,
}

impl Default for CouplingParams {
    fn default() -> Self {
        // ω = √(k/m) ≈ 173 rad/s (stable at 1 kHz: ω·dt = 0.17), ζ ≈ 0.6; grasping,
        // ζ ≈ 1.7 (6 N·s/m: b·dt/m = 0.6, well inside the explicit damper's limit of 2).
        // A local stiffness of up to 3,000 N/m (a grasped fold of the default skin pulls
        // at 1,000–2,000): with the coupling's, ω·dt = 0.57 at most, stable.
        Self { stiffness_n_per_m: 300.0, damping_n_s_per_m: 2.0, grasp_damping_n_s_per_m: 6.0, proxy_mass_kg: 0.01, local_max_stiffness_n_per_m: 3000.0 }
    }
}

impl CouplingParams {
    /// Whether the coupling can run with these: its spring and the proxy's mass positive,
    /// its dampers and the local model's largest stiffness positive or zero, all finite.
    pub fn check(&self) -> Result<(), String> {
        let positive = [("stiffness_n_per_m", self.stiffness_n_per_m), ("proxy_mass_kg", self.proxy_mass_kg)];
        let at_least_zero = [("damping_n_s_per_m", self.damping_n_s_per_m), ("grasp_damping_n_s_per_m", self.grasp_damping_n_s_per_m), ("local_max_stiffness_n_per_m", self.local_max_stiffness_n_per_m)];
        for (name, v) in positive {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be a positive number, got {v}"));
            }
        }
        for (name, v) in at_least_zero {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be a number of at least 0, got {v}"));
            }
        }
        Ok(())
    }
}

#[derive(Debug, Clone)]
pub struct Coupling {
    params: CouplingParams,
    pub proxy: V3,
    proxy_velocity: V3,
    started: bool,
    grasping: bool,
    local: LocalModel,
}

impl Coupling {
    pub fn new(params: CouplingParams) -> Self {
        let local = LocalModel::new(params.local_max_stiffness_n_per_m);
        Self { params, proxy: V3::default(), proxy_velocity: V3::default(), started: false, grasping: false, local }
    }

    /// A new answer from the server: `tissue_force`, of which `resistance` is
    /// dissipative, computed with the tool at `at` (the proxy pose the answer echoes).
    /// The local model learns from it and carries it to the proxy's pose in the steps
    /// that use it.
    pub fn answered(&mut self, at: V3, tissue_force: V3, resistance: V3) {
        self.local.answered(at, tissue_force - resistance);
    }

    /// No answer to go by (stale, or one whose pose is unknown): the local model
    /// forgets what it learnt, and answers act as they come.
    pub fn forget_answers(&mut self) {
        self.local.forget();
    }

    /// The tissue stiffness the local model believes now, N/m.
    pub fn local_stiffness_n_per_m(&self) -> f64 {
        self.local.stiffness_n_per_m()
    }

    /// Whether the tool grasps tissue now (the server's newest fresh answer says so):
    /// the coupling then damps with `grasp_damping_n_s_per_m`. A grasped fold is a stiff
    /// load answered milliseconds late — its pull changes by newtons per millimetre of
    /// the jaws' motion — and with the free-motion damper the proxy swings against it
    /// and the grasp is lost (docs/haptic-bridge.md, "Grasping through the bridge").
    /// A damper stores no energy, so switching it keeps the coupling passive; a firmer
    /// one everywhere would carry the stepwise answers of a multirate session to the
    /// hand (the force-rate limit was reached there at 4–6 N·s/m).
    pub fn set_grasping(&mut self, grasping: bool) {
        self.grasping = grasping;
    }

    /// One step of `dt_s`: the device at `device` moving at `device_velocity` (scene
    /// frame), the tissue pushing the tool with `tissue_force`, of which `resistance` is
    /// dissipative (the cutting resistance: it may stop the proxy, never drive it).
    /// Returns the force to render on the device (scene frame), N.
    pub fn step(&mut self, dt_s: f64, device: V3, device_velocity: V3, tissue_force: V3, resistance: V3) -> V3 {
        if !self.started {
            self.proxy = device;
            self.started = true;
        }
        let p = &self.params;
        let damping = if self.grasping { p.grasp_damping_n_s_per_m } else { p.damping_n_s_per_m };
        let coupling = (device - self.proxy) * p.stiffness_n_per_m + (device_velocity - self.proxy_velocity) * damping;
        let dt_per_kg = dt_s / p.proxy_mass_kg;
        let elastic = self.local.force_at(self.proxy, tissue_force - resistance);
        self.proxy_velocity = proxy_velocity_after(self.proxy_velocity + (coupling + elastic) * dt_per_kg, resistance, dt_per_kg);
        self.proxy = self.proxy + self.proxy_velocity * dt_s;
        if !(self.proxy.is_finite() && self.proxy_velocity.is_finite()) {
            // Never let a broken state reach the device: start over at the device.
            self.proxy = device;
            self.proxy_velocity = V3::default();
            return V3::default();
        }
        -coupling
    }

    /// The steps since the last tick, `elapsed_s` long, in which the device went from
    /// `from` to `to`: its velocity is that distance over that time, and the proxy moves
    /// in steps of at most `max_step_s` with the device between them. A tick the OS
    /// delayed spans more than a millisecond; measuring its velocity over one
    /// millisecond would multiply the damper's force (a jolt), and one long step of the
    /// stiff spring is no longer stable. Returns the force to render now, N.
    pub fn advance(&mut self, elapsed_s: f64, max_step_s: f64, from: V3, to: V3, tissue_force: V3, resistance: V3) -> V3 {
        let velocity = (to - from) * (1.0 / elapsed_s);
        // (A tick of 6.000000001 ms is six steps, not seven.)
        let steps = (elapsed_s / max_step_s - 1e-6).ceil().clamp(1.0, MAX_STEPS_PER_TICK as f64) as usize;
        let dt_s = elapsed_s / steps as f64;
        let mut force = V3::default();
        for i in 1..=steps {
            let device = from + (to - from) * (i as f64 / steps as f64);
            force = self.step(dt_s, device, velocity, tissue_force, resistance);
        }
        force
    }
}

/// The most steps one tick takes the proxy through (a tick delayed by more than this
/// many steps is stale anyway: the limiter fades the force out).
const MAX_STEPS_PER_TICK: usize = 50;

/// The proxy's velocity after the dissipative `resistance` acts for one step on the
/// velocity `v` the other forces gave it (`dt_per_kg` = dt / m). Its share against the
/// motion may stop the proxy but never reverse it, as with Coulomb friction integrated
/// implicitly: a cutting force of 2 N on a 10 g proxy, applied explicitly, would throw it
/// back and forth every millisecond (stick–slip at the loop rate, felt as a buzz). It
/// only takes energy out, so the coupling stays passive.
fn proxy_velocity_after(v: V3, resistance: V3, dt_per_kg: f64) -> V3 {
    let speed = v.norm();
    if speed == 0.0 {
        return v;
    }
    let direction = v * (1.0 / speed);
    let along = resistance.dot(direction).min(0.0);
    let slowed = (speed + along * dt_per_kg).max(0.0);
    direction * slowed
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_force_against_the_motion_stops_the_proxy_but_never_throws_it_back() {
        // 0.1 m/s, 10 g, 1 ms: 1 N takes 0.1 m/s off; 5 N would reverse it, and stops it.
        let v = V3(0.1, 0.0, 0.0);
        assert!((proxy_velocity_after(v, V3(-0.5, 0.0, 0.0), 0.1) - V3(0.05, 0.0, 0.0)).norm() < 1e-12);
        assert_eq!(proxy_velocity_after(v, V3(-5.0, 0.0, 0.0), 0.1), V3(0.0, 0.0, 0.0));
        // A resistance never drives: not from rest, not along the motion, not across it.
        assert_eq!(proxy_velocity_after(V3::default(), V3(-5.0, 0.0, 0.0), 0.1), V3::default());
        assert_eq!(proxy_velocity_after(v, V3(1.0, 0.0, 0.0), 0.1), v);
        assert_eq!(proxy_velocity_after(v, V3(0.0, 3.0, 0.0), 0.1), v);
    }

    #[test]
    fn a_steady_resistance_dragged_at_constant_speed_is_felt_smoothly() {
        // A resistance of 2 N against motion, fading to zero below 2 mm/s of the velocity
        // smoothed over 10 ms, answered one step late (as the server does); the device
        // moves at 10 mm/s. The rendered force settles near 2 N and stops changing by
        // more than a few mN per millisecond.
        let mut c = Coupling::new(CouplingParams::default());
        let (mut last_x, mut tissue, mut smoothed) = (V3::default(), V3::default(), V3::default());
        let mut forces = Vec::new();
        for i in 0..3000 {
            let device = V3(0.01 * i as f64 * 0.001, 0.0, 0.0);
            let f = c.step(0.001, device, V3(0.01, 0.0, 0.0), tissue, tissue);
            forces.push(f.0);
            let v = (c.proxy - last_x) * 1000.0;
            last_x = c.proxy;
            smoothed = smoothed + (v - smoothed) * (1.0 / 11.0);
            let speed = smoothed.norm();
            tissue = if speed > 0.0 { smoothed * (-2.0 * (speed / 0.002).min(1.0) / speed) } else { V3::default() };
        }
        let tail = &forces[2000..];
        let steps = tail.windows(2).map(|w| (w[1] - w[0]).abs()).fold(0.0, f64::max);
        let mean = tail.iter().sum::<f64>() / tail.len() as f64;
        assert!((mean + 2.0).abs() < 0.1, "the device feels the resistance: {mean} N");
        assert!(steps < 0.02, "and smoothly: largest change {steps} N per ms");
    }

    #[test]
    fn a_delayed_tick_renders_what_punctual_ticks_would_have() {
        // The device moving at 10 mm/s into a 0.2 N tissue force; one run ticks every
        // millisecond, the other misses four ticks at 50 ms and catches up in one.
        let device = |t: f64| V3(0.01 * t, 0.0, 0.0);
        let tissue = V3(-0.2, 0.0, 0.0);
        let (mut punctual, mut delayed) = (Coupling::new(CouplingParams::default()), Coupling::new(CouplingParams::default()));
        let (mut f_punctual, mut f_delayed) = (V3::default(), V3::default());
        for i in 1..=60 {
            let (t0, t1) = ((i - 1) as f64 * 1e-3, i as f64 * 1e-3);
            f_punctual = punctual.advance(1e-3, 1e-3, device(t0), device(t1), tissue, V3::default());
            if !(50..55).contains(&i) {
                let t0 = if i == 55 { 49e-3 } else { t0 };
                f_delayed = delayed.advance(t1 - t0, 1e-3, device(t0), device(t1), tissue, V3::default());
            }
        }
        assert!((f_punctual - f_delayed).norm() < 1e-12, "{f_punctual:?} against {f_delayed:?}");
        assert!((delayed.proxy - punctual.proxy).norm() < 1e-15);
    }

    #[test]
    fn at_rest_the_device_feels_the_tissue_force() {
        let mut c = Coupling::new(CouplingParams::default());
        let tissue = V3(0.0, 0.0, 0.5);
        let mut f = V3::default();
        for _ in 0..3000 {
            f = c.step(0.001, V3(0.0, 0.0, -0.002), V3::default(), tissue, V3::default());
        }
        assert!((f - tissue).norm() < 1e-6, "{f:?}");
    }

    /// The proxy held still by the device against a grasped fold: a stiff pull towards
    /// 2 mm below it (`stiffness` N/m, capped at 2.4 N) answered `delay` ms late. The
    /// peak-to-peak force on the device over the last second, and its mean.
    fn held_against_a_grasp(params: CouplingParams, grasping: bool, stiffness: f64, delay: usize) -> (f64, f64) {
        let mut c = Coupling::new(params);
        c.set_grasping(grasping);
        let mut sent = std::collections::VecDeque::from(vec![0.0; delay]);
        let mut forces = Vec::new();
        for _ in 0..3000 {
            let late = sent.pop_front().expect("a pose sent `delay` ms ago");
            let tissue = V3(0.0, 0.0, (-stiffness * (late + 0.002)).clamp(-2.4, 2.4));
            c.answered(V3(0.0, 0.0, late), tissue, V3::default());
            forces.push(c.step(0.001, V3::default(), V3::default(), tissue, V3::default()).2);
            sent.push_back(c.proxy.2);
        }
        let tail = &forces[2000..];
        (tail.iter().copied().fold(f64::MIN, f64::max) - tail.iter().copied().fold(f64::MAX, f64::min), tail.iter().sum::<f64>() / tail.len() as f64)
    }

    #[test]
    fn grasping_the_coupling_holds_a_stiff_late_pull_steadily() {
        // 1,000–2,000 N/m (a grasped fold of the default skin pulls by newtons per
        // millimetre) answered 2–8 ms late (the server's step and the round trip): the
        // free-motion damper swings by newtons, the grasp damper settles where the
        // coupling spring meets the pull.
        let without_local_model = CouplingParams { local_max_stiffness_n_per_m: 0.0, ..Default::default() };
        for (stiffness, delay) in [(1000.0, 4), (1000.0, 8), (2000.0, 2)] {
            let (free_swing, _) = held_against_a_grasp(without_local_model, false, stiffness, delay);
            let (swing, mean) = held_against_a_grasp(without_local_model, true, stiffness, delay);
            let rest = -stiffness * 0.002 * 300.0 / (300.0 + stiffness);
            println!("no local model, {stiffness} N/m, {delay} ms: free-motion damper {free_swing:.4} N peak to peak, grasp damper {swing:.4} N about {mean:.4} N (rest {rest:.4} N)");
            assert!(free_swing > 1.0, "{stiffness} N/m, {delay} ms: the free-motion damper swings ({free_swing} N)");
            assert!(swing < 0.3 && (mean - rest).abs() < 0.01, "{stiffness} N/m, {delay} ms: grasping, {swing} N peak to peak about {mean} N (rest {rest} N)");
        }
    }

    #[test]
    fn with_the_local_model_a_stiff_late_pull_settles() {
        // Those loads and stiffer, later ones: the answers carried to the proxy's pose by
        // the stiffness learnt from them leave no delay in the loop to swing on.
        // - The grasp damper now settles every case; without the model it swings by
        //   4.5–5.2 N at 2,000 N/m 8 ms late and 3,000 N/m 4 ms late.
        // - The light damper that keeps free motion transparent now settles all but the
        //   stiffest loads answered latest (2,000 and 3,000 N/m, 8 ms: 1.7 and 2.8 N peak to
        //   peak, against 7.4 N without the model). They start 2.4 N off their rest, past
        //   the load's cap, where the model learns nothing, and swing before it has
        //   learnt the stiffness.
        let without_local_model = CouplingParams { local_max_stiffness_n_per_m: 0.0, ..Default::default() };
        for (stiffness, delay) in [(1000.0, 4), (1000.0, 8), (2000.0, 2), (2000.0, 8), (500.0, 20), (3000.0, 4), (3000.0, 8)] {
            let rest = -stiffness * 0.002 * 300.0 / (300.0 + stiffness);
            for grasping in [false, true] {
                let (swing, mean) = held_against_a_grasp(CouplingParams::default(), grasping, stiffness, delay);
                let (swing_without, _) = held_against_a_grasp(without_local_model, grasping, stiffness, delay);
                println!("{stiffness} N/m, {delay} ms, grasp damper {grasping}: {swing:.4} N peak to peak about {mean:.4} N (rest {rest:.4} N); without the local model {swing_without:.4} N");
                if grasping || delay < 8 || stiffness < 2000.0 {
                    assert!(swing < 1e-3 && (mean - rest).abs() < 1e-3, "{stiffness} N/m, {delay} ms, grasp damper {grasping}: {swing} N peak to peak about {mean} N (rest {rest} N)");
                } else {
                    assert!(swing < 0.5 * swing_without, "{stiffness} N/m, {delay} ms, free-motion damper: {swing} N peak to peak, {swing_without} N without the local model");
                }
                if grasping && [(2000.0, 8), (3000.0, 4)].contains(&(stiffness, delay)) {
                    assert!(swing_without > 4.0, "{stiffness} N/m, {delay} ms: the grasp damper alone swings ({swing_without} N)");
                }
            }
        }
    }

    #[test]
    fn a_coupling_that_cannot_run_is_refused_by_name() {
        assert_eq!(CouplingParams::default().check(), Ok(()));
        let bad = CouplingParams { local_max_stiffness_n_per_m: -1.0, ..Default::default() };
        assert_eq!(bad.check(), Err("local_max_stiffness_n_per_m must be a number of at least 0, got -1".into()));
        let bad = CouplingParams { proxy_mass_kg: 0.0, ..Default::default() };
        assert_eq!(bad.check(), Err("proxy_mass_kg must be a positive number, got 0".into()));
        let bad = CouplingParams { damping_n_s_per_m: f64::NAN, ..Default::default() };
        assert!(bad.check().unwrap_err().starts_with("damping_n_s_per_m must be"));
    }

    #[test]
    fn free_motion_has_no_force_at_rest() {
        let mut c = Coupling::new(CouplingParams::default());
        let mut f = V3(1.0, 1.0, 1.0);
        for _ in 0..2000 {
            f = c.step(0.001, V3(0.01, 0.02, 0.03), V3::default(), V3::default(), V3::default());
        }
        assert!(f.norm() < 1e-9);
    }
}
