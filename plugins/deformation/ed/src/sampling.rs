//! Node sampling on a point set at spacing epsilon ([`crate::graph::Sampling`]): a greedy
//! Poisson disc (also the growth of a graph, clear of its nodes) or one node per occupied voxel.

use misslam_framework::nalgebra::Vector3;

/// Greedy Poisson-disc sample of `points` at radius `eps`, keeping clear of `existing` nodes too.
pub(crate) fn poisson_disc(
    points: &[Vector3<f64>],
    existing: &[Vector3<f64>],
    eps: f64,
) -> Vec<Vector3<f64>> {
    // A hash of cells of side eps / sqrt(3) holds at most one accepted node each; a candidate checks
    // the 5x5x5 block around it.
    let cell = eps / 3f64.sqrt();
    let key = |p: &Vector3<f64>| {
        [
            (p.x / cell).floor() as i64,
            (p.y / cell).floor() as i64,
            (p.z / cell).floor() as i64,
        ]
    };
    let mut occupied: std::collections::HashMap<[i64; 3], Vec<u32>> =
        std::collections::HashMap::new();
    let mut all: Vec<Vector3<f64>> = existing.to_vec();
    for (i, g) in existing.iter().enumerate() {
        occupied.entry(key(g)).or_default().push(i as u32);
    }
    let first_new = all.len();
    let eps2 = eps * eps;
    for p in points {
        if !p.iter().all(|c| c.is_finite()) {
            continue;
        }
        let k = key(p);
        let mut clear = true;
        'search: for dz in -2..=2 {
            for dy in -2..=2 {
                for dx in -2..=2 {
                    if let Some(ids) = occupied.get(&[k[0] + dx, k[1] + dy, k[2] + dz]) {
                        if ids
                            .iter()
                            .any(|&i| (all[i as usize] - p).norm_squared() < eps2)
                        {
                            clear = false;
                            break 'search;
                        }
                    }
                }
            }
        }
        if clear {
            occupied.entry(k).or_default().push(all.len() as u32);
            all.push(*p);
        }
    }
    all.split_off(first_new)
}

/// Per occupied voxel of side `eps`, the point nearest to the voxel's centroid of points.
pub(crate) fn voxel_sample(points: &[Vector3<f64>], eps: f64) -> Vec<Vector3<f64>> {
    let key = |p: &Vector3<f64>| {
        [
            (p.x / eps).floor() as i64,
            (p.y / eps).floor() as i64,
            (p.z / eps).floor() as i64,
        ]
    };
    let mut sums: std::collections::BTreeMap<[i64; 3], (Vector3<f64>, usize)> = Default::default();
    for p in points.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        let e = sums.entry(key(p)).or_insert((Vector3::zeros(), 0));
        e.0 += p;
        e.1 += 1;
    }
    let mut best: std::collections::BTreeMap<[i64; 3], (f64, Vector3<f64>)> = Default::default();
    for p in points.iter().filter(|p| p.iter().all(|c| c.is_finite())) {
        let k = key(p);
        let (s, n) = sums[&k];
        let d = (p - s / n as f64).norm_squared();
        let e = best.entry(k).or_insert((f64::INFINITY, *p));
        if d < e.0 {
            *e = (d, *p);
        }
    }
    best.into_values().map(|e| e.1).collect()
}
