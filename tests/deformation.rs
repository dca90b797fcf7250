#![allow(clippy::unwrap_used)]
//! The ED nodes in a graph on the phantom, and the scaling benchmark on a short run.

mod common;

use misslam::framework::graph;
use std::path::Path;

fn run_deform(plugin: &str) -> serde_json::Value {
    let out = common::tmp_dir(&format!("deform-{plugin}"));
    let sets = vec![
        "graph.frames.count=6".to_string(),
        format!("ed.plugin={plugin}"),
    ];
    let report = common::run_graph_file("graphs/deform_heart.toml", &sets, &out);
    assert_eq!(report.metrics.frames.processed, 6);
    serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap()
}

#[test]
fn both_ed_solvers_track_the_phantom_heart_template() {
    for plugin in ["deformation.decoupled", "deformation.batch"] {
        let m = run_deform(plugin);
        let mean = m["eval"]["recon.mean_mm"].as_f64().unwrap();
        let p95 = m["eval"]["recon.p95_mm"].as_f64().unwrap();
        println!("{plugin}: recon.mean_mm {mean:.3}, p95 {p95:.3}");
        // Measured 0.16 / 0.44 mm over 30 frames (heartbeat 3 mm, sweeping scope).
        assert!(mean < 0.25 && p95 < 0.8, "{plugin}: mean {mean} p95 {p95}");
        assert!(
            m["timing_ms"]["ed"]["mean_ms"].is_f64(),
            "the ED node is timed"
        );
    }
}

#[test]
fn a_wrong_ed_parameter_is_rejected_with_its_name() {
    // Ranges are checked when the node is built, before any frame runs.
    let g = graph::load(
        Path::new("graphs/deform_heart.toml"),
        &misslam::builtin_registry(),
        &["ed.graph.point_neighbors=12".to_string()],
    )
    .unwrap();
    let Err(e) = misslam::framework::Runtime::build(g) else {
        panic!("point_neighbors = 12 was accepted");
    };
    let e = e.to_string();
    assert!(e.contains("point_neighbors"), "{e}");
}

#[test]
fn ed_scaling_decoupled_solves_a_bounded_set_while_the_map_grows() {
    let p = misslam::bench::EdScalingParams {
        frames: 4,
        ..Default::default()
    };
    let rows = misslam::bench::ed_scaling(&p).unwrap();
    assert_eq!(rows.len(), 4);
    for w in rows.windows(2) {
        assert!(w[1].total_nodes > w[0].total_nodes, "the map grows");
    }
    for r in &rows {
        assert_eq!(r.batch_solved, r.total_nodes);
        assert!(r.decoupled_solved < r.total_nodes / 3, "{r:?}");
        assert!(r.batch_err_mm < 0.4 && r.decoupled_err_mm < 0.4, "{r:?}");
        // Where the camera looks both solvers see the same data: the decoupled one must match the
        // batch one there (measured equal to 0.001 mm; the issue allows 10 %).
        assert!(r.batch_seen_err_mm < 0.1, "{r:?}");
        assert!(
            r.decoupled_seen_err_mm <= 1.1 * r.batch_seen_err_mm + 1e-3,
            "{r:?}"
        );
        assert!(r.batch_iterations >= 1, "{r:?}");
        assert!(
            r.batch_assemble_ms + r.batch_factor_ms <= r.batch_ms,
            "{r:?}"
        );
    }
    // The JSON the CLI writes carries every documented field.
    let v = serde_json::to_value(&rows[0]).unwrap();
    for k in [
        "frame",
        "total_nodes",
        "map_points",
        "visible_points",
        "batch_solved",
        "batch_ms",
        "batch_iterations",
        "batch_assemble_ms",
        "batch_factor_ms",
        "batch_err_mm",
        "batch_seen_err_mm",
        "decoupled_solved",
        "decoupled_ms",
        "decoupled_err_mm",
        "decoupled_seen_err_mm",
    ] {
        assert!(v.get(k).is_some(), "{k}");
    }
}
