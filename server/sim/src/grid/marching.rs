//! The marching-cubes case table, generated rather than typed in.
//!
//! A cube's corners are 8 voxel centres; a corner is "inside" when its voxel holds
//! material. On each face, the edges whose two corners differ carry a surface vertex
//! (at the edge's midpoint: the face between the two voxels), and are joined in pairs
//! by segments; on a face with two diagonal inside corners (the ambiguous case) each
//! inside corner is cut off on its own, which matches the 6-connectivity the grid uses
//! for its components and, since both cubes sharing a face see the same corners,
//! makes the surface watertight. The segments form closed polygons on the cube's
//! boundary; each is oriented so that its normal points from the inside corners to
//! the outside ones and is fan-triangulated.

use std::sync::OnceLock;

/// Cube edges as (lower corner, upper corner, axis); corner bits are (x, y, z).
pub const EDGES: [(usize, usize, usize); 12] = {
    let mut edges = [(0, 0, 0); 12];
    let mut i = 0;
    let mut axis = 0;
    while axis < 3 {
        let mut c = 0;
        while c < 8 {
            if (c >> axis) & 1 == 0 {
                edges[i] = (c, c | (1 << axis), axis);
                i += 1;
            }
            c += 1;
        }
        axis += 1;
    }
    edges
};

fn edge_between(a: usize, b: usize) -> usize {
    EDGES.iter().position(|&(p, q, _)| (p, q) == (a.min(b), a.max(b))).expect("corners share an edge")
}

fn corner_position(c: usize) -> [f64; 3] {
    [(c & 1) as f64, ((c >> 1) & 1) as f64, ((c >> 2) & 1) as f64]
}

fn edge_midpoint(e: usize) -> [f64; 3] {
    let (a, b, _) = EDGES[e];
    let (pa, pb) = (corner_position(a), corner_position(b));
    [0, 1, 2].map(|k| (pa[k] + pb[k]) / 2.0)
}

/// Triangles (as cube-edge triples, counter-clockwise seen from outside) for every
/// configuration of inside corners (bit c = corner c inside).
pub fn table() -> &'static [Vec<[u8; 3]>; 256] {
    static TABLE: OnceLock<[Vec<[u8; 3]>; 256]> = OnceLock::new();
    TABLE.get_or_init(|| std::array::from_fn(case))
}

fn case(config: usize) -> Vec<[u8; 3]> {
    let inside = |c: usize| (config >> c) & 1 == 1;
    let mut neighbours: [Vec<usize>; 12] = Default::default();
    for axis in 0..3 {
        for side in 0..2 {
            let (u, v) = ((axis + 1) % 3, (axis + 2) % 3);
            let base = side << axis;
            let corners = [base, base | (1 << u), base | (1 << u) | (1 << v), base | (1 << v)];
            let face_edges: Vec<usize> = (0..4).map(|k| edge_between(corners[k], corners[(k + 1) % 4])).collect();
            let crossing: Vec<usize> = (0..4).filter(|&k| inside(corners[k]) != inside(corners[(k + 1) % 4])).collect();
            let mut segments = Vec::new();
            match crossing.len() {
                0 => {}
                2 => segments.push((face_edges[crossing[0]], face_edges[crossing[1]])),
                4 => {
                    for k in 0..4 {
                        if inside(corners[k]) {
                            segments.push((face_edges[(k + 3) % 4], face_edges[k]));
                        }
                    }
                }
                _ => unreachable!("a face has an even number of crossings"),
            }
            for (a, b) in segments {
                neighbours[a].push(b);
                neighbours[b].push(a);
            }
        }
    }
    let mut visited = [false; 12];
    let mut triangles = Vec::new();
    for start in 0..12 {
        if visited[start] || neighbours[start].is_empty() {
            continue;
        }
        debug_assert_eq!(neighbours[start].len(), 2);
        let mut polygon = vec![start];
        visited[start] = true;
        let mut previous = start;
        let mut current = neighbours[start][0];
        while current != start {
            polygon.push(current);
            visited[current] = true;
            let next = if neighbours[current][0] == previous { neighbours[current][1] } else { neighbours[current][0] };
            previous = current;
            current = next;
        }
        // Orientation: Newell normal against the inside → outside directions of its edges.
        let points: Vec<[f64; 3]> = polygon.iter().map(|&e| edge_midpoint(e)).collect();
        let mut normal = [0.0; 3];
        for i in 0..points.len() {
            let (p, q) = (points[i], points[(i + 1) % points.len()]);
            normal[0] += (p[1] - q[1]) * (p[2] + q[2]);
            normal[1] += (p[2] - q[2]) * (p[0] + q[0]);
            normal[2] += (p[0] - q[0]) * (p[1] + q[1]);
        }
        let mut outward = [0.0; 3];
        for &e in &polygon {
            let (a, b, axis) = EDGES[e];
            outward[axis] += if inside(a) { 1.0 } else { -1.0 };
            let _ = b;
        }
        if normal[0] * outward[0] + normal[1] * outward[1] + normal[2] * outward[2] < 0.0 {
            polygon.reverse();
        }
        for k in 1..polygon.len() - 1 {
            triangles.push([polygon[0] as u8, polygon[k] as u8, polygon[k + 1] as u8]);
        }
    }
    triangles
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn simple_cases() {
        assert!(table()[0].is_empty() && table()[255].is_empty());
        // One inside corner: one triangle facing away from it.
        let t = table()[1][0];
        let p = t.map(|e| edge_midpoint(e as usize));
        let n = [
            (p[1][1] - p[0][1]) * (p[2][2] - p[0][2]) - (p[1][2] - p[0][2]) * (p[2][1] - p[0][1]),
            (p[1][2] - p[0][2]) * (p[2][0] - p[0][0]) - (p[1][0] - p[0][0]) * (p[2][2] - p[0][2]),
            (p[1][0] - p[0][0]) * (p[2][1] - p[0][1]) - (p[1][1] - p[0][1]) * (p[2][0] - p[0][0]),
        ];
        assert!(n.iter().all(|&c| c > 0.0), "the normal points away from corner 0: {n:?}");
        // Half the cube inside (z = 0 face): a quad, two triangles.
        assert_eq!(table()[0b0000_1111].len(), 2);
        // Two diagonal inside corners on a face: two separate triangles.
        assert_eq!(table()[0b0000_1001].len(), 2);
    }
}
