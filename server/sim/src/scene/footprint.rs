//! How much memory a scene's tissue will take, estimated before it is built, so that a
//! server can refuse a session that would not fit instead of running out of memory
//! while building it.
//!
//! The estimate reads the scene and, for files, only their size (for a gzipped volume,
//! the uncompressed size gzip stores in its last four bytes): never the data. It is an
//! upper-leaning estimate: a volume is taken as one byte per voxel with every voxel
//! tissue (up to the grid's material limit). The per-node and per-voxel costs were
//! measured on the bundled scenes (peak resident memory of a build, docs/server.md).

use std::io::{Read, Seek, SeekFrom};

use super::{ModelSpec, Scene, SceneError, SurfaceGeometry, VolumeSource};

/// Bytes a mass-spring node costs at its peak (the build's temporaries included).
pub const BYTES_PER_SKIN_NODE: u64 = 4096;
/// Bytes a tissue voxel of a branched grid costs at its peak (labels, condensation,
/// surface, the solver's vectors).
pub const BYTES_PER_TISSUE_VOXEL: u64 = 2048;
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
                Ok(Footprint {
                    bytes: voxels.saturating_mul(BYTES_PER_IMAGE_VOXEL).saturating_add(tissue * BYTES_PER_TISSUE_VOXEL),
                    basis: format!("about {voxels} voxels"),
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
