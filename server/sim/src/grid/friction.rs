//! Coulomb friction between a tool and the branched grid's surface: a stick spring
//! inside the implicit solve.
//!
//! Where a surface vertex touches a tool whose material has friction, an anchor is
//! kept: the point of the tool the vertex stuck to (stored relative to the tool's tip,
//! so it moves with the tool). A spring across the contact normal pulls the vertex
//! toward it, `f_t = k_t P (a − p)` with `P = I − n nᵀ`; its stiffness enters the
//! system matrix and, with the anchor moving with the tool over the step,
//! `−h k_t P (v − u)` the right-hand side (u the tool's velocity) — the same
//! linearisation as the normal penalty, so a stuck vertex follows the tool whatever
//! the damping and elastic forces of the solve (a velocity filter after the solve was
//! tried: the next solve undid it). While `|f_t|` stays within the static cone
//! `μ_s f_n` the vertex sticks; beyond it, it slides: the anchor is moved to where the
//! spring pulls with the dynamic force `μ_d f_n` along the slip. An anchor lives while
//! its vertex stays in contact with its tool.

use super::solver::PointContact;
use super::topology::Topology;
use crate::math::{Matrix3, Vec3};
use crate::solver::block_sparse::IndexSet;

/// A material's friction coefficients.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct Friction {
    pub static_coefficient: f64,
    pub dynamic_coefficient: f64,
}

/// Where a vertex stuck to a tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Anchor {
    pub tool: usize,
    /// From the tool's tip to the anchor, m (grid frame).
    pub from_tip: Vec3,
    /// The step it was last in contact.
    pub step: u64,
}

/// Every surface vertex's anchor, if it has one. A cut forgets them all (the surface
/// around the blade is remade); forgetting visits only the vertices that were given an
/// anchor since the last time (`held`), not the whole surface: on a large body (the
/// layered abdomen's 100k vertices) clearing and refilling every slot after each cut
/// made the next step 0.4 ms longer.
#[derive(Debug, Clone, Default)]
pub struct Anchors {
    slots: Vec<Option<Anchor>>,
    /// Every vertex whose slot holds an anchor is in it (some in it may since have let
    /// go).
    held: IndexSet,
}

impl crate::hash::HashState for Anchor {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        (self.tool, self.from_tip, self.step).hash_state(h);
    }
}

impl crate::hash::HashState for Anchors {
    /// Every vertex's anchor (the `held` index is how they are found again).
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        self.slots.hash_state(h);
    }
}

impl Anchors {
    /// `vertices` empty slots, with room for `room` without reallocating.
    pub fn with_room(vertices: usize, room: usize) -> Anchors {
        let mut anchors = Anchors { slots: Vec::with_capacity(room.max(vertices)), held: IndexSet::default() };
        anchors.held.reset(room.max(vertices));
        anchors.fit(vertices);
        anchors
    }

    /// One slot per surface vertex (`vertices` of them), new slots empty; a shorter
    /// surface forgets every anchor first.
    pub fn fit(&mut self, vertices: usize) {
        if vertices < self.slots.len() {
            self.forget_all();
            self.slots.truncate(vertices);
            self.held.reset(vertices);
        } else if vertices > self.slots.len() {
            self.slots.resize(vertices, None);
            self.held.grow(vertices);
        }
    }

    /// Vertex `vertex`'s anchor (none beyond the slots).
    pub fn get(&self, vertex: usize) -> Option<Anchor> {
        self.slots.get(vertex).copied().flatten()
    }

    pub fn set(&mut self, vertex: usize, anchor: Anchor) {
        self.slots[vertex] = Some(anchor);
        self.held.insert(vertex as u32);
    }

    /// Vertex `vertex`'s slot, to change or empty an anchor it holds.
    pub fn slot_mut(&mut self, vertex: usize) -> &mut Option<Anchor> {
        &mut self.slots[vertex]
    }

    /// Every slot empty.
    pub fn forget_all(&mut self) {
        for v in self.held.iter() {
            self.slots[v as usize] = None;
        }
        self.held.clear();
    }
}

/// `I − n nᵀ`: the projection across the unit normal `n`.
pub fn tangent_projection(n: &Vec3) -> Matrix3<f64> {
    Matrix3::identity() - n * n.transpose()
}

/// The stick spring's force on the tissue at `point` toward `anchor`, across `normal`,
/// within the static cone of `normal_n`: (force, sliding). Beyond the cone the force is
/// the dynamic one along the same direction and the anchor must move (see
/// [`slid_anchor`]).
pub fn stick_force(point: &Vec3, anchor: &Vec3, normal: &Vec3, stiffness: f64, normal_n: f64, friction: Friction) -> (Vec3, bool) {
    let pull = tangent_projection(normal) * (anchor - point) * stiffness;
    let size = pull.norm();
    if size <= friction.static_coefficient * normal_n {
        (pull, false)
    } else {
        (pull * (friction.dynamic_coefficient * normal_n / size), true)
    }
}

/// Where the anchor goes when the vertex slides: so far from `point` that the spring
/// pulls with `force` (the dynamic force).
pub fn slid_anchor(point: &Vec3, force: &Vec3, stiffness: f64) -> Vec3 {
    point + force / stiffness
}

/// Friction's stick spring on a point at `point` held along `normal` with `normal_n`,
/// anchored at `anchor`, for the implicit step: (its stiffness in the solve, its force
/// on the tissue at the step's start, where its anchor is to be kept). Within the static
/// cone it sticks: the spring. Beyond it the point slides, the anchor moves to where the
/// spring pulls with the dynamic force, and the force is a damper on the point's
/// velocity relative to its anchor's (`slip`, at the step's start), `μ_d N / |slip|`
/// across the normal: the dynamic force while the slip goes on as it was, less as the
/// point catches up, never pushing it past the tool. (A constant dynamic force made stiff
/// contacts' light points overshoot the tool within the step, and the force flipped sign
/// every step: a probe drawn along a block at 20,000 N/m felt 0.006 of its press instead
/// of μ_d.) The damper is returned as a stick spring with no force of its own at the
/// step's start (a damper c is a spring of stiffness c / h in the step's
/// linearisation). Where it would be stiffer than the stick spring (a slip per step
/// under the spring's give at the dynamic force, which a constant force cannot
/// overshoot) the force is the constant dynamic one (stiffness 0).
#[allow(clippy::too_many_arguments)]
pub fn rub(point: &Vec3, anchor: &Vec3, normal: &Vec3, stiffness: f64, normal_n: f64, friction: Friction, slip: &Vec3, h: f64) -> (f64, Vec3, Vec3) {
    let (force, sliding) = stick_force(point, anchor, normal, stiffness, normal_n, friction);
    if !sliding {
        return (stiffness, force, *anchor);
    }
    let anchor = slid_anchor(point, &force, stiffness);
    let speed = (tangent_projection(normal) * slip).norm();
    let damper = friction.dynamic_coefficient * normal_n / (speed * h);
    if damper <= stiffness { (damper, Vec3::zeros(), anchor) } else { (0.0, force, anchor) }
}

/// The stick spring's force of `contact` at the end of a step of h whose velocities
/// `topo` holds (the linearisation the solve used), N.
pub fn stick_force_after(contact: &PointContact, topo: &Topology, h: f64) -> Vec3 {
    if contact.stick_stiffness == 0.0 {
        return contact.stick_force;
    }
    let slip = contact.point_velocity(topo) - contact.tool_velocity;
    contact.stick_force - tangent_projection(&contact.normal) * slip * (h * contact.stick_stiffness)
}

#[cfg(test)]
mod tests {
    use super::*;

    const FRICTION: Friction = Friction { static_coefficient: 0.5, dynamic_coefficient: 0.4 };

    #[test]
    fn anchors_forget_every_anchor_grow_within_their_room_in_place_and_forget_all_when_shrunk() {
        let anchor = |step| Anchor { tool: 0, from_tip: Vec3::new(0.0, 0.0, 0.001), step };
        let mut anchors = Anchors::with_room(10, 20);
        anchors.set(3, anchor(1));
        anchors.set(7, anchor(2));
        anchors.set(3, anchor(3));
        *anchors.slot_mut(7) = None;
        assert_eq!(anchors.get(3), Some(anchor(3)));
        assert_eq!(anchors.get(7), None);
        assert_eq!(anchors.get(10), None, "beyond the slots: none");
        anchors.forget_all();
        assert!((0..10).all(|v| anchors.get(v).is_none()));
        // Growing within the room keeps the slots where they are and what they hold.
        anchors.set(9, anchor(4));
        let before = anchors.slots.as_ptr();
        anchors.fit(20);
        assert_eq!(anchors.slots.as_ptr(), before, "no reallocation within the room");
        assert_eq!((anchors.slots.len(), anchors.get(9)), (20, Some(anchor(4))));
        anchors.set(19, anchor(5));
        anchors.forget_all();
        assert!((0..20).all(|v| anchors.get(v).is_none()));
        anchors.set(2, anchor(6));
        anchors.fit(5);
        assert_eq!(anchors.slots.len(), 5);
        assert!((0..5).all(|v| anchors.get(v).is_none()), "a shorter surface forgets them all");
    }

    #[test]
    fn within_the_static_cone_the_spring_pulls_across_the_normal_toward_the_anchor() {
        // 1 mm off along x and 1 mm along the normal: only the 1 mm across counts.
        let (force, sliding) = stick_force(&Vec3::zeros(), &Vec3::new(1e-3, 0.0, 1e-3), &Vec3::z(), 100.0, 1.0, FRICTION);
        assert!(!sliding && (force - Vec3::new(0.1, 0.0, 0.0)).norm() < 1e-15, "{force:?}");
    }

    #[test]
    fn beyond_it_the_vertex_slides_with_the_dynamic_force_and_the_anchor_follows() {
        let point = Vec3::new(0.0, 0.0, 0.0);
        let (force, sliding) = stick_force(&point, &Vec3::new(0.01, 0.0, 0.0), &Vec3::z(), 100.0, 1.0, FRICTION);
        assert!(sliding && (force - Vec3::new(0.4, 0.0, 0.0)).norm() < 1e-15, "{force:?}");
        let anchor = slid_anchor(&point, &force, 100.0);
        assert!((anchor - Vec3::new(4e-3, 0.0, 0.0)).norm() < 1e-15);
        let (again, still) = stick_force(&point, &anchor, &Vec3::z(), 100.0, 1.0, FRICTION);
        assert!(!still && (again - force).norm() < 1e-15, "at the moved anchor it pulls with the dynamic force and sticks");
    }
}
