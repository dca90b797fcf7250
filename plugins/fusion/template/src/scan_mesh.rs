//! A template from the first scan: the depth's vertex map triangulated on a pixel grid, for data
//! that come without a pre-operative model (the in-vivo Hamlyn frames). The surface the scope saw
//! on the first frame then plays the CT model's part: the later frames deform it.

use misslam_framework::nalgebra::{Isometry3, Point3};
use misslam_framework::{Image, Mesh};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// How the first scan becomes a template.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct ScanTemplateParams {
    /// Grid step in pixels: one vertex every `stride_px` pixels along both axes.
    pub stride_px: u32,
    /// A triangle is kept only when each of its edges is at most this long, mm: it drops the
    /// triangles that would bridge an occlusion edge between two surfaces.
    pub max_edge_mm: f64,
}

impl Default for ScanTemplateParams {
    fn default() -> Self {
        ScanTemplateParams {
            stride_px: 4,
            max_edge_mm: 3.0,
        }
    }
}

impl ScanTemplateParams {
    /// Checks ranges, naming the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.stride_px == 0 {
            return Err("template_from_scan.stride_px must be at least 1".into());
        }
        if !(self.max_edge_mm.is_finite() && self.max_edge_mm > 0.0) {
            return Err(format!(
                "template_from_scan.max_edge_mm must be positive, got {}",
                self.max_edge_mm
            ));
        }
        Ok(())
    }
}

/// Triangulates a vertex map (camera frame, row-major `width` x `height`, non-finite invalid) on
/// the grid of every `stride_px`-th pixel into a mesh in the world frame (`world_from_camera`),
/// wound to face the camera, coloured from `left` where given (same size as the map). Each grid
/// cell gives up to two triangles, each kept when its three corners are valid and its edges at
/// most `max_edge_mm`; only vertices some triangle uses are kept. Fails when no triangle is left.
pub fn scan_mesh(
    vertices: &[[f32; 3]],
    width: usize,
    height: usize,
    left: Option<&Image>,
    world_from_camera: &Isometry3<f64>,
    p: &ScanTemplateParams,
) -> Result<Mesh, String> {
    p.validate()?;
    if vertices.len() != width * height {
        return Err(format!(
            "the vertex map has {} entries for {width}x{height} pixels",
            vertices.len()
        ));
    }
    let s = p.stride_px as usize;
    let (gw, gh) = ((width - 1) / s + 1, (height - 1) / s + 1);
    let at = |gx: usize, gy: usize| gy * s * width + gx * s;
    let valid = |i: usize| vertices[i].iter().all(|c| c.is_finite());
    let max2 = (p.max_edge_mm * p.max_edge_mm) as f32;
    let close = |a: usize, b: usize| {
        let (u, v) = (vertices[a], vertices[b]);
        (0..3).map(|k| (u[k] - v[k]) * (u[k] - v[k])).sum::<f32>() <= max2
    };
    let keep = |t: [usize; 3]| {
        t.iter().all(|&i| valid(i)) && close(t[0], t[1]) && close(t[1], t[2]) && close(t[2], t[0])
    };
    // Pixel-index triangles. In the camera frame (x right, y down, z ahead) the order a, c, b of
    // a cell's corners a = (x, y), b = (x + 1, y), c = (x, y + 1) is counter-clockwise seen from
    // the camera.
    let mut tris = Vec::new();
    for gy in 0..gh.saturating_sub(1) {
        for gx in 0..gw.saturating_sub(1) {
            let (a, b) = (at(gx, gy), at(gx + 1, gy));
            let (c, d) = (at(gx, gy + 1), at(gx + 1, gy + 1));
            for t in [[a, c, b], [b, c, d]] {
                if keep(t) {
                    tris.push(t);
                }
            }
        }
    }
    if tris.is_empty() {
        return Err(format!(
            "the first scan gives no triangle (stride_px {}, max_edge_mm {}): is its depth valid?",
            p.stride_px, p.max_edge_mm
        ));
    }
    let mut index = vec![u32::MAX; vertices.len()];
    let mut mesh = Mesh::default();
    let mut colors = Vec::new();
    for t in &mut tris {
        for i in t.iter_mut() {
            if index[*i] == u32::MAX {
                index[*i] = mesh.vertices.len() as u32;
                let v = vertices[*i];
                let w = world_from_camera
                    * Point3::new(f64::from(v[0]), f64::from(v[1]), f64::from(v[2]));
                mesh.vertices.push([w.x as f32, w.y as f32, w.z as f32]);
                if let Some(img) = left {
                    colors.push(misslam_deformation_ed::observe::color_at(Some(img), *i));
                }
            }
            *i = index[*i] as usize;
        }
        mesh.triangles.push(t.map(|i| i as u32));
    }
    if left.is_some() {
        mesh.colors = Some(colors);
    }
    Ok(mesh)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A plane at z = 100 mm seen by a 400 px camera, `w` x `h` pixels.
    fn plane(w: usize, h: usize) -> Vec<[f32; 3]> {
        let mut v = Vec::new();
        for y in 0..h {
            for x in 0..w {
                let z = 100.0f32;
                v.push([
                    (x as f32 - 4.5) * z / 400.0,
                    (y as f32 - 3.5) * z / 400.0,
                    z,
                ]);
            }
        }
        v
    }

    #[test]
    fn a_plane_becomes_a_grid_of_triangles_facing_the_camera() {
        let v = plane(10, 8);
        let p = ScanTemplateParams {
            stride_px: 3,
            max_edge_mm: 3.0,
        };
        let m = scan_mesh(&v, 10, 8, None, &Isometry3::identity(), &p).unwrap();
        // Grid columns 0, 3, 6, 9 and rows 0, 3, 6: 4 x 3 vertices, 3 x 2 cells, 12 triangles.
        assert_eq!(m.vertices.len(), 12);
        assert_eq!(m.triangles.len(), 12);
        for t in &m.triangles {
            let [a, b, c] = t.map(|i| {
                let q = m.vertices[i as usize];
                misslam_framework::nalgebra::Vector3::new(q[0], q[1], q[2])
            });
            let n = (b - a).cross(&(c - a));
            // Counter-clockwise seen from the camera: the normal points back at it (-z).
            assert!(n.z < 0.0, "{n:?}");
        }
        assert!(m.colors.is_none());
    }

    #[test]
    fn occlusion_edges_and_invalid_pixels_are_not_bridged() {
        let mut v = plane(10, 8);
        // The right half 20 mm farther: no triangle may join the two.
        for y in 0..8 {
            for x in 5..10 {
                v[y * 10 + x][2] += 20.0;
            }
        }
        v[0] = [f32::NAN; 3];
        let p = ScanTemplateParams {
            stride_px: 1,
            max_edge_mm: 3.0,
        };
        let pose = Isometry3::translation(1.0, 2.0, 3.0);
        let m = scan_mesh(&v, 10, 8, None, &pose, &p).unwrap();
        // Left block 5 x 8 pixels: 4 x 7 cells, less the one triangle that uses the NaN corner;
        // right block the same 4 x 7 cells; none across.
        assert_eq!(m.triangles.len(), 2 * 28 - 1 + 2 * 28);
        for t in &m.triangles {
            let z: Vec<f32> = t.iter().map(|&i| m.vertices[i as usize][2] - 3.0).collect();
            let near = z.iter().all(|&z| (z - 100.0).abs() < 1e-4);
            let far = z.iter().all(|&z| (z - 120.0).abs() < 1e-4);
            assert!(near || far, "a triangle across the edge: {z:?}");
        }
        assert_eq!(m.vertices.len(), 10 * 8 - 1);
    }

    #[test]
    fn bad_settings_and_empty_scans_are_refused_by_name() {
        let v = plane(4, 4);
        let id = Isometry3::identity();
        let zero = ScanTemplateParams {
            stride_px: 0,
            ..Default::default()
        };
        let e = scan_mesh(&v, 4, 4, None, &id, &zero).unwrap_err();
        assert!(e.contains("stride_px"), "{e}");
        let e = scan_mesh(&v, 5, 4, None, &id, &Default::default()).unwrap_err();
        assert!(e.contains("5x4"), "{e}");
        let empty = vec![[f32::NAN; 3]; 16];
        let e = scan_mesh(&empty, 4, 4, None, &id, &Default::default()).unwrap_err();
        assert!(e.contains("no triangle"), "{e}");
    }
}
