//! The branched grid's visible surface: marching cubes over the voxels (cube corners at
//! voxel centres), each vertex embedded in the element that owns its inside voxel by
//! trilinear coordinates, smoothed in rest space, with stable ids.
//!
//! A vertex sits on a cube edge between an inside and an outside voxel — the face
//! between them — and is named by that edge, so a vertex keeps its id for as long as
//! the edge carries the surface. After voxels are removed only the 8 cubes around
//! each of them are redone ([`GridSurface::update`]); the change comes back as the
//! triangles and vertices removed and added (ids are never reused).
//!
//! Smoothing: Taubin's λ|μ filter (λ = 0.5, μ = −0.53) on rest positions, then the
//! trilinear coordinates are taken at the smoothed position in the same cell (the
//! element stays the one of the vertex's voxel). After a cut the smoothing is redone
//! exactly for the vertices within reach of the change, so the surface does not depend
//! on the order of the cuts that made it.

use std::collections::{BTreeSet, HashMap};

use super::marching::{EDGES, table};
use super::topology::{NONE, Topology};
use crate::math::Vec3;

const LAMBDA: f64 = 0.5;
const MU: f64 = -0.53;

/// What an update changed (ids); the model turns it into a topology delta.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SurfaceChange {
    pub removed_triangles: Vec<u32>,
    pub removed_vertices: Vec<u32>,
    pub added_vertices: Vec<u32>,
    pub added_triangles: Vec<u32>,
    /// Existing vertices whose smoothed rest position moved.
    pub moved_vertices: usize,
}

#[derive(Debug, Clone)]
pub struct GridSurface {
    dims: [usize; 3],
    iterations: u32,
    // Vertices (by id).
    pub edge: Vec<u64>,
    /// The inside voxel the vertex belongs to.
    pub voxel: Vec<u32>,
    /// Rest position before smoothing (a voxel face centre), m.
    pub raw: Vec<Vec3>,
    /// Rest position after smoothing, m.
    pub rest: Vec<Vec3>,
    /// Trilinear weights of `rest` in the voxel's cell.
    pub weights: Vec<[f64; 8]>,
    pub vertex_alive: Vec<bool>,
    vertex_triangles: Vec<Vec<u32>>,
    edge_vertex: HashMap<u64, u32>,
    // Triangles (by id).
    pub triangles: Vec<[u32; 3]>,
    pub triangle_alive: Vec<bool>,
    cube_triangles: HashMap<u64, Vec<u32>>,
    /// Per coarse cell: the live vertices embedded in it (for contact queries).
    pub cell_vertices: Vec<Vec<u32>>,
    pub alive_vertices: usize,
    pub alive_triangles: usize,
    /// The filter's intermediate passes (all but the last, which is `rest`), per vertex.
    passes: Vec<Vec<Vec3>>,
    /// Per vertex: the epoch of the last smoothing update that reached it.
    mark: Vec<u32>,
    epoch: u32,
}

impl GridSurface {
    /// Extracts the surface of the topology's voxels.
    pub fn build(topo: &Topology, smoothing_iterations: u32) -> Self {
        let dims = topo.layout.voxels;
        let mut s = GridSurface {
            dims,
            iterations: smoothing_iterations,
            edge: Vec::new(),
            voxel: Vec::new(),
            raw: Vec::new(),
            rest: Vec::new(),
            weights: Vec::new(),
            vertex_alive: Vec::new(),
            vertex_triangles: Vec::new(),
            edge_vertex: HashMap::new(),
            triangles: Vec::new(),
            triangle_alive: Vec::new(),
            cube_triangles: HashMap::new(),
            cell_vertices: vec![Vec::new(); topo.layout.cell_count()],
            alive_vertices: 0,
            alive_triangles: 0,
            passes: vec![Vec::new(); (2 * smoothing_iterations as usize).saturating_sub(1)],
            mark: Vec::new(),
            epoch: 0,
        };
        let mut added = Vec::new();
        // Only cubes with a corner in a material voxel can carry surface.
        let mut cubes = BTreeSet::new();
        for (v, &m) in topo.material.iter().enumerate() {
            if m != 0 {
                let g = topo.layout.voxel_coords(v);
                for c in 0..8 {
                    cubes.insert(s.cube_key([g[0] + (c & 1), g[1] + ((c >> 1) & 1), g[2] + ((c >> 2) & 1)]));
                }
            }
        }
        for key in cubes {
            s.make_cube(topo, key, &mut added);
        }
        let all: Vec<u32> = (0..s.raw.len() as u32).collect();
        s.smooth_from(topo, &all, 0);
        s
    }

    pub fn vertex_count(&self) -> usize {
        self.raw.len()
    }

    /// Cube (ci, cj, ck): corners at voxels (ci − 1 + bit, …); 0 ≤ ci ≤ nx.
    fn cube_key(&self, c: [usize; 3]) -> u64 {
        (c[0] + (self.dims[0] + 1) * (c[1] + (self.dims[1] + 1) * c[2])) as u64
    }

    fn cube_coords(&self, key: u64) -> [usize; 3] {
        let key = key as usize;
        let (nx, ny) = (self.dims[0] + 1, self.dims[1] + 1);
        [key % nx, (key / nx) % ny, key / (nx * ny)]
    }

    /// Edge from padded point P (voxel + 1) along `axis`.
    fn edge_key(&self, p: [usize; 3], axis: usize) -> u64 {
        3 * (p[0] + (self.dims[0] + 2) * (p[1] + (self.dims[1] + 2) * p[2])) as u64 + axis as u64
    }

    fn inside(topo: &Topology, padded: [usize; 3]) -> Option<usize> {
        let d = topo.layout.voxels;
        if (0..3).any(|a| padded[a] == 0 || padded[a] > d[a]) {
            return None;
        }
        let v = topo.layout.voxel_index([padded[0] - 1, padded[1] - 1, padded[2] - 1]);
        (topo.material[v] != 0).then_some(v)
    }

    /// Triangulates one cube, creating the vertices it needs.
    fn make_cube(&mut self, topo: &Topology, key: u64, added_vertices: &mut Vec<u32>) -> Vec<u32> {
        let c = self.cube_coords(key);
        let corner = |n: usize| [c[0] + (n & 1), c[1] + ((n >> 1) & 1), c[2] + ((n >> 2) & 1)];
        let mut config = 0usize;
        let mut voxels = [None; 8];
        for n in 0..8 {
            voxels[n] = Self::inside(topo, corner(n));
            if voxels[n].is_some() {
                config |= 1 << n;
            }
        }
        let cases = &table()[config];
        if cases.is_empty() {
            return Vec::new();
        }
        let mut edge_vertex = [NONE; 12];
        let mut made = Vec::with_capacity(cases.len());
        for tri in cases {
            let mut ids = [0u32; 3];
            for (k, &e) in tri.iter().enumerate() {
                let e = e as usize;
                if edge_vertex[e] == NONE {
                    let (a, b, axis) = EDGES[e];
                    let edge = self.edge_key(corner(a), axis);
                    let inside_voxel = voxels[a].or(voxels[b]).expect("a crossing edge has an inside end");
                    let outward = if voxels[a].is_some() { 1.0 } else { -1.0 };
                    edge_vertex[e] = match self.edge_vertex.get(&edge) {
                        Some(&id) => id,
                        None => {
                            let id = self.add_vertex(topo, edge, inside_voxel, axis, outward);
                            added_vertices.push(id);
                            id
                        }
                    };
                }
                ids[k] = edge_vertex[e];
            }
            let id = self.triangles.len() as u32;
            self.triangles.push(ids);
            self.triangle_alive.push(true);
            self.alive_triangles += 1;
            for &v in &ids {
                self.vertex_triangles[v as usize].push(id);
            }
            made.push(id);
        }
        self.cube_triangles.insert(key, made.clone());
        made
    }

    fn add_vertex(&mut self, topo: &Topology, edge: u64, voxel: usize, axis: usize, outward: f64) -> u32 {
        let mut p = topo.voxel_centre(voxel);
        p[axis] += outward * 0.5 * topo.layout.spacing_m[axis];
        let id = self.raw.len() as u32;
        self.edge.push(edge);
        self.voxel.push(voxel as u32);
        self.raw.push(p);
        self.rest.push(p);
        for pass in &mut self.passes {
            pass.push(p);
        }
        self.mark.push(0);
        self.weights.push(cell_weights(topo, voxel, p));
        self.vertex_alive.push(true);
        self.vertex_triangles.push(Vec::new());
        self.edge_vertex.insert(edge, id);
        let cell = topo.layout.cell_index(topo.layout.cell_of_voxel(topo.layout.voxel_coords(voxel)));
        self.cell_vertices[cell].push(id);
        self.alive_vertices += 1;
        id
    }

    /// Redoes the cubes around removed voxels (their material must already be gone).
    pub fn update(&mut self, topo: &Topology, removed_voxels: &[usize]) -> SurfaceChange {
        let mut change = SurfaceChange::default();
        let first_new = self.raw.len() as u32;
        let mut cubes = BTreeSet::new();
        for &v in removed_voxels {
            let g = topo.layout.voxel_coords(v);
            for c in 0..8 {
                cubes.insert(self.cube_key([g[0] + (c & 1), g[1] + ((c >> 1) & 1), g[2] + ((c >> 2) & 1)]));
            }
        }
        let mut touched = BTreeSet::new();
        for &key in &cubes {
            for t in self.cube_triangles.remove(&key).unwrap_or_default() {
                self.triangle_alive[t as usize] = false;
                self.alive_triangles -= 1;
                change.removed_triangles.push(t);
                for v in self.triangles[t as usize] {
                    self.vertex_triangles[v as usize].retain(|&x| x != t);
                    touched.insert(v);
                }
            }
        }
        for &key in &cubes {
            let made = self.make_cube(topo, key, &mut change.added_vertices);
            for &t in &made {
                touched.extend(self.triangles[t as usize]);
            }
            change.added_triangles.extend(made);
        }
        for &v in &touched {
            if self.vertex_alive[v as usize] && self.vertex_triangles[v as usize].is_empty() {
                self.vertex_alive[v as usize] = false;
                self.alive_vertices -= 1;
                self.edge_vertex.remove(&self.edge[v as usize]);
                let voxel = self.voxel[v as usize] as usize;
                let cell = topo.layout.cell_index(topo.layout.cell_of_voxel(topo.layout.voxel_coords(voxel)));
                self.cell_vertices[cell].retain(|&x| x != v);
                change.removed_vertices.push(v);
            }
        }
        change.removed_vertices.sort_unstable();
        change.removed_triangles.sort_unstable();
        // Re-smooth where the change reaches.
        let seeds: Vec<u32> = touched.into_iter().filter(|&v| self.vertex_alive[v as usize]).collect();
        change.moved_vertices = self.smooth_from(topo, &seeds, first_new);
        change
    }

    fn neighbours(&self, v: u32, out: &mut Vec<u32>) {
        out.clear();
        for &t in &self.vertex_triangles[v as usize] {
            for w in self.triangles[t as usize] {
                if w != v && !out.contains(&w) {
                    out.push(w);
                }
            }
        }
    }

    /// Redoes the smoothing where `seeds` (vertices whose position or neighbours
    /// changed) reach, pass by pass: pass p can only change the vertices within p rings
    /// of the seeds, and every other vertex keeps its stored value of that pass, so the
    /// result equals smoothing the whole surface again at a cost that follows the size
    /// of the change. Returns how many vertices with an id below `first_new` moved.
    fn smooth_from(&mut self, topo: &Topology, seeds: &[u32], first_new: u32) -> usize {
        let passes = 2 * self.iterations as usize;
        self.epoch = self.epoch.wrapping_add(1).max(1);
        let mut set: Vec<u32> = Vec::with_capacity(seeds.len() * 8);
        for &v in seeds {
            if self.mark[v as usize] != self.epoch {
                self.mark[v as usize] = self.epoch;
                set.push(v);
            }
        }
        let mut before: Vec<Vec3> = Vec::new();
        // Neighbour lists of the set's members, computed once each: member i's
        // neighbours are adjacency[spans[i].0..spans[i].1].
        let mut adjacency: Vec<u32> = Vec::with_capacity(set.len() * 8);
        let mut spans: Vec<(usize, usize)> = Vec::with_capacity(set.len());
        let mut scratch = Vec::new();
        let mut values: Vec<Vec3> = Vec::with_capacity(set.len());
        for pass in 0..passes {
            // Grow the set by one ring: the neighbours of the members not yet expanded.
            let frontier = spans.len()..set.len();
            for i in frontier {
                self.neighbours(set[i], &mut scratch);
                spans.push((adjacency.len(), adjacency.len() + scratch.len()));
                adjacency.extend_from_slice(&scratch);
                for &w in &scratch {
                    if self.mark[w as usize] != self.epoch {
                        self.mark[w as usize] = self.epoch;
                        set.push(w);
                    }
                }
            }
            let factor = if pass % 2 == 0 { LAMBDA } else { MU };
            let input = if pass == 0 { &self.raw } else { &self.passes[pass - 1] };
            values.clear();
            for (i, &v) in set.iter().enumerate() {
                let neighbours: &[u32] = match spans.get(i) {
                    Some(&(a, b)) => &adjacency[a..b],
                    None => {
                        self.neighbours(v, &mut scratch);
                        &scratch
                    }
                };
                let here = input[v as usize];
                values.push(if neighbours.is_empty() {
                    here
                } else {
                    let mean = neighbours.iter().map(|&w| input[w as usize]).sum::<Vec3>() / neighbours.len() as f64;
                    here + (mean - here) * factor
                });
            }
            let output = if pass + 1 == passes { &mut self.rest } else { &mut self.passes[pass] };
            if pass + 1 == passes {
                before = set.iter().map(|&v| output[v as usize]).collect();
            }
            for (&v, &value) in set.iter().zip(&values) {
                output[v as usize] = value;
            }
        }
        if passes == 0 {
            before = set.iter().map(|&v| self.rest[v as usize]).collect();
            for &v in &set {
                self.rest[v as usize] = self.raw[v as usize];
            }
        }
        let mut moved = 0;
        for (&v, old) in set.iter().zip(before) {
            let v = v as usize;
            if self.vertex_alive[v] {
                self.weights[v] = cell_weights(topo, self.voxel[v] as usize, self.rest[v]);
                moved += usize::from(self.rest[v] != old && (v as u32) < first_new);
            }
        }
        moved
    }

    /// Whether vertex `v` moves with an element: its voxel's element is live (a vertex
    /// whose voxel was cut away stands still at its rest position and touches nothing).
    pub fn in_element(&self, topo: &Topology, v: usize) -> bool {
        topo.voxel_element[self.voxel[v] as usize] != NONE
    }

    /// The vertex's position from its element's nodes (grid frame), m.
    pub fn position(&self, topo: &Topology, v: usize) -> Vec3 {
        let e = topo.voxel_element[self.voxel[v] as usize];
        if e == NONE {
            return self.rest[v];
        }
        let nodes = &topo.elements.nodes[e as usize];
        let w = &self.weights[v];
        let mut p = Vec3::zeros();
        for k in 0..8 {
            p += topo.nodes.x[nodes[k] as usize] * w[k];
        }
        p
    }

    /// The triangles vertex `v` is a corner of (live ones only: a removed triangle is
    /// taken off its vertices' lists).
    pub fn triangles_of(&self, v: usize) -> &[u32] {
        &self.vertex_triangles[v]
    }

    /// Live triangles (id, vertices).
    pub fn live_triangles(&self) -> impl Iterator<Item = (u32, [u32; 3])> + '_ {
        self.triangles.iter().enumerate().filter(|(t, _)| self.triangle_alive[*t]).map(|(t, tri)| (t as u32, *tri))
    }
}

/// Trilinear weights of a rest-space point in the cell of `voxel`.
pub fn cell_weights(topo: &Topology, voxel: usize, rest: Vec3) -> [f64; 8] {
    let cell = topo.layout.cell_index(topo.layout.cell_of_voxel(topo.layout.voxel_coords(voxel)));
    super::hex::trilinear_weights(topo.cell_coordinates(cell, rest))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::condense::VoxelMatrices;
    use crate::grid::topology::Layout;
    use crate::volume::LabelVolume;

    fn topo(volume: &LabelVolume, levels: u32) -> Topology {
        let layout = Layout::new(volume.dims, levels, volume.spacing_m);
        let material = volume.labels.iter().map(|&l| u16::from(l != 0)).collect();
        Topology::build(layout, material, VoxelMatrices::new(volume.spacing_m, &[(1e4, 0.4, 1000.0)], crate::grid::condense::Volumetric::MeanDilatation))
    }

    /// Each directed edge once and its reverse once: closed and consistently oriented.
    fn assert_closed(s: &GridSurface) {
        let mut directed: Vec<(u32, u32)> = s.live_triangles().flat_map(|(_, t)| (0..3).map(move |k| (t[k], t[(k + 1) % 3]))).collect();
        directed.sort_unstable();
        for w in directed.windows(2) {
            assert_ne!(w[0], w[1], "a directed edge is used twice");
        }
        for &(a, b) in &directed {
            assert!(directed.binary_search(&(b, a)).is_ok(), "edge {a}→{b} has no twin: the surface has a hole");
        }
    }

    fn enclosed_volume(s: &GridSurface, t: &Topology) -> f64 {
        s.live_triangles()
            .map(|(_, tri)| {
                let [a, b, c] = tri.map(|v| s.position(t, v as usize));
                a.dot(&b.cross(&c)) / 6.0
            })
            .sum()
    }

    /// A random-ish blob with holes and diagonal contacts (the ambiguous cases).
    fn blob() -> LabelVolume {
        let mut v = LabelVolume::new([9, 8, 7], [0.001; 3], Vec3::zeros());
        for k in 0..7 {
            for j in 0..8 {
                for i in 0..9 {
                    let h = (i * 73 + j * 151 + k * 199 + i * j * k) % 7;
                    if h < 4 {
                        v.set(i, j, k, 1);
                    }
                }
            }
        }
        v
    }

    #[test]
    fn the_surface_is_closed_and_oriented_outwards() {
        let v = blob();
        let t = topo(&v, 1);
        let s = GridSurface::build(&t, 0);
        assert_closed(&s);
        assert!(enclosed_volume(&s, &t) > 0.0, "normals point out");
        // A single voxel: an octahedron through its 6 face centres, 1/6 of its volume.
        let mut one = LabelVolume::new([1, 1, 1], [0.001; 3], Vec3::zeros());
        one.labels[0] = 1;
        let t1 = topo(&one, 0);
        let s1 = GridSurface::build(&t1, 0);
        assert_eq!((s1.alive_vertices, s1.alive_triangles), (6, 8));
        assert!((enclosed_volume(&s1, &t1) - 1e-9 / 6.0).abs() < 1e-18);
    }

    #[test]
    fn updates_equal_a_fresh_extraction_and_keep_ids() {
        let mut v = blob();
        let mut t = topo(&v, 1);
        let mut s = GridSurface::build(&t, 2);
        let kept_before: Vec<(u64, u32)> = s.edge.iter().enumerate().map(|(id, &e)| (e, id as u32)).collect();
        let removed: Vec<usize> = (0..v.len()).filter(|&i| v.labels[i] != 0 && i % 5 == 0).take(12).collect();
        t.remove_voxels(&removed);
        for &i in &removed {
            v.labels[i] = 0;
        }
        let change = s.update(&t, &removed);
        assert!(!change.added_triangles.is_empty() && !change.removed_triangles.is_empty());
        assert_closed(&s);
        // The same surface as extracted from scratch: same edges, same smoothed positions.
        let fresh = GridSurface::build(&topo(&v, 1), 2);
        let live = |s: &GridSurface| -> Vec<(u64, [u64; 3])> {
            let mut out: Vec<(u64, [u64; 3])> = (0..s.raw.len()).filter(|&i| s.vertex_alive[i]).map(|i| (s.edge[i], s.rest[i].map(|c| (c * 1e12).round() as i64 as u64).into())).collect();
            out.sort_unstable();
            out
        };
        let (a, b) = (live(&s), live(&fresh));
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(x.0, y.0);
            for k in 0..3 {
                assert!((x.1[k] as i64 - y.1[k] as i64).abs() <= 1, "smoothed positions differ at edge {}", x.0);
            }
        }
        // Vertices that survived kept their ids.
        for (edge, id) in kept_before {
            if let Some(&now) = s.edge_vertex.get(&edge) {
                assert_eq!(now, id);
            }
        }
    }
}
