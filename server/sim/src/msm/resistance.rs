//! Cutting that resists (docs/tool-tissue.md): the force a blade needs to part the
//! skin, from the material's fracture toughness.
//!
//! A cut advances only where the blade's edge leads: the blade's motion relative to the
//! skin, in the skin's plane, within [`MAX_EDGE_ANGLE_DEG`] of the direction its edge
//! faces. Drawn sideways (a flat leading) or backwards (the spine leading) the blade
//! does not cut; its contact pushes the skin instead.
//!
//! While the edge cuts, the skin resists with the work of fracture: advancing the cut by
//! a distance d through skin of thickness t creates d·t of crack, which costs J·d·t, so
//! the force along the cut is J·t. Slicing — the blade also moving along its own edge
//! line, which for a blade crossing a membrane is its axis — needs less: with the
//! slice–push ratio ξ (speed along the edge line over speed into the cut) we take
//! F = J·t / √(1 + ξ²), the push force falling as slicing grows as Atkins, Xu &
//! Jeronimidis (2004) measured (a model, not their formula). Below a creep speed the
//! force fades linearly to zero, so that a blade held still in its cut feels none and
//! the direction never flips at rest.
//!
//! Before any of this the blade must get in: pressed tip first against intact skin
//! (held by [`super::hold`]), it punctures when it presses with
//! [`puncture_force_n`].

use crate::math::{Vec3, across};

/// The force with which a blade's tip must press intact skin to go through it, N: the
/// work of opening a crack as wide as the blade, `blade_width_m`, while the tip travels
/// through the skin's thickness t is J·w·t, spent over that travel t, so F = J·w. This
/// is the fracture term of the model of deep penetration by sharp punches (Shergold and
/// Fleck, Proc. R. Soc. A 460:3037, 2004), without its elastic term: the skin's
/// elastic resistance before the puncture is the held contact's own force. With the
/// default scene's J = 1.1 kJ/m² and a 1 mm scalpel: 1.1 N.
pub fn puncture_force_n(toughness_j_per_m2: f64, blade_width_m: f64) -> f64 {
    toughness_j_per_m2 * blade_width_m
}

/// The largest angle between the blade's motion and its edge's facing that still cuts.
pub const MAX_EDGE_ANGLE_DEG: f64 = 60.0;

/// Below this speed against the skin the cutting force fades to zero, m/s.
pub const CREEP_SPEED_M_PER_S: f64 = 0.002;

/// How a blade moves through the skin at its crossing point this step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct BladeMotion {
    /// The blade's velocity at the crossing minus the skin's there, m/s.
    pub relative_velocity: Vec3,
    /// The skin's unit normal at the crossing.
    pub normal: Vec3,
    /// The direction the blade's edge faces (world, unit).
    pub edge: Vec3,
    /// The blade's axis (world, unit): its edge line.
    pub axis: Vec3,
}

/// What the skin does to a blade this step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Resistance {
    /// Whether the edge leads, so that the cut may advance.
    pub cuts: bool,
    /// The force of the skin on the blade, N (opposite the motion in the skin's plane).
    pub force_n: Vec3,
    /// The slice–push ratio ξ of the motion (0 when not cutting).
    pub slice_push_ratio: f64,
}

impl Resistance {
    pub const NONE: Resistance = Resistance { cuts: false, force_n: Vec3::new(0.0, 0.0, 0.0), slice_push_ratio: 0.0 };
}

/// The resistance of skin of `thickness_m` and fracture toughness `toughness_j_per_m2`
/// to a blade moving as `motion` says.
pub fn resistance(motion: &BladeMotion, toughness_j_per_m2: f64, thickness_m: f64) -> Resistance {
    let n = motion.normal;
    let in_plane = |v: Vec3| across(&v, &n);
    let v_plane = in_plane(motion.relative_velocity);
    let speed = v_plane.norm();
    let edge_plane = in_plane(motion.edge);
    if speed <= 0.0 || edge_plane.norm() < 1e-6 {
        return Resistance::NONE;
    }
    let (direction, facing) = (v_plane / speed, edge_plane.normalize());
    if direction.dot(&facing) < MAX_EDGE_ANGLE_DEG.to_radians().cos() {
        return Resistance::NONE;
    }
    let push = speed;
    let slice = motion.relative_velocity.dot(&motion.axis).abs();
    let ratio = slice / push;
    let creep = (speed / CREEP_SPEED_M_PER_S).min(1.0);
    let magnitude = toughness_j_per_m2 * thickness_m / (1.0 + ratio * ratio).sqrt() * creep;
    Resistance { cuts: true, force_n: -direction * magnitude, slice_push_ratio: ratio }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn motion(velocity: Vec3, edge: Vec3) -> BladeMotion {
        BladeMotion { relative_velocity: velocity, normal: Vec3::z(), edge, axis: Vec3::z() }
    }

    #[test]
    fn pushing_along_the_edge_costs_toughness_times_thickness() {
        let r = resistance(&motion(Vec3::new(0.01, 0.0, 0.0), Vec3::x()), 1000.0, 0.002);
        assert!(r.cuts);
        assert!((r.force_n - Vec3::new(-2.0, 0.0, 0.0)).norm() < 1e-12, "{:?}", r.force_n);
    }

    #[test]
    fn sideways_and_backwards_do_not_cut() {
        for velocity in [Vec3::new(0.0, 0.01, 0.0), Vec3::new(-0.01, 0.0, 0.0), Vec3::new(0.004, 0.01, 0.0)] {
            let r = resistance(&motion(velocity, Vec3::x()), 1000.0, 0.002);
            assert!(!r.cuts && r.force_n == Vec3::zeros(), "{velocity:?}");
        }
        // Within 60° of the edge: cuts.
        assert!(resistance(&motion(Vec3::new(0.01, 0.015, 0.0), Vec3::x()), 1000.0, 0.002).cuts);
    }

    #[test]
    fn slicing_needs_less_force_and_a_still_blade_none() {
        let press = resistance(&motion(Vec3::new(0.01, 0.0, 0.0), Vec3::x()), 1000.0, 0.002).force_n.norm();
        let slice = resistance(&motion(Vec3::new(0.01, 0.0, 0.02), Vec3::x()), 1000.0, 0.002);
        assert!((slice.slice_push_ratio - 2.0).abs() < 1e-12);
        assert!((slice.force_n.norm() - press / 5f64.sqrt()).abs() < 1e-12);
        let creeping = resistance(&motion(Vec3::new(0.001, 0.0, 0.0), Vec3::x()), 1000.0, 0.002).force_n.norm();
        assert!((creeping - 0.5 * press).abs() < 1e-12);
        assert_eq!(resistance(&motion(Vec3::zeros(), Vec3::x()), 1000.0, 0.002), Resistance::NONE);
    }
}
