//! NIfTI-1 label images (`.nii`, `.nii.gz`): reader and writer.
//!
//! Read: single-file NIfTI-1 (`n+1`) in either byte order, 3D (or 4D/5D with one
//! volume), integer or integral floating-point voxels, with `scl_slope`/`scl_inter`
//! applied. Orientation from the sform when its code is set, else the qform, else the
//! voxel sizes alone; units from `xyzt_units` (metres, millimetres or micrometres;
//! unknown is taken as millimetres, the convention of medical images). Everything else
//! (a two-file `.hdr/.img` pair, NIfTI-2, non-integral labels, sheared axes) is refused
//! with a message that says what the file has and what is supported.
//!
//! Written: `n+1`, little-endian, uint8 when every label fits, else uint16, with both
//! sform and qform set (code 2, aligned) and millimetre units.

use std::path::Path;

use super::{LabelVolume, MAX_VOXELS};
use crate::math::{Matrix3, Quat, Vec3};

const HEADER_SIZE: usize = 348;

/// Reads a NIfTI-1 file (gzipped or not).
pub fn read_nifti(path: &Path) -> Result<LabelVolume, String> {
    let bytes = super::read_maybe_gzip(path, (MAX_VOXELS as u64) * 8 + (1 << 20))?;
    parse_nifti(&bytes).map_err(|e| format!("{}: {e}", path.display()))
}

struct Reader<'a> {
    bytes: &'a [u8],
    swap: bool,
}

impl Reader<'_> {
    fn raw<const N: usize>(&self, at: usize) -> [u8; N] {
        let mut b: [u8; N] = self.bytes[at..at + N].try_into().expect("in range");
        if self.swap {
            b.reverse();
        }
        b
    }
    fn i16(&self, at: usize) -> i16 {
        i16::from_le_bytes(self.raw(at))
    }
    fn f32(&self, at: usize) -> f32 {
        f32::from_le_bytes(self.raw(at))
    }
}

/// Parses the bytes of an (already decompressed) NIfTI-1 file.
pub fn parse_nifti(bytes: &[u8]) -> Result<LabelVolume, String> {
    if bytes.len() < HEADER_SIZE {
        return Err(format!("not a NIfTI-1 file: {} bytes, the header alone has {HEADER_SIZE}", bytes.len()));
    }
    let size_le = i32::from_le_bytes(bytes[0..4].try_into().expect("4 bytes"));
    let size_be = i32::from_be_bytes(bytes[0..4].try_into().expect("4 bytes"));
    let swap = match (size_le, size_be) {
        (348, _) => false,
        (_, 348) => true,
        (540, _) | (_, 540) => return Err("this is a NIfTI-2 file; only NIfTI-1 is supported (convert it, e.g. with nibabel)".into()),
        _ => return Err(format!("not a NIfTI-1 file: the header size field is {size_le}, expected 348")),
    };
    let r = Reader { bytes, swap };
    let magic = &bytes[344..348];
    if magic == b"ni1\0" {
        return Err("this is the header of a two-file NIfTI (.hdr/.img); give a single-file .nii or .nii.gz".into());
    }
    if magic != b"n+1\0" {
        return Err(format!("not a NIfTI-1 file: magic {magic:?}, expected \"n+1\""));
    }
    let dim: Vec<i64> = (0..8).map(|k| i64::from(r.i16(40 + 2 * k))).collect();
    let rank = dim[0];
    if !(1..=7).contains(&rank) {
        return Err(format!("dim[0] is {rank}; it must be 1 to 7"));
    }
    if rank > 3 && dim[4..=rank as usize].iter().any(|&d| d > 1) {
        return Err(format!("the image has {rank} dimensions {:?}; only one 3D volume (extra dimensions of size 1) is supported", &dim[1..=rank as usize]));
    }
    let mut dims = [1usize; 3];
    for a in 0..3 {
        if (a as i64) < rank {
            let d = dim[a + 1];
            if d < 1 {
                return Err(format!("dim[{}] is {d}; sizes must be at least 1", a + 1));
            }
            dims[a] = d as usize;
        }
    }
    let count = dims[0] * dims[1] * dims[2];
    if count > MAX_VOXELS {
        return Err(format!("the image has {count} voxels ({dims:?}); at most {MAX_VOXELS} are supported (crop it)"));
    }
    let datatype = r.i16(70);
    let (bytes_per, kind) = match datatype {
        2 => (1, Kind::U8),
        4 => (2, Kind::I16),
        8 => (4, Kind::I32),
        16 => (4, Kind::F32),
        64 => (8, Kind::F64),
        256 => (1, Kind::I8),
        512 => (2, Kind::U16),
        768 => (4, Kind::U32),
        other => {
            return Err(format!(
                "datatype {other} is not supported for a label image; supported: uint8 (2), int8 (256), int16 (4), uint16 (512), int32 (8), uint32 (768), float32 (16), float64 (64)"
            ));
        }
    };
    let vox_offset = r.f32(108);
    if !(vox_offset.is_finite() && vox_offset >= HEADER_SIZE as f32) {
        return Err(format!("vox_offset is {vox_offset}; it must be at least {HEADER_SIZE}"));
    }
    // A huge vox_offset saturates the cast; the sum must not wrap (found by fuzzing:
    // vox_offset 1e30 wrapped `start + needed` past the length check).
    let start = vox_offset as usize;
    let needed = count * bytes_per;
    if start.checked_add(needed).is_none_or(|end| bytes.len() < end) {
        return Err(format!(
            "the file is truncated: the header promises {needed} bytes of voxel data from byte {start}, but the file has {} bytes",
            bytes.len()
        ));
    }
    let (slope, inter) = (r.f32(112), r.f32(116));
    let scale = |v: f64| if slope != 0.0 && slope.is_finite() { v * f64::from(slope) + f64::from(inter) } else { v };
    let data = &bytes[start..start + needed];
    let mut labels = Vec::with_capacity(count);
    for n in 0..count {
        let at = n * bytes_per;
        let chunk = &data[at..at + bytes_per];
        let mut b = [0u8; 8];
        b[..bytes_per].copy_from_slice(chunk);
        if swap {
            b[..bytes_per].reverse();
        }
        let value = match kind {
            Kind::U8 => f64::from(b[0]),
            Kind::I8 => f64::from(b[0] as i8),
            Kind::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Kind::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Kind::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Kind::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Kind::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Kind::F64 => f64::from_le_bytes(b),
        };
        let value = scale(value);
        if !(value.is_finite() && value >= 0.0 && value <= f64::from(u16::MAX) && value.fract() == 0.0) {
            let (i, j, k) = (n % dims[0], (n / dims[0]) % dims[1], n / (dims[0] * dims[1]));
            return Err(format!("voxel ({i}, {j}, {k}) has value {value}; labels must be whole numbers from 0 to 65535"));
        }
        labels.push(value as u16);
    }

    let unit_m = match bytes[123] & 0x07 {
        1 => 1.0,
        3 => 1e-6,
        _ => 1e-3, // 2 = mm; 0 = unknown, taken as mm
    };
    let pixdim: Vec<f64> = (0..8).map(|k| f64::from(r.f32(76 + 4 * k))).collect();
    let (qform_code, sform_code) = (r.i16(252), r.i16(254));
    let (affine, offset) = if sform_code > 0 {
        let row = |at: usize| [r.f32(at), r.f32(at + 4), r.f32(at + 8), r.f32(at + 12)].map(f64::from);
        let (x, y, z) = (row(280), row(296), row(312));
        (Matrix3::new(x[0], x[1], x[2], y[0], y[1], y[2], z[0], z[1], z[2]), Vec3::new(x[3], y[3], z[3]))
    } else if qform_code > 0 {
        let (b, c, d) = (f64::from(r.f32(256)), f64::from(r.f32(260)), f64::from(r.f32(264)));
        let a = (1.0 - (b * b + c * c + d * d)).max(0.0).sqrt();
        let rotation = Quat::from_quaternion(nalgebra::Quaternion::new(a, b, c, d)).to_rotation_matrix().into_inner();
        let qfac = if pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let scale = Matrix3::from_diagonal(&Vec3::new(pixdim[1].abs(), pixdim[2].abs(), qfac * pixdim[3].abs()));
        (rotation * scale, Vec3::new(f64::from(r.f32(268)), f64::from(r.f32(272)), f64::from(r.f32(276))))
    } else {
        (Matrix3::from_diagonal(&Vec3::new(pixdim[1].abs(), pixdim[2].abs(), pixdim[3].abs())), Vec3::zeros())
    };
    let mut spacing = [0.0; 3];
    let mut direction = Matrix3::zeros();
    for a in 0..3 {
        let column = affine.column(a);
        let length = column.norm();
        if !(length.is_finite() && length > 0.0) {
            return Err(format!("axis {a} of the orientation has length {length}; the voxel size must be positive"));
        }
        spacing[a] = length * unit_m;
        direction.set_column(a, &(column / length));
    }
    let volume = LabelVolume { dims, spacing_m: spacing, origin_m: offset * unit_m, direction, labels };
    volume.check()?;
    Ok(volume)
}

#[derive(Clone, Copy)]
enum Kind {
    U8,
    I8,
    I16,
    U16,
    I32,
    U32,
    F32,
    F64,
}

/// Writes a NIfTI-1 file; gzipped when the path ends in `.gz`.
pub fn write_nifti(volume: &LabelVolume, path: &Path) -> Result<(), String> {
    let bytes = encode_nifti(volume);
    let out = if path.extension().is_some_and(|e| e == "gz") {
        use std::io::Write;
        let mut encoder = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::default());
        encoder.write_all(&bytes).and_then(|_| encoder.finish()).map_err(|e| e.to_string())?
    } else {
        bytes
    };
    std::fs::write(path, out).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// The bytes of a NIfTI-1 file holding `volume` (see the module documentation).
pub fn encode_nifti(volume: &LabelVolume) -> Vec<u8> {
    let wide = volume.labels.iter().any(|&l| l > 255);
    let mut h = vec![0u8; HEADER_SIZE + 4];
    let put = |h: &mut Vec<u8>, at: usize, b: &[u8]| h[at..at + b.len()].copy_from_slice(b);
    put(&mut h, 0, &348i32.to_le_bytes());
    let dim = [3i16, volume.dims[0] as i16, volume.dims[1] as i16, volume.dims[2] as i16, 1, 1, 1, 1];
    for (k, d) in dim.iter().enumerate() {
        put(&mut h, 40 + 2 * k, &d.to_le_bytes());
    }
    put(&mut h, 70, &(if wide { 512i16 } else { 2 }).to_le_bytes());
    put(&mut h, 72, &(if wide { 16i16 } else { 8 }).to_le_bytes());
    let mm = volume.spacing_m.map(|s| (s * 1e3) as f32);
    let rotation = nalgebra::Rotation3::from_matrix_unchecked(volume.direction);
    let proper = volume.direction.determinant() > 0.0;
    let pixdim = [if proper { 1.0f32 } else { -1.0 }, mm[0], mm[1], mm[2], 1.0, 1.0, 1.0, 1.0];
    for (k, p) in pixdim.iter().enumerate() {
        put(&mut h, 76 + 4 * k, &p.to_le_bytes());
    }
    put(&mut h, 108, &((HEADER_SIZE + 4) as f32).to_le_bytes());
    put(&mut h, 112, &1.0f32.to_le_bytes());
    h[123] = 2; // millimetres
    put(&mut h, 252, &2i16.to_le_bytes());
    put(&mut h, 254, &2i16.to_le_bytes());
    // The qform's rotation: for a mirrored frame, qfac −1 flips the k axis first.
    let proper_rotation = if proper {
        rotation.into_inner()
    } else {
        volume.direction * Matrix3::from_diagonal(&Vec3::new(1.0, 1.0, -1.0))
    };
    let q = Quat::from_matrix(&proper_rotation);
    let q = if q.w < 0.0 { -q.into_inner() } else { q.into_inner() };
    for (k, c) in [q.i, q.j, q.k].iter().enumerate() {
        put(&mut h, 256 + 4 * k, &(*c as f32).to_le_bytes());
    }
    let origin_mm = volume.origin_m * 1e3;
    for a in 0..3 {
        put(&mut h, 268 + 4 * a, &(origin_mm[a] as f32).to_le_bytes());
        let row: [f32; 4] = [
            (volume.direction[(a, 0)] * mm[0] as f64) as f32,
            (volume.direction[(a, 1)] * mm[1] as f64) as f32,
            (volume.direction[(a, 2)] * mm[2] as f64) as f32,
            origin_mm[a] as f32,
        ];
        for (k, v) in row.iter().enumerate() {
            put(&mut h, 280 + 16 * a + 4 * k, &v.to_le_bytes());
        }
    }
    put(&mut h, 344, b"n+1\0");
    for &l in &volume.labels {
        if wide {
            h.extend_from_slice(&l.to_le_bytes());
        } else {
            h.push(l as u8);
        }
    }
    h
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> LabelVolume {
        let mut v = LabelVolume::new([5, 4, 3], [0.003, 0.003, 0.0025], Vec3::new(-0.17795, 0.011319, 0.0943));
        for (n, l) in v.labels.iter_mut().enumerate() {
            *l = ((n * 7) % 6) as u16;
        }
        v
    }

    #[test]
    fn writes_and_reads_back() {
        let v = sample();
        let back = parse_nifti(&encode_nifti(&v)).unwrap();
        assert_eq!(back.dims, v.dims);
        assert_eq!(back.labels, v.labels);
        for a in 0..3 {
            assert!((back.spacing_m[a] - v.spacing_m[a]).abs() < 1e-9);
            assert!((back.origin_m[a] - v.origin_m[a]).abs() < 1e-7);
        }
        assert!((back.direction - v.direction).norm() < 1e-6);
    }

    #[test]
    fn sixteen_bit_labels_and_rotations_round_trip() {
        let mut v = sample();
        v.labels[3] = 1000;
        v.direction = Quat::from_euler_angles(0.3, -0.2, 1.1).to_rotation_matrix().into_inner();
        let back = parse_nifti(&encode_nifti(&v)).unwrap();
        assert_eq!(back.labels, v.labels);
        assert!((back.direction - v.direction).norm() < 1e-6);
    }

    #[test]
    fn corrupt_files_say_what_is_wrong() {
        let bytes = encode_nifti(&sample());
        assert!(parse_nifti(&bytes[..100]).unwrap_err().contains("the header alone has 348"));
        let truncated = parse_nifti(&bytes[..bytes.len() - 5]).unwrap_err();
        assert!(truncated.contains("truncated") && truncated.contains("60 bytes of voxel data"), "{truncated}");
        let mut bad = bytes.clone();
        bad[70] = 32; // complex64
        assert!(parse_nifti(&bad).unwrap_err().contains("datatype 32 is not supported"));
        let mut bad = bytes.clone();
        bad[344..348].copy_from_slice(b"ni1\0");
        assert!(parse_nifti(&bad).unwrap_err().contains("two-file"));
        let mut bad = bytes;
        bad[0] = 0;
        assert!(parse_nifti(&bad).unwrap_err().contains("header size field"));
    }
}
