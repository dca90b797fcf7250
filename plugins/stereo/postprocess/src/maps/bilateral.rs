//! The bilateral filter of `depth.postprocess` ([`bilateral`]): its weight tables (shared with
//! the GPU kernel), the per-pixel definition, and its interior in AVX2 and AVX-512 registers.

use rayon::prelude::*;

/// Edge-preserving smoothing: a bilateral filter over valid pixels within `radius`, weighted by
/// the pixel distance (sigma `sigma_px`) and the depth difference (sigma `sigma_mm`), so depth
/// steps (tissue folds, instrument edges) stay sharp. Invalid pixels stay invalid and are never
/// used.
pub fn bilateral(
    depth: &[f32],
    w: usize,
    h: usize,
    radius: usize,
    sigma_px: f32,
    sigma_mm: f32,
) -> Vec<f32> {
    bilateral_with(depth, w, h, radius, sigma_px, sigma_mm, Simd::best())
}

/// The vector instructions the bilateral filter's interior runs on (each gives the same bits).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub(crate) enum Simd {
    /// One pixel at a time.
    Scalar,
    /// 8 pixels a vector.
    Avx2,
    /// 16 pixels a vector (and AVX2's 8 for what is left).
    Avx512,
}

impl Simd {
    /// The widest this CPU runs.
    pub(crate) fn best() -> Self {
        *Self::available().last().unwrap_or(&Simd::Scalar)
    }

    /// Those this CPU runs, narrowest first.
    pub(crate) fn available() -> Vec<Self> {
        let mut v = vec![Simd::Scalar];
        #[cfg(target_arch = "x86_64")]
        {
            if std::arch::is_x86_feature_detected!("avx2") {
                v.push(Simd::Avx2);
                if std::arch::is_x86_feature_detected!("avx512f") {
                    v.push(Simd::Avx512);
                }
            }
        }
        v
    }
}

/// [`bilateral`] on the given vector instructions (the tests run each this CPU has).
pub(crate) fn bilateral_with(
    depth: &[f32],
    w: usize,
    h: usize,
    radius: usize,
    sigma_px: f32,
    sigma_mm: f32,
    simd: Simd,
) -> Vec<f32> {
    let BilateralTables {
        spatial,
        range,
        lut_scale,
    } = BilateralTables::new(radius, sigma_px, sigma_mm);
    // Invalid pixels become a far value: their range weight is 0 and 0 times it adds +0, so the
    // loops need no branch and every valid pixel gets the same sums, in the same tap order.
    let far = sanitize(depth);
    let t = Taps {
        depth: &far,
        w,
        h,
        radius,
        spatial: &spatial,
        range: &range,
        lut_scale,
        simd,
    };
    let mut out = vec![f32::NAN; w * h];
    out.par_chunks_mut(w.max(1)).enumerate().for_each_init(
        || (vec![0.0f32; w], vec![0.0f32; w]),
        |(num, den), (y, row)| {
            bilateral_row(&t, y, num, den);
            for (x, o) in row.iter_mut().enumerate() {
                if depth[y * w + x].is_finite() {
                    *o = num[x] / den[x];
                }
            }
        },
    );
    out
}

/// Entries of the bilateral filter's range-weight table (one more, 0, for beyond it).
pub(crate) const RANGE_LUT: usize = 1024;

/// The bilateral filter's weights, as the CPU and the GPU kernel read them.
pub(crate) struct BilateralTables {
    /// Spatial weights of the (2 radius + 1)^2 window, row by row.
    pub spatial: Vec<f32>,
    /// Range weights over |d| in [0, 4 sigma), RANGE_LUT of them, then 0 (beyond the table).
    pub range: [f32; RANGE_LUT + 1],
    /// Table entries per mm of depth difference.
    pub lut_scale: f32,
}

impl BilateralTables {
    pub(crate) fn new(radius: usize, sigma_px: f32, sigma_mm: f32) -> Self {
        let r = radius as i64;
        let spatial: Vec<f32> = (-r..=r)
            .flat_map(|dy| {
                (-r..=r).map(move |dx| {
                    (-((dx * dx + dy * dy) as f32) / (2.0 * sigma_px * sigma_px)).exp()
                })
            })
            .collect();
        // Range weights from a table over |d| in [0, 4 sigma) (beyond it the weight is below
        // 3.4e-4 and taken as 0): no exp per neighbour.
        let lut_scale = RANGE_LUT as f32 / (4.0 * sigma_mm);
        // Index RANGE_LUT: beyond the table, weight 0.
        let mut range = [0.0f32; RANGE_LUT + 1];
        for (k, r) in range.iter_mut().take(RANGE_LUT).enumerate() {
            let d = (k as f32 + 0.5) / lut_scale;
            *r = (-(d * d) / (2.0 * sigma_mm * sigma_mm)).exp();
        }
        BilateralTables {
            spatial,
            range,
            lut_scale,
        }
    }
}

/// Stand-in for invalid pixels in the bilateral filter: farther than any range weight reaches.
pub(crate) const FAR: f32 = 1e30;

fn sanitize(depth: &[f32]) -> Vec<f32> {
    depth
        .par_iter()
        .map(|&v| if v.is_finite() { v } else { FAR })
        .collect()
}

/// What a row of the bilateral filter reads.
struct Taps<'a> {
    depth: &'a [f32],
    w: usize,
    h: usize,
    radius: usize,
    spatial: &'a [f32],
    range: &'a [f32; RANGE_LUT + 1],
    lut_scale: f32,
    simd: Simd,
}

/// Weighted sums of row `y`, each pixel's over its window's taps in window order (rows, then
/// columns; taps outside the image skipped), so every pixel gets the per-tap definition's bits.
/// The interior runs 32 and then 16 pixels at a time with AVX-512, then 32 and 8 with AVX2, the
/// sums in registers; the pixels within `radius` of the row's ends, and all of them without
/// AVX2, one at a time.
fn bilateral_row(t: &Taps, y: usize, num: &mut [f32], den: &mut [f32]) {
    let (w, r) = (t.w, t.radius);
    #[cfg(target_arch = "x86_64")]
    if t.simd != Simd::Scalar && w >= 2 * r + 8 {
        // SAFETY: `Simd::available` found the instructions on this CPU (AVX-512 only with
        // AVX2); the blocks stay within the row (their loops' bounds).
        let end = unsafe {
            let x = if t.simd == Simd::Avx512 {
                bilateral_interior_avx512(t, y, num, den)
            } else {
                r
            };
            bilateral_interior_avx2(t, y, x, num, den)
        };
        for x in (0..r).chain(end..w) {
            (num[x], den[x]) = pixel_sums(t, x, y);
        }
        return;
    }
    for x in 0..w {
        (num[x], den[x]) = pixel_sums(t, x, y);
    }
}

#[inline(always)]
fn range_index(v: f32, z: f32, lut_scale: f32) -> usize {
    // In [0, RANGE_LUT] for finite values (no NaN reaches here: see `sanitize`).
    let k = ((v - z).abs() * lut_scale).min(RANGE_LUT as f32) as i32;
    (k as u32).min(RANGE_LUT as u32) as usize
}

/// The sums of pixel (x, y): `num += w v`, `den += w` with w = spatial * range(|v - z|) over
/// the taps inside the image, in window order.
fn pixel_sums(t: &Taps, x: usize, y: usize) -> (f32, f32) {
    let (w, r) = (t.w, t.radius);
    let side = 2 * r + 1;
    let z = t.depth[y * w + x];
    let (mut num, mut den) = (0.0f32, 0.0f32);
    for yy in y.saturating_sub(r)..=(y + r).min(t.h - 1) {
        let row = &t.depth[yy * w..(yy + 1) * w];
        let sw = &t.spatial[(yy + r - y) * side..(yy + r - y + 1) * side];
        for xx in x.saturating_sub(r)..=(x + r).min(w - 1) {
            let v = row[xx];
            let wgt = sw[xx + r - x] * t.range[range_index(v, z, t.lut_scale)];
            num += wgt * v;
            den += wgt;
        }
    }
    (num, den)
}

/// [`pixel_sums`] for the pixels `radius..end` of row `y`, blocks of 8 pixels a vector (the
/// gather reads the range table), four vectors at once while they fit; returns `end`, the
/// first pixel left (every pixel from there has a tap past the row's end). Each lane takes the
/// same operations in the same order as [`pixel_sums`], so the same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn bilateral_interior_avx2(
    t: &Taps,
    y: usize,
    from: usize,
    num: &mut [f32],
    den: &mut [f32],
) -> usize {
    let (w, r) = (t.w, t.radius);
    let mut x = from;
    while x + 32 + r <= w {
        bilateral_block_avx2::<4>(t, y, x, num, den);
        x += 32;
    }
    while x + 8 + r <= w {
        bilateral_block_avx2::<1>(t, y, x, num, den);
        x += 8;
    }
    x
}

/// The sums of the `8 K` pixels from `x0` of row `y` (all their taps within the row).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn bilateral_block_avx2<const K: usize>(
    t: &Taps,
    y: usize,
    x0: usize,
    num: &mut [f32],
    den: &mut [f32],
) {
    use std::arch::x86_64::*;
    let (w, r) = (t.w, t.radius);
    let side = 2 * r + 1;
    assert!(x0 >= r && x0 + 8 * K + r <= w && num.len() >= x0 + 8 * K && den.len() >= x0 + 8 * K);
    let scale = _mm256_set1_ps(t.lut_scale);
    let top = _mm256_set1_ps(RANGE_LUT as f32);
    let abs = _mm256_castsi256_ps(_mm256_set1_epi32(0x7fff_ffff));
    let row0 = &t.depth[y * w..(y + 1) * w];
    // SAFETY (every load and store below): the lanes x0 - r .. x0 + 8 K + r lie within the row
    // (asserted above); the gather indices are in [0, RANGE_LUT] (|v - z| * scale is finite and
    // non-negative, clamped to RANGE_LUT before truncation).
    unsafe {
        let z: [__m256; K] =
            std::array::from_fn(|j| _mm256_loadu_ps(row0.as_ptr().add(x0 + 8 * j)));
        let mut n = [_mm256_setzero_ps(); K];
        let mut d = [_mm256_setzero_ps(); K];
        for yy in y.saturating_sub(r)..=(y + r).min(t.h - 1) {
            let row = t.depth[yy * w..(yy + 1) * w].as_ptr().add(x0 - r);
            let sw = &t.spatial[(yy + r - y) * side..(yy + r - y + 1) * side];
            for (dxi, &s) in sw.iter().enumerate() {
                let swv = _mm256_set1_ps(s);
                for j in 0..K {
                    let v = _mm256_loadu_ps(row.add(dxi + 8 * j));
                    let k = _mm256_min_ps(
                        _mm256_mul_ps(_mm256_and_ps(_mm256_sub_ps(v, z[j]), abs), scale),
                        top,
                    );
                    let rw = _mm256_i32gather_ps::<4>(t.range.as_ptr(), _mm256_cvttps_epi32(k));
                    let wgt = _mm256_mul_ps(swv, rw);
                    n[j] = _mm256_add_ps(n[j], _mm256_mul_ps(wgt, v));
                    d[j] = _mm256_add_ps(d[j], wgt);
                }
            }
        }
        for j in 0..K {
            _mm256_storeu_ps(num.as_mut_ptr().add(x0 + 8 * j), n[j]);
            _mm256_storeu_ps(den.as_mut_ptr().add(x0 + 8 * j), d[j]);
        }
    }
}

/// [`pixel_sums`] for the pixels `radius..end` of row `y`, blocks of 16 pixels a vector, two at
/// once while they fit; returns `end`, the first pixel left for the AVX2 blocks. Each lane takes
/// the operations of [`pixel_sums`] in its order (a multiply then an add, never fused), so the
/// same bits.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx2")]
fn bilateral_interior_avx512(t: &Taps, y: usize, num: &mut [f32], den: &mut [f32]) -> usize {
    let (w, r) = (t.w, t.radius);
    let mut x = r;
    while x + 32 + r <= w {
        bilateral_block_avx512::<2>(t, y, x, num, den);
        x += 32;
    }
    while x + 16 + r <= w {
        bilateral_block_avx512::<1>(t, y, x, num, den);
        x += 16;
    }
    x
}

/// The sums of the `16 K` pixels from `x0` of row `y` (all their taps within the row).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f")]
fn bilateral_block_avx512<const K: usize>(
    t: &Taps,
    y: usize,
    x0: usize,
    num: &mut [f32],
    den: &mut [f32],
) {
    use std::arch::x86_64::*;
    let (w, r) = (t.w, t.radius);
    let side = 2 * r + 1;
    assert!(
        x0 >= r && x0 + 16 * K + r <= w && num.len() >= x0 + 16 * K && den.len() >= x0 + 16 * K
    );
    let scale = _mm512_set1_ps(t.lut_scale);
    let top = _mm512_set1_ps(RANGE_LUT as f32);
    let row0 = &t.depth[y * w..(y + 1) * w];
    // SAFETY (every load, gather and store below): the lanes x0 - r .. x0 + 16 K + r lie within
    // the row (asserted above); the gather indices are in [0, RANGE_LUT] (|v - z| * scale is
    // finite and non-negative, clamped to RANGE_LUT before truncation).
    unsafe {
        let z: [__m512; K] =
            std::array::from_fn(|j| _mm512_loadu_ps(row0.as_ptr().add(x0 + 16 * j)));
        let mut n = [_mm512_setzero_ps(); K];
        let mut d = [_mm512_setzero_ps(); K];
        for yy in y.saturating_sub(r)..=(y + r).min(t.h - 1) {
            let row = t.depth[yy * w..(yy + 1) * w].as_ptr().add(x0 - r);
            let sw = &t.spatial[(yy + r - y) * side..(yy + r - y + 1) * side];
            for (dxi, &s) in sw.iter().enumerate() {
                let swv = _mm512_set1_ps(s);
                for j in 0..K {
                    let v = _mm512_loadu_ps(row.add(dxi + 16 * j));
                    let k = _mm512_min_ps(
                        _mm512_mul_ps(_mm512_abs_ps(_mm512_sub_ps(v, z[j])), scale),
                        top,
                    );
                    let rw = _mm512_i32gather_ps::<4>(_mm512_cvttps_epi32(k), t.range.as_ptr());
                    let wgt = _mm512_mul_ps(swv, rw);
                    n[j] = _mm512_add_ps(n[j], _mm512_mul_ps(wgt, v));
                    d[j] = _mm512_add_ps(d[j], wgt);
                }
            }
        }
        for j in 0..K {
            _mm512_storeu_ps(num.as_mut_ptr().add(x0 + 16 * j), n[j]);
            _mm512_storeu_ps(den.as_mut_ptr().add(x0 + 16 * j), d[j]);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bilateral_equals_the_per_tap_definition() {
        // The clipped-window loops must take the same taps in the same order as testing every
        // tap against the image: equal bits, on a map with holes, at the borders and the corners.
        // Every vector width this CPU has: AVX2 takes blocks of 8 pixels at 23 px, of 32 too at
        // 77; AVX-512 blocks of 16 at 23 and 31 (then AVX2's 8 at 31), of 32 at 77 and 102.
        let levels = Simd::available();
        println!("vector widths on this CPU: {levels:?}");
        for simd in levels {
            for (w, h) in [(23usize, 17usize), (31, 6), (77, 9), (102, 5)] {
                bilateral_equals_the_per_tap_definition_at(w, h, simd);
            }
        }
    }

    fn bilateral_equals_the_per_tap_definition_at(w: usize, h: usize, simd: Simd) {
        let (radius, sigma_px, sigma_mm) = (3usize, 2.0f32, 1.5f32);
        let mut s = 7u32;
        let depth: Vec<f32> = (0..w * h)
            .map(|i| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                if s >> 28 == 0 {
                    f32::NAN
                } else {
                    60.0 + (i % w) as f32 * 0.3 + ((s >> 8) as f32 / (1u32 << 24) as f32) * 3.0
                }
            })
            .collect();
        let got = bilateral_with(&depth, w, h, radius, sigma_px, sigma_mm, simd);
        let r = radius as i64;
        let lut_scale = 1024.0 / (4.0 * sigma_mm);
        let range: Vec<f32> = (0..1024)
            .map(|k| {
                let d = (k as f32 + 0.5) / lut_scale;
                (-(d * d) / (2.0 * sigma_mm * sigma_mm)).exp()
            })
            .collect();
        for i in 0..w * h {
            let z = depth[i];
            if !z.is_finite() {
                assert!(got[i].is_nan());
                continue;
            }
            let (x, y) = ((i % w) as i64, (i / w) as i64);
            let (mut num, mut den) = (0.0f32, 0.0f32);
            for dy in -r..=r {
                for dx in -r..=r {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx < 0 || yy < 0 || xx >= w as i64 || yy >= h as i64 {
                        continue;
                    }
                    let v = depth[yy as usize * w + xx as usize];
                    if !v.is_finite() {
                        continue;
                    }
                    let Some(&rw) = range.get(((v - z).abs() * lut_scale) as usize) else {
                        continue;
                    };
                    let sw = (-((dx * dx + dy * dy) as f32) / (2.0 * sigma_px * sigma_px)).exp();
                    num += sw * rw * v;
                    den += sw * rw;
                }
            }
            assert_eq!(
                got[i].to_bits(),
                (num / den).to_bits(),
                "pixel {i} of {w}x{h}, {simd:?}"
            );
        }
    }

    #[test]
    fn bilateral_smooths_noise_but_keeps_a_step() {
        let (w, h) = (40usize, 20usize);
        let mut s = 1u32;
        let noisy: Vec<f32> = (0..w * h)
            .map(|i| {
                s = s.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                let n = ((s >> 8) as f32 / (1u32 << 24) as f32 - 0.5) * 0.6;
                (if i % w < 20 { 60.0 } else { 80.0 }) + n
            })
            .collect();
        let out = bilateral(&noisy, w, h, 3, 2.0, 1.0);
        let rms = |v: &[f32], x0: usize, x1: usize, mean: f32| {
            let mut acc = 0.0;
            let mut n = 0;
            for y in 0..h {
                for x in x0..x1 {
                    acc += (v[y * w + x] - mean).powi(2);
                    n += 1;
                }
            }
            (acc / n as f32).sqrt()
        };
        assert!(rms(&out, 4, 16, 60.0) < 0.5 * rms(&noisy, 4, 16, 60.0));
        // Right at the step, each side keeps its own level (within the noise).
        for y in 0..h {
            assert!((out[y * w + 19] - 60.0).abs() < 0.3, "{}", out[y * w + 19]);
            assert!((out[y * w + 20] - 80.0).abs() < 0.3, "{}", out[y * w + 20]);
        }
        // Invalid stays invalid and does not leak.
        let mut holes = noisy.clone();
        holes[5 * w + 5] = f32::NAN;
        let out = bilateral(&holes, w, h, 3, 2.0, 1.0);
        assert!(out[5 * w + 5].is_nan());
        assert!(out
            .iter()
            .enumerate()
            .all(|(i, v)| i == 5 * w + 5 || v.is_finite()));
    }
}
