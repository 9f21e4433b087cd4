//! From physical parameters (E, ν, thickness t, density ρ) to masses and spring constants.
//!
//! Springs: Van Gelder's rule for triangle meshes ("Approximate simulation of elastic
//! membranes by triangulated spring meshes", J. Graphics Tools 3(2), 1998): each
//! triangle T adds E·t·A_T / |e|² to the stiffness of each of its edges e. On an
//! equilateral mesh an interior edge gets two such shares, k = (√3/2)·E·t, and the
//! lattice is exactly an isotropic membrane with Young's modulus E and Poisson ratio
//! 1/3 (the per-triangle share √3/4·E·t is the value ALGORITHMS.md quotes). A
//! triangle spring lattice cannot represent other Poisson ratios; ν is recorded and
//! reported, and E is matched. The uniaxial stretch test checks how close the
//! calibrated patch comes to E.
//!
//! Masses: each triangle gives ρ·t·A_T / 3 to each of its vertices (lumped mass).

/// Membrane material, SI units.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MembraneMaterial {
    pub young_pa: f64,
    pub poisson: f64,
    pub thickness_m: f64,
    pub density_kg_per_m3: f64,
}

impl MembraneMaterial {
    /// Stiffness (N/m) that triangle of area `area_m2` adds to its edge of length `edge_m`.
    pub fn edge_stiffness_share(&self, area_m2: f64, edge_m: f64) -> f64 {
        self.young_pa * self.thickness_m * area_m2 / (edge_m * edge_m)
    }

    /// Mass (kg) that a triangle of area `area_m2` gives to each of its three vertices.
    pub fn vertex_mass_share(&self, area_m2: f64) -> f64 {
        self.density_kg_per_m3 * self.thickness_m * area_m2 / 3.0
    }

    /// In-plane isotropic membrane stress (N/m) of the intact prestrained lattice:
    /// E·t/(1 − ν_eff)·εr/(1 + εr), with ν_eff = 1/3 for the spring lattice.
    pub fn prestress_n_per_m(&self, residual_strain: f64) -> f64 {
        self.young_pa * self.thickness_m * 1.5 * residual_strain / (1.0 + residual_strain)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn equilateral_interior_edge_gets_sqrt3_over_2_et() {
        let m = MembraneMaterial { young_pa: 1e5, poisson: 1.0 / 3.0, thickness_m: 0.002, density_kg_per_m3: 1000.0 };
        let a = 0.01;
        let area = 3f64.sqrt() / 4.0 * a * a;
        let k = 2.0 * m.edge_stiffness_share(area, a);
        assert!((k - 3f64.sqrt() / 2.0 * 1e5 * 0.002).abs() < 1e-9);
    }
}
