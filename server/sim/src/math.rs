//! Small geometric helpers shared by the tissue models: closest points, distances,
//! intersections and triangle quality. All lengths are in metres.

pub use nalgebra::{Matrix3, Quaternion, UnitQuaternion, Vector3};

/// A unit quaternion from (w, x, y, z), renormalised (inputs are checked to be within
/// 1e-3 of unit length before they get here).
pub fn quat_from_wxyz(w: f64, x: f64, y: f64, z: f64) -> Quat {
    Quat::from_quaternion(Quaternion::new(w, x, y, z))
}

/// A unit quaternion from (w, x, y, z) taken as is, bit for bit (they were normalised
/// before, e.g. on the other side of a lock-free handoff).
pub fn quat_from_wxyz_exact(w: f64, x: f64, y: f64, z: f64) -> Quat {
    Quat::new_unchecked(Quaternion::new(w, x, y, z))
}

/// A 3-vector of f64 (positions in m, velocities in m/s, forces in N).
pub type Vec3 = Vector3<f64>;
/// A unit quaternion (rotation).
pub type Quat = UnitQuaternion<f64>;

/// A rigid pose: position in m and orientation as a unit quaternion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pose {
    pub position_m: Vec3,
    pub orientation: Quat,
}

impl Pose {
    pub fn new(position_m: Vec3, orientation: Quat) -> Self {
        Self { position_m, orientation }
    }

    /// The tool's axis: its local +z in world space (unit length).
    pub fn axis(&self) -> Vec3 {
        self.orientation * Vec3::z()
    }

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.position_m.iter().all(|c| c.is_finite())
            && self.orientation.coords.iter().all(|c| c.is_finite())
    }
}

impl Default for Pose {
    fn default() -> Self {
        Self { position_m: Vec3::zeros(), orientation: Quat::identity() }
    }
}

/// `v` without its component along the unit vector `n` (in the plane normal to `n`).
pub fn across(v: &Vec3, n: &Vec3) -> Vec3 {
    v - n * v.dot(n)
}

/// Closest point on segment `a`–`b` to `p`: returns (parameter in [0, 1], point).
pub fn closest_point_on_segment(p: &Vec3, a: &Vec3, b: &Vec3) -> (f64, Vec3) {
    let ab = b - a;
    let len2 = ab.norm_squared();
    if len2 <= f64::MIN_POSITIVE {
        return (0.0, *a);
    }
    let t = ((p - a).dot(&ab) / len2).clamp(0.0, 1.0);
    (t, a + ab * t)
}

/// Closest point on triangle `a`,`b`,`c` to `p` (Ericson, Real-Time Collision Detection 5.1.5).
pub fn closest_point_on_triangle(p: &Vec3, a: &Vec3, b: &Vec3, c: &Vec3) -> Vec3 {
    let ab = b - a;
    let ac = c - a;
    let ap = p - a;
    let d1 = ab.dot(&ap);
    let d2 = ac.dot(&ap);
    if d1 <= 0.0 && d2 <= 0.0 {
        return *a;
    }
    let bp = p - b;
    let d3 = ab.dot(&bp);
    let d4 = ac.dot(&bp);
    if d3 >= 0.0 && d4 <= d3 {
        return *b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let d5 = ab.dot(&cp);
    let d6 = ac.dot(&cp);
    if d6 >= 0.0 && d5 <= d6 {
        return *c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// Intersection of segment `p0`–`p1` with triangle `a`,`b`,`c` (Möller–Trumbore, both
/// faces). Returns the segment parameter in [0, 1] of the hit.
pub fn segment_triangle_intersection(p0: &Vec3, p1: &Vec3, a: &Vec3, b: &Vec3, c: &Vec3) -> Option<f64> {
    let dir = p1 - p0;
    let e1 = b - a;
    let e2 = c - a;
    let pvec = dir.cross(&e2);
    let det = e1.dot(&pvec);
    let scale = e1.norm() * e2.norm() * dir.norm();
    if det.abs() <= 1e-14 * scale {
        return None;
    }
    let inv = 1.0 / det;
    let tvec = p0 - a;
    let u = tvec.dot(&pvec) * inv;
    if !(0.0..=1.0).contains(&u) {
        return None;
    }
    let qvec = tvec.cross(&e1);
    let v = dir.dot(&qvec) * inv;
    if v < 0.0 || u + v > 1.0 {
        return None;
    }
    let t = e2.dot(&qvec) * inv;
    (0.0..=1.0).contains(&t).then_some(t)
}

/// Shortest distance between segments `p0`–`p1` and `q0`–`q1`.
pub fn segment_segment_distance(p0: &Vec3, p1: &Vec3, q0: &Vec3, q1: &Vec3) -> f64 {
    let (p, q) = segment_segment_closest(p0, p1, q0, q1);
    (p - q).norm()
}

/// The closest points of segments `p0`–`p1` and `q0`–`q1` (on the first, on the second).
pub fn segment_segment_closest(p0: &Vec3, p1: &Vec3, q0: &Vec3, q1: &Vec3) -> (Vec3, Vec3) {
    // Ericson 5.1.9, with the degenerate cases folded into clamps.
    let d1 = p1 - p0;
    let d2 = q1 - q0;
    let r = p0 - q0;
    let a = d1.norm_squared();
    let e = d2.norm_squared();
    let f = d2.dot(&r);
    let (s, t);
    if a <= f64::MIN_POSITIVE && e <= f64::MIN_POSITIVE {
        return (*p0, *q0);
    }
    if a <= f64::MIN_POSITIVE {
        s = 0.0;
        t = (f / e).clamp(0.0, 1.0);
    } else {
        let c = d1.dot(&r);
        if e <= f64::MIN_POSITIVE {
            t = 0.0;
            s = (-c / a).clamp(0.0, 1.0);
        } else {
            let b = d1.dot(&d2);
            let denom = a * e - b * b;
            let mut s0 = if denom > 1e-300 { ((b * f - c * e) / denom).clamp(0.0, 1.0) } else { 0.0 };
            let mut t0 = (b * s0 + f) / e;
            if t0 < 0.0 {
                t0 = 0.0;
                s0 = (-c / a).clamp(0.0, 1.0);
            } else if t0 > 1.0 {
                t0 = 1.0;
                s0 = ((b - c) / a).clamp(0.0, 1.0);
            }
            s = s0;
            t = t0;
        }
    }
    (p0 + d1 * s, q0 + d2 * t)
}

/// The closest points of segment `a`–`b` and triangle `tri` (on the segment, on the
/// triangle): where the segment crosses the triangle, that point twice.
pub fn segment_triangle_closest(a: &Vec3, b: &Vec3, tri: &[Vec3; 3]) -> (Vec3, Vec3) {
    let [p, q, r] = tri;
    if let Some(t) = segment_triangle_intersection(a, b, p, q, r) {
        let at = a + (b - a) * t;
        return (at, at);
    }
    // Otherwise the closest pair has an end of the segment or an edge of the triangle.
    let ends = [a, b].map(|x| (*x, closest_point_on_triangle(x, p, q, r)));
    let edges = [(p, q), (q, r), (r, p)].map(|(u, v)| segment_segment_closest(a, b, u, v));
    ends.into_iter().chain(edges).min_by(|x, y| (x.0 - x.1).norm_squared().total_cmp(&(y.0 - y.1).norm_squared())).expect("five candidates")
}

/// Area of triangle `a`,`b`,`c` in m².
pub fn triangle_area(a: &Vec3, b: &Vec3, c: &Vec3) -> f64 {
    0.5 * (b - a).cross(&(c - a)).norm()
}

/// Unnormalised normal (b − a) × (c − a): its length is twice the area.
pub fn triangle_normal(a: &Vec3, b: &Vec3, c: &Vec3) -> Vec3 {
    (b - a).cross(&(c - a))
}

/// Smallest interior angle of triangle `a`,`b`,`c`, in degrees (0 for a degenerate one).
pub fn triangle_min_angle_deg(a: &Vec3, b: &Vec3, c: &Vec3) -> f64 {
    let angle = |p: &Vec3, q: &Vec3, r: &Vec3| -> f64 {
        let u = q - p;
        let v = r - p;
        let nu = u.norm();
        let nv = v.norm();
        if nu <= 0.0 || nv <= 0.0 {
            return 0.0;
        }
        (u.dot(&v) / (nu * nv)).clamp(-1.0, 1.0).acos().to_degrees()
    };
    angle(a, b, c).min(angle(b, c, a)).min(angle(c, a, b))
}

/// Any unit vector perpendicular to `axis` (deterministic).
pub fn any_perpendicular(axis: &Vec3) -> Vec3 {
    let helper = if axis.x.abs() < 0.6 { Vec3::x() } else { Vec3::y() };
    axis.cross(&helper).normalize()
}

/// Barycentric coordinates of the point of triangle `a`,`b`,`c` closest to `p`.
pub fn barycentric_closest(p: &Vec3, a: &Vec3, b: &Vec3, c: &Vec3) -> [f64; 3] {
    barycentric_in_plane(&closest_point_on_triangle(p, a, b, c), a, b, c).unwrap_or([1.0, 0.0, 0.0])
}

/// Barycentric coordinates of `p`'s projection onto the plane of triangle `a`,`b`,`c`,
/// unclamped (negative outside the triangle); None for a degenerate triangle.
pub fn barycentric_in_plane(p: &Vec3, a: &Vec3, b: &Vec3, c: &Vec3) -> Option<[f64; 3]> {
    let v0 = b - a;
    let v1 = c - a;
    let v2 = p - a;
    let d00 = v0.dot(&v0);
    let d01 = v0.dot(&v1);
    let d11 = v1.dot(&v1);
    let d20 = v2.dot(&v0);
    let d21 = v2.dot(&v1);
    let denom = d00 * d11 - d01 * d01;
    if denom.abs() <= f64::MIN_POSITIVE {
        return None;
    }
    let v = (d11 * d20 - d01 * d21) / denom;
    let w = (d00 * d21 - d01 * d20) / denom;
    Some([1.0 - v - w, v, w])
}

/// The stretch of segment `a`–`b` that lies over triangle `tri` (its projection along
/// the triangle's normal inside the triangle): the barycentric coordinates of the
/// stretch's two ends on the triangle, the one nearer `a` first; None where no part of
/// the segment lies over it. Barycentric coordinates are affine along the segment, so
/// the stretch is the segment's parameters where all three stay non-negative.
pub fn segment_over_triangle(a: &Vec3, b: &Vec3, tri: &[Vec3; 3]) -> Option<([f64; 3], [f64; 3])> {
    let [p, q, r] = tri;
    let (from, to) = (barycentric_in_plane(a, p, q, r)?, barycentric_in_plane(b, p, q, r)?);
    let (mut lo, mut hi) = (0.0f64, 1.0f64);
    for k in 0..3 {
        let change = to[k] - from[k];
        if change.abs() <= 1e-15 {
            if from[k] < 0.0 {
                return None;
            }
        } else if change > 0.0 {
            lo = lo.max(-from[k] / change);
        } else {
            hi = hi.min(-from[k] / change);
        }
    }
    let at = |t: f64| std::array::from_fn(|k| (from[k] + (to[k] - from[k]) * t).max(0.0));
    (lo <= hi).then(|| (at(lo), at(hi)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn closest_point_on_segment_clamps_to_ends() {
        let a = Vec3::new(0.0, 0.0, 0.0);
        let b = Vec3::new(1.0, 0.0, 0.0);
        assert_eq!(closest_point_on_segment(&Vec3::new(-1.0, 1.0, 0.0), &a, &b).0, 0.0);
        assert_eq!(closest_point_on_segment(&Vec3::new(2.0, 1.0, 0.0), &a, &b).0, 1.0);
        let (t, p) = closest_point_on_segment(&Vec3::new(0.25, 3.0, 0.0), &a, &b);
        assert!((t - 0.25).abs() < 1e-15 && (p - Vec3::new(0.25, 0.0, 0.0)).norm() < 1e-15);
    }

    #[test]
    fn segment_hits_triangle_at_expected_parameter() {
        let (a, b, c) = (Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0));
        let t = segment_triangle_intersection(&Vec3::new(0.2, 0.2, 1.0), &Vec3::new(0.2, 0.2, -3.0), &a, &b, &c);
        assert!((t.unwrap() - 0.25).abs() < 1e-12);
        assert!(segment_triangle_intersection(&Vec3::new(0.8, 0.8, 1.0), &Vec3::new(0.8, 0.8, -1.0), &a, &b, &c).is_none());
    }

    #[test]
    fn closest_point_on_triangle_regions() {
        let (a, b, c) = (Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0));
        assert!((closest_point_on_triangle(&Vec3::new(0.2, 0.2, 5.0), &a, &b, &c) - Vec3::new(0.2, 0.2, 0.0)).norm() < 1e-15);
        assert_eq!(closest_point_on_triangle(&Vec3::new(-1.0, -1.0, 0.0), &a, &b, &c), a);
        let p = closest_point_on_triangle(&Vec3::new(1.0, 1.0, 0.0), &a, &b, &c);
        assert!((p - Vec3::new(0.5, 0.5, 0.0)).norm() < 1e-15);
    }

    #[test]
    fn segment_distance_of_skew_lines() {
        let d = segment_segment_distance(
            &Vec3::new(-1.0, 0.0, 0.0),
            &Vec3::new(1.0, 0.0, 0.0),
            &Vec3::new(0.0, -1.0, 2.0),
            &Vec3::new(0.0, 1.0, 2.0),
        );
        assert!((d - 2.0).abs() < 1e-15);
    }

    #[test]
    fn a_segment_meets_a_triangle_where_it_crosses_or_at_its_nearest_end_or_edge() {
        let tri = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
        // Through the inside: the crossing point, twice.
        let (s, t) = segment_triangle_closest(&Vec3::new(0.2, 0.3, 1.0), &Vec3::new(0.2, 0.3, -1.0), &tri);
        assert!((s - Vec3::new(0.2, 0.3, 0.0)).norm() < 1e-12 && (s - t).norm() < 1e-12);
        // Above the inside, not reaching it: its lower end and the point below.
        let (s, t) = segment_triangle_closest(&Vec3::new(0.2, 0.3, 0.5), &Vec3::new(0.2, 0.3, 2.0), &tri);
        assert!((s - Vec3::new(0.2, 0.3, 0.5)).norm() < 1e-12 && (t - Vec3::new(0.2, 0.3, 0.0)).norm() < 1e-12);
        // Across, beyond the hypotenuse: its nearest point to that edge.
        let (s, t) = segment_triangle_closest(&Vec3::new(1.0, 1.0, -1.0), &Vec3::new(1.0, 1.0, 1.0), &tri);
        assert!((s - Vec3::new(1.0, 1.0, 0.0)).norm() < 1e-12 && (t - Vec3::new(0.5, 0.5, 0.0)).norm() < 1e-12);
        assert!((segment_segment_distance(&Vec3::new(1.0, 1.0, -1.0), &Vec3::new(1.0, 1.0, 1.0), &tri[1], &tri[2]) - 0.5f64.sqrt()).abs() < 1e-12);
    }

    #[test]
    fn the_stretch_of_a_segment_over_a_triangle_is_clipped_to_its_edges() {
        let tri = [Vec3::new(0.0, 0.0, 0.0), Vec3::new(1.0, 0.0, 0.0), Vec3::new(0.0, 1.0, 0.0)];
        let point = |b: [f64; 3]| tri[0] * b[0] + tri[1] * b[1] + tri[2] * b[2];
        // Above the triangle along y = 0.25, from x = -1 to 2: over it from x = 0 to 0.75.
        let (near, far) = segment_over_triangle(&Vec3::new(-1.0, 0.25, 0.3), &Vec3::new(2.0, 0.25, 0.3), &tri).unwrap();
        assert!((point(near) - Vec3::new(0.0, 0.25, 0.0)).norm() < 1e-12 && (point(far) - Vec3::new(0.75, 0.25, 0.0)).norm() < 1e-12);
        // Wholly over it (below the plane too): its own ends, projected.
        let (near, far) = segment_over_triangle(&Vec3::new(0.1, 0.1, -0.5), &Vec3::new(0.3, 0.2, 0.5), &tri).unwrap();
        assert!((point(near) - Vec3::new(0.1, 0.1, 0.0)).norm() < 1e-12 && (point(far) - Vec3::new(0.3, 0.2, 0.0)).norm() < 1e-12);
        // Beside it, and along the plane's normal over a point: none, and that point twice.
        assert!(segment_over_triangle(&Vec3::new(-1.0, 1.5, 0.0), &Vec3::new(2.0, 1.5, 0.0), &tri).is_none());
        assert!(segment_over_triangle(&Vec3::new(-1.0, -0.1, 0.0), &Vec3::new(2.0, -0.1, 0.0), &tri).is_none());
        let (near, far) = segment_over_triangle(&Vec3::new(0.2, 0.2, 1.0), &Vec3::new(0.2, 0.2, -1.0), &tri).unwrap();
        assert!((point(near) - Vec3::new(0.2, 0.2, 0.0)).norm() < 1e-12 && (point(far) - point(near)).norm() < 1e-12);
    }

    #[test]
    fn equilateral_min_angle_is_sixty() {
        let a = Vec3::new(0.0, 0.0, 0.0);
        let b = Vec3::new(1.0, 0.0, 0.0);
        let c = Vec3::new(0.5, 3f64.sqrt() / 2.0, 0.0);
        assert!((triangle_min_angle_deg(&a, &b, &c) - 60.0).abs() < 1e-9);
    }
}
