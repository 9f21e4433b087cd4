//! Closed surface meshes → label volumes: a voxel is inside when its centre is inside
//! the surface (ray parity along +z, one ray per column of voxel centres).
//!
//! The mesh is welded first (vertices at the same position become one), then split into
//! connected parts; parts that are not closed (an edge used by other than two
//! triangles) or enclose no volume are dropped and reported, since parity is only
//! meaningful for closed surfaces. Ties where a ray passes exactly through an edge or a
//! vertex are broken by a top-left rule on canonically ordered edges, so a crossing is
//! counted exactly once.

use std::collections::BTreeMap;

use super::LabelVolume;
use crate::geometry::TriMesh;
use crate::math::Vec3;

/// What voxelization kept and dropped.
#[derive(Debug, Clone, PartialEq)]
pub struct VoxelizeReport {
    pub parts_kept: usize,
    /// Parts dropped: (triangles, why).
    pub parts_dropped: Vec<(usize, String)>,
    pub voxels_inside: usize,
}

/// Voxelizes the inside of `mesh` (positions in m) with cubic voxels of `voxel_m`,
/// giving the inside voxels `label`. The volume covers the mesh plus one empty voxel
/// on every side.
pub fn voxelize(mesh: &TriMesh, voxel_m: f64, label: u16, max_voxels: usize) -> Result<(LabelVolume, VoxelizeReport), String> {
    if !(voxel_m.is_finite() && voxel_m > 0.0) {
        return Err(format!("the voxel size must be positive, got {voxel_m} m"));
    }
    let welded = weld(mesh);
    let (triangles, report) = closed_parts(&welded)?;
    let mut lo = Vec3::repeat(f64::INFINITY);
    let mut hi = Vec3::repeat(f64::NEG_INFINITY);
    for t in &triangles {
        for &v in t {
            lo = lo.inf(&welded.positions[v as usize]);
            hi = hi.sup(&welded.positions[v as usize]);
        }
    }
    let extent = hi - lo;
    let dims = [0, 1, 2].map(|a| (extent[a] / voxel_m).floor() as usize + 3);
    let total = dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d)).unwrap_or(usize::MAX);
    if total > max_voxels {
        return Err(format!(
            "a {voxel_m} m voxel gives {dims:?} = {total} voxels around the mesh ({:.4} × {:.4} × {:.4} m); at most {max_voxels} are allowed: use a larger voxel size",
            extent.x, extent.y, extent.z
        ));
    }
    // Centre the grid on the mesh so the margins are even.
    let used = Vec3::new((dims[0] - 1) as f64, (dims[1] - 1) as f64, (dims[2] - 1) as f64) * voxel_m;
    let origin = (lo + hi) * 0.5 - used * 0.5;
    let mut volume = LabelVolume::new(dims, [voxel_m; 3], origin);

    // Crossings per column (i, j): the z of every triangle the column's ray passes through.
    let mut crossings: Vec<Vec<f64>> = vec![Vec::new(); dims[0] * dims[1]];
    for t in &triangles {
        let p = t.map(|v| (welded.positions[v as usize] - origin) / voxel_m);
        let (min_x, max_x) = (p.iter().map(|q| q.x).fold(f64::INFINITY, f64::min), p.iter().map(|q| q.x).fold(f64::NEG_INFINITY, f64::max));
        let (min_y, max_y) = (p.iter().map(|q| q.y).fold(f64::INFINITY, f64::min), p.iter().map(|q| q.y).fold(f64::NEG_INFINITY, f64::max));
        let area = cross2(p[1].x - p[0].x, p[1].y - p[0].y, p[2].x - p[0].x, p[2].y - p[0].y);
        if area == 0.0 {
            continue; // vertical in projection: its neighbours carry the crossing
        }
        for j in min_y.ceil().max(0.0) as usize..=(max_y.floor().min((dims[1] - 1) as f64)).max(-1.0) as usize {
            for i in min_x.ceil().max(0.0) as usize..=(max_x.floor().min((dims[0] - 1) as f64)).max(-1.0) as usize {
                let (x, y) = (i as f64, j as f64);
                if let Some(z) = crossing(&p, &t.map(|v| welded.positions[v as usize]), x, y, area) {
                    crossings[i + dims[0] * j].push(z);
                }
            }
        }
    }
    let mut inside = 0;
    for j in 0..dims[1] {
        for i in 0..dims[0] {
            let column = &mut crossings[i + dims[0] * j];
            if column.is_empty() {
                continue;
            }
            column.sort_by(f64::total_cmp);
            for k in 0..dims[2] {
                let below = column.partition_point(|&z| z < k as f64);
                if below % 2 == 1 {
                    volume.set(i, j, k, label);
                    inside += 1;
                }
            }
        }
    }
    Ok((volume, VoxelizeReport { voxels_inside: inside, ..report }))
}

fn cross2(ax: f64, ay: f64, bx: f64, by: f64) -> f64 {
    ax * by - ay * bx
}

/// Where the vertical line through (x, y) crosses triangle `p` (grid units), if it does.
/// `original` are the same vertices in metres: each edge function is evaluated from its
/// endpoints in a canonical order, so the two triangles sharing an edge get exactly
/// opposite values, and a point on the edge goes to exactly one of them (top-left rule
/// on the counter-clockwise traversal).
fn crossing(p: &[Vec3; 3], original: &[Vec3; 3], x: f64, y: f64, area: f64) -> Option<f64> {
    let order = if area > 0.0 { [0, 1, 2] } else { [0, 2, 1] };
    let key = |q: &Vec3| (q.x, q.y, q.z);
    let mut w = [0.0; 3];
    for e in 0..3 {
        let (a, b, c) = (order[e], order[(e + 1) % 3], order[(e + 2) % 3]);
        let swapped = key(&original[a]).partial_cmp(&key(&original[b])) == Some(std::cmp::Ordering::Greater);
        let (u, v) = if swapped { (p[b], p[a]) } else { (p[a], p[b]) };
        let canonical = cross2(v.x - u.x, v.y - u.y, x - u.x, y - u.y);
        // Positive on the left of a→b, the inside of the counter-clockwise triangle.
        let value = if swapped { -canonical } else { canonical };
        if value == 0.0 {
            let sign = if swapped { -1.0 } else { 1.0 };
            let (dx, dy) = (sign * (v.x - u.x), sign * (v.y - u.y));
            let owner = dy > 0.0 || (dy == 0.0 && dx < 0.0);
            if !owner {
                return None;
            }
        } else if value < 0.0 {
            return None;
        }
        w[c] = value.max(0.0);
    }
    let sum = w[0] + w[1] + w[2];
    if sum <= 0.0 {
        return None;
    }
    Some((w[0] * p[0].z + w[1] * p[1].z + w[2] * p[2].z) / sum)
}

/// Merges vertices at exactly the same position (files often repeat them per face).
pub fn weld(mesh: &TriMesh) -> TriMesh {
    let mut index: BTreeMap<[u64; 3], u32> = BTreeMap::new();
    let mut map = Vec::with_capacity(mesh.positions.len());
    let mut positions = Vec::new();
    for p in &mesh.positions {
        let key = [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
        let id = *index.entry(key).or_insert_with(|| {
            positions.push(*p);
            (positions.len() - 1) as u32
        });
        map.push(id);
    }
    let triangles = mesh
        .triangles
        .iter()
        .map(|t| t.map(|v| map[v as usize]))
        .filter(|t| t[0] != t[1] && t[1] != t[2] && t[0] != t[2])
        .collect();
    TriMesh { positions, triangles }
}

/// The triangles of the closed parts of the mesh, and what was dropped.
fn closed_parts(mesh: &TriMesh) -> Result<(Vec<[u32; 3]>, VoxelizeReport), String> {
    let n = mesh.positions.len();
    let mut sets = crate::union_find::UnionFind::new(n);
    for t in &mesh.triangles {
        sets.union(t[0] as usize, t[1] as usize);
        sets.union(t[0] as usize, t[2] as usize);
    }
    let mut parts: BTreeMap<usize, Vec<[u32; 3]>> = BTreeMap::new();
    for t in &mesh.triangles {
        parts.entry(sets.find(t[0] as usize)).or_default().push(*t);
    }
    let mut kept = Vec::new();
    let mut report = VoxelizeReport { parts_kept: 0, parts_dropped: Vec::new(), voxels_inside: 0 };
    let volumes: Vec<f64> = parts.values().map(|tris| signed_volume(&mesh.positions, tris).abs()).collect();
    let largest = volumes.iter().copied().fold(0.0, f64::max);
    for ((_, tris), volume) in parts.into_iter().zip(volumes) {
        let mut edges: Vec<(u32, u32)> = tris.iter().flat_map(|t| (0..3).map(move |k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3])))).collect();
        edges.sort_unstable();
        let open = edges.chunk_by(|a, b| a == b).find(|run| run.len() != 2);
        if let Some(run) = open {
            report.parts_dropped.push((tris.len(), format!("not closed: edge {}–{} is used by {} triangle(s)", run[0].0, run[0].1, run.len())));
        } else if volume <= 1e-9 * largest || volume == 0.0 {
            report.parts_dropped.push((tris.len(), "encloses no volume".into()));
        } else {
            report.parts_kept += 1;
            kept.extend(tris);
        }
    }
    if kept.is_empty() {
        let why: Vec<String> = report.parts_dropped.iter().map(|(n, why)| format!("{n} triangles: {why}")).collect();
        return Err(format!("the mesh has no closed part to voxelize ({})", why.join("; ")));
    }
    Ok((kept, report))
}

fn signed_volume(positions: &[Vec3], tris: &[[u32; 3]]) -> f64 {
    tris.iter()
        .map(|t| {
            let [a, b, c] = t.map(|v| positions[v as usize]);
            a.dot(&b.cross(&c)) / 6.0
        })
        .sum()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A closed UV sphere of radius r.
    fn sphere(r: f64, rings: usize, segments: usize) -> TriMesh {
        let mut m = TriMesh::default();
        m.positions.push(Vec3::new(0.0, 0.0, r));
        for i in 1..rings {
            let theta = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segments {
                let phi = 2.0 * std::f64::consts::PI * j as f64 / segments as f64;
                m.positions.push(Vec3::new(r * theta.sin() * phi.cos(), r * theta.sin() * phi.sin(), r * theta.cos()));
            }
        }
        m.positions.push(Vec3::new(0.0, 0.0, -r));
        let ring = |i: usize, j: usize| (1 + (i - 1) * segments + j % segments) as u32;
        let bottom = (m.positions.len() - 1) as u32;
        for j in 0..segments {
            m.triangles.push([0, ring(1, j), ring(1, j + 1)]);
            m.triangles.push([bottom, ring(rings - 1, j + 1), ring(rings - 1, j)]);
        }
        for i in 1..rings - 1 {
            for j in 0..segments {
                m.triangles.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
                m.triangles.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
            }
        }
        m
    }

    #[test]
    fn a_sphere_fills_its_volume() {
        let r = 0.02;
        let (v, report) = voxelize(&sphere(r, 48, 96), 0.001, 3, 1 << 24).unwrap();
        let expected = 4.0 / 3.0 * std::f64::consts::PI * r * r * r;
        let got = report.voxels_inside as f64 * 1e-9;
        assert!((got / expected - 1.0).abs() < 0.02, "{got} vs {expected}");
        assert_eq!(v.count(3), report.voxels_inside);
        // The centre is inside, the corners outside.
        let c = v.dims.map(|d| d / 2);
        assert_eq!(v.get(c[0], c[1], c[2]), 3);
        assert_eq!(v.get(0, 0, 0), 0);
    }

    #[test]
    fn a_cube_aligned_with_voxel_centres_counts_each_crossing_once() {
        // Faces exactly through voxel centres and rays exactly through edges and vertices.
        let mut m = TriMesh::default();
        for z in [0.0, 4.0] {
            for y in [0.0, 4.0] {
                for x in [0.0, 4.0] {
                    m.positions.push(Vec3::new(x, y, z) * 1e-3);
                }
            }
        }
        let quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]];
        for q in quads {
            m.triangles.push([q[0], q[1], q[2]]);
            m.triangles.push([q[0], q[2], q[3]]);
        }
        let (v, report) = voxelize(&m, 1e-3, 1, 1 << 20).unwrap();
        // Every column inside the square has the same count: no double or missed crossings.
        let counts: Vec<usize> = (0..v.dims[1]).flat_map(|j| (0..v.dims[0]).map(move |i| (i, j))).map(|(i, j)| (0..v.dims[2]).filter(|&k| v.get(i, j, k) == 1).count()).filter(|&n| n > 0).collect();
        assert!(counts.iter().all(|&n| n == counts[0]), "{counts:?}");
        assert!(report.voxels_inside > 0);
    }

    #[test]
    fn open_parts_are_dropped_and_reported() {
        let mut m = sphere(0.01, 8, 16);
        let n = m.positions.len() as u32;
        m.positions.extend([Vec3::new(1.0, 0.0, 0.0), Vec3::new(1.1, 0.0, 0.0), Vec3::new(1.0, 0.1, 0.0)]);
        m.triangles.push([n, n + 1, n + 2]);
        let (_, report) = voxelize(&m, 0.002, 1, 1 << 24).unwrap();
        assert_eq!(report.parts_kept, 1);
        assert_eq!(report.parts_dropped.len(), 1);
        assert!(report.parts_dropped[0].1.contains("not closed"));
        let open = TriMesh { positions: m.positions[n as usize..].to_vec(), triangles: vec![[0, 1, 2]] };
        assert!(voxelize(&open, 0.002, 1, 1 << 24).unwrap_err().contains("no closed part"));
    }
}
