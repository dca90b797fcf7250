//! Exact distances from points to a triangle mesh: the point-to-triangle distance, and a uniform
//! grid over the triangles ([`SurfaceIndex`]) that finds the nearest one.

use crate::{dot, sub, V3};
use misslam_framework::Mesh;
use rayon::prelude::*;

/// Squared distance from `p` to triangle `abc` (Ericson, Real-Time Collision Detection 5.1.5).
pub fn point_triangle_dist2(p: V3, a: V3, b: V3, c: V3) -> f32 {
    let (ab, ac, ap) = (sub(b, a), sub(c, a), sub(p, a));
    let (d1, d2) = (dot(ab, ap), dot(ac, ap));
    let closest = if d1 <= 0.0 && d2 <= 0.0 {
        a
    } else {
        let bp = sub(p, b);
        let (d3, d4) = (dot(ab, bp), dot(ac, bp));
        if d3 >= 0.0 && d4 <= d3 {
            b
        } else {
            let vc = d1 * d4 - d3 * d2;
            if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
                let v = d1 / (d1 - d3);
                [a[0] + v * ab[0], a[1] + v * ab[1], a[2] + v * ab[2]]
            } else {
                let cp = sub(p, c);
                let (d5, d6) = (dot(ab, cp), dot(ac, cp));
                if d6 >= 0.0 && d5 <= d6 {
                    c
                } else {
                    let vb = d5 * d2 - d1 * d6;
                    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
                        let w = d2 / (d2 - d6);
                        [a[0] + w * ac[0], a[1] + w * ac[1], a[2] + w * ac[2]]
                    } else {
                        let va = d3 * d6 - d5 * d4;
                        if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
                            let w = (d4 - d3) / ((d4 - d3) + (d5 - d6));
                            let bc = sub(c, b);
                            [b[0] + w * bc[0], b[1] + w * bc[1], b[2] + w * bc[2]]
                        } else {
                            let denom = 1.0 / (va + vb + vc);
                            let (v, w) = (vb * denom, vc * denom);
                            [
                                a[0] + ab[0] * v + ac[0] * w,
                                a[1] + ab[1] * v + ac[1] * w,
                                a[2] + ab[2] * v + ac[2] * w,
                            ]
                        }
                    }
                }
            }
        }
    };
    let d = sub(p, closest);
    dot(d, d)
}

/// Triangles bucketed in a uniform grid for nearest-triangle queries: per cell a range of
/// `items` (compressed rows), and the triangles' corners stored with them.
pub struct SurfaceIndex {
    origin: V3,
    cell: f32,
    dims: [usize; 3],
    /// Cell c's triangles are `items[start[c]..start[c + 1]]`.
    start: Vec<u32>,
    items: Vec<u32>,
    /// Each triangle's corners.
    corners: Vec<[V3; 3]>,
}

impl SurfaceIndex {
    /// Indexes `mesh` (cell size: twice the mean edge length).
    pub fn new(mesh: &Mesh) -> Result<Self, String> {
        if mesh.triangles.is_empty() {
            return Err("the ground-truth mesh has no triangles".into());
        }
        let mut lo = [f32::INFINITY; 3];
        let mut hi = [f32::NEG_INFINITY; 3];
        let mut edge_sum = 0.0;
        for t in &mesh.triangles {
            if t.iter().any(|&i| i as usize >= mesh.vertices.len()) {
                return Err("a ground-truth triangle indexes past the vertices".into());
            }
            let v = t.map(|i| mesh.vertices[i as usize]);
            for p in v {
                for k in 0..3 {
                    lo[k] = lo[k].min(p[k]);
                    hi[k] = hi[k].max(p[k]);
                }
            }
            edge_sum += dot(sub(v[1], v[0]), sub(v[1], v[0])).sqrt();
        }
        if lo.iter().chain(&hi).any(|v| !v.is_finite()) {
            return Err("the ground-truth mesh has non-finite vertices".into());
        }
        let cell = (2.0 * edge_sum / mesh.triangles.len() as f32).max(1e-3);
        let dims = [0, 1, 2].map(|k| (((hi[k] - lo[k]) / cell) as usize + 1).min(512));
        let cell = (0..3)
            .map(|k| (hi[k] - lo[k]) / dims[k] as f32)
            .fold(cell, f32::max)
            .max(1e-3);
        let index = |p: f32, k: usize| (((p - lo[k]) / cell) as usize).min(dims[k] - 1);
        let corners: Vec<[V3; 3]> = mesh
            .triangles
            .par_iter()
            .map(|t| t.map(|i| mesh.vertices[i as usize]))
            .collect();
        // Each triangle's block of cells, then a counting sort into compressed rows (in triangle
        // order within a cell).
        let boxes: Vec<[(usize, usize); 3]> = corners
            .par_iter()
            .map(|v| {
                [0, 1, 2].map(|k| {
                    let a = v.iter().map(|p| p[k]).fold(f32::INFINITY, f32::min);
                    let b = v.iter().map(|p| p[k]).fold(f32::NEG_INFINITY, f32::max);
                    (index(a, k), index(b, k))
                })
            })
            .collect();
        let cells_of = |r: &[(usize, usize); 3]| {
            let (xs, ys, zs) = (r[0], r[1], r[2]);
            (zs.0..=zs.1).flat_map(move |z| {
                (ys.0..=ys.1)
                    .flat_map(move |y| (xs.0..=xs.1).map(move |x| (z * dims[1] + y) * dims[0] + x))
            })
        };
        let mut start = vec![0u32; dims[0] * dims[1] * dims[2] + 1];
        for r in &boxes {
            for c in cells_of(r) {
                start[c + 1] += 1;
            }
        }
        for c in 1..start.len() {
            start[c] += start[c - 1];
        }
        let mut fill = start.clone();
        let mut items = vec![0u32; start[start.len() - 1] as usize];
        for (ti, r) in boxes.iter().enumerate() {
            for c in cells_of(r) {
                items[fill[c] as usize] = ti as u32;
                fill[c] += 1;
            }
        }
        Ok(SurfaceIndex {
            origin: lo,
            cell,
            dims,
            start,
            items,
            corners,
        })
    }

    /// Squared distance from `p` to the box of cell `c`.
    #[inline]
    fn cell_dist2(&self, p: V3, c: [usize; 3]) -> f32 {
        let mut d2 = 0.0;
        for k in 0..3 {
            let lo = self.origin[k] + c[k] as f32 * self.cell;
            let hi = lo + self.cell;
            let e = (lo - p[k]).max(p[k] - hi).max(0.0);
            d2 += e * e;
        }
        d2
    }

    /// Distance from `p` to the nearest triangle, exact.
    pub fn distance(&self, p: V3) -> f32 {
        let c = [0, 1, 2].map(|k| ((p[k] - self.origin[k]) / self.cell).floor() as i64);
        let mut best = f32::INFINITY;
        // Enough rings to reach every cell from wherever p is, inside the grid or far outside.
        let outside = (0..3)
            .map(|k| (-c[k]).max(c[k] - (self.dims[k] as i64 - 1)).max(0))
            .max()
            .unwrap_or(0);
        let max_ring = *self.dims.iter().max().unwrap_or(&1) as i64 + outside + 1;
        // The offsets of a ring that land inside the grid (a point far outside it, e.g. of a
        // diverged model, visits only the grid's cells, not the empty rings around it).
        let span = |k: usize, ring: i64| {
            (
                ring.min(c[k]).max(-ring),
                ring.min(self.dims[k] as i64 - 1 - c[k]),
            )
        };
        for ring in outside..=max_ring {
            // Every triangle within `ring` cells has been seen: nothing unseen is closer than
            // the distance from p to the boundary of the searched block.
            let ((z0, z1), (y0, y1), (x0, x1)) = (span(2, ring), span(1, ring), span(0, ring));
            for dz in -z0..=z1 {
                for dy in -y0..=y1 {
                    for dx in -x0..=x1 {
                        if dx.abs().max(dy.abs()).max(dz.abs()) != ring {
                            continue;
                        }
                        let (x, y, z) = (c[0] + dx, c[1] + dy, c[2] + dz);
                        if x < 0 || y < 0 || z < 0 {
                            continue;
                        }
                        let (x, y, z) = (x as usize, y as usize, z as usize);
                        if x >= self.dims[0] || y >= self.dims[1] || z >= self.dims[2] {
                            continue;
                        }
                        // A triangle lies inside the cells it is listed in, so none in a cell
                        // farther than `best` can be closer.
                        if self.cell_dist2(p, [x, y, z]) > best {
                            continue;
                        }
                        let c = (z * self.dims[1] + y) * self.dims[0] + x;
                        let (s, e) = (self.start[c] as usize, self.start[c + 1] as usize);
                        for &ti in &self.items[s..e] {
                            let [a, b, cc] = self.corners[ti as usize];
                            best = best.min(point_triangle_dist2(p, a, b, cc));
                        }
                    }
                }
            }
            // Distance from p to the outside of the searched block of cells.
            let reach = (0..3)
                .map(|k| {
                    let lo = self.origin[k] + (c[k] - ring) as f32 * self.cell;
                    let hi = self.origin[k] + (c[k] + ring + 1) as f32 * self.cell;
                    (p[k] - lo).min(hi - p[k])
                })
                .fold(f32::INFINITY, f32::min);
            if best.is_finite() && best <= reach * reach.max(0.0) {
                break;
            }
        }
        best.sqrt()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn point_triangle_regions() {
        let (a, b, c) = ([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]);
        assert_eq!(point_triangle_dist2([0.2, 0.2, 3.0], a, b, c), 9.0, "face");
        assert_eq!(
            point_triangle_dist2([-1.0, -1.0, 0.0], a, b, c),
            2.0,
            "vertex a"
        );
        assert_eq!(
            point_triangle_dist2([0.5, -2.0, 0.0], a, b, c),
            4.0,
            "edge ab"
        );
        assert!(
            (point_triangle_dist2([1.0, 1.0, 0.0], a, b, c) - 0.5).abs() < 1e-6,
            "edge bc"
        );
    }

    #[test]
    fn the_index_finds_the_nearest_of_all_triangles() {
        // A crumpled sheet (random heights on a 25x25 grid, uneven spacing) against brute force,
        // for points on it, near it, and far outside its box.
        let mut st = 0x9e3779b97f4a7c15u64;
        let mut rnd = || {
            st ^= st << 13;
            st ^= st >> 7;
            st ^= st << 17;
            (st >> 40) as f32 / (1u64 << 24) as f32
        };
        let gt = crate::grid_mesh(25, |i, j| {
            let (x, y) = (i as f32 * 2.0 + rnd(), j as f32 * 2.0 + rnd());
            [x, y, 100.0 + 6.0 * rnd()]
        });
        let index = SurfaceIndex::new(&gt).unwrap();
        for k in 0..400 {
            let spread = [2.0, 10.0, 200.0][k % 3];
            let p = [
                24.0 + spread * (rnd() - 0.5),
                24.0 + spread * (rnd() - 0.5),
                103.0 + spread * (rnd() - 0.5),
            ];
            let brute = gt
                .triangles
                .iter()
                .map(|t| {
                    let [a, b, c] = t.map(|i| gt.vertices[i as usize]);
                    point_triangle_dist2(p, a, b, c)
                })
                .fold(f32::INFINITY, f32::min)
                .sqrt();
            assert_eq!(index.distance(p), brute, "{p:?}");
        }
    }
}
