//! Support points (ELAS step 2): robust sparse matches on a regular grid.
//!
//! A candidate on the grid is matched over the whole disparity range with the descriptors at its
//! four diagonal neighbours (+-2 px); it is kept when the best cost beats the second best by the
//! ratio `support_threshold`, its own patch has at least `support_texture`, and matching back
//! from the right image agrees within `lr_threshold`. Points with too few agreeing neighbours
//! are then removed, and so are redundant points inside straight runs of equal disparity.

use crate::descriptor::{sad, texture, Desc};
use crate::ElasParams;

/// A support point: left-image position and integer disparity.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct SupportPoint {
    /// Column in the left image, px (may lie outside the image for the added corners).
    pub u: i32,
    /// Row, px.
    pub v: i32,
    /// Disparity, px.
    pub d: i32,
}

/// Offset of the four diagonal descriptors around a support candidate.
const STEP: usize = 2;
/// libelas's descriptor window half-size used for the range limits.
const WINDOW: usize = 3;

/// Disparity of pixel (u, v) of the reference image `a` searched in `b`, or `None`. `right`
/// searches from the right image into the left (u + d) instead of u - d.
#[allow(clippy::too_many_arguments)]
pub fn match_support(
    u: usize,
    v: usize,
    a: &[Desc],
    b: &[Desc],
    w: usize,
    h: usize,
    right: bool,
    p: &ElasParams,
) -> Option<i32> {
    let m = WINDOW + STEP;
    if u < m || v < m || u + m + 1 > w || v + m + 1 > h {
        return None;
    }
    if texture(&a[v * w + u]) < p.support_texture {
        return None;
    }
    let (top, bot) = ((v - STEP) * w, (v + STEP) * w);
    let r = [
        &a[top + u - STEP],
        &a[top + u + STEP],
        &a[bot + u - STEP],
        &a[bot + u + STEP],
    ];
    let d_lo = p.disp_min as usize;
    let room = if right { w - u - m - 1 } else { u - m };
    let d_hi = (p.disp_max as usize).min(room);
    if d_hi < d_lo + 10 {
        return None;
    }
    let (mut e1, mut d1, mut e2) = (u32::MAX, usize::MAX, u32::MAX);
    for d in d_lo..=d_hi {
        let uw = if right { u + d } else { u - d };
        // The costs only add up: once the top pair reaches the second best, this disparity can
        // be neither best nor second (the result is exactly that of the full sum).
        let top_pair = sad(r[0], &b[top + uw - STEP]) + sad(r[1], &b[top + uw + STEP]);
        if top_pair >= e2 {
            continue;
        }
        let e = top_pair + sad(r[2], &b[bot + uw - STEP]) + sad(r[3], &b[bot + uw + STEP]);
        if e < e1 {
            e2 = e1;
            e1 = e;
            d1 = d;
        } else if e < e2 {
            e2 = e;
        }
    }
    (e2 != u32::MAX && (e1 as f32) < p.support_threshold * e2 as f32).then_some(d1 as i32)
}

/// The grid of candidates: `d[v_can * cw + u_can]`, -1 where there is no support point; the
/// candidate (u_can, v_can) lies at (u_can, v_can) x `candidate_stepsize`.
pub struct CandidateGrid {
    /// Columns of the grid.
    pub cw: usize,
    /// Rows of the grid.
    pub ch: usize,
    /// Disparity per candidate, -1 invalid.
    pub d: Vec<i32>,
}

/// Matches every grid candidate (left to right and back), in parallel over rows.
pub fn match_candidates(
    l: &[Desc],
    r: &[Desc],
    w: usize,
    h: usize,
    p: &ElasParams,
) -> CandidateGrid {
    use rayon::prelude::*;
    let step = p.candidate_stepsize as usize;
    let (cw, ch) = (w.div_ceil(step), h.div_ceil(step));
    let mut d = vec![-1i32; cw * ch];
    d.par_chunks_mut(cw).enumerate().for_each(|(vc, row)| {
        if vc == 0 {
            return;
        }
        let v = vc * step;
        for (uc, out) in row.iter_mut().enumerate().skip(1) {
            let u = uc * step;
            if let Some(dl) = match_support(u, v, l, r, w, h, false, p) {
                let ur = u - dl as usize;
                if let Some(dr) = match_support(ur, v, r, l, w, h, true, p) {
                    if (dl - dr).unsigned_abs() <= p.lr_threshold {
                        *out = dl;
                    }
                }
            }
        }
    });
    CandidateGrid { cw, ch, d }
}

/// Removes support points with fewer than `incon_min_support` points (themselves included)
/// within `incon_threshold` disparity in the (2 `incon_window_size` + 1)^2 candidate window.
/// Runs in place in raster order, as libelas does.
pub fn remove_inconsistent(g: &mut CandidateGrid, p: &ElasParams) {
    let win = p.incon_window_size as isize;
    let (cw, ch) = (g.cw as isize, g.ch as isize);
    for vc in 0..ch {
        for uc in 0..cw {
            let dc = g.d[(vc * cw + uc) as usize];
            if dc < 0 {
                continue;
            }
            let mut support = 0;
            for v2 in (vc - win).max(0)..=(vc + win).min(ch - 1) {
                for u2 in (uc - win).max(0)..=(uc + win).min(cw - 1) {
                    let d2 = g.d[(v2 * cw + u2) as usize];
                    if d2 >= 0 && (dc - d2).unsigned_abs() <= p.incon_threshold {
                        support += 1;
                    }
                }
            }
            if support < p.incon_min_support {
                g.d[(vc * cw + uc) as usize] = -1;
            }
        }
    }
}

/// Removes points that have a support point within `threshold` disparity on both sides
/// (within `max_dist` candidates) along rows (`vertical == false`) or columns: they add only
/// redundant triangles. In place, raster order.
pub fn remove_redundant(g: &mut CandidateGrid, max_dist: usize, threshold: u32, vertical: bool) {
    let (cw, ch) = (g.cw as isize, g.ch as isize);
    let dirs: [(isize, isize); 2] = if vertical {
        [(0, -1), (0, 1)]
    } else {
        [(-1, 0), (1, 0)]
    };
    for vc in 0..ch {
        for uc in 0..cw {
            let dc = g.d[(vc * cw + uc) as usize];
            if dc < 0 {
                continue;
            }
            let redundant = dirs.iter().all(|&(du, dv)| {
                let (mut u2, mut v2) = (uc, vc);
                for _ in 0..max_dist {
                    u2 += du;
                    v2 += dv;
                    if u2 < 0 || v2 < 0 || u2 >= cw || v2 >= ch {
                        return false;
                    }
                    let d2 = g.d[(v2 * cw + u2) as usize];
                    if d2 >= 0 && (dc - d2).unsigned_abs() <= threshold {
                        return true;
                    }
                }
                false
            });
            if redundant {
                g.d[(vc * cw + uc) as usize] = -1;
            }
        }
    }
}

/// The support points of a pair: candidate matching, the two removals, and (with `add_corners`)
/// the four image corners at the disparity of their nearest support point, plus the two right
/// corners shifted so that the right image's triangulation reaches its border.
pub fn support_points(
    l: &[Desc],
    r: &[Desc],
    w: usize,
    h: usize,
    p: &ElasParams,
) -> Vec<SupportPoint> {
    let mut g = match_candidates(l, r, w, h, p);
    remove_inconsistent(&mut g, p);
    remove_redundant(&mut g, 5, 1, true);
    remove_redundant(&mut g, 5, 1, false);
    let step = p.candidate_stepsize as i32;
    let mut pts = Vec::new();
    for vc in 0..g.ch {
        for uc in 0..g.cw {
            let d = g.d[vc * g.cw + uc];
            if d >= 0 {
                pts.push(SupportPoint {
                    u: uc as i32 * step,
                    v: vc as i32 * step,
                    d,
                });
            }
        }
    }
    if p.add_corners && !pts.is_empty() {
        add_corners(&mut pts, w as i32, h as i32);
    }
    pts
}

/// Adds the image corners with the disparity of the nearest support point (libelas's
/// `addCornerSupportPoints`).
pub fn add_corners(pts: &mut Vec<SupportPoint>, w: i32, h: i32) {
    let mut corners = [(0, 0), (0, h - 1), (w - 1, 0), (w - 1, h - 1)].map(|(u, v)| {
        let nearest = pts
            .iter()
            .min_by_key(|s| {
                let (du, dv) = ((s.u - u) as i64, (s.v - v) as i64);
                du * du + dv * dv
            })
            .map_or(0, |s| s.d);
        SupportPoint { u, v, d: nearest }
    });
    let extra = [corners[2], corners[3]].map(|c| SupportPoint { u: c.u + c.d, ..c });
    for c in corners.iter_mut() {
        pts.push(*c);
    }
    pts.extend(extra);
}

#[cfg(test)]
mod tests {
    #![allow(clippy::unwrap_used)]
    use super::*;

    fn grid(cw: usize, ch: usize, d: Vec<i32>) -> CandidateGrid {
        CandidateGrid { cw, ch, d }
    }

    #[test]
    fn inconsistent_point_is_removed_and_its_neighbours_stay() {
        let p = ElasParams::robotics();
        // 5x5 plane at d = 20 with one outlier at 40 in the middle.
        let mut d = vec![20; 25];
        d[12] = 40;
        let mut g = grid(5, 5, d);
        remove_inconsistent(&mut g, &p);
        assert_eq!(g.d[12], -1);
        assert_eq!(g.d.iter().filter(|&&x| x == 20).count(), 24);
        // Four points alone are too few (min support 5).
        let mut g = grid(4, 1, vec![7; 4]);
        remove_inconsistent(&mut g, &p);
        assert!(g.d.iter().all(|&x| x == -1));
    }

    #[test]
    fn redundant_points_inside_straight_runs_go() {
        // A row of equal disparities: a point with an agreeing point on both sides (within 5
        // candidates) goes; raster order removes the interior one by one, each still seeing
        // the first. The last 10 has only the 30 to its right, so it stays (a run's end).
        let mut g = grid(6, 1, vec![10, 10, 10, 10, 10, 30]);
        remove_redundant(&mut g, 5, 1, false);
        assert_eq!(g.d, [10, -1, -1, -1, 10, 30]);
        // Vertical pass on the same row does nothing (no vertical neighbours).
        let mut g = grid(6, 1, vec![10, 10, 10, 10, 10, 30]);
        remove_redundant(&mut g, 5, 1, true);
        assert_eq!(g.d, [10, 10, 10, 10, 10, 30]);
    }

    #[test]
    fn corners_take_the_nearest_disparity() {
        let mut pts = vec![
            SupportPoint { u: 10, v: 10, d: 5 },
            SupportPoint { u: 90, v: 50, d: 9 },
        ];
        add_corners(&mut pts, 100, 60);
        assert_eq!(pts.len(), 8);
        assert_eq!(pts[2], SupportPoint { u: 0, v: 0, d: 5 });
        assert_eq!(pts[5], SupportPoint { u: 99, v: 59, d: 9 });
        // The right image's corner: u - d = 99.
        assert_eq!(
            pts[7],
            SupportPoint {
                u: 108,
                v: 59,
                d: 9
            }
        );
    }
}
