//! The branched grid's topology: coarse cells, one element per connected component of
//! a cell's voxels (superimposed when there are several), and nodes shared only where
//! material touches across a cell border (paper 004, Section 2.1).
//!
//! Node sharing is decided per grid point: the element corners ("slots") that meet at a
//! point are joined when their elements lie in face-adjacent cells whose voxels touch
//! across that face; each class of joined slots is one node. Since a point's classes
//! depend only on the ≤ 8 cells around it, removing voxels re-decides only the corners
//! of the cells that held them ([`Topology::remove_voxels`]): the cost follows the
//! number of removed voxels, not the size of the volume.

use std::collections::{BTreeMap, BTreeSet, HashMap};

use super::condense::{CellVoxel, Condensed, Dilatation, VoxelMatrices, condense_direct, remove_contribution, voxel_contribution};
use super::hex::{Mat8, Mat24, corner_bits};
use super::shared_stiffness::SharedStiffness;
use crate::solver::kernels::{Planar24, to_planar};
use crate::union_find::UnionFind;
use crate::math::Vec3;

pub const NONE: u32 = u32::MAX;

/// Sizes of the voxel grid and of the coarse grid above it.
#[derive(Debug, Clone, PartialEq)]
pub struct Layout {
    /// Voxels along each axis.
    pub voxels: [usize; 3],
    /// Coarsening level L: a cell is 2^L voxels a side.
    pub levels: u32,
    pub side: usize,
    /// Cells along each axis.
    pub cells: [usize; 3],
    /// Voxel size along each axis, m.
    pub spacing_m: [f64; 3],
}

impl Layout {
    pub fn new(voxels: [usize; 3], levels: u32, spacing_m: [f64; 3]) -> Self {
        let side = 1usize << levels;
        Self { voxels, levels, side, cells: voxels.map(|n| n.div_ceil(side)), spacing_m }
    }

    /// A voxel's smallest side, m.
    pub fn smallest_side_m(&self) -> f64 {
        self.spacing_m.into_iter().fold(f64::INFINITY, f64::min)
    }

    pub fn voxel_index(&self, v: [usize; 3]) -> usize {
        v[0] + self.voxels[0] * (v[1] + self.voxels[1] * v[2])
    }

    pub fn voxel_coords(&self, index: usize) -> [usize; 3] {
        [index % self.voxels[0], (index / self.voxels[0]) % self.voxels[1], index / (self.voxels[0] * self.voxels[1])]
    }

    pub fn cell_count(&self) -> usize {
        self.cells[0] * self.cells[1] * self.cells[2]
    }

    pub fn cell_index(&self, c: [usize; 3]) -> usize {
        c[0] + self.cells[0] * (c[1] + self.cells[1] * c[2])
    }

    pub fn cell_coords(&self, index: usize) -> [usize; 3] {
        [index % self.cells[0], (index / self.cells[0]) % self.cells[1], index / (self.cells[0] * self.cells[1])]
    }

    pub fn cell_of_voxel(&self, v: [usize; 3]) -> [usize; 3] {
        v.map(|c| c / self.side)
    }

    pub fn point_index(&self, p: [usize; 3]) -> usize {
        p[0] + (self.cells[0] + 1) * (p[1] + (self.cells[1] + 1) * p[2])
    }

    pub fn point_coords(&self, index: usize) -> [usize; 3] {
        let (nx, ny) = (self.cells[0] + 1, self.cells[1] + 1);
        [index % nx, (index / nx) % ny, index / (nx * ny)]
    }

    /// Rest position of a grid point in the grid's frame (voxel (0,0,0) spans
    /// [0, spacing] on each axis), m.
    pub fn point_position(&self, p: [usize; 3]) -> Vec3 {
        Vec3::new(
            (p[0] * self.side) as f64 * self.spacing_m[0],
            (p[1] * self.side) as f64 * self.spacing_m[1],
            (p[2] * self.side) as f64 * self.spacing_m[2],
        )
    }

    /// Side lengths of a cell, m.
    pub fn cell_size_m(&self) -> Vec3 {
        Vec3::new(self.spacing_m[0], self.spacing_m[1], self.spacing_m[2]) * self.side as f64
    }

    /// The point at corner `n` of cell `c`.
    pub fn corner_point(&self, c: [usize; 3], n: usize) -> [usize; 3] {
        [c[0] + (n & 1), c[1] + ((n >> 1) & 1), c[2] + ((n >> 2) & 1)]
    }

    /// Cells around a point, with the corner each has there.
    pub fn cells_around(&self, p: [usize; 3]) -> impl Iterator<Item = ([usize; 3], usize)> + '_ {
        (0..8usize).filter_map(move |n| {
            let b = [n & 1, (n >> 1) & 1, (n >> 2) & 1];
            let c = [0, 1, 2].map(|a| p[a].wrapping_sub(b[a]));
            (0..3).all(|a| c[a] < self.cells[a]).then_some((c, n))
        })
    }
}

/// Elements, one per connected component of a cell's voxels (struct of arrays).
#[derive(Debug, Clone, Default)]
pub struct Elements {
    pub cell: Vec<u32>,
    pub nodes: Vec<[u32; 8]>,
    pub stiffness: Vec<Mat24>,
    /// What the solver uses: `stiffness` plus the ghost (see [`Topology::set_ghost`]),
    /// rounded to single precision — half the memory traffic of the double-precision
    /// matrices, which do not fit in cache on large scenes, at a relative precision
    /// (6e-8) far below the solve's tolerance — in the planar layout the vectorized
    /// kernels take (`solver::kernels::Planar24`). At rest the strain is exactly zero,
    /// so the rounding makes no force there. Each distinct matrix is stored once
    /// (`super::shared_stiffness`): at level 0 an element's is its voxel's.
    pub stiffness_single: SharedStiffness,
    /// Consistent scalar mass (the 3D matrix is this ⊗ I₃).
    pub mass: Vec<Mat8>,
    /// Per material present, its volume as a function of the nodes (mean-dilatation
    /// elements; empty with fully integrated ones).
    pub dilatations: Vec<Vec<Dilatation>>,
    pub voxel_count: Vec<u32>,
    pub alive: Vec<bool>,
}

impl Elements {
    pub fn len(&self) -> usize {
        self.cell.len()
    }

    pub fn is_empty(&self) -> bool {
        self.cell.is_empty()
    }

    pub fn alive_count(&self) -> usize {
        self.alive.iter().filter(|&&a| a).count()
    }

    fn push(&mut self, cell: u32, nodes: [u32; 8], condensed: Condensed, ghost: &Mat24, voxels: u32) -> u32 {
        self.cell.push(cell);
        self.nodes.push(nodes);
        self.stiffness_single.push(&single(&(condensed.stiffness + ghost)));
        self.stiffness.push(condensed.stiffness);
        self.mass.push(condensed.mass);
        self.dilatations.push(condensed.dilatations);
        self.voxel_count.push(voxels);
        self.alive.push(true);
        (self.cell.len() - 1) as u32
    }
}

/// A stiffness as the solver stores it (single precision, planar).
fn single(k: &Mat24) -> Planar24 {
    let values: Vec<f32> = k.as_slice().iter().map(|&v| v as f32).collect();
    to_planar(&values)
}

/// Nodes: grid point, rest position, state and lumped mass.
#[derive(Debug, Clone, Default)]
pub struct Nodes {
    pub point: Vec<u32>,
    pub rest: Vec<Vec3>,
    pub x: Vec<Vec3>,
    pub v: Vec<Vec3>,
    /// Lumped mass (row sums of the elements' consistent mass), kg.
    pub mass: Vec<f64>,
    pub fixed: Vec<bool>,
    pub alive: Vec<bool>,
}

impl Nodes {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn is_empty(&self) -> bool {
        self.x.is_empty()
    }

    pub fn alive_count(&self) -> usize {
        self.alive.iter().filter(|&&a| a).count()
    }

    fn push(&mut self, point: u32, rest: Vec3, x: Vec3, v: Vec3, fixed: bool) -> u32 {
        self.point.push(point);
        self.rest.push(rest);
        self.x.push(x);
        self.v.push(v);
        self.mass.push(0.0);
        self.fixed.push(fixed);
        self.alive.push(true);
        (self.x.len() - 1) as u32
    }
}

/// What a voxel removal did to the coarse grid.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct UpdateReport {
    pub voxels_removed: usize,
    /// Elements whose last voxel went.
    pub cells_removed: usize,
    /// Elements that fell into several components (replaced by superimposed elements).
    pub cells_split: usize,
    /// Elements that kept their material in one piece but lost a link to a neighbour.
    pub cells_disconnected: usize,
    /// Elements that only lost stiffness and mass.
    pub cells_updated: usize,
    pub nodes_added: usize,
    pub nodes_removed: usize,
    /// Elements created (split products), and grid points whose nodes were re-decided.
    pub new_elements: Vec<u32>,
    pub points: Vec<u32>,
}

/// The grid's voxels, cells, elements and nodes.
#[derive(Debug, Clone)]
pub struct Topology {
    pub layout: Layout,
    /// Per voxel: 0 empty, else material index + 1.
    pub material: Vec<u16>,
    /// Per voxel: its element, or NONE.
    pub voxel_element: Vec<u32>,
    /// Per cell: its alive elements.
    pub cell_elements: Vec<Vec<u32>>,
    pub elements: Elements,
    pub nodes: Nodes,
    voxel_matrices: VoxelMatrices,
    /// Added to every element's stiffness in the solver (zero unless set).
    ghost: Mat24,
    /// The held level-0 points that are not nodes (coarse levels), on springs.
    pub supports: super::support::Supports,
}

impl Topology {
    /// Builds the grid from per-voxel materials (0 empty, else material index + 1).
    pub fn build(layout: Layout, material: Vec<u16>, voxel_matrices: VoxelMatrices) -> Self {
        assert_eq!(material.len(), layout.voxels.iter().product::<usize>());
        let mut t = Topology {
            voxel_element: vec![NONE; material.len()],
            cell_elements: vec![Vec::new(); layout.cell_count()],
            layout,
            material,
            elements: Elements::default(),
            nodes: Nodes::default(),
            voxel_matrices,
            ghost: Mat24::zeros(),
            supports: Default::default(),
        };
        for cell in 0..t.layout.cell_count() {
            for component in t.components(cell) {
                t.add_element(cell, &component, None);
            }
        }
        let points: Vec<usize> = (0..(t.layout.cells[0] + 1) * (t.layout.cells[1] + 1) * (t.layout.cells[2] + 1)).collect();
        let mut faces = HashMap::new();
        for &p in &points {
            t.assign_point(p, &mut faces, &BTreeMap::new(), None);
        }
        t
    }

    /// Fills every cell's void with a ghost material of stiffness `ghost` (an element's
    /// stiffness for a full cell), seen only by the solver. Without it the far corners
    /// of an element holding a few voxels have almost no stiffness and mass: the solve
    /// leaves them nearly free, they drift, and through the element's rotation they
    /// disturb their neighbours. The scene builder uses 1e-3 of the softest material.
    pub fn set_ghost(&mut self, ghost: Mat24) {
        self.ghost = ghost;
        for e in 0..self.elements.len() {
            self.elements.stiffness_single.set(e, &single(&(self.elements.stiffness[e] + ghost)));
        }
    }

    /// The ghost stiffness added to every element in the solver.
    pub fn ghost(&self) -> &Mat24 {
        &self.ghost
    }

    pub fn voxel_matrices(&self) -> &VoxelMatrices {
        &self.voxel_matrices
    }

    /// The voxels of a cell (global indices) that hold material.
    fn cell_voxels(&self, cell: usize) -> Vec<usize> {
        let c = self.layout.cell_coords(cell);
        let s = self.layout.side;
        let mut out = Vec::new();
        for z in c[2] * s..((c[2] + 1) * s).min(self.layout.voxels[2]) {
            for y in c[1] * s..((c[1] + 1) * s).min(self.layout.voxels[1]) {
                for x in c[0] * s..((c[0] + 1) * s).min(self.layout.voxels[0]) {
                    let v = self.layout.voxel_index([x, y, z]);
                    if self.material[v] != 0 {
                        out.push(v);
                    }
                }
            }
        }
        out
    }

    /// The 6-connected components of a cell's material, each sorted, ordered by first voxel.
    fn components(&self, cell: usize) -> Vec<Vec<usize>> {
        let voxels = self.cell_voxels(cell);
        let c = self.layout.cell_coords(cell);
        let s = self.layout.side;
        let local = |v: usize| {
            let g = self.layout.voxel_coords(v);
            (g[0] - c[0] * s) + s * ((g[1] - c[1] * s) + s * (g[2] - c[2] * s))
        };
        let mut label = vec![NONE; s * s * s];
        for &v in &voxels {
            label[local(v)] = 0;
        }
        let mut out: Vec<Vec<usize>> = Vec::new();
        let mut stack = Vec::new();
        for &start in &voxels {
            if label[local(start)] != 0 {
                continue;
            }
            let id = out.len() as u32 + 1;
            let mut component = Vec::new();
            label[local(start)] = id;
            stack.push(start);
            while let Some(v) = stack.pop() {
                component.push(v);
                let g = self.layout.voxel_coords(v);
                for a in 0..3 {
                    for step in [-1i64, 1] {
                        let n = g[a] as i64 + step;
                        if n < (c[a] * s) as i64 || n >= ((c[a] + 1) * s).min(self.layout.voxels[a]) as i64 {
                            continue;
                        }
                        let mut ng = g;
                        ng[a] = n as usize;
                        let nv = self.layout.voxel_index(ng);
                        if label.get(local(nv)) == Some(&0) {
                            label[local(nv)] = id;
                            stack.push(nv);
                        }
                    }
                }
            }
            component.sort_unstable();
            out.push(component);
        }
        out
    }

    fn cell_voxel(&self, cell: usize, v: usize) -> CellVoxel {
        let c = self.layout.cell_coords(cell);
        let g = self.layout.voxel_coords(v);
        let s = self.layout.side;
        CellVoxel { at: [0, 1, 2].map(|a| (g[a] - c[a] * s) as u16), material: self.material[v] - 1 }
    }

    /// Adds an element for a component, condensed directly; its nodes start as `nodes`.
    fn add_element(&mut self, cell: usize, voxels: &[usize], nodes: Option<[u32; 8]>) -> u32 {
        let cell_voxels: Vec<CellVoxel> = voxels.iter().map(|&v| self.cell_voxel(cell, v)).collect();
        let condensed = condense_direct(&cell_voxels, self.layout.levels, &self.voxel_matrices);
        let e = self.elements.push(cell as u32, nodes.unwrap_or([NONE; 8]), condensed, &self.ghost, voxels.len() as u32);
        for &v in voxels {
            self.voxel_element[v] = e;
        }
        self.cell_elements[cell].push(e);
        e
    }

    /// Element pairs (lower cell's, upper cell's) whose voxels touch across the face
    /// between cell `c` and its neighbour along `axis`.
    fn face_pairs(&self, c: [usize; 3], axis: usize) -> Vec<(u32, u32)> {
        let s = self.layout.side;
        let (u_axis, v_axis) = ((axis + 1) % 3, (axis + 2) % 3);
        let lower = c[axis] * s + s - 1;
        if lower + 1 >= self.layout.voxels[axis] {
            return Vec::new();
        }
        let mut pairs = Vec::new();
        for u in c[u_axis] * s..((c[u_axis] + 1) * s).min(self.layout.voxels[u_axis]) {
            for v in c[v_axis] * s..((c[v_axis] + 1) * s).min(self.layout.voxels[v_axis]) {
                let mut g = [0usize; 3];
                g[axis] = lower;
                g[u_axis] = u;
                g[v_axis] = v;
                let a = self.layout.voxel_index(g);
                g[axis] = lower + 1;
                let b = self.layout.voxel_index(g);
                if self.material[a] != 0 && self.material[b] != 0 {
                    pairs.push((self.voxel_element[a], self.voxel_element[b]));
                }
            }
        }
        pairs.sort_unstable();
        pairs.dedup();
        pairs
    }

    /// Decides the nodes at grid point `p`: joins the slots of touching elements and
    /// gives every class a node — the node its slots had (`source`), or a new copy of it
    /// when another class took that one first. Returns (nodes added, old nodes released).
    fn assign_point(
        &mut self,
        p: usize,
        faces: &mut HashMap<(usize, usize), Vec<(u32, u32)>>,
        parent: &BTreeMap<u32, u32>,
        old_nodes: Option<&BTreeSet<u32>>,
    ) -> (usize, usize) {
        let pc = self.layout.point_coords(p);
        let around: Vec<([usize; 3], usize)> = self.layout.cells_around(pc).collect();
        let mut slots: Vec<(u32, usize)> = Vec::new();
        for &(c, n) in &around {
            for &e in &self.cell_elements[self.layout.cell_index(c)] {
                slots.push((e, n));
            }
        }
        if slots.is_empty() {
            return (0, old_nodes.map_or(0, |o| self.release(o, &BTreeSet::new())));
        }
        slots.sort_unstable();
        let index_of = |slots: &[(u32, usize)], e: u32| slots.iter().position(|s| s.0 == e).expect("element around the point");
        let mut classes = UnionFind::new(slots.len());
        // Face-adjacent cell pairs around p: corners differing in one bit.
        for &(c1, n1) in &around {
            for axis in 0..3 {
                if (n1 >> axis) & 1 == 0 {
                    continue; // c1 must be the lower cell along axis: its corner at p has bit 1
                }
                let n2 = n1 & !(1 << axis);
                // The cell across the face must be one of the cells around p too.
                if !around.iter().any(|&(_, n)| n == n2) {
                    continue;
                }
                let pairs = faces.entry((self.layout.cell_index(c1), axis)).or_insert_with(|| self.face_pairs(c1, axis));
                for &(a, b) in pairs.iter() {
                    classes.union(index_of(&slots, a), index_of(&slots, b));
                }
            }
        }
        // Classes in order of their first slot.
        let mut members: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for i in 0..slots.len() {
            members.entry(classes.find(i)).or_default().push(i);
        }
        let point_position = self.layout.point_position(pc);
        let mut claimed = BTreeSet::new();
        let mut added = 0;
        for class in members.values() {
            // The node the class's slots had (new elements look at their parent's).
            let source = class
                .iter()
                .map(|&i| {
                    let (e, n) = slots[i];
                    let node = self.elements.nodes[e as usize][n];
                    if node == NONE { parent.get(&e).map_or(NONE, |&pe| self.elements.nodes[pe as usize][n]) } else { node }
                })
                .filter(|&n| n != NONE)
                .min();
            let node = match source {
                Some(s) if !claimed.contains(&s) => s,
                Some(s) => {
                    added += 1;
                    let (x, v, fixed) = (self.nodes.x[s as usize], self.nodes.v[s as usize], self.nodes.fixed[s as usize]);
                    self.nodes.push(p as u32, point_position, x, v, fixed)
                }
                None => self.nodes.push(p as u32, point_position, point_position, Vec3::zeros(), false),
            };
            claimed.insert(node);
            for &i in class {
                let (e, n) = slots[i];
                self.elements.nodes[e as usize][n] = node;
            }
        }
        // Lumped masses of the point's nodes.
        for &node in &claimed {
            self.nodes.mass[node as usize] = 0.0;
        }
        for &(e, n) in &slots {
            let m = &self.elements.mass[e as usize];
            let row: f64 = (0..8).map(|j| m[(n, j)]).sum();
            self.nodes.mass[self.elements.nodes[e as usize][n] as usize] += row;
        }
        let released = old_nodes.map_or(0, |o| self.release(o, &claimed));
        (added, released)
    }

    fn release(&mut self, old: &BTreeSet<u32>, kept: &BTreeSet<u32>) -> usize {
        let mut n = 0;
        for &node in old.difference(kept) {
            if self.nodes.alive[node as usize] {
                self.nodes.alive[node as usize] = false;
                self.nodes.mass[node as usize] = 0.0;
                self.nodes.v[node as usize] = Vec3::zeros();
                n += 1;
            }
        }
        n
    }

    /// Removes voxels (global indices; empty ones are ignored) and updates the cells
    /// that held them: removal, split, disconnect or update only (see the module docs).
    pub fn remove_voxels(&mut self, removed: &[usize]) -> UpdateReport {
        let mut report = UpdateReport::default();
        let mut by_cell: BTreeMap<usize, Vec<usize>> = BTreeMap::new();
        for &v in removed {
            if v < self.material.len() && self.material[v] != 0 {
                let cell = self.layout.cell_index(self.layout.cell_of_voxel(self.layout.voxel_coords(v)));
                by_cell.entry(cell).or_default().push(v);
            }
        }
        if by_cell.is_empty() {
            return report;
        }
        // The corners of the affected cells and the nodes there now.
        let mut points = BTreeSet::new();
        for &cell in by_cell.keys() {
            let c = self.layout.cell_coords(cell);
            for n in 0..8 {
                points.insert(self.layout.point_index(self.layout.corner_point(c, n)));
            }
        }
        let mut old_nodes: BTreeMap<usize, BTreeSet<u32>> = BTreeMap::new();
        for &p in &points {
            let pc = self.layout.point_coords(p);
            let set = old_nodes.entry(p).or_default();
            for (c, n) in self.layout.cells_around(pc) {
                for &e in &self.cell_elements[self.layout.cell_index(c)] {
                    set.insert(self.elements.nodes[e as usize][n]);
                }
            }
        }
        let mut parent: BTreeMap<u32, u32> = BTreeMap::new();
        let mut kept_elements = Vec::new();
        for (&cell, voxels) in &by_cell {
            for &v in voxels {
                let e = self.voxel_element[v];
                let part = voxel_contribution(self.cell_voxel(cell, v), self.layout.side as u32, &self.voxel_matrices);
                let e = e as usize;
                let elements = &mut self.elements;
                remove_contribution(&mut elements.stiffness[e], &mut elements.mass[e], &mut elements.dilatations[e], &part, &self.voxel_matrices);
                elements.stiffness_single.set(e, &single(&(elements.stiffness[e] + self.ghost)));
                let e = e as u32;
                self.elements.voxel_count[e as usize] -= 1;
                self.material[v] = 0;
                self.voxel_element[v] = NONE;
                report.voxels_removed += 1;
            }
            let old: Vec<u32> = self.cell_elements[cell].clone();
            let components = self.components(cell);
            // Which old element each component came from (components never merge).
            let mut per_old: BTreeMap<u32, Vec<Vec<usize>>> = BTreeMap::new();
            for component in components {
                per_old.entry(self.voxel_element[component[0]]).or_default().push(component);
            }
            for &e in &old {
                match per_old.remove(&e) {
                    None => {
                        self.elements.alive[e as usize] = false;
                        self.cell_elements[cell].retain(|&x| x != e);
                        report.cells_removed += 1;
                    }
                    Some(parts) if parts.len() == 1 => kept_elements.push(e),
                    Some(parts) => {
                        // Split: superimposed elements, each condensed from its own voxels.
                        self.elements.alive[e as usize] = false;
                        self.cell_elements[cell].retain(|&x| x != e);
                        for part in parts {
                            let new = self.add_element(cell, &part, Some([NONE; 8]));
                            parent.insert(new, e);
                            report.new_elements.push(new);
                        }
                        report.cells_split += 1;
                    }
                }
            }
        }
        let before: BTreeMap<u32, [u32; 8]> = kept_elements.iter().map(|&e| (e, self.elements.nodes[e as usize])).collect();
        let mut faces = HashMap::new();
        for &p in &points {
            let (added, released) = self.assign_point(p, &mut faces, &parent, old_nodes.get(&p));
            report.nodes_added += added;
            report.nodes_removed += released;
        }
        for (e, nodes) in before {
            if self.elements.nodes[e as usize] != nodes {
                report.cells_disconnected += 1;
            } else {
                report.cells_updated += 1;
            }
        }
        report.points = points.into_iter().map(|p| p as u32).collect();
        report
    }

    /// Connected pieces: elements joined through shared nodes.
    pub fn pieces(&self) -> usize {
        let numbers = self.element_pieces();
        numbers.iter().filter(|&&p| p != NONE).max().map_or(0, |&p| p as usize + 1)
    }

    /// The elements' piece number (0-based, in order of their lowest element id).
    pub fn element_pieces(&self) -> Vec<u32> {
        let mut sets = UnionFind::new(self.nodes.len());
        for (e, nodes) in self.elements.nodes.iter().enumerate() {
            if self.elements.alive[e] {
                for &n in &nodes[1..] {
                    sets.union(nodes[0] as usize, n as usize);
                }
            }
        }
        let mut numbers: BTreeMap<usize, u32> = BTreeMap::new();
        (0..self.elements.len())
            .map(|e| {
                if !self.elements.alive[e] {
                    return NONE;
                }
                let root = sets.find(self.elements.nodes[e][0] as usize);
                let next = numbers.len() as u32;
                *numbers.entry(root).or_insert(next)
            })
            .collect()
    }

    /// Rest position of a cell's corner 0, m.
    pub fn cell_origin(&self, cell: usize) -> Vec3 {
        self.layout.point_position(self.layout.cell_coords(cell))
    }

    /// Unit-cube coordinates of a rest-space point inside cell `cell`.
    pub fn cell_coordinates(&self, cell: usize, rest: Vec3) -> [f64; 3] {
        let o = self.cell_origin(cell);
        let size = self.layout.cell_size_m();
        [(rest.x - o.x) / size.x, (rest.y - o.y) / size.y, (rest.z - o.z) / size.z]
    }

    /// Rest-space centre of a voxel, m.
    pub fn voxel_centre(&self, v: usize) -> Vec3 {
        let g = self.layout.voxel_coords(v);
        Vec3::new((g[0] as f64 + 0.5) * self.layout.spacing_m[0], (g[1] as f64 + 0.5) * self.layout.spacing_m[1], (g[2] as f64 + 0.5) * self.layout.spacing_m[2])
    }

    /// A description independent of element and node numbering, for comparing an
    /// incrementally updated grid with one rebuilt from scratch: per element (named by
    /// its sorted voxels) its matrices, and per grid point the partition of the
    /// element corners there into nodes.
    pub fn canonical(&self) -> CanonicalGrid {
        let mut voxels_of: BTreeMap<u32, Vec<usize>> = BTreeMap::new();
        for (v, &e) in self.voxel_element.iter().enumerate() {
            if e != NONE {
                voxels_of.entry(e).or_default().push(v);
            }
        }
        let name = |e: u32| voxels_of[&e][0];
        let elements = voxels_of.iter().map(|(&e, voxels)| (voxels.clone(), (self.elements.stiffness[e as usize], self.elements.mass[e as usize]))).collect();
        let mut points: BTreeMap<u32, BTreeMap<u32, BTreeSet<(usize, usize)>>> = BTreeMap::new();
        for &e in voxels_of.keys() {
            for n in 0..8 {
                let node = self.elements.nodes[e as usize][n];
                points.entry(self.nodes.point[node as usize]).or_default().entry(node).or_default().insert((name(e), n));
            }
        }
        let sharing = points.into_iter().map(|(p, classes)| (p, classes.into_values().collect())).collect();
        CanonicalGrid { elements, sharing }
    }
}

/// See [`Topology::canonical`].
#[derive(Debug, Clone)]
pub struct CanonicalGrid {
    pub elements: BTreeMap<Vec<usize>, (Mat24, Mat8)>,
    pub sharing: BTreeMap<u32, BTreeSet<BTreeSet<(usize, usize)>>>,
}

impl CanonicalGrid {
    /// None when equal (matrices to `tolerance` relative), else what differs.
    pub fn difference(&self, other: &CanonicalGrid, tolerance: f64) -> Option<String> {
        if self.elements.len() != other.elements.len() {
            return Some(format!("{} elements against {}", self.elements.len(), other.elements.len()));
        }
        for ((va, (ka, ma)), (vb, (kb, mb))) in self.elements.iter().zip(&other.elements) {
            if va != vb {
                return Some(format!("an element holds voxels {:?}… against {:?}…", &va[..va.len().min(4)], &vb[..vb.len().min(4)]));
            }
            let dk = (ka - kb).norm() / ka.norm().max(kb.norm()).max(f64::MIN_POSITIVE);
            let dm = (ma - mb).norm() / ma.norm().max(mb.norm()).max(f64::MIN_POSITIVE);
            if dk > tolerance || dm > tolerance {
                return Some(format!("the element of voxel {} differs: stiffness {dk:e}, mass {dm:e}", va[0]));
            }
        }
        if self.sharing != other.sharing {
            let p = self.sharing.iter().find(|(p, s)| other.sharing.get(p) != Some(s)).map(|(p, _)| *p);
            return Some(format!("node sharing differs at grid point {p:?}"));
        }
        None
    }
}

/// Corner `n`'s unit-cube position (re-exported for the model).
pub fn corner_unit(n: usize) -> [f64; 3] {
    corner_bits(n)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::volume::LabelVolume;
    use crate::volume::procedural::{UTube, ellipsoid, solid_box, u_tube};

    fn topology(volume: &LabelVolume, levels: u32) -> Topology {
        let layout = Layout::new(volume.dims, levels, volume.spacing_m);
        let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
        Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(1e4, 0.4, 1000.0)], crate::grid::condense::Volumetric::MeanDilatation))
    }

    #[test]
    fn a_u_tube_branches_where_its_arms_share_a_cell() {
        let v = u_tube(UTube { arm: 3, gap: 2, depth: 8, base: 8, arm_length: 16 }, 0.001, 1);
        let t = topology(&v, 3);
        assert_eq!(t.layout.cells, [1, 1, 3]);
        assert_eq!(t.elements.alive_count(), 5, "a base element and two superimposed arm elements in each upper cell");
        // Base: 8 nodes; the arms share the base's top 4; above, each arm has its own.
        assert_eq!(t.nodes.alive_count(), 4 + 4 + 8 + 8);
        let top: Vec<[u32; 8]> = t.cell_elements[2].iter().map(|&e| t.elements.nodes[e as usize]).collect();
        assert_eq!(top.len(), 2);
        assert!(top[0].iter().all(|n| !top[1].contains(n)), "the arm tips share no node");
        let middle: Vec<[u32; 8]> = t.cell_elements[1].iter().map(|&e| t.elements.nodes[e as usize]).collect();
        assert_eq!(middle[0][..4], middle[1][..4], "both arms hang from the base's top nodes");
        assert_eq!(t.pieces(), 1);
        // Mass: all of it, once.
        let total: f64 = (0..t.nodes.len()).filter(|&n| t.nodes.alive[n]).map(|n| t.nodes.mass[n]).sum();
        assert!((total - v.count(1) as f64 * 1e-9 * 1000.0).abs() < 1e-15);
    }

    #[test]
    fn removing_voxels_equals_rebuilding_without_them() {
        let mut v = ellipsoid([0.008, 0.006, 0.005], 0.001, 1);
        let mut t = topology(&v, 2);
        let before = t.nodes.alive_count();
        // A voxel deep inside, then a slab that cuts the body in two, then a column.
        let centre = v.dims.map(|d| d / 2);
        let mut steps: Vec<Vec<[usize; 3]>> = vec![vec![centre]];
        steps.push((0..v.dims[1]).flat_map(|j| (0..v.dims[2]).map(move |k| [centre[0], j, k])).collect());
        steps.push((0..v.dims[2]).map(|k| [centre[0] + 3, centre[1], k]).collect());
        for (s, voxels) in steps.into_iter().enumerate() {
            let indices: Vec<usize> = voxels.iter().map(|&g| t.layout.voxel_index(g)).collect();
            let report = t.remove_voxels(&indices);
            for g in &voxels {
                v.set(g[0], g[1], g[2], 0);
            }
            let rebuilt = topology(&v, 2);
            if let Some(diff) = t.canonical().difference(&rebuilt.canonical(), 1e-10) {
                panic!("step {s}: {diff} ({report:?})");
            }
            // Only the corners of the cells that held the voxels were re-decided.
            let cells: BTreeSet<usize> = if report.voxels_removed > 0 { indices.iter().map(|&i| t.layout.cell_index(t.layout.cell_of_voxel(t.layout.voxel_coords(i)))).collect() } else { BTreeSet::new() };
            assert!(report.points.len() <= 8 * cells.len());
            if s == 1 {
                assert_eq!(t.pieces(), 2, "the slab separates the two halves");
                assert!(report.cells_split + report.cells_removed + report.cells_disconnected > 0);
                assert!(t.nodes.alive_count() > before - 20);
            }
        }
    }

    #[test]
    fn a_voxel_removal_that_splits_a_cell_keeps_node_positions() {
        let v = solid_box([0.004, 0.004, 0.004], 0.001, 1);
        let mut t = topology(&v, 2);
        for n in 0..t.nodes.len() {
            t.nodes.x[n] += Vec3::new(0.001 * n as f64, 0.0, 0.0);
            t.nodes.v[n] = Vec3::new(0.0, n as f64, 0.0);
        }
        // Remove the middle layer x = 1..=2 except nothing: the cell splits into two slabs.
        let slab: Vec<usize> = (0..4).flat_map(|j| (0..4).flat_map(move |k| [1usize, 2].map(|i| [i, j, k]))).map(|g| t.layout.voxel_index(g)).collect();
        let report = t.remove_voxels(&slab);
        assert_eq!(report.cells_split, 1);
        assert_eq!(t.elements.alive_count(), 2);
        assert_eq!(report.nodes_added, 8);
        assert_eq!(t.pieces(), 2);
        for n in 0..t.nodes.len() {
            if t.nodes.alive[n] {
                let p = t.nodes.point[n] as usize;
                let original = (0..8).find(|&m| t.nodes.point[m] as usize == p).unwrap();
                assert_eq!(t.nodes.x[n], t.nodes.x[original], "a new node starts where its source is");
                assert_eq!(t.nodes.v[n], t.nodes.v[original]);
            }
        }
    }
}
