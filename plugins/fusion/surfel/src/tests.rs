//! Tests of the node's own helpers: rebinding, the visible cloud, the local inverses.

use super::*;
use misslam_framework::nalgebra::Matrix3;

#[test]
fn surfels_moved_past_the_rebind_distance_or_reached_by_new_nodes_are_bound_again() {
    let pts: Vec<Vector3<f64>> = (0..900)
        .map(|i| Vector3::new((i % 30) as f64, (i / 30) as f64, 0.0))
        .collect();
    let mut graph = EdGraph::from_points(
        &pts,
        misslam_deformation_ed::graph::GraphParams {
            spacing: 4.0,
            ..Default::default()
        },
    )
    .unwrap();
    let mut bindings = graph.bind_all(&pts);
    let mut bound_at = pts.clone();
    // Fusion moves the canonical points after they were bound: by 0, 0.1, ..., 0.4 mm.
    let shift = |i: usize| 0.1 * (i % 5) as f64;
    let moved: Vec<Vector3<f64>> = pts
        .iter()
        .enumerate()
        .map(|(i, p)| p + Vector3::new(shift(i), 0.0, 0.0))
        .collect();
    let n = rebind(&graph, &moved, &mut bindings, &mut bound_at, None, 0.25);
    assert_eq!(n, 2 * 900 / 5);
    let fresh = graph.bind_all(&moved);
    for i in 0..pts.len() {
        if shift(i) > 0.25 {
            assert_eq!(bindings[i], fresh[i], "point {i}");
            assert_eq!(bound_at[i], moved[i]);
        } else {
            assert_eq!(bindings[i], graph.bind(&pts[i]), "point {i}");
            assert_eq!(bound_at[i], pts[i]);
        }
    }
    // A distance of 0 binds every moved point again; then the bindings are all fresh.
    let n = rebind(&graph, &moved, &mut bindings, &mut bound_at, None, 0.0);
    assert_eq!(n, 900 - 2 * 900 / 5 - 900 / 5);
    assert_eq!(bindings, fresh);
    // New nodes beyond one edge: the points they reach are bound again, and only those.
    let first_new = graph.len();
    let strip: Vec<Vector3<f64>> = (0..8)
        .map(|i| Vector3::new(36.0, 4.0 * i as f64, 0.0))
        .collect();
    assert!(graph.grow(&strip) > 0);
    let new = graph.new_nodes(first_new);
    let n = rebind(
        &graph,
        &moved,
        &mut bindings,
        &mut bound_at,
        Some(&new),
        1.0,
    );
    assert!(n > 0 && n < 300, "{n} rebound");
    assert_eq!(bindings, graph.bind_all(&moved));
}

#[test]
fn the_visible_cloud_colours_what_the_solve_took() {
    let live: Vec<Vector3<f64>> = (0..10).map(|i| Vector3::new(i as f64, 0.0, 1.0)).collect();
    let visible = [1, 3, 4, 7, 9];
    let c = visible_cloud_of(&visible, Some(&[3, 9]), &live);
    assert_eq!(c.positions, visible.map(|i| [i as f32, 0.0, 1.0]));
    let (s, l) = (VISIBLE_SOLVED, VISIBLE_LEFT);
    assert_eq!(c.colors, Some(vec![l, s, l, l, s]));
    // Without thinning the solve took every visible surfel.
    let c = visible_cloud_of(&visible, None, &live);
    assert_eq!(c.colors, Some(vec![s; 5]));
}

#[test]
fn local_inverses_undo_an_affine_warp() {
    // One node with A = diag(2, 1, 0.5) plus a rotation: A^-1 and A^T from its normal matrix.
    let a = Matrix3::new(0.0, -1.0, 0.0, 2.0, 0.0, 0.0, 0.0, 0.0, 0.5);
    let nm = vec![a.try_inverse().unwrap().transpose()];
    let mut b = Binding {
        nodes: [0; misslam_deformation_ed::graph::MAX_K],
        weights: [0.0; misslam_deformation_ed::graph::MAX_K],
        len: 1,
        ..Binding::EMPTY
    };
    b.weights[0] = 1.0;
    let (a_inv, a_t) = local_inverses(&b, &nm);
    assert!((a_inv * a - Matrix3::identity()).norm() < 1e-12);
    assert!((a_t - a.transpose()).norm() < 1e-12);
}
