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

use super::hex::{Mat8, Mat24, box_mass, box_stiffness, corner_bits, trilinear};

/// One voxel inside a cell: its position in voxels from the cell's corner, and its material.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct CellVoxel {
    pub at: [u16; 3],
    pub material: u16,
}

/// The stiffness and (scalar) mass of one voxel of each material.
#[derive(Debug, Clone)]
pub struct VoxelMatrices {
    pub stiffness: Vec<Mat24>,
    pub mass: Vec<Mat8>,
}

impl VoxelMatrices {
    /// `materials`: (E in Pa, ν, ρ in kg/m³) per material index.
    pub fn new(voxel_m: [f64; 3], materials: &[(f64, f64, f64)]) -> Self {
        let volume = voxel_m[0] * voxel_m[1] * voxel_m[2];
        Self {
            stiffness: materials.iter().map(|&(e, nu, _)| box_stiffness(voxel_m, e, nu)).collect(),
            mass: materials.iter().map(|&(_, _, rho)| box_mass(volume, rho)).collect(),
        }
    }
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

/// One voxel's contribution to its cell (what Eq. 5 subtracts when it is removed).
pub fn voxel_contribution(v: CellVoxel, cell: u32, voxel: &VoxelMatrices) -> (Mat24, Mat8) {
    let w = interpolation(v.at, 1, cell);
    let (mut k, mut m) = (Mat24::zeros(), Mat8::zeros());
    add_projected_stiffness(&mut k, &voxel.stiffness[v.material as usize], &w, 1.0);
    add_projected_mass(&mut m, &voxel.mass[v.material as usize], &w, 1.0);
    (k, m)
}

/// Every voxel straight onto the cell.
pub fn condense_brute(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> (Mat24, Mat8) {
    let cell = 1u32 << levels;
    let (mut k, mut m) = (Mat24::zeros(), Mat8::zeros());
    for v in voxels {
        let (dk, dm) = voxel_contribution(*v, cell, voxel);
        k += dk;
        m += dm;
    }
    (k, m)
}

/// Level by level, 8 children → 1 parent, from the voxels up to the cell.
pub fn condense_recursive(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> (Mat24, Mat8) {
    // Octree nodes of the current level by Morton index; a child's interpolation in its parent.
    let child_w: Vec<Mat8> = (0..8).map(|c| interpolation(demorton(c as u32, 1), 1, 2)).collect();
    let mut current: std::collections::BTreeMap<u32, (Mat24, Mat8)> = std::collections::BTreeMap::new();
    for v in voxels {
        let e = current.entry(morton(v.at, levels)).or_insert((Mat24::zeros(), Mat8::zeros()));
        e.0 += voxel.stiffness[v.material as usize];
        e.1 += voxel.mass[v.material as usize];
    }
    for _ in 0..levels {
        let mut parents: std::collections::BTreeMap<u32, (Mat24, Mat8)> = std::collections::BTreeMap::new();
        for (index, (k, m)) in current {
            let parent = parents.entry(index >> 3).or_insert((Mat24::zeros(), Mat8::zeros()));
            let w = &child_w[(index & 7) as usize];
            add_projected_stiffness(&mut parent.0, &k, w, 1.0);
            add_projected_mass(&mut parent.1, &m, w, 1.0);
        }
        current = parents;
    }
    current.remove(&0).unwrap_or((Mat24::zeros(), Mat8::zeros()))
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
            let aligned = start as usize % size == 0;
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
pub fn condense_direct(voxels: &[CellVoxel], levels: u32, voxel: &VoxelMatrices) -> (Mat24, Mat8) {
    let cell = 1u32 << levels;
    let (mut k, mut m) = (Mat24::zeros(), Mat8::zeros());
    for (start, level, material) in full_subcubes(voxels, levels) {
        let w = interpolation(demorton(start, levels), 1 << level, cell);
        add_projected_stiffness(&mut k, &voxel.stiffness[material as usize], &w, f64::from(1u32 << level));
        add_projected_mass(&mut m, &voxel.mass[material as usize], &w, f64::from(1u32 << (3 * level)));
    }
    (k, m)
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
        let voxel = VoxelMatrices::new([0.003, 0.003, 0.0025], &[(5e3, 0.45, 1060.0), (40e3, 0.3, 1100.0)]);
        for levels in 1..=4 {
            let voxels = pattern(levels);
            let brute = condense_brute(&voxels, levels, &voxel);
            let recursive = condense_recursive(&voxels, levels, &voxel);
            let direct = condense_direct(&voxels, levels, &voxel);
            assert!(relative(&brute.0, &recursive.0) < 1e-10, "level {levels}");
            assert!(relative(&brute.0, &direct.0) < 1e-10, "level {levels}");
            assert!((brute.1 - direct.1).norm() / brute.1.norm() < 1e-10);
            assert!((brute.1 - recursive.1).norm() / brute.1.norm() < 1e-10);
            // Direct condensation takes far fewer steps than voxels.
            let blocks = full_subcubes(&voxels, levels);
            let covered: usize = blocks.iter().map(|b| 1usize << (3 * b.1)).sum();
            assert_eq!(covered, voxels.len());
            // The full one-material octant is a single block.
            assert!(blocks.contains(&(0, levels - 1, 0)), "{blocks:?}");
            assert!(levels == 1 || blocks.len() < voxels.len());
            // K annihilates rigid translations; the mass is the voxels' mass.
            let t = nalgebra::SMatrix::<f64, 24, 1>::from_fn(|r, _| [0.3, -1.0, 2.0][r % 3]);
            assert!((direct.0 * t).norm() < 1e-10 * direct.0.norm());
            let voxel_mass: f64 = voxels.iter().map(|v| voxel.mass[v.material as usize].sum()).sum();
            assert!((direct.1.sum() - voxel_mass).abs() < 1e-12 * voxel_mass);
        }
    }

    #[test]
    fn a_full_cell_is_one_block_and_removal_subtracts_exactly() {
        let voxel = VoxelMatrices::new([0.002; 3], &[(1e4, 0.4, 1000.0)]);
        let full: Vec<CellVoxel> = (0..64u32).map(|m| CellVoxel { at: demorton(m, 2), material: 0 }).collect();
        assert_eq!(full_subcubes(&full, 2), vec![(0, 2, 0)]);
        // A full cell of 4³ voxels equals one hexahedron of the cell's size.
        let big = box_stiffness([0.008; 3], 1e4, 0.4);
        assert!(relative(&condense_direct(&full, 2, &voxel).0, &big) < 1e-12);
        let (mut k, mut m) = condense_direct(&full, 2, &voxel);
        let removed = full[21];
        let (dk, dm) = voxel_contribution(removed, 4, &voxel);
        k -= dk;
        m -= dm;
        let rest: Vec<CellVoxel> = full.iter().copied().filter(|v| *v != removed).collect();
        let rebuilt = condense_brute(&rest, 2, &voxel);
        assert!(relative(&k, &rebuilt.0) < 1e-12);
        assert!((m - rebuilt.1).norm() < 1e-12 * m.norm());
    }
}
