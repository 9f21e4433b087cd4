//! A tool's contact patch: what a deformation step publishes so that the haptic loop can
//! render the tool's contact every millisecond until the next one.
//!
//! SOFA's multirate haptics publishes the compliance of the contact points,
//! W = H A⁻¹ Hᵀ, and the free motion; the haptic thread re-solves the small contact
//! problem against W with the device's newest pose. A full W needs three solves of the
//! deformation system per contact point; the patch keeps the part of it that a probe
//! feels most — the patch's compliance to a force on it as a whole (three solves per
//! tool) — and the patch's surface vertices as the deformation step left them. The
//! haptic loop moves the vertices together by `u = C (F − F_applied)`, finds the
//! vertices inside the tool's capsule at its newest pose (new ones come into contact as
//! the tool moves), and solves `u` and the penalty forces `F(u)` together by Newton's
//! method. The dent's shape changes at the deformation rate, not in between: that is
//! the reduction (docs/branched-grid.md, "Multirate haptics").

use crate::math::{Matrix3, Vec3, closest_point_on_segment};

/// The most surface vertices a patch keeps (the nearest to the tool).
pub const MAX_PATCH_VERTICES: usize = 512;

/// One tool's contact patch, in the scene's (world) frame.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ContactPatch {
    /// Surface vertex ids near the tool (within its radius and the patch margin) when
    /// the deformation step ended, nearest first.
    pub vertices: Vec<u32>,
    /// Their positions then, m.
    pub positions: Vec<Vec3>,
    /// How far the patch moves, over one deformation step, per newton pushed on it as a
    /// whole: `h² Hᵀ A⁻¹ H` with H spreading a force evenly over the vertices the tool
    /// touches (or, touching none, the nearest), m/N, symmetric.
    pub compliance: Matrix3<f64>,
    /// The force the deformation step ended with on the tissue through this tool (its
    /// own implicit contact with the tool where it was then), N: `positions` already
    /// include its effect.
    pub applied: Vec3,
    /// The relative residual the compliance solves reached (the largest of the three).
    pub compliance_residual: f64,
}

/// The tool's capsule at a haptic step, world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub tip: Vec3,
    pub top: Vec3,
    pub radius_m: f64,
    /// Penalty stiffness per vertex, N/m.
    pub stiffness_n_per_m: f64,
}

/// The solved contact of a tool with its patch.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct PatchContact {
    /// On the tool, N, and its torque about the tip, N·m.
    pub force_n: Vec3,
    pub torque_nm: Vec3,
    /// Vertices inside the capsule.
    pub contacts: u32,
    /// The patch's solved displacement from its published positions, m.
    pub displacement_m: Vec3,
}

/// Newton iterations of the patch solve (it converges in two or three: the penalty is
/// piecewise linear in the displacement).
const NEWTON_ITERATIONS: usize = 8;

impl ContactPatch {
    /// Empties the patch (the tool away or touching nothing near).
    pub fn clear(&mut self) {
        self.vertices.clear();
        self.positions.clear();
        self.compliance = Matrix3::zeros();
        self.applied = Vec3::zeros();
        self.compliance_residual = 0.0;
    }

    /// Solves the tool's contact with the patch: the displacement `u` with
    /// `u = C (F(u) − F_applied)`, `F(u)` the penalty forces on the vertices moved by `u`.
    /// Allocates nothing.
    pub fn solve(&self, tool: &Capsule) -> PatchContact {
        let mut u = Vec3::zeros();
        for _ in 0..NEWTON_ITERATIONS {
            let (force, stiffness) = self.penalty(tool, &u);
            // G(u) = u − C (F(u) − F_applied); dF/du = −K (K = Σ k n nᵀ over the touching).
            let residual = u - self.compliance * (force - self.applied);
            let jacobian = Matrix3::identity() + self.compliance * stiffness;
            let Some(step) = jacobian.lu().solve(&residual) else { break };
            u -= step;
            if step.norm() < 1e-9 {
                break;
            }
        }
        let mut contact = PatchContact { displacement_m: u, ..PatchContact::default() };
        for x in &self.positions {
            let Some(on_tissue) = vertex_force(tool, &(x + u)) else { continue };
            contact.force_n -= on_tissue;
            contact.torque_nm += (x + u - tool.tip).cross(&-on_tissue);
            contact.contacts += 1;
        }
        contact
    }

    /// The penalty forces on the tissue with the patch moved by `u`: their sum and their
    /// stiffness Σ k n nᵀ.
    fn penalty(&self, tool: &Capsule, u: &Vec3) -> (Vec3, Matrix3<f64>) {
        let (mut force, mut stiffness) = (Vec3::zeros(), Matrix3::zeros());
        for x in &self.positions {
            if let Some(f) = vertex_force(tool, &(x + u)) {
                let n = f.normalize();
                force += f;
                stiffness += n * n.transpose() * tool.stiffness_n_per_m;
            }
        }
        (force, stiffness)
    }
}

/// The penalty force on a vertex at `p` inside the capsule (pushed out radially, as the
/// grid's own contact does), N; None outside.
fn vertex_force(tool: &Capsule, p: &Vec3) -> Option<Vec3> {
    let (_, closest) = closest_point_on_segment(p, &tool.tip, &tool.top);
    let offset = p - closest;
    let distance = offset.norm();
    if distance >= tool.radius_m || distance <= 1e-12 {
        return None;
    }
    Some(offset * (tool.stiffness_n_per_m * (tool.radius_m - distance) / distance))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn flat_patch(compliance: f64) -> ContactPatch {
        // A 9 × 9 grid of vertices 1 mm apart on z = 0.
        let positions: Vec<Vec3> = (0..81).map(|i| Vec3::new((i % 9) as f64 * 1e-3 - 4e-3, (i / 9) as f64 * 1e-3 - 4e-3, 0.0)).collect();
        ContactPatch { vertices: (0..81).collect(), positions, compliance: Matrix3::identity() * compliance, ..ContactPatch::default() }
    }

    fn probe(depth: f64) -> Capsule {
        // A ball-ended rod of radius 3 mm pressed straight down, its centre line at x = y = 0.
        Capsule { tip: Vec3::new(0.0, 0.0, 3e-3 - depth), top: Vec3::new(0.0, 0.0, 0.1), radius_m: 3e-3, stiffness_n_per_m: 500.0 }
    }

    #[test]
    fn a_rigid_patch_pushes_back_with_its_penalty_alone() {
        let patch = flat_patch(0.0);
        let contact = patch.solve(&probe(1e-3));
        assert!(contact.contacts > 0);
        assert!(contact.force_n.z > 0.0, "pushed up: {:?}", contact.force_n);
        assert_eq!(contact.displacement_m, Vec3::zeros());
    }

    #[test]
    fn a_compliant_patch_yields_until_its_spring_and_the_penalty_balance() {
        let rigid = flat_patch(0.0).solve(&probe(1e-3));
        let patch = flat_patch(1e-3); // 1 mm per newton
        let contact = patch.solve(&probe(1e-3));
        // The patch moved down by C F: the force on the tool is the force it moved by.
        let on_tissue = -contact.force_n;
        assert!((contact.displacement_m - patch.compliance * on_tissue).norm() < 1e-9, "{contact:?}");
        assert!(contact.force_n.z > 0.0 && contact.force_n.z < rigid.force_n.z, "softer than rigid: {} vs {}", contact.force_n.z, rigid.force_n.z);
    }

    #[test]
    fn a_force_already_applied_is_not_counted_twice() {
        // The published positions include the applied force's displacement: with the
        // tool where it settled, the solve finds the same force and no further motion.
        let patch = flat_patch(1e-3);
        let settled = patch.solve(&probe(1e-3));
        let mut moved = flat_patch(1e-3);
        moved.positions.iter_mut().for_each(|x| *x += settled.displacement_m);
        moved.applied = -settled.force_n;
        let again = moved.solve(&probe(1e-3));
        assert!((again.force_n - settled.force_n).norm() < 1e-9 * settled.force_n.norm().max(1.0), "{again:?} vs {settled:?}");
        assert!(again.displacement_m.norm() < 1e-9);
    }
}
