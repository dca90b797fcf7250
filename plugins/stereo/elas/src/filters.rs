//! ELAS post-processing (step 6) on disparity maps with NaN for invalid pixels: left-right
//! check, gap interpolation, the adaptive mean and the separable median of libelas. Small
//! segments are removed by [`misslam_depth_sgm::sgm::remove_speckles_with`].

/// Invalidates left pixels whose right partner (at u - d, rounded) disagrees by more than
/// `threshold`, and (if `both`) right pixels whose left partner (u + d) does. Both checks read
/// the maps as they were before either changed (`tmp` keeps the right map's copy when both
/// change).
pub fn lr_check(
    left: &mut [f32],
    right: &mut [f32],
    w: usize,
    threshold: f32,
    both: bool,
    tmp: &mut Vec<f32>,
) {
    if !both {
        check_rows(left, right, w, threshold, -1.0);
        return;
    }
    tmp.clear();
    tmp.extend_from_slice(right);
    check_rows(right, left, w, threshold, 1.0);
    check_rows(left, tmp, w, threshold, -1.0);
}

/// Invalidates pixels of `own` whose partner in `other` (at u + sign * d) disagrees; rows on
/// rayon's threads.
fn check_rows(own: &mut [f32], other: &[f32], w: usize, threshold: f32, sign: f32) {
    use rayon::prelude::*;
    own.par_chunks_mut(w)
        .zip(other.par_chunks(w))
        .for_each(|(row, orow)| {
            for (x, d) in row.iter_mut().enumerate() {
                if !d.is_finite() {
                    continue;
                }
                // `(x + sign d).round()` as an integer, without the library call.
                let xo = crate::dense::round_i32(x as f32 + sign * *d);
                let ok = xo >= 0 && (xo as usize) < w && {
                    let e = orow[xo as usize];
                    e.is_finite() && (e - *d).abs() <= threshold
                };
                if !ok {
                    *d = f32::NAN;
                }
            }
        });
}

/// Interpolation across a disparity step larger than this takes the smaller disparity (the
/// background), as in libelas.
const DISCONTINUITY: f32 = 3.0;

/// Fills runs of at most `gap` invalid pixels between two valid ones, first along rows, then
/// along columns: the mean of the two ends, or the smaller end across a discontinuity. With
/// `extrapolate`, also copies the first and last valid value up to `gap` pixels towards the
/// border (libelas does this with `add_corners`).
pub fn gap_interpolation(d: &mut [f32], w: usize, h: usize, gap: usize, extrapolate: bool) {
    fill_lines(d, w, h, 1, w, gap, extrapolate);
    fill_lines(d, h, w, w, 1, gap, extrapolate);
}

/// One pass of [`gap_interpolation`]: `lines` lines of `len` pixels, pixel i of line k at
/// `k * line_stride + i * stride`.
fn fill_lines(
    d: &mut [f32],
    len: usize,
    lines: usize,
    stride: usize,
    line_stride: usize,
    gap: usize,
    extrapolate: bool,
) {
    for k in 0..lines {
        let at = |i: usize| k * line_stride + i * stride;
        let mut count = 0;
        for i in 0..len {
            if d[at(i)].is_finite() {
                if count >= 1 && count <= gap && i > count {
                    let (first, last) = (i - count, i - 1);
                    let (d1, d2) = (d[at(first - 1)], d[at(last + 1)]);
                    let fill = if (d1 - d2).abs() < DISCONTINUITY {
                        0.5 * (d1 + d2)
                    } else {
                        d1.min(d2)
                    };
                    for j in first..=last {
                        d[at(j)] = fill;
                    }
                }
                count = 0;
            } else {
                count += 1;
            }
        }
        if extrapolate {
            if let Some(i) = (0..len).find(|&i| d[at(i)].is_finite()) {
                let v = d[at(i)];
                for j in i.saturating_sub(gap)..i {
                    d[at(j)] = v;
                }
            }
            if let Some(i) = (0..len).rev().find(|&i| d[at(i)].is_finite()) {
                let v = d[at(i)];
                for j in i + 1..=(i + gap).min(len - 1) {
                    d[at(j)] = v;
                }
            }
        }
    }
}

/// Stand-in for an invalid pixel inside the filters: at least 9.5 from any valid disparity
/// (valid ones are >= -0.5), so it weighs nothing in the adaptive mean and sorts first in the
/// median, as libelas's -10 does.
const INVALID: f32 = -10.0;

fn to_sentinel(d: &[f32], buf: &mut Vec<f32>) {
    buf.clear();
    buf.extend(d.iter().map(|&v| if v.is_finite() { v } else { INVALID }));
}

/// libelas's adaptive mean: a separable 8-tap filter (offsets -4..=3) whose weights are
/// `max(0, 4 - |d_i - d_centre|)`, so it smooths within a surface and stops at steps. Invalid
/// pixels weigh nothing and stay invalid; pixels within 4 of the border keep the other pass's
/// value.
pub fn adaptive_mean(d: &mut [f32], w: usize, h: usize, buf: &mut Vec<f32>) {
    use rayon::prelude::*;
    // Rows on rayon's threads, each with its own sums.
    let sums = || (vec![0f32; w], vec![0f32; w]);
    // Horizontal: tap k of pixel x is x - 4 + k.
    to_sentinel(d, buf);
    if w >= 8 {
        d.par_chunks_mut(w)
            .zip(buf.par_chunks(w))
            .for_each_init(sums, |(ws, fs), (row, src)| {
                let n = w - 7;
                let centre = &src[4..4 + n];
                ws[..n].fill(0.0);
                fs[..n].fill(0.0);
                for k in 0..8 {
                    let tap = &src[k..k + n];
                    for (((a, b), &v), &c) in
                        ws[..n].iter_mut().zip(&mut fs[..n]).zip(tap).zip(centre)
                    {
                        let wt = (4.0 - (v - c).abs()).max(0.0);
                        *a += wt;
                        *b += wt * v;
                    }
                }
                for (((o, &c), &a), &b) in row[4..4 + n].iter_mut().zip(centre).zip(&*ws).zip(&*fs)
                {
                    if c != INVALID {
                        *o = b / a;
                    }
                }
            });
    }
    // Vertical, row by row: tap k of row y is row y - 4 + k.
    to_sentinel(d, buf);
    if h >= 8 {
        let buf = &*buf;
        d.par_chunks_mut(w)
            .enumerate()
            .filter(|(y, _)| (4..h - 3).contains(y))
            .for_each_init(sums, |(ws, fs), (y, row)| {
                let centre = &buf[y * w..(y + 1) * w];
                ws.fill(0.0);
                fs.fill(0.0);
                for k in 0..8 {
                    let tap = &buf[(y - 4 + k) * w..(y - 3 + k) * w];
                    for (((a, b), &v), &c) in ws.iter_mut().zip(fs.iter_mut()).zip(tap).zip(centre)
                    {
                        let wt = (4.0 - (v - c).abs()).max(0.0);
                        *a += wt;
                        *b += wt * v;
                    }
                }
                for (((o, &c), &a), &b) in row.iter_mut().zip(centre).zip(&*ws).zip(&*fs) {
                    if c != INVALID {
                        *o = b / a;
                    }
                }
            });
    }
}

/// libelas's median: a separable 7-tap median on valid centres, invalid neighbours counted as
/// -10 (so a centre with four invalid neighbours becomes invalid).
pub fn median(d: &mut [f32], w: usize, h: usize, buf: &mut Vec<f32>) {
    fn med7(mut v: [f32; 7]) -> f32 {
        for i in 1..7 {
            let mut j = i;
            while j > 0 && v[j - 1] > v[j] {
                v.swap(j - 1, j);
                j -= 1;
            }
        }
        if v[3] >= 0.0 {
            v[3]
        } else {
            f32::NAN
        }
    }
    to_sentinel(d, buf);
    if w >= 7 {
        for (row, src) in d.chunks_mut(w).zip(buf.chunks(w)) {
            for x in 3..w - 3 {
                if src[x] != INVALID {
                    let t = &src[x - 3..x + 4];
                    row[x] = med7([t[0], t[1], t[2], t[3], t[4], t[5], t[6]]);
                }
            }
        }
    }
    to_sentinel(d, buf);
    if h >= 7 {
        for y in 3..h - 3 {
            let rows: [&[f32]; 7] = std::array::from_fn(|k| &buf[(y - 3 + k) * w..(y - 2 + k) * w]);
            for (x, o) in d[y * w..(y + 1) * w].iter_mut().enumerate() {
                if rows[3][x] != INVALID {
                    *o = med7(std::array::from_fn(|k| rows[k][x]));
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;
    const N: f32 = f32::NAN;

    fn same(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        for (i, (x, y)) in a.iter().zip(b).enumerate() {
            assert!(
                x.to_bits() == y.to_bits() || (x - y).abs() < 1e-6,
                "{i}: {x} vs {y}"
            );
        }
    }

    #[test]
    fn lr_check_keeps_agreeing_pixels_only() {
        // Left pixel 3 with d = 2 meets right pixel 1 (d = 2): kept. Left 4 (d = 2) meets right 2
        // (d = 5): dropped. Left 0 with d = 1 points outside: dropped.
        let mut l = vec![1.0, N, N, 2.0, 2.0, N];
        let mut r = vec![N, 2.0, 5.0, N, N, N];
        lr_check(&mut l, &mut r, 6, 2.0, true, &mut Vec::new());
        same(&l, &[N, N, N, 2.0, N, N]);
        // Right pixel 1 (d 2) meets left 3 (d 2): kept; right 2 (d 5) meets left 7: outside.
        same(&r, &[N, 2.0, N, N, N, N]);
    }

    #[test]
    fn gaps_are_filled_by_the_mean_or_the_background() {
        let mut d = vec![10.0, N, N, 12.0, N, 20.0, N, N, N, N, 5.0];
        gap_interpolation(&mut d, 11, 1, 3, false);
        // 10..12: mean 11. 12..20: a step, the background 12. The run of 4 is too long.
        same(&d, &[10.0, 11.0, 11.0, 12.0, 12.0, 20.0, N, N, N, N, 5.0]);
        let mut d = vec![N, N, 7.0, N, N];
        gap_interpolation(&mut d, 5, 1, 1, true);
        same(&d, &[N, 7.0, 7.0, 7.0, N]);
    }

    #[test]
    fn adaptive_mean_smooths_within_a_surface_and_keeps_steps() {
        let w = 16;
        // Alternating 10 / 11 on the left half, 30 on the right half.
        let mut d: Vec<f32> = (0..w)
            .map(|x| if x < 8 { 10.0 + (x % 2) as f32 } else { 30.0 })
            .collect();
        adaptive_mean(&mut d, w, 1, &mut Vec::new());
        // Pixel 5 (11): window 1..=8 holds four 11s (weight 4), three 10s (weight 3) and a 30
        // (weight 0): (4 * 4 * 11 + 3 * 3 * 10) / 25.
        assert!((d[5] - 266.0 / 25.0).abs() < 1e-5, "{}", d[5]);
        assert_eq!(d[9], 30.0, "the step does not leak");
        assert_eq!(d[0], 10.0, "the border is left alone");
    }

    /// A seeded map of 37 x 23 with surfaces, steps and invalid pixels.
    fn random_map(w: usize, h: usize) -> Vec<f32> {
        let mut st = 0x1234_5678u32;
        (0..w * h)
            .map(|i| {
                st ^= st << 13;
                st ^= st >> 17;
                st ^= st << 5;
                if st.is_multiple_of(7) {
                    N
                } else {
                    let base = if (i % w) < w / 2 { 12.0 } else { 30.0 };
                    base + (st % 300) as f32 / 100.0
                }
            })
            .collect()
    }

    #[test]
    fn adaptive_mean_and_lr_check_on_rows_in_parallel_match_the_definition() {
        let (w, h) = (37, 23);
        let d = random_map(w, h);
        // The definition, pixel by pixel: horizontal then vertical, invalid pixels at INVALID.
        let sent = |v: f32| if v.is_finite() { v } else { INVALID };
        let pass = |src: &[f32], at: &dyn Fn(usize, usize, usize) -> usize, lines, len| {
            let mut out = src.to_vec();
            for line in 0..lines {
                for i in 4..len - 3 {
                    let c = sent(src[at(line, i, 0)]);
                    if c == INVALID {
                        continue;
                    }
                    let (mut a, mut b) = (0f32, 0f32);
                    for k in 0..8 {
                        let v = sent(src[at(line, i + k, 4)]);
                        let wt = (4.0 - (v - c).abs()).max(0.0);
                        a += wt;
                        b += wt * v;
                    }
                    out[at(line, i, 0)] = b / a;
                }
            }
            out
        };
        let horizontal = pass(&d, &|y, x, back| y * w + x - back, h, w);
        let want = pass(&horizontal, &|x, y, back| (y - back) * w + x, w, h);
        let mut got = d.clone();
        adaptive_mean(&mut got, w, h, &mut Vec::new());
        same(&got, &want);
        // The left-right check against its definition on every row.
        let right = random_map(w, h);
        let mut want = d.clone();
        for y in 0..h {
            for x in 0..w {
                let v = d[y * w + x];
                if !v.is_finite() {
                    continue;
                }
                let xo = (x as f32 - v).round();
                let ok = xo >= 0.0
                    && (xo as usize) < w
                    && right[y * w + xo as usize].is_finite()
                    && (right[y * w + xo as usize] - v).abs() <= 2.0;
                if !ok {
                    want[y * w + x] = N;
                }
            }
        }
        let (mut l, mut r) = (d.clone(), right.clone());
        lr_check(&mut l, &mut r, w, 2.0, false, &mut Vec::new());
        same(&l, &want);
        assert!(
            want.iter().filter(|v| v.is_finite()).count() > 20,
            "the case tests nothing"
        );
    }

    #[test]
    fn vertical_passes_match_the_horizontal_ones_on_a_column() {
        // A 1-pixel-wide column skips the horizontal pass (too narrow), so the vertical pass
        // alone must give what the horizontal pass gives on the same values as a row.
        let row: Vec<f32> = vec![
            10.0, 11.0, N, 11.0, 10.0, 11.0, 10.0, 30.0, 30.0, 31.0, 30.0, 12.0,
        ];
        let n = row.len();
        for filter in [adaptive_mean, median] {
            let (mut r, mut c) = (row.clone(), row.clone());
            filter(&mut r, n, 1, &mut Vec::new());
            filter(&mut c, 1, n, &mut Vec::new());
            same(&c, &r);
            assert!(
                r.iter()
                    .zip(&row)
                    .any(|(a, b)| a.is_finite() && b.is_finite() && a != b),
                "the filter changed nothing: the case tests nothing"
            );
        }
    }

    #[test]
    fn median_removes_a_spike_and_invalid_majority_invalidates() {
        let mut d = vec![5.0, 5.0, 5.0, 50.0, 5.0, 5.0, 5.0];
        median(&mut d, 7, 1, &mut Vec::new());
        same(&d, &[5.0, 5.0, 5.0, 5.0, 5.0, 5.0, 5.0]);
        let mut d = vec![N, N, N, 5.0, N, 5.0, 5.0];
        median(&mut d, 7, 1, &mut Vec::new());
        assert!(d[3].is_nan());
    }
}
