//! The filters after the selection: left-right check, 3x3 median, speckle removal (also used by
//! `depth.elas`).

use crate::sgm::SgmParams;
use rayon::prelude::*;

/// Left-right check, median and speckle removal on a full disparity image.
pub fn finish(disp: &mut Vec<f32>, right: &[f32], w: usize, h: usize, p: &SgmParams) {
    finish_with(disp, right, w, h, p, &mut SpeckleScratch::default());
}

pub(crate) fn finish_with(
    disp: &mut Vec<f32>,
    right: &[f32],
    w: usize,
    h: usize,
    p: &SgmParams,
    speckle: &mut SpeckleScratch,
) {
    if p.lr_check && w > 0 {
        for (row, rrow) in disp.chunks_exact_mut(w).zip(right.chunks_exact(w)) {
            for (x, d) in row.iter_mut().enumerate() {
                if !d.is_finite() {
                    continue;
                }
                let xr = (x as f32 - *d).round();
                if xr < 0.0 || xr as usize >= w {
                    *d = f32::NAN;
                    continue;
                }
                let dr = rrow[xr as usize];
                if !(dr.is_finite() && (dr - *d).abs() <= p.lr_max_diff) {
                    *d = f32::NAN;
                }
            }
        }
    }
    if p.median {
        *disp = median3(disp, w, h);
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
    let mut out = vec![f32::NAN; w * h];
    if w == 0 {
        return out;
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
    out
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
    label: Vec<u32>,
    stack: Vec<usize>,
    region: Vec<usize>,
}

/// Invalidates 4-connected regions (neighbours within `range`) smaller than `window` pixels.
pub fn remove_speckles(d: &mut [f32], w: usize, h: usize, window: usize, range: f32) {
    remove_speckles_with(d, w, h, window, range, &mut SpeckleScratch::default());
}

/// [`remove_speckles`] with buffers kept by the caller.
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
        stack,
        region,
    } = s;
    label.clear();
    label.resize(w * h, 0);
    stack.clear();
    let mut next = 1u32;
    for start in 0..w * h {
        if label[start] != 0 || !d[start].is_finite() {
            continue;
        }
        region.clear();
        stack.push(start);
        label[start] = next;
        while let Some(i) = stack.pop() {
            region.push(i);
            let (y, x) = (i / w, i % w);
            let mut visit = |j: usize| {
                if label[j] == 0 && d[j].is_finite() && (d[j] - d[i]).abs() <= range {
                    label[j] = next;
                    stack.push(j);
                }
            };
            if x > 0 {
                visit(i - 1);
            }
            if x + 1 < w {
                visit(i + 1);
            }
            if y > 0 {
                visit(i - w);
            }
            if y + 1 < h {
                visit(i + w);
            }
        }
        if region.len() < window {
            for &i in region.iter() {
                d[i] = f32::NAN;
            }
        }
        next += 1;
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
                crate::simd::force_portable(false);
                for (i, (g, r)) in got.iter().zip(&want).enumerate() {
                    assert!(
                        g.to_bits() == r.to_bits(),
                        "{w}x{h} pixel {i}: {g} instead of {r} (portable {portable})"
                    );
                }
            }
        }
    }
}
