#![allow(clippy::unwrap_used)]
//! `fusion.template` and `graphs/template_dff.toml`: the distance field on the GPU against its CPU
//! reference, the template deformed onto exact and stereo depth, DFF against back-projection on
//! the same sequence, ICP alignment, a template read from a file, and bad input.

mod common;

use misslam_deformation_ed::observe::scan_from_depth;
use misslam_deformation_ed::{DistanceField, Intrinsics};
use misslam_fusion_template::gpu::DffKernel;
use misslam_source_phantom::{Params as PhantomParams, Phantom};
use std::collections::BTreeMap;

/// Runs a graph file into a fresh folder; returns the figures and the folder.
fn run(graph: &str, sets: &[&str], name: &str) -> (BTreeMap<String, f64>, std::path::PathBuf) {
    let out = common::tmp_dir(name);
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let eval = common::run_graph_file(graph, &sets, &out).metrics.eval;
    (eval, out)
}

/// The template on exact depth and the true pose: only the deformation is estimated.
const EXACT_GRAPH: &str = r#"
[graph]
name = "template_exact"
frames = { count = 10 }
seed = 7

[[node]]
id = "src"
plugin = "source.phantom"
params = { scene = "heart", trajectory = "sweep", width = 320, height = 240, focal_px = 350.0, mesh_step_mm = 2.0 }

[[node]]
id = "fusion"
plugin = "fusion.template"
inputs = { depth = "src.depth_gt", stereo = "src.stereo", pose = "src.pose_gt", template = "src.mesh_rest" }
params = { graph = { spacing = 8.0 }, solver = { max_iterations = 5 } }

[[node]]
id = "recon"
plugin = "eval.recon"
inputs = { mesh_gt = "src.mesh_gt", mesh = "fusion.mesh", pose = "fusion.pose", pose_gt = "src.pose_gt", rest_points_gt = "src.rest_points_gt", depth_gt = "src.depth_gt" }

[[node]]
id = "seen"
plugin = "eval.recon"
inputs = { mesh_gt = "src.mesh_gt", points = "fusion.visible" }
params = { prefix = "seen" }
"#;

/// Runs [`EXACT_GRAPH`] with overrides.
fn exact(sets: &[&str], name: &str) -> BTreeMap<String, f64> {
    exact_report(sets, name).metrics.eval
}

/// The same, the whole report.
fn exact_report(sets: &[&str], name: &str) -> misslam::framework::RunReport {
    let dir = common::tmp_dir(name);
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("exact.toml");
    std::fs::write(&path, EXACT_GRAPH).unwrap();
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    common::run_graph_file(path.to_str().unwrap(), &sets, &dir.join("out"))
}

#[test]
fn the_gpu_distance_field_matches_the_cpu_reference() {
    let Some(ctx) = common::gpu() else { return };
    let mut ph = Phantom::new(
        PhantomParams {
            width: 320,
            height: 240,
            focal_px: 350.0,
            ..Default::default()
        },
        7,
    )
    .unwrap();
    let f = ph.render(3).unwrap();
    let c = &f.depth.calib;
    let k = Intrinsics {
        fx: c.fx,
        fy: c.fy,
        cx: c.cx,
        cy: c.cy,
        width: 320,
        height: 240,
    };
    let (v, n) = scan_from_depth(&f.depth.map.data, &k, 3.0);
    let kernel = DffKernel::new(&ctx);
    for (voxel, trunc, window) in [(1.0, 5.0, 2), (0.7, 3.0, 0), (1.5, 4.0, 3)] {
        let t = std::time::Instant::now();
        let cpu = DistanceField::from_maps(&v, &n, &k, voxel, trunc, window, 50_000_000).unwrap();
        let cpu_ms = t.elapsed().as_secs_f64() * 1e3;
        let (gpu, timing) = kernel
            .build(&ctx, &v, &n, &k, voxel, trunc, window, 50_000_000, false)
            .unwrap();
        assert_eq!(cpu.dims, gpu.dims);
        assert_eq!(cpu.origin, gpu.origin);
        // Tolerance: the same f32 arithmetic, but the GPU may fuse multiply-adds, which can move
        // a projection that falls exactly between two pixels: at most 0.1 % of the voxels may
        // differ in validity or by more than 1e-4 mm, and none by more than 0.05 mm.
        let (mut known, mut mask_diff, mut off, mut worst) = (0usize, 0usize, 0usize, 0f32);
        for (a, b) in cpu.values.iter().zip(&gpu.values) {
            match (a.is_finite(), b.is_finite()) {
                (true, true) => {
                    known += 1;
                    let d = (a - b).abs();
                    worst = worst.max(d);
                    if d > 1e-4 {
                        off += 1;
                    }
                }
                (false, false) => {}
                _ => mask_diff += 1,
            }
        }
        let total = cpu.values.len();
        println!(
            "voxel {voxel} mm, window {window}: {total} voxels, {known} known, {mask_diff} differ in validity, {off} by > 1e-4 mm, worst {worst} mm; CPU {cpu_ms:.1} ms, {} {:.1} + {:.1} ms",
            ctx.adapter_info.name, timing.prepare_ms, timing.gpu_ms
        );
        assert!(known > total / 20, "{known} of {total} known");
        assert!(mask_diff * 1000 <= total, "{mask_diff}");
        assert!(off * 1000 <= known, "{off}");
        assert!(worst < 0.05, "{worst}");
    }
    // With the mean normals (`main_normals`): the same values as without, and normals that
    // match the CPU's as the values do; NaN exactly where the value is unknown.
    let (voxel, trunc, window) = (1.0, 5.0, 2);
    let cpu = DistanceField::from_maps_with_normals(&v, &n, &k, voxel, trunc, window, 50_000_000)
        .unwrap();
    let plain = kernel
        .build(&ctx, &v, &n, &k, voxel, trunc, window, 50_000_000, false)
        .unwrap()
        .0;
    let gpu = kernel
        .build(&ctx, &v, &n, &k, voxel, trunc, window, 50_000_000, true)
        .unwrap()
        .0;
    let bits = |f: &DistanceField| f.values.iter().map(|v| v.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&gpu), bits(&plain));
    assert!(plain.normals.is_empty());
    assert_eq!(gpu.normals.len(), gpu.values.len());
    assert_eq!(cpu.normals.len(), cpu.values.len());
    let (mut both, mut off, mut worst) = (0usize, 0usize, 0f32);
    for ((a, b), v) in cpu.normals.iter().zip(&gpu.normals).zip(&gpu.values) {
        assert_eq!(b[0].is_nan(), v.is_nan());
        if a[0].is_finite() && b[0].is_finite() {
            both += 1;
            let d = (0..3).map(|i| (a[i] - b[i]).abs()).fold(0f32, f32::max);
            worst = worst.max(d);
            if d > 1e-5 {
                off += 1;
            }
        }
    }
    println!("normals: {both} known on both, {off} differ by > 1e-5, worst {worst}");
    assert!(
        both > cpu.values.len() / 20 && off * 1000 <= both,
        "{off} of {both}"
    );
    // Wrong map sizes are an error, not a panic.
    assert!(kernel
        .build(&ctx, &v[1..], &n, &k, 1.0, 5.0, 2, 1_000_000, false)
        .is_err());
}

#[test]
fn the_node_builds_its_field_and_normals_on_the_gpu_as_on_the_cpu() {
    // The template on exact depth with its field (values and the normals its rows take, the
    // default `field_normal`) from the WGSL kernel: the run of the CPU field, the figures within
    // what the kernel's rare rounding differences allow (bit-exact on lavapipe).
    if common::gpu().is_none() {
        return;
    }
    let sets = ["graph.frames.count=4", "fusion.field.window_px=2"];
    let cpu = exact(&sets, "template_field_cpu");
    let gpu = exact(
        &[sets[0], sets[1], "fusion.field.device=gpu"],
        "template_field_gpu",
    );
    for key in ["recon.mean_mm", "recon.rms_mm", "seen.mean_mm"] {
        let (c, g) = (cpu[key], gpu[key]);
        eprintln!("{key}: cpu {c}, gpu {g}");
        assert!(
            (c - g).abs() <= 1e-3 * c.abs().max(1e-3),
            "{key}: cpu {c}, gpu {g}"
        );
    }
}

#[test]
fn the_template_follows_exact_depth_with_either_data_term() {
    for dt in ["dff", "projective"] {
        let report = exact_report(
            &[&format!("fusion.data_term={dt}")],
            &format!("template_exact_{dt}"),
        );
        // The node's stages are timed: the template's set-up on the first frame, every later
        // frame's selection, correspondences, solve (and its parts) and output; the field with
        // DFF only.
        let t = &report.metrics.timing_ms;
        let frames = |stage: &str| t.get(&format!("fusion.{stage}")).map_or(0, |s| s.frames);
        assert_eq!(frames("init"), 1);
        for stage in [
            "scan",
            "select",
            "corr",
            "solve",
            "solve.associate",
            "solve.assemble",
            "solve.factor",
            "solve.prepare",
            "solve.level2",
            "output",
        ] {
            assert_eq!(frames(stage), 10, "{dt}: fusion.{stage}");
        }
        assert_eq!(frames("field"), if dt == "dff" { 10 } else { 0 }, "{dt}");
        let e = &report.metrics.eval;
        let (seen, all) = (e["seen.mean_mm"], e["recon.mean_mm"]);
        let drift = e["recon.drift_mm"];
        eprintln!(
            "exact depth, {dt}: seen {seen:.4} mm, whole template {all:.4} mm, drift {drift:.4} mm"
        );
        // Measured 0.020 (dff) and 0.017 (projective) seen, 0.135 and 0.132 for the whole
        // template, whose unseen parts only follow the graph (0.16 when level II of the decoupled
        // solve carried only 3 rings of unseen nodes).
        assert!(seen < 0.05, "{dt}: seen.mean_mm {seen}");
        // The template's vertices followed by index: 0.37 mm of tangential sliding with either
        // term (depth constrains the surface, not where on it the tissue is).
        assert!(drift < 0.6, "{dt}: recon.drift_mm {drift}");
        assert!(all < 0.3, "{dt}: recon.mean_mm {all}");
        assert_eq!(e["template.vertices"], 4636.0);
    }
}

#[test]
fn a_template_made_from_the_first_scan_follows_the_tissue() {
    // No pre-operative mesh: the first frame's exact depth, triangulated every 4 pixels, is the
    // template (it takes precedence over the connected `template` port). It covers only what the
    // scope saw on frame 0, so the whole template is scored and it must stay on the surface while
    // the heart beats and the scope sweeps.
    let e = exact(
        &["fusion.template_from_scan={ stride_px = 4 }"],
        "template_from_scan",
    );
    let (seen, all) = (e["seen.mean_mm"], e["recon.mean_mm"]);
    let n = e["template.vertices"];
    eprintln!(
        "template from the first scan: {n} vertices, seen {seen:.4} mm, whole template {all:.4} mm"
    );
    assert!(n > 2000.0 && n != 4636.0, "{n} vertices");
    // Measured: 4,800 vertices (the whole view), 0.009 mm seen and 0.010 mm over the whole
    // template.
    assert!(seen < 0.05, "seen.mean_mm {seen}");
    assert!(all < 0.05, "recon.mean_mm {all}");
}

#[test]
fn template_fusion_runs_over_the_real_hamlyn_frames_without_failing() {
    // Real in-vivo frames 3 s apart, a template from the first scan: the lost frames are
    // reported and leave the template as it was; nothing may crash, skip or go non-finite.
    let Some(_) = common::data_set("hamlyn20") else {
        return;
    };
    let out = common::tmp_dir("template_dff_hamlyn");
    let report = common::run_graph_file("graphs/template_dff_hamlyn.toml", &[], &out);
    let e = &report.metrics.eval;
    eprintln!("template_dff_hamlyn: {e:?}");
    assert_eq!(report.metrics.frames.processed, 17);
    assert_eq!(report.metrics.frames.skipped, 0);
    assert!(e["template.vertices"] > 1000.0, "{e:?}");
    let traj = std::fs::read_to_string(out.join("export/pose.txt")).expect("pose.txt written");
    assert_eq!(traj.lines().count(), 17);
    let lost = traj.lines().filter(|l| l.starts_with("# frame")).count();
    assert!((1..17).contains(&lost), "{traj}");
    let nv = common::finite_ply_vertices(&out.join("export/mesh/final.ply"));
    assert_eq!(nv as f64, e["template.vertices"]);
}

#[test]
fn keypoint_correspondences_keep_the_template_from_sliding() {
    // Depth tells the template where the surface is, not where on it the tissue went: from
    // exact depth and pose it slides 0.37 mm over 10 frames (material drift). ORB keypoints
    // matched frame to frame (E_corr, as in fusion.surfel) hold it closer to the tissue.
    let graph = EXACT_GRAPH
        .replace(
            "template = \"src.mesh_rest\" }",
            "template = \"src.mesh_rest\", features = \"features.features\" }",
        )
        .replace(
            "[[node]]\nid = \"fusion\"",
            "[[node]]\nid = \"features\"\nplugin = \"features.orb\"\ninputs = { stereo = \"src.stereo\" }\n\n[[node]]\nid = \"fusion\"",
        );
    assert!(graph.contains("features.features"));
    let dir = common::tmp_dir("template_corr");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("graph.toml");
    std::fs::write(&path, graph).unwrap();
    let path = path.to_str().unwrap();
    let (with, _) = run(path, &[], "template_corr_on");
    let (without, _) = run(
        path,
        &["fusion.correspondences.enabled=false"],
        "template_corr_off",
    );
    let (a, b) = (with["recon.drift_mm"], without["recon.drift_mm"]);
    eprintln!(
        "exact depth, 10 frames: drift {a:.3} mm with E_corr, {b:.3} mm without; recon {:.3} / {:.3} mm",
        with["recon.mean_mm"], without["recon.mean_mm"]
    );
    // Measured 0.163 against 0.356 mm (persistent keypoints; 0.229 matched frame to frame).
    assert!(a < 0.9 * b, "drift {a} with E_corr, {b} without");
    assert!(with["recon.mean_mm"] < 0.3, "{}", with["recon.mean_mm"]);
}

#[test]
fn dff_is_at_least_as_accurate_as_back_projection_on_heart_kidney_and_liver() {
    // The thesis's Table 3.1 comparison on the graph as shipped (ELAS depth, the ORB tracker's
    // pose and keypoint correspondences, sensor noise, the first solve held by E_m), the same 20
    // frames for both data terms. Measured (whole template's distance to the surface, DFF vs
    // back-projection; session 38, the field's 11x11 window and its normal as the rows'
    // direction): heart 0.2792 vs 0.2932 mm, kidney 0.1839 vs 0.1859, liver 0.2386 vs 0.2389;
    // tracked vertices where seen (`recon.vertex_seen_mm`): 0.2842 vs 0.2854, 0.145 vs 0.173,
    // 0.158 vs 0.226. On the heart the tracked vertices are close to a tie (over 4 seeds and
    // 40 frames 0.310 vs 0.304 mm before session 38), so there DFF is held within 5 %.
    for organ in ["heart", "kidney", "liver"] {
        let mut r = BTreeMap::new();
        let mut out = BTreeMap::new();
        for dt in ["dff", "projective"] {
            let (e, dir) = run(
                "graphs/template_dff.toml",
                &[
                    "graph.frames.count=20",
                    &format!("src.scene={organ}"),
                    &format!("fusion.data_term={dt}"),
                ],
                &format!("template_stereo_{organ}_{dt}"),
            );
            eprintln!(
                "{organ}, stereo depth, {dt}: whole template {:.4} mm (seen so far {:.4}, never seen {:.4}), seen {:.3} mm, tracked vertices where seen {:.4} mm, drift {:.3} mm, ATE {:.3} mm",
                e["recon.mean_mm"],
                e["recon.observed_mm"],
                e["recon.unobserved_mm"],
                e["seen.mean_mm"],
                e["recon.vertex_seen_mm"],
                e["recon.drift_mm"],
                e["tracking.ate_mm"]
            );
            r.insert(dt, e);
            out.insert(dt, dir);
        }
        let (d, p) = (&r["dff"], &r["projective"]);
        assert!(d["recon.mean_mm"] < 0.6, "{organ}: {}", d["recon.mean_mm"]);
        assert!(d["seen.mean_mm"] < 0.15, "{organ}: {}", d["seen.mean_mm"]);
        // The whole template's figure split by whether the true camera has seen a vertex yet
        // (measured, DFF / back-projection: heart 0.073 / 0.079 mm seen so far, 0.349 / 0.366
        // never seen; kidney 0.082 / 0.086 and 0.224 / 0.226; liver 0.082 / 0.081 and 0.283 /
        // 0.283): what the data placed lies on the surface, what only the warp extrapolates
        // does not.
        for (dt, e) in &r {
            let (seen, unseen) = (e["recon.observed_mm"], e["recon.unobserved_mm"]);
            assert!(seen < 0.15, "{organ}, {dt}: seen so far {seen}");
            assert!(
                seen < 0.6 * unseen,
                "{organ}, {dt}: seen so far {seen}, never seen {unseen}"
            );
        }
        let tolerance = if organ == "heart" { 1.05 } else { 1.0 };
        for (key, tol) in [("recon.mean_mm", 1.0), ("recon.vertex_seen_mm", tolerance)] {
            assert!(
                d[key] <= tol * p[key],
                "{organ}, {key}: dff {} vs projective {}",
                d[key],
                p[key]
            );
        }
        if organ == "heart" {
            // The export: the coloured template as PLY.
            let ply =
                std::fs::read(out["dff"].join("export/mesh/final.ply")).expect("final.ply written");
            let header = String::from_utf8_lossy(&ply[..ply.len().min(400)]).to_string();
            assert!(header.contains("property uchar red"), "{header}");
            assert!(header.contains("element face"), "{header}");
        }
    }
}

#[test]
fn the_template_is_output_in_the_scope_frame_too() {
    // `camera_mesh = true`: `mesh_camera` is the deformed template seen from fusion's pose; the
    // last frame's pose carries each of its vertices onto the world-frame mesh's.
    let dir = common::run_with_sink(
        "graphs/template_dff.toml",
        "scope",
        r#"{ mesh = "fusion.mesh_camera", pose = "fusion.pose" }"#,
        &["graph.frames.count=4", "fusion.camera_mesh=true"],
        "template_scope_frame",
    );
    let (n, apart) = common::assert_scope_frame(
        &dir.join("export/mesh/final.ply"),
        &dir.join("scope/mesh/final.ply"),
        &dir.join("scope/pose.txt"),
    );
    assert!(n > 1000, "{n} vertices");
    assert!(apart > 1.0, "{apart}");
}

#[test]
fn the_decoupled_solve_moves_the_whole_template() {
    // The decoupled solver, swapped in by one line: level II must carry every unseen node of the
    // template along (its default here), not only those within a few rings of the seen ones, or
    // the far side of the beating heart stays behind. Measured over 20 frames: 0.258 mm over the
    // whole template (batch 0.280), 1.578 mm with `level2_rings = 3`.
    let mut r = Vec::new();
    for rings in [None, Some(3)] {
        let mut sets = vec![
            "graph.frames.count=20".to_string(),
            "fusion.solver_kind=decoupled".to_string(),
        ];
        if let Some(n) = rings {
            sets.push(format!("fusion.decoupled.level2_rings={n}"));
        }
        let sets: Vec<&str> = sets.iter().map(String::as_str).collect();
        let (e, _) = run(
            "graphs/template_dff.toml",
            &sets,
            &format!("template_decoupled_{rings:?}"),
        );
        eprintln!(
            "decoupled, level2_rings = {rings:?} (None: the default): whole template {:.3} mm, seen {:.3} mm",
            e["recon.mean_mm"], e["seen.mean_mm"]
        );
        r.push(e);
    }
    assert!(r[0]["recon.mean_mm"] < 0.4, "{}", r[0]["recon.mean_mm"]);
    assert!(r[0]["seen.mean_mm"] < 0.1, "{}", r[0]["seen.mean_mm"]);
    assert!(
        r[0]["recon.mean_mm"] < 0.5 * r[1]["recon.mean_mm"],
        "default {} vs 3 rings {}",
        r[0]["recon.mean_mm"],
        r[1]["recon.mean_mm"]
    );
}

#[test]
fn surface_samples_give_a_coarse_template_its_data() {
    // A coarse pre-operative mesh (the heart's rest surface at 6 mm instead of 2) leaves few data
    // rows per node. `data_subdivision = 3` adds the points of each triangle's 1/3 grid to the
    // data term (the output mesh keeps the template's vertices). Measured over 20 frames: whole
    // template 0.630 mm without the samples, 0.392 with (546 vertices, 4,636 data points); tracked
    // vertices where seen 0.424 and 0.307 mm.
    let mut r = Vec::new();
    for n in ["1", "3"] {
        let (e, _) = run(
            "graphs/template_dff.toml",
            &[
                "graph.frames.count=20",
                "src.mesh_step_mm=6",
                &format!("fusion.data_subdivision={n}"),
            ],
            &format!("template_subdivision_{n}"),
        );
        eprintln!(
            "6 mm template, data_subdivision {n}: whole template {:.4} mm, tracked where seen {:.4} mm, {} vertices, {} data points",
            e["recon.mean_mm"], e["recon.vertex_seen_mm"], e["template.vertices"], e["template.data_points"]
        );
        r.push(e);
    }
    assert_eq!(r[0]["template.vertices"], r[1]["template.vertices"]);
    assert_eq!(r[0]["template.data_points"], r[0]["template.vertices"]);
    assert!(r[1]["template.data_points"] > 4.0 * r[1]["template.vertices"]);
    assert!(
        r[1]["recon.mean_mm"] < 0.8 * r[0]["recon.mean_mm"],
        "{} with samples, {} without",
        r[1]["recon.mean_mm"],
        r[0]["recon.mean_mm"]
    );
    assert!(
        r[1]["recon.vertex_seen_mm"] < r[0]["recon.vertex_seen_mm"],
        "{} with samples, {} without",
        r[1]["recon.vertex_seen_mm"],
        r[0]["recon.vertex_seen_mm"]
    );
}

#[test]
fn the_first_solve_is_held_where_the_template_was_placed() {
    // On its first frame the template is the tissue exactly (the phantom's frame 0 is its rest
    // shape). Fitted to noisy depth with no keypoint anchor yet, the first solve slid it along
    // the surface, where the depth cannot see it, and the anchors made from then on held the
    // slid state. `first_frame_motion` (E_m on the first solve, default 3) holds it: liver, 20
    // frames, tracked vertices where seen 0.379 mm without, 0.156 with; surface 0.252 and 0.238.
    // E_m on every frame (`solver.weights.motion`) holds a slowly breathing liver as well.
    let mut r = Vec::new();
    for set in [
        "fusion.first_frame_motion=0",
        "fusion.first_frame_motion=3",
        "fusion.solver.weights.motion=3",
    ] {
        let (e, _) = run(
            "graphs/template_dff.toml",
            &["graph.frames.count=20", "src.scene=liver", set],
            &format!("template_hold_{}", r.len()),
        );
        eprintln!(
            "liver, {set}: tracked vertices where seen {:.3} mm, all {:.3} mm, surface {:.4} mm",
            e["recon.vertex_seen_mm"], e["recon.vertex_mm"], e["recon.mean_mm"]
        );
        r.push(e);
    }
    for held in [&r[1], &r[2]] {
        assert!(
            held["recon.vertex_seen_mm"] < 0.6 * r[0]["recon.vertex_seen_mm"],
            "{} held, {} without",
            held["recon.vertex_seen_mm"],
            r[0]["recon.vertex_seen_mm"]
        );
        assert!(
            held["recon.mean_mm"] < r[0]["recon.mean_mm"],
            "{} held, {} without",
            held["recon.mean_mm"],
            r[0]["recon.mean_mm"]
        );
    }
    // Out-of-range weights are refused by name.
    let g = misslam::framework::graph::load(
        std::path::Path::new("graphs/template_dff.toml"),
        &misslam::builtin_registry(),
        &["fusion.first_frame_motion=-1".to_string()],
    );
    let msg = match g {
        Err(e) => e.to_string(),
        Ok(g) => match misslam::framework::Runtime::build(g) {
            Err(e) => e.to_string(),
            Ok(_) => panic!("a negative first_frame_motion was accepted"),
        },
    };
    assert!(msg.contains("first_frame_motion"), "{msg}");
}

#[test]
fn keypoints_hold_the_template_to_the_tissue_on_stereo_depth() {
    // The shipped graph with and without its ORB correspondences, on the liver, where they once
    // made the template slide (9.5 mm of drift over 40 frames: keypoints anchored off the surface
    // flattened the node affines). Measured over 20 frames: drift 0.114 mm with E_corr, 0.574
    // without; whole template 0.252 against 0.247 mm.
    let sets = ["graph.frames.count=20", "src.scene=liver"];
    let (with, _) = run("graphs/template_dff.toml", &sets, "template_liver_corr");
    let mut off = sets.to_vec();
    off.push("fusion.correspondences.enabled=false");
    let (without, _) = run("graphs/template_dff.toml", &off, "template_liver_nocorr");
    let (a, b) = (with["recon.drift_mm"], without["recon.drift_mm"]);
    eprintln!(
        "liver, 20 frames: drift {a:.3} mm with E_corr, {b:.3} mm without; recon {:.3} / {:.3} mm",
        with["recon.mean_mm"], without["recon.mean_mm"]
    );
    assert!(a < 0.7 * b, "drift {a} with E_corr, {b} without");
    assert!(
        with["recon.mean_mm"] < 1.15 * without["recon.mean_mm"],
        "recon {} with E_corr, {} without",
        with["recon.mean_mm"],
        without["recon.mean_mm"]
    );
}

#[test]
fn a_lost_track_leaves_its_frame_unscored_and_the_run_goes_on() {
    // A jerk of the scope 0.5 s in (8 mm out and back in 0.2 s) loses the ORB track on frame 18:
    // the template is not deformed there and nothing is visible, so `seen` has no point to score.
    // That frame is counted as unscored and the run goes on to the last frame.
    let (e, _) = run(
        "graphs/template_dff.toml",
        &[
            "graph.frames.count=22",
            "src.trajectory=fast",
            "src.fast_start_s=0.5",
        ],
        "template_lost",
    );
    eprintln!(
        "jerk: lost {:.1} %, seen unscored {:.1} %, recon {:.3} mm",
        e["tracking.lost_pct"], e["seen.unscored_pct"], e["recon.mean_mm"]
    );
    assert!(e["tracking.lost_pct"] > 0.0, "the jerk must lose the track");
    assert_eq!(e["seen.unscored_pct"], e["tracking.lost_pct"]);
    assert_eq!(e["recon.unscored_pct"], 0.0);
    assert!(e["recon.mean_mm"] < 1.0, "{}", e["recon.mean_mm"]);
    assert!(e["seen.mean_mm"] < 0.2, "{}", e["seen.mean_mm"]);
}

#[test]
fn icp_recovers_a_misplaced_template() {
    let base = exact(&[], "template_icp_base");
    let e = exact(
        &[
            "fusion.align.mode=icp",
            "fusion.align.translation_mm=[2.5, -2.0, 3.0]",
            "fusion.align.rotation_deg=[1.5, -1.0, 2.0]",
        ],
        "template_icp",
    );
    let (before, after) = (
        e["template.align_rms_before_mm"],
        e["template.align_rms_after_mm"],
    );
    eprintln!(
        "ICP: rms {before:.3} -> {after:.3} mm; whole template {:.4} mm (placed exactly: {:.4} mm)",
        e["recon.mean_mm"], base["recon.mean_mm"]
    );
    assert!(before > 1.0 && after < 0.5 * before, "{before} -> {after}");
    assert!(
        e["recon.mean_mm"] < base["recon.mean_mm"] + 0.15,
        "{} vs {}",
        e["recon.mean_mm"],
        base["recon.mean_mm"]
    );
    // Without ICP the same misplacement stays wrong: the test above is not vacuous. (The
    // deformation takes out part of it: with the first solve held where the template was placed
    // 0.412 mm against ICP's 0.143, without that hold 0.210, since the decoupled solve's level II
    // carries the whole template.)
    let off = exact(
        &[
            "fusion.align.translation_mm=[2.5, -2.0, 3.0]",
            "fusion.align.rotation_deg=[1.5, -1.0, 2.0]",
        ],
        "template_no_icp",
    );
    eprintln!("without ICP: whole template {:.4} mm", off["recon.mean_mm"]);
    assert!(
        off["recon.mean_mm"] > 1.3 * e["recon.mean_mm"],
        "{} vs {}",
        off["recon.mean_mm"],
        e["recon.mean_mm"]
    );
}

#[test]
fn a_template_read_from_a_file_gives_the_ports_result() {
    // The phantom's rest surface written as OBJ (1-based faces) and read through template_path.
    let ph = Phantom::new(
        PhantomParams {
            width: 320,
            height: 240,
            focal_px: 350.0,
            mesh_step_mm: 2.0,
            ..Default::default()
        },
        7,
    )
    .unwrap();
    let dir = common::tmp_dir("template_file");
    std::fs::create_dir_all(&dir).unwrap();
    // `inverted` writes every face with the opposite winding (normals pointing into the organ).
    let write = |name: &str, inverted: bool| {
        let mut obj = String::new();
        for v in ph.rest_vertices() {
            obj += &format!("v {} {} {}\n", v[0], v[1], v[2]);
        }
        for t in ph.triangles() {
            let (b, c) = if inverted { (t[2], t[1]) } else { (t[1], t[2]) };
            obj += &format!("f {} {} {}\n", t[0] + 1, b + 1, c + 1);
        }
        let path = dir.join(name);
        std::fs::write(&path, obj).unwrap();
        path
    };
    let path = write("rest.obj", false);
    let from_port = exact(&[], "template_port");
    let set = format!("fusion.template_path=\"{}\"", path.display());
    let from_file = exact(&[&set], "template_file_run");
    let (a, b) = (from_port["recon.mean_mm"], from_file["recon.mean_mm"]);
    eprintln!("template from the port {a:.4} mm, from OBJ {b:.4} mm");
    assert_eq!(from_file["template.vertices"], 4636.0);
    // The OBJ carries no normals: they are recomputed from the faces (the port gives the
    // phantom's analytic ones), so the figures agree closely, not bit for bit.
    assert!((a - b).abs() < 0.02, "{a} vs {b}");
    // Inverted winding, misplaced and aligned by ICP: the ICP does not rely on the normals, and
    // the winding is detected against the aligned template and flipped.
    let inv = write("inverted.obj", true);
    let e = exact(
        &[
            &format!("fusion.template_path=\"{}\"", inv.display()),
            "fusion.align.mode=icp",
            "fusion.align.translation_mm=[2.5, -2.0, 3.0]",
            "fusion.align.rotation_deg=[1.5, -1.0, 2.0]",
        ],
        "template_file_inverted",
    );
    eprintln!(
        "inverted winding with ICP: rms {:.3} -> {:.3} mm, whole template {:.4} mm",
        e["template.align_rms_before_mm"], e["template.align_rms_after_mm"], e["recon.mean_mm"]
    );
    assert!(
        e["recon.mean_mm"] < b + 0.15,
        "{} vs {b}",
        e["recon.mean_mm"]
    );
}

/// `graphs/template_oracle.toml`: exact data where the camera looks, against every vertex.
#[test]
fn the_oracle_separates_the_warps_extrapolation_from_what_the_graph_can_represent() {
    let run_mode = |mode: &str, rot_unseen: &str| {
        run(
            "graphs/template_oracle.toml",
            &[
                &format!("fusion.oracle.mode={mode}"),
                "graph.frames.count=15",
                &format!("fusion.solver.weights.rot_unseen={rot_unseen}"),
            ],
            &format!("template_oracle_{mode}_{rot_unseen}"),
        )
        .0
    };
    let (vis, all) = (run_mode("visible", "1"), run_mode("all", "1"));
    let rigid = run_mode("visible", "1000");
    for (name, e) in [
        ("visible", &vis),
        ("all", &all),
        ("visible, rot_unseen 1000", &rigid),
    ] {
        eprintln!(
            "oracle {name}: whole {:.4} mm, seen so far {:.4}, never seen {:.4}, vertices {:.4}, pulled {:.0} a frame",
            e["recon.mean_mm"],
            e["recon.observed_mm"],
            e["recon.unobserved_mm"],
            e["recon.vertex_mm"],
            e["template.oracle_points"]
        );
    }
    // Every vertex pulled to its true place: the graph represents the heart's motion (measured
    // 0.008 mm over the surface, 0.015 mm per vertex).
    assert_eq!(all["template.oracle_points"], 4636.0);
    assert!(all["recon.mean_mm"] < 0.03, "{all:?}");
    assert!(all["recon.vertex_mm"] < 0.05, "{all:?}");
    // Only what the camera sees: that part follows (measured ...), the part never seen is left
    // to the warp's extrapolation, several times the error.
    let pulled = vis["template.oracle_points"];
    assert!(pulled > 200.0 && pulled < 3000.0, "{vis:?}");
    assert!(vis["recon.observed_mm"] < 0.06, "{vis:?}");
    assert!(
        vis["recon.unobserved_mm"] > 3.0 * vis["recon.observed_mm"].max(all["recon.unobserved_mm"]),
        "{vis:?}"
    );
    // The nodes no data binds held to rotations (`weights.rot_unseen = 1000`, the seen part's
    // w_rot left at 1): this heart's never-seen part follows its seen part far better (measured
    // 0.095 against 0.250 mm), and the seen part no worse (0.026 against 0.030).
    assert_eq!(rigid["template.oracle_points"], pulled);
    assert!(
        rigid["recon.unobserved_mm"] < 0.6 * vis["recon.unobserved_mm"],
        "{rigid:?}"
    );
    assert!(
        rigid["recon.observed_mm"] < 1.1 * vis["recon.observed_mm"],
        "{rigid:?}"
    );
}

#[test]
fn bad_template_input_is_refused_with_the_field_or_frame() {
    let reg = misslam::builtin_registry();
    let load = |sets: &[&str]| {
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        misslam::framework::graph::load(
            std::path::Path::new("graphs/template_dff.toml"),
            &reg,
            &sets,
        )
    };
    for (set, needle) in [
        (
            "fusion.template_path=\"/nonexistent/organ.obj\"",
            "template_path",
        ),
        ("fusion.template_path=\"/tmp/organ.xyz\"", "template_path"),
        ("fusion.field.voxel_mm=0", "field.voxel_mm"),
        ("fusion.solver.weights.rot_unseen=-1", "weights.rot_unseen"),
        ("fusion.solver.weights.reg_unseen=nan", "weights.reg_unseen"),
        ("fusion.field.truncation_mm=-1", "field.truncation_mm"),
        ("fusion.visible_angle_deg=0", "visible_angle_deg"),
        (
            "fusion.align.rotation_deg=[0, nan, 0]",
            "align.rotation_deg",
        ),
        ("fusion.data_term=\"nearest\"", "data_term"),
        ("fusion.oracle.mode=\"psychic\"", "oracle"),
        (
            "fusion.oracle.max_depth_gap_mm=0",
            "oracle.max_depth_gap_mm",
        ),
    ] {
        let g = load(&[set]);
        let msg = match g {
            Err(e) => e.to_string(),
            Ok(g) => match misslam::framework::Runtime::build(g) {
                Err(e) => e.to_string(),
                Ok(_) => panic!("`{set}` was accepted"),
            },
        };
        assert!(msg.contains(needle), "`{set}`: {msg}");
    }
    // A template with a vertex 6e19 mm off (a corrupt byte): refused, naming the vertex.
    let dir = common::tmp_dir("template_stray");
    std::fs::create_dir_all(&dir).unwrap();
    let stray = dir.join("stray.obj");
    std::fs::write(
        &stray,
        "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 6e19 10 0\nf 1 2 3\nf 2 4 3\n",
    )
    .unwrap();
    let set = format!("fusion.template_path=\"{}\"", stray.display());
    let e = match misslam::framework::Runtime::build(load(&[&set]).unwrap()) {
        Err(e) => e.to_string(),
        Ok(_) => panic!("a template 6e19 mm wide was accepted"),
    };
    assert!(
        e.contains("template_path") && e.contains("vertex 3 ") && e.contains("millimetres"),
        "{e}"
    );
    // No template at all: the first frame fails, naming both ways to give one.
    let graph = EXACT_GRAPH.replace(", template = \"src.mesh_rest\"", "");
    assert!(!graph.contains("src.mesh_rest"));
    let dir = common::tmp_dir("template_none");
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("none.toml");
    std::fs::write(&path, graph).unwrap();
    let sets = [
        "graph.frames.count=1".to_owned(),
        "graph.on_error=\"abort\"".to_owned(),
    ];
    let g = misslam::framework::graph::load(&path, &reg, &sets).unwrap();
    let report = common::run_graph(g, &dir.join("out"));
    let err = report
        .error
        .expect("the run fails without a template")
        .to_string();
    assert!(
        err.contains("template_path") && err.contains("`template` input"),
        "{err}"
    );
    // No data term, no keypoints, no oracle: nothing would move the template.
    let msg = match load(&[
        "fusion.data_term=\"none\"",
        "fusion.correspondences.enabled=false",
    ]) {
        Err(e) => e.to_string(),
        Ok(g) => misslam::framework::Runtime::build(g)
            .err()
            .expect("a template with no data is refused")
            .to_string(),
    };
    assert!(
        msg.contains("data_term") && msg.contains("nothing"),
        "{msg}"
    );
    // The oracle without its ground truth wired, or with a template that is not the phantom's
    // rest mesh: the first frame fails, naming the input or the vertex counts.
    for (graph, set, needle) in [
        (
            "graphs/template_dff.toml",
            "fusion.oracle.mode=\"visible\"",
            "`mesh_gt` input",
        ),
        (
            "graphs/template_oracle.toml",
            "fusion.template_from_scan={ stride_px = 4, max_edge_mm = 3.0 }",
            "vertices and the template",
        ),
    ] {
        let sets = [
            set.to_owned(),
            "graph.frames.count=1".to_owned(),
            "graph.on_error=\"abort\"".to_owned(),
        ];
        let g = misslam::framework::graph::load(std::path::Path::new(graph), &reg, &sets).unwrap();
        let report = common::run_graph(g, &common::tmp_dir("template_oracle_bad"));
        let err = report.error.expect("the oracle's frame fails").to_string();
        assert!(
            err.contains(needle) && err.contains("frame 0"),
            "{set}: {err}"
        );
    }
}
