//! The tissue under the skin: an elastic, viscous (Winkler) foundation
//! (docs/tool-tissue.md).
//!
//! Per unit area, a normal stiffness k pulls each node back toward its reference
//! position along the surface's reference normal n, a shear stiffness k_t across it (the
//! subcutaneous layer anchoring the skin in its plane), and drag resists the node's
//! velocity against the underlying tissue, c_n along n and c_t across it. With
//! d_i = x_i − x_ref,i and P_n = n nᵀ:
//!
//!   f_i = −A_i (k P_n + k_t (I − P_n)) d_i − A_i (c_n P_n + c_t (I − P_n)) v_i,
//!
//! with A_i the node's share of the reference area (a third of each live triangle it
//! belongs to). A pressure p on a patch far from its border therefore sinks it by p/k.
//! The drag is integrated implicitly, like the mass damping, so it never limits the time
//! step: a wound retracts under the residual stress against c_t over a time the
//! scene sets, not as elastic ringing. The stiffness enters the implicit system's matrix
//! and the explicit stability bound.

use nalgebra::Matrix3;

use super::state::{Nodes, Topology};
use crate::math::Vec3;

/// The foundation's constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FoundationParams {
    /// k, Pa/m.
    pub stiffness_pa_per_m: f64,
    /// k_t, Pa/m.
    pub shear_stiffness_pa_per_m: f64,
    /// c_n, Pa·s/m.
    pub normal_damping_pa_s_per_m: f64,
    /// c_t, Pa·s/m.
    pub shear_damping_pa_s_per_m: f64,
}

/// The foundation under each node: its area share and reference normal.
#[derive(Debug, Clone)]
pub(crate) struct Foundation {
    pub params: FoundationParams,
    area: Vec<f64>,
    normal: Vec<Vec3>,
}

impl Foundation {
    pub fn new(params: FoundationParams, nodes: &Nodes, topo: &Topology) -> Self {
        let mut foundation = Foundation { params, area: Vec::new(), normal: Vec::new() };
        foundation.refresh(nodes, topo);
        foundation
    }

    /// Recomputes every node's area share and normal from the live triangles at their
    /// reference positions (at build and after a cut; allocates only when nodes were added).
    pub fn refresh(&mut self, nodes: &Nodes, topo: &Topology) {
        let n = nodes.len();
        self.area.clear();
        self.area.resize(n, 0.0);
        self.normal.clear();
        self.normal.resize(n, Vec3::zeros());
        for (t, tri) in topo.tris.iter().enumerate() {
            if !topo.tri_alive[t] {
                continue;
            }
            let [a, b, c] = tri.map(|v| nodes.x_ref[v as usize]);
            // |cross| / 2 is the area; its direction the normal.
            let area_normal = (b - a).cross(&(c - a)) * 0.5;
            let third = topo.tri_area_ref[t] / 3.0;
            for &v in tri {
                self.area[v as usize] += third;
                self.normal[v as usize] += area_normal;
            }
        }
        for i in 0..n {
            let len = self.normal[i].norm();
            if nodes.alive[i] && len > 0.0 {
                self.normal[i] /= len;
            } else {
                self.area[i] = 0.0;
                self.normal[i] = Vec3::zeros();
            }
        }
    }

    /// The largest node spring, N/m (for the explicit stability bound).
    pub fn max_node_stiffness(&self) -> f64 {
        self.area.iter().fold(0.0f64, |m, &a| m.max(a)) * self.params.stiffness_pa_per_m.max(self.params.shear_stiffness_pa_per_m)
    }

    /// (k P_n + k_t (I − P_n)) d at node `i`, per unit area.
    fn spring(&self, i: usize, d: Vec3) -> Vec3 {
        let n = self.normal[i];
        let along = n * n.dot(&d);
        along * self.params.stiffness_pa_per_m + (d - along) * self.params.shear_stiffness_pa_per_m
    }

    /// Adds the elastic part to the force accumulators.
    pub fn add_forces(&self, nodes: &mut Nodes) {
        for i in 0..nodes.len() {
            let a = self.area[i];
            if a > 0.0 {
                nodes.f[i] -= self.spring(i, nodes.x[i] - nodes.x_ref[i]) * a;
            }
        }
    }

    /// A_i (c_n P_n + c_t (I − P_n)), N·s/m: the drag's matrix at node `i`.
    pub fn drag_matrix(&self, i: usize) -> Matrix3<f64> {
        let n = self.normal[i];
        let along = n * n.transpose();
        (along * self.params.normal_damping_pa_s_per_m + (Matrix3::identity() - along) * self.params.shear_damping_pa_s_per_m) * self.area[i]
    }

    /// The velocity after the drag, integrated implicitly over `h`: `w` is the velocity
    /// the other forces would give, `mass_coef` the mass damping's 1 + hα.
    pub fn damped_velocity(&self, i: usize, w: Vec3, h: f64, inv_mass: f64, mass_coef: f64) -> Vec3 {
        let (a, n) = (self.area[i], self.normal[i]);
        let along = n * w.dot(&n);
        let across = w - along;
        along / (mass_coef + h * a * self.params.normal_damping_pa_s_per_m * inv_mass)
            + across / (mass_coef + h * a * self.params.shear_damping_pa_s_per_m * inv_mass)
    }

    /// Node `i`'s share of `stiff_coef · K_f + damp_coef · C_f` as `iso·I + along·n nᵀ`:
    /// (iso, along, n). Zero where the node has no foundation.
    pub fn node_term(&self, i: usize, stiff_coef: f64, damp_coef: f64) -> (f64, f64, Vec3) {
        let a = self.area[i];
        if a <= 0.0 {
            return (0.0, 0.0, Vec3::zeros());
        }
        let p = &self.params;
        let across = a * (stiff_coef * p.shear_stiffness_pa_per_m + damp_coef * p.shear_damping_pa_s_per_m);
        let normal = a * (stiff_coef * p.stiffness_pa_per_m + damp_coef * p.normal_damping_pa_s_per_m);
        (across, normal - across, self.normal[i])
    }
}
