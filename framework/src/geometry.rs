//! Small geometry shared by plugins: the rigid alignment of point sets (Kabsch / Horn), which
//! vertices of a mesh a camera sees on a depth map, surfaces seen from a camera, and the
//! conversions between payload points (`[f32; 3]`) and solver vectors (`Vector3<f64>`).

use crate::payload::{DepthMap, Mesh};
use nalgebra::{Isometry3, Matrix3, Point3, Rotation3, Translation3, UnitQuaternion, Vector3};

/// A payload point as a solver vector.
#[inline]
pub fn vec3(p: [f32; 3]) -> Vector3<f64> {
    Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64)
}

/// A solver vector as a payload point.
#[inline]
pub fn arr3(v: &Vector3<f64>) -> [f32; 3] {
    [v.x as f32, v.y as f32, v.z as f32]
}

/// Surface points and their normals (world frame) seen from the camera at `world_from_camera`,
/// as payload points: the points through its inverse, the normals through its inverse rotation
/// (in parallel on the calling pool).
pub fn in_camera_frame(
    world_from_camera: &Isometry3<f64>,
    points: &[Vector3<f64>],
    normals: &[Vector3<f64>],
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    use rayon::prelude::*;
    let cfw = world_from_camera.inverse();
    (
        points
            .par_iter()
            .map(|p| arr3(&(cfw * Point3::from(*p)).coords))
            .collect(),
        normals
            .par_iter()
            .map(|n| arr3(&(cfw.rotation * n)))
            .collect(),
    )
}

/// The rigid motion `m` minimising sum |m(src_i) - dst_i|^2 (Kabsch; reflection-safe).
pub fn align_rigid(src: &[Vector3<f64>], dst: &[Vector3<f64>]) -> Isometry3<f64> {
    let n = src.len().min(dst.len());
    if n == 0 {
        return Isometry3::identity();
    }
    let cs = src[..n].iter().sum::<Vector3<f64>>() / n as f64;
    let cd = dst[..n].iter().sum::<Vector3<f64>>() / n as f64;
    if n < 3 {
        return Isometry3::from_parts(Translation3::from(cd - cs), UnitQuaternion::identity());
    }
    let mut h = Matrix3::zeros();
    for (s, d) in src[..n].iter().zip(&dst[..n]) {
        h += (s - cs) * (d - cd).transpose();
    }
    let svd = h.svd(true, true);
    let (Some(u), Some(vt)) = (svd.u, svd.v_t) else {
        return Isometry3::from_parts(Translation3::from(cd - cs), UnitQuaternion::identity());
    };
    let mut d = Matrix3::identity();
    if (vt.transpose() * u.transpose()).determinant() < 0.0 {
        d[(2, 2)] = -1.0;
    }
    let r = Rotation3::from_matrix_unchecked(vt.transpose() * d * u.transpose());
    let t = cd - r * cs;
    Isometry3::from_parts(
        Translation3::from(t),
        UnitQuaternion::from_rotation_matrix(&r),
    )
}

/// Which vertices of `gt` (world frame) the camera at `world_from_camera` sees: in the image and
/// within `max_gap` mm of the true depth at their pixel (in front of the surface, not behind a
/// fold). A map whose values are not its width times its height is an error.
pub fn seen_vertices(
    gt: &Mesh,
    world_from_camera: &Isometry3<f64>,
    depth: &DepthMap,
    max_gap: f32,
) -> Result<Vec<bool>, String> {
    let (w, h) = (depth.map.width as usize, depth.map.height as usize);
    if depth.map.data.len() != w * h {
        return Err(format!(
            "the depth map has {} values for {w}x{h} pixels",
            depth.map.data.len()
        ));
    }
    let c = &depth.calib;
    let cfw = world_from_camera.inverse();
    Ok(gt
        .vertices
        .iter()
        .map(|v| {
            let p = cfw * Point3::new(v[0] as f64, v[1] as f64, v[2] as f64);
            if p.z <= 0.0 {
                return false;
            }
            let u = (c.fx * p.x / p.z + c.cx).round();
            let r = (c.fy * p.y / p.z + c.cy).round();
            if !(u >= 0.0 && r >= 0.0 && (u as usize) < w && (r as usize) < h) {
                return false;
            }
            let z = depth.map.data[r as usize * w + u as usize] as f64;
            (p.z - z).abs() <= max_gap as f64
        })
        .collect())
}
