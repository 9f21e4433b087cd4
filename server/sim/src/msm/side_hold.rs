//! Contact that holds along a tool's side: a node beside the shaft is pushed out on the
//! side it came in from, not radially from the axis (as the branched grid's vertices
//! are, crate::grid::hold).
//!
//! The paper's radial penalty pushes a node inside the tool away from the nearest point
//! of its axis. A tool laid along the skin and pressed down pushes the nodes under it
//! down until they are deeper than its radius; then they are past the axis, pushed up,
//! and the tool is through the skin: the default scene's 6 mm probe laid flat went
//! through at 4.2 N (its rated force is 10 N), the 1 mm scalpel laid flat with no force
//! at all (measured 2026-11-29, both integrators; [`super::face_hold`] holds such thin
//! tools). Here a node that touches a tool's side remembers which way it came in — the
//! section's way out where it first touched, in the tool's own frame (along its edge and
//! its flat's normal, so it turns with the tool) — and while it stays in contact it is pushed along that direction by as far as
//! the section lies across the ray from it: a node under the shaft is pushed down below
//! it however deep the tool goes. Near the surface (within [`SHALLOW`] of the section's
//! half-size) it is pushed along the surface's own normal, so the tool slides over the
//! skin (against its friction, [`super::side_friction`]). The contact lets go when the ray misses the section
//! (the node came out, or the tool moved off it), and past the depth at which one node
//! would push with the tool's rated force (it has gone through: it must not be flung
//! back harder).
//!
//! The tip face's nodes are not here ([`super::hold`] holds them), nor a blade's that
//! cuts or a tool's through the skin (the paper's radial rule and the shortest way out).
//! A tool that fits between the nodes is also held on the triangles' insides along it
//! ([`super::face_hold`]), whose points this memory keeps too ([`Slot::FacePoint`]).

use crate::math::Vec3;
use crate::hash::{HashState, StateHasher};
use crate::tool::{PlacedTool, Section, TipShape};

/// How deep inside the section, as a fraction of its smallest half-size, a node is
/// pushed along the surface's normal nearest it (and slides over it); deeper, along the
/// way it came in.
pub const SHALLOW: f64 = 0.25;

/// A node touching a tool's side: the way it came in, in the tool's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
struct SideTouch {
    body: usize,
    /// The way out, as components along the tool's edge and its flat's normal.
    along_edge: f64,
    along_flat: f64,
    /// The contact pass it was last in contact.
    pass: u64,
    /// A triangle's point: its barycentric weights (the material point, kept while the
    /// contact lasts).
    weights: [f64; 3],
    /// Where friction holds it ([`super::side_friction`]): from the tool's tip, as
    /// components along its axis, edge and flat's normal; None until the pass that
    /// touched it first has rubbed.
    anchor: Option<[f64; 3]>,
}

/// What touches a tool's side: a node, or one of the two points a triangle's inside is
/// held at (super::face_hold).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    Node(usize),
    FacePoint { triangle: u32, end: usize },
}

/// Per node and per triangle's point, the side of a tool it touches; kept while the
/// contact lasts from one contact pass (a substep) to the next.
#[derive(Debug, Clone, Default)]
pub struct SideMemory {
    nodes: Vec<Option<SideTouch>>,
    face_points: Vec<Option<SideTouch>>,
    pass: u64,
}

impl HashState for SideTouch {
    fn hash_state(&self, h: &mut StateHasher) {
        let Self { body, along_edge, along_flat, pass, weights, anchor } = self;
        (body, along_edge, along_flat).hash_state(h);
        (pass, weights, anchor).hash_state(h);
    }
}

impl HashState for SideMemory {
    /// Which side of a tool each node and triangle's point came in from, and where
    /// friction holds it.
    fn hash_state(&self, h: &mut StateHasher) {
        (&self.nodes, &self.face_points, self.pass).hash_state(h);
    }
}

impl SideMemory {
    /// Room for `nodes` nodes and `triangles` triangles (at build and after a cut; it
    /// only grows).
    pub fn fit(&mut self, nodes: usize, triangles: usize) {
        if self.nodes.len() < nodes {
            self.nodes.resize(nodes, None);
        }
        if self.face_points.len() < 2 * triangles {
            self.face_points.resize(2 * triangles, None);
        }
    }

    /// A memory with room for `nodes` nodes and `triangles` triangles.
    pub fn with_room(nodes: usize, triangles: usize) -> Self {
        let mut memory = Self::default();
        memory.fit(nodes, triangles);
        memory
    }

    /// A new contact pass (a substep).
    pub fn begin_pass(&mut self) {
        self.pass += 1;
    }

    fn slot(&mut self, slot: Slot) -> &mut Option<SideTouch> {
        match slot {
            Slot::Node(node) => &mut self.nodes[node],
            Slot::FacePoint { triangle, end } => &mut self.face_points[2 * triangle as usize + end],
        }
    }

    /// What `slot` remembers of body `body`'s side: its touch, if it touched it in the
    /// last pass or this one.
    fn live(&self, slot: Slot, body: usize) -> Option<SideTouch> {
        let touch = match slot {
            Slot::Node(node) => self.nodes[node],
            Slot::FacePoint { triangle, end } => self.face_points[2 * triangle as usize + end],
        };
        touch.filter(|t| t.body == body && t.pass + 1 >= self.pass)
    }

    /// Whether `slot` touched body `body`'s side in the last pass or this one.
    pub fn remembers(&self, slot: Slot, body: usize) -> bool {
        self.live(slot, body).is_some()
    }

    /// The way `slot` came into body `body`'s side (world frame, across the axis).
    fn remembered(&self, slot: Slot, body: usize, tool: &PlacedTool) -> Option<Vec3> {
        self.live(slot, body).map(|t| tool.edge * t.along_edge + tool.flat_normal() * t.along_flat)
    }

    fn remember(&mut self, slot: Slot, body: usize, tool: &PlacedTool, way_out: &Vec3) {
        // A contact that goes on keeps its anchor; a new one is anchored anew.
        let anchor = self.live(slot, body).and_then(|t| t.anchor);
        let pass = self.pass;
        let entry = self.slot(slot);
        let weights = entry.map_or([0.0; 3], |t| t.weights);
        *entry = Some(SideTouch { body, along_edge: way_out.dot(&tool.edge), along_flat: way_out.dot(&tool.flat_normal()), pass, weights, anchor });
    }

    /// Where friction holds `slot` against body `body` (world frame), if it has been
    /// anchored during its contact.
    pub fn anchor(&self, slot: Slot, body: usize, tool: &PlacedTool) -> Option<Vec3> {
        Some(tool.from_frame(self.live(slot, body)?.anchor?))
    }

    /// Keeps `slot`'s anchor at `at` (world frame), in the tool's frame.
    pub fn keep_anchor(&mut self, slot: Slot, body: usize, tool: &PlacedTool, at: &Vec3) {
        let anchor = tool.to_frame(at);
        if let Some(t) = self.slot(slot).as_mut().filter(|t| t.body == body) {
            t.anchor = Some(anchor);
        }
    }

    /// The material point a triangle's point in contact with body `body` is (its
    /// barycentric weights).
    pub fn face_point(&self, triangle: u32, end: usize, body: usize) -> Option<[f64; 3]> {
        self.live(Slot::FacePoint { triangle, end }, body).map(|t| t.weights)
    }

    /// Keeps the barycentric weights of a triangle's point in contact (after
    /// [`side_contact`] took it).
    pub fn keep_face_point(&mut self, triangle: u32, end: usize, weights: [f64; 3]) {
        if let Some(t) = self.slot(Slot::FacePoint { triangle, end }).as_mut() {
            t.weights = weights;
        }
    }

    fn forget(&mut self, slot: Slot) {
        *self.slot(slot) = None;
    }
}

/// How `slot` at `x` touches body `body`'s side, given `radial` (the paper's way out
/// across the axis and its depth, if it is inside): the direction it is pushed along and
/// how far, remembered for the next pass; None (forgotten) if it does not touch it or
/// has gone through. `max_depth_m`: the depth at which the point alone would push with
/// the tool's rated force.
pub fn side_contact(memory: &mut SideMemory, slot: Slot, body: usize, tool: &PlacedTool, x: &Vec3, radial: Option<(Vec3, f64)>, max_depth_m: f64) -> Option<(Vec3, f64)> {
    let Some(way_in) = memory.remembered(slot, body, tool) else {
        let (direction, depth) = radial?;
        memory.remember(slot, body, tool, &direction);
        return Some((direction, depth));
    };
    if let Some((direction, depth)) = radial
        && depth <= SHALLOW * half_size_m(tool)
        && direction.dot(&way_in) > 0.0
    {
        memory.remember(slot, body, tool, &way_in);
        return Some((direction, depth));
    }
    match exit_along(tool, x, &way_in).filter(|&depth| depth <= max_depth_m) {
        Some(depth) => {
            memory.remember(slot, body, tool, &way_in);
            Some((way_in, depth))
        }
        None => {
            memory.forget(slot);
            None
        }
    }
}

/// The section's smallest half-size, m: a cylinder's radius, half a plate's thickness.
fn half_size_m(tool: &PlacedTool) -> f64 {
    match tool.section {
        Section::Round => tool.radius_m,
        Section::Plate { half_width_m, half_thickness_m } | Section::Jaws { half_width_m, half_thickness_m, .. } => half_width_m.min(half_thickness_m),
    }
}

/// How far a point's height along the axis from the tip may lie outside the tool's ends
/// and still count as within them, m: rounding. A triangle's point taken where the
/// axis's stretch over it ends, at the tip, lies there to the last bit, on either side;
/// taken as beyond the end it was let go the pass after it was taken, and the triangles
/// round a plate's end went unheld (the 3 × 0.4 mm plate laid on its edge on the
/// explicit skin: held to 9.1 N, then the skin closed over it).
const END_ROUNDING_M: f64 = 1e-9;

/// Whether height `along` (from the tip, along the axis) is within the tool's ends.
pub fn within_ends(tool: &PlacedTool, along: f64) -> bool {
    (-END_ROUNDING_M..=tool.length_m + END_ROUNDING_M).contains(&along)
}

/// How far `x` must move along `n` (unit, across the axis) to leave the tool's section
/// at its height: the exit of the ray from `x` along `n`, if the section lies across it
/// ahead of `x` (or around it); None beyond the tool's ends or if the ray misses.
pub fn exit_along(tool: &PlacedTool, x: &Vec3, n: &Vec3) -> Option<f64> {
    let along = (x - tool.tip).dot(&tool.axis);
    if !within_ends(tool, along) {
        return None;
    }
    let along = along.clamp(0.0, tool.length_m);
    let offset = x - tool.tip - tool.axis * along;
    let exit = match tool.section {
        Section::Round => {
            // A round tip's hemisphere is, at this height, a disc of smaller radius.
            let radius = if tool.tip_shape == TipShape::Round && along < tool.radius_m {
                (tool.radius_m * tool.radius_m - (tool.radius_m - along).powi(2)).sqrt()
            } else {
                tool.radius_m
            };
            let b = offset.dot(n);
            let discriminant = b * b - (offset.norm_squared() - radius * radius);
            (discriminant >= 0.0).then(|| -b + discriminant.sqrt())?
        }
        Section::Plate { half_width_m, half_thickness_m } => {
            let normal = tool.flat_normal();
            slab_exit([(offset.dot(&tool.edge), n.dot(&tool.edge), half_width_m), (offset.dot(&normal), n.dot(&normal), half_thickness_m)])?
        }
        // Forceps meet the skin as their jaws, each a plate (crate::tool::bodies).
        Section::Jaws { .. } => return None,
    };
    (exit > 0.0).then_some(exit)
}

/// The exit of a ray from a box given per axis as (the start, the direction, the half
/// size), if the ray meets it.
fn slab_exit(axes: [(f64, f64, f64); 2]) -> Option<f64> {
    let (mut enter, mut exit) = (f64::NEG_INFINITY, f64::INFINITY);
    for (start, direction, half) in axes {
        if direction.abs() < 1e-12 {
            if start.abs() >= half {
                return None;
            }
            continue;
        }
        let (t0, t1) = ((-half - start) / direction, (half - start) / direction);
        enter = enter.max(t0.min(t1));
        exit = exit.min(t0.max(t1));
    }
    (enter <= exit).then_some(exit)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 3 mm rod laid along +x at height 0, 8 cm long.
    fn laid_flat() -> PlacedTool {
        PlacedTool::round(Vec3::new(-0.04, 0.0, 0.0), Vec3::x(), 0.003, 0.08)
    }

    #[test]
    fn a_node_that_came_in_under_the_shaft_is_pushed_down_below_it_however_deep() {
        let tool = laid_flat();
        let mut memory = SideMemory::default();
        memory.fit(1, 0);
        memory.begin_pass();
        // It touches first just under the shaft: pushed down (radially).
        let x = Vec3::new(0.0, 0.0005, -0.0029);
        let (n, depth) = side_contact(&mut memory, Slot::Node(0), 0, &tool, &x, Some((Vec3::new(0.0, 0.0005, -0.0029).normalize(), 0.003 - x.norm())), 1.0).unwrap();
        assert!(n.z < -0.9 && depth < 1e-4);
        // Two passes later it is above the axis (the shaft pressed past it): radially it
        // would go up; it is pushed down, to below the shaft.
        memory.begin_pass();
        let x = Vec3::new(0.0, 0.0, 0.001);
        let (m, depth) = side_contact(&mut memory, Slot::Node(0), 0, &tool, &x, Some((Vec3::z(), 0.002)), 1.0).unwrap();
        assert!((m - n).norm() < 1e-12, "along the way it came in");
        assert!((x + m * depth).norm() > 0.003 - 1e-12 && (x + m * depth).z < 0.0, "out below the shaft: {:?}", x + m * depth);
        // Deeper than its rated force allows: let go, and forgotten.
        memory.begin_pass();
        assert_eq!(side_contact(&mut memory, Slot::Node(0), 0, &tool, &x, Some((Vec3::z(), 0.002)), 1e-3), None);
        memory.begin_pass();
        let (fresh, _) = side_contact(&mut memory, Slot::Node(0), 0, &tool, &x, Some((Vec3::z(), 0.002)), 1.0).unwrap();
        assert_eq!(fresh, Vec3::z(), "a new contact: radial");
    }

    #[test]
    fn shallow_contacts_slide_and_a_stale_or_other_bodys_memory_is_not_used() {
        let tool = laid_flat();
        let mut memory = SideMemory::default();
        memory.fit(1, 0);
        memory.begin_pass();
        side_contact(&mut memory, Slot::Node(0), 0, &tool, &Vec3::new(0.0, 0.0, -0.0029), Some((-Vec3::z(), 1e-4)), 1.0);
        // Shallow, on the same side: along the surface's normal there.
        memory.begin_pass();
        let tilted = Vec3::new(0.0, 0.6, -0.8);
        let (n, _) = side_contact(&mut memory, Slot::Node(0), 0, &tool, &(tilted * 0.0029), Some((tilted, 1e-4)), 1.0).unwrap();
        assert_eq!(n, tilted);
        // Another body's memory, or one two passes old, is not this contact's.
        memory.begin_pass();
        let (n, _) = side_contact(&mut memory, Slot::Node(0), 1, &tool, &Vec3::new(0.0, 0.0, 0.001), Some((Vec3::z(), 0.002)), 1.0).unwrap();
        assert_eq!(n, Vec3::z());
        memory.begin_pass();
        memory.begin_pass();
        let (n, _) = side_contact(&mut memory, Slot::Node(0), 1, &tool, &Vec3::new(0.0, 0.0, -0.001), Some((-Vec3::z(), 0.002)), 1.0).unwrap();
        assert_eq!(n, -Vec3::z(), "two passes old: a new contact");
    }

    #[test]
    fn the_way_out_of_a_disc_a_hemisphere_and_a_plate() {
        let tool = laid_flat();
        // From 1 mm above the axis straight down: out at 3 mm below it.
        assert!((exit_along(&tool, &Vec3::new(0.0, 0.0, 0.001), &-Vec3::z()).unwrap() - 0.004).abs() < 1e-12);
        // Beside the disc, or beyond the ends: none.
        assert_eq!(exit_along(&tool, &Vec3::new(0.0, 0.004, 0.001), &-Vec3::z()), None);
        assert_eq!(exit_along(&tool, &Vec3::new(0.05, 0.0, 0.001), &-Vec3::z()), None);
        // A round tip 1 mm from its apex is a disc of radius √(9 − 4) mm there.
        let round = PlacedTool { tip_shape: TipShape::Round, ..tool };
        let at = Vec3::new(-0.039, 0.0, 0.0);
        assert!((exit_along(&round, &at, &-Vec3::z()).unwrap() - 5e-6f64.sqrt()).abs() < 1e-12);
        // A 4 × 1 mm plate (edge +y, flat normal x × y = +z): out through its flat.
        let plate = PlacedTool { section: Section::Plate { half_width_m: 0.002, half_thickness_m: 0.0005 }, edge: Vec3::y(), ..tool };
        assert!((exit_along(&plate, &Vec3::new(0.0, 0.001, 0.0003), &-Vec3::z()).unwrap() - 0.0008).abs() < 1e-12);
        assert!((exit_along(&plate, &Vec3::new(0.0, 0.001, 0.0003), &Vec3::y()).unwrap() - 0.001).abs() < 1e-12);
        assert_eq!(exit_along(&plate, &Vec3::new(0.0, 0.003, 0.0003), &-Vec3::z()), None);
    }
}
