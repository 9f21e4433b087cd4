//! The branched grid's side of multirate haptics (crate::multirate): after a
//! deformation step's tissue system is assembled, each tool's contact patch — the
//! surface vertices near it and their compliance — for the haptic loop to render
//! against until the next deformation step.

use super::BranchedGrid;
use crate::math::{Matrix3, Vec3, closest_point_on_segment};
use crate::multirate::patch::{ContactPatch, MAX_PATCH_VERTICES};
use crate::tool::ToolCommand;

/// A tool's patch compliance being kept up to date (see `patch_compliance`): where its
/// tip was and the topology when its columns were first solved, the columns (grid
/// frame) with their solves' residuals, and the column to solve next.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct CachedCompliance {
    tip: Vec3,
    topology_version: u64,
    columns: Matrix3<f64>,
    residuals: [f64; 3],
    next_axis: usize,
}

impl crate::hash::HashState for CachedCompliance {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        (self.tip, self.topology_version, self.next_axis).hash_state(h);
        self.columns.iter().for_each(|c| h.write_f64(*c));
        self.residuals.hash_state(h);
    }
}

impl BranchedGrid {
    /// Surface vertices within `margin_m` of tool `i`'s outer capsule (its axis within
    /// its radius plus the margin), nearest first, at most [`MAX_PATCH_VERTICES`]:
    /// (vertex, distance from the axis) into `out`.
    fn near_vertices(&self, i: usize, command: &ToolCommand, margin_m: f64, out: &mut Vec<(u32, f64)>) {
        out.clear();
        if !command.active || !command.pose.is_finite() {
            return;
        }
        let tool = &self.tools[i];
        let tip = self.frame.to_local(&command.pose.position_m);
        let top = tip + self.frame.rotation.transpose() * command.pose.axis() * tool.length_m;
        let reach = tool.radius_m + margin_m;
        let (lo, hi) = (tip.inf(&top) - Vec3::repeat(reach), tip.sup(&top) + Vec3::repeat(reach));
        for v in self.surface_vertices_near(lo, hi) {
            let p = self.surface.position(&self.topo, v as usize);
            let distance = (p - closest_point_on_segment(&p, &tip, &top).1).norm();
            if distance < reach {
                out.push((v, distance));
            }
        }
        out.sort_unstable_by(|a, b| a.1.total_cmp(&b.1).then(a.0.cmp(&b.0)));
        out.truncate(MAX_PATCH_VERTICES);
    }

    /// Tool `i`'s patch compliance from the tissue's system (before the tools' contacts
    /// enter it): a unit force spread over the vertices the tool presses on, in
    /// proportion to their contact forces (the mode the contact loads; touching none,
    /// evenly over the nearest vertices, within half a voxel of the nearest), solved along
    /// an axis, and the patch's motion read with the same weights: a column of C. Each
    /// solve costs about what the step's own does, so while the tool stays within a voxel
    /// of where its columns were first solved and nothing is cut, one column is solved
    /// a step, in turn; otherwise all three.
    pub(super) fn patch_compliance(&mut self, i: usize, command: &ToolCommand, margin_m: f64, patch: &mut ContactPatch) {
        patch.compliance = Matrix3::zeros();
        patch.compliance_residual = 0.0;
        let Some(tip) = (command.active && command.pose.is_finite()).then(|| self.frame.to_local(&command.pose.position_m)) else {
            self.compliance_cache[i] = None;
            return;
        };
        let voxel = self.topo.layout.spacing_m.iter().copied().fold(0.0, f64::max);
        let mut shares = std::mem::take(&mut self.patch_scratch);
        let (start, end) = self.contact_ranges[i];
        shares.clear();
        shares.extend((start..end).map(|c| (self.contact_vertices[c], self.contacts[c].force.norm())).filter(|&(_, f)| f > 0.0));
        if shares.is_empty() {
            self.near_vertices(i, command, margin_m, &mut shares);
            let limit = shares.first().map_or(0.0, |&(_, d)| d + voxel * 0.5);
            shares.retain(|&(_, d)| d <= limit);
            shares.iter_mut().for_each(|(_, w)| *w = 1.0);
        }
        let total: f64 = shares.iter().map(|&(_, w)| w).sum();
        if total > 0.0 {
            shares.iter_mut().for_each(|(_, w)| *w /= total);
            let kept = self.compliance_cache[i].filter(|c| c.topology_version == self.topology_version && (c.tip - tip).norm() < voxel);
            let mut cached = kept.unwrap_or(CachedCompliance { tip, topology_version: self.topology_version, columns: Matrix3::zeros(), residuals: [0.0; 3], next_axis: 0 });
            let axes = if kept.is_some() { cached.next_axis..cached.next_axis + 1 } else { 0..3 };
            for axis in axes {
                let (column, residual) = self.compliance_column(&shares, axis);
                cached.columns.set_column(axis, &column);
                cached.residuals[axis] = residual;
            }
            cached.next_axis = if kept.is_some() { (cached.next_axis + 1) % 3 } else { 0 };
            let symmetric = (cached.columns + cached.columns.transpose()) * 0.5;
            patch.compliance = self.frame.rotation * symmetric * self.frame.rotation.transpose();
            patch.compliance_residual = cached.residuals.iter().copied().fold(0.0, f64::max);
            self.compliance_cache[i] = Some(cached);
        } else {
            self.compliance_cache[i] = None;
        }
        self.patch_scratch = shares;
    }

    /// How far the vertices `shares` (vertex, weight summing to 1) move on average per
    /// newton spread over them along `axis`, over one step of the tissue's system, and
    /// the relative residual of that solve.
    fn compliance_column(&mut self, shares: &[(u32, f64)], axis: usize) -> (Vec3, f64) {
        let n = self.topo.nodes.len();
        let (mut force, mut motion) = (std::mem::take(&mut self.compliance_force), std::mem::take(&mut self.compliance_motion));
        force.clear();
        force.resize(n, Vec3::zeros());
        motion.resize(n, Vec3::zeros());
        for (node, weight) in self.share_nodes(shares) {
            force[node] += Vec3::ith(axis, weight);
        }
        let convergence = self.dynamics.compliance(&self.topo, &self.settings, self.step_index, &force, &mut motion);
        let moved = self.share_nodes(shares).map(|(node, weight)| motion[node] * weight).sum();
        (self.compliance_force, self.compliance_motion) = (force, motion);
        (moved, convergence.residual)
    }

    /// The grid nodes the vertices `shares` (vertex, weight) are embedded in, with each
    /// vertex's weight times its trilinear weight there.
    fn share_nodes<'a>(&'a self, shares: &'a [(u32, f64)]) -> impl Iterator<Item = (usize, f64)> + 'a {
        shares.iter().flat_map(move |&(v, share)| {
            let element = self.topo.voxel_element[self.surface.voxel[v as usize] as usize] as usize;
            self.topo.elements.nodes[element].iter().zip(self.surface.weights[v as usize]).map(move |(&node, w)| (node as usize, share * w))
        })
    }

    /// Tool `i`'s patch vertices, their positions (world) and their friction anchors on
    /// the tool as this step left them (where a cut cleared the anchors, none), as the
    /// step and its cuts left the surface; then the points on triangles' insides it held
    /// (a tool thinner than the vertex spacing: face_contact), which the haptic loop
    /// holds as it holds vertices (without them a 0.5 mm probe or a 0.4 mm blade plate
    /// pressed tip first rendered 0 N where the deformation pushed with 8 N).
    pub(super) fn patch_vertices(&mut self, i: usize, command: &ToolCommand, margin_m: f64, patch: &mut ContactPatch) {
        let mut near = std::mem::take(&mut self.patch_scratch);
        self.near_vertices(i, command, margin_m, &mut near);
        near.truncate(MAX_PATCH_VERTICES - self.held_face_points(i).count().min(MAX_PATCH_VERTICES));
        patch.vertices.clear();
        patch.positions.clear();
        patch.anchors.clear();
        patch.held.clear();
        for &(v, _) in &near {
            patch.vertices.push(v);
            patch.positions.push(self.frame.to_world(&self.surface.position(&self.topo, v as usize)));
            let anchor = self.anchors.get(v as usize).filter(|a| a.tool == i && a.step == self.step_index);
            patch.anchors.push(anchor.map(|a| self.frame.rotation * a.from_tip));
            // The normal it was held along this step, tool frame (the grid's own).
            let touch = self.touches.get(v as usize).copied().flatten().filter(|t| t.tool == i && t.step == self.step_index);
            patch.held.push(touch.map(|t| t.normal_in_tool));
        }
        patch.face_points = 0;
        for (v, point, held) in self.held_face_points(i).take(MAX_PATCH_VERTICES - near.len()) {
            patch.face_points += 1;
            patch.vertices.push(v);
            patch.positions.push(self.frame.to_world(&point));
            patch.anchors.push(held.anchor_from_tip.map(|a| self.frame.rotation * a));
            patch.held.push(Some(held.normal_in_tool));
        }
        patch.tool_tip_m = (command.active && command.pose.is_finite()).then_some(command.pose.position_m);
        patch.friction = near.first().map_or_else(Default::default, |&(v, _)| self.friction_at(v as usize));
        patch.blade_pushes = near.first().is_some_and(|&(v, _)| !self.cuts_through(i, v as usize));
        self.patch_scratch = near;
    }
}
