//! A uniform grid over a point set for k-nearest and radius queries. Built in O(n); a query visits
//! cube shells of cells around the query until the k-th best distance is closer than the next shell,
//! so a query near the set costs a few dozen cells whatever the set's size.

use misslam_framework::nalgebra::Vector3;

/// Points bucketed in cubic cells (CSR layout: `starts[c]..starts[c + 1]` indexes `items`).
#[derive(Clone, Debug, Default)]
pub struct GridIndex {
    origin: Vector3<f64>,
    cell: f64,
    dims: [i64; 3],
    starts: Vec<u32>,
    items: Vec<u32>,
}

impl GridIndex {
    /// Buckets `points` in cells of side `cell` (mm). Non-finite points are left out.
    pub fn build(points: &[Vector3<f64>], cell: f64) -> Self {
        let cell = if cell.is_finite() && cell > 0.0 {
            cell
        } else {
            1.0
        };
        let finite = || points.iter().filter(|p| p.iter().all(|c| c.is_finite()));
        let mut lo = Vector3::repeat(f64::INFINITY);
        let mut hi = Vector3::repeat(f64::NEG_INFINITY);
        for p in finite() {
            lo = lo.inf(p);
            hi = hi.sup(p);
        }
        if lo.x > hi.x {
            return GridIndex {
                cell,
                ..Default::default()
            };
        }
        let mut dims = [0i64; 3];
        for a in 0..3 {
            dims[a] = (((hi[a] - lo[a]) / cell).floor() as i64 + 1).max(1);
        }
        // Very sparse sets in a huge box: coarsen so the cell array stays near the point count.
        let mut grid = GridIndex {
            origin: lo,
            cell,
            dims,
            starts: Vec::new(),
            items: Vec::new(),
        };
        let limit = (points.len() as i64 * 8).max(4096);
        while grid.dims.iter().product::<i64>() > limit {
            grid.cell *= 2.0;
            for a in 0..3 {
                grid.dims[a] = (((hi[a] - lo[a]) / grid.cell).floor() as i64 + 1).max(1);
            }
        }
        let ncell = grid.dims.iter().product::<i64>() as usize;
        let mut counts = vec![0u32; ncell + 1];
        let cell_of: Vec<Option<usize>> = points
            .iter()
            .map(|p| {
                p.iter()
                    .all(|c| c.is_finite())
                    .then(|| grid.flat(grid.coords(p)))
            })
            .collect();
        for c in cell_of.iter().flatten() {
            counts[c + 1] += 1;
        }
        for c in 0..ncell {
            counts[c + 1] += counts[c];
        }
        let mut fill = counts.clone();
        let mut items = vec![0u32; counts[ncell] as usize];
        for (i, c) in cell_of.iter().enumerate() {
            if let Some(c) = c {
                items[fill[*c] as usize] = i as u32;
                fill[*c] += 1;
            }
        }
        grid.starts = counts;
        grid.items = items;
        grid
    }

    fn coords(&self, p: &Vector3<f64>) -> [i64; 3] {
        let mut c = [0i64; 3];
        for a in 0..3 {
            c[a] = ((p[a] - self.origin[a]) / self.cell).floor() as i64;
        }
        c
    }

    fn flat(&self, c: [i64; 3]) -> usize {
        let cl = |a: usize| c[a].clamp(0, self.dims[a] - 1);
        ((cl(2) * self.dims[1] + cl(1)) * self.dims[0] + cl(0)) as usize
    }

    fn cell_items(&self, c: [i64; 3]) -> &[u32] {
        for a in 0..3 {
            if c[a] < 0 || c[a] >= self.dims[a] {
                return &[];
            }
        }
        let f = self.flat(c);
        &self.items[self.starts[f] as usize..self.starts[f + 1] as usize]
    }

    /// Number of indexed points.
    pub fn len(&self) -> usize {
        self.items.len()
    }

    /// True when no point is indexed.
    pub fn is_empty(&self) -> bool {
        self.items.is_empty()
    }

    /// Visits the cells of the cube shell at Chebyshev radius `r` around `c`.
    fn shell(&self, c: [i64; 3], r: i64, mut visit: impl FnMut(&[u32])) {
        for z in c[2] - r..=c[2] + r {
            if z < 0 || z >= self.dims[2] {
                continue;
            }
            let zedge = (z - c[2]).abs() == r;
            for y in c[1] - r..=c[1] + r {
                if y < 0 || y >= self.dims[1] {
                    continue;
                }
                let yedge = zedge || (y - c[1]).abs() == r;
                if yedge {
                    for x in (c[0] - r).max(0)..=(c[0] + r).min(self.dims[0] - 1) {
                        visit(self.cell_items([x, y, z]));
                    }
                } else {
                    for x in [c[0] - r, c[0] + r] {
                        visit(self.cell_items([x, y, z]));
                    }
                }
            }
        }
    }

    /// Chebyshev distance (in cells) from cell `c` to the grid box, and to its far corner.
    fn shell_range(&self, c: [i64; 3]) -> (i64, i64) {
        let (mut near, mut far) = (0i64, 0i64);
        for a in 0..3 {
            let below = -c[a];
            let above = c[a] - (self.dims[a] - 1);
            near = near.max(below.max(above).max(0));
            far = far.max(c[a].abs().max((self.dims[a] - 1 - c[a]).abs()));
        }
        (near, far)
    }

    /// The `k` nearest points to `q`, as (squared distance, index), ascending, into `out`.
    pub fn knn(
        &self,
        points: &[Vector3<f64>],
        q: &Vector3<f64>,
        k: usize,
        out: &mut Vec<(f64, u32)>,
    ) {
        out.clear();
        if k == 0 || self.items.is_empty() || !q.iter().all(|c| c.is_finite()) {
            return;
        }
        let c = self.coords(q);
        let (near, far) = self.shell_range(c);
        // Distance from q to the outside of the shell r block is at least (r - near_offset) cells;
        // q lies in cell c, so a point in shell r + 1 is at least r cells away.
        for r in near..=far {
            self.shell(c, r, |ids| {
                for &i in ids {
                    let d2 = (points[i as usize] - q).norm_squared();
                    if out.len() < k {
                        let at = out.partition_point(|e| e.0 <= d2);
                        out.insert(at, (d2, i));
                    } else if d2 < out[k - 1].0 {
                        out.pop();
                        let at = out.partition_point(|e| e.0 <= d2);
                        out.insert(at, (d2, i));
                    }
                }
            });
            if out.len() == k {
                let reach = r as f64 * self.cell;
                if out[k - 1].0 <= reach * reach {
                    break;
                }
            }
        }
    }

    /// The nearest point within `radius` of `q`, as (squared distance, index).
    pub fn nearest_within(
        &self,
        points: &[Vector3<f64>],
        q: &Vector3<f64>,
        radius: f64,
    ) -> Option<(f64, u32)> {
        if self.items.is_empty() || !q.iter().all(|c| c.is_finite()) {
            return None;
        }
        let c = self.coords(q);
        let cells = (radius / self.cell).ceil() as i64;
        let mut best: Option<(f64, u32)> = None;
        let r2 = radius * radius;
        for r in 0..=cells {
            self.shell(c, r, |ids| {
                for &i in ids {
                    let d2 = (points[i as usize] - q).norm_squared();
                    if d2 <= r2 && best.is_none_or(|b| d2 < b.0) {
                        best = Some((d2, i));
                    }
                }
            });
            if let Some(b) = best {
                let reach = r as f64 * self.cell;
                if b.0 <= reach * reach {
                    break;
                }
            }
        }
        best
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn brute(points: &[Vector3<f64>], q: &Vector3<f64>, k: usize) -> Vec<u32> {
        let mut all: Vec<(f64, u32)> = points
            .iter()
            .enumerate()
            .map(|(i, p)| ((p - q).norm_squared(), i as u32))
            .collect();
        all.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        all.iter().take(k).map(|e| e.1).collect()
    }

    #[test]
    fn knn_matches_brute_force_inside_and_far_outside_the_set() {
        // A deterministic scatter (LCG) in a 100 x 40 x 10 box.
        let mut s = 12345u64;
        let mut rnd = || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        let points: Vec<Vector3<f64>> = (0..500)
            .map(|_| Vector3::new(rnd() * 100.0, rnd() * 40.0, rnd() * 10.0))
            .collect();
        let grid = GridIndex::build(&points, 7.0);
        let mut out = Vec::new();
        for q in [
            Vector3::new(50.0, 20.0, 5.0),
            Vector3::new(0.0, 0.0, 0.0),
            Vector3::new(-300.0, 500.0, 80.0),
            Vector3::new(99.9, 39.9, 9.9),
        ] {
            for k in [1, 5, 9] {
                grid.knn(&points, &q, k, &mut out);
                let got: Vec<u32> = out.iter().map(|e| e.1).collect();
                assert_eq!(got, brute(&points, &q, k), "q {q:?} k {k}");
            }
            let near = grid.nearest_within(&points, &q, 6.0);
            let b = brute(&points, &q, 1)[0];
            let d = (points[b as usize] - q).norm();
            assert_eq!(near.map(|n| n.1), (d <= 6.0).then_some(b));
        }
    }
}
