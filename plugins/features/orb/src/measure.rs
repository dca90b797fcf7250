//! The per-keypoint measures of ORB: the Harris response that ranks corners, the
//! intensity-centroid orientation, and the steered binary tests of the descriptor.

use crate::extract::{pattern, PatternKind, HALF_PATCH};

/// Harris response with Sobel gradients over a 7x7 block, normalised as OpenCV's ORB does.
/// The 9x9 pixels the gradients read are loaded once into a local block (one bounds check a
/// row, not one a tap); the sums are exact in i32 (49 x (4 x 255)^2 < 2^31).
pub(crate) fn harris(img: &[u8], w: usize, x: i32, y: i32, k: f32) -> f32 {
    let mut p = [[0i32; 9]; 9];
    for (r, row) in p.iter_mut().enumerate() {
        let start = (y - 4 + r as i32) as usize * w + (x - 4) as usize;
        for (d, &s) in row.iter_mut().zip(&img[start..start + 9]) {
            *d = s as i32;
        }
    }
    let (mut a, mut b, mut c) = (0i32, 0i32, 0i32);
    for v in 1..8 {
        for u in 1..8 {
            let ix = (p[v - 1][u + 1] - p[v - 1][u - 1])
                + 2 * (p[v][u + 1] - p[v][u - 1])
                + (p[v + 1][u + 1] - p[v + 1][u - 1]);
            let iy = (p[v + 1][u - 1] - p[v - 1][u - 1])
                + 2 * (p[v + 1][u] - p[v - 1][u])
                + (p[v + 1][u + 1] - p[v - 1][u + 1]);
            a += ix * ix;
            b += iy * iy;
            c += ix * iy;
        }
    }
    harris_response(a as i64, b as i64, c as i64, k)
}

/// The response from the block's sums of Ix^2, Iy^2 and Ix Iy (Sobel gains 4 per unit step; 7x7
/// block; 8-bit range).
fn harris_response(a: i64, b: i64, c: i64, k: f32) -> f32 {
    let scale = 1.0 / (4.0 * 7.0 * 255.0);
    let (a, b, c) = (
        a as f32 * scale * scale,
        b as f32 * scale * scale,
        c as f32 * scale * scale,
    );
    a * b - c * c - k * (a + b) * (a + b)
}

/// Offsets of the circular orientation patch: `UMAX[v]` is the half width of row `v`.
fn umax() -> &'static [i32; HALF_PATCH as usize + 1] {
    static U: std::sync::OnceLock<[i32; HALF_PATCH as usize + 1]> = std::sync::OnceLock::new();
    U.get_or_init(|| {
        let r = HALF_PATCH as f32;
        std::array::from_fn(|v| ((r * r - (v * v) as f32).sqrt() + 0.5).floor() as i32)
    })
}

/// Intensity-centroid orientation in radians (image axes: x right, y down): atan2(m01, m10)
/// of the moments over the disc of radius [`HALF_PATCH`]. With AVX2, each of the disc's 31
/// rows is one 32-byte load multiplied by that row's weights (its offsets, and ones for the
/// row sum, zero outside the disc); the integer moments, and so the angle, are those of
/// [`orientation_scalar`].
pub fn orientation(img: &[u8], w: usize, x: i32, y: i32) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        // The loads span x - 15 ..= x + 16 on rows y - 15 ..= y + 15.
        let h = img.len() / w.max(1);
        let inside = x >= HALF_PATCH
            && (x + HALF_PATCH + 1) < w as i32
            && y >= HALF_PATCH
            && (y + HALF_PATCH) < h as i32;
        if inside && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            let (m01, m10) = unsafe { moments_avx2(img, w, x, y) };
            return (m01 as f32).atan2(m10 as f32);
        }
    }
    orientation_scalar(img, w, x, y)
}

/// [`orientation`] one pixel at a time. Row sums in 32-bit integers (at most 31 x 15 x 255
/// per row).
pub fn orientation_scalar(img: &[u8], w: usize, x: i32, y: i32) -> f32 {
    let um = umax();
    let (mut m01, mut m10) = (0i64, 0i64);
    for v in -HALF_PATCH..=HALF_PATCH {
        let u = um[v.unsigned_abs() as usize];
        let start = ((y + v) as usize) * w + (x - u) as usize;
        let row = &img[start..start + (2 * u + 1) as usize];
        let (mut sum_row, mut moment) = (0i32, 0i32);
        for (k, &p) in row.iter().enumerate() {
            sum_row += p as i32;
            moment += (k as i32 - u) * p as i32;
        }
        m10 += moment as i64;
        m01 += v as i64 * sum_row as i64;
    }
    (m01 as f32).atan2(m10 as f32)
}

/// Per |v|, the 32 byte weights of a row loaded from x - 15: the offset k - 15 inside the
/// disc's chord (|k - 15| <= umax), and 1 there for the row sum; 0 elsewhere (byte 31 always).
fn disc_weights() -> &'static [([i8; 32], [i8; 32]); HALF_PATCH as usize + 1] {
    type Table = [([i8; 32], [i8; 32]); HALF_PATCH as usize + 1];
    static T: std::sync::OnceLock<Table> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let um = umax();
        std::array::from_fn(|v| {
            let inside = |k: usize| (k as i32 - HALF_PATCH).abs() <= um[v] && k < 31;
            (
                std::array::from_fn(|k| if inside(k) { k as i8 - 15 } else { 0 }),
                std::array::from_fn(|k| inside(k) as i8),
            )
        })
    })
}

/// The moments (m01, m10) of [`orientation`], a row of the disc per 32-byte load.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn moments_avx2(img: &[u8], w: usize, x: i32, y: i32) -> (i64, i64) {
    use std::arch::x86_64::*;
    let table = disc_weights();
    let ones = _mm256_set1_epi16(1);
    let (mut m10, mut m01) = (_mm256_setzero_si256(), _mm256_setzero_si256());
    for v in -HALF_PATCH..=HALF_PATCH {
        let (wk, wm) = &table[v.unsigned_abs() as usize];
        let start = (y + v) as usize * w + (x - HALF_PATCH) as usize;
        let bytes: &[u8; 32] = img[start..start + 32].try_into().expect("a full load");
        // SAFETY: `bytes`, `wk` and `wm` are 32 readable bytes each; the loads are unaligned.
        let (p, wk, wm) = unsafe {
            (
                _mm256_loadu_si256(bytes.as_ptr().cast()),
                _mm256_loadu_si256(wk.as_ptr().cast()),
                _mm256_loadu_si256(wm.as_ptr().cast()),
            )
        };
        // u8 x i8 pairs summed to i16 (at most 2 x 255 x 15), then pairs of those to i32.
        let moment = _mm256_madd_epi16(_mm256_maddubs_epi16(p, wk), ones);
        let sum = _mm256_madd_epi16(_mm256_maddubs_epi16(p, wm), ones);
        m10 = _mm256_add_epi32(m10, moment);
        m01 = _mm256_add_epi32(m01, _mm256_mullo_epi32(sum, _mm256_set1_epi32(v)));
    }
    let hsum = |s: __m256i| -> i64 {
        let mut lanes = [0i32; 8];
        // SAFETY: `lanes` is 32 writable bytes; the store is unaligned.
        unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), s) };
        lanes.iter().map(|&l| l as i64).sum()
    };
    (hsum(m01), hsum(m10))
}

/// The pattern as four coordinate arrays (x1, y1, x2, y2), for loops the compiler vectorises.
fn pattern_soa(kind: PatternKind) -> &'static [[f32; 256]; 4] {
    type Soa = std::sync::OnceLock<[[f32; 256]; 4]>;
    static GAUSSIAN: Soa = Soa::new();
    static LEARNED: Soa = Soa::new();
    let cell = match kind {
        PatternKind::Gaussian => &GAUSSIAN,
        PatternKind::Learned => &LEARNED,
    };
    cell.get_or_init(|| {
        let p = pattern(kind);
        std::array::from_fn(|k| std::array::from_fn(|i| p[i][k]))
    })
}

/// Steered BRIEF: the 256 tests of [`pattern`] rotated by `angle` (upright when NaN), on the
/// smoothed level; bit `i` is set when the first point of pair `i` is darker than the second.
/// The rotated offsets are computed in one vectorised pass, the tests without branches.
pub fn describe(
    smooth: &[u8],
    w: usize,
    x: i32,
    y: i32,
    angle: f32,
    kind: PatternKind,
) -> [u64; 4] {
    let (s, c) = if angle.is_finite() {
        angle.sin_cos()
    } else {
        (0.0, 1.0)
    };
    let centre = y as isize * w as isize + x as isize;
    let [x1, y1, x2, y2] = pattern_soa(kind);
    // Round to nearest by the float trick: adding 1.5 * 2^23 pushes the fraction out, and the
    // low mantissa bits are then the integer (for |v| < 2^22; the pattern's are below 16). Pure
    // bit arithmetic, so the loop vectorises (a float-to-int `as` cast saturates and does not).
    let round = |v: f32| (v + 12_582_912.0).to_bits() as i32 - 0x4B40_0000;
    let wi = w as i32;
    let mut o1 = [0i32; 256];
    let mut o2 = [0i32; 256];
    for i in 0..256 {
        o1[i] = round(s * x1[i] + c * y1[i]) * wi + round(c * x1[i] - s * y1[i]);
        o2[i] = round(s * x2[i] + c * y2[i]) * wi + round(c * x2[i] - s * y2[i]);
    }
    // Every test point lies within PATTERN_RADIUS (15) of the centre, so each rotated and
    // rounded offset is within 15 rows and 15 columns: one check that the block of radius 16
    // fits serves all 512 loads (keypoints stay `edge_threshold` inside their level).
    let reach = 16 * w as isize + 16;
    if centre >= reach && centre + reach < smooth.len() as isize {
        // SAFETY: each index is centre + o with |o| <= 15 w + 15 < reach, inside `smooth`.
        tests(
            |o| unsafe { *smooth.get_unchecked((centre + o as isize) as usize) },
            &o1,
            &o2,
        )
    } else {
        tests(|o| smooth[(centre + o as isize) as usize], &o1, &o2)
    }
}

/// The 256 binary tests, point `o1[i]` darker than `o2[i]`, the pixels read by `at`.
#[inline(always)]
fn tests(at: impl Fn(i32) -> u8, o1: &[i32; 256], o2: &[i32; 256]) -> [u64; 4] {
    let mut d = [0u64; 4];
    for (word, out) in d.iter_mut().enumerate() {
        let mut bits = 0u64;
        for b in 0..64 {
            let i = word * 64 + b;
            bits |= ((at(o1[i]) < at(o2[i])) as u64) << b;
        }
        *out = bits;
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::extract::pattern;

    #[test]
    fn harris_equals_the_per_tap_definition() {
        let (w, h) = (40usize, 30usize);
        let img = crate::noise_image(w * h, 4242);
        let at = |x: i32, y: i32| img[y as usize * w + x as usize] as i64;
        for (x, y) in [(4, 4), (20, 15), (35, 25), (11, 22)] {
            let (mut a, mut b, mut c) = (0i64, 0i64, 0i64);
            for v in y - 3..=y + 3 {
                for u in x - 3..=x + 3 {
                    let ix = (at(u + 1, v - 1) - at(u - 1, v - 1))
                        + 2 * (at(u + 1, v) - at(u - 1, v))
                        + (at(u + 1, v + 1) - at(u - 1, v + 1));
                    let iy = (at(u - 1, v + 1) - at(u - 1, v - 1))
                        + 2 * (at(u, v + 1) - at(u, v - 1))
                        + (at(u + 1, v + 1) - at(u + 1, v - 1));
                    a += ix * ix;
                    b += iy * iy;
                    c += ix * iy;
                }
            }
            let want = harris_response(a, b, c, 0.04);
            assert_eq!(
                harris(&img, w, x, y, 0.04).to_bits(),
                want.to_bits(),
                "({x}, {y})"
            );
        }
        // The largest sums fit: a checkerboard of 0 and 255.
        let board: Vec<u8> = (0..w * h)
            .map(|i| if (i % w + i / w) % 2 == 0 { 255 } else { 0 })
            .collect();
        assert!(harris(&board, w, 20, 15, 0.04).is_finite());
    }

    #[test]
    fn orientation_equals_the_pixel_by_pixel_moments() {
        let (w, h) = (70usize, 52usize);
        let img = crate::noise_image(w * h, 977);
        // Bright top-right, for moments far from zero, plus noise.
        let ramp: Vec<u8> = (0..w * h)
            .map(|i| ((i % w) * 2 + (h - i / w) * 2).min(255) as u8 / 2 + img[i] / 2)
            .collect();
        for im in [&img, &ramp] {
            // Every position the disc fits, the border ones included (they take the scalar path).
            for y in 15..h as i32 - 15 {
                for x in 15..w as i32 - 15 {
                    let (a, b) = (orientation(im, w, x, y), orientation_scalar(im, w, x, y));
                    assert_eq!(a.to_bits(), b.to_bits(), "({x}, {y})");
                }
            }
        }
        // Saturated pixels: the largest products fit.
        let white = vec![255u8; w * h];
        assert_eq!(
            orientation(&white, w, 30, 30),
            orientation_scalar(&white, w, 30, 30)
        );
    }

    #[test]
    fn rotated_tests_stay_within_the_block_describe_checks_once() {
        // describe reads without a per-load check when the block of radius 16 fits: every
        // rotated, rounded test point must lie within 15 rows and columns of the centre.
        let round = |v: f32| v.round() as i32;
        for kind in [PatternKind::Learned, PatternKind::Gaussian] {
            for step in 0..3600 {
                let (s, c) = (step as f32 * 0.1).to_radians().sin_cos();
                for t in pattern(kind).iter() {
                    for (x, y) in [(t[0], t[1]), (t[2], t[3])] {
                        let (dy, dx) = (round(s * x + c * y), round(c * x - s * y));
                        assert!(dx.abs() <= 15 && dy.abs() <= 15, "{kind:?} {step} {t:?}");
                    }
                }
            }
        }
        // Near the border the checked path gives the same descriptor as an interior copy.
        let (w, h) = (64usize, 64usize);
        let img = crate::noise_image(w * h, 5);
        let mut shifted = vec![0u8; w * h];
        for y in 0..h - 11 {
            shifted[y * w..y * w + w].copy_from_slice(&img[(y + 11) * w..(y + 11) * w + w]);
        }
        for angle in [0.0f32, 0.7, 2.9] {
            let inner = describe(&img, w, 32, 26, angle, PatternKind::Learned);
            // Row 15: the block of radius 16 does not fit above it.
            let near = describe(&shifted, w, 32, 15, angle, PatternKind::Learned);
            assert_eq!(inner, near);
        }
    }

    #[test]
    fn orientation_points_to_the_bright_side() {
        let (w, h) = (41usize, 41usize);
        for (dx, dy, want) in [
            (1, 0, 0.0f32),
            (0, 1, std::f32::consts::FRAC_PI_2),
            (-1, 0, std::f32::consts::PI),
        ] {
            let img: Vec<u8> = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as i32 - 20, (i / w) as i32 - 20);
                    (128 + 4 * (dx * x + dy * y)) as u8
                })
                .collect();
            let a = orientation(&img, w, 20, 20);
            let diff = (a - want).rem_euclid(std::f32::consts::TAU);
            assert!(
                diff.min(std::f32::consts::TAU - diff) < 1e-3,
                "{a} vs {want}"
            );
        }
    }
}
