//! The reference problems: small static problems on voxel meshes that an independent
//! finite-element code (scikit-fem, `tools/reference/`) solves too. Each is a
//! branched-grid scene plus a load; the mesh the reference solves is the scene's level-0
//! grid, exported as it is (nodes shared exactly where the grid shares them), so both
//! sides discretise the same body.
//!
//! A displacement is compared at sample points named by (voxel, corner): the corner of
//! a material voxel. That name does not depend on node numbering, and at a coarser
//! level the point is evaluated through the element that holds the voxel (the same
//! trilinear embedding the surface uses).

use serde_json::json;

use crate::grid::hex::{box_mass, box_stiffness};
use crate::grid::surface::cell_weights;
use crate::grid::topology::Topology;
use crate::grid::{GridParts, build_parts};
use crate::hash::{StateHasher, hash_hex};
use crate::math::Vec3;
use crate::quantity::AccelerationMPerS2;
use crate::scene::{ModelSpec, Scene, SceneError};

/// How a problem is loaded.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Load {
    /// The scene's gravity on every voxel's mass.
    Gravity,
    /// A uniform traction (Pa, grid frame) on the voxel faces at the body's far side
    /// along `axis` (its largest coordinate).
    Traction { axis: usize, traction_pa: Vec3 },
}

/// A reference problem.
#[derive(Debug, Clone)]
pub struct Problem {
    pub name: &'static str,
    pub summary: &'static str,
    /// A branched-grid scene; its `level` is overridden per use.
    pub scene: Scene,
    pub load: Load,
    /// The reference also computes the first eigenfrequency (a small body only).
    pub frequency: bool,
    /// The reference also solves with triquadratic hexahedra (a small body only).
    pub quadratic: bool,
    /// The reference also solves with Taylor–Hood hexahedra (a small body only): the
    /// non-locking reference for nearly incompressible material.
    pub mixed: bool,
    /// Keep every n-th node as a sample point (1: all).
    pub sample_stride: usize,
}

/// The block the cantilever problems use: 40 × 10 × 10 mm of 1.25 mm voxels (32 × 8 × 8),
/// clamped at x = 0, E = 1 MPa, ν = 0.3, ρ = 1000 kg/m³ — stiff enough that gravity bends
/// it by about 1 % of its length (the linear regime), soft tissue's order of magnitude.
pub fn cantilever_scene(name: &str) -> Scene {
    block_scene(name, [0.04, 0.01, 0.01], 1e6, 0.3, "-x")
}

/// The cantilever block at ν = 0.49 (nearly incompressible soft tissue).
pub fn incompressible_cantilever_scene(name: &str) -> Scene {
    block_scene(name, [0.04, 0.01, 0.01], 1e6, 0.49, "-x")
}

/// The cube the compression problem uses: 10 mm of 1.25 mm voxels (8³), held at z = 0,
/// E = 1 MPa, ν = 0.45 (nearly incompressible: it bulges).
pub fn cube_scene(name: &str) -> Scene {
    block_scene(name, [0.01, 0.01, 0.01], 1e6, 0.45, "-z")
}

fn block_scene(name: &str, size_m: [f64; 3], young_pa: f64, poisson: f64, side: &str) -> Scene {
    let text = json!({
        "name": name,
        "time_step_s": 0.001,
        "gravity_m_per_s2": [0.0, 0.0, -9.81],
        "model": { "branched-grid": {
            "volume": { "box": { "size_m": size_m, "voxel_size_m": 0.00125, "label": 1 } },
            "materials": [ { "label": 1, "name": "block", "young_pa": young_pa, "poisson": poisson, "density_kg_per_m3": 1000 } ],
            "level": 0,
            "damping": { "mass_per_s": 0, "stiffness_s": 0 },
            "solver": { "cg_max_iterations": 400, "cg_tolerance": 1e-6 },
            "fixed": [ { "side": { "side": side } } ]
        } }
    });
    Scene::from_json_str(&text.to_string(), &format!("reference problem {name}"), None).expect("the reference block scenes are valid")
}

/// Standard gravity, m/s².
pub const G: f64 = 9.81;

/// The scene with gravity `m_per_s2` pointing down (−z).
pub fn with_gravity_down(scene: &Scene, m_per_s2: f64) -> Scene {
    let mut scene = scene.clone();
    let a = |v: f64| AccelerationMPerS2::new(v).unwrap_or_else(|e| panic!("{e}"));
    scene.gravity_m_per_s2 = Some([a(0.0), a(0.0), a(-m_per_s2)]);
    scene
}

/// The bundled liver scene under gravity (it has none of its own).
pub fn liver_scene() -> Result<Scene, SceneError> {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../scenes/liver.json");
    Ok(with_gravity_down(&Scene::load(&path)?, G))
}

/// Every reference problem (the liver needs the shared data).
pub fn problems() -> Result<Vec<Problem>, SceneError> {
    Ok(vec![
        Problem {
            name: "cantilever-gravity",
            summary: "40 × 10 × 10 mm block clamped at one end, under its own weight",
            scene: cantilever_scene("cantilever-gravity"),
            load: Load::Gravity,
            frequency: true,
            quadratic: true,
            mixed: false,
            sample_stride: 1,
        },
        Problem {
            name: "cantilever-incompressible",
            summary: "the same block at ν = 0.49 under its own weight",
            scene: incompressible_cantilever_scene("cantilever-incompressible"),
            load: Load::Gravity,
            frequency: false,
            quadratic: false,
            mixed: true,
            sample_stride: 1,
        },
        Problem {
            name: "cantilever-tip",
            summary: "the same block under a 0.01 N downward load spread over its free end",
            scene: cantilever_scene("cantilever-tip"),
            load: Load::Traction { axis: 0, traction_pa: Vec3::new(0.0, 0.0, -100.0) },
            frequency: false,
            quadratic: true,
            mixed: false,
            sample_stride: 1,
        },
        Problem {
            name: "compressed-cube",
            summary: "10 mm cube (ν = 0.45) held at its base, 1 kPa pressing on its top",
            scene: cube_scene("compressed-cube"),
            load: Load::Traction { axis: 2, traction_pa: Vec3::new(0.0, 0.0, -1000.0) },
            frequency: false,
            quadratic: true,
            mixed: false,
            sample_stride: 1,
        },
        Problem {
            name: "liver-gravity",
            summary: "the liver of the CT label map (3 mm voxels, E = 6 kPa, ν = 0.45), held along its posterior side, under gravity",
            scene: liver_scene()?,
            load: Load::Gravity,
            frequency: false,
            quadratic: false,
            mixed: false,
            sample_stride: 16,
        },
    ])
}

impl Problem {
    /// The same problem with elements that resist volume change as `volumetric` says.
    pub fn with_volumetric(&self, volumetric: crate::scene::VolumetricSpec) -> Problem {
        let mut problem = self.clone();
        if let ModelSpec::BranchedGrid(spec) = &mut problem.scene.model {
            spec.volumetric = volumetric;
        }
        problem
    }

    /// The grid at coarsening level `level`, with its fixed nodes.
    pub fn parts(&self, level: u32) -> Result<GridParts, SceneError> {
        let scene = self.scene.with_grid_level(level);
        let ModelSpec::BranchedGrid(spec) = &scene.model else { unreachable!("reference problems are branched grids") };
        build_parts(&scene, spec)
    }

    /// Nodal loads of the grid `parts` (grid frame, N): gravity on the lumped mass, or the
    /// traction's consistent share at each face corner, carried to the element's nodes
    /// by the trilinear weights of the corner in it.
    pub fn loads(&self, parts: &GridParts) -> Vec<Vec3> {
        let topo = &parts.topo;
        let mut loads = vec![Vec3::zeros(); topo.nodes.len()];
        match self.load {
            Load::Gravity => {
                let g = parts.settings.gravity.unwrap_or_else(Vec3::zeros);
                for n in 0..topo.nodes.len() {
                    loads[n] = g * topo.nodes.mass[n];
                }
            }
            Load::Traction { axis, traction_pa } => {
                let layout = &topo.layout;
                let far = (0..topo.material.len()).filter(|&v| topo.material[v] != 0).map(|v| layout.voxel_coords(v)[axis]).max().unwrap_or(0);
                let (a1, a2) = ((axis + 1) % 3, (axis + 2) % 3);
                let area = layout.spacing_m[a1] * layout.spacing_m[a2];
                for v in 0..topo.material.len() {
                    if topo.material[v] == 0 || layout.voxel_coords(v)[axis] != far {
                        continue;
                    }
                    for corner in (0..8).filter(|c| (c >> axis) & 1 == 1) {
                        for (node, w) in embedding(topo, v, corner) {
                            loads[node] += traction_pa * (area / 4.0 * w);
                        }
                    }
                }
            }
        }
        loads
    }

    /// The sample points: per node of the level-0 grid, the first (voxel, corner) that
    /// names it, every `sample_stride`-th node kept.
    pub fn samples(&self, level0: &GridParts) -> Vec<(usize, usize)> {
        let topo = &level0.topo;
        let mut named = vec![false; topo.nodes.len()];
        let mut out = Vec::new();
        let mut seen = 0usize;
        for v in 0..topo.material.len() {
            let e = topo.voxel_element[v];
            if e == crate::grid::topology::NONE {
                continue;
            }
            for corner in 0..8 {
                let node = topo.elements.nodes[e as usize][corner] as usize;
                if !named[node] {
                    named[node] = true;
                    if seen.is_multiple_of(self.sample_stride) {
                        out.push((v, corner));
                    }
                    seen += 1;
                }
            }
        }
        out
    }

    /// The level-0 mesh, its loads and sample points, as the JSON the reference script
    /// reads; `digest` names this exact problem (the reference copies it).
    pub fn export(&self) -> Result<serde_json::Value, SceneError> {
        let parts = self.parts(0)?;
        let topo = &parts.topo;
        let ModelSpec::BranchedGrid(spec) = &self.scene.model else { unreachable!() };
        let nodes: Vec<[f64; 3]> = topo.nodes.rest.iter().map(|r| [r.x, r.y, r.z]).collect();
        let hexes: Vec<[u32; 8]> = (0..topo.elements.len()).filter(|&e| topo.elements.alive[e]).map(|e| topo.elements.nodes[e]).collect();
        let mut element_material = vec![0u16; topo.elements.len()];
        for v in 0..topo.material.len() {
            if topo.voxel_element[v] != crate::grid::topology::NONE {
                element_material[topo.voxel_element[v] as usize] = topo.material[v] - 1;
            }
        }
        let fixed: Vec<usize> = (0..topo.nodes.len()).filter(|&n| topo.nodes.fixed[n]).collect();
        let samples = self.samples(&parts);
        let sample_nodes: Vec<u32> = samples.iter().map(|&(v, c)| topo.elements.nodes[topo.voxel_element[v] as usize][c]).collect();
        let materials: Vec<serde_json::Value> = spec
            .materials
            .iter()
            .map(|m| json!({ "young_pa": m.young_pa.get(), "poisson": m.poisson.get(), "density_kg_per_m3": m.density_kg_per_m3.get() }))
            .collect();
        let (gravity, traction) = match self.load {
            Load::Gravity => (parts.settings.gravity.map(|g| [g.x, g.y, g.z]), None),
            Load::Traction { axis, traction_pa } => {
                let far = topo.nodes.rest.iter().map(|r| r[axis]).fold(f64::NEG_INFINITY, f64::max);
                (None, Some(json!({ "axis": axis, "coordinate_m": far, "traction_pa": [traction_pa.x, traction_pa.y, traction_pa.z] })))
            }
        };
        let mut hasher = StateHasher::new();
        for r in &nodes {
            r.iter().for_each(|&c| hasher.write_f64(c));
        }
        for h in &hexes {
            h.iter().for_each(|&n| hasher.write_u32(n));
        }
        fixed.iter().for_each(|&n| hasher.write_u64(n as u64));
        samples.iter().for_each(|&(v, c)| hasher.write_u64((v * 8 + c) as u64));
        for m in &spec.materials {
            [m.young_pa.get(), m.poisson.get(), m.density_kg_per_m3.get()].iter().for_each(|&x| hasher.write_f64(x));
        }
        gravity.iter().flatten().for_each(|&g| hasher.write_f64(g));
        if let Load::Traction { axis, traction_pa } = self.load {
            hasher.write_u64(axis as u64);
            traction_pa.iter().for_each(|&t| hasher.write_f64(t));
        }
        Ok(json!({
            "name": self.name,
            "summary": self.summary,
            "digest": hash_hex(hasher.finish()),
            "nodes": nodes,
            "hexes": hexes,
            "element_material": element_material,
            "materials": materials,
            "fixed": fixed,
            "gravity_m_per_s2": gravity,
            "traction": traction,
            "frequency": self.frequency,
            "quadratic": self.quadratic,
            "mixed": self.mixed,
            "samples": samples,
            "sample_nodes": sample_nodes,
        }))
    }
}

/// The nodes (and weights) whose displacements interpolate corner `corner` of voxel `v`
/// in the element holding the voxel (the surface's embedding, `cell_weights`).
pub fn embedding(topo: &Topology, v: usize, corner: usize) -> impl Iterator<Item = (usize, f64)> + '_ {
    let e = topo.voxel_element[v] as usize;
    let half = Vec3::from(topo.layout.spacing_m) * 0.5;
    let offset = Vec3::new(((corner & 1) as f64 * 2.0 - 1.0) * half.x, (((corner >> 1) & 1) as f64 * 2.0 - 1.0) * half.y, (((corner >> 2) & 1) as f64 * 2.0 - 1.0) * half.z);
    let weights = cell_weights(topo, v, topo.voxel_centre(v) + offset);
    (0..8).filter(move |&k| weights[k] != 0.0).map(move |k| (topo.elements.nodes[e][k] as usize, weights[k]))
}

/// Whether voxel `v` (one with an element) lies in a held piece, `held` being
/// [`crate::grid::support::held_pieces`] of `topo`.
pub fn in_held_piece(topo: &Topology, held: &[bool], v: usize) -> bool {
    held[topo.elements.nodes[topo.voxel_element[v] as usize][0] as usize]
}

/// The samples that lie in a held piece of `topo` ([`crate::grid::support::held_pieces`]):
/// a free piece has no static answer to compare.
pub fn held_samples(topo: &Topology, samples: &[(usize, usize)]) -> Vec<(usize, usize)> {
    let held = crate::grid::support::held_pieces(topo);
    samples.iter().copied().filter(|&(v, _)| in_held_piece(topo, &held, v)).collect()
}

/// The displacement (grid frame) at each sample point of the grid `topo` in its current
/// state.
pub fn sample_displacements(topo: &Topology, samples: &[(usize, usize)]) -> Vec<Vec3> {
    samples.iter().map(|&(v, c)| embedding(topo, v, c).map(|(n, w)| (topo.nodes.x[n] - topo.nodes.rest[n]) * w).sum()).collect()
}

/// Replaces every element's stiffness and mass by the full cell's, scaled by the
/// fraction of the cell its voxels fill (the fill-ratio weighting of common sparse
/// grids), instead of the condensed matrices. Several materials in one element: their
/// voxel-weighted mean modulus and density (the mean Poisson ratio).
pub fn apply_fill_ratio_weighting(parts: &mut GridParts) {
    let topo = &mut parts.topo;
    let cell = topo.layout.cell_size_m();
    let cell_voxels = (topo.layout.side * topo.layout.side * topo.layout.side) as f64;
    let mut sums = vec![[0.0f64; 4]; topo.elements.len()];
    for v in 0..topo.material.len() {
        let e = topo.voxel_element[v];
        if e != crate::grid::topology::NONE {
            let m = &parts.materials[topo.material[v] as usize - 1];
            let s = &mut sums[e as usize];
            s[0] += m.young_pa;
            s[1] += m.poisson;
            s[2] += m.density_kg_per_m3;
            s[3] += 1.0;
        }
    }
    for e in 0..topo.elements.len() {
        let [young, poisson, density, count] = sums[e];
        if count == 0.0 {
            continue;
        }
        let fill = count / cell_voxels;
        topo.elements.stiffness[e] = box_stiffness([cell.x, cell.y, cell.z], young / count, poisson / count) * fill;
        topo.elements.mass[e] = box_mass(cell.x * cell.y * cell.z * fill, density / count);
    }
    // The lumped masses (and so gravity) follow the weighted matrices.
    topo.nodes.mass.iter_mut().for_each(|m| *m = 0.0);
    for e in 0..topo.elements.len() {
        if topo.elements.alive[e] {
            for i in 0..8 {
                topo.nodes.mass[topo.elements.nodes[e][i] as usize] += topo.elements.mass[e].row(i).sum();
            }
        }
    }
}
