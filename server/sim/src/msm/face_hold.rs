//! Contact on the insides of the skin's triangles along a tool laid along the skin, for
//! a tool that fits between the nodes (as the branched grid's thin tools have,
//! crate::grid::model::face_contact).
//!
//! A node beside the shaft is held on the side it came in from ([`super::side_hold`]),
//! but a shaft narrower than about two node spacings passes between two rows of nodes,
//! through the triangles between them: laid flat on the default skin and pressed down,
//! a 4 mm probe went through at 5.3 N, a 3 mm one at 2.2 N, the 1 mm scalpel with no
//! force at all. Here, on each live triangle that the shaft lies along (its axis more
//! than 60° from the triangle's normal: the tip face holds the others, [`super::hold`]),
//! the triangle's material points where the ends of the stretch of the axis over it
//! come into the section (where the axis lies beside it, its point nearest the axis)
//! are pushed out of the tool's section as a node is: on the side they came in from,
//! each kept (its barycentric weights and its way in, per triangle, in the tool's
//! frame) while its contact lasts; a face the axis crosses, or one that has turned
//! towards the tip, is not taken anew, but a point taken before is held however its
//! triangle tilts (dropped once its triangle sloped 30° along the axis, the points round
//! a thin shaft's ends let go one after another and the skin unzipped from both ends:
//! the 1 mm scalpel went through at 6.5 N explicit, 7.2 N implicit). Triangles
//! whose nodes the side touches too are held as well: skipping them let the 4 mm probe
//! through at 5.3 N as before, once its nodes slid round the shaft. A point's push is
//! shared by the triangle's three nodes by their barycentric weights (and its
//! stiffness, in the implicit system, by the same weights: each node's share of the
//! point's row sum). Each point is drawn towards the axis by a spring across its push
//! ([`towards_axis`]), and rubs with the skin's friction ([`super::side_friction`]). The
//! 1 mm scalpel laid flat reaches its rated 10 N with either integrator, and so does the
//! blade's plate on its edge, since a point that the skin beyond the tool's end draws
//! past it is taken again beside it (docs/tool-tissue.md, "The shaft's side").

use super::contact::{Contact, SideHold};
use super::side_friction::{side_friction, stick_contacts};
use super::side_hold::{Slot, side_contact, within_ends};
use super::state::{Nodes, Topology};
use crate::broad_phase::PointGrid;
use crate::math::{Vec3, across, barycentric_closest, closest_point_on_segment, segment_over_triangle, segment_triangle_closest, segment_triangle_intersection, triangle_normal};
use crate::tool::{PlacedTool, ToolFeedback};

/// A triangle whose normal is within this cosine of the axis faces the tool's tip (the
/// tip face holds it), not its side.
const SIDE_COSINE: f64 = 0.5;

/// The tool's contacts on the insides of the triangles near it (see the module's
/// documentation); the nodes its side touches this pass are in `side`'s memory.
/// `triangles`: scratch. Adds to `contacts` only within its capacity (never allocates).
#[allow(clippy::too_many_arguments)]
pub(crate) fn apply_face_contacts(
    tool: &PlacedTool,
    stiffness: f64,
    side: &mut SideHold<'_>,
    nodes: &mut Nodes,
    topo: &Topology,
    grid: &PointGrid,
    triangles: &mut Vec<u32>,
    contacts: &mut Vec<Contact>,
    feedback: &mut ToolFeedback,
    weight: f64,
    query_margin_m: f64,
) {
    let (min, max) = tool.bounds(query_margin_m);
    super::cut::triangles_near(grid, topo, &min, &max, triangles);
    let (mut force, mut torque, mut count) = (Vec3::zeros(), Vec3::zeros(), 0u32);
    for &t in triangles.iter() {
        if !topo.tri_alive[t as usize] {
            continue;
        }
        let ids = topo.tris[t as usize];
        let corners = ids.map(|v| nodes.x[v as usize]);
        let normal = triangle_normal(&corners[0], &corners[1], &corners[2]);
        // A face the axis crosses has been passed: which side it belongs on is not known;
        // a face that turned towards the tip is the tip face's. A point taken before
        // either remembers, and is held however the skin has tilted since.
        let slot = |end: usize| Slot::FacePoint { triangle: t, end };
        let remembered = (0..2).any(|end| side.memory.remembers(slot(end), side.body));
        let faces_tip = normal.norm() <= 0.0 || normal.normalize().dot(&tool.axis).abs() > SIDE_COSINE;
        if !remembered && (faces_tip || segment_triangle_intersection(&tool.tip, &tool.top, &corners[0], &corners[1], &corners[2]).is_some()) {
            continue;
        }
        // The ends of the axis's stretch over the triangle; where it lies beside it, the
        // triangle's point nearest the axis.
        let (near, far) = segment_over_triangle(&tool.tip, &tool.top, &corners).unwrap_or_else(|| {
            let (_, point) = segment_triangle_closest(&tool.tip, &tool.top, &corners);
            let w = barycentric_closest(&point, &corners[0], &corners[1], &corners[2]);
            (w, w)
        });
        let ends = if near == far { 1 } else { 2 };
        for (end, fresh) in [near, far].into_iter().enumerate().take(ends) {
            if contacts.len() + 12 > super::contact_room(nodes) {
                break;
            }
            // A new point is taken where the axis's stretch over the triangle ends; a
            // point in contact stays the material point it was while it is beside the
            // tool, and one the skin beyond the tool's end drew past it is taken again
            // where the stretch ends (the part of the triangle still beside the tool),
            // keeping the way it came in. Let go, the triangles round a plate's end went
            // unheld one after another and the skin closed over the plate laid on its
            // edge (held to 9.1 N under the explicit integrator).
            let at = |w: [f64; 3]| -> Vec3 { (0..3).map(|k| corners[k] * w[k]).sum() };
            let beside = |p: &Vec3| within_ends(tool, (p - tool.tip).dot(&tool.axis));
            let (w, point) = match side.memory.face_point(t, end, side.body).map(|kept| (kept, at(kept))) {
                Some((kept, p)) if beside(&p) || !beside(&at(fresh)) => (kept, p),
                _ => (fresh, at(fresh)),
            };
            let radial = super::contact::tool_penetration(tool, &point, true).map(|p| (p.direction, p.depth_m));
            let Some((direction, depth)) = side_contact(side.memory, slot(end), side.body, tool, &point, radial, side.max_depth_m) else { continue };
            side.memory.keep_face_point(t, end, w);
            let centring = towards_axis(tool, &point, &direction);
            let rub = match side.friction {
                Some(friction) => {
                    stick_contacts(&ids, &w, &direction, stiffness, &side.tool_velocity, contacts);
                    side_friction(side.memory, slot(end), side.body, tool, &point, &direction, stiffness * depth, stiffness, friction)
                }
                None => Vec3::zeros(),
            };
            let on_point = direction * (stiffness * depth) + centring * stiffness + rub;
            let across = centring.try_normalize(1e-12);
            for k in 0..3 {
                let i = ids[k] as usize;
                nodes.f[i] += on_point * w[k];
                contacts.push(Contact { node: ids[k], normal: direction, stiffness: stiffness * w[k], drive_m_per_s: 0.0 });
                if let Some(across) = across {
                    contacts.push(Contact { node: ids[k], normal: across, stiffness: stiffness * w[k], drive_m_per_s: 0.0 });
                }
            }
            force -= on_point;
            torque -= (point - tool.tip).cross(&on_point);
            count += 1;
        }
    }
    feedback.force_n += force * weight;
    feedback.torque_nm += torque * weight;
    feedback.contacts = feedback.contacts.max(count);
}

/// From the material point `point`, pushed out along `push`, to the tool's axis, across
/// both the push and the axis: the offset a spring of the contact's stiffness closes. It
/// stands for the groove's walls along a thin shaft, which push a point that slid off
/// sideways back under it (the branched grid's face contacts have the same spring).
/// Measured without friction: the 3 × 0.4 mm plate on its edge laid flat held 8.3 N
/// without it, 8.7 N with it (explicit integrator); the other laid-flat tools reached
/// their rated force either way. Along the axis it pulls nothing: a shaft drawn along
/// itself is held back by friction only ([`super::side_friction`]).
fn towards_axis(tool: &PlacedTool, point: &Vec3, push: &Vec3) -> Vec3 {
    let (_, on_axis) = closest_point_on_segment(point, &tool.tip, &tool.top);
    let offset = on_axis - point;
    across(&across(&offset, push), &tool.axis)
}
