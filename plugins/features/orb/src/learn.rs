//! Learning the binary tests of rBRIEF (Rublee et al., ICCV 2011, section 4.3): from patches
//! around real keypoints, each turned to its keypoint's orientation, keep tests that split the
//! patches evenly (mean near 0.5, so each bit carries information) and that are uncorrelated with
//! each other (so the bits do not repeat each other).
//!
//! The candidates are pairs of points on a grid of sub-window centres inside the patch whose 5x5
//! windows do not overlap; the smoothed image the descriptor reads stands in for the window
//! averages. The greedy search: order the candidates by `|mean - 0.5|`, take the first, then each
//! next candidate whose absolute correlation with every test taken so far is at most the
//! threshold; when the candidates run out before `n` tests, raise the threshold and start again.
//!
//! `examples/learn_orb_pattern.rs` runs it on surgical stereo frames and writes
//! `learned_pattern.rs`, the table [`crate::extract::pattern`] uses by default.

use crate::extract::PATTERN_RADIUS;

/// Half width of the grid of test points: centres lie in `[-GRID_HALF, GRID_HALF]^2` and within
/// [`PATTERN_RADIUS`] - 2 of the centre (so a 5x5 window around them stays within the radius).
pub const GRID_HALF: i32 = 13;
/// Side of the grid.
pub const GRID: usize = (2 * GRID_HALF + 1) as usize;

/// One training patch: the smoothed level sampled on the grid, turned by the keypoint's angle
/// (`[(dy + GRID_HALF) * GRID + dx + GRID_HALF]`).
pub type Patch = [u8; GRID * GRID];

/// Samples the smoothed level around (x, y) on the grid turned by `angle`, rounding each turned
/// point to a pixel exactly as [`crate::extract::describe`] does. None when the turned grid
/// leaves the image.
pub fn sample_patch(
    smooth: &[u8],
    w: usize,
    h: usize,
    x: i32,
    y: i32,
    angle: f32,
) -> Option<Patch> {
    let (s, c) = if angle.is_finite() {
        angle.sin_cos()
    } else {
        (0.0, 1.0)
    };
    let reach = GRID_HALF + 2;
    if x < reach || y < reach || x + reach >= w as i32 || y + reach >= h as i32 {
        return None;
    }
    let mut p = [0u8; GRID * GRID];
    for dy in -GRID_HALF..=GRID_HALF {
        for dx in -GRID_HALF..=GRID_HALF {
            let (fx, fy) = (dx as f32, dy as f32);
            let u = x + (c * fx - s * fy).round() as i32;
            let v = y + (s * fx + c * fy).round() as i32;
            p[((dy + GRID_HALF) as usize) * GRID + (dx + GRID_HALF) as usize] =
                smooth[v as usize * w + u as usize];
        }
    }
    Some(p)
}

/// Settings of [`learn`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LearnParams {
    /// Tests wanted.
    pub tests: usize,
    /// Starting correlation threshold.
    pub threshold: f64,
    /// Added to the threshold when a pass runs out of candidates.
    pub threshold_step: f64,
    /// Side of the sub-windows whose overlap excludes a pair.
    pub window: i32,
}

impl Default for LearnParams {
    fn default() -> Self {
        LearnParams {
            tests: 256,
            threshold: 0.2,
            threshold_step: 0.05,
            window: 5,
        }
    }
}

/// What [`learn`] found.
#[derive(Clone, Debug, PartialEq)]
pub struct Learned {
    /// The tests (x1, y1, x2, y2), in the order taken.
    pub tests: Vec<[i8; 4]>,
    /// The correlation threshold of the pass that found them.
    pub threshold: f64,
    /// Candidates considered.
    pub candidates: usize,
    /// Mean of each test over the patches.
    pub means: Vec<f64>,
    /// Largest absolute correlation between two of the tests.
    pub max_correlation: f64,
}

/// The candidate tests: pairs of grid points within the radius whose windows do not overlap.
pub fn candidates(window: i32) -> Vec<[i8; 4]> {
    let r = PATTERN_RADIUS - 2.0;
    let pts: Vec<(i32, i32)> = (-GRID_HALF..=GRID_HALF)
        .flat_map(|y| (-GRID_HALF..=GRID_HALF).map(move |x| (x, y)))
        .filter(|&(x, y)| ((x * x + y * y) as f32) <= r * r)
        .collect();
    let mut out = Vec::new();
    for (i, &(x1, y1)) in pts.iter().enumerate() {
        for &(x2, y2) in &pts[i + 1..] {
            if (x1 - x2).abs() < window && (y1 - y2).abs() < window {
                continue;
            }
            out.push([x1 as i8, y1 as i8, x2 as i8, y2 as i8]);
        }
    }
    out
}

#[inline]
fn at(t: &[i8; 4], k: usize) -> usize {
    let (x, y) = (t[2 * k] as i32 + GRID_HALF, t[2 * k + 1] as i32 + GRID_HALF);
    y as usize * GRID + x as usize
}

/// The bits of test `t` over the patches (bit set: the first point darker than the second, as in
/// the descriptor).
fn bits(t: &[i8; 4], patches: &[Patch]) -> Vec<u64> {
    let (a, b) = (at(t, 0), at(t, 1));
    let mut out = vec![0u64; patches.len().div_ceil(64)];
    for (i, p) in patches.iter().enumerate() {
        out[i / 64] |= ((p[a] < p[b]) as u64) << (i % 64);
    }
    out
}

/// Pearson correlation of two binary tests from their bit vectors and means over `n` patches.
fn correlation(a: &[u64], b: &[u64], ma: f64, mb: f64, n: f64) -> f64 {
    let both = a
        .iter()
        .zip(b)
        .map(|(x, y)| (x & y).count_ones() as u64)
        .sum::<u64>() as f64
        / n;
    let den = (ma * (1.0 - ma) * mb * (1.0 - mb)).sqrt();
    if den <= 0.0 {
        return 1.0;
    }
    (both - ma * mb) / den
}

/// Runs the greedy search over [`candidates`] on `patches`.
pub fn learn(patches: &[Patch], p: &LearnParams) -> Result<Learned, String> {
    if patches.len() < 64 {
        return Err(format!(
            "learning the tests needs at least 64 patches, got {}",
            patches.len()
        ));
    }
    if p.tests == 0 || !(p.threshold > 0.0 && p.threshold <= 1.0) || p.threshold_step <= 0.0 {
        return Err(format!(
            "learning needs tests > 0, 0 < threshold <= 1 and threshold_step > 0: {p:?}"
        ));
    }
    let cand = candidates(p.window);
    if cand.len() < p.tests {
        return Err(format!(
            "{} candidate tests for {} wanted",
            cand.len(),
            p.tests
        ));
    }
    let n = patches.len() as f64;
    // Means of every candidate: count the patches where the first point is darker.
    let mut count = vec![0u32; cand.len()];
    for patch in patches {
        for (c, t) in count.iter_mut().zip(&cand) {
            *c += (patch[at(t, 0)] < patch[at(t, 1)]) as u32;
        }
    }
    let mean: Vec<f64> = count.iter().map(|&c| c as f64 / n).collect();
    let mut order: Vec<usize> = (0..cand.len()).collect();
    order.sort_by(|&a, &b| {
        (mean[a] - 0.5)
            .abs()
            .total_cmp(&(mean[b] - 0.5).abs())
            .then(a.cmp(&b))
    });
    // Bit vectors are computed when a candidate is first considered (empty until then: a
    // computed one has a word per 64 patches), and kept across passes.
    let mut cache: Vec<Vec<u64>> = vec![Vec::new(); cand.len()];
    let mut threshold = p.threshold;
    loop {
        let mut taken: Vec<usize> = Vec::with_capacity(p.tests);
        let mut considered = 0;
        for &c in &order {
            if taken.len() == p.tests {
                break;
            }
            considered += 1;
            if cache[c].is_empty() {
                cache[c] = bits(&cand[c], patches);
            }
            let fits = taken.iter().all(|&t| {
                correlation(&cache[c], &cache[t], mean[c], mean[t], n).abs() <= threshold
            });
            if fits {
                taken.push(c);
            }
        }
        if taken.len() == p.tests {
            let mut max_correlation = 0.0f64;
            for (i, &a) in taken.iter().enumerate() {
                for &b in &taken[i + 1..] {
                    let r = correlation(&cache[a], &cache[b], mean[a], mean[b], n);
                    max_correlation = max_correlation.max(r.abs());
                }
            }
            return Ok(Learned {
                tests: taken.iter().map(|&c| cand[c]).collect(),
                threshold,
                candidates: considered,
                means: taken.iter().map(|&c| mean[c]).collect(),
                max_correlation,
            });
        }
        threshold += p.threshold_step;
        if threshold > 1.0 + 1e-9 {
            return Err("no set of tests was found under any threshold".into());
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn ones(v: &[u64]) -> u64 {
        v.iter().map(|w| w.count_ones() as u64).sum()
    }

    /// Patches of smooth random blobs (a few Gaussians of random sign and place), so tests close
    /// together agree and tests far apart do not.
    fn blobs(n: usize) -> Vec<Patch> {
        let mut state = 0x1234_5678u64;
        let mut uniform = move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| {
                let centres: Vec<(f64, f64, f64)> = (0..4)
                    .map(|_| {
                        (
                            (uniform() - 0.5) * 30.0,
                            (uniform() - 0.5) * 30.0,
                            (uniform() - 0.5) * 200.0,
                        )
                    })
                    .collect();
                let mut p = [0u8; GRID * GRID];
                for y in 0..GRID {
                    for x in 0..GRID {
                        let (fx, fy) = (x as f64 - GRID_HALF as f64, y as f64 - GRID_HALF as f64);
                        let v: f64 = centres
                            .iter()
                            .map(|&(cx, cy, a)| {
                                a * (-((fx - cx).powi(2) + (fy - cy).powi(2)) / 50.0).exp()
                            })
                            .sum();
                        p[y * GRID + x] = (128.0 + v).clamp(0.0, 255.0) as u8;
                    }
                }
                p
            })
            .collect()
    }

    #[test]
    fn candidates_lie_within_the_radius_and_their_windows_do_not_overlap() {
        let c = candidates(5);
        assert!(c.len() > 100_000, "{}", c.len());
        let r = PATTERN_RADIUS - 2.0;
        for t in &c {
            for k in 0..2 {
                let (x, y) = (t[2 * k] as f32, t[2 * k + 1] as f32);
                assert!(x * x + y * y <= r * r);
            }
            assert!((t[0] - t[2]).abs() >= 5 || (t[1] - t[3]).abs() >= 5);
        }
    }

    #[test]
    fn learned_tests_are_balanced_and_less_correlated_than_random_ones() {
        let patches = blobs(2000);
        let p = LearnParams {
            tests: 64,
            ..Default::default()
        };
        let l = learn(&patches, &p).unwrap();
        assert_eq!(l.tests.len(), 64);
        assert!(l.max_correlation <= l.threshold + 1e-12);
        for m in &l.means {
            assert!((m - 0.5).abs() < 0.1, "mean {m}");
        }
        // The same number of tests drawn at random from the candidates correlate more.
        let cand = candidates(5);
        let n = patches.len() as f64;
        let random: Vec<[i8; 4]> = (0..64)
            .map(|i| cand[(i * 7919 + 13) % cand.len()])
            .collect();
        let stats = |tests: &[[i8; 4]]| {
            let b: Vec<Vec<u64>> = tests.iter().map(|t| bits(t, &patches)).collect();
            let m: Vec<f64> = b.iter().map(|v| ones(v) as f64 / n).collect();
            let mut worst = 0.0f64;
            for i in 0..b.len() {
                for j in i + 1..b.len() {
                    worst = worst.max(correlation(&b[i], &b[j], m[i], m[j], n).abs());
                }
            }
            worst
        };
        let (learned, drawn) = (stats(&l.tests), stats(&random));
        assert!((learned - l.max_correlation).abs() < 1e-12);
        assert!(
            learned < drawn,
            "largest correlation: learned {learned:.3}, random {drawn:.3}"
        );
    }

    #[test]
    fn too_few_patches_or_bad_settings_are_errors() {
        assert!(learn(&blobs(10), &LearnParams::default())
            .unwrap_err()
            .contains("64 patches"));
        let bad = LearnParams {
            threshold: 0.0,
            ..Default::default()
        };
        assert!(learn(&blobs(100), &bad).unwrap_err().contains("threshold"));
    }

    #[test]
    fn a_patch_is_the_turned_grid_and_none_near_the_border() {
        let (w, h) = (64usize, 64usize);
        let img: Vec<u8> = (0..w * h).map(|i| (i % w) as u8).collect();
        let p = sample_patch(&img, w, h, 32, 32, 0.0).unwrap();
        // Upright: x grows along the row.
        assert_eq!(p[GRID_HALF as usize * GRID], 32 - GRID_HALF as u8);
        // A quarter turn: the grid's x axis points down the image, where the ramp is constant.
        let q = sample_patch(&img, w, h, 32, 32, std::f32::consts::FRAC_PI_2).unwrap();
        assert_eq!(q[GRID_HALF as usize * GRID], 32);
        assert_eq!(q[GRID_HALF as usize], 32 + GRID_HALF as u8);
        assert!(sample_patch(&img, w, h, 10, 32, 0.0).is_none());
    }
}
