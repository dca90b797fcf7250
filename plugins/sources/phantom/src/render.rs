//! A z-buffer rasteriser for one pinhole view, with perspective-correct barycentrics, so GT
//! depth is exact for the planar triangles of the mesh and every pixel knows which triangle and
//! which point of it it sees. Pixel centres are at integer coordinates (OpenCV).

use misslam_framework::nalgebra::{Isometry3, Point3};

/// A pinhole camera.
#[derive(Clone, Copy, Debug)]
pub struct View {
    /// Focal length x, px.
    pub fx: f32,
    /// Focal length y, px.
    pub fy: f32,
    /// Principal point x, px.
    pub cx: f32,
    /// Principal point y, px.
    pub cy: f32,
    /// Width, px.
    pub width: u32,
    /// Height, px.
    pub height: u32,
    /// World to this camera.
    pub camera_from_world: Isometry3<f32>,
}

/// What each pixel sees.
#[derive(Clone, Debug, Default)]
pub struct Raster {
    /// Camera-frame depth, NaN where nothing is seen.
    pub depth: Vec<f32>,
    /// Triangle index (u32::MAX where nothing).
    pub triangle: Vec<u32>,
    /// Perspective-correct barycentric weights of the triangle's vertices.
    pub bary: Vec<[f32; 3]>,
}

/// Nearest depth accepted (mm): geometry closer than this is not drawn.
pub const NEAR_MM: f32 = 1.0;

/// Rasterises `triangles` of `vertices` (world frame) into `out` (resized as needed).
pub fn rasterize(
    view: &View,
    vertices: &[[f32; 3]],
    triangles: &[[u32; 3]],
    cam: &mut Vec<[f32; 3]>,
    out: &mut Raster,
) {
    let (w, h) = (view.width as usize, view.height as usize);
    out.depth.clear();
    out.depth.resize(w * h, f32::INFINITY);
    out.triangle.clear();
    out.triangle.resize(w * h, u32::MAX);
    out.bary.clear();
    out.bary.resize(w * h, [0.0; 3]);
    cam.clear();
    cam.extend(vertices.iter().map(|v| {
        let p = view.camera_from_world * Point3::new(v[0], v[1], v[2]);
        [p.x, p.y, p.z]
    }));
    for (ti, tri) in triangles.iter().enumerate() {
        let p = [
            cam[tri[0] as usize],
            cam[tri[1] as usize],
            cam[tri[2] as usize],
        ];
        if p.iter().any(|q| q[2] < NEAR_MM) {
            continue;
        }
        let s: [[f32; 2]; 3] = p.map(|q| {
            [
                view.fx * q[0] / q[2] + view.cx,
                view.fy * q[1] / q[2] + view.cy,
            ]
        });
        let area =
            (s[1][0] - s[0][0]) * (s[2][1] - s[0][1]) - (s[2][0] - s[0][0]) * (s[1][1] - s[0][1]);
        if area.abs() < 1e-12 {
            continue;
        }
        let min_x = s
            .iter()
            .map(|q| q[0])
            .fold(f32::INFINITY, f32::min)
            .ceil()
            .max(0.0);
        let max_x = s
            .iter()
            .map(|q| q[0])
            .fold(f32::NEG_INFINITY, f32::max)
            .floor()
            .min(w as f32 - 1.0);
        let min_y = s
            .iter()
            .map(|q| q[1])
            .fold(f32::INFINITY, f32::min)
            .ceil()
            .max(0.0);
        let max_y = s
            .iter()
            .map(|q| q[1])
            .fold(f32::NEG_INFINITY, f32::max)
            .floor()
            .min(h as f32 - 1.0);
        if min_x > max_x || min_y > max_y {
            continue;
        }
        let inv_z = p.map(|q| 1.0 / q[2]);
        for py in min_y as usize..=max_y as usize {
            for px in min_x as usize..=max_x as usize {
                let (x, y) = (px as f32, py as f32);
                let e = |a: [f32; 2], b: [f32; 2]| {
                    (b[0] - a[0]) * (y - a[1]) - (x - a[0]) * (b[1] - a[1])
                };
                let l0 = e(s[1], s[2]) / area;
                let l1 = e(s[2], s[0]) / area;
                let l2 = e(s[0], s[1]) / area;
                if l0 < 0.0 || l1 < 0.0 || l2 < 0.0 {
                    continue;
                }
                let iz = l0 * inv_z[0] + l1 * inv_z[1] + l2 * inv_z[2];
                let z = 1.0 / iz;
                let i = py * w + px;
                if z < out.depth[i] {
                    out.depth[i] = z;
                    out.triangle[i] = ti as u32;
                    out.bary[i] = [l0 * inv_z[0] / iz, l1 * inv_z[1] / iz, l2 * inv_z[2] / iz];
                }
            }
        }
    }
    for d in &mut out.depth {
        if !d.is_finite() {
            *d = f32::NAN;
        }
    }
}

/// Interpolates a per-vertex attribute at pixel `i` of a raster.
#[inline]
pub fn interpolate(
    r: &Raster,
    triangles: &[[u32; 3]],
    attr: &[[f32; 3]],
    i: usize,
) -> Option<[f32; 3]> {
    let t = *triangles.get(r.triangle[i] as usize)?;
    let b = r.bary[i];
    let (a0, a1, a2) = (
        attr[t[0] as usize],
        attr[t[1] as usize],
        attr[t[2] as usize],
    );
    Some([
        b[0] * a0[0] + b[1] * a1[0] + b[2] * a2[0],
        b[0] * a0[1] + b[1] * a1[1] + b[2] * a2[1],
        b[0] * a0[2] + b[1] * a1[2] + b[2] * a2[2],
    ])
}

/// A scan of a raster: per pixel the camera-frame point (from the exact depth) and the unit face
/// normal of the triangle seen there, turned towards the camera; NaN where nothing is seen.
/// `cam` are the vertices in the camera frame, as [`rasterize`] leaves them.
pub fn scan_maps(
    view: &View,
    r: &Raster,
    cam: &[[f32; 3]],
    triangles: &[[u32; 3]],
) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
    let n = r.depth.len();
    let mut points = vec![[f32::NAN; 3]; n];
    let mut normals = vec![[f32::NAN; 3]; n];
    for i in 0..n {
        let z = r.depth[i];
        let Some(t) = triangles.get(r.triangle[i] as usize) else {
            continue;
        };
        if !z.is_finite() {
            continue;
        }
        let (u, v) = (
            (i % view.width as usize) as f32,
            (i / view.width as usize) as f32,
        );
        let p = [(u - view.cx) / view.fx * z, (v - view.cy) / view.fy * z, z];
        let (a, b, c) = (cam[t[0] as usize], cam[t[1] as usize], cam[t[2] as usize]);
        let e1 = [b[0] - a[0], b[1] - a[1], b[2] - a[2]];
        let e2 = [c[0] - a[0], c[1] - a[1], c[2] - a[2]];
        let mut nn = [
            e1[1] * e2[2] - e1[2] * e2[1],
            e1[2] * e2[0] - e1[0] * e2[2],
            e1[0] * e2[1] - e1[1] * e2[0],
        ];
        let len = (nn[0] * nn[0] + nn[1] * nn[1] + nn[2] * nn[2]).sqrt();
        if len.is_nan() || len <= 0.0 {
            continue;
        }
        let facing = nn[0] * p[0] + nn[1] * p[1] + nn[2] * p[2];
        let s = if facing > 0.0 { -1.0 / len } else { 1.0 / len };
        nn = nn.map(|x| x * s);
        points[i] = p;
        normals[i] = nn;
    }
    (points, normals)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_fronto_parallel_quad_has_exact_depth_and_coverage() {
        let view = View {
            fx: 100.0,
            fy: 100.0,
            cx: 10.0,
            cy: 10.0,
            width: 21,
            height: 21,
            camera_from_world: Isometry3::identity(),
        };
        // A 20 x 20 mm square at z = 100 covers pixels 0..=20 (x = +-10 mm -> +-10 px).
        let v = [
            [-10.0, -10.0, 100.0],
            [10.0, -10.0, 100.0],
            [10.0, 10.0, 100.0],
            [-10.0, 10.0, 100.0],
        ];
        let t = [[0, 1, 2], [0, 2, 3]];
        let mut r = Raster::default();
        rasterize(&view, &v, &t, &mut Vec::new(), &mut r);
        assert!(
            r.depth.iter().all(|&d| (d - 100.0).abs() < 1e-4),
            "every pixel covered at z = 100"
        );
        // A tilted plane: z = 100 + x; depth at pixel column px is exact (perspective-correct).
        let v = [
            [-10.0, -10.0, 90.0],
            [10.0, -10.0, 110.0],
            [10.0, 10.0, 110.0],
            [-10.0, 10.0, 90.0],
        ];
        rasterize(&view, &v, &t, &mut Vec::new(), &mut r);
        // The ray through pixel u meets z = 100 + x with x = (u - cx) z / fx: z = 100 / (1 - (u - cx)/fx).
        for px in 3..18 {
            let z = 100.0 / (1.0 - (px as f32 - 10.0) / 100.0);
            let got = r.depth[10 * 21 + px];
            assert!((got - z).abs() < 1e-3, "column {px}: {got} vs {z}");
        }
    }
}
