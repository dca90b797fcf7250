//! ORB (Rublee, Rabaud, Konolige and Bradski, ICCV 2011): FAST-9 on a scale pyramid, Harris
//! ranking, an even spread over the image, intensity-centroid orientation and steered BRIEF.

use misslam_framework::Keypoint;
use rayon::prelude::*;

use crate::fast::{self, Corner, FastScratch};
use crate::learned_pattern::LEARNED;
use crate::pyramid::{gaussian7, resize_bilinear, Level};

/// Which 256 binary tests the descriptor uses.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum PatternKind {
    /// rBRIEF: tests learned for high variance and low correlation on oriented keypoints of
    /// surgical frames (the ORB paper's section 4.3; `examples/learn_orb_pattern.rs`).
    Learned,
    /// Steered BRIEF's isotropic Gaussian pattern (G II), from a fixed seed.
    Gaussian,
}

/// How the kept corners are spread over each level.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Distribution {
    /// ORB-SLAM's quadtree: split the cell with the most corners until there are as many cells
    /// as wanted corners, keep the best (Harris) corner of each.
    Quadtree,
    /// A regular grid with about as many cells as wanted corners, the best corner of each.
    Grid,
    /// No spreading: the best corners by Harris response.
    None,
}

/// Parameters of the extractor (`features.orb`).
#[derive(Clone, Debug, PartialEq, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct OrbParams {
    /// Keypoints wanted over all levels.
    pub n_features: usize,
    /// Scale between pyramid levels.
    pub scale_factor: f32,
    /// Pyramid levels.
    pub levels: usize,
    /// FAST threshold (intensity difference).
    pub fast_threshold: u8,
    /// FAST threshold used again in any `cell_px` cell where `fast_threshold` found nothing
    /// (ORB-SLAM: 20 then 7), so weakly textured tissue still gets corners; 0 disables the retry.
    pub min_fast_threshold: u8,
    /// Cell of the low-threshold retry, pixels of each level.
    pub cell_px: usize,
    /// Distance from the level's border within which no keypoint is kept, pixels (at least 16:
    /// the orientation patch has radius 15).
    pub edge_threshold: usize,
    /// How corners are spread.
    pub distribution: Distribution,
    /// Harris `k` in `det - k trace^2`.
    pub harris_k: f32,
    /// Compute orientations (false gives upright descriptors, angle NaN).
    pub oriented: bool,
    /// The binary tests: `learned` (rBRIEF) or `gaussian` (steered BRIEF). Descriptors of the two
    /// are not comparable with each other.
    pub pattern: PatternKind,
}

impl Default for OrbParams {
    fn default() -> Self {
        OrbParams {
            n_features: 1000,
            scale_factor: 1.2,
            levels: 8,
            fast_threshold: 20,
            min_fast_threshold: 7,
            cell_px: 30,
            edge_threshold: 19,
            distribution: Distribution::Quadtree,
            harris_k: 0.04,
            oriented: true,
            pattern: PatternKind::Learned,
        }
    }
}

impl OrbParams {
    /// Checks the ranges; the message names the field.
    pub fn validate(&self) -> Result<(), String> {
        if self.n_features == 0 || self.n_features > 100_000 {
            return Err(format!(
                "`n_features` must lie in 1..=100000, got {}",
                self.n_features
            ));
        }
        if !(self.scale_factor > 1.0 && self.scale_factor <= 2.0) {
            return Err(format!(
                "`scale_factor` must lie in (1, 2], got {}",
                self.scale_factor
            ));
        }
        if self.levels == 0 || self.levels > 16 {
            return Err(format!("`levels` must lie in 1..=16, got {}", self.levels));
        }
        if self.fast_threshold == 0 {
            return Err("`fast_threshold` must be positive".into());
        }
        if self.min_fast_threshold > self.fast_threshold {
            return Err(format!(
                "`min_fast_threshold` ({}) must not exceed `fast_threshold` ({})",
                self.min_fast_threshold, self.fast_threshold
            ));
        }
        if self.cell_px < 8 {
            return Err(format!("`cell_px` must be >= 8, got {}", self.cell_px));
        }
        if !(16..=64).contains(&self.edge_threshold) {
            return Err(format!(
                "`edge_threshold` must lie in 16..=64, got {}",
                self.edge_threshold
            ));
        }
        if !self.harris_k.is_finite() || self.harris_k < 0.0 {
            return Err(format!("`harris_k` must be >= 0, got {}", self.harris_k));
        }
        Ok(())
    }

    /// Keypoints wanted on each level: a geometric series in the area ratio (ORB-SLAM).
    pub fn per_level(&self) -> Vec<usize> {
        let f = 1.0 / self.scale_factor as f64;
        let n = self.n_features as f64;
        let mut out = Vec::with_capacity(self.levels);
        let mut left = self.n_features;
        let first = n * (1.0 - f) / (1.0 - f.powi(self.levels as i32));
        for l in 0..self.levels {
            let want = if l + 1 == self.levels {
                left
            } else {
                ((first * f.powi(l as i32)).round() as usize).min(left)
            };
            out.push(want);
            left -= want;
        }
        out
    }
}

/// Corners per wanted keypoint that get a Harris response (the strongest by FAST score).
pub const PREFILTER: usize = 2;

/// Radius of the orientation patch.
pub const HALF_PATCH: i32 = 15;
/// Test points of the binary descriptor lie within this radius (so any rotation stays inside
/// the orientation patch, and inside the border of `edge_threshold` >= 16 with the blur).
pub const PATTERN_RADIUS: f32 = 15.0;

/// The 256 point pairs (x1, y1, x2, y2) of the binary tests of `kind`.
pub fn pattern(kind: PatternKind) -> &'static [[f32; 4]; 256] {
    match kind {
        PatternKind::Gaussian => gaussian_pattern(),
        PatternKind::Learned => learned_pattern(),
    }
}

fn learned_pattern() -> &'static [[f32; 4]; 256] {
    static PATTERN: std::sync::OnceLock<[[f32; 4]; 256]> = std::sync::OnceLock::new();
    PATTERN.get_or_init(|| LEARNED.map(|t| t.map(|v| v as f32)))
}

/// BRIEF's isotropic Gaussian pattern (G II, sigma = 31 / 5) from a fixed seed, clipped to
/// [`PATTERN_RADIUS`]. Deterministic across runs and platforms, so descriptors are comparable
/// between runs.
fn gaussian_pattern() -> &'static [[f32; 4]; 256] {
    static PATTERN: std::sync::OnceLock<[[f32; 4]; 256]> = std::sync::OnceLock::new();
    PATTERN.get_or_init(|| {
        let mut state = 0x6d69_7373_6c61_6d00u64; // "misslam"
        let mut uniform = move || {
            state = state.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        };
        let sigma = 31.0 / 5.0;
        let mut point = move || loop {
            // Box-Muller.
            let (u1, u2) = (uniform().max(1e-300), uniform());
            let r = (-2.0 * u1.ln()).sqrt() * sigma;
            let a = std::f64::consts::TAU * u2;
            let (x, y) = ((r * a.cos()).round(), (r * a.sin()).round());
            if x * x + y * y <= (PATTERN_RADIUS * PATTERN_RADIUS) as f64 {
                return [x as f32, y as f32];
            }
        };
        let mut out = [[0f32; 4]; 256];
        for pair in out.iter_mut() {
            loop {
                let (a, b) = (point(), point());
                if a != b {
                    *pair = [a[0], a[1], b[0], b[1]];
                    break;
                }
            }
        }
        out
    })
}

/// Reusable state of the extractor: pyramid and buffers, so a frame allocates almost nothing.
#[derive(Default)]
pub struct OrbScratch {
    levels: Vec<Level>,
    work: Vec<LevelWork>,
}

/// One level's buffers and output, so that the levels run in parallel.
#[derive(Default)]
struct LevelWork {
    fast: FastScratch,
    corners: Vec<Corner>,
    nms_map: Vec<u8>,
    responses: Vec<f32>,
    order: Vec<u32>,
    cells: Vec<u32>,
    blur_tmp: Vec<u16>,
    kept: Vec<(Corner, f32)>,
    keypoints: Vec<Keypoint>,
    descriptors: Vec<[u64; 4]>,
}

impl OrbScratch {
    /// The pyramid of the last extraction.
    pub fn levels(&self) -> &[Level] {
        &self.levels
    }
}

/// Extracts ORB keypoints (level-0 coordinates) and their descriptors from a gray image.
pub fn extract(
    gray: &[u8],
    width: usize,
    height: usize,
    params: &OrbParams,
    scratch: &mut OrbScratch,
    keypoints: &mut Vec<Keypoint>,
    descriptors: &mut Vec<[u64; 4]>,
) -> Result<(), String> {
    params.validate()?;
    if gray.len() != width * height {
        return Err(format!(
            "a {width}x{height} image needs {} bytes, got {}",
            width * height,
            gray.len()
        ));
    }
    keypoints.clear();
    descriptors.clear();
    build_pyramid(gray, width, height, params, scratch);
    // The levels in parallel (each with its own buffers), their keypoints then concatenated in
    // level order: the output of one level after the other.
    let per_level = params.per_level();
    scratch.work.resize_with(params.levels, LevelWork::default);
    scratch
        .levels
        .par_iter_mut()
        .zip(scratch.work.par_iter_mut())
        .zip(per_level.par_iter())
        .enumerate()
        .for_each(|(l, ((level, work), &want))| {
            extract_level(l, want, (width, height), params, level, work)
        });
    for work in &scratch.work {
        keypoints.extend_from_slice(&work.keypoints);
        descriptors.extend_from_slice(&work.descriptors);
    }
    Ok(())
}

/// Resizes each level from the one before (the smoothing is [`extract_level`]'s).
fn build_pyramid(gray: &[u8], width: usize, height: usize, p: &OrbParams, s: &mut OrbScratch) {
    s.levels.resize_with(p.levels, Level::default);
    for l in 0..p.levels {
        let scale = p.scale_factor.powi(l as i32);
        let (w, h) = if l == 0 {
            (width, height)
        } else {
            (
                (width as f32 / scale).round() as usize,
                (height as f32 / scale).round() as usize,
            )
        };
        if l == 0 {
            let lv = &mut s.levels[0];
            lv.data.clear();
            lv.data.extend_from_slice(gray);
        } else {
            let (prev, rest) = s.levels.split_at_mut(l);
            let pr = &prev[l - 1];
            resize_bilinear(&pr.data, pr.width, pr.height, &mut rest[0].data, w, h);
        }
        let lv = &mut s.levels[l];
        lv.width = w;
        lv.height = h;
        lv.scale = scale;
    }
}

/// One level: its smoothed image, then `want` keypoints (level-0 coordinates of the
/// `width` x `height` image) with their descriptors in `work`.
fn extract_level(
    l: usize,
    want: usize,
    (width, height): (usize, usize),
    params: &OrbParams,
    level: &mut Level,
    work: &mut LevelWork,
) {
    let (w, h) = (level.width, level.height);
    gaussian7(&level.data, w, h, &mut level.smooth, &mut work.blur_tmp);
    work.keypoints.clear();
    work.descriptors.clear();
    let e = params.edge_threshold;
    if want == 0 || w <= 2 * e + 1 || h <= 2 * e + 1 {
        return;
    }
    detect_level(level, params, work);
    select(level, want, params, work);
    // Level pixel centres to level-0 pixel centres: each level is resized from the one before
    // with centres aligned, so x0 + 0.5 = (x_l + 0.5) * (width / w).
    let (sx, sy) = (width as f32 / w as f32, height as f32 / h as f32);
    for &(c, response) in &work.kept {
        let angle = if params.oriented {
            orientation(&level.data, w, c.x as i32, c.y as i32)
        } else {
            f32::NAN
        };
        work.descriptors.push(describe(
            &level.smooth,
            w,
            c.x as i32,
            c.y as i32,
            angle,
            params.pattern,
        ));
        work.keypoints.push(Keypoint {
            x: (c.x as f32 + 0.5) * sx - 0.5,
            y: (c.y as f32 + 0.5) * sy - 0.5,
            size: 31.0 * level.scale,
            angle,
            response,
            octave: l as i32,
        });
    }
}

/// FAST at `fast_threshold` over the level, again at `min_fast_threshold` in empty cells, then
/// non-maximum suppression.
fn detect_level(lv: &Level, p: &OrbParams, s: &mut LevelWork) {
    let (w, h) = (lv.width, lv.height);
    let e = p.edge_threshold;
    // FAST itself needs 3 pixels; keypoints must stay `e` inside.
    let region = (e, e, w - e, h - e);
    s.corners.clear();
    fast::detect(
        &lv.data,
        w,
        h,
        region,
        p.fast_threshold,
        &mut s.fast,
        &mut s.corners,
    );
    if p.min_fast_threshold > 0 && p.min_fast_threshold < p.fast_threshold {
        let cell = p.cell_px;
        let (cols, rows) = ((w - 2 * e).div_ceil(cell), (h - 2 * e).div_ceil(cell));
        s.cells.clear();
        s.cells.resize(cols * rows, 0);
        for c in &s.corners {
            let (cx, cy) = ((c.x as usize - e) / cell, (c.y as usize - e) / cell);
            s.cells[cy * cols + cx] += 1;
        }
        for cy in 0..rows {
            for cx in 0..cols {
                if s.cells[cy * cols + cx] != 0 {
                    continue;
                }
                let x0 = e + cx * cell;
                let y0 = e + cy * cell;
                let rect = (x0, y0, (x0 + cell).min(w - e), (y0 + cell).min(h - e));
                fast::detect(
                    &lv.data,
                    w,
                    h,
                    rect,
                    p.min_fast_threshold,
                    &mut s.fast,
                    &mut s.corners,
                );
            }
        }
        // The retry cells are disjoint from each other and held no corner before: no pixel is
        // detected twice, so no sort or de-duplication is needed.
    }
    // The map stays zeroed between calls (the suppression clears what it wrote), so it only
    // needs to grow, never to be cleared.
    if s.nms_map.len() < w * h {
        s.nms_map.resize(w * h, 0);
    }
    fast::non_max_suppression(&mut s.corners, w, &mut s.nms_map[..w * h]);
}

/// Harris response with Sobel gradients over a 7x7 block, normalised as OpenCV's ORB does.
/// The 9x9 pixels the gradients read are loaded once into a local block (one bounds check a
/// row, not one a tap); the sums are exact in i32 (49 x (4 x 255)^2 < 2^31).
fn harris(img: &[u8], w: usize, x: i32, y: i32, k: f32) -> f32 {
    let mut p = [[0i32; 9]; 9];
    for (r, row) in p.iter_mut().enumerate() {
        let start = (y - 4 + r as i32) as usize * w + (x - 4) as usize;
        for (d, &s) in row.iter_mut().zip(&img[start..start + 9]) {
            *d = s as i32;
        }
    }
    let (mut a, mut b, mut c) = (0i32, 0i32, 0i32);
    for v in 1..8 {
        for u in 1..8 {
            let ix = (p[v - 1][u + 1] - p[v - 1][u - 1])
                + 2 * (p[v][u + 1] - p[v][u - 1])
                + (p[v + 1][u + 1] - p[v + 1][u - 1]);
            let iy = (p[v + 1][u - 1] - p[v - 1][u - 1])
                + 2 * (p[v + 1][u] - p[v - 1][u])
                + (p[v + 1][u + 1] - p[v - 1][u + 1]);
            a += ix * ix;
            b += iy * iy;
            c += ix * iy;
        }
    }
    harris_response(a as i64, b as i64, c as i64, k)
}

/// The response from the block's sums of Ix^2, Iy^2 and Ix Iy (Sobel gains 4 per unit step; 7x7
/// block; 8-bit range).
fn harris_response(a: i64, b: i64, c: i64, k: f32) -> f32 {
    let scale = 1.0 / (4.0 * 7.0 * 255.0);
    let (a, b, c) = (
        a as f32 * scale * scale,
        b as f32 * scale * scale,
        c as f32 * scale * scale,
    );
    a * b - c * c - k * (a + b) * (a + b)
}

/// Ranks the level's corners by Harris response and keeps `want` of them, spread as asked.
fn select(lv: &Level, want: usize, p: &OrbParams, s: &mut LevelWork) {
    let w = lv.width;
    // Harris only for the strongest corners by FAST score (OpenCV's ORB does the same).
    let budget = (PREFILTER * want).max(64);
    if s.corners.len() > budget {
        s.corners.select_nth_unstable_by(budget, |a, b| {
            b.score.cmp(&a.score).then((a.y, a.x).cmp(&(b.y, b.x)))
        });
        s.corners.truncate(budget);
    }
    s.responses.clear();
    s.responses.extend(
        s.corners
            .iter()
            .map(|c| harris(&lv.data, w, c.x as i32, c.y as i32, p.harris_k)),
    );
    s.order.clear();
    s.order.extend(0..s.corners.len() as u32);
    let e = p.edge_threshold as f32;
    let bounds = (e, e, (lv.width as f32 - e), (lv.height as f32 - e));
    let chosen: Vec<u32> = match p.distribution {
        Distribution::None => s.order.clone(),
        Distribution::Quadtree => quadtree(&s.corners, &s.responses, &mut s.order, bounds, want),
        Distribution::Grid => grid(&s.corners, &s.responses, bounds, want),
    };
    let mut chosen = chosen;
    let r = &s.responses;
    chosen.sort_unstable_by(|&a, &b| r[b as usize].total_cmp(&r[a as usize]).then(a.cmp(&b)));
    chosen.truncate(want);
    s.kept.clear();
    s.kept.extend(
        chosen
            .iter()
            .map(|&i| (s.corners[i as usize], r[i as usize])),
    );
}

/// ORB-SLAM's quadtree: start from square-ish cells over `bounds`, split the most populated
/// cell in four until there are at least `want` cells or none holds two corners, then keep the
/// strongest corner of each cell. `order` is permuted in place (each cell a contiguous range).
fn quadtree(
    corners: &[Corner],
    resp: &[f32],
    order: &mut [u32],
    (x0, y0, x1, y1): (f32, f32, f32, f32),
    want: usize,
) -> Vec<u32> {
    #[derive(Clone, Copy)]
    struct Cell {
        x0: f32,
        y0: f32,
        x1: f32,
        y1: f32,
        start: usize,
        end: usize,
    }
    let roots = (((x1 - x0) / (y1 - y0)).round() as usize).max(1);
    let rw = (x1 - x0) / roots as f32;
    // Partition `order[start..end]` by a key in 0..k; returns the k + 1 boundaries.
    fn partition(order: &mut [u32], key: impl Fn(u32) -> usize, k: usize) -> Vec<usize> {
        let mut counts = vec![0usize; k + 1];
        for &i in order.iter() {
            counts[key(i) + 1] += 1;
        }
        for j in 0..k {
            counts[j + 1] += counts[j];
        }
        let mut fill = counts.clone();
        let src = order.to_vec();
        for i in src {
            let b = key(i);
            order[fill[b]] = i;
            fill[b] += 1;
        }
        counts
    }
    let xy = |i: u32| (corners[i as usize].x as f32, corners[i as usize].y as f32);
    let bounds = partition(
        order,
        |i| (((xy(i).0 - x0) / rw) as usize).min(roots - 1),
        roots,
    );
    let mut cells: Vec<Cell> = (0..roots)
        .map(|r| Cell {
            x0: x0 + r as f32 * rw,
            y0,
            x1: x0 + (r + 1) as f32 * rw,
            y1,
            start: bounds[r],
            end: bounds[r + 1],
        })
        .filter(|c| c.end > c.start)
        .collect();
    while cells.len() < want {
        let Some((ci, _)) = cells
            .iter()
            .enumerate()
            .filter(|(_, c)| c.end - c.start > 1 && c.x1 - c.x0 > 1.0)
            .max_by_key(|(_, c)| c.end - c.start)
        else {
            break;
        };
        let c = cells.swap_remove(ci);
        let (mx, my) = ((c.x0 + c.x1) * 0.5, (c.y0 + c.y1) * 0.5);
        let quadrant = |i: u32| {
            let (x, y) = xy(i);
            (x >= mx) as usize + 2 * (y >= my) as usize
        };
        let b = partition(&mut order[c.start..c.end], quadrant, 4);
        for q in 0..4 {
            let (s, e) = (c.start + b[q], c.start + b[q + 1]);
            if e > s {
                let (qx0, qx1) = if q & 1 == 0 { (c.x0, mx) } else { (mx, c.x1) };
                let (qy0, qy1) = if q & 2 == 0 { (c.y0, my) } else { (my, c.y1) };
                cells.push(Cell {
                    x0: qx0,
                    y0: qy0,
                    x1: qx1,
                    y1: qy1,
                    start: s,
                    end: e,
                });
            }
        }
    }
    cells
        .iter()
        .map(|c| {
            *order[c.start..c.end]
                .iter()
                .max_by(|&&a, &&b| {
                    resp[a as usize]
                        .total_cmp(&resp[b as usize])
                        .then(b.cmp(&a))
                })
                .unwrap_or(&order[c.start])
        })
        .collect()
}

/// A regular grid of about `want` square cells over `bounds`; the strongest corner of each.
fn grid(
    corners: &[Corner],
    resp: &[f32],
    (x0, y0, x1, y1): (f32, f32, f32, f32),
    want: usize,
) -> Vec<u32> {
    let area = ((x1 - x0) * (y1 - y0)).max(1.0);
    let side = (area / want.max(1) as f32).sqrt().max(1.0);
    let cols = (((x1 - x0) / side).ceil() as usize).max(1);
    let rows = (((y1 - y0) / side).ceil() as usize).max(1);
    let mut best = vec![u32::MAX; cols * rows];
    for (i, c) in corners.iter().enumerate() {
        let cx = (((c.x as f32 - x0) / side) as usize).min(cols - 1);
        let cy = (((c.y as f32 - y0) / side) as usize).min(rows - 1);
        let b = &mut best[cy * cols + cx];
        if *b == u32::MAX || resp[i] > resp[*b as usize] {
            *b = i as u32;
        }
    }
    best.into_iter().filter(|&b| b != u32::MAX).collect()
}

/// Offsets of the circular orientation patch: `UMAX[v]` is the half width of row `v`.
fn umax() -> &'static [i32; HALF_PATCH as usize + 1] {
    static U: std::sync::OnceLock<[i32; HALF_PATCH as usize + 1]> = std::sync::OnceLock::new();
    U.get_or_init(|| {
        let r = HALF_PATCH as f32;
        std::array::from_fn(|v| ((r * r - (v * v) as f32).sqrt() + 0.5).floor() as i32)
    })
}

/// Intensity-centroid orientation in radians (image axes: x right, y down): atan2(m01, m10)
/// of the moments over the disc of radius [`HALF_PATCH`]. With AVX2, each of the disc's 31
/// rows is one 32-byte load multiplied by that row's weights (its offsets, and ones for the
/// row sum, zero outside the disc); the integer moments, and so the angle, are those of
/// [`orientation_scalar`].
pub fn orientation(img: &[u8], w: usize, x: i32, y: i32) -> f32 {
    #[cfg(target_arch = "x86_64")]
    {
        // The loads span x - 15 ..= x + 16 on rows y - 15 ..= y + 15.
        let h = img.len() / w.max(1);
        let inside = x >= HALF_PATCH
            && (x + HALF_PATCH + 1) < w as i32
            && y >= HALF_PATCH
            && (y + HALF_PATCH) < h as i32;
        if inside && std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2 (checked just above).
            let (m01, m10) = unsafe { moments_avx2(img, w, x, y) };
            return (m01 as f32).atan2(m10 as f32);
        }
    }
    orientation_scalar(img, w, x, y)
}

/// [`orientation`] one pixel at a time. Row sums in 32-bit integers (at most 31 x 15 x 255
/// per row).
pub fn orientation_scalar(img: &[u8], w: usize, x: i32, y: i32) -> f32 {
    let um = umax();
    let (mut m01, mut m10) = (0i64, 0i64);
    for v in -HALF_PATCH..=HALF_PATCH {
        let u = um[v.unsigned_abs() as usize];
        let start = ((y + v) as usize) * w + (x - u) as usize;
        let row = &img[start..start + (2 * u + 1) as usize];
        let (mut sum_row, mut moment) = (0i32, 0i32);
        for (k, &p) in row.iter().enumerate() {
            sum_row += p as i32;
            moment += (k as i32 - u) * p as i32;
        }
        m10 += moment as i64;
        m01 += v as i64 * sum_row as i64;
    }
    (m01 as f32).atan2(m10 as f32)
}

/// Per |v|, the 32 byte weights of a row loaded from x - 15: the offset k - 15 inside the
/// disc's chord (|k - 15| <= umax), and 1 there for the row sum; 0 elsewhere (byte 31 always).
fn disc_weights() -> &'static [([i8; 32], [i8; 32]); HALF_PATCH as usize + 1] {
    type Table = [([i8; 32], [i8; 32]); HALF_PATCH as usize + 1];
    static T: std::sync::OnceLock<Table> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let um = umax();
        std::array::from_fn(|v| {
            let inside = |k: usize| (k as i32 - HALF_PATCH).abs() <= um[v] && k < 31;
            (
                std::array::from_fn(|k| if inside(k) { k as i8 - 15 } else { 0 }),
                std::array::from_fn(|k| inside(k) as i8),
            )
        })
    })
}

/// The moments (m01, m10) of [`orientation`], a row of the disc per 32-byte load.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2")]
fn moments_avx2(img: &[u8], w: usize, x: i32, y: i32) -> (i64, i64) {
    use std::arch::x86_64::*;
    let table = disc_weights();
    let ones = _mm256_set1_epi16(1);
    let (mut m10, mut m01) = (_mm256_setzero_si256(), _mm256_setzero_si256());
    for v in -HALF_PATCH..=HALF_PATCH {
        let (wk, wm) = &table[v.unsigned_abs() as usize];
        let start = (y + v) as usize * w + (x - HALF_PATCH) as usize;
        let bytes: &[u8; 32] = img[start..start + 32].try_into().expect("a full load");
        // SAFETY: `bytes`, `wk` and `wm` are 32 readable bytes each; the loads are unaligned.
        let (p, wk, wm) = unsafe {
            (
                _mm256_loadu_si256(bytes.as_ptr().cast()),
                _mm256_loadu_si256(wk.as_ptr().cast()),
                _mm256_loadu_si256(wm.as_ptr().cast()),
            )
        };
        // u8 x i8 pairs summed to i16 (at most 2 x 255 x 15), then pairs of those to i32.
        let moment = _mm256_madd_epi16(_mm256_maddubs_epi16(p, wk), ones);
        let sum = _mm256_madd_epi16(_mm256_maddubs_epi16(p, wm), ones);
        m10 = _mm256_add_epi32(m10, moment);
        m01 = _mm256_add_epi32(m01, _mm256_mullo_epi32(sum, _mm256_set1_epi32(v)));
    }
    let hsum = |s: __m256i| -> i64 {
        let mut lanes = [0i32; 8];
        // SAFETY: `lanes` is 32 writable bytes; the store is unaligned.
        unsafe { _mm256_storeu_si256(lanes.as_mut_ptr().cast(), s) };
        lanes.iter().map(|&l| l as i64).sum()
    };
    (hsum(m01), hsum(m10))
}

/// The pattern as four coordinate arrays (x1, y1, x2, y2), for loops the compiler vectorises.
fn pattern_soa(kind: PatternKind) -> &'static [[f32; 256]; 4] {
    type Soa = std::sync::OnceLock<[[f32; 256]; 4]>;
    static GAUSSIAN: Soa = Soa::new();
    static LEARNED: Soa = Soa::new();
    let cell = match kind {
        PatternKind::Gaussian => &GAUSSIAN,
        PatternKind::Learned => &LEARNED,
    };
    cell.get_or_init(|| {
        let p = pattern(kind);
        std::array::from_fn(|k| std::array::from_fn(|i| p[i][k]))
    })
}

/// Steered BRIEF: the 256 tests of [`pattern`] rotated by `angle` (upright when NaN), on the
/// smoothed level; bit `i` is set when the first point of pair `i` is darker than the second.
/// The rotated offsets are computed in one vectorised pass, the tests without branches.
pub fn describe(
    smooth: &[u8],
    w: usize,
    x: i32,
    y: i32,
    angle: f32,
    kind: PatternKind,
) -> [u64; 4] {
    let (s, c) = if angle.is_finite() {
        angle.sin_cos()
    } else {
        (0.0, 1.0)
    };
    let centre = y as isize * w as isize + x as isize;
    let [x1, y1, x2, y2] = pattern_soa(kind);
    // Round to nearest by the float trick: adding 1.5 * 2^23 pushes the fraction out, and the
    // low mantissa bits are then the integer (for |v| < 2^22; the pattern's are below 16). Pure
    // bit arithmetic, so the loop vectorises (a float-to-int `as` cast saturates and does not).
    let round = |v: f32| (v + 12_582_912.0).to_bits() as i32 - 0x4B40_0000;
    let wi = w as i32;
    let mut o1 = [0i32; 256];
    let mut o2 = [0i32; 256];
    for i in 0..256 {
        o1[i] = round(s * x1[i] + c * y1[i]) * wi + round(c * x1[i] - s * y1[i]);
        o2[i] = round(s * x2[i] + c * y2[i]) * wi + round(c * x2[i] - s * y2[i]);
    }
    // Every test point lies within PATTERN_RADIUS (15) of the centre, so each rotated and
    // rounded offset is within 15 rows and 15 columns: one check that the block of radius 16
    // fits serves all 512 loads (keypoints stay `edge_threshold` inside their level).
    let reach = 16 * w as isize + 16;
    if centre >= reach && centre + reach < smooth.len() as isize {
        // SAFETY: each index is centre + o with |o| <= 15 w + 15 < reach, inside `smooth`.
        tests(
            |o| unsafe { *smooth.get_unchecked((centre + o as isize) as usize) },
            &o1,
            &o2,
        )
    } else {
        tests(|o| smooth[(centre + o as isize) as usize], &o1, &o2)
    }
}

/// The 256 binary tests, point `o1[i]` darker than `o2[i]`, the pixels read by `at`.
#[inline(always)]
fn tests(at: impl Fn(i32) -> u8, o1: &[i32; 256], o2: &[i32; 256]) -> [u64; 4] {
    let mut d = [0u64; 4];
    for (word, out) in d.iter_mut().enumerate() {
        let mut bits = 0u64;
        for b in 0..64 {
            let i = word * 64 + b;
            bits |= ((at(o1[i]) < at(o2[i])) as u64) << b;
        }
        *out = bits;
    }
    d
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn harris_equals_the_per_tap_definition() {
        let (w, h) = (40usize, 30usize);
        let img = crate::noise_image(w * h, 4242);
        let at = |x: i32, y: i32| img[y as usize * w + x as usize] as i64;
        for (x, y) in [(4, 4), (20, 15), (35, 25), (11, 22)] {
            let (mut a, mut b, mut c) = (0i64, 0i64, 0i64);
            for v in y - 3..=y + 3 {
                for u in x - 3..=x + 3 {
                    let ix = (at(u + 1, v - 1) - at(u - 1, v - 1))
                        + 2 * (at(u + 1, v) - at(u - 1, v))
                        + (at(u + 1, v + 1) - at(u - 1, v + 1));
                    let iy = (at(u - 1, v + 1) - at(u - 1, v - 1))
                        + 2 * (at(u, v + 1) - at(u, v - 1))
                        + (at(u + 1, v + 1) - at(u + 1, v - 1));
                    a += ix * ix;
                    b += iy * iy;
                    c += ix * iy;
                }
            }
            let want = harris_response(a, b, c, 0.04);
            assert_eq!(
                harris(&img, w, x, y, 0.04).to_bits(),
                want.to_bits(),
                "({x}, {y})"
            );
        }
        // The largest sums fit: a checkerboard of 0 and 255.
        let board: Vec<u8> = (0..w * h)
            .map(|i| if (i % w + i / w) % 2 == 0 { 255 } else { 0 })
            .collect();
        assert!(harris(&board, w, 20, 15, 0.04).is_finite());
    }

    #[test]
    fn orientation_equals_the_pixel_by_pixel_moments() {
        let (w, h) = (70usize, 52usize);
        let img = crate::noise_image(w * h, 977);
        // Bright top-right, for moments far from zero, plus noise.
        let ramp: Vec<u8> = (0..w * h)
            .map(|i| ((i % w) * 2 + (h - i / w) * 2).min(255) as u8 / 2 + img[i] / 2)
            .collect();
        for im in [&img, &ramp] {
            // Every position the disc fits, the border ones included (they take the scalar path).
            for y in 15..h as i32 - 15 {
                for x in 15..w as i32 - 15 {
                    let (a, b) = (orientation(im, w, x, y), orientation_scalar(im, w, x, y));
                    assert_eq!(a.to_bits(), b.to_bits(), "({x}, {y})");
                }
            }
        }
        // Saturated pixels: the largest products fit.
        let white = vec![255u8; w * h];
        assert_eq!(
            orientation(&white, w, 30, 30),
            orientation_scalar(&white, w, 30, 30)
        );
    }

    #[test]
    fn rotated_tests_stay_within_the_block_describe_checks_once() {
        // describe reads without a per-load check when the block of radius 16 fits: every
        // rotated, rounded test point must lie within 15 rows and columns of the centre.
        let round = |v: f32| v.round() as i32;
        for kind in [PatternKind::Learned, PatternKind::Gaussian] {
            for step in 0..3600 {
                let (s, c) = (step as f32 * 0.1).to_radians().sin_cos();
                for t in pattern(kind).iter() {
                    for (x, y) in [(t[0], t[1]), (t[2], t[3])] {
                        let (dy, dx) = (round(s * x + c * y), round(c * x - s * y));
                        assert!(dx.abs() <= 15 && dy.abs() <= 15, "{kind:?} {step} {t:?}");
                    }
                }
            }
        }
        // Near the border the checked path gives the same descriptor as an interior copy.
        let (w, h) = (64usize, 64usize);
        let img = crate::noise_image(w * h, 5);
        let mut shifted = vec![0u8; w * h];
        for y in 0..h - 11 {
            shifted[y * w..y * w + w].copy_from_slice(&img[(y + 11) * w..(y + 11) * w + w]);
        }
        for angle in [0.0f32, 0.7, 2.9] {
            let inner = describe(&img, w, 32, 26, angle, PatternKind::Learned);
            // Row 15: the block of radius 16 does not fit above it.
            let near = describe(&shifted, w, 32, 15, angle, PatternKind::Learned);
            assert_eq!(inner, near);
        }
    }

    #[test]
    fn per_level_counts_sum_to_the_total_and_decrease() {
        let p = OrbParams::default();
        let n = p.per_level();
        assert_eq!(n.iter().sum::<usize>(), 1000);
        assert_eq!(n.len(), 8);
        for k in 1..7 {
            assert!(n[k] <= n[k - 1]);
        }
        // 1000 (1 - 1/1.2) / (1 - 1.2^-8) = 217.
        assert_eq!(n[0], 217);
    }

    #[test]
    fn levels_in_parallel_give_one_level_after_the_other() {
        // A textured image: blobs of every size, so that every level finds corners.
        let (w, h) = (320, 240);
        let mut state = 12345u32;
        let mut img = vec![0u8; w * h];
        for _ in 0..400 {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            let (cx, cy, r) = (
                state % w as u32,
                (state >> 9) % h as u32,
                2 + (state >> 20) % 14,
            );
            let v = (state >> 24) as u8;
            for y in cy.saturating_sub(r)..(cy + r).min(h as u32) {
                for x in cx.saturating_sub(r)..(cx + r).min(w as u32) {
                    img[y as usize * w + x as usize] = v;
                }
            }
        }
        let p = OrbParams {
            n_features: 500,
            ..Default::default()
        };
        let run = |threads: usize, scratch: &mut OrbScratch| {
            let pool = rayon::ThreadPoolBuilder::new()
                .num_threads(threads)
                .build()
                .unwrap();
            let (mut k, mut d) = (Vec::new(), Vec::new());
            pool.install(|| extract(&img, w, h, &p, scratch, &mut k, &mut d))
                .unwrap();
            (k, d)
        };
        let mut scratch = OrbScratch::default();
        let (k1, d1) = run(1, &mut scratch);
        // Level by level, each within its share, and every level finds some.
        let want = p.per_level();
        let octaves: Vec<i32> = k1.iter().map(|k| k.octave).collect();
        assert!(octaves.windows(2).all(|o| o[0] <= o[1]), "{octaves:?}");
        for (l, &n) in want.iter().enumerate() {
            let got = octaves.iter().filter(|&&o| o == l as i32).count();
            assert!(got > 0 && got <= n, "level {l}: {got} of {n}");
        }
        assert_eq!(k1.len(), d1.len());
        // The same with four threads, and again with the buffers of a larger image left over.
        let same = |(k, d): (Vec<Keypoint>, Vec<[u64; 4]>)| {
            let bits = |k: &[Keypoint]| {
                k.iter()
                    .map(|k| (k.x.to_bits(), k.y.to_bits(), k.angle.to_bits(), k.octave))
                    .collect::<Vec<_>>()
            };
            assert_eq!(bits(&k), bits(&k1));
            assert_eq!(d, d1);
        };
        same(run(4, &mut OrbScratch::default()));
        let big = vec![128u8; 640 * 480];
        let (mut k, mut d) = (Vec::new(), Vec::new());
        extract(&big, 640, 480, &p, &mut scratch, &mut k, &mut d).unwrap();
        same(run(4, &mut scratch));
    }

    #[test]
    fn pattern_is_deterministic_and_inside_the_radius() {
        let p = pattern(PatternKind::Gaussian);
        for t in p.iter() {
            for k in [0, 2] {
                assert!(t[k] * t[k] + t[k + 1] * t[k + 1] <= PATTERN_RADIUS * PATTERN_RADIUS);
            }
            assert!(t[0] != t[2] || t[1] != t[3]);
        }
        // Spread like a Gaussian of sigma 6.2 clipped at 13: the RMS radius is near 8.
        let rms = (p.iter().map(|t| t[0] * t[0] + t[1] * t[1]).sum::<f32>() / 256.0).sqrt();
        assert!((6.0..10.0).contains(&rms), "{rms}");
    }

    #[test]
    fn the_learned_tests_are_distinct_candidates_inside_the_radius() {
        let p = pattern(PatternKind::Learned);
        let r = PATTERN_RADIUS - 2.0;
        let mut seen = std::collections::HashSet::new();
        for t in p.iter() {
            for k in [0, 2] {
                assert!(t[k] * t[k] + t[k + 1] * t[k + 1] <= r * r, "{t:?}");
            }
            // Their 5x5 windows do not overlap, and no test is taken twice.
            assert!(
                (t[0] - t[2]).abs() >= 5.0 || (t[1] - t[3]).abs() >= 5.0,
                "{t:?}"
            );
            assert!(seen.insert(t.map(|v| v as i32)), "{t:?} twice");
        }
        assert_ne!(p, pattern(PatternKind::Gaussian));
    }

    #[test]
    fn orientation_points_to_the_bright_side() {
        let (w, h) = (41usize, 41usize);
        for (dx, dy, want) in [
            (1, 0, 0.0f32),
            (0, 1, std::f32::consts::FRAC_PI_2),
            (-1, 0, std::f32::consts::PI),
        ] {
            let img: Vec<u8> = (0..w * h)
                .map(|i| {
                    let (x, y) = ((i % w) as i32 - 20, (i / w) as i32 - 20);
                    (128 + 4 * (dx * x + dy * y)) as u8
                })
                .collect();
            let a = orientation(&img, w, 20, 20);
            let diff = (a - want).rem_euclid(std::f32::consts::TAU);
            assert!(
                diff.min(std::f32::consts::TAU - diff) < 1e-3,
                "{a} vs {want}"
            );
        }
    }
}
