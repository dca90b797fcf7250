//! The census transform of SGM: 64-pixel blocks in u32 halves on a 255-padded image, AVX2 chosen
//! at run time.

use rayon::prelude::*;

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
    if crate::simd::avx2() {
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
