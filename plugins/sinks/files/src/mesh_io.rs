//! Point clouds and meshes as binary PLY and as glTF binary (`.glb`).

use std::io::{self, Write};
use std::path::Path;

/// What a PLY or glTF file holds: positions, optional normals and colours, optional triangles.
pub struct Geometry<'a> {
    /// Positions, mm.
    pub positions: &'a [[f32; 3]],
    /// Unit normals.
    pub normals: Option<&'a [[f32; 3]]>,
    /// Colours.
    pub colors: Option<&'a [[u8; 3]]>,
    /// Triangles (none for a point cloud).
    pub triangles: &'a [[u32; 3]],
}

/// Writes binary little-endian PLY.
pub fn write_ply(path: &Path, g: &Geometry) -> io::Result<()> {
    let mut out = io::BufWriter::new(std::fs::File::create(path)?);
    writeln!(
        out,
        "ply\nformat binary_little_endian 1.0\ncomment misslam, units mm"
    )?;
    writeln!(out, "element vertex {}", g.positions.len())?;
    writeln!(out, "property float x\nproperty float y\nproperty float z")?;
    if g.normals.is_some() {
        writeln!(
            out,
            "property float nx\nproperty float ny\nproperty float nz"
        )?;
    }
    if g.colors.is_some() {
        writeln!(
            out,
            "property uchar red\nproperty uchar green\nproperty uchar blue"
        )?;
    }
    if !g.triangles.is_empty() {
        writeln!(
            out,
            "element face {}\nproperty list uchar uint vertex_indices",
            g.triangles.len()
        )?;
    }
    writeln!(out, "end_header")?;
    for (i, p) in g.positions.iter().enumerate() {
        for v in p {
            out.write_all(&v.to_le_bytes())?;
        }
        if let Some(n) = g.normals {
            for v in n.get(i).copied().unwrap_or([0.0; 3]) {
                out.write_all(&v.to_le_bytes())?;
            }
        }
        if let Some(c) = g.colors {
            out.write_all(&c.get(i).copied().unwrap_or([0; 3]))?;
        }
    }
    for t in g.triangles {
        out.write_all(&[3u8])?;
        for v in t {
            out.write_all(&v.to_le_bytes())?;
        }
    }
    out.flush()
}

/// Writes a self-contained glTF 2.0 binary: one mesh, triangles or points, positions in metres
/// (glTF's unit; our mm are scaled by 1e-3), normals and colours when present.
pub fn write_glb(path: &Path, g: &Geometry) -> io::Result<()> {
    let mut bin: Vec<u8> = Vec::new();
    let mut views = Vec::new();
    let mut accessors = Vec::new();
    let mut push_view = |bin: &mut Vec<u8>, bytes: &[u8], target: u32| -> usize {
        while !bin.len().is_multiple_of(4) {
            bin.push(0);
        }
        let offset = bin.len();
        bin.extend_from_slice(bytes);
        views.push(serde_json::json!({"buffer": 0, "byteOffset": offset, "byteLength": bytes.len(), "target": target}));
        views.len() - 1
    };
    const ARRAY_BUFFER: u32 = 34962;
    const ELEMENT_ARRAY_BUFFER: u32 = 34963;
    const FLOAT: u32 = 5126;
    const UNSIGNED_INT: u32 = 5125;

    let pos_m: Vec<[f32; 3]> = g.positions.iter().map(|p| p.map(|v| v * 1e-3)).collect();
    let (mut lo, mut hi) = ([f32::INFINITY; 3], [f32::NEG_INFINITY; 3]);
    for p in &pos_m {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    if pos_m.is_empty() {
        (lo, hi) = ([0.0; 3], [0.0; 3]);
    }
    let v = push_view(&mut bin, &f32_bytes(pos_m.iter().flatten()), ARRAY_BUFFER);
    accessors.push(serde_json::json!({"bufferView": v, "componentType": FLOAT, "count": pos_m.len(), "type": "VEC3", "min": lo, "max": hi}));
    let mut attributes = serde_json::json!({"POSITION": 0});
    if let Some(n) = g.normals {
        let v = push_view(&mut bin, &f32_bytes(n.iter().flatten()), ARRAY_BUFFER);
        accessors.push(serde_json::json!({"bufferView": v, "componentType": FLOAT, "count": n.len(), "type": "VEC3"}));
        attributes["NORMAL"] = (accessors.len() - 1).into();
    }
    if let Some(c) = g.colors {
        let lin: Vec<f32> = c.iter().flatten().map(|&v| srgb_to_linear(v)).collect();
        let v = push_view(&mut bin, &f32_bytes(lin.iter()), ARRAY_BUFFER);
        accessors.push(serde_json::json!({"bufferView": v, "componentType": FLOAT, "count": c.len(), "type": "VEC3"}));
        attributes["COLOR_0"] = (accessors.len() - 1).into();
    }
    let mut primitive = serde_json::json!({"attributes": attributes, "mode": if g.triangles.is_empty() { 0 } else { 4 }});
    if !g.triangles.is_empty() {
        let idx: Vec<u8> = g
            .triangles
            .iter()
            .flatten()
            .flat_map(|i| i.to_le_bytes())
            .collect();
        let v = push_view(&mut bin, &idx, ELEMENT_ARRAY_BUFFER);
        accessors.push(serde_json::json!({"bufferView": v, "componentType": UNSIGNED_INT, "count": g.triangles.len() * 3, "type": "SCALAR"}));
        primitive["indices"] = (accessors.len() - 1).into();
    }
    while !bin.len().is_multiple_of(4) {
        bin.push(0);
    }
    let doc = serde_json::json!({
        "asset": {"version": "2.0", "generator": "misslam"},
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [{"mesh": 0}],
        "meshes": [{"primitives": [primitive]}],
        "buffers": [{"byteLength": bin.len()}],
        "bufferViews": views,
        "accessors": accessors,
    });
    let mut json = serde_json::to_vec(&doc).map_err(io::Error::other)?;
    while !json.len().is_multiple_of(4) {
        json.push(b' ');
    }
    let total = 12 + 8 + json.len() + 8 + bin.len();
    let mut out = io::BufWriter::new(std::fs::File::create(path)?);
    out.write_all(b"glTF")?;
    out.write_all(&2u32.to_le_bytes())?;
    out.write_all(&(total as u32).to_le_bytes())?;
    out.write_all(&(json.len() as u32).to_le_bytes())?;
    out.write_all(b"JSON")?;
    out.write_all(&json)?;
    out.write_all(&(bin.len() as u32).to_le_bytes())?;
    out.write_all(b"BIN\0")?;
    out.write_all(&bin)?;
    out.flush()
}

fn f32_bytes<'a>(vals: impl Iterator<Item = &'a f32>) -> Vec<u8> {
    vals.flat_map(|v| v.to_le_bytes()).collect()
}

fn srgb_to_linear(v: u8) -> f32 {
    let c = v as f32 / 255.0;
    if c <= 0.04045 {
        c / 12.92
    } else {
        ((c + 0.055) / 1.055).powf(2.4)
    }
}
