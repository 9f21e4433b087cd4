//! VTK legacy polydata reader (`.vtk`): `ASCII` or `BINARY` (big-endian), `POINTS`
//! (float or double), `POLYGONS` and `TRIANGLE_STRIPS` in the classic cell layout
//! (`n size` then `count i0 i1 …` per cell) or the `OFFSETS`/`CONNECTIVITY` layout of
//! file version 5. Polygons are fan-triangulated, strips unrolled with alternating
//! winding. `VERTICES` and `LINES` are skipped; point and cell attributes end the read.

use crate::geometry::TriMesh;
use crate::math::Vec3;

/// Reads a legacy VTK polydata file; positions are in the file's units.
pub fn read_vtk_file(path: &std::path::Path) -> Result<TriMesh, String> {
    let bytes = std::fs::read(path).map_err(|e| format!("cannot read {}: {e}", path.display()))?;
    parse_vtk(&bytes).map_err(|e| format!("{}: {e}", path.display()))
}

struct Cursor<'a> {
    bytes: &'a [u8],
    at: usize,
    binary: bool,
}

impl<'a> Cursor<'a> {
    /// The next line (without its end), or None at the end of the file.
    fn line(&mut self) -> Option<&'a str> {
        if self.at >= self.bytes.len() {
            return None;
        }
        let end = self.bytes[self.at..].iter().position(|&b| b == b'\n').map_or(self.bytes.len(), |p| p + self.at);
        let line = std::str::from_utf8(&self.bytes[self.at..end]).unwrap_or("");
        self.at = end + 1;
        Some(line.trim_end_matches('\r'))
    }

    /// The next non-blank line.
    fn keyword_line(&mut self) -> Option<&'a str> {
        loop {
            let line = self.line()?;
            if !line.trim().is_empty() {
                return Some(line);
            }
        }
    }

    fn ascii_token(&mut self) -> Result<&'a str, String> {
        while self.at < self.bytes.len() && self.bytes[self.at].is_ascii_whitespace() {
            self.at += 1;
        }
        let start = self.at;
        while self.at < self.bytes.len() && !self.bytes[self.at].is_ascii_whitespace() {
            self.at += 1;
        }
        if start == self.at {
            return Err("the file ends in the middle of a data section (truncated)".into());
        }
        std::str::from_utf8(&self.bytes[start..self.at]).map_err(|_| "a number is not ASCII text".to_string())
    }

    fn take(&mut self, n: usize) -> Result<&'a [u8], String> {
        let end = self.at.checked_add(n).filter(|&e| e <= self.bytes.len()).ok_or_else(|| {
            format!("the file is truncated: {n} bytes of binary data expected at byte {}, {} left", self.at, self.bytes.len().saturating_sub(self.at))
        })?;
        let out = &self.bytes[self.at..end];
        self.at = end;
        Ok(out)
    }

    fn reals(&mut self, n: usize, kind: &str) -> Result<Vec<f64>, String> {
        if !self.binary {
            return (0..n).map(|_| self.ascii_token()?.parse::<f64>().map_err(|_| "a coordinate is not a number".to_string())).collect();
        }
        let (size, double) = match kind {
            "float" => (4, false),
            "double" => (8, true),
            other => return Err(format!("point type {other:?} is not supported (float or double)")),
        };
        let raw = self.take(n * size)?;
        Ok(raw
            .chunks_exact(size)
            .map(|c| if double { f64::from_be_bytes(c.try_into().expect("8")) } else { f64::from(f32::from_be_bytes(c.try_into().expect("4"))) })
            .collect())
    }

    fn ints(&mut self, n: usize, kind: &str) -> Result<Vec<i64>, String> {
        if !self.binary {
            return (0..n).map(|_| self.ascii_token()?.parse::<i64>().map_err(|_| "an index is not an integer".to_string())).collect();
        }
        let size = match kind {
            "int" | "vtktypeint32" => 4,
            "vtktypeint64" | "long" => 8,
            other => return Err(format!("index type {other:?} is not supported")),
        };
        let raw = self.take(n * size)?;
        Ok(raw
            .chunks_exact(size)
            .map(|c| if size == 8 { i64::from_be_bytes(c.try_into().expect("8")) } else { i64::from(i32::from_be_bytes(c.try_into().expect("4"))) })
            .collect())
    }
}

fn count(word: Option<&str>, what: &str) -> Result<usize, String> {
    word.and_then(|w| w.parse::<usize>().ok()).filter(|&n| n <= 100_000_000).ok_or_else(|| format!("{what} needs a count"))
}

/// Parses a legacy VTK polydata file.
pub fn parse_vtk(bytes: &[u8]) -> Result<TriMesh, String> {
    let mut c = Cursor { bytes, at: 0, binary: false };
    let version = c.line().unwrap_or("");
    if !version.starts_with("# vtk DataFile Version") {
        return Err("not a legacy VTK file: the first line must be \"# vtk DataFile Version x.x\"".into());
    }
    let _title = c.line().ok_or("the file ends after its first line")?;
    c.binary = match c.keyword_line().map(str::trim) {
        Some("ASCII") => false,
        Some("BINARY") => true,
        other => return Err(format!("line 3 must be ASCII or BINARY, found {other:?}")),
    };
    let dataset = c.keyword_line().unwrap_or("");
    if dataset.split_whitespace().nth(1) != Some("POLYDATA") {
        return Err(format!("only POLYDATA is supported, the file has {:?}", dataset.trim()));
    }
    let mut mesh = TriMesh::default();
    while let Some(line) = c.keyword_line() {
        let mut words = line.split_whitespace();
        let keyword = words.next().unwrap_or("");
        match keyword {
            "POINTS" => {
                let n = count(words.next(), "POINTS")?;
                let kind = words.next().unwrap_or("float").to_owned();
                let values = c.reals(3 * n, &kind)?;
                if let Some(bad) = values.iter().position(|v| !v.is_finite()) {
                    return Err(format!("point {} has a non-finite coordinate", bad / 3));
                }
                mesh.positions = values.chunks_exact(3).map(|p| Vec3::new(p[0], p[1], p[2])).collect();
                if c.binary {
                    c.line(); // the newline after the binary block
                }
            }
            "POLYGONS" | "TRIANGLE_STRIPS" | "VERTICES" | "LINES" => {
                let cells = read_cells(&mut c, &mut words)?;
                let n = mesh.positions.len();
                for cell in cells {
                    if let Some(&bad) = cell.iter().find(|&&i| i < 0 || i as usize >= n) {
                        return Err(format!("{keyword}: index {bad} is out of range (the file has {n} points)"));
                    }
                    let cell: Vec<u32> = cell.iter().map(|&i| i as u32).collect();
                    if keyword == "POLYGONS" {
                        for k in 1..cell.len().saturating_sub(1) {
                            mesh.triangles.push([cell[0], cell[k], cell[k + 1]]);
                        }
                    } else if keyword == "TRIANGLE_STRIPS" {
                        for k in 0..cell.len().saturating_sub(2) {
                            let t = if k % 2 == 0 { [cell[k], cell[k + 1], cell[k + 2]] } else { [cell[k + 1], cell[k], cell[k + 2]] };
                            mesh.triangles.push(t);
                        }
                    }
                }
            }
            "METADATA" => {
                // Blank-line-terminated block of information keys.
                while let Some(l) = c.line() {
                    if l.trim().is_empty() {
                        break;
                    }
                }
            }
            "POINT_DATA" | "CELL_DATA" | "FIELD" => break,
            other => return Err(format!("unknown section {other:?} in polydata")),
        }
    }
    if mesh.positions.is_empty() {
        return Err("the file has no POINTS".into());
    }
    Ok(mesh)
}

fn read_cells<'a>(c: &mut Cursor, words: &mut impl Iterator<Item = &'a str>) -> Result<Vec<Vec<i64>>, String> {
    let first = count(words.next(), "a cell section")?;
    let second = count(words.next(), "a cell section")?;
    // Version 5 layout: "POLYGONS n_offsets n_connectivity", then OFFSETS and CONNECTIVITY arrays.
    let save = c.at;
    let next = c.keyword_line().unwrap_or("");
    if next.starts_with("OFFSETS") {
        let kind = next.split_whitespace().nth(1).unwrap_or("vtktypeint64").to_owned();
        let offsets = c.ints(first, &kind)?;
        if c.binary {
            c.line();
        }
        let conn_line = c.keyword_line().unwrap_or("");
        if !conn_line.starts_with("CONNECTIVITY") {
            return Err("OFFSETS must be followed by CONNECTIVITY".into());
        }
        let kind = conn_line.split_whitespace().nth(1).unwrap_or("vtktypeint64").to_owned();
        let conn = c.ints(second, &kind)?;
        if c.binary {
            c.line();
        }
        let mut cells = Vec::new();
        for w in offsets.windows(2) {
            let (a, b) = (w[0], w[1]);
            if a < 0 || b < a || b as usize > conn.len() {
                return Err(format!("cell offsets {a}..{b} are out of range"));
            }
            cells.push(conn[a as usize..b as usize].to_vec());
        }
        return Ok(cells);
    }
    c.at = save;
    let data = c.ints(second, "int")?;
    if c.binary {
        c.line();
    }
    let mut cells = Vec::with_capacity(first);
    let mut at = 0usize;
    for cell in 0..first {
        let n = *data.get(at).ok_or_else(|| format!("cell {cell} is missing (the section promised {first} cells in {second} numbers)"))?;
        if n < 0 || at + 1 + n as usize > data.len() {
            return Err(format!("cell {cell} claims {n} points, beyond the section's {second} numbers"));
        }
        cells.push(data[at + 1..at + 1 + n as usize].to_vec());
        at += 1 + n as usize;
    }
    Ok(cells)
}

#[cfg(test)]
mod tests {
    use super::*;

    const TETRA: &str = "# vtk DataFile Version 3.0\ntetra\nASCII\nDATASET POLYDATA\nPOINTS 4 float\n0 0 0 1 0 0 0 1 0 0 0 1\nPOLYGONS 4 16\n3 0 2 1\n3 0 1 3\n3 0 3 2\n3 1 2 3\n";

    #[test]
    fn reads_ascii_and_binary_and_version5_layouts() {
        let ascii = parse_vtk(TETRA.as_bytes()).unwrap();
        assert_eq!(ascii.positions.len(), 4);
        assert_eq!(ascii.triangles.len(), 4);
        ascii.check().unwrap();

        let mut binary = b"# vtk DataFile Version 3.0\nt\nBINARY\nDATASET POLYDATA\nPOINTS 4 float\n".to_vec();
        for p in &ascii.positions {
            for c in p.iter() {
                binary.extend_from_slice(&(*c as f32).to_be_bytes());
            }
        }
        binary.extend_from_slice(b"\nPOLYGONS 4 16\n");
        for t in &ascii.triangles {
            for v in [3, t[0], t[1], t[2]] {
                binary.extend_from_slice(&(v as i32).to_be_bytes());
            }
        }
        binary.extend_from_slice(b"\n");
        assert_eq!(parse_vtk(&binary).unwrap(), ascii);

        let v5 = "# vtk DataFile Version 5.1\nt\nASCII\nDATASET POLYDATA\nPOINTS 4 float\n0 0 0 1 0 0 0 1 0 0 0 1\nPOLYGONS 5 12\nOFFSETS vtktypeint64\n0 3 6 9 12\nCONNECTIVITY vtktypeint64\n0 2 1 0 1 3 0 3 2 1 2 3\n";
        assert_eq!(parse_vtk(v5.as_bytes()).unwrap(), ascii);
    }

    #[test]
    fn errors_say_what_is_wrong() {
        assert!(parse_vtk(b"hello").unwrap_err().contains("not a legacy VTK file"));
        let truncated = &TETRA[..TETRA.len() - 12];
        assert!(parse_vtk(truncated.as_bytes()).unwrap_err().contains("truncated"));
        let bad_index = TETRA.replace("3 1 2 3", "3 1 2 9");
        assert!(parse_vtk(bad_index.as_bytes()).unwrap_err().contains("index 9 is out of range"));
        let grid = TETRA.replace("POLYDATA", "STRUCTURED_POINTS");
        assert!(parse_vtk(grid.as_bytes()).unwrap_err().contains("only POLYDATA"));
    }
}
