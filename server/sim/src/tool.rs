//! Tools: their shapes (from the scene), the commands that move them each step, and
//! the feedback (force, torque, contacts) the tissue returns for the haptic device.

use crate::math::{Pose, Vec3};

/// A cylindrical tool (a scalpel blade or a probe): the segment from its tip along its
/// local +z axis, with a radius. Built once from the scene.
#[derive(Debug, Clone, PartialEq)]
pub struct ToolShape {
    pub name: String,
    pub radius_m: f64,
    pub length_m: f64,
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
}

impl ToolShape {
    /// The inner (cutting) capsule of a branched-grid tool, (radius, length) in m: the
    /// scene's `cutting_shape`, else half the tool's radius and its full length.
    pub fn cutting_capsule(&self) -> (f64, f64) {
        self.cutting_shape.unwrap_or((self.radius_m * 0.5, self.length_m))
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
    pub cut: bool,
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
}

impl PlacedTool {
    pub fn new(shape: &ToolShape, pose: &Pose) -> Self {
        let axis = pose.axis();
        let tip = pose.position_m;
        Self { tip, top: tip + axis * shape.length_m, axis, radius_m: shape.radius_m, length_m: shape.length_m }
    }

    /// Axis-aligned box around the tool grown by `margin` m: (min, max).
    pub fn bounds(&self, margin: f64) -> (Vec3, Vec3) {
        let grow = Vec3::repeat(self.radius_m + margin);
        (self.tip.inf(&self.top) - grow, self.tip.sup(&self.top) + grow)
    }
}

/// The scene's tools as shapes.
pub fn tool_shapes(scene: &crate::scene::Scene) -> Vec<ToolShape> {
    scene
        .tools
        .iter()
        .map(|t| {
            let crate::scene::ToolShapeSpec::Cylinder { radius_m, length_m } = t.shape;
            ToolShape {
                name: t.name.clone(),
                radius_m: radius_m.get(),
                length_m: length_m.get(),
                contact_stiffness_n_per_m: t.contact_stiffness_n_per_m.get(),
                can_cut: t.can_cut,
                max_force_n: t.max_force_n.get(),
                cutting_shape: t.cutting_shape.as_ref().map(|crate::scene::ToolShapeSpec::Cylinder { radius_m, length_m }| (radius_m.get(), length_m.get())),
                edge_local: t.edge.local(),
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
