//! The census transform of SGM on a 255-padded image: with AVX2 (chosen at run time) 32 pixels
//! per step, one byte compare per neighbour and the bits gathered in byte planes; otherwise 64
//! pixels per step in u32 halves.

use rayon::prelude::*;

/// Census transform: bit k is set when neighbour k of the window (row by row, the centre
/// skipped, the first neighbour in the highest bit) is darker than the centre. Neighbours outside
/// the image count as equal to the centre (bit 0).
pub fn census(img: &[u8], w: usize, h: usize, cw: usize, ch: usize, out: &mut Vec<u64>) {
    census_with(img, w, h, cw, ch, &mut Vec::new(), out);
}

/// [`census`] with the padded image kept in `pad` between calls (no allocation per frame).
pub fn census_with(
    img: &[u8],
    w: usize,
    h: usize,
    cw: usize,
    ch: usize,
    pad: &mut Vec<u8>,
    out: &mut Vec<u64>,
) {
    let (rx, ry) = (cw / 2, ch / 2);
    // Pad with 255: "255 < centre" is never true, the same bit 0 as "equal to the centre". The
    // AVX2 rows compare signed bytes, so there every byte is offset by 128 (255 becomes 127,
    // still never below a centre); they read 32 bytes from each pixel on, hence the slack.
    let simd = crate::simd::avx2();
    let flip = if simd { 0x80 } else { 0 };
    let pw = w + 2 * rx;
    // Every byte is set here: the border and slack to the pad value, the inside to the image.
    pad.clear();
    pad.resize(pw * (h + 2 * ry) + 32, 255u8 ^ flip);
    for y in 0..h {
        let dst = &mut pad[(y + ry) * pw + rx..(y + ry) * pw + rx + w];
        for (d, &s) in dst.iter_mut().zip(&img[y * w..(y + 1) * w]) {
            *d = s ^ flip;
        }
    }
    // Every row is written below: only a size change needs the buffer reset.
    if out.len() != w * h {
        out.clear();
        out.resize(w * h, 0);
    }
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        #[cfg(target_arch = "x86_64")]
        if simd {
            // SAFETY: the CPU supports AVX2 (checked above); `pad` is offset by 128 and has
            // 32 bytes of slack after its last row.
            unsafe { census_row_avx2(pad, pw, rx, ry, y, row) };
            return;
        }
        census_row_generic(pad, pw, rx, ry, y, row);
    });
}

/// One census row, 32 pixels at a time: per neighbour (offsets from a table), a signed byte
/// compare with the centres (the padded image is offset by 128) shifted into a byte accumulator
/// (`acc + acc - mask`), eight neighbours per byte plane; the planes are then transposed into
/// one u64 per pixel by byte, word and dword unpacks.
///
/// # Safety
/// The CPU has AVX2; `pad` is the padded image offset by 128 with 32 bytes after its last row.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
unsafe fn census_row_avx2(pad: &[u8], pw: usize, rx: usize, ry: usize, y: usize, row: &mut [u64]) {
    use std::arch::x86_64::*;
    const B: usize = 32;
    let n = (2 * rx + 1) * (2 * ry + 1) - 1;
    let w = row.len();
    let wh = 2 * ry + 1;
    assert!(pad.len() >= (y + wh) * pw + B && n <= 64);
    let load = |at: usize| {
        // SAFETY: at + 32 <= pad.len(): at <= (y + 2 ry) * pw + x0 + 2 rx with x0 < w
        // (asserted above).
        unsafe { _mm256_loadu_si256(pad.as_ptr().add(at).cast()) }
    };
    // Offsets of the neighbours from the window's top-left pixel, in bit order (neighbour k
    // lands in bit n - 1 - k), and how many fill the top byte plane.
    let mut offs = [0usize; 64];
    let mut k = 0;
    for wy in 0..wh {
        for wx in 0..=2 * rx {
            if !(wy == ry && wx == rx) {
                offs[k] = wy * pw + wx;
                k += 1;
            }
        }
    }
    let offs = &offs[..n];
    let planes_used = n.div_ceil(8);
    let top = n - 8 * (planes_used - 1);
    let mut x0 = 0;
    while x0 < w {
        let c = load((y + ry) * pw + rx + x0);
        let base = y * pw + x0;
        let mut planes = [_mm256_setzero_si256(); 8];
        let mut k = 0;
        for b in (0..planes_used).rev() {
            // All ones where the neighbour is darker: acc = acc << 1 | bit, per byte.
            let count = if b + 1 == planes_used { top } else { 8 };
            let mut acc = _mm256_setzero_si256();
            for &off in &offs[k..k + count] {
                let darker = _mm256_cmpgt_epi8(c, load(base + off));
                acc = _mm256_sub_epi8(_mm256_add_epi8(acc, acc), darker);
            }
            k += count;
            planes[b] = acc;
        }
        let [p0, p1, p2, p3, p4, p5, p6, p7] = planes;
        // Bytes 2i and 2i + 1 of 16 pixels per 128-bit lane (pixels 0-7 | 16-23, then 8-15 |
        // 24-31), then bytes 0-3 and 4-7 of 4 pixels, then whole u64 of 2 pixels.
        let (t0, t1) = (_mm256_unpacklo_epi8(p0, p1), _mm256_unpackhi_epi8(p0, p1));
        let (t2, t3) = (_mm256_unpacklo_epi8(p2, p3), _mm256_unpackhi_epi8(p2, p3));
        let (t4, t5) = (_mm256_unpacklo_epi8(p4, p5), _mm256_unpackhi_epi8(p4, p5));
        let (t6, t7) = (_mm256_unpacklo_epi8(p6, p7), _mm256_unpackhi_epi8(p6, p7));
        let (q0, q1) = (_mm256_unpacklo_epi16(t0, t2), _mm256_unpackhi_epi16(t0, t2));
        let (q2, q3) = (_mm256_unpacklo_epi16(t1, t3), _mm256_unpackhi_epi16(t1, t3));
        let (q4, q5) = (_mm256_unpacklo_epi16(t4, t6), _mm256_unpackhi_epi16(t4, t6));
        let (q6, q7) = (_mm256_unpacklo_epi16(t5, t7), _mm256_unpackhi_epi16(t5, t7));
        // r[i]: pixels 2i, 2i + 1 | 16 + 2i, 17 + 2i.
        let r = [
            _mm256_unpacklo_epi32(q0, q4),
            _mm256_unpackhi_epi32(q0, q4),
            _mm256_unpacklo_epi32(q1, q5),
            _mm256_unpackhi_epi32(q1, q5),
            _mm256_unpacklo_epi32(q2, q6),
            _mm256_unpackhi_epi32(q2, q6),
            _mm256_unpacklo_epi32(q3, q7),
            _mm256_unpackhi_epi32(q3, q7),
        ];
        let mut codes = [0u64; B];
        for i in 0..4 {
            let (a, b) = (r[2 * i], r[2 * i + 1]);
            // SAFETY: codes holds 32 u64; 4 i + 4 <= 16 and 16 + 4 i + 4 <= 32.
            unsafe {
                let dst = codes.as_mut_ptr();
                _mm256_storeu_si256(
                    dst.add(4 * i).cast(),
                    _mm256_permute2x128_si256::<0x20>(a, b),
                );
                _mm256_storeu_si256(
                    dst.add(16 + 4 * i).cast(),
                    _mm256_permute2x128_si256::<0x31>(a, b),
                );
            }
        }
        let bw = B.min(w - x0);
        row[x0..x0 + bw].copy_from_slice(&codes[..bw]);
        x0 += bw;
    }
}

/// One census row, 64 pixels at a time in two u32 halves (the comparisons that land in bits 32
/// and above first, then the low 32), so the compare-shift-or loops run 8 lanes wide.
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
