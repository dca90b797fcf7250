#![allow(clippy::unwrap_used)]
//! ORB on images related by known similarity transforms: keypoints are found again where the
//! transform puts them, and descriptor matches are mostly correct, through rotation and scale.

use misslam_features_matching::{match_descriptors, MatchParams, MatchScratch};
use misslam_features_orb::extract::{extract, Distribution, OrbParams, OrbScratch};
use misslam_framework::{Descriptors, Keypoint};

/// A texture of random rectangles and discs, sampled at any point (supersampled 4x4 so the
/// transformed renders are anti-aliased the same way).
struct Texture {
    shapes: Vec<(f32, f32, f32, f32, f32, bool)>,
    /// Shapes whose bounding box touches each 32-pixel cell of [-200, 1016)^2.
    cells: Vec<Vec<u32>>,
}

const CELL: f32 = 32.0;
const ORIGIN: f32 = -200.0;
const CELLS: usize = 38;

impl Texture {
    fn new(seed: u64) -> Self {
        let mut s = seed;
        let mut r = move || {
            s = s
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((s >> 33) as f32) / (1u64 << 31) as f32
        };
        let shapes = (0..700)
            .map(|_| {
                (
                    r() * 900.0 - 130.0,
                    r() * 700.0 - 110.0,
                    3.0 + r() * 14.0,
                    3.0 + r() * 14.0,
                    r() * 200.0 - 100.0,
                    r() < 0.5,
                )
            })
            .collect::<Vec<_>>();
        let mut cells = vec![Vec::new(); CELLS * CELLS];
        let cell_of = |v: f32| (((v - ORIGIN) / CELL).floor().max(0.0) as usize).min(CELLS - 1);
        for (i, &(cx, cy, a, b, _, _)) in shapes.iter().enumerate() {
            let e = a.max(b);
            for gy in cell_of(cy - e)..=cell_of(cy + e) {
                for gx in cell_of(cx - e)..=cell_of(cx + e) {
                    cells[gy * CELLS + gx].push(i as u32);
                }
            }
        }
        Texture { shapes, cells }
    }

    fn value(&self, x: f32, y: f32) -> f32 {
        let mut v = 128.0 + 20.0 * (0.05 * x).sin() * (0.07 * y).cos();
        let cell = |v: f32| ((v - ORIGIN) / CELL).floor();
        let (gx, gy) = (cell(x), cell(y));
        if gx < 0.0 || gy < 0.0 || gx >= CELLS as f32 || gy >= CELLS as f32 {
            return v.clamp(0.0, 255.0);
        }
        for &i in &self.cells[gy as usize * CELLS + gx as usize] {
            let (cx, cy, a, b, dv, disc) = self.shapes[i as usize];
            let (dx, dy) = (x - cx, y - cy);
            let inside = if disc {
                dx * dx + dy * dy <= a * a
            } else {
                dx.abs() <= a && dy.abs() <= b
            };
            if inside {
                v += dv * 0.5;
            }
        }
        v.clamp(0.0, 255.0)
    }

    /// Renders `w` x `h` pixels; pixel (u, v) shows texture point `map(u, v)`.
    fn render(&self, w: usize, h: usize, map: impl Fn(f32, f32) -> (f32, f32)) -> Vec<u8> {
        let mut out = vec![0u8; w * h];
        for v in 0..h {
            for u in 0..w {
                let mut acc = 0.0;
                for sy in 0..3 {
                    for sx in 0..3 {
                        let (x, y) = map(
                            u as f32 + (sx as f32 + 0.5) / 3.0 - 0.5,
                            v as f32 + (sy as f32 + 0.5) / 3.0 - 0.5,
                        );
                        acc += self.value(x, y);
                    }
                }
                out[v * w + u] = (acc / 9.0).round() as u8;
            }
        }
        out
    }
}

fn orb_with(
    img: &[u8],
    w: usize,
    h: usize,
    n: usize,
    distribution: Distribution,
) -> (Vec<Keypoint>, Vec<[u64; 4]>) {
    let p = OrbParams {
        n_features: n,
        distribution,
        ..OrbParams::default()
    };
    let (mut k, mut d) = (Vec::new(), Vec::new());
    extract(img, w, h, &p, &mut OrbScratch::default(), &mut k, &mut d).unwrap();
    (k, d)
}

fn orb(img: &[u8], w: usize, h: usize, n: usize) -> (Vec<Keypoint>, Vec<[u64; 4]>) {
    orb_with(img, w, h, n, Distribution::Quadtree)
}

/// Fraction of ratio-test matches that land within `tol` pixels of where `to_b` maps them, and
/// their count.
fn precision(
    a: &(Vec<Keypoint>, Vec<[u64; 4]>),
    b: &(Vec<Keypoint>, Vec<[u64; 4]>),
    to_b: impl Fn(f32, f32) -> (f32, f32),
    tol: f32,
) -> (f64, usize) {
    let m = match_descriptors(
        &Descriptors::Binary256(a.1.clone()),
        &Descriptors::Binary256(b.1.clone()),
        &MatchParams {
            ratio: 0.8,
            max_distance: 64.0,
            cross_check: true,
        },
        &mut MatchScratch::default(),
    )
    .unwrap();
    let good = m
        .iter()
        .filter(|m| {
            let ka = &a.0[m.query as usize];
            let kb = &b.0[m.train as usize];
            let (x, y) = to_b(ka.x, ka.y);
            (x - kb.x).hypot(y - kb.y) <= tol
        })
        .count();
    (good as f64 / m.len().max(1) as f64, m.len())
}

#[test]
fn keypoints_are_spread_and_inside_the_border() {
    let (w, h) = (640usize, 480usize);
    let t = Texture::new(1);
    let img = t.render(w, h, |u, v| (u, v));
    let (k, d) = orb(&img, w, h, 1000);
    assert_eq!(k.len(), d.len());
    assert!(k.len() >= 900, "{} keypoints", k.len());
    assert!(k.len() <= 1000);
    // Every quarter of the image has a fair share (quadtree spread).
    for (qx, qy) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
        let n = k
            .iter()
            .filter(|p| (p.x >= 320.0) as i32 == qx && (p.y >= 240.0) as i32 == qy)
            .count();
        assert!(n > k.len() / 8, "quarter ({qx}, {qy}) has {n}");
    }
    for p in &k {
        let s = 1.2f32.powi(p.octave);
        assert!(
            p.x >= 19.0 * s - 1.0 && p.x <= w as f32 - 19.0 * s + 1.0,
            "{p:?}"
        );
        assert!(p.angle.is_finite());
    }
    // Deterministic.
    let (k2, d2) = orb(&img, w, h, 1000);
    assert_eq!(k, k2);
    assert_eq!(d, d2);
}

#[test]
fn matches_survive_rotation_and_scale() {
    let (w, h) = (640usize, 480usize);
    let t = Texture::new(2);
    let a = t.render(w, h, |u, v| (u, v));
    let (cx, cy) = (320.0f32, 240.0f32);
    // Strongest corners only (as OpenCV's ORB keeps them; OpenCV scores 0.95 to 0.96 on these
    // pairs), and the quadtree spread ORB-SLAM uses, which trades some repeatability for
    // coverage (weaker corners in sparse cells).
    for (distribution, min_precision) in [(Distribution::None, 0.93), (Distribution::Quadtree, 0.8)]
    {
        let fa = orb_with(&a, w, h, 1000, distribution);
        for (deg, scale) in [
            (0.0f32, 1.0f32),
            (30.0, 1.0),
            (90.0, 1.0),
            (0.0, 1.3),
            (20.0, 1.2),
        ] {
            let (s, c) = deg.to_radians().sin_cos();
            // Image B shows the texture rotated by `deg` and magnified by `scale` about the
            // centre: pixel (u, v) of B shows the texture at R^-1 (p - centre) / scale + centre.
            let b = t.render(w, h, |u, v| {
                let (x, y) = ((u - cx) / scale, (v - cy) / scale);
                (c * x + s * y + cx, -s * x + c * y + cy)
            });
            let fb = orb_with(&b, w, h, 1000, distribution);
            let to_b = |x: f32, y: f32| {
                let (x, y) = (x - cx, y - cy);
                (scale * (c * x - s * y) + cx, scale * (s * x + c * y) + cy)
            };
            let (prec, n) = precision(&fa, &fb, to_b, 3.0 * scale);
            eprintln!("{distribution:?}: rotation {deg} deg, scale {scale}: {n} matches, precision {prec:.3}");
            assert!(n >= 150, "rotation {deg}, scale {scale}: only {n} matches");
            assert!(
                prec >= min_precision,
                "{distribution:?}, rotation {deg}, scale {scale}: precision {prec}"
            );
        }
    }
}
