//! Internal forces of the mass-spring model (paper Eq. 2 and 4) and its energies.
//!
//! F_i = Σ_j k (|x_ij| − L0) x̂_ij + support_i + m_i g; the damping −α·m·v is applied
//! by the integrators (implicitly, so it never limits the time step). The residual
//! stress of Eq. 4 needs no separate term: springs rest at L/(1 + εr), so every spring
//! carries the prestress, and when a cut removes springs the remaining ones are no
//! longer balanced on the wound edge — exactly the σr force the paper adds.

use super::implicit::ImplicitSolver;
use super::state::{Nodes, Spring};
use crate::math::Vec3;

/// Resets the accumulators to the external forces (support and gravity), then adds the
/// springs. `spring_damping_s` > 0 adds β·k·(relative speed along the spring).
///
/// With `tangents`, the implicit integrator's tangent stiffness of every spring is
/// recorded in the same pass, while the spring's vector is at hand.
pub(crate) fn accumulate(
    nodes: &mut Nodes,
    springs: &[Spring],
    gravity: Option<Vec3>,
    spring_damping_s: f64,
    scratch: &mut SpringScratch,
    tangents: Option<&mut ImplicitSolver>,
) {
    let Nodes { x, v, f, mass, support, .. } = nodes;
    match gravity {
        Some(g) => {
            for ((f, s), m) in f.iter_mut().zip(support.iter()).zip(mass.iter()) {
                *f = s + g * *m;
            }
        }
        None => f.copy_from_slice(support),
    }
    if let Some(solver) = tangents {
        debug_assert_eq!(spring_damping_s, 0.0, "the implicit integrator damps the springs in its system");
        solver.begin_tangents(x.len(), springs.len());
        spring_forces(x, f, springs, scratch, |k, s, d, inv_len| solver.record_tangent(k, s, d, inv_len));
    } else if spring_damping_s > 0.0 {
        for s in springs {
            let (a, b) = (s.a as usize, s.b as usize);
            let d = x[b] - x[a];
            let len = d.norm();
            if len > 0.0 {
                let dir = d / len;
                let tension = s.k * (len - s.l0) + spring_damping_s * s.k * (v[b] - v[a]).dot(&dir);
                f[a] += dir * tension;
                f[b] -= dir * tension;
            }
        }
    } else {
        spring_forces(x, f, springs, scratch, |_, _, _, _| {});
    }
}

/// Adds the spring forces to `f`, in three passes: the spring vectors and squared
/// lengths (gathers), 1/length over a contiguous array (vectorised square roots and
/// divisions, off any dependency chain), then the forces. Springs are stored sorted by
/// their first node (they come from sorted edges; a cut's removal moves the last spring
/// into the hole it leaves, `SpringSet::remove`, and its new springs come last, so after
/// cuts the order holds between those places), so the force on that node is summed in a
/// register over each run of springs sharing it, which avoids a store → load chain on
/// `f[a]` (a run broken by a moved spring is only summed in more pieces). `each` sees every spring (its
/// index, the spring, its vector and its inverse length) in the force pass.
#[inline]
fn spring_forces(x: &[Vec3], f: &mut [Vec3], springs: &[Spring], scratch: &mut SpringScratch, mut each: impl FnMut(usize, &Spring, Vec3, f64)) {
    let n = springs.len();
    scratch.d.resize(n, Vec3::zeros());
    scratch.inv_len.resize(n, 0.0);
    for ((s, d), l2) in springs.iter().zip(scratch.d.iter_mut()).zip(scratch.inv_len.iter_mut()) {
        *d = x[s.b as usize] - x[s.a as usize];
        *l2 = d.norm_squared();
    }
    inverse_lengths(&mut scratch.inv_len);
    let mut current = u32::MAX;
    let mut on_current = Vec3::zeros();
    for (k, ((s, d), &inv_len)) in springs.iter().zip(&scratch.d).zip(&scratch.inv_len).enumerate() {
        each(k, s, *d, inv_len);
        let pull = d * (s.k * (1.0 - s.l0 * inv_len));
        if s.a != current {
            if current != u32::MAX {
                f[current as usize] += on_current;
            }
            current = s.a;
            on_current = pull;
        } else {
            on_current += pull;
        }
        f[s.b as usize] -= pull;
    }
    if current != u32::MAX {
        f[current as usize] += on_current;
    }
}

crate::solver::kernels::dispatch! {
    /// Squared lengths to inverse lengths, in place: a loop the compiler vectorizes, four
    /// lanes wide in the AVX2 clone (square roots and divisions are correctly rounded:
    /// the same bits at any width).
    pub fn inverse_lengths(l2: &mut [f64]) {
        for l in l2.iter_mut() {
            // max() keeps a zero-length spring at zero force instead of NaN, without a branch.
            *l = 1.0 / l.sqrt().max(1e-300);
        }
    }
}

/// Per-spring scratch of the force pass (sized to the springs; grows only after cuts).
#[derive(Debug, Clone, Default)]
pub(crate) struct SpringScratch {
    d: Vec<Vec3>,
    inv_len: Vec<f64>,
}


/// Kinetic energy, J.
pub(crate) fn kinetic_energy(nodes: &Nodes) -> f64 {
    nodes.v.iter().zip(&nodes.mass).map(|(v, m)| 0.5 * m * v.norm_squared()).sum()
}

/// Elastic energy of the springs plus the potential of the constant external forces
/// (support and gravity) measured from the reference positions, J.
pub(crate) fn potential_energy(nodes: &Nodes, springs: &[Spring], gravity: Option<Vec3>) -> f64 {
    let elastic: f64 = springs
        .iter()
        .map(|s| {
            let stretch = (nodes.x[s.b as usize] - nodes.x[s.a as usize]).norm() - s.l0;
            0.5 * s.k * stretch * stretch
        })
        .sum();
    let external: f64 = (0..nodes.len())
        .filter(|&i| nodes.alive[i])
        .map(|i| {
            let weight = gravity.map_or(Vec3::zeros(), |g| g * nodes.mass[i]);
            -(nodes.support[i] + weight).dot(&(nodes.x[i] - nodes.x_ref[i]))
        })
        .sum();
    elastic + external
}
