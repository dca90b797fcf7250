//! Semi-global matching (Hirschmueller, PAMI 2008) on rectified gray images, as a plain library:
//! census transform, Hamming matching cost, path-wise aggregation with P1/P2, winner-takes-all
//! with a uniqueness margin and a sub-pixel parabola, right disparities from the same aggregated
//! cost along the diagonals, left-right check, 3x3 median and speckle removal.
//!
//! The fast path aggregates in two passes, as OpenCV's full-size mode does: a forward pass
//! (top-down, left to right) runs the paths that come from above and from the left, a backward
//! pass the other half. Each keeps only the previous row of each path and handles 16 disparities
//! per step in i16 lanes, or 32 in u8 lanes when every L fits a byte (AVX2 when the CPU has it,
//! chosen at run time; SSE2 otherwise). On one thread the forward pass computes the Hamming costs
//! row by row and keeps them (H x W x D' u8) with its sums (H x W x D' i16, D' = D rounded up to
//! 16 or 32); the backward pass reads both, adds its own sums and selects the disparities of each
//! row as it completes. With two or more threads the passes run side by side, each computing its
//! costs: whichever completes a row first publishes its sums, the other adds them to its own and
//! selects the row. The result is bit-identical to the one-pass-per-direction transcription in
//! [`crate::reference`] (tested, on one and two threads).
//!
//! Memory: the sums and the census images live in a [`Scratch`] the caller reuses across frames.

use std::sync::atomic::{AtomicU8, Ordering};

pub use crate::aggregate::path_step;
use crate::aggregate::{pass, Costs, Ctx, PassScratch, LANES, NO_PEER};
pub use crate::census::{census, census_with};
use crate::filters::finish_with;
pub use crate::filters::{finish, median3, remove_speckles, remove_speckles_with, SpeckleScratch};
use crate::select::{select_row, RightScratch};

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
    /// How the GPU kernels keep the aggregated costs: "per_direction" (a volume of L per
    /// direction, summed by the selection), "summed" (the directions add their L into one
    /// volume of sums by atomic adds: a quarter of the memory with eight paths, and the faster
    /// on an H100, 0.86 against 1.05 ms for aggregation and selection at 640x480 with 128
    /// disparities), or "auto" (summed on a discrete GPU or where a volume per direction does
    /// not fit the adapter's limits, else per direction: the faster on Mesa's lavapipe). The
    /// output is the same.
    pub gpu_volumes: GpuVolumes,
    /// How the GPU aggregation's invocations of one path exchange their neighbouring costs and
    /// their minimum at each pixel: "subgroup" (subgroup shuffles, no barrier; needs an adapter
    /// whose subgroups have one size that holds a path's invocations), "workgroup" (workgroup
    /// memory and a barrier per pixel, on any adapter) or "auto" (subgroups where the adapter
    /// allows, else workgroup memory). The output is the same.
    pub gpu_exchange: GpuExchange,
    /// How the host waits for the GPU's disparity map: "spin" polls the fence for up to 5 ms
    /// before it blocks, keeping one core busy meanwhile (as CUDA's default schedule does
    /// where a core is free: on an H100 a 640x480 pair alone took 0.95 to 0.98 ms against 1.01
    /// to 1.03 blocking at once, the same binary), "block" blocks at once, "auto" spins on a
    /// discrete GPU and blocks elsewhere (Mesa's lavapipe runs the kernels on the host's cores,
    /// which spinning would take from it). The output is the same.
    pub gpu_wait: GpuWait,
}

/// How the host waits for the GPU's map (see [`SgmParams::gpu_wait`]).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum GpuWait {
    /// Spin on a discrete GPU, block elsewhere.
    #[default]
    Auto,
    /// Poll for up to 5 ms, then block.
    Spin,
    /// Block on the fence at once.
    Block,
}

/// How the GPU aggregation exchanges values between a path's invocations (see
/// [`SgmParams::gpu_exchange`]).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum GpuExchange {
    /// Subgroups where the adapter allows, else workgroup memory.
    #[default]
    Auto,
    /// Subgroup shuffles.
    Subgroup,
    /// Workgroup memory and barriers.
    Workgroup,
}

/// Layout of the GPU kernels' aggregated costs (see [`SgmParams::gpu_volumes`]).
#[derive(
    Clone,
    Copy,
    Debug,
    Default,
    PartialEq,
    Eq,
    serde::Serialize,
    serde::Deserialize,
    schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum GpuVolumes {
    /// Per direction when that fits the adapter's limits, else summed.
    #[default]
    Auto,
    /// A volume of L per direction.
    PerDirection,
    /// One volume of sums.
    Summed,
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
            gpu_volumes: GpuVolumes::Auto,
            gpu_exchange: GpuExchange::Auto,
            gpu_wait: GpuWait::Auto,
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
    /// One row of sums for the backward pass when it selects as it goes (and for the forward
    /// pass with two threads; `row_b` the backward pass's then).
    row: Vec<i16>,
    row_b: Vec<i16>,
    right_scratch: RightScratch,
    right_scratch_b: RightScratch,
    /// Matching costs kept by the forward pass for the backward one (one thread).
    cost_vol: Vec<u8>,
    /// The padded images of the census transform.
    census_pad: [Vec<u8>; 2],
    /// The median's output, swapped with the disparities.
    median: Vec<f32>,
    speckle: SpeckleScratch,
    timing: SgmTiming,
}

/// Wall time of each stage of the last [`sgm`] call, ms (see [`Scratch::last_timing`]).
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SgmTiming {
    /// Census transform of both images.
    pub census_ms: f64,
    /// The forward aggregation pass (with two threads: both passes side by side, each
    /// selecting the rows it completes second).
    pub forward_ms: f64,
    /// The backward pass and the winner selection of each row as it completes (with two
    /// threads: nothing left, about 0).
    pub backward_select_ms: f64,
    /// Left-right check, median and speckle removal.
    pub finish_ms: f64,
    /// The whole call.
    pub total_ms: f64,
}

impl Scratch {
    /// The stage times of the last [`sgm`] call made with this scratch.
    pub fn last_timing(&self) -> SgmTiming {
        self.timing
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
    if w == 0 || h == 0 {
        return Err(format!("the images are {w}x{h}: nothing to match"));
    }
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
        row_b,
        right_scratch,
        right_scratch_b,
        cost_vol,
        census_pad: [pad_l, pad_r],
        median,
        speckle,
        timing,
    } = s;
    let ms = |t: std::time::Instant| t.elapsed().as_secs_f64() * 1e3;
    let t0 = std::time::Instant::now();
    rayon::join(
        || census_with(left, w, h, cw, ch, pad_l, census_l),
        || census_with(right, w, h, cw, ch, pad_r, census_r),
    );
    let nd = p.max_disparity as usize;
    // Every L is at most C_max + P2 (C_max: the census bits); when that fits a byte the AVX2
    // pass runs the paths 32 disparities per register, in D' a multiple of 32.
    let narrow = crate::simd::avx2() && (cw * ch - 1) + p.p2 as usize <= 255;
    let lanes = if narrow { 2 * LANES } else { LANES };
    let dp = nd.div_ceil(lanes) * lanes;
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
        narrow,
        avx512: crate::simd::avx512(),
    };
    let mut disp = vec![f32::NAN; w * h];
    right_disp.clear();
    right_disp.resize(w * h, f32::NAN);
    let plane = h * w * dp;
    sum_f.resize(plane, 0);
    timing.census_ms = ms(t0);
    let t1 = std::time::Instant::now();
    if rayon::current_num_threads() > 1 {
        // Both passes at once, each into a row buffer. Whichever pass completes a row first
        // publishes its sums there; the second adds them to its own and selects the row at
        // once, while its sums are in the cache. So about half of each pass's rows go through
        // memory, and the selection runs inside the passes, on both threads.
        sum_b.resize(plane, 0);
        row.resize(w * dp, 0);
        row_b.resize(w * dp, 0);
        let published: Vec<AtomicU8> = (0..h).map(|_| AtomicU8::new(0)).collect();
        let vol_f = SharedRows::new(&mut sum_f[..], w * dp);
        let vol_b = SharedRows::new(&mut sum_b[..], w * dp);
        let out = SharedRows::new(&mut disp[..], w);
        let out_r = SharedRows::new(&mut right_disp[..], w);
        let (ctx, published) = (&ctx, &published);
        let finish_row = |mine: &SharedRows<i16>,
                          other: &SharedRows<i16>,
                          tot: &mut Vec<i16>,
                          rs: &mut RightScratch,
                          y: usize,
                          sums: &mut [i16]| {
            // SAFETY: row y of `other` is written by the other pass before it increments
            // `published[y]` (release) and read here only after that increment was seen
            // (acquire); row y of `mine` is written only by this pass, before its increment.
            // The output rows y are written by whichever pass sees the other's increment, one
            // of the two.
            unsafe {
                if published[y].load(Ordering::Acquire) == 0 {
                    publish_copy(mine.row_mut(y), sums);
                    if published[y].fetch_add(1, Ordering::AcqRel) == 0 {
                        return;
                    }
                }
                tot.clear();
                tot.extend(
                    sums.iter()
                        .zip(other.row(y))
                        .map(|(a, b)| a.saturating_add(*b)),
                );
                select_row(ctx, y, tot, valid, out.row_mut(y), out_r.row_mut(y), rs);
            }
        };
        // A row the other pass has published before this one starts it is read at its end.
        let peer = |vol: &SharedRows<i16>, y: usize| {
            if published[y].load(Ordering::Acquire) == 0 {
                std::ptr::null()
            } else {
                // SAFETY: row y of `vol` was written before its increment (seen above) and is
                // not written again.
                unsafe { vol.row(y).as_ptr() }
            }
        };
        let peer_f = |y: usize| peer(&vol_f, y);
        let peer_b = |y: usize| peer(&vol_b, y);
        let (rs_a, rs_b) = (right_scratch, right_scratch_b);
        let (mut tot_a, mut tot_b) = (Vec::new(), Vec::new());
        rayon::join(
            || {
                pass(
                    true,
                    ctx,
                    pass_f,
                    None,
                    Costs::Compute,
                    row,
                    &peer_b,
                    |y, sums| finish_row(&vol_f, &vol_b, &mut tot_a, rs_a, y, sums),
                )
            },
            || {
                pass(
                    false,
                    ctx,
                    pass_b,
                    None,
                    Costs::Compute,
                    row_b,
                    &peer_f,
                    |y, sums| finish_row(&vol_b, &vol_f, &mut tot_b, rs_b, y, sums),
                )
            },
        );
        timing.forward_ms = ms(t1);
    } else {
        sum_b.clear();
        cost_vol.resize(h * w * dp, 0);
        pass(
            true,
            &ctx,
            pass_f,
            None,
            Costs::Store(cost_vol),
            sum_f,
            NO_PEER,
            |_, _| {},
        );
        timing.forward_ms = ms(t1);
        row.resize(w * dp, 0);
        let costs = Costs::Load(cost_vol);
        pass(
            false,
            &ctx,
            pass_b,
            Some(sum_f),
            costs,
            row,
            NO_PEER,
            |y, tot| {
                let r = y * w..(y + 1) * w;
                let (dl, dr) = (&mut disp[r.clone()], &mut right_disp[r]);
                select_row(&ctx, y, tot, valid, dl, dr, right_scratch);
            },
        );
    }
    let t2 = std::time::Instant::now();
    timing.backward_select_ms = (t2 - t1).as_secs_f64() * 1e3 - timing.forward_ms;
    finish_with(&mut disp, right_disp, w, h, p, median, speckle);
    timing.finish_ms = ms(t2);
    timing.total_ms = ms(t0);
    Ok(disp)
}

/// Copies a row of sums the other pass reads much later (from memory): with AVX2, by
/// non-temporal stores, which do not first read the destination's lines into the cache, then a
/// store fence, so that the copy is visible before the release that publishes it.
fn publish_copy(dst: &mut [i16], src: &[i16]) {
    assert_eq!(dst.len(), src.len());
    #[cfg(target_arch = "x86_64")]
    if crate::simd::avx2() {
        // SAFETY: AVX2 was detected; the lengths are equal.
        unsafe { publish_copy_avx2(dst, src) };
        return;
    }
    dst.copy_from_slice(src);
}

/// [`publish_copy`] with AVX2: the head up to a 32-byte boundary and the tail by plain stores.
///
/// # Safety
/// The CPU has AVX2; `dst` and `src` have the same length.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn publish_copy_avx2(dst: &mut [i16], src: &[i16]) {
    use std::arch::x86_64::*;
    let n = dst.len();
    // Elements before dst's first 32-byte boundary (i16 are 2-byte aligned).
    let head = (dst.as_ptr().align_offset(32)).min(n);
    dst[..head].copy_from_slice(&src[..head]);
    let body = (n - head) / 16 * 16;
    for i in (head..head + body).step_by(16) {
        // SAFETY: i + 16 <= n in both slices; dst + i is 32-byte aligned (head, then steps of
        // 32 bytes).
        unsafe {
            let v = _mm256_loadu_si256(src.as_ptr().add(i).cast());
            _mm256_stream_si256(dst.as_mut_ptr().add(i).cast(), v);
        }
    }
    dst[head + body..].copy_from_slice(&src[head + body..]);
    _mm_sfence();
}

/// Rows of a buffer shared by the two passes (see [`sgm`]): each row is written by one thread
/// and read by the other only after an atomic hand-over, which the callers make.
struct SharedRows<T> {
    ptr: *mut T,
    rows: usize,
    len: usize,
}

// SAFETY: the rows are only accessed through the unsafe methods, whose callers order the
// accesses (one writer per row, readers after a release/acquire hand-over).
unsafe impl<T: Send> Sync for SharedRows<T> {}

impl<T> SharedRows<T> {
    fn new(buf: &mut [T], len: usize) -> Self {
        SharedRows {
            ptr: buf.as_mut_ptr(),
            rows: buf.len() / len.max(1),
            len,
        }
    }

    /// # Safety
    /// No other thread writes row `y` meanwhile.
    unsafe fn row(&self, y: usize) -> &[T] {
        assert!(y < self.rows);
        // SAFETY: y < rows, so the row lies in the buffer; the caller excludes writers.
        unsafe { std::slice::from_raw_parts(self.ptr.add(y * self.len), self.len) }
    }

    /// # Safety
    /// No other thread reads or writes row `y` meanwhile.
    #[allow(clippy::mut_from_ref)]
    unsafe fn row_mut(&self, y: usize) -> &mut [T] {
        assert!(y < self.rows);
        // SAFETY: as above, and the caller excludes every other access.
        unsafe { std::slice::from_raw_parts_mut(self.ptr.add(y * self.len), self.len) }
    }
}
