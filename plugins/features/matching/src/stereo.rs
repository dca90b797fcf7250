//! Stereo matching of keypoints on a rectified pair (as ORB-SLAM2's stereo front end does):
//! each left keypoint is compared with the right keypoints on its row band and inside the
//! disparity range, the best descriptor wins, and its disparity is refined to sub-pixel by SAD
//! block matching along the row with an equiangular (V) fit through the three lowest costs. The 3D point
//! follows from the calibration.

use misslam_framework::{Descriptors, Keypoint, Match, Matches, StereoCalib};

use crate::distance;

/// Parameters of [`stereo_match`].
#[derive(
    Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(deny_unknown_fields, default)]
pub struct StereoParams {
    /// Smallest disparity searched, pixels.
    pub min_disparity: f32,
    /// Largest disparity searched, pixels.
    pub max_disparity: f32,
    /// Half height of the row band, pixels, for a keypoint of size 31; it grows in proportion to
    /// the keypoint's size (coarser pyramid levels localise less precisely).
    pub row_tolerance_px: f32,
    /// Largest accepted Hamming distance of binary descriptors, bits.
    pub max_distance: f32,
    /// Largest accepted L2 distance of float descriptors.
    pub max_distance_l2: f32,
    /// Ratio of best to second-best distance on the band; 1 disables the test.
    pub ratio: f32,
    /// Largest difference of pyramid level between the two keypoints.
    pub max_octave_gap: i32,
    /// Half size of the SAD window of the sub-pixel refinement (5 gives 11x11); 0 disables
    /// the refinement (the disparity is then the keypoints' x difference).
    pub refine_half_window: u32,
    /// The refinement searches +-this many pixels around the keypoint match.
    pub refine_range_px: u32,
    /// A match whose SAD exceeds this factor times the median SAD is dropped (ORB-SLAM uses
    /// 1.5 x 1.4 = 2.1); 0 disables the test.
    pub sad_outlier_factor: f32,
}

impl Default for StereoParams {
    fn default() -> Self {
        StereoParams {
            min_disparity: 0.0,
            max_disparity: 128.0,
            row_tolerance_px: 2.0,
            max_distance: 75.0,
            max_distance_l2: 0.3,
            ratio: 0.9,
            max_octave_gap: 1,
            refine_half_window: 5,
            refine_range_px: 5,
            sad_outlier_factor: 2.1,
        }
    }
}

impl StereoParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if !(self.min_disparity >= 0.0 && self.max_disparity > self.min_disparity) {
            return Err(format!(
                "`min_disparity` ({}) must be >= 0 and below `max_disparity` ({})",
                self.min_disparity, self.max_disparity
            ));
        }
        if self.row_tolerance_px.is_nan() || self.row_tolerance_px < 0.0 {
            return Err(format!(
                "`row_tolerance_px` must be >= 0, got {}",
                self.row_tolerance_px
            ));
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
        if !(self.ratio > 0.0 && self.ratio <= 1.0) {
            return Err(format!("`ratio` must lie in (0, 1], got {}", self.ratio));
        }
        if self.refine_half_window > 15 || self.refine_range_px > 32 {
            return Err(format!(
                "`refine_half_window` ({}) must be <= 15 and `refine_range_px` ({}) <= 32",
                self.refine_half_window, self.refine_range_px
            ));
        }
        if self.sad_outlier_factor.is_nan() || self.sad_outlier_factor < 0.0 {
            return Err(format!(
                "`sad_outlier_factor` must be >= 0, got {}",
                self.sad_outlier_factor
            ));
        }
        Ok(())
    }
}

/// A gray image borrowed for the refinement.
#[derive(Clone, Copy, Debug)]
pub struct GrayView<'a> {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Row-major bytes.
    pub data: &'a [u8],
}

/// One stereo match: a left keypoint, its right keypoint, the refined disparity.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct StereoMatch {
    /// Left keypoint index.
    pub left: u32,
    /// Right keypoint index.
    pub right: u32,
    /// Disparity `x_left - x_right`, pixels.
    pub disparity: f32,
    /// Descriptor distance.
    pub distance: f32,
}

/// Reusable buffers of [`stereo_match`].
#[derive(Default)]
pub struct StereoScratch {
    row_starts: Vec<u32>,
    row_items: Vec<u32>,
    sads: Vec<f32>,
}

/// Matches left keypoints to right keypoints of a rectified pair; at most one match per left
/// keypoint, sorted by left index. `left_img` and `right_img` are needed only for the refinement.
#[allow(clippy::too_many_arguments)]
pub fn stereo_match(
    left: &[Keypoint],
    left_desc: &Descriptors,
    right: &[Keypoint],
    right_desc: &Descriptors,
    left_img: GrayView,
    right_img: GrayView,
    params: &StereoParams,
    scratch: &mut StereoScratch,
) -> Vec<StereoMatch> {
    let h = left_img.height;
    // Right keypoints binned by every row their band covers.
    let band = |k: &Keypoint| params.row_tolerance_px * (k.size / 31.0).max(1.0);
    let rows_of = |k: &Keypoint| -> Option<(usize, usize)> {
        if !(k.x.is_finite() && k.y.is_finite()) {
            return None;
        }
        let r = band(k);
        let lo = (k.y - r).floor().max(0.0) as usize;
        let hi = ((k.y + r).ceil() as i64).min(h as i64 - 1);
        (hi >= lo as i64).then_some((lo, hi as usize))
    };
    let starts = &mut scratch.row_starts;
    starts.clear();
    starts.resize(h + 1, 0);
    for k in right {
        if let Some((lo, hi)) = rows_of(k) {
            for y in lo..=hi {
                starts[y + 1] += 1;
            }
        }
    }
    for y in 0..h {
        starts[y + 1] += starts[y];
    }
    let items = &mut scratch.row_items;
    items.clear();
    items.resize(starts[h] as usize, 0);
    let mut fill: Vec<u32> = starts[..h].to_vec();
    for (j, k) in right.iter().enumerate() {
        if let Some((lo, hi)) = rows_of(k) {
            for f in &mut fill[lo..=hi] {
                items[*f as usize] = j as u32;
                *f += 1;
            }
        }
    }

    let limit = crate::distance_limit(left_desc, params.max_distance, params.max_distance_l2);
    let mut out = Vec::new();
    scratch.sads.clear();
    for (i, kl) in left.iter().enumerate() {
        if !(kl.x.is_finite() && kl.y.is_finite()) || kl.y < 0.0 || kl.y >= h as f32 {
            continue;
        }
        let y = kl.y.round().min(h as f32 - 1.0) as usize;
        let (mut d1, mut d2, mut arg) = (f32::INFINITY, f32::INFINITY, u32::MAX);
        for &j in &items[starts[y] as usize..starts[y + 1] as usize] {
            let kr = &right[j as usize];
            if (kr.octave - kl.octave).abs() > params.max_octave_gap {
                continue;
            }
            // The band of the coarser of the two.
            if (kr.y - kl.y).abs() > band(kl).max(band(kr)) {
                continue;
            }
            let disp = kl.x - kr.x;
            if disp < params.min_disparity || disp > params.max_disparity {
                continue;
            }
            let d = distance(left_desc, i, right_desc, j as usize);
            if d < d1 {
                d2 = d1;
                d1 = d;
                arg = j;
            } else if d < d2 {
                d2 = d;
            }
        }
        if arg == u32::MAX || d1 > limit {
            continue;
        }
        if params.ratio < 1.0 && d2.is_finite() && d1 >= params.ratio * d2 {
            continue;
        }
        let kr = &right[arg as usize];
        let (disparity, sad) = if params.refine_half_window > 0 {
            match refine(kl, kr, left_img, right_img, params) {
                Some(r) => r,
                None => continue,
            }
        } else {
            (kl.x - kr.x, 0.0)
        };
        if disparity < params.min_disparity || disparity > params.max_disparity {
            continue;
        }
        out.push(StereoMatch {
            left: i as u32,
            right: arg,
            disparity,
            distance: d1,
        });
        scratch.sads.push(sad);
    }
    if params.refine_half_window > 0 && params.sad_outlier_factor > 0.0 && !out.is_empty() {
        let mut sorted = scratch.sads.clone();
        let mid = sorted.len() / 2;
        let median = *sorted.select_nth_unstable_by(mid, f32::total_cmp).1;
        let limit = params.sad_outlier_factor * median.max(1.0);
        let sads = &scratch.sads;
        let mut k = 0;
        out.retain(|_| {
            let keep = sads[k] <= limit;
            k += 1;
            keep
        });
    }
    out
}

/// Sub-pixel disparity by SAD along the row (intensities relative to each window's centre, so a
/// brightness offset between the cameras does not matter), and the lowest SAD per pixel.
fn refine(
    kl: &Keypoint,
    kr: &Keypoint,
    left: GrayView,
    right: GrayView,
    p: &StereoParams,
) -> Option<(f32, f32)> {
    let w = p.refine_half_window as i64;
    let range = p.refine_range_px as i64;
    let (xl, yl) = (kl.x.round() as i64, kl.y.round() as i64);
    let xr0 = kr.x.round() as i64;
    let inside = |x: i64, y: i64, img: &GrayView| {
        x - w >= 0 && y - w >= 0 && x + w < img.width as i64 && y + w < img.height as i64
    };
    if !inside(xl, yl, &left)
        || !inside(xr0 - range, yl, &right)
        || !inside(xr0 + range, yl, &right)
    {
        return None;
    }
    let at = |img: &GrayView, x: i64, y: i64| img.data[y as usize * img.width + x as usize] as i32;
    let cl = at(&left, xl, yl);
    let mut costs = [0f32; 65];
    let n = (2 * range + 1) as usize;
    for (k, cost) in costs[..n].iter_mut().enumerate() {
        let xr = xr0 - range + k as i64;
        let cr = at(&right, xr, yl);
        let mut s = 0i32;
        for dy in -w..=w {
            let rl = ((yl + dy) as usize * left.width) as i64;
            let rr = ((yl + dy) as usize * right.width) as i64;
            for dx in -w..=w {
                let a = left.data[(rl + xl + dx) as usize] as i32 - cl;
                let b = right.data[(rr + xr + dx) as usize] as i32 - cr;
                s += (a - b).abs();
            }
        }
        *cost = s as f32;
    }
    let (best, &c1) = costs[..n]
        .iter()
        .enumerate()
        .min_by(|a, b| a.1.total_cmp(b.1))?;
    if best == 0 || best == n - 1 {
        // The minimum lies on the edge of the search: no reliable sub-pixel position.
        return None;
    }
    // SAD is V-shaped around its minimum: the equiangular line fit (Shimizu and Okutomi 2001)
    // is unbiased there, where a parabola pulls the estimate towards the integer pixel.
    let (c0, c2) = (costs[best - 1], costs[best + 1]);
    let denom = 2.0 * (c0.max(c2) - c1);
    let delta = if denom > 0.0 { (c0 - c2) / denom } else { 0.0 };
    if !(-1.0..=1.0).contains(&delta) {
        return None;
    }
    let xr = (xr0 - range + best as i64) as f32 + delta;
    Some((xl as f32 - xr, c1))
}

/// Stereo matches of a rectified pair turned into what a feature node outputs: per left
/// keypoint its camera-frame 3D point (NaN without a match), and the matches (query = left,
/// train = right) with the left 3D points.
#[allow(clippy::too_many_arguments)]
pub fn stereo_points(
    left: &[Keypoint],
    left_desc: &Descriptors,
    right: &[Keypoint],
    right_desc: &Descriptors,
    left_img: GrayView,
    right_img: GrayView,
    calib: &StereoCalib,
    params: &StereoParams,
    scratch: &mut StereoScratch,
) -> (Vec<[f32; 3]>, Matches) {
    let sm = stereo_match(
        left, left_desc, right, right_desc, left_img, right_img, params, scratch,
    );
    let mut points = vec![[f32::NAN; 3]; left.len()];
    let mut matches = Matches::default();
    for m in &sm {
        let kl = &left[m.left as usize];
        let kr = &right[m.right as usize];
        let p3 = triangulate(calib, kl.x, kl.y, m.disparity);
        points[m.left as usize] = p3;
        matches.pairs.push(Match {
            query: m.left,
            train: m.right,
            distance: m.distance,
        });
        matches.query_xy.push([kl.x, kl.y]);
        matches.train_xy.push([kr.x, kr.y]);
        matches.query_points.push(p3);
    }
    (points, matches)
}

/// The 3D point in the left camera frame (mm) of pixel (x, y) at `disparity`; NaN when the
/// disparity gives no positive depth.
pub fn triangulate(calib: &StereoCalib, x: f32, y: f32, disparity: f32) -> [f32; 3] {
    let z = calib.depth_from_disparity(disparity) as f64;
    if !z.is_finite() {
        return [f32::NAN; 3];
    }
    [
        ((x as f64 - calib.cx) * z / calib.fx) as f32,
        ((y as f64 - calib.cy) * z / calib.fy) as f32,
        z as f32,
    ]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kp(x: f32, y: f32, octave: i32) -> Keypoint {
        Keypoint {
            x,
            y,
            size: 31.0,
            angle: 0.0,
            response: 1.0,
            octave,
        }
    }

    /// A smooth random texture, and its copy shifted right by `shift` pixels (fractional:
    /// linear interpolation of a texture smooth enough for it to be exact to ~0.05 px).
    fn textured_pair(w: usize, h: usize, shift: f32) -> (Vec<u8>, Vec<u8>) {
        let f = |x: f32, y: f32| {
            let v = 128.0
                + 50.0 * (0.31 * x + 0.17 * y).sin()
                + 40.0 * (0.23 * x - 0.29 * y + 1.0).cos()
                + 25.0 * (0.11 * x * 0.7 + 0.41 * y).sin();
            v.clamp(0.0, 255.0)
        };
        let left: Vec<u8> = (0..w * h)
            .map(|i| f((i % w) as f32, (i / w) as f32).round() as u8)
            .collect();
        // right(x) = left(x + shift): a point at left x appears at x - shift on the right.
        let right: Vec<u8> = (0..w * h)
            .map(|i| f((i % w) as f32 + shift, (i / w) as f32).round() as u8)
            .collect();
        (left, right)
    }

    #[test]
    fn matches_on_the_row_band_and_refines_to_sub_pixel() {
        let (w, h) = (160usize, 120usize);
        let shift = 12.4f32;
        let (li, ri) = textured_pair(w, h, shift);
        let d = |b: u64| [b, !b, b.rotate_left(7), b ^ 0x5555];
        let left = vec![kp(60.0, 50.0, 0), kp(90.0, 70.0, 0), kp(100.0, 30.0, 0)];
        // Right: the true partners at x - 12 (integer detection), a decoy with the same
        // descriptor on another row, and a decoy outside the disparity range.
        let right = vec![
            kp(48.0, 50.0, 0),
            kp(78.0, 70.3, 1),
            kp(88.0, 90.0, 0), // same descriptor as left 2, wrong row
            kp(99.0, 30.0, 0), // same descriptor as left 2, disparity 1 < min 2
        ];
        let ld = Descriptors::Binary256(vec![d(1), d(2), d(3)]);
        let rd = Descriptors::Binary256(vec![d(1), d(2), d(3), d(3)]);
        let p = StereoParams {
            min_disparity: 2.0,
            max_disparity: 40.0,
            sad_outlier_factor: 0.0,
            ..StereoParams::default()
        };
        fn view(d: &[u8]) -> GrayView<'_> {
            GrayView {
                width: 160,
                height: 120,
                data: d,
            }
        }
        let mut scratch = StereoScratch::default();
        let m = stereo_match(
            &left,
            &ld,
            &right,
            &rd,
            view(&li),
            view(&ri),
            &p,
            &mut scratch,
        );
        assert_eq!(m.len(), 2, "{m:?}");
        assert_eq!((m[0].left, m[0].right), (0, 0));
        assert_eq!((m[1].left, m[1].right), (1, 1));
        for s in &m {
            assert!(
                (s.disparity - shift).abs() < 0.1,
                "refined disparity {} vs {shift}",
                s.disparity
            );
        }
        // Without refinement the disparity is the keypoints' difference.
        let p0 = StereoParams {
            refine_half_window: 0,
            ..p
        };
        let m = stereo_match(
            &left,
            &ld,
            &right,
            &rd,
            view(&li),
            view(&ri),
            &p0,
            &mut scratch,
        );
        assert_eq!(m[0].disparity, 12.0);
    }

    #[test]
    fn triangulation_inverts_projection() {
        let calib = StereoCalib {
            width: 640,
            height: 480,
            fx: 700.0,
            fy: 710.0,
            cx: 320.0,
            cy: 240.0,
            cx_right: 320.0,
            baseline_mm: 5.0,
        };
        let p = triangulate(&calib, 400.0, 100.0, 35.0);
        assert!((p[2] - 100.0).abs() < 1e-4);
        assert!((p[0] as f64 - 80.0 * 100.0 / 700.0).abs() < 1e-4);
        assert!((p[1] as f64 + 140.0 * 100.0 / 710.0).abs() < 1e-4);
        assert!(triangulate(&calib, 1.0, 1.0, -3.0)[2].is_nan());
        assert!(StereoParams {
            max_disparity: -1.0,
            ..StereoParams::default()
        }
        .validate()
        .is_err());
    }
}
