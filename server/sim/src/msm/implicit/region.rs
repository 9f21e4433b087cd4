//! The implicit skin's preconditioner where a tool disturbs it: symmetric Gauss–Seidel
//! sweeps over the nodes round the disturbance, Jacobi elsewhere.
//!
//! A step's residual (after the warm start) sits near the tools: the contacts and the
//! cut change from step to step there, and the rest of the patch follows a slowly
//! moving far field. With Jacobi alone the conjugate gradient spends its iterations
//! carrying that local disturbance ring by ring over the springs (a node a ring an
//! iteration). Here the nodes whose residual is large (the seeds) and a few rings of
//! springs around them (the region, in breadth-first order) are swept forward and back
//! by block Gauss–Seidel from zero, which carries it outwards in one sweep; the rest of
//! the patch keeps Jacobi. Symmetric sweeps from zero are a symmetric positive definite
//! operator, and so is the whole (a block-diagonal preconditioner whose region block is
//! that operator), as the conjugate gradient needs. The region is chosen each step from
//! that step's residual only, so the same state gives the same region and the same bits.
//!
//! - [`Adjacency`]: each node's springs (rebuilt when the springs change).
//! - [`Region`]: the region's nodes, their diagonal blocks, and the sweeps; it keeps the
//!   adjacency it grows the region along.

use super::{AxialBlock, NodeTerm, SpringTangent};
use crate::math::{Matrix3, Vec3};
use crate::msm::contact::Contact;

// The constants were chosen on the step benchmark's 10k patch (docs/benchmarks.md,
// "Sweeping where the tool disturbs the skin") when its blade cut nothing but a hole:
// there more rings or sweeps, or lower seeds, saved at most half an iteration and cost
// more than it. Checked again on a real cut ("The real cut's iterations"): 20 rings save
// 3.6 of 17 iterations and 12 % of the cutting step's median, but not its p99, and
// slow the resting probe's step by 10–20 %, so they stay.

/// Patches of fewer nodes keep Jacobi alone: there a few iterations converge a step
/// (1k nodes: 1.3 resting, 5.9 cutting) and the sweeps cost more than they save.
const MIN_PATCH_NODES: usize = 5_000;

/// A node is a seed if its residual's square is at least this fraction of the whole
/// residual's square.
const SEED_FRACTION: f64 = 1e-2;

/// Rings of springs grown round the seeds.
const RINGS: usize = 12;

/// At most this fraction of the patch's nodes in the region (the sweeps' cost).
const MAX_FRACTION: f64 = 0.1;

/// Symmetric sweeps (one forward, one back) per application.
const SWEEPS: usize = 2;

/// A node's slot when it is not in the region.
const OUTSIDE: u32 = u32::MAX;

/// Whether a patch of `nodes` nodes is swept (else Jacobi alone, and nothing here is
/// built or kept for it).
fn sweeps(nodes: usize) -> bool {
    nodes >= MIN_PATCH_NODES
}

/// Each node's springs: the tangents it is an end of (compressed rows).
#[derive(Debug, Clone, Default)]
struct Adjacency {
    start: Vec<u32>,
    springs: Vec<u32>,
    /// The springs' version and count it was built for.
    built_for: Option<(u64, usize)>,
}

impl Adjacency {
    /// Rebuilds from the tangents' ends unless already built for `version` and as many
    /// springs (allocates only when the mesh grew).
    fn refresh(&mut self, tangents: &[SpringTangent], nodes: usize, version: u64) {
        if self.built_for == Some((version, tangents.len())) && self.start.len() == nodes + 1 {
            return;
        }
        self.start.clear();
        self.start.resize(nodes + 1, 0);
        for t in tangents {
            self.start[t.a as usize + 1] += 1;
            self.start[t.b as usize + 1] += 1;
        }
        for i in 0..nodes {
            self.start[i + 1] += self.start[i];
        }
        self.springs.clear();
        self.springs.resize(2 * tangents.len(), 0);
        // Fill from each row's start, then shift the starts back.
        for (k, t) in tangents.iter().enumerate() {
            for end in [t.a, t.b] {
                let slot = &mut self.start[end as usize];
                self.springs[*slot as usize] = k as u32;
                *slot += 1;
            }
        }
        for i in (1..=nodes).rev() {
            self.start[i] = self.start[i - 1];
        }
        self.start[0] = 0;
        self.built_for = Some((version, tangents.len()));
    }

    /// Node `node`'s springs (tangent indices).
    fn of(&self, node: usize) -> &[u32] {
        &self.springs[self.range(node)]
    }

    /// Where node `node`'s springs lie in `springs` (while the region grows, which
    /// borrows the region mutably).
    fn range(&self, node: usize) -> std::ops::Range<usize> {
        self.start[node] as usize..self.start[node + 1] as usize
    }
}

/// A region node's coupling to another region node: the spring's tangent times the
/// system's stiffness coefficient (the off-diagonal block is its negative).
#[derive(Debug, Clone, Copy)]
struct Coupling {
    /// The other node's position in the region.
    other: u32,
    k: AxialBlock,
}

/// The region of one step and its scratch.
#[derive(Debug, Clone, Default)]
pub(crate) struct Region {
    /// Each node's springs, kept while the springs do not change.
    adjacency: Adjacency,
    /// Its nodes, breadth-first from the seeds.
    nodes: Vec<u32>,
    /// Per node of the patch: its position in `nodes`, [`OUTSIDE`] if not in it.
    slot: Vec<u32>,
    /// Per region node: the inverse of its diagonal block on its free axes (zero on
    /// fixed ones), and where its couplings start in `couplings`.
    inverse: Vec<Matrix3<f64>>,
    coupling_start: Vec<u32>,
    couplings: Vec<Coupling>,
    /// The residual and the sweeps' solution on the region, in its order.
    r: Vec<Vec3>,
    z: Vec<Vec3>,
}

impl Region {
    /// Forgets the last region and sizes the scratch for the largest region of a patch
    /// of `nodes` nodes and `springs` springs (each spring couples at most two region
    /// nodes), so that choosing one allocates nothing until the patch grows.
    fn clear(&mut self, nodes: usize, springs: usize) {
        for &i in &self.nodes {
            self.slot[i as usize] = OUTSIDE;
        }
        self.nodes.clear();
        if !sweeps(nodes) {
            return;
        }
        let largest = (MAX_FRACTION * nodes as f64) as usize;
        for v in [&mut self.r, &mut self.z] {
            v.clear();
            v.reserve(largest);
        }
        self.nodes.reserve(largest);
        self.inverse.clear();
        self.inverse.reserve(largest);
        self.coupling_start.clear();
        self.coupling_start.reserve(largest + 1);
        self.couplings.clear();
        self.couplings.reserve(2 * springs);
        self.slot.resize(nodes, OUTSIDE);
    }

    /// Takes node `i` into the region.
    fn take(&mut self, i: usize) {
        self.slot[i] = self.nodes.len() as u32;
        self.nodes.push(i as u32);
    }

    /// Chooses the region from the residual `r` (square sum `rr`) and makes its system:
    /// each node's diagonal block (its own terms, its springs' tangents and its
    /// contacts, the latter two times `stiff_coef`) inverted, and its couplings to the
    /// other region nodes. `springs_version` changes whenever the springs do (the
    /// adjacency is rebuilt then).
    #[allow(clippy::too_many_arguments)]
    pub fn choose(&mut self, tangents: &[SpringTangent], springs_version: u64, contacts: &[Contact], node_terms: &[NodeTerm], free: &[Vec3], stiff_coef: f64, r: &[Vec3], rr: f64) {
        let n = r.len();
        self.clear(n, tangents.len());
        if rr <= 0.0 || !sweeps(n) {
            return;
        }
        self.adjacency.refresh(tangents, n, springs_version);
        let max_nodes = (MAX_FRACTION * n as f64) as usize;
        let threshold = SEED_FRACTION * rr;
        for (i, ri) in r.iter().enumerate() {
            if ri.norm_squared() >= threshold && self.nodes.len() < max_nodes {
                self.take(i);
            }
        }
        let mut ring_start = 0;
        for _ in 0..RINGS {
            let ring_end = self.nodes.len();
            for at in ring_start..ring_end {
                let i = self.nodes[at] as usize;
                for at_k in self.adjacency.range(i) {
                    let t = &tangents[self.adjacency.springs[at_k] as usize];
                    let j = if t.a as usize == i { t.b } else { t.a } as usize;
                    if self.slot[j] == OUTSIDE && self.nodes.len() < max_nodes && free[j] != Vec3::zeros() {
                        self.take(j);
                    }
                }
            }
            ring_start = ring_end;
        }
        for &i in &self.nodes {
            let i = i as usize;
            let mut block = node_terms[i].matrix();
            self.coupling_start.push(self.couplings.len() as u32);
            for &k in self.adjacency.of(i) {
                let t = &tangents[k as usize];
                block += t.k.matrix() * stiff_coef;
                let j = if t.a as usize == i { t.b } else { t.a } as usize;
                if self.slot[j] != OUTSIDE {
                    self.couplings.push(Coupling { other: self.slot[j], k: t.k.scaled(stiff_coef) });
                }
            }
            self.inverse.push(block);
        }
        self.coupling_start.push(self.couplings.len() as u32);
        for c in contacts {
            let i = c.node as usize;
            if self.slot[i] != OUTSIDE {
                self.inverse[self.slot[i] as usize] += c.normal * c.normal.transpose() * (c.stiffness * stiff_coef);
            }
        }
        for (block, &i) in self.inverse.iter_mut().zip(&self.nodes) {
            let mask = Matrix3::from_diagonal(&free[i as usize]);
            let fixed = Matrix3::identity() - mask;
            let inverse = (mask * *block * mask + fixed).try_inverse().unwrap_or_else(Matrix3::zeros);
            *block = mask * inverse * mask;
        }
        self.r.resize(self.nodes.len(), Vec3::zeros());
        self.z.resize(self.nodes.len(), Vec3::zeros());
    }

    /// `z` on the region from `r`: symmetric block Gauss–Seidel sweeps from zero on the
    /// region's own system (its nodes' couplings to the rest left out), replacing what
    /// `z` held there. Returns the change of Σ r·z over the region.
    pub fn apply(&mut self, r: &[Vec3], z: &mut [Vec3]) -> f64 {
        let mut before = 0.0;
        for (at, &i) in self.nodes.iter().enumerate() {
            let i = i as usize;
            before += r[i].dot(&z[i]);
            self.r[at] = r[i];
            self.z[at] = Vec3::zeros();
        }
        let Region { inverse, coupling_start, couplings, r: r_local, z: z_local, .. } = self;
        let mut relax = |at: usize| {
            // r minus the off-diagonal blocks (−stiff_coef·K_s) times z.
            let mut s = r_local[at];
            for c in &couplings[coupling_start[at] as usize..coupling_start[at + 1] as usize] {
                s += c.k.times(z_local[c.other as usize]);
            }
            z_local[at] = inverse[at] * s;
        };
        let m = self.nodes.len();
        for _ in 0..SWEEPS {
            for at in 0..m {
                relax(at);
            }
            for at in (0..m).rev() {
                relax(at);
            }
        }
        let mut after = 0.0;
        for (at, &i) in self.nodes.iter().enumerate() {
            let i = i as usize;
            z[i] = self.z[at];
            after += r[i].dot(&z[i]);
        }
        after - before
    }
}

#[cfg(test)]
mod tests {
    use super::super::{NodeTerm, SpringTangent, apply_a};
    use super::*;

    /// A square lattice of `m × m` nodes, springs along x, y and one diagonal, stiff
    /// along themselves and slack across (as the prestressed skin's), each node's mass
    /// and foundation of the springs' order (as a step's mass and drag are: the response
    /// to a local push fades over a few rings); one node held by a stiff contact. The
    /// system of one implicit step (stiff_coef 1).
    fn lattice(m: usize) -> (Vec<SpringTangent>, Vec<NodeTerm>, Vec<Vec3>, Vec<Contact>) {
        let id = |x: usize, y: usize| (y * m + x) as u32;
        let mut tangents = Vec::new();
        for y in 0..m {
            for x in 0..m {
                for (dx, dy) in [(1, 0), (0, 1), (1, 1)] {
                    if x + dx < m && y + dy < m {
                        let n = Vec3::new(dx as f64, dy as f64, 0.0).normalize();
                        tangents.push(SpringTangent { a: id(x, y), b: id(x + dx, y + dy), k: AxialBlock { iso: 10.0, along: 90.0, n } });
                    }
                }
            }
        }
        let terms = vec![NodeTerm { iso: 20.0, along: 10.0, n: Vec3::z() }; m * m];
        let free = vec![Vec3::repeat(1.0); m * m];
        let contacts = vec![Contact { node: id(m / 2, m / 2), normal: Vec3::new(0.0, 0.6, 0.8), stiffness: 1e4, drive_m_per_s: 0.0 }];
        (tangents, terms, free, contacts)
    }

    /// The Jacobi inverse of the lattice's diagonal, per axis.
    fn jacobi(tangents: &[SpringTangent], terms: &[NodeTerm], contacts: &[Contact]) -> Vec<Vec3> {
        let mut diagonal: Vec<Vec3> = terms.iter().map(|t| t.diagonal()).collect();
        for t in tangents {
            diagonal[t.a as usize] += t.k.diagonal();
            diagonal[t.b as usize] += t.k.diagonal();
        }
        for c in contacts {
            diagonal[c.node as usize] += c.normal.component_mul(&c.normal) * c.stiffness;
        }
        diagonal.iter().map(|d| d.map(|x| 1.0 / x)).collect()
    }

    /// Conjugate gradient on the lattice from zero for `b`, preconditioned by Jacobi and,
    /// with `region`, the sweeps round `b`'s residual: the iterations to a relative
    /// residual of 1e-4 (the skin's tolerance), and the solution.
    fn solve(m: usize, b: &[Vec3], region: bool) -> (u32, Vec<Vec3>) {
        let (tangents, terms, free, contacts) = lattice(m);
        let inv = jacobi(&tangents, &terms, &contacts);
        let mut sweeps = Region::default();
        let n = m * m;
        let (mut x, mut r, mut z, mut q) = (vec![Vec3::zeros(); n], b.to_vec(), vec![Vec3::zeros(); n], vec![Vec3::zeros(); n]);
        let precondition = |r: &[Vec3], z: &mut [Vec3], sweeps: &mut Region| {
            let mut rz = 0.0;
            for i in 0..n {
                z[i] = r[i].component_mul(&inv[i]);
                rz += r[i].dot(&z[i]);
            }
            rz + if region { sweeps.apply(r, z) } else { 0.0 }
        };
        let rr: f64 = r.iter().map(|v| v.norm_squared()).sum();
        if region {
            sweeps.choose(&tangents, 0, &contacts, &terms, &free, 1.0, &r, rr);
            assert!(!sweeps.nodes.is_empty() && sweeps.nodes.len() <= n / 10, "{} region nodes", sweeps.nodes.len());
        }
        let b_norm = rr.sqrt();
        let mut rz = precondition(&r, &mut z, &mut sweeps);
        let mut p = z.clone();
        for iteration in 1..=1000 {
            let pq = apply_a(&tangents, &contacts, &terms, &free, 1.0, &p, &mut q);
            let alpha = rz / pq;
            for i in 0..n {
                x[i] += p[i] * alpha;
                r[i] -= q[i] * alpha;
            }
            if r.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt() < 1e-4 * b_norm {
                return (iteration, x);
            }
            let rz_next = precondition(&r, &mut z, &mut sweeps);
            for i in 0..n {
                p[i] = z[i] + p[i] * (rz_next / rz);
            }
            rz = rz_next;
        }
        panic!("no convergence");
    }

    #[test]
    fn the_sweeps_are_a_symmetric_positive_operator() {
        let m = 75;
        let (tangents, terms, free, contacts) = lattice(m);
        let n = m * m;
        // A residual round the held node chooses the region.
        let centre = (m / 2) * m + m / 2;
        let mut seedlike = vec![Vec3::zeros(); n];
        seedlike[centre] = Vec3::new(0.0, 0.0, 1.0);
        let mut region = Region::default();
        region.choose(&tangents, 0, &contacts, &terms, &free, 1.0, &seedlike, 1.0);
        let vector = |seed: u64| -> Vec<Vec3> {
            (0..n).map(|i| {
                let h = |k: u64| (((i as u64 * 2654435761 + seed * 97 + k * 31) % 1000) as f64) / 500.0 - 1.0;
                Vec3::new(h(1), h(2), h(3))
            }).collect()
        };
        let (u, v) = (vector(1), vector(2));
        let apply = |r: &[Vec3], region: &mut Region| {
            let mut z = vec![Vec3::zeros(); n];
            region.apply(r, &mut z);
            z
        };
        let (mu, mv) = (apply(&u, &mut region), apply(&v, &mut region));
        let dot = |a: &[Vec3], b: &[Vec3]| a.iter().zip(b).map(|(x, y)| x.dot(y)).sum::<f64>();
        let (uv, vu) = (dot(&u, &mv), dot(&v, &mu));
        assert!((uv - vu).abs() <= 1e-12 * uv.abs().max(1.0), "u·Mv {uv} against v·Mu {vu}");
        assert!(dot(&u, &mu) > 0.0 && dot(&v, &mv) > 0.0);
    }

    #[test]
    fn sweeping_round_a_local_disturbance_takes_fewer_iterations_to_the_same_solution() {
        let m = 75;
        // A push at the held node and its neighbours, as a tool's contact makes.
        let mut b = vec![Vec3::zeros(); m * m];
        let centre = (m / 2) * m + m / 2;
        for (k, i) in [centre, centre + 1, centre + m, centre - 1].into_iter().enumerate() {
            b[i] = Vec3::new(0.1 * k as f64, 0.0, 1.0);
        }
        let (jacobi_iterations, x_jacobi) = solve(m, &b, false);
        let (region_iterations, x_region) = solve(m, &b, true);
        let difference = x_jacobi.iter().zip(&x_region).map(|(a, b)| (a - b).norm_squared()).sum::<f64>().sqrt();
        let size = x_jacobi.iter().map(|a| a.norm_squared()).sum::<f64>().sqrt();
        println!("Jacobi {jacobi_iterations} iterations, with the sweeps {region_iterations}; solutions differ by {:.1e} of their size", difference / size);
        assert!(region_iterations * 2 <= jacobi_iterations, "Jacobi {jacobi_iterations}, with the sweeps {region_iterations}");
        // Both within the tolerance of the one solution (the residual's 1e-4 times the
        // system's spread of scales).
        assert!(difference <= 1e-3 * size, "the solutions differ by {:.1e} of their size", difference / size);
    }
}
