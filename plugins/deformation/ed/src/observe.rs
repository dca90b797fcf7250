//! Turning a depth map into the scan the data term reads (vertex and normal maps), and selecting
//! the visible model points V^n (method.md 5.1: they project inside the image onto valid depth
//! within epsilon_dv and with normals within epsilon_nv).

use crate::graph::{Binding, EdGraph};
use crate::problem::Intrinsics;
use misslam_framework::geometry::vec3;
use misslam_framework::nalgebra::{Isometry3, Point3, Vector3};
use misslam_framework::{Image, Mesh};
use rayon::prelude::*;

/// Lifts depth (mm, NaN invalid, row-major) to camera-frame vertices and normals. A normal is the
/// cross product of central differences, turned towards the camera; it is NaN when a neighbour is
/// invalid or a depth step to a neighbour exceeds `max_step_mm` (an occlusion edge).
pub fn scan_from_depth(
    depth: &[f32],
    k: &Intrinsics,
    max_step_mm: f32,
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let (mut vertices, mut normals) = (Vec::new(), Vec::new());
    scan_from_depth_into(depth, k, max_step_mm, &mut vertices, &mut normals);
    (vertices, normals)
}

/// [`scan_from_depth`] into reused buffers (a node calls it every frame); the maps are those of
/// `depth.postprocess` ([`misslam_depth_postprocess::maps::vertex_normal_maps_into`]).
pub fn scan_from_depth_into(
    depth: &[f32],
    k: &Intrinsics,
    max_step_mm: f32,
    vertices: &mut Vec<[f32; 3]>,
    normals: &mut Vec<[f32; 3]>,
) {
    let pinhole = misslam_depth_postprocess::Pinhole {
        width: k.width as usize,
        height: k.height as usize,
        fx: k.fx,
        fy: k.fy,
        cx: k.cx,
        cy: k.cy,
    };
    misslam_depth_postprocess::maps::vertex_normal_maps_into(
        depth,
        &pinhole,
        max_step_mm,
        vertices,
        normals,
    );
}

/// Area-weighted unit vertex normals of a triangle mesh, following the winding (NaN for a vertex
/// without a triangle of non-zero area).
pub fn mesh_normals(v: &[Vector3<f64>], triangles: &[[u32; 3]]) -> Vec<Vector3<f64>> {
    let mut n = vec![Vector3::zeros(); v.len()];
    for tri in triangles {
        let (a, b, c) = (v[tri[0] as usize], v[tri[1] as usize], v[tri[2] as usize]);
        let f = (b - a).cross(&(c - a));
        for &i in tri {
            n[i as usize] += f;
        }
    }
    n.iter()
        .map(|x| x.try_normalize(1e-12).unwrap_or(Vector3::repeat(f64::NAN)))
        .collect()
}

/// Solver vectors.
pub type Points = Vec<Vector3<f64>>;

/// A template mesh's vertices and unit normals as solver vectors, checked: every triangle indexes
/// an existing vertex, every vertex is finite; normals come from the mesh when it has one per
/// vertex, else from its faces.
pub fn template_points(mesh: &Mesh) -> Result<(Points, Points), String> {
    let nv = mesh.vertices.len();
    if nv == 0 {
        return Err("the template has no vertices".into());
    }
    if let Some(t) = mesh
        .triangles
        .iter()
        .find(|t| t.iter().any(|&i| i as usize >= nv))
    {
        return Err(format!(
            "template triangle {t:?} indexes past its {nv} vertices"
        ));
    }
    if let Some(i) = mesh
        .vertices
        .iter()
        .position(|p| !p.iter().all(|c| c.is_finite()))
    {
        return Err(format!("template vertex {i} is not finite"));
    }
    let points: Vec<Vector3<f64>> = mesh.vertices.iter().map(|p| vec3(*p)).collect();
    let normals = match &mesh.normals {
        Some(n) if n.len() == nv => n.iter().map(|q| vec3(*q)).collect(),
        _ if !mesh.triangles.is_empty() => mesh_normals(&points, &mesh.triangles),
        _ => {
            return Err(
                "the template has neither normals nor triangles to compute them from".into(),
            )
        }
    };
    Ok((points, normals))
}

/// Indices of the model points visible in the scan: the warped point projects inside the image
/// onto a valid vertex within `max_distance_mm` of it, and the warped normal is within
/// `max_angle_deg` of the scan's normal (and faces the camera).
#[allow(clippy::too_many_arguments)]
pub fn visible_points(
    graph: &EdGraph,
    points: &[Vector3<f64>],
    normals: &[Vector3<f64>],
    bindings: &[Binding],
    world_from_camera: &Isometry3<f64>,
    k: &Intrinsics,
    vertices: &[[f32; 3]],
    scan_normals: &[[f32; 3]],
    max_distance_mm: f64,
    max_angle_deg: f64,
) -> Vec<u32> {
    let cam = graph.framed(&world_from_camera.inverse());
    let cos_max = max_angle_deg.to_radians().cos();
    // Runs of GROUP points: warped and projected, then the scan read at every pixel hit (the
    // independent loads let their cache misses overlap), then tested in order.
    const GROUP: usize = 32;
    points
        .par_chunks(1024)
        .enumerate()
        .flat_map_iter(|(ci, chunk)| {
            let mut keep = Vec::new();
            let mut at = [(Point3::origin(), None, [0f32; 3], [0f32; 3]); GROUP];
            for (gi, group) in chunk.chunks(GROUP).enumerate() {
                let i0 = ci * 1024 + gi * GROUP;
                for (j, v) in group.iter().enumerate() {
                    let p = Point3::from(cam.point(v, &bindings[i0 + j]));
                    at[j] = (p, k.pixel(&p.coords), [0.0; 3], [0.0; 3]);
                }
                for a in at[..group.len()].iter_mut() {
                    if let Some(idx) = a.1 {
                        (a.2, a.3) = (vertices[idx], scan_normals[idx]);
                    }
                }
                for (j, &(p, idx, q, n)) in at[..group.len()].iter().enumerate() {
                    let i = i0 + j;
                    if idx.is_none() || !q.iter().chain(&n).all(|c| c.is_finite()) {
                        continue;
                    }
                    let q = Vector3::new(q[0] as f64, q[1] as f64, q[2] as f64);
                    if (p.coords - q).norm() > max_distance_mm {
                        continue;
                    }
                    let nc = cam.normal(&normals[i], &bindings[i]);
                    if nc.dot(&Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64)) >= cos_max {
                        keep.push(i as u32);
                    }
                }
            }
            keep
        })
        .collect()
}

/// The colour of pixel `i` of the left image (grey replicated; a tissue-like default without an
/// image).
pub fn color_at(img: Option<&Image>, i: usize) -> [u8; 3] {
    match img {
        Some(im) if im.channels == 3 && (i + 1) * 3 <= im.data.len() => {
            [im.data[3 * i], im.data[3 * i + 1], im.data[3 * i + 2]]
        }
        Some(im) if im.channels == 1 && i < im.data.len() => [im.data[i]; 3],
        _ => [200, 120, 110],
    }
}

/// How much an observation's colour is trusted: the surface faces the scope (cosine of the view
/// angle, the normal being in the camera frame) and the colour is saturated. Specular
/// highlights, which a scope-mounted light puts exactly on the frontal views, are pale and lose
/// to a vivid observation from another angle. Both fusion variants keep, per point, the colour of
/// the best observation so far ("vivid texture").
pub fn color_quality(normal_cam: [f32; 3], c: [u8; 3]) -> f32 {
    let hi = c.iter().copied().max().unwrap_or(0) as f32;
    let lo = c.iter().copied().min().unwrap_or(0) as f32;
    let saturation = if hi > 0.0 { (hi - lo) / hi } else { 0.0 };
    (-normal_cam[2]).max(0.0) * saturation
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_vivid_oblique_colour_beats_a_frontal_highlight() {
        let frontal = [0.0, 0.0, -1.0];
        let oblique = [0.0, 0.5, -0.866];
        let highlight = [250, 235, 230];
        let tissue = [180, 70, 60];
        assert!(color_quality(oblique, tissue) > color_quality(frontal, highlight));
        // Facing away: no trust at all.
        assert_eq!(color_quality([0.0, 0.0, 1.0], tissue), 0.0);
        // Among equally vivid colours, the frontal one wins.
        assert!(color_quality(frontal, tissue) > color_quality(oblique, tissue));
    }

    #[test]
    fn a_tilted_plane_gives_its_points_and_normal_and_edges_are_invalid() {
        let k = Intrinsics {
            fx: 100.0,
            fy: 100.0,
            cx: 10.0,
            cy: 8.0,
            width: 21,
            height: 17,
        };
        // Plane z = 50 + 0.5 x: depth at pixel u solves z = 50 + 0.5 (u - cx) z / fx.
        let mut depth = vec![0f32; 21 * 17];
        for (i, d) in depth.iter_mut().enumerate() {
            let u = (i % 21) as f64;
            *d = (50.0 / (1.0 - 0.5 * (u - 10.0) / 100.0)) as f32;
        }
        depth[5 * 21 + 5] = f32::NAN;
        let (v, n) = scan_from_depth(&depth, &k, 5.0);
        let expect = Vector3::new(0.5, 0.0, -1.0).normalize();
        let i = 8 * 21 + 12;
        let got = Vector3::new(n[i][0] as f64, n[i][1] as f64, n[i][2] as f64);
        assert!((got - expect).norm() < 1e-4, "{got:?}");
        assert!((v[i][2] as f64 - 50.0 - 0.5 * v[i][0] as f64).abs() < 1e-3);
        // Borders, the invalid pixel and its four neighbours have no normal.
        for j in [0, 20, 5 * 21 + 5, 5 * 21 + 4, 4 * 21 + 5] {
            assert!(n[j][0].is_nan(), "pixel {j}");
        }
        assert!(v[5 * 21 + 4][0].is_finite());
    }
}
