//! Temporal matching guided by a predicted pose: each reference keypoint is projected into the
//! current image (by the caller, with the predicted pose) and matched only against the current
//! keypoints within a radius of its prediction. Far fewer comparisons than brute force, and no
//! match across the image on repeated texture.

use misslam_framework::{Descriptors, Keypoint, Match};
use rayon::prelude::*;

use crate::distance;

/// Keypoints binned in square cells (compressed rows: one flat index list, offsets per cell).
#[derive(Clone, Debug, Default)]
pub struct KeypointGrid {
    cell: f32,
    cols: usize,
    rows: usize,
    starts: Vec<u32>,
    items: Vec<u32>,
}

impl KeypointGrid {
    /// Bins `keypoints` of an image of `width` x `height` into cells of `cell` pixels.
    pub fn build(keypoints: &[Keypoint], width: u32, height: u32, cell: f32) -> Self {
        let cell = cell.max(1.0);
        let cols = ((width as f32 / cell).ceil() as usize).max(1);
        let rows = ((height as f32 / cell).ceil() as usize).max(1);
        let index = |k: &Keypoint| -> Option<usize> {
            if !(k.x.is_finite() && k.y.is_finite()) || k.x < 0.0 || k.y < 0.0 {
                return None;
            }
            let (cx, cy) = ((k.x / cell) as usize, (k.y / cell) as usize);
            (cx < cols && cy < rows).then_some(cy * cols + cx)
        };
        let mut counts = vec![0u32; cols * rows + 1];
        for k in keypoints {
            if let Some(c) = index(k) {
                counts[c + 1] += 1;
            }
        }
        for c in 0..cols * rows {
            counts[c + 1] += counts[c];
        }
        let mut fill = counts.clone();
        let mut items = vec![0u32; counts[cols * rows] as usize];
        for (i, k) in keypoints.iter().enumerate() {
            if let Some(c) = index(k) {
                items[fill[c] as usize] = i as u32;
                fill[c] += 1;
            }
        }
        KeypointGrid {
            cell,
            cols,
            rows,
            starts: counts,
            items,
        }
    }

    /// Calls `f` with every keypoint index in the cells that the disc (x, y, r) touches (a
    /// superset of the keypoints within `r`; the caller checks the distance).
    pub fn for_each_near(&self, x: f32, y: f32, r: f32, mut f: impl FnMut(u32)) {
        if !(x.is_finite() && y.is_finite()) {
            return;
        }
        let lo = |v: f32| ((v - r) / self.cell).floor().max(0.0) as usize;
        let hi =
            |v: f32, n: usize| (((v + r) / self.cell).floor().max(-1.0) as i64).min(n as i64 - 1);
        let (x0, y0) = (lo(x), lo(y));
        let (x1, y1) = (hi(x, self.cols), hi(y, self.rows));
        if x1 < 0 || y1 < 0 {
            return;
        }
        for cy in y0..=y1 as usize {
            for cx in x0..=x1 as usize {
                let c = cy * self.cols + cx;
                for &i in &self.items[self.starts[c] as usize..self.starts[c + 1] as usize] {
                    f(i);
                }
            }
        }
    }
}

/// Settings of [`match_guided`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct GuidedParams {
    /// Search radius around the prediction, pixels.
    pub radius_px: f32,
    /// Largest accepted descriptor distance.
    pub max_distance: f32,
    /// Ratio between the best and second-best distance within the radius; 1 disables it.
    pub ratio: f32,
    /// Largest difference of pyramid level (octave) between the two keypoints; negative: any.
    pub max_octave_gap: i32,
}

/// Matches reference descriptors `train` (keypoint `j` predicted at `predicted[j]` in the current
/// image, NaN when it is not expected to be seen) against the current keypoints `query`. Each
/// current keypoint keeps at most one match, the nearest in descriptor distance. Sorted by query.
#[allow(clippy::too_many_arguments)]
pub fn match_guided(
    predicted: &[[f32; 2]],
    train_octaves: &[i32],
    train: &Descriptors,
    query_keypoints: &[Keypoint],
    query: &Descriptors,
    grid: &KeypointGrid,
    params: &GuidedParams,
) -> Vec<Match> {
    let r2 = params.radius_px * params.radius_px;
    // Each train point's nearest query within the radius (in parallel: thousands of anchors
    // per frame in fusion's correspondences), then the best train per query in train order, as
    // one serial pass would (ties go to the first).
    let nearest: Vec<Option<(u32, f32)>> = predicted
        .par_iter()
        .enumerate()
        .map(|(j, p)| {
            let (mut d1, mut d2, mut arg) = (f32::INFINITY, f32::INFINITY, u32::MAX);
            grid.for_each_near(p[0], p[1], params.radius_px, |i| {
                let k = &query_keypoints[i as usize];
                let (dx, dy) = (k.x - p[0], k.y - p[1]);
                if dx * dx + dy * dy > r2 {
                    return;
                }
                if params.max_octave_gap >= 0
                    && (k.octave - train_octaves.get(j).copied().unwrap_or(k.octave)).abs()
                        > params.max_octave_gap
                {
                    return;
                }
                let d = distance(query, i as usize, train, j);
                if d < d1 {
                    d2 = d1;
                    d1 = d;
                    arg = i;
                } else if d < d2 {
                    d2 = d;
                }
            });
            if arg == u32::MAX || d1 > params.max_distance {
                return None;
            }
            if params.ratio < 1.0 && d2.is_finite() && d1 >= params.ratio * d2 {
                return None;
            }
            Some((arg, d1))
        })
        .collect();
    // Best train per query: (distance, train index).
    let mut best: Vec<(f32, u32)> = vec![(f32::INFINITY, u32::MAX); query_keypoints.len()];
    for (j, n) in nearest.into_iter().enumerate() {
        let Some((arg, d1)) = n else { continue };
        let slot = &mut best[arg as usize];
        if d1 < slot.0 {
            *slot = (d1, j as u32);
        }
    }
    best.iter()
        .enumerate()
        .filter(|(_, (_, j))| *j != u32::MAX)
        .map(|(i, &(d, j))| Match {
            query: i as u32,
            train: j,
            distance: d,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 31.0,
            angle: 0.0,
            response: 1.0,
            octave: 0,
        }
    }

    #[test]
    fn grid_returns_every_keypoint_within_the_radius() {
        let kps: Vec<Keypoint> = (0..400)
            .map(|i| kp((i * 37 % 640) as f32 + 0.5, (i * 91 % 480) as f32 + 0.25))
            .collect();
        let grid = KeypointGrid::build(&kps, 640, 480, 16.0);
        for &(x, y, r) in &[
            (100.0f32, 100.0f32, 20.0f32),
            (0.0, 0.0, 50.0),
            (639.0, 479.0, 5.0),
        ] {
            let mut got = Vec::new();
            grid.for_each_near(x, y, r, |i| {
                let k = &kps[i as usize];
                if (k.x - x).powi(2) + (k.y - y).powi(2) <= r * r {
                    got.push(i);
                }
            });
            got.sort_unstable();
            let want: Vec<u32> = (0..kps.len() as u32)
                .filter(|&i| {
                    let k = &kps[i as usize];
                    (k.x - x).powi(2) + (k.y - y).powi(2) <= r * r
                })
                .collect();
            assert_eq!(got, want, "disc ({x}, {y}, {r})");
        }
        // Out of the image, or NaN: nothing, no panic.
        grid.for_each_near(-100.0, -100.0, 5.0, |_| panic!("nothing there"));
        grid.for_each_near(f32::NAN, 3.0, 5.0, |_| panic!("nothing there"));
    }

    #[test]
    fn guided_matching_uses_the_prediction_and_keeps_one_match_per_keypoint() {
        // Two identical descriptors far apart: brute force cannot tell them apart, the
        // prediction can.
        let d = [0xABCDu64, 1, 2, 3];
        let other = [!0u64, 0, 0, 0];
        let query_kps = vec![kp(100.0, 100.0), kp(400.0, 300.0), kp(105.0, 100.0)];
        let query = Descriptors::Binary256(vec![d, d, other]);
        let train = Descriptors::Binary256(vec![d, d]);
        let grid = KeypointGrid::build(&query_kps, 640, 480, 32.0);
        let p = GuidedParams {
            radius_px: 10.0,
            max_distance: 50.0,
            ratio: 1.0,
            max_octave_gap: 1,
        };
        let m = match_guided(
            &[[398.0, 303.0], [101.0, 99.0]],
            &[0, 0],
            &train,
            &query_kps,
            &query,
            &grid,
            &p,
        );
        let pairs: Vec<(u32, u32)> = m.iter().map(|m| (m.query, m.train)).collect();
        assert_eq!(pairs, vec![(0, 1), (1, 0)]);
        // Both predicted at the same place: the query keypoint keeps one of them.
        let m = match_guided(
            &[[100.0, 100.0], [100.0, 101.0]],
            &[0, 0],
            &train,
            &query_kps,
            &query,
            &grid,
            &p,
        );
        assert_eq!(m.len(), 1);
        // Not visible (NaN) or out of the radius: no match.
        let m = match_guided(
            &[[f32::NAN, 0.0], [200.0, 200.0]],
            &[0, 0],
            &train,
            &query_kps,
            &query,
            &grid,
            &p,
        );
        assert!(m.is_empty());
        // Octave gap.
        let m = match_guided(
            &[[100.0, 100.0]],
            &[5],
            &train,
            &query_kps,
            &query,
            &grid,
            &p,
        );
        assert!(m.is_empty());
    }
}
