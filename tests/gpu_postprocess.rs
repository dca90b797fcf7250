//! `depth.postprocess` on the GPU (`device = "gpu"`) against its CPU path, on whatever adapter
//! exists: in CI, Mesa's software Vulkan (lavapipe); without one the tests say so and pass,
//! unless `MISSLAM_REQUIRE_GPU=1`.
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use common::gpu;
use misslam::framework::Image;
use std::sync::Arc;

/// `depth.postprocess` on the GPU against its CPU path: every mask, the filter and the maps, for
/// 1, 3 and 4 channels, with and without the pair's mask, smoothing and dilation, sizes that are
/// not multiples of the 8 x 8 workgroups. The masks and counts are exact; the values within
/// the tolerances below (a driver may fuse the filter's multiply-adds; the points multiply in
/// f32 where the CPU multiplies in f64).
#[test]
fn postprocess_kernels_match_the_cpu_path() {
    use misslam::framework::{Mask, StereoCalib, StereoFrame};
    use misslam_depth_postprocess::{clean, gpu::PostGpu, Params, Smoothing};
    let Some(ctx) = gpu() else { return };
    let mut kernels = PostGpu::new(&ctx);
    let base = Params::default();
    let variants: Vec<(&str, Params)> = vec![
        ("defaults", base.clone()),
        (
            // The tables' length unchanged, their values not: the kernels must get the new ones.
            "sigma 0.8 px and 0.6 mm, saturation 0.05",
            Params {
                smooth_sigma_px: 0.8,
                smooth_sigma_mm: 0.6,
                specular_max_saturation: 0.05,
                ..base.clone()
            },
        ),
        (
            "no smoothing",
            Params {
                smoothing: Smoothing::None,
                ..base.clone()
            },
        ),
        (
            "radius 5, no dilation, no step limit",
            Params {
                smooth_radius: 5,
                smooth_sigma_mm: 0.7,
                specular_dilate_px: 0,
                max_normal_step_mm: f32::INFINITY,
                ..base.clone()
            },
        ),
        (
            "no masks, dilation 9",
            Params {
                mask_border: false,
                specular_dilate_px: 9,
                min_depth_mm: 55.0,
                max_depth_mm: 70.0,
                ..base.clone()
            },
        ),
        (
            "border only, saturation 0.05",
            Params {
                mask_specular: false,
                specular_max_saturation: 0.05,
                black_level: 6,
                ..base.clone()
            },
        ),
    ];
    let mut worst = [0.0f64; 3];
    for (w, h) in [(5usize, 4usize), (67, 45), (640, 480)] {
        let calib = StereoCalib {
            width: w as u32,
            height: h as u32,
            fx: 500.0,
            fy: 510.0,
            cx: w as f64 / 2.0 - 0.3,
            cy: h as f64 / 2.0 + 0.7,
            cx_right: w as f64 / 2.0,
            baseline_mm: 5.0,
        };
        for c in [1usize, 3, 4] {
            let (depth, img) = misslam::bench::post_scene(w, h, c, (w * 131 + h * 7 + c) as u64);
            // Built field by field: `Image::new` takes 1 or 3 channels, a plugin may send 4.
            let image = |data: Vec<u8>| Image {
                width: w as u32,
                height: h as u32,
                channels: c as u8,
                data,
            };
            let mut mask = vec![255u8; w * h];
            mask[w * (h / 3)..w * (h / 3 + 1)].fill(0);
            for with_mask in [false, true] {
                let pair = StereoFrame {
                    index: 0,
                    timestamp: 0.0,
                    left: Arc::new(image(img.clone())),
                    right: Arc::new(image(img.clone())),
                    calib,
                    left_mask: with_mask.then(|| Mask {
                        width: w as u32,
                        height: h as u32,
                        data: mask.clone(),
                    }),
                    right_mask: None,
                };
                for (name, p) in &variants {
                    for pair in [Some(&pair), None] {
                        if pair.is_none() && (with_mask || c != 3) {
                            continue;
                        }
                        let case = format!(
                            "{w}x{h}, {c} channels, mask {with_mask}, pair {}, {name}",
                            pair.is_some()
                        );
                        let cpu = clean(depth.clone(), &calib, pair, p).unwrap();
                        let (got, _) = kernels
                            .clean_into(
                                &ctx,
                                depth.clone(),
                                &calib,
                                pair,
                                p,
                                (Vec::new(), Vec::new()),
                            )
                            .unwrap_or_else(|e| panic!("{case}: {e}"));
                        assert_eq!(
                            (got.out_of_range, got.border, got.specular),
                            (cpu.out_of_range, cpu.border, cpu.specular),
                            "{case}: counts (out of range, border, specular)"
                        );
                        assert_eq!(got.depth.len(), w * h);
                        let smoothed = p.smoothing == Smoothing::Bilateral;
                        let mut depth_exact = true;
                        for i in 0..w * h {
                            let (a, b) = (got.depth[i], cpu.depth[i]);
                            assert_eq!(a.is_nan(), b.is_nan(), "{case}: depth validity at {i}");
                            if b.is_nan() {
                                continue;
                            }
                            depth_exact &= a.to_bits() == b.to_bits();
                            if smoothed {
                                // A few roundings of sums of at most 121 taps (lavapipe: none).
                                let e = f64::from((a - b).abs()) / f64::from(b);
                                worst[0] = worst[0].max(e);
                                assert!(e <= 2e-6, "{case}: depth {a} against {b} at {i}");
                            } else {
                                assert_eq!(a.to_bits(), b.to_bits(), "{case}: depth at {i}");
                            }
                            for k in 0..3 {
                                let (a, b) = (got.vertices[i][k], cpu.vertices[i][k]);
                                // Two f32 roundings (the table's, the product's) against one of
                                // an f64 product, on top of the depth's own difference.
                                let e = f64::from((a - b).abs()) / f64::from(cpu.depth[i]);
                                worst[1] = worst[1].max(e);
                                assert!(e <= 4e-6, "{case}: point {k} {a} against {b} at {i}");
                            }
                        }
                        let step = |i: usize| {
                            // The CPU's largest depth step to a 4-neighbour at pixel i.
                            let z = cpu.vertices[i][2];
                            [i - 1, i + 1, i - w, i + w]
                                .iter()
                                .map(|&j| (cpu.vertices[j][2] - z).abs())
                                .fold(0.0f32, f32::max)
                        };
                        for i in 0..w * h {
                            let (a, b) = (got.normals[i], cpu.normals[i]);
                            if a[0].is_nan() != b[0].is_nan() {
                                // Only where a step lies on the limit within the depth's
                                // tolerance can one side keep a normal the other drops.
                                let s = step(i);
                                assert!(
                                    (s - p.max_normal_step_mm).abs() <= 1e-3,
                                    "{case}: normal validity at {i} ({a:?} against {b:?}, step {s})"
                                );
                                continue;
                            }
                            if b[0].is_nan() {
                                continue;
                            }
                            let e = (0..3)
                                .map(|k| f64::from((a[k] - b[k]).abs()))
                                .fold(0.0, f64::max);
                            worst[2] = worst[2].max(e);
                            // From points an f32 rounding apart, across the noise's steps (lavapipe:
                            // 2.8e-5); from depth a few roundings apart, more.
                            let tol = if depth_exact { 1e-4 } else { 2e-3 };
                            assert!(e <= tol, "{case}: normal {a:?} against {b:?} at {i}");
                        }
                    }
                }
            }
        }
    }
    println!(
        "worst differences: depth {:.2e} (relative), points {:.2e} (of depth), normals {:.2e}",
        worst[0], worst[1], worst[2]
    );
}

/// `depth.postprocess` with `device = "gpu"` in the main graph (`graphs/mis_slam.toml`, one line
/// changed): the model fused from its maps scores as on the CPU, and the node reports the GPU's
/// stages.
#[test]
fn depth_postprocess_on_the_gpu_runs_the_main_graph_as_on_the_cpu() {
    if gpu().is_none() {
        return;
    }
    let mut runs = Vec::new();
    for device in ["cpu", "gpu"] {
        let sets: Vec<String> = [
            "src.width=160",
            "src.height=120",
            "src.focal_px=175.0",
            "depth.max_disparity=24",
            "graph.frames.count=4",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([format!("post.device=\"{device}\"")])
        .collect();
        let report = common::run_graph_file(
            "graphs/mis_slam.toml",
            &sets,
            &common::tmp_dir(&format!("post-main-{device}")),
        );
        assert!(report.error.is_none(), "{device}: {:?}", report.error);
        let eval = report.metrics.eval.clone();
        let timing = &report.metrics.timing_ms;
        let stages: Vec<&String> = timing.keys().filter(|k| k.starts_with("post.")).collect();
        println!(
            "{device}: recon {:.6} mm, tracking ATE {:.6} mm; stages {stages:?}",
            eval["recon.mean_mm"], eval["tracking.ate_mm"]
        );
        let want = if device == "gpu" {
            ["post.upload", "post.gpu", "post.readback"]
        } else {
            ["post.masks", "post.smooth", "post.maps"]
        };
        assert!(
            want.iter().all(|k| timing.contains_key(*k)),
            "{device}: {stages:?}"
        );
        runs.push(eval);
    }
    let (c, g) = (runs[0]["recon.mean_mm"], runs[1]["recon.mean_mm"]);
    assert!(
        c.is_finite() && (c - g).abs() <= 1e-3,
        "recon.mean_mm: CPU {c}, GPU {g}"
    );
}

#[test]
fn bench_post_gpu_reports_parity_stages_and_cpu_time() {
    if gpu().is_none() {
        return;
    }
    let r = misslam::bench::post_gpu(67, 45, 2).unwrap();
    assert_eq!((r.width, r.height, r.runs), (67, 45, 2));
    assert!(r.masks_equal, "{r:?}");
    assert!(
        r.max_depth_diff_mm <= 1e-3 && r.max_point_diff_mm <= 1e-3 && r.max_normal_diff <= 1e-2,
        "{r:?}"
    );
    assert!(
        r.cpu_ms > 0.0 && r.gpu_ms > 0.0 && r.gpu_kernels_ms > 0.0 && r.gpu_readback_ms >= 0.0,
        "{r:?}"
    );
    // Both paths use some CPU (where the platform says: NaN elsewhere).
    assert!(
        r.cpu_cpu_ms.is_nan() || (r.cpu_cpu_ms > 0.0 && r.gpu_cpu_ms > 0.0),
        "{r:?}"
    );
    assert!(misslam::bench::post_gpu(2, 45, 1)
        .unwrap_err()
        .contains("--width"));
}

/// A map too large for the adapter's buffers is refused with a message that names the size and
/// the way out (where the adapter's limits make such a map small enough to allocate here).
#[test]
fn postprocess_on_the_gpu_refuses_a_map_beyond_the_buffer_limits() {
    use misslam::framework::StereoCalib;
    use misslam_depth_postprocess::{gpu::PostGpu, Params};
    let Some(ctx) = gpu() else { return };
    let binding = ctx.device.limits().max_storage_buffer_binding_size;
    if binding > 256 << 20 {
        println!("skipped: this adapter binds {binding} bytes, a map past it is too large to allocate here");
        return;
    }
    let w = 4096usize;
    let h = (binding as usize / 12 + 1).div_ceil(w);
    let calib = StereoCalib {
        width: w as u32,
        height: h as u32,
        fx: 500.0,
        fy: 500.0,
        cx: w as f64 / 2.0,
        cy: h as f64 / 2.0,
        cx_right: w as f64 / 2.0,
        baseline_mm: 5.0,
    };
    let err = PostGpu::new(&ctx)
        .clean_into(
            &ctx,
            vec![60.0; w * h],
            &calib,
            None,
            &Params::default(),
            Default::default(),
        )
        .map(|_| ())
        .expect_err("refused");
    assert!(
        err.contains(&format!("{w}x{h}")) && err.contains("device = \"cpu\""),
        "{err}"
    );
}
