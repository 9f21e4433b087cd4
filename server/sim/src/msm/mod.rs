//! `msm`: the surface mass-spring skin (paper 000, ALGORITHMS.md part A).
//!
//! Nodes with mass joined by springs along the triangle edges, calibrated from E, t and
//! ρ ([`calibration`]); residual stress as a prestrain of every spring ([`forces`]);
//! cylinder tools ([`contact`]); symplectic Euler with substeps ([`explicit`]) or
//! implicit Euler with CG ([`implicit`]); three-stage cutting ([`cut`]).
//!
//! [`MassSpring::step`] reads as the outline of one physics step: place the tools,
//! then per (sub)step accumulate forces, add contacts, hold the skin at tip faces
//! ([`hold`]) and at the flats of blades through it ([`flat`]), and integrate; contain a
//! blow-up if one is detected; then let cutting tools cut. Nothing in a step without a
//! cut allocates.

mod apply_cut;
mod build;
pub mod calibration;
pub mod contact;
pub mod cut;
pub mod explicit;
pub(crate) mod flat;
pub(crate) mod forces;
pub mod foundation;
pub(crate) mod face_hold;
pub(crate) mod grasp;
pub(crate) mod hold;
pub(crate) mod side_friction;
pub(crate) mod side_hold;
pub mod resistance;
pub(crate) mod implicit;
pub(crate) mod state;

pub use build::{IntegratorChoice, MsmParams, build_from_scene};
pub use cut::{CuttingParams, Incision};
pub use explicit::StabilityBound;
pub use foundation::FoundationParams;

use std::time::Instant;

use calibration::MembraneMaterial;
use contact::{Contact, ContactMode, SideHold, apply_tool_contacts};
use cut::{CutStep, CutView, Cutter};
use implicit::ImplicitSolver;
use state::{Nodes, SpringSet, Topology};

use crate::broad_phase::PointGrid;
use crate::hash::StateHasher;
use crate::math::Vec3;
use crate::surface::{SurfaceSnapshot, SurfaceTriangle, SurfaceVertex, TopologyDelta};
use crate::tissue::{CutFallback, Tissue, TissueCounters};
use crate::tool::{PlacedTool, ToolCommand, ToolFeedback, ToolShape};

#[derive(Debug, Clone)]
enum Integrator {
    SymplecticEuler { substeps: u32 },
    /// Boxed: its scratch (the region's included) is large beside the other variant.
    ImplicitEuler(Box<ImplicitSolver>),
}

/// Time spent in each stage, accumulated while profiling is on (for benchmarks).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct StageTimes {
    pub forces_ns: u64,
    pub contacts_ns: u64,
    pub integrate_ns: u64,
    pub cut_ns: u64,
    pub steps: u64,
}

/// The cutting force's reaction spreads over the skin nodes within this many mean edge
/// lengths of the crossing.
const REACTION_REACH_EDGES: f64 = 3.0;
/// Nodes that share one blade's cutting reaction in a step, at most (room reserved at
/// build, so the 1 kHz path does not allocate).
const MAX_CUT_REACTIONS_PER_TOOL: usize = 64;

/// With the implicit integrator a point held at a tip face is a contact this many times
/// stiffer than the tool's penalty, in the system matrix along the tool's axis: stiff
/// enough that within a step the skin moves off the face by a small fraction of an
/// edge, soft enough for the Jacobi-preconditioned CG.
const HELD_STIFFNESS_OVER_CONTACT: f64 = 100.0;

/// Room for this many contacts per node, sized at load and on cuts so a step does not
/// allocate: a node in a tool's penalty takes one, a held point three (its push and,
/// stuck by friction under the implicit integrator, two across it) per node, and only
/// the few nodes at a tip are held.
const CONTACTS_PER_NODE: usize = 4;

/// How many contacts a step may make: [`CONTACTS_PER_NODE`] per node, the room the
/// contact list is given. A fixed bound, not the list's capacity: a copy of the tissue
/// (a replay's kept state) must make the same contacts as its original, and a clone's
/// vectors keep their lengths, not their capacities.
fn contact_room(nodes: &state::Nodes) -> usize {
    CONTACTS_PER_NODE * nodes.len()
}

/// The cutting force follows the blade's velocity smoothed over this time, s. Taken
/// step by step, the force would switch on and off with the pose's millisecond jitter,
/// and a haptic proxy pulled through the cut would stick and slip at the loop rate (a
/// buzz); smoothed, it holds while the blade moves and fades over this time when it
/// stops.
pub const BLADE_VELOCITY_TIME_CONSTANT_S: f64 = 0.01;

/// How a blade moves through the skin at its crossing `hit` this step: its velocity there
/// (from its pose last step) against the tissue beneath, which holds still. Measured
/// against the skin's own nodes instead, the cut would feed back on itself: the skin the
/// blade drags would change the very motion that decides whether it cuts.
fn blade_motion(blade: &PlacedTool, before: &PlacedTool, hit: &cut::Crossing, nodes: &state::Nodes, topo: &Topology, dt_s: f64) -> resistance::BladeMotion {
    let along = hit.blade_t * blade.length_m;
    let then = before.tip + before.axis * along;
    let [a, b, c] = topo.tris[hit.triangle as usize].map(|v| nodes.x[v as usize]);
    let normal = (b - a).cross(&(c - a));
    let normal = if normal.norm() > 0.0 { normal.normalize() } else { blade.axis };
    resistance::BladeMotion { relative_velocity: (blade.tip + blade.axis * along - then) / dt_s, normal, edge: blade.edge, axis: blade.axis }
}

/// The mass-spring skin.
#[derive(Debug, Clone)]
pub struct MassSpring {
    dt_s: f64,
    material: MembraneMaterial,
    residual_strain: f64,
    mass_damping_per_s: f64,
    spring_damping_s: f64,
    gravity: Option<Vec3>,
    foundation: Option<foundation::Foundation>,
    fracture_toughness_j_per_m2: f64,
    integrator: Integrator,
    pub(crate) nodes: Nodes,
    pub(crate) springs: SpringSet,
    pub(crate) topo: Topology,
    grid: PointGrid,
    /// The scene's tools (what commands and feedback are per).
    scene_tools: Vec<ToolShape>,
    /// The solids the skin meets, each with its own state below: the scene's tools, with
    /// forceps as their two jaws ([`crate::tool::bodies`]).
    tools: Vec<ToolShape>,
    /// The split between tools and bodies where they differ (forceps).
    bodies: Option<crate::tool::bodies::Bodies>,
    /// Per body, the body whose state it takes when it comes back ([`crate::tool::bodies::Bodies::twins`]).
    twins: Vec<Option<usize>>,
    /// What the forceps hold ([`grasp`]); None without forceps.
    grasps: Option<grasp::Grasps>,
    placed: Vec<Option<PlacedTool>>,
    /// Where each tool was last step (the blade's velocity through the skin).
    previous_placed: Vec<Option<PlacedTool>>,
    /// Where each tool is at the current substep: swept from last step's pose to this
    /// step's, so that a tool moving fast pushes the skin ahead instead of jumping past.
    swept: Vec<Option<PlacedTool>>,
    /// Each tool's velocity this step, m/s (zero on the step it appears).
    tool_velocity: Vec<Vec3>,
    /// Tools through the skin: appeared below it, or a blade that punctured it; until
    /// their axis no longer crosses the skin. Others hold the skin at their tip face.
    pierced: Vec<bool>,
    /// Which tools hold the skin at their tip face this step ([`hold`]).
    holding: Vec<bool>,
    /// Which tools hold the skin on the insides of triangles along their side in this
    /// contact pass ([`face_hold`]).
    side_holds: Vec<bool>,
    /// Which tools are blades through the skin with their cut button held this step.
    blade_through: Vec<bool>,
    /// Blades through the skin: where they pass through it (taken at the step's start;
    /// [`flat`]).
    holes: Vec<Option<flat::Hole>>,
    holder: hold::Holder,
    /// Which side of a tool each node beside its shaft came in from ([`side_hold`]).
    side_memory: side_hold::SideMemory,
    /// Triangles near a tool laid along the skin ([`face_hold`]; scratch).
    face_scratch: Vec<u32>,
    /// Each blade's velocity through the skin, smoothed over
    /// [`BLADE_VELOCITY_TIME_CONSTANT_S`] (zero outside a resisted stroke).
    blade_velocity: Vec<Vec3>,
    /// The skin's share of the cutting resistance: forces on nodes, applied next step.
    cut_reactions: Vec<(u32, Vec3)>,
    contacts: Vec<Contact>,
    cutter: Option<Cutter>,
    deltas: Vec<TopologyDelta>,
    topology_version: u64,
    step_index: u64,
    counters: TissueCounters,
    /// The cut updates that fell back to an open hole, and why (a report's list).
    fallbacks: Vec<CutFallback>,
    mean_edge_m: f64,
    max_edge_m: f64,
    max_contact_stiffness: f64,
    stability: StabilityBound,
    spring_scratch: forces::SpringScratch,
    profile: Option<StageTimes>,
    last_cut_min_angle_deg: Option<f64>,
    min_cut_angle_deg: Option<f64>,
}

impl MassSpring {
    /// Advances one step of `time_step_s`; see the module documentation for the stages.
    pub fn step(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        crate::tool::assert_one_per_tool(commands, feedback, &self.scene_tools);
        // Taken out for the step and put back: no allocation.
        match self.bodies.take() {
            None => self.step_bodies(commands, feedback),
            Some(mut bodies) => {
                if let Some(grasps) = self.grasps.as_mut() {
                    grasps.begin_step(commands, &self.scene_tools, &mut bodies, &self.nodes, &self.grid);
                }
                bodies.split(commands, &self.scene_tools, &mut self.tools, self.dt_s);
                self.step_bodies(&bodies.commands, &mut bodies.feedback);
                self.counters.force_clamps += bodies.gather(&self.scene_tools, feedback);
                self.bodies = Some(bodies);
            }
        }
    }

    /// One step with a command and a feedback per body ([`crate::tool::bodies`]).
    fn step_bodies(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        self.place_tools(commands, feedback);

        let finite_check = match &self.integrator {
            Integrator::SymplecticEuler { substeps } => {
                let substeps = *substeps;
                let h = self.dt_s / f64::from(substeps);
                let weight = 1.0 / f64::from(substeps);
                let mut check = 0.0;
                for k in 1..=substeps {
                    self.sweep_tools(f64::from(k) / f64::from(substeps));
                    self.timed(|s| s.accumulate_forces(), |t, ns| t.forces_ns += ns);
                    self.timed(|s| s.add_contacts(commands, feedback, weight), |t, ns| t.contacts_ns += ns);
                    self.timed(|s| s.hold_skin(feedback, weight), |t, ns| t.contacts_ns += ns);
                    self.timed(|s| s.push_with_flats(feedback, weight), |t, ns| t.contacts_ns += ns);
                    self.timed(|s| s.grasp_skin(feedback, weight, f64::from(k) / f64::from(substeps)), |t, ns| t.contacts_ns += ns);
                    check = self.timed(
                        |s| explicit::substep(&mut s.nodes, h, s.mass_damping_per_s, s.foundation.as_ref()),
                        |t, ns| t.integrate_ns += ns,
                    );
                }
                check
            }
            Integrator::ImplicitEuler(_) => {
                self.sweep_tools(1.0);
                self.timed(|s| s.accumulate_forces(), |t, ns| t.forces_ns += ns);
                self.timed(|s| s.add_contacts(commands, feedback, 1.0), |t, ns| t.contacts_ns += ns);
                self.timed(|s| s.hold_skin(feedback, 1.0), |t, ns| t.contacts_ns += ns);
                self.timed(|s| s.push_with_flats(feedback, 1.0), |t, ns| t.contacts_ns += ns);
                self.timed(|s| s.grasp_skin(feedback, 1.0, 1.0), |t, ns| t.contacts_ns += ns);
                let check = self.timed(|s| s.implicit_step(), |t, ns| t.integrate_ns += ns);
                let drag = hold::Drag { mass_damping_per_s: self.mass_damping_per_s, foundation: self.foundation.as_ref() };
                self.holder.rub_after_solve(&mut self.nodes, drag, self.dt_s, self.spring_damping_s, feedback);
                if let Some(grasps) = self.grasps.as_mut() {
                    grasps.after_solve(&self.nodes, self.holder.friction().map(side_friction::stick_friction), &self.placed, feedback);
                }
                check
            }
        };
        if !finite_check.is_finite() {
            self.contain_blowup(feedback);
        }
        self.timed(|s| explicit::refresh_grid(&s.nodes, &mut s.grid), |t, ns| t.integrate_ns += ns);
        self.release_pierced();
        if self.cutter.is_some() {
            self.timed(|s| s.cut(commands, feedback), |t, ns| t.cut_ns += ns);
        }
        self.finish_feedback(feedback);
        self.previous_placed.copy_from_slice(&self.placed);
        self.step_index += 1;
        if let Some(p) = self.profile.as_mut() {
            p.steps += 1;
        }
    }

    /// Runs `stage`, adding its duration to the profile when profiling is on.
    fn timed<R>(&mut self, stage: impl FnOnce(&mut Self) -> R, record: impl FnOnce(&mut StageTimes, u64)) -> R {
        if self.profile.is_none() {
            return stage(self);
        }
        let start = Instant::now();
        let out = stage(self);
        let ns = start.elapsed().as_nanos() as u64;
        if let Some(p) = self.profile.as_mut() {
            record(p, ns);
        }
        out
    }

    fn place_tools(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        self.holder.begin_step();
        for (i, (command, fb)) in commands.iter().zip(feedback.iter_mut()).enumerate() {
            *fb = ToolFeedback::default();
            self.placed[i] = if !command.active {
                None
            } else if command.pose.is_finite() {
                Some(PlacedTool::new(&self.tools[i], &command.pose))
            } else {
                self.counters.rejected_poses += 1;
                None
            };
            self.tool_velocity[i] = match (self.placed[i], self.previous_placed[i]) {
                (Some(now), Some(before)) => (now.tip - before.tip) / self.dt_s,
                _ => Vec3::zeros(),
            };
            // A forceps' jaw that comes back (reopening) is as its twin is: through the
            // skin if the twin is, else holding where the twin holds.
            let back_as = match (self.placed[i], self.previous_placed[i]) {
                (Some(_), None) => self.twins[i].filter(|&t| self.placed[t].is_some()),
                _ => None,
            };
            if let Some(twin) = back_as {
                self.holder.take_twin(i, twin);
            }
            self.pierced[i] = match (self.placed[i], self.previous_placed[i]) {
                (None, _) => false,
                (Some(_), None) if let Some(twin) = back_as => self.pierced[twin],
                // A tool that appears below the skin is through it; the skin is not
                // dragged to its tip.
                (Some(tool), None) => self.holder.first_crossing(&tool, &self.nodes, &self.topo, &self.grid, self.max_edge_m).is_some(),
                (Some(_), Some(_)) => self.pierced[i],
            };
            // A blade cutting by the paper's rule (no fracture toughness) passes freely.
            let paper_blade = self.cuts_by_crossing(i, command);
            self.holding[i] = self.placed[i].is_some() && !self.pierced[i] && !paper_blade;
            self.blade_through[i] = !self.holding[i] && self.tools[i].can_cut && command.cut;
            self.holes[i] = self.hole(i, command);
        }
    }

    /// Where blade `i`, through the skin, passes through it: the hole it held last step,
    /// while the flat still holds it; else the skin's material point its axis crossed at last
    /// step's pose, on the mesh as the last cut left it. None for a tool that is not a
    /// blade or not through the skin, or one cutting by the paper's rule (it cuts
    /// whatever it crosses).
    fn hole(&mut self, i: usize, command: &ToolCommand) -> Option<flat::Hole> {
        if !self.pierced[i] || !self.tools[i].can_cut || self.cuts_by_crossing(i, command) {
            return None;
        }
        self.placed[i]?;
        let before = self.previous_placed[i]?;
        if let Some(kept) = self.holes[i] {
            return Some(kept);
        }
        let crossing = self.holder.first_crossing(&before, &self.nodes, &self.topo, &self.grid, self.max_edge_m)?;
        Some(flat::Hole::at(&crossing, &self.nodes, &self.topo))
    }

    /// Whether tool `i` cuts wherever its axis crosses the skin (the paper's rule, for a
    /// material without fracture toughness), so nothing holds it.
    fn cuts_by_crossing(&self, i: usize, command: &ToolCommand) -> bool {
        self.tools[i].can_cut && command.cut && self.fracture_toughness_j_per_m2 <= 0.0
    }

    /// Places every tool at fraction `s` of its motion this step. A blade cutting its
    /// way through the skin is not swept: it passes by the paper's rule at its pose.
    fn sweep_tools(&mut self, s: f64) {
        for (((swept, now), before), &blade_through) in self.swept.iter_mut().zip(&self.placed).zip(&self.previous_placed).zip(&self.blade_through) {
            *swept = match (now, before) {
                (Some(now), Some(before)) if s < 1.0 && !blade_through => {
                    let tip = before.tip + (now.tip - before.tip) * s;
                    let top = before.top + (now.top - before.top) * s;
                    let axis = (top - tip).try_normalize(0.0).unwrap_or(now.axis);
                    Some(now.moved(tip, axis))
                }
                _ => *now,
            };
        }
    }

    /// Holds the skin at the tip face of every tool that holds this step.
    fn hold_skin(&mut self, feedback: &mut [ToolFeedback], weight: f64) {
        let h = self.substep_s();
        let implicit = matches!(self.integrator, Integrator::ImplicitEuler(_));
        for i in 0..self.tools.len() {
            let Some(tool) = self.swept[i].filter(|_| self.holding[i]) else {
                self.holder.release(i);
                continue;
            };
            let view = hold::HoldView {
                nodes: &mut self.nodes,
                topo: &self.topo,
                grid: &self.grid,
                max_edge_m: self.max_edge_m,
                margin_m: 0.5 * self.grid.cell_size_m(),
                h,
                drag: hold::Drag { mass_damping_per_s: self.mass_damping_per_s, foundation: self.foundation.as_ref() },
                implicit: implicit.then_some(hold::ImplicitHold {
                    contacts: &mut self.contacts,
                    stiffness_n_per_m: HELD_STIFFNESS_OVER_CONTACT * self.tools[i].contact_stiffness_n_per_m,
                }),
            };
            let reach_m = hold::hold_reach_m(self.tool_velocity[i], tool.axis, h, self.mean_edge_m);
            let held_tool = hold::HeldTool { placed: &tool, velocity: self.tool_velocity[i], reach_m };
            // Got under the skin from the side: through it, from the next step on; unless
            // the triangles along its side hold the skin (a thin tool laid along the skin,
            // the skin draped over its end crossing its axis there).
            if !self.holder.hold(i, held_tool, view, &mut feedback[i], weight) && !self.side_holds[i] {
                self.pierced[i] = true;
            }
        }
    }

    /// Every blade through the skin pushes it with its flat ([`flat`]).
    fn push_with_flats(&mut self, feedback: &mut [ToolFeedback], weight: f64) {
        let h = self.substep_s();
        let implicit = matches!(self.integrator, Integrator::ImplicitEuler(_));
        for i in 0..self.tools.len() {
            let (Some(hole), Some(tool)) = (self.holes[i], self.swept[i]) else { continue };
            let blade = flat::Blade { placed: &tool, velocity: self.tool_velocity[i] };
            let stiffness = HELD_STIFFNESS_OVER_CONTACT * self.tools[i].contact_stiffness_n_per_m;
            let contacts = implicit.then_some((stiffness, &mut self.contacts));
            if !flat::push_with_flat(&hole, blade, &mut self.nodes, &self.topo, h, contacts, &mut feedback[i], weight) {
                self.holes[i] = None;
            }
        }
    }

    /// The forceps pull what they grasp ([`grasp`]), with the tools a fraction `s` of
    /// their way through the step.
    fn grasp_skin(&mut self, feedback: &mut [ToolFeedback], weight: f64, s: f64) {
        let h = self.substep_s();
        let Some(grasps) = self.grasps.as_mut() else { return };
        let contacts = matches!(self.integrator, Integrator::ImplicitEuler(_)).then_some(&mut self.contacts);
        grasps.pull(&mut self.nodes, self.holder.friction().map(side_friction::stick_friction), s, h, contacts, &self.placed, feedback, weight);
    }

    /// The time one integration substep covers, s.
    fn substep_s(&self) -> f64 {
        match &self.integrator {
            Integrator::SymplecticEuler { substeps } => self.dt_s / f64::from(*substeps),
            Integrator::ImplicitEuler(_) => self.dt_s,
        }
    }

    /// Tools through the skin stay so until their axis no longer crosses it (and a
    /// blade until its stroke has ended). Runs before the cut stage: a blade that
    /// punctures the skin there, still lying at its tip, is through it.
    fn release_pierced(&mut self) {
        for i in 0..self.tools.len() {
            if self.cutter.as_ref().is_some_and(|c| c.in_stroke(i)) {
                continue;
            }
            if let (true, Some(tool)) = (self.pierced[i], self.placed[i])
                && self.holder.first_crossing(&tool, &self.nodes, &self.topo, &self.grid, self.max_edge_m).is_none()
            {
                self.pierced[i] = false;
            }
        }
    }

    fn accumulate_forces(&mut self) {
        let (beta, tangents) = match &mut self.integrator {
            // The implicit integrator damps the springs in its system, from the tangents
            // the force pass records.
            Integrator::ImplicitEuler(solver) => (0.0, Some(solver.as_mut())),
            Integrator::SymplecticEuler { .. } => (self.spring_damping_s, None),
        };
        forces::accumulate(&mut self.nodes, &self.springs.list, self.gravity, beta, &mut self.spring_scratch, tangents);
        if let Some(foundation) = &self.foundation {
            foundation.add_forces(&mut self.nodes);
        }
    }

    fn add_contacts(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback], weight: f64) {
        self.contacts.clear();
        self.side_memory.begin_pass();
        self.side_holds.fill(false);
        for (i, placed) in self.swept.iter().enumerate() {
            let Some(tool) = placed else { continue };
            let shape = &self.tools[i];
            // The broad phase is refreshed once per step: half a cell of margin covers
            // what nodes travel in between.
            let margin = 0.5 * self.grid.cell_size_m();
            let substep_s = self.substep_s();
            let friction = self.holder.friction();
            let mut side = self.holding[i].then(|| SideHold { memory: &mut self.side_memory, body: i, max_depth_m: shape.hold_max_depth_m(), friction, tool_velocity: self.tool_velocity[i] });
            let mode = if self.holding[i] {
                ContactMode::SideOnly { face_reach_m: hold::hold_reach_m(self.tool_velocity[i], tool.axis, substep_s, self.mean_edge_m) }
            } else if shape.can_cut && commands[i].cut {
                ContactMode::Radial
            } else {
                ContactMode::ShortestWayOut
            };
            apply_tool_contacts(
                tool,
                shape.contact_stiffness_n_per_m,
                mode,
                &mut self.nodes,
                &self.grid,
                &mut self.contacts,
                &mut feedback[i],
                weight,
                margin,
                side.as_mut(),
            );
            // A tool that fits between the nodes is also held by the triangles' insides;
            // not a blade with its cut button held (it parts the skin it meets).
            if let Some(side) = side.as_mut().filter(|_| tool.radius_m < self.mean_edge_m && !(shape.can_cut && commands[i].cut)) {
                let before = self.contacts.len();
                let k = shape.contact_stiffness_n_per_m;
                face_hold::apply_face_contacts(tool, k, side, &mut self.nodes, &self.topo, &self.grid, &mut self.face_scratch, &mut self.contacts, &mut feedback[i], weight, margin);
                self.side_holds[i] = self.contacts.len() > before;
            }
        }
        for &(node, force) in &self.cut_reactions {
            self.nodes.f[node as usize] += force;
        }
    }

    /// Makes the room the step fills without allocating: the contacts
    /// ([`contact_room`]), the tip face's candidates (every triangle thrice: face_hold)
    /// and the cut's reactions. After a build, a cut and a copy.
    pub(super) fn reserve_step_room(&mut self) {
        fn reserve<T>(v: &mut Vec<T>, room: usize) {
            if v.capacity() < room {
                v.reserve(room - v.len());
            }
        }
        reserve(&mut self.contacts, contact_room(&self.nodes));
        reserve(&mut self.face_scratch, 3 * self.topo.tris.len());
        reserve(&mut self.cut_reactions, MAX_CUT_REACTIONS_PER_TOOL * self.tools.len());
        if let Some(grasps) = self.grasps.as_mut() {
            grasps.reserve(self.nodes.len());
        }
    }

    fn implicit_step(&mut self) -> f64 {
        let Integrator::ImplicitEuler(solver) = &mut self.integrator else { unreachable!() };
        let check = solver.step(&mut self.nodes, &self.springs.list, &self.contacts, self.foundation.as_ref(), self.topology_version, self.dt_s, self.mass_damping_per_s, self.spring_damping_s);
        let cap_hit = solver.last_iterations >= solver.max_iterations && solver.last_residual > solver.tolerance;
        self.counters.count_solve(&crate::solver::pcg::Convergence { iterations: solver.last_iterations, residual: solver.last_residual, cap_hit });
        check
    }

    /// A non-finite state was produced: put every broken node back where it was made,
    /// at rest, report it, and send no force to the device this step.
    fn contain_blowup(&mut self, feedback: &mut [ToolFeedback]) {
        for i in 0..self.nodes.len() {
            let broken = !(self.nodes.x[i].iter().all(|c| c.is_finite()) && self.nodes.v[i].iter().all(|c| c.is_finite()));
            if broken {
                self.nodes.x[i] = self.nodes.x_ref[i];
                self.nodes.v[i] = Vec3::zeros();
                if self.nodes.alive[i] {
                    self.grid.update(i as u32, &self.nodes.x[i]);
                }
            }
        }
        if let Integrator::ImplicitEuler(solver) = &mut self.integrator {
            solver.reset_warm_start();
        }
        for fb in feedback.iter_mut() {
            fb.force_n = Vec3::zeros();
            fb.torque_nm = Vec3::zeros();
        }
        self.counters.blowups_contained += 1;
    }

    fn cut(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        self.cut_reactions.clear();
        for tool in 0..self.tools.len() {
            let wants_cut = self.tools[tool].can_cut && commands[tool].cut;
            let cutter = self.cutter.as_mut().expect("cut stage runs only with a cutter");
            let view = CutView {
                x: &self.nodes.x,
                v: &self.nodes.v,
                x_ref: &self.nodes.x_ref,
                topo: &self.topo,
                grid: &self.grid,
                max_edge_m: self.max_edge_m,
            };
            let next_id = self.nodes.len() as u32;
            let step = match self.placed[tool].filter(|_| wants_cut) {
                Some(blade) => {
                    let hit = if self.holding[tool] {
                        // Pressing intact skin: it gives when the tip presses hard enough.
                        // The blade is then through it: from the next step it passes, the
                        // skin springs back up along it, and its stroke begins where it
                        // crosses the skin then.
                        let hold = self.holder.tools[tool];
                        let puncture = resistance::puncture_force_n(self.fracture_toughness_j_per_m2, self.tools[tool].width_m());
                        self.pierced[tool] |= hold.force_n >= puncture;
                        None
                    } else {
                        cutter.crossing(&blade, &view)
                    };
                    // The skin resists a blade already through it (a stroke under way).
                    let resisted = match (hit, self.previous_placed[tool]) {
                        (Some(hit), Some(before)) if cutter.in_stroke(tool) && self.fracture_toughness_j_per_m2 > 0.0 => {
                            let mut motion = blade_motion(&blade, &before, &hit, &self.nodes, &self.topo, self.dt_s);
                            let smoothed = &mut self.blade_velocity[tool];
                            *smoothed += (motion.relative_velocity - *smoothed) * (self.dt_s / (BLADE_VELOCITY_TIME_CONSTANT_S + self.dt_s));
                            motion.relative_velocity = *smoothed;
                            Some((hit, resistance::resistance(&motion, self.fracture_toughness_j_per_m2, self.material.thickness_m)))
                        }
                        _ => {
                            self.blade_velocity[tool] = Vec3::zeros();
                            None
                        }
                    };
                    // Without a fracture toughness every crossing cuts (the paper's rule).
                    let advance = resisted.is_none_or(|(_, r)| r.cuts) || self.fracture_toughness_j_per_m2 <= 0.0;
                    let step = cutter.update(tool, &blade, hit, advance, &view, next_id);
                    if let Some((hit, r)) = resisted.filter(|(_, r)| r.cuts) {
                        feedback[tool].force_n += r.force_n;
                        feedback[tool].resistance_n += r.force_n;
                        feedback[tool].torque_nm += (hit.point - blade.tip).cross(&r.force_n);
                        // The opposite force drags the skin the blade cuts through, spread
                        // over the nodes around the crossing (one triangle's nodes weigh
                        // too little to take it alone within a step).
                        let reach = REACTION_REACH_EDGES * self.mean_edge_m;
                        let first = self.cut_reactions.len();
                        // A fixed bound, not the vector's capacity: a copy of the tissue
                        // (a replay's kept state) must step exactly as the original.
                        let room = MAX_CUT_REACTIONS_PER_TOOL * self.tools.len();
                        let (reactions, x) = (&mut self.cut_reactions, &self.nodes.x);
                        self.grid.query_box(&(hit.point - Vec3::repeat(reach)), &(hit.point + Vec3::repeat(reach)), |v| {
                            if reactions.len() < room && (x[v as usize] - hit.point).norm() <= reach {
                                reactions.push((v, Vec3::zeros()));
                            }
                        });
                        let share = -r.force_n / (self.cut_reactions.len() - first).max(1) as f64;
                        self.cut_reactions[first..].iter_mut().for_each(|(_, f)| *f = share);
                    }
                    step
                }
                None => {
                    self.blade_velocity[tool] = Vec3::zeros();
                    cutter.end_stroke(tool, &view, next_id)
                }
            };
            match step {
                CutStep::Unchanged => {}
                CutStep::Cut(plan) => {
                    feedback[tool].cutting = true;
                    self.apply_cut(plan);
                    // Node ids of the crossed triangle may have gone with the cut.
                    self.cut_reactions.retain(|&(v, _)| self.nodes.alive[v as usize]);
                }
                CutStep::LastPieceLeftUncut => self.counters.uncut_last_pieces += 1,
            }
        }
    }

    fn finish_feedback(&mut self, feedback: &mut [ToolFeedback]) {
        for (fb, tool) in feedback.iter_mut().zip(&self.tools) {
            if !(fb.force_n.iter().all(|c| c.is_finite()) && fb.torque_nm.iter().all(|c| c.is_finite())) {
                fb.force_n = Vec3::zeros();
                fb.torque_nm = Vec3::zeros();
            }
            fb.clamp_force(tool.max_force_n);
            if fb.force_clamped {
                self.counters.force_clamps += 1;
            }
        }
    }

    // ----- read access (tests, tools, reports) -----

    /// Node positions by id, m (dead ids included; see [`Self::node_alive`]).
    pub fn positions(&self) -> &[Vec3] {
        &self.nodes.x
    }

    pub fn velocities(&self) -> &[Vec3] {
        &self.nodes.v
    }

    pub fn masses(&self) -> &[f64] {
        &self.nodes.mass
    }

    pub fn node_alive(&self, id: u32) -> bool {
        self.nodes.alive.get(id as usize).copied().unwrap_or(false)
    }

    pub fn node_count(&self) -> usize {
        self.nodes.alive_count()
    }

    pub fn spring_count(&self) -> usize {
        self.springs.len()
    }

    /// Live triangles: (id, vertex ids).
    pub fn triangles(&self) -> impl Iterator<Item = (u32, [u32; 3])> + '_ {
        self.topo.tris.iter().enumerate().filter(|(t, _)| self.topo.tri_alive[*t]).map(|(t, tri)| (t as u32, *tri))
    }

    /// Sum of node masses, kg.
    pub fn total_mass(&self) -> f64 {
        self.nodes.mass.iter().sum()
    }

    /// ρ·t·(sum of the live triangles' reference areas), kg: what the total mass must be.
    pub fn mass_of_triangles(&self) -> f64 {
        let area: f64 = self.triangles().map(|(t, _)| self.topo.tri_area_ref[t as usize]).sum();
        self.material.density_kg_per_m3 * self.material.thickness_m * area
    }

    pub fn kinetic_energy(&self) -> f64 {
        forces::kinetic_energy(&self.nodes)
    }

    /// Elastic plus external-force potential, J (see `forces::potential_energy`).
    pub fn potential_energy(&self) -> f64 {
        forces::potential_energy(&self.nodes, &self.springs.list, self.gravity)
    }

    /// Net spring force on a node, N (for reactions at fixed nodes).
    pub fn spring_force_on(&self, node: u32) -> Vec3 {
        let mut f = Vec3::zeros();
        for s in &self.springs.list {
            if s.a != node && s.b != node {
                continue;
            }
            let d = self.nodes.x[s.b as usize] - self.nodes.x[s.a as usize];
            let len = d.norm();
            if len > 0.0 {
                let pull = d * (s.k * (len - s.l0) / len);
                f += if s.a == node { pull } else { -pull };
            }
        }
        f
    }

    /// Springs as (a, b, stiffness N/m, natural length m).
    pub fn springs(&self) -> impl Iterator<Item = (u32, u32, f64, f64)> + '_ {
        self.springs.list.iter().map(|s| (s.a, s.b, s.k, s.l0))
    }

    /// Moves a node (with zero velocity). On a fixed node this prescribes a displacement.
    pub fn set_node_position(&mut self, id: u32, x: Vec3) {
        self.nodes.x[id as usize] = x;
        self.nodes.v[id as usize] = Vec3::zeros();
        self.grid.update(id, &x);
    }

    /// Steps `steps` times with tool 0 held at `pose` (None: every tool away), the cut
    /// button `cut`; returns tool 0's last feedback. For experiments and tests.
    pub fn step_holding(&mut self, pose: Option<crate::math::Pose>, cut: bool, steps: usize) -> ToolFeedback {
        let tools = self.tools().len();
        let mut commands = vec![ToolCommand::default(); tools];
        let mut feedback = vec![ToolFeedback::default(); tools];
        if let Some(p) = pose {
            commands[0] = ToolCommand { pose: p, active: true, cut, grip: None };
        }
        for _ in 0..steps {
            self.step(&commands, &mut feedback);
        }
        feedback.first().copied().unwrap_or_default()
    }

    /// How many nodes scene tool `tool` (forceps) holds ([`grasp`]).
    pub fn grasped_nodes(&self, tool: usize) -> usize {
        self.grasps.as_ref().map_or(0, |g| g.held_by(tool))
    }

    /// The nodes scene tool `tool` (forceps) holds.
    pub fn grasped_node_ids(&self, tool: usize) -> Vec<u32> {
        self.grasps.as_ref().map_or_else(Vec::new, |g| g.nodes_held_by(tool).collect())
    }

    /// The incisions made so far, with their curves and lips.
    pub fn incisions(&self) -> &[Incision] {
        self.cutter.as_ref().map_or(&[], |c| &c.incisions)
    }

    pub fn mean_edge_length_m(&self) -> f64 {
        self.mean_edge_m
    }

    /// Stability of the explicit integrator at the current configuration.
    pub fn stability_bound(&self) -> StabilityBound {
        self.stability
    }

    /// Current explicit substeps (None for the implicit integrator).
    pub fn substeps(&self) -> Option<u32> {
        match &self.integrator {
            Integrator::SymplecticEuler { substeps } => Some(*substeps),
            Integrator::ImplicitEuler(_) => None,
        }
    }

    /// CG iterations and relative residual of the last implicit step.
    pub fn last_solve(&self) -> Option<(u32, f64)> {
        match &self.integrator {
            Integrator::ImplicitEuler(s) => Some((s.last_iterations, s.last_residual)),
            Integrator::SymplecticEuler { .. } => None,
        }
    }

    /// Why the last cut update that could not stitch the wound failed.
    pub fn last_fallback_reason(&self) -> Option<&str> {
        self.fallbacks.last().map(|f| f.reason.as_str())
    }

    /// Smallest angle of all triangles cut updates have created, degrees.
    pub fn min_cut_angle_deg(&self) -> Option<f64> {
        self.min_cut_angle_deg
    }

    /// Smallest angle of the triangles the last cut update created, degrees.
    pub fn last_cut_min_angle_deg(&self) -> Option<f64> {
        self.last_cut_min_angle_deg
    }

    pub fn material(&self) -> MembraneMaterial {
        self.material
    }

    pub fn residual_strain(&self) -> f64 {
        self.residual_strain
    }

    /// Turns per-stage timing on (with fresh totals) or off.
    pub fn set_profiling(&mut self, on: bool) {
        self.profile = on.then(StageTimes::default);
    }

    pub fn stage_times(&self) -> Option<StageTimes> {
        self.profile
    }

    /// Connected pieces of the mesh (triangles joined through shared vertices).
    pub fn piece_count(&self) -> usize {
        let n = self.nodes.len();
        let mut sets = crate::union_find::UnionFind::new(n);
        for (_, [a, b, c]) in self.triangles() {
            sets.union(a as usize, b as usize);
            sets.union(b as usize, c as usize);
        }
        let mut roots: Vec<usize> = (0..n).filter(|&i| self.nodes.alive[i] && !self.topo.node_tris[i].is_empty()).map(|i| sets.find(i)).collect();
        roots.sort_unstable();
        roots.dedup();
        roots.len()
    }
}

impl MassSpring {
    /// What the tools leave for the next step (crate::hash::HashState): the jaws and the
    /// grasps, where each tool was, which are through the skin and where, the tip faces'
    /// and the sides' holds with their friction anchors, the blades' smoothed velocity
    /// and the skin's share of their resistance still to apply, and the cuts in progress.
    fn hash_contact_memory(&self, h: &mut StateHasher) {
        use crate::hash::HashState;
        (&self.bodies, &self.grasps, &self.previous_placed).hash_state(h);
        (&self.pierced, &self.holding, &self.side_holds).hash_state(h);
        (&self.blade_through, &self.holes, &self.holder).hash_state(h);
        (&self.side_memory, &self.blade_velocity, &self.cut_reactions).hash_state(h);
        self.cutter.hash_state(h);
    }
}

impl Tissue for MassSpring {
    fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        self.bodies.as_ref()?.jaws_half_gap_m(tool)
    }

    fn model_name(&self) -> &'static str {
        "msm"
    }

    fn time_step_s(&self) -> f64 {
        self.dt_s
    }

    // The scene's tools, as commands and feedback name them (`tools` are the bodies).
    #[allow(clippy::misnamed_getters)]
    fn tools(&self) -> &[ToolShape] {
        &self.scene_tools
    }

    fn step(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        MassSpring::step(self, commands, feedback);
    }

    fn step_index(&self) -> u64 {
        self.step_index
    }

    fn cut_fallbacks(&self) -> &[CutFallback] {
        &self.fallbacks
    }

    fn snapshot(&self) -> SurfaceSnapshot {
        let vertices = (0..self.nodes.len())
            .filter(|&i| self.nodes.alive[i] && !self.topo.node_tris[i].is_empty())
            .map(|i| {
                let p = self.nodes.x[i];
                SurfaceVertex { id: i as u32, position_m: [p.x as f32, p.y as f32, p.z as f32], material: 0 }
            })
            .collect();
        let triangles = self.triangles().map(|(id, vertices)| SurfaceTriangle { id, vertices }).collect();
        SurfaceSnapshot { version: self.topology_version, vertices, triangles }
    }

    fn topology_version(&self) -> u64 {
        self.topology_version
    }

    fn drain_deltas(&mut self, out: &mut Vec<TopologyDelta>) {
        out.append(&mut self.deltas);
    }

    fn vertex_capacity(&self) -> usize {
        self.nodes.len()
    }

    fn write_positions(&self, out: &mut [[f32; 3]]) {
        for (o, p) in out.iter_mut().zip(&self.nodes.x) {
            *o = [p.x as f32, p.y as f32, p.z as f32];
        }
    }

    fn vertex_alive(&self, id: u32) -> bool {
        self.node_alive(id) && !self.topo.node_tris[id as usize].is_empty()
    }

    fn state_hash(&self) -> u64 {
        let mut h = StateHasher::new();
        h.write_u64(self.step_index);
        h.write_u64(self.topology_version);
        for i in 0..self.nodes.len() {
            h.write_u8(u8::from(self.nodes.alive[i]));
            for c in self.nodes.x[i].iter().chain(self.nodes.v[i].iter()) {
                h.write_f64(*c);
            }
        }
        for (id, tri) in self.triangles() {
            h.write_u32(id);
            for v in tri {
                h.write_u32(v);
            }
        }
        for s in &self.springs.list {
            h.write_u32(s.a);
            h.write_u32(s.b);
            h.write_f64(s.k);
            h.write_f64(s.l0);
        }
        self.hash_contact_memory(&mut h);
        h.finish()
    }

    fn counters(&self) -> TissueCounters {
        TissueCounters {
            nodes: self.nodes.alive_count() as u64,
            elements: self.springs.len() as u64,
            surface_vertices: (0..self.nodes.len()).filter(|&i| self.vertex_alive(i as u32)).count() as u64,
            surface_triangles: self.topo.alive_tris as u64,
            ..self.counters
        }
    }

    fn pieces(&self) -> usize {
        self.piece_count()
    }

    fn clone_box(&self) -> Box<dyn Tissue> {
        let mut copy = self.clone();
        // A clone keeps the lengths, not the room reserved for the 1 kHz path.
        copy.reserve_step_room();
        Box::new(copy)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{ModelSpec, Scene};

    /// The state hash covers what the tools leave for the next step, not only the nodes:
    /// two skins alike but for one piece of contact memory hash differently.
    #[test]
    fn the_state_hash_covers_the_tools_contact_memory() {
        let scene = Scene::load(std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/../scenes/skin-patch.json"))).unwrap();
        let ModelSpec::Msm(spec) = &scene.model else { unreachable!() };
        let skin = build_from_scene(&scene, spec).unwrap();
        let hash = skin.state_hash();
        assert_eq!(skin.clone().state_hash(), hash, "a copy hashes the same");
        let edits: [(&str, fn(&mut MassSpring)); 4] = [
            ("a tool through the skin", |m| m.pierced[0] = true),
            ("where a tool was", |m| m.previous_placed[1] = Some(PlacedTool::new(&m.tools[1], &crate::math::Pose::default()))),
            ("a blade's smoothed velocity", |m| m.blade_velocity[0] = Vec3::x()),
            ("the skin's share of a cutting resistance still to apply", |m| m.cut_reactions.push((3, Vec3::z()))),
        ];
        for (what, edit) in edits {
            let mut other = skin.clone();
            edit(&mut other);
            assert_ne!(other.state_hash(), hash, "{what}");
        }
    }
}
