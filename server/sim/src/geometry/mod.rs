//! Surface geometry sources: a procedural skin patch and OBJ meshes, and the checks a
//! mesh must pass before it is simulated (non-empty, valid indices, no degenerate
//! triangle, edge- and vertex-manifold, consistently oriented).

pub mod obj;
pub mod vtk;
pub mod patch;

use std::collections::HashMap;

use crate::math::{Vec3, triangle_area, triangle_min_angle_deg};

/// An indexed triangle mesh, positions in m.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct TriMesh {
    pub positions: Vec<Vec3>,
    pub triangles: Vec<[u32; 3]>,
}

impl TriMesh {
    /// Checks that the mesh can be simulated and cut; the error says what is wrong and where.
    pub fn check(&self) -> Result<(), String> {
        if self.positions.is_empty() || self.triangles.is_empty() {
            return Err(format!(
                "the mesh is empty ({} vertices, {} triangles); at least one triangle is needed",
                self.positions.len(),
                self.triangles.len()
            ));
        }
        if let Some(i) = self.positions.iter().position(|p| !p.iter().all(|c| c.is_finite())) {
            return Err(format!("vertex {i} has a non-finite coordinate"));
        }
        let n = self.positions.len() as u32;
        for (t, tri) in self.triangles.iter().enumerate() {
            if let Some(&bad) = tri.iter().find(|&&v| v >= n) {
                return Err(format!("triangle {t} uses vertex {bad}, but the mesh has {n} vertices"));
            }
            if tri[0] == tri[1] || tri[1] == tri[2] || tri[0] == tri[2] {
                return Err(format!("triangle {t} repeats a vertex: {tri:?}"));
            }
            let [a, b, c] = tri.map(|v| self.positions[v as usize]);
            let scale = (b - a).norm().max((c - a).norm()).max(1e-300);
            if triangle_area(&a, &b, &c) <= 1e-12 * scale * scale {
                return Err(format!("triangle {t} {tri:?} has zero area"));
            }
        }
        // Sorted lists (not hash maps) so that the first error reported is deterministic.
        let mut directed: Vec<(u32, u32, usize)> = self
            .triangles
            .iter()
            .enumerate()
            .flat_map(|(t, tri)| (0..3).map(move |k| (tri[k], tri[(k + 1) % 3], t)))
            .collect();
        let mut undirected: Vec<(u32, u32)> = directed.iter().map(|&(a, b, _)| (a.min(b), a.max(b))).collect();
        undirected.sort_unstable();
        for run in undirected.chunk_by(|x, y| x == y) {
            if run.len() > 2 {
                let (a, b) = run[0];
                return Err(format!("edge {a}–{b} is shared by {} triangles (non-manifold)", run.len()));
            }
        }
        directed.sort_unstable();
        for pair in directed.windows(2) {
            if (pair[0].0, pair[0].1) == (pair[1].0, pair[1].1) {
                return Err(format!(
                    "triangles {} and {} traverse edge {}→{} in the same direction: orientation is inconsistent",
                    pair[0].2, pair[1].2, pair[0].0, pair[0].1
                ));
            }
        }
        self.check_vertex_manifold()
    }

    /// Every vertex's incident triangles must form one fan (a disc or a half-disc).
    fn check_vertex_manifold(&self) -> Result<(), String> {
        let mut incident: Vec<Vec<u32>> = vec![Vec::new(); self.positions.len()];
        for (t, tri) in self.triangles.iter().enumerate() {
            for &v in tri {
                incident[v as usize].push(t as u32);
            }
        }
        for (v, tris) in incident.iter().enumerate() {
            if tris.is_empty() {
                continue;
            }
            if fan_components(v as u32, tris, &self.triangles) != 1 {
                return Err(format!("vertex {v} joins separate fans of triangles (non-manifold vertex)"));
            }
        }
        Ok(())
    }

    /// Removes vertices no triangle uses; returns the old→new index map (u32::MAX: dropped).
    pub fn drop_unreferenced_vertices(&mut self) -> Vec<u32> {
        let mut used = vec![false; self.positions.len()];
        for tri in &self.triangles {
            for &v in tri {
                if let Some(u) = used.get_mut(v as usize) {
                    *u = true;
                }
            }
        }
        let mut map = vec![u32::MAX; self.positions.len()];
        let mut next = 0u32;
        let mut kept = Vec::with_capacity(self.positions.len());
        for (i, p) in self.positions.iter().enumerate() {
            if used[i] {
                map[i] = next;
                next += 1;
                kept.push(*p);
            }
        }
        self.positions = kept;
        for tri in &mut self.triangles {
            for v in tri.iter_mut() {
                *v = map[*v as usize];
            }
        }
        map
    }

    /// Unique undirected edges (a < b), sorted.
    pub fn edges(&self) -> Vec<(u32, u32)> {
        let mut edges: Vec<(u32, u32)> = self
            .triangles
            .iter()
            .flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))))
            .collect();
        edges.sort_unstable();
        edges.dedup();
        edges
    }

    /// True for vertices on an edge used by a single triangle.
    pub fn boundary_vertices(&self) -> Vec<bool> {
        let mut count: HashMap<(u32, u32), u32> = HashMap::new();
        for t in &self.triangles {
            for k in 0..3 {
                let (a, b) = (t[k], t[(k + 1) % 3]);
                *count.entry((a.min(b), a.max(b))).or_default() += 1;
            }
        }
        let mut on_boundary = vec![false; self.positions.len()];
        for ((a, b), c) in count {
            if c == 1 {
                on_boundary[a as usize] = true;
                on_boundary[b as usize] = true;
            }
        }
        on_boundary
    }

    pub fn mean_edge_length(&self) -> f64 {
        let edges = self.edges();
        if edges.is_empty() {
            return 0.0;
        }
        edges.iter().map(|&(a, b)| (self.positions[a as usize] - self.positions[b as usize]).norm()).sum::<f64>()
            / edges.len() as f64
    }

    /// Smallest interior angle over all triangles, degrees.
    pub fn min_angle_deg(&self) -> f64 {
        self.triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(|v| self.positions[v as usize]);
                triangle_min_angle_deg(&a, &b, &c)
            })
            .fold(f64::INFINITY, f64::min)
    }

    pub fn scale_and_offset(&mut self, scale: f64, offset: Vec3) {
        for p in &mut self.positions {
            *p = *p * scale + offset;
        }
    }
}

/// Number of edge-connected fans among the triangles `tris` around vertex `v`.
pub(crate) fn fan_components(v: u32, tris: &[u32], triangles: &[[u32; 3]]) -> usize {
    // Union-find over the (few) incident triangles; two are joined when they share an
    // edge that contains v.
    let mut sets = crate::union_find::UnionFind::new(tris.len());
    for i in 0..tris.len() {
        for j in (i + 1)..tris.len() {
            let (ti, tj) = (triangles[tris[i] as usize], triangles[tris[j] as usize]);
            let shares_edge_with_v = ti.iter().any(|&w| w != v && tj.contains(&w));
            if shares_edge_with_v {
                sets.union(i, j);
            }
        }
    }
    (0..tris.len()).filter(|&i| sets.find(i) == i).count()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn square() -> TriMesh {
        TriMesh {
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(0.0, 1.0, 0.0),
            ],
            triangles: vec![[0, 1, 2], [0, 2, 3]],
        }
    }

    #[test]
    fn square_is_valid_and_all_boundary() {
        let m = square();
        m.check().unwrap();
        assert_eq!(m.boundary_vertices(), vec![true; 4]);
        assert_eq!(m.edges().len(), 5);
    }

    #[test]
    fn flipped_triangle_is_refused() {
        let mut m = square();
        m.triangles[1] = [0, 3, 2];
        let err = m.check().unwrap_err();
        assert!(err.contains("orientation is inconsistent"), "{err}");
    }

    #[test]
    fn empty_and_degenerate_meshes_are_refused() {
        assert!(TriMesh::default().check().unwrap_err().contains("empty"));
        let mut m = square();
        m.positions[2] = Vec3::new(0.5, 0.5, 0.0);
        m.positions[3] = Vec3::new(1.0, 1.0, 0.0);
        m.triangles = vec![[0, 1, 3], [0, 2, 3]];
        assert!(m.check().unwrap_err().contains("zero area"));
    }

    #[test]
    fn bow_tie_vertex_is_refused() {
        let m = TriMesh {
            positions: vec![
                Vec3::new(0.0, 0.0, 0.0),
                Vec3::new(1.0, 0.0, 0.0),
                Vec3::new(1.0, 1.0, 0.0),
                Vec3::new(-1.0, 0.0, 0.0),
                Vec3::new(-1.0, -1.0, 0.0),
            ],
            triangles: vec![[0, 1, 2], [0, 3, 4]],
        };
        assert!(m.check().unwrap_err().contains("non-manifold vertex"));
    }
}
