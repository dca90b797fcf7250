//! `misslam bench ed-scaling`: the thesis's Fig. 5.9, batch against decoupled ED on a growing map.

/// One frame of `misslam bench ed-scaling`.
#[derive(Clone, Debug, serde::Serialize)]
pub struct EdScalingRow {
    /// Frame index.
    pub frame: usize,
    /// Nodes in the map (both solvers grow the same graph).
    pub total_nodes: usize,
    /// Model points in the map.
    pub map_points: usize,
    /// Model points visible this frame.
    pub visible_points: usize,
    /// Nodes the batch solver solved (all).
    pub batch_solved: usize,
    /// Batch solve time, ms.
    pub batch_ms: f64,
    /// Batch: Gauss-Newton / LM iterations run.
    pub batch_iterations: usize,
    /// Batch: assembly time summed over the iterations, ms.
    pub batch_assemble_ms: f64,
    /// Batch: numeric factorisation and triangular solves summed over the iterations, ms.
    pub batch_factor_ms: f64,
    /// Batch: mean distance of every map point from its GT position, mm.
    pub batch_err_mm: f64,
    /// Batch: mean distance from GT over the map points in view this frame, mm.
    pub batch_seen_err_mm: f64,
    /// Nodes the decoupled solver solved (PR plus the PI rings).
    pub decoupled_solved: usize,
    /// Decoupled solve time (both levels), ms.
    pub decoupled_ms: f64,
    /// Decoupled: mean distance of every map point from its GT position, mm.
    pub decoupled_err_mm: f64,
    /// Decoupled: mean distance from GT over the map points in view this frame, mm.
    pub decoupled_seen_err_mm: f64,
}

/// Options of the ED scaling benchmark.
#[derive(Clone, Debug)]
pub struct EdScalingParams {
    /// Frames.
    pub frames: usize,
    /// Camera advance along the strip per frame, mm.
    pub advance_mm: f64,
    /// Node spacing, mm.
    pub spacing_mm: f64,
    /// Model point spacing, mm.
    pub point_step_mm: f64,
    /// Solver iterations per frame.
    pub iterations: usize,
    /// Batch: factorise all 12 unknowns of every node (no elimination of the data-free nodes'
    /// affine parts), to time what that elimination saves.
    pub full_factorisation: bool,
}

impl Default for EdScalingParams {
    fn default() -> Self {
        EdScalingParams {
            frames: 30,
            advance_mm: 110.0,
            spacing_mm: 5.0,
            point_step_mm: 1.5,
            iterations: 3,
            full_factorisation: false,
        }
    }
}

/// The thesis's Fig. 5.9 experiment: a tissue strip 60 mm wide, 60 mm below a camera that moves
/// along it; the map (every point seen so far) and its graph grow each frame while the camera sees
/// a bounded window. The tissue breathes under the camera (a 2.5 mm bump that follows it and
/// pulses) and rests elsewhere. Per frame the batch and the decoupled solver each update their own
/// copy of the warp from the same exact depth (ray-cast analytically), and are scored against the
/// GT position of every map point. Every 15th visible point also gets its exact GT target as a
/// sparse correspondence (what feature matches provide).
pub fn ed_scaling(p: &EdScalingParams) -> Result<Vec<EdScalingRow>, String> {
    use misslam_deformation_ed::observe::visible_points;
    use misslam_deformation_ed::*;
    use misslam_framework::nalgebra::{Isometry3, Translation3, Vector3};
    const Z0: f64 = 60.0;
    const HALF_W: f64 = 30.0;
    let rest_h = |x: f64, y: f64| 2.0 * (x / 15.0).sin() * (y / 20.0).cos();
    let rest_grad = |x: f64, y: f64| {
        (
            2.0 / 15.0 * (x / 15.0).cos() * (y / 20.0).cos(),
            -2.0 / 20.0 * (x / 15.0).sin() * (y / 20.0).sin(),
        )
    };
    // GT displacement (z only) at frame f: a bump centred under the camera.
    let bump = |x: f64, y: f64, cam_x: f64, f: usize| {
        let a = 2.5 * (0.6 + 0.4 * (f as f64 * 0.9).sin());
        a * (-((x - cam_x).powi(2) + y * y) / (2.0 * 15.0f64.powi(2))).exp()
    };
    let bump_grad = |x: f64, y: f64, cam_x: f64, f: usize| {
        let b = bump(x, y, cam_x, f);
        (-b * (x - cam_x) / 225.0, -b * y / 225.0)
    };
    let k = Intrinsics {
        fx: 300.0,
        fy: 300.0,
        cx: 159.5,
        cy: 119.5,
        width: 320,
        height: 240,
    };
    let window = (k.width as f64 / 2.0) / k.fx * (Z0 + 4.0) + 2.0;
    let mut points: Vec<Vector3<f64>> = Vec::new();
    let mut normals: Vec<Vector3<f64>> = Vec::new();
    let mut covered_to = f64::NEG_INFINITY;
    let mut batch_graph: Option<EdGraph> = None;
    let mut dec_graph: Option<EdGraph> = None;
    let mut batch = Solver::default();
    batch.set_full_factorisation(p.full_factorisation);
    let mut dec = DecoupledSolver::default();
    let params = SolverParams {
        max_iterations: p.iterations,
        ..Default::default()
    };
    let gp = GraphParams {
        spacing: p.spacing_mm,
        ..Default::default()
    };
    let mut rows = Vec::new();
    // The first frame sees a longer stretch (so the map starts near 1,000 nodes).
    let start = -(p.advance_mm * 3.0).max(window);
    for f in 0..p.frames {
        let cam_x = f as f64 * p.advance_mm;
        // New map points: everything from the last covered x to the window's far edge.
        let from = if f == 0 { start } else { covered_to };
        let to = cam_x + window;
        let mut x = (from / p.point_step_mm).ceil() * p.point_step_mm;
        let first_new = points.len();
        while x <= to {
            let mut y = -HALF_W;
            while y <= HALF_W {
                let (gx, gy) = rest_grad(x, y);
                points.push(Vector3::new(x, y, Z0 + rest_h(x, y)));
                normals.push(Vector3::new(gx, gy, -1.0).normalize());
                y += p.point_step_mm;
            }
            x += p.point_step_mm;
        }
        covered_to = x;
        let new = &points[first_new..];
        match (&mut batch_graph, &mut dec_graph) {
            (Some(b), Some(d)) => {
                b.grow(new);
                d.grow(new);
            }
            _ => {
                batch_graph = Some(EdGraph::from_points(new, gp.clone())?);
                dec_graph = batch_graph.clone();
            }
        }
        let (Some(bg), Some(dg)) = (batch_graph.as_mut(), dec_graph.as_mut()) else {
            return Err("no graph".into());
        };
        if bg.topology_version() != dg.topology_version() || bg.len() != dg.len() {
            return Err("the two graphs grew differently".into());
        }
        // Bindings of all points against the (grown) graph; both graphs share the topology.
        let bindings = bg.bind_all(&points);
        // The scan: exact ray cast of the deformed strip from the camera at (cam_x, 0, 0).
        let (w, h) = (k.width as usize, k.height as usize);
        let mut verts = vec![[f32::NAN; 3]; w * h];
        let mut norms = vec![[f32::NAN; 3]; w * h];
        for v in 0..h {
            for u in 0..w {
                let (rx, ry) = ((u as f64 - k.cx) / k.fx, (v as f64 - k.cy) / k.fy);
                let mut z = Z0;
                for _ in 0..30 {
                    let (x, y) = (cam_x + rx * z, ry * z);
                    z = Z0 + rest_h(x, y) + bump(x, y, cam_x, f);
                }
                let (x, y) = (cam_x + rx * z, ry * z);
                if y.abs() > HALF_W {
                    continue;
                }
                let (gx, gy) = rest_grad(x, y);
                let (bx, by) = bump_grad(x, y, cam_x, f);
                let n = Vector3::new(gx + bx, gy + by, -1.0).normalize();
                verts[v * w + u] = [(x - cam_x) as f32, y as f32, z as f32];
                norms[v * w + u] = [n.x as f32, n.y as f32, n.z as f32];
            }
        }
        let pose = Isometry3::from_parts(Translation3::new(cam_x, 0.0, 0.0), Default::default());
        let truth: Vec<Vector3<f64>> = points
            .iter()
            .map(|q| q + Vector3::new(0.0, 0.0, bump(q.x, q.y, cam_x, f)))
            .collect();
        // In view: the true point projects into the image (the strip is a height field, nothing
        // occludes). The rest of the map is unseen: its GT relaxes back to rest as the bump moves
        // on, which no solver can observe, so the whole-map error mixes in that memory.
        let in_view: Vec<usize> = (0..points.len())
            .filter(|&i| {
                let c = truth[i] - Vector3::new(cam_x, 0.0, 0.0);
                let (u, v) = (k.fx * c.x / c.z + k.cx, k.fy * c.y / c.z + k.cy);
                u >= 0.0 && v >= 0.0 && u <= (k.width - 1) as f64 && v <= (k.height - 1) as f64
            })
            .collect();
        let dist =
            |g: &EdGraph, i: usize| (g.warp_point(&points[i], &bindings[i]) - truth[i]).norm();
        let err =
            |g: &EdGraph| (0..points.len()).map(|i| dist(g, i)).sum::<f64>() / points.len() as f64;
        let seen_err = |g: &EdGraph| {
            in_view.iter().map(|&i| dist(g, i)).sum::<f64>() / in_view.len().max(1) as f64
        };
        let mut solve =
            |g: &mut EdGraph, decoupled: bool| -> Result<(usize, f64, usize, Info), String> {
                let vis = visible_points(
                    g, &points, &normals, &bindings, &pose, &k, &verts, &norms, 5.0, 60.0,
                );
                let mut l = ModelSubset::default();
                l.gather(&vis, &points, &normals, &bindings);
                // Sparse correspondences on every 15th visible point (what feature matches give;
                // point-to-plane alone cannot see sliding along the surface).
                let corr: Vec<Correspondence> = vis
                    .iter()
                    .step_by(15)
                    .map(|&i| Correspondence {
                        point: points[i as usize],
                        binding: bindings[i as usize],
                        target: truth[i as usize] - Vector3::new(cam_x, 0.0, 0.0),
                        normal: None,
                    })
                    .collect();
                let problem = Problem {
                    model: l.view(),
                    scan: Some(Scan {
                        intrinsics: k,
                        vertices: &verts,
                        normals: &norms,
                    }),
                    field: None,
                    correspondences: &corr,
                    pose_prior: pose,
                };
                let mut ps = pose;
                let t = std::time::Instant::now();
                let (solved, info) = if decoupled {
                    dec.solve(g, &mut ps, &problem, &params, &DecoupledParams::default())?;
                    let i = dec.solve_info();
                    (i.pr_nodes + i.pi_solved, i.combined())
                } else {
                    let set = SolveSet::all(g, false);
                    let info = batch.solve(g, &mut ps, &problem, &set, &params)?;
                    (info.solved_nodes, info)
                };
                Ok((solved, t.elapsed().as_secs_f64() * 1e3, vis.len(), info))
            };
        let (bs, bms, nvis, binfo) = solve(bg, false)?;
        let (ds, dms, _, _) = solve(dg, true)?;
        rows.push(EdScalingRow {
            frame: f,
            total_nodes: bg.len(),
            map_points: points.len(),
            visible_points: nvis,
            batch_solved: bs,
            batch_ms: bms,
            batch_iterations: binfo.iterations,
            batch_assemble_ms: binfo.ms_assemble,
            batch_factor_ms: binfo.ms_factor,
            batch_err_mm: err(bg),
            batch_seen_err_mm: seen_err(bg),
            decoupled_solved: ds,
            decoupled_ms: dms,
            decoupled_err_mm: err(dg),
            decoupled_seen_err_mm: seen_err(dg),
        });
    }
    Ok(rows)
}
