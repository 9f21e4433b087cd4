//! Coulomb friction on a tool's side: a stick spring anchored on the tool.
//!
//! The tip face rubs ([`super::hold`]); the side did not: a node beside a shaft, or a
//! triangle's point along a thin one ([`super::side_hold`], [`super::face_hold`]), was
//! pushed out of the section only, so the skin slid freely along a tool laid on it and
//! a tool drawn along the skin dragged nothing. Laid flat on the default skin and
//! pressed, the blade's plate on its edge lost its points one triangle after another as
//! the skin beyond its end pulled them past it, and went through at 8.7 N (explicit).
//!
//! A point touching the side sticks where it first touched: the anchor, kept in the
//! tool's frame beside the point's way out (so it moves and turns with the tool). A
//! spring of the contact's stiffness across the push draws the point towards it. While
//! that pull stays within the static cone `μ_s f_n` (`f_n` the point's push) the point
//! sticks; beyond it, it slides: the anchor is moved to where the spring pulls with the
//! dynamic force `μ_d f_n`, along the slip. The branched grid's vertices rub the same
//! way (crate::grid::friction). Under the implicit integrator the springs are in the
//! system (two contacts across the push, driven with the tool's velocity, so that a
//! stuck point moves with the tool within the step); under the explicit integrator the
//! pull is a force of the contact pass, at the contact's own stiffness (stable where
//! the push is).

use super::contact::Contact;
pub(crate) use super::hold::Friction;
use super::side_hold::{SideMemory, Slot};
use crate::grid::friction::{slid_anchor, stick_force};
use crate::math::Vec3;
use crate::tool::PlacedTool;

/// The friction on a point at `at` that a tool's side pushes along `push` (unit) with
/// `normal_n`: the pull of its stick spring (stiffness `stiffness`) towards its anchor,
/// at most the dynamic force once it slides, N (the grid's stick spring,
/// crate::grid::friction). Keeps the anchor in `memory` (the point's
/// [`side_contact`](super::side_hold::side_contact) must have taken it this pass).
#[allow(clippy::too_many_arguments)]
pub(crate) fn side_friction(memory: &mut SideMemory, slot: Slot, body: usize, tool: &PlacedTool, at: &Vec3, push: &Vec3, normal_n: f64, stiffness: f64, (static_coefficient, dynamic_coefficient): Friction) -> Vec3 {
    let anchor = memory.anchor(slot, body, tool).unwrap_or(*at);
    let (pull, _) = stick_force(at, &anchor, push, stiffness, normal_n, stick_friction((static_coefficient, dynamic_coefficient)));
    memory.keep_anchor(slot, body, tool, &slid_anchor(at, &pull, stiffness));
    pull
}

/// The skin's friction coefficients (static, dynamic) as the stick springs take them.
pub(crate) fn stick_friction((static_coefficient, dynamic_coefficient): Friction) -> crate::grid::friction::Friction {
    crate::grid::friction::Friction { static_coefficient, dynamic_coefficient }
}

/// The stick springs of a point's friction as the implicit system's contacts: across
/// `push`, `stiffness` times each node's weight, driven with the tool's velocity.
pub(crate) fn stick_contacts(ids: &[u32], weights: &[f64], push: &Vec3, stiffness: f64, tool_velocity: &Vec3, contacts: &mut Vec<Contact>) {
    for t in super::hold::tangents_across(*push) {
        for (&node, &w) in ids.iter().zip(weights) {
            if w != 0.0 {
                contacts.push(Contact { node, normal: t, stiffness: stiffness * w, drive_m_per_s: tool_velocity.dot(&t) });
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A 6 mm rod laid along +x from the origin.
    fn laid_flat() -> PlacedTool {
        PlacedTool::round(Vec3::zeros(), Vec3::x(), 0.003, 0.08)
    }

    #[test]
    fn a_point_sticks_within_the_static_cone_and_slides_at_the_dynamic_force() {
        let tool = laid_flat();
        let mut memory = SideMemory::with_room(4, 0);
        let (up, slot, k) = (Vec3::z(), Slot::Node(1), 200.0);
        memory.begin_pass();
        let at = Vec3::new(0.02, 0.0, -0.002);
        crate::msm::side_hold::side_contact(&mut memory, slot, 0, &tool, &at, Some((-up, 0.001)), 1.0);
        // First touch: anchored where it is, no pull.
        assert_eq!(side_friction(&mut memory, slot, 0, &tool, &at, &-up, 1.0, k, (0.5, 0.4)), Vec3::zeros());
        // The tool moved 1 mm along itself: the anchor went with it; 0.2 N ≤ 0.5 × 1 N sticks.
        let moved = tool.moved(Vec3::new(0.001, 0.0, 0.0), Vec3::x());
        memory.begin_pass();
        crate::msm::side_hold::side_contact(&mut memory, slot, 0, &moved, &at, Some((-up, 0.001)), 1.0);
        let pull = side_friction(&mut memory, slot, 0, &moved, &at, &-up, 1.0, k, (0.5, 0.4));
        assert!((pull - Vec3::new(0.2, 0.0, 0.0)).norm() < 1e-12, "{pull:?}");
        // 4 mm further: 1 N > 0.5 N, it slides at 0.4 N, its anchor 2 mm ahead of it.
        let moved = tool.moved(Vec3::new(0.005, 0.0, 0.0), Vec3::x());
        memory.begin_pass();
        crate::msm::side_hold::side_contact(&mut memory, slot, 0, &moved, &at, Some((-up, 0.001)), 1.0);
        let pull = side_friction(&mut memory, slot, 0, &moved, &at, &-up, 1.0, k, (0.5, 0.4));
        assert!((pull - Vec3::new(0.4, 0.0, 0.0)).norm() < 1e-12, "{pull:?}");
        assert!((memory.anchor(slot, 0, &moved).unwrap() - (at + Vec3::new(0.002, 0.0, 0.0))).norm() < 1e-12);
        // Along the push it pulls nothing.
        let pull = side_friction(&mut memory, slot, 0, &moved, &(at + Vec3::new(0.002, 0.0, 0.0005)), &-up, 1.0, k, (0.5, 0.4));
        assert!(pull.norm() < 1e-12, "{pull:?}");
    }
}
