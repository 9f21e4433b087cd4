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
use crate::hash::{HashState, StateHasher};
use crate::math::{Vec3, barycentric_closest};
use crate::tool::{PlacedTool, ToolFeedback};

/// The skin's material point a blade passes through.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Hole {
    triangle: u32,
    w: [f64; 3],
}

impl HashState for Hole {
    fn hash_state(&self, h: &mut StateHasher) {
        (self.triangle, self.w).hash_state(h);
    }
}

impl Hole {
    /// The material point at `crossing`.
    pub fn at(crossing: &Crossing, nodes: &Nodes, topo: &Topology) -> Self {
        let [a, b, c] = topo.tris[crossing.triangle as usize].map(|v| nodes.x[v as usize]);
        Hole { triangle: crossing.triangle, w: barycentric_closest(&crossing.point, &a, &b, &c) }
    }
}

/// A blade as the flat sees it for one substep: where it is (its edge and flat with
/// it) and its velocity, m/s.
#[derive(Debug, Clone, Copy)]
pub(crate) struct Blade<'a> {
    pub placed: &'a PlacedTool,
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
    let Blade { placed: tool, velocity: tool_velocity } = blade;
    let (n, edge) = (tool.flat_normal(), tool.edge);
    let ids = topo.tris[t];
    let w = hole.w;
    let point: Vec3 = (0..3).map(|k| nodes.x[ids[k] as usize] * w[k]).sum();
    let along = (point - tool.tip).dot(&tool.axis);
    let ahead = (point - tool.tip).dot(&edge);
    // Off the blade: below its tip, above its top, or left behind its back by more than
    // its width (the blade moved on along its edge, cutting: the point is on the wound).
    if along < 0.0 || along > tool.length_m || ahead < -tool.width_m() {
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
                contacts.push(Contact { node: ids[k], normal: n, stiffness: stiffness * w[k], drive_m_per_s: 0.0 });
                if back {
                    contacts.push(Contact { node: ids[k], normal: edge, stiffness: stiffness * w[k], drive_m_per_s: 0.0 });
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

#[cfg(test)]
mod tests {
    use super::*;

    use crate::msm::contact::tests::tool;

    /// One horizontal triangle 5 mm below the top of the vertical test tool (tip at the
    /// origin, 1 mm radius), its nodes of 1 g, the tool's axis through its centroid.
    fn skin() -> (Nodes, Topology, Hole) {
        let mut nodes = Nodes::default();
        let mut topo = Topology::default();
        for p in [Vec3::new(-2e-3, -1e-3, 5e-3), Vec3::new(2e-3, -1e-3, 5e-3), Vec3::new(0.0, 2e-3, 5e-3)] {
            let id = nodes.push(p, Vec3::zeros());
            nodes.set_mass(id, 1e-3);
            topo.node_tris.push(Vec::new());
        }
        topo.push_tri([0, 1, 2], 6e-6);
        let hole = Hole { triangle: 0, w: [1.0 / 3.0; 3] };
        (nodes, topo, hole)
    }

    fn point(nodes: &Nodes, hole: &Hole) -> Vec3 {
        (0..3).map(|k| nodes.x[k] * hole.w[k]).sum()
    }

    /// The test tool moved by `by`, with its edge facing +x (its flat's normal +y).
    fn step(nodes: &mut Nodes, topo: &Topology, hole: &Hole, by: Vec3) -> (bool, ToolFeedback) {
        let mut placed = tool();
        placed.tip += by;
        placed.top += by;
        placed.edge = Vec3::x();
        assert_eq!(placed.flat_normal(), Vec3::y());
        let blade = Blade { placed: &placed, velocity: by / 1e-3 };
        let mut feedback = ToolFeedback::default();
        let held = push_with_flat(hole, blade, nodes, topo, 1e-3, None, &mut feedback, 1.0);
        (held, feedback)
    }

    #[test]
    fn the_flat_takes_the_hole_along_across_it_and_pushes_back_on_the_blade() {
        let (mut nodes, topo, hole) = skin();
        let (held, feedback) = step(&mut nodes, &topo, &hole, Vec3::new(0.0, 3e-4, 0.0));
        assert!(held);
        assert!((point(&nodes, &hole).y - 3e-4).abs() < 1e-15, "on the flat's plane: {:?}", point(&nodes, &hole));
        // The force that gives the point (3 g over its weights: 1/Σw²/m = 3 g) the
        // blade's 0.3 m/s across the flat within the millisecond, opposite on the blade.
        assert!((feedback.force_n - Vec3::new(0.0, -0.9, 0.0)).norm() < 1e-9, "{:?}", feedback.force_n);
        assert!((0..3).all(|k| (nodes.f[k] - Vec3::new(0.0, 0.3, 0.0)).norm() < 1e-9));
    }

    #[test]
    fn forward_along_the_edge_and_along_the_axis_the_hole_is_free() {
        let (mut nodes, topo, hole) = skin();
        let before = point(&nodes, &hole);
        for by in [Vec3::new(5e-4, 0.0, 0.0), Vec3::new(0.0, 0.0, -1e-3)] {
            let (held, feedback) = step(&mut nodes, &topo, &hole, by);
            assert!(held);
            assert_eq!((point(&nodes, &hole), feedback.force_n), (before, Vec3::zeros()), "moved by {by:?}");
        }
        // Cut on past the hole by more than the blade's width: let go.
        assert!(!step(&mut nodes, &topo, &hole, Vec3::new(2.5e-3, 0.0, 0.0)).0);
    }

    #[test]
    fn drawn_back_the_blade_pushes_the_hole_with_its_back() {
        let (mut nodes, topo, hole) = skin();
        let (held, feedback) = step(&mut nodes, &topo, &hole, Vec3::new(-4e-4, 0.0, 0.0));
        assert!(held);
        assert!((point(&nodes, &hole).x + 4e-4).abs() < 1e-15, "back at the axis: {:?}", point(&nodes, &hole));
        assert!(feedback.force_n.x > 0.0, "the skin resists: {:?}", feedback.force_n);
    }

    #[test]
    fn a_hole_cut_away_or_off_the_blade_is_let_go() {
        let (mut nodes, mut topo, hole) = skin();
        assert!(!step(&mut nodes, &topo, &hole, Vec3::new(0.0, 0.0, 6e-3)).0, "below the tip");
        topo.kill_tri(0);
        assert!(!step(&mut nodes, &topo, &hole, Vec3::zeros()).0, "cut away");
    }
}
