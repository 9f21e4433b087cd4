//! Contact on the insides of surface triangles, for a tool thinner than the surface's
//! vertex spacing: such a tool fits between the vertices (they stand at the voxels'
//! face centres), so vertex contacts alone (crate::grid::hold) let it into the tissue
//! with no force: a 0.5 mm probe pressed between the 2 mm vertices of a block went
//! 30 mm in at 0 N. A wider tool meets vertices first and is held by them alone (see
//! `fits_between_vertices`), so nothing here changes its contacts.
//!
//! - **Under the tip**: while no vertex is held under the tool's tip (along its axis),
//!   the point of a triangle the tool reaches nearest its tip is taken as a material
//!   point (the triangle and barycentric weights) and held by the vertices' rule
//!   (`hold::contact`): pushed out of the tool along the normal it came in with, kept in
//!   the tool's frame while the contact lasts (a face the axis crossed within the step
//!   is held on its outer side, the side the tool came from). It is centred on the
//!   tool's axis by a spring of the contact's stiffness (friction's stick spring,
//!   anchored on the axis): it stands for the dent that rings a thin tip, whose walls
//!   push it back under the tip; alone and frictionless it slid off sideways and the
//!   probe went in. It lets go as a vertex does (the ray along its normal misses the
//!   tool, or it alone would push with more than the tool's rated force) or when its
//!   triangle is cut away; then the next is taken.
//! - **Along the shaft**: on each other triangle the capsule reaches into, none of
//!   whose vertices the tool touches, the ends of the axis's stretch over the triangle
//!   (where the axis lies beside it, its point nearest the axis) are taken as material
//!   points and held by the same rule, each kept while the contact lasts and drawn
//!   towards the axis across its normal by the same spring as the tip's (the groove's
//!   walls along a thin shaft). A flat triangle held at both ends of the stretch under
//!   a shaft cannot tilt across it; pushed only away from the axis, with nothing kept,
//!   a 0.5 mm shaft laid on a block and pressed in passed the faces once the penalty's
//!   give exceeded its radius (1.34 N at 3 mm in, then 0.56 N). A face the axis
//!   crosses is not taken anew (which side it belongs on is not known; a point taken
//!   before it was crossed remembers), nor a point the tip's ball pushes along the axis
//!   (that is the tip's). Each point rubs with its material's friction besides the
//!   drawing spring (super::BranchedGrid's contacts: a stick spring of its own anchor,
//!   decided before the solve).

use super::BranchedGrid;
use crate::grid::hold::{Capsule, Contact, contact_along_entry};
use crate::grid::surface::cell_weights;
use crate::math::{Matrix3, Vec3, barycentric_closest, segment_over_triangle, segment_triangle_closest, triangle_normal};

/// A material point on a triangle's inside that a tool holds.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct HeldFace {
    pub triangle: u32,
    pub barycentric: [f64; 3],
    /// The normal it came in with, in the tool's frame.
    pub normal_in_tool: Vec3,
    /// The step it was last held.
    pub step: u64,
    /// Where friction holds it (from the tool's tip, grid frame; crate::grid::friction):
    /// None until its first step has rubbed, and on frictionless tissue.
    pub anchor_from_tip: Option<Vec3>,
}

impl crate::hash::HashState for HeldFace {
    fn hash_state(&self, h: &mut crate::hash::StateHasher) {
        let Self { triangle, barycentric, normal_in_tool, step, anchor_from_tip } = self;
        (triangle, barycentric, normal_in_tool).hash_state(h);
        (step, anchor_from_tip).hash_state(h);
    }
}

/// A tool's contact on a triangle's inside this step.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(super) struct FaceContact {
    /// The material point, to hold next step.
    pub held: HeldFace,
    /// The point (grid frame), m.
    pub point: Vec3,
    /// The element the point moves with, and its weights there.
    pub element: u32,
    pub weights: [f64; 8],
    /// The triangle's vertex nearest the point (it stands for the contact where
    /// per-vertex data are asked for: the multirate patch's shares).
    pub vertex: u32,
    pub contact: Contact,
    /// Under the tip: from the point to the tool's axis across the normal (m), which a
    /// spring of the contact's stiffness closes (see `hold_face`).
    pub centring: Option<Vec3>,
}

/// A triangle a tool reaches into and where: its corners now, and the closest points of
/// the tool's axis and of the triangle (grid frame).
struct NearestFace {
    triangle: u32,
    corners: [Vec3; 3],
    on_axis: Vec3,
    point: Vec3,
}

/// Where a tool is this step, as the face contact needs it.
pub(super) struct ToolAt<'a> {
    pub tool: usize,
    pub capsule: &'a Capsule,
    pub tool_to_grid: &'a Matrix3<f64>,
    /// The tool's motion over the step (grid frame), if it moved from a known pose.
    pub moved: Option<Vec3>,
    pub max_depth: f64,
    pub lo: &'a Vec3,
    pub hi: &'a Vec3,
}

impl BranchedGrid {
    /// The face contacts of the tool at `at`, which touches the vertices `touching`, into
    /// `out`: none for a tool too wide to fit between the vertices (see
    /// [`Self::fits_between_vertices`]); else the points it held last step that it
    /// still holds, a new point under its tip where nothing holds it there, then new
    /// points along its shaft on the triangles it reaches into that hold none (by id).
    /// `candidates`: scratch.
    pub(super) fn face_contacts(&self, at: &ToolAt<'_>, touching: &[(u32, Contact)], candidates: &mut Vec<u32>, out: &mut Vec<FaceContact>) {
        out.clear();
        if !self.fits_between_vertices(at.capsule.half_size()) {
            return;
        }
        for held in self.held_faces[at.tool].iter().filter(|h| h.step + 1 >= self.step_index) {
            out.extend(self.hold_face(at, *held, Some(at.tool_to_grid * held.normal_in_tool)));
        }
        self.triangles_near(at.lo, at.hi, candidates);
        let holds = |faces: &[FaceContact], t: u32| faces.iter().any(|f| f.held.triangle == t);
        // A vertex or a point held by the tip face (along the axis) holds the tool;
        // those beside it (pushed off the shaft) do not.
        let tip_held = touching.iter().any(|(_, c)| at.capsule.pushes_with_tip(&c.entry)) || out.iter().any(|f| at.capsule.pushes_with_tip(&f.contact.entry));
        if !tip_held {
            let free = candidates.iter().copied().filter(|&t| !holds(out, t));
            if let Some(tip) = self.face_nearest_tip(at.capsule, free).and_then(|nearest| self.tip_face(at, nearest)) {
                out.push(tip);
            }
        }
        let taken = out.len();
        for &t in candidates.iter() {
            if holds(&out[..taken], t) || !self.live_triangle(t) {
                continue;
            }
            let vertices = self.surface.triangles[t as usize];
            if vertices.iter().any(|&v| touching.iter().any(|&(w, _)| w == v)) {
                continue;
            }
            let corners = self.corners(t);
            let (on_axis, point) = segment_triangle_closest(&at.capsule.a, &at.capsule.b, &corners);
            let distance = (point - on_axis).norm();
            // A face the axis crosses has been passed: which side it belongs on is not
            // known (a point taken before it was crossed remembers it).
            if distance >= at.capsule.radius || distance <= 1e-9 * at.capsule.radius {
                continue;
            }
            // A point the tip's ball reaches is the tip's to hold (above): held along
            // the axis here, a wall's point would stand in for the tip's.
            let new = |barycentric: [f64; 3]| {
                let held = HeldFace { triangle: t, barycentric, normal_in_tool: Vec3::zeros(), step: self.step_index, anchor_from_tip: None };
                self.hold_face(at, held, None).filter(|f| !at.capsule.pushes_with_tip(&f.contact.entry))
            };
            let before = out.len();
            if let Some((near, far)) = segment_over_triangle(&at.capsule.a, &at.capsule.b, &corners) {
                out.extend(new(near));
                let apart = (0..3).map(|k| corners[k] * (far[k] - near[k])).sum::<Vec3>().norm();
                if apart > 1e-3 * at.capsule.radius {
                    out.extend(new(far));
                }
            }
            // Neither end inside the tool (a wall beside it, the axis not over it): the
            // point nearest the axis.
            if out.len() == before {
                out.extend(new(barycentric_closest(&point, &corners[0], &corners[1], &corners[2])));
            }
        }
        self.plate_end_contacts(at, candidates, out);
    }

    /// A blade's plate has a flat end as wide as the blade, wider than one point under
    /// its tip can hold: on each triangle under the end's centre line (from edge to
    /// back, through the tip) that holds no point, the ends of that line's stretch over
    /// it are held by the end face (along the axis), as the points along the shaft are
    /// held by its side, also where a vertex of it is held (the end reaches past it).
    /// Without them the triangles under the rest of a 3 mm end were passed through one
    /// after another and the end went into a block at 1.5 N. A plate thick for the grid
    /// (closed forceps) is held so on several lines across its thickness ([`end_lines`]).
    /// A triangle the end held last step stays the end's (held along the axis) while the
    /// line lies over it, also once the point it held slid off the end's corner.
    fn plate_end_contacts(&self, at: &ToolAt<'_>, candidates: &[u32], out: &mut Vec<FaceContact>) {
        let Some(plate) = &at.capsule.plate else { return };
        let lines = end_lines(plate.half_thickness, self.topo.layout.smallest_side_m());
        for line in 0..lines {
            let across = if lines == 1 { 0.0 } else { (2.0 * line as f64 / (lines - 1) as f64 - 1.0) * END_LINES_REACH * plate.half_thickness };
            let middle = at.capsule.a + plate.flat * across;
            // A hair inside the end's corners: a point on the box's boundary is not
            // inside it, so the point a line reaching the corner found there (where the
            // tissue is pressed hardest) was taken by no contact.
            let along = END_WIDTH_REACH * plate.half_width;
            let (back, edge) = (middle - plate.edge * along, middle + plate.edge * along);
            for &t in candidates {
                if out.iter().any(|f| f.held.triangle == t) || !self.live_triangle(t) {
                    continue;
                }
                let Some((near, far)) = segment_over_triangle(&back, &edge, &self.corners(t)) else { continue };
                // A triangle the end held last step whose held point slid off it (the
                // tissue pressed under a thin end stretches outwards, and its material
                // point with it) is held by the end still, at the line's points: taken
                // anew, the one at the corner already beside the end came in through the
                // side by its path and was left to close over the end.
                let held_by_end = self.held_faces[at.tool].iter().any(|h| h.triangle == t && h.step + 1 >= self.step_index && at.capsule.pushes_with_tip(&(at.tool_to_grid * h.normal_in_tool)));
                let remembered = if held_by_end { at.capsule.out_of_tip() } else { None };
                for barycentric in [near, far] {
                    let held = HeldFace { triangle: t, barycentric, normal_in_tool: Vec3::zeros(), step: self.step_index, anchor_from_tip: None };
                    out.extend(self.hold_face(at, held, remembered).filter(|f| at.capsule.pushes_with_tip(&f.contact.entry)));
                }
            }
        }
    }

    /// Whether a tool whose thinnest half-size is `radius` (a capsule's radius, half a
    /// plate's thickness) can touch the surface between its vertices, under
    /// [`Self::held_by_vertices_from_m`]. Wider tools meet vertices first and are held by
    /// them alone.
    pub(super) fn fits_between_vertices(&self, radius: f64) -> bool {
        radius < self.held_by_vertices_from_m()
    }

    /// The thinnest half-size (a capsule's radius, half a plate's thickness) of a tool
    /// the surface's vertices hold, m: half the diagonal of a voxel's largest face. A
    /// ball narrower than that rests on a flat face of the surface without touching a
    /// vertex (they stand at the voxels' face centres), and the insides of the triangles
    /// hold it.
    pub fn held_by_vertices_from_m(&self) -> f64 {
        let mut sides = self.topo.layout.spacing_m;
        sides.sort_by(f64::total_cmp);
        0.5 * sides[1].hypot(sides[2])
    }

    /// A new point under the tip on the triangle `nearest` names: its point nearest the
    /// tool.
    fn tip_face(&self, at: &ToolAt<'_>, nearest: NearestFace) -> Option<FaceContact> {
        let NearestFace { triangle, corners, on_axis, point } = nearest;
        let barycentric = barycentric_closest(&point, &corners[0], &corners[1], &corners[2]);
        // A face the axis crosses (the tool came through it within the step, or a
        // point held before let go) is held on its outer side, the side the tool came
        // from: along the face's inward normal (along the axis, where the tip faces
        // it), not across the axis as a point on it would be by the vertices' rule.
        let crossed = (on_axis - point).norm() <= 1e-9 * at.capsule.radius;
        let inward = -triangle_normal(&corners[0], &corners[1], &corners[2]).try_normalize(1e-18)?;
        let remembered = crossed.then(|| at.capsule.face_normal(&inward));
        self.hold_face(at, HeldFace { triangle, barycentric, normal_in_tool: Vec3::zeros(), step: self.step_index, anchor_from_tip: None }, remembered)
    }

    /// `held`'s point under the vertices' rule: with the normal it came in with
    /// (`remembered`, grid frame), or as a new contact.
    fn hold_face(&self, at: &ToolAt<'_>, held: HeldFace, remembered: Option<Vec3>) -> Option<FaceContact> {
        if !self.live_triangle(held.triangle) {
            return None;
        }
        let vertices = self.surface.triangles[held.triangle as usize];
        let corners = self.corners(held.triangle);
        let point: Vec3 = (0..3).map(|k| corners[k] * held.barycentric[k]).sum();
        // Held along the normal it came in with even near the tool's surface (no
        // shallow band, where a vertex is pushed out radially to slide round the tool):
        // the drawing spring below acts across the normal, and a point that went in and
        // out of the band each step was drawn and not drawn by turns (the force on a
        // shaft laid on the block alternated step by step, growing to 0.4 N).
        let contact = contact_along_entry(at.capsule, &point, remembered, at.moved.map(|m| point + m), at.max_depth)?;
        let (element, weights, vertex) = self.embed_on_triangle(vertices, held.barycentric);
        let held = HeldFace { normal_in_tool: at.tool_to_grid.transpose() * contact.entry, step: self.step_index, ..held };
        // The point is drawn towards the axis across its normal: the spring stands for
        // the dent that rings a thin tip (or the groove along a thin shaft), whose walls
        // push the tissue back under the tool. Frictionless and alone, a point under the
        // tip slid off sideways (0.5 mm in 25 steps, the probe then went in), and points
        // under a shaft laid on the block slid off its side one after another (the
        // elements, 4 mm there, shear under a 1 mm tool): the force fell and rose by
        // turns (6.3, 4.9, 5.6, 3.7 N at 3, 4, 5, 6 mm in; docs/tool-tissue.md).
        // A blade's plate is drawn across its thickness only: across its width, under
        // its flat, the tissue is not in a groove.
        let centring = at.capsule.centring(&point).map(|(_, offset)| crate::grid::friction::tangent_projection(&contact.normal) * offset);
        Some(FaceContact { held, point, element, weights, vertex, contact, centring })
    }

    /// The points on triangles' insides tool `i` held this step, as the surface is now:
    /// each with its triangle's vertex of the largest weight (which names it), where it
    /// is (grid frame), and what is kept of it (the multirate patch publishes them).
    pub(super) fn held_face_points(&self, i: usize) -> impl Iterator<Item = (u32, Vec3, &HeldFace)> + '_ {
        self.held_faces[i].iter().filter(|h| h.step == self.step_index && self.live_triangle(h.triangle)).map(|h| {
            let vertices = self.surface.triangles[h.triangle as usize];
            let corners = self.corners(h.triangle);
            let point = (0..3).map(|k| corners[k] * h.barycentric[k]).sum();
            let heaviest = (0..3).fold(0, |best, k| if h.barycentric[k] > h.barycentric[best] { k } else { best });
            (vertices[heaviest], point, h)
        })
    }

    /// The surface triangles near [lo, hi] into `out`, each once, by id (the contacts'
    /// order is part of the state): those of the vertices near the box grown by a voxel
    /// (a triangle spans at most one, so one reaching the box has its vertices within a
    /// voxel of it). A triangle found through one live vertex may still have a dead one:
    /// see [`Self::live_triangle`].
    fn triangles_near(&self, lo: &Vec3, hi: &Vec3, out: &mut Vec<u32>) {
        out.clear();
        let voxel = Vec3::from(self.topo.layout.spacing_m);
        for v in self.surface_vertices_near(lo - voxel, hi + voxel) {
            out.extend_from_slice(self.surface.triangles_of(v as usize));
        }
        out.sort_unstable();
        out.dedup();
    }

    /// Whether triangle `t` is on the surface with all its vertices in live elements.
    fn live_triangle(&self, t: u32) -> bool {
        self.surface.triangle_alive[t as usize] && self.surface.triangles[t as usize].iter().all(|&v| self.surface.in_element(&self.topo, v as usize))
    }

    /// Among `candidates`, the live triangle `capsule` reaches into whose point nearest
    /// the capsule is nearest its tip (`capsule.a`; ties to the lowest id).
    fn face_nearest_tip(&self, capsule: &Capsule, candidates: impl Iterator<Item = u32>) -> Option<NearestFace> {
        let mut best: Option<(f64, NearestFace)> = None;
        for triangle in candidates {
            if !self.live_triangle(triangle) {
                continue;
            }
            let corners = self.corners(triangle);
            let (on_axis, point) = segment_triangle_closest(&capsule.a, &capsule.b, &corners);
            if (on_axis - point).norm() >= capsule.radius {
                continue;
            }
            let from_tip = (point - capsule.a).norm();
            if best.as_ref().is_none_or(|(d, _)| from_tip < *d) {
                best = Some((from_tip, NearestFace { triangle, corners, on_axis, point }));
            }
        }
        best.map(|(_, nearest)| nearest)
    }

    /// Triangle `t`'s corners where they are now (grid frame).
    fn corners(&self, t: u32) -> [Vec3; 3] {
        self.surface.triangles[t as usize].map(|v| self.surface.position(&self.topo, v as usize))
    }

    /// The point of the triangle `vertices` at barycentric `b`: the element it moves
    /// with, its weights there, and the vertex nearest it. Where the three vertices move
    /// with one element the weights are theirs interpolated (the point stays on the
    /// surface as drawn); else the point's rest position is embedded in the nearest
    /// vertex's element, as a vertex is in its own.
    fn embed_on_triangle(&self, vertices: [u32; 3], b: [f64; 3]) -> (u32, [f64; 8], u32) {
        let nearest = (0..3).max_by(|&x, &y| b[x].total_cmp(&b[y])).expect("three vertices");
        let voxel = |k: usize| self.surface.voxel[vertices[k] as usize] as usize;
        let element = self.topo.voxel_element[voxel(nearest)];
        let weights = if (0..3).all(|k| self.topo.voxel_element[voxel(k)] == element) {
            std::array::from_fn(|n| (0..3).map(|k| b[k] * self.surface.weights[vertices[k] as usize][n]).sum())
        } else {
            let rest: Vec3 = (0..3).map(|k| self.surface.rest[vertices[k] as usize] * b[k]).sum();
            cell_weights(&self.topo, voxel(nearest), rest)
        };
        (element, weights, vertices[nearest])
    }
}

/// How far along a plate's end, as a fraction of its half width, its lines of held
/// points reach: a hair inside its corners (see `plate_end_contacts`).
const END_WIDTH_REACH: f64 = 0.999;

/// How far across a plate's end, as a fraction of its half thickness, its outer lines
/// of held points reach (see [`end_lines`]).
const END_LINES_REACH: f64 = 0.8;

/// How many lines of points across its thickness hold a plate's end on a grid whose
/// smallest voxel side is `voxel_m`: its centre line alone where the strips beside it
/// (half its thickness `half_thickness_m`) are at most a quarter of a voxel wide, too
/// narrow for a triangle the line misses; else lines at most a fifth of a voxel apart
/// over [`END_LINES_REACH`] of its thickness (an odd number: one on the centre). With
/// the centre line alone, a 2 × 2 mm end (closed forceps) pressed into 2 mm voxels let
/// the surface close over it from 3.2 mm in while it pushed with under 1 N.
fn end_lines(half_thickness_m: f64, voxel_m: f64) -> usize {
    if half_thickness_m <= 0.25 * voxel_m {
        return 1;
    }
    let intervals = (2.0 * END_LINES_REACH * half_thickness_m / (0.2 * voxel_m)).ceil() as usize;
    2 * intervals.div_ceil(2) + 1
}

#[cfg(test)]
mod tests {
    #[test]
    fn a_plate_thin_for_the_grid_is_held_on_its_centre_line_a_thick_one_on_lines_a_fifth_of_a_voxel_apart() {
        use super::end_lines;
        // A 0.4 mm blade and 1 mm forceps' jaws on 2 mm voxels: the centre line.
        assert_eq!(end_lines(0.2e-3, 2e-3), 1);
        assert_eq!(end_lines(0.5e-3, 2e-3), 1);
        // Closed 2 mm jaws: 1.6 mm spanned by lines 0.4 mm apart.
        assert_eq!(end_lines(1e-3, 2e-3), 5);
        // Just over a quarter of a voxel: 0.82 mm spanned, lines at most 0.4 mm apart,
        // an even number of gaps (a line on the centre).
        assert_eq!(end_lines(0.51e-3, 2e-3), 5);
        assert_eq!(end_lines(1.6e-3, 2e-3), 9);
    }
}
