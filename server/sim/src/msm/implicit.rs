//! Linearised backward Euler (Baraff & Witkin 1998) solved by preconditioned conjugate
//! gradient, warm-started with the previous step's solution.
//!
//! (M(1 + hα) + hC + (h² + hβ)K) Δv = h(F − αMv − Cv) − h(h + β)K v,  v ← v + Δv,  x ← x + h·v,
//! with K = −∂F/∂x of the springs, contacts and foundation, and C the foundation's drag. Each spring's tangent is
//! k[n nᵀ + max(0, 1 − L0/L)(I − n nᵀ)]: the geometric part is clamped at zero in
//! compression so that K stays positive semi-definite and CG applies. Fixed axes are
//! filtered out of the system. Matrix-free: nothing is assembled, nothing allocated.

use super::contact::Contact;
use super::foundation::Foundation;
use super::state::{Nodes, Spring};
use crate::math::Vec3;

#[derive(Debug, Clone, Copy, Default)]
struct SpringTangent {
    n: Vec3,
    axial: f64,
    lateral: f64,
}

/// Scratch space and settings of the implicit integrator.
#[derive(Debug, Clone, Default)]
pub(crate) struct ImplicitSolver {
    pub max_iterations: u32,
    pub tolerance: f64,
    dv: Vec<Vec3>,
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
    b: Vec<Vec3>,
    inv_diag: Vec<Vec3>,
    tangents: Vec<SpringTangent>,
    /// Iterations used by the last solve.
    pub last_iterations: u32,
    /// Relative residual reached by the last solve.
    pub last_residual: f64,
}

impl ImplicitSolver {
    pub fn new(max_iterations: u32, tolerance: f64) -> Self {
        Self { max_iterations, tolerance, ..Default::default() }
    }

    /// Sizes the scratch for `nodes` nodes and `springs` springs (allocates only when they grew).
    pub fn reserve(&mut self, nodes: usize, springs: usize) {
        for buf in [&mut self.dv, &mut self.r, &mut self.z, &mut self.p, &mut self.q, &mut self.b, &mut self.inv_diag] {
            buf.resize(nodes, Vec3::zeros());
        }
        self.tangents.resize(springs, SpringTangent::default());
    }

    /// One implicit step. `nodes.f` must hold the forces at the current state (springs,
    /// support, gravity, contacts). Returns the finite-check sum (see `explicit::substep`).
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        nodes: &mut Nodes,
        springs: &[Spring],
        contacts: &[Contact],
        foundation: Option<&Foundation>,
        h: f64,
        mass_damping_per_s: f64,
        spring_damping_s: f64,
    ) -> f64 {
        let n = nodes.len();
        self.reserve(n, springs.len());
        let mass_coef = 1.0 + h * mass_damping_per_s;
        let stiff_coef = h * h + h * spring_damping_s;

        for (t, s) in self.tangents.iter_mut().zip(springs) {
            let d = nodes.x[s.b as usize] - nodes.x[s.a as usize];
            let len = d.norm();
            *t = if len > 0.0 {
                SpringTangent { n: d / len, axial: s.k, lateral: s.k * (1.0 - s.l0 / len).max(0.0) }
            } else {
                SpringTangent { n: Vec3::zeros(), axial: 0.0, lateral: s.k }
            };
        }

        // Right-hand side: h(F − αMv − Cv) − h(h + β)Kv, using q as scratch for Kv (and
        // z for Cv).
        apply_stiffness(&self.tangents, springs, contacts, foundation, &nodes.v, &mut self.q);
        if let Some(foundation) = foundation {
            self.z.iter_mut().for_each(|x| *x = Vec3::zeros());
            foundation.add_damping_product(&nodes.v, &mut self.z, 1.0);
            for i in 0..n {
                nodes.f[i] -= self.z[i];
            }
        }
        for i in 0..n {
            let rhs = (nodes.f[i] - nodes.v[i] * (mass_damping_per_s * nodes.mass[i])) * h
                - self.q[i] * (h * (h + spring_damping_s));
            self.b[i] = rhs.component_mul(&nodes.free[i]);
        }

        // Jacobi preconditioner.
        for i in 0..n {
            self.inv_diag[i] = Vec3::repeat(nodes.mass[i] * mass_coef);
        }
        for (t, s) in self.tangents.iter().zip(springs) {
            let d = (t.n.component_mul(&t.n) * (t.axial - t.lateral)).add_scalar(t.lateral) * stiff_coef;
            self.inv_diag[s.a as usize] += d;
            self.inv_diag[s.b as usize] += d;
        }
        for c in contacts {
            self.inv_diag[c.node as usize] += c.normal.component_mul(&c.normal) * (c.stiffness * stiff_coef);
        }
        if let Some(foundation) = foundation {
            for i in 0..n {
                self.inv_diag[i] += foundation.diagonal(i, stiff_coef, h);
            }
        }
        for i in 0..n {
            let d = self.inv_diag[i];
            self.inv_diag[i] = Vec3::new(inv_or_zero(d.x), inv_or_zero(d.y), inv_or_zero(d.z)).component_mul(&nodes.free[i]);
        }

        // PCG on A·dv = b, starting from the previous solution. Node passes are fused so
        // that an iteration is one pass over the springs and two over the nodes.
        for i in 0..n {
            self.dv[i] = self.dv[i].component_mul(&nodes.free[i]);
        }
        let coefficients = Coefficients { mass: mass_coef, stiffness: stiff_coef, drag: h };
        apply_a(&self.tangents, springs, contacts, foundation, nodes, coefficients, &self.dv, &mut self.q);
        let b_norm = dot(&self.b, &self.b).sqrt();
        let mut rz = 0.0;
        let mut rr = 0.0;
        for i in 0..n {
            let r = self.b[i] - self.q[i];
            let z = r.component_mul(&self.inv_diag[i]);
            self.r[i] = r;
            self.z[i] = z;
            self.p[i] = z;
            rz += r.dot(&z);
            rr += r.norm_squared();
        }
        let mut iterations = 0;
        let mut residual = if b_norm > 0.0 { rr.sqrt() / b_norm } else { 0.0 };
        if b_norm == 0.0 {
            self.dv.iter_mut().for_each(|x| *x = Vec3::zeros());
        }
        while b_norm > 0.0 && residual > self.tolerance && iterations < self.max_iterations {
            let pq = apply_a(&self.tangents, springs, contacts, foundation, nodes, coefficients, &self.p, &mut self.q);
            if pq <= 0.0 || !pq.is_finite() {
                break;
            }
            let alpha = rz / pq;
            let (mut rz_next, mut rr_next) = (0.0, 0.0);
            for i in 0..n {
                self.dv[i] += self.p[i] * alpha;
                let r = self.r[i] - self.q[i] * alpha;
                let z = r.component_mul(&self.inv_diag[i]);
                self.r[i] = r;
                self.z[i] = z;
                rz_next += r.dot(&z);
                rr_next += r.norm_squared();
            }
            let beta = rz_next / rz;
            rz = rz_next;
            for i in 0..n {
                self.p[i] = self.z[i] + self.p[i] * beta;
            }
            iterations += 1;
            residual = rr_next.sqrt() / b_norm;
        }
        self.last_iterations = iterations;
        self.last_residual = residual;

        let mut check = 0.0;
        for i in 0..n {
            let v = nodes.v[i] + self.dv[i];
            nodes.v[i] = v;
            nodes.x[i] += v * h;
            check += nodes.x[i].x + nodes.x[i].y + nodes.x[i].z + v.x + v.y + v.z;
        }
        check
    }

    /// Forgets the warm start (after a blow-up or a reset).
    pub fn reset_warm_start(&mut self) {
        self.dv.iter_mut().for_each(|x| *x = Vec3::zeros());
    }
}

fn inv_or_zero(d: f64) -> f64 {
    if d > 0.0 { 1.0 / d } else { 0.0 }
}

fn dot(a: &[Vec3], b: &[Vec3]) -> f64 {
    a.iter().zip(b).map(|(x, y)| x.dot(y)).sum()
}

#[derive(Debug, Clone, Copy)]
struct Coefficients {
    /// 1 + hα: multiplies the mass.
    mass: f64,
    /// h² + hβ: multiplies the stiffness.
    stiffness: f64,
    /// h: multiplies the foundation's drag.
    drag: f64,
}

/// out = A·p = (M(1 + hα) + hC + (h² + hβ)K)·p on free axes; returns p·out.
#[allow(clippy::too_many_arguments)]
fn apply_a(
    tangents: &[SpringTangent],
    springs: &[Spring],
    contacts: &[Contact],
    foundation: Option<&Foundation>,
    nodes: &Nodes,
    c: Coefficients,
    p: &[Vec3],
    out: &mut [Vec3],
) -> f64 {
    apply_stiffness(tangents, springs, contacts, foundation, p, out);
    if let Some(foundation) = foundation {
        // (h² + hβ)K p + hC p = (h² + hβ)(K p + h/(h² + hβ) C p).
        foundation.add_damping_product(p, out, c.drag / c.stiffness);
    }
    let mut p_dot_out = 0.0;
    for i in 0..p.len() {
        let a = (out[i] * c.stiffness + p[i] * (nodes.mass[i] * c.mass)).component_mul(&nodes.free[i]);
        out[i] = a;
        p_dot_out += p[i].dot(&a);
    }
    p_dot_out
}

/// out = K·p for the springs, contacts and foundation. As in the force pass, the product
/// on each spring's first node is summed in a register over runs of springs sharing it.
fn apply_stiffness(tangents: &[SpringTangent], springs: &[Spring], contacts: &[Contact], foundation: Option<&Foundation>, p: &[Vec3], out: &mut [Vec3]) {
    out.iter_mut().for_each(|x| *x = Vec3::zeros());
    let mut current = u32::MAX;
    let mut on_current = Vec3::zeros();
    for (t, s) in tangents.iter().zip(springs) {
        let d = p[s.b as usize] - p[s.a as usize];
        let kd = d * t.lateral + t.n * ((t.axial - t.lateral) * t.n.dot(&d));
        if s.a != current {
            if current != u32::MAX {
                out[current as usize] -= on_current;
            }
            current = s.a;
            on_current = kd;
        } else {
            on_current += kd;
        }
        out[s.b as usize] += kd;
    }
    if current != u32::MAX {
        out[current as usize] -= on_current;
    }
    for c in contacts {
        let i = c.node as usize;
        out[i] += c.normal * (c.stiffness * c.normal.dot(&p[i]));
    }
    if let Some(foundation) = foundation {
        foundation.add_stiffness_product(p, out);
    }
}
