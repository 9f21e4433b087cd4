//! Tools: their shapes (from the scene), the commands that move them each step, and
//! the feedback (force, torque, contacts) the tissue returns for the haptic device.

pub(crate) mod bodies;

use crate::math::{Pose, Vec3, across, any_perpendicular};
use crate::scene::{ModelSpec, TipSpec, ToolShapeSpec};

/// A tool: the segment from its tip along its local +z axis, with a cross-section (a
/// disc: a probe or a blade idealised as a cylinder; a rectangle: a scalpel blade's
/// plate; two rectangles: forceps' jaws). Built once from the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolShape {
    pub name: String,
    /// The farthest the cross-section reaches from the axis, m: a cylinder's radius, a
    /// plate's half-diagonal (what bounds the tool for broad phases).
    pub radius_m: f64,
    pub length_m: f64,
    pub section: Section,
    /// Penalty stiffness of the contact between the tool and a tissue node, N/m.
    pub contact_stiffness_n_per_m: f64,
    /// Whether the tool may cut (a blade) or only push (a probe).
    pub can_cut: bool,
    /// The largest force ever reported to the device, N; larger forces are clamped and counted.
    pub max_force_n: f64,
    /// Branched grid: the inner (cutting) capsule, (radius, length) in m; the tool's own
    /// shape repels. None: half the radius and the full length for a cutting tool.
    pub cutting_shape: Option<(f64, f64)>,
    /// The direction a blade's edge faces, in the tool's frame (unit, across its +z axis).
    pub edge_local: Vec3,
    /// Its end at the tip.
    pub tip_shape: TipShape,
}

/// A tool's end at its tip.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum TipShape {
    /// Cut off square to the axis (a rod's end, a blade's plate).
    #[default]
    Flat,
    /// A hemisphere of the tool's radius (a blunt probe; a round tool only), its apex at
    /// the tip.
    Round,
}

/// A tool's cross-section across its axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Section {
    /// A disc of the tool's radius.
    Round,
    /// A rectangle: `half_width_m` along the edge's direction, `half_thickness_m` across
    /// the flat (its normal: axis × edge).
    Plate { half_width_m: f64, half_thickness_m: f64 },
    /// Forceps' jaws: two such rectangles on either side of the axis across the flat,
    /// their inner flats `2 half_gap_m` apart when open (closed: touching), pinched
    /// together with `grip_force_n` on what they grasp within `grip_length_m` of the tip
    /// (crate::msm::grasp).
    Jaws { half_width_m: f64, half_thickness_m: f64, half_gap_m: f64, grip_force_n: f64, grip_length_m: f64 },
}

impl Section {
    /// How wide a tool of this section (and `radius_m`) is along its edge's direction,
    /// m: the crack it must open to pass through the skin (a cylinder's diameter, a
    /// plate's width).
    fn width_m(self, radius_m: f64) -> f64 {
        match self {
            Section::Round => 2.0 * radius_m,
            Section::Plate { half_width_m, .. } | Section::Jaws { half_width_m, .. } => 2.0 * half_width_m,
        }
    }
}

impl ToolShape {
    /// How wide the tool is along its edge's direction, m ([`Section`]).
    pub fn width_m(&self) -> f64 {
        self.section.width_m(self.radius_m)
    }

    /// Half the width of the path its edge cuts, m: a cylinder's radius, half a plate's
    /// thickness.
    pub fn cut_half_width_m(&self) -> f64 {
        match self.section {
            Section::Round => self.radius_m,
            Section::Plate { half_thickness_m, .. } | Section::Jaws { half_thickness_m, .. } => half_thickness_m,
        }
    }

    /// The inner (cutting) capsule of a branched-grid tool, (radius, length) in m: the
    /// scene's `cutting_shape`, else half the tool's radius and its full length.
    pub fn cutting_capsule(&self) -> (f64, f64) {
        self.cutting_shape.unwrap_or((self.radius_m * 0.5, self.length_m))
    }

    /// Whether the tool cuts under `command`: a cutting tool, active at a finite pose,
    /// with its button held.
    pub fn cuts(&self, command: &ToolCommand) -> bool {
        self.can_cut && command.active && command.cut && command.pose.is_finite()
    }

    /// How deep one surface vertex may lie in the tool before its contact lets go: its
    /// penalty would then carry the tool's rated force alone (crate::grid::hold), m.
    pub fn hold_max_depth_m(&self) -> f64 {
        self.max_force_n / self.contact_stiffness_n_per_m
    }
}

/// What the device (or a script) asks of one tool for one step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ToolCommand {
    /// Pose of the tool's tip; its axis is the local +z.
    pub pose: Pose,
    /// False when the tool is away (not in the scene this step).
    pub active: bool,
    /// Cutting enabled (a pedal or button on the device); ignored for tools that cannot cut.
    /// On forceps, the jaws close while it is held.
    pub cut: bool,
    /// How hard the hand squeezes forceps' handles, as a fraction (0–1) of the tool's
    /// `grip_force_n` — a device with an analog gripper; None: the whole grip while the
    /// button is held (a device whose jaw is a button). A squeeze of 0 closes nothing.
    /// Ignored by tools without jaws.
    pub grip: Option<f64>,
}

impl ToolCommand {
    /// Whether forceps commanded so close their jaws: the button held with some squeeze.
    pub fn closes_jaws(&self) -> bool {
        self.cut && self.grip.is_none_or(|g| g > 0.0)
    }

    /// The force the hand pinches forceps rated `grip_force_n` with, N (0 while their
    /// jaws do not close).
    pub fn grip_n(&self, grip_force_n: f64) -> f64 {
        if self.closes_jaws() { grip_force_n * self.grip.unwrap_or(1.0).clamp(0.0, 1.0) } else { 0.0 }
    }
}

/// Why a command's `grip` cannot be used (None: it can): a fraction of the tool's grip,
/// finite, 0–1.
pub fn grip_error(grip: f64) -> Option<String> {
    (!(grip.is_finite() && (0.0..=1.0).contains(&grip))).then(|| format!("grip must be a fraction of the tool's grip force from 0 to 1, got {grip}"))
}

/// A step's contract: one command and one feedback slot per tool of the scene, in its
/// order. Checked on every step (two comparisons) in every build: a caller that passed
/// fewer had a tool left out without a word, or an index past the end deep inside a
/// model (the skin's grasp, in release tests written when the default scene had two tools).
pub fn assert_one_per_tool(commands: &[ToolCommand], feedback: &[ToolFeedback], tools: &[ToolShape]) {
    assert!(
        commands.len() == tools.len() && feedback.len() == tools.len(),
        "a step takes one command and one feedback slot per tool of the scene ({} tools); got {} commands and {} feedback slots",
        tools.len(),
        commands.len(),
        feedback.len()
    );
}

/// What the tissue returns for one tool after a step.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct ToolFeedback {
    /// Force the tissue exerts on the tool, N (what the haptic device renders).
    pub force_n: Vec3,
    /// Torque about the tool tip, N·m.
    pub torque_nm: Vec3,
    /// Tissue nodes in contact with the tool.
    pub contacts: u32,
    /// True when the tool removed tissue this step.
    pub cutting: bool,
    /// True when the force was above the tool's limit and was clamped.
    pub force_clamped: bool,
    /// The dissipative share of `force_n`, N: the cutting resistance, which opposes the
    /// blade's motion and may stop it but never drives it. A haptic coupling integrates
    /// it like friction (docs/haptic-bridge.md); the rest of the force is elastic.
    pub resistance_n: Vec3,
    /// True while forceps close on tissue between their jaws or hold it, stopped on it
    /// (until the button is released, or on the branched grid until what they held
    /// slips out: tool::bodies::Bodies::pinch): a stiff load whose pull changes by newtons per
    /// millimetre, which a haptic coupling damps more firmly (docs/haptic-bridge.md,
    /// "Grasping through the bridge").
    pub grasping: bool,
    /// Forceps: how hard what lies between the jaws pushes them apart, N — what an
    /// analog gripper renders against the hand's squeeze (docs/haptic-bridge.md). Jaws
    /// stopped on tissue are closed by force, so it pushes back as hard as they pinch
    /// (the squeeze's share of the grip: [`ToolCommand::grip_n`]); grid jaws still
    /// closing feel the lesser of the two jaws' outward forces; open jaws, jaws closing
    /// on nothing and other tools, 0. (Not hashed: it follows from the jaws' hashed
    /// state and the bodies' feedback.)
    pub jaws_force_n: f64,
}

impl crate::hash::HashState for ToolFeedback {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        let Self { force_n, torque_nm, contacts, cutting, force_clamped, resistance_n, grasping, jaws_force_n: _ } = self;
        (force_n, torque_nm).hash_state(h);
        (contacts, cutting).hash_state(h);
        (force_clamped, grasping).hash_state(h);
        resistance_n.hash_state(h);
    }
}

/// A tool placed in space for one step: the segment from `tip` to `top`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PlacedTool {
    pub tip: Vec3,
    pub top: Vec3,
    /// Unit axis from tip to top.
    pub axis: Vec3,
    pub radius_m: f64,
    pub length_m: f64,
    /// Unit direction its edge faces, across the axis.
    pub edge: Vec3,
    pub section: Section,
    pub tip_shape: TipShape,
}

impl crate::hash::HashState for PlacedTool {
    /// Where it is (its shape is the scene's).
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        [self.tip, self.top, self.axis, self.edge].hash_state(h);
    }
}

impl PlacedTool {
    pub fn new(shape: &ToolShape, pose: &Pose) -> Self {
        let axis = pose.axis();
        let tip = pose.position_m;
        let edge = unit_across(&axis, &(pose.orientation * shape.edge_local));
        Self { tip, top: tip + axis * shape.length_m, axis, radius_m: shape.radius_m, length_m: shape.length_m, edge, section: shape.section, tip_shape: shape.tip_shape }
    }

    /// A round tool of `radius_m` with a flat tip (its edge facing any way across the axis).
    pub fn round(tip: Vec3, axis: Vec3, radius_m: f64, length_m: f64) -> Self {
        Self { tip, top: tip + axis * length_m, axis, radius_m, length_m, edge: any_perpendicular(&axis), section: Section::Round, tip_shape: TipShape::Flat }
    }

    /// The same tool with its tip at `tip` and its axis along `axis` (unit), its edge
    /// turned with it.
    pub fn moved(&self, tip: Vec3, axis: Vec3) -> Self {
        Self { tip, top: tip + axis * self.length_m, axis, edge: unit_across(&axis, &self.edge), ..*self }
    }

    /// How wide the tool is along its edge's direction, m ([`Section`]).
    pub fn width_m(&self) -> f64 {
        self.section.width_m(self.radius_m)
    }

    /// Unit normal of its flat (a plate's; for a round tool, the plane of its edge).
    pub fn flat_normal(&self) -> Vec3 {
        self.axis.cross(&self.edge)
    }

    /// `x` in the tool's frame: [along its axis from the tip, along its edge, across
    /// its flat] (where a point held by the tool is kept as the tool moves and turns).
    pub fn to_frame(&self, x: &Vec3) -> [f64; 3] {
        let from_tip = x - self.tip;
        [from_tip.dot(&self.axis), from_tip.dot(&self.edge), from_tip.dot(&self.flat_normal())]
    }

    /// The point at `[along, edge, flat]` in the tool's frame ([`Self::to_frame`]), world.
    pub fn from_frame(&self, [along, edge, flat]: [f64; 3]) -> Vec3 {
        self.tip + self.axis * along + self.edge * edge + self.flat_normal() * flat
    }

    /// Where a point at `offset` from the axis (across it) lies in the cross-section:
    /// how far it is from the way out and the way out (unit, across the axis); None
    /// outside. A plate's way out is through the nearer of its flat or its edge (back).
    pub fn section_exit(&self, offset: &Vec3) -> Option<(f64, Vec3)> {
        match self.section {
            Section::Round => {
                let d = offset.norm();
                if d >= self.radius_m {
                    return None;
                }
                // On the axis itself the way out is undefined: any perpendicular will
                // do, chosen deterministically.
                let direction = if d > 1e-12 * self.radius_m { offset / d } else { any_perpendicular(&self.axis) };
                Some((self.radius_m - d, direction))
            }
            Section::Plate { half_width_m, half_thickness_m } => {
                let normal = self.flat_normal();
                plate_exit(offset.dot(&self.edge), offset.dot(&normal), half_width_m, half_thickness_m, &self.edge, &normal)
            }
            Section::Jaws { half_width_m, half_thickness_m, half_gap_m, .. } => {
                // The open jaws (the mass-spring skin takes each jaw as a plate of its
                // own: `msm::bodies`): the jaw on the point's side of the axis.
                let normal = self.flat_normal();
                let (a, b) = (offset.dot(&self.edge), offset.dot(&normal));
                let centre = (half_gap_m + half_thickness_m) * if b < 0.0 { -1.0 } else { 1.0 };
                plate_exit(a, b - centre, half_width_m, half_thickness_m, &self.edge, &normal)
            }
        }
    }

    /// A round tip's hemisphere, for a point `x` nearer the tip than the hemisphere's
    /// centre (one radius up the axis): how deep it lies inside and the way out
    /// (radially from the centre, the sphere's normal); None outside the sphere, above
    /// its centre (the side's), or for a flat tip.
    pub fn round_tip_exit(&self, x: &Vec3) -> Option<(f64, Vec3)> {
        if self.tip_shape != TipShape::Round {
            return None;
        }
        let from_centre = x - (self.tip + self.axis * self.radius_m);
        let d = from_centre.norm();
        if d >= self.radius_m || from_centre.dot(&self.axis) > 0.0 {
            return None;
        }
        // At the centre itself the way out is undefined: out through the apex.
        let direction = if d > 1e-12 * self.radius_m { from_centre / d } else { -self.axis };
        Some((self.radius_m - d, direction))
    }

    /// Axis-aligned box around the tool grown by `margin` m: (min, max).
    pub fn bounds(&self, margin: f64) -> (Vec3, Vec3) {
        let grow = Vec3::repeat(self.radius_m + margin);
        (self.tip.inf(&self.top) - grow, self.tip.sup(&self.top) + grow)
    }
}

/// A point at `a` along `edge` and `b` along `normal` from a plate's centre line (across
/// the axis): how deep it lies inside the plate and the way out through the nearer of
/// its flats (±`normal`) or its sides (±`edge`); None outside.
fn plate_exit(a: f64, b: f64, half_width_m: f64, half_thickness_m: f64, edge: &Vec3, normal: &Vec3) -> Option<(f64, Vec3)> {
    if a.abs() >= half_width_m || b.abs() >= half_thickness_m {
        return None;
    }
    let sign = |c: f64| if c < 0.0 { -1.0 } else { 1.0 };
    let (through_flat, through_side) = (half_thickness_m - b.abs(), half_width_m - a.abs());
    Some(if through_flat <= through_side { (through_flat, normal * sign(b)) } else { (through_side, edge * sign(a)) })
}

/// `direction` made square to the unit `axis` and unit (any perpendicular if it lies
/// along the axis).
fn unit_across(axis: &Vec3, direction: &Vec3) -> Vec3 {
    across(direction, axis).try_normalize(1e-9).unwrap_or_else(|| any_perpendicular(axis))
}

/// The scene's tools as shapes.
pub fn tool_shapes(scene: &crate::scene::Scene) -> Vec<ToolShape> {
    scene
        .tools
        .iter()
        .map(|t| {
            let (radius_m, section) = match t.shape {
                ToolShapeSpec::Cylinder { radius_m, .. } => (radius_m.get(), Section::Round),
                ToolShapeSpec::Blade { width_m, thickness_m, .. } => {
                    let (half_width_m, half_thickness_m) = (0.5 * width_m.get(), 0.5 * thickness_m.get());
                    (half_width_m.hypot(half_thickness_m), Section::Plate { half_width_m, half_thickness_m })
                }
                ToolShapeSpec::Forceps { width_m, thickness_m, opening_m, grip_force_n, grip_length_m, .. } => {
                    let (half_width_m, half_thickness_m, half_gap_m) = (0.5 * width_m.get(), 0.5 * thickness_m.get(), 0.5 * opening_m.get());
                    // Bounded by the open jaws' outer corners.
                    (half_width_m.hypot(half_gap_m + 2.0 * half_thickness_m), Section::Jaws { half_width_m, half_thickness_m, half_gap_m, grip_force_n: grip_force_n.get(), grip_length_m: grip_length_m.get() })
                }
            };
            // The branched grid's tools are capsules (its scenes refuse a flat tip).
            let tip_shape = match (&t.shape, &scene.model) {
                (ToolShapeSpec::Cylinder { tip: Some(TipSpec::Round), .. }, _) => TipShape::Round,
                (ToolShapeSpec::Cylinder { .. }, ModelSpec::BranchedGrid(_)) => TipShape::Round,
                _ => TipShape::Flat,
            };
            ToolShape {
                name: t.name.clone(),
                radius_m,
                length_m: t.shape.length_m(),
                section,
                contact_stiffness_n_per_m: t.contact_stiffness_n_per_m.get(),
                can_cut: t.can_cut,
                max_force_n: t.max_force_n.get(),
                // Validated at load: a cutting shape is a cylinder.
                cutting_shape: t.cutting_shape.as_ref().and_then(|inner| match inner {
                    ToolShapeSpec::Cylinder { radius_m, length_m, .. } => Some((radius_m.get(), length_m.get())),
                    ToolShapeSpec::Blade { .. } | ToolShapeSpec::Forceps { .. } => None,
                }),
                edge_local: t.edge.local(),
                tip_shape,
            }
        })
        .collect()
}

impl ToolFeedback {
    /// Clamps the force magnitude to `max_force_n`, scaling the torque with it.
    pub fn clamp_force(&mut self, max_force_n: f64) {
        let magnitude = self.force_n.norm();
        if magnitude > max_force_n {
            let scale = max_force_n / magnitude;
            self.force_n *= scale;
            self.torque_nm *= scale;
            self.resistance_n *= scale;
            self.force_clamped = true;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::Quat;

    /// A #10-like blade's plate, 6 mm wide and 0.4 mm thick, its edge facing +x at the
    /// identity pose, turned `turn` about its (vertical) axis.
    fn blade(turn: f64) -> PlacedTool {
        let shape = ToolShape {
            name: "blade".into(),
            radius_m: 3e-3_f64.hypot(2e-4),
            length_m: 0.04,
            section: Section::Plate { half_width_m: 3e-3, half_thickness_m: 2e-4 },
            contact_stiffness_n_per_m: 200.0,
            can_cut: true,
            max_force_n: 10.0,
            cutting_shape: None,
            edge_local: Vec3::x(),
            tip_shape: TipShape::Flat,
        };
        PlacedTool::new(&shape, &Pose::new(Vec3::zeros(), Quat::from_axis_angle(&Vec3::z_axis(), turn)))
    }

    #[test]
    fn a_plate_is_left_through_its_nearer_flat_or_side() {
        let b = blade(0.0);
        assert_eq!((b.edge, b.flat_normal(), b.width_m()), (Vec3::x(), Vec3::y(), 6e-3));
        // Beside the flat: out across it, whichever side.
        let (depth, out) = b.section_exit(&Vec3::new(1e-3, 1.5e-4, 0.0)).unwrap();
        assert!((depth - 5e-5).abs() < 1e-15 && out == Vec3::y(), "{depth} {out:?}");
        assert_eq!(b.section_exit(&Vec3::new(1e-3, -1.5e-4, 0.0)).unwrap().1, -Vec3::y());
        // Just inside the edge, on the flat's mid-plane: out through the edge.
        let (depth, out) = b.section_exit(&Vec3::new(2.95e-3, 0.0, 0.0)).unwrap();
        assert!((depth - 5e-5).abs() < 1e-15 && out == Vec3::x(), "{depth} {out:?}");
        // Beyond the flat or beyond the edge: outside, though within the bounding radius.
        assert!(b.section_exit(&Vec3::new(0.0, 2.5e-4, 0.0)).is_none());
        assert!(b.section_exit(&Vec3::new(3.05e-3, 0.0, 0.0)).is_none());
    }

    #[test]
    fn a_plate_turns_with_its_tool_and_keeps_its_edge_across_the_axis_when_swept() {
        let b = blade(std::f64::consts::FRAC_PI_2);
        assert!((b.edge - Vec3::y()).norm() < 1e-15, "{:?}", b.edge);
        assert!(b.section_exit(&Vec3::new(0.0, 2e-3, 0.0)).is_some() && b.section_exit(&Vec3::new(2e-3, 0.0, 0.0)).is_none());
        // Tilted by the sweep between two poses, the edge stays square to the axis.
        let axis = Vec3::new(0.3, 0.0, 1.0).normalize();
        let moved = blade(0.0).moved(Vec3::new(0.0, 0.0, 1e-3), axis);
        assert!(moved.edge.dot(&axis).abs() < 1e-15 && (moved.edge.norm() - 1.0).abs() < 1e-15);
        assert!((moved.top - moved.tip - axis * 0.04).norm() < 1e-15);
    }

    /// A point's place in a tool's frame is along its axis, its edge and its flat's
    /// normal from the tip, and maps back.
    #[test]
    fn a_point_goes_into_the_tools_frame_and_back() {
        let tool = PlacedTool { tip: Vec3::new(0.01, 0.0, 0.0), ..blade(0.0) };
        let (axis, edge, normal) = (tool.axis, tool.edge, tool.flat_normal());
        let x = tool.tip + axis * 0.003 + edge * 0.002 - normal * 0.001;
        let local = tool.to_frame(&x);
        assert!((Vec3::from(local) - Vec3::new(0.003, 0.002, -0.001)).norm() < 1e-15, "{local:?}");
        assert!((tool.from_frame(local) - x).norm() < 1e-15);
    }

    #[test]
    fn open_jaws_are_two_plates_and_the_gap_between_them_is_outside() {
        // Jaws 2 mm wide (along the edge, x) and 1 mm thick, inner flats 8 mm apart.
        let jaws = PlacedTool { section: Section::Jaws { half_width_m: 1e-3, half_thickness_m: 5e-4, half_gap_m: 4e-3, grip_force_n: 3.0, grip_length_m: 0.01 }, ..blade(0.0) };
        assert_eq!(jaws.flat_normal(), Vec3::y());
        assert!(jaws.section_exit(&Vec3::zeros()).is_none() && jaws.section_exit(&Vec3::new(0.0, 3.9e-3, 0.0)).is_none(), "the gap is outside");
        // In the +y jaw near its inner flat: out towards the axis; near its outer flat:
        // away from it; on the −y side the same, mirrored.
        let (depth, out) = jaws.section_exit(&Vec3::new(0.0, 4.1e-3, 0.0)).unwrap();
        assert!((depth - 1e-4).abs() < 1e-15 && out == -Vec3::y(), "{depth} {out:?}");
        let (depth, out) = jaws.section_exit(&Vec3::new(0.0, -4.9e-3, 0.0)).unwrap();
        assert!((depth - 1e-4).abs() < 1e-15 && out == -Vec3::y(), "{depth} {out:?}");
        // Near a jaw's side: out through it, along the edge.
        assert_eq!(jaws.section_exit(&Vec3::new(9.5e-4, 4.5e-3, 0.0)).unwrap().1, Vec3::x());
        assert!(jaws.section_exit(&Vec3::new(0.0, 5.1e-3, 0.0)).is_none() && jaws.section_exit(&Vec3::new(1.1e-3, 4.5e-3, 0.0)).is_none());
        assert_eq!(jaws.width_m(), 2e-3);
    }

    #[test]
    fn a_round_tool_is_left_radially() {
        let rod = PlacedTool::round(Vec3::zeros(), Vec3::z(), 1e-3, 0.1);
        let (depth, out) = rod.section_exit(&Vec3::new(0.0, 9e-4, 0.0)).unwrap();
        assert!((depth - 1e-4).abs() < 1e-15 && out == Vec3::y());
        assert_eq!(rod.width_m(), 2e-3);
        assert!(rod.section_exit(&Vec3::new(8e-4, 8e-4, 0.0)).is_none());
    }
}
