//! The aggregation pass of [`crate::aggregate`] in AVX2 registers: the same recurrence, the
//! same buffers and the same order of work, written with raw pointers so the inner loop is the
//! arithmetic alone (no bounds checks, no reloads of the buffers' addresses, the broadcasts
//! hoisted out of the disparity loop, the minimum over d by `minpos`, and the sums started
//! from `init` or zero by the first path instead of a copy).

use std::arch::x86_64::*;

use crate::aggregate::{Costs, Ctx, PassScratch, FAR, GUARD, LANES};

/// One pass (see [`crate::aggregate::pass`]). Only called after AVX2 and POPCNT were detected.
#[target_feature(enable = "avx2,popcnt")]
pub(crate) fn pass(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    after_row: impl FnMut(usize, &mut [i16]),
) {
    if ctx.vdx.len() == 3 {
        pass_n::<3>(forward, ctx, ps, init, costs, out, after_row);
    } else {
        pass_n::<1>(forward, ctx, ps, init, costs, out, after_row);
    }
}

/// Minimum of 16 lanes that all lie in 0..=i16::MAX (so the unsigned `minpos` is the signed one).
#[target_feature(enable = "avx2")]
#[inline]
fn hmin(v: __m256i) -> i16 {
    let m = _mm_min_epi16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    _mm_cvtsi128_si32(_mm_minpos_epu16(m)) as i16
}

/// The recurrence on 16 disparities from the previous L at d - 16.. (`lo`), d.. (`a`) and
/// d + 16.. (`hi`): `cost + min(a, a[d-1] + p1, a[d+1] + p1, jump) - min_prev`.
#[target_feature(enable = "avx2")]
#[inline]
fn step(
    c: __m256i,
    lo: __m256i,
    a: __m256i,
    hi: __m256i,
    p1: __m256i,
    jump: __m256i,
    min_prev: __m256i,
) -> __m256i {
    let am = _mm256_alignr_epi8::<14>(a, _mm256_permute2x128_si256::<0x21>(lo, a));
    let ap = _mm256_alignr_epi8::<2>(_mm256_permute2x128_si256::<0x21>(a, hi), a);
    let best = _mm256_min_epi16(
        _mm256_min_epi16(a, jump),
        _mm256_min_epi16(_mm256_adds_epi16(am, p1), _mm256_adds_epi16(ap, p1)),
    );
    _mm256_adds_epi16(c, _mm256_sub_epi16(best, min_prev))
}

/// One path over the D' disparities of one pixel. `prev` points at the previous pixel's L (d =
/// 0; GUARD lanes at FAR before it, and after the last chunk). The new L goes to `dst`, or, for
/// a delayed path, to `holding` while `held` (when given) overwrites `prev` chunk by chunk once
/// read. `acc_in` gives the sums the path adds to (written to `acc`). Returns min over d of L.
///
/// # Safety
/// `prev - GUARD .. prev + chunks * LANES + LANES`, and `chunks * LANES` lanes from `cost`,
/// `acc_in`, `acc`, the slot, `held` and `holding`, are valid.
#[target_feature(enable = "avx2")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn path(
    chunks: usize,
    prev: *mut i16,
    cost: *const i16,
    acc_in: Option<*const i16>,
    acc: *mut i16,
    dst: Dst,
    p1: __m256i,
    jump: i16,
    min_prev: i16,
) -> i16 {
    // SAFETY: the caller guarantees the pointers' extents (see the doc above).
    unsafe {
        let (jump, mp) = (_mm256_set1_epi16(jump), _mm256_set1_epi16(min_prev));
        let (mut lo, mut a) = (
            _mm256_loadu_si256(prev.sub(LANES).cast()),
            _mm256_loadu_si256(prev.cast()),
        );
        let mut mn = _mm256_set1_epi16(FAR);
        for q in 0..chunks {
            let at = q * LANES;
            let hi = _mm256_loadu_si256(prev.add(at + LANES).cast());
            let c = _mm256_loadu_si256(cost.add(at).cast());
            let l = step(c, lo, a, hi, p1, jump, mp);
            mn = _mm256_min_epi16(mn, l);
            let base = match acc_in {
                Some(src) => _mm256_loadu_si256(src.add(at).cast()),
                None => _mm256_setzero_si256(),
            };
            _mm256_storeu_si256(acc.add(at).cast(), _mm256_adds_epi16(base, l));
            match dst {
                Dst::Slot(d) => _mm256_storeu_si256(d.add(at).cast(), l),
                Dst::Delayed { held, holding } => {
                    if let Some(h) = held {
                        _mm256_storeu_si256(
                            prev.add(at).cast(),
                            _mm256_loadu_si256(h.add(at).cast()),
                        );
                    }
                    _mm256_storeu_si256(holding.add(at).cast(), l);
                }
            }
            (lo, a) = (a, hi);
        }
        hmin(mn)
    }
}

/// Where a path's new L goes.
#[derive(Clone, Copy)]
enum Dst {
    /// Its own slot.
    Slot(*mut i16),
    /// Held back a pixel (see [`crate::aggregate`]'s `pass_n`).
    Delayed {
        held: Option<*const i16>,
        holding: *mut i16,
    },
}

#[target_feature(enable = "avx2,popcnt")]
#[inline]
fn pass_n<const NV: usize>(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    mut costs: Costs,
    out: &mut [i16],
    mut after_row: impl FnMut(usize, &mut [i16]),
) {
    let (w, h, dp, p) = (ctx.w, ctx.h, ctx.dp, ctx.p);
    let stride = ctx.stride();
    let chunks = dp / LANES;
    let mut vdx = [0isize; NV];
    vdx.copy_from_slice(ctx.vdx);
    let step_x: isize = if forward { 1 } else { -1 };
    let row_len = w * dp;
    let whole = out.len() == h * row_len;
    assert!(out.len() >= row_len && init.is_none_or(|s| s.len() >= h * row_len));
    ps.begin(ctx, NV);
    assert_eq!(ps.paths.len(), NV * (w + 2) * stride + GUARD);
    assert!(ps.mins.len() == NV * (w + 2) && ps.held.len() == dp && ps.holding.len() == dp);
    assert_eq!(ps.cost.len(), row_len);
    let p1 = _mm256_set1_epi16(p.p1 as i16);
    let delayed_v = vdx.iter().position(|&dx| dx == step_x);
    for k in 0..h {
        let y = if forward { k } else { h - 1 - k };
        ps.start_row(ctx, y, &mut costs);
        let mut row_min = 0i16;
        let mut held_min = 0i16;
        let prev_y = if forward { y.wrapping_sub(1) } else { y + 1 };
        let o = if whole { y * row_len } else { 0 };
        let out_row = &mut out[o..o + row_len];
        let img_row = &ctx.img[y * w..(y + 1) * w];
        let paths = ps.paths.as_mut_ptr();
        let row_path = ps.row_path.as_mut_ptr();
        let cost_row = ps.cost.as_ptr();
        let acc_row = out_row.as_mut_ptr();
        let init_row = init.map(|s| s[y * row_len..(y + 1) * row_len].as_ptr());
        for j in 0..w {
            let x = if forward { j } else { w - 1 - j };
            let g = img_row[x];
            // Swapped after every pixel.
            let (held, holding) = (ps.held.as_ptr(), ps.holding.as_mut_ptr());
            let p2_from = |xp: usize, yp: usize| ctx.p2_from(g, xp, yp);
            // SAFETY: x < w; the cell x * dp.. of the cost row, the sums and `init` hold dp
            // lanes; path slots s <= w + 1 of NV segments of `stride` lanes (plus a trailing
            // guard) lie in `paths` (sized by `begin`), held and holding hold dp lanes, and
            // the row path one guarded segment.
            unsafe {
                let cost = cost_row.add(x * dp);
                let acc = acc_row.add(x * dp);
                let acc_in = init_row.map(|r| r.add(x * dp));
                for (v, &dx) in vdx.iter().enumerate() {
                    let s = (x as isize - dx + 1) as usize;
                    let mins_at = v * (w + 2);
                    let min_prev = ps.mins[mins_at + s];
                    let p2 = if k == 0 {
                        0
                    } else {
                        p2_from(s.wrapping_sub(1), prev_y)
                    };
                    let prev = paths.add((s * NV + v) * stride + GUARD);
                    let dst = if delayed_v == Some(v) {
                        Dst::Delayed {
                            held: (j > 0).then_some(held),
                            holding,
                        }
                    } else {
                        Dst::Slot(paths.add(((x + 1) * NV + v) * stride + GUARD))
                    };
                    let new_min = path(
                        chunks,
                        prev,
                        cost,
                        if v == 0 {
                            acc_in
                        } else {
                            Some(acc.cast_const())
                        },
                        acc,
                        dst,
                        p1,
                        min_prev + p2,
                        min_prev,
                    );
                    if delayed_v == Some(v) {
                        if j > 0 {
                            ps.mins[mins_at + s] = held_min;
                        }
                        held_min = new_min;
                    } else {
                        ps.mins[mins_at + x + 1] = new_min;
                    }
                }
                let xh = if forward { x.wrapping_sub(1) } else { x + 1 };
                let jump_h = row_min + if j == 0 { 0 } else { p2_from(xh, y) };
                let rp = row_path.add(GUARD);
                row_min = path(
                    chunks,
                    rp,
                    cost,
                    Some(acc.cast_const()),
                    acc,
                    Dst::Slot(rp),
                    p1,
                    jump_h,
                    row_min,
                );
            }
            std::mem::swap(&mut ps.held, &mut ps.holding);
        }
        if let Some(v) = delayed_v {
            ps.flush_held(ctx, NV, v, forward, held_min);
        }
        after_row(y, out_row);
    }
}
