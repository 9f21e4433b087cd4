//! The linear static problem `K u = f` of a branched grid (small displacements, no
//! rotation), for tests and the accuracy studies (crate::accuracy): their references
//! are level-0 solutions converged to a relative residual of 1e-10.
//!
//! `K` is assembled once, in double precision (the elements' own matrices, not the
//! single-precision copies a step uses: a reference must agree with scikit-fem to
//! 1e-11), and solved by conjugate gradient preconditioned by a V-cycle over the
//! branched hierarchy (`grid::preconditioning::static_hierarchy`: the coarse grids
//! the dynamics' multigrid uses, their operators Galerkin products of this `K`, held
//! nodes left out). Block Jacobi, which this solve used before,
//! needs iterations that grow with resolution and, without a mass term, with the
//! body's size: 2,329 on the CT liver at level 0, and the layered abdomen's level-0
//! reference (170,000 nodes) had run over half an hour when it was stopped.

use std::cell::RefCell;

use super::preconditioning::{STATIC_COARSEST_UNKNOWNS, static_hierarchy};
use super::solver::{Assembled, stiffness_times, system_pattern};
use super::support::held_pieces;
use super::topology::Topology;
use crate::math::{Matrix3, Vec3};
use crate::solver::block_sparse::{BlockMatrix, Scatter};
use crate::solver::multigrid::{DenseSolve, VCycle};
use crate::solver::pcg::{Pcg, PcgSettings};
use crate::solver::preconditioner::BlockJacobi;

/// A solve whose residual has not halved for this many iterations has stalled: the
/// problem has no solution (a piece held at a point or along a line turns about it).
/// Solvable bundled problems halve it every few iterations to a few dozen (the layered
/// abdomen's level 0: 238 iterations to 1e-10; its level 3: 480).
const STALLED_AFTER: u32 = 2_000;

/// An answer whose own relative residual is above this solves nothing (round-off
/// leaves at most about 1e-9 on the bundled problems).
const NO_SOLUTION: f64 = 1e-6;

/// Solves the linear static problem K u = f for the free nodes (no rotation; small
/// displacements), with fixed nodes held at their current displacement and the
/// supports' embedded points on their springs; the nodes are left at the solution.
/// Returns the CG iterations taken and the relative residual |b − K u| / |b|, with b
/// the loads less what the held nodes' displacements pull, which is above `tolerance`
/// where the solve stopped at `max_iterations` or stalled. The conjugate gradient is
/// the dynamics' (`solver::pcg`), in the Euclidean norm (the references are asserted
/// to a relative residual in it) and stopped when it stalls.
pub fn solve_static(topo: &mut Topology, loads: &[Vec3], tolerance: f64, max_iterations: u32) -> (u32, f64) {
    let n = topo.nodes.len();
    // Pieces that touch no hold have no static answer but where nothing loads them:
    // then they stay where they are (any rigid motion would do), and are left out of
    // the solve, whose operator they would make singular. Loaded, they stay in, and
    // the residual says there is no solution.
    let held = held_pieces(topo);
    let loose_unloaded = (0..n).all(|i| held[i] || loads[i] == Vec3::zeros());
    let free: Vec<bool> = (0..n).map(|i| topo.nodes.alive[i] && !topo.nodes.fixed[i] && (held[i] || !loose_unloaded)).collect();
    let u0: Vec<Vec3> = (0..n).map(|i| topo.nodes.x[i] - topo.nodes.rest[i]).collect();
    // CG solves K u = b on the free rows from their displacements, b = f − K u_held:
    // the loads less what the held nodes' displacements pull (the assembled K couples
    // free nodes only).
    let (mut u, held_only): (Vec<Vec3>, Vec<Vec3>) = (0..n).map(|i| if free[i] { (u0[i], Vec3::zeros()) } else { (Vec3::zeros(), u0[i]) }).unzip();
    let b = residual(topo, loads, &free, &held_only);
    let k = assemble(topo);
    let b_norm2 = b.iter().map(Vec3::norm_squared).sum::<f64>();
    // A problem as small as a coarsest level is solved exactly (CG then checks it in one
    // iteration); any other, by V-cycles.
    let settings = PcgSettings { max_iterations, tolerance, floor: 0.0, stalled_after: STALLED_AFTER };
    let euclidean = vec![Vec3::repeat(1.0); n];
    let operator = Assembled { matrix: &k, active: &free };
    let convergence = match DenseSolve::new(&k, &free, STATIC_COARSEST_UNKNOWNS) {
        Some(exact) => Pcg::default().solve(&operator, &exact, &b, &mut u, &free, &euclidean, &settings),
        None => {
            let (mut hierarchy, smoother, mut scratch) = (static_hierarchy(topo, &k, &free), BlockJacobi::new(&k, &free), Vec::new());
            let v_cycle = VCycle { hierarchy: RefCell::new(&mut hierarchy), matrix: &k, smoother: &smoother, active: &free, scratch: RefCell::new(&mut scratch) };
            Pcg::default().solve(&operator, &v_cycle, &b, &mut u, &free, &euclidean, &settings)
        }
    };
    for i in (0..n).filter(|&i| !free[i]) {
        u[i] = u0[i];
    }
    let mut r2 = convergence.residual * convergence.residual * b_norm2;
    // The recursion's residual drifts from the answer's own: by round-off (the answer's
    // own cannot go below about 1e-11 on the cantilever, 2e-9 near incompressibility),
    // and, where K is singular (a loaded piece free to move), without bound: the
    // solution grows along a rigid motion and the round-off of K times it cancels the
    // recursion's residual while the true one stays (a free bar under gravity: 7e-11
    // against 1). Where the answer's own is far above round-off, it is reported.
    let own2 = residual(topo, loads, &free, &u).iter().map(Vec3::norm_squared).sum::<f64>();
    if own2 > NO_SOLUTION * NO_SOLUTION * b_norm2 {
        r2 = own2;
    }
    for ((x, rest), u) in topo.nodes.x.iter_mut().zip(&topo.nodes.rest).zip(&u) {
        *x = rest + u;
    }
    (convergence.iterations, if b_norm2 > 0.0 { (r2 / b_norm2).sqrt() } else { 0.0 })
}

/// `f − K u` on the free nodes (zero on the others), element by element: the assembled
/// matrix leaves out the held nodes' couplings, through which their displacements load
/// the body.
fn residual(topo: &Topology, loads: &[Vec3], free: &[bool], u: &[Vec3]) -> Vec<Vec3> {
    let mut r = vec![Vec3::zeros(); u.len()];
    stiffness_times(topo, &vec![Matrix3::identity(); topo.elements.len()], u, &mut r);
    topo.supports.add_stiffness_times(topo, u, &mut r);
    for (i, r) in r.iter_mut().enumerate() {
        *r = if free[i] { loads[i] - *r } else { Vec3::zeros() };
    }
    r
}

/// `K` over the free nodes' couplings (the step's pattern), with the supports' springs.
fn assemble(topo: &Topology) -> BlockMatrix<f64> {
    let pattern = system_pattern(topo);
    let scatter = Scatter::new(&pattern, &topo.elements.nodes, &topo.elements.alive);
    let mut k = BlockMatrix::<f64>::zeros(pattern);
    for e in (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]) {
        let stiffness = &topo.elements.stiffness[e];
        for i in 0..8 {
            for j in 0..8 {
                let block = Matrix3::from_fn(|p, q| stiffness[(3 * i + p, 3 * j + q)]);
                k.add(scatter.blocks[e][8 * i + j] as usize, &block);
            }
        }
    }
    topo.supports.for_each_block(topo, 1.0, |e, i, j, block| k.add(scatter.blocks[e][8 * i + j] as usize, &block));
    k
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::condense::{Volumetric, VoxelMatrices};
    use crate::grid::topology::Layout;
    use crate::volume::procedural::solid_box;

    /// A bar of 2.5 mm voxels (`size_m`) at level `level`, clamped at x = 0.
    fn bar(size_m: [f64; 3], level: u32) -> Topology {
        let volume = solid_box(size_m, 0.0025, 1);
        let layout = Layout::new(volume.dims, level, volume.spacing_m);
        let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
        let mut t = Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(3e4, 0.45, 1000.0)], Volumetric::MeanDilatation));
        for i in 0..t.nodes.len() {
            t.nodes.fixed[i] = t.nodes.rest[i].x < 1e-9;
        }
        t
    }

    /// The same problem by element-by-element products and Jacobi-preconditioned CG
    /// (how it was solved before the V-cycle).
    fn jacobi_solution(topo: &Topology, loads: &[Vec3]) -> Vec<Vec3> {
        let n = topo.nodes.len();
        let identity = vec![Matrix3::identity(); topo.elements.len()];
        let free: Vec<bool> = (0..n).map(|i| !topo.nodes.fixed[i]).collect();
        let mut diagonal = vec![Vec3::zeros(); n];
        for e in 0..topo.elements.len() {
            for c in 0..8 {
                let k = &topo.elements.stiffness[e];
                diagonal[topo.elements.nodes[e][c] as usize] += Vec3::new(k[(3 * c, 3 * c)], k[(3 * c + 1, 3 * c + 1)], k[(3 * c + 2, 3 * c + 2)]);
            }
        }
        let precondition = |r: &[Vec3]| -> Vec<Vec3> { (0..n).map(|i| if free[i] { r[i].component_div(&diagonal[i]) } else { Vec3::zeros() }).collect() };
        let mut u = vec![Vec3::zeros(); n];
        let mut r: Vec<Vec3> = (0..n).map(|i| if free[i] { loads[i] } else { Vec3::zeros() }).collect();
        let mut z = precondition(&r);
        let mut p = z.clone();
        let mut q = vec![Vec3::zeros(); n];
        let mut rz: f64 = r.iter().zip(&z).map(|(a, b)| a.dot(b)).sum();
        for _ in 0..20_000 {
            stiffness_times(topo, &identity, &p, &mut q);
            (0..n).filter(|&i| !free[i]).for_each(|i| q[i] = Vec3::zeros());
            let alpha = rz / p.iter().zip(&q).map(|(a, b)| a.dot(b)).sum::<f64>();
            for i in 0..n {
                u[i] += p[i] * alpha;
                r[i] -= q[i] * alpha;
            }
            if r.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt() < 1e-13 * loads.iter().map(|v| v.norm_squared()).sum::<f64>().sqrt() {
                break;
            }
            z = precondition(&r);
            let rz_next: f64 = r.iter().zip(&z).map(|(a, b)| a.dot(b)).sum();
            for i in 0..n {
                p[i] = z[i] + p[i] * (rz_next / rz);
            }
            rz = rz_next;
        }
        u
    }

    #[test]
    fn the_static_solve_reaches_the_jacobi_solution_in_a_fraction_of_its_iterations() {
        // 3,321 nodes: V-cycles (40 iterations; block Jacobi needs 727); 117 nodes: an
        // exact solve (two iterations: the first leaves round-off near 1e-12).
        for (size_m, level, at_most) in [([0.1, 0.02, 0.02], 0, 50), ([0.06, 0.01, 0.01], 1, 2)] {
            let mut t = bar(size_m, level);
            let loads: Vec<Vec3> = (0..t.nodes.len()).map(|i| Vec3::new(0.0, 0.0, -9.81 * t.nodes.mass[i])).collect();
            let expected = jacobi_solution(&t, &loads);
            let (iterations, residual) = solve_static(&mut t, &loads, 1e-12, 1_000);
            assert!(residual <= 1e-12, "level {level}: residual {residual:e} after {iterations} iterations");
            let scale = expected.iter().map(|u| u.norm()).fold(0.0, f64::max);
            let worst = (0..t.nodes.len()).map(|i| (t.nodes.x[i] - t.nodes.rest[i] - expected[i]).norm()).fold(0.0, f64::max);
            assert!(worst < 1e-9 * scale, "level {level}: off by {worst:e} of {scale:e}");
            assert!(iterations <= at_most, "level {level}: {iterations} iterations");
        }
    }

    #[test]
    fn a_loaded_body_nothing_holds_stops_as_stalled_not_at_the_cap() {
        let mut t = bar([0.06, 0.01, 0.01], 1);
        t.nodes.fixed.iter_mut().for_each(|f| *f = false);
        let loads: Vec<Vec3> = (0..t.nodes.len()).map(|i| Vec3::new(0.0, 0.0, -9.81 * t.nodes.mass[i])).collect();
        let (iterations, residual) = solve_static(&mut t, &loads, 1e-10, 30_000);
        assert!(residual > 1e-3, "a free body under gravity has no static solution: residual {residual:e} after {iterations} iterations");
        assert!(iterations < 30_000, "{iterations} iterations");
    }

    #[test]
    fn held_displacements_load_the_body() {
        // The clamped end pulled 1 mm along x with no other load: every node of a bar
        // that only stretches moves along x by at most that, the free end by about it.
        let mut t = bar([0.1, 0.02, 0.02], 0);
        for i in 0..t.nodes.len() {
            if t.nodes.fixed[i] {
                t.nodes.x[i].x -= 0.001;
            }
        }
        let loads = vec![Vec3::zeros(); t.nodes.len()];
        let (_, residual) = solve_static(&mut t, &loads, 1e-12, 1_000);
        assert!(residual <= 1e-12, "residual {residual:e}");
        for i in 0..t.nodes.len() {
            let u = t.nodes.x[i] - t.nodes.rest[i];
            assert!((u.x + 0.001).abs() < 1e-9, "node {i} moved {u:?}");
        }
    }
}
