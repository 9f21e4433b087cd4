//! The branched grid's multigrid hierarchy: the same voxels at coarser levels, and the
//! prolongations between them — each fine node interpolated trilinearly from the corners
//! of the coarse element that holds its voxels, the interpolation the condensation itself
//! uses (paper 004, Eq. 1–4). Branching carries over: a fine node follows the coarse
//! element of its own material component, so the two arms of a U-tube in one coarse
//! cell stay apart on every level.

use super::condense::VoxelMatrices;
use super::hex::trilinear_weights;
use super::topology::{Layout, NONE, Topology};
use crate::math::Vec3;
use crate::solver::multigrid::Prolongation;

/// Coarse levels stop when a level has at most this many nodes (its dense factor is
/// then at most (3 × 200)² entries) …
pub const COARSEST_NODES: usize = 200;
/// … or after this many levels.
pub const MAX_COARSE_LEVELS: usize = 6;

/// What building the hierarchy needs of a grid (a copy: it is built off the step).
#[derive(Debug, Clone)]
pub struct Coarsening {
    pub layout: Layout,
    pub material: Vec<u16>,
    pub voxel_matrices: VoxelMatrices,
    /// The fine grid's ghost stiffness (per element, at its cell size).
    pub ghost: super::hex::Mat24,
    pub fine: FineLevel,
}

/// A level's elements and nodes, as the prolongation to the next level needs them.
#[derive(Debug, Clone, Default)]
pub struct FineLevel {
    pub voxel_element: Vec<u32>,
    pub element_nodes: Vec<[u32; 8]>,
    pub element_alive: Vec<bool>,
    pub node_rest: Vec<Vec3>,
    pub node_alive: Vec<bool>,
}

impl FineLevel {
    pub fn of(topo: &Topology) -> Self {
        FineLevel {
            voxel_element: topo.voxel_element.clone(),
            element_nodes: topo.elements.nodes.clone(),
            element_alive: topo.elements.alive.clone(),
            node_rest: topo.nodes.rest.clone(),
            node_alive: topo.nodes.alive.clone(),
        }
    }
}

impl Coarsening {
    pub fn of(topo: &Topology) -> Self {
        Coarsening { layout: topo.layout.clone(), material: topo.material.clone(), voxel_matrices: topo.voxel_matrices().clone(), ghost: *topo.ghost(), fine: FineLevel::of(topo) }
    }

    /// The prolongations from the fine level down, coarsening until a level has at most
    /// `coarsest_nodes` nodes ([`COARSEST_NODES`] in the solver), a coarser level would
    /// not be smaller, or [`MAX_COARSE_LEVELS`] are made.
    pub fn prolongations(&self, coarsest_nodes: usize) -> Vec<Prolongation> {
        self.levels(coarsest_nodes).0
    }

    /// [`Coarsening::prolongations`] and the coarse grids they lead to.
    pub fn levels(&self, coarsest_nodes: usize) -> (Vec<Prolongation>, Vec<Topology>) {
        let mut out = Vec::new();
        let mut grids = Vec::new();
        let mut fine = self.fine.clone();
        let mut level = self.layout.levels;
        let live = |l: &FineLevel| l.node_alive.iter().filter(|&&a| a).count();
        while out.len() < MAX_COARSE_LEVELS && live(&fine) > coarsest_nodes {
            level += 1;
            let layout = Layout::new(self.layout.voxels, level, self.layout.spacing_m);
            let coarse = Topology::build(layout, self.material.clone(), self.voxel_matrices.clone());
            if coarse.nodes.alive_count() >= live(&fine) {
                break;
            }
            out.push(prolongation(&fine, &coarse));
            fine = FineLevel::of(&coarse);
            let single_cell = coarse.layout.cells.iter().all(|&c| c <= 1);
            grids.push(coarse);
            if single_cell {
                break;
            }
        }
        (out, grids)
    }
}

/// Each alive fine node, interpolated trilinearly from the coarse element that holds the
/// voxels of a fine element it belongs to.
pub fn prolongation(fine: &FineLevel, coarse: &Topology) -> Prolongation {
    // A voxel of each fine element.
    let mut voxel_of = vec![usize::MAX; fine.element_nodes.len()];
    for (v, &e) in fine.voxel_element.iter().enumerate() {
        if e != NONE && voxel_of[e as usize] == usize::MAX {
            voxel_of[e as usize] = v;
        }
    }
    let mut rows: Vec<Vec<(u32, f64)>> = vec![Vec::new(); fine.node_rest.len()];
    let mut done = vec![false; fine.node_rest.len()];
    for (e, nodes) in fine.element_nodes.iter().enumerate() {
        if !fine.element_alive[e] || voxel_of[e] == usize::MAX {
            continue;
        }
        let coarse_element = coarse.voxel_element[voxel_of[e]];
        if coarse_element == NONE {
            continue;
        }
        let cell = coarse.elements.cell[coarse_element as usize] as usize;
        let corners = &coarse.elements.nodes[coarse_element as usize];
        for &n in nodes {
            let n = n as usize;
            if done[n] || !fine.node_alive[n] {
                continue;
            }
            done[n] = true;
            let weights = trilinear_weights(coarse.cell_coordinates(cell, fine.node_rest[n]));
            rows[n] = (0..8).map(|k| (corners[k], weights[k])).collect();
        }
    }
    Prolongation::from_rows(coarse.nodes.len(), &rows)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::procedural::{UTube, solid_box, u_tube};

    fn topology(volume: &crate::volume::LabelVolume, levels: u32) -> Topology {
        let layout = Layout::new(volume.dims, levels, volume.spacing_m);
        let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
        Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(1e4, 0.4, 1000.0)], crate::grid::condense::Volumetric::MeanDilatation))
    }

    #[test]
    fn prolongation_reproduces_linear_fields_and_keeps_branches_apart() {
        // A linear field on the coarse nodes, interpolated, is the same field on the fine ones.
        let fine = topology(&solid_box([0.016, 0.008, 0.008], 0.001, 1), 1);
        let coarsening = Coarsening::of(&fine);
        let ps = coarsening.prolongations(8);
        assert!(!ps.is_empty());
        let coarse = Topology::build(Layout::new(fine.layout.voxels, 2, fine.layout.spacing_m), fine.material.clone(), fine.voxel_matrices().clone());
        let field = |x: &Vec3| 3.0 * x.x - 2.0 * x.y + 0.5 * x.z + 1.0;
        let p = &ps[0];
        for n in 0..fine.nodes.len() {
            let value: f64 = (p.start[n] as usize..p.start[n + 1] as usize).map(|k| p.weights[k] * field(&coarse.nodes.rest[p.cols[k] as usize])).sum();
            assert!((value - field(&fine.nodes.rest[n])).abs() < 1e-12, "node {n}");
        }
        // U-tube: the arms share coarse cells but not coarse elements.
        let tube = topology(&u_tube(UTube { arm: 3, gap: 2, depth: 8, base: 8, arm_length: 16 }, 0.001, 1), 2);
        let ps = Coarsening::of(&tube).prolongations(8);
        let coarse = Topology::build(Layout::new(tube.layout.voxels, 3, tube.layout.spacing_m), tube.material.clone(), tube.voxel_matrices().clone());
        // A node at the tip of each arm depends on that arm's coarse element only.
        let tip = |x: f64| (0..tube.nodes.len()).filter(|&n| tube.nodes.alive[n]).min_by(|&a, &b| {
            let d = |n: usize| (tube.nodes.rest[n] - Vec3::new(x, 0.004, 0.024)).norm();
            d(a).total_cmp(&d(b))
        }).unwrap();
        let sources = |n: usize| -> std::collections::BTreeSet<u32> { (ps[0].start[n]..ps[0].start[n + 1]).map(|k| ps[0].cols[k as usize]).collect() };
        let (left, right) = (sources(tip(0.0)), sources(tip(0.008)));
        assert!(left.is_disjoint(&right), "the arms' tips do not share coarse nodes: {left:?} {right:?}");
        assert!(coarse.elements.alive_count() >= 4);
    }
}
