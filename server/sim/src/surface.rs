//! The visible surface of a tissue, with stable ids, and its topology deltas.
//!
//! Vertex and triangle ids are handles that never change meaning: an id is never
//! reused for another vertex or triangle, and no cut reshuffles them. A snapshot lists
//! the surface at one topology version; each cut produces a [`TopologyDelta`] that takes
//! version v−1 to v by naming what was removed and what was added. A
//! [`SurfaceReplica`] (what a viewer or a bot holds) applies them, and its
//! [`SurfaceReplica::surface_hash`] equals the server's when both hold the same surface.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};

use crate::hash::StateHasher;

pub type VertexId = u32;
pub type TriangleId = u32;
/// Index into the scene's materials (0 for single-material models).
pub type MaterialId = u16;

#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct SurfaceVertex {
    pub id: VertexId,
    /// Position in m (f32: what viewers draw and what the wire carries).
    pub position_m: [f32; 3],
    pub material: MaterialId,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct SurfaceTriangle {
    pub id: TriangleId,
    /// Counter-clockwise seen from outside the tissue.
    pub vertices: [VertexId; 3],
}

/// The whole surface at one topology version, sorted by id.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct SurfaceSnapshot {
    pub version: u64,
    pub vertices: Vec<SurfaceVertex>,
    pub triangles: Vec<SurfaceTriangle>,
}

/// What one cut changed: applying it to version `version − 1` gives `version`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct TopologyDelta {
    pub version: u64,
    pub removed_triangles: Vec<TriangleId>,
    pub removed_vertices: Vec<VertexId>,
    pub added_vertices: Vec<SurfaceVertex>,
    pub added_triangles: Vec<SurfaceTriangle>,
}

impl TopologyDelta {
    pub fn is_empty(&self) -> bool {
        self.removed_triangles.is_empty()
            && self.removed_vertices.is_empty()
            && self.added_vertices.is_empty()
            && self.added_triangles.is_empty()
    }
}

/// Why a delta could not be applied.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplicaError {
    #[error("topology version gap: replica holds version {have}, delta goes to {got} (expected {expected})")]
    VersionGap { have: u64, got: u64, expected: u64 },
    #[error("delta {version} removes unknown {what} {id}")]
    UnknownId { version: u64, what: &'static str, id: u32 },
    #[error("delta {version} adds {what} {id} which already exists")]
    DuplicateId { version: u64, what: &'static str, id: u32 },
    #[error("delta {version}: triangle {triangle} uses vertex {vertex}, which does not exist")]
    DanglingVertex { version: u64, triangle: TriangleId, vertex: VertexId },
}

/// A copy of a surface built from a snapshot and kept current with deltas.
#[derive(Debug, Clone, Default)]
pub struct SurfaceReplica {
    version: u64,
    vertices: BTreeMap<VertexId, ([f32; 3], MaterialId)>,
    triangles: BTreeMap<TriangleId, [VertexId; 3]>,
}

impl SurfaceReplica {
    pub fn from_snapshot(snapshot: &SurfaceSnapshot) -> Self {
        Self {
            version: snapshot.version,
            vertices: snapshot.vertices.iter().map(|v| (v.id, (v.position_m, v.material))).collect(),
            triangles: snapshot.triangles.iter().map(|t| (t.id, t.vertices)).collect(),
        }
    }

    pub fn version(&self) -> u64 {
        self.version
    }

    pub fn vertex_count(&self) -> usize {
        self.vertices.len()
    }

    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// Applies one delta; on error the replica is unchanged.
    pub fn apply(&mut self, delta: &TopologyDelta) -> Result<(), ReplicaError> {
        let expected = self.version + 1;
        if delta.version != expected {
            return Err(ReplicaError::VersionGap { have: self.version, got: delta.version, expected });
        }
        let version = delta.version;
        for &id in &delta.removed_triangles {
            if !self.triangles.contains_key(&id) {
                return Err(ReplicaError::UnknownId { version, what: "triangle", id });
            }
        }
        for &id in &delta.removed_vertices {
            if !self.vertices.contains_key(&id) {
                return Err(ReplicaError::UnknownId { version, what: "vertex", id });
            }
        }
        for v in &delta.added_vertices {
            if self.vertices.contains_key(&v.id) {
                return Err(ReplicaError::DuplicateId { version, what: "vertex", id: v.id });
            }
        }
        for t in &delta.added_triangles {
            if self.triangles.contains_key(&t.id) {
                return Err(ReplicaError::DuplicateId { version, what: "triangle", id: t.id });
            }
            for &vertex in &t.vertices {
                let removed = delta.removed_vertices.contains(&vertex);
                let exists = self.vertices.contains_key(&vertex) && !removed;
                let added = delta.added_vertices.iter().any(|v| v.id == vertex);
                if !exists && !added {
                    return Err(ReplicaError::DanglingVertex { version, triangle: t.id, vertex });
                }
            }
        }
        for id in &delta.removed_triangles {
            self.triangles.remove(id);
        }
        for id in &delta.removed_vertices {
            self.vertices.remove(id);
        }
        for v in &delta.added_vertices {
            self.vertices.insert(v.id, (v.position_m, v.material));
        }
        for t in &delta.added_triangles {
            self.triangles.insert(t.id, t.vertices);
        }
        self.version = version;
        Ok(())
    }

    /// Moves a vertex; unknown ids are ignored (a position frame may race a delta).
    pub fn set_position(&mut self, id: VertexId, position_m: [f32; 3]) -> bool {
        match self.vertices.get_mut(&id) {
            Some(v) => {
                v.0 = position_m;
                true
            }
            None => false,
        }
    }

    pub fn to_snapshot(&self) -> SurfaceSnapshot {
        SurfaceSnapshot {
            version: self.version,
            vertices: self
                .vertices
                .iter()
                .map(|(&id, &(position_m, material))| SurfaceVertex { id, position_m, material })
                .collect(),
            triangles: self.triangles.iter().map(|(&id, &vertices)| SurfaceTriangle { id, vertices }).collect(),
        }
    }

    /// Hash of topology and positions; equal to [`SurfaceSnapshot::surface_hash`] of the same surface.
    pub fn surface_hash(&self) -> u64 {
        surface_hash(
            self.version,
            self.vertices.iter().map(|(&id, &(p, m))| SurfaceVertex { id, position_m: p, material: m }),
            self.triangles.iter().map(|(&id, &vertices)| SurfaceTriangle { id, vertices }),
        )
    }

    /// Hash of topology only (ids and connectivity).
    pub fn topology_hash(&self) -> u64 {
        topology_hash(self.version, self.vertices.keys().copied(), self.triangles.iter().map(|(&id, &v)| (id, v)))
    }
}

impl SurfaceSnapshot {
    /// Hash of topology and positions; `vertices` and `triangles` must be sorted by id
    /// (as every snapshot the models produce is).
    pub fn surface_hash(&self) -> u64 {
        surface_hash(self.version, self.vertices.iter().copied(), self.triangles.iter().copied())
    }

    pub fn topology_hash(&self) -> u64 {
        topology_hash(
            self.version,
            self.vertices.iter().map(|v| v.id),
            self.triangles.iter().map(|t| (t.id, t.vertices)),
        )
    }
}

fn surface_hash(
    version: u64,
    vertices: impl Iterator<Item = SurfaceVertex>,
    triangles: impl Iterator<Item = SurfaceTriangle>,
) -> u64 {
    let mut h = StateHasher::new();
    h.write_u64(version);
    for v in vertices {
        h.write_u32(v.id);
        for c in v.position_m {
            h.write_f32(c);
        }
        h.write_u32(u32::from(v.material));
    }
    h.write_u8(0xff);
    for t in triangles {
        h.write_u32(t.id);
        for id in t.vertices {
            h.write_u32(id);
        }
    }
    h.finish()
}

fn topology_hash(
    version: u64,
    vertex_ids: impl Iterator<Item = VertexId>,
    triangles: impl Iterator<Item = (TriangleId, [VertexId; 3])>,
) -> u64 {
    let mut h = StateHasher::new();
    h.write_u64(version);
    for id in vertex_ids {
        h.write_u32(id);
    }
    h.write_u8(0xff);
    for (id, verts) in triangles {
        h.write_u32(id);
        for v in verts {
            h.write_u32(v);
        }
    }
    h.finish()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn vertex(id: u32) -> SurfaceVertex {
        SurfaceVertex { id, position_m: [id as f32, 0.0, 0.0], material: 0 }
    }

    #[test]
    fn replica_applies_delta_and_matches_hash() {
        let snapshot = SurfaceSnapshot {
            version: 0,
            vertices: (0..4).map(vertex).collect(),
            triangles: vec![
                SurfaceTriangle { id: 0, vertices: [0, 1, 2] },
                SurfaceTriangle { id: 1, vertices: [1, 3, 2] },
            ],
        };
        let mut replica = SurfaceReplica::from_snapshot(&snapshot);
        assert_eq!(replica.surface_hash(), snapshot.surface_hash());
        let delta = TopologyDelta {
            version: 1,
            removed_triangles: vec![1],
            removed_vertices: vec![3],
            added_vertices: vec![vertex(4)],
            added_triangles: vec![SurfaceTriangle { id: 2, vertices: [1, 4, 2] }],
        };
        replica.apply(&delta).unwrap();
        let expected = SurfaceSnapshot {
            version: 1,
            vertices: [0, 1, 2, 4].into_iter().map(vertex).collect(),
            triangles: vec![
                SurfaceTriangle { id: 0, vertices: [0, 1, 2] },
                SurfaceTriangle { id: 2, vertices: [1, 4, 2] },
            ],
        };
        assert_eq!(replica.to_snapshot(), expected);
        assert_eq!(replica.surface_hash(), expected.surface_hash());
    }

    #[test]
    fn replica_refuses_gaps_and_dangling_vertices() {
        let mut replica = SurfaceReplica::from_snapshot(&SurfaceSnapshot::default());
        let gap = TopologyDelta { version: 2, ..Default::default() };
        assert!(matches!(replica.apply(&gap), Err(ReplicaError::VersionGap { .. })));
        let dangling = TopologyDelta {
            version: 1,
            added_triangles: vec![SurfaceTriangle { id: 0, vertices: [0, 1, 2] }],
            ..Default::default()
        };
        assert!(matches!(replica.apply(&dangling), Err(ReplicaError::DanglingVertex { .. })));
        assert_eq!(replica.version(), 0);
    }
}
