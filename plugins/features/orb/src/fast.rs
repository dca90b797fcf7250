//! FAST-9 corners (Rosten and Drummond, ECCV 2006): a pixel is a corner when 9 contiguous
//! pixels of the radius-3 Bresenham circle are all brighter than `p + t` or all darker than
//! `p - t`. A row-wise rejection test on the four compass pixels (two adjacent ones must pass,
//! since any 9-arc covers two of them) runs as plain byte loops the compiler vectorises; the
//! survivors get the full test as 16-bit masks. The score is the largest threshold at which the
//! pixel is still a corner (as OpenCV's), used for 3x3 non-maximum suppression.

/// The circle, clockwise from the top: index 0 is (0, -3), 4 is (3, 0), 8 is (0, 3), 12 is (-3, 0).
pub const CIRCLE: [(i32, i32); 16] = [
    (0, -3),
    (1, -3),
    (2, -2),
    (3, -1),
    (3, 0),
    (3, 1),
    (2, 2),
    (1, 3),
    (0, 3),
    (-1, 3),
    (-2, 2),
    (-3, 1),
    (-3, 0),
    (-3, -1),
    (-2, -2),
    (-1, -3),
];

/// A corner on one pyramid level.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Corner {
    /// Column, pixels.
    pub x: u32,
    /// Row, pixels.
    pub y: u32,
    /// Largest threshold at which it is still a corner.
    pub score: u8,
}

/// True when the 16-bit ring mask has 9 contiguous set bits (wrapping around).
#[inline(always)]
fn has_arc9(mask: u32) -> bool {
    let x = mask | (mask << 16);
    let r2 = x & (x >> 1);
    let r4 = r2 & (r2 >> 2);
    let r8 = r4 & (r4 >> 4);
    (r8 & (x >> 8)) != 0
}

/// Corner score: the largest `t` for which 9 contiguous pixels all differ from the centre by
/// more than `t` with one sign. Sliding minima over the wrapped ring (windows of 2, 4, 8, 9),
/// fixed-size loops the compiler unrolls into a handful of SIMD operations. This scalar form
/// serves the portable path and the row tails; the vector detectors compute the same in
/// saturating bytes for a whole chunk.
#[inline]
fn score(d: &[i16; 16]) -> u8 {
    let mut b = [0i16; 32];
    let mut k = [0i16; 32];
    for i in 0..32 {
        b[i] = d[i & 15];
        k[i] = -d[i & 15];
    }
    let min_window = |x: &[i16; 32]| -> i16 {
        let mut m2 = [0i16; 24];
        for i in 0..24 {
            m2[i] = x[i].min(x[i + 1]);
        }
        let mut m4 = [0i16; 16];
        let mut best = i16::MIN;
        for i in 0..16 {
            m4[i] = m2[i].min(m2[i + 2]);
        }
        for i in 0..16 {
            // Window [i, i + 9): [i, i + 4) and [i + 4, i + 8) and i + 8.
            let m4b = m2[i + 4].min(m2[i + 6]);
            best = best.max(m4[i].min(m4b).min(x[i + 8]));
        }
        best
    };
    let best = min_window(&b).max(min_window(&k));
    (best - 1).clamp(0, 255) as u8
}

/// Reusable buffers.
#[derive(Default)]
pub struct FastScratch {
    flags: Vec<u8>,
}

/// Detects FAST-9 corners with centres in `[x0, x1) x [y0, y1)` (clamped to 3 pixels from the
/// border) of a `w`-wide image, appending them to `out` in raster order with their scores (no
/// suppression). On x86-64, 32 pixels at a time with AVX2 where the CPU has it and the rows are
/// wide enough, else 16 at a time with SSE2 (part of the x86-64 baseline).
#[allow(clippy::too_many_arguments)]
pub fn detect(
    img: &[u8],
    w: usize,
    h: usize,
    rect: (usize, usize, usize, usize),
    threshold: u8,
    scratch: &mut FastScratch,
    out: &mut Vec<Corner>,
) {
    #[cfg(target_arch = "x86_64")]
    {
        let _ = scratch;
        // Rows of at least 32 pixels go 32 at a time (the retry cells, 30 wide by default, 16).
        let width = rect
            .2
            .min(w.saturating_sub(3))
            .saturating_sub(rect.0.max(3));
        if width >= 32 && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            unsafe { detect_avx2(img, w, h, rect, threshold, out) }
        } else {
            // SAFETY: SSE2 is part of the x86-64 baseline, so every x86-64 CPU has it.
            unsafe { detect_sse2(img, w, h, rect, threshold, out) }
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    detect_scalar(img, w, h, rect, threshold, scratch, out)
}

/// The full segment test of the pixel at `centre`: its score when it is a corner.
#[inline]
fn full_test(img: &[u8], centre: usize, offsets: &[isize; 16], t: u8) -> Option<u8> {
    let p = img[centre] as i16;
    let mut d = [0i16; 16];
    let (mut bright, mut dark) = (0u32, 0u32);
    for k in 0..16 {
        let v = img[(centre as isize + offsets[k]) as usize] as i16 - p;
        d[k] = v;
        bright |= ((v > t as i16) as u32) << k;
        dark |= ((v < -(t as i16)) as u32) << k;
    }
    (has_arc9(bright) || has_arc9(dark)).then(|| score(&d).max(t))
}

/// The vector detector, generated for SSE2 (16 lanes) and AVX2 (32 lanes) from one body.
macro_rules! fast_simd {
    ($name:ident, $feature:literal, $lanes:literal, $vec:ty, $load:ident, $set1:ident,
     $zero:ident, $xor:ident, $adds:ident, $subs:ident, $cmpgt:ident, $and:ident, $or:ident,
     $movemask:ident, $min:ident, $max:ident, $store:ident) => {
        #[cfg(target_arch = "x86_64")]
        #[target_feature(enable = $feature)]
        fn $name(
            img: &[u8],
            w: usize,
            h: usize,
            (x0, y0, x1, y1): (usize, usize, usize, usize),
            threshold: u8,
            out: &mut Vec<Corner>,
        ) {
            use std::arch::x86_64::*;
            let (x0, y0) = (x0.max(3), y0.max(3));
            let (x1, y1) = (x1.min(w.saturating_sub(3)), y1.min(h.saturating_sub(3)));
            if x1 <= x0 || y1 <= y0 {
                return;
            }
            let offsets: [isize; 16] =
                CIRCLE.map(|(dx, dy)| dy as isize * w as isize + dx as isize);
            let t = threshold.max(1);
            let bias = $set1(-128);
            let tv = $set1(t as i8);
            let one = $set1(1);
            let zero = $zero();
            for y in y0..y1 {
                let mut x = x0;
                // Chunks of $lanes; the last one of a row is moved back to end at x1 (when the row is at
                // least $lanes wide) and ignores the pixels already done, so no pixel goes to the slow tail.
                while x + $lanes <= x1 || (x < x1 && x1 >= x0 + $lanes) {
                    let skip = (x + $lanes).saturating_sub(x1);
                    x -= skip;
                    let c = y * w + x;
                    // Every load reads img[c + o .. c + o + lanes] with |o| <= 3 w + 3: inside the
                    // image, because 3 <= x, x + lanes - 1 + 3 < w and 3 <= y < h - 3.
                    debug_assert!(
                        c as isize + offsets[0] >= 0 && c + 3 * w + 3 + $lanes <= img.len()
                    );
                    let ld = |o: isize| -> $vec {
                        let at = (c as isize + o) as usize;
                        let bytes: &[u8; $lanes] =
                            img[at..at + $lanes].try_into().expect("a full load");
                        // SAFETY: `bytes` is one vector of readable bytes; the load is unaligned.
                        unsafe { $load(bytes.as_ptr().cast()) }
                    };
                    let p = ld(0);
                    // Unsigned comparisons as signed ones on values shifted by 128.
                    let hi = $xor($adds(p, tv), bias);
                    let lo = $xor($subs(p, tv), bias);
                    let mut b = [zero; 16];
                    let mut d = [zero; 16];
                    let ring = |b: &mut [$vec; 16], d: &mut [$vec; 16], k: usize| {
                        let v = $xor(ld(offsets[k]), bias);
                        b[k] = $cmpgt(v, hi);
                        d[k] = $cmpgt(lo, v);
                    };
                    for k in [0, 4, 8, 12, 2, 6, 10, 14] {
                        ring(&mut b, &mut d, k);
                    }
                    // Quick rejection: two adjacent compass points and two adjacent diagonal points.
                    let pair = |m: &[$vec; 16], a: [usize; 4]| {
                        let o1 = $or($and(m[a[0]], m[a[1]]), $and(m[a[1]], m[a[2]]));
                        let o2 = $or($and(m[a[2]], m[a[3]]), $and(m[a[3]], m[a[0]]));
                        $or(o1, o2)
                    };
                    let quick_b = $and(pair(&b, [0, 4, 8, 12]), pair(&b, [2, 6, 10, 14]));
                    let quick_d = $and(pair(&d, [0, 4, 8, 12]), pair(&d, [2, 6, 10, 14]));
                    let done = ((1u64 << skip) - 1) as u32;
                    if ($movemask($or(quick_b, quick_d)) as u32) & !done == 0 {
                        x += $lanes;
                        continue;
                    }
                    for k in [1, 3, 5, 7, 9, 11, 13, 15] {
                        ring(&mut b, &mut d, k);
                    }
                    // 9 contiguous: windows of 2, 4, 8 and then 9, over the wrapped ring.
                    let arc9 = |m: &[$vec; 16]| {
                        let r2: [$vec; 16] = std::array::from_fn(|k| $and(m[k], m[(k + 1) & 15]));
                        let r4: [$vec; 16] = std::array::from_fn(|k| $and(r2[k], r2[(k + 2) & 15]));
                        let mut any = zero;
                        for k in 0..16 {
                            let r8 = $and(r4[k], r4[(k + 4) & 15]);
                            any = $or(any, $and(r8, m[(k + 8) & 15]));
                        }
                        any
                    };
                    let mut mask = ($movemask($or(arc9(&b), arc9(&d))) as u32) & !done;
                    if mask != 0 {
                        // The scores of every lane at once (`score`, in saturating bytes: a
                        // corner's best arc minimum is above t >= 1, so clamping the
                        // differences at 0 changes no maximum that matters).
                        let (mut best_b, mut best_d) = (zero, zero);
                        let (mut bd, mut dd) = ([zero; 16], [zero; 16]);
                        for k in 0..16 {
                            let v = ld(offsets[k]);
                            bd[k] = $subs(v, p);
                            dd[k] = $subs(p, v);
                        }
                        for (diffs, best) in [(&bd, &mut best_b), (&dd, &mut best_d)] {
                            let m2: [$vec; 16] =
                                std::array::from_fn(|k| $min(diffs[k], diffs[(k + 1) & 15]));
                            let m4: [$vec; 16] =
                                std::array::from_fn(|k| $min(m2[k], m2[(k + 2) & 15]));
                            for k in 0..16 {
                                let m9 = $min($min(m4[k], m4[(k + 4) & 15]), diffs[(k + 8) & 15]);
                                *best = $max(*best, m9);
                            }
                        }
                        let scores = $max($subs($max(best_b, best_d), one), tv);
                        let mut lanes = [0u8; $lanes];
                        // SAFETY: `lanes` is one vector of writable bytes; the store is unaligned.
                        unsafe { $store(lanes.as_mut_ptr().cast(), scores) };
                        while mask != 0 {
                            let i = mask.trailing_zeros() as usize;
                            mask &= mask - 1;
                            out.push(Corner {
                                x: (x + i) as u32,
                                y: y as u32,
                                score: lanes[i],
                            });
                        }
                    }
                    x += $lanes;
                }
                // The tail of the row, one pixel at a time.
                for xt in x..x1 {
                    if let Some(score) = full_test(img, y * w + xt, &offsets, t) {
                        out.push(Corner {
                            x: xt as u32,
                            y: y as u32,
                            score,
                        });
                    }
                }
            }
        }
    };
}

fast_simd!(
    detect_sse2,
    "sse2",
    16,
    __m128i,
    _mm_loadu_si128,
    _mm_set1_epi8,
    _mm_setzero_si128,
    _mm_xor_si128,
    _mm_adds_epu8,
    _mm_subs_epu8,
    _mm_cmpgt_epi8,
    _mm_and_si128,
    _mm_or_si128,
    _mm_movemask_epi8,
    _mm_min_epu8,
    _mm_max_epu8,
    _mm_storeu_si128
);
fast_simd!(
    detect_avx2,
    "avx2",
    32,
    __m256i,
    _mm256_loadu_si256,
    _mm256_set1_epi8,
    _mm256_setzero_si256,
    _mm256_xor_si256,
    _mm256_adds_epu8,
    _mm256_subs_epu8,
    _mm256_cmpgt_epi8,
    _mm256_and_si256,
    _mm256_or_si256,
    _mm256_movemask_epi8,
    _mm256_min_epu8,
    _mm256_max_epu8,
    _mm256_storeu_si256
);

/// The portable detector: a vectorisable byte-wise rejection test per row, then the full test.
#[allow(clippy::too_many_arguments, dead_code)]
fn detect_scalar(
    img: &[u8],
    w: usize,
    h: usize,
    (x0, y0, x1, y1): (usize, usize, usize, usize),
    threshold: u8,
    scratch: &mut FastScratch,
    out: &mut Vec<Corner>,
) {
    let (x0, y0) = (x0.max(3), y0.max(3));
    let (x1, y1) = (x1.min(w.saturating_sub(3)), y1.min(h.saturating_sub(3)));
    if x1 <= x0 || y1 <= y0 {
        return;
    }
    let n = x1 - x0;
    let offsets: [isize; 16] = CIRCLE.map(|(dx, dy)| dy as isize * w as isize + dx as isize);
    scratch.flags.resize(n, 0);
    let t = threshold.max(1);
    for y in y0..y1 {
        let row = &img[y * w..(y + 1) * w];
        let up = &img[(y - 3) * w..(y - 2) * w];
        let dn = &img[(y + 3) * w..(y + 4) * w];
        let c = &row[x0..x1];
        let top = &up[x0..x1];
        let bot = &dn[x0..x1];
        let right = &row[x0 + 3..x1 + 3];
        let left = &row[x0 - 3..x1 - 3];
        // Diagonal points: 2 = (2, -2), 6 = (2, 2), 10 = (-2, 2), 14 = (-2, -2). `up1[i]` is
        // (-2, -2) and `up1[i + 4]` is (2, -2) relative to pixel x0 + i; likewise `dn1`.
        let up1 = &img[(y - 2) * w + x0 - 2..(y - 2) * w + x1 + 2];
        let dn1 = &img[(y + 2) * w + x0 - 2..(y + 2) * w + x1 + 2];
        let flags = &mut scratch.flags[..n];
        for i in 0..n {
            let p = c[i];
            let hi = p.saturating_add(t);
            let lo = p.saturating_sub(t);
            let (bt, br, bb, bl) = (
                (top[i] > hi) as u8,
                (right[i] > hi) as u8,
                (bot[i] > hi) as u8,
                (left[i] > hi) as u8,
            );
            let (dt, dr, db, dl) = (
                (top[i] < lo) as u8,
                (right[i] < lo) as u8,
                (bot[i] < lo) as u8,
                (left[i] < lo) as u8,
            );
            let compass = (bt & br)
                | (br & bb)
                | (bb & bl)
                | (bl & bt)
                | (dt & dr)
                | (dr & db)
                | (db & dl)
                | (dl & dt);
            // Any 9-arc also covers two adjacent ones of the diagonal points 2, 6, 10, 14.
            let (q1, q2, q3, q4) = (up1[i], up1[i + 4], dn1[i + 4], dn1[i]);
            let (e1, e2, e3, e4) = (
                (q1 > hi) as u8,
                (q2 > hi) as u8,
                (q3 > hi) as u8,
                (q4 > hi) as u8,
            );
            let (f1, f2, f3, f4) = (
                (q1 < lo) as u8,
                (q2 < lo) as u8,
                (q3 < lo) as u8,
                (q4 < lo) as u8,
            );
            let diagonal = (e1 & e2)
                | (e2 & e3)
                | (e3 & e4)
                | (e4 & e1)
                | (f1 & f2)
                | (f2 & f3)
                | (f3 & f4)
                | (f4 & f1);
            flags[i] = compass & diagonal;
        }
        // Skip eight flags at a time.
        let mut i = 0;
        while i < n {
            if i + 8 <= n {
                let mut chunk = [0u8; 8];
                chunk.copy_from_slice(&flags[i..i + 8]);
                if u64::from_ne_bytes(chunk) == 0 {
                    i += 8;
                    continue;
                }
            }
            if flags[i] != 0 {
                let x = x0 + i;
                if let Some(score) = full_test(img, y * w + x, &offsets, t) {
                    out.push(Corner {
                        x: x as u32,
                        y: y as u32,
                        score,
                    });
                }
            }
            i += 1;
        }
    }
}

/// Keeps the corners that are strict maxima of the score in their 3x3 neighbourhood (ties
/// broken by raster order, so a plateau keeps exactly one). Each pixel must appear at most once. `map` is a zeroed `w * h` buffer
/// and is zeroed again on return.
pub fn non_max_suppression(corners: &mut Vec<Corner>, w: usize, map: &mut [u8]) {
    KEEP.with_borrow_mut(|keep| suppress(corners, w, map, keep));
}

thread_local! {
    /// Per-thread buffer of the suppression's decisions (no allocation per level and frame).
    static KEEP: std::cell::RefCell<Vec<bool>> = const { std::cell::RefCell::new(Vec::new()) };
}

fn suppress(corners: &mut Vec<Corner>, w: usize, map: &mut [u8], keep: &mut Vec<bool>) {
    for c in corners.iter() {
        let i = c.y as usize * w + c.x as usize;
        map[i] = map[i].max(c.score.max(1));
    }
    keep.clear();
    keep.extend(corners.iter().map(|c| {
        let i = c.y as usize * w + c.x as usize;
        let s = map[i];
        // The row above and the left neighbour come earlier in raster order and win ties; the
        // right neighbour and the row below must be strictly lower. A duplicate of the pixel
        // with a lower score fails the first test. Branch-free: corners cluster, so a branch
        // per neighbour would be mispredicted.
        let (up, row, down) = (
            &map[i - w - 1..i - w + 2],
            &map[i - 1..i + 2],
            &map[i + w - 1..i + w + 2],
        );
        let earlier = up[0].max(up[1]).max(up[2]).max(row[0]);
        let later = down[0].max(down[1]).max(down[2]).max(row[2]);
        (s == c.score.max(1)) & (earlier < s) & (later <= s)
    }));
    for c in corners.iter() {
        map[c.y as usize * w + c.x as usize] = 0;
    }
    let mut k = 0;
    corners.retain(|_| {
        let keep = keep[k];
        k += 1;
        keep
    });
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute-force segment test, straight from the definition.
    fn is_corner(img: &[u8], w: usize, x: usize, y: usize, t: u8) -> bool {
        let p = img[y * w + x] as i32;
        let ring: Vec<i32> = CIRCLE
            .iter()
            .map(|&(dx, dy)| img[(y as i32 + dy) as usize * w + (x as i32 + dx) as usize] as i32)
            .collect();
        for s in 0..16 {
            if (0..9).all(|j| ring[(s + j) % 16] > p + t as i32)
                || (0..9).all(|j| ring[(s + j) % 16] < p - t as i32)
            {
                return true;
            }
        }
        false
    }

    #[test]
    fn detection_equals_the_definition_on_noise() {
        let (w, h) = (64usize, 48usize);
        let img = crate::noise_image(w * h, 12345);
        for t in [10u8, 20, 40] {
            let mut out = Vec::new();
            detect(
                &img,
                w,
                h,
                (0, 0, w, h),
                t,
                &mut FastScratch::default(),
                &mut out,
            );
            let got: Vec<(u32, u32)> = out.iter().map(|c| (c.x, c.y)).collect();
            let mut want = Vec::new();
            for y in 3..h - 3 {
                for x in 3..w - 3 {
                    if is_corner(&img, w, x, y, t) {
                        want.push((x as u32, y as u32));
                    }
                }
            }
            assert_eq!(got, want, "threshold {t}");
            let mut portable = Vec::new();
            detect_scalar(
                &img,
                w,
                h,
                (0, 0, w, h),
                t,
                &mut FastScratch::default(),
                &mut portable,
            );
            assert_eq!(
                portable, out,
                "portable and dispatched detectors differ at {t}"
            );
            // Sub-rectangles as the low-threshold retry uses them: 30 wide (a chunk moved back
            // to end at the edge), 10 wide (narrower than a chunk), offset.
            for rect in [(5, 4, 35, 40), (10, 10, 20, 30), (21, 6, 61, 20)] {
                let mut part = Vec::new();
                detect(&img, w, h, rect, t, &mut FastScratch::default(), &mut part);
                let inside = |&(x, y): &(u32, u32)| {
                    (rect.0 as u32..rect.2 as u32).contains(&x)
                        && (rect.1 as u32..rect.3 as u32).contains(&y)
                };
                let want_part: Vec<(u32, u32)> = want.iter().copied().filter(inside).collect();
                let got_part: Vec<(u32, u32)> = part.iter().map(|c| (c.x, c.y)).collect();
                assert_eq!(got_part, want_part, "threshold {t}, rect {rect:?}");
                // The same scores on the narrower vector path (16 lanes) and the scalar tail.
                let whole: Vec<Corner> = out
                    .iter()
                    .copied()
                    .filter(|c| inside(&(c.x, c.y)))
                    .collect();
                assert_eq!(part, whole, "threshold {t}, rect {rect:?}");
            }
            assert!(!want.is_empty());
            // The score is the largest threshold that keeps the corner.
            for c in &out {
                assert!(is_corner(&img, w, c.x as usize, c.y as usize, c.score));
                if c.score < 255 {
                    assert!(!is_corner(&img, w, c.x as usize, c.y as usize, c.score + 1));
                }
            }
        }
    }

    /// Suppression against its definition, on dense random corners with few score values (many
    /// ties): a corner stays when no 8-neighbour scores higher, and no earlier neighbour in
    /// raster order (the row above, the left pixel) scores the same.
    #[test]
    fn suppression_keeps_strict_maxima_with_raster_order_ties() {
        let (w, h) = (23usize, 17usize);
        let mut state = 11u32;
        let mut rnd = move || {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            state >> 24
        };
        for round in 0..50 {
            let mut corners = Vec::new();
            for y in 1..h - 1 {
                for x in 1..w - 1 {
                    if rnd() % 3 != 0 {
                        let score = (rnd() % 4) as u8 + (round % 2) as u8 * 20;
                        corners.push(Corner {
                            x: x as u32,
                            y: y as u32,
                            score,
                        });
                    }
                }
            }
            let at = |x: i64, y: i64| {
                corners
                    .iter()
                    .find(|c| c.x as i64 == x && c.y as i64 == y)
                    .map_or(0, |c| c.score.max(1))
            };
            let want: Vec<Corner> = corners
                .iter()
                .copied()
                .filter(|c| {
                    let (x, y, s) = (c.x as i64, c.y as i64, c.score.max(1));
                    (-1..=1i64).all(|dy| {
                        (-1..=1i64).all(|dx| {
                            let n = at(x + dx, y + dy);
                            let earlier = dy < 0 || (dy == 0 && dx < 0);
                            (dx == 0 && dy == 0) || n < s || (n == s && !earlier)
                        })
                    })
                })
                .collect();
            let mut map = vec![0u8; w * h];
            let mut got = corners.clone();
            non_max_suppression(&mut got, w, &mut map);
            assert_eq!(got, want, "round {round}");
            assert!(map.iter().all(|&v| v == 0));
        }
    }

    #[test]
    fn a_bright_square_has_corners_at_its_corners_only() {
        let (w, h) = (40usize, 40usize);
        let mut img = vec![50u8; w * h];
        for y in 15..25 {
            for x in 15..25 {
                img[y * w + x] = 200;
            }
        }
        let mut out = Vec::new();
        detect(
            &img,
            w,
            h,
            (0, 0, w, h),
            20,
            &mut FastScratch::default(),
            &mut out,
        );
        let mut map = vec![0u8; w * h];
        non_max_suppression(&mut out, w, &mut map);
        assert!(map.iter().all(|&v| v == 0));
        // Every corner lies within 3 pixels (the circle's radius) of a corner of the square,
        // and every corner of the square has one; nothing along the edges or inside.
        let near = |c: &Corner, x: u32, y: u32| c.x.abs_diff(x) <= 3 && c.y.abs_diff(y) <= 3;
        let square = [(15, 15), (24, 15), (15, 24), (24, 24)];
        for c in &out {
            assert!(square.iter().any(|&(x, y)| near(c, x, y)), "{c:?}");
        }
        for (x, y) in square {
            assert!(
                out.iter().any(|c| near(c, x, y)),
                "none at ({x}, {y}): {out:?}"
            );
        }
        assert!(out.len() <= 8, "{out:?}");
    }
}
