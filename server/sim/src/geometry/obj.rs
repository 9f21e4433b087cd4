//! Wavefront OBJ reader: vertices (`v`) and faces (`f`, polygons fan-triangulated),
//! with `v/vt/vn` index forms and negative (relative) indices. Texture coordinates,
//! normals, groups, smoothing and material statements are accepted and ignored.

use std::io::BufRead;

use crate::geometry::TriMesh;
use crate::math::Vec3;

/// Reads an OBJ file; positions are in the file's units (the caller scales them).
pub fn read_obj_file(path: &std::path::Path) -> Result<TriMesh, String> {
    let file = std::fs::File::open(path).map_err(|e| format!("cannot open {}: {e}", path.display()))?;
    parse_obj(std::io::BufReader::new(file)).map_err(|e| format!("{}: {e}", path.display()))
}

/// Parses OBJ text. Errors name the line and what was expected.
pub fn parse_obj(reader: impl BufRead) -> Result<TriMesh, String> {
    const MAX_VERTICES: usize = 10_000_000;
    let mut mesh = TriMesh::default();
    let mut face: Vec<u32> = Vec::new();
    for (index, line) in reader.lines().enumerate() {
        let line_no = index + 1;
        let line = line.map_err(|e| format!("line {line_no}: cannot read: {e}"))?;
        let line = line.split('#').next().unwrap_or("").trim();
        let mut words = line.split_whitespace();
        let Some(keyword) = words.next() else { continue };
        match keyword {
            "v" => {
                let mut xyz = [0.0f64; 3];
                for (k, c) in xyz.iter_mut().enumerate() {
                    let word = words
                        .next()
                        .ok_or_else(|| format!("line {line_no}: a vertex needs 3 coordinates, found {k}"))?;
                    *c = word
                        .parse::<f64>()
                        .ok()
                        .filter(|v| v.is_finite())
                        .ok_or_else(|| format!("line {line_no}: vertex coordinate {word:?} is not a finite number"))?;
                }
                if mesh.positions.len() >= MAX_VERTICES {
                    return Err(format!("line {line_no}: more than {MAX_VERTICES} vertices"));
                }
                mesh.positions.push(Vec3::new(xyz[0], xyz[1], xyz[2]));
            }
            "f" => {
                face.clear();
                for word in words {
                    let first = word.split('/').next().unwrap_or("");
                    let raw: i64 = first
                        .parse()
                        .map_err(|_| format!("line {line_no}: face index {word:?} is not an integer"))?;
                    let count = mesh.positions.len() as i64;
                    let resolved = if raw > 0 { raw - 1 } else if raw < 0 { count + raw } else { -1 };
                    if resolved < 0 || resolved >= count {
                        return Err(format!(
                            "line {line_no}: face index {raw} is out of range (the file has {count} vertices before this line; indices start at 1, negative ones count back)"
                        ));
                    }
                    face.push(resolved as u32);
                }
                if face.len() < 3 {
                    return Err(format!("line {line_no}: a face needs at least 3 vertices, found {}", face.len()));
                }
                for k in 1..face.len() - 1 {
                    mesh.triangles.push([face[0], face[k], face[k + 1]]);
                }
            }
            "vt" | "vn" | "vp" | "g" | "o" | "s" | "usemtl" | "mtllib" | "l" | "p" => {}
            other => {
                return Err(format!("line {line_no}: unknown statement {other:?} (an OBJ file has v, f, vt, vn, g, o, s, usemtl, mtllib)"));
            }
        }
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parses_quads_slashes_and_negative_indices() {
        let text = "# square\nv 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nvn 0 0 1\nf 1//1 2//1 3//1 4//1\nf -4 -3 -2\n";
        let mesh = parse_obj(text.as_bytes()).unwrap();
        assert_eq!(mesh.positions.len(), 4);
        assert_eq!(mesh.triangles, vec![[0, 1, 2], [0, 2, 3], [0, 1, 2]]);
    }

    #[test]
    fn errors_name_the_line() {
        let err = parse_obj("v 0 0 0\nv 1 0\n".as_bytes()).unwrap_err();
        assert_eq!(err, "line 2: a vertex needs 3 coordinates, found 2");
        let err = parse_obj("v 0 0 0\nf 1 2 3\n".as_bytes()).unwrap_err();
        assert!(err.starts_with("line 2: face index 2 is out of range"), "{err}");
        let err = parse_obj("v 0 0 nan\n".as_bytes()).unwrap_err();
        assert!(err.contains("not a finite number"), "{err}");
        let err = parse_obj("hello\n".as_bytes()).unwrap_err();
        assert!(err.contains("unknown statement"), "{err}");
    }
}
