//! Procedural label volumes: a box, an ellipsoid and a U-tube, centred on the origin and
//! axis-aligned, with cubic voxels. They need no data files.

use super::LabelVolume;
use crate::math::Vec3;

/// A volume of `dims` cubic voxels of `voxel_m`, centred on the origin.
fn centred(dims: [usize; 3], voxel_m: f64) -> LabelVolume {
    let half = Vec3::new((dims[0] - 1) as f64, (dims[1] - 1) as f64, (dims[2] - 1) as f64) * (0.5 * voxel_m);
    LabelVolume::new(dims, [voxel_m; 3], -half)
}

/// Voxels along an extent: the nearest whole number, at least one.
pub fn voxels_for(extent_m: f64, voxel_m: f64) -> usize {
    ((extent_m / voxel_m).round() as usize).max(1)
}

/// A solid box of `size_m` (rounded to whole voxels).
pub fn solid_box(size_m: [f64; 3], voxel_m: f64, label: u16) -> LabelVolume {
    let dims = size_m.map(|s| voxels_for(s, voxel_m));
    let mut v = centred(dims, voxel_m);
    v.labels.fill(label);
    v
}

/// A solid ellipsoid with semi-axes `radii_m`, with one empty voxel around it.
pub fn ellipsoid(radii_m: [f64; 3], voxel_m: f64, label: u16) -> LabelVolume {
    let dims = radii_m.map(|r| voxels_for(2.0 * r, voxel_m) + 2);
    let mut v = centred(dims, voxel_m);
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let p = v.world_of(Vec3::new(i as f64, j as f64, k as f64));
                let s = (p.x / radii_m[0]).powi(2) + (p.y / radii_m[1]).powi(2) + (p.z / radii_m[2]).powi(2);
                if s <= 1.0 {
                    v.set(i, j, k, label);
                }
            }
        }
    }
    v
}

/// The shape of a U-tube, in voxels: two arms of `arm` × `depth` voxels in x × y rising
/// `arm_length` voxels along z from a base `base` voxels thick that joins them, with
/// `gap` empty voxels between the arms.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct UTube {
    pub arm: usize,
    pub gap: usize,
    pub depth: usize,
    pub base: usize,
    pub arm_length: usize,
}

/// A U-tube (the paper's Fig. 3): its arms are separate material joined only through the base.
pub fn u_tube(shape: UTube, voxel_m: f64, label: u16) -> LabelVolume {
    let dims = [2 * shape.arm + shape.gap, shape.depth, shape.base + shape.arm_length];
    let mut v = centred(dims, voxel_m);
    for k in 0..dims[2] {
        for j in 0..dims[1] {
            for i in 0..dims[0] {
                let in_gap = i >= shape.arm && i < shape.arm + shape.gap;
                if k < shape.base || !in_gap {
                    v.set(i, j, k, label);
                }
            }
        }
    }
    v
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shapes_have_their_volumes() {
        let b = solid_box([0.01, 0.02, 0.005], 0.001, 2);
        assert_eq!(b.dims, [10, 20, 5]);
        assert_eq!(b.count(2), 1000);
        let e = ellipsoid([0.01, 0.01, 0.01], 0.0005, 1);
        let expected = 4.0 / 3.0 * std::f64::consts::PI * 1e-6;
        assert!((e.count(1) as f64 * 0.0005f64.powi(3) / expected - 1.0).abs() < 0.03);
        let u = u_tube(UTube { arm: 3, gap: 2, depth: 3, base: 2, arm_length: 6 }, 0.001, 1);
        assert_eq!(u.dims, [8, 3, 8]);
        assert_eq!(u.count(1), 8 * 3 * 2 + 2 * 3 * 3 * 6);
        assert_eq!(u.get(3, 1, 5), 0);
        assert_eq!(u.get(3, 1, 1), 1);
    }
}
