//! Label volumes: a 3D image with one integer label per voxel (0 = empty), its voxel
//! spacing, origin and orientation — what the branched-grid model is built from.
//!
//! Sources: NIfTI-1 ([`nifti`]), VTK XML ImageData ([`vti`]), closed surface meshes
//! voxelized at a chosen voxel size ([`voxelize`]) and procedural shapes
//! ([`procedural`]). Every reader returns the same [`LabelVolume`], so one volume
//! written in both file formats reads back identically.
//!
//! Conventions: voxel (i, j, k) has its centre at `origin + D · (i·sx, j·sy, k·sz)` in
//! metres, D the direction matrix (its columns are the world directions of the i, j and
//! k axes). Labels are stored with i fastest, then j, then k (the NIfTI and VTK order).

pub mod nifti;
pub mod procedural;
pub mod voxelize;
pub mod vti;

use crate::math::{Matrix3, Vec3};

/// A label image. See the module documentation for the conventions.
#[derive(Debug, Clone, PartialEq)]
pub struct LabelVolume {
    pub dims: [usize; 3],
    /// Voxel size along i, j, k, m.
    pub spacing_m: [f64; 3],
    /// Centre of voxel (0, 0, 0) in world coordinates, m.
    pub origin_m: Vec3,
    /// Orthonormal; columns are the world directions of the i, j, k axes.
    pub direction: Matrix3<f64>,
    /// One label per voxel, i fastest.
    pub labels: Vec<u16>,
}

/// Largest number of voxels a volume may have (about 1.1 GB of labels as u16 would be
/// far beyond what the physics can use; this refuses absurd headers early).
pub const MAX_VOXELS: usize = 512 * 512 * 512;

impl LabelVolume {
    /// An empty (all 0) volume, axis-aligned.
    pub fn new(dims: [usize; 3], spacing_m: [f64; 3], origin_m: Vec3) -> Self {
        Self { dims, spacing_m, origin_m, direction: Matrix3::identity(), labels: vec![0; dims[0] * dims[1] * dims[2]] }
    }

    pub fn len(&self) -> usize {
        self.labels.len()
    }

    pub fn is_empty(&self) -> bool {
        self.labels.is_empty()
    }

    pub fn index(&self, i: usize, j: usize, k: usize) -> usize {
        i + self.dims[0] * (j + self.dims[1] * k)
    }

    pub fn get(&self, i: usize, j: usize, k: usize) -> u16 {
        self.labels[self.index(i, j, k)]
    }

    /// The label at signed coordinates; 0 outside the volume.
    pub fn get_or_empty(&self, i: i64, j: i64, k: i64) -> u16 {
        if i < 0 || j < 0 || k < 0 || i >= self.dims[0] as i64 || j >= self.dims[1] as i64 || k >= self.dims[2] as i64 {
            0
        } else {
            self.get(i as usize, j as usize, k as usize)
        }
    }

    pub fn set(&mut self, i: usize, j: usize, k: usize, label: u16) {
        let index = self.index(i, j, k);
        self.labels[index] = label;
    }

    /// World position of a point given in voxel-index coordinates (voxel centres at integers), m.
    pub fn world_of(&self, ijk: Vec3) -> Vec3 {
        self.origin_m + self.direction * Vec3::new(ijk.x * self.spacing_m[0], ijk.y * self.spacing_m[1], ijk.z * self.spacing_m[2])
    }

    /// Voxels with this label.
    pub fn count(&self, label: u16) -> usize {
        self.labels.iter().filter(|&&l| l == label).count()
    }

    /// The distinct non-zero labels present, sorted, with their voxel counts.
    pub fn histogram(&self) -> Vec<(u16, usize)> {
        let mut counts = std::collections::BTreeMap::new();
        for &l in &self.labels {
            if l != 0 {
                *counts.entry(l).or_insert(0usize) += 1;
            }
        }
        counts.into_iter().collect()
    }

    /// Checks the invariants every reader guarantees.
    pub fn check(&self) -> Result<(), String> {
        let n = self.dims.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d)).ok_or("the volume's dimensions overflow")?;
        if self.dims.contains(&0) {
            return Err(format!("the volume has a zero dimension: {:?}", self.dims));
        }
        if n > MAX_VOXELS {
            return Err(format!("the volume has {n} voxels; at most {MAX_VOXELS} are supported (crop it)"));
        }
        if self.labels.len() != n {
            return Err(format!("{} labels for {:?} voxels", self.labels.len(), self.dims));
        }
        if let Some(s) = self.spacing_m.iter().find(|s| !(s.is_finite() && **s > 0.0)) {
            return Err(format!("voxel spacing must be positive and finite, got {s} m"));
        }
        if !self.origin_m.iter().all(|c| c.is_finite()) {
            return Err("the volume's origin is not finite".into());
        }
        let gram = self.direction.transpose() * self.direction;
        if !(gram - Matrix3::identity()).iter().all(|e| e.abs() < 1e-4) {
            return Err("the volume's axes are not orthonormal (sheared or oblique scaling is not supported)".into());
        }
        Ok(())
    }

    /// Reorders the voxels so that the direction matrix is a rotation (determinant +1):
    /// a mirrored image (common for LPS/RAS conversions) has its i axis reversed. The
    /// voxels stay where they are in the world.
    pub fn to_right_handed(mut self) -> Self {
        if self.direction.determinant() > 0.0 {
            return self;
        }
        let [nx, ny, nz] = self.dims;
        let mut flipped = vec![0u16; self.labels.len()];
        for k in 0..nz {
            for j in 0..ny {
                for i in 0..nx {
                    flipped[self.index(nx - 1 - i, j, k)] = self.get(i, j, k);
                }
            }
        }
        self.origin_m = self.world_of(Vec3::new((nx - 1) as f64, 0.0, 0.0));
        let mut column = self.direction.column_mut(0);
        column.neg_mut();
        self.labels = flipped;
        self
    }

    /// The sub-volume of voxels `min..=max` (clamped to the volume); errors when empty.
    pub fn crop(&self, min: [usize; 3], max: [usize; 3]) -> Result<Self, String> {
        let hi: Vec<usize> = (0..3).map(|a| max[a].min(self.dims[a] - 1)).collect();
        if (0..3).any(|a| min[a] > hi[a]) {
            return Err(format!(
                "the crop region {min:?}..={max:?} does not overlap the volume of {:?} voxels (indices 0..={:?})",
                self.dims,
                self.dims.map(|d| d - 1)
            ));
        }
        let dims = [hi[0] - min[0] + 1, hi[1] - min[1] + 1, hi[2] - min[2] + 1];
        let origin = self.world_of(Vec3::new(min[0] as f64, min[1] as f64, min[2] as f64));
        let mut out = LabelVolume { direction: self.direction, ..LabelVolume::new(dims, self.spacing_m, origin) };
        for k in 0..dims[2] {
            for j in 0..dims[1] {
                for i in 0..dims[0] {
                    out.set(i, j, k, self.get(i + min[0], j + min[1], k + min[2]));
                }
            }
        }
        Ok(out)
    }

    /// Keeps the voxels whose label is in `keep` (others become 0) and shrinks the volume
    /// to their bounding box plus `margin` empty voxels. None when nothing is kept.
    pub fn select(&self, keep: &[u16], margin: usize) -> Option<Self> {
        let mut lo = [usize::MAX; 3];
        let mut hi = [0usize; 3];
        for k in 0..self.dims[2] {
            for j in 0..self.dims[1] {
                for i in 0..self.dims[0] {
                    if keep.contains(&self.get(i, j, k)) {
                        for (a, c) in [i, j, k].into_iter().enumerate() {
                            lo[a] = lo[a].min(c);
                            hi[a] = hi[a].max(c);
                        }
                    }
                }
            }
        }
        if lo[0] == usize::MAX {
            return None;
        }
        let dims = [0, 1, 2].map(|a| hi[a] - lo[a] + 1 + 2 * margin);
        let start = Vec3::new(lo[0] as f64 - margin as f64, lo[1] as f64 - margin as f64, lo[2] as f64 - margin as f64);
        let mut out = LabelVolume { direction: self.direction, ..LabelVolume::new(dims, self.spacing_m, self.world_of(start)) };
        for k in lo[2]..=hi[2] {
            for j in lo[1]..=hi[1] {
                for i in lo[0]..=hi[0] {
                    let l = self.get(i, j, k);
                    if keep.contains(&l) {
                        out.set(i - lo[0] + margin, j - lo[1] + margin, k - lo[2] + margin, l);
                    }
                }
            }
        }
        Some(out)
    }
}

/// Whether a file name ends like a gzip file.
fn is_gzip(bytes: &[u8]) -> bool {
    bytes.len() >= 2 && bytes[0] == 0x1f && bytes[1] == 0x8b
}

/// Reads a whole file, gunzipping it when it is gzip-compressed, with at most `limit`
/// bytes after decompression.
pub(crate) fn read_maybe_gzip(path: &std::path::Path, limit: u64) -> Result<Vec<u8>, String> {
    use std::io::Read;
    let raw = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    if !is_gzip(&raw) {
        return Ok(raw);
    }
    let mut out = Vec::new();
    flate2::read::MultiGzDecoder::new(&raw[..])
        .take(limit + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("{}: the gzip data is corrupt or truncated ({e})", path.display()))?;
    if out.len() as u64 > limit {
        return Err(format!("{}: decompresses to more than {limit} bytes", path.display()));
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> LabelVolume {
        let mut v = LabelVolume::new([4, 3, 2], [0.001, 0.002, 0.003], Vec3::new(0.1, 0.2, 0.3));
        for (n, l) in v.labels.iter_mut().enumerate() {
            *l = (n % 5) as u16;
        }
        v
    }

    #[test]
    fn mirrored_volumes_become_right_handed_without_moving_voxels() {
        let mut v = sample();
        v.direction = Matrix3::new(-1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0);
        let before: Vec<(Vec3, u16)> =
            (0..4).flat_map(|i| (0..3).map(move |j| (i, j))).map(|(i, j)| (v.world_of(Vec3::new(i as f64, j as f64, 1.0)), v.get(i, j, 1))).collect();
        let r = v.to_right_handed();
        assert!(r.direction.determinant() > 0.0);
        for (p, label) in before {
            let local = r.direction.transpose() * (p - r.origin_m);
            let (i, j, k) = ((local.x / 0.001).round() as usize, (local.y / 0.002).round() as usize, (local.z / 0.003).round() as usize);
            assert_eq!(r.get(i, j, k), label);
        }
    }

    #[test]
    fn crop_and_select_keep_world_positions() {
        let v = sample();
        let c = v.crop([1, 1, 0], [2, 9, 1]).unwrap();
        assert_eq!(c.dims, [2, 2, 2]);
        assert_eq!(c.get(0, 0, 1), v.get(1, 1, 1));
        assert_eq!(c.world_of(Vec3::zeros()), v.world_of(Vec3::new(1.0, 1.0, 0.0)));
        assert!(v.crop([5, 0, 0], [6, 1, 1]).unwrap_err().contains("does not overlap"));
        let s = v.select(&[3], 1).unwrap();
        assert_eq!(s.count(3), v.count(3));
        assert_eq!(s.histogram().len(), 1);
        assert!(v.select(&[9], 0).is_none());
    }
}
