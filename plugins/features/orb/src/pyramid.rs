//! The scale pyramid: level `l` is the image resized by `1 / scale^l` (bilinear, each level from
//! the previous one), and a Gaussian-smoothed copy of each level for the binary tests.

/// One 8-bit gray level.
#[derive(Clone, Debug, Default)]
pub struct Level {
    /// Width, pixels.
    pub width: usize,
    /// Height, pixels.
    pub height: usize,
    /// Row-major bytes.
    pub data: Vec<u8>,
    /// The same, smoothed by a 7x7 Gaussian (sigma 2); valid from 3 pixels inside the border.
    pub smooth: Vec<u8>,
    /// Level-0 pixels per pixel of this level (`scale^l`).
    pub scale: f32,
}

/// Resizes `src` (`sw` x `sh`) into `dst` (`dw` x `dh`) bilinearly, pixel centres aligned.
/// Separable: each source row is resized horizontally once (8-bit weights, rounded back to 8
/// bits) and kept while two consecutive output rows use it; the vertical blend is a 16-bit loop
/// the compiler vectorises. Within one gray level of exact bilinear interpolation.
pub fn resize_bilinear(src: &[u8], sw: usize, sh: usize, dst: &mut Vec<u8>, dw: usize, dh: usize) {
    dst.clear();
    dst.resize(dw * dh, 0);
    if dw == 0 || dh == 0 || sw == 0 || sh == 0 {
        return;
    }
    let fy = sh as f32 / dh as f32;
    let cols = columns(sw, dw);
    let chunks = shuffle_chunks(&cols, sw);
    let horizontal = |row: &[u8], out: &mut [u16]| {
        let done = horizontal_simd(row, &chunks, out);
        horizontal_scalar(row, &cols[done..], &mut out[done..]);
    };
    let (mut top, mut bot) = (vec![0u16; dw], vec![0u16; dw]);
    let (mut top_row, mut bot_row) = (usize::MAX, usize::MAX);
    for y in 0..dh {
        let s = ((y as f32 + 0.5) * fy - 0.5).clamp(0.0, (sh - 1) as f32);
        let j = (s as usize).min(sh.saturating_sub(2));
        let j1 = (j + 1).min(sh - 1);
        let b = ((s - j as f32) * 256.0).round().clamp(0.0, 256.0) as u16;
        if top_row != j {
            if bot_row == j {
                std::mem::swap(&mut top, &mut bot);
                bot_row = usize::MAX;
            } else {
                horizontal(&src[j * sw..(j + 1) * sw], &mut top);
            }
            top_row = j;
        }
        if bot_row != j1 {
            horizontal(&src[j1 * sw..(j1 + 1) * sw], &mut bot);
            bot_row = j1;
        }
        for ((d, &t), &u) in dst[y * dw..(y + 1) * dw].iter_mut().zip(&top).zip(&bot) {
            *d = ((t * (256 - b) + u * b + 128) >> 8) as u8;
        }
    }
}

/// Per output column: the left source index and the 8-bit weight of the right neighbour.
fn columns(sw: usize, dw: usize) -> Vec<(usize, u16)> {
    let fx = sw as f32 / dw as f32;
    (0..dw)
        .map(|x| {
            let s = ((x as f32 + 0.5) * fx - 0.5).clamp(0.0, (sw - 1) as f32);
            let i = (s as usize).min(sw.saturating_sub(2));
            let a = ((s - i as f32) * 256.0).round().clamp(0.0, 256.0) as u16;
            (i, a)
        })
        .collect()
}

/// The horizontal pass, one pixel at a time: `out[k]` from the source pair of `cols[k]`.
fn horizontal_scalar(row: &[u8], cols: &[(usize, u16)], out: &mut [u16]) {
    let last = row.len() - 1;
    for (o, &(i, a)) in out.iter_mut().zip(cols) {
        let i1 = (i + 1).min(last);
        *o = (row[i] as u16 * (256 - a) + row[i1] as u16 * a + 128) >> 8;
    }
}

/// Eight output pixels of a horizontal resize pass: the 16 source bytes from `base` hold both
/// neighbours of each, `left` and `right` pick them into 16-bit lanes (a byte shuffle; 0x80 gives
/// the zero high byte), `weight` is each right neighbour's 8-bit weight.
#[derive(Clone, Copy)]
struct Chunk {
    base: usize,
    left: [u8; 16],
    right: [u8; 16],
    weight: [u16; 8],
}

/// The leading run of output pixels, eight at a time, whose two source neighbours lie within 16
/// bytes that can be loaded inside the row (all of them for a downscale by less than 1.85).
fn shuffle_chunks(cols: &[(usize, u16)], sw: usize) -> Vec<Chunk> {
    let mut out = Vec::with_capacity(cols.len() / 8);
    for group in cols.chunks_exact(8) {
        let base = group[0].0;
        if base + 16 > sw {
            break;
        }
        let mut c = Chunk {
            base,
            left: [0x80; 16],
            right: [0x80; 16],
            weight: [0; 8],
        };
        let mut fits = true;
        for (k, &(i, a)) in group.iter().enumerate() {
            let (l, r) = (i - base, (i + 1).min(sw - 1) - base);
            fits &= r < 16;
            c.left[2 * k] = l as u8;
            c.right[2 * k] = r as u8;
            c.weight[k] = a;
        }
        if !fits {
            break;
        }
        out.push(c);
    }
    out
}

/// The horizontal pass over the leading chunks; returns how many output pixels it wrote.
fn horizontal_simd(row: &[u8], chunks: &[Chunk], out: &mut [u16]) -> usize {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("ssse3") {
        // SAFETY: the CPU supports SSSE3 (checked just above).
        unsafe { horizontal_ssse3(row, chunks, out) };
        return 8 * chunks.len();
    }
    let _ = (row, chunks, out);
    0
}

#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "ssse3")]
fn horizontal_ssse3(row: &[u8], chunks: &[Chunk], out: &mut [u16]) {
    use std::arch::x86_64::*;
    let round = _mm_set1_epi16(128);
    let full = _mm_set1_epi16(256);
    for (c, o) in chunks.iter().zip(out.chunks_exact_mut(8)) {
        let src: &[u8; 16] = row[c.base..c.base + 16].try_into().expect("16 bytes");
        // SAFETY: every load reads 16 bytes of a 16-byte array, every store writes 8 u16 of an
        // 8-element chunk; all unaligned.
        unsafe {
            let v = _mm_loadu_si128(src.as_ptr().cast());
            let l = _mm_shuffle_epi8(v, _mm_loadu_si128(c.left.as_ptr().cast()));
            let r = _mm_shuffle_epi8(v, _mm_loadu_si128(c.right.as_ptr().cast()));
            let a = _mm_loadu_si128(c.weight.as_ptr().cast());
            // l (256 - a) + r a + 128 <= 255 * 256 + 128: exact in 16 bits.
            let sum = _mm_add_epi16(
                _mm_add_epi16(
                    _mm_mullo_epi16(l, _mm_sub_epi16(full, a)),
                    _mm_mullo_epi16(r, a),
                ),
                round,
            );
            _mm_storeu_si128(o.as_mut_ptr().cast(), _mm_srli_epi16(sum, 8));
        }
    }
}

/// 7-tap Gaussian, sigma 2, in 8-bit fixed point (sums to 256).
const GAUSS7: [u32; 4] = [54, 49, 34, 18];

/// Smooths `src` by the separable 7x7 Gaussian into `dst` (the 3-pixel border is copied);
/// within one gray level of the exact filter. `dst` and `tmp` are reused as they come: every
/// byte of `dst` is written (the interior by the filter, the border copied), and `tmp` only
/// grows, its columns 3..w-3 of every row written by the horizontal pass before the vertical
/// pass reads them (the per-level zeroing and full copy were 8 % of ORB's time).
pub fn gaussian7(src: &[u8], w: usize, h: usize, dst: &mut Vec<u8>, tmp: &mut Vec<u16>) {
    assert!(
        src.len() >= w * h,
        "gaussian7: {} bytes for {w}x{h}",
        src.len()
    );
    let src = &src[..w * h];
    if w < 7 || h < 7 {
        dst.clear();
        dst.extend_from_slice(src);
        return;
    }
    dst.resize(w * h, 0);
    // The border: three rows at the top and bottom, three columns either side of the others.
    dst[..3 * w].copy_from_slice(&src[..3 * w]);
    dst[(h - 3) * w..].copy_from_slice(&src[(h - 3) * w..]);
    for y in 3..h - 3 {
        let r = y * w;
        dst[r..r + 3].copy_from_slice(&src[r..r + 3]);
        dst[r + w - 3..r + w].copy_from_slice(&src[r + w - 3..r + w]);
    }
    if tmp.len() < w * h {
        tmp.resize(w * h, 0);
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") {
        // SAFETY: the CPU supports AVX2 (checked just above).
        unsafe { passes_avx2(src, w, h, dst, tmp) };
        return;
    }
    passes(src, w, h, dst, tmp);
}

/// [`passes`] compiled for AVX2: the same integer arithmetic, vectorised 16 lanes at a time
/// instead of SSE2's 8 (the filter was a tenth of ORB's time).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn passes_avx2(src: &[u8], w: usize, h: usize, dst: &mut [u8], tmp: &mut [u16]) {
    passes(src, w, h, dst, tmp)
}

/// The two passes of [`gaussian7`] over the interior (`w`, `h` >= 7; `dst` and `tmp` hold
/// `w` x `h`), written for the compiler to vectorise.
#[inline(always)]
fn passes(src: &[u8], w: usize, h: usize, dst: &mut [u8], tmp: &mut [u16]) {
    // Both passes in 16-bit lanes (8 per SSE2 register, 16 per AVX2 one): a pass sums at most 255 * 256, and
    // its result is rounded back to 8 bits before the next.
    let [k0, k1, k2, k3] = GAUSS7.map(|k| k as u16);
    // Horizontal: u8 -> u8 precision, kept in u16.
    for y in 0..h {
        let r = &src[y * w..(y + 1) * w];
        let n = w - 6;
        let t = &mut tmp[y * w + 3..y * w + 3 + n];
        let (a, b, c, d, e, f, g) = (
            &r[0..n],
            &r[1..n + 1],
            &r[2..n + 2],
            &r[3..n + 3],
            &r[4..n + 4],
            &r[5..n + 5],
            &r[6..n + 6],
        );
        for i in 0..n {
            let v = k0 * d[i] as u16
                + k1 * (c[i] as u16 + e[i] as u16)
                + k2 * (b[i] as u16 + f[i] as u16)
                + k3 * (a[i] as u16 + g[i] as u16);
            t[i] = (v + 128) >> 8;
        }
    }
    // Vertical: -> u8.
    for y in 3..h - 3 {
        let row = |k: usize| &tmp[(y + k - 3) * w + 3..(y + k - 3) * w + w - 3];
        let (a, b, c, d, e, f, g) = (row(0), row(1), row(2), row(3), row(4), row(5), row(6));
        let out = &mut dst[y * w + 3..y * w + w - 3];
        for i in 0..out.len() {
            let v = k0 * d[i] + k1 * (c[i] + e[i]) + k2 * (b[i] + f[i]) + k3 * (a[i] + g[i]);
            out[i] = ((v + 128) >> 8) as u8;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn resize_keeps_constant_and_linear_images() {
        let (sw, sh) = (60usize, 40usize);
        let flat = vec![77u8; sw * sh];
        let mut out = Vec::new();
        resize_bilinear(&flat, sw, sh, &mut out, 50, 33);
        assert!(out.iter().all(|&v| v == 77));
        // A horizontal ramp stays a ramp: value at the resized centre = value of the source there.
        let ramp: Vec<u8> = (0..sw * sh).map(|i| (i % sw) as u8 * 4).collect();
        resize_bilinear(&ramp, sw, sh, &mut out, 50, 33);
        for x in 1..49 {
            let s = (x as f32 + 0.5) * 60.0 / 50.0 - 0.5;
            assert!((out[10 * 50 + x] as f32 - 4.0 * s).abs() <= 1.0, "x {x}");
        }
    }

    #[test]
    fn fixed_point_filters_are_within_one_level_of_exact_ones() {
        let (w, h) = (37usize, 29usize);
        let img = crate::noise_image(w * h, 99);
        let (mut out, mut tmp) = (Vec::new(), Vec::new());
        gaussian7(&img, w, h, &mut out, &mut tmp);
        let k: Vec<f64> = (-3..=3)
            .map(|d: i32| (-(d * d) as f64 / 8.0).exp())
            .collect();
        let norm: f64 = k.iter().sum();
        for y in 3..h - 3 {
            for x in 3..w - 3 {
                let mut v = 0.0;
                for (j, kj) in k.iter().enumerate() {
                    for (i, ki) in k.iter().enumerate() {
                        v += kj * ki * img[(y + j - 3) * w + x + i - 3] as f64;
                    }
                }
                let exact = v / (norm * norm);
                assert!((out[y * w + x] as f64 - exact).abs() <= 1.5, "({x}, {y})");
            }
        }
        let (dw, dh) = (30usize, 24usize);
        resize_bilinear(&img, w, h, &mut out, dw, dh);
        for y in 0..dh {
            for x in 0..dw {
                let sx = ((x as f64 + 0.5) * w as f64 / dw as f64 - 0.5).clamp(0.0, (w - 1) as f64);
                let sy = ((y as f64 + 0.5) * h as f64 / dh as f64 - 0.5).clamp(0.0, (h - 1) as f64);
                let (i, j) = ((sx as usize).min(w - 2), (sy as usize).min(h - 2));
                let (a, b) = (sx - i as f64, sy - j as f64);
                let p = |x: usize, y: usize| img[y * w + x] as f64;
                let exact = (1.0 - b) * ((1.0 - a) * p(i, j) + a * p(i + 1, j))
                    + b * ((1.0 - a) * p(i, j + 1) + a * p(i + 1, j + 1));
                assert!((out[y * dw + x] as f64 - exact).abs() <= 1.5, "({x}, {y})");
            }
        }
    }

    #[test]
    fn the_shuffled_horizontal_pass_equals_the_scalar_one_at_every_pyramid_step() {
        let mut state = 7u32;
        let mut sw = 640usize;
        for _ in 0..7 {
            let dw = (sw as f32 / 1.2).round() as usize;
            let row: Vec<u8> = (0..sw)
                .map(|_| {
                    state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
                    (state >> 24) as u8
                })
                .collect();
            let cols = columns(sw, dw);
            let chunks = shuffle_chunks(&cols, sw);
            // All but the last chunk or two (whose 16-byte load would leave the row).
            assert!(
                8 * chunks.len() + 24 >= dw,
                "{sw} -> {dw}: {} chunks",
                chunks.len()
            );
            let (mut fast, mut slow) = (vec![0u16; dw], vec![0u16; dw]);
            let done = horizontal_simd(&row, &chunks, &mut fast);
            horizontal_scalar(&row, &cols, &mut slow);
            #[cfg(target_arch = "x86_64")]
            if std::arch::is_x86_feature_detected!("ssse3") {
                assert_eq!(done, 8 * chunks.len());
            }
            assert_eq!(fast[..done], slow[..done], "{sw} -> {dw}");
            sw = dw;
        }
    }

    #[test]
    fn gaussian_output_does_not_depend_on_what_the_reused_buffers_held() {
        let (w, h) = (41usize, 23usize);
        let img = crate::noise_image(w * h, 7);
        let (mut fresh, mut tmp) = (Vec::new(), Vec::new());
        gaussian7(&img, w, h, &mut fresh, &mut tmp);
        assert_eq!(fresh.len(), w * h);
        // The border is the source's.
        for y in 0..h {
            for x in 0..w {
                if x < 3 || y < 3 || x >= w - 3 || y >= h - 3 {
                    assert_eq!(fresh[y * w + x], img[y * w + x], "({x}, {y})");
                }
            }
        }
        // Buffers left larger or smaller, full of other values, give the same image.
        for (dst_len, tmp_len) in [(3 * w * h, 2 * w * h), (w * h / 2, 10), (0, 0)] {
            let mut dst = vec![0xab; dst_len];
            let mut tmp = vec![0xffff; tmp_len];
            gaussian7(&img, w, h, &mut dst, &mut tmp);
            assert_eq!(dst, fresh, "dst {dst_len}, tmp {tmp_len}");
        }
    }

    #[test]
    fn gaussian_gives_the_portable_passes_output_on_every_instruction_set() {
        // gaussian7 takes the AVX2 build where the CPU has it; `passes` called from here is
        // the baseline (SSE2) build. Widths around the vector lengths and their tails.
        for (w, h) in [(7usize, 7usize), (38, 9), (45, 20), (64, 13), (101, 31)] {
            let img = crate::noise_image(w * h, (w * 31 + h) as u32);
            let (mut out, mut tmp) = (Vec::new(), Vec::new());
            gaussian7(&img, w, h, &mut out, &mut tmp);
            let mut want = img.clone();
            let mut t = vec![0u16; w * h];
            passes(&img, w, h, &mut want, &mut t);
            assert_eq!(out, want, "{w}x{h}");
        }
    }

    #[test]
    fn gaussian_preserves_constants_and_smooths_an_impulse() {
        let (w, h) = (20usize, 20usize);
        let mut img = vec![100u8; w * h];
        let (mut out, mut tmp) = (Vec::new(), Vec::new());
        gaussian7(&img, w, h, &mut out, &mut tmp);
        assert!(out.iter().all(|&v| v == 100));
        img[10 * w + 10] = 255;
        gaussian7(&img, w, h, &mut out, &mut tmp);
        let c = out[10 * w + 10];
        // 100 + 155 * (54/256)^2 = 106.9
        assert!((106..=108).contains(&c), "{c}");
        assert_eq!(out[10 * w + 11], out[10 * w + 9]);
        assert_eq!(out[11 * w + 10], out[10 * w + 11]);
        assert_eq!(out[10 * w + 14], 100);
    }
}
