//! Supports: the regions of a branched grid held in place (`model.branched-grid.fixed`),
//! by one of two rules (`model.branched-grid.support`).
//!
//! `coarse-nodes` (the default) holds the level's nodes inside each region. At level 0
//! they are the voxel corners the region takes; a coarse element of 2^L voxels a side
//! has nodes only at its cell's corners, so coarser levels hold fewer nodes, farther
//! apart (the liver's posterior box: 7,701 nodes at level 0, 75 at level 3).
//!
//! `embedded` keeps level 0's support at every level. A region holds the level-0
//! points inside it (the corners of the voxels it takes: in its box, on its side of the
//! body, or of its labels). A held point at a corner of its element's cell holds that
//! node; any other, where the region meets material it does not hold (a corner of a
//! voxel the region holds only partly), is embedded in its element by its trilinear
//! weights — the interpolation the condensation builds the element with — and a stiff
//! spring holds the interpolated point at its rest position. A piece of the body that
//! a region holds wholly (a small organ of a label map inside a held box) meets no such
//! voxel: all its held points that are no cell corner get springs, or it would be held
//! only at the few cell corners its voxels reach and turn about them. Level 0 is unchanged
//! (every held point is a node there). Measured, it makes coarse levels stiffer, not
//! more accurate: a trilinear element cut by the support cannot bend within itself as
//! the fine mesh does (docs/branched-grid.md, "Supports").
//!
//! The spring force on the element's nodes is `f_i = −k w_i (Σ_j w_j x_j − p)`; its
//! stiffness `k w_i w_j I` enters the implicit system within the element's own blocks
//! (no new pattern), and with it `−h k w_i (Σ_j w_j v_j)` on the right-hand side (the
//! spring at the step's end, linearised like the contacts). A point is found through
//! its voxel, so a cut that re-splits the elements finds it in its new element; a
//! point whose voxel was cut away holds nothing more.

use std::collections::{BTreeMap, BTreeSet};

use super::hex::trilinear_weights;
use super::model::Frame;
use super::topology::{NONE, Topology};
use crate::math::{Matrix3, Vec3};
use crate::scene::{BranchedGridSpec, GridFixedSpec, Scene, SceneError, SupportSpec};

/// The spring of an embedded point against the stiffness of one voxel of its material
/// (E × the voxel's mean side): stiff enough that the held point moves about 1 % of what
/// the body around it does, soft enough that the conjugate gradient's iterations barely
/// change. Each point's is its own material's: a spring as stiff as the stiffest
/// material on a 50 times softer one (the abdomen's fat under its skin) made the
/// static solve at level 3 crawl (a relative residual of 4e-7 after 5,000 V-cycles).
pub const SUPPORT_STIFFNESS_PER_VOXEL: f64 = 100.0;

/// A level-0 point of a support inside a coarse element, held by a spring.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct EmbeddedPoint {
    /// A voxel the point is a corner of: its element is the point's element.
    pub voxel: u32,
    /// Trilinear weights of the point in its element's cell.
    pub weights: [f64; 8],
    /// Where the spring holds it (the grid's frame), m.
    pub rest: Vec3,
    /// Its spring's stiffness, N/m.
    pub stiffness_n_per_m: f64,
}

/// The embedded points of a grid's supports.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Supports {
    pub points: Vec<EmbeddedPoint>,
}

impl Supports {
    /// Each live embedded point with its element: (element, point).
    pub fn live<'a>(&'a self, topo: &'a Topology) -> impl Iterator<Item = (usize, &'a EmbeddedPoint)> + 'a {
        self.points.iter().filter_map(|p| {
            let e = topo.voxel_element[p.voxel as usize];
            (e != NONE && topo.elements.alive[e as usize]).then_some((e as usize, p))
        })
    }

    /// Adds the springs' forces to `force`: at the end of a step of h, linearised,
    /// `−k (w·x − p) − h k (w·v)` with the nodes' positions and velocities now.
    pub fn add_forces(&self, topo: &Topology, h: f64, force: &mut [Vec3]) {
        for (e, p) in self.live(topo) {
            let nodes = &topo.elements.nodes[e];
            let at: Vec3 = (0..8).map(|k| topo.nodes.x[nodes[k] as usize] * p.weights[k]).sum();
            let moving: Vec3 = (0..8).map(|k| topo.nodes.v[nodes[k] as usize] * p.weights[k]).sum();
            let pull = -(at - p.rest + moving * h) * p.stiffness_n_per_m;
            for k in 0..8 {
                force[nodes[k] as usize] += pull * p.weights[k];
            }
        }
    }

    /// The springs' stiffness blocks, scaled: calls `add(element, i, j, block)` for the
    /// 8 × 8 corner pairs of each live point's element.
    pub fn for_each_block(&self, topo: &Topology, scale: f64, mut add: impl FnMut(usize, usize, usize, Matrix3<f64>)) {
        for (e, p) in self.live(topo) {
            for i in 0..8 {
                for j in 0..8 {
                    let k = scale * p.stiffness_n_per_m * p.weights[i] * p.weights[j];
                    if k != 0.0 {
                        add(e, i, j, Matrix3::from_diagonal_element(k));
                    }
                }
            }
        }
    }

    /// `out += K_s u` (the springs' stiffness times a displacement field).
    pub fn add_stiffness_times(&self, topo: &Topology, u: &[Vec3], out: &mut [Vec3]) {
        for (e, p) in self.live(topo) {
            let nodes = &topo.elements.nodes[e];
            let at: Vec3 = (0..8).map(|k| u[nodes[k] as usize] * p.weights[k]).sum::<Vec3>() * p.stiffness_n_per_m;
            for k in 0..8 {
                out[nodes[k] as usize] += at * p.weights[k];
            }
        }
    }

    /// Adds the springs' share of each node's diagonal stiffness.
    pub fn add_diagonal(&self, topo: &Topology, diagonal: &mut [Vec3]) {
        for (e, p) in self.live(topo) {
            for k in 0..8 {
                diagonal[topo.elements.nodes[e][k] as usize] += Vec3::repeat(p.stiffness_n_per_m * p.weights[k] * p.weights[k]);
            }
        }
    }
}

/// Holds the scene's regions by the scene's rule. Errors name a region that holds
/// nothing.
pub fn hold_regions(scene: &Scene, spec: &BranchedGridSpec, topo: &mut Topology, frame: &Frame) -> Result<(), SceneError> {
    let holds = match spec.support {
        SupportSpec::CoarseNodes => hold_coarse_nodes(spec, topo, frame),
        SupportSpec::Embedded => hold_embedded(spec, topo, frame),
    };
    match holds.iter().position(|&held| held == 0) {
        Some(i) => Err(SceneError::new(
            &scene.origin,
            format!("model.branched-grid.fixed[{i}]"),
            match spec.support {
                SupportSpec::CoarseNodes => "holds no node: check the region against the body's position (with \"centre\": true the body is centred on the origin); at a coarse level a small region may hold no node, where \"support\": \"embedded\" holds it",
                SupportSpec::Embedded => "holds no node: check the region against the body's position (with \"centre\": true the body is centred on the origin)",
            },
        )),
        None => Ok(()),
    }
}

/// The level's nodes in each region; returns how many each region holds.
fn hold_coarse_nodes(spec: &BranchedGridSpec, topo: &mut Topology, frame: &Frame) -> Vec<usize> {
    let (lo, hi) = super::build::rest_bounds(topo);
    let mut holds = Vec::new();
    for fixed in &spec.fixed {
        let mut held = 0;
        let mut hold = |topo: &mut Topology, n: usize| {
            held += usize::from(!topo.nodes.fixed[n]);
            topo.nodes.fixed[n] = true;
        };
        match fixed {
            GridFixedSpec::Box { min_m, max_m } => {
                for n in 0..topo.nodes.len() {
                    let w = frame.to_world(&topo.nodes.rest[n]);
                    if topo.nodes.alive[n] && (0..3).all(|a| w[a] >= min_m[a].get() && w[a] <= max_m[a].get()) {
                        hold(topo, n);
                    }
                }
            }
            GridFixedSpec::Side { side } => {
                let (axis, target) = side_plane(side, lo.as_slice(), hi.as_slice());
                for n in 0..topo.nodes.len() {
                    if topo.nodes.alive[n] && (topo.nodes.rest[n][axis] - target).abs() < 1e-9 {
                        hold(topo, n);
                    }
                }
            }
            GridFixedSpec::Labels { labels } => {
                let indices = material_indices(spec, labels);
                for v in 0..topo.material.len() {
                    if indices.contains(&topo.material[v]) {
                        let e = topo.voxel_element[v] as usize;
                        for k in 0..8 {
                            let node = topo.elements.nodes[e][k] as usize;
                            hold(topo, node);
                        }
                    }
                }
            }
        }
        holds.push(held);
    }
    holds
}

/// The axis of a side ("-x" … "+z") and the coordinate of that face of `lo`–`hi`.
fn side_plane<T: Copy>(side: &str, lo: &[T], hi: &[T]) -> (usize, T) {
    let axis = match &side[1..] {
        "x" => 0,
        "y" => 1,
        _ => 2,
    };
    (axis, if side.starts_with('-') { lo[axis] } else { hi[axis] })
}

/// The material indices (as `Topology::material` stores them) of `labels`.
fn material_indices(spec: &BranchedGridSpec, labels: &[crate::quantity::LabelValue]) -> Vec<u16> {
    labels.iter().filter_map(|l| spec.materials.iter().position(|m| m.label == *l).map(|i| i as u16 + 1)).collect()
}

/// Level 0's support at any level: a held level-0 point at a corner of its element's
/// cell fixes that node; one where the region meets material it does not hold becomes
/// an embedded point of `topo.supports`. Returns how many points each region holds.
fn hold_embedded(spec: &BranchedGridSpec, topo: &mut Topology, frame: &Frame) -> Vec<usize> {
    let layout = topo.layout.clone();
    let spacing = Vec3::from(layout.spacing_m);
    let point_rest = |p: [usize; 3]| Vec3::new(p[0] as f64, p[1] as f64, p[2] as f64).component_mul(&spacing);
    let voxel_side = (spacing.x + spacing.y + spacing.z) / 3.0;
    // Each point's spring after the material of the voxel it was found through.
    let spring = |material: u16| SUPPORT_STIFFNESS_PER_VOXEL * spec.materials[usize::from(material) - 1].young_pa.get() * voxel_side;
    let live_voxels: Vec<usize> = (0..topo.material.len()).filter(|&v| topo.material[v] != 0 && topo.voxel_element[v] != NONE).collect();
    let corners = |v: usize| {
        let g = layout.voxel_coords(v);
        (0..8usize).map(move |n| [g[0] + (n & 1), g[1] + ((n >> 1) & 1), g[2] + ((n >> 2) & 1)])
    };
    // The body's level-0 extent (a side region holds the points on one of its faces).
    let (mut lo, mut hi) = ([usize::MAX; 3], [0usize; 3]);
    for &v in &live_voxels {
        for p in corners(v) {
            for a in 0..3 {
                lo[a] = lo[a].min(p[a]);
                hi[a] = hi[a].max(p[a]);
            }
        }
    }
    let mut embedded: BTreeSet<([usize; 3], u32)> = BTreeSet::new();
    let mut points = Vec::new();
    // Held points inside the region (every corner of their voxel held) that are no cell
    // corner: springs only for a piece the region holds wholly (below).
    let mut inner = BTreeMap::new();
    let mut holds = Vec::new();
    for region in &spec.fixed {
        let labelled = match region {
            GridFixedSpec::Labels { labels } => material_indices(spec, labels),
            _ => Vec::new(),
        };
        let held_by = |v: usize, p: [usize; 3]| -> bool {
            match region {
                GridFixedSpec::Box { min_m, max_m } => {
                    let w = frame.to_world(&point_rest(p));
                    (0..3).all(|a| w[a] >= min_m[a].get() && w[a] <= max_m[a].get())
                }
                GridFixedSpec::Side { side } => {
                    let (axis, target) = side_plane(side, &lo, &hi);
                    p[axis] == target
                }
                GridFixedSpec::Labels { .. } => labelled.contains(&topo.material[v]),
            }
        };
        let mut held: BTreeSet<[usize; 3]> = BTreeSet::new();
        for &v in &live_voxels {
            let e = topo.voxel_element[v];
            // Only where the region meets material it does not hold does the support
            // reach the free body: a voxel whose corners it holds partly.
            let partly = corners(v).any(|p| !held_by(v, p));
            for p in corners(v) {
                if !held_by(v, p) {
                    continue;
                }
                held.insert(p);
                let cell = topo.elements.cell[e as usize] as usize;
                let rest = point_rest(p);
                let weights = trilinear_weights(topo.cell_coordinates(cell, rest));
                match weights.iter().position(|&w| w > 1.0 - 1e-9) {
                    Some(corner) => topo.nodes.fixed[topo.elements.nodes[e as usize][corner] as usize] = true,
                    None if partly && embedded.insert((p, e)) => points.push(EmbeddedPoint { voxel: v as u32, weights, rest, stiffness_n_per_m: spring(topo.material[v]) }),
                    None if !partly => {
                        inner.insert((p, e), EmbeddedPoint { voxel: v as u32, weights, rest, stiffness_n_per_m: spring(topo.material[v]) });
                    }
                    None => {}
                }
            }
        }
        holds.push(held.len());
    }
    inner.retain(|key, _| !embedded.contains(key));
    points.extend(inner_points_of_unsprung_pieces(topo, &points, inner.into_values()));
    // A point whose weights all fall on fixed nodes is held already.
    points.retain(|p| {
        let nodes = &topo.elements.nodes[topo.voxel_element[p.voxel as usize] as usize];
        (0..8).any(|k| p.weights[k] > 1e-12 && !topo.nodes.fixed[nodes[k] as usize])
    });
    topo.supports = Supports { points };
    holds
}

/// The inner points of the pieces (elements connected through shared nodes) that hold
/// no spring. A piece lying wholly in a region has no voxel the region holds partly, so
/// its only holds would be the cell corners its voxels reach: a small piece of a label
/// map (one coarse element filled in part) can be held there at one or two nodes and
/// turn about them. Its inner points hold it as level 0 does.
fn inner_points_of_unsprung_pieces(topo: &Topology, springs: &[EmbeddedPoint], inner: impl Iterator<Item = EmbeddedPoint>) -> Vec<EmbeddedPoint> {
    let mut pieces = pieces_of_nodes(topo);
    let mut piece_of = |p: &EmbeddedPoint| pieces.find(topo.elements.nodes[topo.voxel_element[p.voxel as usize] as usize][0] as usize);
    let sprung: BTreeSet<usize> = springs.iter().map(&mut piece_of).collect();
    inner.filter(|p| !sprung.contains(&piece_of(p))).collect()
}

/// Nodes joined through the live elements they share.
fn pieces_of_nodes(topo: &Topology) -> crate::union_find::UnionFind {
    let mut pieces = crate::union_find::UnionFind::new(topo.nodes.len());
    for e in (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]) {
        let nodes = &topo.elements.nodes[e];
        for k in 1..8 {
            pieces.union(nodes[0] as usize, nodes[k] as usize);
        }
    }
    pieces
}

/// The number of held level-0 points: fixed nodes and embedded points (what the
/// accuracy report calls held nodes).
pub fn held_count(topo: &Topology) -> usize {
    (0..topo.nodes.len()).filter(|&n| topo.nodes.alive[n] && topo.nodes.fixed[n]).count() + topo.supports.live(topo).count()
}

/// Which nodes belong to a held piece: a set of live elements connected through shared
/// nodes that contains a fixed node or an embedded point's element. A label map's
/// organs need not touch the held region (nothing between them is labelled), and such a
/// free piece has no static equilibrium under a load: the accuracy study leaves it out
/// of the static problem and of the error.
pub fn held_pieces(topo: &Topology) -> Vec<bool> {
    let n = topo.nodes.len();
    let mut pieces = pieces_of_nodes(topo);
    let mut held_root = vec![false; n];
    for i in (0..n).filter(|&i| topo.nodes.alive[i] && topo.nodes.fixed[i]) {
        held_root[pieces.find(i)] = true;
    }
    for (e, _) in topo.supports.live(topo) {
        held_root[pieces.find(topo.elements.nodes[e][0] as usize)] = true;
    }
    (0..n).map(|i| topo.nodes.alive[i] && held_root[pieces.find(i)]).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::grid::condense::{Volumetric, VoxelMatrices};
    use crate::grid::topology::Layout;
    use crate::scene::ModelSpec;

    /// Level 2 (4-voxel cells) of 1 mm voxels: a bar (8 × 4 × 4 voxels) held at its
    /// −x end, and apart from it a blob of 2 × 2 × 1 voxels alone in the cell at
    /// (12, 4, 0), which it fills in part; a second region holds the blob wholly. Of the
    /// blob's held points one is a cell corner: by the corners alone it is held at one
    /// node, about which it would turn.
    fn bar_and_held_blob() -> Topology {
        let (dims, level, spacing) = ([16, 8, 4], 2, [1e-3; 3]);
        let layout = Layout::new(dims, level, spacing);
        let in_bar = |g: [usize; 3]| g[0] < 8 && g[1] < 4;
        let in_blob = |g: [usize; 3]| (12..14).contains(&g[0]) && (4..6).contains(&g[1]) && g[2] == 0;
        let material = (0..dims.iter().product()).map(|v| u16::from(in_bar(layout.voxel_coords(v)) || in_blob(layout.voxel_coords(v)))).collect();
        let mut topo = Topology::build(layout, material, VoxelMatrices::new(spacing, &[(3e4, 0.45, 1000.0)], Volumetric::MeanDilatation));
        let json = r#"{ "name": "held blob", "gravity_m_per_s2": [0, 0, -9.81],
            "model": { "branched-grid": {
                "volume": { "box": { "size_m": [0.016, 0.008, 0.004], "voxel_size_m": 0.001 } },
                "materials": [ { "label": 1, "young_pa": 30000, "density_kg_per_m3": 1000 } ],
                "level": 2, "support": "embedded",
                "fixed": [ { "box": { "min_m": [-0.0005, -1, -1], "max_m": [0.0015, 1, 1] } },
                           { "box": { "min_m": [0.0115, 0.0035, -0.0005], "max_m": [0.0145, 0.0065, 0.0015] } } ] } },
            "tools": [] }"#;
        let scene = Scene::from_json_str(json, "held blob", None).unwrap_or_else(|e| panic!("{e}"));
        let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!() };
        let frame = Frame { rotation: Matrix3::identity(), translation: Vec3::zeros() };
        hold_regions(&scene, spec, &mut topo, &frame).unwrap();
        topo
    }

    #[test]
    fn a_piece_the_region_holds_wholly_is_held_at_its_inner_points() {
        let mut topo = bar_and_held_blob();
        let blob_element = topo.voxel_element[topo.layout.voxel_index([12, 4, 0])] as usize;
        let blob_nodes = topo.elements.nodes[blob_element];
        assert_eq!(blob_nodes.iter().filter(|&&n| topo.nodes.fixed[n as usize]).count(), 1, "one cell corner of the blob is held");
        // The blob's 3 × 3 × 2 held points less that corner are springs.
        let blob_springs = topo.supports.live(&topo).filter(|&(e, _)| e == blob_element).count();
        assert_eq!(blob_springs, 17);
        // So the static problem under gravity is posed (it was singular: the blob turned
        // about its one node), and the held points stay put while the bar sags.
        let loads: Vec<Vec3> = topo.nodes.mass.iter().map(|m| Vec3::new(0.0, 0.0, -9.81 * m)).collect();
        let (_, residual) = crate::grid::solver::solve_static(&mut topo, &loads, 1e-10, 10_000);
        assert!(residual < 1e-8, "converged: {residual:e}");
        let moved = |topo: &Topology, n: usize| (topo.nodes.x[n] - topo.nodes.rest[n]).norm();
        let sag = (0..topo.nodes.len()).map(|n| moved(&topo, n)).fold(0.0, f64::max);
        let blob = blob_nodes.iter().map(|&n| moved(&topo, n as usize)).fold(0.0, f64::max);
        assert!(sag > 1e-5 && blob < 0.01 * sag, "bar sags {sag:e} m, blob moves {blob:e} m");
    }
}
