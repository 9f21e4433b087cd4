//! Cutting that resists, for the branched grid (docs/branched-grid.md, "Cutting that
//! resists"): the force a blade needs to part the tissue, from its materials' fracture
//! toughness.
//!
//! A blade moving a distance s with a depth d of it in the tissue opens a crack of d·s
//! (the area of the cut face), which costs J·d·s: the force against its motion is J·d,
//! as for the skin (J·t); for a cutting capsule of radius r whose tip is d deep, the
//! depth engaged is d + r (its round end cuts too). The depth engaged is read from what
//! the cut removes: the
//! extent, along the blade's axis, of the voxels its cutting capsule removed over the
//! last [`WINDOW_STEPS`] steps (a step removes a few voxels at a time, somewhere across
//! the depth; a few steps' worth span it). The removed
//! volume would not do: soft tissue gives way before the blade, so it removes a slot
//! narrower than its capsule (on a 6 kPa block, 10 voxels a millimetre where the
//! capsule sweeps 26) and the volume over the capsule's width read 2.6 times low. In
//! such soft tissue the blade drags the tissue ahead of it and the slot lags behind the
//! capsule; the extent it removes over the window, and with it the force, is then less
//! than the nominal depth (0.59 N for J·(d + r) = 1.64 N on that block; on a 30 kPa
//! block 1.71 N for 1.64 N).
//!
//! Voxels go whole, in bursts, as their centres enter the capsule; J·d is therefore
//! averaged over the steps that removed some ([`AVERAGING_TIME_S`], exponentially) and
//! held between them, fading once the blade has removed nothing for [`IDLE_S`] (it left
//! the tissue, or stopped). Below a creep speed the force fades to zero (a blade held
//! still in its cut feels none, and the direction never flips at rest), as the skin's.
//!
//! Only the edge parts tough tissue, as on the skin: a blade moving across its axis cuts
//! a material with a fracture toughness only where its edge leads, its motion across the
//! axis within [`MAX_EDGE_ANGLE_DEG`] of the direction the edge faces ([`edge_leads`]).
//! Moving along its own line — the point going in, or the blade drawn out along its
//! edge — it cuts (the point and the edge lead). Drawn sideways or backwards the blade
//! pushes the tissue with its flat or its back instead, and holds it as a probe does.

use crate::math::Vec3;
use crate::msm::resistance::{CREEP_SPEED_M_PER_S, MAX_EDGE_ANGLE_DEG};

/// A blade moving within this angle of its own axis moves along its line: its point
/// (going in) or its edge (drawn out) leads, deg.
pub const ALONG_AXIS_DEG: f64 = 30.0;

/// Whether a blade whose axis is `axis` and whose edge faces `edge` (unit, across the
/// axis), moving by `motion` over a step of `dt_s`, leads with its edge or its point
/// (so that it cuts tough tissue). None when it moved slower than the creep speed: too
/// little to say (the stroke keeps what it last was).
pub fn edge_leads(motion: &Vec3, axis: &Vec3, edge: &Vec3, dt_s: f64) -> Option<bool> {
    let travel = motion.norm();
    if travel < CREEP_SPEED_M_PER_S * dt_s {
        return None;
    }
    let along = motion.dot(axis);
    let across = motion - axis * along;
    if across.norm() <= along.abs() * ALONG_AXIS_DEG.to_radians().tan() {
        return Some(true);
    }
    Some(across.dot(edge) >= across.norm() * MAX_EDGE_ANGLE_DEG.to_radians().cos())
}

/// The time over which J·d is averaged, s.
pub const AVERAGING_TIME_S: f64 = 0.02;
/// The steps whose removed voxels together give the depth engaged.
pub const WINDOW_STEPS: usize = 32;
/// After this long without a removal the resistance fades (over the averaging time), s.
pub const IDLE_S: f64 = 0.05;

/// One cutting tool's averaged resistance over its current stroke.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct CutResistance {
    /// Averaged J·d, N.
    level_n: f64,
    /// Time since the last step that removed voxels, s.
    idle_s: f64,
    /// The last [`WINDOW_STEPS`] steps' removals, a ring: where along the blade they
    /// spanned (m) and their mean toughness (J/m²); None where a step removed none.
    recent: [Option<Removed>; WINDOW_STEPS],
    next: usize,
}

/// The voxels one step removed: their extent along the blade (from its tip, m) and their
/// materials' mean toughness (J/m²).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Removed {
    pub lo_m: f64,
    pub hi_m: f64,
    pub toughness_j_per_m2: f64,
}

impl crate::hash::HashState for CutResistance {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        (self.level_n, self.idle_s, self.next).hash_state(h);
        for removed in &self.recent {
            removed.map(|r| (r.lo_m, r.hi_m, r.toughness_j_per_m2)).hash_state(h);
        }
    }
}

impl CutResistance {
    /// After a step of `dt_s` in which the blade moved by `motion` (m) and removed
    /// `removed` (voxels `voxel_m` across), the tissue's force on it (N, in `motion`'s
    /// frame).
    pub fn step(&mut self, motion: Vec3, removed: Option<Removed>, voxel_m: f64, dt_s: f64) -> Vec3 {
        let share = 1.0 - (-dt_s / AVERAGING_TIME_S).exp();
        self.recent[self.next] = removed;
        self.next = (self.next + 1) % WINDOW_STEPS;
        match removed.map(|_| self.window_level_n(voxel_m)) {
            Some(level) => {
                // The first removal of a stroke starts from its own level.
                self.level_n = if self.level_n == 0.0 { level } else { self.level_n + share * (level - self.level_n) };
                self.idle_s = 0.0;
            }
            None => {
                self.idle_s += dt_s;
                if self.idle_s > IDLE_S {
                    self.level_n -= share * self.level_n;
                }
            }
        }
        let travel = motion.norm();
        if travel <= 0.0 {
            return Vec3::zeros();
        }
        let creep = (travel / dt_s / CREEP_SPEED_M_PER_S).min(1.0);
        -motion / travel * (self.level_n * creep)
    }

    /// J·d over the window: the removals' extent along the blade plus a voxel, times
    /// their mean toughness.
    fn window_level_n(&self, voxel_m: f64) -> f64 {
        let (mut lo, mut hi, mut toughness, mut count) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0u32);
        for r in self.recent.iter().flatten() {
            lo = lo.min(r.lo_m);
            hi = hi.max(r.hi_m);
            toughness += r.toughness_j_per_m2;
            count += 1;
        }
        toughness / f64::from(count.max(1)) * (hi - lo + voxel_m).max(0.0)
    }
}

/// What a step removed: `along` gives each removed voxel's position along the blade's
/// axis (m) and its material's toughness (J/m²). None when none was removed.
pub fn removed(along: impl Iterator<Item = (f64, f64)>) -> Option<Removed> {
    let (mut lo, mut hi, mut toughness, mut count) = (f64::INFINITY, f64::NEG_INFINITY, 0.0, 0usize);
    for (u, j) in along {
        lo = lo.min(u);
        hi = hi.max(u);
        toughness += j;
        count += 1;
    }
    (count > 0).then(|| Removed { lo_m: lo, hi_m: hi, toughness_j_per_m2: toughness / count as f64 })
}

#[cfg(test)]
mod tests {
    use super::*;

    const VOXEL: f64 = 1e-3;

    #[test]
    fn only_the_edge_or_the_point_leading_cuts() {
        let (axis, edge, dt) = (Vec3::z(), Vec3::x(), 1e-3);
        let leads = |motion: Vec3| edge_leads(&(motion * 1e-4), &axis, &edge, dt);
        // Edge first, within 60° of it; sideways, backwards and past 60°: the flat or back.
        assert_eq!(leads(Vec3::x()), Some(true));
        assert_eq!(leads(Vec3::new(1.0, 1.6, 0.0)), Some(true));
        assert_eq!(leads(Vec3::new(1.0, 1.8, 0.0)), Some(false));
        assert_eq!(leads(Vec3::y()), Some(false));
        assert_eq!(leads(-Vec3::x()), Some(false));
        // Along its own line, in or out, even drifting a little sideways: it cuts.
        assert_eq!(leads(-Vec3::z()), Some(true));
        assert_eq!(leads(Vec3::new(0.0, 0.5, 1.0)), Some(true));
        assert_eq!(leads(Vec3::new(0.0, 0.7, -1.0)), Some(false));
        // Slower than the creep speed (2 mm/s, 2 µm a step): no say.
        assert_eq!(edge_leads(&Vec3::new(0.0, 1.5e-6, 0.0), &axis, &edge, dt), None);
    }

    #[test]
    fn the_depth_is_the_window_of_removals_extent_along_the_blade_and_the_toughness_their_mean() {
        assert_eq!(removed(std::iter::empty()), None);
        let r = removed([(2e-3, 100.0), (5e-3, 300.0)].into_iter()).unwrap();
        assert_eq!((r.lo_m, r.hi_m, r.toughness_j_per_m2), (2e-3, 5e-3, 200.0));
        // Three steps removing voxels at 0–2, 4–6 and 7–9 mm: 10 mm engaged.
        let mut resistance = CutResistance::default();
        let mut force = Vec3::zeros();
        for (lo, hi) in [(0.0, 2e-3), (4e-3, 6e-3), (7e-3, 9e-3)] {
            force = resistance.step(Vec3::new(1e-4, 0.0, 0.0), Some(Removed { lo_m: lo, hi_m: hi, toughness_j_per_m2: 200.0 }), VOXEL, 1e-3);
        }
        assert!(force.x < 0.0 && (resistance.window_level_n(VOXEL) - 200.0 * 0.01).abs() < 1e-12);
    }

    #[test]
    fn a_steady_cut_feels_toughness_times_depth_against_its_motion_however_bursty() {
        // Every third step removes a few voxels somewhere across 10 mm of J = 200 J/m².
        let step = Vec3::new(1e-4, 0.0, 0.0);
        let mut resistance = CutResistance::default();
        let mut forces = Vec::new();
        for k in 0..400u32 {
            let at = f64::from((k / 3 * 7) % 9) * 1e-3;
            let cut = (k % 3 == 0).then_some(Removed { lo_m: at, hi_m: at + 1e-3, toughness_j_per_m2: 200.0 });
            forces.push(resistance.step(step, cut, VOXEL, 1e-3));
        }
        let settled = &forces[100..];
        let mean = -settled.iter().map(|f| f.x).sum::<f64>() / settled.len() as f64;
        assert!((mean - 2.0).abs() < 0.2, "mean {mean} N against J·d = 2 N");
        assert!(settled.iter().all(|f| f.y == 0.0 && f.z == 0.0 && -f.x > 1.6 && -f.x < 2.4), "steady against the motion");
    }

    #[test]
    fn a_blade_held_still_feels_nothing_and_one_out_of_the_tissue_soon_nothing() {
        let mut resistance = CutResistance::default();
        let full = Removed { lo_m: 0.0, hi_m: 9e-3, toughness_j_per_m2: 200.0 };
        for _ in 0..50 {
            resistance.step(Vec3::new(1e-4, 0.0, 0.0), Some(full), VOXEL, 1e-3);
        }
        assert_eq!(resistance.step(Vec3::zeros(), None, VOXEL, 1e-3), Vec3::zeros());
        let creeping = resistance.step(Vec3::new(1e-6, 0.0, 0.0), None, VOXEL, 1e-3).norm();
        assert!(creeping < 0.6 * 2.0, "1 mm/s against the 2 mm/s creep speed: {creeping}");
        // Moving on without removing anything (out of the tissue): held for IDLE_S, then gone.
        let forces: Vec<f64> = (0..300).map(|_| resistance.step(Vec3::new(1e-4, 0.0, 0.0), None, VOXEL, 1e-3).norm()).collect();
        assert!(forces[10] > 1.9 && forces[299] < 0.01, "{} then {}", forces[10], forces[299]);
    }
}
