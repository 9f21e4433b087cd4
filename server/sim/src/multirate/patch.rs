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
//!
//! Friction, where the tissue's material has it, is the deformation's own model
//! (crate::grid::friction) carried on between deformation steps: each vertex in contact
//! keeps its anchor on the tool (published by the deformation step, then moved by the
//! haptic loop as the vertex slides: [`ContactPatch::commit`]); its stick spring across
//! the normal enters the patch's Newton solve beside the penalty.

use crate::grid::friction::{Friction, slid_anchor, stick_force, tangent_projection};
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
    /// Per vertex: where it sticks to the tool, from the tool's tip, m (world frame);
    /// None: not in frictional contact. The haptic loop keeps them up to date.
    pub anchors: Vec<Option<Vec3>>,
    /// The friction of the tissue under the tool (its nearest vertex's material).
    pub friction: Friction,
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

/// The most evaluations of the patch's forces a Newton solve makes (it needs three to
/// six where it converges; each costs a pass over the patch's vertices).
const NEWTON_EVALUATIONS: usize = 16;

impl ContactPatch {
    /// Empties the patch (the tool away or touching nothing near).
    pub fn clear(&mut self) {
        self.vertices.clear();
        self.positions.clear();
        self.compliance = Matrix3::zeros();
        self.applied = Vec3::zeros();
        self.compliance_residual = 0.0;
        self.anchors.clear();
        self.friction = Friction::default();
    }

    /// Solves the tool's contact with the patch: the displacement `u` with
    /// `u = C (F(u) − F_applied)`, `F(u)` the penalty and stick forces on the vertices
    /// moved by `u`. Allocates nothing; changes nothing (see [`Self::commit`]).
    pub fn solve(&self, tool: &Capsule) -> PatchContact {
        // Which vertices slide is decided between Newton solves, not inside one (a
        // vertex switching between sticking and sliding from one iteration to the next
        // keeps Newton's method from converging): all that have an anchor start stuck;
        // one whose stick force leaves the static cone at the solution slides in the
        // next solve (return mapping, as the deformation's friction does over a step).
        let mut sliding = Sliding::default();
        let mut u = Vec3::zeros();
        for _ in 0..SLIDE_PASSES {
            u = self.newton(tool, &sliding);
            if !self.mark_sliding(tool, &u, &mut sliding) {
                break;
            }
        }
        let mut contact = PatchContact { displacement_m: u, ..PatchContact::default() };
        for (j, x) in self.positions.iter().enumerate() {
            let p = x + u;
            let Some((on_tissue, _)) = self.vertex_forces(tool, j, &p, &sliding, false) else { continue };
            contact.force_n -= on_tissue;
            contact.torque_nm += (p - tool.tip).cross(&-on_tissue);
            contact.contacts += 1;
        }
        contact
    }

    /// The displacement `u` with `u = C (F(u) − F_applied)` for the vertices' sliding
    /// as given, by Newton's method with backtracking: the forces are only piecewise
    /// smooth in u (vertices coming into contact, the penalty's kinks, a sliding vertex's
    /// direction), and full steps can cycle between pieces without converging.
    fn newton(&self, tool: &Capsule, sliding: &Sliding) -> Vec3 {
        // G(u) = u − C (F(u) − F_applied); dF/du = −K (K = Σ k n nᵀ over the touching,
        // less the directions' turning near the solution (`normal_force`), and
        // k (I − n nᵀ) over those that stick).
        let residual_at = |u: &Vec3, exact: bool| {
            let (force, stiffness) = self.forces(tool, u, sliding, exact);
            (u - self.compliance * (force - self.applied), stiffness)
        };
        let mut u = Vec3::zeros();
        let (mut residual, mut stiffness) = residual_at(&u, false);
        let (mut evaluations, mut best) = (1, (residual.norm(), u));
        // Within 10 nm (a force within 0.3 mN on a stiff patch): solved.
        while evaluations < NEWTON_EVALUATIONS && residual.norm() >= 1e-8 {
            let Some(step) = (Matrix3::identity() + self.compliance * stiffness).lu().solve(&residual) else { break };
            // Far from the solution the stiffness across the normals (the directions'
            // turning) can make the Jacobian near-singular and the step wild: it enters
            // only within 10 µm, where it makes the convergence quadratic.
            let exact = residual.norm() < 1e-5;
            let mut scale = 1.0;
            let (mut next, mut next_stiffness) = residual_at(&(u - step), exact);
            evaluations += 1;
            while next.norm() > residual.norm() && scale > 1.0 / 8.0 && evaluations < NEWTON_EVALUATIONS {
                scale *= 0.5;
                (next, next_stiffness) = residual_at(&(u - step * scale), exact);
                evaluations += 1;
            }
            u -= step * scale;
            (residual, stiffness) = (next, next_stiffness);
            if residual.norm() < best.0 {
                best = (residual.norm(), u);
            }
            if step.norm() * scale < 1e-8 {
                break;
            }
        }
        // Out of evaluations (a tool deep among the cut surface's vertices can keep it
        // from converging): the best found.
        best.1
    }

    /// Marks the stuck vertices whose stick force at `u` leaves the static cone as
    /// sliding; whether any was.
    fn mark_sliding(&self, tool: &Capsule, u: &Vec3, sliding: &mut Sliding) -> bool {
        if self.friction.static_coefficient <= 0.0 {
            return false;
        }
        let mut changed = false;
        for (j, x) in self.positions.iter().enumerate().take(MAX_PATCH_VERTICES) {
            let (Some(Some(from_tip)), false) = (self.anchors.get(j), sliding.get(j)) else { continue };
            let p = x + u;
            let Some((normal, normal_n, _)) = normal_force(tool, &p, false) else { continue };
            let pull = tangent_projection(&normal) * (tool.tip + from_tip - p) * tool.stiffness_n_per_m;
            if pull.norm() > self.friction.static_coefficient * normal_n {
                sliding.set(j);
                changed = true;
            }
        }
        changed
    }

    /// After the haptic step's `contact` was rendered: each vertex in frictional contact
    /// keeps its anchor while it sticks, moves it to the dynamic cone while it slides,
    /// gets one where it first touches; one that let go loses it (as the deformation's
    /// own friction does over its step). Allocates nothing.
    pub fn commit(&mut self, tool: &Capsule, contact: &PatchContact) {
        if self.friction.static_coefficient <= 0.0 {
            return;
        }
        let k = tool.stiffness_n_per_m;
        for j in 0..self.positions.len().min(self.anchors.len()) {
            let p = self.positions[j] + contact.displacement_m;
            self.anchors[j] = match (normal_force(tool, &p, false), self.anchors[j]) {
                (None, _) => None,
                (Some(_), None) => Some(p - tool.tip),
                (Some((normal, normal_n, _)), Some(from_tip)) => {
                    let (force, sliding) = stick_force(&p, &(tool.tip + from_tip), &normal, k, normal_n, self.friction);
                    Some(if sliding { slid_anchor(&p, &force, k) - tool.tip } else { from_tip })
                }
            };
        }
    }

    /// The forces on the tissue with the patch moved by `u`: their sum and their
    /// stiffness (see [`Self::newton`]).
    fn forces(&self, tool: &Capsule, u: &Vec3, sliding: &Sliding, exact: bool) -> (Vec3, Matrix3<f64>) {
        let (mut force, mut stiffness) = (Vec3::zeros(), Matrix3::zeros());
        for (j, x) in self.positions.iter().enumerate() {
            if let Some((f, k)) = self.vertex_forces(tool, j, &(x + u), sliding, exact) {
                force += f;
                stiffness += k;
            }
        }
        (force, stiffness)
    }

    /// Vertex `j`'s force on the tissue at `p` (penalty, and the stick spring where it
    /// has an anchor) and its stiffness; None outside the tool. A vertex that sticks
    /// pulls toward its anchor across the normal; one that slides, with the dynamic
    /// force in that direction (no stiffness: its size follows the normal force only).
    #[inline]
    fn vertex_forces(&self, tool: &Capsule, j: usize, p: &Vec3, sliding: &Sliding, exact: bool) -> Option<(Vec3, Matrix3<f64>)> {
        let (normal, normal_n, mut stiffness) = normal_force(tool, p, exact)?;
        let k = tool.stiffness_n_per_m;
        let mut force = normal * normal_n;
        if let (true, Some(Some(from_tip))) = (self.friction.static_coefficient > 0.0, self.anchors.get(j)) {
            let pull = tangent_projection(&normal) * (tool.tip + from_tip - p) * k;
            if sliding.get(j) {
                force += pull.try_normalize(1e-15).map_or(Vec3::zeros(), |d| d * (self.friction.dynamic_coefficient * normal_n));
            } else {
                force += pull;
                stiffness += tangent_projection(&normal) * k;
            }
        }
        Some((force, stiffness))
    }
}

/// Solve passes that may find more sliding vertices (each a Newton solve).
const SLIDE_PASSES: usize = 4;

/// Which of a patch's vertices slide in this haptic step's solve (a bit each; on the
/// stack: the haptic loop allocates nothing).
#[derive(Debug, Clone, Copy, Default)]
struct Sliding([u64; MAX_PATCH_VERTICES / 64]);

impl Sliding {
    fn get(&self, j: usize) -> bool {
        j < MAX_PATCH_VERTICES && self.0[j / 64] & (1 << (j % 64)) != 0
    }

    fn set(&mut self, j: usize) {
        self.0[j / 64] |= 1 << (j % 64);
    }
}

/// The penalty on a vertex at `p` inside the capsule (pushed out radially, as the grid's
/// own contact does): its direction and size, N, and its stiffness `−∂f/∂p`: `k n nᵀ`
/// across the surface less the turning of the direction, `k (r − d)/d` across `n` (and
/// along the axis, for the shaft) — without the latter Newton's method converged only
/// linearly, about a fifth of the error an iteration. None outside.
#[inline]
fn normal_force(tool: &Capsule, p: &Vec3, exact: bool) -> Option<(Vec3, f64, Matrix3<f64>)> {
    let (t, closest) = closest_point_on_segment(p, &tool.tip, &tool.top);
    let offset = p - closest;
    let squared = offset.norm_squared();
    // Most of a patch's vertices are outside: nothing more to compute for them.
    if squared >= tool.radius_m * tool.radius_m || squared <= 1e-24 {
        return None;
    }
    let distance = squared.sqrt();
    let k = tool.stiffness_n_per_m;
    let normal = offset / distance;
    if !exact {
        return Some((normal, k * (tool.radius_m - distance), normal * normal.transpose() * k));
    }
    let across = if t > 0.0 && t < 1.0 {
        let axis = (tool.top - tool.tip).normalize();
        tangent_projection(&normal) - axis * axis.transpose()
    } else {
        tangent_projection(&normal)
    };
    let stiffness = normal * normal.transpose() * k - across * (k * (tool.radius_m - distance) / distance);
    Some((normal, k * (tool.radius_m - distance), stiffness))
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

    #[test]
    fn a_tool_dragged_over_a_patch_with_friction_is_held_back_within_the_static_cone() {
        let drag = |friction: Friction| {
            let mut patch = flat_patch(0.0);
            patch.friction = friction;
            patch.anchors = vec![None; patch.positions.len()];
            let mut tool = probe(1e-3);
            let first = patch.solve(&tool);
            patch.commit(&tool, &first);
            let anchored = patch.anchors.iter().filter(|a| a.is_some()).count();
            let mut forces = Vec::new();
            // 2 mm along +x in 10 µm steps.
            for _ in 0..200 {
                tool.tip.x += 1e-5;
                tool.top.x += 1e-5;
                let contact = patch.solve(&tool);
                patch.commit(&tool, &contact);
                forces.push(contact.force_n);
            }
            (anchored, first.contacts as usize, forces)
        };
        let (anchored, contacts, forces) = drag(Friction { static_coefficient: 0.5, dynamic_coefficient: 0.4 });
        assert_eq!(anchored, contacts, "each vertex in contact sticks where it first touched");
        assert!(forces[0].x < 0.0, "a step along +x is held back: {:?}", forces[0]);
        let ratio = |f: &Vec3| -f.x / f.z;
        let peak = forces.iter().map(ratio).fold(0.0, f64::max);
        let sliding = ratio(forces.last().unwrap());
        println!("drag over normal force: peak {peak:.3}, sliding {sliding:.3}");
        assert!(peak <= 0.5 * 1.2 && sliding > 0.25 && sliding < peak, "peak {peak}, sliding {sliding}");
        let (anchored, _, frictionless) = drag(Friction::default());
        assert_eq!(anchored, 0);
        assert!(frictionless.iter().all(|f| ratio(f).abs() < 0.05), "no friction, no drag");
    }
}
