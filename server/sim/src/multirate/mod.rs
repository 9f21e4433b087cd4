//! Multirate haptics: a contact loop at the haptic rate against the compliance of a
//! deformation model stepped at a lower rate on a thread of its own.
//!
//! - [`patch`]: what a deformation step publishes per tool (its contact patch: vertices,
//!   positions and compliance) and the haptic loop's contact solve against it.
//! - [`Multirate`]: the schedule behind the session's [`Tissue`] interface.
//!
//! The schedule, by step index (haptic steps of the scene's `time_step_s`, deformation
//! every N of them):
//!
//! ```text
//! haptic step   0 ... N-1 | N ... 2N-1 | 2N ...
//! deformation   [ job 0  ]  [ job N   ]  [ job 2N ...        (on the worker thread)
//! job k takes   the tools' commands at step k; its result is swapped in at step k + N
//! haptic loop   renders against the patches job k-N published (from step k on)
//! ```
//!
//! The deformation model is the branched grid with a step of N haptic steps, its
//! contact with the tools solved implicitly in its own step with the tools where the
//! newest commands put them (as SOFA's simulation does; its haptic loop only renders).
//! Handing the haptic loop's forces to the deformation step as constant loads instead
//! was tried: an explicit coupling of the stiff penalty, it rang in a limit cycle of
//! ±0.1 N around a probe held still (docs/branched-grid.md). A job's result is taken at
//! its step index whatever the clock says (a late one is waited for and counted), so a
//! session gives the same state hash in real time, in lockstep and in replay. When a
//! new patch arrives the force it gives differs from the old one's at the same pose: the
//! difference is rendered and faded out over the next N steps, so the force a device
//! feels has no step (docs/branched-grid.md, "Multirate haptics").

pub mod patch;

use std::cell::RefCell;
use std::sync::Arc;

use crate::grid::BranchedGrid;
use crate::hash::StateHasher;
use crate::math::Vec3;
use crate::quantity::TimeStepS;
use crate::scene::{FidelitySpec, ModelSpec, MultirateSpec, Scene, SceneError, ScheduleSpec};
use crate::solver::background::Background;
use crate::surface::{SurfaceSnapshot, SurfaceTriangle, SurfaceVertex, TopologyDelta};
use crate::tissue::{ChosenFidelity, Tissue, TissueCounters};
use crate::grid::hold::Plate;
use crate::tool::bodies::{Bodies, Pinch};
use crate::tool::{Section, ToolCommand, ToolFeedback, ToolShape};
use patch::{Capsule, ContactPatch, MAX_PATCH_VERTICES, PatchContact};

/// The fastest a tool is assumed to move, m/s: a patch reaches this far beyond the
/// tool's radius for the two deformation periods it is used over after it was chosen.
const TOOL_SPEED_M_PER_S: f64 = 0.2;

/// How far a forceps' jaws may move between two deformation steps, in voxels (the
/// smallest side): the haptic loop moves them at that pace (crate::tool::bodies). The
/// deformation meets the jaws only at its steps, and jaws that jumped far between two
/// of them passed the ridge of tissue that rises between them instead of pushing it
/// aside, and ended closed inside the tissue, holding nothing. Measured with jaws
/// 4 × 3 mm on 2 mm voxels, deformation every 33 ms, pressed 6 mm in (single-rate: 0.90 N
/// open, 0.43 N closed, 0.37 N reopened): jumps of 1.5 mm per deformation step closed
/// at 0 N, of 0.5 mm closed at 0.42 N but reopened at 0 N, of 0.2 mm (this pace) closed
/// at 0.44 N and reopened at 0.38–0.43 N.
pub const JAW_TRAVEL_PER_DEFORMATION_VOXELS: f64 = 0.1;

/// How far beyond a tool's radius its patch reaches for a deformation step of
/// `period_s`, m: two voxels, and the distance a tool at [`TOOL_SPEED_M_PER_S`] covers
/// in the two periods a patch is used over after it was chosen.
pub fn patch_margin_m(grid: &BranchedGrid, period_s: f64) -> f64 {
    let voxel = grid.topology().layout.spacing_m.iter().copied().fold(0.0, f64::max);
    2.0 * voxel + TOOL_SPEED_M_PER_S * 2.0 * period_s
}

/// The branched grid under a multirate schedule.
pub struct Multirate {
    /// The haptic step, s, and the haptic steps per deformation step.
    dt_s: f64,
    every: u64,
    /// The scene's tools, and the bodies the tissue meets (forceps as their two jaws,
    /// crate::tool::bodies; a jaw's section as the jaws are now) with the split between
    /// them (None where they are the same). The haptic loop renders, and the deformation
    /// steps, per body: the per-tool lists below are per body.
    scene_tools: Vec<ToolShape>,
    tools: Vec<ToolShape>,
    bodies: Option<Bodies>,
    /// Per body: its pinch this step (a jaw stopped on what it pinches), for the next job.
    pinches: Vec<Option<Pinch>>,
    step_index: u64,
    /// Per tool: the patch the haptic loop renders against now.
    patches: Vec<ContactPatch>,
    /// Per tool: the force and torque on the tool to add while they fade (the old
    /// patch's minus the new one's when it arrived), and the steps left of the N they
    /// fade over.
    fading: Vec<(Vec3, Vec3)>,
    fade_left: u64,
    /// The deformation model's state as the last job left it.
    published: Published,
    /// Per tool: the last deformation step's cut (whether it removed tissue, its
    /// resistance), rendered until the next one.
    cut_feedback: Vec<(bool, Vec3)>,
    deltas: Vec<TopologyDelta>,
    /// The commands of this period's haptic steps (one per tool per step), handed to the
    /// next job to cut along.
    path: Vec<ToolCommand>,
    /// Hash of the pending job's commands (its grid is the published state).
    pending_inputs: u64,
    deformer: RefCell<Deformer>,
    /// The haptic loop's own counts: commands whose pose was not finite, forces clamped.
    rejected_poses: u64,
    force_clamps: u64,
    fidelity: Option<ChosenFidelity>,
}

/// A deformation step's inputs, outputs and the model it steps: one box that goes to
/// the worker and comes back, its buffers reused.
#[derive(Clone)]
struct Job {
    grid: BranchedGrid,
    commands: Vec<ToolCommand>,
    /// The bodies' shapes and pinches at the job's step (a forceps' jaws open or
    /// closed, pinching or not: crate::tool::bodies).
    shapes: Vec<ToolShape>,
    pinches: Vec<Option<Pinch>>,
    /// The haptic steps' commands over the period before (one per tool per step): the
    /// deformation step cuts along them.
    path: Vec<ToolCommand>,
    patches: Vec<ContactPatch>,
    feedback: Vec<ToolFeedback>,
    published: Published,
    /// How far beyond a tool's radius its patch reaches, m ([`patch_margin_m`]).
    margin_m: f64,
}

impl Job {
    fn run(mut self: Box<Self>) -> Box<Self> {
        let started = std::time::Instant::now();
        let job = &mut *self;
        job.grid.deformation_step(&job.commands, &job.shapes, &job.pinches, &job.path, &mut job.patches, job.margin_m, &mut job.feedback);
        // What each patch's own contact gives where the deformation had the tool: the
        // haptic loop balances that, not the deformation's force (patch::ContactPatch's
        // `balanced`).
        for ((patch, shape), command) in job.patches.iter_mut().zip(&job.shapes).zip(&job.commands) {
            let then = capsule(shape, command, patch.blade_pushes);
            patch.balance_at(then.as_ref());
        }
        job.published.refresh(&mut job.grid);
        job.published.took_ns = started.elapsed().as_nanos() as u64;
        self
    }
}

/// What the session reads of the deformation model between its steps.
#[derive(Clone, Default)]
struct Published {
    /// Per vertex slot: world position (f32, as viewers get it) and whether it lives.
    positions: Vec<[f32; 3]>,
    alive: Vec<bool>,
    /// Per vertex slot: its material index; and the live triangles. Rebuilt when the
    /// topology changed.
    materials: Arc<Vec<u16>>,
    triangles: Arc<Vec<SurfaceTriangle>>,
    topology_version: Option<u64>,
    pieces: usize,
    deltas: Vec<TopologyDelta>,
    counters: TissueCounters,
    grid_hash: u64,
    /// Per body: the contacts its inner flat pressed in the deformation step, where it
    /// pinched (grid::BranchedGrid::inner_flat_contacts): the haptic loop's jaws let go
    /// of what slipped out from between them by it (crate::tool::bodies::Bodies::pinch).
    inner_flat_contacts: Vec<Option<u32>>,
    /// How long the job took, ns (its step, compliance solves and this copy).
    took_ns: u64,
}

impl Published {
    fn refresh(&mut self, grid: &mut BranchedGrid) {
        let capacity = grid.vertex_capacity();
        self.positions.resize(capacity, [0.0; 3]);
        grid.write_positions(&mut self.positions);
        self.alive.clear();
        self.alive.extend((0..capacity).map(|v| grid.vertex_alive(v as u32)));
        grid.drain_deltas(&mut self.deltas);
        self.counters = grid.counters();
        self.grid_hash = grid.state_hash();
        self.inner_flat_contacts.clear();
        self.inner_flat_contacts.extend_from_slice(grid.inner_flat_contacts());
        if self.topology_version != Some(grid.topology_version()) {
            let snapshot = grid.snapshot();
            let mut materials = vec![0u16; capacity];
            for v in &snapshot.vertices {
                materials[v.id as usize] = v.material;
            }
            self.materials = Arc::new(materials);
            self.triangles = Arc::new(snapshot.triangles);
            self.topology_version = Some(grid.topology_version());
            self.pieces = grid.pieces();
        }
    }
}

/// Where the deformation job is: out with the worker thread, or home (finished early,
/// or run here when no thread could be started).
struct Deformer {
    worker: Option<Background<Box<Job>, Box<Job>>>,
    /// A finished job, and the step its result is due at.
    home: Option<Box<Job>>,
    due: u64,
    /// Run jobs here, at submission (tests compare this with the worker).
    inline: bool,
    waits: u64,
}

impl Deformer {
    fn submit(&mut self, job: Box<Job>, due: u64) {
        self.due = due;
        if !self.inline && self.worker.is_none() {
            self.worker = Background::new("multirate-deformation", Job::run).ok();
        }
        let refused = match self.worker.as_mut() {
            Some(worker) if !self.inline => worker.submit(job, due).err(),
            _ => Some(job),
        };
        // Inline, or no worker thread could be started: run here, due as planned.
        if let Some(job) = refused {
            self.home = Some(job.run());
        }
    }

    /// The job due at `step` (waiting for it if it is not finished).
    fn take_due(&mut self, step: u64) -> Box<Job> {
        debug_assert_eq!(self.due, step);
        if let Some(job) = self.home.take() {
            return job;
        }
        let worker = self.worker.as_mut().expect("a worker has the job");
        let before = worker.waits;
        let job = worker.take_if_due(step).expect("the multirate deformation worker died (its panic is above)");
        self.waits += worker.waits - before;
        job
    }

    /// The pending job, home (waiting for the worker to finish it).
    fn fetch_home(&mut self) -> &Job {
        if self.home.is_none() {
            let worker = self.worker.as_mut().expect("a worker has the job");
            self.home = Some(worker.take_early().expect("the multirate deformation worker died (its panic is above)"));
        }
        self.home.as_deref().expect("the job is home")
    }
}

/// Builds a branched-grid scene with a multirate schedule: the grid with a step of
/// `deformation_every_steps` haptic steps (its load-time checks run at that step), under
/// the schedule. Under `"fidelity": "auto"` that is the longest period allowed: the level
/// is fitted to it, and the period then shortened as far as the level allows.
pub fn build_from_scene(scene: &Scene, schedule: &MultirateSpec) -> Result<Multirate, SceneError> {
    let every = schedule.deformation_every_steps.get();
    let dt = scene.time_step_s.get();
    let field = "model.branched-grid.schedule.multirate.deformation_every_steps";
    let deformation_dt = TimeStepS::new(dt * f64::from(every))
        .map_err(|e| SceneError::new(&scene.origin, field, format!("{every} haptic steps of {dt} s make a deformation step out of range: {e}")))?;
    let mut deformation = scene.clone();
    deformation.time_step_s = deformation_dt;
    let ModelSpec::BranchedGrid(grid_spec) = &mut deformation.model else { unreachable!("a branched-grid scene") };
    grid_spec.schedule = ScheduleSpec::SingleRate;
    let grid_spec = grid_spec.clone();
    let (grid, every) = match grid_spec.fidelity {
        // The deformation's level is fitted to its period, not to the haptic step, and
        // its rate to the level.
        FidelitySpec::Auto => {
            let mut haptic = deformation;
            haptic.time_step_s = scene.time_step_s;
            crate::grid::fidelity::build_auto_multirate(&haptic, &grid_spec, every)?
        }
        FidelitySpec::Fixed => (crate::grid::build_from_scene(&deformation, &grid_spec)?, every),
    };
    refuse_thin_jaws(scene, &grid, every)?;
    Ok(Multirate::new(grid, dt, every, false))
}

/// Forceps whose jaws fit between the grid's vertices are held by the insides of its
/// triangles (crate::grid::model's face contact), whose points a deformation step of
/// tens of milliseconds does not hold steadily: measured with 2 × 1 mm jaws at
/// 20,000 N/m on 2 mm voxels, deformation every 33 ms, their forces swung between −170
/// and +630 N and a third of the solves stopped at the cap. Refused, naming the field.
fn refuse_thin_jaws(scene: &Scene, grid: &BranchedGrid, every: u32) -> Result<(), SceneError> {
    for (i, tool) in grid.tools().iter().enumerate() {
        let Section::Jaws { half_thickness_m, .. } = tool.section else { continue };
        let held_from = grid.held_by_vertices_from_m();
        if half_thickness_m < held_from {
            return Err(SceneError::new(
                &scene.origin,
                format!("tools[{i}].shape.forceps.thickness_m"),
                format!(
                    "jaws {:.2} mm thick fit between this grid's surface vertices ({:.2} mm voxels), where the insides of its triangles hold them, and a multirate deformation step ({every} haptic steps) does not hold those steadily: under a multirate schedule forceps' jaws must be at least {:.2} mm thick here (the diagonal of a voxel's largest face); or use \"schedule\": \"single-rate\"",
                    2.0 * half_thickness_m * 1e3,
                    grid.topology().layout.smallest_side_m() * 1e3,
                    2.0 * held_from * 1e3
                ),
            ));
        }
    }
    Ok(())
}

impl Multirate {
    /// The grid, built with a step of `every` haptic steps of `dt_s`, under the schedule.
    /// `inline`: run the deformation on the calling thread (same results, for tests).
    pub fn new(mut grid: BranchedGrid, dt_s: f64, every: u32, inline: bool) -> Self {
        let every = u64::from(every.max(1));
        let scene_tools = grid.tools().to_vec();
        // The grid's own bodies, as it expands them.
        let (tools, mut bodies) = crate::tool::bodies::expand(&scene_tools);
        if let Some(bodies) = bodies.as_mut() {
            bodies.pace_jaws_for(every as f64 * dt_s, JAW_TRAVEL_PER_DEFORMATION_VOXELS * grid.topology().layout.smallest_side_m());
            if let Some(floor) = grid.pinch_floor_m() {
                bodies.pinch_no_closer_than(floor);
            }
        }
        let count = tools.len();
        let margin_m = patch_margin_m(&grid, every as f64 * dt_s);
        let mut published = Published::default();
        published.refresh(&mut grid);
        let fidelity = Tissue::fidelity(&grid);
        let job = Box::new(Job {
            grid,
            commands: vec![ToolCommand::default(); count],
            shapes: tools.clone(),
            pinches: vec![None; count],
            path: Vec::with_capacity(count * every as usize),
            patches: vec![ContactPatch::default(); count],
            feedback: vec![ToolFeedback::default(); count],
            published: published.clone(),
            margin_m,
        });
        let patches = (0..count)
            .map(|_| ContactPatch { vertices: Vec::with_capacity(MAX_PATCH_VERTICES), positions: Vec::with_capacity(MAX_PATCH_VERTICES), anchors: Vec::with_capacity(MAX_PATCH_VERTICES), ..ContactPatch::default() })
            .collect();
        Multirate {
            dt_s,
            every,
            scene_tools,
            tools,
            bodies,
            pinches: vec![None; count],
            step_index: 0,
            patches,
            fading: vec![(Vec3::zeros(), Vec3::zeros()); count],
            fade_left: 0,
            published,
            cut_feedback: vec![(false, Vec3::zeros()); count],
            deltas: Vec::new(),
            path: Vec::with_capacity(count * every as usize),
            pending_inputs: 0,
            deformer: RefCell::new(Deformer { worker: None, home: Some(job), due: 0, inline, waits: 0 }),
            rejected_poses: 0,
            force_clamps: 0,
            fidelity,
        }
    }

    /// How long the deformation job whose results are current took, ns (its step, its
    /// patches' compliance solves, publishing).
    pub fn last_deformation_ns(&self) -> u64 {
        self.published.took_ns
    }

    /// Haptic steps per deformation step.
    pub fn deformation_every(&self) -> u32 {
        self.every as u32
    }

    /// Steps that waited for a deformation job past its due step.
    pub fn deformation_waits(&self) -> u64 {
        self.deformer.borrow().waits
    }

    /// Body `i`'s patch now (the tools', forceps as their two jaws: crate::tool::bodies).
    pub fn patch(&self, i: usize) -> &ContactPatch {
        &self.patches[i]
    }

    /// Scene tool `tool`'s jaws' half gap as the haptic loop has them, m: half the
    /// distance between their inner flats (0 closed; None for a tool without jaws).
    pub fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        self.bodies.as_ref()?.jaws_half_gap_m(tool)
    }

    /// The deformation model as the last finished job left it (waits for the pending
    /// job: for tests and reports, not for the haptic loop).
    pub fn with_grid<R>(&self, read: impl FnOnce(&BranchedGrid) -> R) -> R {
        read(&self.deformer.borrow_mut().fetch_home().grid)
    }

    /// At a deformation boundary: takes the finished job (from step `k − N`), makes its
    /// patches current (the force's jump fading out), and hands the next job over with
    /// the newest commands.
    fn exchange(&mut self, commands: &[ToolCommand]) {
        let k = self.step_index;
        let deformer = self.deformer.get_mut();
        let mut job = if k == 0 { deformer.home.take().expect("the first job is home") } else { deformer.take_due(k) };
        if k > 0 {
            std::mem::swap(&mut self.patches, &mut job.patches);
            std::mem::swap(&mut self.published, &mut job.published);
            self.deltas.append(&mut self.published.deltas);
            for (i, (fb, command)) in job.feedback.iter().zip(commands).enumerate() {
                self.cut_feedback[i] = (fb.cutting, fb.resistance_n);
                // The old patch (now in `job`) at this step's pose; `render` takes the new
                // one's force off it (the step's own solve), and the difference fades out
                // over the N steps to the next arrival (the last one has faded by now).
                let old = match capsule(&self.tools[i], command, self.patches[i].blade_pushes) {
                    Some(tool) => {
                        // The new patch's friction anchors are the deformation's, on the
                        // tool as it was N steps ago: brought to this step's pose first
                        // (those stretched past the static cone slide), so that the force
                        // faded from is the one rendered from now on.
                        let relaxed = self.patches[i].solve(&tool);
                        self.patches[i].commit(&tool, &relaxed);
                        job.patches[i].solve(&tool)
                    }
                    None => PatchContact::default(),
                };
                self.fading[i] = (old.force_n, old.torque_nm);
            }
            self.fade_left = self.every;
        }
        job.commands.copy_from_slice(commands);
        for (shape, tool) in job.shapes.iter_mut().zip(&self.tools) {
            shape.section = tool.section;
        }
        job.pinches.copy_from_slice(&self.pinches);
        std::mem::swap(&mut job.path, &mut self.path);
        self.path.clear();
        let mut h = StateHasher::new();
        for c in commands.iter().chain(&job.path) {
            hash_command(&mut h, c);
        }
        self.pending_inputs = h.finish();
        deformer.submit(job, k + self.every);
    }

    /// A haptic step with the bodies' `commands`: at a deformation boundary the jobs are
    /// exchanged, then each body's contact is rendered.
    fn step_bodies(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        debug_assert_eq!(commands.len(), self.tools.len());
        if self.step_index.is_multiple_of(self.every) {
            self.exchange(commands);
        }
        self.render(commands, feedback);
        self.path.extend_from_slice(commands);
    }

    /// The haptic step: each tool's contact solved against its patch.
    fn render(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        let fade = if self.fade_left > 0 { self.fade_left as f64 / self.every as f64 } else { 0.0 };
        for (i, (command, fb)) in commands.iter().zip(feedback.iter_mut()).enumerate() {
            *fb = ToolFeedback::default();
            if command.active && !command.pose.is_finite() {
                self.rejected_poses += 1;
            }
            let Some(tool) = capsule(&self.tools[i], command, self.patches[i].blade_pushes) else {
                // Lifted away: nothing stays stuck to it.
                self.patches[i].anchors.iter_mut().for_each(|a| *a = None);
                continue;
            };
            let contact = self.patches[i].solve(&tool);
            self.patches[i].commit(&tool, &contact);
            if self.fade_left == self.every {
                // A new patch arrived this step: the fading term is the old patch's force
                // until its difference from this one's is taken.
                let (old_force, old_torque) = self.fading[i];
                self.fading[i] = (old_force - contact.force_n, old_torque - contact.torque_nm);
            }
            let (force, torque) = self.fading[i];
            fb.force_n = contact.force_n + force * fade;
            fb.torque_nm = contact.torque_nm + torque * fade;
            fb.contacts = contact.contacts;
            let (cutting, resistance) = self.cut_feedback[i];
            if self.tools[i].cuts(command) {
                fb.cutting = cutting;
                fb.force_n += resistance;
                fb.resistance_n = resistance;
            }
            fb.clamp_force(self.tools[i].max_force_n);
            if fb.force_clamped {
                self.force_clamps += 1;
            }
        }
        self.fade_left = self.fade_left.saturating_sub(1);
    }
}

/// A tool's outer solid at its commanded pose (None: away or not finite): a capsule, or
/// a blade's plate; a blade whose flat or back leads into tough tissue (`blade_pushes`)
/// holds it off as a probe.
fn capsule(tool: &ToolShape, command: &ToolCommand, blade_pushes: bool) -> Option<Capsule> {
    if !command.active || !command.pose.is_finite() {
        return None;
    }
    let tip = command.pose.position_m;
    let rotation = *command.pose.orientation.to_rotation_matrix().matrix();
    Some(Capsule {
        tip,
        top: tip + command.pose.axis() * tool.length_m,
        radius_m: tool.radius_m,
        stiffness_n_per_m: tool.contact_stiffness_n_per_m,
        rotation,
        // As the deformation's own contact: a blade cutting is not held off the tissue.
        holds: !tool.cuts(command) || blade_pushes,
        max_depth_m: tool.hold_max_depth_m(),
        // A forceps' jaw comes as a plate of its own (crate::tool::bodies).
        plate: Plate::of_tool(tool, &rotation),
    })
}

fn hash_command(h: &mut StateHasher, c: &ToolCommand) {
    h.write_u8(u8::from(c.active) | (u8::from(c.cut) << 1));
    for x in c.pose.position_m.iter() {
        h.write_f64(*x);
    }
    for x in c.pose.orientation.coords.iter() {
        h.write_f64(*x);
    }
    // Only where given, so that commands without a squeeze hash as before it existed.
    if let Some(grip) = c.grip {
        h.write_f64(grip);
    }
}

impl Tissue for Multirate {
    fn jaws_half_gap_m(&self, tool: usize) -> Option<f64> {
        Multirate::jaws_half_gap_m(self, tool)
    }

    fn model_name(&self) -> &'static str {
        "branched-grid"
    }

    fn fidelity(&self) -> Option<ChosenFidelity> {
        self.fidelity.as_ref().map(|chosen| ChosenFidelity {
            level: chosen.level,
            deformation_every_steps: Some(self.every as u32),
            summary: format!("{}; multirate: haptics every {:.1} ms, the deformation at that level every {} steps ({:.0} Hz)", chosen.summary, self.dt_s * 1e3, self.every, 1.0 / (self.dt_s * self.every as f64)),
        })
    }

    fn time_step_s(&self) -> f64 {
        self.dt_s
    }

    fn deformation_rate_hz(&self) -> Option<f64> {
        Some(1.0 / (self.dt_s * self.every as f64))
    }

    // The session's tools are the scene's; `self.tools` are the bodies they move (forceps
    // as two jaws).
    #[allow(clippy::misnamed_getters)]
    fn tools(&self) -> &[ToolShape] {
        &self.scene_tools
    }

    fn step(&mut self, commands: &[ToolCommand], feedback: &mut [ToolFeedback]) {
        crate::tool::assert_one_per_tool(commands, feedback, &self.scene_tools);
        // Taken out for the step and put back: no allocation.
        match self.bodies.take() {
            None => self.step_bodies(commands, feedback),
            Some(mut bodies) => {
                bodies.split(commands, &self.scene_tools, &mut self.tools, self.dt_s);
                bodies.pinches(&self.scene_tools, &mut self.pinches);
                self.step_bodies(&bodies.commands, &mut bodies.feedback);
                // Closing jaws stop on what pushes them back with the grip, as in the
                // grid's own step (crate::grid::model): the rendered force is the squeeze.
                // They let go of what slipped out by the last deformation step's contacts
                // under their inner flats (unknown until a step has pinched with them).
                bodies.pinch(&self.scene_tools, &self.published.inner_flat_contacts, self.dt_s);
                self.force_clamps += bodies.gather(&self.scene_tools, feedback);
                self.bodies = Some(bodies);
            }
        }
        self.step_index += 1;
    }

    fn step_index(&self) -> u64 {
        self.step_index
    }

    fn snapshot(&self) -> SurfaceSnapshot {
        let p = &self.published;
        let vertices = (0..p.positions.len()).filter(|&v| p.alive[v]).map(|v| SurfaceVertex { id: v as u32, position_m: p.positions[v], material: p.materials.get(v).copied().unwrap_or(0) }).collect();
        SurfaceSnapshot { version: p.topology_version.unwrap_or(0), vertices, triangles: p.triangles.as_ref().clone() }
    }

    fn topology_version(&self) -> u64 {
        self.published.topology_version.unwrap_or(0)
    }

    fn drain_deltas(&mut self, out: &mut Vec<TopologyDelta>) {
        out.append(&mut self.deltas);
    }

    fn vertex_capacity(&self) -> usize {
        self.published.positions.len()
    }

    fn write_positions(&self, out: &mut [[f32; 3]]) {
        let p = &self.published;
        for ((o, position), alive) in out.iter_mut().zip(&p.positions).zip(&p.alive) {
            if *alive {
                *o = *position;
            }
        }
    }

    fn vertex_alive(&self, id: u32) -> bool {
        self.published.alive.get(id as usize).copied().unwrap_or(false)
    }

    fn state_hash(&self) -> u64 {
        let mut h = StateHasher::new();
        h.write_u64(self.step_index);
        h.write_u64(self.published.grid_hash);
        h.write_u64(self.pending_inputs);
        for c in &self.path {
            hash_command(&mut h, c);
        }
        for (force, torque) in &self.fading {
            force.iter().chain(torque.iter()).for_each(|c| h.write_f64(*c));
        }
        h.write_u64(self.fade_left);
        // The haptic loop's jaws (the deformation's memory is in its grid's hash).
        crate::hash::HashState::hash_state(&self.bodies, &mut h);
        h.finish()
    }

    fn counters(&self) -> TissueCounters {
        let waits = self.deformer.borrow().waits;
        TissueCounters {
            rejected_poses: self.rejected_poses,
            // The forces rendered are the haptic loop's; the deformation step's own
            // contact forces are never sent to a device.
            force_clamps: self.force_clamps,
            solver_waits: self.published.counters.solver_waits + waits,
            ..self.published.counters
        }
    }

    fn pieces(&self) -> usize {
        self.published.pieces
    }

    fn clone_box(&self) -> Box<dyn Tissue> {
        let mut deformer = self.deformer.borrow_mut();
        let job = Box::new(deformer.fetch_home().clone());
        let copy = Deformer { worker: None, home: Some(job), due: deformer.due, inline: deformer.inline, waits: deformer.waits };
        Box::new(Multirate {
            dt_s: self.dt_s,
            every: self.every,
            scene_tools: self.scene_tools.clone(),
            tools: self.tools.clone(),
            bodies: self.bodies.clone(),
            pinches: self.pinches.clone(),
            step_index: self.step_index,
            patches: self.patches.clone(),
            fading: self.fading.clone(),
            fade_left: self.fade_left,
            published: self.published.clone(),
            cut_feedback: self.cut_feedback.clone(),
            deltas: self.deltas.clone(),
            path: {
                let mut path = Vec::with_capacity(self.path.capacity());
                path.extend_from_slice(&self.path);
                path
            },
            pending_inputs: self.pending_inputs,
            deformer: RefCell::new(copy),
            rejected_poses: self.rejected_poses,
            force_clamps: self.force_clamps,
            fidelity: self.fidelity.clone(),
        })
    }
}
