//! VTK XML ImageData (`.vti`) label images: reader and writer.
//!
//! Read: one piece covering the whole extent; a one-component scalar array in the
//! point data (VTK's usual place for an image's voxels: a point per voxel centre) or
//! the cell data; `ascii`, inline `binary` (base64) or `appended` data (`raw` or
//! `base64` encoding); uncompressed or `vtkZLibDataCompressor`; `UInt32` or `UInt64`
//! headers; either byte order; the `Direction` attribute of VTK 9. The array is the one
//! the scene names, else the data's active `Scalars`, else the first. Lengths are in
//! the file's units (the scene gives metres per unit; medical images are in mm).
//!
//! Written: point data, `appended` with the chosen encoding and compression (the
//! writer serves tests and conversions).

use std::path::Path;

use base64::Engine;

use super::{LabelVolume, MAX_VOXELS};
use crate::math::{Matrix3, Vec3};

/// How the writer stores the voxels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VtiEncoding {
    Ascii,
    /// Base64 inside the DataArray element.
    InlineBase64 { zlib: bool },
    /// Raw bytes in the AppendedData section.
    AppendedRaw { zlib: bool },
    /// Base64 in the AppendedData section.
    AppendedBase64 { zlib: bool },
}

/// Reads a `.vti` file. `array`: the data array to take (None: the active scalars or the
/// first); `unit_m`: metres per file unit.
pub fn read_vti(path: &Path, array: Option<&str>, unit_m: f64) -> Result<LabelVolume, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    parse_vti(&bytes, array, unit_m).map_err(|e| format!("{}: {e}", path.display()))
}

/// One XML start tag: its name and attributes, and where its content starts.
struct Tag {
    name: String,
    attrs: Vec<(String, String)>,
    /// Byte just after the `>`.
    end: usize,
    self_closing: bool,
}

impl Tag {
    fn attr(&self, name: &str) -> Option<&str> {
        self.attrs.iter().find(|(k, _)| k == name).map(|(_, v)| v.as_str())
    }
}

/// Finds the next start tag at or after `from` (skipping declarations, comments and end
/// tags). Stops at `<AppendedData`'s content, which is not XML.
fn next_tag(bytes: &[u8], mut from: usize) -> Result<Option<Tag>, String> {
    loop {
        let Some(open) = bytes[from..].iter().position(|&b| b == b'<').map(|p| p + from) else { return Ok(None) };
        let rest = &bytes[open..];
        if rest.starts_with(b"<!--") {
            let close = find(bytes, b"-->", open).ok_or("an XML comment is not closed")?;
            from = close + 3;
            continue;
        }
        if rest.starts_with(b"<?") || rest.starts_with(b"</") || rest.starts_with(b"<!") {
            from = bytes[open..].iter().position(|&b| b == b'>').map(|p| p + open + 1).ok_or("an XML tag is not closed")?;
            continue;
        }
        let close = bytes[open..].iter().position(|&b| b == b'>').map(|p| p + open).ok_or("an XML tag is not closed")?;
        let inside = std::str::from_utf8(&bytes[open + 1..close]).map_err(|_| format!("the XML tag at byte {open} is not UTF-8"))?;
        let self_closing = inside.ends_with('/');
        let inside = inside.trim_end_matches('/');
        let name_end = inside.find(|c: char| c.is_whitespace()).unwrap_or(inside.len());
        let name = inside[..name_end].to_owned();
        let mut attrs = Vec::new();
        let mut rest = inside[name_end..].trim_start();
        while !rest.is_empty() {
            let eq = rest.find('=').ok_or_else(|| format!("attribute without a value in <{name}>"))?;
            let key = rest[..eq].trim().to_owned();
            let after = rest[eq + 1..].trim_start();
            let quote = after.chars().next().filter(|c| *c == '"' || *c == '\'').ok_or_else(|| format!("attribute {key} of <{name}> is not quoted"))?;
            let value_end = after[1..].find(quote).ok_or_else(|| format!("attribute {key} of <{name}> is not closed"))?;
            attrs.push((key, after[1..1 + value_end].to_owned()));
            rest = after[value_end + 2..].trim_start();
        }
        return Ok(Some(Tag { name, attrs, end: close + 1, self_closing }));
    }
}

fn find(haystack: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    haystack[from..].windows(needle.len()).position(|w| w == needle).map(|p| p + from)
}

fn numbers<const N: usize>(text: Option<&str>, what: &str) -> Result<Option<[f64; N]>, String> {
    let Some(text) = text else { return Ok(None) };
    let values: Vec<f64> = text
        .split_whitespace()
        .map(|w| w.parse::<f64>().ok().filter(|v| v.is_finite()))
        .collect::<Option<_>>()
        .ok_or_else(|| format!("{what} {text:?} is not a list of numbers"))?;
    let array: [f64; N] = values.try_into().map_err(|v: Vec<f64>| format!("{what} has {} numbers, expected {N}", v.len()))?;
    Ok(Some(array))
}

struct ArrayInfo {
    name: String,
    data_type: String,
    format: String,
    offset: Option<usize>,
    /// Inline content (ascii or base64), for non-appended arrays.
    content: String,
    cell_data: bool,
}

/// Parses the bytes of a `.vti` file.
pub fn parse_vti(bytes: &[u8], wanted: Option<&str>, unit_m: f64) -> Result<LabelVolume, String> {
    let mut at = 0;
    let mut vtk_file = None;
    let mut image = None;
    let mut piece = None;
    let mut section: Option<(bool, Option<String>)> = None; // (is cell data, active scalars)
    let mut arrays: Vec<ArrayInfo> = Vec::new();
    let mut active: Vec<(bool, String)> = Vec::new();
    let mut appended: Option<(String, usize)> = None; // (encoding, offset of the byte after '_')
    while let Some(tag) = next_tag(bytes, at)? {
        at = tag.end;
        match tag.name.as_str() {
            "VTKFile" => {
                if tag.attr("type") != Some("ImageData") {
                    return Err(format!("the VTK file holds {:?}, not ImageData", tag.attr("type").unwrap_or("(no type)")));
                }
                vtk_file = Some(tag);
            }
            "ImageData" => image = Some(tag),
            "Piece" => {
                if piece.is_some() {
                    return Err("the file has several pieces; only one piece is supported".into());
                }
                piece = Some(tag);
            }
            "PointData" | "CellData" => {
                let cell = tag.name == "CellData";
                if let Some(s) = tag.attr("Scalars") {
                    active.push((cell, s.to_owned()));
                }
                section = Some((cell, None));
            }
            "DataArray" => {
                let Some((cell, _)) = &section else { continue };
                let format = tag.attr("format").unwrap_or("ascii").to_owned();
                let content = if tag.self_closing {
                    String::new()
                } else {
                    let close = find(bytes, b"</DataArray>", tag.end).ok_or("a DataArray is not closed")?;
                    at = close;
                    String::from_utf8_lossy(&bytes[tag.end..close]).into_owned()
                };
                if tag.attr("NumberOfComponents").is_some_and(|c| c.trim() != "1") {
                    arrays.push(ArrayInfo { name: format!("{} (vector, skipped)", tag.attr("Name").unwrap_or("")), data_type: String::new(), format: "skip".into(), offset: None, content, cell_data: *cell });
                    continue;
                }
                arrays.push(ArrayInfo {
                    name: tag.attr("Name").unwrap_or("").to_owned(),
                    data_type: tag.attr("type").unwrap_or("").to_owned(),
                    format,
                    offset: tag.attr("offset").map(|o| o.trim().parse::<usize>().map_err(|_| format!("DataArray offset {o:?} is not a number"))).transpose()?,
                    content,
                    cell_data: *cell,
                });
            }
            "AppendedData" => {
                let underscore = bytes[tag.end..].iter().position(|&b| b == b'_').map(|p| p + tag.end).ok_or("the AppendedData section has no '_' marker")?;
                appended = Some((tag.attr("encoding").unwrap_or("raw").to_owned(), underscore + 1));
                break;
            }
            _ => {}
        }
    }
    let vtk_file = vtk_file.ok_or("not a VTK XML file: no <VTKFile> element")?;
    let image = image.ok_or("no <ImageData> element")?;
    let big_endian = match vtk_file.attr("byte_order").unwrap_or("LittleEndian") {
        "LittleEndian" => false,
        "BigEndian" => true,
        other => return Err(format!("byte_order {other:?} is neither LittleEndian nor BigEndian")),
    };
    let header_bytes = match vtk_file.attr("header_type").unwrap_or("UInt32") {
        "UInt32" => 4,
        "UInt64" => 8,
        other => return Err(format!("header_type {other:?} is not supported (UInt32 or UInt64)")),
    };
    let zlib = match vtk_file.attr("compressor") {
        None | Some("") => false,
        Some("vtkZLibDataCompressor") => true,
        Some(other) => return Err(format!("compressor {other:?} is not supported; write the file uncompressed or with vtkZLibDataCompressor")),
    };
    let extent = numbers::<6>(image.attr("WholeExtent"), "WholeExtent")?.ok_or("ImageData has no WholeExtent")?;
    if let Some(p) = &piece
        && let Some(pe) = numbers::<6>(p.attr("Extent"), "Piece Extent")?
        && pe != extent
    {
        return Err(format!("the piece's extent {pe:?} is not the whole extent {extent:?}; only single-piece files are supported"));
    }
    let origin = numbers::<3>(image.attr("Origin"), "Origin")?.unwrap_or([0.0; 3]);
    let spacing = numbers::<3>(image.attr("Spacing"), "Spacing")?.unwrap_or([1.0; 3]);
    let direction = numbers::<9>(image.attr("Direction"), "Direction")?.unwrap_or([1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]);

    let chosen = match wanted {
        Some(name) => arrays.iter().find(|a| a.name == name).ok_or_else(|| {
            let names: Vec<&str> = arrays.iter().map(|a| a.name.as_str()).collect();
            format!("no data array named {name:?}; the file has: {}", if names.is_empty() { "(none)".into() } else { names.join(", ") })
        })?,
        None => active
            .iter()
            .find_map(|(cell, name)| arrays.iter().find(|a| a.cell_data == *cell && &a.name == name && a.format != "skip"))
            .or_else(|| arrays.iter().find(|a| a.format != "skip"))
            .ok_or("the file has no one-component data array")?,
    };
    if chosen.format == "skip" {
        return Err(format!("data array {:?} has more than one component; a label image has one", chosen.name));
    }
    // Points per axis for point data, cells for cell data.
    let extra = if chosen.cell_data { 0.0 } else { 1.0 };
    let mut dims = [0usize; 3];
    for a in 0..3 {
        let n = extent[2 * a + 1] - extent[2 * a] + extra;
        if !(n >= 1.0 && n.fract() == 0.0) {
            return Err(format!("the extent {extent:?} gives {n} voxels along axis {a}"));
        }
        dims[a] = n as usize;
    }
    let count = dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]);
    if count > MAX_VOXELS {
        return Err(format!("the image has {count} voxels ({dims:?}); at most {MAX_VOXELS} are supported"));
    }
    let (size, kind) = scalar_type(&chosen.data_type)?;
    let blob = match chosen.format.as_str() {
        "ascii" => None,
        "binary" => {
            let text: String = chosen.content.chars().filter(|c| !c.is_whitespace()).collect();
            Some(decode_block(Source::Base64(text.as_bytes()), header_bytes, big_endian, zlib)?)
        }
        "appended" => {
            let (encoding, start) = appended.as_ref().ok_or("a DataArray is appended but the file has no AppendedData section")?;
            let offset = chosen.offset.ok_or("an appended DataArray has no offset")?;
            let from = start + offset;
            if from > bytes.len() {
                return Err(format!("the appended data is truncated: the array starts at byte {from}, the file has {} bytes", bytes.len()));
            }
            Some(match encoding.as_str() {
                "raw" => decode_block(Source::Raw(&bytes[from..]), header_bytes, big_endian, zlib)?,
                "base64" => {
                    let end = find(bytes, b"</AppendedData>", from).unwrap_or(bytes.len());
                    let text: Vec<u8> = bytes[from..end].iter().copied().filter(|b| !b.is_ascii_whitespace()).collect();
                    decode_block(Source::Base64(&text), header_bytes, big_endian, zlib)?
                }
                other => return Err(format!("AppendedData encoding {other:?} is neither raw nor base64")),
            })
        }
        other => return Err(format!("DataArray format {other:?} is not ascii, binary or appended")),
    };
    let values: Vec<f64> = match blob {
        None => chosen
            .content
            .split_whitespace()
            .map(|w| w.parse::<f64>().map_err(|_| format!("ascii value {w:?} is not a number")))
            .collect::<Result<_, _>>()?,
        Some(data) => {
            if data.len() < count * size {
                return Err(format!("the data array holds {} bytes, {count} voxels of {} need {}", data.len(), chosen.data_type, count * size));
            }
            data.chunks_exact(size).take(count).map(|c| kind.decode(c, big_endian)).collect()
        }
    };
    if values.len() != count {
        return Err(format!("the data array has {} values for {count} voxels ({dims:?})", values.len()));
    }
    let mut labels = Vec::with_capacity(count);
    for (n, v) in values.into_iter().enumerate() {
        if !(v.is_finite() && v >= 0.0 && v <= f64::from(u16::MAX) && v.fract() == 0.0) {
            let (i, j, k) = (n % dims[0], (n / dims[0]) % dims[1], n / (dims[0] * dims[1]));
            return Err(format!("voxel ({i}, {j}, {k}) has value {v}; labels must be whole numbers from 0 to 65535"));
        }
        labels.push(v as u16);
    }
    let d = Matrix3::new(direction[0], direction[1], direction[2], direction[3], direction[4], direction[5], direction[6], direction[7], direction[8]);
    let shift = if chosen.cell_data { 0.5 } else { 0.0 };
    let first = Vec3::new(
        (extent[0] + shift) * spacing[0],
        (extent[2] + shift) * spacing[1],
        (extent[4] + shift) * spacing[2],
    );
    let volume = LabelVolume {
        dims,
        spacing_m: spacing.map(|s| s.abs() * unit_m),
        origin_m: (Vec3::from(origin) + d * first) * unit_m,
        direction: d * Matrix3::from_diagonal(&Vec3::new(spacing[0].signum(), spacing[1].signum(), spacing[2].signum())),
        labels,
    };
    volume.check()?;
    Ok(volume)
}

enum Source<'a> {
    Raw(&'a [u8]),
    Base64(&'a [u8]),
}

fn read_uint(bytes: &[u8], big_endian: bool) -> u64 {
    let mut b = [0u8; 8];
    if big_endian {
        b[8 - bytes.len()..].copy_from_slice(bytes);
        u64::from_be_bytes(b)
    } else {
        b[..bytes.len()].copy_from_slice(bytes);
        u64::from_le_bytes(b)
    }
}

fn b64(text: &[u8]) -> Result<Vec<u8>, String> {
    base64::engine::general_purpose::STANDARD.decode(text).map_err(|e| format!("the base64 data is corrupt ({e})"))
}

/// Decodes base64 text that may be several independently padded pieces (VTK encodes a
/// block's header and its data separately), returning the first `header` bytes and the rest.
fn b64_split(text: &[u8], header: usize) -> Result<(Vec<u8>, Vec<u8>), String> {
    let header_chars = header.div_ceil(3) * 4;
    if text.len() < header_chars {
        return Err("the base64 data is truncated (shorter than its header)".into());
    }
    if text[..header_chars].contains(&b'=') || header.is_multiple_of(3) {
        // Encoded separately (padded), or a header whose encoding ends on a boundary.
        let head = b64(&text[..header_chars])?;
        Ok((head, b64(&text[header_chars..])?))
    } else {
        let all = b64(text)?;
        if all.len() < header {
            return Err("the base64 data is truncated (shorter than its header)".into());
        }
        let rest = all[header..].to_vec();
        let mut head = all;
        head.truncate(header);
        Ok((head, rest))
    }
}

/// One array's block: `[byte count]` + data, or the zlib header + compressed blocks.
fn decode_block(source: Source, h: usize, big_endian: bool, zlib: bool) -> Result<Vec<u8>, String> {
    if !zlib {
        let (head, data) = match source {
            Source::Raw(bytes) => {
                if bytes.len() < h {
                    return Err("the appended data is truncated (no byte count)".into());
                }
                (bytes[..h].to_vec(), bytes[h..].to_vec())
            }
            Source::Base64(text) => b64_split(text, h)?,
        };
        let n = read_uint(&head, big_endian) as usize;
        if data.len() < n {
            return Err(format!("the data array is truncated: its header promises {n} bytes, {} are present", data.len()));
        }
        return Ok(data[..n].to_vec());
    }
    // Compressed: [#blocks][block size][last block size][compressed sizes…] then blocks.
    let (blocks, head, data) = match source {
        Source::Raw(bytes) => {
            if bytes.len() < 3 * h {
                return Err("the compressed data is truncated (no header)".into());
            }
            let blocks = read_uint(&bytes[..h], big_endian) as usize;
            let head_len = (3 + blocks).checked_mul(h).filter(|&l| l <= bytes.len()).ok_or("the compressed data is truncated (header)")?;
            (blocks, bytes[..head_len].to_vec(), bytes[head_len..].to_vec())
        }
        Source::Base64(text) => {
            let first_chars = ((3 * h).div_ceil(3) * 4).min(text.len());
            let first = b64(&text[..first_chars]).unwrap_or_default();
            if first.len() < h {
                return Err("the compressed data is truncated (no header)".into());
            }
            let blocks = read_uint(&first[..h], big_endian) as usize;
            if blocks > 1 << 24 {
                return Err(format!("the compressed data header claims {blocks} blocks"));
            }
            let (head, data) = b64_split(text, (3 + blocks) * h)?;
            (blocks, head, data)
        }
    };
    let block_size = read_uint(&head[h..2 * h], big_endian) as usize;
    let last_size = read_uint(&head[2 * h..3 * h], big_endian) as usize;
    let mut out = Vec::new();
    let mut at = 0usize;
    for b in 0..blocks {
        let c = read_uint(&head[(3 + b) * h..(4 + b) * h], big_endian) as usize;
        let chunk = data.get(at..at + c).ok_or_else(|| format!("compressed block {b} is truncated"))?;
        at += c;
        let expect = if b + 1 == blocks && last_size != 0 { last_size } else { block_size };
        if out.len() + expect > MAX_VOXELS * 8 {
            return Err("the compressed data inflates beyond the size limit".into());
        }
        let mut inflated = Vec::with_capacity(expect);
        use std::io::Read;
        flate2::read::ZlibDecoder::new(chunk)
            .take(expect as u64 + 1)
            .read_to_end(&mut inflated)
            .map_err(|e| format!("compressed block {b} is corrupt ({e})"))?;
        if inflated.len() != expect {
            return Err(format!("compressed block {b} inflates to {} bytes, its header says {expect}", inflated.len()));
        }
        out.extend_from_slice(&inflated);
    }
    Ok(out)
}

#[derive(Clone, Copy)]
enum Scalar {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    U64,
    I64,
    F32,
    F64,
}

impl Scalar {
    fn decode(self, c: &[u8], big_endian: bool) -> f64 {
        let mut b = [0u8; 8];
        b[..c.len()].copy_from_slice(c);
        if big_endian {
            b[..c.len()].reverse();
        }
        match self {
            Scalar::U8 => f64::from(b[0]),
            Scalar::I8 => f64::from(b[0] as i8),
            Scalar::U16 => f64::from(u16::from_le_bytes([b[0], b[1]])),
            Scalar::I16 => f64::from(i16::from_le_bytes([b[0], b[1]])),
            Scalar::U32 => f64::from(u32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::I32 => f64::from(i32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::U64 => u64::from_le_bytes(b) as f64,
            Scalar::I64 => i64::from_le_bytes(b) as f64,
            Scalar::F32 => f64::from(f32::from_le_bytes([b[0], b[1], b[2], b[3]])),
            Scalar::F64 => f64::from_le_bytes(b),
        }
    }
}

fn scalar_type(name: &str) -> Result<(usize, Scalar), String> {
    Ok(match name {
        "UInt8" | "unsigned_char" => (1, Scalar::U8),
        "Int8" | "char" => (1, Scalar::I8),
        "UInt16" | "unsigned_short" => (2, Scalar::U16),
        "Int16" | "short" => (2, Scalar::I16),
        "UInt32" | "unsigned_int" => (4, Scalar::U32),
        "Int32" | "int" => (4, Scalar::I32),
        "UInt64" => (8, Scalar::U64),
        "Int64" => (8, Scalar::I64),
        "Float32" | "float" => (4, Scalar::F32),
        "Float64" | "double" => (8, Scalar::F64),
        other => return Err(format!("data type {other:?} is not supported (UInt8 … Int64, Float32, Float64)")),
    })
}

/// Writes a `.vti` file in millimetres (file units) with the given encoding.
pub fn write_vti(volume: &LabelVolume, path: &Path, encoding: VtiEncoding) -> Result<(), String> {
    std::fs::write(path, encode_vti(volume, encoding)).map_err(|e| format!("cannot write {}: {e}", path.display()))
}

/// The bytes of a `.vti` file holding `volume` (point data, UInt16 labels, lengths in mm).
pub fn encode_vti(volume: &LabelVolume, encoding: VtiEncoding) -> Vec<u8> {
    let mm = |m: f64| m * 1e3;
    let [nx, ny, nz] = volume.dims;
    let d = volume.direction;
    let zlib = matches!(encoding, VtiEncoding::InlineBase64 { zlib: true } | VtiEncoding::AppendedRaw { zlib: true } | VtiEncoding::AppendedBase64 { zlib: true });
    let data: Vec<u8> = volume.labels.iter().flat_map(|l| l.to_le_bytes()).collect();
    // Header and payload of the block, kept apart so base64 can encode them separately.
    let (header, payload) = if zlib {
        use std::io::Write;
        let mut e = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::default());
        e.write_all(&data).expect("in memory");
        let compressed = e.finish().expect("in memory");
        let header: Vec<u8> = [1u32, data.len() as u32, data.len() as u32, compressed.len() as u32].iter().flat_map(|v| v.to_le_bytes()).collect();
        (header, compressed)
    } else {
        ((data.len() as u32).to_le_bytes().to_vec(), data)
    };
    let b64 = |b: &[u8]| base64::engine::general_purpose::STANDARD.encode(b);
    let (format, inline, appended_encoding) = match encoding {
        VtiEncoding::Ascii => ("ascii", volume.labels.iter().map(|l| l.to_string()).collect::<Vec<_>>().join(" "), None),
        VtiEncoding::InlineBase64 { .. } => ("binary", format!("{}{}", b64(&header), b64(&payload)), None),
        VtiEncoding::AppendedRaw { .. } => ("appended", String::new(), Some("raw")),
        VtiEncoding::AppendedBase64 { .. } => ("appended", String::new(), Some("base64")),
    };
    let mut out = String::new();
    out.push_str("<?xml version=\"1.0\"?>\n");
    out.push_str(&format!(
        "<VTKFile type=\"ImageData\" version=\"1.0\" byte_order=\"LittleEndian\" header_type=\"UInt32\"{}>\n",
        if zlib { " compressor=\"vtkZLibDataCompressor\"" } else { "" }
    ));
    let extent = format!("0 {} 0 {} 0 {}", nx - 1, ny - 1, nz - 1);
    let o = volume.origin_m;
    out.push_str(&format!(
        "  <ImageData WholeExtent=\"{extent}\" Origin=\"{:?} {:?} {:?}\" Spacing=\"{:?} {:?} {:?}\" Direction=\"{:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?} {:?}\">\n",
        mm(o.x), mm(o.y), mm(o.z),
        mm(volume.spacing_m[0]), mm(volume.spacing_m[1]), mm(volume.spacing_m[2]),
        d[(0, 0)], d[(0, 1)], d[(0, 2)], d[(1, 0)], d[(1, 1)], d[(1, 2)], d[(2, 0)], d[(2, 1)], d[(2, 2)],
    ));
    out.push_str(&format!("    <Piece Extent=\"{extent}\">\n      <PointData Scalars=\"labels\">\n"));
    if appended_encoding.is_some() {
        out.push_str(&format!("        <DataArray type=\"UInt16\" Name=\"labels\" format=\"{format}\" offset=\"0\"/>\n"));
    } else {
        out.push_str(&format!("        <DataArray type=\"UInt16\" Name=\"labels\" format=\"{format}\">\n{inline}\n        </DataArray>\n"));
    }
    out.push_str("      </PointData>\n      <CellData>\n      </CellData>\n    </Piece>\n  </ImageData>\n");
    let mut bytes = out.into_bytes();
    if let Some(enc) = appended_encoding {
        bytes.extend_from_slice(format!("  <AppendedData encoding=\"{enc}\">\n   _").as_bytes());
        if enc == "raw" {
            bytes.extend_from_slice(&header);
            bytes.extend_from_slice(&payload);
        } else {
            bytes.extend_from_slice(b64(&header).as_bytes());
            bytes.extend_from_slice(b64(&payload).as_bytes());
        }
        bytes.extend_from_slice(b"\n  </AppendedData>\n");
    }
    bytes.extend_from_slice(b"</VTKFile>\n");
    bytes
}

#[cfg(test)]
mod tests {
    use super::*;

    fn sample() -> LabelVolume {
        let mut v = LabelVolume::new([6, 5, 4], [0.003, 0.003, 0.002], Vec3::new(-0.1, 0.02, 0.05));
        for (n, l) in v.labels.iter_mut().enumerate() {
            *l = ((n * 13) % 7) as u16 * 300;
        }
        v.direction = crate::math::Quat::from_euler_angles(0.1, 0.2, -0.4).to_rotation_matrix().into_inner();
        v
    }

    fn same(a: &LabelVolume, b: &LabelVolume) {
        assert_eq!(a.dims, b.dims);
        assert_eq!(a.labels, b.labels);
        for k in 0..3 {
            assert!((a.spacing_m[k] - b.spacing_m[k]).abs() < 1e-12);
            assert!((a.origin_m[k] - b.origin_m[k]).abs() < 1e-12);
        }
        assert!((a.direction - b.direction).norm() < 1e-12);
    }

    #[test]
    fn every_encoding_reads_back() {
        let v = sample();
        for enc in [
            VtiEncoding::Ascii,
            VtiEncoding::InlineBase64 { zlib: false },
            VtiEncoding::InlineBase64 { zlib: true },
            VtiEncoding::AppendedRaw { zlib: false },
            VtiEncoding::AppendedRaw { zlib: true },
            VtiEncoding::AppendedBase64 { zlib: false },
            VtiEncoding::AppendedBase64 { zlib: true },
        ] {
            let back = parse_vti(&encode_vti(&v, enc), None, 1e-3).unwrap_or_else(|e| panic!("{enc:?}: {e}"));
            same(&v, &back);
        }
    }

    #[test]
    fn base64_header_and_data_encoded_together_also_reads() {
        let v = sample();
        let data: Vec<u8> = v.labels.iter().flat_map(|l| l.to_le_bytes()).collect();
        let mut joined = (data.len() as u32).to_le_bytes().to_vec();
        joined.extend_from_slice(&data);
        let text = String::from_utf8(encode_vti(&v, VtiEncoding::Ascii)).unwrap();
        let (before, after) = (text.find("format=\"ascii\">").unwrap(), text.find("</DataArray>").unwrap());
        let encoded = base64::engine::general_purpose::STANDARD.encode(&joined);
        let mixed = format!("{}format=\"binary\">{encoded}{}", &text[..before], &text[after..]);
        same(&v, &parse_vti(mixed.as_bytes(), None, 1e-3).unwrap());
    }

    #[test]
    fn corrupt_files_say_what_is_wrong() {
        let v = sample();
        let raw = encode_vti(&v, VtiEncoding::AppendedRaw { zlib: false });
        let cut = raw.len() - 100;
        let e = parse_vti(&raw[..cut], None, 1e-3).unwrap_err();
        assert!(e.contains("truncated"), "{e}");
        let mut zipped = encode_vti(&v, VtiEncoding::AppendedRaw { zlib: true });
        let n = zipped.len();
        zipped[n - 40] ^= 0xff;
        let e = parse_vti(&zipped, None, 1e-3).unwrap_err();
        assert!(e.contains("corrupt") || e.contains("inflates"), "{e}");
        let e = parse_vti(b"<VTKFile type=\"PolyData\">", None, 1e-3).unwrap_err();
        assert!(e.contains("not ImageData"), "{e}");
        let e = parse_vti(&encode_vti(&v, VtiEncoding::Ascii), Some("density"), 1e-3).unwrap_err();
        assert!(e.contains("no data array named \"density\"") && e.contains("labels"), "{e}");
        let text = String::from_utf8(encode_vti(&v, VtiEncoding::Ascii)).unwrap().replacen(" 300 ", " 3.5 ", 1);
        assert!(parse_vti(text.as_bytes(), None, 1e-3).unwrap_err().contains("whole numbers"));
    }
}
