//! GPU code on whatever adapter exists: in CI, Mesa's software Vulkan (lavapipe). Where no
//! adapter exists the tests say so and pass, unless `MISSLAM_REQUIRE_GPU=1` (CI sets it, so a
//! missing driver fails CI instead of hiding).
#![allow(clippy::unwrap_used)] // test code: a failed unwrap is the test failing

mod common;

use std::sync::Arc;

use misslam::framework::gpu::{GpuProvider, GrayKernel};
use misslam::framework::{luma_bt601, Device, Image};

use common::gpu;

/// Deterministic pseudo-random bytes, so the test is seeded.
fn bytes(n: usize, seed: u64) -> Vec<u8> {
    misslam::bench::SeededBytes::new(seed).bytes(n)
}

#[test]
fn gray_kernel_is_bit_exact_with_the_cpu_reference() {
    let Some(ctx) = gpu() else { return };
    println!(
        "adapter: {} ({:?})",
        ctx.adapter_info.name, ctx.adapter_info.device_type
    );
    let kernel = GrayKernel::new(&ctx);
    // Sizes that are not multiples of 4 pixels or of the workgroup exercise the tails.
    for (w, h) in [(1, 1), (3, 1), (7, 5), (640, 480), (721, 289)] {
        let rgb = bytes(w * h * 3, (w * 31 + h) as u64);
        let got = kernel.run(&ctx, &rgb).expect("kernel ran");
        let want: Vec<u8> = rgb
            .chunks_exact(3)
            .map(|p| luma_bt601(p[0], p[1], p[2]))
            .collect();
        assert_eq!(got.len(), want.len());
        let diff = got.iter().zip(&want).filter(|(a, b)| a != b).count();
        assert_eq!(
            diff, 0,
            "{w}x{h}: {diff} pixels differ (tolerance: bit-exact, integer arithmetic)"
        );
    }
    assert!(
        kernel.run(&ctx, &[1, 2]).is_err(),
        "a partial pixel is an error"
    );
}

#[test]
fn one_device_is_shared_and_auto_falls_back() {
    let provider = GpuProvider::new();
    assert!(
        provider.for_device(Device::Cpu, "n").unwrap().is_none(),
        "cpu never opens a device"
    );
    assert!(!provider.is_open());
    let Some(_) = gpu() else {
        // Without an adapter: `auto` falls back to the CPU, `gpu` is a clear error.
        assert!(provider.for_device(Device::Auto, "n").unwrap().is_none());
        let e = provider
            .for_device(Device::Gpu, "n")
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("mesa-vulkan-drivers"), "{e}");
        return;
    };
    let a = provider.for_device(Device::Gpu, "a").unwrap().unwrap();
    let b = provider.for_device(Device::Auto, "b").unwrap().unwrap();
    assert!(Arc::ptr_eq(&a, &b), "every node gets the same device");
}

#[test]
fn gray_node_on_gpu_matches_cpu_node() {
    let Some(_) = gpu() else { return };
    let provider = GpuProvider::new();
    let build = |device| {
        let ctx = misslam::framework::BuildContext {
            node_id: "gray",
            graph_dir: std::path::Path::new("."),
            seed: 0,
            gpu: &provider,
        };
        misslam_image_gray::build(misslam_image_gray::Params { device }, &ctx).expect("built")
    };
    let img = Arc::new(Image::new(33, 17, 3, bytes(33 * 17 * 3, 9)).unwrap());
    let cpu = build(Device::Cpu).convert(&img).unwrap();
    let gpu = build(Device::Gpu).convert(&img).unwrap();
    assert_eq!(cpu.data, gpu.data);
    assert_eq!((gpu.width, gpu.height, gpu.channels), (33, 17, 1));
}

/// Right image of a random-dot scene: a slanted background and a nearer square (occlusions).
/// `p` with the directions' costs summed into one volume.
fn summed_params(p: &misslam_depth_sgm::sgm::SgmParams) -> misslam_depth_sgm::sgm::SgmParams {
    misslam_depth_sgm::sgm::SgmParams {
        gpu_volumes: misslam_depth_sgm::sgm::GpuVolumes::Summed,
        ..*p
    }
}

fn stereo_scene(w: usize, h: usize, seed: u64) -> (Vec<u8>, Vec<u8>) {
    let left = bytes(w * h, seed);
    let fill = bytes(w * h, seed + 1);
    let disp = |x: usize, y: usize| {
        if (w / 3..w / 2).contains(&x) && (h / 4..h / 2).contains(&y) {
            14
        } else {
            3 + (x + 2 * y) / 25
        }
    };
    let right = misslam_depth_sgm::synthetic::right_view(&left, w, h, disp, fill);
    (left, right)
}

/// The kernels keep their parameters across pairs and write them again only when they change: a
/// run with other penalties, uniqueness and speckle settings on the same buffers gives what
/// fresh kernels give, and the CPU's output.
#[test]
fn sgm_kernels_take_changed_parameters_on_the_same_buffers() {
    use misslam_depth_sgm::gpu::SgmGpu;
    use misslam_depth_sgm::sgm::{sgm, Scratch, SgmParams};
    let Some(ctx) = gpu() else { return };
    let (w, h) = (97, 41);
    let (left, right) = stereo_scene(w, h, 5);
    let first = SgmParams::default();
    let second = SgmParams {
        p1: 6,
        p2: 60,
        uniqueness_pct: 5,
        speckle_window: 20,
        lr_max_diff: 2.0,
        ..first
    };
    let mut reused = SgmGpu::new(&ctx);
    let (a, _) = reused.run(&ctx, &left, &right, w, h, None, &first).unwrap();
    let (b, _) = reused
        .run(&ctx, &left, &right, w, h, None, &second)
        .unwrap();
    let (fresh, _) = SgmGpu::new(&ctx)
        .run(&ctx, &left, &right, w, h, None, &second)
        .unwrap();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_ne!(bits(&a), bits(&b), "the parameters change the output");
    assert_eq!(
        bits(&b),
        bits(&fresh),
        "the second run used the first's parameters"
    );
    let want = sgm(&left, &right, w, h, None, &second, &mut Scratch::default()).unwrap();
    let (validity, max_diff) = misslam::bench::disparity_parity(&b, &want);
    assert!(
        validity * 1000 <= w * h && max_diff <= 1e-4,
        "{validity} {max_diff}"
    );
}

/// Pairs submitted two at a time (the next uploaded and submitted before the one before is read)
/// come back in order, each as `run` gives it alone; a third submission, a collection with
/// none in flight, `run` with a pair in flight and a pair of another size while one is in
/// flight are errors that say what to do, and the kernels still run after them.
#[test]
fn sgm_pairs_in_flight_come_back_in_order_as_run_gives_them() {
    let Some(ctx) = gpu() else { return };
    // Both layouts: with the directions' costs summed, each pair starts from the sums the pair
    // before left cleared.
    let p = misslam_depth_sgm::sgm::SgmParams::default();
    for p in [p, summed_params(&p)] {
        pairs_in_flight(&ctx, &p);
    }
    // The host polling for each map before it blocks (on a discrete GPU by default), and
    // blocking at once: the same maps.
    use misslam_depth_sgm::sgm::GpuWait;
    let waits = [GpuWait::Spin, GpuWait::Block].map(|gpu_wait| {
        let q = misslam_depth_sgm::sgm::SgmParams { gpu_wait, ..p };
        pairs_in_flight(&ctx, &q)
    });
    assert!(
        waits[0] == waits[1],
        "spinning and blocking gave other maps"
    );
}

/// Five pairs submitted two at a time, each identical to its run alone; returns the maps' bits.
fn pairs_in_flight(
    ctx: &misslam::framework::GpuContext,
    p: &misslam_depth_sgm::sgm::SgmParams,
) -> Vec<Vec<u32>> {
    use misslam_depth_sgm::gpu::{SgmGpu, IN_FLIGHT};
    let (w, h) = (97, 41);
    let pairs: Vec<_> = (0..5).map(|k| stereo_scene(w, h, 11 + 3 * k)).collect();
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    let alone: Vec<_> = pairs
        .iter()
        .map(|(l, r)| bits(&SgmGpu::new(ctx).run(ctx, l, r, w, h, None, p).unwrap().0))
        .collect();
    for (k, a) in alone.iter().enumerate().skip(1) {
        assert_ne!(a, &alone[0], "pair {k} differs from pair 0");
    }
    let mut k = SgmGpu::new(ctx);
    let err = k.collect(ctx).unwrap_err();
    assert!(err.contains("no GPU SGM pair in flight"), "{err}");
    let mut got = Vec::new();
    let mut next = 0;
    while got.len() < pairs.len() {
        while next < pairs.len() && k.in_flight() < IN_FLIGHT {
            let (l, r) = &pairs[next];
            k.submit(ctx, l, r, w, h, None, p).unwrap();
            next += 1;
        }
        if next < pairs.len() {
            let (l, r) = &pairs[next];
            let err = k.submit(ctx, l, r, w, h, None, p).unwrap_err();
            assert!(err.contains("collect one first"), "{err}");
            let err = k.run(ctx, l, r, w, h, None, p).unwrap_err();
            assert!(err.contains("collect them before"), "{err}");
        }
        got.push(bits(&k.collect(ctx).unwrap().0));
    }
    assert_eq!(k.in_flight(), 0);
    for (n, (g, a)) in got.iter().zip(&alone).enumerate() {
        assert!(g == a, "pair {n} in flight differs from its run alone");
    }
    let (l, r) = &pairs[0];
    k.submit(ctx, l, r, w, h, None, p).unwrap();
    let (l2, r2) = stereo_scene(w + 8, h, 2);
    let err = k.submit(ctx, &l2, &r2, w + 8, h, None, p).unwrap_err();
    assert!(err.contains("collect it first"), "{err}");
    assert_eq!(bits(&k.collect(ctx).unwrap().0), alone[0]);
    assert_eq!(bits(&k.run(ctx, l, r, w, h, None, p).unwrap().0), alone[0]);
    alone
}

#[test]
fn sgm_kernels_match_the_cpu_path() {
    use misslam_depth_sgm::gpu::{Breakdown, SgmGpu};
    use misslam_depth_sgm::sgm::{sgm, GpuExchange, GpuVolumes, Scratch, SgmParams};
    let Some(ctx) = gpu() else { return };
    let mut kernels = SgmGpu::new(&ctx);
    let cases = [
        ("default (8 paths, census 9x7, 64 d)", SgmParams::default()),
        (
            "32 d, 8 paths (a path in 8 subgroup lanes)",
            SgmParams {
                max_disparity: 32,
                ..SgmParams::default()
            },
        ),
        (
            "4 paths, adaptive P2, d from -3, 20 d, no sub-pixel, census 21x3 (the widest)",
            SgmParams {
                paths: 4,
                census_width: 21,
                census_height: 3,
                p2_adaptive: true,
                p2: 300,
                min_disparity: -3,
                max_disparity: 20,
                subpixel: false,
                uniqueness_pct: 15,
                ..SgmParams::default()
            },
        ),
        (
            "d from 4, 33 d, census 7x9, no LR / median / speckles",
            SgmParams {
                min_disparity: 4,
                max_disparity: 33,
                census_width: 7,
                census_height: 9,
                lr_check: false,
                median: false,
                speckle_window: 0,
                ..SgmParams::default()
            },
        ),
    ];
    // Wide disparity ranges: one path per workgroup (36 and 64 invocations), u8 and u16 costs.
    let wide = [
        (
            "150 d from -5, 4 paths, P2 200 (u16 costs)",
            SgmParams {
                max_disparity: 150,
                min_disparity: -5,
                paths: 4,
                p2: 200,
                ..SgmParams::default()
            },
        ),
        (
            "256 d, 8 paths",
            SgmParams {
                max_disparity: 256,
                ..SgmParams::default()
            },
        ),
    ];
    let mut subgroup_runs = 0;
    for (w, h, cases) in [
        (83, 37, &cases[..]),
        (161, 120, &cases[..]),
        (301, 40, &wide[..]),
    ] {
        let (left, right) = stereo_scene(w, h, (w * 7 + h) as u64);
        let mut mask = vec![1u8; w * h];
        mask[..2 * w].fill(0);
        for (i, (name, p)) in cases.iter().enumerate() {
            let m = (i == 1).then_some(mask.as_slice());
            let want = sgm(&left, &right, w, h, m, p, &mut Scratch::default()).unwrap();
            let (got, timing) = kernels.run(&ctx, &left, &right, w, h, m, p).unwrap();
            let valid = want.iter().filter(|v| v.is_finite()).count();
            assert!(
                valid > w * h / 3,
                "{name}: the CPU output is dense enough to compare ({valid})"
            );
            let (validity, max_diff) = misslam::bench::disparity_parity(&got, &want);
            println!(
                "{w}x{h} {name}: {validity} pixels differ in validity, max |diff| {max_diff:.2e} px over {valid} valid; GPU {:.1} ms ({timing:?})",
                timing.total_ms
            );
            // Stated tolerance: the integers are the same; only the parabola's f32 division may
            // round differently in WGSL (2.5 ulp), which can move a pixel across the LR or
            // median thresholds: at most 0.1 % of pixels, and 1e-4 px.
            assert!(
                validity * 1000 <= w * h,
                "{name}: {validity} of {} pixels differ in validity",
                w * h
            );
            assert!(max_diff <= 1e-4, "{name}: max |diff| {max_diff} px");
            // The directions' costs summed into one volume (atomic adds) and a volume per
            // direction give the same output ("auto" took one of them).
            let same = |a: &[f32]| {
                a.iter()
                    .zip(&got)
                    .all(|(a, b)| a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan()))
            };
            let mut t = timing;
            for summed in [false, true] {
                let q = SgmParams {
                    gpu_volumes: if summed {
                        GpuVolumes::Summed
                    } else {
                        GpuVolumes::PerDirection
                    },
                    ..*p
                };
                let (got_layout, tl) = kernels.run(&ctx, &left, &right, w, h, m, &q).unwrap();
                assert_eq!(tl.summed_volumes, summed, "{name}");
                assert!(
                    same(&got_layout),
                    "{name}: the layout (summed {summed}) changes the output"
                );
                t = tl;
            }
            // The sums by 32-bit atomics give the same output as by 64-bit ones, where the
            // adapter has those (lavapipe does).
            kernels.set_int64_atomics(false);
            let (got32, t32) = kernels
                .run(&ctx, &left, &right, w, h, m, &summed_params(p))
                .unwrap();
            kernels.set_int64_atomics(true);
            let (got64, t64) = kernels
                .run(&ctx, &left, &right, w, h, m, &summed_params(p))
                .unwrap();
            assert!(
                !t32.atomics64 && t64.atomics64 == ctx.has_int64_atomics(),
                "{name}"
            );
            assert!(
                same(&got32) && same(&got64),
                "{name}: 32- and 64-bit sums differ"
            );
            // Timing the stages (a pass per stage, timestamps or each stage waited for) changes
            // nothing but the timing; untimed runs report no stages.
            assert_eq!(timing.aggregate_ms, 0.0, "{name}: untimed");
            for breakdown in [Breakdown::Timestamps, Breakdown::Staged] {
                kernels.set_breakdown(breakdown);
                let (got_timed, tt) = kernels.run(&ctx, &left, &right, w, h, m, p).unwrap();
                kernels.set_breakdown(Breakdown::Off);
                assert!(same(&got_timed), "{name}: {breakdown:?} changes the output");
                assert!(
                    tt.aggregate_ms > 0.0 && tt.select_ms > 0.0,
                    "{name}: {breakdown:?} {tt:?}"
                );
            }
            // The exchange through workgroup memory gives the same output as the subgroup one
            // the adapter's subgroups allow ("auto"), in both layouts.
            subgroup_runs += usize::from(timing.subgroups) + usize::from(t.subgroups);
            for volumes in [GpuVolumes::PerDirection, GpuVolumes::Summed] {
                let q = SgmParams {
                    gpu_exchange: GpuExchange::Workgroup,
                    gpu_volumes: volumes,
                    ..*p
                };
                let (got_wg, t) = kernels.run(&ctx, &left, &right, w, h, m, &q).unwrap();
                assert!(!t.subgroups, "{name}");
                assert!(
                    same(&got_wg),
                    "{name}: the workgroup exchange differs from the subgroup one ({volumes:?})"
                );
            }
            if p.speckle_window > 0 {
                // The speckle kernels had work to do: without them the output differs.
                let q = SgmParams {
                    speckle_window: 0,
                    ..*p
                };
                let (kept, _) = kernels.run(&ctx, &left, &right, w, h, m, &q).unwrap();
                let removed = kept
                    .iter()
                    .zip(&got)
                    .filter(|(a, b)| a.is_finite() && !b.is_finite())
                    .count();
                assert!(removed > 0, "{name}: no speckle was removed");
            }
        }
    }
    // Where the adapter has subgroups of one size (lavapipe: 8 on AVX2 machines, NVIDIA: 32),
    // the cases whose paths fit one ran the subgroup kernel.
    let sub = ctx.subgroup_size();
    println!("subgroups: {sub:?}; {subgroup_runs} runs with the subgroup exchange");
    if sub.is_some_and(|s| s >= 8) {
        assert!(subgroup_runs >= 2, "the subgroup kernel never ran");
    }
    // Beyond the kernel's disparity limit: a clear error.
    let p = SgmParams {
        max_disparity: 1024 + 1,
        ..SgmParams::default()
    };
    let (l, r) = stereo_scene(40, 30, 1);
    assert!(kernels.run(&ctx, &l, &r, 40, 30, None, &p).is_err());
}

#[test]
fn sgm_at_the_h100_target_size_runs_on_this_adapter() {
    // Issue 4's GPU configuration, 640x480 with 128 disparities over 8 paths, whose volumes of L
    // per direction (315 MB) exceed the storage buffers of Mesa's lavapipe (128 MiB): there the
    // costs are summed into one volume (79 MB), as on a discrete GPU, where that is the faster
    // layout. Either way the output is the CPU path's.
    use misslam_depth_sgm::gpu::SgmGpu;
    use misslam_depth_sgm::sgm::{sgm, Scratch, SgmParams};
    let Some(ctx) = gpu() else { return };
    let (w, h) = (640, 480);
    let p = SgmParams {
        max_disparity: 128,
        ..SgmParams::default()
    };
    let (left, right) = stereo_scene(w, h, 5);
    let want = sgm(&left, &right, w, h, None, &p, &mut Scratch::default()).unwrap();
    let (got, timing) = SgmGpu::new(&ctx)
        .run(&ctx, &left, &right, w, h, None, &p)
        .unwrap();
    let limits = ctx.device.limits();
    let per_direction = (w * h * 128 * 8) as u64;
    let discrete = ctx.is_discrete();
    assert_eq!(
        timing.summed_volumes,
        discrete
            || per_direction
                > limits
                    .max_storage_buffer_binding_size
                    .min(limits.max_buffer_size),
        "summed exactly on a discrete GPU or where a volume per direction does not fit"
    );
    let (validity, max_diff) = misslam::bench::disparity_parity(&got, &want);
    println!(
        "640x480x128, 8 paths: {validity} pixels differ in validity, max |diff| {max_diff:.2e} px; summed {}; GPU {:.0} ms",
        timing.summed_volumes, timing.total_ms
    );
    assert!(
        validity * 1000 <= w * h,
        "{validity} pixels differ in validity"
    );
    assert!(max_diff <= 1e-4, "max |diff| {max_diff} px");
}

#[test]
fn depth_sgm_on_the_gpu_scores_as_on_the_cpu() {
    // graphs/depth_sgm_phantom.toml with one line changed (`depth.device`), scored against the
    // phantom's exact depth: the same disparities, so the same figures (within the parabola's
    // rounding).
    if gpu().is_none() {
        return;
    }
    let mut scores = Vec::new();
    // A forced subgroup exchange that the adapter cannot give (a path of 256 disparities takes
    // 64 lanes: more than lavapipe's 8 or an NVIDIA GPU's 32) is refused when the graph is
    // built, naming the parameter.
    let sets = [
        "graph.frames.count=1",
        "depth.device=\"gpu\"",
        "depth.max_disparity=256",
        "depth.gpu_exchange=\"subgroup\"",
    ]
    .map(String::from);
    let g = misslam::framework::graph::load(
        std::path::Path::new("graphs/depth_sgm_phantom.toml"),
        &misslam::builtin_registry(),
        &sets,
    )
    .expect("a valid graph");
    let err = misslam::framework::Runtime::build(g)
        .err()
        .expect("the node is refused when built")
        .to_string();
    assert!(
        err.contains("gpu_exchange") && (err.contains("64 lanes") || err.contains("no subgroups")),
        "{err}"
    );
    // The GPU twice: a volume of costs per direction, and the costs summed into one.
    // The host's wait for the map through the graph too (`gpu_wait`; the output is the same).
    for (device, volumes, wait) in [
        ("cpu", "auto", "auto"),
        ("gpu", "per_direction", "block"),
        ("gpu", "summed", "spin"),
    ] {
        let sets: Vec<String> = [
            "src.width=160",
            "src.height=120",
            "src.focal_px=175.0",
            "depth.max_disparity=24",
            "graph.frames.count=1",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([
            format!("depth.device=\"{device}\""),
            format!("depth.gpu_volumes=\"{volumes}\""),
            format!("depth.gpu_wait=\"{wait}\""),
        ])
        .collect();
        let report = common::run_graph_file(
            "graphs/depth_sgm_phantom.toml",
            &sets,
            &common::tmp_dir(&format!("sgm-phantom-{device}-{volumes}")),
        );
        assert!(report.error.is_none(), "{device}: {:?}", report.error);
        let eval = &report.metrics.eval;
        let s = (
            eval["depth.bad2_valid_pct"],
            eval["depth.density_pct"],
            eval["depth.mae_mm"],
        );
        println!(
            "{device} ({volumes}): bad2 valid {:.3} %, density {:.1} %, MAE {:.3} mm",
            s.0, s.1, s.2
        );
        assert!(s.1 > 80.0, "{device}: density {} %", s.1);
        scores.push(s);
    }
    // The same integers; the parabola's f32 division may round differently on a GPU (about
    // 4e-6 px on an H100, exact on lavapipe), which moves the scores by far less than this.
    let c = scores[0];
    for g in &scores[1..] {
        assert!(
            (c.0 - g.0).abs() <= 0.05 && (c.1 - g.1).abs() <= 0.05 && (c.2 - g.2).abs() <= 1e-3,
            "CPU and GPU score differently: {c:?} vs {g:?}"
        );
    }
    assert_eq!(
        scores[1], scores[2],
        "the summed costs give the same disparities"
    );
}

#[test]
fn bench_sgm_gpu_reports_parity_and_stages() {
    if gpu().is_none() {
        return;
    }
    let p = misslam_depth_sgm::sgm::SgmParams {
        max_disparity: 32,
        ..Default::default()
    };
    let r = misslam::bench::sgm_gpu(None, (96, 40), &p, 2, true).unwrap();
    assert_eq!((r.width, r.height, r.disparities, r.runs), (96, 40, 32, 2));
    assert_eq!(r.validity_differs, 0, "{r:?}");
    assert!(r.max_abs_diff_px <= 1e-4, "{r:?}");
    assert!(r.density_pct > 50.0, "{r:?}");
    assert!(r.stream_identical && r.stream_ms > 0.0, "{r:?}");
    let s = r.stages_ms;
    assert!(
        s.aggregate_ms > 0.0 && s.select_ms > 0.0 && s.total_ms > 0.0,
        "{s:?}"
    );
}

/// ELAS's dense matching on the GPU gives the CPU's disparities: the same integers (so the same
/// bits without sub-pixel refinement, both presets), and the sub-pixel fit within 1e-5 px.
#[test]
fn elas_dense_matching_on_the_gpu_gives_the_cpu_disparities() {
    use misslam_depth_elas::dense_gpu::DenseGpu;
    use misslam_depth_elas::{elas_gpu, elas_with, ElasParams, Scratch};
    let Some(ctx) = gpu() else { return };
    let (w, h) = (160, 96);
    let (left, right) = stereo_scene(w, h, 21);
    let mut kernel = DenseGpu::new(&ctx);
    for (name, base) in [
        ("robotics", ElasParams::robotics()),
        ("middlebury", ElasParams::middlebury()),
    ] {
        for subpixel in [false, true] {
            let p = ElasParams {
                disp_max: 40,
                subpixel,
                ..base
            };
            let cpu = elas_with(&left, &right, w, h, &p, &mut Scratch::default()).unwrap();
            let mut s = Scratch::default();
            let got = elas_gpu(&left, &right, w, h, &p, &mut s, (&ctx, &mut kernel)).unwrap();
            assert!(got.timing.dense_gpu.is_some());
            let valid = cpu.left.iter().filter(|d| d.is_finite()).count();
            assert!(valid * 2 > w * h, "{name}: {valid} valid pixels");
            let (validity, max_diff) = misslam::bench::disparity_parity(&got.left, &cpu.left);
            println!("{name}, sub-pixel {subpixel}: {validity} pixels differ in validity, max |diff| {max_diff:.2e} px, {valid} valid");
            assert_eq!(validity, 0, "{name}, sub-pixel {subpixel}");
            if subpixel {
                assert!(max_diff <= 1e-5, "{name}: {max_diff}");
            } else {
                let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(bits(&got.left), bits(&cpu.left), "{name}");
            }
        }
    }
}

/// `depth.elas` with `device = "gpu"` in a graph (`graphs/depth_elas_phantom.toml`, sub-pixel)
/// scores as on the CPU.
#[test]
fn depth_elas_on_the_gpu_scores_as_on_the_cpu() {
    if gpu().is_none() {
        return;
    }
    let mut scores = Vec::new();
    for device in ["cpu", "gpu"] {
        let sets: Vec<String> = [
            "src.width=160",
            "src.height=120",
            "src.focal_px=175.0",
            "graph.frames.count=1",
        ]
        .iter()
        .map(|s| s.to_string())
        .chain([format!("depth.device=\"{device}\"")])
        .collect();
        let report = common::run_graph_file(
            "graphs/depth_elas_phantom.toml",
            &sets,
            &common::tmp_dir(&format!("elas-phantom-{device}")),
        );
        assert!(report.error.is_none(), "{device}: {:?}", report.error);
        let eval = &report.metrics.eval;
        let s = (eval["depth.density_pct"], eval["depth.mae_mm"]);
        println!("{device}: density {:.1} %, MAE {:.4} mm", s.0, s.1);
        assert!(s.0 > 50.0, "{device}: density {} %", s.0);
        scores.push(s);
    }
    // The same integers; the sub-pixel fit's division may round differently on a GPU, which
    // moves the scores by far less than this.
    assert!(
        (scores[0].0 - scores[1].0).abs() <= 0.05 && (scores[0].1 - scores[1].1).abs() <= 1e-3,
        "CPU and GPU score differently: {scores:?}"
    );
}
