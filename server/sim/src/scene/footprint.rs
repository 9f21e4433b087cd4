//! How much memory a scene's tissue will take, estimated before it is built, so that a
//! server can refuse a session that would not fit instead of running out of memory
//! while building it.
//!
//! The estimate reads the scene and, for files, only their size (for a gzipped volume,
//! the uncompressed size gzip stores in its last four bytes): never the data. It is an
//! upper-leaning estimate: a volume is taken as one byte per voxel with every voxel
//! tissue (up to the grid's material limit). The per-node and per-voxel costs are the
//! peak resident memory of builds measured with `/usr/bin/time -f %M cutsim-server run
//! SCENE --steps 1`, rounded up: a skin patch of 1M nodes took 640 B a node; a solid box
//! of 51³ voxels 14.4 kB a voxel at level 0, 1.8 kB at level 1, 280 B at level 2,
//! 120 B at level 3 (101³ at level 1: 1.85 kB).

use std::io::{Read, Seek, SeekFrom};

use super::{ModelSpec, Scene, SceneError, SurfaceGeometry, VolumeSource};

/// Bytes a mass-spring node costs at its peak (the build's temporaries included).
pub const BYTES_PER_SKIN_NODE: u64 = 1024;
/// Bytes a tissue voxel of a branched grid costs at its peak (labels, condensation,
/// surface, the solver's data), by coarsening level 0, 1, 2, 3 and coarser.
pub const BYTES_PER_TISSUE_VOXEL: [u64; 4] = [16384, 2048, 320, 160];
/// Bytes per voxel of a label image held while it is read.
pub const BYTES_PER_IMAGE_VOXEL: u64 = 8;
/// Vertices in an OBJ file of this many bytes: a vertex line and two face lines take at
/// least this many bytes.
const OBJ_BYTES_PER_VERTEX: u64 = 40;

/// What a scene is estimated to take, and from what.
#[derive(Debug, Clone, PartialEq)]
pub struct Footprint {
    pub bytes: u64,
    /// e.g. "10,201 skin nodes" or "about 1.9M voxels".
    pub basis: String,
}

impl Scene {
    /// The memory its tissue is estimated to take; an error when a file it names cannot
    /// be looked at.
    pub fn footprint(&self) -> Result<Footprint, SceneError> {
        let file_len = |written: &str, at: &str| -> Result<u64, SceneError> {
            let path = self.resolve_path(written);
            std::fs::metadata(&path).map(|m| m.len()).map_err(|e| SceneError::new(&self.origin, at, format!("cannot read {}: {e}", path.display())))
        };
        match &self.model {
            ModelSpec::Msm(spec) => {
                let nodes = match &spec.geometry {
                    SurfaceGeometry::Patch(p) => (u64::from(p.resolution[0].get()) + 1) * (u64::from(p.resolution[1].get()) + 1),
                    SurfaceGeometry::Obj(o) => file_len(&o.path, "model.msm.geometry.obj.path")? / OBJ_BYTES_PER_VERTEX + 1,
                };
                Ok(Footprint { bytes: nodes * BYTES_PER_SKIN_NODE, basis: format!("{nodes} skin nodes") })
            }
            ModelSpec::BranchedGrid(spec) => {
                let at = "model.branched-grid.volume";
                let voxels = match &spec.volume {
                    VolumeSource::Nifti { path } => {
                        let resolved = self.resolve_path(path);
                        let len = file_len(path, at)?;
                        if path.ends_with(".gz") { gzip_uncompressed_len(&resolved).unwrap_or(len.saturating_mul(64)) } else { len }
                    }
                    // Base64 and zlib: at most a few voxels per byte.
                    VolumeSource::Vti { path, .. } => file_len(path, at)?.saturating_mul(8),
                    VolumeSource::Mesh { path, scale_m_per_unit, voxel_size_m, .. } => {
                        // The mesh's extent is not known without reading it: bounded by
                        // the image limit of the voxelizer.
                        let _ = (file_len(path, at)?, scale_m_per_unit, voxel_size_m);
                        crate::grid::MAX_MATERIAL_VOXELS as u64
                    }
                    VolumeSource::Box { size_m, voxel_size_m, .. } => size_m.iter().map(|s| (s.get() / voxel_size_m.get()).ceil() as u64 + 1).product(),
                    VolumeSource::Ellipsoid { radii_m, voxel_size_m, .. } => radii_m.iter().map(|r| (2.0 * r.get() / voxel_size_m.get()).ceil() as u64 + 1).product(),
                    VolumeSource::UTube { arm_voxels, gap_voxels, depth_voxels, base_voxels, arm_length_voxels, .. } => {
                        let width = 2 * u64::from(arm_voxels.get()) + u64::from(gap_voxels.get());
                        width * u64::from(depth_voxels.get()) * (u64::from(base_voxels.get()) + u64::from(arm_length_voxels.get()))
                    }
                };
                let voxels = match &spec.crop_voxels {
                    Some(c) => voxels.min((0..3).map(|i| u64::from(c.max[i].get()).saturating_sub(u64::from(c.min[i].get())) + 1).product()),
                    None => voxels,
                };
                let tissue = voxels.min(crate::grid::MAX_MATERIAL_VOXELS as u64);
                // "fidelity": "auto" builds its finest candidate, `level`, too.
                let level = spec.level.get();
                let per_voxel = BYTES_PER_TISSUE_VOXEL[(level as usize).min(BYTES_PER_TISSUE_VOXEL.len() - 1)];
                Ok(Footprint {
                    bytes: voxels.saturating_mul(BYTES_PER_IMAGE_VOXEL).saturating_add(tissue * per_voxel),
                    basis: format!("about {voxels} voxels at level {level}"),
                })
            }
        }
    }
}

/// The uncompressed length a gzip file records in its last four bytes (modulo 4 GiB:
/// volumes are limited far below that).
fn gzip_uncompressed_len(path: &std::path::Path) -> Option<u64> {
    let mut file = std::fs::File::open(path).ok()?;
    file.seek(SeekFrom::End(-4)).ok()?;
    let mut tail = [0u8; 4];
    file.read_exact(&mut tail).ok()?;
    Some(u64::from(u32::from_le_bytes(tail)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn scene(json: &str) -> Scene {
        Scene::from_json_str(json, "test", None).unwrap()
    }

    #[test]
    fn procedural_scenes_are_sized_from_their_parameters() {
        let patch = r#"{"name": "p", "model": {"msm": {"geometry": {"patch": {"size_m": [0.1, 0.1], "resolution": [99, 99]}},
            "material": {"young_pa": 1e5, "thickness_m": 0.002, "density_kg_per_m3": 1000}, "integrator": {"implicit-euler": {}}}}}"#;
        assert_eq!(scene(patch).footprint().unwrap(), Footprint { bytes: 10_000 * BYTES_PER_SKIN_NODE, basis: "10000 skin nodes".into() });
        let box_at = |level: u32| {
            format!(
                r#"{{"name": "b", "model": {{"branched-grid": {{"volume": {{"box": {{"size_m": [0.01, 0.01, 0.01], "voxel_size_m": 0.001}}}},
                "materials": [{{"label": 1, "name": "t", "young_pa": 1e4, "density_kg_per_m3": 1000}}], "level": {level}}}}}}}"#
            )
        };
        // 11³ voxels: the estimate counts a voxel more than the size along each side.
        let fine = scene(&box_at(0)).footprint().unwrap();
        assert_eq!(fine.bytes, 1331 * (BYTES_PER_IMAGE_VOXEL + BYTES_PER_TISSUE_VOXEL[0]));
        assert!(scene(&box_at(3)).footprint().unwrap().bytes < fine.bytes / 50, "coarse levels take far less");
    }
}
