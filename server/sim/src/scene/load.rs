//! Reading scenes: JSON text → [`Scene`], with errors that say where and why.

use std::path::{Path, PathBuf};

use super::Scene;

/// A scene that cannot be used: where (file, JSON path) and why (with units and ranges).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
#[error("{origin}: {}: {message}", if path.is_empty() { "(scene)" } else { path.as_str() })]
pub struct SceneError {
    /// The scene file, or "inline scene".
    pub origin: String,
    /// JSON path of the offending value, e.g. `model.msm.material.young_pa`.
    pub path: String,
    pub message: String,
}

impl SceneError {
    pub fn new(origin: impl Into<String>, path: impl Into<String>, message: impl Into<String>) -> Self {
        Self { origin: origin.into(), path: path.into(), message: message.into() }
    }
}

impl Scene {
    /// Parses a scene from JSON text. `origin` names it in errors; relative paths are
    /// resolved against `base_dir` (the current directory when `None`).
    pub fn from_json_str(text: &str, origin: &str, base_dir: Option<&Path>) -> Result<Scene, SceneError> {
        let deserializer = &mut serde_json::Deserializer::from_str(text);
        let mut scene: Scene = serde_path_to_error::deserialize(deserializer).map_err(|err| {
            let path = err.path().to_string();
            let inner = err.into_inner();
            let message = explain_json_error(text, &inner);
            SceneError::new(origin, if path == "." { String::new() } else { path }, message)
        })?;
        scene.base_dir = base_dir.map(Path::to_path_buf);
        scene.origin = origin.to_owned();
        scene.check_cross_fields(origin)?;
        Ok(scene)
    }

    /// Reads and parses a scene file.
    pub fn load(path: &Path) -> Result<Scene, SceneError> {
        let origin = path.display().to_string();
        let text = std::fs::read_to_string(path)
            .map_err(|e| SceneError::new(&origin, "", format!("cannot read the scene file: {e}")))?;
        Scene::from_json_str(&text, &origin, path.parent())
    }

    /// Resolves a path written in this scene: `data:<path>` is inside the data directory
    /// (see [`data_dir`]); anything else is relative to the scene file.
    pub fn resolve_path(&self, written: &str) -> PathBuf {
        if let Some(inside) = written.strip_prefix("data:") {
            return data_dir().join(inside);
        }
        match &self.base_dir {
            Some(dir) => dir.join(written),
            None => PathBuf::from(written),
        }
    }

    /// The files the scene reads, as written, with their JSON paths.
    pub fn file_references(&self) -> Vec<(&'static str, &str)> {
        use super::{ModelSpec, SurfaceGeometry, VolumeSource};
        match &self.model {
            ModelSpec::Msm(m) => match &m.geometry {
                SurfaceGeometry::Obj(obj) => vec![("model.msm.geometry.obj.path", obj.path.as_str())],
                SurfaceGeometry::Patch(_) => vec![],
            },
            ModelSpec::BranchedGrid(g) => match &g.volume {
                VolumeSource::Nifti { path } => vec![("model.branched-grid.volume.nifti.path", path.as_str())],
                VolumeSource::Vti { path, .. } => vec![("model.branched-grid.volume.vti.path", path.as_str())],
                VolumeSource::Mesh { path, .. } => vec![("model.branched-grid.volume.mesh.path", path.as_str())],
                VolumeSource::Box { .. } | VolumeSource::Ellipsoid { .. } | VolumeSource::UTube { .. } => vec![],
            },
        }
    }

    /// For a scene that came over the network: it may read only the shared data
    /// directory (`data:<path>`, no `..`), never an arbitrary file of the server.
    pub fn check_network_file_references(&self, origin: &str) -> Result<(), SceneError> {
        for (path, written) in self.file_references() {
            let inside = written.strip_prefix("data:");
            let safe = inside.is_some_and(|p| !p.starts_with('/') && !p.split(['/', '\\']).any(|part| part == ".."));
            if !safe {
                return Err(SceneError::new(
                    origin,
                    path,
                    format!("a scene sent to the server may read only the shared data directory: write \"data:<path inside it>\" without \"..\", not {written:?}"),
                ));
            }
        }
        Ok(())
    }

    fn check_cross_fields(&self, origin: &str) -> Result<(), SceneError> {
        if self.name.trim().is_empty() {
            return Err(SceneError::new(origin, "name", "the scene needs a non-empty name"));
        }
        for (i, tool) in self.tools.iter().enumerate() {
            if tool.name.trim().is_empty() {
                return Err(SceneError::new(origin, format!("tools[{i}].name"), "a tool needs a non-empty name"));
            }
            if let super::ToolShapeSpec::Blade { width_m, thickness_m, .. } = &tool.shape
                && thickness_m.get() >= width_m.get()
            {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].shape.blade.thickness_m"),
                    format!("a blade is a plate thinner than it is wide: thickness {} m, width {} m", thickness_m.get(), width_m.get()),
                ));
            }
            if matches!(tool.shape, super::ToolShapeSpec::Forceps { .. }) && tool.can_cut {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].can_cut"),
                    "forceps are blunt: their jaws press and rub but do not cut (their button closes them); set can_cut to false, or use a blade to cut",
                ));
            }
            if let super::ToolShapeSpec::Forceps { length_m, grip_length_m, .. } = &tool.shape
                && grip_length_m.get() > length_m.get()
            {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].shape.forceps.grip_length_m"),
                    format!("the jaws grip along their own length at most: grip length {} m, jaws {} m long", grip_length_m.get(), length_m.get()),
                ));
            }
            if let Some(j) = self.tools[..i].iter().position(|t| t.name == tool.name) {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].name"),
                    format!("tool name {:?} is already used by tools[{j}]; tool names must be unique", tool.name),
                ));
            }
        }
        if let Some(task) = &self.task {
            task.compile(&crate::tool::tool_shapes(self), origin)?;
        }
        match &self.model {
            super::ModelSpec::Msm(msm) => {
                for (i, fixed) in msm.fixed.iter().enumerate() {
                    if let super::FixedSpec::Box { min_m, max_m, .. } = fixed {
                        check_box(origin, &format!("model.msm.fixed[{i}].box"), min_m, max_m)?;
                    }
                }
                if let Some(friction) = &msm.material.friction
                    && friction.dynamic_coefficient.get() > friction.static_coefficient.get()
                {
                    return Err(SceneError::new(
                        origin,
                        "model.msm.material.friction.dynamic_coefficient",
                        format!(
                            "the dynamic friction coefficient ({}) must not exceed the static one ({}): skin that slides would hold harder than skin that sticks",
                            friction.dynamic_coefficient.get(),
                            friction.static_coefficient.get()
                        ),
                    ));
                }
                if let Some(i) = self.tools.iter().position(|t| t.cutting_shape.is_some()) {
                    return Err(SceneError::new(
                        origin,
                        format!("tools[{i}].cutting_shape"),
                        "a cutting shape is used by the branched-grid model only; the mass-spring skin cuts along the blade's swept path",
                    ));
                }
            }
            super::ModelSpec::BranchedGrid(grid) => self.check_branched_grid(origin, grid)?,
        }
        Ok(())
    }
}

impl Scene {
    fn check_branched_grid(&self, origin: &str, grid: &super::BranchedGridSpec) -> Result<(), SceneError> {
        let at = |path: String, message: String| SceneError::new(origin, format!("model.branched-grid.{path}"), message);
        if grid.materials.is_empty() {
            return Err(at("materials".into(), "give at least one label with its material".into()));
        }
        for (i, m) in grid.materials.iter().enumerate() {
            if let Some(j) = grid.materials[..i].iter().position(|o| o.label == m.label) {
                return Err(at(format!("materials[{i}].label"), format!("label {} already has a material in materials[{j}]", m.label.get())));
            }
        }
        for (i, fixed) in grid.fixed.iter().enumerate() {
            match fixed {
                super::GridFixedSpec::Box { min_m, max_m } => check_box(origin, &format!("model.branched-grid.fixed[{i}].box"), min_m, max_m)?,
                super::GridFixedSpec::Side { side } => {
                    if !["-x", "+x", "-y", "+y", "-z", "+z"].contains(&side.as_str()) {
                        return Err(at(format!("fixed[{i}].side.side"), format!("a side is one of -x, +x, -y, +y, -z, +z; got {side:?}")));
                    }
                }
                super::GridFixedSpec::Labels { labels } => {
                    if let Some(l) = labels.iter().find(|l| !grid.materials.iter().any(|m| m.label == **l)) {
                        return Err(at(format!("fixed[{i}].labels.labels"), format!("label {} has no material, so none of its voxels is built", l.get())));
                    }
                }
            }
        }
        if let Some(crop) = &grid.crop_voxels {
            for a in 0..3 {
                if crop.min[a].get() > crop.max[a].get() {
                    return Err(at("crop_voxels".into(), format!("min[{a}] = {} is above max[{a}] = {}", crop.min[a].get(), crop.max[a].get())));
                }
            }
        }
        for (i, material) in grid.materials.iter().enumerate() {
            if let Some(friction) = &material.friction
                && friction.dynamic_coefficient.get() > friction.static_coefficient.get()
            {
                return Err(at(
                    format!("materials[{i}].friction.dynamic_coefficient"),
                    format!(
                        "the dynamic friction coefficient ({}) must not exceed the static one ({}): tissue that slides would hold harder than tissue that sticks",
                        friction.dynamic_coefficient.get(),
                        friction.static_coefficient.get()
                    ),
                ));
            }
        }
        for (i, tool) in self.tools.iter().enumerate() {
            // How far across its axis a cutting shape may reach: less than a cylinder's
            // radius, at most a blade's half width (the slit its edge opens).
            let (reach_m, length_m, tip) = match &tool.shape {
                super::ToolShapeSpec::Cylinder { radius_m, length_m, tip } => (radius_m.get() * (1.0 - 1e-12), length_m, tip),
                super::ToolShapeSpec::Blade { width_m, length_m, .. } => (0.5 * width_m.get(), length_m, &None),
                super::ToolShapeSpec::Forceps { width_m, length_m, .. } => (0.5 * width_m.get(), length_m, &None),
            };
            if *tip == Some(super::TipSpec::Flat) {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].shape.cylinder.tip"),
                    "the branched grid's tools are capsules (a round tip against its voxels); a flat tip is built for the mass-spring skin only: use \"round\" or leave it out",
                ));
            }
            let Some(inner) = &tool.cutting_shape else { continue };
            let super::ToolShapeSpec::Cylinder { radius_m: r_in, length_m: l_in, tip: inner_tip } = inner else {
                return Err(SceneError::new(origin, format!("tools[{i}].cutting_shape"), "a cutting shape is a cylinder"));
            };
            if *inner_tip == Some(super::TipSpec::Flat) {
                return Err(SceneError::new(origin, format!("tools[{i}].cutting_shape.cylinder.tip"), "a cutting shape is a capsule (a round tip): use \"round\" or leave it out"));
            }
            if r_in.get() > reach_m || l_in.get() > length_m.get() {
                return Err(SceneError::new(
                    origin,
                    format!("tools[{i}].cutting_shape"),
                    format!(
                        "the cutting shape (radius {} m, length {} m) must fit inside the tool's shape (a cylinder's radius or a blade's half width {} m, length {} m): a smaller radius, no longer",
                        r_in.get(), l_in.get(), reach_m, length_m.get()
                    ),
                ));
            }
            if !tool.can_cut {
                return Err(SceneError::new(origin, format!("tools[{i}].cutting_shape"), "a tool with a cutting shape must have can_cut: true"));
            }
        }
        Ok(())
    }
}

fn check_box(origin: &str, path: &str, min_m: &[crate::quantity::CoordinateM; 3], max_m: &[crate::quantity::CoordinateM; 3]) -> Result<(), SceneError> {
    for axis in 0..3 {
        if min_m[axis].get() > max_m[axis].get() {
            return Err(SceneError::new(
                origin,
                path,
                format!(
                    "min_m[{axis}] = {} m is above max_m[{axis}] = {} m; a box needs min ≤ max on every axis",
                    min_m[axis].get(),
                    max_m[axis].get()
                ),
            ));
        }
    }
    Ok(())
}

/// The directory of shared anatomical data that `data:` paths point into:
/// `$CUTSIM_DATA_DIR` when set, else `../shared/data` beside the repository.
pub fn data_dir() -> PathBuf {
    match std::env::var_os("CUTSIM_DATA_DIR") {
        Some(dir) => PathBuf::from(dir),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data"),
    }
}

/// serde_json's message, made plainer where JSON's rules surprise people.
fn explain_json_error(text: &str, err: &serde_json::Error) -> String {
    let base = err.to_string();
    if err.is_syntax() {
        // JSON has no NaN or Infinity; serde_json reports them as a bare syntax error.
        let line = text.lines().nth(err.line().saturating_sub(1)).unwrap_or("");
        let tail = line.get(err.column().saturating_sub(1)..).unwrap_or("");
        let head = line.get(..err.column().saturating_sub(1)).unwrap_or("");
        let near = format!("{}{}", head.rsplit([' ', ':', ',', '[']).next().unwrap_or(""), tail);
        let near = near.trim_start_matches('-');
        if near.starts_with("NaN") || near.starts_with("Infinity") || near.starts_with("inf") {
            return format!("NaN and Infinity are not numbers JSON allows; give a finite value ({base})");
        }
    }
    base
}

/// The JSON Schema of scene files, generated from the types (docs/scene.schema.json).
pub fn json_schema() -> serde_json::Value {
    let schema = schemars::schema_for!(Scene);
    serde_json::to_value(schema).expect("schema serialises")
}

/// Finds a scene by bundled name (`skin-patch` → `<dir>/skin-patch.json` in the first
/// directory that has it) or by path (anything containing a `/` or ending in `.json`).
/// A bundled scene by name only (what the network may ask for): letters, digits, '-'
/// and '_', looked up in the scene directories.
pub fn resolve_bundled_scene(name: &str, scene_dirs: &[PathBuf]) -> Result<PathBuf, SceneError> {
    if name.contains('/') || name.contains('\\') || name.ends_with(".json") {
        return Err(SceneError::new(name, "", "give a bundled scene's name (letters, digits, '-' and '_'), not a path; a scene of your own goes in scene_json"));
    }
    resolve_scene_path(name, scene_dirs)
}

pub fn resolve_scene_path(name_or_path: &str, scene_dirs: &[PathBuf]) -> Result<PathBuf, SceneError> {
    let looks_like_path = name_or_path.contains('/') || name_or_path.ends_with(".json");
    if looks_like_path {
        let path = PathBuf::from(name_or_path);
        return if path.is_file() {
            Ok(path)
        } else {
            Err(SceneError::new(name_or_path, "", "no such scene file"))
        };
    }
    let valid_name = !name_or_path.is_empty()
        && name_or_path.chars().all(|c| c.is_ascii_alphanumeric() || c == '-' || c == '_');
    if !valid_name {
        return Err(SceneError::new(
            name_or_path,
            "",
            "a bundled scene name uses only letters, digits, '-' and '_'",
        ));
    }
    for dir in scene_dirs {
        let candidate = dir.join(format!("{name_or_path}.json"));
        if candidate.is_file() {
            return Ok(candidate);
        }
    }
    let known = bundled_scene_names(scene_dirs);
    Err(SceneError::new(
        name_or_path,
        "",
        format!("unknown scene; bundled scenes are: {}", if known.is_empty() { "(none found)".into() } else { known.join(", ") }),
    ))
}

/// Names of the `.json` scenes in the given directories, sorted.
pub fn bundled_scene_names(scene_dirs: &[PathBuf]) -> Vec<String> {
    let mut names: Vec<String> = scene_dirs
        .iter()
        .filter_map(|d| std::fs::read_dir(d).ok())
        .flatten()
        .filter_map(|e| e.ok())
        .filter_map(|e| {
            let name = e.file_name().to_string_lossy().into_owned();
            name.strip_suffix(".json").map(str::to_owned)
        })
        .collect();
    names.sort();
    names.dedup();
    names
}
