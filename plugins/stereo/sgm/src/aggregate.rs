//! The two aggregation passes of the fast SGM path (see [`crate::sgm`]): matching costs one row
//! at a time, 16 disparities per step in i16 lanes, the previous row of each path updated in place.

use crate::sgm::SgmParams;

/// Disparities per SIMD step: 16 i16 lanes, one AVX2 register.
pub(crate) const LANES: usize = 16;
/// Lanes (at FAR) before each pixel's disparities in the path buffers, so the d - 1 and d + 1
/// neighbours of every step are plain loads.
pub(crate) const GUARD: usize = LANES;
/// Cost of the padding lanes beyond `max_disparity`: saturating adds keep them at FAR, so they
/// never win a minimum.
pub(crate) const FAR: i16 = i16::MAX;

/// Row buffers of one aggregation pass.
#[derive(Default)]
pub(crate) struct PassScratch {
    /// Costs of the current row, W x D' (padding lanes FAR).
    pub(crate) cost: Vec<i16>,
    /// The right census row reversed and padded, so one pixel's candidates are contiguous.
    pub(crate) rev: Vec<u64>,
    /// Paths from the previous row (NV = 3 with 8 paths, 1 with 4): W + 2 slots of NV segments
    /// of GUARD + D' lanes (the paths of one pixel side by side, one memory stream); slots 0
    /// and W + 1 are zero, the start of a path at the image border.
    pub(crate) paths: Vec<i16>,
    /// Minimum over d of each slot of `paths`.
    pub(crate) mins: Vec<i16>,
    /// The L held back a pixel (see [`pass_n`]): the previous pixel's, and this pixel's.
    pub(crate) held: Vec<i16>,
    pub(crate) holding: Vec<i16>,
    /// The path along the row: the previous pixel's L, overwritten in place (one guarded slot).
    pub(crate) row_path: Vec<i16>,
    /// P2 of each path into each pixel of the current row (AVX2 pass): NV + 1 rows of W.
    pub(crate) p2_row: Vec<i16>,
    /// Costs of the current row as bytes, W x D' (AVX2 pass, when they are not kept).
    pub(crate) cost_u8: Vec<u8>,
    /// `paths`, `held`, `holding` and `row_path` in u8 lanes for the AVX2 pass with narrow
    /// lanes (guards of 32 lanes at 255).
    pub(crate) paths8: Vec<u8>,
    pub(crate) held8: Vec<u8>,
    pub(crate) holding8: Vec<u8>,
    pub(crate) row_path8: Vec<u8>,
}

impl PassScratch {
    /// Sizes and resets the buffers for a pass with `nv` paths from the previous row.
    pub(crate) fn begin(&mut self, ctx: &Ctx, nv: usize) {
        self.begin_rows(ctx, nv);
        let bufs = [
            &mut self.paths,
            &mut self.held,
            &mut self.holding,
            &mut self.row_path,
        ];
        size_paths(bufs, nv * (ctx.w + 2), ctx.dp, GUARD, FAR);
        self.cost.clear();
        self.cost.resize(ctx.w * ctx.dp, FAR);
    }

    /// Sizes and resets what every pass uses whatever its lanes: the minima of the paths from
    /// the previous row and the reversed right census row.
    pub(crate) fn begin_rows(&mut self, ctx: &Ctx, nv: usize) {
        self.mins.clear();
        self.mins.resize(nv * (ctx.w + 2), 0);
        // LANES more at the end: the SIMD costs read whole chunks of candidates.
        self.rev.clear();
        self.rev.resize(ctx.w + 2 * ctx.rev_pad() + LANES, 0);
    }

    /// Starts row `y`: its matching costs, and the path along the row from zero at the border
    /// (L = C).
    #[inline(always)]
    pub(crate) fn start_row(&mut self, ctx: &Ctx, y: usize, costs: &mut Costs) {
        self.row_costs(ctx, y, costs);
        self.row_path.clear();
        push_paths(&mut self.row_path, 1, ctx.dp, GUARD, FAR);
    }

    /// Ends a row: the last pixel's held-back L (path `v` of `nv`, minimum `held_min`) goes to
    /// its slot.
    pub(crate) fn flush_held(
        &mut self,
        ctx: &Ctx,
        nv: usize,
        v: usize,
        forward: bool,
        held_min: i16,
    ) {
        let (w, dp) = (ctx.w, ctx.dp);
        let x_last = if forward { w - 1 } else { 0 };
        let s = ((x_last + 1) * nv + v) * ctx.stride() + GUARD;
        self.paths[s..s + dp].copy_from_slice(&self.held);
        self.mins[v * (w + 2) + x_last + 1] = held_min;
    }

    /// The matching costs of row `y` into `self.cost` (W x D', padding lanes FAR). Inlined, so
    /// the caller's target features (POPCNT) apply.
    #[inline(always)]
    pub(crate) fn row_costs(&mut self, ctx: &Ctx, y: usize, costs: &mut Costs) {
        let (w, nd, dp) = (ctx.w, ctx.nd, ctx.dp);
        let pad = ctx.rev_pad();
        let unknown = i16::from(ctx.p.unknown_cost());
        match costs {
            Costs::Compute => cost_row(ctx, y, pad, unknown, &mut self.rev, &mut self.cost),
            Costs::Store(vol) => {
                cost_row(ctx, y, pad, unknown, &mut self.rev, &mut self.cost);
                let dst = &mut vol[y * w * dp..(y + 1) * w * dp];
                for (d, c) in dst.chunks_exact_mut(dp).zip(self.cost.chunks_exact(dp)) {
                    for (o, &v) in d[..nd].iter_mut().zip(c) {
                        *o = v as u8;
                    }
                }
            }
            Costs::Load(vol) => {
                let src = &vol[y * w * dp..(y + 1) * w * dp];
                for (c, d) in self.cost.chunks_exact_mut(dp).zip(src.chunks_exact(dp)) {
                    for (o, &v) in c[..nd].iter_mut().zip(d) {
                        *o = i16::from(v);
                    }
                }
            }
        }
    }
}

/// One step of the path recurrence for all disparities:
/// `out[d] = cost[d] + min(prev[d], prev[d-1] + p1, prev[d+1] + p1, min(prev) + p2) - min(prev)`.
/// The scalar statement of what the SIMD passes compute (and the reference uses).
#[inline]
pub fn path_step(cost: &[u8], prev: &[u16], p1: u16, p2: u16, out: &mut [u16]) {
    let n = cost.len();
    if n == 0 {
        return;
    }
    let min_prev = prev.iter().copied().min().unwrap_or(0);
    let jump = min_prev.saturating_add(p2);
    let edge = |d: usize, other: u16| prev[d].min(jump).min(other.saturating_add(p1));
    if n == 1 {
        out[0] = cost[0] as u16 + (prev[0].min(jump) - min_prev);
        return;
    }
    out[0] = cost[0] as u16 + (edge(0, prev[1]) - min_prev);
    out[n - 1] = cost[n - 1] as u16 + (edge(n - 1, prev[n - 2]) - min_prev);
    for ((o, &c), w) in out[1..n - 1]
        .iter_mut()
        .zip(&cost[1..n - 1])
        .zip(prev.windows(3))
    {
        let best = w[1]
            .min(jump)
            .min(w[0].saturating_add(p1))
            .min(w[2].saturating_add(p1));
        *o = c as u16 + (best - min_prev);
    }
}

/// Where a pass finds, at the start of row y, a row of W x D' sums it will read when the row
/// is done (the other pass's, already published): the AVX2 pass prefetches it pixel by pixel
/// while it aggregates, so that the read finds it in the cache. Null: none.
pub(crate) type Peer<'a> = &'a (dyn Fn(usize) -> *const i16 + Sync);

/// No row to prefetch.
pub(crate) const NO_PEER: Peer<'static> = &|_| std::ptr::null();

/// What both passes read.
pub(crate) struct Ctx<'a> {
    pub(crate) img: &'a [u8],
    pub(crate) cl: &'a [u64],
    pub(crate) cr: &'a [u64],
    pub(crate) w: usize,
    pub(crate) h: usize,
    pub(crate) nd: usize,
    /// D rounded up to LANES.
    pub(crate) dp: usize,
    pub(crate) p: &'a SgmParams,
    /// dx of the paths that come from the previous row.
    pub(crate) vdx: &'a [isize],
    /// The AVX2 pass runs the paths in u8 lanes (C_max + P2 <= 255; D' a multiple of 32).
    pub(crate) narrow: bool,
    /// The AVX2 pass may use the AVX-512 kernels ([`crate::simd::Level::Avx512`]).
    pub(crate) avx512: bool,
}

impl Ctx<'_> {
    pub(crate) fn stride(&self) -> usize {
        GUARD + self.dp
    }

    /// Entries on each side of the reversed right census row (see [`cost_row`]).
    pub(crate) fn rev_pad(&self) -> usize {
        self.nd + self.p.min_disparity.unsigned_abs() as usize + 1
    }

    /// P2 for each intensity step 0..=255 (see [`SgmParams::p2_at`]).
    pub(crate) fn p2_table(&self) -> [i16; 256] {
        std::array::from_fn(|step| self.p.p2_at(step as u16) as i16)
    }

    /// P2 between a pixel of gray level `g` and its predecessor (xp, yp) on a path; 0 when the
    /// predecessor is outside the image (a path start: min(prev) = 0 and every term is >= 0,
    /// so P2 plays no part).
    #[inline(always)]
    pub(crate) fn p2_from(&self, g: u8, xp: usize, yp: usize) -> i16 {
        if xp < self.w && yp < self.h {
            self.p
                .p2_at(u16::from(g.abs_diff(self.img[yp * self.w + xp]))) as i16
        } else {
            0
        }
    }
}

/// Where a pass gets its matching costs: computed from the census images, computed and kept
/// (H x W x D' u8, the lanes from D to D' unused) for the other pass, or read from that volume.
pub(crate) enum Costs<'a> {
    Compute,
    Store(&'a mut [u8]),
    Load(&'a [u8]),
}

/// One aggregation pass: forward runs rows top-down and pixels left to right with the paths
/// from above and from the left; backward the mirror. Each row's sums (plus `init`'s, when given)
/// go to `out` (the whole image, or one row buffer), then `after_row(y, row)` runs; `peer(y)`
/// names a row to prefetch meanwhile (see [`Peer`]).
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
    #[cfg(target_arch = "x86_64")]
    if crate::simd::avx2() {
        // SAFETY: the CPU supports AVX2 and POPCNT (checked just above).
        unsafe { crate::aggregate_avx2::pass(forward, ctx, ps, init, costs, out, peer, after_row) };
        return;
    }
    let _ = peer;
    if ctx.vdx.len() == 3 {
        pass_n::<3>(forward, ctx, ps, init, costs, out, after_row);
    } else {
        pass_n::<1>(forward, ctx, ps, init, costs, out, after_row);
    }
}

/// 16 lanes of `s` from `at`.
#[inline(always)]
pub(crate) fn lanes(s: &[i16], at: usize) -> &[i16; LANES] {
    s[at..at + LANES]
        .try_into()
        .unwrap_or_else(|_| unreachable!("a slice of LANES elements"))
}

#[inline(always)]
pub(crate) fn lanes_mut(s: &mut [i16], at: usize) -> &mut [i16; LANES] {
    (&mut s[at..at + LANES])
        .try_into()
        .unwrap_or_else(|_| unreachable!("a slice of LANES elements"))
}

/// The recurrence on 16 disparities, from the previous pixel's L at d - 16.. (`lo`), d..
/// (`a`) and d + 16.. (`hi`): returns L, folds it into the running minimum `mn` and adds it to
/// `acc`.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn step(
    cost: &[i16; LANES],
    lo: &[i16; LANES],
    a: &[i16; LANES],
    hi: &[i16; LANES],
    min_prev: i16,
    p1: i16,
    jump: i16,
    mn: &mut [i16; LANES],
    acc: &mut [i16; LANES],
) -> [i16; LANES] {
    let am: [i16; LANES] = std::array::from_fn(|l| if l == 0 { lo[LANES - 1] } else { a[l - 1] });
    let ap: [i16; LANES] = std::array::from_fn(|l| if l == LANES - 1 { hi[0] } else { a[l + 1] });
    let mut out = [0i16; LANES];
    for l in 0..LANES {
        let best = a[l]
            .min(am[l].saturating_add(p1))
            .min(ap[l].saturating_add(p1))
            .min(jump);
        let v = cost[l].saturating_add(best - min_prev);
        out[l] = v;
        mn[l] = mn[l].min(v);
        acc[l] = acc[l].saturating_add(v);
    }
    out
}

/// Appends `slots` path slots: `guard` lanes at `far`, then D' disparities at 0 (a path start:
/// L = C), and a trailing guard.
fn push_paths<T: Copy + Default>(buf: &mut Vec<T>, slots: usize, dp: usize, guard: usize, far: T) {
    for _ in 0..slots {
        buf.extend(std::iter::repeat_n(far, guard));
        buf.extend(std::iter::repeat_n(T::default(), dp));
    }
    buf.extend(std::iter::repeat_n(far, guard));
}

/// Sizes and resets one kind of path buffers, `[paths, held, holding, row path]`: `slots`
/// guarded slots of the paths from the previous row, one of the path along the row, and D'
/// zeros for the two held-back L.
pub(crate) fn size_paths<T: Copy + Default>(
    [paths, held, holding, row_path]: [&mut Vec<T>; 4],
    slots: usize,
    dp: usize,
    guard: usize,
    far: T,
) {
    paths.clear();
    push_paths(paths, slots, dp, guard, far);
    row_path.clear();
    push_paths(row_path, 1, dp, guard, far);
    for b in [held, holding] {
        b.clear();
        b.resize(dp, T::default());
    }
}

/// The pass with `NV` paths from the previous row (3 with 8 paths, 1 with 4) and one along the
/// row. The previous-row paths are updated in place: pixel x reads slot x - dx + 1 and its new
/// L goes to slot x + 1 once the pixel is done; for the path whose dx equals the traversal step
/// the next pixel still needs the old slot x + 1, so that write waits one pixel.
#[inline(always)]
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
    let mut vdx = [0isize; NV];
    vdx.copy_from_slice(ctx.vdx);
    let step_x: isize = if forward { 1 } else { -1 };
    let row_len = w * dp;
    let whole = out.len() == h * row_len;
    ps.begin(ctx, NV);
    let p1 = p.p1 as i16;
    for k in 0..h {
        let y = if forward { k } else { h - 1 - k };
        ps.start_row(ctx, y, &mut costs);
        let mut row_min = 0i16;
        let mut held_min = 0i16;
        let prev_y = if forward { y.wrapping_sub(1) } else { y + 1 };
        let o = if whole { y * row_len } else { 0 };
        let out_row = &mut out[o..o + row_len];
        for j in 0..w {
            let x = if forward { j } else { w - 1 - j };
            let g = ctx.img[y * w + x];
            let p2_from = |xp: usize, yp: usize| ctx.p2_from(g, xp, yp);
            let mut slot = [0usize; NV];
            let mut jump = [0i16; NV];
            let mut min_prev = [0i16; NV];
            for v in 0..NV {
                // Slot of the previous pixel on this path: x - dx, shifted by the zero slot.
                let s = (x as isize - vdx[v] + 1) as usize;
                slot[v] = s;
                min_prev[v] = ps.mins[v * (w + 2) + s];
                let p2 = if k == 0 {
                    0
                } else {
                    p2_from(s.wrapping_sub(1), prev_y)
                };
                jump[v] = min_prev[v] + p2;
            }
            let xh = if forward { x.wrapping_sub(1) } else { x + 1 };
            let jump_h = row_min + if j == 0 { 0 } else { p2_from(xh, y) };
            let init_cell = init.map(|s| &s[y * row_len + x * dp..y * row_len + (x + 1) * dp]);
            // The row of sums starts from `init` (the other pass's sums) or zero.
            let acc_row = &mut out_row[x * dp..(x + 1) * dp];
            match init_cell {
                Some(s) => acc_row.copy_from_slice(s),
                None => acc_row.fill(0),
            }
            let chunks = dp / LANES;
            // One path at a time over all disparities, so its window of the previous L stays in
            // registers: three aligned chunks (d - 16.., d.., d + 16..) that roll along d, so a
            // chunk can be overwritten in place once read; the d - 1 and d + 1 neighbours are
            // shuffled from them.
            for v in 0..NV {
                let base = (slot[v] * NV + v) * stride + GUARD;
                let delayed = vdx[v] == step_x;
                let own = ((x + 1) * NV + v) * stride + GUARD;
                let (mut lo, mut a) = (*lanes(&ps.paths, base - LANES), *lanes(&ps.paths, base));
                let mut mn = [FAR; LANES];
                for q in 0..chunks {
                    let at = q * LANES;
                    let hi = *lanes(&ps.paths, base + at + LANES);
                    let c = lanes(&ps.cost, x * dp + at);
                    let acc = lanes_mut(acc_row, at);
                    let l = step(c, &lo, &a, &hi, min_prev[v], p1, jump[v], &mut mn, acc);
                    (lo, a) = (a, hi);
                    if delayed {
                        // Slot x + 1 is the next pixel's predecessor: the previous pixel's L
                        // goes into the slot this pixel reads (chunk by chunk, once read) and
                        // this one is held back.
                        if j > 0 {
                            *lanes_mut(&mut ps.paths, base + at) = *lanes(&ps.held, at);
                        }
                        *lanes_mut(&mut ps.holding, at) = l;
                    } else {
                        *lanes_mut(&mut ps.paths, own + at) = l;
                    }
                }
                let new_min = mn.iter().copied().fold(FAR, i16::min);
                if delayed {
                    if j > 0 {
                        ps.mins[v * (w + 2) + slot[v]] = held_min;
                    }
                    held_min = new_min;
                } else {
                    ps.mins[v * (w + 2) + x + 1] = new_min;
                }
            }
            let (mut lo, mut a) = (*lanes(&ps.row_path, 0), *lanes(&ps.row_path, GUARD));
            let mut mn = [FAR; LANES];
            for q in 0..chunks {
                let at = q * LANES;
                let hi = *lanes(&ps.row_path, GUARD + at + LANES);
                let c = lanes(&ps.cost, x * dp + at);
                let acc = lanes_mut(acc_row, at);
                let l = step(c, &lo, &a, &hi, row_min, p1, jump_h, &mut mn, acc);
                (lo, a) = (a, hi);
                *lanes_mut(&mut ps.row_path, GUARD + at) = l;
            }
            row_min = mn.iter().copied().fold(FAR, i16::min);
            std::mem::swap(&mut ps.held, &mut ps.holding);
        }
        if let Some(v) = vdx.iter().position(|&dx| dx == step_x) {
            ps.flush_held(ctx, NV, v, forward, held_min);
        }
        after_row(y, out_row);
    }
}

/// Hamming costs of row `y` for every pixel and disparity into `cost` (W x D', padding lanes
/// untouched at FAR); a partner outside the right image costs `unknown`.
#[inline(always)]
pub(crate) fn cost_row(
    ctx: &Ctx,
    y: usize,
    pad: usize,
    unknown: i16,
    rev: &mut [u64],
    cost: &mut [i16],
) {
    let (w, nd, dp) = (ctx.w, ctx.nd, ctx.dp);
    let dmin = ctx.p.min_disparity as isize;
    let cr = &ctx.cr[y * w..(y + 1) * w];
    // rev[pad + w - 1 - xr] = cr[xr]: for a left pixel x the partners x - d - dmin, d = 0.., are
    // rev[pad + w - 1 - x + dmin + d], contiguous in d.
    for (xr, &c) in cr.iter().enumerate() {
        rev[pad + w - 1 - xr] = c;
    }
    for (x, &c) in ctx.cl[y * w..(y + 1) * w].iter().enumerate() {
        let t0 = (pad as isize + w as isize - 1 - x as isize + dmin) as usize;
        let cell = &mut cost[x * dp..x * dp + nd];
        for (o, &r) in cell.iter_mut().zip(&rev[t0..t0 + nd]) {
            *o = (c ^ r).count_ones() as i16;
        }
        // Valid d: 0 <= x - d - dmin < w.
        let hi = x as isize - dmin; // largest valid d
        let lo = x as isize - dmin - w as isize + 1; // smallest valid d
        let first_bad_hi = (hi + 1).clamp(0, nd as isize) as usize;
        cell[first_bad_hi..].fill(unknown);
        let end_bad_lo = lo.clamp(0, nd as isize) as usize;
        cell[..end_bad_lo].fill(unknown);
    }
}
