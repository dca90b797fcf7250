#![allow(clippy::unwrap_used)]
//! `graphs/tracking_orb.toml` end to end: ORB on both views, the stereo tracker, scored by
//! `eval.tracking` against the phantom's ground-truth pose.

mod common;

#[test]
fn tracking_orb_graph_on_a_rigid_sweep_is_sub_half_millimetre() {
    let out = common::tmp_dir("tracking_orb_rigid");
    let sets = [
        "graph.frames.count=60",
        "src.heartbeat_mm=0",
        "src.breathing_mm=0",
    ]
    .map(String::from);
    let report = common::run_graph_file("graphs/tracking_orb.toml", &sets, &out);
    let eval = &report.metrics.eval;
    let ate = eval["tracking.ate_mm"];
    let point = eval["tracking.point_err_mm"];
    eprintln!(
        "tracking_orb, rigid sweep, 60 frames: ATE {ate:.3} mm, tracked points {point:.3} mm"
    );
    assert!(ate < 0.5, "ATE {ate} mm");
    // The 3D keypoints the deformation stage receives, against the GT surface at their pixels.
    assert!(point < 0.5, "point error {point} mm");
    assert_eq!(eval["tracking.lost_pct"], 0.0);
    assert!(report.metrics.timing_ms.contains_key("track"));
}

#[test]
fn tracking_on_the_beating_heart_is_bounded_by_the_tissue_motion() {
    // The heart's surface moves by up to 3 mm (heartbeat) and 1 mm (breathing) across most of
    // the view: a rigid tracker follows the tissue, so its error against the scope's true pose
    // is of the order of that motion (this is what the deformation stage then explains), and it
    // must not drift beyond it.
    let out = common::tmp_dir("tracking_orb_heart");
    let sets = ["graph.frames.count=60".to_owned()];
    let report = common::run_graph_file("graphs/tracking_orb.toml", &sets, &out);
    let eval = &report.metrics.eval;
    let ate = eval["tracking.ate_mm"];
    eprintln!("tracking_orb, beating heart, 60 frames: ATE {ate:.3} mm");
    assert!(ate.is_finite() && ate < 4.0, "ATE {ate} mm");
    assert_eq!(eval["tracking.lost_pct"], 0.0);
}

#[test]
fn tracking_surf_graph_on_a_rigid_sweep_is_sub_half_millimetre() {
    // One line differs from tracking_orb.toml: the feature plugin (and its parameters).
    let out = common::tmp_dir("tracking_surf_rigid");
    let sets = [
        "graph.frames.count=40",
        "src.heartbeat_mm=0",
        "src.breathing_mm=0",
    ]
    .map(String::from);
    let report = common::run_graph_file("graphs/tracking_surf.toml", &sets, &out);
    let eval = &report.metrics.eval;
    let ate = eval["tracking.ate_mm"];
    eprintln!("tracking_surf, rigid sweep, 40 frames: ATE {ate:.3} mm");
    assert!(ate < 0.5, "ATE {ate} mm");
    assert_eq!(eval["tracking.lost_pct"], 0.0);
}

#[test]
fn swapping_the_feature_plugin_by_set_runs() {
    // `--set features.plugin=features.surf` on the ORB graph: the shared parameters
    // (`detector.n_features`, `stereo.*`) mean nothing else has to change.
    let out = common::tmp_dir("tracking_swap");
    let sets = ["graph.frames.count=4", "features.plugin=features.surf"].map(String::from);
    let report = common::run_graph_file("graphs/tracking_orb.toml", &sets, &out);
    assert_eq!(report.metrics.frames.processed, 4);
    assert_eq!(report.metrics.eval["tracking.lost_pct"], 0.0);
}

#[test]
fn eval_tracking_cli_agrees_with_the_eval_node() {
    // The trajectory the graph writes, scored by `misslam eval tracking` against the GT of a
    // phantom export of the same sequence, gives the node's ATE and RPE.
    let out = common::tmp_dir("tracking_cli");
    let sets = [
        "graph.frames.count=12",
        "src.heartbeat_mm=0",
        "src.breathing_mm=0",
    ]
    .map(String::from);
    let report = common::run_graph_file("graphs/tracking_orb.toml", &sets, &out);
    let data = common::tmp_dir("tracking_cli_gt");
    let params: misslam::framework::toml::Table = misslam::framework::toml::from_str(
        "scene = \"heart\"\ntrajectory = \"sweep\"\nheartbeat_mm = 0.0\nbreathing_mm = 0.0\nframes = 12",
    )
    .unwrap();
    misslam::phantom_export::export(&params, 7, &data).unwrap();
    let s = misslam::eval_cli::eval_tracking(
        &out.join("files/pose.txt"),
        &data.join("poses_gt.txt"),
        misslam_eval_tracking::Align::Rigid,
    )
    .unwrap();
    let e = &report.metrics.eval;
    assert_eq!(s.frames, 12);
    assert!(
        (s.ate_mm - e["tracking.ate_mm"]).abs() < 1e-4,
        "{} vs {}",
        s.ate_mm,
        e["tracking.ate_mm"]
    );
    assert!((s.rpe_mm - e["tracking.rpe_mm"]).abs() < 1e-4);
    // A malformed line is an error naming the file and line.
    let bad = out.join("bad.txt");
    std::fs::write(&bad, "0 1 2 3 0 0 0 1\n1 1 2 x 0 0 0 1\n").unwrap();
    let err = misslam::eval_cli::read_tum(&bad).unwrap_err();
    assert!(err.contains("bad.txt:2"), "{err}");
}
