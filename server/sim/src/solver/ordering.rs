//! The order in which a sparse Cholesky factorization eliminates the nodes, chosen to
//! keep the factor small: nested dissection by the nodes' rest positions.
//!
//! Eliminating a node couples all its remaining neighbours, so the factor fills in. A
//! plane of nodes that splits a mesh in two keeps the halves apart if it is eliminated
//! last: each half fills only within itself and towards the plane. Splitting the halves
//! again the same way, down to a few nodes, is George's (1973) nested dissection; on a
//! lattice of n nodes in 3D its factor grows as n^(4/3), against n^(5/3) for an order
//! along the lattice. The grid's nodes sit on lattice planes (every element spans one
//! lattice step of its level), so a plane of equal coordinates is a separator, found
//! from the positions alone: no graph partitioning.
//!
//! Measured against faer's approximate minimum degree (entries of L of the step
//! systems): box lattices fill in a third to a half less (30 × 30 × 30 nodes 124 M →
//! 76 M, 81 × 17 × 17 nodes 101 M → 48 M), the level-0 cantilever of the MuJoCo
//! comparison 15 % less (3.50 M → 2.99 M; its numeric factorization 40 ms instead of
//! 53 ms in double precision on this project's Xeon); but minimum degree does better on
//! the layered abdomen, whose
//! branched nodes make poor planes. `cholesky::Ordering::Fewest` computes both and
//! keeps the smaller.

use crate::math::Vec3;

/// Parts of at most this many nodes are not split further (ordered along their longest
/// axis): smaller leaves save little fill and cost recursion (8 gave the fewest entries
/// on the lattices above, 27 within 2 %).
const LEAF: usize = 8;

/// Coordinates within this fraction of a part's extent of the splitting plane's lie on
/// it (rest positions on a lattice are equal or a lattice step apart).
const ON_PLANE: f64 = 1e-6;

/// `nodes` in nested-dissection order by their `positions`: each part's two halves
/// first (recursively), then the plane between them.
pub fn nested_dissection(positions: &[Vec3], nodes: &[u32]) -> Vec<u32> {
    let mut part = nodes.to_vec();
    let mut order = Vec::with_capacity(nodes.len());
    dissect(positions, &mut part, &mut order);
    debug_assert_eq!(order.len(), nodes.len());
    order
}

fn dissect(positions: &[Vec3], part: &mut [u32], order: &mut Vec<u32>) {
    if part.len() <= LEAF {
        order.extend_from_slice(part);
        return;
    }
    let (mut lo, mut hi) = (Vec3::repeat(f64::INFINITY), Vec3::repeat(f64::NEG_INFINITY));
    for &n in part.iter() {
        lo = lo.inf(&positions[n as usize]);
        hi = hi.sup(&positions[n as usize]);
    }
    let extent = hi - lo;
    // The longest axis first; if its median plane leaves a side empty (most nodes on
    // one plane), the next.
    let mut axes = [0usize, 1, 2];
    axes.sort_by(|&a, &b| extent[b].total_cmp(&extent[a]));
    for axis in axes {
        if !(extent[axis] > 0.0) {
            break;
        }
        // Sorted along the axis (ties by index: the same order on every machine).
        part.sort_unstable_by(|&a, &b| positions[a as usize][axis].total_cmp(&positions[b as usize][axis]).then(a.cmp(&b)));
        let plane = positions[part[part.len() / 2] as usize][axis];
        let tolerance = ON_PLANE * extent[axis];
        let below = part.partition_point(|&n| positions[n as usize][axis] < plane - tolerance);
        let above = part.partition_point(|&n| positions[n as usize][axis] <= plane + tolerance);
        if below == 0 || above == part.len() {
            continue;
        }
        let (first, rest) = part.split_at_mut(below);
        let (separator, second) = rest.split_at_mut(above - below);
        dissect(positions, first, order);
        dissect(positions, second, order);
        order.extend_from_slice(separator);
        return;
    }
    // No plane splits it (all nodes on one plane of every axis, or at one point).
    order.extend_from_slice(part);
}

#[cfg(test)]
mod tests {
    use super::*;

    fn lattice(nx: usize, ny: usize, nz: usize) -> Vec<Vec3> {
        let mut p = Vec::new();
        for i in 0..nx {
            for j in 0..ny {
                for k in 0..nz {
                    p.push(Vec3::new(i as f64, j as f64, k as f64) * 0.0025);
                }
            }
        }
        p
    }

    #[test]
    fn the_order_is_a_permutation_of_the_nodes_given() {
        let positions = lattice(9, 4, 3);
        let nodes: Vec<u32> = (0..positions.len() as u32).filter(|n| n % 5 != 0).collect();
        let mut order = nested_dissection(&positions, &nodes);
        order.sort_unstable();
        assert_eq!(order, nodes);
    }

    #[test]
    fn the_middle_plane_of_a_bar_comes_last() {
        // 9 planes along x: the first split is the plane x = 4 (nodes 4·9 .. 5·9).
        let positions = lattice(9, 3, 3);
        let nodes: Vec<u32> = (0..positions.len() as u32).collect();
        let order = nested_dissection(&positions, &nodes);
        let mut last: Vec<u32> = order[order.len() - 9..].to_vec();
        last.sort_unstable();
        assert_eq!(last, (36..45).collect::<Vec<u32>>());
        // Each half comes whole before it, the lower first.
        assert!(order[..36].iter().all(|&n| n < 36), "{order:?}");
    }

    #[test]
    fn nodes_on_one_point_are_kept_whole() {
        let positions = vec![Vec3::new(1.0, 2.0, 3.0); 20];
        let nodes: Vec<u32> = (0..20).collect();
        assert_eq!(nested_dissection(&positions, &nodes), nodes);
    }
}
