//! ORB (Rublee, Rabaud, Konolige and Bradski, ICCV 2011): FAST-9 on a scale pyramid, Harris
//! ranking, an even spread over the image, intensity-centroid orientation and steered BRIEF.

use misslam_framework::Keypoint;
use rayon::prelude::*;

use crate::fast::{self, Corner, FastScratch};
use crate::learned_pattern::LEARNED;
use crate::measure::harris;
pub use crate::measure::{describe, orientation, orientation_scalar};
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

#[cfg(test)]
mod tests {
    use super::*;

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
}
