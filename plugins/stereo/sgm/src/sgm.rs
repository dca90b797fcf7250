//! Semi-global matching (Hirschmueller, PAMI 2008) on rectified gray images, as a plain library:
//! census transform, Hamming matching cost, path-wise aggregation with P1/P2, winner-takes-all
//! with a uniqueness margin and a sub-pixel parabola, right disparities from the same aggregated
//! cost along the diagonals, left-right check, 3x3 median and speckle removal.
//!
//! Memory: the cost volume (u8) and the summed cost S (u16) are H x W x D, kept in a
//! [`Scratch`] the caller reuses across frames; paths keep only their previous row.

use rayon::prelude::*;

/// Parameters of SGM (and of the `depth.sgm` plugin: `misslam plugins depth.sgm` prints these docs).
#[derive(
    Clone, Copy, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(deny_unknown_fields, default)]
pub struct SgmParams {
    /// Number of disparities searched, starting at `min_disparity`.
    pub max_disparity: u32,
    /// Smallest disparity searched, px.
    pub min_disparity: i32,
    /// Census window width (odd).
    pub census_width: u32,
    /// Census window height (odd); width x height - 1 must not exceed 64.
    pub census_height: u32,
    /// Aggregation paths: 4 or 8.
    pub paths: u32,
    /// Penalty for a disparity change of one pixel between neighbours (census cost units, 0..63).
    pub p1: u16,
    /// Penalty for larger changes; must exceed `p1`.
    pub p2: u16,
    /// Divide P2 by the intensity step along each path (Hirschmueller's edge-aware P2), never below P1 + 1.
    pub p2_adaptive: bool,
    /// Uniqueness margin, %: the best aggregated cost must beat the second best (beyond +-1 px) by this much.
    pub uniqueness_pct: u32,
    /// Sub-pixel refinement by a parabola through the costs at d-1, d, d+1.
    pub subpixel: bool,
    /// Left-right consistency check (right disparities from the same aggregated cost).
    pub lr_check: bool,
    /// Largest left-right disagreement kept, px.
    pub lr_max_diff: f32,
    /// 3x3 median filter of the valid disparities.
    pub median: bool,
    /// Remove connected regions smaller than this many pixels (0: off).
    pub speckle_window: u32,
    /// Neighbours within this disparity difference belong to one region, px.
    pub speckle_range: f32,
}

impl Default for SgmParams {
    fn default() -> Self {
        SgmParams {
            max_disparity: 64,
            min_disparity: 0,
            census_width: 9,
            census_height: 7,
            paths: 8,
            p1: 10,
            p2: 120,
            p2_adaptive: false,
            uniqueness_pct: 5,
            subpixel: true,
            lr_check: true,
            lr_max_diff: 1.0,
            median: true,
            speckle_window: 100,
            speckle_range: 2.0,
        }
    }
}

impl SgmParams {
    /// Checks the parameters; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.max_disparity < 2 || self.max_disparity > 1024 {
            return Err(format!(
                "`max_disparity` must be in 2..=1024, got {}",
                self.max_disparity
            ));
        }
        if self.census_width.is_multiple_of(2)
            || self.census_height.is_multiple_of(2)
            || self.census_width < 3
            || self.census_height < 3
        {
            return Err("`census_width` and `census_height` must be odd and at least 3".into());
        }
        if self.census_width * self.census_height - 1 > 64 {
            return Err(format!(
                "a {}x{} census window has more than 64 comparisons",
                self.census_width, self.census_height
            ));
        }
        if self.paths != 4 && self.paths != 8 {
            return Err(format!("`paths` must be 4 or 8, got {}", self.paths));
        }
        if self.p2 <= self.p1 {
            return Err(format!("`p2` ({}) must exceed `p1` ({})", self.p2, self.p1));
        }
        let non_negative = |v: f32| v.is_finite() && v >= 0.0;
        if !non_negative(self.lr_max_diff) || !non_negative(self.speckle_range) {
            return Err("`lr_max_diff` and `speckle_range` must be >= 0".into());
        }
        Ok(())
    }
}

/// Buffers reused across frames.
#[derive(Default)]
pub struct Scratch {
    census_l: Vec<u64>,
    census_r: Vec<u64>,
    cost: Vec<u8>,
    sum: Vec<u16>,
    /// Path costs of the previous and the current row, and one pixel's copy.
    prev_row: Vec<u16>,
    cur_row: Vec<u16>,
    tmp: Vec<u16>,
    /// Right-image disparities for the left-right check.
    right: Vec<f32>,
}

/// Census transform: bit k is set when neighbour k of the window is darker than the centre.
/// Neighbours outside the image count as equal to the centre (bit 0).
pub fn census(img: &[u8], w: usize, h: usize, cw: usize, ch: usize, out: &mut Vec<u64>) {
    out.clear();
    out.resize(w * h, 0);
    let (rx, ry) = ((cw / 2) as isize, (ch / 2) as isize);
    out.par_chunks_mut(w).enumerate().for_each(|(y, row)| {
        for (x, dst) in row.iter_mut().enumerate() {
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
            *dst = bits;
        }
    });
}

/// One step of the path recurrence for all disparities:
/// `out[d] = cost[d] + min(prev[d], prev[d-1] + p1, prev[d+1] + p1, min(prev) + p2) - min(prev)`.
#[inline]
pub fn path_step(cost: &[u8], prev: &[u16], p1: u16, p2: u16, out: &mut [u16]) {
    let n = cost.len();
    if n == 0 {
        return;
    }
    let min_prev = prev.iter().copied().min().unwrap_or(0);
    let jump = min_prev.saturating_add(p2);
    let edge = |d: usize, other: u16| prev[d].min(jump).min(other.saturating_add(p1));
    if n == 1 {
        out[0] = cost[0] as u16 + (prev[0].min(jump) - min_prev);
        return;
    }
    out[0] = cost[0] as u16 + (edge(0, prev[1]) - min_prev);
    out[n - 1] = cost[n - 1] as u16 + (edge(n - 1, prev[n - 2]) - min_prev);
    // Interior without branches, so the loop vectorises (saturating u16 adds and mins).
    for ((o, &c), w) in out[1..n - 1]
        .iter_mut()
        .zip(&cost[1..n - 1])
        .zip(prev.windows(3))
    {
        let best = w[1]
            .min(jump)
            .min(w[0].saturating_add(p1))
            .min(w[2].saturating_add(p1));
        *o = c as u16 + (best - min_prev);
    }
}

/// Disparity of the left image (px, NaN invalid), from `left` and `right` gray images.
/// `valid` masks pixels that may not get a disparity (e.g. the black border).
pub fn sgm(
    left: &[u8],
    right: &[u8],
    w: usize,
    h: usize,
    valid: Option<&[u8]>,
    p: &SgmParams,
    s: &mut Scratch,
) -> Result<Vec<f32>, String> {
    p.validate()?;
    if left.len() != w * h || right.len() != w * h {
        return Err(format!("images must be {w}x{h} gray"));
    }
    let nd = p.max_disparity as usize;
    let dmin = p.min_disparity as isize;
    census(
        left,
        w,
        h,
        p.census_width as usize,
        p.census_height as usize,
        &mut s.census_l,
    );
    census(
        right,
        w,
        h,
        p.census_width as usize,
        p.census_height as usize,
        &mut s.census_r,
    );
    // Matching cost: Hamming distance. A match outside the right image is unknown, not bad: it
    // costs half the maximum, so it neither attracts nor repels, the paths carry the disparity in
    // from where it can be measured, and the left-right check then rejects the pixel (its partner
    // is outside the image). Scoring it as the maximum instead pulls the left band towards zero
    // disparity, which the LR check cannot catch.
    let unknown = ((p.census_width * p.census_height - 1) / 2) as u8;
    s.cost.clear();
    s.cost.resize(w * h * nd, unknown);
    let (cl, cr) = (&s.census_l, &s.census_r);
    s.cost
        .par_chunks_mut(w * nd)
        .enumerate()
        .for_each(|(y, row)| {
            for x in 0..w {
                let c = cl[y * w + x];
                let cell = &mut row[x * nd..(x + 1) * nd];
                for (d, v) in cell.iter_mut().enumerate() {
                    let xr = x as isize - (d as isize + dmin);
                    if xr >= 0 && (xr as usize) < w {
                        *v = (c ^ cr[y * w + xr as usize]).count_ones() as u8;
                    }
                }
            }
        });
    aggregate(left, w, h, nd, p, s);
    Ok(select(w, h, nd, p, &s.sum, valid, &mut s.right))
}

/// Directions as (dx, dy); the first four run top-down or left-right, the rest reverse them.
const DIRS: [(isize, isize); 8] = [
    (1, 0),
    (1, 1),
    (0, 1),
    (-1, 1),
    (-1, 0),
    (-1, -1),
    (0, -1),
    (1, -1),
];

fn aggregate(img: &[u8], w: usize, h: usize, nd: usize, p: &SgmParams, s: &mut Scratch) {
    let Scratch {
        cost,
        sum,
        prev_row,
        cur_row,
        tmp,
        ..
    } = s;
    sum.clear();
    sum.resize(w * h * nd, 0);
    let dirs: &[(isize, isize)] = if p.paths == 8 {
        &DIRS
    } else {
        &[(1, 0), (0, 1), (-1, 0), (0, -1)]
    };
    // Each path keeps L of the previous pixel along it: for rows-order traversal that is the
    // previous row (dy != 0) or the previous pixel in the row (dy == 0).
    prev_row.clear();
    prev_row.resize(w * nd, 0);
    cur_row.clear();
    cur_row.resize(w * nd, 0);
    tmp.clear();
    tmp.resize(nd, 0);
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
                let out = &mut cur_row[x * nd..(x + 1) * nd];
                if !inside || (dy != 0 && first_row) {
                    for d in 0..nd {
                        out[d] = c[d] as u16;
                    }
                } else {
                    let prev: &[u16] = if dy == 0 {
                        // Same row: the previous pixel's L is already in cur_row.
                        tmp.copy_from_slice(&cur_row[px as usize * nd..(px as usize + 1) * nd]);
                        tmp
                    } else {
                        &prev_row[px as usize * nd..(px as usize + 1) * nd]
                    };
                    let p2 = if p.p2_adaptive {
                        let step = (img[i] as i32 - img[py as usize * w + px as usize] as i32)
                            .unsigned_abs() as u16;
                        (p.p2 / step.max(1)).max(p.p1 + 1)
                    } else {
                        p.p2
                    };
                    let out = &mut cur_row[x * nd..(x + 1) * nd];
                    path_step(c, prev, p.p1, p2, out);
                }
                let out = &cur_row[x * nd..(x + 1) * nd];
                for (sv, &l) in sum[i * nd..(i + 1) * nd].iter_mut().zip(out) {
                    *sv = sv.saturating_add(l);
                }
            }
            std::mem::swap(prev_row, cur_row);
            first_row = false;
        }
    }
}

/// Winner-takes-all with uniqueness and sub-pixel fit, left-right check, median, speckles.
fn select(
    w: usize,
    h: usize,
    nd: usize,
    p: &SgmParams,
    sum: &[u16],
    valid: Option<&[u8]>,
    right: &mut Vec<f32>,
) -> Vec<f32> {
    let dmin = p.min_disparity as f32;
    let mut disp: Vec<f32> = (0..w * h)
        .into_par_iter()
        .map(|i| {
            if valid.is_some_and(|m| m[i] == 0) {
                return f32::NAN;
            }
            let s = &sum[i * nd..(i + 1) * nd];
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
            d + dmin
        })
        .collect();
    if p.lr_check {
        // Right disparity at xr: argmin over d of S(y, xr + d, d).
        right.clear();
        right.resize(w * h, f32::NAN);
        right.par_iter_mut().enumerate().for_each(|(j, out)| {
            let (y, xr) = (j / w, j % w);
            let (mut best, mut bd) = (u16::MAX, None);
            for d in 0..nd {
                let x = xr as isize + d as isize + p.min_disparity as isize;
                if x < 0 || x as usize >= w {
                    continue;
                }
                let v = sum[(y * w + x as usize) * nd + d];
                if v < best {
                    best = v;
                    bd = Some(d);
                }
            }
            *out = bd.map_or(f32::NAN, |d| d as f32 + dmin);
        });
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
        disp = median3(&disp, w, h);
    }
    if p.speckle_window > 0 {
        remove_speckles(&mut disp, w, h, p.speckle_window as usize, p.speckle_range);
    }
    disp
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
