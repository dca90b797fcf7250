#![allow(clippy::unwrap_used)]
//! `depth.elas` end to end: constructed pairs with a known disparity, a black frame, parameter
//! errors, the noise-free phantom against its GT, and the graph on real Hamlyn frames.

mod common;

use misslam_depth_elas::{elas, ElasParams};

/// Value noise: random values on a 3 px lattice, bilinearly interpolated, so the texture can
/// be sampled at any real position (a right image shifted by a fractional disparity).
struct Texture {
    w: usize,
    v: Vec<f32>,
}

impl Texture {
    fn new(w: usize, h: usize, seed: u64) -> Self {
        let (gw, gh) = (w / 3 + 3, h / 3 + 3);
        let mut s = seed;
        let v = (0..gw * gh)
            .map(|_| {
                s = s
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                ((s >> 33) % 200) as f32 + 20.0
            })
            .collect();
        Texture { w: gw, v }
    }

    fn at(&self, x: f32, y: f32) -> u8 {
        let (gx, gy) = (x / 3.0 + 1.0, y / 3.0 + 1.0);
        let (x0, y0) = (gx.floor() as usize, gy.floor() as usize);
        let (fx, fy) = (gx - x0 as f32, gy - y0 as f32);
        let g = |x: usize, y: usize| self.v[y * self.w + x];
        let top = g(x0, y0) * (1.0 - fx) + g(x0 + 1, y0) * fx;
        let bot = g(x0, y0 + 1) * (1.0 - fx) + g(x0 + 1, y0 + 1) * fx;
        (top * (1.0 - fy) + bot * fy).round() as u8
    }
}

/// A pair whose left pixel (x, y) has disparity `disp(x)`: right(x', y) = T(x', y) and
/// left(x, y) = T(x - disp(x), y).
fn pair(w: usize, h: usize, disp: impl Fn(f32) -> f32) -> (Vec<u8>, Vec<u8>) {
    let t = Texture::new(w + 64, h, 11);
    let right = (0..w * h)
        .map(|i| t.at((i % w) as f32 + 32.0, (i / w) as f32))
        .collect();
    let left = (0..w * h)
        .map(|i| {
            let x = (i % w) as f32;
            t.at(x - disp(x) + 32.0, (i / w) as f32)
        })
        .collect();
    (left, right)
}

fn params() -> ElasParams {
    ElasParams {
        disp_max: 48,
        ..ElasParams::robotics()
    }
}

#[test]
fn a_constant_shift_is_recovered_exactly() {
    let (w, h) = (160, 120);
    let (l, r) = pair(w, h, |_| 12.0);
    let out = elas(&l, &r, w, h, &params()).unwrap();
    // On one plane the redundancy removal keeps little more than the border of the grid.
    assert!(
        out.support.len() > 10,
        "{} support points",
        out.support.len()
    );
    // Left of u = 12 the true match lies outside the right image (an occluded band), and
    // below u = 17 the search stops short of 12 (libelas searches d <= u - 5): a point there
    // may take the edge of its range, as in libelas.
    let off: Vec<_> = out
        .support
        .iter()
        .filter(|s| s.u >= 17 && s.d != 12)
        .collect();
    assert!(off.is_empty(), "support points off 12: {off:?}");
    let inside: Vec<f32> = (10..h - 10)
        .flat_map(|y| (30..w - 10).map(move |x| (x, y)))
        .map(|(x, y)| out.left[y * w + x])
        .collect();
    let exact = inside.iter().filter(|&&d| d == 12.0).count();
    let wrong = inside
        .iter()
        .filter(|&&d| d.is_finite() && d != 12.0)
        .count();
    assert!(
        exact as f64 > 0.97 * inside.len() as f64,
        "{exact} of {} exact",
        inside.len()
    );
    assert_eq!(wrong, 0, "pixels with a wrong disparity");
    // The middlebury preset fills everything, with the same answer inside.
    let p = ElasParams {
        disp_max: 48,
        ..ElasParams::middlebury()
    };
    let out = elas(&l, &r, w, h, &p).unwrap();
    assert!(
        out.left.iter().all(|d| d.is_finite()),
        "middlebury left a hole"
    );
    let wrong = (10..h - 10)
        .flat_map(|y| (30..w - 10).map(move |x| y * w + x))
        .filter(|&i| out.left[i] != 12.0)
        .count();
    assert_eq!(wrong, 0);
}

#[test]
fn a_slanted_plane_is_followed_and_subpixel_sharpens_it() {
    let (w, h) = (200, 120);
    let disp = |x: f32| 8.0 + 0.06 * x;
    let (l, r) = pair(w, h, disp);
    let err = |subpixel: bool| {
        let p = ElasParams {
            subpixel,
            filter_adaptive_mean: false,
            ..params()
        };
        let out = elas(&l, &r, w, h, &p).unwrap();
        let mut e: Vec<f32> = (10..h - 10)
            .flat_map(|y| (40..w - 10).map(move |x| (x, y)))
            .filter_map(|(x, y)| {
                let d = out.left[y * w + x];
                d.is_finite().then(|| (d - disp(x as f32)).abs())
            })
            .collect();
        assert!(e.len() > 14_500, "{} of 15000 pixels valid", e.len());
        e.sort_by(f32::total_cmp);
        (
            e.iter().sum::<f32>() / e.len() as f32,
            e[e.len() * 99 / 100],
        )
    };
    let (mean_int, p99_int) = err(false);
    let (mean_sub, p99_sub) = err(true);
    eprintln!("integer: mean {mean_int:.3} px, p99 {p99_int:.3}; subpixel: mean {mean_sub:.3}, p99 {p99_sub:.3}");
    // Integer MAP disparities are within half a pixel (plus a little at plane boundaries).
    assert!(p99_int <= 1.0 && mean_int < 0.35, "{mean_int} {p99_int}");
    assert!(
        mean_sub < 0.6 * mean_int,
        "subpixel {mean_sub} vs integer {mean_int}"
    );
}

#[test]
fn a_black_frame_gives_no_disparity_and_no_error() {
    let (w, h) = (64, 48);
    let black = vec![0u8; w * h];
    let out = elas(&black, &black, w, h, &params()).unwrap();
    assert!(out.support.is_empty());
    assert!(out.left.iter().all(|d| d.is_nan()));
    // A size mismatch is an error, not a panic.
    assert!(elas(&black, &black[1..], w, h, &params()).is_err());
}

#[test]
fn bad_parameters_are_refused_naming_the_field() {
    for (set, field) in [
        ("depth.disp_max=5", "disp_max"),
        ("depth.support_threshold=1.5", "support_threshold"),
        ("depth.preset=\"kitti\"", "preset"),
        ("depth.sigma=0", "sigma"),
    ] {
        let e = match misslam::framework::graph::load(
            std::path::Path::new("graphs/depth_elas_phantom.toml"),
            &misslam::builtin_registry(),
            &[set.to_owned()],
        ) {
            Err(e) => e.to_string(),
            Ok(g) => match misslam::framework::Runtime::build(g) {
                Err(e) => e.to_string(),
                Ok(_) => panic!("{set} was accepted"),
            },
        };
        assert!(e.contains(field) && e.contains("depth"), "{set}: {e}");
    }
}

#[test]
fn elas_depth_on_the_noise_free_phantom_is_sub_half_millimetre() {
    let out = common::tmp_dir("elas_phantom");
    let sets = ["graph.frames.count=2", "src.noise_sigma=0"].map(String::from);
    let report = common::run_graph_file("graphs/depth_elas_phantom.toml", &sets, &out);
    let e = &report.metrics.eval;
    eprintln!(
        "ELAS raw: MAE {:.3} mm, density {:.1} %, valid-only bad-2 {:.3} %; post: MAE {:.3} mm",
        e["depth.mae_mm"], e["depth.density_pct"], e["depth.bad2_valid_pct"], e["post.mae_mm"]
    );
    // Measured 0.142 mm raw and 0.135 mm post-processed at 88 % density (3 frames).
    assert!(e["depth.mae_mm"] < 0.5, "{}", e["depth.mae_mm"]);
    assert!(e["post.mae_mm"] < 0.5, "{}", e["post.mae_mm"]);
    assert!(e["depth.density_pct"] > 80.0, "{}", e["depth.density_pct"]);
    assert!(
        e["depth.bad2_valid_pct"] < 0.5,
        "{}",
        e["depth.bad2_valid_pct"]
    );
    assert_eq!(e["depth.range_saturated_frames"], 0.0);
    // With 40 disparities the nearer tissue lies beyond the range: flagged on every frame.
    let sets = ["graph.frames.count=2", "depth.disp_max=40"].map(String::from);
    let report = common::run_graph_file(
        "graphs/depth_elas_phantom.toml",
        &sets,
        &common::tmp_dir("elas_range"),
    );
    let e = &report.metrics.eval;
    eprintln!(
        "ELAS, disp_max 40: MAE {:.2} mm, {} frames flagged",
        e["depth.mae_mm"], e["depth.range_saturated_frames"]
    );
    assert_eq!(e["depth.range_saturated_frames"], 2.0);
}

#[test]
fn depth_elas_graph_runs_on_hamlyn_frames() {
    let Some(dir) = common::data_set("hamlyn20") else {
        return;
    };
    let out = common::tmp_dir("elas_hamlyn");
    let sets = [
        format!("src.path={}", dir.display()),
        "graph.frames.count=2".to_owned(),
    ];
    let report = common::run_graph_file("graphs/depth_elas.toml", &sets, &out);
    assert_eq!(report.metrics.frames.processed, 2);
    let pfm = out.join("files/disparity/000000.pfm");
    let map = misslam::framework::pfm::read_pfm(&pfm).unwrap();
    let valid: Vec<f32> = map.data.iter().copied().filter(|d| d.is_finite()).collect();
    let density = valid.len() as f64 / map.data.len() as f64;
    eprintln!("Hamlyn frame 0: ELAS density {:.1} %", 100.0 * density);
    assert!(density > 0.3, "density {density}");
    assert!(valid.iter().all(|&d| (0.0..=64.5).contains(&d)));
}

#[test]
fn empty_and_tiny_images_are_errors_or_results_never_a_panic() {
    for (w, h) in [(0, 0), (0, 5), (5, 0), (1, 1), (3, 2), (16, 1), (1, 16)] {
        let img = vec![128u8; w * h];
        match elas(&img, &img, w, h, &params()) {
            Ok(out) => assert_eq!(out.left.len(), w * h, "{w}x{h}"),
            Err(e) => assert!(e.contains(&format!("{w}x{h}")), "{w}x{h}: {e}"),
        }
    }
}
