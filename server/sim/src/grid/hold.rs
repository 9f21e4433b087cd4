//! Contact that holds: a surface vertex touching a tool is pushed out of the tool on the
//! side it came in from, not radially from the tool's axis.
//!
//! A radial penalty (each vertex inside the capsule pushed away from the nearest point
//! of its axis) lets a probe through the tissue: pressed deeper than the ball's centre,
//! the vertices under it are pushed sideways and then up, and the probe slips between
//! them (a 6 mm probe went through a 30 kPa block at 0.97 N). Here each vertex in
//! contact remembers the capsule's outward normal where it came in, in the tool's own
//! frame (so it turns with the tool), and while it stays in contact it is pushed along
//! that normal by as far as the tool lies across the ray from it along the normal: the
//! ray's exit from the capsule. A vertex under the probe's ball is pushed down until it
//! is below the ball, however deep the probe goes; a vertex the tool has passed over is
//! pushed back out the side it came from. The contact lets go when the ray misses the
//! tool (the vertex has come out, or the tool has moved off it). A new contact's normal
//! is where its path relative to the tool over the step (the tool's motion) entered the
//! capsule, so a vertex the tool reached in one long step is not pushed out the far side;
//! one that came in through the tip's ball is held along the tool's axis (the tip a face
//! that pushes along the tool), since along the ball's inclined normal it would still
//! be pushed out sideways once the tool was a radius in. Near the tool's surface a vertex
//! is pushed along the surface's normal there, so a tool slides over the tissue as a
//! frictionless one does (see [`contact`]).

use crate::math::{Matrix3, Vec3, closest_point_on_segment};

/// A surface vertex in contact with a tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Touch {
    pub tool: usize,
    /// The capsule's outward unit normal where the vertex came in (kept while the
    /// contact lasts), in the tool's frame.
    pub normal_in_tool: Vec3,
    /// The step it was last in contact.
    pub step: u64,
}

impl crate::hash::HashState for Touch {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        (self.tool, self.normal_in_tool, self.step).hash_state(h);
    }
}

/// A tool's solid against the grid's vertices: the segment `a` (its tip) – `b` swept
/// by a ball of radius `radius` (a capsule), or, for a scalpel blade's plate, by its
/// rectangular section (a box from `a` to `b`, `radius` then its half-diagonal: what
/// bounds it).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub a: Vec3,
    pub b: Vec3,
    pub radius: f64,
    pub plate: Option<Plate>,
}

/// How far below its tip (along its axis) `tool` reaches as the grid holds it: a
/// cylinder is a capsule whose ball is centred on the tip, so by its radius; a blade's
/// plate and forceps' jaws end at the tip itself. Where to put a tool's tip so that its
/// end is at a given height (the load-time check, the fidelity calibration and the
/// schedules study press a probe into the body's top).
pub fn reach_below_tip(tool: &crate::tool::ToolShape) -> f64 {
    match tool.section {
        crate::tool::Section::Round => tool.radius_m,
        crate::tool::Section::Plate { .. } | crate::tool::Section::Jaws { .. } => 0.0,
    }
}

/// A blade's plate across the axis: `half_width` along `edge` (the way its edge faces,
/// a unit vector across the axis), `half_thickness` along `flat` (its flat's normal).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Plate {
    pub edge: Vec3,
    pub flat: Vec3,
    pub half_width: f64,
    pub half_thickness: f64,
}

impl Plate {
    /// `tool`'s plate turned by `rotation` (from the tool's frame into the frame the
    /// contact is solved in: the grid's, or the world's for the multirate haptic loop);
    /// None for a round tool and for forceps, whose jaws come as plates of their own
    /// (crate::tool::bodies).
    pub fn of_tool(tool: &crate::tool::ToolShape, rotation: &Matrix3<f64>) -> Option<Plate> {
        match tool.section {
            crate::tool::Section::Plate { half_width_m, half_thickness_m } => {
                let edge = rotation * tool.edge_local;
                Some(Plate { edge, flat: (rotation * Vec3::z()).cross(&edge), half_width: half_width_m, half_thickness: half_thickness_m })
            }
            crate::tool::Section::Round | crate::tool::Section::Jaws { .. } => None,
        }
    }
}

impl Capsule {
    /// A round tool: the segment `a`–`b` swept by a ball of `radius`.
    pub fn round(a: Vec3, b: Vec3, radius: f64) -> Self {
        Capsule { a, b, radius, plate: None }
    }

    /// How the tool draws a point at `p` that it holds on a triangle's inside towards its
    /// axis (grid::model::face_contact; the multirate patch likewise): the directions it
    /// draws along as a projection (across the axis; for a plate across its flat only:
    /// along its width, under its flat, the tissue is not in a groove) and the point's
    /// offset from the axis along them. None for a ball (no axis).
    pub fn centring(&self, p: &Vec3) -> Option<(Matrix3<f64>, Vec3)> {
        self.out_of_tip().map(|axis| {
            let on_axis = self.a + axis * (p - self.a).dot(&axis);
            match &self.plate {
                Some(plate) => (plate.flat * plate.flat.transpose(), plate.flat * plate.flat.dot(&(on_axis - p))),
                None => (Matrix3::identity() - axis * axis.transpose(), on_axis - p),
            }
        })
    }

    /// The solid's smallest half-size across its axis: a capsule's radius, half a plate's
    /// thickness (the depth scale of its shallow band, and what fits between vertices).
    pub fn half_size(&self) -> f64 {
        self.plate.map_or(self.radius, |plate| plate.half_thickness)
    }

    /// The box's three axes from the tip (along the tool, its edge, its flat's normal)
    /// with the half-extents across them, and its length.
    fn plate_axes(&self, plate: &Plate) -> ([Vec3; 3], [f64; 2], f64) {
        let along = self.b - self.a;
        let length = along.norm();
        ([along / length.max(1e-12), plate.edge, plate.flat], [plate.half_width, plate.half_thickness], length)
    }

    /// Where the line `p + t n` (n a unit vector) lies in the solid: its interval of t,
    /// or None if it misses. The solid is convex, so the interval is one: for a capsule
    /// the hull of the intervals of its two balls and of its cylinder between them; for a
    /// plate the intersection of its three slabs.
    pub fn interval(&self, p: &Vec3, n: &Vec3) -> Option<(f64, f64)> {
        if let Some(plate) = &self.plate {
            let (axes, half, length) = self.plate_axes(plate);
            let m = p - self.a;
            let bounds = [(0.0, length), (-half[0], half[0]), (-half[1], half[1])];
            let (mut lo, mut hi) = (f64::NEG_INFINITY, f64::INFINITY);
            for (axis, (min, max)) in axes.iter().zip(bounds) {
                let (at, going) = (m.dot(axis), n.dot(axis));
                if going.abs() < 1e-12 {
                    if at < min || at > max {
                        return None;
                    }
                    continue;
                }
                let (t0, t1) = ((min - at) / going, (max - at) / going);
                lo = lo.max(t0.min(t1));
                hi = hi.min(t0.max(t1));
            }
            return (lo <= hi).then_some((lo, hi));
        }
        let mut hull: Option<(f64, f64)> = None;
        let mut take = |lo: f64, hi: f64| {
            if lo <= hi {
                hull = Some(hull.map_or((lo, hi), |(l, h)| (l.min(lo), h.max(hi))));
            }
        };
        for centre in [self.a, self.b] {
            if let Some((lo, hi)) = quadratic_interval(1.0, (p - centre).dot(n), (p - centre).norm_squared() - self.radius * self.radius) {
                take(lo, hi);
            }
        }
        let axis = self.b - self.a;
        let length = axis.norm();
        if length > 1e-12 {
            let w = axis / length;
            let m = p - self.a;
            let (m_along, n_along) = (m.dot(&w), n.dot(&w));
            let (m_across, n_across) = (m - w * m_along, n - w * n_along);
            // The infinite cylinder's interval, then the slab 0 ≤ along ≤ length.
            let across = if n_across.norm_squared() < 1e-18 {
                (m_across.norm_squared() <= self.radius * self.radius).then_some((f64::NEG_INFINITY, f64::INFINITY))
            } else {
                quadratic_interval(n_across.norm_squared(), m_across.dot(&n_across), m_across.norm_squared() - self.radius * self.radius)
            };
            let slab = if n_along.abs() < 1e-12 {
                (0.0..=length).contains(&m_along).then_some((f64::NEG_INFINITY, f64::INFINITY))
            } else {
                let (t0, t1) = (-m_along / n_along, (length - m_along) / n_along);
                Some((t0.min(t1), t0.max(t1)))
            };
            if let (Some((c0, c1)), Some((s0, s1))) = (across, slab) {
                take(c0.max(s0), c1.min(s1));
            }
        }
        hull
    }

    /// How far `p` must move along the unit vector `n` to be clear of the capsule: the
    /// exit of the ray from `p` along `n`, if the capsule lies across it ahead of `p`
    /// (or around it).
    pub fn depth_along(&self, p: &Vec3, n: &Vec3) -> Option<f64> {
        self.interval(p, n).map(|(_, exit)| exit).filter(|&exit| exit > 0.0)
    }

    /// The outward normal at the surface point nearest `p` (a point on the axis: any
    /// normal across it), and how far inside `p` is (negative outside).
    pub fn radial(&self, p: &Vec3) -> (Vec3, f64) {
        if let Some(plate) = &self.plate {
            return self.plate_nearest(plate, p);
        }
        let (_, closest) = closest_point_on_segment(p, &self.a, &self.b);
        let offset = p - closest;
        let distance = offset.norm();
        let normal = if distance > 1e-12 { offset / distance } else { (self.b - self.a).cross(&Vec3::x()).try_normalize(1e-9).unwrap_or(Vec3::y()) };
        (normal, self.radius - distance)
    }

    /// [`Self::radial`] for a plate: inside, the face nearest `p`; outside, from the box's
    /// point nearest `p` towards it.
    fn plate_nearest(&self, plate: &Plate, p: &Vec3) -> (Vec3, f64) {
        let (axes, half, length) = self.plate_axes(plate);
        let m = p - self.a;
        let at = axes.map(|axis| m.dot(&axis));
        let bounds = [(0.0, length), (-half[0], half[0]), (-half[1], half[1])];
        let inside = (0..3).all(|k| at[k] >= bounds[k].0 && at[k] <= bounds[k].1);
        if inside {
            let mut best = (axes[0] * -1.0, at[0]);
            for k in 0..3 {
                for (depth, normal) in [(at[k] - bounds[k].0, -axes[k]), (bounds[k].1 - at[k], axes[k])] {
                    if depth < best.1 {
                        best = (normal, depth);
                    }
                }
            }
            return best;
        }
        let outside: Vec3 = (0..3).map(|k| axes[k] * (at[k] - at[k].clamp(bounds[k].0, bounds[k].1))).sum();
        let distance = outside.norm();
        (outside / distance, -distance)
    }

    /// The outward normal where the path from `before` (outside) to `p` (inside) came
    /// into the capsule; None if `before` is inside too or the path is too short to say.
    pub fn entry_normal(&self, before: &Vec3, p: &Vec3) -> Option<Vec3> {
        let path = p - before;
        let length = path.norm();
        if length < 1e-12 || self.radial(before).1 >= 0.0 {
            return None;
        }
        let direction = path / length;
        let (entry, _) = self.interval(before, &direction)?;
        (0.0..=length).contains(&entry).then(|| self.radial(&(before + direction * entry)).0)
    }
}

impl Capsule {
    /// The normal a vertex that came in at the surface normal `n` is held along: the
    /// tool's axis out of its tip where it came in through the tip's ball (the tip is a
    /// face that pushes along the tool, as a probe's end does: a vertex under it stays
    /// under it however deep the tool goes, where along the ball's inclined normal it
    /// would be pushed out sideways once the tool was a radius in), `n` elsewhere.
    pub fn face_normal(&self, n: &Vec3) -> Vec3 {
        match self.out_of_tip() {
            Some(out_of_tip) if n.dot(&out_of_tip) > 1e-9 => out_of_tip,
            _ => *n,
        }
    }

    /// The direction out of the tool's tip along its axis (None for a ball).
    pub fn out_of_tip(&self) -> Option<Vec3> {
        (self.a - self.b).try_normalize(1e-12)
    }

    /// Whether a contact pushed out along `normal` is held by the tip's face: pushed
    /// along the tool's axis (a contact that came in through the tip is held along
    /// exactly [`Self::out_of_tip`], see [`Self::face_normal`]; one beside the shaft
    /// across it).
    pub fn pushes_with_tip(&self, normal: &Vec3) -> bool {
        self.out_of_tip().is_some_and(|out_of_tip| normal.dot(&out_of_tip) > 0.5)
    }
}

/// The roots of `A t² + 2 B t + C = 0` (A > 0) in order, if real.
fn quadratic_interval(a: f64, b: f64, c: f64) -> Option<(f64, f64)> {
    let discriminant = b * b - a * c;
    (discriminant >= 0.0).then(|| {
        let root = discriminant.sqrt();
        ((-b - root) / a, (-b + root) / a)
    })
}

/// How deep inside the tool (a fraction of its radius, of half a plate's thickness) a
/// vertex is pushed out along the
/// tool's surface normal nearest it, as a frictionless contact is, and slides over it
/// (the normal turning as it goes); deeper, along the normal it came in with.
pub const SHALLOW: f64 = 0.25;

/// A vertex's contact with a tool: the normal it is pushed out along, how far, and the
/// normal it came in with (to remember while the contact lasts).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Contact {
    pub normal: Vec3,
    pub depth: f64,
    pub entry: Vec3,
}

/// How a vertex at `p` touches `capsule`, given the normal it came in with if it was in
/// contact last step (`entry`, grid frame) and, for a new contact, where it was
/// relative to the tool a step before (`before`); None if it does not. Near the tool's
/// surface (within [`SHALLOW`] of its half-size) the normal is the surface's there, so a
/// tool rolls or slides over the tissue as a frictionless one does; deeper, or once that
/// normal has turned more than a right angle from the one it came in with, the vertex
/// is pushed along the normal it came in with, so it cannot be pushed round the tool's
/// far side. The entry normal is kept for the whole contact, never turned step by step,
/// so a vertex going in and out of the shallow band cannot ratchet it round.
///
/// A contact deeper than `max_depth` lets go: one vertex alone would push on the tool
/// with more than its rated force there, so the tool has gone through (or the vertex
/// was flung past it, which must not fling it back harder).
pub fn contact(capsule: &Capsule, p: &Vec3, entry: Option<Vec3>, before: Option<Vec3>, max_depth: f64) -> Option<Contact> {
    let (radial, inside) = capsule.radial(p);
    let entry = entry_of(capsule, p, entry, before, radial, inside)?;
    if inside > 0.0 && inside <= SHALLOW * capsule.half_size() && radial.dot(&entry) > 0.0 {
        return Some(Contact { normal: radial, depth: inside, entry });
    }
    held_along(capsule, p, entry, max_depth)
}

/// [`contact`] without the shallow band: always pushed along the normal it came in
/// with, however near the tool's surface. For a point that a spring across its normal
/// also holds (grid::model::face_contact), which the band's radial normal would switch
/// on and off step by step.
pub fn contact_along_entry(capsule: &Capsule, p: &Vec3, entry: Option<Vec3>, before: Option<Vec3>, max_depth: f64) -> Option<Contact> {
    let (radial, inside) = capsule.radial(p);
    held_along(capsule, p, entry_of(capsule, p, entry, before, radial, inside)?, max_depth)
}

/// The normal a contact is held along: `entry` if it goes on, else (a new one, only if
/// `p` is inside) where its path came in (see [`contact`]).
fn entry_of(capsule: &Capsule, p: &Vec3, entry: Option<Vec3>, before: Option<Vec3>, radial: Vec3, inside: f64) -> Option<Vec3> {
    match entry {
        Some(entry) => Some(entry),
        None if inside > 0.0 => Some(capsule.face_normal(&before.and_then(|before| capsule.entry_normal(&before, p)).unwrap_or(radial))),
        None => None,
    }
}

/// `p` pushed out along `entry` by the ray's exit from the capsule, unless deeper than
/// `max_depth` (or the ray misses the tool): see [`contact`].
fn held_along(capsule: &Capsule, p: &Vec3, entry: Vec3, max_depth: f64) -> Option<Contact> {
    capsule.depth_along(p, &entry).filter(|&depth| depth <= max_depth).map(|depth| Contact { normal: entry, depth, entry })
}

/// The tool's orientation in the grid's frame, for its normals' round trip.
pub fn tool_to_grid(grid_rotation: &Matrix3<f64>, tool_rotation: &Matrix3<f64>) -> Matrix3<f64> {
    grid_rotation.transpose() * tool_rotation
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A ball-ended rod of radius 3 mm standing on its tip at the origin.
    fn probe() -> Capsule {
        Capsule::round(Vec3::new(0.0, 0.0, 0.003), Vec3::new(0.0, 0.0, 0.1), 0.003)
    }

    #[test]
    fn a_line_meets_the_ball_the_cylinder_or_misses() {
        let c = probe();
        // Down the axis: from the top of the segment's ball to the apex.
        let (lo, hi) = c.interval(&Vec3::new(0.0, 0.0, 0.2), &-Vec3::z()).unwrap();
        assert!((lo - (0.2 - 0.103)).abs() < 1e-12 && (hi - 0.2).abs() < 1e-12, "{lo} {hi}");
        // Across the shaft at 5 cm: its diameter.
        let (lo, hi) = c.interval(&Vec3::new(-1.0, 0.001, 0.05), &Vec3::x()).unwrap();
        let half = (0.003f64.powi(2) - 0.001f64.powi(2)).sqrt();
        assert!((lo - (1.0 - half)).abs() < 1e-12 && (hi - (1.0 + half)).abs() < 1e-12);
        // Across under the apex: nothing.
        assert!(c.interval(&Vec3::new(-1.0, 0.0, -0.0001), &Vec3::x()).is_none());
    }

    #[test]
    fn a_vertex_that_came_in_under_the_ball_is_pushed_down_below_it_however_deep_the_probe_goes() {
        let c = probe();
        let down = -Vec3::z();
        // 1 mm off the axis, at the height of the ball's centre (radially, it would go
        // out sideways): along its normal it must go down to the ball's underside.
        let p = Vec3::new(0.001, 0.0, 0.003);
        let Contact { normal, depth, .. } = contact(&c, &p, Some(down), None, 1.0).unwrap();
        let underside = 0.003 - (0.003f64.powi(2) - 0.001f64.powi(2)).sqrt();
        assert_eq!(normal, down);
        assert!((depth - (0.003 - underside)).abs() < 1e-12, "{depth}");
        // Radially it goes sideways by 2 mm.
        let (radial, inside) = c.radial(&p);
        assert!((radial - Vec3::x()).norm() < 1e-12 && (inside - 0.002).abs() < 1e-12);
        // Beside the ball, or below it: the ray misses, the contact lets go.
        assert!(contact(&c, &Vec3::new(0.004, 0.0, 0.003), Some(down), None, 1.0).is_none());
        assert!(contact(&c, &Vec3::new(0.0, 0.0, -0.001), Some(down), None, 1.0).is_none());
        // Deeper than one vertex could be below the tool's rated force: let go.
        assert!(contact(&c, &p, Some(down), None, 0.001).is_none());
    }

    #[test]
    fn a_new_contact_is_pushed_out_where_its_path_came_in() {
        let c = probe();
        // The probe came down 3.5 mm in one step onto a vertex 0.5 mm off its axis: the
        // vertex is now above the ball's centre, beside the shaft; it came in through the
        // ball's underside, so it is pushed down, not sideways.
        let p = Vec3::new(0.0005, 0.0, 0.0035);
        let before = p + Vec3::new(0.0, 0.0, -0.0035);
        let Contact { normal, depth, .. } = contact(&c, &p, None, Some(before), 1.0).unwrap();
        assert!(normal.z < -0.9, "{normal:?}");
        assert!(depth > 0.003, "{depth}");
        // Without a path, radially.
        let normal = contact(&c, &p, None, None, 1.0).unwrap().normal;
        assert!(normal.x > 0.9, "{normal:?}");
        // Outside: no contact.
        assert!(contact(&c, &Vec3::new(0.0, 0.0, -0.0001), None, None, 1.0).is_none());
    }
    /// A 3 × 0.4 mm blade plate standing on its tip at the origin, 40 mm long, its edge
    /// facing +x.
    fn blade() -> Capsule {
        let plate = Plate { edge: Vec3::x(), flat: Vec3::z().cross(&Vec3::x()), half_width: 0.0015, half_thickness: 0.0002 };
        Capsule { a: Vec3::zeros(), b: Vec3::new(0.0, 0.0, 0.04), radius: 0.0015f64.hypot(0.0002), plate: Some(plate) }
    }

    #[test]
    fn a_plate_is_a_box_rays_cross_its_slabs_and_points_leave_by_the_nearest_face() {
        let c = blade();
        assert_eq!(c.half_size(), 0.0002);
        // Across the flat (y) at 1 mm up: its thickness; across the edge (x): its width.
        let (lo, hi) = c.interval(&Vec3::new(0.001, -1.0, 0.001), &Vec3::y()).unwrap();
        assert!((lo - (1.0 - 0.0002)).abs() < 1e-12 && (hi - (1.0 + 0.0002)).abs() < 1e-12, "{lo} {hi}");
        let (lo, hi) = c.interval(&Vec3::new(-1.0, 0.0, 0.001), &Vec3::x()).unwrap();
        assert!((lo - (1.0 - 0.0015)).abs() < 1e-12 && (hi - (1.0 + 0.0015)).abs() < 1e-12, "{lo} {hi}");
        // Beside the flat, or below the tip: missed (a capsule of its bounding radius
        // would reach both).
        assert!(c.interval(&Vec3::new(-1.0, 0.0005, 0.001), &Vec3::x()).is_none());
        assert!(c.interval(&Vec3::new(-1.0, 0.0, -0.0001), &Vec3::x()).is_none());
        assert!(Capsule::round(c.a, c.b, c.radius).interval(&Vec3::new(-1.0, 0.0005, 0.001), &Vec3::x()).is_some());
        // Inside near the flat: out through it; near the tip: out through the tip face.
        let (normal, inside) = c.radial(&Vec3::new(0.0005, 0.00015, 0.01));
        assert!((normal - Vec3::y()).norm() < 1e-12 && (inside - 0.00005).abs() < 1e-12, "{normal:?} {inside}");
        let (normal, inside) = c.radial(&Vec3::new(0.0005, 0.0, 0.0001));
        assert!((normal + Vec3::z()).norm() < 1e-12 && (inside - 0.0001).abs() < 1e-12, "{normal:?} {inside}");
        // Outside beside the edge: from the nearest point, negative.
        let (normal, inside) = c.radial(&Vec3::new(0.0025, 0.0, 0.01));
        assert!((normal - Vec3::x()).norm() < 1e-12 && (inside + 0.001).abs() < 1e-12, "{normal:?} {inside}");
        // A vertex that came in through the tip face is held along the axis, pushed
        // down below the tip however deep the blade goes.
        let p = Vec3::new(0.001, 0.0001, 0.005);
        let Contact { normal, depth, .. } = contact(&c, &p, None, Some(p - Vec3::new(0.0, 0.0, 0.006)), 1.0).unwrap();
        assert!((normal + Vec3::z()).norm() < 1e-12 && (depth - 0.005).abs() < 1e-12, "{normal:?} {depth}");
    }
}
