//! Stage 2 of the three-stage cut (paper Section 2.3.2, Eq. 5–8): the incision is a
//! cubic Bézier curve; a long cut is a chain of cubic segments joined with C1
//! continuity whose end moves with the tool as the cut grows.
//!
//! Each new segment starts where the previous one ended, with the previous segment's
//! end derivative (so the chain is C1), and ends at the blade's newest crossing point
//! with the chord as its end derivative.
//!
//! One departure from the paper: where a C1 join would carry the new segment farther
//! from its chord than the blade's swept path reaches (a short update after a long one,
//! or a sharp turn after a fast straight stretch: the old derivative is many chords long,
//! and the curve hooks out sideways or past its end, where the blade never went), the
//! start derivative keeps its direction but is shortened until the segment stays within
//! that reach. The join is then G1 (same tangent direction) rather than C1. Ordinary
//! updates, whose curve stays near its chord, are C1 as in the paper.

use crate::math::{Vec3, closest_point_on_segment};

/// A cubic Bézier segment with control points P0..P3 (P0 and P3 on the curve).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CubicBezier {
    pub control: [Vec3; 4],
}

impl CubicBezier {
    /// P(a) = Σ Pk·B_k,3(a), with the Bernstein polynomials of Eq. 7.
    pub fn point(&self, a: f64) -> Vec3 {
        let b = 1.0 - a;
        let [p0, p1, p2, p3] = self.control;
        p0 * (b * b * b) + p1 * (3.0 * a * b * b) + p2 * (3.0 * a * a * b) + p3 * (a * a * a)
    }

    /// The matrix form of Eq. 8: [a³ a² a 1]·M·[P0 P1 P2 P3]ᵀ.
    pub fn point_matrix_form(&self, a: f64) -> Vec3 {
        const M: [[f64; 4]; 4] = [[-1.0, 3.0, -3.0, 1.0], [3.0, -6.0, 3.0, 0.0], [-3.0, 3.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]];
        let powers = [a * a * a, a * a, a, 1.0];
        let mut out = Vec3::zeros();
        for (k, p) in self.control.iter().enumerate() {
            let weight: f64 = (0..4).map(|r| powers[r] * M[r][k]).sum();
            out += p * weight;
        }
        out
    }

    /// dP/da.
    pub fn derivative(&self, a: f64) -> Vec3 {
        let b = 1.0 - a;
        let [p0, p1, p2, p3] = self.control;
        (p1 - p0) * (3.0 * b * b) + (p2 - p1) * (6.0 * a * b) + (p3 - p2) * (3.0 * a * a)
    }

    /// The segment from `p0` to `p3` with end derivatives `d0` and `d3` (Hermite form).
    pub fn from_hermite(p0: Vec3, d0: Vec3, p3: Vec3, d3: Vec3) -> Self {
        Self { control: [p0, p0 + d0 / 3.0, p3 - d3 / 3.0, p3] }
    }

    /// How far the curve strays from the straight segment P0–P3, m (the largest
    /// distance of 32 points along it: sideways, behind its start or past its end).
    pub fn stray_from_chord(&self) -> f64 {
        const N: usize = 32;
        let [p0, .., p3] = self.control;
        (1..N)
            .map(|k| {
                let p = self.point(k as f64 / N as f64);
                (p - closest_point_on_segment(&p, &p0, &p3).1).norm()
            })
            .fold(0.0, f64::max)
    }

    /// Arc length, m (polyline of 64 chords: far below the mesh resolution in error).
    pub fn length(&self) -> f64 {
        const N: usize = 64;
        (0..N).map(|k| (self.point((k + 1) as f64 / N as f64) - self.point(k as f64 / N as f64)).norm()).sum()
    }

    /// `segments` + 1 points spaced evenly along the arc, from P0 to P3.
    pub fn sample_by_arc_length(&self, segments: usize, out: &mut Vec<Vec3>) {
        const N: usize = 256;
        let mut table = [0.0f64; N + 1];
        let mut prev = self.point(0.0);
        for k in 1..=N {
            let p = self.point(k as f64 / N as f64);
            table[k] = table[k - 1] + (p - prev).norm();
            prev = p;
        }
        let total = table[N];
        out.clear();
        out.push(self.control[0]);
        let mut k = 0;
        for s in 1..segments {
            let target = total * s as f64 / segments as f64;
            while k < N && table[k + 1] < target {
                k += 1;
            }
            let span = (table[k + 1] - table[k]).max(f64::MIN_POSITIVE);
            let a = (k as f64 + ((target - table[k]) / span).clamp(0.0, 1.0)) / N as f64;
            out.push(self.point(a));
        }
        out.push(self.control[3]);
    }
}

/// The incision of one cut stroke: a C1 chain of cubic segments.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct BezierChain {
    pub segments: Vec<CubicBezier>,
}

impl BezierChain {
    /// Grows the incision from `start` to `end` and returns the new segment. The start
    /// derivative is the previous segment's end derivative (C1), halved until the
    /// segment strays at most `max_stray_m` from its chord (see the module's note); the
    /// first segment is straight.
    pub fn extend(&mut self, start: Vec3, end: Vec3, max_stray_m: f64) -> CubicBezier {
        let chord = end - start;
        let mut start_derivative = match self.segments.last() {
            Some(prev) => prev.derivative(1.0),
            None => chord,
        };
        let mut segment = CubicBezier::from_hermite(start, start_derivative, end, chord);
        // Each halving halves the part of the curve the start derivative moves off the
        // chord (the curve is linear in it), so a few rounds always suffice; the cap only
        // guards against a non-finite input.
        for _ in 0..32 {
            if segment.stray_from_chord() <= max_stray_m {
                break;
            }
            start_derivative *= 0.5;
            segment = CubicBezier::from_hermite(start, start_derivative, end, chord);
        }
        self.segments.push(segment);
        segment
    }

    pub fn length(&self) -> f64 {
        self.segments.iter().map(CubicBezier::length).sum()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> CubicBezier {
        CubicBezier { control: [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 2.0, 0.0), Vec3::new(3.0, 2.0, 1.0), Vec3::new(4.0, 0.0, 0.0)] }
    }

    #[test]
    fn bernstein_and_matrix_forms_agree_and_interpolate_ends() {
        let c = sample();
        for k in 0..=10 {
            let a = k as f64 / 10.0;
            assert!((c.point(a) - c.point_matrix_form(a)).norm() < 1e-12);
        }
        assert_eq!(c.point(0.0), c.control[0]);
        assert_eq!(c.point(1.0), c.control[3]);
    }

    #[test]
    fn derivative_matches_finite_difference() {
        let c = sample();
        let eps = 1e-6;
        for a in [0.1, 0.5, 0.9] {
            let fd = (c.point(a + eps) - c.point(a - eps)) / (2.0 * eps);
            assert!((fd - c.derivative(a)).norm() < 1e-6);
        }
    }

    #[test]
    fn chain_is_c1_at_every_joint() {
        let mut chain = BezierChain::default();
        let points = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(0.01, 0.0, 0.0), Vec3::new(0.02, 0.004, 0.0), Vec3::new(0.028, 0.012, 0.0)];
        for w in points.windows(2) {
            chain.extend(w[0], w[1], 1.0);
        }
        for pair in chain.segments.windows(2) {
            assert_eq!(pair[0].point(1.0), pair[1].point(0.0), "C0");
            assert!((pair[0].derivative(1.0) - pair[1].derivative(0.0)).norm() < 1e-15, "C1");
        }
        // A straight first segment has the chord as its length.
        assert!((chain.segments[0].length() - 0.01).abs() < 1e-12);
    }

    #[test]
    fn a_short_update_after_a_long_one_keeps_its_tangent_but_not_its_hook() {
        // A fast first stroke 35 mm long, then a 4 mm update turning 60°: the C1 join
        // would start the new segment with a derivative of 35 mm, and the curve would
        // swing about 5 mm out past the blade's path.
        let mut chain = BezierChain::default();
        let (a, b) = (Vec3::zeros(), Vec3::new(0.035, 0.0, 0.0));
        let c = b + Vec3::new(0.002, 0.0035, 0.0);
        chain.extend(a, b, 1.25e-3);
        let c1 = CubicBezier::from_hermite(b, chain.segments[0].derivative(1.0), c, c - b);
        assert!(c1.stray_from_chord() > 4e-3, "the C1 segment should hook: {}", c1.stray_from_chord());
        let segment = chain.extend(b, c, 1.25e-3);
        assert!(segment.stray_from_chord() <= 1.25e-3, "{}", segment.stray_from_chord());
        assert_eq!((segment.point(0.0), segment.point(1.0)), (b, c));
        // G1: the same tangent direction as the previous segment's end, shorter.
        let (before, after) = (chain.segments[0].derivative(1.0), segment.derivative(0.0));
        assert!(before.normalize().dot(&after.normalize()) > 1.0 - 1e-12);
        assert!(after.norm() < 0.5 * before.norm());
        // An ordinary update (4 mm on, turning 60° back) stays C1.
        let d = c + Vec3::new(0.004, 0.0, 0.0);
        let next = chain.extend(c, d, 1.25e-3);
        assert_eq!(next.derivative(0.0), segment.derivative(1.0));
    }

    #[test]
    fn arc_length_sampling_is_even() {
        let c = sample();
        let mut pts = Vec::new();
        c.sample_by_arc_length(8, &mut pts);
        assert_eq!(pts.len(), 9);
        let gaps: Vec<f64> = pts.windows(2).map(|w| (w[1] - w[0]).norm()).collect();
        let mean = gaps.iter().sum::<f64>() / gaps.len() as f64;
        assert!(gaps.iter().all(|g| (g / mean - 1.0).abs() < 0.02), "{gaps:?}");
    }
}
