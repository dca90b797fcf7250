//! Semi-global matching (Hirschmueller, PAMI 2008) on rectified gray images, as a plain library:
//! census transform, Hamming matching cost, path-wise aggregation with P1/P2, winner-takes-all
//! with a uniqueness margin and a sub-pixel parabola, right disparities from the same aggregated
//! cost along the diagonals, left-right check, 3x3 median and speckle removal.
//!
//! The fast path aggregates in two passes, as OpenCV's full-size mode does: a forward pass
//! (top-down, left to right) runs the paths that come from above and from the left, a backward
//! pass the other half. Each pass computes the Hamming costs of one row at a time from the census
//! images (no cost volume), keeps only the previous row of each path, and handles 16 disparities
//! per step in i16 lanes (AVX2 when the CPU has it, chosen at run time; SSE2 otherwise). Only the
//! forward pass's sums are stored (H x W x D' i16, D' = D rounded up to 16); the backward pass adds
//! its own and selects the disparities of each row as it completes. With two or more threads the
//! passes run side by side into two sum buffers. The result is bit-identical to the one-pass-per-
//! direction transcription in [`crate::reference`] (tested).
//!
//! Memory: the sums and the census images live in a [`Scratch`] the caller reuses across frames.

use rayon::prelude::*;

/// Bound on P2 so that eight paths of at most 64 + P2 fit an i16.
pub const MAX_P2: u16 = 4000;

/// Parameters of SGM (and of the `depth.sgm` plugin: `misslam plugins depth.sgm` prints these docs).
#[derive(
    Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(deny_unknown_fields, default)]
pub struct SgmParams {
    /// Number of disparities searched, starting at `min_disparity`.
    pub max_disparity: u32,
    /// Smallest disparity searched, px.
    pub min_disparity: i32,
    /// Census window width (odd).
    pub census_width: u32,
    /// Census window height (odd); width x height - 1 must not exceed 64.
    pub census_height: u32,
    /// Aggregation paths: 4 or 8.
    pub paths: u32,
    /// Penalty for a disparity change of one pixel between neighbours (census cost units, 0..63).
    pub p1: u16,
    /// Penalty for larger changes; must exceed `p1` and be at most 4000 (the sums of eight paths
    /// are kept in 16-bit lanes; census costs are at most 64, typical P2 values 50 to 300).
    pub p2: u16,
    /// Divide P2 by the intensity step along each path (Hirschmueller's edge-aware P2), never below P1 + 1.
    pub p2_adaptive: bool,
    /// Uniqueness margin, %: the best aggregated cost must beat the second best (beyond +-1 px) by this much.
    pub uniqueness_pct: u32,
    /// Sub-pixel refinement by a parabola through the costs at d-1, d, d+1.
    pub subpixel: bool,
    /// Left-right consistency check (right disparities from the same aggregated cost).
    pub lr_check: bool,
    /// Largest left-right disagreement kept, px.
    pub lr_max_diff: f32,
    /// 3x3 median filter of the valid disparities.
    pub median: bool,
    /// Remove connected regions smaller than this many pixels (0: off).
    pub speckle_window: u32,
    /// Neighbours within this disparity difference belong to one region, px.
    pub speckle_range: f32,
    /// Where the `depth.sgm` node runs it: "cpu", "gpu" (WGSL kernels; an error without an
    /// adapter) or "auto" (the GPU when an adapter exists). The library function [`sgm`] is
    /// the CPU path; [`crate::gpu::SgmGpu`] the GPU one.
    pub device: misslam_framework::gpu::Device,
}

impl Default for SgmParams {
    fn default() -> Self {
        SgmParams {
            max_disparity: 64,
            min_disparity: 0,
            census_width: 9,
            census_height: 7,
            paths: 8,
            p1: 10,
            p2: 120,
            p2_adaptive: false,
            uniqueness_pct: 5,
            subpixel: true,
            lr_check: true,
            lr_max_diff: 1.0,
            median: true,
            speckle_window: 100,
            speckle_range: 2.0,
            device: misslam_framework::gpu::Device::Cpu,
        }
    }
}

impl SgmParams {
    /// Checks the parameters; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_disparity < 2 || self.max_disparity > 1024 {
            return Err(format!(
                "`max_disparity` must be in 2..=1024, got {}",
                self.max_disparity
            ));
        }
        if self.census_width.is_multiple_of(2)
            || self.census_height.is_multiple_of(2)
            || self.census_width < 3
            || self.census_height < 3
        {
            return Err("`census_width` and `census_height` must be odd and at least 3".into());
        }
        if self.census_width * self.census_height - 1 > 64 {
            return Err(format!(
                "a {}x{} census window has more than 64 comparisons",
                self.census_width, self.census_height
            ));
        }
        if self.paths != 4 && self.paths != 8 {
            return Err(format!("`paths` must be 4 or 8, got {}", self.paths));
        }
        if self.p2 <= self.p1 {
            return Err(format!("`p2` ({}) must exceed `p1` ({})", self.p2, self.p1));
        }
        if self.p2 > MAX_P2 {
            // Eight paths of at most 64 + P2 each must fit the i16 lanes of the fast path.
            return Err(format!("`p2` must be at most {MAX_P2}, got {}", self.p2));
        }
        if self.uniqueness_pct > 1000 {
            return Err(format!(
                "`uniqueness_pct` must be at most 1000, got {}",
                self.uniqueness_pct
            ));
        }
        let non_negative = |v: f32| v.is_finite() && v >= 0.0;
        if !non_negative(self.lr_max_diff) || !non_negative(self.speckle_range) {
            return Err("`lr_max_diff` and `speckle_range` must be >= 0".into());
        }
        Ok(())
    }

    /// Cost of a match whose partner lies outside the right image: half the maximum, so it
    /// neither attracts nor repels. The paths carry the disparity in from where it can be
    /// measured, and the left-right check then rejects the pixel (its partner is outside the
    /// image). Scoring it as the maximum instead pulls the left band towards zero disparity,
    /// which the left-right check cannot catch.
    pub fn unknown_cost(&self) -> u8 {
        ((self.census_width * self.census_height - 1) / 2) as u8
    }

    /// P2 for a step of `step` gray levels between a pixel and its predecessor on a path.
    #[inline]
    pub fn p2_at(&self, step: u16) -> u16 {
        if self.p2_adaptive {
            (self.p2 / step.max(1)).max(self.p1 + 1)
        } else {
            self.p2
        }
    }
}

/// Disparities per SIMD step: 16 i16 lanes, one AVX2 register.
const LANES: usize = 16;
/// Lanes (at FAR) before each pixel's disparities in the path buffers, so the d - 1 and d + 1
/// neighbours of every step are plain loads.
const GUARD: usize = LANES;
/// Cost of the padding lanes beyond `max_disparity`: saturating adds keep them at FAR, so they
/// never win a minimum.
const FAR: i16 = i16::MAX;

/// Buffers reused across frames.
#[derive(Default)]
pub struct Scratch {
    census_l: Vec<u64>,
    census_r: Vec<u64>,
    /// Forward-pass sums, H x W x D' (and the backward pass's with two threads).
    sum_f: Vec<i16>,
    sum_b: Vec<i16>,
    pass_f: PassScratch,
    pass_b: PassScratch,
    /// Right-image disparities for the left-right check.
    right: Vec<f32>,
    /// One row of sums for the backward pass when it selects as it goes.
    row: Vec<i16>,
    right_scratch: RightScratch,
    /// Matching costs kept by the forward pass for the backward one (one thread).
    cost_vol: Vec<u8>,
    speckle: SpeckleScratch,
}

/// Row buffers of one aggregation pass.
#[derive(Default)]
struct PassScratch {
    /// Costs of the current row, W x D' (padding lanes FAR).
    cost: Vec<i16>,
    /// The right census row reversed and padded, so one pixel's candidates are contiguous.
    rev: Vec<u64>,
    /// Paths from the previous row (NV = 3 with 8 paths, 1 with 4): W + 2 slots of NV segments
    /// of GUARD + D' lanes (the paths of one pixel side by side, one memory stream); slots 0
    /// and W + 1 are zero, the start of a path at the image border.
    paths: Vec<i16>,
    /// Minimum over d of each slot of `paths`.
    mins: Vec<i16>,
    /// The L held back a pixel (see [`pass_n`]): the previous pixel's, and this pixel's.
    held: Vec<i16>,
    holding: Vec<i16>,
    /// The path along the row: the previous pixel's L, overwritten in place (one guarded slot).
    row_path: Vec<i16>,
}

/// Census transform: bit k is set when neighbour k of the window (row by row, the centre
/// skipped, the first neighbour in the highest bit) is darker than the centre. Neighbours outside
/// the image count as equal to the centre (bit 0).
pub fn census(img: &[u8], w: usize, h: usize, cw: usize, ch: usize, out: &mut Vec<u64>) {
    let (rx, ry) = (cw / 2, ch / 2);
    // Pad with 255: "255 < centre" is never true, the same bit 0 as "equal to the centre".
    let pw = w + 2 * rx;
    let mut pad = vec![255u8; pw * (h + 2 * ry)];
    for y in 0..h {
        pad[(y + ry) * pw + rx..(y + ry) * pw + rx + w].copy_from_slice(&img[y * w..(y + 1) * w]);
    }
    out.clear();
    out.resize(w * h, 0);
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        census_row(&pad, pw, rx, ry, y, row);
    });
}

fn census_row(pad: &[u8], pw: usize, rx: usize, ry: usize, y: usize, row: &mut [u64]) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { census_row_avx2(pad, pw, rx, ry, y, row) };
        return;
    }
    census_row_generic(pad, pw, rx, ry, y, row);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn census_row_avx2(pad: &[u8], pw: usize, rx: usize, ry: usize, y: usize, row: &mut [u64]) {
    census_row_generic(pad, pw, rx, ry, y, row);
}

/// One census row, 64 pixels at a time in two u32 halves (the comparisons that land in bits 32
/// and above first, then the low 32), so the compare-shift-or loops run 8 lanes wide.
#[inline(always)]
fn census_row_generic(pad: &[u8], pw: usize, rx: usize, ry: usize, y: usize, row: &mut [u64]) {
    const B: usize = 64;
    let n = (2 * rx + 1) * (2 * ry + 1) - 1;
    let centre = &pad[(y + ry) * pw + rx..];
    let w = row.len();
    let mut x0 = 0;
    while x0 < w {
        let bw = B.min(w - x0);
        let (mut hi, mut lo) = ([0u32; B], [0u32; B]);
        let c = &centre[x0..x0 + bw];
        let mut k = 0;
        for wy in 0..=2 * ry {
            for wx in 0..=2 * rx {
                if wy == ry && wx == rx {
                    continue;
                }
                let nb = &pad[(y + wy) * pw + x0 + wx..(y + wy) * pw + x0 + wx + bw];
                let acc = if k + 32 < n { &mut hi } else { &mut lo };
                for ((a, &v), &cv) in acc[..bw].iter_mut().zip(nb).zip(c) {
                    *a = (*a << 1) | u32::from(v < cv);
                }
                k += 1;
            }
        }
        for ((o, &h), &l) in row[x0..x0 + bw].iter_mut().zip(&hi).zip(&lo) {
            *o = (u64::from(h) << 32) | u64::from(l);
        }
        x0 += bw;
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

/// What both passes read.
struct Ctx<'a> {
    img: &'a [u8],
    cl: &'a [u64],
    cr: &'a [u64],
    w: usize,
    h: usize,
    nd: usize,
    /// D rounded up to LANES.
    dp: usize,
    p: &'a SgmParams,
    /// dx of the paths that come from the previous row.
    vdx: &'a [isize],
}

impl Ctx<'_> {
    fn stride(&self) -> usize {
        GUARD + self.dp
    }
}

/// The checks every SGM entry point makes: the parameters, the image sizes and the mask's.
pub fn check_pair(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    valid: Option<&[u8]>,
    p: &SgmParams,
) -> Result<(), String> {
    p.validate()?;
    if left.len() != w * h || right.len() != w * h {
        return Err(format!("images must be {w}x{h} gray"));
    }
    if valid.is_some_and(|m| m.len() != w * h) {
        return Err(format!("the mask must be {w}x{h}"));
    }
    Ok(())
}

/// Disparity of the left image (px, NaN invalid), from `left` and `right` gray images.
/// `valid` masks pixels that may not get a disparity (e.g. the black border).
pub fn sgm(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    valid: Option<&[u8]>,
    p: &SgmParams,
    s: &mut Scratch,
) -> Result<Vec<f32>, String> {
    check_pair(left, right, w, h, valid, p)?;
    let (cw, ch) = (p.census_width as usize, p.census_height as usize);
    let Scratch {
        census_l,
        census_r,
        sum_f,
        sum_b,
        pass_f,
        pass_b,
        right: right_disp,
        row,
        right_scratch,
        cost_vol,
        speckle,
    } = s;
    rayon::join(
        || census(left, w, h, cw, ch, census_l),
        || census(right, w, h, cw, ch, census_r),
    );
    let nd = p.max_disparity as usize;
    let dp = nd.div_ceil(LANES) * LANES;
    let ctx = Ctx {
        img: left,
        cl: census_l,
        cr: census_r,
        w,
        h,
        nd,
        dp,
        p,
        vdx: if p.paths == 8 { &[1, 0, -1] } else { &[0] },
    };
    let mut disp = vec![f32::NAN; w * h];
    right_disp.clear();
    right_disp.resize(w * h, f32::NAN);
    let plane = h * w * dp;
    sum_f.resize(plane, 0);
    if rayon::current_num_threads() > 1 {
        // Both passes at once, then the selection row by row in parallel.
        sum_b.resize(plane, 0);
        rayon::join(
            || pass(true, &ctx, pass_f, None, Costs::Compute, sum_f, |_, _| {}),
            || pass(false, &ctx, pass_b, None, Costs::Compute, sum_b, |_, _| {}),
        );
        let (sf, sb) = (&*sum_f, &*sum_b);
        disp.par_chunks_mut(w)
            .zip(right_disp.par_chunks_mut(w))
            .enumerate()
            .for_each_init(
                || (Vec::new(), RightScratch::default()),
                |(tot, rs), (y, (dl, dr))| {
                    let r = y * w * dp..(y + 1) * w * dp;
                    tot.clear();
                    tot.extend(
                        sf[r.clone()]
                            .iter()
                            .zip(&sb[r])
                            .map(|(a, b)| a.saturating_add(*b)),
                    );
                    select_row(&ctx, y, tot, valid, dl, dr, rs);
                },
            );
    } else {
        sum_b.clear();
        cost_vol.resize(h * w * nd, 0);
        pass(
            true,
            &ctx,
            pass_f,
            None,
            Costs::Store(cost_vol),
            sum_f,
            |_, _| {},
        );
        row.resize(w * dp, 0);
        let costs = Costs::Load(cost_vol);
        pass(false, &ctx, pass_b, Some(sum_f), costs, row, |y, tot| {
            let r = y * w..(y + 1) * w;
            let (dl, dr) = (&mut disp[r.clone()], &mut right_disp[r]);
            select_row(&ctx, y, tot, valid, dl, dr, right_scratch);
        });
    }
    finish_with(&mut disp, right_disp, w, h, p, speckle);
    Ok(disp)
}

/// Where a pass gets its matching costs: computed from the census images, computed and kept
/// (H x W x D u8) for the other pass, or read from that volume.
enum Costs<'a> {
    Compute,
    Store(&'a mut [u8]),
    Load(&'a [u8]),
}

/// One aggregation pass: forward runs rows top-down and pixels left to right with the paths
/// from above and from the left; backward the mirror. Each row's sums (plus `init`'s, when given)
/// go to `out` (the whole image, or one row buffer), then `after_row(y, row)` runs.
fn pass(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    after_row: impl FnMut(usize, &mut [i16]),
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("popcnt")
    {
        // SAFETY: the CPU supports AVX2 and POPCNT (checked just above).
        unsafe { pass_avx2(forward, ctx, ps, init, costs, out, after_row) };
        return;
    }
    pass_generic::<Portable>(forward, ctx, ps, init, costs, out, after_row);
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,popcnt")]
fn pass_avx2(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    after_row: impl FnMut(usize, &mut [i16]),
) {
    pass_generic::<Avx2>(forward, ctx, ps, init, costs, out, after_row);
}

/// 16 lanes of `s` from `at`.
#[inline(always)]
fn lanes(s: &[i16], at: usize) -> &[i16; LANES] {
    s[at..at + LANES]
        .try_into()
        .unwrap_or_else(|_| unreachable!("a slice of LANES elements"))
}

#[inline(always)]
fn lanes_mut(s: &mut [i16], at: usize) -> &mut [i16; LANES] {
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

/// The lane arithmetic of a pass: portable arrays (SSE2 through autovectorisation) or AVX2
/// intrinsics (the shuffles for d - 1 and d + 1 do not autovectorise well).
trait Kernel {
    #[allow(clippy::too_many_arguments)]
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
    ) -> [i16; LANES];
}

struct Portable;

impl Kernel for Portable {
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
        step(cost, lo, a, hi, min_prev, p1, jump, mn, acc)
    }
}

/// Only named by [`pass_avx2`], which runs after AVX2 was detected.
#[cfg(target_arch = "x86_64")]
struct Avx2;

#[cfg(target_arch = "x86_64")]
impl Kernel for Avx2 {
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
        // SAFETY: `Avx2` is used only inside `pass_avx2`, which is called after
        // `is_x86_feature_detected!("avx2")`.
        unsafe { step_avx2(cost, lo, a, hi, min_prev, p1, jump, mn, acc) }
    }
}

/// [`step`] with AVX2 intrinsics: d - 1 is `alignr` of the chunk with the last lane of the one
/// below, d + 1 with the first lane of the one above.
#[cfg(target_arch = "x86_64")]
#[allow(clippy::too_many_arguments)]
#[target_feature(enable = "avx2")]
#[inline]
fn step_avx2(
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
    use std::arch::x86_64::*;
    // SAFETY: [i16; 16] and __m256i have the same size and every bit pattern is valid in both.
    let v = |x: &[i16; LANES]| unsafe { std::mem::transmute::<[i16; LANES], __m256i>(*x) };
    let (lo, a, hi, c) = (v(lo), v(a), v(hi), v(cost));
    let am = _mm256_alignr_epi8::<14>(a, _mm256_permute2x128_si256::<0x21>(lo, a));
    let ap = _mm256_alignr_epi8::<2>(_mm256_permute2x128_si256::<0x21>(a, hi), a);
    let p1v = _mm256_set1_epi16(p1);
    let best = _mm256_min_epi16(
        _mm256_min_epi16(a, _mm256_set1_epi16(jump)),
        _mm256_min_epi16(_mm256_adds_epi16(am, p1v), _mm256_adds_epi16(ap, p1v)),
    );
    let out = _mm256_adds_epi16(c, _mm256_sub_epi16(best, _mm256_set1_epi16(min_prev)));
    // SAFETY: as above, back to arrays.
    let arr = |x: __m256i| unsafe { std::mem::transmute::<__m256i, [i16; LANES]>(x) };
    *mn = arr(_mm256_min_epi16(v(mn), out));
    *acc = arr(_mm256_adds_epi16(v(acc), out));
    arr(out)
}

/// Appends `slots` path slots: GUARD lanes at FAR, then D' disparities at 0 (a path start:
/// L = C), and a trailing guard.
fn push_paths(buf: &mut Vec<i16>, slots: usize, dp: usize) {
    for _ in 0..slots {
        buf.extend(std::iter::repeat_n(FAR, GUARD));
        buf.extend(std::iter::repeat_n(0, dp));
    }
    buf.extend(std::iter::repeat_n(FAR, GUARD));
}

#[inline(always)]
fn pass_generic<K: Kernel>(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    costs: Costs,
    out: &mut [i16],
    after_row: impl FnMut(usize, &mut [i16]),
) {
    if ctx.vdx.len() == 3 {
        pass_n::<3, K>(forward, ctx, ps, init, costs, out, after_row);
    } else {
        pass_n::<1, K>(forward, ctx, ps, init, costs, out, after_row);
    }
}

/// The pass with `NV` paths from the previous row (3 with 8 paths, 1 with 4) and one along the
/// row. The previous-row paths are updated in place: pixel x reads slot x - dx + 1 and its new
/// L goes to slot x + 1 once the pixel is done; for the path whose dx equals the traversal step
/// the next pixel still needs the old slot x + 1, so that write waits one pixel.
#[inline(always)]
fn pass_n<const NV: usize, K: Kernel>(
    forward: bool,
    ctx: &Ctx,
    ps: &mut PassScratch,
    init: Option<&[i16]>,
    mut costs: Costs,
    out: &mut [i16],
    mut after_row: impl FnMut(usize, &mut [i16]),
) {
    let (w, h, nd, dp, p) = (ctx.w, ctx.h, ctx.nd, ctx.dp, ctx.p);
    let stride = ctx.stride();
    let mut vdx = [0isize; NV];
    vdx.copy_from_slice(ctx.vdx);
    let step_x: isize = if forward { 1 } else { -1 };
    let row_len = w * dp;
    let whole = out.len() == h * row_len;
    ps.paths.clear();
    push_paths(&mut ps.paths, NV * (w + 2), dp);
    ps.mins.clear();
    ps.mins.resize(NV * (w + 2), 0);
    ps.held.clear();
    ps.held.resize(dp, 0);
    ps.holding.clear();
    ps.holding.resize(dp, 0);
    ps.cost.clear();
    ps.cost.resize(row_len, FAR);
    let pad = nd + p.min_disparity.unsigned_abs() as usize + 1;
    ps.rev.clear();
    ps.rev.resize(w + 2 * pad, 0);
    let unknown = i16::from(p.unknown_cost());
    let p1 = p.p1 as i16;
    for k in 0..h {
        let y = if forward { k } else { h - 1 - k };
        match &mut costs {
            Costs::Compute => cost_row(ctx, y, pad, unknown, &mut ps.rev, &mut ps.cost),
            Costs::Store(vol) => {
                cost_row(ctx, y, pad, unknown, &mut ps.rev, &mut ps.cost);
                let dst = &mut vol[y * w * nd..(y + 1) * w * nd];
                for (d, c) in dst.chunks_exact_mut(nd).zip(ps.cost.chunks_exact(dp)) {
                    for (o, &v) in d.iter_mut().zip(c) {
                        *o = v as u8;
                    }
                }
            }
            Costs::Load(vol) => {
                let src = &vol[y * w * nd..(y + 1) * w * nd];
                for (c, d) in ps.cost.chunks_exact_mut(dp).zip(src.chunks_exact(nd)) {
                    for (o, &v) in c.iter_mut().zip(d) {
                        *o = i16::from(v);
                    }
                }
            }
        }
        // The path along the row starts from zero at the border (L = C).
        ps.row_path.clear();
        push_paths(&mut ps.row_path, 1, dp);
        let mut row_min = 0i16;
        let mut held_min = 0i16;
        let prev_y = if forward { y.wrapping_sub(1) } else { y + 1 };
        let o = if whole { y * row_len } else { 0 };
        let out_row = &mut out[o..o + row_len];
        for j in 0..w {
            let x = if forward { j } else { w - 1 - j };
            let g = ctx.img[y * w + x];
            let p2_from = |xp: usize, yp: usize| -> i16 {
                if xp < w && yp < h {
                    p.p2_at(u16::from(g.abs_diff(ctx.img[yp * w + xp]))) as i16
                } else {
                    0 // a path start: min(prev) = 0 and every term is >= 0, P2 plays no part
                }
            };
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
                    let l = K::step(c, &lo, &a, &hi, min_prev[v], p1, jump[v], &mut mn, acc);
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
                let l = K::step(c, &lo, &a, &hi, row_min, p1, jump_h, &mut mn, acc);
                (lo, a) = (a, hi);
                *lanes_mut(&mut ps.row_path, GUARD + at) = l;
            }
            row_min = mn.iter().copied().fold(FAR, i16::min);
            std::mem::swap(&mut ps.held, &mut ps.holding);
        }
        // The last pixel's held-back L.
        for (v, &dx) in vdx.iter().enumerate() {
            if dx == step_x {
                let x_last = if forward { w - 1 } else { 0 };
                let s = ((x_last + 1) * NV + v) * stride + GUARD;
                ps.paths[s..s + dp].copy_from_slice(&ps.held);
                ps.mins[v * (w + 2) + x_last + 1] = held_min;
            }
        }
        after_row(y, out_row);
    }
}

/// Hamming costs of row `y` for every pixel and disparity into `cost` (W x D', padding lanes
/// untouched at FAR); a partner outside the right image costs `unknown`.
#[inline(always)]
fn cost_row(ctx: &Ctx, y: usize, pad: usize, unknown: i16, rev: &mut [u64], cost: &mut [i16]) {
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

/// Buffers of the right-disparity search of one row.
#[derive(Default)]
struct RightScratch {
    /// Best sum and its disparity per right pixel, stored reversed (index pad + w - 1 - xr) so
    /// that one left pixel's 16 disparities update 16 contiguous entries.
    best: Vec<i16>,
    arg: Vec<i16>,
}

/// Winner-takes-all for one completed row of sums: the left disparity with the uniqueness
/// margin and the parabola, and the right disparity argmin_d S(y, xr + d + dmin, d).
fn select_row(
    ctx: &Ctx,
    y: usize,
    tot: &[i16],
    valid: Option<&[u8]>,
    disp: &mut [f32],
    right: &mut [f32],
    rs: &mut RightScratch,
) {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { select_row_avx2(ctx, y, tot, valid, disp, right, rs) };
        return;
    }
    select_row_generic(ctx, y, tot, valid, disp, right, rs);
}

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
    select_row_generic(ctx, y, tot, valid, disp, right, rs);
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
        // Without a second candidate the margin test passes (as with u16::MAX in the reference).
        let second = if second == FAR {
            u64::from(u16::MAX)
        } else {
            second as u64
        };
        if (best as u64) * (100 + p.uniqueness_pct as u64) > second * 100 {
            *out = f32::NAN;
            continue;
        }
        let mut d = bd as f32;
        if p.subpixel && bd > 0 && bd + 1 < nd {
            let (a, b, c) = (cell[bd - 1] as f32, cell[bd] as f32, cell[bd + 1] as f32);
            let den = a - 2.0 * b + c;
            if den > 0.0 {
                d += 0.5 * (a - c) / den;
            }
        }
        *out = d + dmin;
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

/// Left-right check, median and speckle removal on a full disparity image.
pub fn finish(disp: &mut Vec<f32>, right: &[f32], w: usize, h: usize, p: &SgmParams) {
    finish_with(disp, right, w, h, p, &mut SpeckleScratch::default());
}

fn finish_with(
    disp: &mut Vec<f32>,
    right: &[f32],
    w: usize,
    h: usize,
    p: &SgmParams,
    speckle: &mut SpeckleScratch,
) {
    if p.lr_check {
        for (i, d) in disp.iter_mut().enumerate() {
            if !d.is_finite() {
                continue;
            }
            let (y, x) = (i / w, i % w);
            let xr = (x as f32 - *d).round();
            if xr < 0.0 || xr as usize >= w {
                *d = f32::NAN;
                continue;
            }
            let dr = right[y * w + xr as usize];
            if !(dr.is_finite() && (dr - *d).abs() <= p.lr_max_diff) {
                *d = f32::NAN;
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

/// 3x3 median over the valid neighbours of each valid pixel.
pub fn median3(d: &[f32], w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            if !d[i].is_finite() {
                return f32::NAN;
            }
            let (y, x) = ((i / w) as isize, (i % w) as isize);
            let mut v = [0.0f32; 9];
            let mut n = 0;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        let q = d[yy as usize * w + xx as usize];
                        if q.is_finite() {
                            v[n] = q;
                            n += 1;
                        }
                    }
                }
            }
            let v = &mut v[..n];
            v.sort_by(f32::total_cmp);
            v[n / 2]
        })
        .collect()
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
