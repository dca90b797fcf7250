//! The ELAS pixel descriptor: 16 bytes sampled from the 3x3 Sobel responses around the pixel.
//!
//! Each response is scaled by 1/4, clamped to [-128, 127] and stored with an offset of 128, so a
//! flat patch has every byte at 128. The 12 horizontal-gradient samples form a diamond of radius 2
//! (the centre counted twice); the 4 vertical-gradient samples are the centre's 4-neighbours, as in
//! libelas. Matching cost = sum of absolute differences of two descriptors ([`sad`]).

/// One descriptor.
pub type Desc = [u8; 16];

/// (dx, dy) of the 12 horizontal-gradient samples.
const DU: [(isize, isize); 12] = [
    (0, -2),
    (-2, -1),
    (0, -1),
    (2, -1),
    (-1, 0),
    (0, 0),
    (0, 0),
    (1, 0),
    (-2, 1),
    (0, 1),
    (2, 1),
    (0, 2),
];
/// (dx, dy) of the 4 vertical-gradient samples.
const DV: [(isize, isize); 4] = [(0, -1), (-1, 0), (1, 0), (0, 1)];

/// Sobel responses (du, dv) of a gray image, each `clamp(r / 4, -128, 127) + 128`; the border
/// replicates the edge pixels.
pub fn sobel(img: &[u8], w: usize, h: usize, du: &mut Vec<u8>, dv: &mut Vec<u8>) {
    du.clear();
    du.resize(w * h, 128);
    dv.clear();
    dv.resize(w * h, 128);
    if w == 0 || h == 0 {
        return;
    }
    let enc = |r: i16| ((r >> 2).clamp(-128, 127) + 128) as u8;
    // Per row: the vertical [1 2 1] smoothing and the vertical difference, then the horizontal
    // difference and smoothing of those (two passes that vectorise).
    let (mut smooth, mut diff) = (vec![0i16; w + 2], vec![0i16; w + 2]);
    for y in 0..h {
        let row = |yy: isize| {
            let yy = yy.clamp(0, h as isize - 1) as usize;
            &img[yy * w..(yy + 1) * w]
        };
        let (r0, r1, r2) = (row(y as isize - 1), row(y as isize), row(y as isize + 1));
        for (((s, d), (&a, &b)), &c) in smooth[1..=w]
            .iter_mut()
            .zip(diff[1..=w].iter_mut())
            .zip(r0.iter().zip(r1))
            .zip(r2)
        {
            *s = a as i16 + 2 * b as i16 + c as i16;
            *d = c as i16 - a as i16;
        }
        // Replicated columns at both ends.
        smooth[0] = smooth[1];
        smooth[w + 1] = smooth[w];
        diff[0] = diff[1];
        diff[w + 1] = diff[w];
        let (ou, ov) = (&mut du[y * w..(y + 1) * w], &mut dv[y * w..(y + 1) * w]);
        for (x, (u, v)) in ou.iter_mut().zip(ov.iter_mut()).enumerate() {
            *u = enc(smooth[x + 2] - smooth[x]);
            *v = enc(diff[x] + 2 * diff[x + 1] + diff[x + 2]);
        }
    }
}

/// Descriptors of every pixel of a gray image (row-major); samples beyond the border replicate
/// the edge. `sobel_maps` holds the two Sobel maps (reused across calls).
pub fn descriptors(
    img: &[u8],
    w: usize,
    h: usize,
    out: &mut Vec<Desc>,
    sobel_maps: &mut (Vec<u8>, Vec<u8>),
) {
    let (du, dv) = sobel_maps;
    sobel(img, w, h, du, dv);
    let (du, dv) = (&*du, &*dv);
    // Every pixel is written below: keep the old contents instead of clearing.
    out.resize(w * h, [128; 16]);
    for (y, row) in out.chunks_exact_mut(w).enumerate() {
        if y >= 2 && y + 2 < h {
            // Interior rows: five row slices, direct offsets.
            fn r(m: &[u8], w: usize, yy: usize) -> &[u8] {
                &m[yy * w..(yy + 1) * w]
            }
            let (u0, u1, u2) = (r(du, w, y - 2), r(du, w, y - 1), r(du, w, y));
            let (u3, u4) = (r(du, w, y + 1), r(du, w, y + 2));
            let (v1, v2, v3) = (r(dv, w, y - 1), r(dv, w, y), r(dv, w, y + 1));
            for x in 2..w.saturating_sub(2) {
                let (a, b, c) = (&u1[x - 2..x + 3], &u2[x - 1..x + 2], &u3[x - 2..x + 3]);
                let e = &v2[x - 1..x + 2];
                row[x] = [
                    u0[x], a[0], a[2], a[4], b[0], b[1], b[1], b[2], c[0], c[2], c[4], u4[x],
                    v1[x], e[0], e[2], v3[x],
                ];
            }
        }
        for (x, d) in row.iter_mut().enumerate() {
            if y >= 2 && y + 2 < h && x >= 2 && x + 2 < w {
                continue;
            }
            let at = |m: &[u8], (dx, dy): (isize, isize)| {
                let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
                m[yy * w + xx]
            };
            for (k, &o) in DU.iter().enumerate() {
                d[k] = at(du, o);
            }
            for (k, &o) in DV.iter().enumerate() {
                d[12 + k] = at(dv, o);
            }
        }
    }
}

/// Sum of absolute differences of two descriptors (SSE2 `psadbw` on x86-64).
#[inline(always)]
pub fn sad(a: &Desc, b: &Desc) -> u32 {
    #[cfg(target_arch = "x86_64")]
    {
        use core::arch::x86_64::{
            __m128i, _mm_cvtsi128_si32, _mm_extract_epi16, _mm_loadu_si128, _mm_sad_epu8,
        };
        // SAFETY: SSE2 is part of the x86-64 baseline; both pointers address 16 readable bytes
        // and `loadu` has no alignment requirement.
        unsafe {
            let x = _mm_loadu_si128(a.as_ptr() as *const __m128i);
            let y = _mm_loadu_si128(b.as_ptr() as *const __m128i);
            let s = _mm_sad_epu8(x, y);
            (_mm_cvtsi128_si32(s) + _mm_extract_epi16::<4>(s)) as u32
        }
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        sad_portable(a, b)
    }
}

/// [`sad`] without SIMD (the reference the SIMD path is tested against).
pub fn sad_portable(a: &Desc, b: &Desc) -> u32 {
    a.iter()
        .zip(b)
        .map(|(&x, &y)| (x as i32 - y as i32).unsigned_abs())
        .sum()
}

/// Texture of a descriptor: sum of |byte - 128| (0 on a flat patch).
#[inline(always)]
pub fn texture(a: &Desc) -> u32 {
    sad(a, &[128; 16])
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    #[test]
    fn sad_matches_the_portable_sum() {
        let mut s = 12345u32;
        let mut next = || {
            s = s.wrapping_mul(1103515245).wrapping_add(12345);
            (s >> 16) as u8
        };
        for _ in 0..200 {
            let a: Desc = std::array::from_fn(|_| next());
            let b: Desc = std::array::from_fn(|_| next());
            assert_eq!(sad(&a, &b), sad_portable(&a, &b));
        }
        assert_eq!(sad(&[0; 16], &[255; 16]), 16 * 255);
    }

    #[test]
    fn fast_interior_rows_match_the_sample_layout() {
        let (w, h) = (23, 11);
        let mut s = 99u32;
        let img: Vec<u8> = (0..w * h)
            .map(|_| {
                s = s.wrapping_mul(1103515245).wrapping_add(12345);
                (s >> 16) as u8
            })
            .collect();
        let (mut du, mut dv) = (Vec::new(), Vec::new());
        sobel(&img, w, h, &mut du, &mut dv);
        // Sobel against its definition, border replicated.
        let px = |x: isize, y: isize| {
            img[y.clamp(0, h as isize - 1) as usize * w + x.clamp(0, w as isize - 1) as usize]
                as i32
        };
        let enc = |r: i32| ((r >> 2).clamp(-128, 127) + 128) as u8;
        for y in 0..h as isize {
            for x in 0..w as isize {
                let gx = (px(x + 1, y - 1) - px(x - 1, y - 1))
                    + 2 * (px(x + 1, y) - px(x - 1, y))
                    + (px(x + 1, y + 1) - px(x - 1, y + 1));
                let gy = (px(x - 1, y + 1) - px(x - 1, y - 1))
                    + 2 * (px(x, y + 1) - px(x, y - 1))
                    + (px(x + 1, y + 1) - px(x + 1, y - 1));
                let i = y as usize * w + x as usize;
                assert_eq!((du[i], dv[i]), (enc(gx), enc(gy)), "sobel at ({x}, {y})");
            }
        }
        let mut d = Vec::new();
        descriptors(&img, w, h, &mut d, &mut Default::default());
        for y in 0..h {
            for x in 0..w {
                let at = |m: &[u8], (dx, dy): (isize, isize)| {
                    let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                    let yy = (y as isize + dy).clamp(0, h as isize - 1) as usize;
                    m[yy * w + xx]
                };
                let want: Vec<u8> = DU
                    .iter()
                    .map(|&o| at(&du, o))
                    .chain(DV.iter().map(|&o| at(&dv, o)))
                    .collect();
                assert_eq!(&d[y * w + x][..], &want[..], "pixel ({x}, {y})");
            }
        }
    }

    #[test]
    fn flat_image_has_flat_descriptors_and_a_ramp_has_known_gradients() {
        let (w, h) = (9, 7);
        let flat = vec![77u8; w * h];
        let mut d = Vec::new();
        descriptors(&flat, w, h, &mut d, &mut Default::default());
        assert!(d.iter().all(|x| *x == [128; 16] && texture(x) == 0));
        // I = 3x: Sobel gx = 8 * 3 = 24, /4 = 6; gy = 0. Interior only (the border replicates).
        let ramp: Vec<u8> = (0..w * h).map(|i| (3 * (i % w)) as u8).collect();
        descriptors(&ramp, w, h, &mut d, &mut Default::default());
        let c = d[3 * w + 4];
        assert_eq!(&c[..12], &[134; 12]);
        assert_eq!(&c[12..], &[128; 4]);
        assert_eq!(texture(&c), 12 * 6);
    }
}
