//! The procedural rectangular skin patch.
//!
//! Rows of nodes alternate by half a cell, which gives equilateral triangles inside
//! when the row spacing is √3/2 of the column spacing; the left and right sides stay
//! straight thanks to an extra node at the ends of the shifted rows. The patch lies in
//! the z = 0 plane, centred on the origin, with its normal along +z.

use crate::geometry::TriMesh;
use crate::math::Vec3;

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct PatchParams {
    pub width_m: f64,
    pub height_m: f64,
    pub cells_x: u32,
    pub cells_y: u32,
    /// Interior node jitter as a fraction of the x spacing.
    pub jitter: f64,
    pub seed: u64,
}

/// The number of nodes [`generate`] will make (to check size limits before building).
pub fn node_count(p: &PatchParams) -> u64 {
    let even_rows = u64::from(p.cells_y / 2 + 1);
    let odd_rows = u64::from(p.cells_y + 1) - even_rows;
    even_rows * u64::from(p.cells_x + 1) + odd_rows * u64::from(p.cells_x + 2)
}

pub fn generate(p: &PatchParams) -> TriMesh {
    let dx = p.width_m / f64::from(p.cells_x);
    let dy = p.height_m / f64::from(p.cells_y);
    let (x0, y0) = (-0.5 * p.width_m, -0.5 * p.height_m);
    let mut rng = SplitMix64(p.seed);
    let mut positions = Vec::new();
    let mut rows: Vec<Vec<u32>> = Vec::with_capacity(p.cells_y as usize + 1);
    for j in 0..=p.cells_y {
        let y = y0 + f64::from(j) * dy;
        let xs: Vec<f64> = if j % 2 == 0 {
            (0..=p.cells_x).map(|i| x0 + f64::from(i) * dx).collect()
        } else {
            std::iter::once(x0)
                .chain((0..p.cells_x).map(|i| x0 + (f64::from(i) + 0.5) * dx))
                .chain(std::iter::once(x0 + p.width_m))
                .collect()
        };
        let last = xs.len() - 1;
        let mut row = Vec::with_capacity(xs.len());
        for (i, &x) in xs.iter().enumerate() {
            let interior = j > 0 && j < p.cells_y && i > 0 && i < last;
            let (mut jx, mut jy) = (0.0, 0.0);
            if interior && p.jitter > 0.0 {
                jx = (rng.next_f64() * 2.0 - 1.0) * p.jitter * dx;
                jy = (rng.next_f64() * 2.0 - 1.0) * p.jitter * dx.min(dy);
            }
            row.push(positions.len() as u32);
            positions.push(Vec3::new(x + jx, y + jy, 0.0));
        }
        rows.push(row);
    }
    let mut triangles = Vec::new();
    for j in 0..p.cells_y as usize {
        zip_rows(&rows[j], &rows[j + 1], &positions, &mut triangles);
    }
    TriMesh { positions, triangles }
}

/// Triangulates the band between a lower row and an upper row of nodes (both sorted by
/// x), counter-clockwise seen from +z, advancing along the row whose next node is
/// further left (the shorter diagonal on a tie).
fn zip_rows(lower: &[u32], upper: &[u32], positions: &[Vec3], out: &mut Vec<[u32; 3]>) {
    let (mut i, mut j) = (0, 0);
    while i + 1 < lower.len() || j + 1 < upper.len() {
        let advance_lower = if i + 1 == lower.len() {
            false
        } else if j + 1 == upper.len() {
            true
        } else {
            let (xl, xu) = (positions[lower[i + 1] as usize].x, positions[upper[j + 1] as usize].x);
            if (xl - xu).abs() > 1e-9 * (xl.abs() + xu.abs() + 1.0) {
                xl < xu
            } else {
                // A tie (at the straight sides): take the shorter diagonal.
                let d_lower = (positions[lower[i + 1] as usize] - positions[upper[j] as usize]).norm();
                let d_upper = (positions[upper[j + 1] as usize] - positions[lower[i] as usize]).norm();
                d_lower <= d_upper
            }
        };
        if advance_lower {
            out.push([lower[i], lower[i + 1], upper[j]]);
            i += 1;
        } else {
            out.push([lower[i], upper[j + 1], upper[j]]);
            j += 1;
        }
    }
}

/// A small deterministic generator (splitmix64): the same seed gives the same patch on
/// every platform.
pub(crate) struct SplitMix64(pub u64);

impl SplitMix64 {
    pub fn next_u64(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9e37_79b9_7f4a_7c15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
        z ^ (z >> 31)
    }

    /// Uniform in [0, 1).
    pub fn next_f64(&mut self) -> f64 {
        (self.next_u64() >> 11) as f64 / (1u64 << 53) as f64
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::math::{triangle_area, triangle_normal};

    fn params(jitter: f64) -> PatchParams {
        PatchParams { width_m: 0.1, height_m: 0.08, cells_x: 20, cells_y: 18, jitter, seed: 3 }
    }

    #[test]
    fn patch_covers_its_area_with_valid_upward_triangles() {
        for jitter in [0.0, 0.2] {
            let p = params(jitter);
            let mesh = generate(&p);
            mesh.check().unwrap();
            assert_eq!(mesh.positions.len() as u64, node_count(&p));
            let area: f64 = mesh
                .triangles
                .iter()
                .map(|t| triangle_area(&mesh.positions[t[0] as usize], &mesh.positions[t[1] as usize], &mesh.positions[t[2] as usize]))
                .sum();
            assert!((area - 0.1 * 0.08).abs() < 1e-12, "area {area}");
            for t in &mesh.triangles {
                let n = triangle_normal(&mesh.positions[t[0] as usize], &mesh.positions[t[1] as usize], &mesh.positions[t[2] as usize]);
                assert!(n.z > 0.0);
            }
        }
    }

    #[test]
    fn equilateral_spacing_gives_sixty_degree_interior_triangles() {
        let cells_x = 10;
        let width = 0.1;
        let dx = width / cells_x as f64;
        let cells_y = 8;
        let height = dx * 3f64.sqrt() / 2.0 * cells_y as f64;
        let mesh = generate(&PatchParams { width_m: width, height_m: height, cells_x, cells_y, jitter: 0.0, seed: 0 });
        let sixty = mesh
            .triangles
            .iter()
            .filter(|t| {
                let [a, b, c] = t.map(|v| mesh.positions[v as usize]);
                (crate::math::triangle_min_angle_deg(&a, &b, &c) - 60.0).abs() < 1e-6
            })
            .count();
        // All but the half-cells at the two straight sides are equilateral.
        assert_eq!(sixty, mesh.triangles.len() - 2 * (cells_y as usize));
    }

    #[test]
    fn same_seed_same_mesh() {
        assert_eq!(generate(&params(0.25)), generate(&params(0.25)));
        assert_ne!(generate(&params(0.25)).positions, generate(&PatchParams { seed: 4, ..params(0.25) }).positions);
    }
}
