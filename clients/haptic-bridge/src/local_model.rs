//! A local model of the tissue's stiffness, learnt from the server's answers, that
//! carries each answer from the pose it was computed at to where the proxy is now.
//!
//! The server answers the pose the bridge sent milliseconds ago (its step, the round
//! trip). Against a stiff load — a grasped fold pulls by newtons per millimetre — the
//! proxy then acts on a force that lags its motion, and the coupling swings unless it
//! is damped hard (docs/haptic-bridge.md, "Grasping through the bridge"). Multirate
//! haptics renders such a load with a local linear model updated at the slow rate and
//! evaluated at the fast one (Çavuşoğlu and Tendick, "Multirate simulation for high
//! fidelity haptic interaction with deformable objects in virtual environments", ICRA
//! 2000): here the fast loop is the bridge's, the slow model is the server's answer,
//! and the answer's stiffness along its own direction is estimated from how the answers
//! changed with the poses they answered (least squares with forgetting). The tissue
//! force on the proxy is then
//!
//! F(x) = F_a − k (n·(x − x_a)) n,  n = F_a / |F_a|,
//!
//! with F_a the newest answer's elastic force, x_a the pose it answered and k ≥ 0 the
//! estimate: the delay is taken out of the loop as far as the load is linear over the
//! proxy's motion in a round trip. Contact only pushes and a grasp only pulls: the
//! extrapolation never turns the force round, and it grows the force over at most
//! [`MAX_EXTRAPOLATION_M`] from the answered pose. A force that changes while the pose
//! does not (a cut going on, the tissue settling) teaches nothing: a pair of answers
//! whose poses differ by less than [`LEAST_MOTION_M`] along n is not used.

use crate::vec::V3;

/// A pair of answers whose poses moved less than this along the force teaches the
/// estimate nothing, m: the tissue's own motion at a still pose would read as a
/// stiffness of millions of N/m.
pub const LEAST_MOTION_M: f64 = 5e-6;

/// Below this the answer is no contact (the model forgets what it learnt), N.
pub const NO_CONTACT_N: f64 = 1e-3;

/// The farthest from the answered pose the model is followed where it makes the force
/// larger, m: it is local.
pub const MAX_EXTRAPOLATION_M: f64 = 1e-3;

/// The weight an older pair keeps per newer informative pair (a memory of about ten
/// pairs: the stiffness of a fold changes as it is lifted).
const FORGETTING: f64 = 0.9;

#[derive(Debug, Clone, Copy, Default)]
pub struct LocalModel {
    /// The largest stiffness believed, N/m (0: the model is off and answers are used as
    /// they come).
    max_stiffness_n_per_m: f64,
    /// The newest answer: the pose it answered and its elastic force.
    anchor: Option<(V3, V3)>,
    /// Σ λ^age Δf·Δx and Σ λ^age Δx² along each pair's force direction.
    sum_fx: f64,
    sum_xx: f64,
    stiffness_n_per_m: f64,
}

impl LocalModel {
    pub fn new(max_stiffness_n_per_m: f64) -> Self {
        Self { max_stiffness_n_per_m, ..Default::default() }
    }

    /// A new answer: `elastic` (the tissue's force less its dissipative share, N) at the
    /// proxy pose `at` it answered.
    pub fn answered(&mut self, at: V3, elastic: V3) {
        let magnitude = elastic.norm();
        if !(magnitude >= NO_CONTACT_N && at.is_finite() && elastic.is_finite()) {
            // Out of contact (or a broken answer): the next contact is another load.
            self.forget();
            return;
        }
        if let Some((before_at, before)) = self.anchor {
            let n = elastic * (1.0 / magnitude);
            let dx = (at - before_at).dot(n);
            if dx.abs() >= LEAST_MOTION_M {
                let df = (elastic - before).dot(n);
                self.sum_fx = FORGETTING * self.sum_fx + df * dx;
                self.sum_xx = FORGETTING * self.sum_xx + dx * dx;
                self.stiffness_n_per_m = (-self.sum_fx / self.sum_xx).clamp(0.0, self.max_stiffness_n_per_m);
            }
        }
        self.anchor = Some((at, elastic));
    }

    /// Forgets the answers (stale ones, a new connection).
    pub fn forget(&mut self) {
        *self = Self::new(self.max_stiffness_n_per_m);
    }

    /// The elastic force on the proxy at `x`, where the newest answer's elastic force is
    /// `answer`: carried along its direction by the stiffness learnt. With no stiffness
    /// learnt, or no answer learnt from (forgotten: [`LocalModel::forget`]), the answer
    /// itself. The caller tells the model of every answer it passes here, or forgets.
    pub fn force_at(&self, x: V3, answer: V3) -> V3 {
        let Some((at, elastic)) = self.anchor else { return answer };
        debug_assert_eq!(elastic, answer, "the model was told of the answer it carries");
        if self.stiffness_n_per_m == 0.0 {
            return answer;
        }
        let magnitude = elastic.norm();
        let n = elastic * (1.0 / magnitude);
        // Towards a larger force at most MAX_EXTRAPOLATION_M; towards a smaller one as far
        // as the force lasts.
        let along = (x - at).dot(n).max(-MAX_EXTRAPOLATION_M);
        n * (magnitude - self.stiffness_n_per_m * along).max(0.0)
    }

    /// The stiffness learnt, N/m.
    pub fn stiffness_n_per_m(&self) -> f64 {
        self.stiffness_n_per_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_stiffness_of_a_linear_load_is_learnt_from_the_poses_answered() {
        // A pull of 1,500 N/m towards z = −2 mm, answered at poses moving up and down.
        let mut m = LocalModel::new(5000.0);
        let load = |z: f64| V3(0.0, 0.0, -1500.0 * (z + 0.002));
        for i in 0..20 {
            let z = 0.0005 * (i as f64 * 0.7).sin();
            m.answered(V3(0.0, 0.0, z), load(z));
        }
        assert!((m.stiffness_n_per_m() - 1500.0).abs() < 1e-6, "{}", m.stiffness_n_per_m());
        // Carried to another pose, the answer is the load there.
        let (at, answer) = (V3(0.0, 0.0, 0.0003), load(0.0003));
        m.answered(at, answer);
        let x = V3(0.001, 0.0, -0.0004);
        assert!((m.force_at(x, answer) - load(-0.0004)).norm() < 1e-9, "{:?}", m.force_at(x, answer));
    }

    #[test]
    fn a_force_that_changes_at_a_still_pose_teaches_nothing() {
        // The tissue settling under a probe held still: the force grows, the pose does
        // not move by more than a micrometre.
        let mut m = LocalModel::new(5000.0);
        for i in 0..50 {
            m.answered(V3(0.0, 0.0, -0.003 + 1e-6 * (i % 2) as f64), V3(0.0, 0.0, 0.2 + 0.01 * i as f64));
        }
        assert_eq!(m.stiffness_n_per_m(), 0.0);
        let answer = V3(0.0, 0.0, 0.69);
        assert_eq!(m.force_at(V3(0.0, 0.0, 0.01), answer), answer);
    }

    #[test]
    fn the_extrapolation_never_turns_the_force_round_and_stays_local() {
        // A contact pushing up at 500 N/m.
        let mut m = LocalModel::new(5000.0);
        for z in [-0.001, -0.0012, -0.0009, -0.0011] {
            m.answered(V3(0.0, 0.0, z), V3(0.0, 0.0, -500.0 * z));
        }
        assert!((m.stiffness_n_per_m() - 500.0).abs() < 1e-9);
        let answer = V3(0.0, 0.0, 0.55);
        // Pulled 3 mm out of the skin: no pull back.
        assert_eq!(m.force_at(V3(0.0, 0.0, 0.002), answer), V3(0.0, 0.0, 0.0));
        // Pushed 5 mm deeper: at most 1 mm's worth more.
        assert!((m.force_at(V3(0.0, 0.0, -0.006), answer).2 - 1.05).abs() < 1e-12);
        // Out of contact, the model forgets.
        m.answered(V3(0.0, 0.0, 0.001), V3::default());
        assert_eq!(m.stiffness_n_per_m(), 0.0);
        assert_eq!(m.force_at(V3(0.0, 0.0, -0.003), V3::default()), V3::default());
    }

    #[test]
    fn the_stiffness_believed_is_bounded() {
        let mut m = LocalModel::new(2000.0);
        // A load of 100,000 N/m (a contact's raw penalty, say).
        for i in 0..10 {
            let z = -1e-4 * i as f64;
            m.answered(V3(0.0, 0.0, z), V3(0.0, 0.0, 0.1 - 1e5 * z));
        }
        assert_eq!(m.stiffness_n_per_m(), 2000.0);
    }
}
