//! Three-stage cutting (paper Section 2.3) for the mass-spring skin, driven by the
//! blade's motion.
//!
//! While a blade with its cut button held crosses the surface, each time its crossing
//! point has moved `min_advance_m` along the skin the incision grows by one update:
//! stage 1 ([`swept_volume`]) removes what the blade swept since the last update,
//! stage 2 ([`bezier`]) extends the incision's C1 Bézier chain to the new crossing point,
//! stage 3 ([`node_matching`]) stitches the surface back with split lips. The previous
//! update's end vertex is removed by the next one, so the incision's end moves with the
//! tool, and a cut made over many steps has the same structure as one made at once.

pub mod bezier;
pub mod node_matching;
pub mod swept_volume;

use bezier::BezierChain;
use node_matching::{MatchError, MatchInput, match_nodes};
use swept_volume::SweptVolume;

use crate::broad_phase::PointGrid;
use crate::hash::{HashState, StateHasher};
use crate::math::{Vec3, across, barycentric_closest, closest_point_on_triangle, segment_triangle_intersection, triangle_normal};
use crate::msm::state::Topology;
use crate::tool::PlacedTool;
use crate::union_find::UnionFind;

/// Cutting settings resolved against the mesh.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CuttingParams {
    /// Radius of the swept volume, m.
    pub sweep_radius_m: f64,
    /// Blade travel along the skin between incision updates, m.
    pub min_advance_m: f64,
    /// Spacing of the incision's vertices, m (the mean edge length).
    pub vertex_spacing_m: f64,
}

/// One incision (a cut stroke): its curve and its two lips.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Incision {
    pub tool: usize,
    pub curve: BezierChain,
    /// Lip vertex ids along the incision, left and right of the curve (seen from the
    /// surface normal), start to end. A closed start or end vertex is in both.
    pub lips: [Vec<u32>; 2],
}

#[derive(Debug, Clone)]
enum Anchor {
    /// The stroke has begun here and has not cut yet, or its incision ended open here
    /// (on a border) and goes on from this point.
    Start(Vec3),
    /// The incision ends at this vertex (its closed tip), which the next update removes.
    Tip(u32),
}

#[derive(Debug, Clone)]
struct Stroke {
    anchor: Anchor,
    /// The blade part near the surface at the last update (tip side, top side).
    last_blade: (Vec3, Vec3),
    incision: Option<usize>,
    /// Where the blade last crossed the skin, with its part near the surface: when the
    /// stroke ends, the incision is completed up to there.
    last_crossing: Option<(Vec3, (Vec3, Vec3))>,
    /// An update that could not be stitched while the blade cuts on is tried again
    /// further on ([`DEFER_SPAN_ADVANCES`]): the next try waits until the crossing is
    /// this far from the anchor, m (0: no update deferred).
    retry_from_m: f64,
}

/// How far, in `min_advance_m`, an incision's end may trail the blade while its updates
/// cannot be stitched before it falls back to an open hole.
const DEFER_SPAN_ADVANCES: f64 = 3.0;

/// What a step of the cutter did to the skin.
#[derive(Debug, Clone)]
pub(crate) enum CutStep {
    /// Nothing changed: no stroke, the blade not far enough on since the last update,
    /// or an update deferred to be tried again further on.
    Unchanged,
    /// An incision update (or, with [`CutPlan::fallback`], an open hole) to apply.
    Cut(CutPlan),
    /// The stroke ended with a last piece inside the skin that could not be stitched and
    /// was left uncut ([`LastPiece::DropIfInside`]): the incision ends short of where the
    /// blade left. Nothing changed, but the model counts it.
    LastPieceLeftUncut,
}

/// What a cut update changes; the model applies it.
#[derive(Debug, Clone, Default)]
pub(crate) struct CutPlan {
    pub removed_tris: Vec<u32>,
    /// New vertices; ids follow the current node count.
    pub new_vertices: Vec<NewVertex>,
    pub new_triangles: Vec<[u32; 3]>,
    pub incision_length_m: f64,
    pub starts_new_cut: bool,
    /// Stitching failed, and why: the swept area was removed and left open.
    pub fallback: Option<String>,
    pub min_angle_deg: Option<f64>,
}

/// A vertex a cut update creates.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct NewVertex {
    /// Where it is now, m.
    pub position: Vec3,
    /// How fast the skin there moved, m/s.
    pub velocity: Vec3,
    /// The same material point in the reference (imported, in-vivo) configuration, m:
    /// new triangles and springs take their rest geometry from here, so that stitching
    /// an already gaping wound does not create skin.
    pub reference: Vec3,
}

/// Read-only view of the model a cut update needs.
pub(crate) struct CutView<'a> {
    pub x: &'a [Vec3],
    pub v: &'a [Vec3],
    pub x_ref: &'a [Vec3],
    pub topo: &'a Topology,
    pub grid: &'a PointGrid,
    /// Longest edge of the mesh, m (bounds the search around the blade).
    pub max_edge_m: f64,
}

/// Where the blade crosses the surface.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Crossing {
    pub point: Vec3,
    /// Parameter along the blade from its tip, [0, 1].
    pub blade_t: f64,
    /// The live triangle crossed.
    pub triangle: u32,
}

#[derive(Debug, Clone)]
pub(crate) struct Cutter {
    pub params: CuttingParams,
    strokes: Vec<Option<Stroke>>,
    pub incisions: Vec<Incision>,
    /// Scratch for candidate triangles (kept to avoid allocating while the blade is in).
    candidates: Vec<u32>,
}

impl HashState for Cutter {
    /// The strokes in progress and the incisions made (their curves and lips).
    fn hash_state(&self, h: &mut StateHasher) {
        h.write_u64(self.strokes.len() as u64);
        for stroke in &self.strokes {
            let Some(s) = stroke else {
                h.write_u8(0);
                continue;
            };
            h.write_u8(1);
            match s.anchor {
                Anchor::Start(p) => (0u32, p).hash_state(h),
                Anchor::Tip(v) => (1u32, v).hash_state(h),
            }
            (s.last_blade, s.incision, s.last_crossing).hash_state(h);
            // Written only while an update is deferred (the hashes of cuts that never
            // defer one stay what they were before deferring existed).
            if s.retry_from_m > 0.0 {
                s.retry_from_m.hash_state(h);
            }
        }
        h.write_u64(self.incisions.len() as u64);
        for incision in &self.incisions {
            incision.tool.hash_state(h);
            incision.curve.segments.iter().for_each(|b| b.control.hash_state(h));
            incision.lips.hash_state(h);
        }
    }
}

impl Cutter {
    pub fn new(params: CuttingParams, tools: usize) -> Self {
        Self { params, strokes: vec![None; tools], incisions: Vec::new(), candidates: Vec::with_capacity(4096) }
    }

    /// Ends the tool's stroke (blade lifted out, button released or tool away): the
    /// incision is completed up to where the blade last crossed the skin, so that it ends
    /// where the blade left (at the patch's edge, a cut goes all the way through). A last
    /// piece inside the skin that cannot be stitched is left uncut (see [`LastPiece`]).
    pub fn end_stroke(&mut self, tool: usize, view: &CutView, next_vertex_id: u32) -> CutStep {
        let Some((stroke, (point, near))) = self.strokes[tool].take().and_then(|s| s.last_crossing.map(|c| (s, c))) else {
            return CutStep::Unchanged;
        };
        let anchor_point = anchor_position(&stroke.anchor, view);
        // A tiny last piece would only make thin triangles.
        if (point - anchor_point).norm() < 0.25 * self.params.vertex_spacing_m {
            return CutStep::Unchanged;
        }
        let step = self.grow(tool, &stroke, anchor_point, point, near, view, next_vertex_id, LastPiece::DropIfInside);
        self.strokes[tool] = None;
        step
    }

    /// Whether the tool has a stroke under way (its blade has crossed the skin).
    pub fn in_stroke(&self, tool: usize) -> bool {
        self.strokes[tool].is_some()
    }

    /// Follows the blade for one step, given where it crosses the skin
    /// ([`Self::crossing`]); returns a topology change when the incision grows. With
    /// `advance` false (the blade is not cutting: its edge does not lead) the stroke is
    /// kept but the incision neither grows nor records the crossing.
    pub fn update(&mut self, tool: usize, blade: &PlacedTool, hit: Option<Crossing>, advance: bool, view: &CutView, next_vertex_id: u32) -> CutStep {
        let Some(hit) = hit else {
            return self.end_stroke(tool, view, next_vertex_id);
        };
        let near = self.blade_near_surface(blade, hit.blade_t, view);
        let Some(stroke) = self.strokes[tool].as_mut() else {
            self.strokes[tool] = Some(Stroke { anchor: Anchor::Start(hit.point), last_blade: near, incision: None, last_crossing: None, retry_from_m: 0.0 });
            return CutStep::Unchanged;
        };
        if !advance {
            return CutStep::Unchanged;
        }
        stroke.last_crossing = Some((hit.point, near));
        let anchor_point = anchor_position(&stroke.anchor, view);
        if (hit.point - anchor_point).norm() < self.params.min_advance_m.max(stroke.retry_from_m) {
            return CutStep::Unchanged;
        }
        let stroke = stroke.clone();
        self.grow(tool, &stroke, anchor_point, hit.point, near, view, next_vertex_id, LastPiece::No)
    }

    /// One incision update: the three stages from the stroke's anchor to `point`.
    #[allow(clippy::too_many_arguments)]
    fn grow(
        &mut self,
        tool: usize,
        stroke: &Stroke,
        anchor_point: Vec3,
        point: Vec3,
        near: (Vec3, Vec3),
        view: &CutView,
        next_vertex_id: u32,
        last: LastPiece,
    ) -> CutStep {
        let mut chain = stroke.incision.map(|i| self.incisions[i].curve.clone()).unwrap_or_default();
        let segment = chain.extend(anchor_point, point, self.params.sweep_radius_m);
        let length = segment.length();
        let segments = ((length / self.params.vertex_spacing_m).round() as usize).max(2);
        let mut curve = Vec::with_capacity(segments + 1);
        segment.sample_by_arc_length(segments, &mut curve);

        let volume = SweptVolume::new(stroke.last_blade, near, &curve, self.params.sweep_radius_m);
        let mut removed = self.swept_triangles(&volume, view);
        if let Anchor::Tip(v) = stroke.anchor {
            removed.extend(view.topo.node_tris[v as usize].iter().copied());
        }
        removed.sort_unstable();
        removed.dedup();
        keep_parts_the_cut_reaches(&mut removed, &anchor_point, view.topo, view.x);
        if removed.is_empty() {
            return CutStep::Unchanged;
        }
        // A last piece after a deferred update is longer than one update: not dropped.
        let droppable = last == LastPiece::DropIfInside && stroke.retry_from_m == 0.0 && !meets_border_away_from(&removed, &stroke.anchor, view, self.params.vertex_spacing_m);

        let mut plan = CutPlan { starts_new_cut: stroke.incision.is_none(), incision_length_m: length, ..Default::default() };
        let mut matched = None;
        let mut failure = String::from("the removed area kept needing to grow");
        for _attempt in 0..8 {
            let normal = area_normal(&removed, view);
            let input = MatchInput {
                topo: view.topo,
                x: view.x,
                removed_tris: &removed,
                curve: &curve,
                normal,
                next_vertex_id,
                lip_spacing_m: self.params.vertex_spacing_m,
            };
            match match_nodes(&input) {
                Ok(out) => {
                    matched = Some(out);
                    break;
                }
                Err(MatchError::Grow(more)) => {
                    removed.extend(more);
                    removed.sort_unstable();
                    removed.dedup();
                }
                Err(e) => {
                    failure = e.to_string();
                    break;
                }
            }
        }
        match matched {
            Some(out) => {
                plan.new_vertices = out.new_vertices.iter().map(|p| material_point(p, &removed, view)).collect();
                plan.new_triangles = out.new_triangles;
                plan.min_angle_deg = Some(out.min_angle_deg);
                let index = match stroke.incision {
                    Some(i) => {
                        self.incisions[i].curve = chain;
                        i
                    }
                    None => {
                        self.incisions.push(Incision { tool, curve: chain, lips: [Vec::new(), Vec::new()] });
                        self.incisions.len() - 1
                    }
                };
                let incision = &mut self.incisions[index];
                for (lip, new) in incision.lips.iter_mut().zip(out.lips) {
                    // A continuing update starts on an older lip vertex: what followed it
                    // (the old tip, and anything the sweep removed) is replaced.
                    match lip.iter().rposition(|v| Some(v) == new.first()) {
                        Some(join) => lip.truncate(join),
                        None => {
                            if let Anchor::Tip(old) = stroke.anchor
                                && lip.last() == Some(&old)
                            {
                                lip.pop();
                            }
                        }
                    }
                    lip.extend(new);
                }
                // A closed end is the next update's anchor (it removes that tip). An open
                // end (the incision met a border: the patch's edge, an older wound, or the
                // edge alongside a one-sided update) leaves no tip: the same incision goes
                // on from the curve's end point while the blade stays in the skin.
                let anchor = out.closed_end_vertex.map_or(Anchor::Start(point), Anchor::Tip);
                self.strokes[tool] = Some(Stroke { anchor, last_blade: near, incision: Some(index), last_crossing: None, retry_from_m: 0.0 });
            }
            // The stroke's last piece, inside the skin: left uncut (LastPiece).
            None if droppable => return CutStep::LastPieceLeftUncut,
            // While the blade cuts on, the update is tried again a little further on,
            // from the same anchor (the blade's sweep since then included).
            None if last == LastPiece::No && (point - anchor_point).norm() < DEFER_SPAN_ADVANCES * self.params.min_advance_m => {
                if let Some(s) = self.strokes[tool].as_mut() {
                    s.retry_from_m = (point - anchor_point).norm() + 0.5 * self.params.min_advance_m;
                }
                return CutStep::Unchanged;
            }
            None => {
                plan.fallback = Some(failure);
                plan.incision_length_m = 0.0;
                self.strokes[tool] = None;
            }
        }
        plan.removed_tris = removed;
        CutStep::Cut(plan)
    }

    /// The first point (from the tip) where the blade's axis crosses a live triangle.
    pub fn crossing(&mut self, blade: &PlacedTool, view: &CutView) -> Option<Crossing> {
        let (min, max) = blade.bounds(view.max_edge_m);
        triangles_near(view.grid, view.topo, &min, &max, &mut self.candidates);
        nearest_crossing(blade, &self.candidates, view.x, view.topo)
    }

    /// The part of the blade within a few edge lengths of the surface crossing.
    fn blade_near_surface(&self, blade: &PlacedTool, t: f64, view: &CutView) -> (Vec3, Vec3) {
        let reach = self.params.sweep_radius_m + 2.0 * view.max_edge_m;
        let at = t * blade.length_m;
        let lo = (at - reach).max(0.0);
        let hi = (at + reach).min(blade.length_m);
        (blade.tip + blade.axis * lo, blade.tip + blade.axis * hi)
    }

    /// Stage 1: triangles with a vertex inside the swept volume, an edge (spring) it
    /// touches, or the incision curve passing over them.
    fn swept_triangles(&self, volume: &SweptVolume, view: &CutView) -> Vec<u32> {
        let (min, max) = volume.bounds(view.max_edge_m);
        let mut nodes = Vec::new();
        view.grid.query_box(&min, &max, |n| nodes.push(n));
        nodes.sort_unstable();
        let mut tris: Vec<u32> = nodes.iter().flat_map(|&n| view.topo.node_tris[n as usize].iter().copied()).collect();
        tris.sort_unstable();
        tris.dedup();
        tris.retain(|&t| {
            let ids = view.topo.tris[t as usize];
            let p = ids.map(|v| view.x[v as usize]);
            p.iter().any(|q| volume.contains(q))
                || (0..3).any(|k| volume.touches_segment(&p[k], &p[(k + 1) % 3]))
                || volume.curve_touches_triangle(&p)
        });
        tris
    }
}

/// The triangles around the nodes within [min, max] (the broad phase's cells), each
/// once, into `out` (cleared first; it keeps its room, so a step does not allocate).
pub(crate) fn triangles_near(grid: &PointGrid, topo: &Topology, min: &Vec3, max: &Vec3, out: &mut Vec<u32>) {
    out.clear();
    grid.query_box(min, max, |node| out.extend(topo.node_tris[node as usize].iter().copied()));
    out.sort_unstable();
    out.dedup();
}

/// Where the tool's axis crosses one of the live `candidates` triangles nearest its tip.
pub(crate) fn nearest_crossing(tool: &PlacedTool, candidates: &[u32], x: &[Vec3], topo: &Topology) -> Option<Crossing> {
    let mut best: Option<Crossing> = None;
    for &t in candidates.iter().filter(|&&t| topo.tri_alive[t as usize]) {
        let [a, b, c] = topo.tris[t as usize].map(|v| x[v as usize]);
        if let Some(s) = segment_triangle_intersection(&tool.tip, &tool.top, &a, &b, &c)
            && best.is_none_or(|h| s < h.blade_t)
        {
            best = Some(Crossing { point: tool.tip + (tool.top - tool.tip) * s, blade_t: s, triangle: t });
        }
    }
    best
}

/// Whether an update is the stroke's last piece (the blade left the skin), and so may be
/// dropped when it cannot be stitched.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum LastPiece {
    /// An update while the blade cuts on: a failure falls back to an open hole.
    No,
    /// The piece from the incision's end to where the blade left the skin (shorter than
    /// `min_advance_m` plus one step's travel, unless an update before it was deferred:
    /// such a piece is not dropped). Where what the blade swept lies inside
    /// the skin (it meets no border farther than a vertex spacing from the incision's
    /// closed tip or the open end it goes on from), a piece that
    /// cannot be stitched is not cut: the incision keeps its stitched tip, a millimetre or
    /// two short of where the blade left, instead of an open hole that growing the
    /// removed area had often carried to the patch's edge. A piece that reaches the
    /// patch's edge or an older wound still falls back: there the hole parts what the
    /// blade parted.
    DropIfInside,
}

/// Whether any of the triangles has an edge on the mesh's border (one live triangle)
/// away from the anchor: the swept area reaches the patch's edge, an older wound, or the
/// incision's own lips well behind its tip. Away is having both ends more than `spacing`
/// from the anchor, measured along the surface. At an open end (the incision met a
/// border there and goes on from that point) the border the incision ended on runs
/// through the anchor itself, and the point was recorded when the blade crossed there
/// (the skin has moved along its normal since); at a closed tip the lips' last edges end
/// at the tip, and the area the blade swept round the tip takes the triangles on them.
fn meets_border_away_from(tris: &[u32], anchor: &Anchor, view: &CutView, spacing: f64) -> bool {
    let normal = area_normal(tris, view);
    let anchor_point = anchor_position(anchor, view);
    let at_anchor = |v: u32| across(&(view.x[v as usize] - anchor_point), &normal).norm() <= spacing;
    view.topo.border_edges_of(tris).any(|(a, b)| !at_anchor(a) && !at_anchor(b))
}

fn anchor_position(anchor: &Anchor, view: &CutView) -> Vec3 {
    match anchor {
        Anchor::Start(p) => *p,
        Anchor::Tip(v) => view.x[*v as usize],
    }
}

/// Leaves out of a swept area (sorted) each part of it, connected through shared
/// vertices (a narrow strip may hang together at a vertex only, which matching mends), that
/// neither holds the triangle nearest the incision's anchor nor reaches a border. Such a
/// part is skin folded into the blade's path, apart from the strip it sweeps: a blade
/// pushing a fine mesh ahead of it crushes the triangles there until they overlap. Its
/// border runs the wrong way round and stitching cannot take it; the next update sweeps
/// it again if it is still there. Parts on either side of an older wound reach that
/// wound's lips (a border), so a cut across a wound keeps them all.
fn keep_parts_the_cut_reaches(removed: &mut Vec<u32>, anchor: &Vec3, topo: &Topology, x: &[Vec3]) {
    let mut parts = UnionFind::new(removed.len());
    for (i, &t) in removed.iter().enumerate() {
        for v in topo.tris[t as usize] {
            for j in topo.node_tris[v as usize].iter().filter_map(|o| removed.binary_search(o).ok()) {
                parts.union(i, j);
            }
        }
    }
    // One part (the smallest index is every root): all of it is the cut's.
    if (0..removed.len()).all(|i| parts.find(i) == 0) {
        return;
    }
    // Indexed by each part's root (its first triangle).
    let mut kept = vec![false; removed.len()];
    if let Some(i) = nearest_triangle(anchor, removed, topo, x) {
        kept[parts.find(i)] = true;
    }
    for (i, &t) in removed.iter().enumerate() {
        if topo.border_edges_of(std::slice::from_ref(&t)).next().is_some() {
            kept[parts.find(i)] = true;
        }
    }
    let mut i = 0;
    removed.retain(|_| {
        i += 1;
        kept[parts.find(i - 1)]
    });
}

/// The index in `tris` of the triangle nearest `p` (the first of equals; none at a finite
/// distance: none).
fn nearest_triangle(p: &Vec3, tris: &[u32], topo: &Topology, x: &[Vec3]) -> Option<usize> {
    tris.iter()
        .map(|&t| {
            let [a, b, c] = topo.tris[t as usize].map(|v| x[v as usize]);
            (closest_point_on_triangle(p, &a, &b, &c) - p).norm_squared()
        })
        .enumerate()
        .filter(|(_, d)| d.is_finite())
        .min_by(|a, b| a.1.total_cmp(&b.1))
        .map(|(i, _)| i)
}

/// Unit area-weighted normal of the given triangles.
fn area_normal(tris: &[u32], view: &CutView) -> Vec3 {
    let sum: Vec3 = tris
        .iter()
        .map(|&t| {
            let [a, b, c] = view.topo.tris[t as usize].map(|v| view.x[v as usize]);
            triangle_normal(&a, &b, &c)
        })
        .sum();
    let n = sum.norm();
    if n > 0.0 { sum / n } else { Vec3::z() }
}

/// The removed skin at `p`: its velocity and its reference position, interpolated in
/// the removed triangle nearest to `p` (new vertices move on as the tissue there did).
fn material_point(p: &Vec3, removed: &[u32], view: &CutView) -> NewVertex {
    let Some(nearest) = nearest_triangle(p, removed, view.topo, view.x) else {
        return NewVertex { position: *p, velocity: Vec3::zeros(), reference: *p };
    };
    let ids = view.topo.tris[removed[nearest] as usize];
    let [a, b, c] = ids.map(|v| view.x[v as usize]);
    let w = barycentric_closest(p, &a, &b, &c);
    let blend = |field: &[Vec3]| field[ids[0] as usize] * w[0] + field[ids[1] as usize] * w[1] + field[ids[2] as usize] * w[2];
    // The offset off the triangle's plane (the curve may lie slightly off the surface) is
    // carried over unchanged.
    let on_triangle = blend(view.x);
    NewVertex { position: *p, velocity: blend(view.v), reference: blend(view.x_ref) + (p - on_triangle) }
}

#[cfg(test)]
pub(super) mod tests {
    use super::*;

    /// A flat grid of unit squares in the xy plane, `nx` × `ny` vertices (id = y·nx + x),
    /// each square split into two counter-clockwise triangles (seen from +z; ids 2k and
    /// 2k + 1 for square k = y·(nx − 1) + x).
    pub(in crate::msm::cut) fn grid(nx: u32, ny: u32) -> (Topology, Vec<Vec3>) {
        let mut topo = Topology { node_tris: vec![Vec::new(); (nx * ny) as usize], ..Default::default() };
        let x = (0..nx * ny).map(|v| Vec3::new((v % nx) as f64, (v / nx) as f64, 0.0)).collect();
        for j in 0..ny - 1 {
            for i in 0..nx - 1 {
                let (a, b, c, d) = (j * nx + i, j * nx + i + 1, (j + 1) * nx + i + 1, (j + 1) * nx + i);
                topo.push_tri([a, b, c], 0.5);
                topo.push_tri([a, c, d], 0.5);
            }
        }
        (topo, x)
    }

    #[test]
    fn a_swept_part_apart_from_the_anchor_and_every_border_is_left_out() {
        let (nx, ny) = (10, 7);
        let (topo, x) = grid(nx, ny);
        let square = |i: u32, j: u32| [2 * (j * (nx - 1) + i), 2 * (j * (nx - 1) + i) + 1];
        // The anchor's part: two squares meeting at a vertex only (one part). Apart from
        // it: a square inside the mesh (left out), and one on the mesh's edge x = 0 (kept:
        // it reaches a border).
        let anchors = [square(2, 2), square(3, 3)].concat();
        let inside = square(7, 3);
        let on_edge = square(0, 5);
        let mut removed = [anchors.as_slice(), &inside, &on_edge].concat();
        removed.sort_unstable();
        keep_parts_the_cut_reaches(&mut removed, &Vec3::new(2.5, 2.5, 0.0), &topo, &x);
        let mut expected = [anchors.as_slice(), &on_edge].concat();
        expected.sort_unstable();
        assert_eq!(removed, expected);

        // One part alone is kept whole, wherever the anchor is.
        let mut one = inside.to_vec();
        keep_parts_the_cut_reaches(&mut one, &Vec3::new(2.5, 2.5, 0.0), &topo, &x);
        assert_eq!(one, inside.to_vec());
    }
}
