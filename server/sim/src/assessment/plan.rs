//! The planned incision's geometry: a polyline with an outward normal. Deviation is the
//! distance across the normal (in the surface, as seen from above), depth the distance
//! along it below the plan, and arc length locates a point along the plan.

use crate::math::{Vec3, across};

/// The most points a plan may have.
pub const MAX_PLAN_POINTS: usize = 10_000;

#[derive(Debug, Clone, PartialEq)]
pub struct Plan {
    points: Vec<Vec3>,
    /// Arc length at each point, m (3-D, along the plan).
    arc: Vec<f64>,
    /// Unit outward normal.
    pub normal: Vec3,
    /// Half-width of the tolerance band, m.
    pub band_m: f64,
}

/// Where a point lies relative to the plan.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Nearest {
    /// Distance across the normal to the nearest point of the plan, m.
    pub deviation_m: f64,
    /// Arc length of that point along the plan, m.
    pub arc_m: f64,
    /// How far below the plan (against the normal) the point is, m.
    pub depth_m: f64,
}

impl Plan {
    /// A plan through `points` (at least two, consecutive ones apart across `normal`).
    pub fn new(points: &[Vec3], normal: Vec3, band_m: f64) -> Result<Plan, String> {
        if points.len() < 2 {
            return Err(format!("a planned incision needs at least two points, got {}", points.len()));
        }
        if points.len() > MAX_PLAN_POINTS {
            return Err(format!("{} points; at most {MAX_PLAN_POINTS} are allowed", points.len()));
        }
        let mut arc = Vec::with_capacity(points.len());
        arc.push(0.0);
        for i in 1..points.len() {
            let d = points[i] - points[i - 1];
            if across(&d, &normal).norm() < 1e-6 {
                return Err(format!(
                    "points {} and {i} are less than 1 µm apart across the normal; consecutive points must differ along the surface",
                    i - 1
                ));
            }
            arc.push(arc[i - 1] + d.norm());
        }
        Ok(Plan { points: points.to_vec(), arc, normal, band_m })
    }

    /// The plan's points, m.
    pub fn points(&self) -> &[Vec3] {
        &self.points
    }

    /// The plan's length, m.
    pub fn length_m(&self) -> f64 {
        *self.arc.last().expect("a plan has at least two points")
    }

    /// The plan's nearest point to `p`, measured across the normal.
    pub fn nearest(&self, p: &Vec3) -> Nearest {
        let mut best = Nearest { deviation_m: f64::INFINITY, arc_m: 0.0, depth_m: 0.0 };
        for i in 1..self.points.len() {
            let a = self.points[i - 1];
            let segment = self.points[i] - a;
            let flat = across(&segment, &self.normal);
            let offset = across(&(p - a), &self.normal);
            let t = (offset.dot(&flat) / flat.norm_squared()).clamp(0.0, 1.0);
            let deviation = (offset - flat * t).norm();
            if deviation < best.deviation_m {
                let on_plan = a + segment * t;
                best = Nearest { deviation_m: deviation, arc_m: self.arc[i - 1] + t * segment.norm(), depth_m: (on_plan - p).dot(&self.normal) };
            }
        }
        best
    }
}


#[cfg(test)]
mod tests {
    use super::*;

    fn straight() -> Plan {
        Plan::new(&[Vec3::new(-0.02, 0.0, 0.0), Vec3::new(0.02, 0.0, 0.0)], Vec3::z(), 0.002).unwrap()
    }

    #[test]
    fn deviation_is_measured_across_the_normal_and_depth_along_it() {
        let plan = straight();
        let n = plan.nearest(&Vec3::new(0.005, 0.001, -0.004));
        assert!((n.deviation_m - 0.001).abs() < 1e-15);
        assert!((n.arc_m - 0.025).abs() < 1e-15);
        assert!((n.depth_m - 0.004).abs() < 1e-15);
        // Beyond the end: the distance to the end point.
        let n = plan.nearest(&Vec3::new(0.023, 0.004, 0.0));
        assert!((n.deviation_m - 0.005).abs() < 1e-12);
        assert_eq!(n.arc_m, 0.04);
    }

    #[test]
    fn an_l_shaped_plan_measures_arc_length_around_the_corner() {
        let plan = Plan::new(&[Vec3::zeros(), Vec3::new(0.01, 0.0, 0.0), Vec3::new(0.01, 0.01, 0.0)], Vec3::z(), 0.001).unwrap();
        assert!((plan.length_m() - 0.02).abs() < 1e-15);
        let n = plan.nearest(&Vec3::new(0.0105, 0.004, 0.0));
        assert!((n.deviation_m - 0.0005).abs() < 1e-12);
        assert!((n.arc_m - 0.014).abs() < 1e-12);
    }

    #[test]
    fn degenerate_plans_are_refused_with_the_reason() {
        let e = Plan::new(&[Vec3::zeros()], Vec3::z(), 0.001).unwrap_err();
        assert!(e.contains("at least two points"), "{e}");
        let e = Plan::new(&[Vec3::zeros(), Vec3::new(0.0, 0.0, -0.01)], Vec3::z(), 0.001).unwrap_err();
        assert!(e.contains("apart across the normal"), "{e}");
    }
}
