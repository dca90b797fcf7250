//! The distance field function (DFF) of the template path (method.md 5.2): a voxel volume around a
//! depth scan whose voxels hold the signed distance to the observed surface (along the observed
//! normal of the nearest scan point, truncated). Model-to-scan distance is then a trilinear lookup
//! and its gradient the data term's Jacobian, with no per-iteration correspondence search.

use crate::knn::GridIndex;
use misslam_framework::nalgebra::Vector3;
use rayon::prelude::*;

/// A regular voxel volume of signed distances (mm), NaN where unknown (farther than the truncation
/// from every scan point).
#[derive(Clone, Debug)]
pub struct DistanceField {
    /// Centre of voxel (0, 0, 0), in the frame of the scan (the camera frame).
    pub origin: Vector3<f64>,
    /// Voxel side, mm.
    pub voxel: f64,
    /// Voxels along x, y, z.
    pub dims: [usize; 3],
    /// Values, x fastest.
    pub values: Vec<f32>,
    /// Truncation distance, mm.
    pub truncation: f64,
}

impl DistanceField {
    /// Builds the field of a scan given as points and unit normals (camera frame; non-finite
    /// entries are skipped): the box around the points padded by `truncation`, voxels of side
    /// `voxel`, each holding n . (x - q) for its nearest scan point q within `truncation`.
    pub fn from_scan(
        points: &[[f32; 3]],
        normals: &[[f32; 3]],
        voxel: f64,
        truncation: f64,
        max_voxels: usize,
    ) -> Result<Self, String> {
        if !(voxel > 0.0 && truncation > 0.0) {
            return Err(format!(
                "voxel ({voxel}) and truncation ({truncation}) must be positive"
            ));
        }
        let mut pts = Vec::new();
        let mut nrm = Vec::new();
        for (p, n) in points.iter().zip(normals) {
            if p.iter().chain(n.iter()).all(|c| c.is_finite()) {
                pts.push(Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64));
                nrm.push(Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64));
            }
        }
        if pts.is_empty() {
            return Err("the scan has no valid point with a normal".into());
        }
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for p in &pts {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        lo -= Vector3::repeat(truncation);
        hi += Vector3::repeat(truncation);
        let mut dims = [0usize; 3];
        for a in 0..3 {
            dims[a] = ((hi[a] - lo[a]) / voxel).ceil() as usize + 1;
        }
        let total = dims[0].saturating_mul(dims[1]).saturating_mul(dims[2]);
        if total > max_voxels {
            return Err(format!(
                "the distance field would need {}x{}x{} = {total} voxels (max_voxels {max_voxels}): raise voxel or max_voxels",
                dims[0], dims[1], dims[2]
            ));
        }
        let index = GridIndex::build(&pts, truncation.max(voxel));
        let mut values = vec![f32::NAN; total];
        values
            .par_chunks_mut(dims[0])
            .enumerate()
            .for_each(|(row, out)| {
                let (y, z) = (row % dims[1], row / dims[1]);
                for (x, v) in out.iter_mut().enumerate() {
                    let c = lo + Vector3::new(x as f64, y as f64, z as f64) * voxel;
                    if let Some((_, i)) = index.nearest_within(&pts, &c, truncation) {
                        let d = nrm[i as usize].dot(&(c - pts[i as usize]));
                        *v = d.clamp(-truncation, truncation) as f32;
                    }
                }
            });
        Ok(DistanceField {
            origin: lo,
            voxel,
            dims,
            values,
            truncation,
        })
    }

    /// Trilinear value and gradient at `p`, or `None` outside the volume or next to unknown voxels.
    pub fn sample(&self, p: &Vector3<f64>) -> Option<(f64, Vector3<f64>)> {
        let q = (p - self.origin) / self.voxel;
        let mut i = [0usize; 3];
        let mut f = [0f64; 3];
        for a in 0..3 {
            if q[a].is_nan() || q[a] < 0.0 || q[a] > (self.dims[a] - 1) as f64 {
                return None;
            }
            let fl = q[a].floor().min((self.dims[a].max(2) - 2) as f64);
            i[a] = fl as usize;
            f[a] = q[a] - fl;
        }
        if self.dims.iter().any(|&d| d < 2) {
            return None;
        }
        let at = |dx: usize, dy: usize, dz: usize| {
            self.values[((i[2] + dz) * self.dims[1] + i[1] + dy) * self.dims[0] + i[0] + dx] as f64
        };
        let mut c = [[[0.0; 2]; 2]; 2];
        for (dz, cz) in c.iter_mut().enumerate() {
            for (dy, cy) in cz.iter_mut().enumerate() {
                for (dx, v) in cy.iter_mut().enumerate() {
                    *v = at(dx, dy, dz);
                    if !v.is_finite() {
                        return None;
                    }
                }
            }
        }
        let lerp = |a: f64, b: f64, t: f64| a + (b - a) * t;
        let (fx, fy, fz) = (f[0], f[1], f[2]);
        let val = |c: &[[[f64; 2]; 2]; 2], fx: f64, fy: f64, fz: f64| {
            lerp(
                lerp(
                    lerp(c[0][0][0], c[0][0][1], fx),
                    lerp(c[0][1][0], c[0][1][1], fx),
                    fy,
                ),
                lerp(
                    lerp(c[1][0][0], c[1][0][1], fx),
                    lerp(c[1][1][0], c[1][1][1], fx),
                    fy,
                ),
                fz,
            )
        };
        let v = val(&c, fx, fy, fz);
        // Exact derivatives of the trilinear interpolant.
        let gx = lerp(
            lerp(c[0][0][1] - c[0][0][0], c[0][1][1] - c[0][1][0], fy),
            lerp(c[1][0][1] - c[1][0][0], c[1][1][1] - c[1][1][0], fy),
            fz,
        );
        let gy = lerp(
            lerp(c[0][1][0] - c[0][0][0], c[0][1][1] - c[0][0][1], fx),
            lerp(c[1][1][0] - c[1][0][0], c[1][1][1] - c[1][0][1], fx),
            fz,
        );
        let gz = lerp(
            lerp(c[1][0][0] - c[0][0][0], c[1][0][1] - c[0][0][1], fx),
            lerp(c[1][1][0] - c[0][1][0], c[1][1][1] - c[0][1][1], fx),
            fy,
        );
        Some((v, Vector3::new(gx, gy, gz) / self.voxel))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_plane_scan_gives_the_signed_distance_and_its_gradient() {
        // Scan: the plane z = 50 seen from the camera, normals towards the camera (-z).
        let mut pts = Vec::new();
        let mut nrm = Vec::new();
        for y in -20..=20 {
            for x in -20..=20 {
                pts.push([x as f32, y as f32, 50.0]);
                nrm.push([0.0, 0.0, -1.0]);
            }
        }
        let f = DistanceField::from_scan(&pts, &nrm, 0.5, 3.0, 10_000_000).unwrap();
        // Within the truncation minus the diagonal of a voxel every corner is known.
        for z in [47.6, 49.0, 50.0, 51.3, 52.4] {
            let (d, g) = f.sample(&Vector3::new(1.3, -2.7, z)).unwrap();
            assert!((d - (50.0 - z)).abs() < 1e-5, "z {z}: {d}");
            assert!((g - Vector3::new(0.0, 0.0, -1.0)).norm() < 1e-5, "{g:?}");
        }
        assert!(f.sample(&Vector3::new(0.0, 0.0, 60.0)).is_none());
        assert!(f.sample(&Vector3::new(0.0, 0.0, f64::NAN)).is_none());
        let err = DistanceField::from_scan(&pts, &nrm, 0.01, 3.0, 1000).unwrap_err();
        assert!(err.contains("max_voxels"), "{err}");
    }
}
