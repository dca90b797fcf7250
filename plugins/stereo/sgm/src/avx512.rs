//! The AVX-512 kernels of the fast SGM path ([`crate::simd::Level::Avx512`]): the matching
//! costs by 64-bit population counts, eight candidates per instruction, and the left winner
//! and second best 32 sums a register. The same output as the AVX2 and portable code, to the
//! bit.

use std::arch::x86_64::*;

use crate::aggregate::{Ctx, LANES};

/// [`crate::aggregate::cost_row`] with AVX-512 (see `aggregate_avx2::cost_row`).
///
/// # Safety
/// The CPU has AVX2 and the extensions of [`crate::simd::Level::Avx512`]; `rev` holds
/// `w + 2 * pad + LANES` entries and `cost` W x D' bytes.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vpopcntdq")]
pub(crate) unsafe fn cost_row(
    ctx: &Ctx,
    y: usize,
    pad: usize,
    unknown: u8,
    rev: &mut [u64],
    cost: &mut [u8],
) {
    // SAFETY: forwarded.
    unsafe {
        crate::aggregate_avx2::cost_row_with(ctx, y, pad, unknown, rev, cost, |src, c, dst, n| {
            cost_chunks(src, c, dst, n)
        })
    }
}

/// The Hamming distances of census `c` to the `chunks` x 16 candidates at `src`, as bytes to
/// `dst`: two registers of eight candidates, their counts narrowed to bytes and joined.
///
/// # Safety
/// `chunks` x 16 entries at `src` and bytes at `dst` are valid.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl,avx512vpopcntdq")]
#[inline]
pub(crate) unsafe fn cost_chunks(src: *const u64, c: u64, dst: *mut u8, chunks: usize) {
    let cv = _mm512_set1_epi64(c as i64);
    // SAFETY: the caller guarantees the extents.
    unsafe {
        for q in 0..chunks {
            let at = q * LANES;
            let count = |i: usize| {
                let r = _mm512_loadu_si512(src.add(at + 8 * i).cast());
                _mm512_cvtepi64_epi8(_mm512_popcnt_epi64(_mm512_xor_si512(r, cv)))
            };
            let b = _mm_unpacklo_epi64(count(0), count(1));
            _mm_storeu_si128(dst.add(at).cast(), b);
        }
    }
}

/// 32 i16 lanes per register.
const W16: usize = 32;

/// The disparity of each lane of a chunk at d = 0.
static LANE_IDS: [i16; W16] = {
    let mut ids = [0i16; W16];
    let mut l = 0;
    while l < W16 {
        ids[l] = l as i16;
        l += 1;
    }
    ids
};

/// Minimum of 32 lanes that all lie in 0..=i16::MAX.
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
#[inline]
fn hmin16(v: __m512i) -> i16 {
    let m = _mm256_min_epi16(_mm512_castsi512_si256(v), _mm512_extracti64x4_epi64::<1>(v));
    let m = _mm_min_epi16(_mm256_castsi256_si128(m), _mm256_extracti128_si256::<1>(m));
    _mm_cvtsi128_si32(_mm_minpos_epu16(m)) as i16
}

/// `select::select_row_avx2` 32 disparities per register, for D' a multiple of 32: the same
/// minimum, first index at it and second best beyond d +- 1, with mask registers for the
/// compares. The right disparities stay with the AVX2 window (`select::right_row_avx2`): in
/// 32-lane registers its lane shift (a two-register permutation) lies on the chain from one
/// pixel to the next, and the whole selection took 0.7 to 1.0 ms longer at 640x480 with 96
/// disparities on an AMD Zen 5.
///
/// # Safety
/// The CPU has AVX2 and the extensions of [`crate::simd::Level::Avx512`].
#[target_feature(enable = "avx2,avx512f,avx512bw,avx512vl")]
pub(crate) unsafe fn select_row(
    ctx: &Ctx,
    y: usize,
    tot: &[i16],
    valid: Option<&[u8]>,
    disp: &mut [f32],
    right: &mut [f32],
    rs: &mut crate::select::RightScratch,
) {
    use crate::aggregate::FAR;
    let (w, nd, dp, p) = (ctx.w, ctx.nd, ctx.dp, ctx.p);
    assert!(dp.is_multiple_of(W16));
    let chunks = dp / W16;
    assert!(tot.len() >= w * dp && disp.len() >= w && right.len() >= w);
    let dmin = p.min_disparity as f32;
    // SAFETY: LANE_IDS holds 32 i16.
    let lane_ids = unsafe { _mm512_loadu_si512(LANE_IDS.as_ptr().cast()) };
    let far = _mm512_set1_epi16(FAR);
    let base = |q: usize| _mm512_add_epi16(lane_ids, _mm512_set1_epi16((q * W16) as i16));
    let load = |at: usize| -> __m512i {
        // SAFETY: at + W16 <= tot.len() (at < w * dp, a multiple of W16; asserted above).
        unsafe { _mm512_loadu_si512(tot.as_ptr().add(at).cast()) }
    };
    for (x, out) in disp.iter_mut().enumerate().take(w) {
        if valid.is_some_and(|m| m[y * w + x] == 0) {
            *out = f32::NAN;
            continue;
        }
        let cell = x * dp;
        let mut m = load(cell);
        let mut idx = lane_ids;
        for q in 1..chunks {
            let c = load(cell + q * W16);
            idx = _mm512_mask_blend_epi16(_mm512_cmpgt_epi16_mask(m, c), idx, base(q));
            m = _mm512_min_epi16(m, c);
        }
        let best = hmin16(m);
        let at_best = _mm512_cmpeq_epi16_mask(m, _mm512_set1_epi16(best));
        let bd = hmin16(_mm512_mask_blend_epi16(at_best, far, idx));
        let bdv = _mm512_set1_epi16(bd);
        let two = _mm512_set1_epi16(2);
        let mut sec = far;
        for q in 0..chunks {
            let near =
                _mm512_cmpgt_epi16_mask(two, _mm512_abs_epi16(_mm512_sub_epi16(base(q), bdv)));
            let c = _mm512_mask_mov_epi16(load(cell + q * W16), near, far);
            sec = _mm512_min_epi16(sec, c);
        }
        *out = crate::select::settle(&tot[cell..cell + dp], best, bd as usize, hmin16(sec), nd, p)
            + dmin;
    }
    // SAFETY: the caller's AVX2.
    unsafe { crate::select::right_row_avx2(ctx, tot, right, rs) };
}
