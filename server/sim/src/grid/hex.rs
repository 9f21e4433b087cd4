//! The trilinear hexahedron on an axis-aligned box: stiffness (2×2×2 Gauss points),
//! consistent mass, and trilinear interpolation weights.
//!
//! Corner numbering: corner `n` sits at `(n & 1, n >> 1 & 1, n >> 2 & 1)` in units of
//! the box's sides, so corner bits match the Morton order of the octree. Degrees of
//! freedom: 3 per corner, corner-major (`3n + axis`).

use nalgebra::SMatrix;

/// 24 × 24: the stiffness of one hexahedron (8 corners × 3 axes).
pub type Mat24 = SMatrix<f64, 24, 24>;
/// A single-precision copy of a stiffness, for the solver's matrix-vector products.
pub type Mat24f = SMatrix<f32, 24, 24>;
/// 8 × 8: a scalar per pair of corners (mass, interpolation weights).
pub type Mat8 = SMatrix<f64, 8, 8>;

/// The corner's position on the unit cube: 0 or 1 per axis.
pub fn corner_bits(n: usize) -> [f64; 3] {
    [(n & 1) as f64, ((n >> 1) & 1) as f64, ((n >> 2) & 1) as f64]
}

/// Trilinear weight of corner `n` at `p` in unit-cube coordinates.
pub fn trilinear(n: usize, p: [f64; 3]) -> f64 {
    let b = corner_bits(n);
    (0..3).map(|a| if b[a] == 1.0 { p[a] } else { 1.0 - p[a] }).product()
}

/// All 8 trilinear weights at `p` in unit-cube coordinates.
pub fn trilinear_weights(p: [f64; 3]) -> [f64; 8] {
    std::array::from_fn(|n| trilinear(n, p))
}

/// 24: a vector over one hexahedron's degrees of freedom.
pub type Vec24 = SMatrix<f64, 24, 1>;

/// Lamé's constants (λ, μ) of Young's modulus and Poisson's ratio.
pub fn lame(young_pa: f64, poisson: f64) -> (f64, f64) {
    (young_pa * poisson / ((1.0 + poisson) * (1.0 - 2.0 * poisson)), young_pa / (2.0 * (1.0 + poisson)))
}

/// The bulk modulus κ = λ + 2μ/3 = E / (3 (1 − 2ν)), Pa.
pub fn bulk_modulus(young_pa: f64, poisson: f64) -> f64 {
    young_pa / (3.0 * (1.0 - 2.0 * poisson))
}

/// Stiffness of a box of sides `size_m` made of an isotropic linear material, fully
/// integrated (the volumetric term at every Gauss point: locks as ν → 0.5).
pub fn box_stiffness(size_m: [f64; 3], young_pa: f64, poisson: f64) -> Mat24 {
    let (lambda, mu) = lame(young_pa, poisson);
    box_stiffness_lame(size_m, lambda, mu)
}

/// The deviatoric part of a box's stiffness: the full integration with λ = −2μ/3, so
/// that the bulk modulus λ + 2μ/3 is zero at every Gauss point. The mean-dilatation
/// element (B-bar, Q1P0) adds the volumetric part once per element, on its mean
/// volume change ([`box_dilatation`]).
pub fn box_deviatoric_stiffness(size_m: [f64; 3], young_pa: f64, poisson: f64) -> Mat24 {
    let (_, mu) = lame(young_pa, poisson);
    box_stiffness_lame(size_m, -2.0 * mu / 3.0, mu)
}

/// The gradient of a box's volume change with respect to its corners' displacements,
/// ∫ ∇N dV (m²): the box's volume changes by `gᵀ u` under small displacements u. For an
/// axis-aligned box it is V · s / (4 · side) per axis, s = ±1 the corner's side.
pub fn box_dilatation(size_m: [f64; 3]) -> Vec24 {
    let volume = size_m[0] * size_m[1] * size_m[2];
    Vec24::from_fn(|r, _| {
        let (n, axis) = (r / 3, r % 3);
        let s = 2.0 * corner_bits(n)[axis] - 1.0;
        volume * s / (4.0 * size_m[axis])
    })
}

/// The mean-dilatation (B-bar) stiffness of a box: deviatoric part plus `κ g gᵀ / V`.
pub fn box_mean_dilatation_stiffness(size_m: [f64; 3], young_pa: f64, poisson: f64) -> Mat24 {
    let g = box_dilatation(size_m);
    box_deviatoric_stiffness(size_m, young_pa, poisson) + g * g.transpose() * (bulk_modulus(young_pa, poisson) / (size_m[0] * size_m[1] * size_m[2]))
}

/// Stiffness of a box with Lamé constants λ, μ (2×2×2 Gauss points).
fn box_stiffness_lame(size_m: [f64; 3], lambda: f64, mu: f64) -> Mat24 {
    let g = 1.0 / 3f64.sqrt();
    let jacobian = size_m[0] * size_m[1] * size_m[2] / 8.0;
    let mut k = Mat24::zeros();
    for gp in 0..8 {
        let xi = corner_bits(gp).map(|b| if b == 1.0 { g } else { -g });
        // dN/dx for every corner at this Gauss point.
        let mut grad = [[0.0f64; 3]; 8];
        for (n, gn) in grad.iter_mut().enumerate() {
            let s = corner_bits(n).map(|b| 2.0 * b - 1.0);
            let f = [(1.0 + s[0] * xi[0]) / 2.0, (1.0 + s[1] * xi[1]) / 2.0, (1.0 + s[2] * xi[2]) / 2.0];
            // N = f0 f1 f2; dN/dξa = (s_a / 2) × the other two; dξ/dx = 2 / size.
            gn[0] = s[0] / 2.0 * f[1] * f[2] * 2.0 / size_m[0];
            gn[1] = s[1] / 2.0 * f[0] * f[2] * 2.0 / size_m[1];
            gn[2] = s[2] / 2.0 * f[0] * f[1] * 2.0 / size_m[2];
        }
        // K_ab = ∫ λ (∇Na)(∇Nb)ᵀ + μ (∇Na·∇Nb I + ∇Nb ∇Naᵀ), per 3×3 block.
        for a in 0..8 {
            for b in 0..8 {
                let (ga, gb) = (grad[a], grad[b]);
                let dot = ga[0] * gb[0] + ga[1] * gb[1] + ga[2] * gb[2];
                for i in 0..3 {
                    for j in 0..3 {
                        let mut v = lambda * ga[i] * gb[j] + mu * gb[i] * ga[j];
                        if i == j {
                            v += mu * dot;
                        }
                        k[(3 * a + i, 3 * b + j)] += v * jacobian;
                    }
                }
            }
        }
    }
    k
}

/// Consistent scalar mass of a box of `volume_m3` and density ρ (the 3D mass matrix is
/// this ⊗ I₃): ρV/216 · Π over axes of (2 where the corners share the coordinate, else 1).
pub fn box_mass(volume_m3: f64, density: f64) -> Mat8 {
    Mat8::from_fn(|i, j| {
        let f: f64 = (0..3).map(|a| if (i >> a) & 1 == (j >> a) & 1 { 2.0 } else { 1.0 }).product();
        density * volume_m3 * f / 216.0
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stiffness_is_symmetric_and_annihilates_rigid_motion() {
        let k = box_stiffness([0.003, 0.002, 0.004], 5e3, 0.45);
        assert!((k - k.transpose()).norm() < 1e-12 * k.norm());
        let translation = SMatrix::<f64, 24, 1>::from_fn(|r, _| [1.0, -2.0, 0.5][r % 3]);
        assert!((k * translation).norm() < 1e-12 * k.norm());
        // An infinitesimal rotation about z: u = ω × x.
        let rotation = SMatrix::<f64, 24, 1>::from_fn(|r, _| {
            let b = corner_bits(r / 3);
            let x = [b[0] * 0.003, b[1] * 0.002, b[2] * 0.004];
            [-x[1], x[0], 0.0][r % 3]
        });
        assert!((k * rotation).norm() < 1e-10 * k.norm());
    }

    #[test]
    fn a_uniaxial_stretch_gives_youngs_modulus_without_lateral_strain_constraint() {
        // Stretch a unit cube by ε along x with ν = 0: the force on the +x face is E·A·ε.
        let (e, eps) = (1000.0, 0.01);
        let k = box_stiffness([1.0, 1.0, 1.0], e, 0.0);
        let u = SMatrix::<f64, 24, 1>::from_fn(|r, _| if r % 3 == 0 { corner_bits(r / 3)[0] * eps } else { 0.0 });
        let f = k * u;
        let face: f64 = (0..8).filter(|n| n & 1 == 1).map(|n| f[3 * n]).sum();
        assert!((face - e * eps).abs() < 1e-9, "{face}");
    }

    #[test]
    fn deviatoric_plus_mean_dilatation_is_the_full_stiffness_on_uniform_strain() {
        // On a uniform strain the dilatation is the same at every Gauss point, so the
        // mean-dilatation element and the fully integrated one agree exactly; on a
        // bending mode (dilatation varying over the element) the former is softer.
        let (size, e, nu) = ([0.003, 0.002, 0.004], 5e3, 0.49);
        let full = box_stiffness(size, e, nu);
        let g = box_dilatation(size);
        let volume = size[0] * size[1] * size[2];
        let bbar = box_mean_dilatation_stiffness(size, e, nu);
        let uniform = SMatrix::<f64, 24, 1>::from_fn(|r, _| {
            let b = corner_bits(r / 3);
            let x = [b[0] * size[0], b[1] * size[1], b[2] * size[2]];
            [0.01 * x[0] + 0.002 * x[1], -0.003 * x[2], 0.004 * x[2] + 0.001 * x[0]][r % 3]
        });
        assert!((full * uniform - bbar * uniform).norm() < 1e-9 * (full * uniform).norm());
        // The volume gradient: a uniform expansion ε changes the volume by 3εV.
        let expand = SMatrix::<f64, 24, 1>::from_fn(|r, _| corner_bits(r / 3)[r % 3] * size[r % 3] * 0.01);
        assert!(((g.transpose() * expand)[0] - 0.03 * volume).abs() < 1e-15);
        // Bending (u_x = x·z): no mean volume change, so B-bar leaves only shear.
        let bend = SMatrix::<f64, 24, 1>::from_fn(|r, _| {
            let b = corner_bits(r / 3);
            if r % 3 == 0 { (b[0] - 0.5) * (b[2] - 0.5) } else { 0.0 }
        });
        let (energy_full, energy_bbar) = ((bend.transpose() * full * bend)[0], (bend.transpose() * bbar * bend)[0]);
        assert!(energy_bbar < 0.1 * energy_full, "{energy_bbar} against {energy_full}");
        assert!((bbar - bbar.transpose()).norm() < 1e-12 * bbar.norm());
    }

    #[test]
    fn mass_sums_to_the_box_mass() {
        let m = box_mass(2e-6, 1000.0);
        assert!((m.sum() - 2e-3).abs() < 1e-15);
        assert!((trilinear_weights([0.3, 0.6, 0.1]).iter().sum::<f64>() - 1.0).abs() < 1e-15);
    }
}
