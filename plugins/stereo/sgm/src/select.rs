//! Winner-takes-all of one completed row of SGM sums: the left disparity (uniqueness margin,
//! parabola) and the right one for the left-right check.

use crate::aggregate::{lanes, lanes_mut, Ctx, FAR, LANES};

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
pub(crate) struct RightScratch {
    /// Best sum and its disparity per right pixel, stored reversed (index pad + w - 1 - xr) so
    /// that one left pixel's 16 disparities update 16 contiguous entries.
    best: Vec<i16>,
    arg: Vec<i16>,
}

/// Winner-takes-all for one completed row of sums: the left disparity with the uniqueness
/// margin and the parabola, and the right disparity argmin_d S(y, xr + d + dmin, d).
pub(crate) fn select_row(
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
