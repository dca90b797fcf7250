//! Winner-takes-all of one completed row of SGM sums: the left disparity (uniqueness margin,
//! parabola) and the right one for the left-right check.

use crate::aggregate::{lanes, lanes_mut, Ctx, FAR, LANES};
use crate::sgm::SgmParams;

/// Minimum of a slice (FAR when empty), 16 lanes at a time.
#[inline(always)]
fn min_i16(s: &[i16]) -> i16 {
    let mut m = [FAR; LANES];
    let chunks = s.chunks_exact(LANES);
    let tail = chunks.remainder().iter().copied().fold(FAR, i16::min);
    for c in chunks {
        for l in 0..LANES {
            m[l] = m[l].min(c[l]);
        }
    }
    m.iter().copied().fold(tail, i16::min)
}

/// The disparity index of a pixel (NaN when it fails the uniqueness margin) from its sums
/// `cell`, the best sum `best` at index `bd`, and the second best `second` beyond `bd` +- 1
/// (FAR when there is none: the margin test then passes, as with u16::MAX in the reference);
/// refined by the parabola through `bd` - 1, `bd`, `bd` + 1 when asked.
#[inline(always)]
pub(crate) fn settle(
    cell: &[i16],
    best: i16,
    bd: usize,
    second: i16,
    nd: usize,
    p: &SgmParams,
) -> f32 {
    let second = if second == FAR {
        u64::from(u16::MAX)
    } else {
        second as u64
    };
    if (best as u64) * (100 + p.uniqueness_pct as u64) > second * 100 {
        return f32::NAN;
    }
    let mut d = bd as f32;
    if p.subpixel && bd > 0 && bd + 1 < nd {
        let (a, b, c) = (cell[bd - 1] as f32, cell[bd] as f32, cell[bd + 1] as f32);
        let den = a - 2.0 * b + c;
        if den > 0.0 {
            d += 0.5 * (a - c) / den;
        }
    }
    d
}

/// Buffers of the right-disparity search of one row.
#[derive(Default)]
pub(crate) struct RightScratch {
    /// Best sum and its disparity per right pixel, stored reversed (index pad + w - 1 - xr) so
    /// that one left pixel's 16 disparities update 16 contiguous entries.
    best: Vec<i16>,
    arg: Vec<i16>,
}

/// Winner-takes-all for one completed row of sums: the left disparity with the uniqueness
/// margin and the parabola, and the right disparity argmin_d S(y, xr + d + dmin, d).
pub(crate) fn select_row(
    ctx: &Ctx,
    y: usize,
    tot: &[i16],
    valid: Option<&[u8]>,
    disp: &mut [f32],
    right: &mut [f32],
    rs: &mut RightScratch,
) {
    #[cfg(target_arch = "x86_64")]
    if ctx.avx512 && ctx.dp.is_multiple_of(32) {
        // SAFETY: the CPU has the AVX-512 extensions when `ctx.avx512` is set.
        unsafe { crate::avx512::select_row(ctx, y, tot, valid, disp, right, rs) };
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if crate::simd::avx2() {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { select_row_avx2(ctx, y, tot, valid, disp, right, rs) };
        return;
    }
    select_row_generic(ctx, y, tot, valid, disp, right, rs);
}

/// Minimum of the 16 lanes (all in 0..=i16::MAX, so the unsigned `minpos` is the signed min).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
#[inline]
fn hmin_avx2(v: std::arch::x86_64::__m256i) -> i16 {
    use std::arch::x86_64::*;
    let m = _mm_min_epi16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    _mm_cvtsi128_si32(_mm_minpos_epu16(m)) as i16
}

/// [`select_row_generic`] in AVX2 registers. Left: the minimum of the D' sums, its first lane
/// by a compare mask, the second best with the lanes at d +- 1 of it raised to FAR. Right: a
/// window of D' lanes, lane d holding the best sum so far (and its d) of right pixel
/// x - dmin - d; each left pixel shifts the window up one lane (chunks from the top, so every
/// load and store is aligned to the previous pixel's) and offers its sums; lane nd - 1 is then
/// complete.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn select_row_avx2(
    ctx: &Ctx,
    y: usize,
    tot: &[i16],
    valid: Option<&[u8]>,
    disp: &mut [f32],
    right: &mut [f32],
    rs: &mut RightScratch,
) {
    use std::arch::x86_64::*;
    let (w, nd, dp, p) = (ctx.w, ctx.nd, ctx.dp, ctx.p);
    let chunks = dp / LANES;
    assert!(tot.len() >= w * dp && disp.len() >= w && right.len() >= w);
    let dmin = p.min_disparity as f32;
    let lane_ids = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let far = _mm256_set1_epi16(FAR);
    let load = |at: usize| -> __m256i {
        // SAFETY: at + LANES <= tot.len() (at < w * dp, a multiple of LANES; asserted above).
        unsafe { _mm256_loadu_si256(tot.as_ptr().add(at).cast()) }
    };
    for (x, out) in disp.iter_mut().enumerate().take(w) {
        if valid.is_some_and(|m| m[y * w + x] == 0) {
            *out = f32::NAN;
            continue;
        }
        let cell = x * dp;
        // Per lane the minimum and the first d that reaches it (a strict compare keeps the
        // earlier chunk on ties); then the smallest such d among the lanes at the overall
        // minimum. No branch on where the minimum lies.
        let mut m = load(cell);
        let mut idx = lane_ids;
        for q in 1..chunks {
            let c = load(cell + q * LANES);
            let lower = _mm256_cmpgt_epi16(m, c);
            let d = _mm256_add_epi16(lane_ids, _mm256_set1_epi16((q * LANES) as i16));
            idx = _mm256_blendv_epi8(idx, d, lower);
            m = _mm256_min_epi16(m, c);
        }
        let best = hmin_avx2(m);
        let bv = _mm256_set1_epi16(best);
        // Lanes not at the minimum take d = i16::MAX; d < 1024 otherwise.
        let at_best = _mm256_cmpeq_epi16(m, bv);
        let bdv = hmin_avx2(_mm256_blendv_epi8(far, idx, at_best));
        let bd = bdv as usize;
        let bdv = _mm256_set1_epi16(bdv);
        let two = _mm256_set1_epi16(2);
        let mut sec = far;
        for q in 0..chunks {
            let d = _mm256_add_epi16(lane_ids, _mm256_set1_epi16((q * LANES) as i16));
            let near = _mm256_cmpgt_epi16(two, _mm256_abs_epi16(_mm256_sub_epi16(d, bdv)));
            let c = _mm256_max_epi16(load(cell + q * LANES), _mm256_and_si256(near, far));
            sec = _mm256_min_epi16(sec, c);
        }
        *out = settle(&tot[cell..cell + dp], best, bd, hmin_avx2(sec), nd, p) + dmin;
    }
    // SAFETY: the caller's AVX2.
    unsafe { right_row_avx2(ctx, tot, right, rs) };
}

/// The right disparities of [`select_row_avx2`] (see there).
///
/// # Safety
/// The CPU has AVX2; `tot` holds W x D' sums and `right` W entries.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
pub(crate) unsafe fn right_row_avx2(
    ctx: &Ctx,
    tot: &[i16],
    right: &mut [f32],
    rs: &mut RightScratch,
) {
    use std::arch::x86_64::*;
    let (w, nd, dp, p) = (ctx.w, ctx.nd, ctx.dp, ctx.p);
    let chunks = dp / LANES;
    assert!(tot.len() >= w * dp && right.len() >= w);
    let dmin = p.min_disparity as f32;
    let lane_ids = _mm256_setr_epi16(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
    let far = _mm256_set1_epi16(FAR);
    let load = |at: usize| -> __m256i {
        // SAFETY: at + LANES <= tot.len() (at < w * dp, a multiple of LANES; asserted above).
        unsafe { _mm256_loadu_si256(tot.as_ptr().add(at).cast()) }
    };
    // Right disparities. Chunk q of the window at rs.best/rs.arg[q * LANES..]: lane d of right
    // pixel xr = x - dmin - d. Guard lanes below d = 0 hold FAR.
    right[..w].fill(f32::NAN);
    rs.best.clear();
    rs.best.resize(dp, FAR);
    rs.arg.clear();
    rs.arg.resize(dp, -1);
    let (bp, ap) = (rs.best.as_mut_ptr(), rs.arg.as_mut_ptr());
    let dmin_i = p.min_disparity as isize;
    let done = nd - 1;
    for x in 0..w {
        let cell = x * dp;
        for q in (0..chunks).rev() {
            // SAFETY: q * LANES + LANES <= dp = rs.best.len() = rs.arg.len().
            let (b, a) = unsafe {
                (
                    _mm256_loadu_si256(bp.add(q * LANES).cast()),
                    _mm256_loadu_si256(ap.add(q * LANES).cast()),
                )
            };
            let (b_lo, a_lo) = if q == 0 {
                (far, _mm256_set1_epi16(-1))
            } else {
                // SAFETY: as above, chunk q - 1.
                unsafe {
                    (
                        _mm256_loadu_si256(bp.add((q - 1) * LANES).cast()),
                        _mm256_loadu_si256(ap.add((q - 1) * LANES).cast()),
                    )
                }
            };
            // One lane up: lane l gets lane l - 1 (lane 0 the top lane of the chunk below).
            let b = _mm256_alignr_epi8::<14>(b, _mm256_permute2x128_si256::<0x21>(b_lo, b));
            let a = _mm256_alignr_epi8::<14>(a, _mm256_permute2x128_si256::<0x21>(a_lo, a));
            let c = load(cell + q * LANES);
            let d = _mm256_add_epi16(lane_ids, _mm256_set1_epi16((q * LANES) as i16));
            let better = _mm256_cmpgt_epi16(b, c);
            // SAFETY: as above.
            unsafe {
                _mm256_storeu_si256(bp.add(q * LANES).cast(), _mm256_min_epi16(b, c));
                _mm256_storeu_si256(ap.add(q * LANES).cast(), _mm256_blendv_epi8(a, d, better));
            }
        }
        let xr = x as isize - dmin_i - done as isize;
        if xr >= 0 && (xr as usize) < w {
            let d = rs.arg[done];
            right[xr as usize] = if d < 0 { f32::NAN } else { d as f32 + dmin };
        }
    }
    // The lanes below nd - 1 are complete too once the row ends.
    for (d, &a) in rs.arg.iter().enumerate().take(done) {
        let xr = (w - 1) as isize - dmin_i - d as isize;
        if xr >= 0 && (xr as usize) < w {
            right[xr as usize] = if a < 0 { f32::NAN } else { a as f32 + dmin };
        }
    }
}

#[inline(always)]
fn select_row_generic(
    ctx: &Ctx,
    y: usize,
    tot: &[i16],
    valid: Option<&[u8]>,
    disp: &mut [f32],
    right: &mut [f32],
    rs: &mut RightScratch,
) {
    let (w, nd, dp, p) = (ctx.w, ctx.nd, ctx.dp, ctx.p);
    let dmin = p.min_disparity as f32;
    for (x, out) in disp.iter_mut().enumerate() {
        if valid.is_some_and(|m| m[y * w + x] == 0) {
            *out = f32::NAN;
            continue;
        }
        let cell = &tot[x * dp..(x + 1) * dp];
        // Argmin with the smallest d on ties: the minimum of sum * 1024 + d (sums < 2^15,
        // d < 1024), 8 i32 lanes at a time. Padding lanes hold FAR and never win.
        let mut key = [i32::MAX; LANES];
        for (q, chunk) in cell.chunks_exact(LANES).enumerate() {
            for l in 0..LANES {
                key[l] = key[l].min((i32::from(chunk[l]) << 10) | (q * LANES + l) as i32);
            }
        }
        let k = key.iter().copied().fold(i32::MAX, i32::min);
        let (best, bd) = (k >> 10, (k & 1023) as usize);
        // Second best beyond d +- 1.
        let second = min_i16(&cell[..bd.saturating_sub(1)]).min(min_i16(&cell[(bd + 2).min(dp)..]));
        *out = settle(cell, best as i16, bd, second, nd, p) + dmin;
    }
    // Right disparities: left pixel x at disparity d votes for xr = x - d - dmin. Visiting x in
    // increasing order visits each xr's candidates in increasing d, so a strict "<" keeps the
    // smallest d on ties, as the reference's scan over d does.
    let pad = dp + p.min_disparity.unsigned_abs() as usize + 1;
    rs.best.clear();
    rs.best.resize(w + 2 * pad, FAR);
    rs.arg.clear();
    rs.arg.resize(w + 2 * pad, -1);
    let dmin_i = p.min_disparity as isize;
    for x in 0..w {
        let cell = &tot[x * dp..(x + 1) * dp];
        let t0 = (pad as isize + w as isize - 1 - x as isize + dmin_i) as usize;
        for q in 0..dp / LANES {
            let c = lanes(cell, q * LANES);
            let (mut b, mut a) = (
                *lanes(&rs.best, t0 + q * LANES),
                *lanes(&rs.arg, t0 + q * LANES),
            );
            for l in 0..LANES {
                let better = c[l] < b[l];
                a[l] = if better { (q * LANES + l) as i16 } else { a[l] };
                b[l] = b[l].min(c[l]);
            }
            *lanes_mut(&mut rs.best, t0 + q * LANES) = b;
            *lanes_mut(&mut rs.arg, t0 + q * LANES) = a;
        }
    }
    for (xr, out) in right.iter_mut().enumerate() {
        let d = rs.arg[pad + w - 1 - xr];
        *out = if d < 0 || d as usize >= nd {
            f32::NAN
        } else {
            d as f32 + dmin
        };
    }
}
