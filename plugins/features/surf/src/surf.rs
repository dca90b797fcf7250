//! SURF (Bay, Ess, Tuytelaars and Van Gool, CVIU 2008): the determinant of a box-filter
//! approximation of the Hessian over octaves and intervals of filter sizes, 3x3x3 non-maximum
//! suppression above a threshold, quadratic interpolation in position and scale, orientation
//! from Haar wavelet responses in a sliding 60-degree window (or upright), and the 64-D
//! descriptor of (sum dx, sum dy, sum |dx|, sum |dy|) over 4x4 sub-regions. Dense SURF computes
//! the same descriptor on a regular grid at one scale.

use std::sync::Arc;

use crate::sampler::UprightSampler;
use misslam_framework::Keypoint;

/// Parameters of the detector and descriptor (`features.surf`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SurfParams {
    /// Threshold on the normalised Hessian determinant (intensities in [0, 1]); lower finds more.
    pub hessian_threshold: f32,
    /// Octaves (filter sizes 9-15-21-27, 15-27-39-51, 27-51-75-99, ...).
    pub octaves: usize,
    /// Filter sizes per octave (at least 3; maxima are searched in the inner ones).
    pub intervals: usize,
    /// Sampling step of the first octave, pixels (it doubles per octave).
    pub init_sample: usize,
    /// Keep at most this many keypoints, the strongest (0: all). ORB's name for the same
    /// limit, so a graph swaps the two by its plugin line alone.
    pub n_features: usize,
    /// Upright SURF (U-SURF): no orientation, faster, for a camera that does not roll.
    pub upright: bool,
    /// Dense SURF: descriptors on a grid instead of detected keypoints.
    pub dense: DenseParams,
}

/// Dense SURF settings.
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct DenseParams {
    /// Use the grid instead of the detector.
    pub enabled: bool,
    /// Grid step, pixels.
    pub step_px: usize,
    /// Scale s of every grid descriptor (its window is 20 s pixels).
    pub scale: f32,
    /// Orient each grid descriptor by its Haar responses (false: upright, as the thesis's
    /// dense matching between nearby frames).
    pub oriented: bool,
}

impl Default for DenseParams {
    fn default() -> Self {
        DenseParams {
            enabled: false,
            step_px: 8,
            scale: 2.0,
            oriented: false,
        }
    }
}

impl Default for SurfParams {
    fn default() -> Self {
        SurfParams {
            hessian_threshold: 0.0002,
            octaves: 4,
            intervals: 4,
            init_sample: 1,
            n_features: 2000,
            upright: false,
            dense: DenseParams::default(),
        }
    }
}

impl SurfParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.hessian_threshold.is_nan() || self.hessian_threshold < 0.0 {
            return Err(format!(
                "`hessian_threshold` must be >= 0, got {}",
                self.hessian_threshold
            ));
        }
        if !(1..=6).contains(&self.octaves) {
            return Err(format!("`octaves` must lie in 1..=6, got {}", self.octaves));
        }
        if !(3..=8).contains(&self.intervals) {
            return Err(format!(
                "`intervals` must lie in 3..=8, got {}",
                self.intervals
            ));
        }
        if !(1..=4).contains(&self.init_sample) {
            return Err(format!(
                "`init_sample` must lie in 1..=4, got {}",
                self.init_sample
            ));
        }
        if self.dense.step_px == 0 {
            return Err("`dense.step_px` must be at least 1".into());
        }
        if !(self.dense.scale >= 0.5 && self.dense.scale <= 20.0) {
            return Err(format!(
                "`dense.scale` must lie in [0.5, 20], got {}",
                self.dense.scale
            ));
        }
        Ok(())
    }
}

/// Summed-area table with one extra row and column: `at(x, y)` sums pixels `< x, < y`.
#[derive(Clone, Debug, Default)]
pub struct Integral {
    w: usize,
    h: usize,
    data: Vec<u32>,
}

impl Integral {
    /// Builds the table of an 8-bit gray image.
    pub fn build(&mut self, gray: &[u8], w: usize, h: usize) {
        self.w = w;
        self.h = h;
        self.data.clear();
        self.data.resize((w + 1) * (h + 1), 0);
        for y in 0..h {
            let mut row = 0u32;
            for x in 0..w {
                row += gray[y * w + x] as u32;
                self.data[(y + 1) * (w + 1) + x + 1] = self.data[y * (w + 1) + x + 1] + row;
            }
        }
    }

    /// Sum over the box of `cols` x `rows` pixels whose top-left pixel is (x, y), which must lie
    /// inside the image (no clipping), divided by 255. Wrapping arithmetic is exact while a box
    /// sums to less than 2^32.
    #[inline(always)]
    pub fn box_inside(&self, x: usize, y: usize, cols: usize, rows: usize) -> f32 {
        let s = self.w + 1;
        let (a, b) = (y * s + x, (y + rows) * s + x);
        let d = &self.data;
        let v = d[b + cols]
            .wrapping_sub(d[a + cols])
            .wrapping_sub(d[b])
            .wrapping_add(d[a]);
        v as f32 * (1.0 / 255.0)
    }

    /// Sum over the box of `cols` x `rows` pixels whose top-left pixel is (x, y), clipped to the
    /// image, divided by 255.
    #[inline(always)]
    pub fn box_sum(&self, x: i64, y: i64, cols: i64, rows: i64) -> f32 {
        let cx = |v: i64| v.clamp(0, self.w as i64) as usize;
        let cy = |v: i64| v.clamp(0, self.h as i64) as usize;
        let (x0, x1, y0, y1) = (cx(x), cx(x + cols), cy(y), cy(y + rows));
        let s = self.w + 1;
        let v = self.data[y1 * s + x1] as i64
            - self.data[y0 * s + x1] as i64
            - self.data[y1 * s + x0] as i64
            + self.data[y0 * s + x0] as i64;
        v as f32 * (1.0 / 255.0)
    }

    /// Haar wavelet response in x of size `size` (even) centred at (x, y): right half minus left.
    #[inline(always)]
    pub fn haar_x(&self, x: i64, y: i64, size: i64) -> f32 {
        let h = size / 2;
        self.box_sum(x, y - h, h, size) - self.box_sum(x - h, y - h, h, size)
    }

    /// Haar wavelet response in y: bottom half minus top half.
    #[inline(always)]
    pub fn haar_y(&self, x: i64, y: i64, size: i64) -> f32 {
        let h = size / 2;
        self.box_sum(x - h, y, size, h) - self.box_sum(x - h, y - h, size, h)
    }
}

/// Filter side of interval `i` of octave `o`: 9, 15, 21, 27; 15, 27, 39, 51; ...
pub fn filter_size(o: usize, i: usize) -> usize {
    3 * ((1 << (o + 1)) * (i + 1) + 1)
}

/// The box-filter Hessian at pixel (x, y) for filter side `l`: (Dxx, Dyy, Dxy), area-normalised.
/// The filter must fit: `l / 2 + 1 <= x < w - l / 2 - 1`, the same for y.
#[inline(always)]
pub fn hessian(ii: &Integral, x: i64, y: i64, l: i64) -> (f32, f32, f32) {
    let lobe = l / 3;
    let b = (l - 1) / 2;
    let inv_area = 1.0 / (l * l) as f32;
    let bx = |x0: i64, y0: i64, c: i64, r: i64| {
        ii.box_inside(x0 as usize, y0 as usize, c as usize, r as usize)
    };
    // Dxx: three lobes of width `lobe` along x (+1, -2, +1), height 2 lobe - 1: the whole
    // box minus three times the middle lobe.
    let dxx = bx(x - b, y - lobe + 1, l, 2 * lobe - 1)
        - 3.0 * bx(x - lobe / 2, y - lobe + 1, lobe, 2 * lobe - 1);
    let dyy = bx(x - lobe + 1, y - b, 2 * lobe - 1, l)
        - 3.0 * bx(x - lobe + 1, y - lobe / 2, 2 * lobe - 1, lobe);
    // Dxy: four lobe x lobe squares around the centre, one pixel apart; + where x and y have the
    // same sign.
    let dxy = bx(x + 1, y + 1, lobe, lobe) + bx(x - lobe, y - lobe, lobe, lobe)
        - bx(x + 1, y - lobe, lobe, lobe)
        - bx(x - lobe, y + 1, lobe, lobe);
    (dxx * inv_area, dyy * inv_area, dxy * inv_area)
}

/// One response layer: the determinant on a grid of step `step`.
#[derive(Clone, Debug, Default)]
struct Layer {
    filter: usize,
    step: usize,
    cols: usize,
    rows: usize,
    det: Vec<f32>,
}

/// Reusable state of the detector.
#[derive(Default)]
pub struct SurfScratch {
    /// The integral image of the last frame.
    pub integral: Integral,
    layers: Vec<Layer>,
    /// Upright dense SURF: the last image's Haar response maps (shared with the features it
    /// gave; rebuilt in place once nobody else holds them).
    pub sampler: Option<Arc<UprightSampler>>,
}

/// Detects (or, dense, places) keypoints and computes their descriptors.
pub fn extract(
    gray: &[u8],
    w: usize,
    h: usize,
    p: &SurfParams,
    s: &mut SurfScratch,
    keypoints: &mut Vec<Keypoint>,
    descriptors: &mut Vec<[f32; 64]>,
) -> Result<(), String> {
    p.validate()?;
    if gray.len() != w * h {
        return Err(format!(
            "a {w}x{h} image needs {} bytes, got {}",
            w * h,
            gray.len()
        ));
    }
    keypoints.clear();
    descriptors.clear();
    s.integral.build(gray, w, h);
    if p.dense.enabled {
        dense_keypoints(w, h, &p.dense, keypoints);
    } else {
        detect(w, h, p, s, keypoints);
    }
    let ii = &s.integral;
    let oriented = if p.dense.enabled {
        p.dense.oriented
    } else {
        !p.upright
    };
    if p.dense.enabled && !oriented {
        // Every grid descriptor from the response maps (the same values, far fewer box sums).
        let mut maps = s
            .sampler
            .take()
            .filter(|a| Arc::strong_count(a) == 1)
            .unwrap_or_default();
        let m = Arc::make_mut(&mut maps);
        m.build(ii, w, h, p.dense.scale);
        for k in keypoints.iter() {
            let d = m
                .at(k.x as i32, k.y as i32)
                .unwrap_or_else(|| descriptor(ii, k.x, k.y, p.dense.scale, f32::NAN));
            descriptors.push(d);
        }
        s.sampler = Some(maps);
        return Ok(());
    }
    s.sampler = None;
    for k in keypoints.iter_mut() {
        if oriented {
            k.angle = orientation(ii, k.x, k.y, k.size / 20.0);
        }
        descriptors.push(descriptor(ii, k.x, k.y, k.size / 20.0, k.angle));
    }
    Ok(())
}

fn dense_keypoints(w: usize, h: usize, d: &DenseParams, out: &mut Vec<Keypoint>) {
    // The descriptor window reaches 10 s * sqrt(2) plus the wavelet: keep it inside.
    let border = (d.scale * 15.0).ceil() as usize;
    let mut y = border;
    while y + border < h {
        let mut x = border;
        while x + border < w {
            out.push(Keypoint {
                x: x as f32,
                y: y as f32,
                size: 20.0 * d.scale,
                angle: f32::NAN,
                response: 0.0,
                octave: 0,
            });
            x += d.step_px;
        }
        y += d.step_px;
    }
}

fn detect(w: usize, h: usize, p: &SurfParams, s: &mut SurfScratch, out: &mut Vec<Keypoint>) {
    let ii = &s.integral;
    let n = p.octaves * p.intervals;
    s.layers.resize_with(n, Layer::default);
    for o in 0..p.octaves {
        let step = p.init_sample << o;
        for i in 0..p.intervals {
            let l = &mut s.layers[o * p.intervals + i];
            l.filter = filter_size(o, i);
            l.step = step;
            l.cols = w / step;
            l.rows = h / step;
            l.det.clear();
            l.det.resize(l.cols * l.rows, 0.0);
            let f = l.filter as i64;
            let b = (l.filter / 2 + 1) as i64;
            for r in 0..l.rows {
                let y = (r * step) as i64;
                if y < b || y >= h as i64 - b {
                    continue;
                }
                for c in 0..l.cols {
                    let x = (c * step) as i64;
                    if x < b || x >= w as i64 - b {
                        continue;
                    }
                    let (dxx, dyy, dxy) = hessian(ii, x, y, f);
                    // 0.9^2: the relative weight of the box-filter Dxy (Bay et al., eq. 4).
                    l.det[r * l.cols + c] = dxx * dyy - 0.81 * dxy * dxy;
                }
            }
        }
    }
    let mut found: Vec<Keypoint> = Vec::new();
    for o in 0..p.octaves {
        for i in 1..p.intervals - 1 {
            let (below, mid, above) = (
                &s.layers[o * p.intervals + i - 1],
                &s.layers[o * p.intervals + i],
                &s.layers[o * p.intervals + i + 1],
            );
            // The largest filter decides where all three are valid.
            let border = above.filter / (2 * mid.step) + 2;
            for r in border..mid.rows.saturating_sub(border) {
                for c in border..mid.cols.saturating_sub(border) {
                    let v = mid.det[r * mid.cols + c];
                    if v.is_nan() || v < p.hessian_threshold {
                        continue;
                    }
                    if !is_max(v, r, c, below, mid, above) {
                        continue;
                    }
                    if let Some(k) = interpolate(r, c, below, mid, above, o) {
                        found.push(k);
                    }
                }
            }
        }
    }
    if p.n_features > 0 && found.len() > p.n_features {
        found.select_nth_unstable_by(p.n_features, |a, b| b.response.total_cmp(&a.response));
        found.truncate(p.n_features);
    }
    found.sort_unstable_by(|a, b| {
        (a.y, a.x)
            .partial_cmp(&(b.y, b.x))
            .unwrap_or(std::cmp::Ordering::Equal)
    });
    out.extend(found);
}

fn is_max(v: f32, r: usize, c: usize, below: &Layer, mid: &Layer, above: &Layer) -> bool {
    for (k, layer) in [below, mid, above].into_iter().enumerate() {
        for dr in 0..3 {
            for dc in 0..3 {
                if k == 1 && dr == 1 && dc == 1 {
                    continue;
                }
                let n = layer.det[(r + dr - 1) * layer.cols + c + dc - 1];
                // Strict against earlier neighbours, so a plateau keeps exactly one.
                if n > v || (n == v && (k, dr, dc) < (1, 1, 1)) {
                    return false;
                }
            }
        }
    }
    true
}

/// Fits a quadratic to the 3x3x3 neighbourhood (Brown and Lowe) and returns the keypoint at its
/// maximum, or None when the maximum lies more than half a sample away (a neighbour's peak).
fn interpolate(
    r: usize,
    c: usize,
    below: &Layer,
    mid: &Layer,
    above: &Layer,
    o: usize,
) -> Option<Keypoint> {
    let m = |l: &Layer, dr: i64, dc: i64| {
        l.det[(r as i64 + dr) as usize * l.cols + (c as i64 + dc) as usize] as f64
    };
    let v = m(mid, 0, 0);
    let dx = (m(mid, 0, 1) - m(mid, 0, -1)) / 2.0;
    let dy = (m(mid, 1, 0) - m(mid, -1, 0)) / 2.0;
    let ds = (m(above, 0, 0) - m(below, 0, 0)) / 2.0;
    let dxx = m(mid, 0, 1) + m(mid, 0, -1) - 2.0 * v;
    let dyy = m(mid, 1, 0) + m(mid, -1, 0) - 2.0 * v;
    let dss = m(above, 0, 0) + m(below, 0, 0) - 2.0 * v;
    let dxy = (m(mid, 1, 1) - m(mid, 1, -1) - m(mid, -1, 1) + m(mid, -1, -1)) / 4.0;
    let dxs = (m(above, 0, 1) - m(above, 0, -1) - m(below, 0, 1) + m(below, 0, -1)) / 4.0;
    let dys = (m(above, 1, 0) - m(above, -1, 0) - m(below, 1, 0) + m(below, -1, 0)) / 4.0;
    let hm = misslam_framework::nalgebra::Matrix3::new(dxx, dxy, dxs, dxy, dyy, dys, dxs, dys, dss);
    let g = misslam_framework::nalgebra::Vector3::new(dx, dy, ds);
    let off = -(hm.try_inverse()? * g);
    if off.iter().any(|v| !v.is_finite() || v.abs() >= 0.5) {
        return None;
    }
    let step = mid.step as f64;
    let filter_step = (mid.filter - below.filter) as f64;
    let filter = mid.filter as f64 + off.z * filter_step;
    let scale = 1.2 / 9.0 * filter;
    Some(Keypoint {
        x: ((c as f64 + off.x) * step) as f32,
        y: ((r as f64 + off.y) * step) as f32,
        size: (20.0 * scale) as f32,
        angle: f32::NAN,
        response: (v + 0.5 * g.dot(&off)) as f32,
        octave: o as i32,
    })
}

/// Gaussian weight.
#[inline]
fn gauss(x: f32, y: f32, sigma: f32) -> f32 {
    (-(x * x + y * y) / (2.0 * sigma * sigma)).exp()
}

/// Gaussian weights of the orientation samples (sigma 2.5, in units of s) for i, j in -6..=6.
fn orientation_weights() -> &'static [[f32; 13]; 13] {
    static W: std::sync::OnceLock<[[f32; 13]; 13]> = std::sync::OnceLock::new();
    W.get_or_init(|| {
        std::array::from_fn(|j| std::array::from_fn(|i| gauss(i as f32 - 6.0, j as f32 - 6.0, 2.5)))
    })
}

/// Dominant orientation: Haar responses (size 4 s) at the samples of radius 6 s (step s),
/// Gaussian-weighted (sigma 2.5 s); the 60-degree window, slid in steps of 0.15 rad, whose
/// summed response vector is longest gives the angle. The responses are sorted by angle once
/// and each window is summed by two pointers.
pub fn orientation(ii: &Integral, x: f32, y: f32, s: f32) -> f32 {
    use std::f32::consts::{FRAC_PI_3, TAU};
    let si = s.round().max(1.0) as i64;
    let haar = 4 * si;
    let (cx, cy) = (x.round() as i64, y.round() as i64);
    let weights = orientation_weights();
    let mut resp: Vec<(f32, f32, f32)> = Vec::with_capacity(2 * 113);
    for j in -6i64..=6 {
        for i in -6i64..=6 {
            if i * i + j * j >= 36 {
                continue;
            }
            let w = weights[(j + 6) as usize][(i + 6) as usize];
            let dx = w * ii.haar_x(cx + i * si, cy + j * si, haar);
            let dy = w * ii.haar_y(cx + i * si, cy + j * si, haar);
            let phi = dy.atan2(dx);
            resp.push((if phi < 0.0 { phi + TAU } else { phi }, dx, dy));
        }
    }
    resp.sort_unstable_by(|a, b| a.0.total_cmp(&b.0));
    // Doubled with +2 pi so a window may wrap past 2 pi.
    let n = resp.len();
    for k in 0..n {
        let (phi, dx, dy) = resp[k];
        resp.push((phi + TAU, dx, dy));
    }
    let (mut best, mut angle) = (0.0f32, 0.0f32);
    let (mut lo, mut hi) = (0usize, 0usize);
    let (mut sx, mut sy) = (0.0f32, 0.0f32);
    let mut a = 0.0f32;
    while a < TAU {
        // Window [a, a + pi/3).
        while hi < resp.len() && resp[hi].0 < a + FRAC_PI_3 {
            sx += resp[hi].1;
            sy += resp[hi].2;
            hi += 1;
        }
        while lo < hi && resp[lo].0 < a {
            sx -= resp[lo].1;
            sy -= resp[lo].2;
            lo += 1;
        }
        let m = sx * sx + sy * sy;
        if m > best {
            best = m;
            angle = sy.atan2(sx);
        }
        a += 0.15;
    }
    angle
}

/// The 64-D descriptor: a 20 s window rotated by `angle` (upright when NaN), 4 x 4 sub-regions
/// of 5 x 5 samples at step s, Haar responses of size 2 s turned into the keypoint's frame,
/// Gaussian-weighted (sigma 3.3 s), summed as (dx, dy, |dx|, |dy|), normalised to unit length.
pub fn descriptor(ii: &Integral, x: f32, y: f32, s: f32, angle: f32) -> [f32; 64] {
    let (sn, co) = if angle.is_finite() {
        angle.sin_cos()
    } else {
        (0.0, 1.0)
    };
    let haar = haar_size(s);
    let mut d = [0f32; 64];
    for sy in 0..4 {
        for sx in 0..4 {
            let mut acc = [0f32; 4];
            for j in 0..5 {
                for i in 0..5 {
                    // Sample centre in the keypoint frame, units of s: -10 + 5 sub + 0.5 + i.
                    let u = -10.0 + 5.0 * sx as f32 + i as f32 + 0.5;
                    let v = -10.0 + 5.0 * sy as f32 + j as f32 + 0.5;
                    let px = x + s * (u * co - v * sn);
                    let py = y + s * (u * sn + v * co);
                    let (ix, iy) = (px.round() as i64, py.round() as i64);
                    let w = descriptor_weight(u, v);
                    let rx = ii.haar_x(ix, iy, haar);
                    let ry = ii.haar_y(ix, iy, haar);
                    let du = w * (rx * co + ry * sn);
                    let dv = w * (-rx * sn + ry * co);
                    acc[0] += du;
                    acc[1] += dv;
                    acc[2] += du.abs();
                    acc[3] += dv.abs();
                }
            }
            d[(sy * 4 + sx) * 4..(sy * 4 + sx) * 4 + 4].copy_from_slice(&acc);
        }
    }
    normalise(&mut d);
    d
}

/// Side of the Haar wavelets of a descriptor at scale `s`: 2 s, even, at least 2.
pub fn haar_size(s: f32) -> i64 {
    (2.0 * s).round().max(2.0) as i64 & !1
}

/// Gaussian weight (sigma 3.3) of the descriptor sample at (u, v), units of s.
pub fn descriptor_weight(u: f32, v: f32) -> f32 {
    gauss(u, v, 3.3)
}

/// Scales a descriptor to unit length (a zero one stays zero).
pub fn normalise(d: &mut [f32; 64]) {
    let n = d.iter().map(|v| v * v).sum::<f32>().sqrt();
    if n > 0.0 {
        for v in d.iter_mut() {
            *v /= n;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn filter_sizes_follow_the_paper() {
        assert_eq!(
            (0..4).map(|i| filter_size(0, i)).collect::<Vec<_>>(),
            [9, 15, 21, 27]
        );
        assert_eq!(
            (0..4).map(|i| filter_size(1, i)).collect::<Vec<_>>(),
            [15, 27, 39, 51]
        );
        assert_eq!(
            (0..4).map(|i| filter_size(2, i)).collect::<Vec<_>>(),
            [27, 51, 75, 99]
        );
    }

    #[test]
    fn integral_boxes_and_haar_responses() {
        let (w, h) = (20usize, 10usize);
        let img: Vec<u8> = (0..w * h)
            .map(|i| if i % w >= 10 { 255 } else { 0 })
            .collect();
        let mut ii = Integral::default();
        ii.build(&img, w, h);
        let near = |a: f32, b: f32| (a - b).abs() < 1e-4;
        assert!(near(ii.box_sum(0, 0, 20, 10), 100.0));
        assert!(near(ii.box_sum(12, 2, 3, 4), 12.0));
        // Clipped at the border.
        assert!(near(ii.box_sum(18, 8, 10, 10), 4.0));
        // A vertical edge at x = 10: strong x response there, none in y.
        assert!(near(ii.haar_x(10, 5, 4), 8.0));
        assert_eq!(ii.haar_y(10, 5, 4), 0.0);
        assert_eq!(ii.haar_x(4, 5, 4), 0.0);
    }

    #[test]
    fn hessian_of_a_quadratic_bowl_matches_its_second_derivatives() {
        // I = a x^2 + b y^2 + c x y around the centre (the 9x9 filters see only +-4 pixels):
        // Dxx responds to a alone, Dyy to b alone with the same gain, Dxy to c alone.
        let (w, h) = (64usize, 64usize);
        let make = |a: f32, b: f32, c: f32| -> Integral {
            let img: Vec<u8> = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as f32 - 32.0, (i / w) as f32 - 32.0);
                    (100.0 + a * x * x + b * y * y + c * x * y)
                        .round()
                        .clamp(0.0, 255.0) as u8
                })
                .collect();
            let mut ii = Integral::default();
            ii.build(&img, w, h);
            ii
        };
        let xx = hessian(&make(2.0, 0.0, 0.0), 32, 32, 9);
        let yy = hessian(&make(0.0, 2.0, 0.0), 32, 32, 9);
        assert!(
            xx.0 > 0.0 && xx.1.abs() < 0.05 * xx.0 && xx.2.abs() < 0.05 * xx.0,
            "{xx:?}"
        );
        assert!(
            yy.1 > 0.0 && (yy.1 - xx.0).abs() < 0.02 * xx.0,
            "{yy:?} vs {xx:?}"
        );
        let xy = hessian(&make(0.0, 0.0, 3.0), 32, 32, 9);
        assert!(xy.2 > 0.0 && xy.0.abs() < 0.1 * xy.2, "{xy:?}");
    }

    #[test]
    fn a_blob_is_found_at_its_centre_and_scale() {
        // A dark Gaussian blob of sigma 4 px on a bright background: one keypoint at its centre
        // with a scale near sigma (box-filter scale s = 1.2 L / 9 responds best at s ~ sigma).
        let (w, h) = (128usize, 128usize);
        let img: Vec<u8> = (0..w * h)
            .map(|i| {
                let (x, y) = ((i % w) as f32 - 60.3, (i / w) as f32 - 70.6);
                (220.0 - 180.0 * (-(x * x + y * y) / 32.0).exp()) as u8
            })
            .collect();
        let p = SurfParams {
            hessian_threshold: 0.001,
            ..SurfParams::default()
        };
        let (mut k, mut d) = (Vec::new(), Vec::new());
        extract(&img, w, h, &p, &mut SurfScratch::default(), &mut k, &mut d).expect("valid");
        assert!(!k.is_empty());
        let best = k
            .iter()
            .max_by(|a, b| a.response.total_cmp(&b.response))
            .expect("one");
        assert!(
            (best.x - 60.3).abs() < 0.5 && (best.y - 70.6).abs() < 0.5,
            "{best:?}"
        );
        let s = best.size / 20.0;
        assert!((2.8..6.0).contains(&s), "scale {s}");
        for v in &d {
            let n: f32 = v.iter().map(|x| x * x).sum();
            assert!((n - 1.0).abs() < 1e-4 || n == 0.0);
        }
    }
}
