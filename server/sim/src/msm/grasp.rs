//! Grasping with forceps: closing jaws hold the skin between them.
//!
//! Forceps meet the skin as two plates ([`crate::tool::bodies`]): open, they press it
//! and it rises between them. Closing on nothing, the jaws meet. Closing on skin, they
//! stop where they meet the fold between them, and hold it by friction:
//!
//! - **Grasp.** While the button closes them, the nodes between the jaws are taken (the
//!   box between their inner flats, `grip_length_m` from the tip, as wide as the jaws
//!   plus half an edge of the mesh: the jaws pinch the triangles they cover, whose nodes
//!   carry the grip): each is anchored where it is in the forceps' frame, drawn towards
//!   its anchor in the plane of the flats, and moves with the forceps.
//! - **Stop.** Holding skin, the jaws stop closing with their inner flats one skin
//!   thickness apart: a fold of two layers squeezed to half their thickness
//!   ([`Bodies::stop_closing_at`]). The skin between them is held across the flats by
//!   the jaws' own contact, as it was while open.
//! - **Grip.** The hand pinches the jaws with the forceps' grip force
//!   (`grip_force_n`, a scene parameter, where the device's jaw is a button; the share
//!   of it the command squeezes with, where the device has an analog gripper), each jaw's
//!   flat pressing the fold with it, so the grasped nodes share a normal force of twice
//!   the grip, and each sticks within the skin's static cone, μ_s times its share;
//!   beyond it, it slides at the dynamic force, its anchor following it. A node pulled
//!   more than half an edge out of the gripping tips is let go; when the last goes, the
//!   jaws close the rest of their way. Releasing the button lets go of everything (the jaws open).
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
use crate::hash::{HashState, StateHasher};
use crate::grid::friction::{Friction, slid_anchor, stick_force, tangent_projection};
use crate::math::Vec3;
use crate::tool::bodies::Bodies;
use crate::tool::{PlacedTool, Section, ToolCommand, ToolFeedback, ToolShape};

/// A grasped node and its anchor in the forceps' frame ([`PlacedTool::to_frame`]:
/// along the axis from the tip, along the edge, across the flats).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Held {
    node: u32,
    anchor: [f64; 3],
}

/// One pair of forceps and what it holds.
#[derive(Debug, Clone)]
struct Forceps {
    /// The scene's tool, and the body of its first jaw (its feedback carries the grasp's).
    tool: usize,
    body: usize,
    tips: Tips,
    /// The half gap the jaws stop at on a fold of skin, m.
    grip_half_gap_m: f64,
    /// The forceps' rated grip, and the hand's on them this step ([`ToolCommand::grip_n`]), N.
    grip_force_n: f64,
    grip_n: f64,
    /// The grasp springs' stiffness, N/m.
    stiffness_n_per_m: f64,
    held: Vec<Held>,
    /// Where the forceps are this step and were last step (None while away).
    now: Option<PlacedTool>,
    before: Option<PlacedTool>,
}

/// The jaws' gripping tips: as wide as the jaws, `length_m` from the tip.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Tips {
    half_width_m: f64,
    length_m: f64,
}

impl Tips {
    /// Whether a point at `local` (the forceps' frame, [`PlacedTool::to_frame`]) lies
    /// within `margin_m` of the tips along the axis and the edge, the edge's way widened
    /// by `reach_m` (the triangles the jaws cover); across the flats, anywhere.
    fn contain(&self, [along, edge, _]: [f64; 3], reach_m: f64, margin_m: f64) -> bool {
        edge.abs() <= self.half_width_m + reach_m + margin_m && (-margin_m..=self.length_m + margin_m).contains(&along)
    }
}

impl Forceps {
    /// The normal force each grasped node takes: both jaws' flats press the fold with
    /// the grip, shared by its nodes, N.
    fn normal_share_n(&self) -> f64 {
        2.0 * self.grip_n / self.held.len() as f64
    }

    /// The forceps `s` of their way from last step's pose to this step's (the tip moved
    /// along a line; the directions are this step's).
    fn swept(&self, now: &PlacedTool, s: f64) -> PlacedTool {
        self.before.map_or(*now, |before| now.moved(before.tip + (now.tip - before.tip) * s, now.axis))
    }
}

/// The grasps of a skin's forceps (None where it has none).
#[derive(Debug, Clone)]
pub(crate) struct Grasps {
    forceps: Vec<Forceps>,
    /// How far beyond the jaws' sides skin counts as between them: half an edge, m.
    reach_m: f64,
}

impl HashState for Grasps {
    /// What each pair of forceps holds (the nodes and their anchors), its grip, and
    /// where it was and is.
    fn hash_state(&self, h: &mut StateHasher) {
        for f in &self.forceps {
            h.write_u64(f.held.len() as u64);
            for held in &f.held {
                (held.node, held.anchor).hash_state(h);
            }
            (f.grip_n, f.now, f.before).hash_state(h);
        }
    }
}

impl Grasps {
    /// The grasps of `tools` (the scene's), on a skin `thickness_m` thick with edges
    /// `mean_edge_m` long; springs `stiffness_over_contact` times the tools' contact
    /// stiffness. None without forceps. Room to grasp is made by [`Grasps::reserve`].
    pub fn new(tools: &[ToolShape], bodies: Option<&Bodies>, thickness_m: f64, mean_edge_m: f64, stiffness_over_contact: f64) -> Option<Self> {
        let bodies = bodies?;
        let forceps: Vec<Forceps> = tools
            .iter()
            .enumerate()
            .filter_map(|(tool, shape)| {
                let Section::Jaws { half_width_m, half_gap_m, grip_force_n, grip_length_m, .. } = shape.section else { return None };
                Some(Forceps {
                    tool,
                    body: bodies.first_jaw(tool)?,
                    tips: Tips { half_width_m, length_m: grip_length_m },
                    grip_half_gap_m: (0.5 * thickness_m).min(half_gap_m),
                    grip_force_n,
                    grip_n: 0.0,
                    stiffness_n_per_m: stiffness_over_contact * shape.contact_stiffness_n_per_m,
                    held: Vec::new(),
                    now: None,
                    before: None,
                })
            })
            .collect();
        (!forceps.is_empty()).then_some(Self { forceps, reach_m: 0.5 * mean_edge_m })
    }

    /// Makes room to grasp every one of `nodes` nodes (at build, and after a cut added some).
    pub fn reserve(&mut self, nodes: usize) {
        for f in &mut self.forceps {
            f.held.reserve(nodes.saturating_sub(f.held.len()));
        }
    }

    /// How many nodes tool `tool` holds.
    pub fn held_by(&self, tool: usize) -> usize {
        self.forceps.iter().find(|f| f.tool == tool).map_or(0, |f| f.held.len())
    }

    /// The nodes tool `tool` holds.
    pub fn nodes_held_by(&self, tool: usize) -> impl Iterator<Item = u32> + '_ {
        self.forceps.iter().filter(move |f| f.tool == tool).flat_map(|f| f.held.iter().map(|h| h.node))
    }

    /// Before the jaws move this step (`commands`: the scene tools'; `nodes` as the
    /// last step left them): lets go where the button is released, a node died or was
    /// pulled out of the jaws; while the jaws close, takes the skin between them; stops
    /// the jaws on what they hold.
    pub fn begin_step(&mut self, commands: &[ToolCommand], tools: &[ToolShape], bodies: &mut Bodies, nodes: &Nodes, grid: &PointGrid) {
        let reach_m = self.reach_m;
        for f in &mut self.forceps {
            let command = &commands[f.tool];
            f.before = f.now;
            f.now = (command.active && command.pose.is_finite()).then(|| PlacedTool::new(&tools[f.tool], &command.pose));
            f.grip_n = command.grip_n(f.grip_force_n);
            let Some(now) = f.now.filter(|_| command.closes_jaws()) else {
                f.held.clear();
                bodies.stop_closing_at(f.tool, 0.0);
                continue;
            };
            // A node pulled out of the jaws (by more than half an edge) is let go.
            let tips = f.tips;
            f.held.retain(|h| nodes.alive[h.node as usize] && tips.contain(now.to_frame(&nodes.x[h.node as usize]), reach_m, reach_m));
            let half_gap_m = bodies.half_gap_m(f.tool);
            if half_gap_m > f.grip_half_gap_m + 1e-9 {
                // Closing: the skin between the jaws is taken as they close on it.
                let (reach, top) = (tools[f.tool].radius_m + reach_m, now.tip + now.axis * f.tips.length_m);
                let (min, max) = (now.tip.inf(&top).add_scalar(-reach), now.tip.sup(&top).add_scalar(reach));
                grid.query_box(&min, &max, |node| {
                    let i = node as usize;
                    let local = now.to_frame(&nodes.x[i]);
                    let between = f.tips.contain(local, reach_m, 0.0) && local[2].abs() < half_gap_m;
                    if between && nodes.alive[i] && nodes.free[i] != Vec3::zeros() && !f.held.iter().any(|h| h.node == node) {
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
            let (Some(now), Some(jaw_tip)) = (f.now, placed[f.body].map(|p| p.tip)) else { continue };
            if f.held.is_empty() {
                continue;
            }
            let (normal_n, k) = (f.normal_share_n(), f.stiffness_n_per_m);
            let normal = now.flat_normal();
            let fb = &mut feedback[f.body];
            if let Some(contacts) = contacts.as_deref_mut() {
                // The solve takes a contact's rest point where it is at the step's
                // start, moving at its drive over the step (its damping then acts on the
                // node's velocity relative to it, not on the node's own).
                let start = f.before.unwrap_or(now);
                let velocity = (now.tip - start.tip) / h;
                for held in &f.held {
                    let (pull, _) = stick_force(&nodes.x[held.node as usize], &start.from_frame(held.anchor), &normal, k, normal_n, friction);
                    nodes.f[held.node as usize] += pull;
                    super::side_friction::stick_contacts(&[held.node], &[1.0], &normal, k, &velocity, contacts);
                }
                continue;
            }
            let frame = f.swept(&now, s);
            let across = tangent_projection(&normal);
            // The first jaw's tip, swept with the forceps.
            let lever_from = jaw_tip - now.tip + frame.tip;
            for held in &mut f.held {
                let i = held.node as usize;
                let (x, m, v) = (nodes.x[i], nodes.mass[i], nodes.v[i]);
                let needed = across * ((frame.from_frame(held.anchor) - x - v * h) * (m / (h * h)) - nodes.f[i]);
                let size = needed.norm();
                let force = if size <= friction.static_coefficient * normal_n {
                    needed
                } else {
                    let sliding = needed * (friction.dynamic_coefficient * normal_n / size);
                    let v_next = v + (nodes.f[i] + sliding) * (h / m);
                    held.anchor = frame.to_frame(&(x + v_next * h));
                    sliding
                };
                nodes.f[i] += force;
                fb.force_n -= force * weight;
                fb.torque_nm -= (x - lever_from).cross(&force) * weight;
            }
        }
    }

    /// After the implicit solve: each grasped node's pull at the solved state, beyond
    /// the static cone brought down to the dynamic force and its anchor slid; against
    /// the device into the first jaw's feedback.
    pub fn after_solve(&mut self, nodes: &Nodes, friction: Option<Friction>, placed: &[Option<PlacedTool>], feedback: &mut [ToolFeedback]) {
        let friction = friction.unwrap_or_default();
        for f in &mut self.forceps {
            let (Some(now), Some(jaw_tip)) = (f.now, placed[f.body].map(|p| p.tip)) else { continue };
            if f.held.is_empty() {
                continue;
            }
            let (normal_n, k, normal) = (f.normal_share_n(), f.stiffness_n_per_m, now.flat_normal());
            let fb = &mut feedback[f.body];
            for held in &mut f.held {
                let x = nodes.x[held.node as usize];
                let (pull, sliding) = stick_force(&x, &now.from_frame(held.anchor), &normal, k, normal_n, friction);
                if sliding {
                    held.anchor = now.to_frame(&slid_anchor(&x, &pull, k));
                }
                fb.force_n -= pull;
                fb.torque_nm -= (x - jaw_tip).cross(&pull);
            }
        }
    }
}
