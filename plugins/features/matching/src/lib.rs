//! Descriptor matching shared by the feature plugins and the tracker (method.md section 2).
//!
//! - [`knn2`]: brute-force two nearest neighbours, Hamming for 256-bit binary descriptors (with
//!   the CPU's `popcnt` when it has one, detected at run time) and L2 for 64-float descriptors;
//! - [`match_descriptors`]: nearest neighbour with Lowe's ratio test, a distance limit and an
//!   optional cross-check;
//! - [`stereo`]: matching along the rows of a rectified pair, with sub-pixel refinement by SAD
//!   block matching and triangulation;
//! - [`extractor`]: what every feature node does around its detector (both views, mask,
//!   stereo 3D keypoints, ports);
//! - [`guided`]: temporal matching of keypoints whose positions a predicted pose gives, searched
//!   within a radius.
#![deny(missing_docs)]

pub mod dense;
pub mod extractor;
pub mod guided;
pub mod stereo;

use misslam_framework::{Descriptors, Keypoint, Mask, Match};

/// Drops the keypoints (and their descriptors) that fall on invalid pixels of `mask` (e.g. the
/// black border of a rectified endoscope image); a mask of another size is ignored.
pub fn retain_in_mask<T>(
    keypoints: &mut Vec<Keypoint>,
    descriptors: &mut Vec<T>,
    mask: Option<&Mask>,
) {
    let Some(m) = mask else { return };
    let (w, h) = (m.width as usize, m.height as usize);
    let keep: Vec<bool> = keypoints
        .iter()
        .map(|k| {
            let (x, y) = (k.x.round(), k.y.round());
            x >= 0.0
                && y >= 0.0
                && (x as usize) < w
                && (y as usize) < h
                && m.data[y as usize * w + x as usize] != 0
        })
        .collect();
    let mut i = 0;
    keypoints.retain(|_| {
        i += 1;
        keep[i - 1]
    });
    let mut i = 0;
    descriptors.retain(|_| {
        i += 1;
        keep[i - 1]
    });
}

/// Hamming distance of two 256-bit descriptors.
#[inline(always)]
pub fn hamming(a: &[u64; 4], b: &[u64; 4]) -> u32 {
    (a[0] ^ b[0]).count_ones()
        + (a[1] ^ b[1]).count_ones()
        + (a[2] ^ b[2]).count_ones()
        + (a[3] ^ b[3]).count_ones()
}

/// Squared L2 distance of two 64-float descriptors (eight independent partial sums, which the
/// compiler keeps in SIMD registers).
#[inline(always)]
pub fn l2_squared(a: &[f32; 64], b: &[f32; 64]) -> f32 {
    let mut acc = [0.0f32; 8];
    for (ca, cb) in a.chunks_exact(8).zip(b.chunks_exact(8)) {
        for k in 0..8 {
            let d = ca[k] - cb[k];
            acc[k] += d * d;
        }
    }
    acc.iter().sum()
}

/// The two nearest train descriptors of one query descriptor.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Knn2 {
    /// Index of the nearest, `u32::MAX` when the train set is empty.
    pub best: u32,
    /// Its distance (Hamming bits, or L2), `f32::INFINITY` when none.
    pub d1: f32,
    /// Distance of the second nearest, `f32::INFINITY` when none.
    pub d2: f32,
}

impl Knn2 {
    const NONE: Knn2 = Knn2 {
        best: u32::MAX,
        d1: f32::INFINITY,
        d2: f32::INFINITY,
    };
}

/// Two nearest neighbours in Hamming distance, as integers (`best`, `d1`, `d2`).
#[inline(always)]
fn knn2_hamming_body(query: &[[u64; 4]], train: &[[u64; 4]], out: &mut Vec<Knn2>) {
    out.clear();
    out.reserve(query.len());
    for q in query {
        let (mut best, mut d1, mut d2) = (u32::MAX, u32::MAX, u32::MAX);
        for (j, t) in train.iter().enumerate() {
            let d = hamming(q, t);
            if d < d2 {
                if d < d1 {
                    d2 = d1;
                    d1 = d;
                    best = j as u32;
                } else {
                    d2 = d;
                }
            }
        }
        let f = |d: u32| {
            if d == u32::MAX {
                f32::INFINITY
            } else {
                d as f32
            }
        };
        out.push(Knn2 {
            best,
            d1: f(d1),
            d2: f(d2),
        });
    }
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "popcnt")]
fn knn2_hamming_popcnt(query: &[[u64; 4]], train: &[[u64; 4]], out: &mut Vec<Knn2>) {
    knn2_hamming_body(query, train, out)
}

/// Brute-force two nearest neighbours in Hamming distance; `out` is reused.
pub fn knn2_hamming(query: &[[u64; 4]], train: &[[u64; 4]], out: &mut Vec<Knn2>) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("popcnt") {
        // SAFETY: the CPU has `popcnt`, checked just above; the function is otherwise safe.
        unsafe { knn2_hamming_popcnt(query, train, out) };
        return;
    }
    knn2_hamming_body(query, train, out)
}

/// Brute-force two nearest neighbours in L2 distance (not squared); `out` is reused.
pub fn knn2_l2(query: &[[f32; 64]], train: &[[f32; 64]], out: &mut Vec<Knn2>) {
    out.clear();
    out.reserve(query.len());
    for q in query {
        let mut k = Knn2::NONE;
        for (j, t) in train.iter().enumerate() {
            let d = l2_squared(q, t);
            if d < k.d2 {
                if d < k.d1 {
                    k.d2 = k.d1;
                    k.d1 = d;
                    k.best = j as u32;
                } else {
                    k.d2 = d;
                }
            }
        }
        k.d1 = k.d1.sqrt();
        k.d2 = k.d2.sqrt();
        out.push(k);
    }
}

/// Two nearest neighbours of every query descriptor; the two sets must be of the same kind.
pub fn knn2(query: &Descriptors, train: &Descriptors, out: &mut Vec<Knn2>) -> Result<(), String> {
    match (query, train) {
        (Descriptors::Binary256(q), Descriptors::Binary256(t)) => knn2_hamming(q, t, out),
        (Descriptors::Float64(q), Descriptors::Float64(t)) => knn2_l2(q, t, out),
        _ => {
            return Err(format!(
                "cannot match {} descriptors against {} descriptors",
                kind(query),
                kind(train)
            ))
        }
    }
    Ok(())
}

/// "binary" or "float" (for messages).
pub fn kind(d: &Descriptors) -> &'static str {
    match d {
        Descriptors::Binary256(_) => "binary 256-bit",
        Descriptors::Float64(_) => "64-float",
    }
}

/// Distance between descriptor `i` of `a` and `j` of `b` (same kind; Hamming bits or L2).
pub fn distance(a: &Descriptors, i: usize, b: &Descriptors, j: usize) -> f32 {
    match (a, b) {
        (Descriptors::Binary256(a), Descriptors::Binary256(b)) => hamming(&a[i], &b[j]) as f32,
        (Descriptors::Float64(a), Descriptors::Float64(b)) => l2_squared(&a[i], &b[j]).sqrt(),
        _ => f32::INFINITY,
    }
}

/// How nearest neighbours become matches.
#[derive(
    Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(deny_unknown_fields, default)]
pub struct MatchParams {
    /// Lowe's ratio test: keep a match when `d1 < ratio * d2`; 1 disables it.
    pub ratio: f32,
    /// Largest accepted Hamming distance of binary descriptors (ORB), bits.
    pub max_distance: f32,
    /// Largest accepted L2 distance of float descriptors (SURF's unit vectors: 0 to 2).
    pub max_distance_l2: f32,
    /// Keep a match only when the query is also the train descriptor's nearest neighbour.
    pub cross_check: bool,
}

impl Default for MatchParams {
    fn default() -> Self {
        MatchParams {
            ratio: 0.8,
            max_distance: 64.0,
            max_distance_l2: 0.4,
            cross_check: false,
        }
    }
}

impl MatchParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(format!("`ratio` must lie in (0, 1], got {}", self.ratio));
        }
        if self.max_distance.is_nan() || self.max_distance <= 0.0 {
            return Err(format!(
                "`max_distance` must be positive, got {}",
                self.max_distance
            ));
        }
        if self.max_distance_l2.is_nan() || self.max_distance_l2 <= 0.0 {
            return Err(format!(
                "`max_distance_l2` must be positive, got {}",
                self.max_distance_l2
            ));
        }
        Ok(())
    }

    /// The distance limit for descriptors of this kind.
    pub fn limit(&self, d: &Descriptors) -> f32 {
        distance_limit(d, self.max_distance, self.max_distance_l2)
    }
}

/// `binary` for binary descriptors, `l2` for float ones.
pub fn distance_limit(d: &Descriptors, binary: f32, l2: f32) -> f32 {
    match d {
        Descriptors::Binary256(_) => binary,
        Descriptors::Float64(_) => l2,
    }
}

/// Reusable buffers of [`match_descriptors`].
#[derive(Default)]
pub struct MatchScratch {
    forward: Vec<Knn2>,
    backward: Vec<Knn2>,
}

/// Matches `query` against `train` (`Match::query` indexes `query`), sorted by query index.
pub fn match_descriptors(
    query: &Descriptors,
    train: &Descriptors,
    params: &MatchParams,
    scratch: &mut MatchScratch,
) -> Result<Vec<Match>, String> {
    knn2(query, train, &mut scratch.forward)?;
    if params.cross_check {
        knn2(train, query, &mut scratch.backward)?;
    }
    let limit = params.limit(query);
    let mut out = Vec::new();
    for (i, k) in scratch.forward.iter().enumerate() {
        if k.best == u32::MAX || k.d1 > limit {
            continue;
        }
        // With a tie for the nearest (d1 == d2) the match is ambiguous and the ratio test drops it.
        if params.ratio < 1.0 && k.d1 >= params.ratio * k.d2 {
            continue;
        }
        if params.cross_check && scratch.backward[k.best as usize].best != i as u32 {
            continue;
        }
        out.push(Match {
            query: i as u32,
            train: k.best,
            distance: k.d1,
        });
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(seed: &mut u64) -> u64 {
        *seed = seed.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = *seed;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }

    #[test]
    fn keypoints_on_the_masked_border_are_dropped_with_their_descriptors() {
        let kp = |x: f32, y: f32| Keypoint {
            x,
            y,
            size: 31.0,
            angle: 0.0,
            response: 1.0,
            octave: 0,
        };
        // A 10x4 mask whose left 3 columns are the black border.
        let mask = Mask {
            width: 10,
            height: 4,
            data: (0..40).map(|i| (i % 10 >= 3) as u8).collect(),
        };
        let mut kps = vec![
            kp(1.0, 1.0),
            kp(5.2, 2.0),
            kp(2.6, 3.0),
            kp(9.4, 0.0),
            kp(12.0, 1.0),
        ];
        let mut desc = vec![10, 11, 12, 13, 14];
        retain_in_mask(&mut kps, &mut desc, Some(&mask));
        // (2.6 rounds to column 3, valid); (12, 1) lies outside the mask: dropped.
        assert_eq!(desc, vec![11, 12, 13]);
        assert_eq!(kps.len(), 3);
        retain_in_mask(&mut kps, &mut desc, None);
        assert_eq!(desc.len(), 3);
    }

    #[test]
    fn hamming_counts_differing_bits() {
        let a = [0u64, u64::MAX, 0b1011, 1 << 63];
        let b = [0u64, 0, 0b0001, 0];
        assert_eq!(hamming(&a, &b), 64 + 2 + 1);
        assert_eq!(hamming(&a, &a), 0);
    }

    #[test]
    fn knn_finds_the_planted_neighbours_in_both_metrics() {
        let mut s = 7u64;
        let train: Vec<[u64; 4]> = (0..300)
            .map(|_| [rng(&mut s), rng(&mut s), rng(&mut s), rng(&mut s)])
            .collect();
        // Each query is train[3 i] with i + 1 bits flipped.
        let query: Vec<[u64; 4]> = (0..50)
            .map(|i| {
                let mut d = train[3 * i];
                for b in 0..=i {
                    d[b % 4] ^= 1 << (b * 5 % 64);
                }
                d
            })
            .collect();
        let mut out = Vec::new();
        knn2_hamming(&query, &train, &mut out);
        for (i, k) in out.iter().enumerate() {
            let exact = (0..train.len())
                .map(|j| hamming(&query[i], &train[j]))
                .collect::<Vec<_>>();
            let mut sorted = exact.clone();
            sorted.sort_unstable();
            assert_eq!(k.d1, sorted[0] as f32);
            assert_eq!(k.d2, sorted[1] as f32);
            assert_eq!(exact[k.best as usize], sorted[0]);
            if i < 20 {
                assert_eq!(k.best as usize, 3 * i);
                assert_eq!(k.d1 as usize, i + 1);
            }
        }
        // The portable body and the dispatched one agree.
        let mut generic = Vec::new();
        knn2_hamming_body(&query, &train, &mut generic);
        assert_eq!(generic, out);

        let f = |x: u64| (x % 1000) as f32 / 1000.0;
        let ftrain: Vec<[f32; 64]> = (0..200)
            .map(|_| std::array::from_fn(|_| f(rng(&mut s))))
            .collect();
        let fquery: Vec<[f32; 64]> = (0..20)
            .map(|i| {
                let mut d = ftrain[5 * i];
                d[i] += 0.01;
                d
            })
            .collect();
        let mut out = Vec::new();
        knn2_l2(&fquery, &ftrain, &mut out);
        for (i, k) in out.iter().enumerate() {
            assert_eq!(k.best as usize, 5 * i);
            assert!((k.d1 - 0.01).abs() < 1e-5, "{}", k.d1);
            assert!(k.d2 > 1.0);
        }
    }

    #[test]
    fn ratio_cross_check_and_kind_errors() {
        let a = [0u64; 4];
        let b = [1u64, 0, 0, 0];
        let c = [3u64, 0, 0, 0];
        let far = [u64::MAX; 4];
        let train = Descriptors::Binary256(vec![a, far]);
        // Query 0 is a (exact), query 1 is b (distance 1 from a, far from the rest): both have a
        // as nearest; cross-check keeps only query 0, whose nearest-back is itself.
        let query = Descriptors::Binary256(vec![a, b, c]);
        let mut scratch = MatchScratch::default();
        let p = MatchParams {
            ratio: 1.0,
            max_distance: 64.0,
            max_distance_l2: 0.4,
            cross_check: false,
        };
        let m = match_descriptors(&query, &train, &p, &mut scratch).expect("same kind");
        assert_eq!(m.len(), 3);
        let p = MatchParams {
            cross_check: true,
            ..p
        };
        let m = match_descriptors(&query, &train, &p, &mut scratch).expect("same kind");
        assert_eq!(
            m,
            vec![Match {
                query: 0,
                train: 0,
                distance: 0.0
            }]
        );
        // Ratio: two equally near train descriptors make the match ambiguous.
        let train2 = Descriptors::Binary256(vec![b, b]);
        let p = MatchParams {
            ratio: 0.8,
            ..MatchParams::default()
        };
        assert!(match_descriptors(&query, &train2, &p, &mut scratch)
            .expect("same kind")
            .is_empty());
        // Distance limit.
        let p = MatchParams {
            ratio: 1.0,
            max_distance: 0.5,
            max_distance_l2: 0.4,
            cross_check: false,
        };
        let m = match_descriptors(&query, &train, &p, &mut scratch).expect("same kind");
        assert_eq!(m.len(), 1);
        let floats = Descriptors::Float64(vec![[0.0; 64]]);
        let e = match_descriptors(&query, &floats, &p, &mut scratch).expect_err("kinds differ");
        assert!(e.contains("binary") && e.contains("float"), "{e}");
        assert!(MatchParams { ratio: 0.0, ..p }.validate().is_err());
    }
}
