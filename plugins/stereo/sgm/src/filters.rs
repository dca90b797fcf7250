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

/// 3x3 median over the valid neighbours of each valid pixel.
pub fn median3(d: &[f32], w: usize, h: usize) -> Vec<f32> {
    (0..w * h)
        .into_par_iter()
        .map(|i| {
            if !d[i].is_finite() {
                return f32::NAN;
            }
            let (y, x) = ((i / w) as isize, (i % w) as isize);
            let mut v = [0.0f32; 9];
            let mut n = 0;
            for dy in -1..=1 {
                for dx in -1..=1 {
                    let (xx, yy) = (x + dx, y + dy);
                    if xx >= 0 && yy >= 0 && (xx as usize) < w && (yy as usize) < h {
                        let q = d[yy as usize * w + xx as usize];
                        if q.is_finite() {
                            v[n] = q;
                            n += 1;
                        }
                    }
                }
            }
            let v = &mut v[..n];
            v.sort_by(f32::total_cmp);
            v[n / 2]
        })
        .collect()
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
