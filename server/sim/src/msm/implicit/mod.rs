//! Linearised backward Euler (Baraff & Witkin 1998) solved by preconditioned conjugate
//! gradient, warm-started with the previous step's solution.
//!
//! (M(1 + hα) + hC + (h² + hβ)K) Δv = h(F − αMv − Cv) − h(h + β)K v,  v ← v + Δv,  x ← x + h·v,
//! with K = −∂F/∂x of the springs, contacts and foundation, and C the foundation's drag. Each spring's tangent is
//! k[n nᵀ + max(0, 1 − L0/L)(I − n nᵀ)]: the geometric part is clamped at zero in
//! compression so that K stays positive semi-definite and CG applies. Fixed axes are
//! filtered out of the system. Matrix-free: nothing is assembled, nothing allocated.
//!
//! A product with the system is one pass over the springs and one over the nodes,
//! reading little: a spring's tangent (`lateral·I + excess·n nᵀ`, with its node ids) is
//! recorded by the force pass while it has the spring's vector at hand, and each node's
//! own terms (mass, foundation stiffness and drag) are folded into one isotropic
//! coefficient and one along its normal, once per step. The step's first pass over the
//! springs makes K·v (for the right-hand side) and K·Δv₀ (for the first residual) at
//! once; everything else the first residual needs is one pass over the nodes. The
//! spring passes are compiled for the baseline and for AVX2, with the same bits.
//!
//! The preconditioner is Jacobi, and on large patches ([`region`]) symmetric block
//! Gauss–Seidel sweeps over the nodes round where the step's first residual sits (a
//! tool's contacts, a cut): there the conjugate gradient otherwise spends its
//! iterations carrying a local disturbance outwards ring by ring. On the 10k-node patch
//! with the blade cutting a step's iterations fall from 19.7 to 17.0 (docs/benchmarks.md:
//! the wound's opening moves the whole patch, which no local sweep reaches).

mod region;

use super::contact::Contact;
use super::foundation::Foundation;
use super::state::{Nodes, Spring};
use crate::math::{Matrix3, Vec3};
use crate::solver::kernels::{self, flat, flat_mut};

/// A 3 × 3 block `iso·I + along·n nᵀ` (n unit, or zero): a spring's tangent stiffness
/// (its lateral stiffness, and the axial stiffness's excess over it along the spring), a
/// node's own terms (its mass and the foundation's drag, and the foundation's stiffness
/// along its normal), a region's coupling (region.rs). Products read five numbers, not
/// nine.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct AxialBlock {
    iso: f64,
    along: f64,
    n: Vec3,
}

impl AxialBlock {
    /// The block times `d`.
    #[inline(always)]
    fn times(&self, d: Vec3) -> Vec3 {
        d * self.iso + self.n * (self.along * self.n.dot(&d))
    }

    /// Its diagonal.
    fn diagonal(&self) -> Vec3 {
        (self.n.component_mul(&self.n) * self.along).add_scalar(self.iso)
    }

    /// The block as a matrix.
    fn matrix(&self) -> Matrix3<f64> {
        Matrix3::identity() * self.iso + self.n * self.n.transpose() * self.along
    }

    /// The block times `s`.
    fn scaled(&self, s: f64) -> AxialBlock {
        AxialBlock { iso: self.iso * s, along: self.along * s, n: self.n }
    }
}

/// A spring's tangent stiffness with its nodes: what a product with the system reads of
/// a spring.
#[derive(Debug, Clone, Copy, Default)]
pub(crate) struct SpringTangent {
    a: u32,
    b: u32,
    k: AxialBlock,
}

impl SpringTangent {
    /// K_s·d for the difference d of the spring's nodes' vectors.
    #[inline(always)]
    fn times(&self, d: Vec3) -> Vec3 {
        self.k.times(d)
    }
}

/// A node's own part of the system (its mass, the foundation's stiffness and drag).
pub(crate) type NodeTerm = AxialBlock;

/// Scratch space and settings of the implicit integrator.
#[derive(Debug, Clone, Default)]
pub(crate) struct ImplicitSolver {
    pub max_iterations: u32,
    pub tolerance: f64,
    dv: Vec<Vec3>,
    r: Vec<Vec3>,
    /// The preconditioned residual.
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
    inv_diag: Vec<Vec3>,
    node_terms: Vec<NodeTerm>,
    tangents: Vec<SpringTangent>,
    /// Where the step's disturbance is swept (region.rs).
    region: region::Region,
    /// The force pass has recorded the tangents since the last step used them.
    tangents_fresh: bool,
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
        for buf in [&mut self.dv, &mut self.r, &mut self.z, &mut self.p, &mut self.q, &mut self.inv_diag] {
            buf.resize(nodes, Vec3::zeros());
        }
        self.node_terms.resize(nodes, NodeTerm::default());
        self.tangents.resize(springs, SpringTangent::default());
    }

    /// Starts a step's tangents: sizes the scratch, clears the diagonal.
    pub fn begin_tangents(&mut self, nodes: usize, springs: usize) {
        self.reserve(nodes, springs);
        self.inv_diag.iter_mut().for_each(|x| *x = Vec3::zeros());
        self.tangents_fresh = true;
    }

    /// Records spring `k`'s tangent from its vector `d` (b − a) and inverse length, and
    /// adds it to the diagonal (still unscaled: `step` finishes it). The force pass calls
    /// it for every spring, in order, after [`Self::begin_tangents`].
    #[inline(always)]
    pub fn record_tangent(&mut self, k: usize, s: &Spring, d: Vec3, inv_len: f64) {
        let (n, lateral) = if inv_len < 1e299 {
            (d * inv_len, s.k * (1.0 - s.l0 * inv_len).max(0.0))
        } else {
            // A spring of zero length resists in every direction alike.
            (Vec3::zeros(), s.k)
        };
        let t = SpringTangent { a: s.a, b: s.b, k: AxialBlock { iso: lateral, along: s.k - lateral, n } };
        self.tangents[k] = t;
        let diagonal = t.k.diagonal();
        self.inv_diag[s.a as usize] += diagonal;
        self.inv_diag[s.b as usize] += diagonal;
    }

    /// One implicit step. `nodes.f` must hold the forces at the current state (springs,
    /// support, gravity, contacts), and the springs' tangents must have been recorded
    /// by the force pass at the current positions. Returns the finite-check sum (see
    /// `explicit::substep`).
    #[allow(clippy::too_many_arguments)]
    pub fn step(
        &mut self,
        nodes: &mut Nodes,
        springs: &[Spring],
        contacts: &[Contact],
        foundation: Option<&Foundation>,
        springs_version: u64,
        h: f64,
        mass_damping_per_s: f64,
        spring_damping_s: f64,
    ) -> f64 {
        let n = nodes.len();
        assert!(std::mem::take(&mut self.tangents_fresh) && self.tangents.len() == springs.len(), "the force pass records every spring's tangent before the implicit step");
        assert_eq!(self.dv.len(), n, "the force pass sized the scratch for these nodes");
        let mass_coef = 1.0 + h * mass_damping_per_s;
        let stiff_coef = h * h + h * spring_damping_s;

        for c in contacts {
            self.inv_diag[c.node as usize] += c.normal.component_mul(&c.normal) * c.stiffness;
            // Its spring's rest point moves at the drive's velocity over the step.
            nodes.f[c.node as usize] += c.normal * (c.stiffness * (h + spring_damping_s) * c.drive_m_per_s);
        }

        // The warm start (the previous solution) on this step's free axes, and the
        // springs' and contacts' K·v (into q) and K·dv (into p) in one pass.
        for (dv, free) in self.dv.iter_mut().zip(&nodes.free) {
            *dv = dv.component_mul(free);
        }
        spring_product_pair(&self.tangents, contacts, &nodes.v, &self.dv, &mut self.q, &mut self.p);

        // One pass over the nodes: each node's own terms; the right-hand side
        // b = h(F − αMv − Cv) − h(h + β)Kv; the Jacobi preconditioner; the first residual
        // r = b − A·dv and its preconditioned p.
        let (mut b_norm2, mut rz, mut rr) = (0.0, 0.0, 0.0);
        for i in 0..n {
            let (iso, along, normal) = foundation.map_or((0.0, 0.0, Vec3::zeros()), |f| f.node_term(i, stiff_coef, h));
            let free = nodes.free[i];
            let v = nodes.v[i];
            let own = NodeTerm { iso, along, n: normal };
            let b = (nodes.f[i] * h - v * (h * mass_damping_per_s * nodes.mass[i]) - own.times(v) - self.q[i] * stiff_coef).component_mul(&free);
            b_norm2 += b.norm_squared();
            let term = NodeTerm { iso: iso + nodes.mass[i] * mass_coef, along, n: normal };
            self.node_terms[i] = term;
            let d = (self.inv_diag[i] * stiff_coef + normal.component_mul(&normal) * along).add_scalar(term.iso);
            let inv_diag = Vec3::new(inv_or_zero(d.x), inv_or_zero(d.y), inv_or_zero(d.z)).component_mul(&free);
            self.inv_diag[i] = inv_diag;
            let a_dv = (self.p[i] * stiff_coef + term.times(self.dv[i])).component_mul(&free);
            let r = b - a_dv;
            let z = r.component_mul(&inv_diag);
            self.r[i] = r;
            self.z[i] = z;
            rz += r.dot(&z);
            rr += r.norm_squared();
        }
        // Where the residual sits, the sweeps instead of Jacobi (region.rs).
        self.region.choose(&self.tangents, springs_version, contacts, &self.node_terms, &nodes.free, stiff_coef, &self.r, rr);
        rz += self.region.apply(&self.r, &mut self.z);
        self.p[..n].copy_from_slice(&self.z[..n]);

        // PCG on A·dv = b. An iteration is one pass over the springs and three over the
        // nodes: the product's node terms, then the update of dv, r and z and the next
        // direction, these two over the coordinates flat, four lanes at a time (their
        // sums in four partial sums: solver::kernels).
        let b_norm = b_norm2.sqrt();
        let mut iterations = 0;
        let mut residual = if b_norm > 0.0 { rr.sqrt() / b_norm } else { 0.0 };
        if b_norm == 0.0 {
            self.dv.iter_mut().for_each(|x| *x = Vec3::zeros());
        }
        while b_norm > 0.0 && residual > self.tolerance && iterations < self.max_iterations {
            let pq = apply_a(&self.tangents, contacts, &self.node_terms, &nodes.free, stiff_coef, &self.p, &mut self.q);
            if pq <= 0.0 || !pq.is_finite() {
                break;
            }
            let alpha = rz / pq;
            let (mut rz_next, rr_next) = kernels::cg_update_jacobi(flat_mut(&mut self.dv), flat(&self.p), flat_mut(&mut self.r), flat(&self.q), flat(&self.inv_diag), flat_mut(&mut self.z), alpha);
            rz_next += self.region.apply(&self.r, &mut self.z);
            let beta = rz_next / rz;
            rz = rz_next;
            kernels::cg_direction(flat_mut(&mut self.p), flat(&self.z), beta);
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

/// out = A·p = ((h² + hβ)K_springs+contacts + node terms)·p on free axes; returns p·out.
fn apply_a(tangents: &[SpringTangent], contacts: &[Contact], node_terms: &[NodeTerm], free: &[Vec3], stiff_coef: f64, p: &[Vec3], out: &mut [Vec3]) -> f64 {
    spring_product(tangents, contacts, p, out);
    add_node_terms(node_terms, free, stiff_coef, p, out)
}

// The node passes, each compiled for the baseline and for AVX2 (plain multiplications
// and additions, no fused ones: the same bits either way).

crate::solver::kernels::dispatch! {
    /// out = (stiff_coef · out + node terms · p) on free axes; returns p·out.
    pub fn add_node_terms(node_terms: &[NodeTerm], free: &[Vec3], stiff_coef: f64, p: &[Vec3], out: &mut [Vec3]) -> f64 {
        let mut p_dot_out = 0.0;
        for (((o, p), term), free) in out.iter_mut().zip(p).zip(node_terms).zip(free) {
            let a = (*o * stiff_coef + term.times(*p)).component_mul(free);
            *o = a;
            p_dot_out += p.dot(&a);
        }
        p_dot_out
    }
}

crate::solver::kernels::dispatch! {
    /// `kv = K·v` and `kw = K·w` for the springs and contacts in one pass (the tangents
    /// are read once), as [`spring_product`] does each.
    pub fn spring_product_pair(tangents: &[SpringTangent], contacts: &[Contact], v: &[Vec3], w: &[Vec3], kv: &mut [Vec3], kw: &mut [Vec3]) {
        kv.iter_mut().for_each(|x| *x = Vec3::zeros());
        kw.iter_mut().for_each(|x| *x = Vec3::zeros());
        let mut current = u32::MAX;
        let (mut v_current, mut w_current) = (Vec3::zeros(), Vec3::zeros());
        for t in tangents {
            let (a, b) = (t.a as usize, t.b as usize);
            let kdv = t.times(v[b] - v[a]);
            let kdw = t.times(w[b] - w[a]);
            if t.a != current {
                if current != u32::MAX {
                    kv[current as usize] -= v_current;
                    kw[current as usize] -= w_current;
                }
                current = t.a;
                (v_current, w_current) = (kdv, kdw);
            } else {
                v_current += kdv;
                w_current += kdw;
            }
            kv[b] += kdv;
            kw[b] += kdw;
        }
        if current != u32::MAX {
            kv[current as usize] -= v_current;
            kw[current as usize] -= w_current;
        }
        for c in contacts {
            let i = c.node as usize;
            kv[i] += c.normal * (c.stiffness * c.normal.dot(&v[i]));
            kw[i] += c.normal * (c.stiffness * c.normal.dot(&w[i]));
        }
    }
}

crate::solver::kernels::dispatch! {
    /// out = K·p for the springs and contacts. As in the force pass, the product on each
    /// spring's first node is summed in a register over runs of springs sharing it.
    /// Plain multiplications and additions (no fused ones): the AVX2 clone gives the
    /// same bits as the baseline.
    pub fn spring_product(tangents: &[SpringTangent], contacts: &[Contact], p: &[Vec3], out: &mut [Vec3]) {
    out.iter_mut().for_each(|x| *x = Vec3::zeros());
    let mut current = u32::MAX;
    let mut on_current = Vec3::zeros();
    for t in tangents {
        let kd = t.times(p[t.b as usize] - p[t.a as usize]);
        if t.a != current {
            if current != u32::MAX {
                out[current as usize] -= on_current;
            }
            current = t.a;
            on_current = kd;
        } else {
            on_current += kd;
        }
        out[t.b as usize] += kd;
    }
    if current != u32::MAX {
        out[current as usize] -= on_current;
    }
    for c in contacts {
        let i = c.node as usize;
        out[i] += c.normal * (c.stiffness * c.normal.dot(&p[i]));
    }
}
}
