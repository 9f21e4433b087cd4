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
//! The contact holds as the deformation's own does (crate::grid::hold): each vertex in
//! contact is pushed out along the normal it came in with, kept in the tool's frame for
//! as long as the contact lasts, so a probe pressed deeper than its ball's centre does
//! not slip between the patch's vertices. The deformation step publishes the normals
//! of the vertices it held; a vertex that first touches between deformation steps gets
//! its own ([`ContactPatch::commit`]). With the radial penalty the patch, sprung back
//! by the force the deformation step had applied, slid past the ball's centre and the
//! force rendered fell to nothing 5 mm into a block while the deformation still held it.
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
    /// Per vertex: the normal it is held along while in contact (crate::grid::hold), in
    /// the tool's frame; None: not in contact. The haptic loop keeps them up to date.
    pub held: Vec<Option<Vec3>>,
    /// A cutting blade's flat or back leads into tissue with a fracture toughness (its
    /// nearest vertex's material; crate::grid::cut_resistance::edge_leads): the haptic
    /// loop holds the tissue off it, as the deformation step did.
    pub blade_pushes: bool,
}

/// The tool's capsule at a haptic step, world frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Capsule {
    pub tip: Vec3,
    pub top: Vec3,
    pub radius_m: f64,
    /// Penalty stiffness per vertex, N/m.
    pub stiffness_n_per_m: f64,
    /// The tool's orientation (tool frame to world): the held normals turn with it.
    pub rotation: Matrix3<f64>,
    /// Whether contacts hold (crate::grid::hold); false for a blade cutting, whose
    /// tissue must reach the cutting shape and is pushed out radially.
    pub holds: bool,
    /// How deep one vertex may be pushed before it lets go (its force would exceed the
    /// tool's rated force), m.
    pub max_depth_m: f64,
}

impl Capsule {
    fn hold(&self) -> crate::grid::hold::Capsule {
        crate::grid::hold::Capsule::round(self.tip, self.top, self.radius_m)
    }
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
        self.held.clear();
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
            let Some(Touch { normal, normal_n, .. }) = self.touch(tool, j, &p, false) else { continue };
            let pull = tangent_projection(&normal) * (tool.tip + from_tip - p) * tool.stiffness_n_per_m;
            if pull.norm() > self.friction.static_coefficient * normal_n {
                sliding.set(j);
                changed = true;
            }
        }
        changed
    }

    /// After the haptic step's `contact` was rendered: each vertex in contact keeps the
    /// normal it is held along, and one that first touched gets the one it came in with;
    /// one that let go loses it. Each vertex in frictional contact keeps its anchor while
    /// it sticks, moves it to the dynamic cone while it slides, gets one where it first
    /// touches; one that let go loses it (as the deformation's own friction does over its
    /// step). Allocates nothing.
    pub fn commit(&mut self, tool: &Capsule, contact: &PatchContact) {
        let to_tool = tool.rotation.transpose();
        for j in 0..self.positions.len() {
            let p = self.positions[j] + contact.displacement_m;
            let touch = self.touch(tool, j, &p, false);
            if let Some(held) = self.held.get_mut(j) {
                *held = touch.filter(|_| tool.holds).map(|t| to_tool * t.entry);
            }
            if self.friction.static_coefficient <= 0.0 || j >= self.anchors.len() {
                continue;
            }
            self.anchors[j] = match (touch, self.anchors[j]) {
                (None, _) => None,
                (Some(_), None) => Some(p - tool.tip),
                (Some(Touch { normal, normal_n, .. }), Some(from_tip)) => {
                    let (force, sliding) = stick_force(&p, &(tool.tip + from_tip), &normal, tool.stiffness_n_per_m, normal_n, self.friction);
                    Some(if sliding { slid_anchor(&p, &force, tool.stiffness_n_per_m) - tool.tip } else { from_tip })
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
        let Touch { normal, normal_n, mut stiffness, .. } = self.touch(tool, j, p, exact)?;
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

impl ContactPatch {
    /// How vertex `j` at `p` touches the tool: pushed out along the normal it is held
    /// along (crate::grid::hold; within a quarter radius of the surface, along the
    /// surface's normal there), or radially where the tool does not hold (a blade
    /// cutting). None: not in contact.
    #[inline]
    fn touch(&self, tool: &Capsule, j: usize, p: &Vec3, exact: bool) -> Option<Touch> {
        if !tool.holds {
            return normal_force(tool, p, exact).map(|(normal, normal_n, stiffness)| Touch { normal, normal_n, stiffness, entry: normal });
        }
        let held = self.held.get(j).copied().flatten();
        // Most of a patch's vertices are outside and held by nothing: nothing more to
        // compute for them (no square root: this runs for each vertex, each evaluation).
        if held.is_none() {
            let (_, closest) = closest_point_on_segment(p, &tool.tip, &tool.top);
            if (p - closest).norm_squared() >= tool.radius_m * tool.radius_m {
                return None;
            }
        }
        let held = held.map(|n| tool.rotation * n);
        let capsule = tool.hold();
        let contact = crate::grid::hold::contact(&capsule, p, held, None, tool.max_depth_m)?;
        let k = tool.stiffness_n_per_m;
        if contact.normal != contact.entry || held.is_none() {
            // Along the surface's normal (the shallow band, or a first touch, whose entry
            // is where it is now): the radial penalty's own stiffness, turning included.
            if let Some((normal, normal_n, stiffness)) = normal_force(tool, p, exact).filter(|(n, _, _)| (n - contact.normal).norm() < 1e-9) {
                return Some(Touch { normal, normal_n, stiffness, entry: contact.entry });
            }
        }
        // Along a fixed normal n the depth t is where the ray from p leaves the capsule,
        // at a point whose outward normal is q: ∂t/∂p = −qᵀ/(q·n), so the stiffness is
        // k n qᵀ/(q·n) (k n nᵀ where the ray leaves square to the surface; a grazing exit
        // is taken as square, its derivative being unbounded).
        let (n, t) = (contact.normal, contact.depth);
        let q = capsule.radial(&(p + n * t)).0;
        let square = q.dot(&n);
        let stiffness = if square > 0.1 { n * q.transpose() * (k / square) } else { n * n.transpose() * k };
        Some(Touch { normal: n, normal_n: k * t, stiffness, entry: contact.entry })
    }
}

/// A vertex's contact: the normal it is pushed out along, the penalty's size on it (N),
/// its stiffness `−∂f/∂p`, and the normal it came in with.
#[derive(Debug, Clone, Copy)]
struct Touch {
    normal: Vec3,
    normal_n: f64,
    stiffness: Matrix3<f64>,
    entry: Vec3,
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

/// The radial penalty on a vertex at `p` inside the capsule (pushed out from the axis, as
/// the grid's own contact does for a blade cutting and near a tool's surface): its
/// direction and size, N, and its stiffness `−∂f/∂p`: `k n nᵀ`
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
        ContactPatch { vertices: (0..81).collect(), held: vec![None; positions.len()], positions, compliance: Matrix3::identity() * compliance, ..ContactPatch::default() }
    }

    fn probe(depth: f64) -> Capsule {
        // A ball-ended rod of radius 3 mm pressed straight down, its centre line at x = y = 0.
        Capsule { tip: Vec3::new(0.0, 0.0, 3e-3 - depth), top: Vec3::new(0.0, 0.0, 0.1), radius_m: 3e-3, stiffness_n_per_m: 500.0, rotation: Matrix3::identity(), holds: true, max_depth_m: 0.02 }
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
        // The patch moved down by C F: the force on the tool is the force it moved by
        // (to the Newton solve's tolerance, 10 nm).
        let on_tissue = -contact.force_n;
        assert!((contact.displacement_m - patch.compliance * on_tissue).norm() < 1e-8, "{contact:?}");
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
    fn a_probe_past_its_balls_centre_still_pushes_the_vertices_it_holds_down() {
        // The probe's ball centre 1 mm below the patch (4 mm in): the vertices within
        // its radius of the axis are inside, above the centre.
        let tool = probe(4e-3);
        let mut held = flat_patch(0.0);
        // As the deformation step publishes them: held along the tool's axis out of its
        // tip (they came in under the ball).
        for (x, n) in held.positions.iter().zip(held.held.iter_mut()) {
            if (x - tool.tip).norm() < tool.radius_m {
                *n = Some(-Vec3::z());
            }
        }
        let contact = held.solve(&tool);
        assert!(contact.contacts > 0);
        // Each pushed down until it is below the ball: 4 mm less the height where the
        // ball crosses its vertical line.
        let expected: f64 = held
            .positions
            .iter()
            .zip(&held.held)
            .filter(|(_, n)| n.is_some())
            .map(|(x, _)| {
                let across = (x - tool.tip).xy().norm_squared();
                500.0 * ((tool.radius_m.powi(2) - across).sqrt() + 1e-3)
            })
            .sum();
        assert!((contact.force_n.z - expected).abs() < 1e-9 * expected, "{} vs {expected}", contact.force_n.z);
        // The radial penalty pushes the same vertices up and out past the ball's centre:
        // the tool is pulled into the tissue.
        let radial = held.solve(&Capsule { holds: false, ..tool });
        assert!(radial.force_n.z < 0.0, "radially: {:?}", radial.force_n);
        // A vertex the haptic loop finds in contact keeps the normal it came in with.
        let before = held.held.clone();
        held.commit(&tool, &contact);
        for (now, then) in held.held.iter().zip(&before) {
            assert!(then.is_none() || now == then, "{then:?} became {now:?}");
        }
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
