//! The filters after the selection: left-right check, 3x3 median, speckle removal (also used by
//! `depth.elas`).

use crate::sgm::SgmParams;
use rayon::prelude::*;

/// Left-right check, median and speckle removal on a full disparity image.
pub fn finish(disp: &mut Vec<f32>, right: &[f32], w: usize, h: usize, p: &SgmParams) {
    finish_with(disp, right, w, h, p, &mut SpeckleScratch::default());
}

pub(crate) fn finish_with(
    disp: &mut Vec<f32>,
    right: &[f32],
    w: usize,
    h: usize,
    p: &SgmParams,
    speckle: &mut SpeckleScratch,
) {
    if p.lr_check {
        for (i, d) in disp.iter_mut().enumerate() {
            if !d.is_finite() {
                continue;
            }
            let (y, x) = (i / w, i % w);
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
    if p.median {
        *disp = median3(disp, w, h);
    }
    if p.speckle_window > 0 {
        remove_speckles_with(
            disp,
            w,
            h,
            p.speckle_window as usize,
            p.speckle_range,
            speckle,
        );
    }
}

/// 3x3 median over the valid neighbours of each valid pixel (with an even count, the upper of
/// the two middle values). Where all nine are valid (almost everywhere) it is Paeth's
/// 19-exchange median-of-9 network; elsewhere a sort of the valid ones.
pub fn median3(d: &[f32], w: usize, h: usize) -> Vec<f32> {
    let mut out = vec![f32::NAN; w * h];
    if w == 0 {
        return out;
    }
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        if y == 0 || y + 1 >= h || w < 3 {
            for (x, o) in row.iter_mut().enumerate() {
                *o = median_at(d, w, h, x, y);
            }
            return;
        }
        let (a, b, c) = (
            &d[(y - 1) * w..y * w],
            &d[y * w..(y + 1) * w],
            &d[(y + 1) * w..(y + 2) * w],
        );
        row[0] = median_at(d, w, h, 0, y);
        row[w - 1] = median_at(d, w, h, w - 1, y);
        for x in 1..w - 1 {
            if !b[x].is_finite() {
                continue;
            }
            let v = [
                a[x - 1],
                a[x],
                a[x + 1],
                b[x - 1],
                b[x],
                b[x + 1],
                c[x - 1],
                c[x],
                c[x + 1],
            ];
            row[x] = if v.iter().all(|q| q.is_finite()) {
                median9(v)
            } else {
                median_at(d, w, h, x, y)
            };
        }
    });
    out
}

/// The median of nine finite values by Paeth's exchange network (19 compare-exchanges).
#[inline(always)]
fn median9(mut p: [f32; 9]) -> f32 {
    #[inline(always)]
    fn sort2(p: &mut [f32; 9], i: usize, j: usize) {
        let (a, b) = (p[i], p[j]);
        p[i] = if a > b { b } else { a };
        p[j] = if a > b { a } else { b };
    }
    for (i, j) in [
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 1),
        (3, 4),
        (6, 7),
        (1, 2),
        (4, 5),
        (7, 8),
        (0, 3),
        (5, 8),
        (4, 7),
        (3, 6),
        (1, 4),
        (2, 5),
        (4, 7),
        (4, 2),
        (6, 4),
        (4, 2),
    ] {
        sort2(&mut p, i, j);
    }
    p[4]
}

/// The median of the valid pixels of the 3x3 window at (x, y) (NaN when the centre is invalid).
fn median_at(d: &[f32], w: usize, h: usize, x: usize, y: usize) -> f32 {
    if !d[y * w + x].is_finite() {
        return f32::NAN;
    }
    let mut v = [0.0f32; 9];
    let mut n = 0;
    for yy in y.saturating_sub(1)..(y + 2).min(h) {
        for xx in x.saturating_sub(1)..(x + 2).min(w) {
            let q = d[yy * w + xx];
            if q.is_finite() {
                v[n] = q;
                n += 1;
            }
        }
    }
    let v = &mut v[..n];
    v.sort_by(f32::total_cmp);
    v[n / 2]
}

/// Buffers of [`remove_speckles_with`], reused across frames.
#[derive(Default)]
pub struct SpeckleScratch {
    label: Vec<u32>,
    stack: Vec<usize>,
    region: Vec<usize>,
}

/// Invalidates 4-connected regions (neighbours within `range`) smaller than `window` pixels.
pub fn remove_speckles(d: &mut [f32], w: usize, h: usize, window: usize, range: f32) {
    remove_speckles_with(d, w, h, window, range, &mut SpeckleScratch::default());
}

/// [`remove_speckles`] with buffers kept by the caller.
pub fn remove_speckles_with(
    d: &mut [f32],
    w: usize,
    h: usize,
    window: usize,
    range: f32,
    s: &mut SpeckleScratch,
) {
    let SpeckleScratch {
        label,
        stack,
        region,
    } = s;
    label.clear();
    label.resize(w * h, 0);
    stack.clear();
    let mut next = 1u32;
    for start in 0..w * h {
        if label[start] != 0 || !d[start].is_finite() {
            continue;
        }
        region.clear();
        stack.push(start);
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
            for &i in region.iter() {
                d[i] = f32::NAN;
            }
        }
        next += 1;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition: sort the valid values of the window, take the middle (upper) one.
    fn median_reference(d: &[f32], w: usize, h: usize) -> Vec<f32> {
        (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as isize, (i / w) as isize);
                if !d[i].is_finite() {
                    return f32::NAN;
                }
                let mut v = Vec::new();
                for dy in -1..=1 {
                    for dx in -1..=1 {
                        let (xx, yy) = (x + dx, y + dy);
                        if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                            let q = d[yy as usize * w + xx as usize];
                            if q.is_finite() {
                                v.push(q);
                            }
                        }
                    }
                }
                v.sort_by(f32::total_cmp);
                v[v.len() / 2]
            })
            .collect()
    }

    #[test]
    fn the_median_network_and_the_holes_match_the_sorted_definition() {
        let mut seed = 12345u64;
        let mut next = || {
            seed = seed
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            (seed >> 33) as u32
        };
        for (w, h) in [(1, 1), (2, 5), (3, 3), (17, 9), (64, 31)] {
            // Few distinct values (ties), a tenth invalid (NaN and infinities).
            let d: Vec<f32> = (0..w * h)
                .map(|_| match next() % 20 {
                    0 => f32::NAN,
                    1 => f32::INFINITY,
                    k => (k % 7) as f32 * 0.5 + (next() % 3) as f32 * 0.25,
                })
                .collect();
            let got = median3(&d, w, h);
            let want = median_reference(&d, w, h);
            for (i, (g, r)) in got.iter().zip(&want).enumerate() {
                assert!(
                    g.to_bits() == r.to_bits(),
                    "{w}x{h} pixel {i}: {g} instead of {r}"
                );
            }
        }
    }
}
