//! The initial guess of a step's solve: the velocity change extrapolated from the last
//! steps' solutions.
//!
//! A step's conjugate gradient starts from a guess and stops at a residual relative to
//! the right-hand side, so the iterations it needs grow with the logarithm of how far
//! the guess is off. The velocity change of a body in motion varies smoothly from step
//! to step (the step is short against the body's own periods), so a polynomial through
//! the last solutions predicts the next far better than the last solution alone (what
//! the warm start used before): through three, `3 Δv₁ − 3 Δv₂ + Δv₃`, exact for a
//! velocity change that is a quadratic function of time. Measured on the bundled scenes
//! (`cargo bench -p cutsim-sim --bench grid`, a probe pressed and held, then a cut):
//! 20–45 % fewer iterations per step; on the level-0 cantilever of
//! `tools/fem-comparison`, 36 → 23 with block Jacobi and 3.1 → 2.0 with the Cholesky
//! preconditioner (docs/branched-grid.md, "The solver core").
//!
//! The guess only changes where the solve starts, not what it converges to, and it is
//! plain arithmetic on the solutions: a replay computes the same bits. With fewer than
//! three solutions since the history began (the start, a contained blow-up), the
//! polynomial is of the degree they allow: the last solution, then a line through two —
//! a quadratic through a first step from rest would triple that step's velocity change.
//! And it goes through only as many as are smooth: each finite difference (the change,
//! the change of the change) must be at most half the one below it. Where the solutions
//! jump — a multirate schedule's 10 ms deformation steps, pushed by the haptic loop's
//! impulses, and cuts — a polynomial through them threw the guess further off than the
//! last solution: the u-tube's scripted slit under that schedule hit its iteration cap
//! in 13 of 119 steps (none without the prediction, none with this rule, which also
//! takes 1 % fewer iterations there than the last solution alone).
//! Nodes a cut added join with a zero history (what they had before did not exist).

use crate::math::Vec3;

/// The solutions before the last one, and how many of them are real.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Predictor {
    /// Δv two steps back and three steps back.
    before: Vec<Vec3>,
    before2: Vec<Vec3>,
    /// Calls since the history began (at most 3): at the first, Δv holds no solution yet
    /// (zeros before the first solve, or after a blow-up); at the second, one; then two,
    /// then three with the history.
    calls: u8,
}

impl Predictor {
    /// Grows the history to `n` unknowns (new ones with zeros).
    pub fn resize(&mut self, n: usize) {
        self.before.resize(n, Vec3::zeros());
        self.before2.resize(n, Vec3::zeros());
    }

    /// Starts the history again (after a contained blow-up, or a jump of the state).
    pub fn forget(&mut self) {
        self.before.iter_mut().for_each(|v| *v = Vec3::zeros());
        self.before2.iter_mut().for_each(|v| *v = Vec3::zeros());
        self.calls = 0;
    }

    /// Takes `dv`, the last step's solution, into the history and replaces it with the
    /// guess for the next step's. Call once per step's solve, before it.
    pub fn predict(&mut self, dv: &mut [Vec3]) {
        assert!(self.before.len() >= dv.len(), "Predictor::resize to the unknowns first");
        let n = dv.len();
        let points = self.points(&dv[..n]);
        for ((last, before), before2) in dv.iter_mut().zip(&mut self.before).zip(&mut self.before2) {
            let guess = match points {
                0 | 1 => *last,
                2 => *last * 2.0 - *before,
                _ => (*last - *before) * 3.0 + *before2,
            };
            *before2 = *before;
            *before = *last;
            *last = guess;
        }
        self.calls = (self.calls + 1).min(3);
    }

    /// Through how many solutions the polynomial goes (1: the last one alone): as many
    /// as the history holds, while each finite difference is at most SMOOTH times the
    /// one below it (the last solution, its change, the change of its change). Where
    /// the solutions jump (a long step under a multirate schedule with the haptic loop's
    /// impulses, a cut) the differences do not fall, and a polynomial through them
    /// would throw the guess further off than the last solution is.
    fn points(&self, last: &[Vec3]) -> u8 {
        if self.calls < 2 {
            return 1;
        }
        let (mut value, mut slope, mut curve) = (0.0, 0.0, 0.0);
        for ((l, b), b2) in last.iter().zip(&self.before).zip(&self.before2) {
            value += l.norm_squared();
            slope += (l - b).norm_squared();
            curve += (l - b * 2.0 + b2).norm_squared();
        }
        let falls = |upper: f64, lower: f64| upper <= SMOOTH * SMOOTH * lower;
        if !falls(slope, value) {
            1
        } else if self.calls < 3 || !falls(curve, slope) {
            2
        } else {
            3
        }
    }
}

/// How much smaller each finite difference of the history must be than the one below
/// it for the extrapolation to take it (see [`Predictor::points`]).
pub const SMOOTH: f64 = 0.5;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_guess_follows_a_quadratic_exactly_once_three_solutions_are_known() {
        let mut p = Predictor::default();
        p.resize(2);
        // Δv(t) = 1 + 0.1t + 0.005t² per axis (each difference a tenth of the one below
        // it: smooth), node 1 twice node 0.
        let exact = |t: f64, node: usize| Vec3::repeat((1.0 + 0.1 * t + 0.005 * t * t) * (node as f64 + 1.0));
        // Before the first solve Δv holds no solution: the guess is what it holds.
        let mut dv = vec![Vec3::zeros(); 2];
        p.predict(&mut dv);
        assert_eq!(dv, vec![Vec3::zeros(); 2]);
        let mut guesses = Vec::new();
        for t in 0..6 {
            // The solve of step t ends with the exact answer.
            for (i, d) in dv.iter_mut().enumerate() {
                *d = exact(f64::from(t), i);
            }
            p.predict(&mut dv);
            guesses.push(dv.clone());
        }
        // After one solution, that solution; after two, a line through them (1 and 1.105
        // at 0 and 1: the line says 1.21 at 2, where it is 1.22).
        assert_eq!(guesses[0][0], exact(0.0, 0));
        assert!((guesses[1][0] - Vec3::repeat(1.21)).amax() < 1e-12, "{:?}", guesses[1][0]);
        for t in 2..6 {
            for i in 0..2 {
                assert!((guesses[t][i] - exact(t as f64 + 1.0, i)).amax() < 1e-12, "step {t}, node {i}");
            }
        }
    }

    #[test]
    fn solutions_that_jump_are_not_extrapolated() {
        let mut p = Predictor::default();
        p.resize(1);
        let mut dv = vec![Vec3::zeros()];
        p.predict(&mut dv);
        // 1, −1, 1: each change as large as the solution: the last one alone.
        for v in [1.0, -1.0, 1.0] {
            dv[0] = Vec3::repeat(v);
            p.predict(&mut dv);
        }
        assert_eq!(dv[0], Vec3::repeat(1.0));
        // 1, 1.1, 1.2 with a kink: 1.2, 1.3, then 1.9: the change of the change is not
        // small against the change, so a line through the last two (2.5), not the
        // parabola (2.8).
        for v in [1.1, 1.2, 1.3, 1.9] {
            dv[0] = Vec3::repeat(v);
            p.predict(&mut dv);
        }
        assert!((dv[0] - Vec3::repeat(2.5)).amax() < 1e-12, "{:?}", dv[0]);
    }

    #[test]
    fn forgetting_starts_from_the_last_solution_again_and_new_nodes_have_no_past() {
        let mut p = Predictor::default();
        p.resize(1);
        let mut dv = vec![Vec3::zeros()];
        for _ in 0..5 {
            p.predict(&mut dv);
            dv[0] = Vec3::repeat(1.0);
        }
        // A blow-up contained: the history and Δv are cleared.
        p.forget();
        dv[0] = Vec3::zeros();
        p.predict(&mut dv);
        assert_eq!(dv[0], Vec3::zeros());
        dv[0] = Vec3::repeat(5.0);
        p.predict(&mut dv);
        assert_eq!(dv[0], Vec3::repeat(5.0), "one solution since: that solution");
        // A node a cut added (no history) beside one whose solutions were 5 and 7.
        p.resize(2);
        dv = vec![Vec3::repeat(7.0), Vec3::repeat(2.0)];
        p.predict(&mut dv);
        assert_eq!(dv[0], Vec3::repeat(9.0));
        assert_eq!(dv[1], Vec3::repeat(4.0), "a line from the zero it did not have");
    }
}
