//! Applying a cut update to the model: topology, springs, masses, the broad phase, the
//! topology delta for viewers, and the stability check of the changed region.
//!
//! Springs and masses of everything the cut touched are recomputed from the live
//! triangles (not patched by differences), so they cannot drift: an edge's stiffness is
//! the sum of its triangles' Van Gelder shares, a node's mass the sum of its triangles'
//! thirds. New triangles take their rest geometry from the reference (in-vivo)
//! positions of their vertices — for a new lip vertex, the material point of the
//! removed skin it was cut from — so they are prestressed like the skin they replace
//! (springs rest at reference length / (1 + εr)), and stitching a wound that has already
//! opened does not create skin.

use super::MassSpring;
use super::cut::CutPlan;
use super::explicit::bound_over;
use super::state::Spring;
use super::Integrator;
use crate::math::triangle_area;
use crate::surface::{SurfaceTriangle, SurfaceVertex, TopologyDelta};
use crate::tissue::CutFallback;

impl MassSpring {
    pub(crate) fn apply_cut(&mut self, mut plan: CutPlan) {
        let mut touched_nodes: Vec<u32> = Vec::new();
        let mut touched_edges: Vec<(u32, u32)> = Vec::new();
        let note_tri = |tri: [u32; 3], nodes: &mut Vec<u32>, edges: &mut Vec<(u32, u32)>| {
            for k in 0..3 {
                let (a, b) = (tri[k], tri[(k + 1) % 3]);
                nodes.push(a);
                edges.push((a.min(b), a.max(b)));
            }
        };

        for &t in &plan.removed_tris {
            note_tri(self.topo.tris[t as usize], &mut touched_nodes, &mut touched_edges);
            self.topo.kill_tri(t);
        }

        let first_new = self.nodes.len() as u32;
        for new in &plan.new_vertices {
            let id = self.nodes.push(new.position, new.velocity);
            self.nodes.x_ref[id as usize] = new.reference;
            self.topo.node_tris.push(Vec::new());
            self.grid.insert(id, &new.position);
        }
        let mut added_tris = Vec::with_capacity(plan.new_triangles.len());
        for &tri in &plan.new_triangles {
            let [a, b, c] = tri.map(|v| self.nodes.x_ref[v as usize]);
            let id = self.topo.push_tri(tri, triangle_area(&a, &b, &c));
            note_tri(tri, &mut touched_nodes, &mut touched_edges);
            added_tris.push(SurfaceTriangle { id, vertices: tri });
            for k in 0..3 {
                let len = (self.nodes.x[tri[(k + 1) % 3] as usize] - self.nodes.x[tri[k] as usize]).norm();
                self.max_edge_m = self.max_edge_m.max(len);
            }
        }

        touched_edges.sort_unstable();
        touched_edges.dedup();
        for &(a, b) in &touched_edges {
            let existing = self.springs.get(a, b);
            let l_ref = match existing {
                Some(slot) => self.springs.list[slot].l_ref,
                None => (self.nodes.x_ref[a as usize] - self.nodes.x_ref[b as usize]).norm(),
            };
            let k: f64 = self
                .topo
                .edge_tris(a, b)
                .map(|t| self.material.edge_stiffness_share(self.topo.tri_area_ref[t as usize], l_ref))
                .sum();
            let has_triangles = self.topo.edge_tris(a, b).next().is_some();
            match (existing, has_triangles) {
                (Some(slot), true) => self.springs.list[slot].k = k,
                (Some(_), false) => {
                    self.springs.remove(a, b);
                }
                (None, true) => {
                    self.springs.insert(Spring { a, b, k, l0: l_ref / (1.0 + self.residual_strain), l_ref });
                }
                (None, false) => {}
            }
        }

        touched_nodes.sort_unstable();
        touched_nodes.dedup();
        let mut removed_vertices = Vec::new();
        for &v in &touched_nodes {
            if self.topo.node_tris[v as usize].is_empty() {
                if self.nodes.alive[v as usize] {
                    self.nodes.kill(v);
                    self.grid.remove(v);
                    removed_vertices.push(v);
                }
            } else {
                let m: f64 = self.topo.node_tris[v as usize]
                    .iter()
                    .map(|&t| self.material.vertex_mass_share(self.topo.tri_area_ref[t as usize]))
                    .sum();
                self.nodes.set_mass(v, m);
            }
        }

        let added_vertices: Vec<SurfaceVertex> = (first_new..self.nodes.len() as u32)
            .filter(|&v| self.nodes.alive[v as usize])
            .map(|v| {
                let p = self.nodes.x[v as usize];
                SurfaceVertex { id: v, position_m: [p.x as f32, p.y as f32, p.z as f32], material: 0 }
            })
            .collect();
        // A new vertex that ended up in no triangle was born and died in this update: it
        // is neither added nor removed for the viewer.
        removed_vertices.retain(|&v| v < first_new);
        self.topology_version += 1;
        self.deltas.push(TopologyDelta {
            version: self.topology_version,
            removed_triangles: plan.removed_tris.clone(),
            removed_vertices,
            added_vertices,
            added_triangles: added_tris,
        });

        self.counters.cut_updates += 1;
        if plan.starts_new_cut && plan.fallback.is_none() {
            self.counters.cuts += 1;
        }
        if let Some(reason) = plan.fallback.take() {
            self.counters.reconstruction_fallbacks += 1;
            self.fallbacks.push(CutFallback { step: self.step_index, reason });
        }
        self.counters.removed_triangles += plan.removed_tris.len() as u64;
        self.counters.removed_elements += plan.removed_tris.len() as u64;
        self.counters.added_triangles += plan.new_triangles.len() as u64;
        self.counters.incision_length_m += plan.incision_length_m;
        self.last_cut_min_angle_deg = plan.min_angle_deg;
        if let Some(a) = plan.min_angle_deg {
            self.min_cut_angle_deg = Some(self.min_cut_angle_deg.map_or(a, |m| m.min(a)));
        }

        let n = self.nodes.len();
        self.reserve_step_room();
        if let Integrator::ImplicitEuler(solver) = &mut self.integrator {
            solver.reserve(n, self.springs.len());
        }
        self.side_memory.fit(n, self.topo.tris.len());
        if let Some(foundation) = &mut self.foundation {
            foundation.refresh(&self.nodes, &self.topo);
        }
        self.keep_explicit_stable(&touched_nodes);
    }

    /// After a cut the new small triangles can raise the highest frequency: if the
    /// explicit substep is now above the bound, raise the substep count (and count it,
    /// so reports say so) rather than let the state blow up.
    fn keep_explicit_stable(&mut self, touched: &[u32]) {
        if !matches!(self.integrator, Integrator::SymplecticEuler { .. }) {
            return;
        }
        let local = bound_over(&self.nodes, &self.springs.list, Some(touched), self.max_contact_stiffness(), self.spring_damping_s);
        let Integrator::SymplecticEuler { substeps } = &mut self.integrator else { return };
        if local.omega_max_rad_s > self.stability.omega_max_rad_s {
            self.stability = local;
        }
        let h = self.dt_s / f64::from(*substeps);
        if h > self.stability.max_substep_s {
            *substeps = (self.dt_s / self.stability.max_substep_s).ceil() as u32;
            self.counters.stability_adjustments += 1;
        }
    }
}
