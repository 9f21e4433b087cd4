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
//! vertices inside the tool's solid at its newest pose (a capsule, or a blade's plate;
//! new ones come into contact as the tool moves), and solves `u` and the penalty forces
//! `F(u)` together by Newton's method. The dent's shape changes at the deformation rate,
//! not in between: that is the reduction (docs/branched-grid.md, "Multirate haptics").
//! For a tool thinner than the vertex spacing the patch also holds the points on
//! triangles' insides the deformation held (grid::model::face_contact).
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
    /// the deformation step ended, nearest first; then the points on triangles' insides
    /// the step held (a tool thinner than the vertex spacing: grid::model::face_contact),
    /// each named by its triangle's vertex of the largest weight: the last
    /// `face_points` entries of this and the per-vertex lists below.
    pub vertices: Vec<u32>,
    /// How many of the entries are points on triangles' insides (at the end).
    pub face_points: usize,
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
    /// The force the patch's own contact puts on the tissue with the tool where the
    /// deformation step had it and the patch as published (`u = 0`), N: what the haptic
    /// loop's solve balances, `u = C (F(u) − balanced)`, so that at that pose the patch
    /// stays where the deformation left it ([`ContactPatch::balance_at`]). It differs
    /// from `applied` where the patch's contact, its vertices and points moved as a
    /// whole, cannot reproduce the deformation's own: balancing `applied` instead, 0.2 N
    /// across a 3 × 0.4 mm blade plate pressed point first (a force of the deformation's
    /// that no patch contact reproduces, along the plate's width) slid the patch 2.4 mm
    /// (its compliance: 12 mm/N) off the plate's end within the first solve, and the
    /// device felt nothing while the deformation pushed with 6.6 N.
    pub balanced: Vec3,
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
    /// Where the tool's tip was (world) at the deformation step that made the patch: a
    /// contact may be as much deeper than the tool's rated depth as the tool has moved
    /// since before it lets go ([`ContactPatch::let_go_depth`]). None: no allowance.
    pub tool_tip_m: Option<Vec3>,
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
    /// A scalpel blade's plate (world frame): the solid is then the box from the tip
    /// along the axis with this section, and `radius_m` its half-diagonal (what bounds
    /// it); None for a round tool.
    pub plate: Option<crate::grid::hold::Plate>,
}

impl Capsule {
    fn hold(&self) -> crate::grid::hold::Capsule {
        crate::grid::hold::Capsule { a: self.tip, b: self.top, radius: self.radius_m, plate: self.plate }
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
        self.balanced = Vec3::zeros();
        self.compliance_residual = 0.0;
        self.anchors.clear();
        self.friction = Friction::default();
        self.held.clear();
        self.face_points = 0;
        self.tool_tip_m = None;
    }

    /// How deep a vertex may be in `tool` at the solved contact before it lets go: the
    /// tool's rated depth, and as much more as the tool has moved since the deformation
    /// step that made the patch (the patch's vertices are where that step's solve left
    /// them against the tool where it was then: 1.65 mm behind it over 33 ms at 50 mm/s,
    /// more than the rated depth of a stiff contact, 0.5 mm for a 0.5 mm probe at
    /// 20,000 N/m). Within a solve no vertex lets go ([`Self::solve`]).
    fn let_go_depth(&self, tool: &Capsule) -> f64 {
        tool.max_depth_m + self.tool_tip_m.map_or(0.0, |tip| (tool.tip - tip).norm())
    }

    /// Whether a contact `touch` of `tool` is deeper than [`Self::let_go_depth`] (its
    /// penalty is the stiffness times its depth); a tool that does not hold (a blade
    /// cutting, pushed off radially) never lets go.
    fn lets_go(&self, tool: &Capsule, touch: &Touch) -> bool {
        tool.holds && touch.normal_n > tool.stiffness_n_per_m * self.let_go_depth(tool)
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
        //
        // Likewise which vertices let go (deeper than `let_go_depth`) is decided at a
        // solution, and the solve repeated without them: within a solve none lets go.
        // Letting go inside it made a second, false solution of a stiff contact on a
        // soft patch: with the vertices dropped the patch springs back by C F_applied
        // (13 mm on a block pressed with 1.4 N by a 0.4 mm blade plate at 20,000 N/m)
        // through the tool, where nothing touches it, and Newton's method, stepping into
        // that piece, ended there: 0 N rendered while the deformation pushed with 1.4 N.
        let (mut sliding, mut released) = (VertexSet::default(), VertexSet::default());
        let mut u = Vec3::zeros();
        for _ in 0..SLIDE_PASSES {
            u = self.newton(tool, &sliding, &released);
            let slid = self.mark_sliding(tool, &u, &released, &mut sliding);
            if !self.mark_released(tool, &u, &mut released) && !slid {
                break;
            }
        }
        let mut contact = PatchContact { displacement_m: u, ..PatchContact::default() };
        for (j, x) in self.positions.iter().enumerate() {
            let p = x + u;
            let Some((on_tissue, _)) = self.vertex_forces(tool, j, &p, &sliding, &released, false) else { continue };
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
    fn newton(&self, tool: &Capsule, sliding: &VertexSet, released: &VertexSet) -> Vec3 {
        // G(u) = u − C (F(u) − F_applied); dF/du = −K (K = Σ k n nᵀ over the touching,
        // less the directions' turning near the solution (`normal_force`), and
        // k (I − n nᵀ) over those that stick).
        let residual_at = |u: &Vec3, exact: bool| {
            let (force, stiffness) = self.forces(tool, u, sliding, released, exact);
            (u - self.compliance * (force - self.balanced), stiffness)
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
    fn mark_sliding(&self, tool: &Capsule, u: &Vec3, released: &VertexSet, sliding: &mut VertexSet) -> bool {
        if self.friction.static_coefficient <= 0.0 {
            return false;
        }
        let mut changed = false;
        for (j, x) in self.positions.iter().enumerate().take(MAX_PATCH_VERTICES) {
            let (Some(Some(from_tip)), false, false) = (self.anchors.get(j), sliding.get(j), released.get(j)) else { continue };
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

    /// Marks the vertices in contact at `u` deeper than [`Self::let_go_depth`] as let go;
    /// whether any was.
    fn mark_released(&self, tool: &Capsule, u: &Vec3, released: &mut VertexSet) -> bool {
        if !tool.holds {
            return false;
        }
        let mut changed = false;
        for (j, x) in self.positions.iter().enumerate().take(MAX_PATCH_VERTICES) {
            if !released.get(j) && self.touch(tool, j, &(x + u), false).is_some_and(|t| self.lets_go(tool, &t)) {
                released.set(j);
                changed = true;
            }
        }
        changed
    }

    /// Sets [`Self::balanced`] from the patch's own contact with `then`, the tool where
    /// the deformation step that made the patch had it (None: away), and the patch as
    /// published: its force `F₀` and stiffness `K₀` there. Balancing `applied`, the solve
    /// at that pose moves the patch by `u = (I + C K₀)⁻¹ C (F₀ − applied)`: where the
    /// contact is stiff (C K₀ ≫ 1) by little, rendering `applied` (the solved state's
    /// force, as wanted), but along a direction no contact of the patch resists (K₀ = 0:
    /// along a thin plate's width, where its end's points are pushed along its axis and
    /// its flats' across it) by the whole of C times the difference, off the tool. So
    /// along each eigendirection e of K₀ (eigenvalue λ) the patch balances its own force
    /// `F₀` in the proportion `1 / (1 + (c λ)²)` (c: the compliance's mean diagonal) and
    /// `applied` in the rest: `applied` where the contact is stiff, `F₀` (no slide) where
    /// nothing resists. Balancing `F₀` everywhere instead rendered a 5 mm probe's force
    /// in a block at 0.50 times the deformation's (its vertices' penalties at the
    /// published positions differ from the solved contact forces by up to 60 %); in the
    /// proportion `1 / (1 + c λ)`, at 0.84 times (its lateral contact, resisting with
    /// c λ of a few, took part of its own force); so, at 0.86 times (1.13 balancing
    /// `applied` alone, where the plate slid off).
    pub fn balance_at(&mut self, then: Option<&Capsule>) {
        self.balanced = self.applied;
        let Some(tool) = then else { return };
        let (own, stiffness) = self.forces(tool, &Vec3::zeros(), &VertexSet::default(), &VertexSet::default(), false);
        let c = self.compliance.trace() / 3.0;
        let eigen = ((stiffness + stiffness.transpose()) * 0.5).symmetric_eigen();
        for (k, lambda) in eigen.eigenvalues.iter().enumerate() {
            let e = eigen.eigenvectors.column(k);
            let resisted = c * lambda.max(0.0);
            self.balanced += e * (e.dot(&(own - self.applied)) / (1.0 + resisted * resisted));
        }
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
            let touch = self.touch(tool, j, &p, false).filter(|t| !self.lets_go(tool, t));
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
    fn forces(&self, tool: &Capsule, u: &Vec3, sliding: &VertexSet, released: &VertexSet, exact: bool) -> (Vec3, Matrix3<f64>) {
        let (mut force, mut stiffness) = (Vec3::zeros(), Matrix3::zeros());
        for (j, x) in self.positions.iter().enumerate() {
            if let Some((f, k)) = self.vertex_forces(tool, j, &(x + u), sliding, released, exact) {
                force += f;
                stiffness += k;
            }
        }
        (force, stiffness)
    }

    /// Vertex `j`'s force on the tissue at `p` (penalty, and the stick spring where it
    /// has an anchor) and its stiffness; None outside the tool or let go (however deep
    /// the others are: see [`Self::solve`]). A vertex that sticks
    /// pulls toward its anchor across the normal; one that slides, with the dynamic
    /// force in that direction (no stiffness: its size follows the normal force only).
    #[inline]
    fn vertex_forces(&self, tool: &Capsule, j: usize, p: &Vec3, sliding: &VertexSet, released: &VertexSet, exact: bool) -> Option<(Vec3, Matrix3<f64>)> {
        if released.get(j) {
            return None;
        }
        let Touch { normal, normal_n, mut stiffness, .. } = self.touch(tool, j, p, exact)?;
        let k = tool.stiffness_n_per_m;
        let mut force = normal * normal_n;
        if tool.holds && j + self.face_points >= self.positions.len() {
            // A point on a triangle's inside is drawn towards the axis across its normal,
            // as the deformation draws it (grid::model::face_contact: the dent's walls
            // round a thin tip); without it the patch, soft as a whole (10 mm per newton
            // on a 30 kPa block), slid off a 0.4 mm plate's end sideways under a lateral
            // force of 0.17 N and the device felt nothing pressing it point first.
            if let Some((across, offset)) = tool.hold().centring(p) {
                let pull = tangent_projection(&normal);
                force += pull * offset * k;
                stiffness += pull * across * k;
            }
        }
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
    /// cutting). None: not in contact. However deep it is ([`Self::lets_go`] says
    /// whether that is past letting go).
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
        let contact = crate::grid::hold::contact(&capsule, p, held, None, f64::INFINITY)?;
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

/// A set of a patch's vertices in this haptic step's solve, such as those that slide or
/// let go (a bit each; on the stack: the haptic loop allocates nothing).
#[derive(Debug, Clone, Copy, Default)]
struct VertexSet([u64; MAX_PATCH_VERTICES / 64]);

impl VertexSet {
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
/// linearly, about a fifth of the error an iteration. A plate pushes out through its
/// nearest face (`k n nᵀ`: a face's normal does not turn). None outside.
#[inline]
fn normal_force(tool: &Capsule, p: &Vec3, exact: bool) -> Option<(Vec3, f64, Matrix3<f64>)> {
    let (t, closest) = closest_point_on_segment(p, &tool.tip, &tool.top);
    let offset = p - closest;
    let squared = offset.norm_squared();
    // Most of a patch's vertices are outside: nothing more to compute for them.
    if squared >= tool.radius_m * tool.radius_m || squared <= 1e-24 {
        return None;
    }
    let k = tool.stiffness_n_per_m;
    if tool.plate.is_some() {
        let (normal, depth) = tool.hold().radial(p);
        return (depth > 0.0).then(|| (normal, k * depth, normal * normal.transpose() * k));
    }
    let distance = squared.sqrt();
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
        Capsule { tip: Vec3::new(0.0, 0.0, 3e-3 - depth), top: Vec3::new(0.0, 0.0, 0.1), radius_m: 3e-3, stiffness_n_per_m: 500.0, rotation: Matrix3::identity(), holds: true, max_depth_m: 0.02, plate: None }
    }

    /// A #10-like blade's plate, 3 mm wide (its edge along x) and 0.4 mm thick, pressed
    /// point first 0.1 mm into the flat patch: the vertices under its end are pushed
    /// down, out through its end face (the nearest), and the vertices beside its flat
    /// but within the plate's bounding radius are not touched.
    #[test]
    fn a_blade_plate_pushes_the_patch_with_its_box_not_its_bounding_capsule() {
        let patch = flat_patch(0.0);
        let (half_width, half_thickness) = (1.5e-3, 0.2e-3);
        let plate = crate::grid::hold::Plate { edge: Vec3::x(), flat: Vec3::y(), half_width, half_thickness };
        let tool = Capsule { tip: Vec3::new(0.0, 0.0, -1e-4), top: Vec3::new(0.0, 0.0, 0.1), radius_m: half_width.hypot(half_thickness), stiffness_n_per_m: 500.0, rotation: Matrix3::identity(), holds: true, max_depth_m: 0.02, plate: Some(plate) };
        let contact = patch.solve(&tool);
        // Under the end: the line y = 0 from x = −1 to 1 mm, each 0.1 mm deep.
        assert_eq!(contact.contacts, 3, "{contact:?}");
        assert!((contact.force_n - Vec3::new(0.0, 0.0, 3.0 * 500.0 * 1e-4)).norm() < 1e-12, "{:?}", contact.force_n);
        // A round tool of the same bounding radius, its ball's centre at the tip, would
        // have pushed every vertex within its radius of the tip.
        let round = patch.solve(&Capsule { plate: None, ..tool });
        assert_eq!(round.contacts, 9, "{round:?}");
    }

    /// A stiff contact on a soft patch (a 0.4 mm blade plate at 20,000 N/m on a block
    /// that gives 10 mm per newton), the tool 1.65 mm on since the deformation step
    /// pushed with 1.38 N: the three points under its end are held along its axis, and
    /// the patch is solved against them. Letting them go inside the solve (they are
    /// deeper than the rated 0.5 mm before it) gave a second solution, the patch sprung
    /// back 13 mm through the tool and 0 N rendered; the one with the points pressed is
    /// the one taken, and only the point still in contact at it pushes.
    #[test]
    fn a_stiff_contact_on_a_soft_patch_is_not_solved_by_springing_back_through_the_tool() {
        let plate = crate::grid::hold::Plate { edge: Vec3::x(), flat: Vec3::y(), half_width: 1.5e-3, half_thickness: 0.2e-3 };
        let tool = Capsule { tip: Vec3::zeros(), top: Vec3::new(0.0, 0.0, 0.06), radius_m: 1.5e-3f64.hypot(0.2e-3), stiffness_n_per_m: 20_000.0, rotation: Matrix3::identity(), holds: true, max_depth_m: 0.0005, plate: Some(plate) };
        let positions = vec![Vec3::new(0.0, 0.0, 1.61e-3), Vec3::new(-0.565e-3, 0.0, 1.87e-3), Vec3::new(0.39e-3, 0.0, 1.72e-3)];
        let compliance = Matrix3::from_diagonal(&Vec3::new(0.0139, 0.0141, 0.0094));
        let patch = ContactPatch { vertices: vec![0, 1, 2], held: vec![Some(-Vec3::z()); 3], positions, compliance, applied: Vec3::new(0.0, 0.0, -1.38), balanced: Vec3::new(0.0, 0.0, -1.38), tool_tip_m: Some(Vec3::new(0.0, 0.0, 1.65e-3)), ..ContactPatch::default() };
        let contact = patch.solve(&tool);
        // Only the highest point stays in: u (1 + kC) = C (−k · 1.87 mm + 1.38 N).
        let u = 0.0094 * (-20_000.0 * 1.87e-3 + 1.38) / (1.0 + 20_000.0 * 0.0094);
        assert_eq!(contact.contacts, 1, "{contact:?}");
        assert!((contact.displacement_m.z - u).abs() < 1e-8, "{contact:?} against u = {u}");
        assert!((contact.force_n.z - 20_000.0 * (1.87e-3 + u)).abs() < 1e-3, "{contact:?}");
        assert!(contact.force_n.z > 1.0);
    }

    /// A patch under a 3 × 0.4 mm plate's end whose deformation step ended with a force
    /// along the plate's width, which none of its contacts (pushed along the axis)
    /// resists: balanced on the deformation's force the patch slides that force times
    /// its compliance (7 mm) off the end and nothing is rendered; balanced on its own
    /// force along the width (`balance_at`) it stays under the end, and the press along
    /// the axis, which its contacts resist, is still the deformation's.
    #[test]
    fn a_patch_balances_its_own_force_where_its_contact_does_not_resist() {
        let plate = crate::grid::hold::Plate { edge: Vec3::x(), flat: Vec3::y(), half_width: 1.5e-3, half_thickness: 0.2e-3 };
        let tool = Capsule { tip: Vec3::zeros(), top: Vec3::new(0.0, 0.0, 0.06), radius_m: 1.5e-3f64.hypot(0.2e-3), stiffness_n_per_m: 20_000.0, rotation: Matrix3::identity(), holds: true, max_depth_m: 0.0005, plate: Some(plate) };
        // Pressed 0.15 mm in by the end where the deformation had the tool.
        let positions = vec![Vec3::new(-0.5e-3, 0.0, 0.15e-3), Vec3::new(0.4e-3, 0.0, 0.15e-3)];
        let compliance = Matrix3::from_diagonal(&Vec3::new(0.014, 0.014, 0.009));
        let applied = Vec3::new(0.5, 0.0, -6.0);
        let mut patch = ContactPatch { vertices: vec![0, 1], held: vec![Some(-Vec3::z()); 2], anchors: vec![None; 2], positions, compliance, applied, balanced: applied, tool_tip_m: Some(Vec3::zeros()), ..ContactPatch::default() };
        let slid = patch.solve(&tool);
        assert!(slid.contacts == 0 && slid.force_n.norm() == 0.0, "balancing the deformation's force it slid off: {slid:?}");
        patch.balance_at(Some(&tool));
        assert!(patch.balanced.x.abs() < 1e-9 && (patch.balanced.z - applied.z).abs() < 0.01 * applied.z.abs(), "{:?}", patch.balanced);
        let held = patch.solve(&tool);
        assert_eq!(held.contacts, 2, "{held:?}");
        assert!(held.displacement_m.x.abs() < 1e-9, "{held:?}");
        assert!((held.force_n.z + applied.z).abs() < 0.05 * applied.z.abs(), "the press is the deformation's: {held:?}");
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
        moved.balanced = moved.applied;
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
