//! The aggregation pass of [`crate::aggregate`] in AVX2 registers: the same recurrence and the
//! same sums, with all the paths of a pixel advanced together, one register of disparities at a
//! time. Per chunk the matching costs and the running sum are loaded once and stored once, and
//! each path from the previous row reads its previous L at d - 1, d and d + 1 by unaligned loads
//! (no lane shuffles). The paths are updated in place in one row buffer, as in the portable pass
//! (so the buffer stays in the L2 cache): the load of chunk q + 1 at d - 1 is made before chunk
//! q is stored, the path that would overwrite an L its right-hand neighbour still has to read
//! holds its new L back a pixel, and the path along the row reads whole chunks and shifts lanes
//! (an unaligned load of what the previous pixel has just stored would wait for the stores). The
//! Hamming costs of a row are computed 16 disparities at a time (nibble-table popcounts,
//! [`cost_row`]) and kept as bytes. The backward pass prefetches the sums and costs it reads, as
//! it walks each row against the address order.
//!
//! Every L lies in 0..=C_max + P2 (C_max: the census bits). When that is at most 255 (the
//! defaults: 62 + 120) the paths run in u8 lanes, 32 disparities per register, with saturating
//! adds ([`Narrow`]); otherwise in i16 lanes ([`Wide`]). The sums stay i16. Saturation at 255
//! cannot change a minimum: every L, and so every candidate that can win, is at most 255.

use std::arch::x86_64::*;

use crate::aggregate::{size_paths, Costs, Ctx, PassScratch, Peer, FAR, LANES};

/// One pass (see [`crate::aggregate::pass`]). Only called after AVX2 and POPCNT were detected.
#[target_feature(enable = "avx2,popcnt")]
#[allow(clippy::too_many_arguments)] // the pass's inputs, outputs and hooks
pub(crate) fn pass(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    peer: Peer,
    after_row: impl FnMut(usize, &mut [i16]),
) {
    // The path held back: the one from the previous row's pixel behind this one (dx = the
    // step along the row), index 0 of [1, 0, -1] forward and 2 backward; none with 4 paths.
    if ctx.narrow {
        kind::<Narrow>(forward, ctx, ps, init, costs, out, peer, after_row);
    } else {
        kind::<Wide>(forward, ctx, ps, init, costs, out, peer, after_row);
    }
}

/// Pixels ahead whose incoming sums are prefetched.
const PREFETCH: usize = 2;

/// The pass with the paths in lanes of kind `K`, monomorphised by the number of paths, the
/// held-back path (by direction) and whether sums come in.
#[target_feature(enable = "avx2,popcnt")]
#[inline]
#[allow(clippy::too_many_arguments)] // the pass's inputs, outputs and hooks
fn kind<K: Kind>(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    peer: Peer,
    after_row: impl FnMut(usize, &mut [i16]),
) {
    let (f, i) = (forward, init.is_some());
    match (ctx.vdx.len(), f, i) {
        (3, true, true) => {
            pass_n::<K, 3, 4, 0, true>(f, ctx, ps, init, costs, out, peer, after_row)
        }
        (3, true, false) => {
            pass_n::<K, 3, 4, 0, false>(f, ctx, ps, init, costs, out, peer, after_row)
        }
        (3, false, true) => {
            pass_n::<K, 3, 4, 2, true>(f, ctx, ps, init, costs, out, peer, after_row)
        }
        (3, false, false) => {
            pass_n::<K, 3, 4, 2, false>(f, ctx, ps, init, costs, out, peer, after_row)
        }
        (_, _, true) => pass_n::<K, 1, 2, 2, true>(f, ctx, ps, init, costs, out, peer, after_row),
        (_, _, false) => pass_n::<K, 1, 2, 2, false>(f, ctx, ps, init, costs, out, peer, after_row),
    }
}

/// The lane type of the paths: i16 ([`Wide`]) or u8 ([`Narrow`]).
pub(crate) trait Kind {
    /// One L.
    type E: Copy + Default;
    /// Lanes per register.
    const LANES: usize;
    /// The path buffers of this kind in the scratch: the rows of paths, held, holding and the
    /// path along the row.
    fn buffers(ps: &mut PassScratch) -> [&mut Vec<Self::E>; 4];
    /// The guard lanes' value, above every L.
    const FAR: Self::E;
    /// A value broadcast to every lane (at most 255 for u8: saturated).
    fn splat(v: i16) -> __m256i;
    /// [`pixel`] for this lane type.
    ///
    /// # Safety
    /// As [`pixel`], in elements of `Self::E`.
    unsafe fn pixel<const NP: usize, const HELD: usize, const INIT: bool>(
        chunks: usize,
        cost: *const u8,
        init: *const i16,
        acc: *mut i16,
        paths: &Paths<NP, Self::E>,
        p1: __m256i,
        pads: &Pads,
    ) -> [i16; NP];
}

/// Paths in i16 lanes, 16 disparities per register.
pub(crate) struct Wide;
/// Paths in u8 lanes, 32 disparities per register (when C_max + P2 <= 255).
pub(crate) struct Narrow;

/// What the lanes from D to D' of the last chunk get: FAR costs in i16 lanes (`wide`), 255
/// costs in u8 lanes (`narrow`), and FAR sums in the two i16 halves of a u8 chunk (`sums`).
pub(crate) struct Pads {
    wide: __m256i,
    narrow: __m256i,
    sums: [__m256i; 2],
}

impl Pads {
    #[target_feature(enable = "avx2")]
    fn new(ctx: &Ctx, lanes: usize) -> Pads {
        let last = ctx.dp - lanes;
        let wide: [i16; 16] =
            std::array::from_fn(|l| if ctx.dp - 16 + l < ctx.nd { 0 } else { FAR });
        let narrow: [u8; 32] = std::array::from_fn(|l| if last + l < ctx.nd { 0 } else { 255 });
        let sums: [i16; 32] = std::array::from_fn(|l| if last + l < ctx.nd { 0 } else { FAR });
        // SAFETY: each array holds 32 bytes (the sums two halves of 32).
        unsafe {
            Pads {
                wide: _mm256_loadu_si256(wide.as_ptr().cast()),
                narrow: _mm256_loadu_si256(narrow.as_ptr().cast()),
                sums: [
                    _mm256_loadu_si256(sums.as_ptr().cast()),
                    _mm256_loadu_si256(sums[16..].as_ptr().cast()),
                ],
            }
        }
    }
}

impl Kind for Wide {
    type E = i16;
    const LANES: usize = LANES;
    fn buffers(ps: &mut PassScratch) -> [&mut Vec<i16>; 4] {
        [
            &mut ps.paths,
            &mut ps.held,
            &mut ps.holding,
            &mut ps.row_path,
        ]
    }
    const FAR: i16 = FAR;
    fn splat(v: i16) -> __m256i {
        // SAFETY: a broadcast; AVX is present wherever this pass runs.
        unsafe { _mm256_set1_epi16(v) }
    }
    unsafe fn pixel<const NP: usize, const HELD: usize, const INIT: bool>(
        chunks: usize,
        cost: *const u8,
        init: *const i16,
        acc: *mut i16,
        paths: &Paths<NP, i16>,
        p1: __m256i,
        pads: &Pads,
    ) -> [i16; NP] {
        // SAFETY: forwarded (see `Kind::pixel`).
        unsafe { pixel::<NP, HELD, INIT>(chunks, cost, init, acc, paths, p1, pads.wide) }
    }
}

impl Kind for Narrow {
    type E = u8;
    const LANES: usize = 32;
    fn buffers(ps: &mut PassScratch) -> [&mut Vec<u8>; 4] {
        [
            &mut ps.paths8,
            &mut ps.held8,
            &mut ps.holding8,
            &mut ps.row_path8,
        ]
    }
    const FAR: u8 = u8::MAX;
    fn splat(v: i16) -> __m256i {
        // SAFETY: a broadcast; AVX is present wherever this pass runs.
        unsafe { _mm256_set1_epi8(v.clamp(0, 255) as u8 as i8) }
    }
    unsafe fn pixel<const NP: usize, const HELD: usize, const INIT: bool>(
        chunks: usize,
        cost: *const u8,
        init: *const i16,
        acc: *mut i16,
        paths: &Paths<NP, u8>,
        p1: __m256i,
        pads: &Pads,
    ) -> [i16; NP] {
        // SAFETY: forwarded (see `Kind::pixel`).
        unsafe { pixel_narrow::<NP, HELD, INIT>(chunks, cost, init, acc, paths, p1, pads) }
    }
}

/// Minimum of 16 lanes that all lie in 0..=i16::MAX (so the unsigned `minpos` is the signed one).
#[target_feature(enable = "avx2")]
#[inline]
fn hmin(v: __m256i) -> i16 {
    let m = _mm_min_epi16(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    _mm_cvtsi128_si32(_mm_minpos_epu16(m)) as i16
}

/// Where the `NP` paths of one pixel read their previous L and write the new one (pointers at
/// d = 0 of a segment with a guard lane at FAR before it and one after its last chunk; `dst`
/// may be `src`), and their `min(prev) + P2` and `min(prev)`, broadcast. The held-back path
/// also gets `held`, the previous pixel's L, stored over its `src` once read.
pub(crate) struct Paths<const NP: usize, E> {
    src: [*mut E; NP],
    dst: [*mut E; NP],
    jump: [__m256i; NP],
    min_prev: [__m256i; NP],
    held: *const E,
}

/// The previous L at d, d - 1 and d + 1 of a path from the previous row, for the chunk of
/// `lanes` lanes at `s`: unaligned loads, d - 1 from `below` (loaded before the chunk below was
/// overwritten), which then gets the next chunk's.
///
/// # Safety
/// `s - 1 .. s + 2 * lanes` is readable.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn from_row<E>(s: *mut E, lanes: usize, below: &mut __m256i) -> (__m256i, __m256i, __m256i) {
    // SAFETY: the caller guarantees the extent.
    unsafe {
        let a = _mm256_loadu_si256(s.cast_const().cast());
        let am = *below;
        let ap = _mm256_loadu_si256(s.add(1).cast_const().cast());
        *below = _mm256_loadu_si256(s.add(lanes - 1).cast_const().cast());
        (a, am, ap)
    }
}

/// The same for the path along the row, from whole chunks (`lo`: the chunk below, `mid`: this
/// one) and the one above, loaded here, with the lanes shifted by one element (`DOWN` =
/// 16 - element bytes, `UP` = element bytes); the chunks then move up by one.
///
/// # Safety
/// `s + lanes .. s + 2 * lanes` is readable.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn along_row<const DOWN: i32, const UP: i32, E>(
    s: *mut E,
    lanes: usize,
    lo: &mut __m256i,
    mid: &mut __m256i,
) -> (__m256i, __m256i, __m256i) {
    // SAFETY: the caller guarantees the extent.
    let hi = unsafe { _mm256_loadu_si256(s.add(lanes).cast_const().cast()) };
    let a = *mid;
    let am = _mm256_alignr_epi8::<DOWN>(a, _mm256_permute2x128_si256::<0x21>(*lo, a));
    let ap = _mm256_alignr_epi8::<UP>(_mm256_permute2x128_si256::<0x21>(a, hi), a);
    (*lo, *mid) = (a, hi);
    (a, am, ap)
}

/// Advances the `NP` paths of one pixel over its `chunks` x 16 disparities: each path's
/// `L = C + min(Lp[d], Lp[d-1] + P1, Lp[d+1] + P1, min(Lp) + P2) - min(Lp)` goes to its `dst`,
/// and `acc = init (INIT) or 0, plus the sum of the new L` over the paths. Path `HELD` (none
/// when >= NP) stores `held` over its `src`, chunk by chunk once read. Returns each path's
/// minimum over d.
///
/// # Safety
/// `chunks * LANES` lanes from `cost`, `acc`, `init` (INIT), `held` (HELD < NP) and each `dst`
/// are valid, and each `src - 1 .. src + chunks * LANES + LANES`. A path's `src` and `dst`
/// are the same or disjoint, and no other pointer overlaps them.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn pixel<const NP: usize, const HELD: usize, const INIT: bool>(
    chunks: usize,
    cost: *const u8,
    init: *const i16,
    acc: *mut i16,
    paths: &Paths<NP, i16>,
    p1: __m256i,
    far_pad: __m256i,
) -> [i16; NP] {
    // SAFETY: the caller guarantees the extents (see the doc above).
    unsafe {
        let mut mn = [_mm256_set1_epi16(FAR); NP];
        // Each path's previous L at d - 1 of the next chunk, loaded before the chunk below it
        // is overwritten.
        let mut below: [__m256i; NP] = std::array::from_fn(|v| {
            _mm256_loadu_si256(paths.src[v].wrapping_sub(1).cast_const().cast())
        });
        // The path along the row (the last) reads the L its previous pixel has just stored:
        // unaligned loads that span two stores would wait for them to reach the cache, so it
        // loads whole chunks (d - 16.., d.. and d + 16..) and shifts the neighbours out of them.
        let row = paths.src[NP - 1];
        let (mut lo, mut mid) = (
            _mm256_loadu_si256(row.sub(LANES).cast_const().cast()),
            _mm256_loadu_si256(row.cast_const().cast()),
        );
        for q in 0..chunks {
            let at = q * LANES;
            let mut c = _mm256_cvtepu8_epi16(_mm_loadu_si128(cost.add(at).cast()));
            if q + 1 == chunks {
                c = _mm256_or_si256(c, far_pad);
            }
            let mut sum = if INIT {
                _mm256_loadu_si256(init.add(at).cast())
            } else {
                _mm256_setzero_si256()
            };
            for (v, m) in mn.iter_mut().enumerate() {
                let s = paths.src[v].add(at);
                let (a, am, ap) = if v + 1 == NP {
                    along_row::<14, 2, _>(s, LANES, &mut lo, &mut mid)
                } else {
                    from_row(s, LANES, &mut below[v])
                };
                // min(am + P1, ap + P1) as min(am, ap) + P1: the same with saturation, as
                // the saturating add is monotonic.
                let best = _mm256_min_epi16(
                    _mm256_min_epi16(a, paths.jump[v]),
                    _mm256_adds_epi16(_mm256_min_epi16(am, ap), p1),
                );
                let l = _mm256_adds_epi16(c, _mm256_sub_epi16(best, paths.min_prev[v]));
                *m = _mm256_min_epi16(*m, l);
                sum = _mm256_adds_epi16(sum, l);
                if v == HELD {
                    _mm256_storeu_si256(s.cast(), _mm256_loadu_si256(paths.held.add(at).cast()));
                }
                _mm256_storeu_si256(paths.dst[v].add(at).cast(), l);
            }
            _mm256_storeu_si256(acc.add(at).cast(), sum);
        }
        let mut out = [0i16; NP];
        for (o, m) in out.iter_mut().zip(mn) {
            *o = hmin(m);
        }
        out
    }
}

/// Minimum of 32 u8 lanes.
#[target_feature(enable = "avx2")]
#[inline]
fn hmin_u8(v: __m256i) -> i16 {
    let m = _mm_min_epu8(_mm256_castsi256_si128(v), _mm256_extracti128_si256::<1>(v));
    let m = _mm_min_epu8(m, _mm_srli_si128::<8>(m));
    _mm_cvtsi128_si32(_mm_minpos_epu16(_mm_cvtepu8_epi16(m))) as i16
}

/// [`pixel`] in u8 lanes, 32 disparities per register: the same recurrence with saturating u8
/// adds (every L is at most 255, see the module doc). The sums are kept in two i16 registers
/// in the order of the byte unpacks (disparities 0-7 and 16-23, then 8-15 and 24-31) and
/// reordered when stored; the lanes from D to D' get FAR sums.
///
/// # Safety
/// As [`pixel`], with `chunks` x 32 lanes of u8 for the paths and the costs.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn pixel_narrow<const NP: usize, const HELD: usize, const INIT: bool>(
    chunks: usize,
    cost: *const u8,
    init: *const i16,
    acc: *mut i16,
    paths: &Paths<NP, u8>,
    p1: __m256i,
    pads: &Pads,
) -> [i16; NP] {
    const W: usize = 32;
    // SAFETY: the caller guarantees the extents (see the doc above).
    unsafe {
        let zero = _mm256_setzero_si256();
        let mut mn = [_mm256_set1_epi8(-1); NP];
        let mut below: [__m256i; NP] = std::array::from_fn(|v| {
            _mm256_loadu_si256(paths.src[v].wrapping_sub(1).cast_const().cast())
        });
        let row = paths.src[NP - 1];
        let (mut lo, mut mid) = (
            _mm256_loadu_si256(row.sub(W).cast_const().cast()),
            _mm256_loadu_si256(row.cast_const().cast()),
        );
        for q in 0..chunks {
            let at = q * W;
            let mut c = _mm256_loadu_si256(cost.add(at).cast());
            let last = q + 1 == chunks;
            if last {
                c = _mm256_or_si256(c, pads.narrow);
            }
            let (mut s_lo, mut s_hi) = if INIT {
                let (i0, i1) = (
                    _mm256_loadu_si256(init.add(at).cast()),
                    _mm256_loadu_si256(init.add(at + 16).cast()),
                );
                (
                    _mm256_permute2x128_si256::<0x20>(i0, i1),
                    _mm256_permute2x128_si256::<0x31>(i0, i1),
                )
            } else {
                (zero, zero)
            };
            for (v, m) in mn.iter_mut().enumerate() {
                let s = paths.src[v].add(at);
                let (a, am, ap) = if v + 1 == NP {
                    along_row::<15, 1, _>(s, W, &mut lo, &mut mid)
                } else {
                    from_row(s, W, &mut below[v])
                };
                let best = _mm256_min_epu8(
                    _mm256_min_epu8(a, paths.jump[v]),
                    _mm256_adds_epu8(_mm256_min_epu8(am, ap), p1),
                );
                // best >= min(prev): the subtraction does not wrap.
                let l = _mm256_adds_epu8(c, _mm256_sub_epi8(best, paths.min_prev[v]));
                *m = _mm256_min_epu8(*m, l);
                s_lo = _mm256_adds_epi16(s_lo, _mm256_unpacklo_epi8(l, zero));
                s_hi = _mm256_adds_epi16(s_hi, _mm256_unpackhi_epi8(l, zero));
                if v == HELD {
                    _mm256_storeu_si256(s.cast(), _mm256_loadu_si256(paths.held.add(at).cast()));
                }
                _mm256_storeu_si256(paths.dst[v].add(at).cast(), l);
            }
            let mut o0 = _mm256_permute2x128_si256::<0x20>(s_lo, s_hi);
            let mut o1 = _mm256_permute2x128_si256::<0x31>(s_lo, s_hi);
            if last {
                o0 = _mm256_or_si256(o0, pads.sums[0]);
                o1 = _mm256_or_si256(o1, pads.sums[1]);
            }
            _mm256_storeu_si256(acc.add(at).cast(), o0);
            _mm256_storeu_si256(acc.add(at + 16).cast(), o1);
        }
        let mut out = [0i16; NP];
        for (o, m) in out.iter_mut().zip(mn) {
            *o = hmin_u8(m);
        }
        out
    }
}

/// NV paths from the previous row plus the path along the row (NP = NV + 1); path HELD of the
/// NV (none when >= NV) is held back a pixel.
#[target_feature(enable = "avx2,popcnt")]
#[inline]
#[allow(clippy::too_many_arguments)] // the pass's inputs, outputs and hooks
fn pass_n<K: Kind, const NV: usize, const NP: usize, const HELD: usize, const INIT: bool>(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    mut costs: Costs,
    out: &mut [i16],
    peer: Peer,
    mut after_row: impl FnMut(usize, &mut [i16]),
) {
    assert_eq!(NP, NV + 1);
    let (w, h, dp) = (ctx.w, ctx.h, ctx.dp);
    // A guard of one register's lanes before each segment (and after the last).
    let guard = K::LANES;
    let stride = guard + dp;
    assert!(dp.is_multiple_of(K::LANES));
    let chunks = dp / K::LANES;
    let mut vdx = [0isize; NV];
    vdx.copy_from_slice(ctx.vdx);
    let step_x: isize = if forward { 1 } else { -1 };
    assert!(HELD >= NV || vdx[HELD] == step_x);
    let row_len = w * dp;
    let whole = out.len() == h * row_len;
    let init = if INIT { init } else { None };
    assert!(out.len() >= row_len && init.is_none_or(|s| s.len() >= h * row_len));
    ps.begin_rows(ctx, NV);
    ps.cost_u8.clear();
    ps.cost_u8.resize(row_len, 0);
    size_paths(K::buffers(ps), NV * (w + 2), dp, guard, K::FAR);
    assert_eq!(ps.mins.len(), NV * (w + 2));
    let [paths_v, held_v, holding_v, row_v] = K::buffers(ps);
    assert_eq!(paths_v.len(), NV * (w + 2) * stride + guard);
    assert!(row_v.len() == stride + guard && held_v.len() == dp && holding_v.len() == dp);
    // The buffers are not resized during the pass.
    let (paths, row_path) = (paths_v.as_mut_ptr(), row_v.as_mut_ptr());
    let (mut held, mut holding) = (held_v.as_mut_ptr(), holding_v.as_mut_ptr());
    match &costs {
        Costs::Compute => {}
        Costs::Store(vol) => assert!(vol.len() >= h * row_len),
        Costs::Load(vol) => assert!(vol.len() >= h * row_len),
    }
    let pad = ctx.rev_pad();
    let unknown = ctx.p.unknown_cost();
    // The lanes from D to D' of the last chunk read the largest cost, so they never win.
    let pads = Pads::new(ctx, K::LANES);
    let loads_costs = matches!(costs, Costs::Load(_));
    let p1 = K::splat(ctx.p.p1 as i16);
    let table = ctx.p2_table();
    ps.p2_row.clear();
    ps.p2_row.resize(NP * w, 0);
    for k in 0..h {
        let y = if forward { k } else { h - 1 - k };
        // The row's costs as bytes (W x D'): computed into the row buffer, computed into the
        // volume kept for the other pass, or read from it.
        let cells = y * row_len..(y + 1) * row_len;
        let cost_row: *const u8 = match &mut costs {
            Costs::Compute => {
                // SAFETY: this pass only runs where AVX2 and POPCNT were detected.
                unsafe { cost_row(ctx, y, pad, unknown, &mut ps.rev, &mut ps.cost_u8) };
                ps.cost_u8.as_ptr()
            }
            Costs::Store(vol) => {
                let row = &mut vol[cells];
                // SAFETY: as above.
                unsafe { cost_row(ctx, y, pad, unknown, &mut ps.rev, row) };
                row.as_ptr()
            }
            Costs::Load(vol) => vol[cells].as_ptr(),
        };
        // The path along the row starts from zero (L = C at the border), and so does the
        // held-back L the first pixel stores over the border slot.
        // SAFETY: the row path holds guard + dp + guard lanes, `held` dp (asserted above; the
        // two buffers only swap).
        unsafe {
            std::ptr::write_bytes(row_path.add(guard), 0, dp);
            std::ptr::write_bytes(held, 0, dp);
        }
        let prev_y = if forward { y.wrapping_sub(1) } else { y + 1 };
        // P2 of each path into each pixel of the row: by the intensity step from the pixel it
        // comes from, 0 where that lies outside the image (a path start).
        let img_row = &ctx.img[y * w..(y + 1) * w];
        for (v, p2s) in ps.p2_row.chunks_exact_mut(w).enumerate() {
            let (dx, dy) = if v < NV {
                (vdx[v], prev_y)
            } else {
                (step_x, y)
            };
            if dy >= h {
                p2s.fill(0);
                continue;
            }
            if ctx.p.p2_adaptive {
                let from = &ctx.img[dy * w..(dy + 1) * w];
                for (x, (o, &g)) in p2s.iter_mut().zip(img_row).enumerate() {
                    let xp = x as isize - dx;
                    *o = if (0..w as isize).contains(&xp) {
                        table[usize::from(g.abs_diff(from[xp as usize]))]
                    } else {
                        0
                    };
                }
            } else {
                p2s.fill(table[0]);
                // The pixel whose predecessor lies beyond the row's end, if any.
                match dx {
                    1 => p2s[0] = 0,
                    -1 => p2s[w - 1] = 0,
                    _ => {}
                }
            }
        }
        let mut row_min = 0i16;
        let mut held_min = 0i16;
        let o = if whole { y * row_len } else { 0 };
        let out_row = &mut out[o..o + row_len];
        let mins = ps.mins.as_mut_ptr();
        let p2_row = ps.p2_row.as_ptr();
        let acc_row = out_row.as_mut_ptr();
        let init_row = init.map_or(std::ptr::null(), |s| s[y * row_len..].as_ptr());
        let peer_row = peer(y);
        for j in 0..w {
            let x = if forward { j } else { w - 1 - j };
            let zero = _mm256_setzero_si256();
            let mut pp = Paths::<NP, K::E> {
                src: [std::ptr::null_mut(); NP],
                dst: [std::ptr::null_mut(); NP],
                jump: [zero; NP],
                min_prev: [zero; NP],
                held,
            };
            let mut slot = [0usize; NV];
            // SAFETY: x < w, and slots s <= w + 1 of NV segments of `stride` lanes lie in
            // `paths` (sized by `begin`, with a trailing guard) and NV (w + 2) minima in
            // `mins`; the row path is one guarded slot, held and holding hold dp lanes, the
            // P2 rows NP x w entries, and the cell x * dp.. of the cost row, the sums and
            // `init` dp lanes. Each path's segment is its own; the held-back path writes to
            // `holding`.
            unsafe {
                for v in 0..NV {
                    // Slot of the previous pixel on this path: x - dx, shifted by the zero slot.
                    let s = (x as isize - vdx[v] + 1) as usize;
                    slot[v] = s;
                    let mp = *mins.add(v * (w + 2) + s);
                    let p2 = *p2_row.add(v * w + x);
                    pp.src[v] = paths.add((s * NV + v) * stride + guard);
                    pp.dst[v] = if v == HELD {
                        holding
                    } else {
                        paths.add(((x + 1) * NV + v) * stride + guard)
                    };
                    pp.jump[v] = K::splat(mp + p2);
                    pp.min_prev[v] = K::splat(mp);
                }
                // The row path's P2 is 0 at the row's first pixel (its predecessor is outside).
                let jump_h = row_min + *p2_row.add(NV * w + x);
                pp.src[NV] = row_path.add(guard);
                pp.dst[NV] = pp.src[NV];
                pp.jump[NV] = K::splat(jump_h);
                pp.min_prev[NV] = K::splat(row_min);
                if !INIT && !peer_row.is_null() && j + PREFETCH < w {
                    // The other pass's sums of this row, read when the row is done.
                    let xa = if forward { x + PREFETCH } else { x - PREFETCH };
                    let cell = peer_row.wrapping_add(xa * dp).cast::<i8>();
                    for line in (0..2 * dp).step_by(64) {
                        _mm_prefetch::<_MM_HINT_T0>(cell.wrapping_add(line));
                    }
                }
                if INIT && j + PREFETCH < w {
                    // The other pass's sums and the kept costs come from memory, against the
                    // address order in the backward pass: ask for a later pixel's cells now.
                    let xa = if forward { x + PREFETCH } else { x - PREFETCH };
                    let cell = init_row.wrapping_add(xa * dp).cast::<i8>();
                    for line in (0..2 * dp).step_by(64) {
                        _mm_prefetch::<_MM_HINT_T0>(cell.wrapping_add(line));
                    }
                    if loads_costs {
                        let cell = cost_row.wrapping_add(xa * dp).cast::<i8>();
                        for line in (0..dp).step_by(64) {
                            _mm_prefetch::<_MM_HINT_T0>(cell.wrapping_add(line));
                        }
                    }
                }
                let new_mins = K::pixel::<NP, HELD, INIT>(
                    chunks,
                    cost_row.add(x * dp),
                    init_row.wrapping_add(x * dp),
                    acc_row.add(x * dp),
                    &pp,
                    p1,
                    &pads,
                );
                for v in 0..NV {
                    if v == HELD {
                        // The previous pixel's L went over the slot just read: so does its min.
                        *mins.add(v * (w + 2) + slot[v]) = held_min;
                        held_min = new_mins[v];
                    } else {
                        *mins.add(v * (w + 2) + x + 1) = new_mins[v];
                    }
                }
                row_min = new_mins[NV];
            }
            std::mem::swap(&mut held, &mut holding);
        }
        if HELD < NV {
            // The last pixel's held-back L goes to its slot.
            let x_last = if forward { w - 1 } else { 0 };
            // SAFETY: slot x_last + 1 of segment HELD lies in `paths`, `held` holds dp lanes,
            // and the minima NV (w + 2).
            unsafe {
                let s = ((x_last + 1) * NV + HELD) * stride + guard;
                std::ptr::copy_nonoverlapping(held, paths.add(s), dp);
                *mins.add(HELD * (w + 2) + x_last + 1) = held_min;
            }
        }
        after_row(y, out_row);
    }
}

/// Popcount of each u64 lane (in the low 16 bits of the lane) by a nibble table.
#[target_feature(enable = "avx2")]
#[inline]
fn popcnt64(v: __m256i, table: __m256i, low: __m256i) -> __m256i {
    let lo = _mm256_and_si256(v, low);
    let hi = _mm256_and_si256(_mm256_srli_epi16::<4>(v), low);
    let bytes = _mm256_add_epi8(
        _mm256_shuffle_epi8(table, lo),
        _mm256_shuffle_epi8(table, hi),
    );
    _mm256_sad_epu8(bytes, _mm256_setzero_si256())
}

/// [`crate::aggregate::cost_row`] 16 disparities at a time, as bytes: the Hamming distances of
/// four candidates per register, packed to 16 lanes in disparity order. The lanes from D to D'
/// are left as computed: the pass reads them as FAR. With AVX-512 ([`Ctx::avx512`]) the
/// distances of eight candidates per register come from one population-count instruction
/// ([`crate::avx512::cost_chunks`]).
///
/// # Safety
/// The CPU has AVX2 (and the AVX-512 extensions of [`crate::simd::Level::Avx512`] when
/// `ctx.avx512`); `rev` holds `w + 2 * pad + LANES` entries and `cost` W x D' bytes.
#[target_feature(enable = "avx2")]
unsafe fn cost_row(ctx: &Ctx, y: usize, pad: usize, unknown: u8, rev: &mut [u64], cost: &mut [u8]) {
    if ctx.avx512 {
        // SAFETY: forwarded; the AVX-512 extensions are present when `ctx.avx512` is set.
        unsafe { crate::avx512::cost_row(ctx, y, pad, unknown, rev, cost) }
    } else {
        // SAFETY: forwarded.
        unsafe {
            cost_row_with(ctx, y, pad, unknown, rev, cost, |src, c, dst, chunks| {
                cost_chunks(src, c, dst, chunks)
            })
        }
    }
}

/// The Hamming distances of census `c` to the `chunks` x 16 candidates at `src`, as bytes to
/// `dst`, four candidates per register.
///
/// # Safety
/// `chunks` x 16 entries at `src` and bytes at `dst` are valid.
#[target_feature(enable = "avx2")]
#[inline]
unsafe fn cost_chunks(src: *const u64, c: u64, dst: *mut u8, chunks: usize) {
    let table = _mm256_setr_epi8(
        0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4, //
        0, 1, 1, 2, 1, 2, 2, 3, 1, 2, 2, 3, 2, 3, 3, 4,
    );
    let low = _mm256_set1_epi8(0x0f);
    let order = _mm256_setr_epi32(0, 4, 1, 5, 2, 6, 3, 7);
    let cv = _mm256_set1_epi64x(c as i64);
    // SAFETY: the caller guarantees the extents.
    unsafe {
        for q in 0..chunks {
            let at = q * LANES;
            let count = |i: usize| {
                let r = _mm256_loadu_si256(src.add(at + 4 * i).cast());
                popcnt64(_mm256_xor_si256(r, cv), table, low)
            };
            // Lanes (d0, d1 | d2, d3), (d4, d5 | d6, d7), ... as u64; two 32-bit packs give
            // (d0 d1 d4 d5 d8 d9 d12 d13 | d2 d3 d6 d7 d10 d11 d14 d15), and a permutation of
            // the 32-bit pairs restores the order; then 16 bytes from the low quadwords of
            // both halves.
            let p01 = _mm256_packus_epi32(count(0), count(1));
            let p23 = _mm256_packus_epi32(count(2), count(3));
            let v = _mm256_permutevar8x32_epi32(_mm256_packus_epi32(p01, p23), order);
            let b = _mm256_permute4x64_epi64::<0b1000>(_mm256_packus_epi16(v, v));
            _mm_storeu_si128(dst.add(at).cast(), _mm256_castsi256_si128(b));
        }
    }
}

/// A row of matching costs: the right census row reversed into `rev`, each pixel's `dp`
/// candidates by `chunks(src, census, dst, dp / LANES)`, then its invalid disparities at
/// `unknown`. Inlined into the callers, whose target features apply.
///
/// # Safety
/// `chunks` reads `dp` entries at `src` and writes `dp` bytes at `dst`; `rev` holds
/// `w + 2 * pad + LANES` entries and `cost` W x D' bytes.
#[inline(always)]
pub(crate) unsafe fn cost_row_with(
    ctx: &Ctx,
    y: usize,
    pad: usize,
    unknown: u8,
    rev: &mut [u64],
    cost: &mut [u8],
    chunks: impl Fn(*const u64, u64, *mut u8, usize),
) {
    let (w, nd, dp) = (ctx.w, ctx.nd, ctx.dp);
    let dmin = ctx.p.min_disparity as isize;
    let cr = &ctx.cr[y * w..(y + 1) * w];
    assert!(rev.len() >= w + 2 * pad + LANES && cost.len() >= w * dp);
    // rev[pad + w - 1 - xr] = cr[xr]: the partners of x are contiguous in d (see cost_row).
    for (xr, &c) in cr.iter().enumerate() {
        rev[pad + w - 1 - xr] = c;
    }
    for (x, &c) in ctx.cl[y * w..(y + 1) * w].iter().enumerate() {
        let t0 = (pad as isize + w as isize - 1 - x as isize + dmin) as usize;
        // t0 + dp <= w + 2 * pad + LANES (t0 <= pad + w - 1 + dmin, dp < nd + LANES,
        // pad >= nd + |dmin| + 1) and the cell x * dp.. holds dp bytes (asserted above).
        chunks(
            rev[t0..].as_ptr(),
            c,
            cost[x * dp..].as_mut_ptr(),
            dp / LANES,
        );
        let cell = &mut cost[x * dp..x * dp + nd];
        // Valid d: 0 <= x - d - dmin < w.
        let hi = x as isize - dmin; // largest valid d
        let lo = x as isize - dmin - w as isize + 1; // smallest valid d
        let first_bad_hi = (hi + 1).clamp(0, nd as isize) as usize;
        let end_bad_lo = lo.clamp(0, nd as isize) as usize;
        // Most pixels have no invalid disparity: no call to fill (a `memset` call per pixel,
        // even of nothing, took 4 % of the two-thread SGM).
        if first_bad_hi < nd {
            cell[first_bad_hi..].fill(unknown);
        }
        if end_bad_lo > 0 {
            cell[..end_bad_lo].fill(unknown);
        }
    }
}
