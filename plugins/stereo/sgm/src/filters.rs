//! The filters after the selection: left-right check, 3x3 median, speckle removal (also used by
//! `depth.elas`).

use crate::sgm::SgmParams;
use rayon::prelude::*;

/// Left-right check, median and speckle removal on a full disparity image.
pub fn finish(disp: &mut Vec<f32>, right: &[f32], w: usize, h: usize, p: &SgmParams) {
    let mut median = Vec::new();
    finish_with(
        disp,
        right,
        w,
        h,
        p,
        &mut median,
        &mut SpeckleScratch::default(),
    );
}

/// [`finish`] with its buffers kept between calls: `median` receives the filtered image and is
/// swapped with `disp`.
pub(crate) fn finish_with(
    disp: &mut Vec<f32>,
    right: &[f32],
    w: usize,
    h: usize,
    p: &SgmParams,
    median: &mut Vec<f32>,
    speckle: &mut SpeckleScratch,
) {
    if p.lr_check && w > 0 {
        for (row, rrow) in disp.chunks_exact_mut(w).zip(right.chunks_exact(w)) {
            lr_check_row(row, rrow, p.lr_max_diff);
        }
    }
    if p.median {
        median3_into(disp, w, h, median);
        std::mem::swap(disp, median);
    }
    if p.speckle_window > 0 {
        remove_speckles_with(
            disp,
            w,
            h,
            p.speckle_window as usize,
            p.speckle_range,
            speckle,
        );
    }
}

/// The left-right check of one row: a left disparity d at x survives when the right disparity
/// at round(x - d) (half away from zero) lies inside the row, is valid and is within `max_diff`
/// of d. With AVX2, 8 pixels per step (the right disparities by a masked gather).
pub(crate) fn lr_check_row(row: &mut [f32], right: &[f32], max_diff: f32) {
    assert_eq!(row.len(), right.len());
    let mut done = 0;
    #[cfg(target_arch = "x86_64")]
    if crate::simd::avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        done = unsafe { lr_check_avx2(row, right, max_diff) };
    }
    let w = row.len();
    for (x, d) in row.iter_mut().enumerate().skip(done) {
        if !d.is_finite() {
            continue;
        }
        let xr = (x as f32 - *d).round();
        if xr < 0.0 || xr as usize >= w {
            *d = f32::NAN;
            continue;
        }
        let dr = right[xr as usize];
        if !(dr.is_finite() && (dr - *d).abs() <= max_diff) {
            *d = f32::NAN;
        }
    }
}

/// [`lr_check_row`] on the first multiple of 8 pixels; returns how many it did. The rounding
/// is `trunc(v + copysign(0.49999997, v))`, which is `round` (half away from zero) for every
/// float.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn lr_check_avx2(row: &mut [f32], right: &[f32], max_diff: f32) -> usize {
    use std::arch::x86_64::*;
    let w = row.len();
    let n = w / 8 * 8;
    // The row index must fit i32 for the gather; wider rows take the scalar loop.
    if w >= i32::MAX as usize {
        return 0;
    }
    let sign = _mm256_set1_ps(-0.0);
    let half = _mm256_set1_ps(0.5f32.next_down());
    let inf = _mm256_set1_ps(f32::INFINITY);
    let nan = _mm256_set1_ps(f32::NAN);
    let limit = _mm256_set1_ps(max_diff);
    let wv = _mm256_set1_epi32(w as i32);
    let lanes = _mm256_setr_ps(0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0);
    for x0 in (0..n).step_by(8) {
        // SAFETY: x0 + 8 <= n <= row.len(); the gather reads right[xr] only in lanes whose
        // xr lies in 0..w (the mask), and right.len() == w.
        unsafe {
            let d = _mm256_loadu_ps(row.as_ptr().add(x0));
            let finite = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(sign, d), inf);
            let v = _mm256_sub_ps(_mm256_add_ps(_mm256_set1_ps(x0 as f32), lanes), d);
            let r = _mm256_round_ps::<{ _MM_FROUND_TO_ZERO | _MM_FROUND_NO_EXC }>(_mm256_add_ps(
                v,
                _mm256_or_ps(half, _mm256_and_ps(v, sign)),
            ));
            // r is integral; NaN or far out of range in the lanes that are not finite.
            let xr = _mm256_cvttps_epi32(r);
            let inside = _mm256_and_ps(
                finite,
                _mm256_castsi256_ps(_mm256_and_si256(
                    _mm256_cmpgt_epi32(xr, _mm256_set1_epi32(-1)),
                    _mm256_cmpgt_epi32(wv, xr),
                )),
            );
            let dr = _mm256_mask_i32gather_ps::<4>(nan, right.as_ptr(), xr, inside);
            // Ordered compare: false where dr is NaN; |dr - d| is +inf where dr is infinite.
            let close =
                _mm256_cmp_ps::<_CMP_LE_OQ>(_mm256_andnot_ps(sign, _mm256_sub_ps(dr, d)), limit);
            let keep = _mm256_and_ps(
                _mm256_and_ps(inside, close),
                _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_andnot_ps(sign, dr), inf),
            );
            // Non-finite input stays as it was (the scalar loop leaves it untouched).
            let out = _mm256_blendv_ps(nan, d, keep);
            let out = _mm256_blendv_ps(d, out, finite);
            _mm256_storeu_ps(row.as_mut_ptr().add(x0), out);
        }
    }
    n
}

/// The optimal 9-input sorting network (25 compare-exchanges, depth 7): calls `$exch!(i, j)`
/// for each exchange in order (literal indices, so the lanes stay in registers).
macro_rules! sort9 {
    ($exch:ident) => {
        $exch!(0, 3);
        $exch!(1, 7);
        $exch!(2, 5);
        $exch!(4, 8);
        $exch!(0, 7);
        $exch!(2, 4);
        $exch!(3, 8);
        $exch!(5, 6);
        $exch!(0, 2);
        $exch!(1, 3);
        $exch!(4, 5);
        $exch!(7, 8);
        $exch!(1, 4);
        $exch!(3, 6);
        $exch!(5, 7);
        $exch!(0, 1);
        $exch!(2, 4);
        $exch!(3, 5);
        $exch!(6, 8);
        $exch!(2, 3);
        $exch!(4, 5);
        $exch!(6, 7);
        $exch!(1, 2);
        $exch!(3, 4);
        $exch!(5, 6);
    };
}

/// 3x3 median over the valid neighbours of each valid pixel (with an even count, the upper of
/// the two middle values). Inside the image, 8 pixels at a time: the nine neighbours with the
/// invalid ones replaced by +inf go through a 25-exchange sorting network (min/max lanes), so
/// the n valid values lead in order and the median is the one at n / 2. The borders (and the
/// tail of each row) take the sort of the valid values.
pub fn median3(d: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = Vec::new();
    median3_into(d, w, h, &mut out);
    out
}

/// [`median3`] into `out`, reusing its allocation (every pixel is written).
pub fn median3_into(d: &[f32], w: usize, h: usize, out: &mut Vec<f32>) {
    if out.len() != w * h {
        out.clear();
        out.resize(w * h, f32::NAN);
    }
    if w == 0 {
        return;
    }
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        if y == 0 || y + 1 >= h || w < 3 {
            for (x, o) in row.iter_mut().enumerate() {
                *o = median_at(d, w, h, x, y);
            }
            return;
        }
        median_row(d, w, h, y, row);
    });
}

fn median_row(d: &[f32], w: usize, h: usize, y: usize, row: &mut [f32]) {
    #[cfg(target_arch = "x86_64")]
    if crate::simd::avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { median_row_avx2(d, w, h, y, row) };
        return;
    }
    median_row_generic(d, w, h, y, row);
}

/// [`median_row_generic`] in AVX2 registers (the same network, the same selection).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn median_row_avx2(d: &[f32], w: usize, h: usize, y: usize, row: &mut [f32]) {
    use std::arch::x86_64::*;
    let rows = [
        &d[(y - 1) * w..y * w],
        &d[y * w..(y + 1) * w],
        &d[(y + 1) * w..(y + 2) * w],
    ];
    assert!(row.len() == w);
    row[0] = median_at(d, w, h, 0, y);
    let inf = _mm256_set1_ps(f32::INFINITY);
    let abs = _mm256_castsi256_ps(_mm256_set1_epi32(i32::MAX));
    let mut x0 = 1;
    while x0 + MB < w {
        let mut v = [inf; 9];
        let mut n = _mm256_setzero_si256();
        let mut centre_ok = inf;
        for (r, src) in rows.iter().enumerate() {
            for dx in 0..3 {
                // SAFETY: x0 + dx - 1 + MB <= x0 + MB + 1 <= w = src.len().
                let q = unsafe { _mm256_loadu_ps(src.as_ptr().add(x0 + dx - 1)) };
                let ok = _mm256_cmp_ps::<_CMP_LT_OQ>(_mm256_and_ps(q, abs), inf);
                v[r * 3 + dx] = _mm256_blendv_ps(inf, q, ok);
                n = _mm256_sub_epi32(n, _mm256_castps_si256(ok));
                if r == 1 && dx == 1 {
                    centre_ok = ok;
                }
            }
        }
        macro_rules! exch {
            ($i:literal, $j:literal) => {{
                let (p, q) = (v[$i], v[$j]);
                v[$i] = _mm256_min_ps(p, q);
                v[$j] = _mm256_max_ps(p, q);
            }};
        }
        sort9!(exch);
        let k = _mm256_srli_epi32::<1>(n);
        let mut m = v[0];
        for (i, vi) in v.iter().enumerate().take(5).skip(1) {
            let pick = _mm256_castsi256_ps(_mm256_cmpeq_epi32(k, _mm256_set1_epi32(i as i32)));
            m = _mm256_blendv_ps(m, *vi, pick);
        }
        let m = _mm256_blendv_ps(_mm256_set1_ps(f32::NAN), m, centre_ok);
        // SAFETY: x0 + MB < w = row.len().
        unsafe { _mm256_storeu_ps(row.as_mut_ptr().add(x0), m) };
        x0 += MB;
    }
    for (x, o) in row.iter_mut().enumerate().skip(x0) {
        *o = median_at(d, w, h, x, y);
    }
}

/// Pixels per step of the vectorised median.
const MB: usize = 8;

/// One interior row (0 < y < h - 1, w >= 3) of [`median3`].
#[inline(always)]
fn median_row_generic(d: &[f32], w: usize, h: usize, y: usize, row: &mut [f32]) {
    let (a, b, c) = (
        &d[(y - 1) * w..y * w],
        &d[y * w..(y + 1) * w],
        &d[(y + 1) * w..(y + 2) * w],
    );
    row[0] = median_at(d, w, h, 0, y);
    let mut x0 = 1;
    while x0 + MB < w {
        // v[k][l]: neighbour k (row by row) of pixel x0 + l, +inf when invalid.
        let mut v = [[0.0f32; MB]; 9];
        let mut n = [0u32; MB];
        for (r, src) in [a, b, c].into_iter().enumerate() {
            for dx in 0..3 {
                let s: &[f32; MB] = src[x0 + dx - 1..x0 + dx - 1 + MB]
                    .try_into()
                    .unwrap_or_else(|_| unreachable!("a slice of MB elements"));
                for l in 0..MB {
                    let ok = s[l].abs() < f32::INFINITY;
                    v[r * 3 + dx][l] = if ok { s[l] } else { f32::INFINITY };
                    n[l] += u32::from(ok);
                }
            }
        }
        // By value, so the lanes stay in registers (v[i] and v[j] cannot alias).
        #[inline(always)]
        fn cx(p: [f32; MB], q: [f32; MB]) -> ([f32; MB], [f32; MB]) {
            (
                std::array::from_fn(|l| if p[l] < q[l] { p[l] } else { q[l] }),
                std::array::from_fn(|l| if p[l] < q[l] { q[l] } else { p[l] }),
            )
        }
        macro_rules! exch {
            ($i:literal, $j:literal) => {
                (v[$i], v[$j]) = cx(v[$i], v[$j])
            };
        }
        sort9!(exch);
        for l in 0..MB {
            let k = n[l] / 2;
            let mut m = v[0][l];
            for (i, vi) in v.iter().enumerate().take(5).skip(1) {
                m = if k == i as u32 { vi[l] } else { m };
            }
            let centre_ok = b[x0 + l].abs() < f32::INFINITY;
            row[x0 + l] = if centre_ok { m } else { f32::NAN };
        }
        x0 += MB;
    }
    for (x, o) in row.iter_mut().enumerate().skip(x0) {
        *o = median_at(d, w, h, x, y);
    }
}

/// The median of the valid pixels of the 3x3 window at (x, y) (NaN when the centre is invalid).
fn median_at(d: &[f32], w: usize, h: usize, x: usize, y: usize) -> f32 {
    if !d[y * w + x].is_finite() {
        return f32::NAN;
    }
    let mut v = [0.0f32; 9];
    let mut n = 0;
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let q = d[yy * w + xx];
            if q.is_finite() {
                v[n] = q;
                n += 1;
            }
        }
    }
    let v = &mut v[..n];
    v.sort_by(f32::total_cmp);
    v[n / 2]
}

/// Buffers of [`remove_speckles_with`], reused across frames.
#[derive(Default)]
pub struct SpeckleScratch {
    /// Provisional region label of each pixel (NONE where invalid).
    label: Vec<u32>,
    /// Union-find parent of each label (always a smaller or equal label).
    parent: Vec<u32>,
    /// Pixels per region root.
    count: Vec<u32>,
}

/// Invalidates 4-connected regions (neighbours within `range`) smaller than `window` pixels.
pub fn remove_speckles(d: &mut [f32], w: usize, h: usize, window: usize, range: f32) {
    remove_speckles_with(d, w, h, window, range, &mut SpeckleScratch::default());
}

/// Label of an invalid pixel.
const NONE: u32 = u32::MAX;

/// Root of label `l`, halving the path on the way.
#[inline]
fn find(parent: &mut [u32], mut l: u32) -> u32 {
    while parent[l as usize] != l {
        let up = parent[parent[l as usize] as usize];
        parent[l as usize] = up;
        l = up;
    }
    l
}

/// [`remove_speckles`] with buffers kept by the caller: one raster scan labels the regions
/// (each valid pixel joins its left and upper neighbours when within `range`, the two labels
/// merged by union-find), a second counts each region and clears the small ones. The regions are
/// those of a flood fill over the same neighbour relation ([`crate::reference`] keeps one).
pub fn remove_speckles_with(
    d: &mut [f32],
    w: usize,
    h: usize,
    window: usize,
    range: f32,
    s: &mut SpeckleScratch,
) {
    let SpeckleScratch {
        label,
        parent,
        count,
    } = s;
    assert!(d.len() >= w * h);
    label.clear();
    label.resize(w * h, NONE);
    parent.clear();
    let near = |a: f32, b: f32| (a - b).abs() <= range;
    for y in 0..h {
        for x in 0..w {
            let i = y * w + x;
            let v = d[i];
            if !v.is_finite() {
                continue;
            }
            let left = x > 0 && label[i - 1] != NONE && near(v, d[i - 1]);
            let up = y > 0 && label[i - w] != NONE && near(v, d[i - w]);
            label[i] = match (left, up) {
                (false, false) => {
                    let l = parent.len() as u32;
                    parent.push(l);
                    l
                }
                (true, false) => label[i - 1],
                (false, true) => label[i - w],
                (true, true) => {
                    let (a, b) = (label[i - 1], label[i - w]);
                    if a == b {
                        a
                    } else {
                        let (a, b) = (find(parent, a), find(parent, b));
                        let (lo, hi) = (a.min(b), a.max(b));
                        parent[hi as usize] = lo;
                        lo
                    }
                }
            };
        }
    }
    // Every parent is a smaller label: in increasing order each becomes its root.
    for l in 0..parent.len() {
        parent[l] = parent[parent[l] as usize];
    }
    count.clear();
    count.resize(parent.len(), 0);
    for &l in label.iter().filter(|&&l| l != NONE) {
        count[parent[l as usize] as usize] += 1;
    }
    for (v, &l) in d.iter_mut().zip(label.iter()) {
        if l != NONE && (count[parent[l as usize] as usize] as usize) < window {
            *v = f32::NAN;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition: sort the valid values of the window, take the middle (upper) one.
    fn median_reference(d: &[f32], w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                if !d[i].is_finite() {
                    return f32::NAN;
                }
                let mut v = Vec::new();
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                            let q = d[yy as usize * w + xx as usize];
                            if q.is_finite() {
                                v.push(q);
                            }
                        }
                    }
                }
                v.sort_by(f32::total_cmp);
                v[v.len() / 2]
            })
            .collect()
    }

    /// Deterministic values for the tests below.
    fn lcg(seed: &mut u64) -> u32 {
        *seed = seed
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        (*seed >> 33) as u32
    }

    #[test]
    fn union_find_speckles_remove_exactly_the_flood_fill_regions() {
        let mut seed = 7u64;
        let mut removed = 0;
        for case in 0..300 {
            let (w, h) = (1 + case % 23, 1 + (case * 7) % 19);
            // Few levels, so regions meander and merge (U shapes, spirals); some invalid.
            let levels = 2 + case % 4;
            let d: Vec<f32> = (0..w * h)
                .map(|_| match lcg(&mut seed) % 12 {
                    0 => f32::NAN,
                    1 => f32::NEG_INFINITY,
                    k => (k as usize % levels) as f32 * 0.75,
                })
                .collect();
            let (window, range) = (1 + case % 9, [0.0, 0.5, 0.75, 1.6][case % 4]);
            let mut want = d.clone();
            crate::reference::remove_speckles_reference(&mut want, w, h, window, range);
            let mut got = d.clone();
            let mut scratch = SpeckleScratch::default();
            remove_speckles_with(&mut got, w, h, window, range, &mut scratch);
            // Again with the same scratch: nothing may leak between calls.
            let mut again = d.clone();
            remove_speckles_with(&mut again, w, h, window, range, &mut scratch);
            for (i, ((g, a), r)) in got.iter().zip(&again).zip(&want).enumerate() {
                assert!(
                    g.to_bits() == r.to_bits() && a.to_bits() == r.to_bits(),
                    "case {case} ({w}x{h}, window {window}, range {range}) pixel {i}: {g} {a} instead of {r}"
                );
            }
            removed += got
                .iter()
                .zip(&d)
                .filter(|(g, o)| g.is_nan() && o.is_finite())
                .count();
        }
        assert!(
            removed > 1000,
            "the cases remove regions ({removed} pixels)"
        );
    }

    #[test]
    fn the_lane_left_right_check_is_the_scalar_one() {
        let mut seed = 11u64;
        for case in 0..200 {
            let w = 1 + case % 37;
            // Disparities on and around the .5 boundaries, negative ones, huge ones, invalid.
            let draw = |seed: &mut u64| match lcg(seed) % 16 {
                0 => f32::NAN,
                1 => f32::INFINITY,
                2 => -f32::INFINITY,
                3 => (lcg(seed) % 8) as f32 + 0.5,
                4 => ((lcg(seed) % 8) as f32 + 0.5).next_down(),
                5 => -((lcg(seed) % 3) as f32) - 0.5,
                6 => 1e9,
                // At x = 0 these give x - d = -+(0.5 - 2^-25), where rounding by
                // trunc(v + 0.5 sign(v)) would be wrong.
                7 => 0.5f32.next_down(),
                8 => -(0.5f32.next_down()),
                _ => (lcg(seed) % 4000) as f32 / 250.0,
            };
            let left: Vec<f32> = (0..w).map(|_| draw(&mut seed)).collect();
            let right: Vec<f32> = (0..w).map(|_| draw(&mut seed)).collect();
            let max_diff = [0.0, 0.5, 1.0, 3.0][case % 4];
            let mut want = left.clone();
            for (x, d) in want.iter_mut().enumerate() {
                if !d.is_finite() {
                    continue;
                }
                let xr = (x as f32 - *d).round();
                let ok = xr >= 0.0 && (xr as usize) < w && {
                    let dr = right[xr as usize];
                    dr.is_finite() && (dr - *d).abs() <= max_diff
                };
                if !ok {
                    *d = f32::NAN;
                }
            }
            for portable in [false, true] {
                crate::simd::force_portable(portable);
                let mut got = left.clone();
                lr_check_row(&mut got, &right, max_diff);
                crate::simd::force_portable(false);
                for (x, (g, r)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        g.to_bits() == r.to_bits(),
                        "case {case} x {x}: {g} instead of {r} (left {}, portable {portable})",
                        left[x]
                    );
                }
            }
        }
    }

    #[test]
    fn the_nine_input_network_sorts_every_zero_one_input() {
        // The 0-1 principle: a comparator network that sorts all 2^9 binary inputs sorts all.
        for bits in 0u32..512 {
            let mut v: [u8; 9] = std::array::from_fn(|i| ((bits >> i) & 1) as u8);
            macro_rules! exch {
                ($i:literal, $j:literal) => {{
                    let (p, q) = (v[$i], v[$j]);
                    v[$i] = p.min(q);
                    v[$j] = p.max(q);
                }};
            }
            sort9!(exch);
            assert!(v.windows(2).all(|p| p[0] <= p[1]), "{bits:09b} -> {v:?}");
        }
    }

    #[test]
    fn the_median_network_and_the_holes_match_the_sorted_definition() {
        let mut seed = 12345u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as u32
        };
        for (w, h) in [
            (1, 1),
            (2, 5),
            (3, 3),
            (9, 3),
            (10, 4),
            (17, 9),
            (64, 31),
            (203, 40),
        ] {
            // Few distinct values (ties), a tenth invalid (NaN and infinities).
            let d: Vec<f32> = (0..w * h)
                .map(|_| match next() % 20 {
                    0 => f32::NAN,
                    1 => f32::INFINITY,
                    k => (k % 7) as f32 * 0.5 + (next() % 3) as f32 * 0.25,
                })
                .collect();
            let want = median_reference(&d, w, h);
            // The AVX2 kernel (where the CPU has it) and the portable one.
            for portable in [false, true] {
                crate::simd::force_portable(portable);
                let got = median3(&d, w, h);
                // Into a reused buffer of the right size holding stale values: every pixel is
                // written, so the result is the same.
                let mut reused = vec![123.0f32; w * h];
                median3_into(&d, w, h, &mut reused);
                crate::simd::force_portable(false);
                for (i, (g, r)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        g.to_bits() == r.to_bits(),
                        "{w}x{h} pixel {i}: {g} instead of {r} (portable {portable})"
                    );
                }
                assert!(
                    reused
                        .iter()
                        .zip(&got)
                        .all(|(a, b)| a.to_bits() == b.to_bits()),
                    "{w}x{h}: a reused buffer kept stale pixels (portable {portable})"
                );
            }
        }
    }
}
