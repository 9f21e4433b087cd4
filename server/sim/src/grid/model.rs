//! [`BranchedGrid`]: the branched-grid tissue behind the session's [`Tissue`] interface.
//!
//! One step: place the tools in the grid's frame; gather penalty contacts between each
//! tool's outer capsule and the surface vertices near it (and, for a tool thinner than
//! the vertex spacing, the insides of triangles: face_contact); take one implicit step with
//! those contacts (their forces at the step's end, as solved, are the haptic force);
//! contain a blow-up if one shows;
//! then let every cutting tool remove the voxels whose deformed centres its inner
//! capsule contains, updating the grid and the surface locally and recording a
//! topology delta. Nothing in a step without a cut allocates once the contact list has
//! grown to its working size.

mod contact_patch;
mod face_contact;

use super::solver::{Dynamics, PointContact, SolverSettings};
use super::surface::GridSurface;
use super::topology::{NONE, Topology, UpdateReport};
use crate::hash::StateHasher;
use crate::math::{Matrix3, Vec3, closest_point_on_segment};
use crate::surface::{SurfaceSnapshot, SurfaceTriangle, SurfaceVertex, TopologyDelta};
use crate::tissue::{Tissue, TissueCounters};
use crate::multirate::patch::ContactPatch;
use crate::tool::{ToolCommand, ToolFeedback, ToolShape};

/// The grid's frame in the scene: `world = rotation · local + translation`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Frame {
    pub rotation: Matrix3<f64>,
    pub translation: Vec3,
}

impl Frame {
    pub fn to_world(&self, local: &Vec3) -> Vec3 {
        self.rotation * local + self.translation
    }
    pub fn to_local(&self, world: &Vec3) -> Vec3 {
        self.rotation.transpose() * (world - self.translation)
    }
}

/// A material of the scene, by label.
#[derive(Debug, Clone, PartialEq)]
pub struct GridMaterial {
    pub label: u16,
    pub name: String,
    pub young_pa: f64,
    pub poisson: f64,
    pub density_kg_per_m3: f64,
    pub friction: super::friction::Friction,
    pub fracture_toughness_j_per_m2: f64,
}

/// Per tool: the current cut stroke (the cut button held).
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct Stroke {
    removed_any: bool,
    /// The blade's flat or back leads (super::cut_resistance::edge_leads): it pushes
    /// tissue with a fracture toughness instead of cutting it.
    pushes: bool,
    last_tip: Option<Vec3>,
    /// The tissue's averaged resistance (super::cut_resistance).
    resistance: super::cut_resistance::CutResistance,
}

impl crate::hash::HashState for Stroke {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        (self.removed_any, self.pushes, self.last_tip).hash_state(h);
        self.resistance.hash_state(h);
    }
}

/// A tool placed in the grid's frame for a step: its tip, orientation and velocity,
/// its outer capsule, the deepest one contact may be held, and the box its contacts
/// are searched in.
#[derive(Debug, Clone, Copy)]
struct ToolPlacement {
    tip: Vec3,
    tool_to_grid: Matrix3<f64>,
    tool_velocity: Vec3,
    moved: Option<Vec3>,
    capsule: super::hold::Capsule,
    max_depth: f64,
    lo: Vec3,
    hi: Vec3,
}

impl ToolPlacement {
    /// Tool `i` so placed, as the face contact reads it.
    fn at(&self, i: usize) -> face_contact::ToolAt<'_> {
        face_contact::ToolAt { tool: i, capsule: &self.capsule, tool_to_grid: &self.tool_to_grid, moved: self.moved, max_depth: self.max_depth, lo: &self.lo, hi: &self.hi }
    }
}

/// The branched-grid tissue.
#[derive(Debug, Clone)]
pub struct BranchedGrid {
    pub(super) dt_s: f64,
    pub(super) frame: Frame,
    pub(super) topo: Topology,
    pub(super) dynamics: Dynamics,
    pub(super) settings: SolverSettings,
    pub(super) surface: GridSurface,
    pub(super) materials: Vec<GridMaterial>,
    /// The bodies the tissue meets: the scene's tools, forceps as their two jaws
    /// ([`crate::tool::bodies`]). Every per-tool list below is per body.
    pub(super) tools: Vec<ToolShape>,
    /// The scene's tools, as commands and feedback name them.
    scene_tools: Vec<ToolShape>,
    /// The split between tools and bodies where they differ (forceps).
    bodies: Option<crate::tool::bodies::Bodies>,
    /// Per body, the body whose contact memory it takes when it comes back (the second
    /// jaw of forceps reopening: [`crate::tool::bodies::Bodies::twins`]).
    twins: Vec<Option<usize>>,
    /// None: the scene cannot be cut.
    pub(super) max_voxels_per_step: Option<usize>,
    contacts: Vec<PointContact>,
    /// Per tool: its contacts' range in `contacts`.
    contact_ranges: Vec<(usize, usize)>,
    /// Per contact: from its tool's tip to the contact point, m (grid frame).
    contact_levers: Vec<Vec3>,
    /// Per contact: its surface vertex (for a contact on a triangle's inside, the
    /// triangle's vertex nearest it).
    contact_vertices: Vec<u32>,
    /// Per contact: whether it is on a triangle's inside (face_contact; its friction is decided before the solve, not moved after it).
    contact_on_face: Vec<bool>,
    /// Per contact: the share of forceps' grip pressing it, N (0 unless it is under the
    /// inner flat of a jaw that pinches: tool::bodies::Bodies::pinched); its friction
    /// takes at least this normal force.
    contact_pinch_n: Vec<f64>,
    /// Per body: its pinch (the direction its inner flat presses, tool frame; the grip,
    /// N), refreshed before each step.
    pinches: Vec<Option<crate::tool::bodies::Pinch>>,
    /// Per body: the contacts its inner flat pressed this step, if it pinched (None
    /// otherwise): jaws whose flats both press nothing have let go (Bodies::pinch).
    inner_flat_contacts: Vec<Option<u32>>,
    /// Per tool: its tip last step (grid frame), for its velocity.
    previous_tips: Vec<Option<Vec3>>,
    /// Per surface vertex: where it stuck to a tool (super::friction); forgotten at every
    /// cut.
    anchors: super::friction::Anchors,
    /// Per surface vertex: how it touches a tool (super::hold); kept across cuts (a
    /// vertex's id is never reused).
    touches: Vec<Option<super::hold::Touch>>,
    /// The vertices a tool touches this step, the triangles near it and the insides of
    /// triangles it reaches (scratch).
    touching_scratch: Vec<(u32, super::hold::Contact)>,
    triangle_scratch: Vec<u32>,
    face_scratch: Vec<face_contact::FaceContact>,
    /// Per tool: the points on triangles' insides it holds (face_contact).
    held_faces: Vec<Vec<face_contact::HeldFace>>,
    backup_x: Vec<Vec3>,
    backup_v: Vec<Vec3>,
    strokes: Vec<Stroke>,
    deltas: Vec<TopologyDelta>,
    topology_version: u64,
    step_index: u64,
    counters: TissueCounters,
    removed_volume_m3: f64,
    last_update: Option<LastUpdate>,
    /// How `"fidelity": "auto"` chose the level (None for a fixed level).
    fidelity: Option<super::fidelity::FidelityChoice>,
    /// Multirate scratch: the vertices near a tool, and the nodal force and motion of a
    /// compliance solve.
    patch_scratch: Vec<(u32, f64)>,
    compliance_force: Vec<Vec3>,
    compliance_motion: Vec<Vec3>,
    /// Per tool: its last patch compliance.
    compliance_cache: Vec<Option<contact_patch::CachedCompliance>>,
}

/// A deformation step's multirate inputs and outputs (see `deformation_step`).
struct Deformation<'a> {
    path: &'a [ToolCommand],
    patches: &'a mut [ContactPatch],
    margin_m: f64,
}

/// How many contacts (surface vertices touching the tools) a step has room for without
/// allocating: far more than the vertices under a tool's end and along its flats on the
/// finest grids bundled.
const CONTACT_ROOM: usize = 1024;

/// Where forceps' jaws that have met tissue stop closing at the latest, in voxels of
/// their half gap (a quarter voxel: their inner flats half a voxel apart). Pinched
/// thinner, the tissue between them would have to pass between the grid's surface
/// vertices, and the jaws met through it, holding nothing (crate::tool::bodies::Bodies::pinch).
const PINCHED_HALF_GAP_VOXELS: f64 = 0.25;

/// What the last voxel removal did and what each part of it cost.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LastUpdate {
    pub report: UpdateReport,
    /// Existing surface vertices whose smoothed rest position moved.
    pub moved_vertices: usize,
    /// Time in the grid's topology update (elements, condensation, nodes), ns.
    pub topology_ns: u64,
    /// Time in the surface update (marching cubes, smoothing), ns.
    pub surface_ns: u64,
    /// Time in the rest (solver buffers, the delta), ns.
    pub other_ns: u64,
}

impl BranchedGrid {
    /// The top of the body where it is broad: the highest voxel whose 5 × 5 neighbourhood
    /// in x and y is all material (so a tool meets a flat top, not a ridge) and whose
    /// element holds no fixed node or support point; world, m, at the voxel's upper face. Benchmarks and
    /// the fidelity calibration press a probe there. None for a body without one.
    pub fn broad_top(&self) -> Option<Vec3> {
        let t = &self.topo;
        let [nx, ny, nz] = t.layout.voxels;
        let full = |i: usize, j: usize, k: usize| t.material[t.layout.voxel_index([i, j, k])] != 0;
        for k in (0..nz).rev() {
            for j in 2..ny.saturating_sub(2) {
                for i in 2..nx.saturating_sub(2) {
                    if (i - 2..=i + 2).all(|a| (j - 2..=j + 2).all(|b| full(a, b, k))) {
                        let v = t.layout.voxel_index([i, j, k]);
                        let element = t.voxel_element[v] as usize;
                        if t.elements.nodes[element].iter().any(|&n| t.nodes.fixed[n as usize]) || t.supports.live(t).any(|(e, _)| e == element) {
                            continue; // pressing on a held region measures nothing
                        }
                        let top = t.voxel_centre(v) + Vec3::new(0.0, 0.0, t.layout.spacing_m[2] * 0.5);
                        return Some(self.frame.to_world(&top));
                    }
                }
            }
        }
        None
    }

    // The parts the builder made, each once: a struct of them would only be unpacked here.
    #[allow(clippy::too_many_arguments)]
    pub(super) fn assemble(
        dt_s: f64,
        frame: Frame,
        topo: Topology,
        settings: SolverSettings,
        surface: GridSurface,
        materials: Vec<GridMaterial>,
        tools: Vec<ToolShape>,
        max_voxels_per_step: Option<usize>,
    ) -> Self {
        let dynamics = Dynamics::new(&topo);
        let n = topo.nodes.len();
        // The grid meets bodies: the tools, forceps as their two jaws.
        let (scene_tools, (tools, bodies)) = (tools.clone(), crate::tool::bodies::expand(&tools));
        let twins = bodies.as_ref().map_or_else(|| vec![None; tools.len()], crate::tool::bodies::Bodies::twins);
        let tool_count = tools.len();
        // The per-vertex contact memory, with room for the surface to double through
        // cuts: growing it on the step after a cut (copying and first touching megabytes
        // on a large body) made that step 0.7 ms longer on the layered abdomen.
        let vertices = surface.voxel.len();
        let mut touches = Vec::with_capacity(2 * vertices);
        touches.resize(vertices, None);
        // Room for the contacts of a step, made here: growing it in a step allocates in
        // the 1 kHz loop (closing forceps touch more vertices than they did pressed).
        let contact_room = vertices.min(CONTACT_ROOM);
        let mut grid = BranchedGrid {
            dt_s,
            frame,
            dynamics,
            settings,
            materials,
            max_voxels_per_step,
            contacts: Vec::with_capacity(contact_room),
            contact_ranges: vec![(0, 0); tool_count],
            contact_levers: Vec::with_capacity(contact_room),
            contact_vertices: Vec::with_capacity(contact_room),
            contact_on_face: Vec::with_capacity(contact_room),
            contact_pinch_n: Vec::with_capacity(contact_room),
            pinches: vec![None; tool_count],
            inner_flat_contacts: vec![None; tool_count],
            previous_tips: vec![None; tool_count],
            anchors: super::friction::Anchors::with_room(vertices, 2 * vertices),
            touches,
            touching_scratch: Vec::with_capacity(contact_room),
            triangle_scratch: Vec::new(),
            face_scratch: Vec::new(),
            held_faces: vec![Vec::new(); tool_count],
            backup_x: vec![Vec3::zeros(); n],
            backup_v: vec![Vec3::zeros(); n],
            strokes: vec![Stroke::default(); tool_count],
            deltas: Vec::new(),
            topology_version: 0,
            step_index: 0,
            counters: TissueCounters::default(),
            removed_volume_m3: 0.0,
            last_update: None,
            fidelity: None,
            patch_scratch: Vec::new(),
            compliance_force: Vec::new(),
            compliance_motion: Vec::new(),
            compliance_cache: vec![None; tool_count],
            tools,
            scene_tools,
            bodies,
            twins,
            topo,
            surface,
        };
        // The preconditioner's first heavy work (a Cholesky factor, the multigrid's
        // coarse grids) is done here, as the model is made, never on a step.
        grid.dynamics.prime(&mut grid.topo, &grid.settings);
        if let (Some(floor), Some(bodies)) = (grid.pinch_floor_m(), grid.bodies.as_mut()) {
            bodies.pinch_no_closer_than(floor);
        }
        grid
    }

    /// Advances one step; see the module documentation.
    pub fn step(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        self.advance_tools(commands, feedback, None);
    }

    /// A step with the scene's tools' `commands` and `feedback`, split into and gathered
    /// from the bodies the grid meets (forceps as their jaws).
    fn advance_tools(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback], multirate: Option<Deformation<'_>>) {
        crate::tool::assert_one_per_tool(commands, feedback, &self.scene_tools);
        // Taken out for the step and put back: no allocation.
        match self.bodies.take() {
            None => self.advance(commands, feedback, multirate),
            Some(mut bodies) => {
                bodies.split(commands, &self.scene_tools, &mut self.tools, self.dt_s);
                bodies.pinches(&self.scene_tools, &mut self.pinches);
                self.inner_flat_contacts.fill(None);
                self.advance(&bodies.commands, &mut bodies.feedback, multirate);
                // Closing jaws stop on what pushes them back with the grip (their grasp:
                // the tissue's friction holds it between them, grid::friction), and let
                // go of it once it has slipped out from between them.
                bodies.pinch(&self.scene_tools, &self.inner_flat_contacts, self.dt_s);
                self.counters.force_clamps += bodies.gather(&self.scene_tools, feedback);
                self.bodies = Some(bodies);
            }
        }
    }

    /// A deformation step as [`Self::deformation_step`] from the scene's tools' commands,
    /// split into the bodies' by the grid itself (its jaws moving for one deformation
    /// step): for timing a deformation step (crate::grid::fidelity), where no haptic loop
    /// splits them. `patches`: one per body.
    pub fn deformation_step_of_tools(&mut self, commands: &[ToolCommand], patches: &mut [ContactPatch], margin_m: f64, feedback: &mut [ToolFeedback]) {
        self.advance_tools(commands, feedback, Some(Deformation { path: &[], patches, margin_m }));
    }

    /// Per body (the bodies the grid meets: forceps as their jaws), the contacts its
    /// inner flat pressed in the last step, where it pinched (None otherwise).
    pub fn inner_flat_contacts(&self) -> &[Option<u32>] {
        &self.inner_flat_contacts
    }

    /// Scene tool `tool`'s jaws' half gap, m: half the distance between their inner
    /// flats (0 closed; None for a tool without jaws).
    pub fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        self.bodies.as_ref()?.jaws_half_gap_m(tool)
    }

    /// Where closing forceps' jaws stop on this tissue at the latest (their half gap, m),
    /// None where they close fully (tool::bodies::Bodies::pinch).
    pub fn pinch_floor_m(&self) -> Option<f64> {
        // Without friction nothing would hold what they pinch: as on the skin without it.
        self.materials.iter().any(|m| m.friction.static_coefficient > 0.0).then(|| PINCHED_HALF_GAP_VOXELS * self.topo.layout.smallest_side_m())
    }

    /// How many bodies the grid meets (its tools, forceps as two jaws).
    pub fn body_count(&self) -> usize {
        self.tools.len()
    }

    /// One deformation step of a multirate schedule (crate::multirate): a step as
    /// [`Self::step`] (its own implicit contact with the tools where `commands` put them,
    /// and cuts, also along `path`: the haptic steps' commands since the last deformation
    /// step, one per tool per step) that also publishes each tool's contact patch into
    /// `patches`: its compliance from this step's system, the contact force the step
    /// ended with, and its vertices within `margin_m` of the tool as the step and its cuts
    /// leave them. Everything here is per body (forceps as their two jaws,
    /// crate::tool::bodies): the haptic loop splits the tools' commands into the bodies'
    /// at its own rate and hands over each body's shape (`bodies`: a jaw's plate open, the
    /// closed pair as one) and pinch (`pinches`: tool::bodies::Bodies::pinched), so that
    /// the deformation meets the jaws where and as the haptic loop renders them.
    #[allow(clippy::too_many_arguments)]
    pub fn deformation_step(&mut self, commands: &[ToolCommand], bodies: &[ToolShape], pinches: &[Option<crate::tool::bodies::Pinch>], path: &[ToolCommand], patches: &mut [ContactPatch], margin_m: f64, feedback: &mut [ToolFeedback]) {
        debug_assert_eq!(bodies.len(), self.tools.len());
        for (tool, body) in self.tools.iter_mut().zip(bodies) {
            tool.section = body.section;
        }
        self.pinches.copy_from_slice(pinches);
        self.inner_flat_contacts.fill(None);
        self.advance(commands, feedback, Some(Deformation { path, patches, margin_m }));
    }

    fn advance(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback], mut multirate: Option<Deformation<'_>>) {
        debug_assert_eq!(commands.len(), self.tools.len());
        self.contacts.clear();
        self.contact_levers.clear();
        self.contact_vertices.clear();
        self.contact_on_face.clear();
        self.contact_pinch_n.clear();
        self.lead_strokes(commands);
        for (i, (command, fb)) in commands.iter().zip(feedback.iter_mut()).enumerate() {
            *fb = ToolFeedback::default();
            let start = self.contacts.len();
            if command.active {
                if command.pose.is_finite() {
                    self.add_tool_contacts(i, command, multirate.is_some(), fb);
                } else {
                    self.counters.rejected_poses += 1;
                }
            }
            self.contact_ranges[i] = (start, self.contacts.len());
        }
        self.backup_x.copy_from_slice(&self.topo.nodes.x);
        self.backup_v.copy_from_slice(&self.topo.nodes.v);
        self.dynamics.assemble_tissue(&mut self.topo, &self.settings);
        if let Some(d) = multirate.as_mut() {
            // The tissue's compliance, before the tools' contacts enter the system.
            for (i, command) in commands.iter().enumerate() {
                self.patch_compliance(i, command, d.margin_m, &mut d.patches[i]);
            }
        }
        self.dynamics.solve_with_contacts(&self.topo, &self.settings, &self.contacts, self.step_index);
        let max_dv = self.dynamics.finish_step(&mut self.topo, &self.settings, self.step_index);
        self.counters.count_solve(&self.dynamics.last);
        self.counters.solver_waits = self.dynamics.waits();
        self.counters.solver_factor_failures = self.dynamics.factor_failures();
        if !max_dv.is_finite() {
            // Contain: back to the last good state, at rest, and say so.
            self.topo.nodes.x.copy_from_slice(&self.backup_x);
            self.topo.nodes.v.iter_mut().for_each(|v| *v = Vec3::zeros());
            self.dynamics.reset_warm_start();
            self.counters.blowups_contained += 1;
            for fb in feedback.iter_mut() {
                fb.force_n = Vec3::zeros();
                fb.torque_nm = Vec3::zeros();
            }
        } else {
            self.solved_contact_forces(feedback);
            self.move_anchors(commands);
        }
        if let Some(d) = multirate.as_mut() {
            for (patch, fb) in d.patches.iter_mut().zip(feedback.iter()) {
                patch.applied = -fb.force_n;
            }
        }
        // The cut reads the tips' motion over the step (`previous_tips`, still last step's).
        if self.max_voxels_per_step.is_some() {
            self.cut_along(multirate.as_ref().map_or(&[], |d| d.path), commands, feedback);
        }
        if let Some(d) = multirate.as_mut() {
            for (i, command) in commands.iter().enumerate() {
                self.patch_vertices(i, command, d.margin_m, &mut d.patches[i]);
            }
        }
        for (previous, command) in self.previous_tips.iter_mut().zip(commands) {
            *previous = (command.active && command.pose.is_finite()).then(|| self.frame.to_local(&command.pose.position_m));
        }
        for (fb, tool) in feedback.iter_mut().zip(&self.tools) {
            fb.clamp_force(tool.max_force_n);
            if fb.force_clamped {
                self.counters.force_clamps += 1;
            }
        }
        self.step_index += 1;
    }

    /// Each tool's force and torque from its contacts at the end of the step, as the
    /// solve left them (the force of the solved state, not the penalty before it).
    fn solved_contact_forces(&self, feedback: &mut [ToolFeedback]) {
        for (fb, &(start, end)) in feedback.iter_mut().zip(&self.contact_ranges) {
            let (mut force, mut torque) = (Vec3::zeros(), Vec3::zeros());
            for (c, lever) in self.contacts[start..end].iter().zip(&self.contact_levers[start..end]) {
                let on_tool = -(c.force_after(&self.topo, self.dt_s) + super::friction::stick_force_after(c, &self.topo, self.dt_s));
                force += on_tool;
                torque += lever.cross(&on_tool);
            }
            fb.force_n = self.frame.rotation * force;
            fb.torque_nm = self.frame.rotation * torque;
        }
    }

    /// After the solve, each frictional contact's anchor: kept (moving with its tool)
    /// while the solved stick force is within the static cone, moved to the dynamic
    /// cone where the vertex slides, dropped where the contact let go.
    fn move_anchors(&mut self, commands: &[ToolCommand]) {
        use super::friction::{Anchor, slid_anchor, stick_force_after};
        let h = self.dt_s;
        for (i, &(start, end)) in self.contact_ranges.iter().enumerate() {
            let tip = self.frame.to_local(&commands[i].pose.position_m);
            for c in start..end {
                if self.contact_on_face[c] {
                    continue;
                }
                let vertex = self.contact_vertices[c];
                let friction = self.friction_at(vertex as usize);
                if friction.static_coefficient <= 0.0 {
                    continue;
                }
                let contact = &self.contacts[c];
                let pressed_n = contact.force_after(&self.topo, h).norm();
                let normal_n = if pressed_n > 0.0 { pressed_n.max(self.contact_pinch_n[c]) } else { 0.0 };
                let force = stick_force_after(contact, &self.topo, h);
                let point = self.surface.position(&self.topo, vertex as usize);
                let anchor = self.anchors.slot_mut(vertex as usize);
                let Some(kept) = anchor.as_mut() else { continue };
                if normal_n <= 0.0 {
                    *anchor = None;
                } else if force.norm() > friction.static_coefficient * normal_n {
                    let sliding = force * (friction.dynamic_coefficient * normal_n / force.norm());
                    *kept = Anchor { tool: i, from_tip: slid_anchor(&point, &sliding, contact.stiffness) - tip, step: self.step_index };
                }
            }
        }
    }

    /// Penalty contacts of tool `i`'s outer capsule with the surface vertices, each
    /// pushed out on the side it came in from (super::hold), and, holding, with the
    /// insides of triangles it reaches between vertices (face_contact); their count goes
    /// into `fb`.
    fn add_tool_contacts(&mut self, i: usize, command: &ToolCommand, deforming: bool, fb: &mut ToolFeedback) {
        use super::hold::Touch;
        // One anchor slot per surface vertex (a cut changes their number).
        self.anchors.fit(self.surface.voxel.len());
        if self.touches.len() < self.surface.voxel.len() {
            self.touches.resize(self.surface.voxel.len(), None);
        }
        let mut touching = std::mem::take(&mut self.touching_scratch);
        let mut triangles = std::mem::take(&mut self.triangle_scratch);
        let mut faces = std::mem::take(&mut self.face_scratch);
        let placed = self.touching(i, command, deforming, &mut touching);
        let ToolPlacement { tip, tool_to_grid, tool_velocity, .. } = placed;
        let k = self.tools[i].contact_stiffness_n_per_m;
        let cutting = self.cutting(i, command);
        self.held_face_contacts(i, cutting, &placed, &touching, &mut triangles, &mut faces);
        // Under a jaw that pinches, the grip shared among the contacts its inner flat
        // presses (vertices and points on the triangles' insides) within its grip
        // length of the tip.
        let pinch = self.pinches[i].map(|p| (tool_to_grid * p.inward_local, p.grip_n, p.grip_length_m));
        let axis = tool_to_grid * Vec3::z();
        let pressed = |normal: &Vec3, point: &Vec3| pinch.is_some_and(|(inward, _, grip_length_m)| normal.dot(&inward) > 0.5 && (point - tip).dot(&axis) <= grip_length_m);
        // Counted only under a pinching jaw: the vertices' positions are not needed else.
        let pressed_count = match pinch {
            None => 0,
            Some(_) => touching.iter().filter(|(v, c)| pressed(&c.normal, &self.surface.position(&self.topo, *v as usize))).count() + faces.iter().filter(|f| pressed(&f.contact.normal, &f.point)).count(),
        };
        self.inner_flat_contacts[i] = pinch.map(|_| pressed_count as u32);
        let pinch_n = |normal: &Vec3, point: &Vec3| match pinch {
            Some((_, grip_n, _)) if pressed(normal, point) => grip_n / pressed_count as f64,
            _ => 0.0,
        };
        for &(v, super::hold::Contact { normal, depth, entry }) in &touching {
            let v = v as usize;
            let p = self.surface.position(&self.topo, v);
            if !cutting || !self.cuts_through(i, v) {
                self.touches[v] = Some(Touch { tool: i, normal_in_tool: tool_to_grid.transpose() * entry, step: self.step_index });
            }
            let element = self.topo.voxel_element[self.surface.voxel[v] as usize];
            let weights = self.surface.weights[v];
            // A vertex in contact with the same tool last step keeps its friction anchor.
            let from_tip = self.anchors.get(v).filter(|a| a.tool == i && a.step + 1 >= self.step_index).map(|a| a.from_tip);
            let slip = super::solver::embedded_velocity(&self.topo, element, &weights) - tool_velocity;
            let pinch_n = pinch_n(&normal, &p);
            let (stick_stiffness, stick_force, kept) = Self::rub_about_tip(from_tip, &p, &tip, &normal, k, (k * depth).max(pinch_n), self.friction_at(v), &slip, self.dt_s);
            if let Some(from_tip) = kept {
                self.anchors.set(v, super::friction::Anchor { tool: i, from_tip, step: self.step_index });
            }
            self.contacts.push(PointContact { element, weights, normal, stiffness: k, force: normal * (k * depth), stick_stiffness, stick_force, tool_velocity });
            self.contact_levers.push(p - tip);
            self.contact_vertices.push(v as u32);
            self.contact_on_face.push(false);
            self.contact_pinch_n.push(pinch_n);
        }
        for f in faces.iter_mut() {
            let (normal, depth) = (f.contact.normal, f.contact.depth);
            // The centring spring is a stick spring anchored on the axis; friction adds
            // one of its own anchor (as a vertex's, but decided before the solve only).
            let (centring_stiffness, centring_force) = f.centring.map_or((0.0, Vec3::zeros()), |offset| (k, offset * k));
            let point_velocity = super::solver::embedded_velocity(&self.topo, f.element, &f.weights);
            let pinched_n = pinch_n(&normal, &f.point);
            let (rub_stiffness, rub_force, kept) = Self::rub_about_tip(f.held.anchor_from_tip, &f.point, &tip, &normal, k, (k * depth).max(pinched_n), self.friction_at(f.vertex as usize), &(point_velocity - tool_velocity), self.dt_s);
            f.held.anchor_from_tip = kept;
            let stick_stiffness = centring_stiffness + rub_stiffness;
            // The two anchors move differently: friction's with the tool; the centring
            // spring's, the foot of the axis, with the tool across the axis and with the
            // point along it (the foot slides along the axis as the point does: the
            // point's velocity at the step's start). Moving it with the tool along the
            // axis too, a frictionless thin shaft drawn along itself dragged the surface
            // with it (2.8 times the force pressing it).
            let mut contact = PointContact { element: f.element, weights: f.weights, normal, stiffness: k, force: normal * (k * depth), stick_stiffness, stick_force: centring_force + rub_force, tool_velocity };
            let foot_velocity = placed.capsule.out_of_tip().map_or(tool_velocity, |axis| tool_velocity + axis * (point_velocity - tool_velocity).dot(&axis));
            if stick_stiffness > 0.0 {
                contact.tool_velocity = (foot_velocity * centring_stiffness + tool_velocity * rub_stiffness) / stick_stiffness;
            }
            self.contacts.push(contact);
            self.contact_levers.push(f.point - tip);
            self.contact_vertices.push(f.vertex);
            self.contact_on_face.push(true);
            self.contact_pinch_n.push(pinched_n);
        }
        self.held_faces[i].clear();
        self.held_faces[i].extend(faces.iter().map(|f| f.held));
        // The force the tool feels is the contacts' after the solve (solved_contact_forces).
        fb.contacts = (touching.len() + faces.len()) as u32;
        self.touching_scratch = touching;
        self.triangle_scratch = triangles;
        self.face_scratch = faces;
    }

    /// The surface vertices tool `i` at `command`'s pose touches, each with the normal it
    /// is pushed out along and how far (super::hold), into `out`; and where the tool is.
    /// `deforming`: a multirate deformation step, after which the tool moved for many
    /// haptic steps (the depth at which a contact lets go allows for it, below).
    fn touching(&self, i: usize, command: &ToolCommand, deforming: bool, out: &mut Vec<(u32, super::hold::Contact)>) -> ToolPlacement {
        use super::hold::{Capsule, Plate, contact};
        out.clear();
        let tool = &self.tools[i];
        let tip = self.frame.to_local(&command.pose.position_m);
        let tool_to_grid = super::hold::tool_to_grid(&self.frame.rotation, command.pose.orientation.to_rotation_matrix().matrix());
        let top = tip + tool_to_grid * Vec3::z() * tool.length_m;
        // Forceps come here as their jaws' plates (crate::tool::bodies).
        let capsule = Capsule { a: tip, b: top, radius: tool.radius_m, plate: Plate::of_tool(tool, &tool_to_grid) };
        let cutting = self.cutting(i, command);
        // The tool's motion over the step: a new contact came in along it.
        let moved = self.previous_tips[i].map(|before| tip - before);
        // A contact deeper than its rated depth lets go (super::hold::contact), as the
        // depth before the solve. A multirate deformation step comes after the tool has
        // moved for many haptic steps (1.65 mm in 33 ms at 50 mm/s), so a vertex or a
        // point the tool reached within it can be that much deeper before the solve
        // pushes it out: without the allowance, stiff contacts (a 0.5 mm probe or a
        // 0.4 mm blade plate at 20,000 N/m, rated depth 0.5 mm) let go as they were
        // made and the tool went 30 mm into the tissue at 0 N. A single-rate step moves
        // the tool within the penalty's give and keeps the rated depth alone.
        let travel = if deforming { moved.map_or(0.0, |m| m.norm()) } else { 0.0 };
        let max_depth = tool.hold_max_depth_m() + travel;
        let tool_velocity = moved.map_or(Vec3::zeros(), |m| m / self.dt_s);
        // A vertex the tool holds may be outside its capsule, by as much as the tool
        // moved and up to a radius beside it: search that much further.
        let reach = 2.0 * tool.radius_m + moved.map_or(0.0, |m| m.norm());
        let (lo, hi) = (tip.inf(&top) - Vec3::repeat(reach), tip.sup(&top) + Vec3::repeat(reach));
        for v in self.surface_vertices_near(lo, hi) {
            let p = self.surface.position(&self.topo, v as usize);
            if cutting && self.cuts_through(i, v as usize) {
                // The cut parts the tissue in front of the blade: it must reach the
                // cutting shape, so nothing holds it out (the cut resists through the
                // material's toughness instead, super::cut_resistance).
                let (normal, depth) = capsule.radial(&p);
                if depth > 0.0 {
                    out.push((v, super::hold::Contact { normal, depth, entry: normal }));
                }
                continue;
            }
            // A jaw coming back (away last step) takes what its twin held: the closed
            // jaws' plate (crate::tool::bodies).
            let back = self.previous_tips[i].is_none();
            let remembered = self.touches.get(v as usize).copied().flatten().filter(|t| (t.tool == i || (back && Some(t.tool) == self.twins[i])) && t.step + 1 >= self.step_index).map(|t| tool_to_grid * t.normal_in_tool);
            if let Some(touch) = contact(&capsule, &p, remembered, moved.map(|m| p + m), max_depth) {
                out.push((v, touch));
            }
        }
        ToolPlacement { tip, tool_to_grid, tool_velocity, moved, capsule, max_depth, lo, hi }
    }

    /// Whether tool `i` cuts under `command` (a cutting tool with its button held).
    fn cutting(&self, i: usize, command: &ToolCommand) -> bool {
        self.tools[i].cuts(command)
    }

    /// Ends the strokes of the tools whose cut button is released, and decides for the
    /// others whether the edge leads over the step (from last step's tip to this one's).
    fn lead_strokes(&mut self, commands: &[ToolCommand]) {
        for (i, command) in commands.iter().enumerate() {
            if !self.cutting(i, command) {
                self.strokes[i] = Stroke::default();
                continue;
            }
            let tip = self.frame.to_local(&command.pose.position_m);
            if let Some(leads) = self.previous_tips[i].and_then(|before| self.edge_leads(i, command, &(tip - before))) {
                self.strokes[i].pushes = !leads;
            }
        }
    }

    /// Whether tool `i` at `command`'s pose, having moved by `motion` (grid frame), leads
    /// with its edge or point (super::cut_resistance::edge_leads); None if too slow to say.
    fn edge_leads(&self, i: usize, command: &ToolCommand, motion: &Vec3) -> Option<bool> {
        let tool_to_grid = super::hold::tool_to_grid(&self.frame.rotation, command.pose.orientation.to_rotation_matrix().matrix());
        let (axis, edge) = (tool_to_grid * Vec3::z(), tool_to_grid * self.tools[i].edge_local);
        super::cut_resistance::edge_leads(motion, &axis, &edge, self.dt_s)
    }

    /// Whether material `m` (a voxel's label index, 1-based) has a fracture toughness:
    /// only a blade's edge parts it.
    fn tough(&self, m: u16) -> bool {
        self.materials[usize::from(m) - 1].fracture_toughness_j_per_m2 > 0.0
    }

    /// Whether tool `i`, cutting, lets surface vertex `v` into its cutting shape: unless
    /// its flat or back leads into tough tissue.
    fn cuts_through(&self, i: usize, v: usize) -> bool {
        !self.strokes[i].pushes || !self.tough(self.topo.material[self.surface.voxel[v] as usize])
    }

    /// The contacts on triangles' insides of tool `i` (face_contact) into `faces`: none
    /// where it cuts through.
    fn held_face_contacts(&self, i: usize, cutting: bool, placed: &ToolPlacement, touching: &[(u32, super::hold::Contact)], triangles: &mut Vec<u32>, faces: &mut Vec<face_contact::FaceContact>) {
        if cutting && !self.strokes[i].pushes {
            faces.clear();
            return;
        }
        self.face_contacts(&placed.at(i), touching, triangles, faces);
        if cutting {
            faces.retain(|f| !self.cuts_through(i, f.vertex as usize));
        }
    }

    /// The penalty force tool `i` at `command`'s pose would feel from the surface as it
    /// is now (each vertex along the normal it touched the tool with last step), world
    /// frame, N: what the step's fed-back force is checked against.
    pub fn penalty_now(&self, i: usize, command: &ToolCommand) -> Vec3 {
        let mut touching = Vec::new();
        let placed = self.touching(i, command, false, &mut touching);
        let mut faces = Vec::new();
        self.held_face_contacts(i, self.cutting(i, command), &placed, &touching, &mut Vec::new(), &mut faces);
        let k = self.tools[i].contact_stiffness_n_per_m;
        let contacts = touching.iter().map(|(_, c)| c).chain(faces.iter().map(|f| &f.contact));
        self.frame.rotation * contacts.map(|c| -c.normal * (k * c.depth)).sum::<Vec3>()
    }

    /// The friction of surface vertex `v`'s material.
    fn friction_at(&self, v: usize) -> super::friction::Friction {
        self.materials[usize::from(self.topo.material[self.surface.voxel[v] as usize]) - 1].friction
    }

    /// Friction's stick spring for a point at `p` held by a tool whose tip is at `tip`
    /// with normal force `normal_n` (super::friction::rub): its anchor `from_tip` (from
    /// the tip; None for a new contact, which sticks where it is), its velocity relative
    /// to the tool `slip`. Returns its stiffness, its force on the tissue now and the
    /// anchor to keep (None on frictionless tissue, where there is no spring).
    #[allow(clippy::too_many_arguments)]
    fn rub_about_tip(from_tip: Option<Vec3>, p: &Vec3, tip: &Vec3, normal: &Vec3, k: f64, normal_n: f64, friction: super::friction::Friction, slip: &Vec3, h: f64) -> (f64, Vec3, Option<Vec3>) {
        if friction.static_coefficient <= 0.0 {
            return (0.0, Vec3::zeros(), None);
        }
        let anchor = from_tip.map_or(*p, |from_tip| tip + from_tip);
        let (stiffness, force, anchor) = super::friction::rub(p, &anchor, normal, k, normal_n, friction, slip, h);
        (stiffness, force, Some(anchor - tip))
    }

    /// The surface vertices that move with an element in the coarse cells whose current
    /// box overlaps [lo, hi], cell by cell in order (the contacts' order is part of the
    /// state): the one search of the surface near a tool, for its vertex contacts, its
    /// face contacts and its multirate patch.
    fn surface_vertices_near(&self, lo: Vec3, hi: Vec3) -> impl Iterator<Item = u32> + '_ {
        self.cells_in_reach(&lo, &hi, &self.moved_at_most())
            .filter(move |&cell| !self.surface.cell_vertices[cell].is_empty() && self.cell_overlaps(cell, &lo, &hi))
            .flat_map(move |cell| self.surface.cell_vertices[cell].iter().copied())
            .filter(move |&v| self.surface.in_element(&self.topo, v as usize))
    }

    /// How far any node is from its rest position, per axis (grid frame, m; infinite
    /// if a position is not finite): what bounds where a cell's nodes can be now.
    fn moved_at_most(&self) -> Vec3 {
        let nodes = &self.topo.nodes;
        // `sup` drops a NaN; the sum keeps it (and an infinity), so a position that is
        // not finite searches everywhere.
        let (mut most, mut sum) = (Vec3::zeros(), 0.0);
        for (x, rest) in nodes.x.iter().zip(&nodes.rest) {
            let d = (x - rest).abs();
            most = most.sup(&d);
            sum += d.x + d.y + d.z;
        }
        if sum.is_finite() { most } else { Vec3::repeat(f64::INFINITY) }
    }

    /// The cells, in increasing index, whose current box can overlap [lo, hi] when no
    /// node is further than `moved` (per axis) from its rest position: those whose rest
    /// box overlaps [lo, hi] widened by `moved` and [`Self::cell_overlaps`]'s slack (a
    /// cell more each way for round-off). A superset of the cells `cell_overlaps`
    /// passes, in the same order, so a search that tests each with it finds what a
    /// scan of every cell finds: a tool's box spans a few cells of the thousands a scan
    /// tested every step (about 30 µs a scan on the layered abdomen's level 3).
    fn cells_in_reach(&self, lo: &Vec3, hi: &Vec3, moved: &Vec3) -> impl Iterator<Item = usize> + use<> {
        let layout = &self.topo.layout;
        let size = layout.cell_size_m();
        let widen = moved + Vec3::from(layout.spacing_m) * 0.5;
        let (lo, hi) = (lo - widen, hi + widen);
        let cells = layout.cells;
        let range = |a: usize| {
            let first = (lo[a] / size[a]).floor() - 1.0;
            let last = (hi[a] / size[a]).floor() + 1.0;
            // NaN or infinite bounds (a position not finite) take every cell.
            let first = if first.is_finite() { first.clamp(0.0, cells[a] as f64) as usize } else { 0 };
            let last = if last.is_finite() { last.clamp(-1.0, cells[a] as f64 - 1.0) } else { cells[a] as f64 - 1.0 };
            first..(last + 1.0) as usize
        };
        let (x, y, z) = (range(0), range(1), range(2));
        z.flat_map(move |k| {
            let x = x.clone();
            y.clone().flat_map(move |j| x.clone().map(move |i| i + cells[0] * (j + cells[1] * k)))
        })
    }

    /// Whether the box around cell `cell`'s current nodes overlaps [lo, hi].
    fn cell_overlaps(&self, cell: usize, lo: &Vec3, hi: &Vec3) -> bool {
        let mut min = Vec3::repeat(f64::INFINITY);
        let mut max = Vec3::repeat(f64::NEG_INFINITY);
        for &e in &self.topo.cell_elements[cell] {
            for &n in &self.topo.elements.nodes[e as usize] {
                let x = self.topo.nodes.x[n as usize];
                min = min.inf(&x);
                max = max.sup(&x);
            }
        }
        // The smoothed surface may stand slightly outside its cell: half a voxel of slack.
        let slack = Vec3::from(self.topo.layout.spacing_m) * 0.5;
        (0..3).all(|a| min[a] - slack[a] <= hi[a] && max[a] + slack[a] >= lo[a])
    }

    /// The deformed centre of a voxel (grid frame), from its element's nodes.
    pub fn voxel_position(&self, v: usize) -> Vec3 {
        let e = self.topo.voxel_element[v];
        let rest = self.topo.voxel_centre(v);
        if e == NONE {
            return rest;
        }
        let cell = self.topo.elements.cell[e as usize] as usize;
        let w = super::hex::trilinear_weights(self.topo.cell_coordinates(cell, rest));
        let nodes = &self.topo.elements.nodes[e as usize];
        (0..8).map(|k| self.topo.nodes.x[nodes[k] as usize] * w[k]).sum()
    }

    /// Removes the voxels inside the inner capsule of every cutting tool, each also
    /// removing the voxels its inner capsule held along `path` — the commands of the
    /// haptic steps since the last deformation step under a multirate schedule (one per
    /// tool per step, in order), taken where the cut button was held and the tip had
    /// moved half a voxel since the last pose taken — so that an incision follows the
    /// blade between deformation steps.
    fn cut_along(&mut self, path: &[ToolCommand], commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        let limit = self.max_voxels_per_step.unwrap_or(0);
        let mut removed: Vec<usize> = Vec::new();
        let mut tips: Vec<(usize, Vec3)> = Vec::new();
        let half_voxel = self.topo.layout.smallest_side_m() * 0.5;
        let tools = self.tools.len();
        let mut moved = None;
        for (i, command) in commands.iter().enumerate() {
            let cutting = |c: &ToolCommand| self.cutting(i, c);
            // A stroke whose button is released was ended at the step's start (lead_strokes).
            if !cutting(command) {
                continue;
            }
            let moved = *moved.get_or_insert_with(|| self.moved_at_most());
            let before = removed.len();
            let mut last_taken: Option<Vec3> = None;
            // Along the path, whether the edge leads is decided from pose to pose.
            let (mut last_tip, mut leads) = (self.previous_tips[i], !self.strokes[i].pushes);
            for step in path.chunks_exact(tools.max(1)) {
                let c = &step[i];
                if !cutting(c) {
                    continue;
                }
                let tip = self.frame.to_local(&c.pose.position_m);
                leads = last_tip.and_then(|before| self.edge_leads(i, c, &(tip - before))).unwrap_or(leads);
                last_tip = Some(tip);
                if last_taken.is_none_or(|p| (p - c.pose.position_m).norm() >= half_voxel) {
                    last_taken = Some(c.pose.position_m);
                    self.voxels_in_cutting_capsule(i, c, limit, leads, &moved, &mut removed);
                }
            }
            let (tip, top, length) = self.voxels_in_cutting_capsule(i, command, limit, !self.strokes[i].pushes, &moved, &mut removed);
            if removed.len() > before {
                feedback[i].cutting = true;
                tips.push((i, tip));
            }
            self.resist_cut(i, tip, (top - tip) / length, &removed[before..], &mut feedback[i]);
        }
        if removed.is_empty() {
            return;
        }
        removed.sort_unstable();
        removed.dedup();
        for (i, tip) in tips {
            let stroke = &mut self.strokes[i];
            if !stroke.removed_any {
                stroke.removed_any = true;
                self.counters.cuts += 1;
            }
            if let Some(last) = stroke.last_tip {
                self.counters.incision_length_m += (tip - last).norm();
            }
            stroke.last_tip = Some(tip);
        }
        self.apply_removal(&removed);
    }

    /// Adds the voxels whose deformed centres tool `i`'s inner capsule holds at
    /// `command`'s pose to `removed` (up to `limit` in all), those of a material with a
    /// fracture toughness only where the edge `leads`; returns the capsule's tip, top and
    /// length (grid frame). `moved`: [`Self::moved_at_most`] now.
    fn voxels_in_cutting_capsule(&self, i: usize, command: &ToolCommand, limit: usize, leads: bool, moved: &Vec3, removed: &mut Vec<usize>) -> (Vec3, Vec3, f64) {
        let (radius, length) = self.tools[i].cutting_capsule();
        let tip = self.frame.to_local(&command.pose.position_m);
        let top = tip + self.frame.rotation.transpose() * command.pose.axis() * length;
        let capsule = Capsule { tip, top, radius, lo: tip.inf(&top) - Vec3::repeat(radius), hi: tip.sup(&top) + Vec3::repeat(radius) };
        for cell in self.cells_in_reach(&capsule.lo, &capsule.hi, moved) {
            if removed.len() >= limit {
                break;
            }
            if self.topo.cell_elements[cell].is_empty() || !self.cell_overlaps(cell, &capsule.lo, &capsule.hi) {
                continue;
            }
            for &e in &self.topo.cell_elements[cell] {
                let e = e as usize;
                let corners: [Vec3; 8] = std::array::from_fn(|n| self.topo.nodes.x[self.topo.elements.nodes[e][n] as usize]);
                let search = VoxelSearch { topo: &self.topo, element: e as u32, cell_first_voxel: self.topo.layout.cell_coords(cell).map(|c| c * self.topo.layout.side), corners, capsule: &capsule, limit, parts: &|m| leads || !self.tough(m) };
                search.descend([0; 3], self.topo.layout.side, removed);
            }
        }
        (tip, top, length)
    }

    /// The tissue's resistance to cutting tool `i`, its tip at `tip` and its axis along
    /// `axis` (grid frame), its cutting capsule having removed `removed` this step: added
    /// to its feedback as a dissipative force (super::cut_resistance).
    fn resist_cut(&mut self, i: usize, tip: Vec3, axis: Vec3, removed: &[usize], feedback: &mut ToolFeedback) {
        let spacing = self.topo.layout.spacing_m;
        let voxel_m = (spacing[0] * spacing[1] * spacing[2]).cbrt();
        let along = removed.iter().map(|&v| ((self.voxel_position(v) - tip).dot(&axis), self.materials[usize::from(self.topo.material[v]) - 1].fracture_toughness_j_per_m2));
        let removed = super::cut_resistance::removed(along);
        let motion = self.previous_tips[i].map_or(Vec3::zeros(), |before| tip - before);
        let force = self.frame.rotation * self.strokes[i].resistance.step(motion, removed, voxel_m, self.dt_s);
        feedback.force_n += force;
        feedback.resistance_n += force;
    }

    /// Removes voxels from the grid and the surface and records the topology delta.
    pub fn apply_removal(&mut self, removed: &[usize]) {
        let start = std::time::Instant::now();
        self.dynamics.before_cut(&self.topo, removed);
        let report = self.topo.remove_voxels(removed);
        if report.voxels_removed == 0 {
            return;
        }
        let topology_done = std::time::Instant::now();
        let change = self.surface.update(&self.topo, removed);
        let surface_done = std::time::Instant::now();
        self.dynamics.resize(&self.topo);
        let n = self.topo.nodes.len();
        self.backup_x.resize(n, Vec3::zeros());
        self.backup_v.resize(n, Vec3::zeros());
        let voxel_volume: f64 = self.topo.layout.spacing_m.iter().product();
        self.removed_volume_m3 += report.voxels_removed as f64 * voxel_volume;
        self.counters.removed_elements += report.voxels_removed as u64;
        self.counters.cut_updates += 1;
        self.counters.removed_triangles += change.removed_triangles.len() as u64;
        self.counters.added_triangles += change.added_triangles.len() as u64;
        self.topology_version += 1;
        // The surface is rebuilt: its vertices are not the anchored ones any more.
        self.anchors.forget_all();
        let added_vertices = change.added_vertices.iter().map(|&v| self.surface_vertex(v as usize)).collect();
        let added_triangles = change.added_triangles.iter().map(|&t| SurfaceTriangle { id: t, vertices: self.surface.triangles[t as usize] }).collect();
        let moved_vertices = change.moved_vertices;
        let delta = TopologyDelta {
            version: self.topology_version,
            removed_triangles: change.removed_triangles,
            removed_vertices: change.removed_vertices,
            added_vertices,
            added_triangles,
        };
        self.deltas.push(delta);
        let ns = |d: std::time::Duration| d.as_nanos() as u64;
        self.last_update = Some(LastUpdate {
            report,
            moved_vertices,
            topology_ns: ns(topology_done - start),
            surface_ns: ns(surface_done - topology_done),
            other_ns: ns(surface_done.elapsed()),
        });
    }

    fn surface_vertex(&self, v: usize) -> SurfaceVertex {
        let p = self.frame.to_world(&self.surface.position(&self.topo, v));
        let material = self.topo.material[self.surface.voxel[v] as usize].saturating_sub(1);
        SurfaceVertex { id: v as u32, position_m: [p.x as f32, p.y as f32, p.z as f32], material }
    }

    // ----- read access (tests, benchmarks, reports) -----

    /// How `"fidelity": "auto"` chose the level (None for a fixed level).
    pub fn fidelity_choice(&self) -> Option<&super::fidelity::FidelityChoice> {
        self.fidelity.as_ref()
    }

    pub(super) fn set_fidelity(&mut self, choice: super::fidelity::FidelityChoice) {
        self.fidelity = Some(choice);
    }

    pub fn topology(&self) -> &Topology {
        &self.topo
    }

    pub fn topology_mut(&mut self) -> &mut Topology {
        &mut self.topo
    }

    pub fn surface(&self) -> &GridSurface {
        &self.surface
    }

    pub fn frame(&self) -> &Frame {
        &self.frame
    }

    pub fn materials(&self) -> &[GridMaterial] {
        &self.materials
    }

    pub fn settings(&self) -> &SolverSettings {
        &self.settings
    }

    /// Volume of the voxels cuts removed, m³ (the paper's method loses it).
    pub fn removed_volume_m3(&self) -> f64 {
        self.removed_volume_m3
    }

    /// What the last cut update did to the grid, and how many surface vertices its
    /// re-smoothing moved.
    pub fn last_update(&self) -> Option<&LastUpdate> {
        self.last_update.as_ref()
    }

    /// How the last step's solve went.
    pub fn last_convergence(&self) -> crate::solver::pcg::Convergence {
        self.dynamics.last
    }

    /// CG iterations and relative residual of the last step.
    pub fn last_solve(&self) -> (u32, f64) {
        (self.dynamics.last.iterations, self.dynamics.last.residual)
    }

    /// Fine voxels holding material now.
    pub fn voxel_count(&self) -> usize {
        self.topo.material.iter().filter(|&&m| m != 0).count()
    }

    pub fn kinetic_energy(&self) -> f64 {
        (0..self.topo.nodes.len()).filter(|&n| self.topo.nodes.alive[n]).map(|n| 0.5 * self.topo.nodes.mass[n] * self.topo.nodes.v[n].norm_squared()).sum()
    }

    /// Centre of mass of each piece, in the scene's frame (pieces in element order).
    pub fn piece_centres(&self) -> Vec<Vec3> {
        let pieces = self.topo.element_pieces();
        let count = pieces.iter().filter(|&&p| p != NONE).map(|&p| p as usize + 1).max().unwrap_or(0);
        let mut sums = vec![(Vec3::zeros(), 0.0); count];
        let mut seen = vec![false; self.topo.nodes.len()];
        for (e, &p) in pieces.iter().enumerate() {
            if p == NONE {
                continue;
            }
            for &n in &self.topo.elements.nodes[e] {
                if !seen[n as usize] {
                    seen[n as usize] = true;
                    let m = self.topo.nodes.mass[n as usize];
                    sums[p as usize].0 += self.topo.nodes.x[n as usize] * m;
                    sums[p as usize].1 += m;
                }
            }
        }
        sums.into_iter().map(|(s, m)| self.frame.to_world(&(s / m.max(f64::MIN_POSITIVE)))).collect()
    }
}

impl BranchedGrid {
    /// What the tools leave for the next step (crate::hash::HashState): the jaws, where
    /// each tool's tip was, the vertices' friction anchors and the way each came in, the
    /// triangles held on their insides, the cut strokes with their averaged resistance,
    /// and under a multirate schedule the patch compliances kept.
    fn hash_contact_memory(&self, h: &mut StateHasher) {
        use crate::hash::HashState;
        (&self.bodies, &self.previous_tips, &self.anchors).hash_state(h);
        (&self.touches, &self.held_faces, &self.strokes).hash_state(h);
        self.compliance_cache.hash_state(h);
    }
}

impl Tissue for BranchedGrid {
    fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        BranchedGrid::jaws_half_gap_m(self, tool)
    }

    fn model_name(&self) -> &'static str {
        "branched-grid"
    }

    fn fidelity(&self) -> Option<crate::tissue::ChosenFidelity> {
        self.fidelity.as_ref().map(|f| crate::tissue::ChosenFidelity { level: f.level, deformation_every_steps: f.rate.as_ref().map(|r| r.every), summary: f.summary() })
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
        BranchedGrid::step(self, commands, feedback);
    }

    fn step_index(&self) -> u64 {
        self.step_index
    }

    fn snapshot(&self) -> SurfaceSnapshot {
        let vertices = (0..self.surface.vertex_count()).filter(|&v| self.surface.vertex_alive[v]).map(|v| self.surface_vertex(v)).collect();
        let triangles = self.surface.live_triangles().map(|(id, vertices)| SurfaceTriangle { id, vertices }).collect();
        SurfaceSnapshot { version: self.topology_version, vertices, triangles }
    }

    fn topology_version(&self) -> u64 {
        self.topology_version
    }

    fn drain_deltas(&mut self, out: &mut Vec<TopologyDelta>) {
        out.append(&mut self.deltas);
    }

    fn vertex_capacity(&self) -> usize {
        self.surface.vertex_count()
    }

    fn write_positions(&self, out: &mut [[f32; 3]]) {
        for (v, o) in out.iter_mut().enumerate().take(self.surface.vertex_count()) {
            if self.surface.vertex_alive[v] {
                let p = self.frame.to_world(&self.surface.position(&self.topo, v));
                *o = [p.x as f32, p.y as f32, p.z as f32];
            }
        }
    }

    fn vertex_alive(&self, id: u32) -> bool {
        self.surface.vertex_alive.get(id as usize).copied().unwrap_or(false)
    }

    fn state_hash(&self) -> u64 {
        let mut h = StateHasher::new();
        h.write_u64(self.step_index);
        h.write_u64(self.topology_version);
        let nodes = &self.topo.nodes;
        for n in 0..nodes.len() {
            h.write_u8(u8::from(nodes.alive[n]));
            for c in nodes.x[n].iter().chain(nodes.v[n].iter()) {
                h.write_f64(*c);
            }
        }
        for e in 0..self.topo.elements.len() {
            h.write_u8(u8::from(self.topo.elements.alive[e]));
            for &n in &self.topo.elements.nodes[e] {
                h.write_u32(n);
            }
        }
        for &m in &self.topo.material {
            h.write_u32(u32::from(m));
        }
        self.hash_contact_memory(&mut h);
        h.finish()
    }

    fn counters(&self) -> TissueCounters {
        TissueCounters {
            nodes: self.topo.nodes.alive_count() as u64,
            elements: self.topo.elements.alive_count() as u64,
            surface_vertices: self.surface.alive_vertices as u64,
            surface_triangles: self.surface.alive_triangles as u64,
            ..self.counters
        }
    }

    fn pieces(&self) -> usize {
        self.topo.pieces()
    }

    fn clone_box(&self) -> Box<dyn Tissue> {
        Box::new(self.clone())
    }
}

/// A tool's inner (cutting) capsule in the grid frame, with its bounding box.
struct Capsule {
    tip: Vec3,
    top: Vec3,
    radius: f64,
    lo: Vec3,
    hi: Vec3,
}

impl Capsule {
    fn contains(&self, p: &Vec3) -> bool {
        (p - closest_point_on_segment(p, &self.tip, &self.top).1).norm() < self.radius
    }
}

/// The voxels of one element whose deformed centres lie in a capsule, found by
/// descending the element's cell as an octree: a trilinear map sends a sub-box into the
/// convex hull of its corners' images, so the box around those images bounds the
/// deformed sub-box and a sub-box far from the capsule is skipped whole. The cost
/// follows the voxels near the blade, not the cell's volume.
struct VoxelSearch<'a> {
    topo: &'a Topology,
    element: u32,
    cell_first_voxel: [usize; 3],
    /// The element's current node positions (corner n at bits x, y, z of n).
    corners: [Vec3; 8],
    capsule: &'a Capsule,
    limit: usize,
    /// Whether the blade parts a voxel of this material (its label index).
    parts: &'a dyn Fn(u16) -> bool,
}

impl VoxelSearch<'_> {
    /// Deformed position of cell-local voxel coordinates (0..side on each axis).
    fn map(&self, v: [f64; 3]) -> Vec3 {
        let side = self.topo.layout.side as f64;
        let w = super::hex::trilinear_weights(v.map(|c| c / side));
        (0..8).map(|n| self.corners[n] * w[n]).sum()
    }

    fn descend(&self, origin: [usize; 3], size: usize, removed: &mut Vec<usize>) {
        if removed.len() >= self.limit {
            return;
        }
        let g: [usize; 3] = std::array::from_fn(|a| self.cell_first_voxel[a] + origin[a]);
        if (0..3).any(|a| g[a] >= self.topo.layout.voxels[a]) {
            return;
        }
        if size == 1 {
            let v = self.topo.layout.voxel_index(g);
            if self.topo.voxel_element[v] == self.element && (self.parts)(self.topo.material[v]) && self.capsule.contains(&self.map(origin.map(|c| c as f64 + 0.5))) {
                removed.push(v);
            }
            return;
        }
        let mut lo = Vec3::repeat(f64::INFINITY);
        let mut hi = Vec3::repeat(f64::NEG_INFINITY);
        for n in 0..8 {
            let p = self.map(std::array::from_fn(|a| (origin[a] + ((n >> a) & 1) * size) as f64));
            lo = lo.inf(&p);
            hi = hi.sup(&p);
        }
        let overlaps = (0..3).all(|a| lo[a] <= self.capsule.hi[a] && hi[a] >= self.capsule.lo[a]);
        let centre = (lo + hi) * 0.5;
        let reach = self.capsule.radius + (hi - lo).norm() * 0.5;
        if !overlaps || (centre - closest_point_on_segment(&centre, &self.capsule.tip, &self.capsule.top).1).norm() > reach {
            return;
        }
        let half = size / 2;
        for n in 0..8 {
            self.descend(std::array::from_fn(|a| origin[a] + ((n >> a) & 1) * half), half, removed);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{ModelSpec, Scene};

    /// The state hash covers what the tools leave for the next step, not only the nodes:
    /// two grids alike but for one piece of contact memory hash differently.
    #[test]
    fn the_state_hash_covers_the_tools_contact_memory() {
        let text = r#"{ "name": "block with a probe",
            "model": { "branched-grid": {
                "volume": { "box": { "size_m": [0.024, 0.012, 0.012], "voxel_size_m": 0.001 } },
                "materials": [ { "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 } ],
                "level": 2 } },
            "tools": [ { "name": "probe", "shape": { "cylinder": { "radius_m": 0.002, "length_m": 0.05 } }, "contact_stiffness_n_per_m": 300, "max_force_n": 10 } ] }"#;
        let scene = Scene::from_json_str(text, "block", None).unwrap();
        let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
        let grid = super::super::build::build_from_scene(&scene, spec).unwrap();
        let hash = grid.state_hash();
        assert_eq!(grid.clone().state_hash(), hash, "a copy hashes the same");
        let edits: [(&str, fn(&mut BranchedGrid)); 3] = [
            ("where a tool's tip was", |g| g.previous_tips[0] = Some(Vec3::x())),
            ("a cut stroke's blade pushing", |g| g.strokes[0].pushes = true),
            ("a vertex's way in", |g| g.touches[0] = Some(super::super::hold::Touch { tool: 0, normal_in_tool: Vec3::z(), step: 1 })),
        ];
        for (what, edit) in edits {
            let mut other = grid.clone();
            edit(&mut other);
            assert_ne!(other.state_hash(), hash, "{what}");
        }
    }

    /// A 24 × 12 × 12 mm block of 1 mm voxels at level 2 (6 × 3 × 3 cells), free.
    fn block() -> BranchedGrid {
        let text = r#"{ "name": "block",
            "model": { "branched-grid": {
                "volume": { "box": { "size_m": [0.024, 0.012, 0.012], "voxel_size_m": 0.001 } },
                "materials": [ { "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 } ],
                "level": 2 } },
            "tools": [] }"#;
        let scene = Scene::from_json_str(text, "block", None).unwrap();
        let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
        super::super::build::build_from_scene(&scene, spec).unwrap()
    }

    /// Every cell whose current box overlaps [lo, hi], by a scan of them all.
    fn scanned(g: &BranchedGrid, lo: &Vec3, hi: &Vec3) -> Vec<usize> {
        (0..g.topo.layout.cell_count()).filter(|&c| !g.topo.cell_elements[c].is_empty() && g.cell_overlaps(c, lo, hi)).collect()
    }

    fn windowed(g: &BranchedGrid, lo: &Vec3, hi: &Vec3) -> Vec<usize> {
        g.cells_in_reach(lo, hi, &g.moved_at_most()).filter(|&c| !g.topo.cell_elements[c].is_empty() && g.cell_overlaps(c, lo, hi)).collect()
    }

    #[test]
    fn the_cells_in_a_tools_reach_are_those_a_scan_of_every_cell_finds_in_order() {
        let mut g = block();
        // Bent and stretched: each node moved by up to 7 mm, more than a cell (4 mm).
        for (x, rest) in g.topo.nodes.x.iter_mut().zip(&g.topo.nodes.rest) {
            let s = rest.x / 0.024;
            *x = rest + Vec3::new(0.3 * rest.x, 0.007 * (std::f64::consts::PI * s).sin(), -0.002 * s);
        }
        let mut found = 0;
        for k in 0..60 {
            let t = k as f64;
            let centre = Vec3::new(-0.004 + 0.0006 * t, 0.006 + 0.004 * (0.7 * t).sin(), 0.006 + 0.005 * (1.3 * t).cos());
            let half = Vec3::new(0.0005, 0.001, 0.0002) * (1.0 + (t % 5.0));
            let (lo, hi) = (centre - half, centre + half);
            let all = scanned(&g, &lo, &hi);
            assert_eq!(windowed(&g, &lo, &hi), all, "box {lo:?}–{hi:?}");
            found += all.len();
        }
        assert!(found > 60, "the boxes reach the body ({found} cells found)");
        let (lo, hi) = (Vec3::repeat(-1.0), Vec3::repeat(1.0));
        assert_eq!(windowed(&g, &lo, &hi).len(), 6 * 3 * 3, "a box around everything reaches every cell");
        // A position that is not finite: every cell is searched.
        g.topo.nodes.x[0] = Vec3::new(f64::NAN, 0.0, 0.0);
        assert_eq!(g.cells_in_reach(&Vec3::zeros(), &Vec3::zeros(), &g.moved_at_most()).count(), 6 * 3 * 3);
    }
}
