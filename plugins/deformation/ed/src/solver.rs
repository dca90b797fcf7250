//! The energy (E_rot, E_reg, projective E_data, distance-field E_data, E_corr, E_r, E_p) with
//! analytic Jacobians, and the Gauss-Newton / Levenberg-Marquardt loop over a chosen set of solved
//! nodes. The batch solver solves every node; the decoupled solver calls the same loop twice on
//! complementary sets.
//!
//! Jacobian structure: with a node's unknowns laid out as the 3x4 matrix `[A_j | t_j]` row-major,
//! the derivative of a deformed point with respect to node j is `w_j I (x) u_j^T` with
//! `u_j = [v - g_j; 1]`. A residual row `a^T (p - q)` of a point therefore contributes
//! `w_j w_k (R a a^T R^T) (x) (u_j u_k^T)` to block (j, k) of J^T J: a 3x3 times a 4x4 outer product,
//! assembled without forming J. The pose update is right-multiplied, world_from_camera <-
//! world_from_camera * exp(xi), xi = (rho, omega), so d p_cam / d xi = [-I, \[p\]x].

use crate::assemble::DataAssembly;
use crate::evaluate::Pass;
use crate::graph::{Binding, EdGraph};
use crate::pairs::pattern_key;
use crate::priors::NodePriors;
use crate::problem::{FieldJacobian, Method, Problem, SolverParams};
use crate::residuals::pose_rot_residual;
pub use crate::residuals::{pose_update, reg_residual, rot_residuals};
use crate::system::{BlockSystem, PatternKey};
use misslam_framework::nalgebra::{Isometry3, Matrix3, Vector3};
use std::time::Instant;

/// What one solve did.
#[derive(Clone, Debug, Default, PartialEq)]
pub struct Info {
    /// Outer iterations run.
    pub iterations: usize,
    /// Cost at the start (with the first association).
    pub cost_before: f64,
    /// Cost at the end (with the last association).
    pub cost_after: f64,
    /// Cost after each accepted iteration.
    pub costs: Vec<f64>,
    /// Levenberg-Marquardt steps tried and rejected (each a factorisation, or a step from a kept
    /// one).
    pub rejected_steps: usize,
    /// Numeric factorisations computed.
    pub factorisations: usize,
    /// Steps taken with the factorisation of an earlier iteration
    /// ([`SolverParams::reuse_factorisation`]).
    pub reused_factorisations: usize,
    /// Nodes solved.
    pub solved_nodes: usize,
    /// Data residuals associated at the end (projective) plus field and correspondence terms.
    pub data_terms: usize,
    /// Symbolic factorisations computed in this solve (0 when the previous one was reused).
    pub symbolic_builds: usize,
    /// Milliseconds: association, assembly, factorisation plus solve, total.
    pub ms_associate: f64,
    /// Assembly time, ms (with the listing of the data terms' couplings under their blocks, once
    /// per solve, beside the first assembly's per-point terms).
    pub ms_assemble: f64,
    /// Numeric factorisation and triangular solves, ms.
    pub ms_factor: f64,
    /// The pattern key, the layout and its factor structures (the symbolic factorisation) when
    /// the pattern changed, and the zeroing of the system before each assembly, ms. The factor
    /// structures are built beside the first assembly: their time is in `ms_assemble` too.
    pub ms_prepare: f64,
    /// Whole solve, ms.
    pub ms_total: f64,
}

impl Info {
    /// The solve's parts as stage names and ms, as the fusion nodes report them under their
    /// `timing_ms` (`solve.associate`, `solve.assemble`, `solve.factor`, `solve.prepare`).
    pub fn stages(&self) -> [(&'static str, f64); 4] {
        [
            ("solve.associate", self.ms_associate),
            ("solve.assemble", self.ms_assemble),
            ("solve.factor", self.ms_factor),
            ("solve.prepare", self.ms_prepare),
        ]
    }
}

/// What an assembly writes.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Assembly {
    /// The blocks and the gradient, the data terms in parallel.
    Full,
    /// The gradient alone (the step reuses a kept factorisation).
    GradientOnly,
    /// The blocks and the gradient, the data terms point by point (the test reference).
    SerialReference,
}

/// Dense J^T W J (row-major), J^T W r, each node's block index (u32::MAX when fixed), cost.
pub type DenseLinearization = (Vec<f64>, Vec<f64>, Vec<u32>, f64);

/// Which nodes and terms one call of the loop solves.
#[derive(Clone, Debug, Default)]
pub struct SolveSet {
    /// Solved nodes, ascending ids.
    pub free: Vec<u32>,
    /// Directed regularisation edges (j, k) with at least one end solved (the other held fixed).
    pub reg_edges: Vec<(u32, u32)>,
    /// Use the data terms (projective, field, correspondences).
    pub data: bool,
    /// Solve the pose too.
    pub pose: bool,
}

impl SolveSet {
    /// Every node, every edge, all terms (the batch problem).
    pub fn all(graph: &EdGraph, pose: bool) -> Self {
        let free: Vec<u32> = (0..graph.len() as u32).collect();
        let mut reg_edges = Vec::new();
        for j in 0..graph.len() {
            for &k in graph.neighbors(j) {
                reg_edges.push((j as u32, k));
            }
        }
        SolveSet {
            free,
            reg_edges,
            data: true,
            pose,
        }
    }
}

/// Reusable solver state (the factorisation workspace; its symbolic part survives across calls
/// while the pattern is unchanged).
#[derive(Default)]
pub struct Solver {
    system: BlockSystem,
    /// Factorise every node's 12 unknowns (no elimination of the data-free affine parts).
    full_factorisation: bool,
    /// The pass at the current state (warped points, association, data cost) ...
    cur: Pass,
    /// ... and at a candidate step's state.
    next: Pass,
    data: DataAssembly,
    dx: Vec<f64>,
    saved: Vec<[f64; 12]>,
    /// The priors that depend on what binds each node (E_m, its unseen part, the unseen E_rot
    /// and E_reg weights), set once per solve.
    priors: NodePriors,
}

#[inline]
fn u_of(v: &Vector3<f64>, g: &Vector3<f64>) -> [f64; 4] {
    [v.x - g.x, v.y - g.y, v.z - g.z, 1.0]
}

impl Solver {
    /// Symbolic factorisations computed so far.
    pub fn symbolic_builds(&self) -> usize {
        self.system.symbolic_builds
    }

    /// With `true`, the sparse Cholesky factorises all 12 unknowns of every node instead of first
    /// eliminating the affine parts of the nodes no data term binds (see [`crate::system`]). The
    /// solution is the same to rounding; this exists to verify that and to time the difference.
    pub fn set_full_factorisation(&mut self, full: bool) {
        self.full_factorisation = full;
    }

    /// Unknowns the sparse factorisation saw in the last solve.
    pub fn factor_dim(&self) -> usize {
        self.system.factor_dim()
    }

    /// Runs the pass at the current state into `cur` (new association) and returns the cost.
    fn start(
        &mut self,
        graph: &EdGraph,
        problem: &Problem,
        pose: &Isometry3<f64>,
        set: &SolveSet,
        params: &SolverParams,
    ) -> f64 {
        if set.data {
            self.cur.run(graph, problem, pose, params, true, None);
        } else {
            self.cur = Pass::default();
        }
        self.cur.cost_new + other_cost(&self.priors, graph, problem, pose, set, params)
    }

    /// Block pattern of `set`: edges between solved nodes and pairs of solved nodes that share a point.
    fn pattern(&self, graph: &EdGraph, problem: &Problem, set: &SolveSet) -> PatternKey {
        pattern_key(graph, problem, set, self.full_factorisation)
    }

    /// Adds one point's residual rows: each row is (a, r, weight) with r = a . (p_cam - target)
    /// (or any residual whose derivative with respect to p_cam is a). `rows` share the point.
    #[allow(clippy::too_many_arguments)]
    fn add_point(
        sys: &mut BlockSystem,
        graph: &EdGraph,
        v: &Vector3<f64>,
        b: &Binding,
        p_cam: &Vector3<f64>,
        r_wc: &Matrix3<f64>,
        rows: &[(Vector3<f64>, f64, f64)],
        pose: bool,
    ) {
        // M_cam = sum w a a^T, b_cam = sum w a r, in the camera frame; world = R M R^T, R b.
        let mut m_cam = Matrix3::zeros();
        let mut b_cam = Vector3::zeros();
        for (a, r, w) in rows {
            m_cam += *w * a * a.transpose();
            b_cam += *w * *r * a;
        }
        let m_w = r_wc * m_cam * r_wc.transpose();
        let b_w = r_wc * b_cam;
        let m: [[f64; 3]; 3] = std::array::from_fn(|i| std::array::from_fn(|j| m_w[(i, j)]));
        let n = b.len as usize;
        let mut us = [[0.0; 4]; crate::graph::MAX_K];
        for a in 0..n {
            us[a] = u_of(v, &graph.nodes()[b.nodes[a] as usize]);
        }
        for a in 0..n {
            let sa = sys.slot[b.nodes[a] as usize];
            if sa == u32::MAX {
                continue;
            }
            let wa = b.weights[a];
            for c in a..n {
                let sc = sys.slot[b.nodes[c] as usize];
                if sc == u32::MAX {
                    continue;
                }
                let wc = b.weights[c];
                if a == c {
                    sys.add_kron(sa, sa, &m, &us[a], &us[a], wa * wa);
                } else if sa == sc {
                    // The same node twice in one binding (never for a proper k-NN): both orders.
                    sys.add_kron(sa, sa, &m, &us[a], &us[c], wa * wc);
                    sys.add_kron(sa, sa, &m, &us[c], &us[a], wa * wc);
                } else {
                    sys.add_kron(sa, sc, &m, &us[a], &us[c], wa * wc);
                }
            }
            let g = &mut sys.grad[12 * sa as usize..12 * sa as usize + 12];
            for mm in 0..3 {
                for c in 0..4 {
                    g[mm * 4 + c] += wa * b_w[mm] * us[a][c];
                }
            }
        }
        if pose {
            // J_xi per row = [-a^T, (a x p)^T]; cross = R sum w a J_xi.
            let off = 12 * sys.blocks_solved();
            let mut q_cam = [[0.0; 6]; 3];
            for (a, r, w) in rows {
                let axp = a.cross(p_cam);
                let jx = [-a.x, -a.y, -a.z, axp.x, axp.y, axp.z];
                for i in 0..6 {
                    for k in 0..=i {
                        sys.pose_block[i * 6 + k] += w * jx[i] * jx[k];
                    }
                    sys.grad[off + i] += w * jx[i] * r;
                    for (mm, q) in q_cam.iter_mut().enumerate() {
                        q[i] += w * a[mm] * jx[i];
                    }
                }
            }
            // Symmetrise the lower-triangle accumulation into the column-major upper storage.
            let mut q_w = [[0.0; 6]; 3];
            for i in 0..6 {
                for mm in 0..3 {
                    q_w[mm][i] = (0..3).map(|s| r_wc[(mm, s)] * q_cam[s][i]).sum();
                }
            }
            for a in 0..n {
                let sa = sys.slot[b.nodes[a] as usize];
                if sa == u32::MAX {
                    continue;
                }
                let wa = b.weights[a];
                let cross = &mut sys.pose_cross[sa as usize];
                for pc in 0..6 {
                    for mm in 0..3 {
                        for c in 0..4 {
                            cross[pc * 12 + mm * 4 + c] += wa * us[a][c] * q_w[mm][pc];
                        }
                    }
                }
            }
        }
    }

    /// Assembles J^T W J and J^T W r of `set` at the current state: E_rot, E_reg and the pose
    /// priors here, the data terms by the parallel [`DataAssembly`] (or, with `reference`, point
    /// by point through [`Self::add_point`], the serial reference it is tested against).
    fn assemble(
        &mut self,
        graph: &EdGraph,
        problem: &Problem,
        pose: &Isometry3<f64>,
        set: &SolveSet,
        params: &SolverParams,
        mode: Assembly,
    ) {
        let grad_only = mode == Assembly::GradientOnly;
        let reference = mode == Assembly::SerialReference;
        let w = &params.weights;
        let pw = self.priors.weights(params);
        let sys = &mut self.system;
        // E_rot.
        for &j in &set.free {
            let s = sys.slot[j as usize];
            let (r, jac) = rot_residuals(&graph.warp[j as usize]);
            let w_rot = pw.rot(j);
            let mut h = [0.0; 144];
            for a in 0..12 {
                for c in 0..12 {
                    let mut acc = 0.0;
                    for q in 0..6 {
                        acc += jac[q][a] * jac[q][c];
                    }
                    h[c * 12 + a] = w_rot * acc;
                }
                let g: f64 = (0..6).map(|q| jac[q][a] * r[q]).sum();
                sys.grad[12 * s as usize + a] += w_rot * g;
            }
            if !grad_only {
                sys.add_diag(s, &h);
            }
        }
        // E_reg: r = A_j (g_k - g_j) + g_j + t_j - g_k - t_k.
        const E4: [f64; 4] = [0.0, 0.0, 0.0, 1.0];
        for &(j, k) in &set.reg_edges {
            let r = reg_residual(graph, j, k);
            let w_reg = pw.reg(j, k);
            let d = graph.nodes()[k as usize] - graph.nodes()[j as usize];
            let u = [d.x, d.y, d.z, 1.0];
            let (sj, sk) = (sys.slot[j as usize], sys.slot[k as usize]);
            if sj != u32::MAX {
                if !grad_only {
                    sys.add_kron_identity(sj, sj, &u, &u, w_reg);
                }
                for m in 0..3 {
                    for c in 0..4 {
                        sys.grad[12 * sj as usize + m * 4 + c] += w_reg * r[m] * u[c];
                    }
                }
            }
            if sk != u32::MAX {
                if !grad_only {
                    sys.add_kron_identity(sk, sk, &E4, &E4, w_reg);
                }
                for m in 0..3 {
                    sys.grad[12 * sk as usize + m * 4 + 3] -= w_reg * r[m];
                }
            }
            if sj != u32::MAX && sk != u32::MAX && !grad_only {
                sys.add_kron_identity(sj, sk, &u, &E4, -w_reg);
            }
        }
        // E_m and its unseen part: r = t_j - t_j^0.
        for &(j, t0, wm) in self.priors.motion_ref() {
            let s = sys.slot[j as usize];
            if s == u32::MAX {
                continue;
            }
            let p = &graph.warp[j as usize];
            let r = Vector3::new(p[3], p[7], p[11]) - t0;
            let mut h = [0.0; 144];
            for a in 0..3 {
                let q = a * 4 + 3;
                h[q * 12 + q] = wm;
                sys.grad[12 * s as usize + q] += wm * r[a];
            }
            if !grad_only {
                sys.add_diag(s, &h);
            }
        }
        if set.data && !reference {
            self.data.assemble(
                sys, graph, problem, pose, set.pose, params, &self.cur, grad_only,
            );
        }
        if set.data && reference {
            let cfw = pose.inverse();
            let r_wc = *pose.rotation.to_rotation_matrix().matrix();
            let model = &problem.model;
            let c = params.robust_scale_mm;
            for a in &self.cur.assoc {
                let i = a.i as usize;
                let vw = graph.warp_point(&model.points[i], &model.bindings[i]);
                let p = (cfw * misslam_framework::nalgebra::Point3::from(vw)).coords;
                let d = p - a.q;
                let rn = a.n.dot(&d);
                let r2 = rn * rn + w.point_to_point * d.norm_squared();
                let (rw, _) = params.robust.weight_cost(r2.sqrt(), c);
                let wd = w.data * rw;
                let pp = w.point_to_point * wd;
                let rows = [
                    (a.n, rn, wd),
                    (Vector3::x(), d.x, pp),
                    (Vector3::y(), d.y, pp),
                    (Vector3::z(), d.z, pp),
                ];
                let used = if w.point_to_point > 0.0 {
                    &rows[..]
                } else {
                    &rows[..1]
                };
                Self::add_point(
                    sys,
                    graph,
                    &model.points[i],
                    &model.bindings[i],
                    &p,
                    &r_wc,
                    used,
                    set.pose,
                );
            }
            if let Some(field) = problem.field {
                let nm = graph.normal_matrices();
                for i in 0..model.points.len() {
                    let vw = graph.warp_point(&model.points[i], &model.bindings[i]);
                    let p = (cfw * misslam_framework::nalgebra::Point3::from(vw)).coords;
                    if let Some((dv, grad)) = crate::assemble::sample_field(field, &p, params) {
                        let grad = match params.field_jacobian {
                            FieldJacobian::Gradient | FieldJacobian::FieldNormal => grad,
                            FieldJacobian::Normal => {
                                let n = cfw.rotation
                                    * graph.warp_normal(&model.normals[i], &model.bindings[i], &nm);
                                n * n.dot(&grad)
                            }
                        };
                        let (rw, _) = params.robust.weight_cost(dv.abs(), c);
                        let rows = [(grad, dv, w.field * rw)];
                        Self::add_point(
                            sys,
                            graph,
                            &model.points[i],
                            &model.bindings[i],
                            &p,
                            &r_wc,
                            &rows,
                            set.pose,
                        );
                    }
                }
            }
            for corr in problem.correspondences {
                let vw = graph.warp_point(&corr.point, &corr.binding);
                let p = (cfw * misslam_framework::nalgebra::Point3::from(vw)).coords;
                let (r3, norm) = corr.rows(&p, w.corr_normal);
                let (rw, _) = params.robust.weight_cost(norm, c);
                let wc = w.corr * rw;
                let rows = r3.map(|(dir, r, f)| (dir, r, wc * f));
                Self::add_point(
                    sys,
                    graph,
                    &corr.point,
                    &corr.binding,
                    &p,
                    &r_wc,
                    &rows,
                    set.pose,
                );
            }
        }
        if set.pose {
            let off = 12 * sys.blocks_solved();
            // E_r: d log(R~^T R exp(w)) / d w ~ I; E_p: d (T + R rho) / d rho = R.
            let rr = pose_rot_residual(&problem.pose_prior, pose);
            let rt = pose.translation.vector - problem.pose_prior.translation.vector;
            let rt_cam = pose.rotation.inverse() * rt;
            for i in 0..3 {
                if !grad_only {
                    sys.pose_block[i * 6 + i] += w.pose_trans;
                    sys.pose_block[(3 + i) * 6 + 3 + i] += w.pose_rot;
                }
                sys.grad[off + i] += w.pose_trans * rt_cam[i];
                sys.grad[off + 3 + i] += w.pose_rot * rr[i];
            }
            // The pose block was accumulated as lower triangle (i >= k) in row-major i * 6 + k,
            // which is the upper triangle in column-major: k * 6 + i with k <= i. Nothing to do.
        }
    }

    /// Diagnostics: associates at the current state, assembles `set` and returns the dense
    /// J^T W J (row-major), J^T W r, each node's block index (u32::MAX when fixed) and the cost.
    /// The cost's gradient is 2 J^T W r; at a zero residual its Hessian is 2 J^T W J.
    pub fn linearize_dense(
        &mut self,
        graph: &EdGraph,
        pose: &Isometry3<f64>,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
    ) -> Result<DenseLinearization, String> {
        self.linearize(graph, pose, problem, set, params, false)
    }

    /// [`Self::linearize_dense`] with the data terms assembled point by point, serially: the
    /// reference the parallel assembly is tested against.
    #[doc(hidden)]
    pub fn linearize_dense_reference(
        &mut self,
        graph: &EdGraph,
        pose: &Isometry3<f64>,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
    ) -> Result<DenseLinearization, String> {
        self.linearize(graph, pose, problem, set, params, true)
    }

    fn linearize(
        &mut self,
        graph: &EdGraph,
        pose: &Isometry3<f64>,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
        reference: bool,
    ) -> Result<DenseLinearization, String> {
        self.priors.set(graph, problem, set, params);
        let key = self.pattern(graph, problem, set);
        self.system.prepare(graph.len(), &key)?;
        if set.data {
            self.data.invalidate();
        }
        let cost = self.start(graph, problem, pose, set, params);
        let mode = if reference {
            Assembly::SerialReference
        } else {
            Assembly::Full
        };
        self.assemble(graph, problem, pose, set, params, mode);
        Ok((
            self.system.to_dense(),
            self.system.grad.clone(),
            self.system.slot.clone(),
            cost,
        ))
    }

    /// Diagnostics: the cost of `set` at the given state with the association of the last
    /// [`Self::linearize_dense`] (for finite differences).
    pub fn cost_fixed_association(
        &self,
        graph: &EdGraph,
        pose: &Isometry3<f64>,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
    ) -> f64 {
        let mut pass = Pass::default();
        if set.data {
            pass.run(graph, problem, pose, params, false, Some(&self.cur));
        }
        pass.cost_old + other_cost(&self.priors, graph, problem, pose, set, params)
    }

    /// Number of projective associations at the last association.
    pub fn associations(&self) -> usize {
        self.cur.assoc.len()
    }

    /// Runs the loop on `set`, updating `graph.warp` and `pose` in place.
    pub fn solve(
        &mut self,
        graph: &mut EdGraph,
        pose: &mut Isometry3<f64>,
        problem: &Problem,
        set: &SolveSet,
        params: &SolverParams,
    ) -> Result<Info, String> {
        params.validate()?;
        let t0 = Instant::now();
        let mut info = Info {
            solved_nodes: set.free.len(),
            ..Default::default()
        };
        if problem.model.points.len() != problem.model.bindings.len() {
            return Err(format!(
                "{} model points but {} bindings",
                problem.model.points.len(),
                problem.model.bindings.len()
            ));
        }
        if let Some(field) = problem.field {
            if params.field_jacobian == FieldJacobian::FieldNormal
                && field.normals.len() != field.values.len()
            {
                return Err(
                    "`field_jacobian = \"field_normal\"` needs a distance field built with its normals (DistanceField::from_maps_with_normals)"
                        .into(),
                );
            }
        }
        if let Some(scan) = &problem.scan {
            let n = (scan.intrinsics.width * scan.intrinsics.height) as usize;
            if scan.vertices.len() != n || scan.normals.len() != n {
                return Err(format!(
                    "the scan has {} vertices and {} normals for {}x{} pixels",
                    scan.vertices.len(),
                    scan.normals.len(),
                    scan.intrinsics.width,
                    scan.intrinsics.height
                ));
            }
        }
        let builds0 = self.system.symbolic_builds;
        let tp = Instant::now();
        self.priors.set(graph, problem, set, params);
        // The first pass (the association at the start) and the other terms' starting cost need
        // no system: they run beside the pattern key and the system's layout. A new layout's
        // factor structures (the elimination plan, the scalar layouts and the symbolic
        // factorisation, serial) are built later, beside the first assembly, which needs the
        // layout only. Each side reports its own time, so the two overlap in `Info`.
        let mut cur = std::mem::take(&mut self.cur);
        let (system, full) = (&mut self.system, self.full_factorisation);
        let priors = &self.priors;
        let ((key, prepared), (other, ms_pass)) = rayon::join(
            || {
                let key = pattern_key(graph, problem, set, full);
                let r = system.prepare_deferred(graph.len(), &key);
                (key, (r, tp.elapsed().as_secs_f64() * 1e3))
            },
            || {
                let ta = Instant::now();
                if set.data {
                    cur.run(graph, problem, pose, params, true, None);
                } else {
                    cur = Pass::default();
                }
                let other = other_cost(priors, graph, problem, pose, set, params);
                (other, ta.elapsed().as_secs_f64() * 1e3)
            },
        );
        self.cur = cur;
        let mut factor_job = prepared.0?;
        info.ms_prepare += prepared.1;
        if set.data {
            self.data.invalidate();
        }
        let mut cost = self.cur.cost_new + other;
        info.ms_associate += ms_pass;
        info.cost_before = cost;
        let mut lambda = match params.method {
            Method::GaussNewton => 0.0,
            Method::LevenbergMarquardt => params.initial_lambda,
        };
        let mut reuses_left = 0;
        for iteration in 0..params.max_iterations {
            info.iterations += 1;
            // The first iteration's system was laid out and zeroed beside the first pass.
            if iteration > 0 {
                let tp = Instant::now();
                self.system.prepare(graph.len(), &key)?;
                info.ms_prepare += tp.elapsed().as_secs_f64() * 1e3;
            }
            // With the factorisation kept from the iteration before, the first attempt needs the
            // gradient only (the blocks are assembled if that step is rejected).
            let mut grad_only = reuses_left > 0 && self.system.is_factored();
            let tb = Instant::now();
            let mode = if grad_only {
                Assembly::GradientOnly
            } else {
                Assembly::Full
            };
            if let Some(job) = factor_job.take() {
                // A new layout: its factor structures beside the first assembly.
                let (built, ()) = rayon::join(
                    move || {
                        let tp = Instant::now();
                        (job.build(), tp.elapsed().as_secs_f64() * 1e3)
                    },
                    || self.assemble(graph, problem, pose, set, params, mode),
                );
                info.ms_prepare += built.1;
                self.system.install(built.0)?;
            } else {
                self.assemble(graph, problem, pose, set, params, mode);
            }
            info.ms_assemble += tb.elapsed().as_secs_f64() * 1e3;
            let pose0 = *pose;
            self.saved.clear();
            self.saved
                .extend(set.free.iter().map(|&j| graph.warp[j as usize]));
            let mut accepted = false;
            let mut converged = false;
            let mut step_norm = 0.0f64;
            for attempt in 0..10 {
                // A later iteration first tries the step from the last factorisation (its
                // Hessian and damping, this iteration's gradient); rejected, it factorises.
                let reuse = attempt == 0 && grad_only;
                if attempt > 0 && grad_only {
                    grad_only = false;
                    let tp = Instant::now();
                    self.system.prepare(graph.len(), &key)?;
                    info.ms_prepare += tp.elapsed().as_secs_f64() * 1e3;
                    let tb = Instant::now();
                    self.assemble(graph, problem, pose, set, params, Assembly::Full);
                    info.ms_assemble += tb.elapsed().as_secs_f64() * 1e3;
                }
                let tf = Instant::now();
                let ok = if reuse {
                    info.reused_factorisations += 1;
                    reuses_left -= 1;
                    self.system.resolve(&mut self.dx)?
                } else {
                    info.factorisations += 1;
                    reuses_left = params.reuse_factorisation;
                    self.system.solve(lambda, 1e-6, &mut self.dx)?
                };
                info.ms_factor += tf.elapsed().as_secs_f64() * 1e3;
                if ok {
                    for (idx, &j) in set.free.iter().enumerate() {
                        let s = self.system.slot[j as usize] as usize;
                        let p = &mut graph.warp[j as usize];
                        for q in 0..12 {
                            p[q] = self.saved[idx][q] + self.dx[12 * s + q];
                        }
                    }
                    if set.pose {
                        let off = 12 * self.system.blocks_solved();
                        *pose = pose_update(&pose0, &self.dx[off..off + 6]);
                    }
                    step_norm = self.dx.iter().fold(0.0, |m, x| m.max(x.abs()));
                    // The candidate state's pass: the cost with the current association decides,
                    // the new association (and its cost) is adopted with the step.
                    // The other terms' cost (serial) beside it.
                    let ta = Instant::now();
                    let (next, cur, priors) = (&mut self.next, &self.cur, &self.priors);
                    let (other, ()) = rayon::join(
                        || other_cost(priors, graph, problem, pose, set, params),
                        || {
                            if set.data {
                                next.run(
                                    graph,
                                    problem,
                                    pose,
                                    params,
                                    problem.scan.is_some(),
                                    Some(cur),
                                );
                            } else {
                                *next = Pass::default();
                            }
                        },
                    );
                    info.ms_associate += ta.elapsed().as_secs_f64() * 1e3;
                    let new_cost = other + self.next.cost_old;
                    if params.method == Method::GaussNewton || new_cost <= cost {
                        accepted = true;
                        std::mem::swap(&mut self.cur, &mut self.next);
                        cost = if problem.scan.is_some() {
                            other + self.cur.cost_new
                        } else {
                            new_cost
                        };
                        lambda = (lambda / 3.0).max(1e-9);
                        break;
                    }
                    // A rejected step that changes the cost by less than the stopping tolerance:
                    // the minimum is reached, and more damping only shortens the step (each try
                    // costs a factorisation). Seen where the Jacobian leaves out part of the
                    // cost's variation (`FieldJacobian::Normal`).
                    if !reuse && new_cost - cost <= params.min_relative_decrease * cost.max(1e-30) {
                        converged = true;
                    }
                }
                // Rejected: restore and damp more.
                info.rejected_steps += 1;
                for (idx, &j) in set.free.iter().enumerate() {
                    graph.warp[j as usize] = self.saved[idx];
                }
                *pose = pose0;
                if converged {
                    break;
                }
                if reuse {
                    // The kept Hessian's step failed: the fresh one is the first real attempt.
                    continue;
                }
                if params.method == Method::GaussNewton {
                    lambda = 1e-6;
                } else {
                    lambda = (lambda * 10.0).max(1e-6);
                }
            }
            if !accepted {
                break;
            }
            let prev = info.costs.last().copied().unwrap_or(info.cost_before);
            info.costs.push(cost);
            if step_norm < params.min_step
                || (prev - cost).abs() <= params.min_relative_decrease * prev.max(1e-30)
            {
                break;
            }
        }
        info.cost_after = cost;
        info.data_terms = self.cur.assoc.len()
            + if set.data {
                problem.correspondences.len()
            } else {
                0
            }
            + if set.data && problem.field.is_some() {
                problem.model.points.len()
            } else {
                0
            };
        info.symbolic_builds = self.system.symbolic_builds - builds0;
        info.ms_total = t0.elapsed().as_secs_f64() * 1e3;
        Ok(info)
    }
}

/// The terms other than the projective and field data on the model points (E_rot, E_reg,
/// E_corr, E_r, E_p) at the current state, with the node priors `priors`.
fn other_cost(
    priors: &NodePriors,
    graph: &EdGraph,
    problem: &Problem,
    pose: &Isometry3<f64>,
    set: &SolveSet,
    params: &SolverParams,
) -> f64 {
    let w = &params.weights;
    let pw = priors.weights(params);
    let mut total = 0.0;
    for &j in &set.free {
        let (r, _) = rot_residuals(&graph.warp[j as usize]);
        total += pw.rot(j) * r.iter().map(|x| x * x).sum::<f64>();
    }
    for &(j, k) in &set.reg_edges {
        total += pw.reg(j, k) * reg_residual(graph, j, k).norm_squared();
    }
    for (j, t0, wm) in priors.motion_ref() {
        let p = &graph.warp[*j as usize];
        total += wm * (Vector3::new(p[3], p[7], p[11]) - t0).norm_squared();
    }
    if set.data {
        let cfw = pose.inverse();
        let c = params.robust_scale_mm;
        for corr in problem.correspondences {
            let vw = graph.warp_point(&corr.point, &corr.binding);
            let p = cfw * misslam_framework::nalgebra::Point3::from(vw);
            let (_, r) = corr.rows(&p.coords, w.corr_normal);
            total += w.corr * params.robust.weight_cost(r, c).1;
        }
    }
    if set.pose {
        total += w.pose_rot * pose_rot_residual(&problem.pose_prior, pose).norm_squared();
        total += w.pose_trans
            * (pose.translation.vector - problem.pose_prior.translation.vector).norm_squared();
    }
    total
}
