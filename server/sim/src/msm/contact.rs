//! Tool collision with the skin's nodes (paper Section 2.2).
//!
//! The tool is the segment tip–top with radius r. A node N is inside when its
//! projection on the axis falls between the two ends (the paper's two angles ≤ 90°)
//! and its distance d to the axis is below r. The paper pushes N out along N − p (p the
//! closest point on the axis); we keep that for a node's first touch of the tool's side,
//! and add one case the paper leaves open: a node that is closer to the tip's end face
//! than to the side (the tool pressed tip-first into the skin) is pushed out through
//! that face, so that pressing is felt. A tool holding the skin keeps each node beside
//! its shaft on the side it came in from ([`super::side_hold`]), so a tool laid along the
//! skin does not push its nodes past its axis. A blade that is cutting uses the paper's
//! radial rule only, so it passes through the skin instead of pushing it ahead.
//!
//! A scalpel blade's plate ([`crate::tool::Section::Plate`]) is the same test with a
//! rectangular cross-section: a node inside it goes out through the nearer of its
//! flats or its sides ([`PlacedTool::section_exit`]).
//!
//! A round tip ([`crate::tool::TipShape::Round`]) is a hemisphere of the tool's radius:
//! a node inside it goes out along the sphere's normal (radially, across the axis to
//! the sphere at its height, for the paper's rule).
//!
//! The response is a penalty force k_c·depth on the node; the tool receives the
//! opposite force, and the sum over nodes is the haptic force. Only nodes the broad
//! phase returns near the tool are tested.

use super::side_friction::{side_friction, stick_contacts};
use super::side_hold::{SideMemory, Slot, side_contact};
use super::state::Nodes;
use crate::broad_phase::PointGrid;
use crate::math::{Vec3, any_perpendicular};
use crate::tool::{PlacedTool, TipShape, ToolFeedback};

/// How a node sits inside the tool, and the way out.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Penetration {
    /// Unit direction the node is pushed along.
    pub direction: Vec3,
    /// Distance to the way out, m.
    pub depth_m: f64,
}

/// Tests one point against the tool. `radial_only`: the paper's rule (always push
/// across the axis: along N − p for a cylinder, through the nearer flat or side for a
/// blade's plate); otherwise the shortest way out, across or through an end face.
pub fn tool_penetration(tool: &PlacedTool, x: &Vec3, radial_only: bool) -> Option<Penetration> {
    let along = (x - tool.tip).dot(&tool.axis);
    if !(0.0..=tool.length_m).contains(&along) {
        return None;
    }
    if tool.tip_shape == TipShape::Round && along < tool.radius_m {
        return round_tip_penetration(tool, x, along, radial_only);
    }
    let (radial_depth, direction) = tool.section_exit(&(x - tool.tip - tool.axis * along))?;
    if !radial_only {
        let (cap_depth, cap_dir) =
            if along <= tool.length_m - along { (along, -tool.axis) } else { (tool.length_m - along, tool.axis) };
        if cap_depth < radial_depth {
            return Some(Penetration { direction: cap_dir, depth_m: cap_depth });
        }
    }
    Some(Penetration { direction, depth_m: radial_depth })
}

/// A point `along` the axis within a round tip's hemisphere: out along the sphere's
/// normal, or (`radial_only`) across the axis to the sphere at the point's height.
fn round_tip_penetration(tool: &PlacedTool, x: &Vec3, along: f64, radial_only: bool) -> Option<Penetration> {
    if !radial_only {
        let (depth_m, direction) = tool.round_tip_exit(x)?;
        return Some(Penetration { direction, depth_m });
    }
    let below_centre = tool.radius_m - along;
    let section_radius = (tool.radius_m * tool.radius_m - below_centre * below_centre).sqrt();
    let offset = x - tool.tip - tool.axis * along;
    let d = offset.norm();
    if d >= section_radius {
        return None;
    }
    let direction = if d > 1e-12 * tool.radius_m { offset / d } else { any_perpendicular(&tool.axis) };
    Some(Penetration { direction, depth_m: section_radius - d })
}

/// Which nodes inside the tool its penalty pushes, and which way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) enum ContactMode {
    /// The paper's rule: every node radially (a blade cutting its way through).
    Radial,
    /// Every node by its shortest way out, radial or through an end face (a tool
    /// through the skin that is not cutting).
    ShortestWayOut,
    /// Only nodes the tip face does not hold (those within this reach of it, m, and
    /// nearer it than the side; [`super::hold`]), radially.
    SideOnly { face_reach_m: f64 },
}

/// A node in contact during the current step (kept for the implicit solver's tangent).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Contact {
    pub node: u32,
    pub normal: Vec3,
    pub stiffness: f64,
    /// The velocity along `normal` the contact drives its node to within the step, m/s
    /// (the implicit solve adds stiffness × (h + β) × this to the node's force, so the
    /// stiff spring ends the step with the node at it): the closing of a gap just off a
    /// round tip (a speculative hold), or the tool's velocity across its push for a
    /// point stuck by friction; 0 for a point held on the face (it stays put along the
    /// push) and for a penalty, whose force the caller has added.
    pub drive_m_per_s: f64,
}

/// A tool's side holding the nodes it touches on the side they came in from
/// ([`super::side_hold`]): the memory, the body's index and the depth at which one node
/// would push with its rated force.
pub(crate) struct SideHold<'a> {
    pub memory: &'a mut SideMemory,
    pub body: usize,
    pub max_depth_m: f64,
    /// The skin's Coulomb friction against the side ([`super::side_friction`]), if any.
    pub friction: Option<super::side_friction::Friction>,
    /// The tool's velocity, m/s (what a stuck point moves with).
    pub tool_velocity: Vec3,
}

/// Adds the contact forces of one tool to the nodes, and their reaction to `feedback`
/// (scaled by `weight`, the substep's share of the step). Contacts are appended to
/// `contacts` (at most [`super::contact_room`], the room made for them, so this never
/// allocates).
/// With `side`, the nodes beside a holding tool ([`ContactMode::SideOnly`]) are pushed out
/// on the side they came in from instead of radially.
#[allow(clippy::too_many_arguments)]
pub(crate) fn apply_tool_contacts(
    tool: &PlacedTool,
    stiffness: f64,
    mode: ContactMode,
    nodes: &mut Nodes,
    grid: &PointGrid,
    contacts: &mut Vec<Contact>,
    feedback: &mut ToolFeedback,
    weight: f64,
    query_margin_m: f64,
    mut side: Option<&mut SideHold<'_>>,
) {
    let (min, max) = tool.bounds(query_margin_m);
    let mut count = 0u32;
    let (mut force, mut torque) = (Vec3::zeros(), Vec3::zeros());
    grid.query_box(&min, &max, |id| {
        let i = id as usize;
        if let ContactMode::SideOnly { face_reach_m } = mode
            && super::hold::face_exit(tool, &nodes.x[i], face_reach_m).is_some()
        {
            return;
        }
        let penetration = tool_penetration(tool, &nodes.x[i], mode != ContactMode::ShortestWayOut);
        let mut rub = Vec3::zeros();
        let pushed = match (&mut side, mode) {
            (Some(side), ContactMode::SideOnly { .. }) => {
                let pushed = side_contact(side.memory, Slot::Node(i), side.body, tool, &nodes.x[i], penetration.map(|p| (p.direction, p.depth_m)), side.max_depth_m);
                if let (Some((direction, depth_m)), Some(friction)) = (pushed, side.friction) {
                    rub = side_friction(side.memory, Slot::Node(i), side.body, tool, &nodes.x[i], &direction, stiffness * depth_m, stiffness, friction);
                    if contacts.len() + 3 <= super::contact_room(nodes) {
                        stick_contacts(&[id], &[1.0], &direction, stiffness, &side.tool_velocity, contacts);
                    }
                }
                pushed.map(|(direction, depth_m)| Penetration { direction, depth_m })
            }
            _ => penetration,
        };
        if let Some(pen) = pushed {
            let on_node = pen.direction * (stiffness * pen.depth_m) + rub;
            nodes.f[i] += on_node;
            force -= on_node;
            torque -= (nodes.x[i] - tool.tip).cross(&on_node);
            contacts.push(Contact { node: id, normal: pen.direction, stiffness, drive_m_per_s: 0.0 });
            count += 1;
        }
    });
    feedback.force_n += force * weight;
    feedback.torque_nm += torque * weight;
    feedback.contacts = feedback.contacts.max(count);
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    pub(crate) fn tool() -> PlacedTool {
        // Vertical tool: tip at the origin, axis +z, 10 cm long, 1 mm radius.
        PlacedTool::round(Vec3::zeros(), Vec3::z(), 1e-3, 0.1)
    }

    #[test]
    fn node_just_inside_and_just_outside_the_side() {
        let t = tool();
        let inside = tool_penetration(&t, &Vec3::new(0.999e-3, 0.0, 0.05), true).unwrap();
        assert!((inside.depth_m - 1e-6).abs() < 1e-12);
        assert!((inside.direction - Vec3::x()).norm() < 1e-12, "pushed along N − p");
        assert!(tool_penetration(&t, &Vec3::new(1.001e-3, 0.0, 0.05), true).is_none());
    }

    #[test]
    fn end_caps_bound_the_cylinder() {
        let t = tool();
        // Beyond the tip face and beyond the top face: outside, however close to the axis.
        assert!(tool_penetration(&t, &Vec3::new(1e-4, 0.0, -1e-6), true).is_none());
        assert!(tool_penetration(&t, &Vec3::new(1e-4, 0.0, 0.1 + 1e-6), true).is_none());
        // Just inside either face: inside; the paper's rule pushes it radially.
        let near_tip = tool_penetration(&t, &Vec3::new(0.0, 5e-4, 1e-6), true).unwrap();
        assert!((near_tip.direction - Vec3::y()).norm() < 1e-12);
        assert!((near_tip.depth_m - 5e-4).abs() < 1e-12);
        let near_top = tool_penetration(&t, &Vec3::new(0.0, 5e-4, 0.1 - 1e-6), true).unwrap();
        assert!((near_top.direction - Vec3::y()).norm() < 1e-12);
    }

    #[test]
    fn pressing_tip_first_pushes_out_through_the_tip_face() {
        let t = tool();
        let p = tool_penetration(&t, &Vec3::new(0.0, 5e-4, 1e-4), false).unwrap();
        assert!((p.direction + Vec3::z()).norm() < 1e-12, "out through the tip, along −axis");
        assert!((p.depth_m - 1e-4).abs() < 1e-12);
        // Deeper than the radial way out: radial again.
        let p = tool_penetration(&t, &Vec3::new(0.0, 5e-4, 0.01), false).unwrap();
        assert!((p.direction - Vec3::y()).norm() < 1e-12);
    }

    #[test]
    fn a_round_tip_is_a_hemisphere_left_along_its_normal_or_across_the_axis() {
        let t = PlacedTool { tip_shape: TipShape::Round, ..tool() };
        // Off the axis near the apex, where a flat tip is solid: outside the hemisphere.
        assert!(tool_penetration(&t, &Vec3::new(8e-4, 0.0, 1e-4), false).is_none());
        assert!(tool_penetration(&tool(), &Vec3::new(8e-4, 0.0, 1e-4), false).is_some());
        // Inside it: out along the sphere's normal (from its centre, 1 mm up the axis).
        let x = Vec3::new(3e-4, 4e-4, 5e-4);
        let from_centre = x - Vec3::new(0.0, 0.0, 1e-3);
        let p = tool_penetration(&t, &x, false).unwrap();
        assert!((p.direction - from_centre.normalize()).norm() < 1e-12 && (p.depth_m - (1e-3 - from_centre.norm())).abs() < 1e-15);
        // The paper's rule: across the axis, to the sphere at the point's height
        // (radius √(r² − (r − z)²) = 0.866 mm at z = 0.5 mm).
        let p = tool_penetration(&t, &x, true).unwrap();
        assert!((p.direction - Vec3::new(0.6, 0.8, 0.0)).norm() < 1e-12 && (p.depth_m - (0.75e-6_f64.sqrt() - 5e-4)).abs() < 1e-12, "{p:?}");
        // Above the centre the rod's side, as for a flat tip.
        assert_eq!(tool_penetration(&t, &Vec3::new(0.0, 5e-4, 0.01), false), tool_penetration(&tool(), &Vec3::new(0.0, 5e-4, 0.01), false));
    }

    #[test]
    fn force_direction_follows_n_minus_p_for_a_tilted_tool() {
        let axis = Vec3::new(1.0, 1.0, 0.0).normalize();
        let t = PlacedTool::round(Vec3::zeros(), axis, 2e-3, 0.1);
        let n = Vec3::new(0.05, 0.05, 1e-3) + Vec3::new(1.0, -1.0, 0.0).normalize() * 1e-3;
        let pen = tool_penetration(&t, &n, true).unwrap();
        let p = t.tip + axis * (n - t.tip).dot(&axis);
        assert!((pen.direction - (n - p).normalize()).norm() < 1e-12);
    }

    #[test]
    fn node_on_the_axis_gets_a_finite_direction() {
        let pen = tool_penetration(&tool(), &Vec3::new(0.0, 0.0, 0.05), true).unwrap();
        assert!((pen.direction.norm() - 1.0).abs() < 1e-12);
        assert!(pen.direction.dot(&Vec3::z()).abs() < 1e-12);
    }
}
