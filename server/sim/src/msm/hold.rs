//! Contact that holds: the tool's tip face against intact skin, as a constraint.
//!
//! The penalty of [`super::contact`] lets a node that sinks deeper than the tool's
//! radius slide out along the shaft, and a tool thinner than the node spacing falls
//! between nodes, so a pressed probe went through intact skin. Here the tip face is a
//! hard constraint instead (a god-object in the sense of Zilles and Salisbury 1995: the
//! skin may not cross the tip): after each substep's integration
//!
//! 1. every node under the tip face (inside the cylinder, nearer its tip face than its
//!    side) is put back on the face plane, and
//! 2. the triangle the tool's axis crosses nearest its tip is moved, point by point
//!    with its barycentric weights over the nodes' inverse masses (position-based
//!    dynamics' point–triangle projection), so that the crossing point lies on the face
//!    plane: a blade 0.5 mm thin between nodes 2.5 mm apart holds as a probe does.
//!
//! Projected nodes lose the velocity with which they approached the tool (relative to
//! the tool's own velocity), so the contact is inelastic and adds no energy; across the
//! face, Coulomb friction (before the explicit integrator's substep, as a force that
//! overcomes the point's mass and implicit drag; in the implicit integrator's solve, as
//! stiff springs that carry a stuck point with the tool, checked against the cone after
//! it, or as the dynamic force on a sliding one: [`Rub`]). Under the implicit integrator
//! a round tip also holds the nodes just off its ball that the skin's forces would carry
//! into it within the step (a speculative contact, whose spring closes the gap and no
//! more), so that the ring of points round a resting ball keeps its members from step
//! to step. The force
//! the tool feels is the force the rest of the skin presses the held points against its
//! face with (their spring, foundation and gravity forces along the axis, never
//! pulling): the force of the solved state, not a penalty depth. A tool that appeared
//! already below the skin (placed there by a script, or through a wound) is through it,
//! and is not held until its axis no longer crosses the skin; so is a blade whose cut
//! has begun ([`super::MassSpring`] decides which tools hold).
//!
//! Only crossings within 60° of the triangle's normal are held: a tool lying along the
//! skin pushes it with its side (the penalty), not with its face.

use nalgebra::Matrix3;

use super::contact::Contact;
use super::foundation::Foundation;
use super::cut::{Crossing, nearest_crossing, triangles_near};
use super::state::{Nodes, Topology};
use crate::broad_phase::PointGrid;
use crate::hash::{HashState, StateHasher};
use crate::math::{Vec3, across, barycentric_closest, closest_point_on_triangle};
use crate::tool::{PlacedTool, TipShape, ToolFeedback};

/// The smallest |cos| between the tool's axis and a held triangle's normal.
const MIN_HOLD_COSINE: f64 = 0.5;

/// What one tool held during the current step.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub(crate) struct HoldState {
    /// Force with which the held skin pushed back along the tool's axis, N, averaged
    /// over the step's substeps (what a blade's puncture is decided on).
    pub force_n: f64,
}

/// Coulomb friction at the tip face: (static, dynamic) coefficients.
pub(crate) type Friction = (f64, f64);

/// The tip-face constraint of every tool, with its scratch (kept so that a step does
/// not allocate).
#[derive(Debug, Clone)]
pub(crate) struct Holder {
    pub tools: Vec<HoldState>,
    /// The triangle each tool held at its last substep: a contact that goes on is kept
    /// however the skin tilts and stretches around the tip (only a new one must face
    /// it), and it and its neighbours are candidates however far their corners moved.
    held_triangle: Vec<Option<u32>>,
    friction: Option<Friction>,
    candidates: Vec<u32>,
    /// The implicit integrator's held points, whose friction acts after its solve.
    rubs: Vec<Rub>,
}

/// A point held by a tool under the implicit integrator. One the static cone can hold
/// sticks to the tool within the solve (stiff springs across the push, like the held
/// contact along it); after the solve the force they took is checked against the cone
/// and, beyond it, replaced by the dynamic friction (a velocity correction). One the
/// cone cannot hold slides against the dynamic friction, a force added before the solve.
/// Friction decided within the solve keeps the membrane's response to it in the same
/// step: as a velocity filter after the solve alone (Bridson, Fedkiw and Anderson
/// 2002) the springs answered it a step late, and the points round a resting round tip
/// alternated between sticking and sliding from step to step.
#[derive(Debug, Clone, Copy)]
struct Rub {
    tool: usize,
    /// Its nodes and their weights (a node alone: weights 1, 0, 0).
    ids: [u32; 3],
    w: [f64; 3],
    push: Vec3,
    /// From the tool's tip to the point, m.
    lever: Vec3,
    tool_velocity: Vec3,
    normal_n: f64,
    /// The substep's share of the step.
    weight: f64,
    /// Stuck within the solve: the stiffness of its springs across the push (times each
    /// node's weight), N/m, and their directions; None when sliding or frictionless.
    stuck: Option<(f64, [Vec3; 2])>,
    /// Sliding: the dynamic friction on it, N (added to its nodes' forces once the
    /// tool's held points are all found, so that it does not count as pressing).
    slide: Vec3,
}

/// The model state a hold reads and changes.
pub(crate) struct HoldView<'a> {
    pub nodes: &'a mut Nodes,
    pub topo: &'a Topology,
    pub grid: &'a PointGrid,
    /// Longest edge of the mesh, m (how far around the tool triangles are looked for).
    pub max_edge_m: f64,
    /// How far nodes may have moved since the broad phase was refreshed, m.
    pub margin_m: f64,
    /// The substep, s.
    pub h: f64,
    pub drag: Drag<'a>,
    /// Implicit integration: the held points' constraint goes into the system matrix
    /// as a stiff contact along the axis (appended here, N/m) instead of as a force
    /// predicted from an explicit substep.
    pub implicit: Option<ImplicitHold<'a>>,
}

/// The damping both integrators take implicitly: the force that holds a point must
/// overcome it too, or a skin point stuck to a tool by friction would lag it by the
/// foundation's drag (ten times the mass over a substep on the default skin).
#[derive(Debug, Clone, Copy)]
pub(crate) struct Drag<'a> {
    pub mass_damping_per_s: f64,
    pub foundation: Option<&'a Foundation>,
}

impl Drag<'_> {
    /// R = m(1 + hα)·I + h·C_i: a force F over the substep h changes node `i`'s velocity
    /// at its end by h·R⁻¹·F.
    fn resistance(&self, nodes: &Nodes, i: usize, h: f64) -> Matrix3<f64> {
        let inertia = Matrix3::identity() * (nodes.mass[i] * (1.0 + h * self.mass_damping_per_s));
        match self.foundation {
            Some(foundation) => inertia + foundation.drag_matrix(i) * h,
            None => inertia,
        }
    }
}

/// Where the implicit integrator takes held points ([`HoldView::implicit`]).
pub(crate) struct ImplicitHold<'a> {
    pub contacts: &'a mut Vec<super::contact::Contact>,
    /// Stiffness of a held point along the axis in the system matrix, N/m.
    pub stiffness_n_per_m: f64,
}

/// A tool as a hold sees it for one substep.
#[derive(Debug, Clone, Copy)]
pub(crate) struct HeldTool<'a> {
    pub placed: &'a PlacedTool,
    /// The tool's velocity, m/s.
    pub velocity: Vec3,
    /// How far above the tip face skin may lie and still be taken as pressed by it, m:
    /// what the tip can have travelled into the skin since the last substep, with a
    /// tolerance ([`hold_reach_m`]). Skin further above is skin the tool got under from
    /// the side (at a border, through a wound): the tool is through it.
    pub reach_m: f64,
}

/// Skin within this many mean edge lengths above the tip face, beyond the tip's own
/// travel, is taken as pressed by it (the skin's own motion within a substep).
const HOLD_TOLERANCE_EDGES: f64 = 0.1;

/// [`HeldTool::reach_m`] for a tool moving at `velocity` along `axis` over a substep h.
pub(crate) fn hold_reach_m(velocity: Vec3, axis: Vec3, h: f64, mean_edge_m: f64) -> f64 {
    (-velocity.dot(&axis)).max(0.0) * h + HOLD_TOLERANCE_EDGES * mean_edge_m
}

/// What one held point sums into the tool's reaction.
#[derive(Default)]
struct Reaction {
    force: Vec3,
    torque: Vec3,
    normal_n: f64,
    points: u32,
}

impl Reaction {
    /// A force `on_tool` at `at` that is not a held point's push (its friction).
    fn rub(&mut self, tool: &PlacedTool, at: Vec3, on_tool: Vec3) {
        self.force += on_tool;
        self.torque += (at - tool.tip).cross(&on_tool);
    }

    fn add(&mut self, tool: &PlacedTool, at: Vec3, on_tool: Vec3, normal_n: f64) {
        self.rub(tool, at, on_tool);
        self.normal_n += normal_n;
        self.points += 1;
    }
}

impl HashState for Holder {
    /// The triangle each tool held and the push it was held with (the implicit
    /// integrator's held points are the step's own).
    fn hash_state(&self, h: &mut StateHasher) {
        self.held_triangle.hash_state(h);
        self.tools.iter().for_each(|t| t.force_n.hash_state(h));
    }
}

impl Holder {
    /// For `tools` tools on a mesh of `triangles` triangles (the candidates' room: each
    /// triangle listed once per corner before duplicates go, so a step never allocates).
    pub fn new(tools: usize, friction: Option<Friction>, triangles: usize) -> Self {
        Self {
            tools: vec![HoldState::default(); tools],
            held_triangle: vec![None; tools],
            friction,
            candidates: Vec::with_capacity(3 * triangles),
            rubs: Vec::with_capacity(triangles),
        }
    }

    /// The skin's friction against the tools, if it has any.
    pub fn friction(&self) -> Option<Friction> {
        self.friction
    }

    /// Forgets last step's holds.
    pub fn begin_step(&mut self) {
        self.tools.iter_mut().for_each(|t| *t = HoldState::default());
        self.rubs.clear();
    }

    /// After the implicit solve, the Coulomb cone on the points that stuck to their
    /// tools within it ([`Rub`]): the force their springs across the push took, beyond
    /// the static coefficient times the normal force, is brought down to the dynamic one
    /// (a velocity correction over the step h). Adds the friction to the tools' feedback.
    /// `spring_damping_s` is the solve's β (its springs act over h + β).
    pub fn rub_after_solve(&mut self, nodes: &mut Nodes, drag: Drag, h: f64, spring_damping_s: f64, feedback: &mut [ToolFeedback]) {
        let Some((mu_static, mu_dynamic)) = self.friction else { return };
        for rub in &self.rubs {
            let Some((stiffness, tangents)) = rub.stuck else { continue };
            // What the springs gave the point over the step: each node's spring pulled it
            // towards the tool's motion by its stiffness times its lag.
            let mut force = Vec3::zeros();
            for k in (0..3).filter(|&k| rub.w[k] != 0.0) {
                let lag = rub.tool_velocity - nodes.v[rub.ids[k] as usize];
                for t in tangents {
                    force += t * (stiffness * rub.w[k] * (h + spring_damping_s) * lag.dot(&t));
                }
            }
            let size = force.norm();
            if size > mu_static * rub.normal_n {
                let sliding = force * (mu_dynamic * rub.normal_n / size);
                // The nodes' velocity changes against their own resistance, scaled so
                // that the point loses at most the tool's motion across the push: the
                // springs that took the force are the rest of the skin's too, and
                // released against the nodes' mass alone they would fling the point.
                let mut dv = [Vec3::zeros(); 3];
                let mut point_dv = Vec3::zeros();
                for k in (0..3).filter(|&k| rub.w[k] != 0.0) {
                    let i = rub.ids[k] as usize;
                    let Some(yields) = drag.resistance(nodes, i, h).try_inverse() else { continue };
                    dv[k] = (yields * (sliding - force) * (h * rub.w[k])).component_mul(&nodes.free[i]);
                    point_dv += dv[k] * rub.w[k];
                }
                let carried = across(&rub.tool_velocity, &rub.push).norm();
                let scale = if point_dv.norm() > carried { carried / point_dv.norm() } else { 1.0 };
                for k in (0..3).filter(|&k| rub.w[k] != 0.0) {
                    let i = rub.ids[k] as usize;
                    nodes.v[i] += dv[k] * scale;
                    nodes.x[i] += dv[k] * (scale * h);
                }
                force = sliding;
            }
            feedback[rub.tool].force_n -= force * rub.weight;
            feedback[rub.tool].torque_nm -= rub.lever.cross(&force) * rub.weight;
        }
    }

    /// Tool `index` does not hold this step (away, or through the skin).
    pub fn release(&mut self, index: usize) {
        self.held_triangle[index] = None;
    }

    /// Body `index` comes back where body `twin` holds the skin (a forceps' second jaw
    /// reopening out of the closed plate): it holds as the twin does, its tip on the
    /// twin's triangle. Taken as new, the skin that the closed plate holds over the
    /// jaw's tip was a triangle crossed above it, so the jaw counted as through the skin
    /// and was held no more (reopened 6 mm deep in the implicit skin, it slid under the
    /// skin beside the dent: the skin 4.6 mm past its tip).
    pub fn take_twin(&mut self, index: usize, twin: usize) {
        self.held_triangle[index] = self.held_triangle[twin];
    }

    /// The live triangle the tool's axis crosses nearest its tip, anywhere along the
    /// tool: whether the tool is through the skin.
    pub fn first_crossing(&mut self, tool: &PlacedTool, nodes: &Nodes, topo: &Topology, grid: &PointGrid, max_edge_m: f64) -> Option<Crossing> {
        let (min, max) = tool.bounds(max_edge_m);
        triangles_near(grid, topo, &min, &max, &mut self.candidates);
        nearest_crossing(tool, &self.candidates, &nodes.x, topo)
    }

    /// Holds the skin at tool `index`'s tip face for one substep; adds the reaction
    /// (times `weight`, the substep's share of the step) to `feedback`. Returns false
    /// when the tool turns out to be through the skin (it got under it from the side).
    pub fn hold(&mut self, index: usize, tool: HeldTool, view: HoldView, feedback: &mut ToolFeedback, weight: f64) -> bool {
        let HoldView { nodes, topo, grid, max_edge_m, margin_m, h, drag, mut implicit } = view;
        let HeldTool { placed: tool, velocity: tool_velocity, reach_m } = tool;
        let push = -tool.axis;
        let friction = self.friction;
        let first_rub = self.rubs.len();
        let mut reaction = Reaction::default();

        // 1. Nodes under the tip face, as far above it as the tip can have come since the
        // last substep (a tool thrust fast has swept the skin it passed).
        // Under the implicit integrator a round tip resting on the skin also holds the
        // nodes just off its ball that would reach it within the step (a speculative
        // contact): only while a held triangle goes on, the resting ball it is for (at
        // first touch the triangle's point is found as before).
        let speculative = implicit.is_some() && tool.tip_shape == TipShape::Round && self.held_triangle[index].is_some();
        let held_corners = self.held_triangle[index].filter(|_| speculative).map_or([u32::MAX; 3], |t| {
            let ids = topo.tris[t as usize];
            let corners = ids.map(|v| nodes.x[v as usize]);
            let middle = (corners[0] + corners[1] + corners[2]) / 3.0;
            let spread = corners.iter().map(|c| (c - middle).norm_squared()).fold(0.0, f64::max);
            let sagitta = tool.radius_m - (tool.radius_m * tool.radius_m - spread).max(0.0).sqrt();
            if sagitta < 0.5 * reach_m { [u32::MAX; 3] } else { ids }
        });
        let reach = tool.radius_m + margin_m + if speculative { reach_m } else { 0.0 };
        let along = tool.radius_m.max(reach_m.min(0.5 * tool.length_m));
        let (min, max) = (tool.tip - Vec3::repeat(reach), tool.tip + Vec3::repeat(reach));
        let (lo, hi) = (min.inf(&(min + tool.axis * along)), max.sup(&(max + tool.axis * along)));
        grid.query_box(&lo, &hi, |id| {
            let i = id as usize;
            if nodes.inv_mass[i] == 0.0 {
                return;
            }
            let Some((depth, push)) = face_exit(tool, &nodes.x[i], reach_m).or_else(|| speculative.then(|| round_tip_gap(tool, &nodes.x[i], reach_m)).flatten().map(|(gap, push)| (-gap, push))) else { return };
            if depth < 0.0 {
                // Off the ball (a speculative contact, one-sided): held only when the
                // skin's forces would carry it further than its gap into the ball. A
                // corner of the triangle the tip rests on only when the ball is wide
                // against the triangle: corners drawn onto the ball put the triangle's
                // middle inside it by the ball's sagitta over the triangle, against the
                // hold of the triangle's point on the ball (stiff springs at odds: the
                // 2 mm ball on the 2.5 mm mesh flung the skin through itself).
                if held_corners.contains(&id) {
                    return;
                }
                let coming = nodes.v[i] + nodes.f[i] * (h * nodes.inv_mass[i]);
                if -(coming - tool_velocity).dot(&push) * h <= -depth {
                    return;
                }
            }
            let at = HeldPoint { ids: [id; 3], w: [1.0, 0.0, 0.0], push, depth };
            hold_point(nodes, &drag, h, implicit.as_mut(), &mut self.rubs, friction, (tool, index, tool_velocity, weight), at, &mut reaction);
        });

        // 2. The triangle the axis crosses nearest the tip, up to where the tip was a
        // substep ago (the sweep of the tip along its axis: skin it passed is held, not
        // left behind). The search starts an edge below the tip: a held triangle that the
        // skin's own motion carried just under it stays held (a contact resting, not
        // pressed), instead of being lost.
        let top = tool.tip + tool.axis * (tool.radius_m + 2.0 * max_edge_m + reach_m).min(tool.length_m);
        let bottom = tool.tip - tool.axis * max_edge_m;
        let near_tip = PlacedTool { tip: bottom, top, length_m: (top - bottom).norm(), ..*tool };
        let (min, max) = near_tip.bounds(max_edge_m);
        triangles_near(grid, topo, &min, &max, &mut self.candidates);
        if let Some(last) = self.held_triangle[index] {
            for v in topo.tris[last as usize] {
                self.candidates.extend(topo.node_tris[v as usize].iter().copied());
            }
            self.candidates.sort_unstable();
            self.candidates.dedup();
        }
        let mut held = None;
        let mut through = false;
        // Pinned at the tip, the held point may sit on an edge or a corner, where the
        // crossing test of every triangle around it can miss by a rounding error: a
        // contact that goes on then keeps its triangle's point nearest the tip.
        let crossing = nearest_crossing(&near_tip, &self.candidates, &nodes.x, topo).or_else(|| {
            let last = self.held_triangle[index]?;
            let [a, b, c] = topo.tris[last as usize].map(|v| nodes.x[v as usize]);
            let point = closest_point_on_triangle(&tool.tip, &a, &b, &c);
            (topo.tri_alive[last as usize] && (point - tool.tip).norm() <= max_edge_m).then_some(Crossing { point, blade_t: 0.0, triangle: last })
        });
        if let Some(hit) = crossing {
            let ids = topo.tris[hit.triangle as usize];
            let [a, b, c] = ids.map(|v| nodes.x[v as usize]);
            let normal = (b - a).cross(&(c - a));
            let facing = normal.norm() > 0.0 && normal.normalize().dot(&tool.axis).abs() >= MIN_HOLD_COSINE;
            let depth = (hit.point - tool.tip).dot(&tool.axis);
            let w = barycentric_closest(&hit.point, &a, &b, &c);
            // The point's inverse mass, as its nodes share it by their weights.
            let point_inv_mass: f64 = (0..3).map(|k| w[k] * w[k] * nodes.inv_mass[ids[k] as usize]).sum();
            let goes_on = self.held_triangle[index].is_some();
            through = !goes_on && depth > reach_m;
            if depth < 0.0 && goes_on {
                held = Some(hit.triangle);
                // Just off the face, the point can close the gap within the substep: the
                // explicit integrator stops its approach beyond the gap (a speculative
                // contact). Without it, a point carrying the whole load (a round tip
                // rests on one triangle) that was a micrometre off the face at one
                // substep was thrown millimetres into the tool by the skin's tension
                // before the next caught it. Round tips only: under a flat face the
                // triangle's held corner carries the load, and pushing the point (its
                // other corners hanging below the face) pushed that corner off the face
                // and its friction with it (the friction drag test: 0.47 → 0.37 mm).
                // Skipping the point wherever a corner is held keeps the flat face but
                // undoes the ball on a node (whose apex node is such a corner: skin
                // 2.65 mm above its tip), so the rule goes by the tip's shape. The
                // implicit solve has its contacts in its system, and none off the face.
                if implicit.is_none() && point_inv_mass > 0.0 && -depth <= reach_m && tool.tip_shape == TipShape::Round {
                    let at = HeldPoint { ids, w: [w[0], w[1], w[2]], push, depth };
                    hold_point(nodes, &drag, h, None, &mut self.rubs, friction, (tool, index, tool_velocity, weight), at, &mut reaction);
                }
            } else if depth >= 0.0 && (goes_on || (facing && !through)) && point_inv_mass > 0.0 {
                held = Some(hit.triangle);
                let at = HeldPoint { ids, w: [w[0], w[1], w[2]], push, depth };
                hold_point(nodes, &drag, h, implicit.as_mut(), &mut self.rubs, friction, (tool, index, tool_velocity, weight), at, &mut reaction);
            }
        }
        for rub in &self.rubs[first_rub..] {
            for k in (0..3).filter(|&k| rub.w[k] != 0.0) {
                let i = rub.ids[k] as usize;
                nodes.f[i] += (rub.slide * rub.w[k]).component_mul(&nodes.free[i]);
            }
        }
        self.finish(index, held, reaction, feedback, weight, through)
    }

    /// Records the triangle tool `index` held this substep (if any) and adds its reaction to `feedback`;
    /// returns whether the tool may go on holding (it is not through the skin).
    fn finish(&mut self, index: usize, held: Option<u32>, reaction: Reaction, feedback: &mut ToolFeedback, weight: f64, through: bool) -> bool {
        self.held_triangle[index] = held;
        self.tools[index].force_n += reaction.normal_n * weight;
        feedback.force_n += reaction.force * weight;
        feedback.torque_nm += reaction.torque * weight;
        feedback.contacts = feedback.contacts.max(reaction.points);
        !through
    }

}

/// A point held at a tool's face: its nodes and their weights (a node alone: itself
/// with weight 1), the way out and how far it lies inside.
#[derive(Debug, Clone, Copy)]
struct HeldPoint {
    ids: [u32; 3],
    w: [f64; 3],
    push: Vec3,
    depth: f64,
}

/// Puts a held point on the tool's face (its nodes sharing the move by their weights
/// over their masses) and gives it the force that stops its approach, with friction
/// (explicit integrator); or removes its approach and enters it in the system as a
/// stiff contact, its friction left to after the solve (implicit). Adds the reaction.
/// `tool` is (the tool, its index, its velocity, the substep's share of the step).
#[allow(clippy::too_many_arguments)]
fn hold_point(
    nodes: &mut Nodes,
    drag: &Drag,
    h: f64,
    implicit: Option<&mut ImplicitHold>,
    rubs: &mut Vec<Rub>,
    friction: Option<Friction>,
    (tool, index, tool_velocity, weight): (&PlacedTool, usize, Vec3, f64),
    at: HeldPoint,
    reaction: &mut Reaction,
) {
    let HeldPoint { ids, w, push, depth } = at;
    let point_inv_mass: f64 = (0..3).map(|k| w[k] * w[k] * nodes.inv_mass[ids[k] as usize]).sum();
    if point_inv_mass <= 0.0 {
        return;
    }
    let share = |k: usize| w[k] * nodes.inv_mass[ids[k] as usize] / point_inv_mass;
    // A point off the face (depth < 0: a gap) is not moved; its approach may close the gap.
    let gap = (-depth).max(0.0);
    for k in 0..3 {
        let i = ids[k] as usize;
        nodes.x[i] += (push * (depth.max(0.0) * share(k))).component_mul(&nodes.free[i]);
    }
    // Where the point now lies on the face (for a node: the node; for the triangle the
    // axis crosses: the tip).
    let point: Vec3 = (0..3).map(|k| nodes.x[ids[k] as usize] * w[k]).sum();
    if let Some(implicit) = implicit {
        let point_velocity: Vec3 = (0..3).map(|k| nodes.v[ids[k] as usize] * w[k]).sum();
        let (dv, _) = contact_velocity_change(point_velocity, tool_velocity, push, gap / h);
        // A point off the face is carried to where the face will be at the step's end,
        // but no further than a point on it (held still along the push: the tool's own
        // travel meets it), and never after a face that lifts away.
        let drive = (tool_velocity.dot(&push).max(0.0) - gap / h).min(0.0);
        for k in (0..3).filter(|&k| w[k] != 0.0) {
            let i = ids[k] as usize;
            nodes.v[i] += (dv * share(k)).component_mul(&nodes.free[i]);
            implicit.contacts.push(Contact { node: ids[k], normal: push, stiffness: implicit.stiffness_n_per_m * w[k], drive_m_per_s: drive });
        }
        // The force the point's nodes press it against the face with, as a constraint
        // on the point takes it (the force F that stops the point, each node taking
        // w_k·F: F = Σ w_k f_k / m_k ÷ Σ w_k² / m_k), less what nodes held this substep
        // already gave to the tools (as the explicit integrator's constraint forces,
        // added to the nodes' forces, do): a triangle whose corners are held carries
        // only what they leave.
        let taken = |i: u32| rubs.iter().filter(|r| r.w[0] == 1.0 && r.ids[0] == i).map(|r| r.push * r.normal_n).sum::<Vec3>();
        let pressing: Vec3 = (0..3)
            .filter(|&k| w[k] != 0.0)
            .map(|k| (nodes.f[ids[k] as usize] + taken(ids[k])) * (w[k] * nodes.inv_mass[ids[k] as usize]))
            .sum::<Vec3>()
            / point_inv_mass;
        let normal_n = (-pressing.dot(&push)).max(0.0);
        reaction.add(tool, point, -push * normal_n, normal_n);
        let mut stuck = None;
        let mut slide = Vec3::zeros();
        if normal_n > 0.0
            && let Some((resists, coming)) = point_dynamics(nodes, drag, h, ids, w, Vec3::zeros())
            && let Some((force, sticks)) = coulomb(coming - tool_velocity, push, &resists, h, normal_n, friction)
        {
            if sticks {
                let tangents = tangents_across(push);
                for t in tangents {
                    for k in (0..3).filter(|&k| w[k] != 0.0) {
                        implicit.contacts.push(Contact { node: ids[k], normal: t, stiffness: implicit.stiffness_n_per_m * w[k], drive_m_per_s: tool_velocity.dot(&t) });
                    }
                }
                stuck = Some((implicit.stiffness_n_per_m, tangents));
            } else {
                slide = force;
                reaction.rub(tool, point, -force);
            }
        }
        rubs.push(Rub { tool: index, ids, w, push, lever: point - tool.tip, tool_velocity, normal_n, weight, stuck, slide });
        return;
    }
    // The point's velocity at the end of the substep were it free, before the drag (its
    // approach is stopped against its mass alone: the position constraint does the rest).
    let undamped: Vec3 = (0..3).map(|k| (nodes.v[ids[k] as usize] + nodes.f[ids[k] as usize] * (h * nodes.inv_mass[ids[k] as usize])) * w[k]).sum();
    let (stop, normal_n) = contact_force(undamped, tool_velocity, push, gap / h, 1.0 / point_inv_mass, h);
    let Some((resists, coming)) = point_dynamics(nodes, drag, h, ids, w, stop) else { return };
    let on_point = stop + friction_force(coming - tool_velocity, push, &resists, h, normal_n, friction);
    // A force F at the point is w_k·F on its nodes; the tool feels what they take.
    let mut taken = Vec3::zeros();
    for k in (0..3).filter(|&k| w[k] != 0.0) {
        let i = ids[k] as usize;
        let on_node = (on_point * w[k]).component_mul(&nodes.free[i]);
        nodes.f[i] += on_node;
        taken += on_node;
    }
    reaction.add(tool, point, -taken, normal_n);
}

/// The velocity change that removes a held point's approach along `push` faster than
/// the tool (an inelastic contact), beyond `allowed_approach` (a gap's closing speed
/// over the substep), and the approach speed it removes.
fn contact_velocity_change(velocity: Vec3, tool_velocity: Vec3, push: Vec3, allowed_approach: f64) -> (Vec3, f64) {
    let approach = -(velocity - tool_velocity).dot(&push) - allowed_approach;
    if approach <= 0.0 {
        // Leaving the face, resting on it, or closing no more than its gap: untouched.
        return (Vec3::zeros(), 0.0);
    }
    (push * approach, approach)
}

/// A held point of nodes `ids` with weights `w`: its resistance R to a force over the
/// substep h (its nodes' mass and drag, shared by their weights: R⁻¹ = Σ w_k² R_k⁻¹)
/// and its velocity at the substep's end with the force `on_point` on it and nothing
/// else holding it. None when none of its nodes can move.
fn point_dynamics(nodes: &Nodes, drag: &Drag, h: f64, ids: [u32; 3], w: [f64; 3], on_point: Vec3) -> Option<(Matrix3<f64>, Vec3)> {
    let mut yields = Matrix3::zeros();
    let mut coming = Vec3::zeros();
    for k in 0..3 {
        let i = ids[k] as usize;
        if nodes.inv_mass[i] == 0.0 || w[k] == 0.0 {
            continue;
        }
        let node_yields = drag.resistance(nodes, i, h).try_inverse()?;
        yields += node_yields * (w[k] * w[k]);
        coming += node_yields * (nodes.v[i] * nodes.mass[i] + (nodes.f[i] + on_point * w[k]) * h) * w[k];
    }
    Some((yields.try_inverse()?, coming))
}

/// The force on a held point of `mass` over the substep h that stops its approach to
/// the tool face (an inelastic contact), and its size, the normal force, N. `coming`
/// is the velocity the point would have at the substep's end were it free.
fn contact_force(coming: Vec3, tool_velocity: Vec3, push: Vec3, allowed_approach: f64, mass: f64, h: f64) -> (Vec3, f64) {
    let (dv, approach) = contact_velocity_change(coming, tool_velocity, push, allowed_approach);
    (dv * (mass / h), approach * mass / h)
}

/// Coulomb friction on a point pressed against the tool face with `normal_n`, moving
/// relative to it at `relative` at the substep's end were nothing to hold it
/// sideways: the point sticks (the force that stops its slip) while that force stays
/// within the static coefficient times the normal force, else it slides against the
/// dynamic coefficient times it. `resists` is the point's resistance R to a force over
/// the substep (a force F changes its end velocity by h·R⁻¹·F: its mass, and the drag
/// the integrator takes implicitly), so stopping the slip takes R·slip/h.
fn friction_force(relative: Vec3, push: Vec3, resists: &Matrix3<f64>, h: f64, normal_n: f64, friction: Option<Friction>) -> Vec3 {
    coulomb(relative, push, resists, h, normal_n, friction).map_or_else(Vec3::zeros, |(force, _)| force)
}

/// [`friction_force`], and whether the point sticks; None without friction or normal force.
fn coulomb(relative: Vec3, push: Vec3, resists: &Matrix3<f64>, h: f64, normal_n: f64, friction: Option<Friction>) -> Option<(Vec3, bool)> {
    let (mu_static, mu_dynamic) = friction?;
    if normal_n <= 0.0 {
        return None;
    }
    let slip = across(&relative, &push);
    let stick = -(resists * slip) / h;
    let sideways = across(&stick, &push).norm();
    Some(if sideways <= mu_static * normal_n { (stick, true) } else { (stick * (mu_dynamic * normal_n / sideways), false) })
}

/// Two unit vectors across `n` (a unit vector), at right angles to each other (the two
/// springs of a stuck point together act as `I − n nᵀ`, whichever pair this is).
pub(crate) fn tangents_across(n: Vec3) -> [Vec3; 2] {
    let first = crate::math::any_perpendicular(&n);
    [first, n.cross(&first)]
}

/// How deep a node inside the tool lies under the tip face and the way out (the face's
/// normal: down the axis for a flat tip, the sphere's for a round one), when the face
/// (not the side) is its nearest way out and it lies within `reach_m` of it (skin the
/// face can have pressed since the last substep); None otherwise.
pub(crate) fn face_exit(tool: &PlacedTool, x: &Vec3, reach_m: f64) -> Option<(f64, Vec3)> {
    let reach_m = reach_m.min(0.5 * tool.length_m);
    if tool.tip_shape == TipShape::Round {
        // Below the hemisphere's centre its surface is the nearest way out; above it,
        // the rod's side (its penalty, as for a flat tip).
        return tool.round_tip_exit(x).filter(|&(depth, _)| depth <= reach_m);
    }
    let along = (x - tool.tip).dot(&tool.axis);
    if along < 0.0 || along > reach_m {
        return None;
    }
    let (through_side, _) = tool.section_exit(&(x - tool.tip - tool.axis * along))?;
    (along < through_side).then_some((along, -tool.axis))
}

/// How far a point just outside a round tip's ball lies off it and the way out (the
/// ball's normal), when within `reach_m` of its lower half (where [`face_exit`] would
/// hold it once inside); None otherwise.
fn round_tip_gap(tool: &PlacedTool, x: &Vec3, reach_m: f64) -> Option<(f64, Vec3)> {
    let from_centre = x - (tool.tip + tool.axis * tool.radius_m);
    let d = from_centre.norm();
    let gap = d - tool.radius_m;
    (gap >= 0.0 && gap <= reach_m && from_centre.dot(&tool.axis) <= 0.0).then(|| (gap, from_centre / d))
}

#[cfg(test)]
mod tests {
    use super::*;

    use crate::msm::contact::tests::tool;

    fn face_depth_of(t: &PlacedTool, x: &Vec3, reach_m: f64) -> Option<f64> {
        face_exit(t, x, reach_m).map(|(depth, out)| {
            assert_eq!(out, -t.axis, "a flat face pushes down the axis");
            depth
        })
    }

    #[test]
    fn the_face_holds_nodes_nearer_it_than_the_side() {
        let t = tool();
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 2e-4, 3e-4), 1.0), Some(3e-4));
        // Nearer the side: the side's penalty pushes it, not the face.
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 9e-4, 3e-4), 1.0), None);
        // Below the tip, outside the radius, or up the shaft: not held.
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 0.0, -1e-6), 1.0), None);
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 1.1e-3, 1e-5), 1.0), None);
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 0.0, 0.06), 1.0), None);
        // Deeper than the tip can have pressed since the last substep: got in from the side.
        assert_eq!(face_depth_of(&t, &Vec3::new(0.0, 2e-4, 3e-4), 1e-4), None);
    }

    #[test]
    fn a_round_tip_holds_nodes_inside_its_hemisphere_out_along_its_normal() {
        // Radius 1 mm: the hemisphere's centre 1 mm above the apex at the origin.
        let t = PlacedTool { tip_shape: TipShape::Round, ..tool() };
        // Under the apex: out down the axis by its depth.
        let (depth, out) = face_exit(&t, &Vec3::new(0.0, 0.0, 2e-4), 1.0).unwrap();
        assert!((depth - 2e-4).abs() < 1e-15 && (out + Vec3::z()).norm() < 1e-12, "{depth} {out:?}");
        // Off the axis, inside the sphere: along the normal through it.
        let x = Vec3::new(6e-4, 0.0, 3e-4);
        let (depth, out) = face_exit(&t, &x, 1.0).unwrap();
        let from_centre = x - Vec3::new(0.0, 0.0, 1e-3);
        assert!((depth - (1e-3 - from_centre.norm())).abs() < 1e-15 && (out - from_centre.normalize()).norm() < 1e-12, "{depth} {out:?}");
        // Where a flat face would hold it, the rounded edge is not there: not inside.
        assert!(face_exit(&t, &Vec3::new(9e-4, 0.0, 1e-4), 1.0).is_none());
        assert!(face_exit(&PlacedTool { tip_shape: TipShape::Flat, ..t }, &Vec3::new(8e-4, 0.0, 1e-4), 1.0).is_some());
        // Above the centre (the side's) or deeper than the reach: not held.
        assert!(face_exit(&t, &Vec3::new(0.0, 5e-4, 1.1e-3), 1.0).is_none());
        assert!(face_exit(&t, &Vec3::new(0.0, 0.0, 2e-4), 1e-4).is_none());
    }

    #[test]
    fn only_the_approach_faster_than_the_tool_is_removed() {
        let (push, mass, h) = (-Vec3::z(), 1e-3, 1e-4);
        let tool_velocity = Vec3::new(0.0, 0.0, -0.01);
        let v = Vec3::new(0.3, 0.0, 0.5);
        let (f, normal_n) = contact_force(v, tool_velocity, push, 0.0, mass, h);
        assert!((v + f * (h / mass) - Vec3::new(0.3, 0.0, -0.01)).norm() < 1e-12, "moves with the tool, keeps its slide: {:?}", v + f * (h / mass));
        assert!((normal_n - 0.51 * mass / h).abs() < 1e-9, "the force that stops it within the substep: {normal_n}");
        let away = Vec3::new(0.0, 0.0, -0.5);
        assert_eq!(contact_force(away, tool_velocity, push, 0.0, mass, h), (Vec3::zeros(), 0.0), "moving away faster: untouched");
        // A gap of 0.2 µm may close over the substep (2 mm/s of approach): only the rest is stopped.
        let (f, _) = contact_force(v, tool_velocity, push, 2e-7 / h, mass, h);
        assert!((v + f * (h / mass) - Vec3::new(0.3, 0.0, -0.008)).norm() < 1e-12, "{:?}", v + f * (h / mass));
    }

    #[test]
    fn coulomb_friction_sticks_within_the_static_cone_and_slides_beyond() {
        let (push, h, mass) = (-Vec3::z(), 1e-4, 1e-3);
        let resists = Matrix3::identity() * mass;
        let friction = Some((0.6, 0.4));
        // Pressed with 1 N; sliding at 5 mm/s takes 0.05 N to stop: stuck.
        let slow = Vec3::new(0.005, 0.0, 0.0);
        let f = friction_force(slow, push, &resists, h, 1.0, friction);
        assert!((slow + f * (h / mass)).norm() < 1e-12, "sticks: {:?}", slow + f * (h / mass));
        // At 1 m/s it takes 10 N: it slides, against μ_d·N.
        let fast = Vec3::new(1.0, 0.0, 0.0);
        assert!((friction_force(fast, push, &resists, h, 1.0, friction) - Vec3::new(-0.4, 0.0, 0.0)).norm() < 1e-12);
        // Only the slip across the face counts; not pressed, nothing holds it.
        assert!((friction_force(Vec3::new(0.005, 0.0, 3.0), push, &resists, h, 1.0, friction) - f).norm() < 1e-12);
        assert_eq!(friction_force(slow, push, &resists, h, 0.0, friction), Vec3::zeros());
        assert_eq!(friction_force(slow, push, &resists, h, 1.0, None), Vec3::zeros());
    }

    #[test]
    fn a_point_stuck_by_friction_moves_with_the_tool_against_the_drag_too() {
        // The skin's drag across its plane resists nine times its mass over a substep:
        // sticking takes ten times the force that the mass alone would.
        let (push, h, mass) = (-Vec3::z(), 1e-4, 1e-3);
        let resists = Matrix3::from_diagonal(&Vec3::new(10.0 * mass, 10.0 * mass, 1.1 * mass));
        let relative = Vec3::new(-0.01, 0.0, 0.0);
        let f = friction_force(relative, push, &resists, h, 2.0, Some((0.6, 0.4)));
        assert!((f.x - 10.0 * mass * 0.01 / h).abs() < 1e-12, "{f:?}");
        assert!((relative + resists.try_inverse().unwrap() * f * h).norm() < 1e-12, "moves with the tool");
    }
}
