//! Condensation of fine voxels onto a coarse hexahedron (paper 004, Eq. 1–6).
//!
//! A coarse cell is a cube of `2^L` voxels a side. Each voxel is a trilinear hexahedron
//! whose corners are interpolated trilinearly from the cell's 8 nodes (H); the cell's
//! matrices are `Σ Hᵀ A_voxel H` over its voxels — a Galerkin projection. Three ways to
//! compute the same sum:
//!
//! - [`condense_brute`]: every voxel straight onto the cell (the reference);
//! - [`condense_recursive`]: 8 → 1 level by level up an octree (Nesme et al. 2006);
//! - [`condense_direct`]: the paper's method: full one-material octree sub-cubes are
//!   found from runs of consecutive Morton indices (Eq. 6) without building a tree,
//!   and each is condensed in one step with `K_l = 2^l K_0`, `M_l = 8^l M_0` (Eq. 2–4).
//!
//! Removing a voxel subtracts its own contribution (Eq. 5): [`voxel_contribution`].
//!
//! **Volume change.** With [`Volumetric::MeanDilatation`] (the default) a voxel's
//! matrix is only its deviatoric (shape-changing) stiffness, and the volumetric
//! stiffness is added once per element and material on the element's mean volume
//! change: `κ g gᵀ / V`, where `g = Σ Hᵀ g_voxel` is the gradient of the material's
//! volume with respect to the element's nodes and `V` its volume — a constant pressure
//! per element and material (B-bar / Q1P0 in linear elasticity). `g` and `V` are sums
//! over voxels like the stiffness, so the direct and incremental condensation carry
//! over (a full sub-cube of level l contributes `4^l g_0` and `8^l V_0`). Condensing the
//! fully integrated voxels instead ([`Volumetric::Full`], the paper's element) keeps a
//! volume constraint per voxel: a coarse element then resists volume change at every
//! voxel while only 24 degrees of freedom move it, and locks — stiff in bending, and
//! the more so the nearer ν is to 0.5.

use super::hex::{Mat8, Mat24, Vec24, box_deviatoric_stiffness, box_dilatation, box_mass, box_stiffness, bulk_modulus, corner_bits, trilinear};

/// How an element resists volume change.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Volumetric {
    /// At every voxel's Gauss points (the fully integrated trilinear hexahedron).
    Full,
    /// On the mean volume change of each material in each element (B-bar, Q1P0).
    MeanDilatation,
}

/// One material's volume inside an element, as a function of the element's node
/// displacements: the volume changes by `gradientᵀ u`.
#[derive(Debug, Clone, PartialEq)]
pub struct Dilatation {
    pub material: u16,
    pub gradient: Vec24,
    pub volume_m3: f64,
}

/// What a set of voxels condenses to: the stiffness (with the volumetric part of
/// `dilatations` already added, see [`volumetric_stiffness`]), the scalar mass, and per
/// material the volume gradient (empty with [`Volumetric::Full`]).
#[derive(Debug, Clone)]
pub struct Condensed {
    pub stiffness: Mat24,
    pub mass: Mat8,
    pub dilatations: Vec<Dilatation>,
}

impl Condensed {
    fn zero() -> Self {
        Condensed { stiffness: Mat24::zeros(), mass: Mat8::zeros(), dilatations: Vec::new() }
    }

    /// Adds `scale` times a gradient of `material` (volume `volume_m3`) to the element's.
    fn add_dilatation(&mut self, material: u16, gradient: Vec24, volume_m3: f64) {
        match self.dilatations.iter_mut().find(|d| d.material == material) {
            Some(d) => {
                d.gradient += gradient;
                d.volume_m3 += volume_m3;
            }
            None => self.dilatations.push(Dilatation { material, gradient, volume_m3 }),
        }
    }

    /// Eq. 5: takes a voxel's contribution ([`voxel_contribution`]) out of this element.
    pub fn remove(&mut self, voxel_part: &Condensed, voxel: &VoxelMatrices) {
        remove_contribution(&mut self.stiffness, &mut self.mass, &mut self.dilatations, voxel_part, voxel);
    }

    /// Adds the volumetric stiffness of every material's mean dilatation.
    fn finish(mut self, voxel: &VoxelMatrices) -> Self {
        self.dilatations.sort_by_key(|d| d.material);
        for d in &self.dilatations {
            self.stiffness += volumetric_stiffness(d, voxel);
        }
        self
    }
}

/// Eq. 5 on an element's parts: subtracts a voxel's deviatoric stiffness and mass, and
/// replaces the volumetric stiffness of the voxel's material by that of what is left of it.
pub fn remove_contribution(stiffness: &mut Mat24, mass: &mut Mat8, dilatations: &mut Vec<Dilatation>, voxel_part: &Condensed, voxel: &VoxelMatrices) {
    *stiffness -= voxel_part.stiffness;
    *mass -= voxel_part.mass;
    for removed in &voxel_part.dilatations {
        let Some(i) = dilatations.iter().position(|d| d.material == removed.material) else { continue };
        *stiffness -= volumetric_stiffness(&dilatations[i], voxel);
        dilatations[i].gradient -= removed.gradient;
        dilatations[i].volume_m3 -= removed.volume_m3;
        // The last voxel of the material left (volumes are sums of equal voxel volumes).
        if dilatations[i].volume_m3 < 0.5 * voxel.volume_m3 {
            dilatations.remove(i);
        } else {
            *stiffness += volumetric_stiffness(&dilatations[i], voxel);
        }
    }
}

/// `κ g gᵀ / V`: the stiffness of a material's constant pressure in an element.
pub fn volumetric_stiffness(d: &Dilatation, voxel: &VoxelMatrices) -> Mat24 {
    if d.volume_m3 <= 0.0 {
        return Mat24::zeros();
    }
    d.gradient * d.gradient.transpose() * (voxel.bulk[d.material as usize] / d.volume_m3)
}

/// One voxel inside a cell: its position in voxels from the cell's corner, and its material.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct CellVoxel {
    pub at: [u16; 3],
    pub material: u16,
}

/// The stiffness and (scalar) mass of one voxel of each material.
#[derive(Debug, Clone)]
pub struct VoxelMatrices {
    pub volumetric: Volumetric,
    /// Per material: the full stiffness, or with [`Volumetric::MeanDilatation`] only its
    /// deviatoric part.
    pub stiffness: Vec<Mat24>,
    pub mass: Vec<Mat8>,
    /// Per material: the bulk modulus κ, Pa.
    pub bulk: Vec<f64>,
    /// A voxel's volume gradient (m²) and volume (m³).
    pub dilatation: Vec24,
    pub volume_m3: f64,
}

impl VoxelMatrices {
    /// `materials`: (E in Pa, ν, ρ in kg/m³) per material index.
    pub fn new(voxel_m: [f64; 3], materials: &[(f64, f64, f64)], volumetric: Volumetric) -> Self {
        let volume = voxel_m[0] * voxel_m[1] * voxel_m[2];
        let stiffness = |e, nu| match volumetric {
            Volumetric::Full => box_stiffness(voxel_m, e, nu),
            Volumetric::MeanDilatation => box_deviatoric_stiffness(voxel_m, e, nu),
        };
        Self {
            volumetric,
            stiffness: materials.iter().map(|&(e, nu, _)| stiffness(e, nu)).collect(),
            mass: materials.iter().map(|&(_, _, rho)| box_mass(volume, rho)).collect(),
            bulk: materials.iter().map(|&(e, nu, _)| bulk_modulus(e, nu)).collect(),
            dilatation: box_dilatation(voxel_m),
            volume_m3: volume,
        }
    }

    /// A sub-cube of `8^level` voxels of `material` at interpolation `w` into `out`.
    fn add_subcube(&self, out: &mut Condensed, material: u16, level: u32, w: &Mat8) {
        add_projected_stiffness(&mut out.stiffness, &self.stiffness[material as usize], w, f64::from(1u32 << level));
        add_projected_mass(&mut out.mass, &self.mass[material as usize], w, f64::from(1u32 << (3 * level)));
        if self.volumetric == Volumetric::MeanDilatation {
            // The cube's gradient is 4^l a voxel's at its own corners; Hᵀ takes it to the cell's.
            let gradient = project_vector(&self.dilatation, w) * f64::from(1u32 << (2 * level));
            out.add_dilatation(material, gradient, self.volume_m3 * f64::from(1u32 << (3 * level)));
        }
    }
}

/// `(W ⊗ I₃)ᵀ g`: a vector over a sub-cube's corners taken to the cell's nodes.
fn project_vector(g: &Vec24, w: &Mat8) -> Vec24 {
    Vec24::from_fn(|r, _| {
        let (m, axis) = (r / 3, r % 3);
        (0..8).map(|i| w[(i, m)] * g[3 * i + axis]).sum()
    })
}

/// The Morton (octree) index of a position inside a cell of `levels` levels (Eq. 6).
pub fn morton(at: [u16; 3], levels: u32) -> u32 {
    let mut m = 0u32;
    for l in 0..levels {
        let bit = |c: u16| u32::from((c >> l) & 1);
        m |= (4 * bit(at[2]) + 2 * bit(at[1]) + bit(at[0])) << (3 * l);
    }
    m
}

/// The position of a Morton index (inverse of [`morton`]).
pub fn demorton(m: u32, levels: u32) -> [u16; 3] {
    let mut at = [0u16; 3];
    for l in 0..levels {
        let triple = (m >> (3 * l)) & 7;
        for (a, c) in at.iter_mut().enumerate() {
            *c |= (((triple >> a) & 1) as u16) << l;
        }
    }
    at
}

/// Interpolation of a sub-cube's corners from the cell's nodes: `W[(n, m)]` is the weight
/// of cell node m at corner n of the cube at `at` (voxels) with side `side` in a cell of
/// `cell` voxels.
pub fn interpolation(at: [u16; 3], side: u32, cell: u32) -> Mat8 {
    Mat8::from_fn(|n, m| {
        let b = corner_bits(n);
        let p = [0, 1, 2].map(|a| (f64::from(at[a]) + b[a] * f64::from(side)) / f64::from(cell));
        trilinear(m, p)
    })
}

/// `k += s · (W ⊗ I₃)ᵀ a (W ⊗ I₃)`.
pub fn add_projected_stiffness(k: &mut Mat24, a: &Mat24, w: &Mat8, s: f64) {
    // t = a (W ⊗ I): 24 × 24.
    let mut t = Mat24::zeros();
    for r in 0..24 {
        for m in 0..8 {
            for ax in 0..3 {
                let mut sum = 0.0;
                for j in 0..8 {
                    sum += a[(r, 3 * j + ax)] * w[(j, m)];
                }
                t[(r, 3 * m + ax)] = sum;
            }
        }
    }
    for m in 0..8 {
        for ax in 0..3 {
            for c in 0..24 {
                let mut sum = 0.0;
                for i in 0..8 {
                    sum += w[(i, m)] * t[(3 * i + ax, c)];
                }
                k[(3 * m + ax, c)] += s * sum;
            }
        }
    }
}

/// `m += s · Wᵀ a W`.
pub fn add_projected_mass(m: &mut Mat8, a: &Mat8, w: &Mat8, s: f64) {
    *m += (w.transpose() * a * w) * s;
}

/// One voxel's contribution to its cell (what Eq. 5 subtracts when it is removed),
/// without the volumetric stiffness: its dilatation is in `dilatations`.
pub fn voxel_contribution(v: CellVoxel, cell: u32, voxel: &VoxelMatrices) -> Condensed {
    let mut out = Condensed::zero();
    voxel.add_subcube(&mut out, v.material, 0, &interpolation(v.at, 1, cell));
    out
}

/// Every voxel straight onto the cell.
pub fn condense_brute(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> Condensed {
    let cell = 1u32 << levels;
    let mut out = Condensed::zero();
    for v in voxels {
        voxel.add_subcube(&mut out, v.material, 0, &interpolation(v.at, 1, cell));
    }
    out.finish(voxel)
}

/// Level by level, 8 children → 1 parent, from the voxels up to the cell.
pub fn condense_recursive(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> Condensed {
    // Octree nodes of the current level by Morton index; a child's interpolation in its parent.
    let child_w: Vec<Mat8> = (0..8).map(|c| interpolation(demorton(c as u32, 1), 1, 2)).collect();
    let mut current: std::collections::BTreeMap<u32, Condensed> = std::collections::BTreeMap::new();
    let identity = Mat8::identity();
    for v in voxels {
        voxel.add_subcube(current.entry(morton(v.at, levels)).or_insert_with(Condensed::zero), v.material, 0, &identity);
    }
    for _ in 0..levels {
        let mut parents: std::collections::BTreeMap<u32, Condensed> = std::collections::BTreeMap::new();
        for (index, child) in current {
            let parent = parents.entry(index >> 3).or_insert_with(Condensed::zero);
            let w = &child_w[(index & 7) as usize];
            add_projected_stiffness(&mut parent.stiffness, &child.stiffness, w, 1.0);
            add_projected_mass(&mut parent.mass, &child.mass, w, 1.0);
            for d in child.dilatations {
                parent.add_dilatation(d.material, project_vector(&d.gradient, w), d.volume_m3);
            }
        }
        current = parents;
    }
    current.remove(&0).unwrap_or_else(Condensed::zero).finish(voxel)
}

/// The full one-material octree sub-cubes of a cell's voxels: (Morton start, level,
/// material), found from runs of consecutive Morton indices.
pub fn full_subcubes(voxels: &[CellVoxel], levels: u32) -> Vec<(u32, u32, u16)> {
    let mut sorted: Vec<(u32, u16)> = voxels.iter().map(|v| (morton(v.at, levels), v.material)).collect();
    sorted.sort_unstable();
    // run_end[p]: the last index of the run of consecutive indices and one material from p.
    let mut run_end = vec![0usize; sorted.len()];
    for p in (0..sorted.len()).rev() {
        run_end[p] = if p + 1 < sorted.len() && sorted[p + 1].0 == sorted[p].0 + 1 && sorted[p + 1].1 == sorted[p].1 { run_end[p + 1] } else { p };
    }
    let mut blocks = Vec::new();
    let mut p = 0;
    while p < sorted.len() {
        let (start, material) = sorted[p];
        let mut level = 0;
        while level < levels {
            let size = 1usize << (3 * (level + 1));
            let aligned = (start as usize).is_multiple_of(size);
            if !aligned || p + size - 1 > run_end[p] {
                break;
            }
            level += 1;
        }
        blocks.push((start, level, material));
        p += 1 << (3 * level);
    }
    blocks
}

/// The paper's direct condensation: one step per full sub-cube.
pub fn condense_direct(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> Condensed {
    let cell = 1u32 << levels;
    let mut out = Condensed::zero();
    for (start, level, material) in full_subcubes(voxels, levels) {
        voxel.add_subcube(&mut out, material, level, &interpolation(demorton(start, levels), 1 << level, cell));
    }
    out.finish(voxel)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn relative(a: &Mat24, b: &Mat24) -> f64 {
        (a - b).norm() / a.norm().max(b.norm())
    }

    /// A cell of 2^levels voxels a side filled by a deterministic pattern of two materials
    /// with holes, plus one full one-material octant so that large blocks occur.
    fn pattern(levels: u32) -> Vec<CellVoxel> {
        let n = 1u16 << levels;
        let mut out = Vec::new();
        for z in 0..n {
            for y in 0..n {
                for x in 0..n {
                    let octant = x < n / 2 && y < n / 2 && z < n / 2;
                    let h = (u32::from(x) * 7 + u32::from(y) * 13 + u32::from(z) * 29) % 11;
                    if octant || h > 2 {
                        out.push(CellVoxel { at: [x, y, z], material: if octant || h % 2 == 0 { 0 } else { 1 } });
                    }
                }
            }
        }
        out
    }

    #[test]
    fn morton_indices_round_trip_and_follow_the_paper() {
        // The paper's 2D example: node 39 at x = 3, y = 5 (its quadtree: 2·y_l + x_l).
        let m = morton([3, 0, 5], 3);
        let quad = |x: u32, z: u32| (0..3).map(|l| (2 * ((z >> l) & 1) + ((x >> l) & 1)) * 4u32.pow(l)).sum::<u32>();
        assert_eq!(quad(3, 5), 39);
        assert_eq!(demorton(m, 3), [3, 0, 5]);
        for i in 0..512 {
            assert_eq!(morton(demorton(i, 3), 3), i);
        }
    }

    #[test]
    fn direct_recursive_and_brute_force_agree() {
        for volumetric in [Volumetric::Full, Volumetric::MeanDilatation] {
            let voxel = VoxelMatrices::new([0.003, 0.003, 0.0025], &[(5e3, 0.45, 1060.0), (40e3, 0.3, 1100.0)], volumetric);
            for levels in 1..=4 {
                let voxels = pattern(levels);
                let brute = condense_brute(&voxels, levels, &voxel);
                let recursive = condense_recursive(&voxels, levels, &voxel);
                let direct = condense_direct(&voxels, levels, &voxel);
                assert!(relative(&brute.stiffness, &recursive.stiffness) < 1e-10, "level {levels}");
                assert!(relative(&brute.stiffness, &direct.stiffness) < 1e-10, "level {levels}");
                assert!((brute.mass - direct.mass).norm() / brute.mass.norm() < 1e-10);
                assert!((brute.mass - recursive.mass).norm() / brute.mass.norm() < 1e-10);
                assert_eq!(direct.dilatations.len(), if volumetric == Volumetric::Full { 0 } else { 2 });
                for (a, b) in brute.dilatations.iter().zip(&direct.dilatations) {
                    assert_eq!(a.material, b.material);
                    assert!((a.gradient - b.gradient).norm() < 1e-10 * a.gradient.norm());
                    assert!((a.volume_m3 - b.volume_m3).abs() < 1e-12 * a.volume_m3);
                }
                // Direct condensation takes far fewer steps than voxels.
                let blocks = full_subcubes(&voxels, levels);
                let covered: usize = blocks.iter().map(|b| 1usize << (3 * b.1)).sum();
                assert_eq!(covered, voxels.len());
                // The full one-material octant is a single block.
                assert!(blocks.contains(&(0, levels - 1, 0)), "{blocks:?}");
                assert!(levels == 1 || blocks.len() < voxels.len());
                // K annihilates rigid translations; the mass is the voxels' mass.
                let t = nalgebra::SMatrix::<f64, 24, 1>::from_fn(|r, _| [0.3, -1.0, 2.0][r % 3]);
                assert!((direct.stiffness * t).norm() < 1e-10 * direct.stiffness.norm());
                let voxel_mass: f64 = voxels.iter().map(|v| voxel.mass[v.material as usize].sum()).sum();
                assert!((direct.mass.sum() - voxel_mass).abs() < 1e-12 * voxel_mass);
                // A material's volume gradient: a uniform expansion changes its volume by 3εV.
                let cell = 0.003 * f64::from(1u32 << levels);
                let expand = nalgebra::SMatrix::<f64, 24, 1>::from_fn(|r, _| corner_bits(r / 3)[r % 3] * [cell, cell, cell * 2.5 / 3.0][r % 3] * 0.01);
                for d in &direct.dilatations {
                    assert!(((d.gradient.transpose() * expand)[0] - 0.03 * d.volume_m3).abs() < 1e-9 * d.volume_m3);
                }
            }
        }
    }

    #[test]
    fn a_full_cell_is_one_block_and_removal_subtracts_exactly() {
        for volumetric in [Volumetric::Full, Volumetric::MeanDilatation] {
            let voxel = VoxelMatrices::new([0.002; 3], &[(1e4, 0.4, 1000.0)], volumetric);
            let full: Vec<CellVoxel> = (0..64u32).map(|m| CellVoxel { at: demorton(m, 2), material: 0 }).collect();
            assert_eq!(full_subcubes(&full, 2), vec![(0, 2, 0)]);
            // A full cell of 4³ voxels equals one hexahedron of the cell's size.
            let big = match volumetric {
                Volumetric::Full => box_stiffness([0.008; 3], 1e4, 0.4),
                Volumetric::MeanDilatation => crate::grid::hex::box_mean_dilatation_stiffness([0.008; 3], 1e4, 0.4),
            };
            let mut element = condense_direct(&full, 2, &voxel);
            assert!(relative(&element.stiffness, &big) < 1e-12);
            let removed = full[21];
            let dk = voxel_contribution(removed, 4, &voxel);
            element.remove(&dk, &voxel);
            let rest: Vec<CellVoxel> = full.iter().copied().filter(|v| *v != removed).collect();
            let rebuilt = condense_brute(&rest, 2, &voxel);
            assert!(relative(&element.stiffness, &rebuilt.stiffness) < 1e-12);
            assert!((element.mass - rebuilt.mass).norm() < 1e-12 * element.mass.norm());
        }
    }
}
