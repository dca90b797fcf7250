//! Reading a template surface and its motion: Wavefront OBJ (`v` and `f` lines; polygons are
//! fanned into triangles) and NumPy `.npy` arrays of per-frame vertex positions
//! (frames x vertices x 3, little-endian f64 or f32, C order). Errors name the file and line.

use std::path::Path;

/// A triangle mesh read from a file.
#[derive(Clone, Debug)]
pub struct MeshData {
    /// Vertex positions.
    pub vertices: Vec<[f32; 3]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
}

/// Reads an OBJ file.
pub fn read_obj(path: &Path) -> Result<MeshData, String> {
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_obj(&text).map_err(|e| format!("{}: {e}", path.display()))
}

/// Parses OBJ text.
pub fn parse_obj(text: &str) -> Result<MeshData, String> {
    let mut vertices = Vec::new();
    let mut faces: Vec<(usize, Vec<i64>)> = Vec::new();
    for (ln, line) in text.lines().enumerate() {
        let mut it = line.split_whitespace();
        match it.next() {
            Some("v") => {
                let c: Vec<f32> = it
                    .take(3)
                    .map(|s| {
                        s.parse::<f32>()
                            .map_err(|_| format!("line {}: `{s}` is not a number", ln + 1))
                    })
                    .collect::<Result<_, _>>()?;
                if c.len() != 3 || c.iter().any(|v| !v.is_finite()) {
                    return Err(format!(
                        "line {}: a vertex needs 3 finite coordinates",
                        ln + 1
                    ));
                }
                vertices.push([c[0], c[1], c[2]]);
            }
            Some("f") => {
                let idx: Vec<i64> = it
                    .map(|s| {
                        let first = s.split('/').next().unwrap_or("");
                        first
                            .parse::<i64>()
                            .map_err(|_| format!("line {}: bad face index `{s}`", ln + 1))
                    })
                    .collect::<Result<_, _>>()?;
                if idx.len() < 3 {
                    return Err(format!("line {}: a face needs at least 3 vertices", ln + 1));
                }
                faces.push((ln + 1, idx));
            }
            _ => {}
        }
    }
    let n = vertices.len() as i64;
    let mut triangles = Vec::new();
    for (ln, idx) in faces {
        // 1-based; negative indices count back from the last vertex read.
        let resolve = |i: i64| -> Result<u32, String> {
            let r = if i > 0 { i - 1 } else { n + i };
            if r < 0 || r >= n {
                return Err(format!(
                    "line {ln}: face index {i} is outside the {n} vertices"
                ));
            }
            Ok(r as u32)
        };
        let v: Vec<u32> = idx.into_iter().map(resolve).collect::<Result<_, _>>()?;
        for k in 1..v.len() - 1 {
            triangles.push([v[0], v[k], v[k + 1]]);
        }
    }
    if triangles.is_empty() {
        return Err("no faces".into());
    }
    Ok(MeshData {
        vertices,
        triangles,
    })
}

/// Reads an `.npy` array of shape (frames, vertices, 3) as f32.
pub fn read_npy_frames(path: &Path) -> Result<(usize, usize, Vec<[f32; 3]>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_npy_frames(&bytes).map_err(|e| format!("{}: {e}", path.display()))
}

/// Parses `.npy` bytes of shape (frames, vertices, 3).
pub fn parse_npy_frames(bytes: &[u8]) -> Result<(usize, usize, Vec<[f32; 3]>), String> {
    if bytes.len() < 10 || &bytes[..6] != b"\x93NUMPY" {
        return Err("not a .npy file".into());
    }
    let (header_len, start) = match bytes[6] {
        1 => (u16::from_le_bytes([bytes[8], bytes[9]]) as usize, 10),
        2 | 3 if bytes.len() >= 12 => (
            u32::from_le_bytes([bytes[8], bytes[9], bytes[10], bytes[11]]) as usize,
            12,
        ),
        v => return Err(format!("unsupported .npy version {v}")),
    };
    let header = std::str::from_utf8(
        bytes
            .get(start..start + header_len)
            .ok_or("truncated header")?,
    )
    .map_err(|_| "header is not text")?;
    let elem = if header.contains("'<f8'") {
        8
    } else if header.contains("'<f4'") {
        4
    } else {
        return Err(format!(
            "dtype must be little-endian f8 or f4: {}",
            header.trim()
        ));
    };
    if header.contains("'fortran_order': True") {
        return Err("Fortran-ordered arrays are not supported".into());
    }
    let shape_text = header
        .split("'shape':")
        .nth(1)
        .and_then(|s| s.split(')').next())
        .ok_or("no shape in header")?;
    let shape: Vec<usize> = shape_text
        .trim()
        .trim_start_matches('(')
        .split(',')
        .filter(|s| !s.trim().is_empty())
        .map(|s| {
            s.trim()
                .parse::<usize>()
                .map_err(|_| format!("bad shape `{shape_text}`"))
        })
        .collect::<Result<_, _>>()?;
    let [frames, verts, 3] = shape[..] else {
        return Err(format!(
            "shape must be (frames, vertices, 3), got {shape:?}"
        ));
    };
    let data = &bytes[start + header_len..];
    let n = frames * verts * 3;
    if data.len() < n * elem {
        return Err(format!("{} bytes of data, {} needed", data.len(), n * elem));
    }
    let value = |i: usize| -> f32 {
        let b = &data[i * elem..(i + 1) * elem];
        if elem == 8 {
            f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]) as f32
        } else {
            f32::from_le_bytes([b[0], b[1], b[2], b[3]])
        }
    };
    let out: Vec<[f32; 3]> = (0..frames * verts)
        .map(|i| [value(3 * i), value(3 * i + 1), value(3 * i + 2)])
        .collect();
    if out.iter().flatten().any(|v| !v.is_finite()) {
        return Err("the array holds non-finite values".into());
    }
    Ok((frames, verts, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn obj_faces_fan_and_errors_name_the_line() {
        let m =
            parse_obj("v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nf 1/1/1 2/2/2 3/3/3 4/4/4\n").unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let m = parse_obj("v 0 0 0\nv 1 0 0\nv 1 1 0\nf -3 -2 -1\n").unwrap();
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        assert_eq!(
            parse_obj("v 0 0 0\nv 1 0 x\n").unwrap_err(),
            "line 2: `x` is not a number"
        );
        assert_eq!(
            parse_obj("v 0 0 0\nv 1 0 0\nv 1 1 0\nf 1 2 9\n").unwrap_err(),
            "line 4: face index 9 is outside the 3 vertices"
        );
    }

    #[test]
    fn npy_round_trip() {
        let header = "{'descr': '<f4', 'fortran_order': False, 'shape': (2, 1, 3), }";
        let mut h = header.to_string();
        while (10 + h.len() + 1) % 64 != 0 {
            h.push(' ');
        }
        h.push('\n');
        let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
        bytes.extend((h.len() as u16).to_le_bytes());
        bytes.extend(h.as_bytes());
        for v in [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0] {
            bytes.extend(v.to_le_bytes());
        }
        let (f, v, data) = parse_npy_frames(&bytes).unwrap();
        assert_eq!((f, v), (2, 1));
        assert_eq!(data, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        assert!(parse_npy_frames(&bytes[..bytes.len() - 4])
            .unwrap_err()
            .contains("needed"));
    }
}
