//! Reading a template surface and its motion: Wavefront OBJ (`v` and `f` lines), PLY (ASCII or
//! binary little-endian; `x y z` vertices and face lists), glTF 2.0 (`.gltf`/`.glb`, every
//! triangle primitive of every mesh, metres converted to mm) — polygons are fanned into
//! triangles — and NumPy `.npy` arrays of per-frame vertex positions (frames x vertices x 3,
//! little-endian f64 or f32, C order). Errors name the file and line.

use std::path::Path;

/// A triangle mesh read from a file.
#[derive(Clone, Debug)]
pub struct MeshData {
    /// Vertex positions.
    pub vertices: Vec<[f32; 3]>,
    /// Triangles.
    pub triangles: Vec<[u32; 3]>,
}

/// Reads the vertices (and faces, if any) of a PLY point cloud or mesh, or of any mesh
/// [`read_mesh`] reads.
pub fn read_geometry(path: &Path) -> Result<MeshData, String> {
    let is_ply = path
        .extension()
        .and_then(|e| e.to_str())
        .is_some_and(|e| e.eq_ignore_ascii_case("ply"));
    if is_ply {
        let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
        return parse_ply_points(&bytes).map_err(|e| format!("{}: {e}", path.display()));
    }
    read_mesh(path)
}

/// Reads a mesh, choosing the format by extension (`obj`, `ply`, `gltf`, `glb`).
pub fn read_mesh(path: &Path) -> Result<MeshData, String> {
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(str::to_ascii_lowercase);
    match ext.as_deref() {
        Some("obj") => read_obj(path),
        Some("ply") => {
            let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
            parse_ply(&bytes).map_err(|e| format!("{}: {e}", path.display()))
        }
        Some("gltf" | "glb") => read_gltf(path),
        _ => Err(format!(
            "{}: unknown mesh format (expected .obj, .ply, .gltf or .glb)",
            path.display()
        )),
    }
}

/// Reads every triangle primitive of a glTF file; positions in metres become mm.
pub fn read_gltf(path: &Path) -> Result<MeshData, String> {
    let (doc, buffers, _) = gltf::import(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    for mesh in doc.meshes() {
        for prim in mesh.primitives() {
            if prim.mode() != gltf::mesh::Mode::Triangles {
                continue;
            }
            let reader = prim.reader(|b| buffers.get(b.index()).map(|d| &d.0[..]));
            let Some(pos) = reader.read_positions() else {
                continue;
            };
            let base = vertices.len() as u32;
            vertices.extend(pos.map(|p| p.map(|v| v * 1000.0)));
            let n = vertices.len() as u32 - base;
            let idx: Vec<u32> = match reader.read_indices() {
                Some(i) => i.into_u32().collect(),
                None => (0..n).collect(),
            };
            for t in idx.chunks_exact(3) {
                if t.iter().any(|&i| i >= n) {
                    return Err(format!(
                        "{}: a triangle indexes past its primitive's vertices",
                        path.display()
                    ));
                }
                triangles.push([base + t[0], base + t[1], base + t[2]]);
            }
        }
    }
    if triangles.is_empty() {
        return Err(format!("{}: no triangle meshes", path.display()));
    }
    Ok(MeshData {
        vertices,
        triangles,
    })
}

/// A PLY property: name, value type, and the count type when it is a list.
type PlyProperty = (String, String, Option<String>);
/// A PLY element: name, count, properties.
type PlyElement = (String, usize, Vec<PlyProperty>);

/// Parses PLY bytes (ASCII or binary little-endian); a mesh needs faces.
pub fn parse_ply(bytes: &[u8]) -> Result<MeshData, String> {
    parse_ply_impl(bytes, true)
}

/// Parses PLY bytes that may hold only vertices (a point cloud or surfel model).
pub fn parse_ply_points(bytes: &[u8]) -> Result<MeshData, String> {
    parse_ply_impl(bytes, false)
}

fn parse_ply_impl(bytes: &[u8], require_faces: bool) -> Result<MeshData, String> {
    let end = bytes
        .windows(10)
        .position(|w| w == b"end_header")
        .ok_or("no end_header")?;
    let header = std::str::from_utf8(&bytes[..end]).map_err(|_| "header is not text")?;
    let mut body = end + 10;
    while body < bytes.len() && (bytes[body] == b'\r' || bytes[body] == b'\n') {
        body += 1;
        if bytes[body - 1] == b'\n' {
            break;
        }
    }
    let mut binary = false;
    let mut elements: Vec<PlyElement> = Vec::new();
    for line in header.lines().skip(1) {
        let w: Vec<&str> = line.split_whitespace().collect();
        match w.as_slice() {
            ["format", "ascii", ..] => binary = false,
            ["format", "binary_little_endian", ..] => binary = true,
            ["format", f, ..] => return Err(format!("unsupported PLY format `{f}`")),
            ["element", name, count] => elements.push((
                name.to_string(),
                count
                    .parse()
                    .map_err(|_| format!("bad count in `{line}`"))?,
                Vec::new(),
            )),
            ["property", "list", it, vt, name] => elements
                .last_mut()
                .ok_or("property before element")?
                .2
                .push((name.to_string(), vt.to_string(), Some(it.to_string()))),
            ["property", t, name] => elements
                .last_mut()
                .ok_or("property before element")?
                .2
                .push((name.to_string(), t.to_string(), None)),
            _ => {}
        }
    }
    let size = |t: &str| -> Result<usize, String> {
        Ok(match t {
            "char" | "uchar" | "int8" | "uint8" => 1,
            "short" | "ushort" | "int16" | "uint16" => 2,
            "int" | "uint" | "int32" | "uint32" | "float" | "float32" => 4,
            "double" | "float64" => 8,
            other => return Err(format!("unknown PLY type `{other}`")),
        })
    };
    let read_bin = |b: &[u8], t: &str| -> f64 {
        match t {
            "char" | "int8" => b[0] as i8 as f64,
            "uchar" | "uint8" => b[0] as f64,
            "short" | "int16" => i16::from_le_bytes([b[0], b[1]]) as f64,
            "ushort" | "uint16" => u16::from_le_bytes([b[0], b[1]]) as f64,
            "int" | "int32" => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            "uint" | "uint32" => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            "float" | "float32" => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            _ => f64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]]),
        }
    };
    let mut vertices = Vec::new();
    let mut triangles = Vec::new();
    let mut pos = body;
    let text = if binary {
        String::new()
    } else {
        String::from_utf8_lossy(&bytes[body..]).into_owned()
    };
    let mut tokens = text.split_whitespace();
    let mut next_value = |t: &str, pos: &mut usize| -> Result<f64, String> {
        if binary {
            let n = size(t)?;
            let b = bytes.get(*pos..*pos + n).ok_or("truncated PLY data")?;
            *pos += n;
            Ok(read_bin(b, t))
        } else {
            tokens
                .next()
                .ok_or("truncated PLY data")?
                .parse::<f64>()
                .map_err(|_| "bad PLY number".to_string())
        }
    };
    for (name, count, props) in &elements {
        for _ in 0..*count {
            let mut xyz = [f32::NAN; 3];
            let mut face: Vec<u32> = Vec::new();
            for (pname, t, list) in props {
                match list {
                    Some(it) => {
                        let n = next_value(it, &mut pos)? as usize;
                        for _ in 0..n {
                            let v = next_value(t, &mut pos)?;
                            if name == "face" {
                                face.push(v as u32);
                            }
                        }
                    }
                    None => {
                        let v = next_value(t, &mut pos)?;
                        match pname.as_str() {
                            "x" => xyz[0] = v as f32,
                            "y" => xyz[1] = v as f32,
                            "z" => xyz[2] = v as f32,
                            _ => {}
                        }
                    }
                }
            }
            if name == "vertex" {
                if xyz.iter().any(|v| !v.is_finite()) {
                    return Err(format!("vertex {} has no finite x, y, z", vertices.len()));
                }
                vertices.push(xyz);
            } else if name == "face" && face.len() >= 3 {
                for k in 1..face.len() - 1 {
                    triangles.push([face[0], face[k], face[k + 1]]);
                }
            }
        }
    }
    if let Some(t) = triangles
        .iter()
        .find(|t| t.iter().any(|&i| i as usize >= vertices.len()))
    {
        return Err(format!(
            "face {t:?} indexes past the {} vertices",
            vertices.len()
        ));
    }
    if require_faces && triangles.is_empty() {
        return Err("no faces".into());
    }
    Ok(MeshData {
        vertices,
        triangles,
    })
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

/// The most an organ's mesh, or its motion, may span along an axis, mm. An organ, or a whole
/// abdomen, is well under it: beyond it the file is corrupt or not in millimetres (and the
/// phantom, which bakes its albedo every 0.1 mm over the mesh's box, would need gigabytes).
pub const MAX_EXTENT_MM: f32 = 1000.0;

/// Checks that `positions` (`per_frame` vertices a frame, frame after frame; one frame for a
/// mesh) span at most [`MAX_EXTENT_MM`] along each axis. The error names the position farthest
/// from the median along the widest axis: its frame (where there are several) and vertex.
pub fn check_extent(positions: &[[f32; 3]], per_frame: usize) -> Result<(), String> {
    let per_frame = per_frame.max(1);
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in positions {
        for a in 0..3 {
            lo[a] = lo[a].min(p[a]);
            hi[a] = hi[a].max(p[a]);
        }
    }
    let span = |a: usize| hi[a] - lo[a];
    let axis = (0..3).fold(0, |w, a| if span(a) > span(w) { a } else { w });
    if span(axis) <= MAX_EXTENT_MM {
        return Ok(());
    }
    let mut along: Vec<f32> = positions.iter().map(|p| p[axis]).collect();
    let mid = along.len() / 2;
    let median = *along.select_nth_unstable_by(mid, f32::total_cmp).1;
    let farthest = positions.iter().enumerate().max_by(|a, b| {
        (a.1[axis] - median)
            .abs()
            .total_cmp(&(b.1[axis] - median).abs())
    });
    // A span over the limit has positions; the let-else only spares a panic path.
    let Some((i, p)) = farthest else {
        return Ok(());
    };
    let at = if positions.len() > per_frame {
        format!("frame {}, vertex {}", i / per_frame, i % per_frame)
    } else {
        format!("vertex {i}")
    };
    let span = if span(axis) < 1e7 {
        format!("{:.0}", span(axis))
    } else {
        format!("{:.1e}", span(axis))
    };
    Err(format!(
        "the positions span {span} mm along {}, more than the {MAX_EXTENT_MM} mm an organ can \
         (corrupt, or not in millimetres?); the farthest out is {at} at {p:?}",
        ["x", "y", "z"][axis],
    ))
}

/// Reads an `.npy` array of shape (frames, vertices, 3) as f32.
pub fn read_npy_frames(path: &Path) -> Result<(usize, usize, Vec<[f32; 3]>), String> {
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    parse_npy_frames(&bytes).map_err(|e| format!("{}: {e}", path.display()))
}

/// `.npy` bytes (version 1, little-endian f32, C order) of shape (frames, vertices, 3) holding
/// `positions`, frame after frame: what [`parse_npy_frames`] reads.
pub fn encode_npy_frames(frames: usize, positions: &[[f32; 3]]) -> Vec<u8> {
    let per_frame = positions.len().checked_div(frames).unwrap_or(0);
    let mut h = format!(
        "{{'descr': '<f4', 'fortran_order': False, 'shape': ({frames}, {per_frame}, 3), }}"
    );
    // The header is padded with spaces to a multiple of 64 bytes, ending in a newline.
    while !(10 + h.len() + 1).is_multiple_of(64) {
        h.push(' ');
    }
    h.push('\n');
    let mut bytes = b"\x93NUMPY\x01\x00".to_vec();
    bytes.extend((h.len() as u16).to_le_bytes());
    bytes.extend(h.as_bytes());
    for c in positions.iter().flatten() {
        bytes.extend(c.to_le_bytes());
    }
    bytes
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
    fn ply_ascii_and_binary() {
        let ascii = b"ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\nproperty float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n0 0 0\n1 0 0\n1 1 0\n0 1 0\n4 0 1 2 3\n";
        let m = parse_ply(ascii).unwrap();
        assert_eq!(m.vertices.len(), 4);
        assert_eq!(m.triangles, vec![[0, 1, 2], [0, 2, 3]]);
        let mut bin = b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty double x\nproperty double y\nproperty double z\nproperty uchar red\nelement face 1\nproperty list uchar uint vertex_indices\nend_header\n".to_vec();
        for v in [[0.0f64, 0.0, 5.0], [1.0, 0.0, 5.0], [0.0, 1.0, 5.0]] {
            for c in v {
                bin.extend(c.to_le_bytes());
            }
            bin.push(200);
        }
        bin.push(3);
        for i in [0u32, 1, 2] {
            bin.extend(i.to_le_bytes());
        }
        let m = parse_ply(&bin).unwrap();
        assert_eq!(m.vertices[1], [1.0, 0.0, 5.0]);
        assert_eq!(m.triangles, vec![[0, 1, 2]]);
        assert!(parse_ply(&bin[..bin.len() - 2])
            .unwrap_err()
            .contains("truncated"));
    }

    #[test]
    fn npy_round_trip() {
        let bytes = encode_npy_frames(2, &[[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        assert_eq!(&bytes[10..30], b"{'descr': '<f4', 'fo");
        assert_eq!((bytes.len() - 24) % 64, 0, "the header pads to 64 bytes");
        let (f, v, data) = parse_npy_frames(&bytes).unwrap();
        assert_eq!((f, v), (2, 1));
        assert_eq!(data, vec![[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]);
        assert!(parse_npy_frames(&bytes[..bytes.len() - 4])
            .unwrap_err()
            .contains("needed"));
    }

    #[test]
    fn an_organ_sized_span_passes_and_a_stray_position_is_named() {
        // A 90 mm organ, 30 vertices, with 0.5 mm of motion over 4 frames.
        let organ: Vec<[f32; 3]> = (0..30)
            .map(|i| [3.0 * i as f32, (i % 5) as f32, 100.0])
            .collect();
        assert!(check_extent(&organ, organ.len()).is_ok());
        let mut frames: Vec<[f32; 3]> = (0..4)
            .flat_map(|f| {
                organ
                    .iter()
                    .map(move |v| [v[0], v[1], v[2] + 0.5 * f as f32 / 3.0])
            })
            .collect();
        assert!(check_extent(&frames, organ.len()).is_ok());
        // Exactly the limit is allowed.
        let edge = [[0.0, 0.0, 0.0], [MAX_EXTENT_MM, 0.0, 0.0]];
        assert!(check_extent(&edge, 2).is_ok());
        // A corrupt byte: vertex 7 of frame 2, 54 m off along z.
        frames[2 * 30 + 7][2] = -53_816.9;
        let e = check_extent(&frames, organ.len()).unwrap_err();
        assert!(
            e.contains("frame 2, vertex 7") && e.contains("along z"),
            "{e}"
        );
        // One frame: the vertex alone; the widest axis is the one named.
        let mut mesh = organ.clone();
        mesh[12] = [5.99e19, -60.0, 94.8];
        mesh[3][1] = 2_000.0;
        let e = check_extent(&mesh, mesh.len()).unwrap_err();
        assert!(
            e.contains("vertex 12 ") && e.contains("along x") && e.contains("6.0e19"),
            "{e}"
        );
    }
}
