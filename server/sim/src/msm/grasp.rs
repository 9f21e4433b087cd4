//! Grasping with forceps: closing jaws hold the skin between them.
//!
//! Forceps meet the skin as two plates ([`crate::tool::bodies`]): open, they press it
//! and it rises between them. Closing on nothing, the jaws meet. Closing on skin, they
//! stop where they meet the fold between them, and hold it by friction:
//!
//! - **Stop.** While the button closes them, if skin lies between the jaws (the box
//!   between their inner flats, as long as the jaws, as wide as them plus half an edge
//!   of the mesh: the jaws pinch the triangles they cover, whose nodes carry the grip),
//!   the jaws stop closing with their inner flats one skin thickness apart: a fold of
//!   two layers squeezed to half their thickness ([`Bodies::stop_closing_at`]). The
//!   skin between them is held across the flats by the jaws' own contact, as it was
//!   while open.
//! - **Grasp.** Once they have stopped, every node between them is grasped: anchored
//!   where it is in the forceps' frame, it is drawn towards its anchor by a stick
//!   spring in the plane of the flats (the side friction's: super::side_friction), and
//!   moves with the forceps. The hand pinches the jaws with the forceps' grip force
//!   (`grip_force_n`, a scene parameter: the device's jaw is a button), each jaw's
//!   flat pressing the fold with it, so the grasped nodes share a normal force of twice
//!   the grip, and each sticks within the skin's static cone, μ_s times its share;
//!   beyond it, it slides at the dynamic force, its anchor following it. A node whose
//!   anchor has slid out of the jaws is let go; when the last goes, the jaws close on
//!   the rest of their way. Releasing the button lets go of everything (the jaws open).
//! - **Force.** The device feels the springs' pull, about the forceps' tip; under the
//!   implicit integrator the springs are in the system (two contacts across the flats'
//!   normal) and the force is that of the solved state.
//!
//! A skin without friction cannot be grasped: the fold slips out as it is pulled.
//! Nothing here allocates in a step: the grasped nodes' room is made at build and after
//! a cut ([`Grasps::reserve`]).

use super::contact::Contact;
use super::state::Nodes;
use crate::broad_phase::PointGrid;
use crate::grid::friction::{Friction, slid_anchor, stick_force, tangent_projection};
use crate::math::Vec3;
use crate::tool::bodies::Bodies;
use crate::tool::{PlacedTool, Section, ToolCommand, ToolFeedback, ToolShape};

/// The forceps' frame for one step: where their tip is, and their edge, axis and
/// flats' normal (axis × edge), unit.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Frame {
    tip: Vec3,
    edge: Vec3,
    axis: Vec3,
    normal: Vec3,
}

impl Frame {
    fn of(shape: &ToolShape, command: &ToolCommand) -> Self {
        let placed = PlacedTool::new(shape, &command.pose);
        Self { tip: placed.tip, edge: placed.edge, axis: placed.axis, normal: placed.axis.cross(&placed.edge) }
    }

    /// `x` in the frame: (along the edge, along the axis from the tip, across the flats).
    fn local(&self, x: &Vec3) -> Vec3 {
        let d = x - self.tip;
        Vec3::new(d.dot(&self.edge), d.dot(&self.axis), d.dot(&self.normal))
    }

    fn world(&self, local: &Vec3) -> Vec3 {
        self.tip + self.edge * local.x + self.axis * local.y + self.normal * local.z
    }

    /// The frame a fraction `s` of the way from `before` to `self` (the tip moved
    /// along a line; its directions are this step's).
    fn swept_from(&self, before: &Frame, s: f64) -> Frame {
        Frame { tip: before.tip + (self.tip - before.tip) * s, ..*self }
    }
}

/// A grasped node and its anchor, in the forceps' frame ([`Frame::local`]).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Held {
    node: u32,
    anchor: Vec3,
}

/// One pair of forceps and what it holds.
#[derive(Debug, Clone)]
struct Forceps {
    /// The scene's tool, and the body of its first jaw (its feedback carries the grasp's).
    tool: usize,
    body: usize,
    half_width_m: f64,
    /// How far from the tip the jaws grip, m.
    length_m: f64,
    /// The half gap the jaws stop at on a fold of skin, m.
    grip_half_gap_m: f64,
    grip_force_n: f64,
    /// The grasp springs' stiffness, N/m.
    stiffness_n_per_m: f64,
    held: Vec<Held>,
    /// This step's frame and last step's (None while the forceps are away).
    frame: Option<Frame>,
    before: Option<Frame>,
}

impl Forceps {
    /// Whether a point at `local` lies between jaws whose inner flats are `2 half_gap`
    /// apart, within the jaws' length and their width plus `reach_m` either side.
    fn between_jaws(&self, local: &Vec3, half_gap_m: f64, reach_m: f64) -> bool {
        local.x.abs() <= self.half_width_m + reach_m && (0.0..=self.length_m).contains(&local.y) && local.z.abs() < half_gap_m
    }
}

/// The grasps of a skin's forceps (None where it has none).
#[derive(Debug, Clone)]
pub(crate) struct Grasps {
    forceps: Vec<Forceps>,
    /// How far beyond the jaws' sides skin counts as between them: half an edge, m.
    reach_m: f64,
}

impl Grasps {
    /// The grasps of `tools` (the scene's), on a skin `thickness_m` thick with edges
    /// `mean_edge_m` long and `nodes` nodes; springs `stiffness_over_contact` times the
    /// tools' contact stiffness. None without forceps.
    pub fn new(tools: &[ToolShape], bodies: Option<&Bodies>, thickness_m: f64, mean_edge_m: f64, nodes: usize, stiffness_over_contact: f64) -> Option<Self> {
        let bodies = bodies?;
        let forceps: Vec<Forceps> = tools
            .iter()
            .enumerate()
            .filter_map(|(tool, shape)| {
                let Section::Jaws { half_width_m, half_gap_m, grip_force_n, grip_length_m, .. } = shape.section else { return None };
                Some(Forceps {
                    tool,
                    body: bodies.first_jaw(tool)?,
                    half_width_m,
                    length_m: grip_length_m,
                    grip_half_gap_m: (0.5 * thickness_m).min(half_gap_m),
                    grip_force_n,
                    stiffness_n_per_m: stiffness_over_contact * shape.contact_stiffness_n_per_m,
                    held: Vec::with_capacity(nodes),
                    frame: None,
                    before: None,
                })
            })
            .collect();
        (!forceps.is_empty()).then_some(Self { forceps, reach_m: 0.5 * mean_edge_m })
    }

    /// Makes room to grasp every one of `nodes` nodes (after a cut added some).
    pub fn reserve(&mut self, nodes: usize) {
        for f in &mut self.forceps {
            f.held.reserve(nodes.saturating_sub(f.held.len()));
        }
    }

    /// How many nodes tool `tool` holds.
    pub fn held_by(&self, tool: usize) -> usize {
        self.forceps.iter().find(|f| f.tool == tool).map_or(0, |f| f.held.len())
    }

    /// Before the jaws move this step (`commands`: the scene tools'; `nodes` as the
    /// last step left them): lets go where the button is released, a node died or slid
    /// out of the jaws; stops closing jaws on skin between them, and grasps it once
    /// they have stopped.
    pub fn begin_step(&mut self, commands: &[ToolCommand], tools: &[ToolShape], bodies: &mut Bodies, nodes: &Nodes, grid: &PointGrid) {
        let reach_m = self.reach_m;
        for f in &mut self.forceps {
            let command = &commands[f.tool];
            f.before = f.frame;
            f.frame = (command.active && command.pose.is_finite()).then(|| Frame::of(&tools[f.tool], command));
            let Some(frame) = f.frame.filter(|_| command.cut) else {
                f.held.clear();
                bodies.stop_closing_at(f.tool, 0.0);
                continue;
            };
            // A node pulled out of the jaws (by more than half an edge) is let go.
            let Forceps { half_width_m, length_m, .. } = *f;
            let within = |local: &Vec3| local.x.abs() <= half_width_m + 2.0 * reach_m && (-reach_m..=length_m + reach_m).contains(&local.y);
            f.held.retain(|h| nodes.alive[h.node as usize] && within(&frame.local(&nodes.x[h.node as usize])));
            let half_gap_m = bodies.half_gap_m(f.tool);
            if half_gap_m > f.grip_half_gap_m + 1e-9 {
                // Closing: the skin between the jaws is taken as they close on it.
                let (reach, top) = (tools[f.tool].radius_m + reach_m, frame.tip + frame.axis * f.length_m);
                let (min, max) = (frame.tip.inf(&top).add_scalar(-reach), frame.tip.sup(&top).add_scalar(reach));
                grid.query_box(&min, &max, |node| {
                    let i = node as usize;
                    let local = frame.local(&nodes.x[i]);
                    if nodes.alive[i] && nodes.free[i] != Vec3::zeros() && f.between_jaws(&local, half_gap_m, reach_m) && !f.held.iter().any(|h| h.node == node) {
                        f.held.push(Held { node, anchor: local });
                    }
                });
            }
            // Skin held between the jaws: they stop on it; nothing: they close.
            bodies.stop_closing_at(f.tool, if f.held.is_empty() { 0.0 } else { f.grip_half_gap_m });
        }
    }

    /// Each grasped node's pull towards its anchor with the forceps a fraction `s` of
    /// their way through the step, into the nodes' forces, and against the device
    /// (weighted by `weight`) into the first jaw's feedback, its torque about that jaw's
    /// tip (`placed`: the bodies this step).
    ///
    /// - Explicit (`contacts` None; `h` the substep): a stick in the flats' plane, the
    ///   force that brings the node onto its anchor over the substep (its other forces
    ///   counted), within the static cone; beyond it the dynamic force, and the anchor
    ///   goes where the node goes. (A spring as soft as the explicit contacts' let the
    ///   node lag its anchor by millimetres and slip out of the jaws before friction
    ///   limited it.)
    /// - Implicit (`contacts`; `h` the step): the spring at the step's start, and the
    ///   spring in the system across the flats' normal, its anchor moving with the
    ///   forceps over the step; the force sent back and the sliding wait for the solved
    ///   state ([`Grasps::after_solve`]).
    #[allow(clippy::too_many_arguments)]
    pub fn pull(&mut self, nodes: &mut Nodes, friction: Option<Friction>, s: f64, h: f64, mut contacts: Option<&mut Vec<Contact>>, placed: &[Option<PlacedTool>], feedback: &mut [ToolFeedback], weight: f64) {
        let friction = friction.unwrap_or_default();
        for f in &mut self.forceps {
            let (Some(now), Some(jaw_tip)) = (f.frame, placed[f.body].map(|p| p.tip)) else { continue };
            if f.held.is_empty() {
                continue;
            }
            let frame = f.before.map_or(now, |before| now.swept_from(&before, s));
            let across = tangent_projection(&frame.normal);
            let normal_n = 2.0 * f.grip_force_n / f.held.len() as f64;
            let fb = &mut feedback[f.body];
            for held in &mut f.held {
                let i = held.node as usize;
                let (x, anchor) = (nodes.x[i], frame.world(&held.anchor));
                if let Some(contacts) = contacts.as_deref_mut() {
                    // The solve takes a contact's rest point where it is at the step's
                    // start, moving at its drive over the step (its damping then acts on
                    // the node's velocity relative to it, not on the node's own).
                    let start = f.before.unwrap_or(now);
                    let (pull, _) = stick_force(&x, &start.world(&held.anchor), &frame.normal, f.stiffness_n_per_m, normal_n, friction);
                    nodes.f[i] += pull;
                    let velocity = (now.tip - start.tip) / h;
                    super::side_friction::stick_contacts(&[held.node], &[1.0], &frame.normal, f.stiffness_n_per_m, &velocity, contacts);
                    continue;
                }
                let (m, v) = (nodes.mass[i], nodes.v[i]);
                let needed = across * ((anchor - x - v * h) * (m / (h * h)) - nodes.f[i]);
                let size = needed.norm();
                let force = if size <= friction.static_coefficient * normal_n {
                    needed
                } else {
                    let sliding = needed * (friction.dynamic_coefficient * normal_n / size);
                    let v_next = v + (nodes.f[i] + sliding) * (h / m);
                    held.anchor = frame.local(&(x + v_next * h));
                    sliding
                };
                nodes.f[i] += force;
                fb.force_n -= force * weight;
                fb.torque_nm -= (x - (jaw_tip - now.tip + frame.tip)).cross(&force) * weight;
            }
        }
    }

    /// After the implicit solve: each grasped node's pull at the solved state, beyond
    /// the static cone brought down to the dynamic force and its anchor slid; against
    /// the device into the first jaw's feedback.
    pub fn after_solve(&mut self, nodes: &Nodes, friction: Option<Friction>, placed: &[Option<PlacedTool>], feedback: &mut [ToolFeedback]) {
        let friction = friction.unwrap_or_default();
        for f in &mut self.forceps {
            let (Some(frame), Some(jaw_tip)) = (f.frame, placed[f.body].map(|p| p.tip)) else { continue };
            if f.held.is_empty() {
                continue;
            }
            let normal_n = 2.0 * f.grip_force_n / f.held.len() as f64;
            let fb = &mut feedback[f.body];
            for h in &mut f.held {
                let x = nodes.x[h.node as usize];
                let (pull, sliding) = stick_force(&x, &frame.world(&h.anchor), &frame.normal, f.stiffness_n_per_m, normal_n, friction);
                if sliding {
                    h.anchor = frame.local(&slid_anchor(&x, &pull, f.stiffness_n_per_m));
                }
                fb.force_n -= pull;
                fb.torque_nm -= (x - jaw_tip).cross(&pull);
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{Pose, Quat};

    #[test]
    fn the_frame_maps_the_edge_axis_and_flats_normal() {
        let shape = ToolShape {
            name: "forceps".into(),
            radius_m: 5e-3,
            length_m: 0.08,
            section: Section::Jaws { half_width_m: 1e-3, half_thickness_m: 5e-4, half_gap_m: 4e-3, grip_force_n: 3.0, grip_length_m: 0.01 },
            contact_stiffness_n_per_m: 200.0,
            can_cut: false,
            max_force_n: 10.0,
            cutting_shape: None,
            edge_local: Vec3::x(),
            tip_shape: crate::tool::TipShape::Flat,
        };
        let command = ToolCommand { pose: Pose::new(Vec3::new(0.01, 0.0, 0.0), Quat::identity()), active: true, cut: true };
        let frame = Frame::of(&shape, &command);
        assert_eq!((frame.edge, frame.axis, frame.normal), (Vec3::x(), Vec3::z(), Vec3::y()));
        let x = Vec3::new(0.012, -0.001, 0.003);
        let local = frame.local(&x);
        assert!((local - Vec3::new(0.002, 0.003, -0.001)).norm() < 1e-15);
        assert!((frame.world(&local) - x).norm() < 1e-15);
    }
}
