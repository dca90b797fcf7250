//! Surface helpers: the albedo (baked atlases over the parameter plane, or triplanar on a
//! template mesh), vertex normals of grid and triangle meshes, bounds.

use misslam_framework::nalgebra::Vector3;
use rayon::prelude::*;

use crate::texture::GradientCache;

/// How albedo is looked up: on the procedural organ's parameter plane, or triplanar on a
/// template mesh (three planar atlases blended by the rest normal).
pub(crate) enum Albedo {
    Planar(Atlas),
    Triplanar { yz: Atlas, xz: Atlas, xy: Atlas },
}

impl Albedo {
    pub(crate) fn sample(&self, p: [f32; 3], n: [f32; 3]) -> [f32; 3] {
        match self {
            Albedo::Planar(a) => a.sample(p[0], p[1]),
            Albedo::Triplanar { yz, xz, xy } => {
                let w = n.map(|c| c.abs().powi(4));
                let sum = (w[0] + w[1] + w[2]).max(1e-12);
                let (a, b, c) = (
                    yz.sample(p[1], p[2]),
                    xz.sample(p[0], p[2]),
                    xy.sample(p[0], p[1]),
                );
                [0, 1, 2].map(|k| (w[0] * a[k] + w[1] * b[k] + w[2] * c[k]) / sum)
            }
        }
    }
}

pub(crate) fn bounds(v: &[[f32; 3]]) -> ([f32; 3], [f32; 3]) {
    let mut lo = [f32::INFINITY; 3];
    let mut hi = [f32::NEG_INFINITY; 3];
    for p in v {
        for k in 0..3 {
            lo[k] = lo[k].min(p[k]);
            hi[k] = hi[k].max(p[k]);
        }
    }
    (lo, hi)
}

/// Area-weighted vertex normals of a triangle mesh, oriented toward the scope (-z) on average.
pub(crate) fn mesh_normals(v: &[[f32; 3]], triangles: &[[u32; 3]]) -> Vec<[f32; 3]> {
    let mut acc = vec![Vector3::<f32>::zeros(); v.len()];
    for t in triangles {
        let [a, b, c] = t.map(|i| Vector3::from(v[i as usize]));
        let n = (b - a).cross(&(c - a));
        for &i in t {
            acc[i as usize] += n;
        }
    }
    // One orientation for the whole surface: the one facing the scope for most of it.
    let facing: f32 = acc.iter().map(|n| -n.z).sum();
    let sign = if facing < 0.0 { -1.0 } else { 1.0 };
    acc.into_iter()
        .map(|n| {
            let n = (sign * n)
                .try_normalize(1e-12)
                .unwrap_or(Vector3::new(0.0, 0.0, -1.0));
            [n.x, n.y, n.z]
        })
        .collect()
}

/// Texel size of the baked albedo, mm (about 1 px at the nearest tissue).
pub(crate) const ATLAS_MM: f32 = 0.1;

/// The albedo baked over the tissue patch's parameter plane, sampled bilinearly.
pub(crate) struct Atlas {
    origin: [f32; 2],
    step: f32,
    nx: usize,
    ny: usize,
    texels: Vec<[f32; 3]>,
}

impl Atlas {
    pub(crate) fn bake(
        lo: [f32; 2],
        hi: [f32; 2],
        step: f32,
        f: impl Fn(f32, f32, &mut GradientCache) -> [f32; 3] + Sync,
    ) -> Self {
        let nx = ((hi[0] - lo[0]) / step).ceil() as usize + 3;
        let ny = ((hi[1] - lo[1]) / step).ceil() as usize + 3;
        let origin = [lo[0] - step, lo[1] - step];
        let mut texels = vec![[0.0; 3]; nx * ny];
        texels.par_chunks_mut(nx).enumerate().for_each(|(j, row)| {
            // A row's texels share their noise's lattice cells.
            let mut cache = GradientCache::new();
            for (i, t) in row.iter_mut().enumerate() {
                *t = f(
                    origin[0] + i as f32 * step,
                    origin[1] + j as f32 * step,
                    &mut cache,
                );
            }
        });
        Atlas {
            origin,
            step,
            nx,
            ny,
            texels,
        }
    }

    pub(crate) fn sample(&self, x: f32, y: f32) -> [f32; 3] {
        let fx = ((x - self.origin[0]) / self.step).clamp(0.0, (self.nx - 2) as f32);
        let fy = ((y - self.origin[1]) / self.step).clamp(0.0, (self.ny - 2) as f32);
        let (i, j) = (fx as usize, fy as usize);
        let (tx, ty) = (fx - i as f32, fy - j as f32);
        let t = |i: usize, j: usize| self.texels[j * self.nx + i];
        let (a, b, c, d) = (t(i, j), t(i + 1, j), t(i, j + 1), t(i + 1, j + 1));
        let mut out = [0.0; 3];
        for k in 0..3 {
            let top = a[k] + (b[k] - a[k]) * tx;
            let bottom = c[k] + (d[k] - c[k]) * tx;
            out[k] = top + (bottom - top) * ty;
        }
        out
    }
}

/// Per-vertex normals of a grid mesh from central differences (pointing toward the scope).
pub(crate) fn grid_normals(v: &[[f32; 3]], (nx, ny): (usize, usize)) -> Vec<[f32; 3]> {
    let at = |i: usize, j: usize| Vector3::from(v[j * nx + i]);
    let mut out = Vec::with_capacity(v.len());
    for j in 0..ny {
        for i in 0..nx {
            let du = at((i + 1).min(nx - 1), j) - at(i.saturating_sub(1), j);
            let dv = at(i, (j + 1).min(ny - 1)) - at(i, j.saturating_sub(1));
            // x right, y down: du x dv points away from the scope (+z); flip it.
            let n = -du.cross(&dv);
            let n = n
                .try_normalize(1e-12)
                .unwrap_or(Vector3::new(0.0, 0.0, -1.0));
            out.push([n.x, n.y, n.z]);
        }
    }
    out
}
