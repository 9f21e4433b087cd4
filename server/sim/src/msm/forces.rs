//! Internal forces of the mass-spring model (paper Eq. 2 and 4) and its energies.
//!
//! F_i = Σ_j k (|x_ij| − L0) x̂_ij + support_i + m_i g; the damping −α·m·v is applied
//! by the integrators (implicitly, so it never limits the time step). The residual
//! stress of Eq. 4 needs no separate term: springs rest at L/(1 + εr), so every spring
//! carries the prestress, and when a cut removes springs the remaining ones are no
//! longer balanced on the wound edge — exactly the σr force the paper adds.

use super::state::{Nodes, Spring};
use crate::math::Vec3;

/// Resets the accumulators to the external forces (support and gravity), then adds the
/// springs. `spring_damping_s` > 0 adds β·k·(relative speed along the spring).
pub(crate) fn accumulate(nodes: &mut Nodes, springs: &[Spring], gravity: Option<Vec3>, spring_damping_s: f64) {
    let Nodes { x, v, f, mass, support, .. } = nodes;
    match gravity {
        Some(g) => {
            for ((f, s), m) in f.iter_mut().zip(support.iter()).zip(mass.iter()) {
                *f = s + g * *m;
            }
        }
        None => f.copy_from_slice(support),
    }
    if spring_damping_s > 0.0 {
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
        for s in springs {
            let (a, b) = (s.a as usize, s.b as usize);
            let d = x[b] - x[a];
            let len = d.norm();
            if len > 0.0 {
                let pull = d * (s.k * (len - s.l0) / len);
                f[a] += pull;
                f[b] -= pull;
            }
        }
    }
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
