//! The straightforward transcription of SGM (Hirschmueller 2008): one pass per path direction
//! over a full u8 cost volume and a u16 sum, per-pixel loops without SIMD. It is slow (about ten
//! times the fast path) and kept only as the oracle: [`crate::sgm::sgm`] and the WGSL kernel are
//! tested to give exactly its output.

use crate::sgm::{check_pair, median3, path_step, SgmParams};

/// Census transform, one pixel at a time (same bits as [`crate::sgm::census`]).
pub fn census_reference(img: &[u8], w: usize, h: usize, cw: usize, ch: usize) -> Vec<u64> {
    let (rx, ry) = ((cw / 2) as isize, (ch / 2) as isize);
    let mut out = vec![0u64; w * h];
    for y in 0..h {
        for x in 0..w {
            let c = img[y * w + x];
            let mut bits = 0u64;
            for dy in -ry..=ry {
                for dx in -rx..=rx {
                    if dx == 0 && dy == 0 {
                        continue;
                    }
                    let (xx, yy) = (x as isize + dx, y as isize + dy);
                    let v = if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        img[yy as usize * w + xx as usize]
                    } else {
                        c
                    };
                    bits = (bits << 1) | u64::from(v < c);
                }
            }
            out[y * w + x] = bits;
        }
    }
    out
}

/// Disparity of the left image (px, NaN invalid): the same contract as [`crate::sgm::sgm`].
pub fn sgm_reference(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    valid: Option<&[u8]>,
    p: &SgmParams,
) -> Result<Vec<f32>, String> {
    check_pair(left, right, w, h, valid, p)?;
    let nd = p.max_disparity as usize;
    let dmin = p.min_disparity as isize;
    let (cw, ch) = (p.census_width as usize, p.census_height as usize);
    let cl = census_reference(left, w, h, cw, ch);
    let cr = census_reference(right, w, h, cw, ch);
    let unknown = p.unknown_cost();
    let mut cost = vec![unknown; w * h * nd];
    for y in 0..h {
        for x in 0..w {
            for d in 0..nd {
                let xr = x as isize - (d as isize + dmin);
                if xr >= 0 && (xr as usize) < w {
                    cost[(y * w + x) * nd + d] =
                        (cl[y * w + x] ^ cr[y * w + xr as usize]).count_ones() as u8;
                }
            }
        }
    }
    let sum = aggregate(left, w, h, nd, p, &cost);
    let (mut disp, mut right_disp) = (vec![f32::NAN; w * h], vec![f32::NAN; w * h]);
    for i in 0..w * h {
        if valid.is_some_and(|m| m[i] == 0) {
            continue;
        }
        disp[i] = winner(&sum[i * nd..(i + 1) * nd], p);
    }
    let dminf = p.min_disparity as f32;
    for (j, out) in right_disp.iter_mut().enumerate() {
        let (y, xr) = (j / w, j % w);
        let (mut best, mut bd) = (u16::MAX, None);
        for d in 0..nd {
            let x = xr as isize + d as isize + dmin;
            if x < 0 || x as usize >= w {
                continue;
            }
            let v = sum[(y * w + x as usize) * nd + d];
            if v < best {
                best = v;
                bd = Some(d);
            }
        }
        *out = bd.map_or(f32::NAN, |d| d as f32 + dminf);
    }
    finish_reference(&mut disp, &right_disp, w, h, p);
    Ok(disp)
}

/// Winner-takes-all over one pixel's summed costs, with the uniqueness margin and the parabola.
fn winner(s: &[u16], p: &SgmParams) -> f32 {
    let nd = s.len();
    let (mut best, mut bd) = (u16::MAX, 0usize);
    for (d, &v) in s.iter().enumerate() {
        if v < best {
            best = v;
            bd = d;
        }
    }
    let second = s
        .iter()
        .enumerate()
        .filter(|(d, _)| d.abs_diff(bd) > 1)
        .map(|(_, &v)| v)
        .min()
        .unwrap_or(u16::MAX);
    if (best as u64) * (100 + p.uniqueness_pct as u64) > (second as u64) * 100 {
        return f32::NAN;
    }
    let mut d = bd as f32;
    if p.subpixel && bd > 0 && bd + 1 < nd {
        let (a, b, c) = (s[bd - 1] as f32, s[bd] as f32, s[bd + 1] as f32);
        let den = a - 2.0 * b + c;
        if den > 0.0 {
            d += 0.5 * (a - c) / den;
        }
    }
    d + p.min_disparity as f32
}

/// Directions as (dx, dy); the GPU kernels run them in this order too.
pub const DIRS: [(isize, isize); 8] = [
    (1, 0),
    (1, 1),
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
];

/// The four directions of `paths = 4`.
pub const DIRS4: [(isize, isize); 4] = [(1, 0), (0, 1), (-1, 0), (0, -1)];

/// One traversal per direction; each keeps L of the previous row (or pixel, for rows).
fn aggregate(img: &[u8], w: usize, h: usize, nd: usize, p: &SgmParams, cost: &[u8]) -> Vec<u16> {
    let mut sum = vec![0u16; w * h * nd];
    let dirs: &[(isize, isize)] = if p.paths == 8 { &DIRS } else { &DIRS4 };
    let mut prev_row = vec![0u16; w * nd];
    let mut cur_row = vec![0u16; w * nd];
    let mut tmp = vec![0u16; nd];
    for &(dx, dy) in dirs {
        // Traverse so that p - r was visited before p.
        let rows_down = dy > 0 || (dy == 0 && dx > 0);
        let cols_right = dx > 0 || (dx == 0 && dy > 0);
        let mut first_row = true;
        for k in 0..h {
            let y = if rows_down { k } else { h - 1 - k };
            for j in 0..w {
                let x = if cols_right { j } else { w - 1 - j };
                let i = y * w + x;
                let c = &cost[i * nd..(i + 1) * nd];
                let (px, py) = (x as isize - dx, y as isize - dy);
                let inside = px >= 0 && py >= 0 && (px as usize) < w && (py as usize) < h;
                if !inside || (dy != 0 && first_row) {
                    for (o, &cv) in cur_row[x * nd..(x + 1) * nd].iter_mut().zip(c) {
                        *o = cv as u16;
                    }
                } else {
                    let prev: &[u16] = if dy == 0 {
                        tmp.copy_from_slice(&cur_row[px as usize * nd..(px as usize + 1) * nd]);
                        &tmp
                    } else {
                        &prev_row[px as usize * nd..(px as usize + 1) * nd]
                    };
                    let step = (img[i] as i32 - img[py as usize * w + px as usize] as i32)
                        .unsigned_abs() as u16;
                    let p2 = p.p2_at(step);
                    path_step(c, prev, p.p1, p2, &mut cur_row[x * nd..(x + 1) * nd]);
                }
                let out = &cur_row[x * nd..(x + 1) * nd];
                for (sv, &l) in sum[i * nd..(i + 1) * nd].iter_mut().zip(out) {
                    *sv = sv.saturating_add(l);
                }
            }
            std::mem::swap(&mut prev_row, &mut cur_row);
            first_row = false;
        }
    }
    sum
}

/// The filters after the selection, one pixel at a time: left-right check, the 3x3 median
/// (tested on its own against the sorted definition) and speckle removal by flood fill.
pub fn finish_reference(disp: &mut Vec<f32>, right: &[f32], w: usize, h: usize, p: &SgmParams) {
    if p.lr_check {
        for y in 0..h {
            for x in 0..w {
                let d = &mut disp[y * w + x];
                if !d.is_finite() {
                    continue;
                }
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
    }
    if p.median {
        *disp = median3(disp, w, h);
    }
    if p.speckle_window > 0 {
        remove_speckles_reference(disp, w, h, p.speckle_window as usize, p.speckle_range);
    }
}

/// Speckle removal by flood fill: each 4-connected region of valid pixels whose neighbours
/// differ by at most `range` is invalidated when it has fewer than `window` pixels.
pub fn remove_speckles_reference(d: &mut [f32], w: usize, h: usize, window: usize, range: f32) {
    let mut label = vec![0u32; w * h];
    let mut next = 1u32;
    for start in 0..w * h {
        if label[start] != 0 || !d[start].is_finite() {
            continue;
        }
        let mut region = Vec::new();
        let mut stack = vec![start];
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
            for &i in &region {
                d[i] = f32::NAN;
            }
        }
        next += 1;
    }
}
