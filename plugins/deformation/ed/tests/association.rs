#![allow(clippy::unwrap_used)]
//! The projective association (the solver's pass) and the visible set, both computed in groups
//! of points whose scan pixels are loaded together, against their plain point-by-point
//! definition, on a sheet that leaves the image on two sides, seen through a scan with holes,
//! with a point count that is no multiple of the groups or the chunks.

mod common;

use common::*;
use misslam_deformation_ed::observe::visible_points;
use misslam_deformation_ed::*;
use misslam_framework::nalgebra::{Isometry3, Point3, Translation3, UnitQuaternion, Vector3};

/// The pixel a camera-frame point meets, written out (rounded to the nearest).
fn pixel(k: &Intrinsics, p: &Vector3<f64>) -> Option<usize> {
    if p.z.is_nan() || p.z <= 1e-6 {
        return None;
    }
    let u = (k.fx * p.x / p.z + k.cx).round();
    let v = (k.fy * p.y / p.z + k.cy).round();
    if u < 0.0 || v < 0.0 || u >= k.width as f64 || v >= k.height as f64 {
        return None;
    }
    Some(v as usize * k.width as usize + u as usize)
}

fn f64s(a: [f32; 3]) -> Vector3<f64> {
    Vector3::new(a[0] as f64, a[1] as f64, a[2] as f64)
}

#[test]
fn grouped_association_and_visible_set_match_their_point_by_point_definition() {
    // 103 x 79 points at 1 mm, 60 mm away: wider than the 160 x 120 view.
    let sheet = Sheet::new(103, 79, 6.0);
    let mut graph = sheet.graph.clone();
    let mut rng = Lcg(11);
    for p in graph.warp.iter_mut() {
        for x in p.iter_mut() {
            *x += 0.02 * rng.next();
        }
    }
    let moved: Vec<Vector3<f64>> = sheet
        .points
        .iter()
        .map(|p| p + Vector3::new(0.4, -0.3, 0.9 + 0.02 * p.x))
        .collect();
    let mut maps = render(&moved, &sheet.tris, &Isometry3::identity());
    // Holes in the scan: every 7th pixel invalid in the vertices, every 11th in the normals.
    for i in (0..maps.0.len()).step_by(7) {
        maps.0[i] = [f32::NAN; 3];
    }
    for i in (3..maps.1.len()).step_by(11) {
        maps.1[i] = [f32::NAN; 3];
    }
    let pose = Isometry3::from_parts(
        Translation3::new(0.3, -0.2, 0.1),
        UnitQuaternion::from_euler_angles(0.01, -0.015, 0.02),
    );
    let k = intrinsics();
    let n = sheet.points.len();
    assert!(!n.is_multiple_of(1024) && !n.is_multiple_of(32) && n > 4 * 1024);
    let cfw = pose.inverse();
    let rot = cfw.rotation.to_rotation_matrix();
    let nm = graph.normal_matrices();
    // The warp and the map into the camera folded into each node, as the pass and the visible
    // set compute them: within rounding of the warp and then the map.
    let cam = graph.framed(&cfw);
    let (max_d, max_angle) = (2.0, 40.0f64);
    let cos_max = max_angle.to_radians().cos();
    // Point by point: the warped point, its pixel, the scan there, the two tests.
    let mut want_visible = Vec::new();
    let (mut want_assoc, mut want_cost, mut outside) = (0usize, 0.0f64, 0usize);
    for i in 0..n {
        let b = &sheet.bindings[i];
        let p = cam.point(&sheet.points[i], b);
        let p_two_steps = (cfw * Point3::from(graph.warp_point(&sheet.points[i], b))).coords;
        assert!((p - p_two_steps).norm() <= 1e-12 * p.norm(), "point {i}");
        let Some(idx) = pixel(&k, &p) else {
            outside += 1;
            continue;
        };
        let (q, sn) = (maps.0[idx], maps.1[idx]);
        if !q.iter().chain(&sn).all(|c| c.is_finite()) {
            continue;
        }
        let (q, sn) = (f64s(q), f64s(sn));
        let nc = cam.normal(&sheet.normals[i], b);
        let nc_two_steps = rot * graph.warp_normal(&sheet.normals[i], b, &nm);
        assert!((nc - nc_two_steps).norm() <= 1e-12, "normal {i}");
        let facing = nc.dot(&sn) >= cos_max;
        if (p - q).norm() <= max_d && facing {
            want_visible.push(i as u32);
        }
        if (p - q).norm_squared() <= max_d * max_d && facing {
            want_assoc += 1;
            want_cost += sn.dot(&(p - q)).powi(2);
        }
    }
    assert!(outside > 1000, "{outside} points outside the view");
    assert!(want_assoc > 2000, "{want_assoc} associations");

    let visible = visible_points(
        &graph,
        &sheet.points,
        &sheet.normals,
        &sheet.bindings,
        &pose,
        &k,
        &maps.0,
        &maps.1,
        max_d,
        max_angle,
    );
    assert_eq!(visible, want_visible);

    // The pass: data terms alone, so the cost at the start is the projective cost.
    let problem = Problem {
        model: ModelPoints {
            points: &sheet.points,
            normals: &sheet.normals,
            bindings: &sheet.bindings,
        },
        scan: Some(scan(&maps)),
        field: None,
        correspondences: &[],
        pose_prior: pose,
    };
    let params = SolverParams {
        max_distance_mm: max_d,
        max_normal_angle_deg: max_angle,
        weights: Weights {
            rot: 0.0,
            reg: 0.0,
            ..Default::default()
        },
        ..Default::default()
    };
    let set = SolveSet::all(&graph, false);
    let mut solver = Solver::default();
    let (_, _, _, cost) = solver
        .linearize_dense(&graph, &pose, &problem, &set, &params)
        .unwrap();
    assert_eq!(solver.associations(), want_assoc);
    assert!(
        (cost - want_cost).abs() <= 1e-12 * want_cost,
        "cost {cost} against {want_cost}"
    );
}
