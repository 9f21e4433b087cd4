//! Scene files: what a session simulates, and nothing more.
//!
//! A scene names its tissue model with the model's geometry source, material,
//! boundary conditions, integrator and optional effects (gravity, residual stress,
//! cutting), and its tools. What a scene does not name is not built or computed.
//! Unknown keys and out-of-range values are refused with the JSON path, the unit and
//! the allowed range (see [`load`]). Units are SI and written in every key.
//!
//! Choices are externally tagged objects, e.g. `"geometry": {"patch": {...}}`: that
//! keeps the JSON path of every error exact.

mod footprint;
mod load;

pub use footprint::Footprint;
pub use load::{SceneError, bundled_scene_names, data_dir, json_schema, resolve_bundled_scene, resolve_scene_path};

use std::path::PathBuf;

use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

use crate::quantity::*;

/// A complete scene.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct Scene {
    /// Short name shown in session lists.
    pub name: String,
    /// One or two sentences for people choosing a scene.
    #[serde(default)]
    pub description: String,
    /// Physics step in seconds (0.001 = 1 kHz).
    #[serde(default = "default_time_step")]
    pub time_step_s: TimeStepS,
    /// Gravity in m/s². Absent: no gravity term is built.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub gravity_m_per_s2: Option<[AccelerationMPerS2; 3]>,
    /// The tissue model.
    pub model: ModelSpec,
    /// Tools the session drives; commands address them by index in this list.
    #[serde(default)]
    pub tools: Vec<ToolSpec>,
    /// The training task: a planned incision, no-go regions, a force limit
    /// (docs/assessment.md). Absent: motion and force metrics only.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub task: Option<crate::assessment::TaskSpec>,
    /// Directory that relative file paths in this scene are resolved against (the scene
    /// file's directory); not part of the JSON.
    #[serde(skip)]
    #[schemars(skip)]
    pub base_dir: Option<PathBuf>,
    /// Where the scene came from (a file path or "inline scene"), for error messages;
    /// not part of the JSON.
    #[serde(skip)]
    #[schemars(skip)]
    pub origin: String,
}

impl Scene {
    /// The scene's task checked against its tools (checked already when the scene was
    /// read, so this cannot fail for a scene that loaded).
    pub fn task(&self) -> crate::assessment::Task {
        let tools = crate::tool::tool_shapes(self);
        match &self.task {
            Some(spec) => spec.compile(&tools, &self.origin).unwrap_or_else(|e| panic!("a loaded scene's task is valid: {e}")),
            None => crate::assessment::Task::none(&tools),
        }
    }

    /// The scene with its branched grid at coarsening level `level` (other models as
    /// they are). Panics on a level outside [`GridLevel`]'s range: callers pass levels
    /// they chose, not input.
    pub fn with_grid_level(&self, level: u32) -> Scene {
        let mut scene = self.clone();
        if let ModelSpec::BranchedGrid(spec) = &mut scene.model {
            spec.level = GridLevel::new(level).unwrap_or_else(|e| panic!("{e}"));
        }
        scene
    }
}

fn default_time_step() -> TimeStepS {
    TimeStepS(0.001)
}

/// The tissue model and its settings.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum ModelSpec {
    /// Surface mass-spring skin with residual stress and three-stage cutting.
    Msm(MsmSpec),
    /// Volumetric Dynamic Branched Grid from a label volume: coarse corotational
    /// hexahedra with condensed stiffness, cutting by voxel removal.
    BranchedGrid(BranchedGridSpec),
}

/// Settings of the mass-spring skin model.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MsmSpec {
    pub geometry: SurfaceGeometry,
    pub material: MembraneMaterialSpec,
    /// Residual strain εr of living skin: springs rest at their imported length / (1 + εr).
    #[serde(default = "default_residual_strain")]
    pub residual_strain: ResidualStrain,
    #[serde(default)]
    pub damping: DampingSpec,
    /// Boundary conditions: nodes held fixed (on some or all axes).
    #[serde(default)]
    pub fixed: Vec<FixedSpec>,
    pub integrator: IntegratorSpec,
    /// The tissue under the skin (docs/tool-tissue.md). Absent: the membrane spans empty
    /// space, as in the paper.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub foundation: Option<FoundationSpec>,
    /// Cutting settings. Absent: the scene cannot be cut and no cutting machinery is built.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cutting: Option<CuttingSpec>,
}

/// An elastic, viscous foundation under the skin (the subcutaneous layer): per unit area,
/// a normal stiffness pulling each node back to its reference position along the
/// surface's reference normal, and drag against the underlying tissue, normal and
/// tangential.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FoundationSpec {
    /// Normal stiffness per unit area (pressure per deflection), Pa/m.
    pub stiffness_pa_per_m: FoundationStiffnessPaPerM,
    /// Tangential stiffness per unit area (the subcutaneous layer's shear modulus over its
    /// thickness), Pa/m: anchors the skin in its plane against the drag of a cut. 0 (the
    /// default): the skin slides freely, held by drag only.
    #[serde(default)]
    pub shear_stiffness_pa_per_m: FoundationStiffnessPaPerM,
    /// Normal drag per unit area, Pa·s/m.
    #[serde(default)]
    pub normal_damping_pa_s_per_m: FoundationDampingPaSPerM,
    /// Tangential drag per unit area against the fascia, Pa·s/m: sets how fast a wound
    /// retracts under the residual stress.
    #[serde(default)]
    pub shear_damping_pa_s_per_m: FoundationDampingPaSPerM,
}

fn default_residual_strain() -> ResidualStrain {
    ResidualStrain(0.1)
}

/// A triangulated surface source.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum SurfaceGeometry {
    /// A procedural rectangular patch in the z = 0 plane, centred on the origin, normal +z.
    Patch(PatchSpec),
    /// A Wavefront OBJ triangle mesh.
    Obj(ObjSpec),
}

#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct PatchSpec {
    /// Side lengths along x and y, m.
    pub size_m: [LengthM; 2],
    /// Cells along x and y. Rows alternate by half a cell, so the triangles are
    /// equilateral when the y spacing is √3/2 of the x spacing.
    pub resolution: [Resolution; 2],
    /// Random displacement of interior nodes, as a fraction of the x spacing.
    #[serde(default = "zero_jitter")]
    pub jitter: Jitter,
    /// Seed of the jitter (the same seed gives the same mesh).
    #[serde(default)]
    pub seed: u64,
}

fn zero_jitter() -> Jitter {
    Jitter(0.0)
}

#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ObjSpec {
    /// Path of the .obj file: relative to the scene file, or `data:<path>` inside the
    /// shared data directory ($CUTSIM_DATA_DIR, default ../shared/data beside the repository).
    pub path: String,
    /// Metres per file unit: 0.001 for a file in millimetres.
    #[serde(default = "unit_scale")]
    pub scale_m_per_unit: ScaleMPerUnit,
    /// Translation applied after scaling, m.
    #[serde(default)]
    pub offset_m: Option<[CoordinateM; 3]>,
}

fn unit_scale() -> ScaleMPerUnit {
    ScaleMPerUnit(1.0)
}

/// Physical parameters of a membrane (skin).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MembraneMaterialSpec {
    pub young_pa: YoungPa,
    /// A triangle spring mesh has an effective Poisson ratio of 1/3; the value is
    /// recorded and reported, and E is matched exactly (see docs/msm.md).
    #[serde(default = "one_third")]
    pub poisson: Poisson,
    pub thickness_m: ThicknessM,
    pub density_kg_per_m3: DensityKgPerM3,
    /// The work a blade needs per unit area of cut, J/m² (docs/tool-tissue.md has the
    /// published values). 0: cutting needs no force.
    #[serde(default)]
    pub fracture_toughness_j_per_m2: FractureToughnessJPerM2,
    /// Coulomb friction between the skin and a tool's tip face (docs/tool-tissue.md).
    /// Absent: frictionless.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<FrictionSpec>,
}

/// Coulomb friction: the skin sticks to a tool while the tangential force stays within
/// `static_coefficient` times the normal force, and slides against
/// `dynamic_coefficient` times it otherwise.
#[derive(Debug, Clone, Copy, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct FrictionSpec {
    pub static_coefficient: FrictionCoefficient,
    pub dynamic_coefficient: FrictionCoefficient,
}

fn one_third() -> Poisson {
    Poisson(1.0 / 3.0)
}

/// Damping: −α·m·v on every node (the paper's −D·v) and optional spring damping.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct DampingSpec {
    /// α in 1/s.
    #[serde(default = "default_mass_damping")]
    pub mass_per_s: DampingPerS,
    /// β in s: each spring also resists its rate of extension with β·k.
    #[serde(default = "zero_spring_damping")]
    pub spring_s: SpringDampingS,
}

impl Default for DampingSpec {
    fn default() -> Self {
        Self { mass_per_s: default_mass_damping(), spring_s: zero_spring_damping() }
    }
}

fn default_mass_damping() -> DampingPerS {
    DampingPerS(10.0)
}

fn zero_spring_damping() -> SpringDampingS {
    SpringDampingS(0.0)
}

/// Which nodes are held, and on which axes.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum FixedSpec {
    /// Every node on the mesh boundary.
    Boundary {
        #[serde(default)]
        axes: Axes,
    },
    /// Every node inside an axis-aligned box (in scene coordinates, m).
    Box {
        min_m: [CoordinateM; 3],
        max_m: [CoordinateM; 3],
        #[serde(default)]
        axes: Axes,
    },
    /// Nodes by index in the geometry source (0-based).
    Nodes {
        indices: Vec<u32>,
        #[serde(default)]
        axes: Axes,
    },
}

/// A set of axes, written as a string such as "xyz", "z" or "xy".
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(into = "String")]
pub struct Axes {
    pub x: bool,
    pub y: bool,
    pub z: bool,
}

impl Default for Axes {
    fn default() -> Self {
        Self { x: true, y: true, z: true }
    }
}

impl From<Axes> for String {
    fn from(a: Axes) -> String {
        [(a.x, 'x'), (a.y, 'y'), (a.z, 'z')].iter().filter(|(on, _)| *on).map(|(_, c)| *c).collect()
    }
}

impl<'de> Deserialize<'de> for Axes {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let text = String::deserialize(d)?;
        let mut axes = Axes { x: false, y: false, z: false };
        for c in text.chars() {
            let slot = match c {
                'x' => &mut axes.x,
                'y' => &mut axes.y,
                'z' => &mut axes.z,
                _ => {
                    return Err(serde::de::Error::custom(format!(
                        "axes must be a combination of x, y and z such as \"xyz\" or \"z\", got {text:?}"
                    )));
                }
            };
            *slot = true;
        }
        if text.is_empty() {
            return Err(serde::de::Error::custom("axes must name at least one of x, y, z"));
        }
        Ok(axes)
    }
}

impl JsonSchema for Axes {
    fn schema_name() -> std::borrow::Cow<'static, str> {
        "Axes".into()
    }
    fn json_schema(_: &mut schemars::SchemaGenerator) -> schemars::Schema {
        schemars::json_schema!({
            "type": "string",
            "pattern": "^(x|y|z|xy|xz|yz|xyz)$",
            "description": "Axes held fixed, e.g. \"xyz\" (default) or \"z\"",
        })
    }
}

/// Time integration.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum IntegratorSpec {
    /// Symplectic (semi-implicit) Euler with substeps: fast, conditionally stable; a
    /// substep above the stability bound is refused with the bound in the message.
    SymplecticEuler { substeps: Substeps },
    /// Linearised backward Euler solved by warm-started conjugate gradient:
    /// unconditionally stable, numerically damped.
    ImplicitEuler {
        #[serde(default = "default_cg_iterations")]
        cg_max_iterations: CgIterations,
        #[serde(default = "default_cg_tolerance")]
        cg_tolerance: CgTolerance,
    },
}

fn default_cg_iterations() -> CgIterations {
    CgIterations(100)
}

fn default_cg_tolerance() -> CgTolerance {
    CgTolerance(1e-6)
}

/// Three-stage cutting settings.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema, Default)]
#[serde(deny_unknown_fields)]
pub struct CuttingSpec {
    /// Radius of the swept volume around the blade path, m. Default: the larger of the
    /// blade radius and half the mean edge length.
    #[serde(default)]
    pub sweep_radius_m: Option<RadiusM>,
    /// How far the blade must travel along the surface before the incision grows, m.
    /// Default: the mean edge length.
    #[serde(default)]
    pub min_advance_m: Option<LengthM>,
}

/// A tool the session drives.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct ToolSpec {
    pub name: String,
    pub shape: ToolShapeSpec,
    #[serde(default = "default_contact_stiffness")]
    pub contact_stiffness_n_per_m: StiffnessNPerM,
    /// True for a blade that cuts when the device's cut button is held.
    #[serde(default)]
    pub can_cut: bool,
    /// Largest force reported to the device, N.
    #[serde(default = "default_max_force")]
    pub max_force_n: ForceN,
    /// Branched grid only: the inner shape that removes the voxels whose deformed
    /// centres it contains (the outer `shape` repels). It must fit inside `shape`.
    /// Default for a cutting tool: half the radius, the full length.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cutting_shape: Option<ToolShapeSpec>,
    /// A blade's edge: the direction it faces in the tool's frame, across the tool's +z
    /// axis. Where the tissue has a fracture toughness, only motion within 60° of it cuts
    /// (on the branched grid, also motion along the tool's own axis: its point).
    #[serde(default)]
    pub edge: EdgeSpec,
}

/// The end of a cylinder at its tip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum TipSpec {
    Flat,
    Round,
}

/// The direction a blade's edge faces, in the tool's frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
pub enum EdgeSpec {
    #[default]
    #[serde(rename = "+x")]
    PlusX,
    #[serde(rename = "-x")]
    MinusX,
    #[serde(rename = "+y")]
    PlusY,
    #[serde(rename = "-y")]
    MinusY,
}

impl EdgeSpec {
    /// The unit vector in the tool's frame.
    pub fn local(self) -> crate::math::Vec3 {
        use crate::math::Vec3;
        match self {
            EdgeSpec::PlusX => Vec3::x(),
            EdgeSpec::MinusX => -Vec3::x(),
            EdgeSpec::PlusY => Vec3::y(),
            EdgeSpec::MinusY => -Vec3::y(),
        }
    }
}

fn default_contact_stiffness() -> StiffnessNPerM {
    StiffnessNPerM(200.0)
}

fn default_grip_force() -> ForceN {
    ForceN(3.0)
}

fn default_grip_length() -> ToolLengthM {
    ToolLengthM(0.01)
}

fn default_max_force() -> ForceN {
    ForceN(20.0)
}

#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum ToolShapeSpec {
    /// A segment from the tip along the tool's +z axis, with a radius, and its tip's end.
    Cylinder {
        radius_m: RadiusM,
        length_m: ToolLengthM,
        /// The end at the tip: `flat` (a cut-off rod) or `round` (a hemisphere of the
        /// rod's radius, a blunt probe). Default: flat on the mass-spring skin; the
        /// branched grid's tools are capsules (round) and refuse `flat`.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        tip: Option<TipSpec>,
    },
    /// A scalpel blade: a flat plate from the tip along the tool's +z axis, `length_m`
    /// long (its cutting edge's length), `width_m` across the axis along the tool's
    /// `edge` direction and `thickness_m` across its flat. Its cutting edge is the long
    /// side facing `edge`; its tip is a flat end (a pointed tip is not modelled). On the
    /// branched grid under either schedule (a multirate haptic loop renders the plate).
    Blade { width_m: BladeWidthM, thickness_m: BladeThicknessM, length_m: ToolLengthM },
    /// Forceps: two jaws, each a plate like a blade's (`width_m` along the tool's `edge`
    /// direction, `thickness_m` across its flat, `length_m` from the tip along the +z
    /// axis), on either side of the axis with their inner flats `opening_m` apart; the
    /// command's button (`cut`, the jaw) closes them, inner flats touching. Blunt: they
    /// press and rub, never cut (`can_cut` must be false). On the skin, jaws closing on
    /// the skin between them stop on it and grasp it, held by friction with the skin's
    /// coefficients under `grip_force_n` (docs/tool-tissue.md, "Grasping"). On
    /// the branched grid under either schedule, where its tissue has friction, closing
    /// jaws stop where it pushes back with `grip_force_n` (or half a voxel apart) and
    /// its friction holds it (docs/branched-grid.md, "Grasping"); under a multirate
    /// schedule the jaws must be
    /// thick enough for its vertices to hold them (at least the diagonal of a voxel's
    /// largest face) and close at a tenth of a voxel per deformation step.
    Forceps {
        width_m: BladeWidthM,
        thickness_m: BladeThicknessM,
        length_m: ToolLengthM,
        opening_m: JawOpeningM,
        /// How hard the hand pinches the closed jaws together, N (the device's jaw is a
        /// button): each jaw's inner flat presses the grasped tissue with it. Default 3 N,
        /// the least pinch that held a 5 N pull on porcine bowel in Heijnsdijk et al.
        /// 2004 (mean pinch applied 6.8 N).
        #[serde(default = "default_grip_force")]
        grip_force_n: ForceN,
        /// How far from the tip the jaws grip, m: tissue forceps grip with their
        /// serrated tips, not their whole length (on the skin, the fold they grasp; on
        /// the branched grid, the contacts under their inner flats that take the grip).
        /// Default 10 mm; at most `length_m` (refused beyond it).
        #[serde(default = "default_grip_length")]
        grip_length_m: ToolLengthM,
    },
}

impl ToolShapeSpec {
    /// The shape's length along the tool's axis, m.
    pub fn length_m(&self) -> f64 {
        match self {
            ToolShapeSpec::Cylinder { length_m, .. } | ToolShapeSpec::Blade { length_m, .. } | ToolShapeSpec::Forceps { length_m, .. } => length_m.get(),
        }
    }
}

/// Settings of the branched-grid model (see docs/branched-grid.md).
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct BranchedGridSpec {
    /// Where the voxels come from.
    pub volume: VolumeSource,
    /// Keep only these voxels of a label image (indices, inclusive), before anything else.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub crop_voxels: Option<CropSpec>,
    /// Move the body so that the centre of its bounding box is at the origin (images keep
    /// their scanner coordinates otherwise).
    #[serde(default)]
    pub centre: bool,
    /// A material per label; voxels of labels not listed are not built.
    pub materials: Vec<LabelMaterialSpec>,
    /// Coarsening level L: a coarse element is 2^L voxels a side (0: one per voxel).
    /// With `"fidelity": "auto"`, the finest level the calibration may choose.
    pub level: GridLevel,
    /// "fixed" (default): build at `level`. "auto": at load, time the levels from 4 down
    /// to `level` on this machine (a probe pressed into the body) and keep the finest
    /// whose p99 step fits `step_budget_ms` with 30 % to spare; the session reports the
    /// choice and its error class (docs/accuracy-speed.md).
    #[serde(default)]
    pub fidelity: FidelitySpec,
    /// The p99 step-time budget of `"fidelity": "auto"`, ms.
    #[serde(default = "default_step_budget")]
    pub step_budget_ms: StepBudgetMs,
    #[serde(default)]
    pub mass: MassSpec,
    /// How elements resist volume change (docs/branched-grid.md, "Volume change").
    #[serde(default)]
    pub volumetric: VolumetricSpec,
    #[serde(default)]
    pub damping: RayleighSpec,
    #[serde(default)]
    pub solver: GridSolverSpec,
    /// Nodes held fixed.
    #[serde(default)]
    pub fixed: Vec<GridFixedSpec>,
    /// How a coarse level holds the `fixed` regions (docs/branched-grid.md, "Supports").
    #[serde(default)]
    pub support: SupportSpec,
    #[serde(default)]
    pub surface: GridSurfaceSpec,
    /// Cutting by voxel removal. Absent: the scene cannot be cut.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub cutting: Option<GridCuttingSpec>,
    /// How the session steps the model: everything every `time_step_s` (single-rate,
    /// the default), or tool contact every `time_step_s` against the compliance of a
    /// deformation stepped less often on a thread of its own (multirate;
    /// docs/branched-grid.md, "Multirate haptics").
    #[serde(default, skip_serializing_if = "ScheduleSpec::is_single_rate")]
    pub schedule: ScheduleSpec,
}

/// How the session steps a branched grid.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum ScheduleSpec {
    /// Contact, deformation and cuts together, every `time_step_s`.
    #[default]
    SingleRate,
    /// Contact every `time_step_s` (the haptic rate), solved against each tool's contact
    /// patch as the last deformation step published it; the deformation, with the
    /// contact forces of the period before and the cuts, every
    /// `deformation_every_steps` haptic steps (its step is that many times
    /// `time_step_s`, at most 0.1 s).
    Multirate(MultirateSpec),
}

impl ScheduleSpec {
    pub fn is_single_rate(&self) -> bool {
        *self == ScheduleSpec::SingleRate
    }
}

/// The multirate schedule's rates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct MultirateSpec {
    /// Haptic steps per deformation step (33 at 1 kHz: deformation at 30 Hz). Under
    /// `"fidelity": "auto"` the longest period allowed: the level is fitted to it, then
    /// the period shortened as far as that level allows on this machine.
    pub deformation_every_steps: DeformationEvery,
}

/// A label volume source.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum VolumeSource {
    /// A NIfTI-1 label image (.nii or .nii.gz); lengths from its header.
    Nifti {
        /// Relative to the scene file, or `data:<path>` in the shared data directory.
        path: String,
    },
    /// A VTK XML ImageData label image (.vti).
    Vti {
        path: String,
        /// The data array holding the labels. Default: the active scalars, else the first.
        #[serde(default, skip_serializing_if = "Option::is_none")]
        array: Option<String>,
        /// Metres per file unit. Default 0.001 (medical images are in mm).
        #[serde(default = "millimetres")]
        scale_m_per_unit: ScaleMPerUnit,
    },
    /// A closed surface mesh (.obj or legacy .vtk polydata), voxelized inside.
    Mesh {
        path: String,
        /// Metres per file unit.
        #[serde(default = "unit_scale")]
        scale_m_per_unit: ScaleMPerUnit,
        voxel_size_m: VoxelSizeM,
        /// The label its inside voxels get.
        #[serde(default = "label_one")]
        label: LabelValue,
    },
    /// A solid box centred on the origin.
    Box {
        size_m: [LengthM; 3],
        voxel_size_m: VoxelSizeM,
        #[serde(default = "label_one")]
        label: LabelValue,
    },
    /// A solid ellipsoid centred on the origin.
    Ellipsoid {
        radii_m: [LengthM; 3],
        voxel_size_m: VoxelSizeM,
        #[serde(default = "label_one")]
        label: LabelValue,
    },
    /// Two arms rising along z from a common base, a gap between them (paper 004, Fig. 3).
    UTube {
        voxel_size_m: VoxelSizeM,
        /// Width of each arm along x.
        arm_voxels: VoxelsAlong,
        /// Gap between the arms along x.
        gap_voxels: VoxelsAlong,
        /// Depth along y.
        depth_voxels: VoxelsAlong,
        /// Thickness of the base along z.
        base_voxels: VoxelsAlong,
        /// Length of the arms above the base.
        arm_length_voxels: VoxelsAlong,
        #[serde(default = "label_one")]
        label: LabelValue,
    },
}

fn millimetres() -> ScaleMPerUnit {
    ScaleMPerUnit(1e-3)
}

fn label_one() -> LabelValue {
    LabelValue(1)
}

/// An inclusive range of voxel indices.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct CropSpec {
    pub min: [VoxelIndex; 3],
    pub max: [VoxelIndex; 3],
}

/// The material of one label.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct LabelMaterialSpec {
    pub label: LabelValue,
    /// Shown in reports and the viewer (e.g. "liver").
    #[serde(default)]
    pub name: String,
    pub young_pa: YoungPa,
    #[serde(default = "soft_tissue_poisson")]
    pub poisson: Poisson,
    pub density_kg_per_m3: DensityKgPerM3,
    /// Coulomb friction of its surface against the tools (docs/branched-grid.md,
    /// "Tools"). Absent: frictionless.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub friction: Option<FrictionSpec>,
    /// The work a blade needs per unit area of cut, J/m²: the cutting tool then feels
    /// J times the depth it has in the tissue against its motion (docs/branched-grid.md,
    /// "Cutting that resists"). 0: cutting needs no force.
    #[serde(default)]
    pub fracture_toughness_j_per_m2: FractureToughnessJPerM2,
}

fn soft_tissue_poisson() -> Poisson {
    Poisson(0.45)
}

/// How the grid's level is chosen.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum FidelitySpec {
    /// The scene's `level`.
    #[default]
    Fixed,
    /// Calibrated at load against the step budget.
    Auto,
}

fn default_step_budget() -> StepBudgetMs {
    StepBudgetMs(1.0)
}

/// Mass matrix.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum MassSpec {
    /// Row sums on the diagonal.
    #[default]
    Lumped,
    /// The condensed consistent mass matrix.
    Consistent,
}

/// Rayleigh damping C = αM + βK.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct RayleighSpec {
    /// α, 1/s.
    #[serde(default = "default_rayleigh_mass")]
    pub mass_per_s: DampingPerS,
    /// β, s.
    #[serde(default = "default_rayleigh_stiffness")]
    pub stiffness_s: SpringDampingS,
}

impl Default for RayleighSpec {
    fn default() -> Self {
        Self { mass_per_s: default_rayleigh_mass(), stiffness_s: default_rayleigh_stiffness() }
    }
}

fn default_rayleigh_mass() -> DampingPerS {
    DampingPerS(5.0)
}

fn default_rayleigh_stiffness() -> SpringDampingS {
    SpringDampingS(0.001)
}

/// The implicit solve.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GridSolverSpec {
    #[serde(default = "default_grid_cg_iterations")]
    pub cg_max_iterations: CgIterations,
    #[serde(default = "default_grid_cg_tolerance")]
    pub cg_tolerance: CgTolerance,
    /// What preconditions the conjugate gradient (docs/branched-grid.md).
    #[serde(default)]
    pub preconditioner: PreconditionerSpec,
}

impl Default for GridSolverSpec {
    fn default() -> Self {
        Self { cg_max_iterations: default_grid_cg_iterations(), cg_tolerance: default_grid_cg_tolerance(), preconditioner: PreconditionerSpec::default() }
    }
}

/// How a coarse level of the branched grid holds its fixed regions.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum SupportSpec {
    /// The level's nodes in the region (a box: whose rest position is inside it; a
    /// side: on that face of the level's bounds; labels: every node of an element
    /// holding them). Coarser levels hold fewer nodes, farther apart; a small region may
    /// hold no node at a coarse level (refused).
    #[default]
    CoarseNodes,
    /// The level-0 points of the region, as at level 0: those at a coarse element's
    /// corner hold that node, the others where the region meets the material it does
    /// not hold are embedded in their coarse elements by their trilinear weights and held
    /// by stiff springs. The same support at every level; any region holding a voxel
    /// corner holds at every level. Stiffer at coarse levels (measured in
    /// docs/branched-grid.md).
    Embedded,
}

/// How the branched grid's elements resist volume change.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum VolumetricSpec {
    /// A constant pressure per element and material on its mean volume change (B-bar,
    /// Q1P0): no volumetric locking, at any level; Poisson ratios up to 0.49.
    #[default]
    MeanDilatation,
    /// At every voxel's Gauss points (the paper's fully integrated hexahedron): locks as
    /// ν nears 0.5, and coarse elements inherit every voxel's volume constraint;
    /// Poisson ratios up to 0.45.
    Full,
}

/// The conjugate gradient's preconditioner (docs/branched-grid.md compares them).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case")]
pub enum PreconditionerSpec {
    /// The inverse of each node's 3×3 diagonal block: the cheapest iteration, the best
    /// choice at coarse levels, where the mass dominates the system.
    #[default]
    Jacobi,
    /// A V-cycle over the grid's coarser levels (block Gauss–Seidel smoothing): a few
    /// iterations at any resolution, each costing about four of Jacobi's.
    Multigrid,
    /// A sparse Cholesky factor of a recent step's system, made on a worker thread every
    /// 16 steps and after cuts: the fewest iterations, each costing a pair of triangular
    /// solves; its memory and factoring time grow fastest with resolution.
    Cholesky,
}

fn default_grid_cg_iterations() -> CgIterations {
    CgIterations(60)
}

fn default_grid_cg_tolerance() -> CgTolerance {
    CgTolerance(1e-5)
}

/// Which grid nodes are held.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "kebab-case", deny_unknown_fields)]
pub enum GridFixedSpec {
    /// Nodes whose rest position is inside a box (scene coordinates, m).
    Box { min_m: [CoordinateM; 3], max_m: [CoordinateM; 3] },
    /// The nodes on one side of the body's bounding box: "-x", "+x", "-y", "+y", "-z" or "+z".
    Side { side: String },
    /// The nodes of every element holding voxels of these labels (e.g. bone).
    Labels { labels: Vec<LabelValue> },
}

/// The visible surface.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GridSurfaceSpec {
    /// Taubin smoothing passes in rest space (0: the raw marching-cubes surface).
    #[serde(default = "default_smoothing")]
    pub smoothing_iterations: SmoothingIterations,
}

impl Default for GridSurfaceSpec {
    fn default() -> Self {
        Self { smoothing_iterations: default_smoothing() }
    }
}

fn default_smoothing() -> SmoothingIterations {
    SmoothingIterations(3)
}

/// Cutting by voxel removal.
#[derive(Debug, Clone, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields)]
pub struct GridCuttingSpec {
    /// At most this many voxels go in one step (the rest in the next ones), which bounds
    /// the time of a cut update.
    #[serde(default = "default_voxels_per_step")]
    pub max_voxels_per_step: VoxelsPerStep,
}

fn default_voxels_per_step() -> VoxelsPerStep {
    VoxelsPerStep(400)
}
