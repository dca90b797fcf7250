#![allow(clippy::unwrap_used)]
//! The solver's derivatives on a small constructed scene: the analytic gradient of every term
//! against finite differences, the parallel assembly against the serial reference on any number
//! of threads, the Gauss-Newton Hessian against finite differences at a zero residual.

mod common;

use common::*;
use misslam_deformation_ed::graph::rigid_warp;
use misslam_deformation_ed::solver::{pose_update, reg_residual, rot_residuals};
use misslam_deformation_ed::*;
use misslam_framework::nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// `graph` with every warp parameter moved by up to `amp`, pseudo-randomly from `seed`.
fn perturbed(graph: &EdGraph, seed: u64, amp: f64) -> EdGraph {
    let mut graph = graph.clone();
    let mut rng = Lcg(seed);
    for p in graph.warp.iter_mut() {
        for x in p.iter_mut() {
            *x += amp * rng.next();
        }
    }
    graph
}

/// The largest difference between the analytic gradient `g` (with its node slots) and central
/// finite differences of the cost at the solver's last association, over every node unknown,
/// relative to the gradient's largest entry.
fn worst_node_gradient_error(
    solver: &Solver,
    graph: &EdGraph,
    pose: &Isometry3<f64>,
    problem: &Problem,
    set: &SolveSet,
    params: &SolverParams,
    (g, slot): (&[f64], &[u32]),
) -> f64 {
    let h = 1e-6;
    let scale = g.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let mut worst = 0.0f64;
    for j in 0..graph.len() {
        for q in 0..12 {
            let mut gp = graph.clone();
            gp.warp[j][q] += h;
            let cp = solver.cost_fixed_association(&gp, pose, problem, set, params);
            gp.warp[j][q] -= 2.0 * h;
            let cm = solver.cost_fixed_association(&gp, pose, problem, set, params);
            let fd = (cp - cm) / (2.0 * h) / 2.0;
            worst = worst.max((fd - g[12 * slot[j] as usize + q]).abs() / scale);
        }
    }
    worst
}

#[test]
fn analytic_gradient_matches_finite_differences_for_every_term() {
    let s = small_scene();
    let graph = perturbed(&s.graph, 7, 0.03);
    let prior = Isometry3::from_parts(
        Translation3::new(0.2, -0.1, 0.3),
        UnitQuaternion::from_euler_angles(0.01, -0.02, 0.015),
    );
    let pose = Isometry3::from_parts(
        Translation3::new(0.1, 0.05, -0.2),
        UnitQuaternion::from_euler_angles(-0.01, 0.01, 0.0),
    );
    for robust in [Robust::None, Robust::Huber, Robust::Cauchy] {
        let problem = Problem {
            model: ModelPoints {
                points: &s.points,
                normals: &s.normals,
                bindings: &s.bindings,
            },
            scan: Some(scan(&s.maps)),
            field: Some(&s.field),
            correspondences: &s.corr,
            pose_prior: prior,
        };
        // The exact derivative of the field term is its gradient (the default `normal`
        // Jacobian leaves out its part along the surface on purpose).
        let params = SolverParams {
            optimize_pose: true,
            robust,
            robust_scale_mm: 0.3,
            field_jacobian: FieldJacobian::Gradient,
            weights: Weights {
                pose_rot: 0.0,
                pose_trans: 2.0,
                point_to_point: 0.1,
                corr_normal: 0.3,
                ..Default::default()
            },
            ..Default::default()
        };
        let set = SolveSet::all(&graph, true);
        let mut solver = Solver::default();
        let (_, g, slot, _) = solver
            .linearize_dense(&graph, &pose, &problem, &set, &params)
            .unwrap();
        assert!(
            solver.associations() > 100,
            "{} associations",
            solver.associations()
        );
        let h = 1e-6;
        let scale = g.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let mut worst =
            worst_node_gradient_error(&solver, &graph, &pose, &problem, &set, &params, (&g, &slot));
        let off = 12 * graph.len();
        for q in 0..6 {
            let mut xi = [0.0; 6];
            xi[q] = h;
            let cp = solver.cost_fixed_association(
                &graph,
                &pose_update(&pose, &xi),
                &problem,
                &set,
                &params,
            );
            xi[q] = -h;
            let cm = solver.cost_fixed_association(
                &graph,
                &pose_update(&pose, &xi),
                &problem,
                &set,
                &params,
            );
            let fd = (cp - cm) / (2.0 * h) / 2.0;
            // The pose-prior rotation Jacobian is the identity approximation of J_r^-1 (exact at
            // zero residual); with a residual of 0.03 rad it is off by O(r^2).
            worst = worst.max((fd - g[off + q]).abs() / scale);
        }
        assert!(
            worst < 1e-5,
            "{robust:?}: worst relative gradient error {worst:e}"
        );
    }
}

#[test]
fn the_unseen_parts_weights_enter_the_gradient_and_only_where_no_data_binds() {
    // The sheet's points on its left third feed the data terms: the nodes only the others bind
    // take `weights.rot_unseen` and their edges `weights.reg_unseen`.
    let s = small_scene();
    let graph = perturbed(&s.graph, 11, 0.03);
    let (lo, hi) = s.points.iter().fold((f64::MAX, f64::MIN), |(lo, hi), p| {
        (lo.min(p.x), hi.max(p.x))
    });
    let cut = lo + (hi - lo) / 3.0;
    let half: Vec<usize> = (0..s.points.len())
        .filter(|&i| s.points[i].x < cut)
        .collect();
    let hp: Vec<Vector3<f64>> = half.iter().map(|&i| s.points[i]).collect();
    let hn: Vec<Vector3<f64>> = half.iter().map(|&i| s.normals[i]).collect();
    let hb: Vec<Binding> = half.iter().map(|&i| s.bindings[i]).collect();
    let hc: Vec<Correspondence> = s.corr.iter().filter(|c| c.point.x < cut).cloned().collect();
    let mut bound = vec![false; graph.len()];
    for b in hb.iter().chain(hc.iter().map(|c| &c.binding)) {
        for &x in &b.nodes[..b.len as usize] {
            bound[x as usize] = true;
        }
    }
    let unbound = bound.iter().filter(|&&b| !b).count();
    assert!(
        unbound > 1 && unbound + 1 < graph.len(),
        "{unbound} of {} nodes unbound",
        graph.len()
    );
    let pose = Isometry3::identity();
    let half_problem = Problem {
        model: ModelPoints {
            points: &hp,
            normals: &hn,
            bindings: &hb,
        },
        scan: Some(scan(&s.maps)),
        field: Some(&s.field),
        correspondences: &hc,
        pose_prior: pose,
    };
    let params =
        |rot: f64, reg: f64, rot_unseen: Option<f64>, reg_unseen: Option<f64>| SolverParams {
            field_jacobian: FieldJacobian::Gradient,
            weights: Weights {
                rot,
                reg,
                rot_unseen,
                reg_unseen,
                ..Default::default()
            },
            ..Default::default()
        };
    let split = params(1.0, 10.0, Some(30.0), Some(3.0));
    let set = SolveSet::all(&graph, false);
    let mut solver = Solver::default();
    let (_, g, slot, cost) = solver
        .linearize_dense(&graph, &pose, &half_problem, &set, &split)
        .unwrap();
    let worst = worst_node_gradient_error(
        &solver,
        &graph,
        &pose,
        &half_problem,
        &set,
        &split,
        (&g, &slot),
    );
    assert!(worst < 1e-5, "worst relative gradient error {worst:e}");
    // The cost is E_rot at 30 on the unbound nodes and at 1 on the others, E_reg at 3 on the
    // edges with an unbound end (both directions), plus the data terms.
    let (_, _, _, plain) = Solver::default()
        .linearize_dense(
            &graph,
            &pose,
            &half_problem,
            &set,
            &params(1.0, 10.0, None, None),
        )
        .unwrap();
    let mut extra = 0.0;
    for j in 0..graph.len() {
        if !bound[j] {
            let (r, _) = rot_residuals(&graph.warp[j]);
            extra += 29.0 * r.iter().map(|x| x * x).sum::<f64>();
        }
        for &k in graph.neighbors(j) {
            if !bound[j] || !bound[k as usize] {
                extra -= 7.0 * reg_residual(&graph, j as u32, k).norm_squared();
            }
        }
    }
    assert!(
        (cost - plain - extra).abs() < 1e-9 * cost,
        "{cost} against {plain} + {extra}"
    );
    // Every node bound (the whole sheet feeds the data): the unseen weights change nothing.
    let full_problem = Problem {
        model: ModelPoints {
            points: &s.points,
            normals: &s.normals,
            bindings: &s.bindings,
        },
        correspondences: &s.corr,
        ..half_problem
    };
    let lin = |set: &SolveSet, p: &SolverParams| {
        Solver::default()
            .linearize_dense(&graph, &pose, &full_problem, set, p)
            .unwrap()
    };
    assert_eq!(lin(&set, &split), lin(&set, &params(1.0, 10.0, None, None)));
    // No data term in the solve (every node unbound): they replace w_rot and w_reg everywhere.
    let no_data = SolveSet {
        data: false,
        ..set.clone()
    };
    assert_eq!(
        lin(&no_data, &split),
        lin(&no_data, &params(30.0, 3.0, None, None))
    );
}

#[test]
fn the_parallel_assembly_equals_the_serial_reference_on_any_number_of_threads() {
    // Every data term (projective with point-to-point rows, field, correspondences), the pose,
    // a robust kernel, a perturbed warp; once over every node, once over a subset with the rest
    // held fixed (the decoupled solver's level I shape, some couplings half outside).
    let s = small_scene();
    let graph = perturbed(&s.graph, 11, 0.02);
    let pose = Isometry3::from_parts(
        Translation3::new(0.1, 0.05, -0.2),
        UnitQuaternion::from_euler_angles(-0.01, 0.01, 0.02),
    );
    let problem = Problem {
        model: ModelPoints {
            points: &s.points,
            normals: &s.normals,
            bindings: &s.bindings,
        },
        scan: Some(scan(&s.maps)),
        field: Some(&s.field),
        correspondences: &s.corr,
        pose_prior: Isometry3::identity(),
    };
    let params = SolverParams {
        optimize_pose: true,
        robust: Robust::Huber,
        robust_scale_mm: 0.3,
        weights: Weights {
            point_to_point: 0.1,
            corr_normal: 0.3,
            ..Default::default()
        },
        ..Default::default()
    };
    // Both Jacobians of the field term; they must give different systems.
    let [normal, gradient] =
        [FieldJacobian::Normal, FieldJacobian::Gradient].map(|field_jacobian| {
            let params = SolverParams {
                field_jacobian,
                ..params.clone()
            };
            parallel_equals_serial(&graph, &pose, &problem, &params)
        });
    assert!(normal != gradient, "the field Jacobian made no difference");
}

fn parallel_equals_serial(
    graph: &EdGraph,
    pose: &Isometry3<f64>,
    problem: &Problem,
    params: &SolverParams,
) -> Vec<f64> {
    let all = SolveSet::all(graph, true);
    let subset = SolveSet {
        free: (0..graph.len() as u32).filter(|j| j % 3 != 1).collect(),
        reg_edges: all.reg_edges.clone(),
        data: true,
        pose: false,
    };
    let pool = |n| {
        rayon::ThreadPoolBuilder::new()
            .num_threads(n)
            .build()
            .unwrap()
    };
    for set in [&all, &subset] {
        let (h_ref, g_ref, _, _) = Solver::default()
            .linearize_dense_reference(graph, pose, problem, set, params)
            .unwrap();
        let run = |threads| {
            pool(threads).install(|| {
                Solver::default()
                    .linearize_dense(graph, pose, problem, set, params)
                    .unwrap()
            })
        };
        let (h1, g1, _, _) = run(1);
        let (h3, g3, _, _) = run(3);
        assert!(
            h1 == h3 && g1 == g3,
            "the system depends on the thread count"
        );
        let hs = h_ref.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        let gs = g_ref.iter().fold(0.0f64, |m, x| m.max(x.abs()));
        assert!(hs > 0.0 && gs > 0.0);
        let eh = h1
            .iter()
            .zip(&h_ref)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        let eg = g1
            .iter()
            .zip(&g_ref)
            .fold(0.0f64, |m, (a, b)| m.max((a - b).abs()));
        assert!(
            eh <= 1e-12 * hs && eg <= 1e-12 * gs,
            "free {}: Hessian off by {eh:e} of {hs:e}, gradient by {eg:e} of {gs:e}",
            set.free.len()
        );
    }
    // One solver reused on problems of other sizes and sets (its buffers keep the values of the
    // last one) assembles what a fresh solver does: half the points and correspondences, then
    // all of them again, with the pose and without, and without the field at poses moved 2 and
    // 5 mm along the view, where part or all of the points find no scan point within reach
    // (their terms must not be the last problem's).
    let m = &problem.model;
    let half = m.points.len() / 2;
    let smaller = Problem {
        model: ModelPoints {
            points: &m.points[..half],
            normals: &m.normals[..half.min(m.normals.len())],
            bindings: &m.bindings[..half],
        },
        correspondences: &problem.correspondences[..problem.correspondences.len() / 2],
        ..*problem
    };
    let with_pose = SolveSet {
        pose: true,
        ..all.clone()
    };
    let no_field = Problem {
        field: None,
        ..*problem
    };
    let moved = |mm: f64| pose * Translation3::new(0.0, 0.0, mm);
    let mut reused = Solver::default();
    for (p, set, pose) in [
        (problem, &with_pose, *pose),
        (&smaller, &subset, *pose),
        (&no_field, &all, moved(2.0)),
        (problem, &all, *pose),
        (&no_field, &with_pose, moved(5.0)),
        (&smaller, &with_pose, *pose),
    ] {
        let fresh = Solver::default()
            .linearize_dense(graph, &pose, p, set, params)
            .unwrap();
        let again = reused
            .linearize_dense(graph, &pose, p, set, params)
            .unwrap();
        assert!(
            fresh.0 == again.0 && fresh.1 == again.1,
            "a reused solver assembled another system ({} points, {} free)",
            p.model.points.len(),
            set.free.len()
        );
    }
    Solver::default()
        .linearize_dense(graph, pose, problem, &all, params)
        .unwrap()
        .1
}

#[test]
fn gauss_newton_hessian_matches_finite_differences_at_a_zero_residual() {
    // State: every node carries the same rigid motion, the scan is that motion of the sheet, the
    // correspondences are exact and the pose equals the prior: every residual is zero, so the cost's
    // Hessian is exactly 2 J^T W J.
    let Sheet {
        points,
        tris,
        normals,
        mut graph,
        bindings,
    } = Sheet::new(21, 15, 7.0);
    let (r, t) = rigid(0.02, -0.03, 0.05, [0.5, -0.3, 1.0]);
    for j in 0..graph.len() {
        graph.warp[j] = rigid_warp(&r, &t, &graph.nodes()[j]);
    }
    let moved: Vec<Vector3<f64>> = points.iter().map(|p| r * p + t).collect();
    let maps = render(&moved, &tris, &Isometry3::identity());
    let corr: Vec<Correspondence> =
        correspondences(&points, &bindings, (0..points.len()).step_by(29), |i| {
            moved[i]
        });
    let pose = Isometry3::identity();
    let problem = Problem {
        model: ModelPoints {
            points: &points,
            normals: &normals,
            bindings: &bindings,
        },
        scan: Some(scan(&maps)),
        field: None,
        correspondences: &corr,
        pose_prior: pose,
    };
    let params = SolverParams {
        optimize_pose: true,
        weights: Weights {
            point_to_point: 0.0,
            pose_rot: 30.0,
            pose_trans: 3.0,
            ..Default::default()
        },
        ..Default::default()
    };
    let set = SolveSet::all(&graph, true);
    let mut solver = Solver::default();
    let (hm, g, slot, cost) = solver
        .linearize_dense(&graph, &pose, &problem, &set, &params)
        .unwrap();
    assert!(cost < 1e-6, "residuals are not zero: cost {cost}");
    let n = g.len();
    // Column of the Hessian for a few unknowns by central differences of the analytic gradient.
    let h = 1e-5;
    let mut worst = 0.0f64;
    let hscale = hm.iter().fold(0.0f64, |m, x| m.max(x.abs()));
    let probes: Vec<(usize, usize)> = (0..graph.len())
        .step_by(3)
        .flat_map(|j| [(j, 0), (j, 3), (j, 6), (j, 11)])
        .collect();
    for &(j, q) in &probes {
        let mut gp = graph.clone();
        gp.warp[j][q] += h;
        let mut sp = Solver::default();
        let (_, g_plus, _, _) = sp
            .linearize_dense(&gp, &pose, &problem, &set, &params)
            .unwrap();
        gp.warp[j][q] -= 2.0 * h;
        let (_, g_minus, _, _) = sp
            .linearize_dense(&gp, &pose, &problem, &set, &params)
            .unwrap();
        let col = 12 * slot[j] as usize + q;
        for row in 0..n {
            let fd = (g_plus[row] - g_minus[row]) / (2.0 * h);
            worst = worst.max((fd - hm[row * n + col]).abs() / hscale);
        }
    }
    for q in 0..6 {
        let mut xi = [0.0; 6];
        xi[q] = h;
        let mut sp = Solver::default();
        let (_, g_plus, _, _) = sp
            .linearize_dense(&graph, &pose_update(&pose, &xi), &problem, &set, &params)
            .unwrap();
        xi[q] = -h;
        let (_, g_minus, _, _) = sp
            .linearize_dense(&graph, &pose_update(&pose, &xi), &problem, &set, &params)
            .unwrap();
        let col = 12 * graph.len() + q;
        for row in 0..n {
            let fd = (g_plus[row] - g_minus[row]) / (2.0 * h);
            worst = worst.max((fd - hm[row * n + col]).abs() / hscale);
        }
    }
    assert!(worst < 1e-4, "worst relative Hessian error {worst:e}");
}
