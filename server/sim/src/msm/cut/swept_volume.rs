//! Stage 1 of the three-stage cut (paper Section 2.3.1, Algorithm 1): the volume the
//! blade sweeps between two consecutive cut updates, and what it removes.
//!
//! The blade part near the surface moves from segment B0 to segment B1; the swept
//! volume is every point within `radius` of the ruled quad B0→B1 (split in two
//! triangles) or of the incision curve itself. Nodes inside are removed with their
//! springs and triangles; springs (edges) the volume touches are removed with their
//! triangles. What is removed is the paper's grey "incision generation area".

use crate::math::{Vec3, closest_point_on_triangle, segment_triangle_closest};

#[derive(Debug, Clone, PartialEq)]
pub struct SweptVolume {
    /// B0.start, B0.end, B1.end, B1.start.
    quad: [Vec3; 4],
    /// Points of the incision curve (a polyline).
    curve: Vec<Vec3>,
    pub radius_m: f64,
}

impl SweptVolume {
    pub fn new(blade_before: (Vec3, Vec3), blade_after: (Vec3, Vec3), curve: &[Vec3], radius_m: f64) -> Self {
        Self { quad: [blade_before.0, blade_before.1, blade_after.1, blade_after.0], curve: curve.to_vec(), radius_m }
    }

    fn quad_triangles(&self) -> [[Vec3; 3]; 2] {
        let [a, b, c, d] = self.quad;
        [[a, b, c], [a, c, d]]
    }

    /// Axis-aligned bounds grown by `margin`: (min, max).
    pub fn bounds(&self, margin: f64) -> (Vec3, Vec3) {
        let grow = Vec3::repeat(self.radius_m + margin);
        let mut lo = self.quad[0];
        let mut hi = self.quad[0];
        for p in self.quad.iter().chain(self.curve.iter()) {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        (lo - grow, hi + grow)
    }

    /// True when `p` is within the radius of the swept quad or of the curve.
    pub fn contains(&self, p: &Vec3) -> bool {
        let r2 = self.radius_m * self.radius_m;
        self.quad_triangles().iter().any(|[a, b, c]| (closest_point_on_triangle(p, a, b, c) - p).norm_squared() <= r2)
            || self.curve.windows(2).any(|w| (crate::math::closest_point_on_segment(p, &w[0], &w[1]).1 - p).norm_squared() <= r2)
    }

    /// True when the segment (a spring) `a`–`b` comes within the radius of the swept quad.
    pub fn touches_segment(&self, a: &Vec3, b: &Vec3) -> bool {
        self.quad_triangles().iter().any(|tri| segment_triangle_distance(a, b, tri) <= self.radius_m)
    }

    /// True when the incision curve passes within the radius of triangle `tri`.
    pub fn curve_touches_triangle(&self, tri: &[Vec3; 3]) -> bool {
        self.curve.windows(2).any(|w| segment_triangle_distance(&w[0], &w[1], tri) <= self.radius_m)
    }
}

/// Distance between segment `a`–`b` and a triangle (0 when they intersect).
pub fn segment_triangle_distance(a: &Vec3, b: &Vec3, tri: &[Vec3; 3]) -> f64 {
    let (on_segment, on_triangle) = segment_triangle_closest(a, b, tri);
    (on_segment - on_triangle).norm()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vertical_blade_moving_along_x_sweeps_a_strip() {
        let before = (Vec3::new(0.0, 0.0, -0.01), Vec3::new(0.0, 0.0, 0.01));
        let after = (Vec3::new(0.02, 0.0, -0.01), Vec3::new(0.02, 0.0, 0.01));
        let v = SweptVolume::new(before, after, &[Vec3::zeros(), Vec3::new(0.02, 0.0, 0.0)], 1e-3);
        assert!(v.contains(&Vec3::new(0.01, 0.0009, 0.0)));
        assert!(!v.contains(&Vec3::new(0.01, 0.0011, 0.0)));
        assert!(!v.contains(&Vec3::new(0.0215, 0.0, 0.0)));
        // A spring crossing the path is touched; one beside it is not.
        assert!(v.touches_segment(&Vec3::new(0.01, -0.003, 0.0), &Vec3::new(0.01, 0.003, 0.0)));
        assert!(!v.touches_segment(&Vec3::new(0.0, 0.002, 0.0), &Vec3::new(0.02, 0.002, 0.0)));
    }

    #[test]
    fn segment_triangle_distance_cases() {
        let tri = [Vec3::zeros(), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
        assert_eq!(segment_triangle_distance(&Vec3::new(0.2, 0.2, -1.0), &Vec3::new(0.2, 0.2, 1.0), &tri), 0.0);
        let d = segment_triangle_distance(&Vec3::new(0.2, 0.2, 0.5), &Vec3::new(0.3, 0.3, 2.0), &tri);
        assert!((d - 0.5).abs() < 1e-12);
        let d = segment_triangle_distance(&Vec3::new(2.0, -1.0, 0.0), &Vec3::new(2.0, 1.0, 0.0), &tri);
        assert!((d - 1.0).abs() < 1e-12);
    }
}
