//! The state of the mass-spring model: nodes, springs and the triangle mesh.
//!
//! Node ids are surface vertex ids and triangle ids are surface triangle ids: both are
//! slots that are only ever appended, never reused, so they stay valid handles across
//! cuts. A removed node keeps its slot with `alive = false` and no mass.

use std::collections::HashMap;
use std::hash::{BuildHasherDefault, Hasher};

use crate::math::Vec3;

/// Per-node arrays (structure of arrays, indexed by node id).
#[derive(Debug, Clone, Default)]
pub(crate) struct Nodes {
    /// Position, m.
    pub x: Vec<Vec3>,
    /// Velocity, m/s.
    pub v: Vec<Vec3>,
    /// Force accumulator, N (scratch of the current step).
    pub f: Vec<Vec3>,
    /// Lumped mass, kg.
    pub mass: Vec<f64>,
    /// 1/mass for live nodes, 0 for dead ones.
    pub inv_mass: Vec<f64>,
    /// 1.0 on free axes, 0.0 on fixed axes (and on every axis of a dead node).
    pub free: Vec<Vec3>,
    /// Force of the underlying tissue that holds the imported shape at rest, N.
    pub support: Vec<Vec3>,
    /// Position the node was created at (imported or cut), m.
    pub x_ref: Vec<Vec3>,
    pub alive: Vec<bool>,
}

impl Nodes {
    pub fn len(&self) -> usize {
        self.x.len()
    }

    pub fn push(&mut self, x: Vec3, v: Vec3) -> u32 {
        let id = self.x.len() as u32;
        self.x.push(x);
        self.v.push(v);
        self.f.push(Vec3::zeros());
        self.mass.push(0.0);
        self.inv_mass.push(0.0);
        self.free.push(Vec3::repeat(1.0));
        self.support.push(Vec3::zeros());
        self.x_ref.push(x);
        self.alive.push(true);
        id
    }

    pub fn kill(&mut self, id: u32) {
        let i = id as usize;
        self.alive[i] = false;
        self.v[i] = Vec3::zeros();
        self.mass[i] = 0.0;
        self.inv_mass[i] = 0.0;
        self.free[i] = Vec3::zeros();
        self.support[i] = Vec3::zeros();
    }

    pub fn set_mass(&mut self, id: u32, mass: f64) {
        let i = id as usize;
        self.mass[i] = mass;
        self.inv_mass[i] = if self.alive[i] && mass > 0.0 { 1.0 / mass } else { 0.0 };
    }

    pub fn alive_count(&self) -> usize {
        self.alive.iter().filter(|a| **a).count()
    }
}

/// A spring between nodes `a` and `b`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Spring {
    pub a: u32,
    pub b: u32,
    /// Stiffness, N/m.
    pub k: f64,
    /// Natural length, m (the reference length / (1 + εr)).
    pub l0: f64,
    /// Length when the spring was made (imported mesh or cut), m: what calibration uses.
    pub l_ref: f64,
}

/// Fast deterministic hasher for edge keys (two u32 packed in a u64). The map is only
/// ever looked up, never iterated, so its order cannot leak into the state.
#[derive(Default)]
pub(crate) struct EdgeHasher(u64);

impl Hasher for EdgeHasher {
    fn finish(&self) -> u64 {
        self.0
    }
    fn write(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0.rotate_left(8) ^ u64::from(b)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
        }
    }
    fn write_u64(&mut self, v: u64) {
        self.0 = (v ^ (v >> 31)).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    }
}

pub(crate) fn edge_key(a: u32, b: u32) -> u64 {
    (u64::from(a.min(b)) << 32) | u64::from(a.max(b))
}

/// The springs, contiguous for the force loop, with an edge → slot index.
#[derive(Debug, Clone, Default)]
pub(crate) struct SpringSet {
    pub list: Vec<Spring>,
    index: HashMap<u64, u32, BuildHasherDefault<EdgeHasher>>,
}

impl SpringSet {
    pub fn with_capacity(n: usize) -> Self {
        Self { list: Vec::with_capacity(n), index: HashMap::with_capacity_and_hasher(n, Default::default()) }
    }

    pub fn len(&self) -> usize {
        self.list.len()
    }

    pub fn get(&self, a: u32, b: u32) -> Option<usize> {
        self.index.get(&edge_key(a, b)).map(|&i| i as usize)
    }

    /// Adds a spring (the edge must not have one).
    pub fn insert(&mut self, spring: Spring) -> usize {
        let slot = self.list.len();
        let previous = self.index.insert(edge_key(spring.a, spring.b), slot as u32);
        debug_assert!(previous.is_none(), "spring {}–{} inserted twice", spring.a, spring.b);
        self.list.push(spring);
        slot
    }

    /// Removes the spring of edge a–b, if any (the last spring takes its slot).
    pub fn remove(&mut self, a: u32, b: u32) -> bool {
        let Some(slot) = self.index.remove(&edge_key(a, b)) else { return false };
        let slot = slot as usize;
        self.list.swap_remove(slot);
        if slot < self.list.len() {
            let moved = self.list[slot];
            self.index.insert(edge_key(moved.a, moved.b), slot as u32);
        }
        true
    }
}

/// The triangle mesh with node → triangle adjacency.
#[derive(Debug, Clone, Default)]
pub(crate) struct Topology {
    pub tris: Vec<[u32; 3]>,
    pub tri_alive: Vec<bool>,
    /// Area when the triangle was made, m² (calibration and mass use it).
    pub tri_area_ref: Vec<f64>,
    /// Live triangles around each node.
    pub node_tris: Vec<Vec<u32>>,
    pub alive_tris: usize,
}

impl Topology {
    /// Live triangles that contain both `a` and `b` (at most two on a manifold mesh).
    pub fn edge_tris(&self, a: u32, b: u32) -> impl Iterator<Item = u32> + '_ {
        self.node_tris[a as usize].iter().copied().filter(move |&t| self.tris[t as usize].contains(&b))
    }

    /// Whether edge a–b lies on the mesh's border (one live triangle: the patch's edge or
    /// a wound).
    pub fn is_border_edge(&self, a: u32, b: u32) -> bool {
        self.edge_tris(a, b).count() == 1
    }

    /// The edges of the triangles `tris` that lie on the mesh's border, each as its
    /// triangle walks it (an edge two of them share is not on the border).
    pub fn border_edges_of<'a>(&'a self, tris: &'a [u32]) -> impl Iterator<Item = (u32, u32)> + 'a {
        tris.iter()
            .flat_map(move |&t| {
                let tri = self.tris[t as usize];
                (0..3).map(move |k| (tri[k], tri[(k + 1) % 3]))
            })
            .filter(|&(a, b)| self.is_border_edge(a, b))
    }

    /// The live triangle across edge a–b from triangle `t`.
    pub fn across(&self, t: u32, a: u32, b: u32) -> Option<u32> {
        self.edge_tris(a, b).find(|&o| o != t)
    }

    pub fn push_tri(&mut self, tri: [u32; 3], area_ref: f64) -> u32 {
        let id = self.tris.len() as u32;
        self.tris.push(tri);
        self.tri_alive.push(true);
        self.tri_area_ref.push(area_ref);
        for &v in &tri {
            self.node_tris[v as usize].push(id);
        }
        self.alive_tris += 1;
        id
    }

    pub fn kill_tri(&mut self, t: u32) {
        if !self.tri_alive[t as usize] {
            return;
        }
        self.tri_alive[t as usize] = false;
        for &v in &self.tris[t as usize] {
            self.node_tris[v as usize].retain(|&o| o != t);
        }
        self.alive_tris -= 1;
    }
}
