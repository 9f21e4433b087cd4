//! A blade through the skin pushes it with its flat.
//!
//! A blade that has punctured the skin passes through it: only its edge cuts, and only
//! by moving along the edge ([`super::resistance`]). Across its flat it must push the
//! skin, but a 1 mm blade between nodes 2.5 mm apart touches no node, so the vertex
//! penalty of [`super::contact`] let a blade drawn sideways slip through the skin with
//! no force. Here the skin's material point where the blade's axis crossed it at the
//! start of the step (a triangle and barycentric weights: the "hole") goes with the
//! blade across its flat: each substep the point is moved onto the plane of the flat
//! through the axis (position-based dynamics' point projection, the nodes sharing by
//! their weights over their masses) and gets the force that makes it move with the
//! blade across the flat (inelastic, both ways: the blade has two flats). Along the
//! edge (where the cut advances) and along the axis (the blade sliding in and out) the
//! point is free. The blade feels the opposite force: the skin dragged sideways.
//!
//! The hole is kept from step to step while the blade spans it; once the blade has
//! moved on along its edge past it by more than its width (cutting), or its triangle is
//! cut away, a new one is taken where the axis crosses the skin.

use super::contact::Contact;
use super::cut::Crossing;
use super::state::{Nodes, Topology};
use crate::math::{Vec3, barycentric_closest};
use crate::tool::{PlacedTool, ToolFeedback};

/// The skin's material point a blade passes through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Hole {
    triangle: u32,
    w: [f64; 3],
}

impl Hole {
    /// The material point at `crossing`.
    pub fn at(crossing: &Crossing, nodes: &Nodes, topo: &Topology) -> Self {
        let [a, b, c] = topo.tris[crossing.triangle as usize].map(|v| nodes.x[v as usize]);
        Hole { triangle: crossing.triangle, w: barycentric_closest(&crossing.point, &a, &b, &c) }
    }
}

/// A blade as the flat sees it for one substep.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Blade<'a> {
    pub placed: &'a PlacedTool,
    /// Unit normal of its flat (across its axis and its edge).
    pub flat_normal: Vec3,
    /// Unit direction its edge faces (across its axis, in its flat).
    pub edge: Vec3,
    /// Its velocity, m/s.
    pub velocity: Vec3,
}

/// Pushes the skin at `hole` with the blade's flat for one substep of h; adds the
/// reaction (times `weight`) to `feedback`. With the implicit integrator
/// (`implicit_contacts`: the stiffness, N/m, and the list the solve takes) the point's
/// nodes enter its matrix as stiff contacts across the flat instead of getting a force.
/// Returns false when the hole's triangle is gone (cut away) or the blade no longer
/// spans it.
#[allow(clippy::too_many_arguments)]
pub(crate) fn push_with_flat(
    hole: &Hole,
    blade: Blade,
    nodes: &mut Nodes,
    topo: &Topology,
    h: f64,
    implicit_contacts: Option<(f64, &mut Vec<Contact>)>,
    feedback: &mut ToolFeedback,
    weight: f64,
) -> bool {
    let t = hole.triangle as usize;
    if !topo.tri_alive[t] {
        return false;
    }
    let Blade { placed: tool, flat_normal: n, edge, velocity: tool_velocity } = blade;
    let ids = topo.tris[t];
    let w = hole.w;
    let point: Vec3 = (0..3).map(|k| nodes.x[ids[k] as usize] * w[k]).sum();
    let along = (point - tool.tip).dot(&tool.axis);
    let ahead = (point - tool.tip).dot(&edge);
    // Off the blade: below its tip, above its top, or left behind its back by more than
    // its width (the blade moved on along its edge, cutting: the point is on the wound).
    if along < 0.0 || along > tool.length_m || ahead < -2.0 * tool.radius_m {
        return false;
    }
    let point_inv_mass: f64 = (0..3).map(|k| w[k] * w[k] * nodes.inv_mass[ids[k] as usize]).sum();
    if point_inv_mass <= 0.0 {
        return true;
    }
    let share = |k: usize| w[k] * nodes.inv_mass[ids[k] as usize] / point_inv_mass;
    // The blade fills its hole: drawn back (its back leading) it pushes the hole's
    // rim with its back, dragging the point along, rather than passing through uncut
    // skin.
    let back = ahead > 0.0;
    // Onto the flat's plane through the axis (and back to the axis along the edge).
    let off = n * (point - tool.tip).dot(&n) + if back { edge * ahead } else { Vec3::zeros() };
    for k in 0..3 {
        let i = ids[k] as usize;
        nodes.x[i] -= (off * share(k)).component_mul(&nodes.free[i]);
    }
    // The relative velocity the blade stops: across its flat, and into its back.
    let stopped = |relative: Vec3| n * relative.dot(&n) + if back { edge * relative.dot(&edge).max(0.0) } else { Vec3::zeros() };
    let lever = point - tool.tip;
    match implicit_contacts {
        Some((stiffness, contacts)) => {
            let velocity: Vec3 = (0..3).map(|k| nodes.v[ids[k] as usize] * w[k]).sum();
            let dv = -stopped(velocity - tool_velocity);
            for k in 0..3 {
                let i = ids[k] as usize;
                nodes.v[i] += (dv * share(k)).component_mul(&nodes.free[i]);
                contacts.push(Contact { node: ids[k], normal: n, stiffness: stiffness * w[k] });
                if back {
                    contacts.push(Contact { node: ids[k], normal: edge, stiffness: stiffness * w[k] });
                }
            }
            // The force the rest of the skin pulls the point off the flat (and against
            // the back) with.
            let skin: Vec3 = (0..3).map(|k| nodes.f[ids[k] as usize] * w[k]).sum();
            let held = n * skin.dot(&n) + if back { edge * skin.dot(&edge).max(0.0) } else { Vec3::zeros() };
            feedback.force_n += held * weight;
            feedback.torque_nm += lever.cross(&held) * weight;
        }
        None => {
            let coming: Vec3 = (0..3).map(|k| (nodes.v[ids[k] as usize] + nodes.f[ids[k] as usize] * (h * nodes.inv_mass[ids[k] as usize])) * w[k]).sum();
            let on_point = -stopped(coming - tool_velocity) / (point_inv_mass * h);
            for k in 0..3 {
                let i = ids[k] as usize;
                nodes.f[i] += (on_point * w[k]).component_mul(&nodes.free[i]);
            }
            feedback.force_n -= on_point * weight;
            feedback.torque_nm -= lever.cross(&on_point) * weight;
        }
    }
    true
}
