//! Dynamics of the branched grid: corotational hexahedra, implicit Euler solved by a
//! warm-started, Jacobi-preconditioned conjugate gradient, Rayleigh damping, lumped or
//! consistent mass, fixed nodes, and penalty contacts whose stiffness enters the solve.
//!
//! Rotation: per element, the polar rotation of its deformation gradient at the centre
//! (the mean of its four x-, y- and z-edges over the cell's sides), by Newton's
//! iteration; inverted elements take the nearest proper rotation from the SVD. It is
//! exact for rigid motions (a rigidly rotated body feels no elastic force). The polar
//! rotation makes the elastic force the gradient of the corotated energy; the QR of the
//! edge frame used before does not, and it pumped energy into nearly incompressible
//! bodies at large deflection (an undamped ν = 0.499 bar sagging under gravity blew up
//! within 0.15 s; the stability sweep in tests/branched_grid.rs covers it).
//!
//! One step of h (linearised backward Euler, rotations frozen over the step):
//! `(M + hC + h²(K_R + K_c)) Δv = h (f(x) − C v − h K_R v)`, `v += Δv`, `x += h v`,
//! with `K_R = R K Rᵀ` per element, `C = αM + βK_R`, `K_c` the contacts' normal
//! stiffness and `f` the elastic, gravity and contact forces.

use nalgebra::SVector;

use super::hex::{Mat24, Mat24f};
use super::topology::Topology;
use crate::math::{Matrix3, Vec3};

type Vec24 = SVector<f64, 24>;

/// Velocity change below which the solve has nothing left to do, m/s.
const VELOCITY_FLOOR: f64 = 1e-9;

/// How the mass matrix is used.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MassModel {
    /// Row sums on the diagonal: cheaper, slightly more damped high modes.
    Lumped,
    /// The condensed consistent matrix, element by element.
    Consistent,
}

/// Solver settings (scene knobs).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SolverSettings {
    pub dt_s: f64,
    pub cg_max_iterations: u32,
    pub cg_tolerance: f64,
    /// Rayleigh damping: C = α M + β K.
    pub alpha_per_s: f64,
    pub beta_s: f64,
    pub mass: MassModel,
    /// In the grid's frame, m/s².
    pub gravity: Option<Vec3>,
}

/// A penalty contact at a point embedded in an element: force `k (depth) n` pushes it
/// out along `n`; its stiffness `k n nᵀ` enters the implicit solve.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PointContact {
    pub element: u32,
    pub weights: [f64; 8],
    pub normal: Vec3,
    pub stiffness: f64,
    /// The contact force, N (already `k · depth · n`).
    pub force: Vec3,
}

/// Buffers and per-element state of the solver; sized to the topology (resized only when
/// a cut adds nodes or elements).
#[derive(Debug, Clone, Default)]
pub struct Dynamics {
    pub rotations: Vec<Matrix3<f64>>,
    force: Vec<Vec3>,
    b: Vec<Vec3>,
    r: Vec<Vec3>,
    z: Vec<Vec3>,
    p: Vec<Vec3>,
    q: Vec<Vec3>,
    diag: Vec<Vec3>,
    /// Δv of the last step: the next solve starts from it.
    pub dv: Vec<Vec3>,
    pub last_iterations: u32,
    pub last_residual: f64,
}

impl Dynamics {
    pub fn new(topo: &Topology) -> Self {
        let mut d = Dynamics::default();
        d.resize(topo);
        d
    }

    /// Grows the buffers to the topology's node and element counts.
    pub fn resize(&mut self, topo: &Topology) {
        let n = topo.nodes.len();
        for buffer in [&mut self.force, &mut self.b, &mut self.r, &mut self.z, &mut self.p, &mut self.q, &mut self.diag, &mut self.dv] {
            buffer.resize(n, Vec3::zeros());
        }
        self.rotations.resize(topo.elements.len(), Matrix3::identity());
    }

    /// Updates every element's rotation from its current corners.
    pub fn update_rotations(&mut self, topo: &Topology) {
        for e in 0..topo.elements.len() {
            if topo.elements.alive[e] {
                let nodes = &topo.elements.nodes[e];
                let x = |n: usize| topo.nodes.x[nodes[n] as usize];
                if let Some(r) = averaged_edge_rotation(&x, &topo.layout.cell_size_m()) {
                    self.rotations[e] = r;
                }
            }
        }
    }

    /// One implicit step with the given contacts. Returns the max |Δv| (not finite on a blow-up).
    pub fn step(&mut self, topo: &mut Topology, settings: &SolverSettings, contacts: &[PointContact]) -> f64 {
        let h = settings.dt_s;
        let a_mass = 1.0 + h * settings.alpha_per_s;
        let a_stiff = h * settings.beta_s + h * h;
        let a_contact = h * h;
        // One pass over the elements: rotations, f_el − (β + h) K_R v, and the stiffness
        // part of the Jacobi preconditioner.
        for n in 0..topo.nodes.len() {
            self.force[n] = Vec3::zeros();
            self.diag[n] = if settings.mass == MassModel::Lumped { Vec3::repeat(a_mass * topo.nodes.mass[n]) } else { Vec3::zeros() };
        }
        let damping = settings.beta_s + h;
        let cell_m = topo.layout.cell_size_m();
        for e in 0..topo.elements.len() {
            if !topo.elements.alive[e] {
                continue;
            }
            let nodes = &topo.elements.nodes[e];
            if let Some(r) = averaged_edge_rotation(&|n: usize| topo.nodes.x[nodes[n] as usize], &cell_m) {
                self.rotations[e] = r;
            }
            let r = self.rotations[e];
            let u = local_displacement(topo, e, &r, damping);
            let k = &topo.elements.stiffness_single[e];
            let f = mat_vec_single(k, &u);
            for c in 0..8 {
                let node = nodes[c] as usize;
                self.force[node] -= r * f.fixed_rows::<3>(3 * c);
                // Jacobi: a third of the diagonal block's trace on each axis — invariant
                // under the rotation, so it needs no R B Rᵀ per corner (exact for the
                // near-isotropic blocks of a hexahedron; any positive diagonal keeps CG correct).
                let trace = f64::from(k[(3 * c, 3 * c)] + k[(3 * c + 1, 3 * c + 1)] + k[(3 * c + 2, 3 * c + 2)]);
                self.diag[node] += Vec3::repeat(trace / 3.0 * a_stiff);
                if settings.mass == MassModel::Consistent {
                    self.diag[node] += Vec3::repeat(a_mass * topo.elements.mass[e][(c, c)]);
                }
            }
        }
        if let Some(g) = settings.gravity {
            for n in 0..topo.nodes.len() {
                self.force[n] += g * topo.nodes.mass[n];
            }
        }
        for c in contacts {
            let nodes = &topo.elements.nodes[c.element as usize];
            for k in 0..8 {
                let w = c.weights[k];
                self.force[nodes[k] as usize] += c.force * w;
                self.diag[nodes[k] as usize] += c.normal.component_mul(&c.normal) * (a_contact * c.stiffness * w * w);
            }
        }
        // b = h (f − αM v − (β + h) K_R v); the last term is already in `force`.
        mass_times(topo, settings.mass, &topo.nodes.v, &mut self.q);
        for n in 0..topo.nodes.len() {
            self.b[n] = (self.force[n] - self.q[n] * settings.alpha_per_s) * h;
        }
        let (iterations, residual) = self.conjugate_gradient(topo, settings, a_mass, a_stiff, a_contact, contacts);
        self.last_iterations = iterations;
        self.last_residual = residual;
        let mut max_dv: f64 = 0.0;
        for n in 0..topo.nodes.len() {
            if !topo.nodes.alive[n] || topo.nodes.fixed[n] {
                topo.nodes.v[n] = Vec3::zeros();
                continue;
            }
            let dv = self.dv[n];
            max_dv = max_dv.max(dv.amax());
            if !dv.iter().all(|c| c.is_finite()) {
                max_dv = f64::NAN;
            }
            topo.nodes.v[n] += dv;
            topo.nodes.x[n] += topo.nodes.v[n] * h;
        }
        max_dv
    }

    /// Solves A Δv = b for the free nodes, starting from the last Δv.
    fn conjugate_gradient(&mut self, topo: &Topology, settings: &SolverSettings, a_mass: f64, a_stiff: f64, a_contact: f64, contacts: &[PointContact]) -> (u32, f64) {
        let n = topo.nodes.len();
        let free = |i: usize| topo.nodes.alive[i] && !topo.nodes.fixed[i];
        for i in 0..n {
            if !free(i) || !self.dv[i].iter().all(|c| c.is_finite()) {
                self.dv[i] = Vec3::zeros();
            }
        }
        let apply = |x: &[Vec3], out: &mut [Vec3], scratch: &mut [Vec3]| {
            mass_times(topo, settings.mass, x, out);
            stiffness_times_single(topo, &self.rotations, x, scratch);
            for i in 0..n {
                out[i] = out[i] * a_mass + scratch[i] * a_stiff;
            }
            for c in contacts {
                let nodes = &topo.elements.nodes[c.element as usize];
                let mut along = 0.0;
                for k in 0..8 {
                    along += c.weights[k] * c.normal.dot(&x[nodes[k] as usize]);
                }
                let push = c.normal * (a_contact * c.stiffness * along);
                for k in 0..8 {
                    out[nodes[k] as usize] += push * c.weights[k];
                }
            }
            for i in 0..n {
                if !free(i) {
                    out[i] = Vec3::zeros();
                }
            }
        };
        let mut scratch = std::mem::take(&mut self.force);
        if self.dv.iter().any(|d| *d != Vec3::zeros()) {
            apply(&self.dv, &mut self.q, &mut scratch);
        } else {
            self.q.iter_mut().for_each(|q| *q = Vec3::zeros());
        }
        // Norms in the Jacobi metric (bᵀD⁻¹b): every node counts by its own scale, so a
        // node of tiny mass and stiffness (the far corner of an element holding a single
        // voxel) is solved as accurately as the others instead of being lost in the sum.
        let mut b_norm2 = 0.0;
        for i in 0..n {
            if !free(i) {
                self.b[i] = Vec3::zeros();
            }
            let d = self.diag[i];
            b_norm2 += safe_div(self.b[i].x * self.b[i].x, d.x) + safe_div(self.b[i].y * self.b[i].y, d.y) + safe_div(self.b[i].z * self.b[i].z, d.z);
            self.r[i] = self.b[i] - self.q[i];
        }
        let precondition = |r: &[Vec3], diag: &[Vec3], z: &mut [Vec3]| {
            for i in 0..n {
                z[i] = if free(i) { Vec3::new(safe_div(r[i].x, diag[i].x), safe_div(r[i].y, diag[i].y), safe_div(r[i].z, diag[i].z)) } else { Vec3::zeros() };
            }
        };
        precondition(&self.r, &self.diag, &mut self.z);
        self.p.copy_from_slice(&self.z);
        let mut rz: f64 = (0..n).map(|i| self.r[i].dot(&self.z[i])).sum();
        let target2 = settings.cg_tolerance * settings.cg_tolerance * b_norm2;
        let mut iterations = 0;
        let mut r_norm2 = rz;
        // Besides the relative test, stop when what is left would change no velocity by
        // more than VELOCITY_FLOOR: a body at rest has round-off forces, not work to do.
        let velocity_error = |z: &[Vec3]| z.iter().map(|v| v.amax()).fold(0.0, f64::max);
        let mut dv_error = velocity_error(&self.z);
        while iterations < settings.cg_max_iterations && r_norm2 > target2 && b_norm2 > 0.0 && dv_error > VELOCITY_FLOOR {
            apply(&self.p, &mut self.q, &mut scratch);
            let pq: f64 = (0..n).map(|i| self.p[i].dot(&self.q[i])).sum();
            if !(pq > 0.0) {
                break;
            }
            let alpha = rz / pq;
            for i in 0..n {
                self.dv[i] += self.p[i] * alpha;
                self.r[i] -= self.q[i] * alpha;
            }
            precondition(&self.r, &self.diag, &mut self.z);
            dv_error = velocity_error(&self.z);
            let rz_next: f64 = (0..n).map(|i| self.r[i].dot(&self.z[i])).sum();
            r_norm2 = rz_next;
            let beta = rz_next / rz;
            rz = rz_next;
            for i in 0..n {
                self.p[i] = self.z[i] + self.p[i] * beta;
            }
            iterations += 1;
        }
        self.force = scratch;
        (iterations, if b_norm2 > 0.0 { (r_norm2 / b_norm2).sqrt() } else { 0.0 })
    }
}

fn safe_div(a: f64, b: f64) -> f64 {
    if b > 0.0 { a / b } else { 0.0 }
}

/// The rotation of an element: the polar rotation of its deformation gradient at the
/// centre, `F = [Σ x-edges / 4a, Σ y-edges / 4b, Σ z-edges / 4c]` for a cell of sides
/// (a, b, c); `x(n)` is corner n's position. Newton's iteration `R ← (R + R⁻ᵀ)/2`
/// converges quadratically; an inverted or collapsed element (det F ≤ 1e-6) takes the
/// proper rotation nearest F from the SVD instead. None when that is undefined.
pub fn averaged_edge_rotation(x: &impl Fn(usize) -> Vec3, cell_m: &Vec3) -> Option<Matrix3<f64>> {
    let mut edges = [Vec3::zeros(); 3];
    for (a, edge) in edges.iter_mut().enumerate() {
        for n in 0..8 {
            if (n >> a) & 1 == 0 {
                *edge += x(n | (1 << a)) - x(n);
            }
        }
        *edge /= 4.0 * cell_m[a];
    }
    let f = Matrix3::from_columns(&edges);
    if f.determinant() > 1e-6 {
        let mut r = f;
        for _ in 0..20 {
            let Some(inverse) = r.try_inverse() else { break };
            let next = (r + inverse.transpose()) * 0.5;
            let change = (next - r).amax();
            r = next;
            if change < 1e-12 {
                break;
            }
        }
        if r.iter().all(|c| c.is_finite()) && (r.determinant() - 1.0).abs() < 1e-6 {
            return Some(r);
        }
    }
    // Inverted or collapsed: the rotation nearest F among proper rotations, from the
    // SVD with the smallest singular direction flipped (Irving et al. 2004), so the
    // element pushes back out of inversion instead of settling into it.
    let svd = f.svd(true, true);
    let (u, v_t) = (svd.u?, svd.v_t?);
    let mut smallest = 0;
    for k in 1..3 {
        if svd.singular_values[k] < svd.singular_values[smallest] {
            smallest = k;
        }
    }
    let mut flip = Matrix3::identity();
    if (u * v_t).determinant() < 0.0 {
        flip[(smallest, smallest)] = -1.0;
    }
    let r = u * flip * v_t;
    r.iter().all(|c| c.is_finite()).then_some(r)
}

/// Element `e`'s displacement in its rotated frame, `Rᵀ(x − x₀) − (X − X₀)` per corner
/// (corner 0 as the reference), plus `damping · Rᵀv` (the step's (β + h) K_R v term;
/// 0 for the elastic force alone). Rest offsets come from the nodes' own rest positions,
/// so a body at rest has exactly zero strain.
fn local_displacement(topo: &Topology, e: usize, r: &Matrix3<f64>, damping: f64) -> Vec24 {
    let nodes = &topo.elements.nodes[e];
    let rt = r.transpose();
    let (x0, rest0) = (topo.nodes.x[nodes[0] as usize], topo.nodes.rest[nodes[0] as usize]);
    let mut u = Vec24::zeros();
    for c in 0..8 {
        let node = nodes[c] as usize;
        let local = rt * (topo.nodes.x[node] - x0) - (topo.nodes.rest[node] - rest0) + rt * topo.nodes.v[node] * damping;
        u.fixed_rows_mut::<3>(3 * c).copy_from(&local);
    }
    u
}

/// Adds −R K (Rᵀ(x − x₀) − (X − X₀)) of every element (corner 0 as the reference), with
/// the same kernel and rotations as the step.
pub fn add_elastic_forces(topo: &Topology, rotations: &[Matrix3<f64>], force: &mut [Vec3]) {
    for e in 0..topo.elements.len() {
        if !topo.elements.alive[e] {
            continue;
        }
        let nodes = &topo.elements.nodes[e];
        let r = &rotations[e];
        let f = mat_vec(&topo.elements.stiffness[e], &local_displacement(topo, e, r, 0.0));
        for c in 0..8 {
            force[nodes[c] as usize] -= r * f.fixed_rows::<3>(3 * c);
        }
    }
}

/// out = K_R x (out is overwritten).
pub fn stiffness_times(topo: &Topology, rotations: &[Matrix3<f64>], x: &[Vec3], out: &mut [Vec3]) {
    rotated_product(topo, rotations, x, out, |e, u| mat_vec(&topo.elements.stiffness[e], u));
}

/// `out = Σ_e R_e P_e(R_eᵀ x_e)` for a per-element product `P_e` (out is overwritten).
fn rotated_product(topo: &Topology, rotations: &[Matrix3<f64>], x: &[Vec3], out: &mut [Vec3], product: impl Fn(usize, &Vec24) -> Vec24) {
    out.iter_mut().for_each(|o| *o = Vec3::zeros());
    for e in 0..topo.elements.len() {
        if !topo.elements.alive[e] {
            continue;
        }
        let nodes = &topo.elements.nodes[e];
        let r = &rotations[e];
        let mut u = Vec24::zeros();
        for c in 0..8 {
            u.fixed_rows_mut::<3>(3 * c).copy_from(&(r.transpose() * x[nodes[c] as usize]));
        }
        let f = product(e, &u);
        for c in 0..8 {
            out[nodes[c] as usize] += r * f.fixed_rows::<3>(3 * c);
        }
    }
}

/// `K u`, column by column (axpy over contiguous columns vectorises; no reassociation).
fn mat_vec(k: &Mat24, u: &Vec24) -> Vec24 {
    let k = k.as_slice();
    let mut f = Vec24::zeros();
    for j in 0..24 {
        let uj = u[j];
        let column = &k[24 * j..24 * j + 24];
        for i in 0..24 {
            f[i] += column[i] * uj;
        }
    }
    f
}

/// `out = K_R x` as [`stiffness_times`], in single precision per element: the solve
/// needs a relative accuracy of its tolerance (≥ 1e-6 in practice), far above f32's
/// 6e-8, and reads half the bytes. Sums over elements stay in double precision.
pub fn stiffness_times_single(topo: &Topology, rotations: &[Matrix3<f64>], x: &[Vec3], out: &mut [Vec3]) {
    rotated_product(topo, rotations, x, out, |e, u| mat_vec_single(&topo.elements.stiffness_single[e], u));
}

/// `K u` with K in single precision: the products in single precision (4 lanes), the
/// result back in double.
fn mat_vec_single(k: &Mat24f, u: &Vec24) -> Vec24 {
    let k = k.as_slice();
    let mut f = [0f32; 24];
    for j in 0..24 {
        let uj = u[j] as f32;
        let column = &k[24 * j..24 * j + 24];
        for i in 0..24 {
            f[i] += column[i] * uj;
        }
    }
    Vec24::from_fn(|i, _| f64::from(f[i]))
}

/// out = M x (out is overwritten).
pub fn mass_times(topo: &Topology, model: MassModel, x: &[Vec3], out: &mut [Vec3]) {
    match model {
        MassModel::Lumped => {
            for n in 0..topo.nodes.len() {
                out[n] = x[n] * topo.nodes.mass[n];
            }
        }
        MassModel::Consistent => {
            out.iter_mut().for_each(|o| *o = Vec3::zeros());
            for e in 0..topo.elements.len() {
                if !topo.elements.alive[e] {
                    continue;
                }
                let nodes = &topo.elements.nodes[e];
                let m = &topo.elements.mass[e];
                for i in 0..8 {
                    let mut sum = Vec3::zeros();
                    for j in 0..8 {
                        sum += x[nodes[j] as usize] * m[(i, j)];
                    }
                    out[nodes[i] as usize] += sum;
                }
            }
        }
    }
}

/// Solves the linear static problem K u = f for the free nodes (no rotation; small
/// displacements), with fixed nodes held at their current displacement. Returns the
/// CG iterations taken and the relative residual. Used by tests and accuracy studies.
pub fn solve_static(topo: &mut Topology, loads: &[Vec3], tolerance: f64, max_iterations: u32) -> (u32, f64) {
    let n = topo.nodes.len();
    let rotations = vec![Matrix3::identity(); topo.elements.len()];
    let free: Vec<bool> = (0..n).map(|i| topo.nodes.alive[i] && !topo.nodes.fixed[i]).collect();
    let u0: Vec<Vec3> = (0..n).map(|i| topo.nodes.x[i] - topo.nodes.rest[i]).collect();
    // Residual r = f − K u for the free nodes.
    let mut ku = vec![Vec3::zeros(); n];
    stiffness_times(topo, &rotations, &u0, &mut ku);
    let mut diag = vec![Vec3::zeros(); n];
    for e in 0..topo.elements.len() {
        if topo.elements.alive[e] {
            for c in 0..8 {
                let k = &topo.elements.stiffness[e];
                diag[topo.elements.nodes[e][c] as usize] += Vec3::new(k[(3 * c, 3 * c)], k[(3 * c + 1, 3 * c + 1)], k[(3 * c + 2, 3 * c + 2)]);
            }
        }
    }
    let mut u = u0;
    let mut r: Vec<Vec3> = (0..n).map(|i| if free[i] { loads[i] - ku[i] } else { Vec3::zeros() }).collect();
    let precondition = |r: &[Vec3]| -> Vec<Vec3> {
        (0..n).map(|i| if free[i] { Vec3::new(safe_div(r[i].x, diag[i].x), safe_div(r[i].y, diag[i].y), safe_div(r[i].z, diag[i].z)) } else { Vec3::zeros() }).collect()
    };
    let b_norm2: f64 = (0..n).filter(|&i| free[i]).map(|i| loads[i].norm_squared()).sum::<f64>().max(r.iter().map(|v| v.norm_squared()).sum());
    let mut z = precondition(&r);
    let mut p = z.clone();
    let mut rz: f64 = (0..n).map(|i| r[i].dot(&z[i])).sum();
    let mut q = vec![Vec3::zeros(); n];
    let mut iterations = 0;
    let mut r2: f64 = r.iter().map(|v| v.norm_squared()).sum();
    while iterations < max_iterations && r2 > tolerance * tolerance * b_norm2 {
        stiffness_times(topo, &rotations, &p, &mut q);
        for i in 0..n {
            if !free[i] {
                q[i] = Vec3::zeros();
            }
        }
        let pq: f64 = (0..n).map(|i| p[i].dot(&q[i])).sum();
        if !(pq > 0.0) {
            break;
        }
        let alpha = rz / pq;
        for i in 0..n {
            u[i] += p[i] * alpha;
            r[i] -= q[i] * alpha;
        }
        r2 = r.iter().map(|v| v.norm_squared()).sum();
        z = precondition(&r);
        let rz_next: f64 = (0..n).map(|i| r[i].dot(&z[i])).sum();
        let beta = rz_next / rz;
        rz = rz_next;
        for i in 0..n {
            p[i] = z[i] + p[i] * beta;
        }
        iterations += 1;
    }
    for i in 0..n {
        topo.nodes.x[i] = topo.nodes.rest[i] + u[i];
    }
    (iterations, if b_norm2 > 0.0 { (r2 / b_norm2).sqrt() } else { 0.0 })
}
