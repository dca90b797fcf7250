#![allow(clippy::unwrap_used)]
//! `graphs/mis_slam.toml` end to end on the phantom (SGM, post-processing, ORB tracker,
//! decoupled ED, surfel fusion), and surfel fusion alone on exact depth and pose.

mod common;

use std::path::PathBuf;

fn run(sets: &[&str], name: &str) -> std::collections::BTreeMap<String, f64> {
    let out = common::tmp_dir(name);
    let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
    let report = common::run_graph_file("graphs/mis_slam.toml", &sets, &out);
    // The coloured model is exported at the end, as PLY and glb.
    let ply = std::fs::read(out.join("export/model/final.ply")).expect("final.ply written");
    let header = String::from_utf8_lossy(&ply[..ply.len().min(400)]).to_string();
    assert!(header.contains("property uchar red"), "{header}");
    assert!(out.join("export/model/final.glb").is_file());
    // The fusion's own stages are timed (every frame after the first solves).
    let t = &report.metrics.timing_ms;
    for stage in [
        "scan",
        "select",
        "solve",
        "solve.factor",
        "solve.prepare",
        "solve.level2",
        "select.corr",
        "fuse",
        "add",
        "grow",
        "output",
        "output.deform",
        "output.anchor",
    ] {
        assert!(t.contains_key(&format!("fusion.{stage}")), "fusion.{stage}");
    }
    // And the post-processing's.
    for stage in ["masks", "smooth", "maps"] {
        assert_eq!(
            t[&format!("post.{stage}")].frames,
            t["post"].frames,
            "post.{stage}"
        );
    }
    report.metrics.eval
}

#[test]
fn mis_slam_reconstructs_the_beating_heart_within_the_targets() {
    // Issue 7's targets, in the scope's frame: noise-free under 0.5 mm, with sensor noise under
    // 1.0 mm.
    for (noise, target) in [("0", 0.5), ("2", 1.0)] {
        let e = run(
            &["graph.frames.count=8", &format!("src.noise_sigma={noise}")],
            &format!("mis_slam_noise{noise}"),
        );
        let mean = e["recon.mean_mm"];
        eprintln!(
            "mis_slam, 8 frames, noise {noise}: recon {mean:.3} mm (world frame {:.3} mm), {} surfels",
            e["recon_world.mean_mm"], e["fusion.surfels"]
        );
        assert!(mean < target, "noise {noise}: recon.mean_mm {mean}");
        assert_eq!(e["tracking.lost_pct"], 0.0);
        assert!(e["fusion.surfels"] > 1000.0);
        assert_eq!(e["fusion.disagreeing_frames"], 0.0);
        assert_eq!(e["fusion.collapsed_frames"], 0.0);
        // The ORB keypoints reach the solve as E_corr constraints (about 190 a frame here).
        let corr = e["fusion.correspondences_per_solve"];
        assert!(
            corr > 50.0,
            "noise {noise}: {corr} correspondences per solve"
        );
        // The graph's two iterations share one factorisation (the node's default
        // `solver.reuse_factorisation = 1`): one for level I, at most one for level II.
        let (f, r) = (
            e["fusion.factorisations_per_solve"],
            e["fusion.reused_factorisations_per_solve"],
        );
        eprintln!("noise {noise}: {f:.2} factorisations and {r:.2} kept ones per solve");
        assert!(r >= 0.5 && f < 2.5, "noise {noise}: {f} made, {r} kept");
    }
}

/// `graphs/mis_slam.toml` with the fusion node's inputs replaced by `inputs`, written into a
/// fresh folder `name`: (the folder, the graph file).
fn mis_slam_with_fusion_inputs(inputs: &str, name: &str) -> (PathBuf, PathBuf) {
    let text = std::fs::read_to_string("graphs/mis_slam.toml").unwrap();
    let node = text
        .find("plugin = \"fusion.surfel\"")
        .expect("a fusion.surfel node");
    let start = node + text[node..].find("inputs = ").expect("its inputs") + "inputs = ".len();
    let end = start + text[start..].find('\n').unwrap();
    let graph = format!("{}{inputs}{}", &text[..start], &text[end..]);
    let dir = common::tmp_dir(name);
    let path = dir.join("graph.toml");
    std::fs::write(&path, graph).unwrap();
    (dir, path)
}

#[test]
fn the_model_is_output_in_the_scope_frame_too() {
    // `camera_model = true`: `model_camera` is the world-frame model seen from fusion's pose.
    // Both exported at the end, with the pose of every frame; the last frame's pose must carry
    // each scope-frame surfel onto its world-frame one.
    let dir = common::run_with_sink(
        "graphs/mis_slam.toml",
        "scope",
        r#"{ model = "fusion.model_camera", pose = "fusion.pose" }"#,
        &["graph.frames.count=8", "fusion.camera_model=true"],
        "mis_slam_scope_frame",
    );
    let (n, moved) = common::assert_scope_frame(
        &dir.join("export/model/final.ply"),
        &dir.join("scope/model/final.ply"),
        &dir.join("scope/pose.txt"),
    );
    assert!(n > 1000, "{n} surfels");
    // The scope's frame is not the world's: the sweep moved the camera.
    assert!(moved > 1.0, "{moved}");
}

#[test]
fn the_visible_surfels_are_output_coloured_by_whether_the_solve_took_them() {
    // `visible_output = true` at 640x480, where the solve takes a share of the visible surfels
    // (`solve_points_per_node`): the last frame's cloud holds as many points as the frame's
    // `fusion.visible`, as many of them green as its `fusion.solve_points`, the rest grey.
    let dir = common::run_with_sink(
        "graphs/mis_slam.toml",
        "seen",
        r#"{ points = "fusion.visible", metrics = "fusion.info" }"#,
        &[
            "graph.frames.count=5",
            "src.width=640",
            "src.height=480",
            "src.focal_px=700",
            "depth.max_disparity=96",
            "fusion.visible_output=true",
        ],
        "mis_slam_visible",
    );
    let cloud = common::ply_vertices(&dir.join("seen/points/final.ply"));
    let jsonl = std::fs::read_to_string(dir.join("seen/metrics.jsonl")).unwrap();
    let last: serde_json::Value = serde_json::from_str(jsonl.lines().last().unwrap()).unwrap();
    let (visible, solved) = (
        last["fusion.visible"].as_f64().unwrap() as usize,
        last["fusion.solve_points"].as_f64().unwrap() as usize,
    );
    let green = cloud
        .iter()
        .filter(|(.., c)| *c == misslam_fusion_surfel::VISIBLE_SOLVED)
        .count();
    let grey = cloud
        .iter()
        .filter(|(.., c)| *c == misslam_fusion_surfel::VISIBLE_LEFT)
        .count();
    eprintln!(
        "visible: {} points, {green} taken by the solve, {grey} left out",
        cloud.len()
    );
    assert_eq!(cloud.len(), visible);
    assert_eq!(green, solved);
    assert_eq!(green + grey, visible);
    assert!(grey > 0 && solved > 1000, "{solved} of {visible}");
}

#[test]
fn fusion_on_a_static_scene_merges_instead_of_duplicating() {
    // Exact depth and pose of a still heart seen by a still scope: after the first frame every
    // depth sample lands on an existing surfel, so the model does not grow, and it stays on the
    // surface.
    let (dir, path) = mis_slam_with_fusion_inputs(
        r#"{ depth = "src.depth_gt", stereo = "src.stereo", pose = "src.pose_gt", features = "features.features" }"#,
        "fusion_static",
    );
    let sets = [
        "graph.frames.count=6",
        "src.trajectory=static",
        "src.heartbeat_mm=0",
        "src.breathing_mm=0",
    ]
    .map(String::from);
    let g = misslam::framework::graph::load(&path, &misslam::builtin_registry(), &sets).unwrap();
    let first = {
        let s1 = ["graph.frames.count=1".to_owned()];
        let g1 = misslam::framework::graph::load(&path, &misslam::builtin_registry(), &s1).unwrap();
        common::run_graph_ok(g1, &dir.join("one")).metrics.eval["fusion.surfels"]
    };
    let e = common::run_graph_ok(g, &dir.join("six")).metrics.eval;
    let (n, mean) = (e["fusion.surfels"], e["recon.mean_mm"]);
    eprintln!("static scene: {first} surfels after 1 frame, {n} after 6; recon {mean:.4} mm");
    assert!(n <= first * 1.02, "{first} -> {n}");
    assert!(mean < 0.05, "{mean}");
    assert_eq!(e["fusion.disagreeing_frames"], 0.0);
    // The same nodes in view frame after frame: each level's sparse pattern is laid out once
    // and its symbolic factorisation serves the solves after (5 solves, 2 levels).
    let layouts = e["fusion.layouts_per_solve"];
    eprintln!("static scene: {layouts:.2} layouts per solve");
    assert!(layouts > 0.0 && layouts <= 2.0 / 5.0 + 1e-9, "{layouts}");
}

#[test]
fn fusion_takes_post_processings_maps_or_lifts_the_depth_itself() {
    // The graph hands fusion post-processing's vertex and normal maps; without them fusion lifts
    // the same depth with the same step limit: the same run, to the bit.
    let sets = ["graph.frames.count=4".to_owned()];
    let load = |path: &std::path::Path| {
        misslam::framework::graph::load(path, &misslam::builtin_registry(), &sets).unwrap()
    };
    let (dir, own) = mis_slam_with_fusion_inputs(
        r#"{ depth = "post.depth", stereo = "src.stereo", pose = "track.pose", features = "features.features" }"#,
        "fusion_maps",
    );
    let text = std::fs::read_to_string("graphs/mis_slam.toml").unwrap();
    assert!(
        text.contains(r#"vertices = "post.vertices", normals = "post.normals""#),
        "the shipped graph wires the maps"
    );
    let shipped = load(std::path::Path::new("graphs/mis_slam.toml"));
    let with_maps = common::run_graph_ok(shipped, &dir.join("maps"))
        .metrics
        .eval;
    let lifted = common::run_graph_ok(load(&own), &dir.join("own"))
        .metrics
        .eval;
    assert_eq!(with_maps.len(), lifted.len());
    for (k, v) in &with_maps {
        assert_eq!(
            v.to_bits(),
            lifted[k].to_bits(),
            "{k}: {v} against {}",
            lifted[k]
        );
    }
    // One map without the other is an error naming both ports and the frame.
    let (dir, half) = mis_slam_with_fusion_inputs(
        r#"{ depth = "post.depth", vertices = "post.vertices", stereo = "src.stereo" }"#,
        "fusion_half_maps",
    );
    let report = common::run_graph(load(&half), &dir.join("run"));
    let err = report.error.expect("the run fails").to_string();
    assert!(
        err.contains("`vertices` and `normals`") && err.contains("frame 0"),
        "{err}"
    );
}

#[test]
fn a_search_distance_of_infinity_means_no_limit() {
    // `inf` is how a parameter says "no limit"; binning the surfels for the anchoring in the
    // keypoints' box grown by an infinite `anchor_distance_mm` once hung the run. Run on its own
    // thread, so that a hang fails the test instead of stalling the suite.
    let (tx, rx) = std::sync::mpsc::channel();
    std::thread::spawn(move || {
        let e = run(
            &[
                "graph.frames.count=4",
                "fusion.correspondences.anchor_distance_mm=inf",
            ],
            "infinite_anchor_distance",
        );
        let _ = tx.send(e);
    });
    let e = rx
        .recv_timeout(std::time::Duration::from_secs(300))
        .expect("the run ends");
    let (mean, anchors) = (e["recon.mean_mm"], e["fusion.anchors"]);
    eprintln!("anchor_distance_mm = inf: recon {mean:.4} mm, {anchors} anchors");
    assert!(mean.is_finite() && mean < 0.5, "{mean}");
    assert!(anchors > 0.0, "{anchors}");
}

#[test]
fn fusion_says_when_the_depth_stops_meeting_the_model() {
    // The scope jumps by up to 20 mm between frames but fusion is given no pose: the depth lands
    // beyond the association distance, most samples become new surfels, and that is counted.
    let (dir, path) = mis_slam_with_fusion_inputs(
        r#"{ depth = "src.depth_gt", stereo = "src.stereo" }"#,
        "fusion_disagree",
    );
    let sets = [
        "graph.frames.count=3",
        "src.sweep_mm=20",
        "src.sweep_period_s=0.1",
    ]
    .map(String::from);
    let g = misslam::framework::graph::load(&path, &misslam::builtin_registry(), &sets).unwrap();
    let e = common::run_graph_ok(g, &dir.join("run")).metrics.eval;
    let n = e["fusion.disagreeing_frames"];
    eprintln!("jumping scope without a pose: {n} of 2 fused frames disagreed");
    assert!(n >= 1.0, "{n}");
}

#[test]
fn a_wide_view_of_noisy_depth_keeps_the_model_together() {
    // f = 175 px at 320x240: twice the field of view of the graph's camera and half its
    // disparities, so about 1 mm of depth noise. With E_rot at the library's weight (1) nodes
    // flatten their noisy surfels onto planes; the node resets them to their nearest rotation and
    // reports it (without the reset the model came apart: 31 mm RMS after 20 frames). With the
    // node's default (10) no node collapses.
    let wide = ["graph.frames.count=20", "src.focal_px=175"];
    let e = run(&wide, "mis_slam_wide");
    let (mean, rms) = (e["recon.mean_mm"], e["recon.rms_mm"]);
    eprintln!(
        "wide view: recon {mean:.3} mm, RMS {rms:.3}, {} collapsed frames",
        e["fusion.collapsed_frames"]
    );
    assert!(mean < 1.2 && rms < 1.5, "recon {mean} mm, RMS {rms}");
    assert_eq!(e["fusion.collapsed_frames"], 0.0);
    let e = run(
        &[&wide[..], &["fusion.solver.weights.rot=1"]].concat(),
        "mis_slam_wide_rot1",
    );
    let (n, rms) = (e["fusion.collapsed_frames"], e["recon.rms_mm"]);
    eprintln!("wide view, w_rot 1: recon RMS {rms:.3} mm, {n} collapsed frames");
    assert!(n >= 1.0, "{n}");
    assert!(rms < 1.5, "RMS {rms}");
}

#[test]
fn a_sample_per_pixel_is_weighed_and_thinned_as_the_default_stride_is() {
    // `stride = 1` gives about 660 visible surfels per node, 14 times the default 4. The solve
    // takes one in ceil(660 / 48) of them (`solve_points_per_node`) and fits as with all of them
    // (20 frames: recon 0.1853 against 0.1844 mm, drift 0.319 against 0.314; fusion 17 against
    // 34 ms a frame on 2 cores).
    let dense = ["graph.frames.count=20", "fusion.stride=1"];
    let e = run(&dense, "mis_slam_stride1");
    let (mean, rms, drift) = (e["recon.mean_mm"], e["recon.rms_mm"], e["recon.drift_mm"]);
    let share = e["fusion.solve_points_share"];
    eprintln!(
        "stride 1: recon {mean:.3} mm, RMS {rms:.3}, drift {drift:.3}, solve share {share:.3}"
    );
    assert!(share > 0.05 && share < 0.15, "solve share {share}");
    assert!(mean < 0.25 && rms < 0.35, "recon {mean} mm, RMS {rms}");
    assert!(drift < 0.55, "drift {drift}");
    assert_eq!(e["fusion.collapsed_frames"], 0.0);
    // Every visible surfel in the solve: E_data scaled by its term count (`data_points_per_node`)
    // keeps its balance with E_rot and E_reg.
    let all = [&dense[..], &["fusion.solve_points_per_node=0"]].concat();
    let f = run(&all, "mis_slam_stride1_all");
    let (mean_all, drift_all) = (f["recon.mean_mm"], f["recon.drift_mm"]);
    eprintln!("stride 1, every surfel solved: recon {mean_all:.3} mm, drift {drift_all:.3}");
    assert_eq!(f["fusion.solve_points_share"], 1.0);
    assert!(
        (mean - mean_all).abs() < 0.05 * mean_all,
        "{mean} against {mean_all}"
    );
    assert!(
        (drift - drift_all).abs() < 0.1 * drift_all,
        "{drift} against {drift_all}"
    );
    assert_eq!(f["fusion.collapsed_frames"], 0.0);
    // Unscaled, nodes collapse (reset and reported) and the surface slides: material drift 0.96
    // against 0.31 mm after 20 frames.
    let e = run(
        &[&all[..], &["fusion.data_points_per_node=0"]].concat(),
        "mis_slam_stride1_unscaled",
    );
    let (n, drift) = (e["fusion.collapsed_frames"], e["recon.drift_mm"]);
    eprintln!("stride 1 unscaled: drift {drift:.3} mm, {n} collapsed frames");
    assert!(n >= 1.0, "{n}");
}

#[test]
fn mis_slam_runs_over_the_real_hamlyn_frames_without_failing() {
    // Real in-vivo frames 3 s apart: tracking is mostly lost (reported, never fused), and nothing
    // may crash, skip or produce a non-finite model.
    let Some(_) = common::data_set("hamlyn20") else {
        return;
    };
    for name in ["mis_slam_hamlyn", "robocentric_surf_hamlyn"] {
        hamlyn_run(name);
    }
}

fn hamlyn_run(name: &str) {
    let out = common::tmp_dir(name);
    let report = common::run_graph_file(&format!("graphs/{name}.toml"), &[], &out);
    eprintln!("{name}: {:?}", report.metrics.eval);
    assert_eq!(report.metrics.frames.processed, 17);
    assert_eq!(report.metrics.frames.skipped, 0);
    let e = &report.metrics.eval;
    assert!(e["fusion.surfels"] > 1000.0, "{e:?}");
    // The trajectory: one line per frame, lost frames as comments (never a guessed pose).
    let traj = std::fs::read_to_string(out.join("export/pose.txt")).expect("pose.txt written");
    assert_eq!(traj.lines().count(), 17);
    assert!(
        traj.lines()
            .any(|l| l.starts_with("# frame") && l.ends_with("lost")),
        "{traj}"
    );
    assert!(
        traj.lines().next().is_some_and(|l| l.starts_with("0 ")),
        "{traj}"
    );
    let nv = common::finite_ply_vertices(&out.join("export/model/final.ply"));
    assert_eq!(nv as f64, e["fusion.surfels"]);
}

#[test]
fn a_sweep_over_the_same_tissue_keeps_one_surfel_per_sample() {
    // 40 frames of the default sweep see little new tissue: the model stays near one view's
    // samples (80 x 60 at stride 4) instead of piling up duplicates where a sample's own cell
    // holds no surfel after the view moved (11,700 surfels after 50 frames before the
    // neighbouring cells were searched; about 4,400 now).
    let e = run(&["graph.frames.count=40"], "mis_slam_sweep_bounded");
    let n = e["fusion.surfels"];
    eprintln!(
        "mis_slam, 40 frames: {n} surfels, {} nodes",
        e["fusion.nodes"]
    );
    assert!(n > 3000.0 && n < 6000.0, "{n} surfels");
    assert_eq!(e["fusion.disagreeing_frames"], 0.0);
}

#[test]
fn a_five_thousand_frame_sweep_stays_bounded_and_accurate() {
    // Issue 7: over 5,000 frames of the sweep the model and the graph stay bounded (about 5,600
    // surfels and 118 nodes at the end), no frame disagrees with the model, and the
    // reconstruction stays within a fifth of a millimetre of the surface. Shorter runs do not
    // show every failure: a change that kept the surfels' bindings after the graph grew
    // (session 22) passed every other test, and this run diverged from frame 3,622 on (90,091
    // surfels, 2,018 nodes, recon 69.8 mm); binding again only the surfels a new node reaches
    // (sessions 32 and 35) ended with collapsed nodes on 2 frames, as fusion moves canonical
    // positions away from where they were bound, until those moved past `rebind_distance_mm`
    // were bound again too. About 2 minutes on 2 cores, pipelined.
    let e = run(
        &[
            "graph.frames.count=5000",
            "src.frames=5000",
            "graph.pipeline=2",
        ],
        "mis_slam_5000",
    );
    let (surfels, nodes) = (e["fusion.surfels"], e["fusion.nodes"]);
    eprintln!(
        "mis_slam, 5,000 frames: {surfels} surfels, {nodes} nodes, recon {:.3} mm, drift {:.2} mm, {} frames disagreeing",
        e["recon.mean_mm"], e["recon.drift_mm"], e["fusion.disagreeing_frames"]
    );
    assert!(surfels < 7000.0, "{surfels} surfels");
    assert!(nodes < 150.0, "{nodes} nodes");
    assert_eq!(e["fusion.disagreeing_frames"], 0.0);
    assert_eq!(e["fusion.collapsed_frames"], 0.0);
    assert_eq!(e["tracking.lost_pct"], 0.0);
    assert!(e["recon.mean_mm"] < 0.2, "recon {}", e["recon.mean_mm"]);
    assert!(e["recon.drift_mm"] < 3.5, "drift {}", e["recon.drift_mm"]);
}

#[test]
fn the_model_and_the_graph_stay_within_their_caps() {
    // A wide, quick sweep keeps showing new tissue: uncapped, the graph grows from its 75 first
    // nodes and the model past 5,000 surfels; capped, both hold (and the persistent keypoint
    // anchors, `correspondences.max_anchors`) and the run goes on.
    let wide = [
        "graph.frames.count=12",
        "src.sweep_mm=30",
        "src.sweep_period_s=1.5",
    ];
    let free = run(&wide, "mis_slam_uncapped");
    let mut capped_sets = wide.to_vec();
    capped_sets.extend([
        "fusion.max_surfels=4500",
        "fusion.max_nodes=80",
        "fusion.correspondences.max_anchors=100",
    ]);
    let capped = run(&capped_sets, "mis_slam_caps");
    eprintln!(
        "uncapped: {} surfels, {} nodes, {} keypoint anchors; capped: {} surfels, {} nodes, {} anchors",
        free["fusion.surfels"],
        free["fusion.nodes"],
        free["fusion.anchors"],
        capped["fusion.surfels"],
        capped["fusion.nodes"],
        capped["fusion.anchors"]
    );
    assert!(free["fusion.nodes"] > 100.0 && free["fusion.surfels"] > 5000.0);
    assert!(capped["fusion.surfels"] <= 4500.0);
    assert!(free["fusion.anchors"] > 100.0 && capped["fusion.anchors"] <= 100.0);
    // The cap stops growth; one growth step may overshoot it by the nodes it adds at once.
    assert!(
        capped["fusion.nodes"] <= 80.0 + 15.0,
        "{}",
        capped["fusion.nodes"]
    );
    assert!(capped["recon.mean_mm"] < 1.0);
}

#[test]
fn robocentric_surf_runs_end_to_end_within_the_targets() {
    // graphs/robocentric_surf.toml: ELAS (robotics, sub-pixel), dense SURF with its matches as
    // refined E_corr constraints, the stereo tracker, the batch ED solve and surfel fusion, with
    // the phantom's default sensor noise, 40 frames. When the anchors took the SURF stereo points
    // and the refined targets the depth, the correspondences twisted the node affines until a
    // few surfels ended hundreds of mm off (RMS 107 mm at 40 frames), which the RMS bound
    // catches; the material drift must be below the same run's without the correspondences.
    let run = |name: &str, sets: &[&str]| {
        let out = common::tmp_dir(name);
        let sets: Vec<String> = sets.iter().map(|s| s.to_string()).collect();
        let report = common::run_graph_file("graphs/robocentric_surf.toml", &sets, &out);
        (out, report.metrics.eval)
    };
    let (out, e) = run("robocentric_surf", &["graph.frames.count=40"]);
    let (_, plain) = run(
        "robocentric_surf_plain",
        &[
            "graph.frames.count=40",
            "fusion.correspondences.enabled=false",
        ],
    );
    eprintln!(
        "robocentric_surf, 40 frames: recon {:.3} mm (RMS {:.3}, world {:.3} mm), drift {:.3} mm ({:.3} without E_corr), ATE {:.3} mm, {} surfels, {:.0} correspondences per solve",
        e["recon.mean_mm"],
        e["recon.rms_mm"],
        e["recon_world.mean_mm"],
        e["recon.drift_mm"],
        plain["recon.drift_mm"],
        e["tracking.ate_mm"],
        e["fusion.surfels"],
        e["fusion.correspondences_per_solve"]
    );
    assert!(e["recon.mean_mm"] < 0.3, "{}", e["recon.mean_mm"]);
    assert!(e["recon.rms_mm"] < 0.5, "{}", e["recon.rms_mm"]);
    assert!(
        e["fusion.correspondences_per_solve"] > 300.0,
        "{}",
        e["fusion.correspondences_per_solve"]
    );
    assert!(
        e["recon.drift_mm"] < plain["recon.drift_mm"],
        "drift {} with E_corr, {} without",
        e["recon.drift_mm"],
        plain["recon.drift_mm"]
    );
    assert_eq!(e["tracking.lost_pct"], 0.0);
    assert!(e["fusion.surfels"] > 1000.0);
    assert!(out.join("export/model/final.ply").is_file());
    assert!(out.join("export/model/final.glb").is_file());
}

#[test]
fn the_pipelined_schedule_reconstructs_what_the_serial_one_does() {
    // `graph.pipeline = 3`: three frames in the graph at once, each level on its own thread. The
    // nodes see the same frames in the same order, so every figure and the exported model must be
    // bit for bit those of the serial schedule: for MIS-SLAM (ORB, decoupled ED) and for the
    // robocentric graph, whose SURF node reuses its descriptor sampler once no frame holds it.
    for graph in ["mis_slam", "robocentric_surf"] {
        let run = |pipeline: &str| {
            let out = common::tmp_dir(&format!("{graph}_pipeline{pipeline}"));
            let sets = vec![
                "graph.frames.count=8".to_owned(),
                format!("graph.pipeline={pipeline}"),
            ];
            let report = common::run_graph_file(&format!("graphs/{graph}.toml"), &sets, &out);
            assert_eq!(report.metrics.pipeline.to_string(), pipeline);
            assert_eq!(report.metrics.frames.processed, 8);
            let ply = std::fs::read(out.join("export/model/final.ply")).expect("final.ply");
            (report.metrics.eval, ply)
        };
        let (serial, serial_ply) = run("1");
        let (piped, piped_ply) = run("3");
        assert!(serial.len() > 10, "{serial:?}");
        for (k, v) in &serial {
            assert_eq!(
                piped.get(k).map(|p| p.to_bits()),
                Some(v.to_bits()),
                "{graph}: {k}: serial {v}, pipelined {:?}",
                piped.get(k)
            );
        }
        assert_eq!(piped.len(), serial.len());
        assert!(
            piped_ply == serial_ply,
            "{graph}: the exported models differ"
        );
    }
}
