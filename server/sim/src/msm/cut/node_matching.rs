//! Stage 3 of the three-stage cut (paper Section 2.3.3, Algorithm 2): shortest-distance
//! node matching, which stitches the surface back around the incision so the wound
//! can open.
//!
//! Input: the triangles stage 1 removed (the grey area) and the incision curve of stage
//! 2, sampled into vertices about one edge length apart. Output: new vertices and
//! triangles that fill the grey area on both sides of the curve.
//!
//! 1. The grey area's border is followed as chains of vertices (each edge oriented as
//!    in the kept triangle beside it, so the hole is on the right of the walk). A chain
//!    is a loop when the hole lies inside the tissue, or open when it ends on a border
//!    of the mesh (the patch edge, or the wound of the same cut growing).
//! 2. Each end of the curve is *closed* (it stops inside the tissue: one vertex ends
//!    both lips there) or *open* (it meets a border: each lip ends on the chain end of
//!    its own side). An open chain end belongs to the curve end it is nearer to (along
//!    the surface, not through space: the skin moves under the blade), except that two
//!    open chains whose ends would split 3 to 1 each run from one end to the other (an
//!    update leaving the mesh at a slant), and a single open chain whose ends would
//!    split 1 to 1 but which runs around the curve belongs with both ends to the curve
//!    end nearer to them (a stroke entering obliquely just inside the patch's edge). At
//!    a closed end the border vertex nearest to the end, preferring those ahead of it,
//!    is the paper's "yellow" node; the chains are split there into two arcs, one on
//!    each side of the curve. Where a single open chain runs from one end to the other,
//!    on one side of the curve all along it (beyond the curve's ends it may round
//!    them), and nothing else borders the removed area, there is tissue on that side
//!    only (the cut severs the last bridge to the patch's edge, or runs along it): that
//!    side is stitched and the other gets no lip.
//! 3. Every curve vertex except the closed ends is split in two, one per lip.
//! 4. Each arc is joined to its lip (the paper's red springs) by walking both and always
//!    closing the quad between them with its shorter diagonal (the green springs). Where
//!    the border zigzags so that no such zipper fits without folding a triangle over,
//!    that strip is triangulated as a polygon by ear clipping instead; where no ear
//!    clipping fits either, the caller removes the kept triangles around the folded
//!    ones as well and tries again.
//! 5. A few Lawson flips inside the new triangles raise the smallest angle; a triangle
//!    still under [`MIN_ANGLE_DEG`] makes the caller remove the kept triangles around it
//!    and try again.
//!
//! The result is manifold by construction; orientation and the smallest angle are
//! checked and reported. When the grey area is not a simple hole (it pinches at a
//! vertex or encloses an island of triangles), the caller is told which triangles to
//! remove as well, and tries again.

use crate::math::{Vec3, across, closest_point_on_segment, triangle_min_angle_deg, triangle_normal};
use crate::msm::state::Topology;

/// Every triangle a cut creates has all its angles at least this large (degrees) in
/// the configuration it is created in; when stitching cannot reach it, the update falls
/// back to leaving the swept area open (and says so).
pub const MIN_ANGLE_DEG: f64 = 10.0;

/// At an open end of the curve, a lip goes through the curve's end point when the
/// border's end on either side lies more than this many lip spacings back from it (see
/// [`match_nodes`]). A continuing cut's border ends about one spacing back (on the lip
/// vertex before the removed tip); how far the threshold reaches across the CT skin is in
/// docs/tool-tissue.md.
const LIP_SPAN_SPACINGS: f64 = 1.5;

/// What node matching needs to see.
pub(crate) struct MatchInput<'a> {
    pub topo: &'a Topology,
    /// Node positions, m.
    pub x: &'a [Vec3],
    /// Triangles stage 1 removes (sorted ascending; still alive in `topo`).
    pub removed_tris: &'a [u32],
    /// Incision curve from its start to its end (segments + 1 points).
    pub curve: &'a [Vec3],
    /// Unit normal of the surface around the cut.
    pub normal: Vec3,
    /// Id the first new vertex will get.
    pub next_vertex_id: u32,
    /// The distance the lip vertices are meant to lie apart (the mesh's mean edge), m.
    pub lip_spacing_m: f64,
}

/// The stitched wound.
#[derive(Debug, Clone, Default, PartialEq)]
pub(crate) struct MatchOutput {
    /// Positions of the new vertices; vertex `k` gets id `next_vertex_id + k`.
    pub new_vertices: Vec<Vec3>,
    pub new_triangles: Vec<[u32; 3]>,
    /// Lip vertex ids from the start of the curve to its end, left and right of it;
    /// empty on a side with no tissue along the curve (a one-sided stitch).
    pub lips: [Vec<u32>; 2],
    /// The vertex that closes the curve's end, when that end is closed.
    pub closed_end_vertex: Option<u32>,
    pub start_open: bool,
    pub end_open: bool,
    /// Smallest angle of the new triangles, degrees.
    pub min_angle_deg: f64,
}

/// Why the grey area could not be stitched.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub(crate) enum MatchError {
    #[error("the removed area is not a simple hole; also remove triangles {0:?}")]
    Grow(Vec<u32>),
    #[error("the removed area has no border with the remaining tissue")]
    NoBorder,
    #[error("{0}")]
    Unsupported(String),
}

/// Signed position of a point relative to the curve.
struct CurveFrame<'a> {
    points: &'a [Vec3],
    cumulative: Vec<f64>,
    normal: Vec3,
}

impl<'a> CurveFrame<'a> {
    fn new(points: &'a [Vec3], normal: Vec3) -> Self {
        let mut cumulative = vec![0.0];
        for w in points.windows(2) {
            cumulative.push(cumulative.last().unwrap() + (w[1] - w[0]).norm());
        }
        Self { points, cumulative, normal }
    }

    fn tangent(&self, segment: usize) -> Vec3 {
        (self.points[segment + 1] - self.points[segment]).normalize()
    }

    /// (arc-length parameter, extended past the ends along the end tangents; side: +1
    /// left of the curve seen from the normal, −1 right).
    fn locate(&self, p: &Vec3) -> (f64, f64) {
        let mut best = (f64::INFINITY, 0usize, 0.0f64);
        for i in 0..self.points.len() - 1 {
            let (t, q) = closest_point_on_segment(p, &self.points[i], &self.points[i + 1]);
            let d = (q - p).norm_squared();
            if d < best.0 {
                best = (d, i, t);
            }
        }
        let (_, i, t) = best;
        let tangent = self.tangent(i);
        let last = self.points.len() - 2;
        let param = if i == 0 && t == 0.0 {
            (p - self.points[0]).dot(&tangent)
        } else if i == last && t == 1.0 {
            self.cumulative[last + 1] + (p - self.points[last + 1]).dot(&tangent)
        } else {
            self.cumulative[i] + t * (self.cumulative[i + 1] - self.cumulative[i])
        };
        let on_curve = self.points[i] + (self.points[i + 1] - self.points[i]) * t;
        let side = tangent.cross(&(p - on_curve)).dot(&self.normal);
        (param, if side >= 0.0 { 1.0 } else { -1.0 })
    }
}

#[derive(Debug, Clone)]
struct Chain {
    vertices: Vec<u32>,
    closed: bool,
}

/// Runs node matching; see the module documentation.
pub(crate) fn match_nodes(input: &MatchInput) -> Result<MatchOutput, MatchError> {
    if input.curve.len() < 2 {
        return Err(MatchError::Unsupported("the incision curve needs at least two points".into()));
    }
    let chains = grey_chains(input)?;
    if chains.is_empty() {
        return Err(MatchError::NoBorder);
    }
    let frame = CurveFrame::new(input.curve, input.normal);
    let n = input.curve.len() - 1;
    let (start_point, end_point) = (input.curve[0], input.curve[n]);

    // Open chain ends belong to the curve end they are nearer to, measured along the
    // surface: the curve's points are where the blade crossed the skin, each when it
    // did, and the skin moves under the blade by millimetres along its normal between
    // them (a continuing update's start lay deep in the dimple the blade pressed), so
    // a distance through space would count that motion and hand an end to the wrong
    // curve end.
    let nearer_start = |v: u32| {
        let p = input.x[v as usize];
        across(&(p - start_point), &input.normal).norm() - across(&(p - end_point), &input.normal).norm()
    };
    let open: Vec<&Chain> = chains.iter().filter(|c| !c.closed).collect();
    let mut start_ends: Vec<u32> = Vec::new();
    let mut end_ends: Vec<u32> = Vec::new();
    for chain in &open {
        for v in [chain.vertices[0], *chain.vertices.last().unwrap()] {
            if nearer_start(v) <= 0.0 { start_ends.push(v) } else { end_ends.push(v) }
        }
    }
    // Two open chains whose four ends split 3 to 1: a short update that leaves the mesh
    // through its edge at a slant has one chain end on the edge about as near the
    // curve's start as its end. Each chain then runs from one end of the curve to the
    // other, as two lips must: of each chain's two ends, the one relatively nearer the
    // start goes to the start. Later checks (arcs on opposite sides) still refuse a
    // pairing that is wrong.
    if open.len() == 2 && start_ends.len().abs_diff(end_ends.len()) == 2 {
        start_ends.clear();
        end_ends.clear();
        for chain in &open {
            let (a, b) = (chain.vertices[0], *chain.vertices.last().unwrap());
            let (first, second) = if nearer_start(a) <= nearer_start(b) { (a, b) } else { (b, a) };
            start_ends.push(first);
            end_ends.push(second);
        }
    }
    // One open chain whose ends split 1 to 1 but which runs around the curve (on both
    // sides of it) rather than alongside one side: where the curve end nearer to the two
    // ends lies on the mesh's border, that chain is the border the curve starts from (or
    // ends on), one of whose ends lies about as near the other curve end (a stroke that
    // enters just inside the patch's edge, obliquely). Both ends go to that curve end;
    // the checks after it still refuse what does not fit. (A curve end away from the
    // border would be opened onto it through tissue the blade did not cross.)
    if chains.len() == 1 && open.len() == 1 && start_ends.len() == 1 && end_ends.len() == 1 && !arc_on_one_side(&open[0].vertices, &frame, input.x) {
        let ends = [start_ends[0], end_ends[0]];
        let to_start = nearer_start(ends[0]) + nearer_start(ends[1]) <= 0.0;
        let curve_end = if to_start { start_point } else { end_point };
        if distance_to_mesh_border(&curve_end, input) <= 0.5 * input.lip_spacing_m {
            let (group, other) = if to_start { (&mut start_ends, &mut end_ends) } else { (&mut end_ends, &mut start_ends) };
            group.clear();
            group.extend(ends);
            other.clear();
        }
    }
    // One open chain from near the start to near the end, and nothing else: tissue
    // along one side of the curve only (the cut severs the last bridge to the patch's
    // edge, or runs along that edge). That side is stitched; the other gets no lip.
    let one_sided = chains.len() == 1 && start_ends.len() == 1 && end_ends.len() == 1;
    for (group, name) in [(&start_ends, "start"), (&end_ends, "end")] {
        if !one_sided && !group.is_empty() && group.len() != 2 {
            return Err(MatchError::Unsupported(format!(
                "the removed area meets the mesh border {} times near the incision's {name} (0 or 2 supported)",
                group.len()
            )));
        }
    }
    let (start_open, end_open) = (!start_ends.is_empty(), !end_ends.is_empty());

    // Yellow nodes at the closed ends.
    let yellow_start = (!start_open).then(|| pick_yellow(&chains, &frame, input.x, &start_point));
    let yellow_end = (!end_open).then(|| pick_yellow(&chains, &frame, input.x, &end_point));
    if yellow_start.is_some() && yellow_start == yellow_end {
        return Err(MatchError::Unsupported("both ends of the incision reach the same border node".into()));
    }

    let arcs = split_into_arcs(&chains, yellow_start, yellow_end)?;
    let expected_arcs = if one_sided { 1 } else { 2 };
    if arcs.len() != expected_arcs {
        return Err(MatchError::Unsupported(format!(
            "the border of the removed area splits into {} arcs ({expected_arcs} supported)",
            arcs.len()
        )));
    }
    if one_sided && !arc_on_one_side(&arcs[0], &frame, input.x) {
        // The chain wraps around the curve (the removed area meets the mesh border in a
        // stretch beside the curve's middle, not at a curve end on the border): no side
        // is free of tissue.
        return Err(MatchError::Unsupported(
            "the removed area meets the mesh border once near each end of the incision, but its border with the remaining tissue runs on both sides".into(),
        ));
    }
    let sides: Vec<f64> = arcs.iter().map(|arc| arc_side(arc, &frame, input.x)).collect();
    if sides.len() == 2 && sides[0] == sides[1] {
        return Err(MatchError::Unsupported("both border arcs lie on the same side of the incision".into()));
    }

    // New vertices: the closed ends (shared by both lips), then each lip's interior.
    let mut out = MatchOutput { start_open, end_open, ..Default::default() };
    let base = input.next_vertex_id;
    let push_vertex = |out: &mut MatchOutput, p: Vec3| {
        out.new_vertices.push(p);
        base + out.new_vertices.len() as u32 - 1
    };
    let closed_start = (!start_open).then(|| push_vertex(&mut out, start_point));
    let closed_end = (!end_open).then(|| push_vertex(&mut out, end_point));
    out.closed_end_vertex = closed_end;
    // At an open end the lips start (or end) on the border's own vertices. Where the
    // border there lies well back along the curve (the wound this cut continues ended
    // in a vertex the update removed, so its lips now end a stretch behind), a lip that
    // went from there straight to the first vertex of the curve would span that stretch
    // and the triangles beside it would be slivers: the lips go through the curve's end
    // point as well (split in two, like the other curve vertices).
    let too_far = LIP_SPAN_SPACINGS * input.lip_spacing_m;
    let start_back = |v: u32| -frame.locate(&input.x[v as usize]).0;
    let end_back = |v: u32| frame.locate(&input.x[v as usize]).0 - frame.cumulative[n];
    let through_start = start_open && start_ends.iter().any(|&v| start_back(v) > too_far);
    let through_end = end_open && end_ends.iter().any(|&v| end_back(v) > too_far);

    let mut strips: Vec<(usize, &[u32], bool)> = Vec::with_capacity(2);
    for (slot, side) in [1.0, -1.0].into_iter().enumerate() {
        // One-sided: the side without an arc keeps no tissue along the curve, no lip.
        let Some(k) = sides.iter().position(|&s| s == side) else { continue };
        let arc: &[u32] = &arcs[k];
        let (first, last) = (arc[0], *arc.last().unwrap());
        let is_start_end = |v: u32| if start_open { start_ends.contains(&v) } else { Some(v) == yellow_start };
        let is_end_end = |v: u32| if end_open { end_ends.contains(&v) } else { Some(v) == yellow_end };
        // The arc is walked with the hole on its right: from the curve's start to its end
        // on the left side, backwards on the right side.
        let forward = if is_start_end(first) && is_end_end(last) {
            true
        } else if is_start_end(last) && is_end_end(first) {
            false
        } else {
            return Err(MatchError::Unsupported("a border arc does not run from one end of the incision to the other".into()));
        };
        let (arc_start, arc_end) = if forward { (first, last) } else { (last, first) };
        let mut lip = vec![closed_start.unwrap_or(arc_start)];
        let inner = if through_start { 0 } else { 1 }..if through_end { n + 1 } else { n };
        for p in &input.curve[inner] {
            lip.push(push_vertex(&mut out, *p));
        }
        lip.push(closed_end.unwrap_or(arc_end));
        out.lips[slot] = lip;
        strips.push((slot, arc, forward));
    }

    let position = |id: u32, out: &MatchOutput| -> Vec3 {
        if id >= base { out.new_vertices[(id - base) as usize] } else { input.x[id as usize] }
    };
    for &(slot, arc, forward) in &strips {
        let mut lip = out.lips[slot].clone();
        if !forward {
            lip.reverse();
        }
        // At an open end the lip starts (or ends) on the arc's own end vertex.
        let mut q: &[u32] = &lip;
        if q[0] == arc[0] {
            q = &q[1..];
        }
        if q.last() == arc.last() {
            q = &q[..q.len() - 1];
        }
        if q.is_empty() {
            return Err(MatchError::Unsupported("a lip has no vertex between its ends".into()));
        }
        let mut strip = Vec::new();
        zip_shortest_diagonal(arc, q, |id| position(id, &out), &input.normal, &mut strip);
        let upright = |t: &[u32; 3]| {
            let [a, b, c] = t.map(|id| position(id, &out));
            triangle_normal(&a, &b, &c).dot(&input.normal) > 0.0
        };
        if !strip.iter().all(upright) {
            // The border zigzags so that no arc-to-lip zipper fits: triangulate the strip
            // as a polygon instead (arc backwards, then the lip).
            let mut polygon: Vec<u32> = arc.iter().rev().copied().collect();
            polygon.extend(lip.iter().copied().filter(|v| !arc.contains(v)));
            let kept_edge = |a: u32, b: u32| {
                a < base && b < base && input.topo.edge_tris(a, b).any(|t| input.removed_tris.binary_search(&t).is_err())
            };
            match ear_clip(&polygon, |id| position(id, &out), &input.normal, kept_edge) {
                Some(clipped) => strip = clipped,
                None => {
                    let folded: Vec<[u32; 3]> = strip.iter().filter(|t| !upright(t)).copied().collect();
                    return Err(grow_around(&folded, base, input, "the border around the incision cannot be stitched without folding"));
                }
            }
        }
        out.new_triangles.extend(strip);
    }

    let positions = |id: u32| if id >= base { out.new_vertices[(id - base) as usize] } else { input.x[id as usize] };
    let mut triangles = std::mem::take(&mut out.new_triangles);
    lawson_flips(&mut triangles, &positions, &input.normal, |a, b| {
        // New vertices have no kept triangles yet.
        a < base && b < base && input.topo.edge_tris(a, b).any(|t| input.removed_tris.binary_search(&t).is_err())
    });
    let (worst, min_angle) = triangles
        .iter()
        .map(|t| {
            let [a, b, c] = t.map(positions);
            (*t, triangle_min_angle_deg(&a, &b, &c))
        })
        .fold(([0; 3], f64::INFINITY), |best, next| if next.1 < best.1 { next } else { best });
    if min_angle < MIN_ANGLE_DEG {
        // Too thin: take the kept triangles around its border vertices away as well, so
        // the border moves back from the incision, and try again.
        return Err(grow_around(
            &[worst],
            base,
            input,
            &format!("the best stitching has a {min_angle:.1}° angle, below the {MIN_ANGLE_DEG}° bound"),
        ));
    }
    out.min_angle_deg = min_angle;
    out.new_triangles = triangles;
    Ok(out)
}

/// Distance from `p` to the nearest edge of the removed triangles on the mesh's border,
/// measured along the surface (across the normal); infinite when they have none.
fn distance_to_mesh_border(p: &Vec3, input: &MatchInput) -> f64 {
    input
        .topo
        .border_edges_of(input.removed_tris)
        .map(|(a, b)| {
            let (_, q) = closest_point_on_segment(p, &input.x[a as usize], &input.x[b as usize]);
            across(&(q - p), &input.normal).norm()
        })
        .fold(f64::INFINITY, f64::min)
}

/// Asks for the kept triangles around the border vertices of `triangles` to be removed
/// as well, so the border moves back from the incision; `failure` when there are none.
fn grow_around(triangles: &[[u32; 3]], base: u32, input: &MatchInput, failure: &str) -> MatchError {
    let mut grow: Vec<u32> = triangles
        .iter()
        .flatten()
        .filter(|&&v| v < base)
        .flat_map(|&v| input.topo.node_tris[v as usize].iter().copied())
        .filter(|t| input.removed_tris.binary_search(t).is_err())
        .collect();
    grow.sort_unstable();
    grow.dedup();
    if grow.is_empty() { MatchError::Unsupported(failure.to_string()) } else { MatchError::Grow(grow) }
}

/// Follows the border between removed and kept triangles.
fn grey_chains(input: &MatchInput) -> Result<Vec<Chain>, MatchError> {
    let removed = |t: u32| input.removed_tris.binary_search(&t).is_ok();
    let mut edges: Vec<(u32, u32)> = Vec::new();
    for &t in input.removed_tris {
        let tri = input.topo.tris[t as usize];
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            if input.topo.across(t, a, b).is_some_and(|o| !removed(o)) {
                // The kept triangle traverses this edge as b → a.
                edges.push((b, a));
            }
        }
    }
    edges.sort_unstable();
    // A kept triangle with two or three edges on the hole is an ear poking into it (the
    // border would zigzag): it goes with the removed area.
    let mut ears: Vec<u32> = Vec::new();
    for &t in input.removed_tris {
        let tri = input.topo.tris[t as usize];
        for k in 0..3 {
            let (a, b) = (tri[k], tri[(k + 1) % 3]);
            let Some(o) = input.topo.across(t, a, b).filter(|&o| !removed(o)) else { continue };
            let ot = input.topo.tris[o as usize];
            let on_hole = (0..3)
                .filter(|&j| input.topo.across(o, ot[j], ot[(j + 1) % 3]).is_some_and(&removed))
                .count();
            if on_hole >= 2 {
                ears.push(o);
            }
        }
    }
    if !ears.is_empty() {
        ears.sort_unstable();
        ears.dedup();
        return Err(MatchError::Grow(ears));
    }
    // A vertex with two outgoing border edges is a pinch: remove its triangles too.
    for w in edges.windows(2) {
        if w[0].0 == w[1].0 {
            let v = w[0].0;
            return Err(MatchError::Grow(input.topo.node_tris[v as usize].clone()));
        }
    }
    let mut targets: Vec<u32> = edges.iter().map(|e| e.1).collect();
    targets.sort_unstable();
    let mut used = vec![false; edges.len()];
    let mut chains = Vec::new();
    let follow = |start: u32, used: &mut Vec<bool>| -> Chain {
        let mut vertices = vec![start];
        let mut v = start;
        while let Ok(i) = edges.binary_search_by_key(&v, |e| e.0) {
            if used[i] {
                return Chain { vertices, closed: true };
            }
            used[i] = true;
            v = edges[i].1;
            if v == start {
                return Chain { vertices, closed: true };
            }
            vertices.push(v);
        }
        Chain { vertices, closed: false }
    };
    for &(from, _) in &edges {
        if targets.binary_search(&from).is_err() {
            chains.push(follow(from, &mut used));
        }
    }
    for i in 0..edges.len() {
        if !used[i] {
            chains.push(follow(edges[i].0, &mut used));
        }
    }

    // A loop that runs counter-clockwise encloses kept triangles: an island inside the
    // hole. Remove the island as well.
    let loops: Vec<&Chain> = chains.iter().filter(|c| c.closed).collect();
    for chain in &loops {
        let area = signed_area(&chain.vertices, input.x, &input.normal);
        if area > 0.0 {
            let island = flood_island(input, &chain.vertices, &removed);
            if island.is_empty() || island.len() > 64 {
                return Err(MatchError::Unsupported(format!(
                    "an island of {} triangles remains inside the removed area",
                    island.len()
                )));
            }
            return Err(MatchError::Grow(island));
        }
    }
    Ok(chains)
}

fn signed_area(loop_vertices: &[u32], x: &[Vec3], normal: &Vec3) -> f64 {
    let origin = x[loop_vertices[0] as usize];
    let mut sum = Vec3::zeros();
    for i in 0..loop_vertices.len() {
        let a = x[loop_vertices[i] as usize] - origin;
        let b = x[loop_vertices[(i + 1) % loop_vertices.len()] as usize] - origin;
        sum += a.cross(&b);
    }
    0.5 * sum.dot(normal)
}

/// Kept triangles reachable from the loop's vertices without crossing the loop.
fn flood_island(input: &MatchInput, loop_vertices: &[u32], removed: &dyn Fn(u32) -> bool) -> Vec<u32> {
    let mut island: Vec<u32> = loop_vertices
        .iter()
        .flat_map(|&v| input.topo.node_tris[v as usize].iter().copied())
        .filter(|&t| !removed(t))
        .filter(|&t| input.topo.tris[t as usize].iter().all(|v| loop_vertices.contains(v)))
        .collect();
    island.sort_unstable();
    island.dedup();
    island
}

/// The yellow node of a closed curve end: where the border, walking around that end,
/// passes from one side of the curve (extended along its end tangent) to the other. Of
/// the two vertices of that crossing, the one nearer the end is taken.
fn pick_yellow(chains: &[Chain], frame: &CurveFrame, x: &[Vec3], end: &Vec3) -> u32 {
    let mut best = (f64::INFINITY, u32::MAX);
    let mut consider = |a: u32, b: u32| {
        let (pa, pb) = (x[a as usize], x[b as usize]);
        if frame.locate(&pa).1 == frame.locate(&pb).1 {
            return;
        }
        let (da, db) = ((pa - end).norm(), (pb - end).norm());
        let (d, v) = if da <= db { (da, a) } else { (db, b) };
        if d < best.0 || (d == best.0 && v < best.1) {
            best = (d, v);
        }
    };
    for chain in chains {
        for w in chain.vertices.windows(2) {
            consider(w[0], w[1]);
        }
        if chain.closed {
            consider(*chain.vertices.last().unwrap(), chain.vertices[0]);
        }
    }
    if best.1 != u32::MAX {
        return best.1;
    }
    // No side change at all (a degenerate border): the nearest vertex.
    chains
        .iter()
        .flat_map(|c| c.vertices.iter().copied())
        .min_by(|&a, &b| (x[a as usize] - end).norm().total_cmp(&(x[b as usize] - end).norm()).then(a.cmp(&b)))
        .expect("chains are not empty")
}

/// Splits loops and open chains at the yellow nodes into arcs (each in walk order).
fn split_into_arcs(chains: &[Chain], yellow_start: Option<u32>, yellow_end: Option<u32>) -> Result<Vec<Vec<u32>>, MatchError> {
    let yellows: Vec<u32> = [yellow_start, yellow_end].into_iter().flatten().collect();
    let mut arcs = Vec::new();
    for chain in chains {
        let cuts: Vec<usize> =
            chain.vertices.iter().enumerate().filter(|(_, v)| yellows.contains(v)).map(|(i, _)| i).collect();
        if chain.closed {
            if cuts.len() != 2 {
                return Err(MatchError::Unsupported(format!(
                    "a closed border holds {} of the incision's ends (2 expected)",
                    cuts.len()
                )));
            }
            let len = chain.vertices.len();
            let rotated: Vec<u32> = (0..len).map(|k| chain.vertices[(cuts[0] + k) % len]).collect();
            let second = cuts[1] - cuts[0];
            arcs.push(rotated[..=second].to_vec());
            let mut rest = rotated[second..].to_vec();
            rest.push(rotated[0]);
            arcs.push(rest);
        } else {
            let mut from = 0;
            for &c in cuts.iter().filter(|&&c| c > 0 && c + 1 < chain.vertices.len()) {
                arcs.push(chain.vertices[from..=c].to_vec());
                from = c;
            }
            arcs.push(chain.vertices[from..].to_vec());
        }
    }
    Ok(arcs.into_iter().filter(|a| a.len() >= 2).collect())
}

/// Side of the curve an arc lies on (+1 left, −1 right), by majority of its interior
/// vertices (or its first edge's midpoint when it has none).
fn arc_side(arc: &[u32], frame: &CurveFrame, x: &[Vec3]) -> f64 {
    let interior = &arc[1..arc.len() - 1];
    if interior.is_empty() {
        let mid = (x[arc[0] as usize] + x[arc[1] as usize]) * 0.5;
        return frame.locate(&mid).1;
    }
    let sum: f64 = interior.iter().map(|&v| frame.locate(&x[v as usize]).1).sum();
    if sum >= 0.0 { 1.0 } else { -1.0 }
}

/// Whether the arc's interior vertices alongside the curve (those whose nearest curve
/// point is not one of its ends) all lie on the same side of it. Vertices beyond the
/// curve's ends do not count: a chain that rounds an end of the curve to reach the mesh
/// border beyond it still leaves that side free of tissue along the curve.
fn arc_on_one_side(arc: &[u32], frame: &CurveFrame, x: &[Vec3]) -> bool {
    let length = *frame.cumulative.last().unwrap();
    let mut sides = arc[1..arc.len() - 1].iter().map(|&v| frame.locate(&x[v as usize])).filter(|&(t, _)| t > 0.0 && t < length).map(|(_, side)| side);
    let Some(first) = sides.next() else { return true };
    sides.all(|side| side == first)
}

/// Triangulates the strip between the arc `p` (walked with the hole on its right) and
/// the lip `q` (walked the same way), closing each quad with its shorter diagonal (the
/// paper's rule) unless only the other diagonal gives an upright triangle (a border
/// that zigzags after the wound opened).
fn zip_shortest_diagonal(p: &[u32], q: &[u32], pos: impl Fn(u32) -> Vec3, normal: &Vec3, out: &mut Vec<[u32; 3]>) {
    let upright = |t: &[u32; 3]| {
        let [a, b, c] = t.map(&pos);
        triangle_normal(&a, &b, &c).dot(normal) > 0.0
    };
    let (m, k) = (p.len() - 1, q.len() - 1);
    let (mut i, mut j) = (0, 0);
    while i < m || j < k {
        let along_p = (i < m).then(|| [p[i + 1], p[i], q[j]]);
        let along_q = (j < k).then(|| [p[i], q[j], q[j + 1]]);
        let advance_p = match (along_p, along_q) {
            (Some(_), None) => true,
            (None, Some(_)) => false,
            (Some(tp), Some(tq)) => match (upright(&tp), upright(&tq)) {
                (true, false) => true,
                (false, true) => false,
                _ => (pos(p[i + 1]) - pos(q[j])).norm() <= (pos(p[i]) - pos(q[j + 1])).norm(),
            },
            (None, None) => unreachable!("the loop stops when both walks are done"),
        };
        if advance_p {
            out.push([p[i + 1], p[i], q[j]]);
            i += 1;
        } else {
            out.push([p[i], q[j], q[j + 1]]);
            j += 1;
        }
    }
}

/// Triangulates a simple polygon (counter-clockwise seen from `normal`) by clipping,
/// at each turn, the ear with the largest smallest angle. `forbidden(a, b)` marks
/// diagonals that may not be made (edges the kept mesh already has). `None` when no
/// valid ear is left.
fn ear_clip(polygon: &[u32], pos: impl Fn(u32) -> Vec3, normal: &Vec3, forbidden: impl Fn(u32, u32) -> bool) -> Option<Vec<[u32; 3]>> {
    let u = crate::math::any_perpendicular(normal);
    let v = normal.cross(&u);
    let flat = |id: u32| {
        let p = pos(id);
        (p.dot(&u), p.dot(&v))
    };
    let cross = |a: (f64, f64), b: (f64, f64), c: (f64, f64)| (b.0 - a.0) * (c.1 - a.1) - (b.1 - a.1) * (c.0 - a.0);
    let mut ring: Vec<u32> = polygon.to_vec();
    let mut out = Vec::with_capacity(ring.len().saturating_sub(2));
    while ring.len() > 3 {
        let n = ring.len();
        let mut best: Option<(f64, usize)> = None;
        for i in 0..n {
            let (a, b, c) = (ring[(i + n - 1) % n], ring[i], ring[(i + 1) % n]);
            let (pa, pb, pc) = (flat(a), flat(b), flat(c));
            if cross(pa, pb, pc) <= 0.0 || forbidden(a, c) {
                continue;
            }
            let blocked = ring.iter().any(|&w| {
                if w == a || w == b || w == c {
                    return false;
                }
                let pw = flat(w);
                cross(pa, pb, pw) >= 0.0 && cross(pb, pc, pw) >= 0.0 && cross(pc, pa, pw) >= 0.0
            });
            if blocked {
                continue;
            }
            let quality = triangle_min_angle_deg(&pos(a), &pos(b), &pos(c));
            if best.is_none_or(|(q, _)| quality > q) {
                best = Some((quality, i));
            }
        }
        let (_, i) = best?;
        let n = ring.len();
        out.push([ring[(i + n - 1) % n], ring[i], ring[(i + 1) % n]]);
        ring.remove(i);
    }
    let (pa, pb, pc) = (flat(ring[0]), flat(ring[1]), flat(ring[2]));
    if cross(pa, pb, pc) <= 0.0 {
        return None;
    }
    out.push([ring[0], ring[1], ring[2]]);
    Some(out)
}

/// Flips interior edges of `tris` while that raises the smaller angle of the two
/// triangles beside them. `edge_exists_outside(a, b)` tells whether a–b is already an
/// edge of the kept mesh (a flip must not duplicate it).
fn lawson_flips(
    tris: &mut [[u32; 3]],
    pos: &impl Fn(u32) -> Vec3,
    normal: &Vec3,
    edge_exists_outside: impl Fn(u32, u32) -> bool,
) {
    let min_angle = |t: &[u32; 3]| {
        let [a, b, c] = t.map(pos);
        triangle_min_angle_deg(&a, &b, &c)
    };
    for _pass in 0..8 {
        let mut flipped = false;
        for i in 0..tris.len() {
            for e in 0..3 {
                let (a, b) = (tris[i][e], tris[i][(e + 1) % 3]);
                let c = tris[i][(e + 2) % 3];
                let Some(j) = (0..tris.len()).find(|&j| j != i && (0..3).any(|f| tris[j][f] == b && tris[j][(f + 1) % 3] == a))
                else {
                    continue;
                };
                let d = *tris[j].iter().find(|&&v| v != a && v != b).unwrap();
                if c == d || edge_exists_outside(c, d) || tris.iter().any(|t| t.contains(&c) && t.contains(&d)) {
                    continue;
                }
                let new1 = [c, a, d];
                let new2 = [d, b, c];
                let upright = |t: &[u32; 3]| {
                    let [p, q, r] = t.map(pos);
                    triangle_normal(&p, &q, &r).dot(normal) > 0.0
                };
                if !(upright(&new1) && upright(&new2)) {
                    continue;
                }
                let before = min_angle(&tris[i]).min(min_angle(&tris[j]));
                let after = min_angle(&new1).min(min_angle(&new2));
                if after > before + 1e-9 {
                    tris[i] = new1;
                    tris[j] = new2;
                    flipped = true;
                    break;
                }
            }
        }
        if !flipped {
            return;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn zipper_makes_counter_clockwise_strip() {
        // An arc along y = 1 with the hole below it is walked towards +x (hole on the
        // right); the lip along y = 0 is walked the same way.
        let pts = [
            Vec3::new(0.0, 1.0, 0.0),
            Vec3::new(1.0, 1.0, 0.0),
            Vec3::new(2.0, 1.0, 0.0),
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(2.0, 0.0, 0.0),
        ];
        let p = [0u32, 1, 2];
        let q = [3u32, 4, 5];
        let mut tris = Vec::new();
        zip_shortest_diagonal(&p, &q, |i| pts[i as usize], &Vec3::z(), &mut tris);
        assert_eq!(tris.len(), 4);
        for t in &tris {
            let [a, b, c] = t.map(|i| pts[i as usize]);
            assert!(triangle_normal(&a, &b, &c).z > 0.0, "{t:?} is clockwise");
        }
    }

    use crate::msm::cut::tests::grid as grid_topology;

    /// Node matching's input on a [`grid_topology`]: normal +z, new vertices numbered
    /// after the grid's, lips one unit apart.
    fn flat_input<'a>(topo: &'a Topology, x: &'a [Vec3], removed: &'a [u32], curve: &'a [Vec3]) -> MatchInput<'a> {
        MatchInput {
            topo,
            x,
            removed_tris: removed,
            curve,
            normal: Vec3::z(),
            next_vertex_id: x.len() as u32,
            lip_spacing_m: 1.0,
        }
    }

    #[test]
    fn a_cut_with_tissue_on_one_side_only_stitches_that_side() {
        // The removed area is the top row of squares x = 2…5 along the mesh's edge y = 3:
        // its only border with kept tissue is one open chain below the curve, from the
        // edge near the curve's start to the edge near its end.
        let (nx, ny) = (8, 4);
        let (topo, x) = grid_topology(nx, ny);
        let removed: Vec<u32> = (2..5).flat_map(|i| [2 * ((ny - 2) * (nx - 1) + i), 2 * ((ny - 2) * (nx - 1) + i) + 1]).collect();
        let curve: Vec<Vec3> = (2..=5).map(|i| Vec3::new(i as f64, 2.7, 0.0)).collect();
        let base = nx * ny;
        let out = match_nodes(&flat_input(&topo, &x, &removed, &curve)).expect("a one-sided stitch");
        assert!(out.start_open && out.end_open && out.closed_end_vertex.is_none());
        // Left of the curve (towards +y) is the mesh's edge: no lip there. The right lip
        // runs from the chain's end at the start, through the curve's inner points, to
        // the chain's end at the end.
        assert!(out.lips[0].is_empty(), "{:?}", out.lips);
        assert_eq!(out.lips[1], vec![ny * nx - nx + 2, base, base + 1, ny * nx - nx + 5]);
        assert_eq!(out.new_vertices, curve[1..3].to_vec());
        assert!(out.min_angle_deg >= MIN_ANGLE_DEG);
        // Upright, and every edge has at most two triangles among the kept and new ones.
        let position = |v: u32| if v >= base { out.new_vertices[(v - base) as usize] } else { x[v as usize] };
        let mut edges: Vec<(u32, u32)> = Vec::new();
        let kept = (0..topo.tris.len() as u32).filter(|t| !removed.contains(t)).map(|t| topo.tris[t as usize]);
        for t in kept.chain(out.new_triangles.iter().copied()) {
            let [a, b, c] = t.map(position);
            assert!(triangle_normal(&a, &b, &c).z > 0.0, "{t:?} is upside down");
            edges.extend((0..3).map(|k| (t[k].min(t[(k + 1) % 3]), t[k].max(t[(k + 1) % 3]))));
        }
        edges.sort_unstable();
        assert!(edges.windows(3).all(|w| w[0] != w[2]), "an edge has three triangles");
        // The new triangles cover the polygon between the chain and the lip: 3 × 0.7 below
        // the curve and a 1 × 0.3 triangle above it at each end (the lip rises to the
        // chain's ends on the edge). The rest of the removed squares stays open.
        let area: f64 = out
            .new_triangles
            .iter()
            .map(|t| {
                let [a, b, c] = t.map(position);
                0.5 * (b - a).cross(&(c - a)).z
            })
            .sum();
        assert!((area - 2.4).abs() < 1e-9, "{area}");
    }

    #[test]
    fn a_border_chain_around_both_sides_is_not_stitched_on_one_side() {
        // The removed area is the row of squares x = 1…6 between y = 1 and 2, and the one
        // square above it at x = 3…4, which reaches the mesh's edge y = 3: the curve runs
        // along the row (y = 1.6), and the one open chain goes from the edge at x = 3
        // around the curve's start, under the curve and around its end back to the edge
        // at x = 4. Its ends lie one near each end of the curve, but it borders kept
        // tissue on both sides (above the row beyond the square): no side is free of it.
        let (nx, ny) = (8, 4);
        let (topo, x) = grid_topology(nx, ny);
        let square = |i: u32, j: u32| [2 * (j * (nx - 1) + i), 2 * (j * (nx - 1) + i) + 1];
        let mut removed: Vec<u32> = (1..6).flat_map(|i| square(i, 1)).chain(square(3, 2)).collect();
        removed.sort_unstable();
        let curve: Vec<Vec3> = (0..5).map(|k| Vec3::new(1.5 + k as f64, 1.6, 0.0)).collect();
        // The kept triangle in the corner left of the square is an ear of the hole: taken
        // with it, as the caller does.
        for _ in 0..4 {
            match match_nodes(&flat_input(&topo, &x, &removed, &curve)) {
                Err(MatchError::Grow(more)) => {
                    removed.extend(more);
                    removed.sort_unstable();
                    removed.dedup();
                }
                Err(MatchError::Unsupported(why)) => return assert!(why.contains("both sides"), "{why}"),
                other => panic!("expected a refusal, got {other:?}"),
            }
        }
        panic!("the removed area kept growing");
    }
}
