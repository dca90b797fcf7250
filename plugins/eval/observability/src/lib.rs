//! The thesis's observability study (chapter 6; `docs/method.md` section 6).
//!
//! With an embedded deformation (ED) graph, a motion of the scope and a deformation of the scene
//! explain the same observations: at every step a rigid motion of all the nodes, undone by the
//! scope's pose, leaves the observations, E_rot and E_reg unchanged, so ED-based SLAM is
//! unobservable without a prior and its Fisher information lacks three ranks per moving step.
//! The thesis's prior: the scene is periodic or regular, and a feature's position is a linear
//! combination of its previous ones, f^n = sum_{i=1..t} c_i f^{n-i} (E_f), with the scope still
//! for an initial period (E_ini) in which the coefficients are fitted. E = E_obs + E_f + E_ini.
//!
//! The simulation ([`scene`]) is the thesis's: a scope moving inside a planar cross-section of a
//! deforming heart, stomach, liver or lung, 2D pose (x, y, heading), odometry and noisy
//! observations of the wall's points in the scope's frame. Each estimator is a batch nonlinear
//! least-squares solve over every step ([`lsq`]), all with the same odometry and E_ini:
//! - [`Method::Odometry`]: dead reckoning, the baseline;
//! - [`Method::Static`]: a rigid scene (one position per feature);
//! - [`Method::Ed`]: an ED graph per step on the first view's features (affine nodes, Sumner
//!   weights, E_rot and E_reg), nothing tying the steps together;
//! - [`Method::Fem`]: a position per feature per step held together by a finite-element model
//!   of the wall (bar elements, rest lengths from the first view), nothing tying the steps;
//! - [`Method::TimeSeries`]: a position per feature per step with E_f.
//!
//! [`run_study`] runs them by Monte Carlo (RMSE of position and heading against the truth) and
//! tests the rank of each one's Fisher information without odometry ([`information_rank`]).

pub mod lsq;
pub mod scene;

use misslam_framework::nalgebra::{DMatrix, Matrix2, Vector2};
use scene::{wrap, Organ, Pose2, Scene, SceneParams};

/// The estimators compared.
#[derive(Clone, Copy, Debug, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Dead reckoning from the odometry.
    Odometry,
    /// SLAM with a rigid scene.
    Static,
    /// SLAM with an ED graph per step, no temporal prior.
    Ed,
    /// SLAM with a finite-element model of the wall per step: linear bar (truss) elements
    /// between neighbouring points and between every other point (bending), rest lengths from
    /// the first view, no temporal prior.
    Fem,
    /// SLAM with the time-series prior E_f and the still period E_ini.
    TimeSeries,
}

impl Method {
    /// Every estimator, in the table's order.
    pub const ALL: [Method; 5] = [
        Method::Odometry,
        Method::Static,
        Method::Ed,
        Method::Fem,
        Method::TimeSeries,
    ];

    /// Its name in the table and the JSON.
    pub fn name(self) -> &'static str {
        match self {
            Method::Odometry => "odometry",
            Method::Static => "static",
            Method::Ed => "ed",
            Method::Fem => "fem",
            Method::TimeSeries => "time_series",
        }
    }
}

/// The estimators' parameters.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct EstimatorParams {
    /// Standard deviation of E_ini (each still pose at the start pose), mm and rad.
    pub ini_sigma: f64,
    /// ED nodes (every features / nodes-th feature of the first view is a node).
    pub ed_nodes: usize,
    /// ED: nodes influencing a feature (Sumner weights to the next one's distance).
    pub ed_k: usize,
    /// ED: weight of E_rot.
    pub w_rot: f64,
    /// ED: weight of E_reg (between neighbouring nodes around the wall).
    pub w_reg: f64,
    /// FEM: stiffness of the bar elements (weight of each element's squared strain times its
    /// rest length, mm^-1).
    pub fem_stiffness: f64,
    /// Order t of the time series; 0: the organ's 2H + 1 for its H frequencies.
    pub order: usize,
    /// Standard deviation of E_f, mm.
    pub ts_sigma_mm: f64,
    /// The coefficients among the unknowns (true, the default), started from their fit on the
    /// still period, so that every step refines them; false: the fit, held.
    pub estimate_coefficients: bool,
    /// 0: the coefficients by total least squares (the default); > 0: by least squares with
    /// this ridge (relative to the regressors' scale).
    pub ridge: f64,
    /// Fit the coefficients as a periodic motion (the default; odd orders): the root at 1 and
    /// the palindromic characteristic polynomial of undamped harmonics imposed, so only
    /// (t - 1) / 2 numbers are fitted, by total least squares on the first differences
    /// ([`fit_periodic`]); false: all t coefficients free ([`fit_recurrence`]).
    pub periodic: bool,
    /// Levenberg-Marquardt steps at most.
    pub max_iterations: usize,
    /// Stop when the cost falls by less than this (relative).
    pub tol: f64,
}

impl Default for EstimatorParams {
    fn default() -> Self {
        EstimatorParams {
            ini_sigma: 1e-3,
            ed_nodes: 8,
            ed_k: 3,
            w_rot: 1.0,
            w_reg: 10.0,
            fem_stiffness: 100.0,
            order: 0,
            ts_sigma_mm: 0.01,
            estimate_coefficients: true,
            ridge: 0.0,
            periodic: true,
            max_iterations: 30,
            tol: 1e-9,
        }
    }
}

impl EstimatorParams {
    /// The parameter that cannot be used, named.
    pub fn validate(&self, features: usize) -> Result<(), String> {
        if self.ed_nodes < 2 || self.ed_nodes > features {
            return Err(format!(
                "`ed_nodes` is {}: between 2 and the features ({features})",
                self.ed_nodes
            ));
        }
        if self.ed_k == 0 || self.ed_k >= self.ed_nodes {
            return Err(format!(
                "`ed_k` is {}: between 1 and `ed_nodes` - 1 ({})",
                self.ed_k,
                self.ed_nodes - 1
            ));
        }
        for (name, v) in [
            ("ini_sigma", self.ini_sigma),
            ("ts_sigma_mm", self.ts_sigma_mm),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("`{name}` is {v}: a finite value > 0"));
            }
        }
        for (name, v) in [
            ("w_rot", self.w_rot),
            ("w_reg", self.w_reg),
            ("fem_stiffness", self.fem_stiffness),
            ("ridge", self.ridge),
            ("tol", self.tol),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("`{name}` is {v}: a finite value >= 0"));
            }
        }
        Ok(())
    }
}

/// One estimate: the scope's poses and, where the estimator has them, the features per step.
#[derive(Clone, Debug)]
pub struct Estimate {
    /// Poses, one per step.
    pub poses: Vec<Pose2>,
    /// Feature positions per step, `features[n][j]` (none for odometry).
    pub features: Option<Vec<Vec<Vector2<f64>>>>,
    /// The solve.
    pub info: lsq::SolveInfo,
}

/// Dead reckoning from the start pose.
pub fn dead_reckoning(s: &Scene) -> Vec<Pose2> {
    let mut poses = vec![Pose2::default()];
    for n in 1..s.params.steps {
        let next = poses[n - 1].compose(&s.odometry[n]);
        poses.push(next);
    }
    poses
}

fn pose_of(x: &[f64]) -> Pose2 {
    Pose2 {
        x: x[0],
        y: x[1],
        th: x[2],
    }
}

/// The observation residual of feature position `f` seen as `z` from pose `p`.
fn obs_residual(p: &Pose2, f: &Vector2<f64>, z: &Vector2<f64>, sigma: f64, out: &mut [f64]) {
    let e = p.to_local(f) - z;
    out[0] = e.x / sigma;
    out[1] = e.y / sigma;
}

/// ED layout: nodes (feature indices of the first view), each feature's nodes and weights, the
/// rest positions (the first view), and the node ring's neighbours.
struct EdGraph {
    rest: Vec<Vector2<f64>>,
    nodes: Vec<usize>,
    weights: Vec<Vec<(usize, f64)>>,
}

impl EdGraph {
    fn new(rest: Vec<Vector2<f64>>, count: usize, k: usize) -> EdGraph {
        let m = rest.len();
        let nodes: Vec<usize> = (0..count).map(|i| i * m / count).collect();
        let weights = rest
            .iter()
            .map(|p| {
                let mut d: Vec<(usize, f64)> = nodes
                    .iter()
                    .enumerate()
                    .map(|(i, &g)| (i, (rest[g] - p).norm()))
                    .collect();
                d.sort_by(|a, b| a.1.total_cmp(&b.1));
                let dmax = d[k].1.max(1e-9);
                let mut w: Vec<(usize, f64)> = d[..k]
                    .iter()
                    .map(|&(i, di)| (i, (1.0 - di / dmax).max(0.0).powi(2)))
                    .collect();
                let sum: f64 = w.iter().map(|x| x.1).sum();
                for x in &mut w {
                    x.1 = if sum > 0.0 { x.1 / sum } else { 1.0 / k as f64 };
                }
                w
            })
            .collect();
        EdGraph {
            rest,
            nodes,
            weights,
        }
    }

    /// The warped position of feature j given its nodes' parameters, in `weights[j]`'s order
    /// (A row-major, then t: six each).
    fn warp(&self, j: usize, params: &[f64]) -> Vector2<f64> {
        let mut out = Vector2::zeros();
        for (slot, &(node, w)) in self.weights[j].iter().enumerate() {
            let q = &params[6 * slot..6 * slot + 6];
            let a = Matrix2::new(q[0], q[1], q[2], q[3]);
            let g = self.rest[self.nodes[node]];
            out += w * (a * (self.rest[j] - g) + g + Vector2::new(q[4], q[5]));
        }
        out
    }
}

/// Builds the least-squares problem of `method` (not odometry) on `s`: its unknowns' initial
/// values (poses by dead reckoning; features and nodes from the observations), and a closure
/// reading the estimate back. Without `odometry` the odometry terms are left out (for the rank
/// test).
#[allow(clippy::type_complexity)]
pub fn build(
    method: Method,
    s: &Scene,
    p: &EstimatorParams,
    odometry: bool,
) -> Result<(lsq::Problem, Vec<f64>, Box<dyn Fn(&[f64]) -> Estimate>), String> {
    build_with(method, s, p, odometry, None)
}

/// [`build`], the time series' coefficients given (`None`: fitted on the still period).
#[allow(clippy::type_complexity)]
pub fn build_with(
    method: Method,
    s: &Scene,
    p: &EstimatorParams,
    odometry: bool,
    coefficients: Option<&[f64]>,
) -> Result<(lsq::Problem, Vec<f64>, Box<dyn Fn(&[f64]) -> Estimate>), String> {
    p.validate(s.params.features)?;
    let sp = &s.params;
    let (nsteps, m) = (sp.steps, sp.features);
    let dr = dead_reckoning(s);
    let mut x: Vec<f64> = dr.iter().flat_map(|q| [q.x, q.y, q.th]).collect();
    let mut prob = lsq::Problem::default();
    let np = 3 * nsteps;
    let (so, st) = (sp.obs_sigma_mm.max(1e-6), sp.odo_sigma_mm.max(1e-6));
    let sth = sp.odo_sigma_deg.to_radians().max(1e-6);
    if odometry {
        for n in 1..nsteps {
            let u = s.odometry[n];
            prob.add((3 * n - 3..3 * n + 3).collect(), 3, move |v, out| {
                let d = pose_of(&v[..3]).between(&pose_of(&v[3..]));
                out[0] = (d.x - u.x) / st;
                out[1] = (d.y - u.y) / st;
                out[2] = wrap(d.th - u.th) / sth;
            });
        }
    }
    let si = p.ini_sigma;
    for n in 0..sp.static_steps {
        prob.add((3 * n..3 * n + 3).collect(), 3, move |v, out| {
            out[0] = v[0] / si;
            out[1] = v[1] / si;
            out[2] = wrap(v[2]) / si;
        });
    }
    let first: Vec<Vector2<f64>> = s.observations[0]
        .iter()
        .map(|z| {
            Pose2::default()
                .compose(&Pose2 {
                    x: z.x,
                    y: z.y,
                    th: 0.0,
                })
                .p()
        })
        .collect();
    match method {
        Method::Odometry => Err("dead reckoning has no least-squares problem".into()),
        Method::Static => {
            x.extend(first.iter().flat_map(|f| [f.x, f.y]));
            for n in 0..nsteps {
                for j in 0..m {
                    let z = s.observations[n][j];
                    let fv = np + 2 * j;
                    prob.add(
                        vec![3 * n, 3 * n + 1, 3 * n + 2, fv, fv + 1],
                        2,
                        move |v, out| {
                            obs_residual(&pose_of(v), &Vector2::new(v[3], v[4]), &z, so, out);
                        },
                    );
                }
            }
            prob.n = x.len();
            Ok((
                prob,
                x,
                Box::new(move |x: &[f64]| {
                    let f: Vec<_> = (0..m)
                        .map(|j| Vector2::new(x[np + 2 * j], x[np + 2 * j + 1]))
                        .collect();
                    Estimate {
                        poses: (0..nsteps).map(|n| pose_of(&x[3 * n..])).collect(),
                        features: Some(vec![f; nsteps]),
                        info: Default::default(),
                    }
                }),
            ))
        }
        Method::Ed => {
            let g = std::sync::Arc::new(EdGraph::new(first, p.ed_nodes, p.ed_k));
            let kn = p.ed_nodes;
            let node_var = move |n: usize, k: usize| np + 6 * (n * kn + k);
            for _ in 0..nsteps * kn {
                x.extend([1.0, 0.0, 0.0, 1.0, 0.0, 0.0]);
            }
            let (wr, wg) = (p.w_rot.sqrt(), p.w_reg.sqrt());
            for n in 0..nsteps {
                for j in 0..m {
                    let z = s.observations[n][j];
                    let mut vars = vec![3 * n, 3 * n + 1, 3 * n + 2];
                    for &(node, _) in &g.weights[j] {
                        vars.extend(node_var(n, node)..node_var(n, node) + 6);
                    }
                    let gj = g.clone();
                    prob.add(vars, 2, move |v, out| {
                        obs_residual(&pose_of(v), &gj.warp(j, &v[3..]), &z, so, out);
                    });
                }
                for k in 0..kn {
                    let v0 = node_var(n, k);
                    prob.add((v0..v0 + 4).collect(), 3, move |v, out| {
                        out[0] = wr * (v[0] * v[1] + v[2] * v[3]);
                        out[1] = wr * (v[0] * v[0] + v[2] * v[2] - 1.0);
                        out[2] = wr * (v[1] * v[1] + v[3] * v[3] - 1.0);
                    });
                    for l in [(k + 1) % kn, (k + kn - 1) % kn] {
                        let (gk, gl) = (g.rest[g.nodes[k]], g.rest[g.nodes[l]]);
                        let vl = node_var(n, l);
                        let mut vars: Vec<usize> = (v0..v0 + 6).collect();
                        vars.extend([vl + 4, vl + 5]);
                        prob.add(vars, 2, move |v, out| {
                            let a = Matrix2::new(v[0], v[1], v[2], v[3]);
                            let e = a * (gl - gk) + gk + Vector2::new(v[4], v[5])
                                - (gl + Vector2::new(v[6], v[7]));
                            out[0] = wg * e.x;
                            out[1] = wg * e.y;
                        });
                    }
                }
            }
            prob.n = x.len();
            Ok((
                prob,
                x,
                Box::new(move |x: &[f64]| {
                    let features = (0..nsteps)
                        .map(|n| {
                            (0..m)
                                .map(|j| {
                                    let q: Vec<f64> = g.weights[j]
                                        .iter()
                                        .flat_map(|&(node, _)| {
                                            let v = node_var(n, node);
                                            x[v..v + 6].to_vec()
                                        })
                                        .collect();
                                    g.warp(j, &q)
                                })
                                .collect()
                        })
                        .collect();
                    Estimate {
                        poses: (0..nsteps).map(|n| pose_of(&x[3 * n..])).collect(),
                        features: Some(features),
                        info: Default::default(),
                    }
                }),
            ))
        }
        Method::Fem => {
            let fv = move |n: usize, j: usize| np + 2 * (n * m + j);
            let ks = p.fem_stiffness.sqrt();
            for (n, pose) in dr.iter().enumerate() {
                for j in 0..m {
                    let z = s.observations[n][j];
                    let f = pose
                        .compose(&Pose2 {
                            x: z.x,
                            y: z.y,
                            th: 0.0,
                        })
                        .p();
                    x.extend([f.x, f.y]);
                    let v = fv(n, j);
                    prob.add(
                        vec![3 * n, 3 * n + 1, 3 * n + 2, v, v + 1],
                        2,
                        move |v, out| {
                            obs_residual(&pose_of(v), &Vector2::new(v[3], v[4]), &z, so, out);
                        },
                    );
                }
                // Strain energy of a bar of rest length L: (k / 2) L ((l - L) / L)^2.
                for j in 0..m {
                    for step in [1, 2] {
                        let k = (j + step) % m;
                        let rest = (first[k] - first[j]).norm().max(1e-9);
                        let scale = ks / rest.sqrt();
                        let (a, b) = (fv(n, j), fv(n, k));
                        prob.add(vec![a, a + 1, b, b + 1], 1, move |v, out| {
                            let l = Vector2::new(v[2] - v[0], v[3] - v[1]).norm();
                            out[0] = scale * (l - rest);
                        });
                    }
                }
            }
            prob.n = x.len();
            Ok((
                prob,
                x,
                Box::new(move |x: &[f64]| Estimate {
                    poses: (0..nsteps).map(|n| pose_of(&x[3 * n..])).collect(),
                    features: Some(
                        (0..nsteps)
                            .map(|n| {
                                (0..m)
                                    .map(|j| Vector2::new(x[fv(n, j)], x[fv(n, j) + 1]))
                                    .collect()
                            })
                            .collect(),
                    ),
                    info: Default::default(),
                }),
            ))
        }
        Method::TimeSeries => {
            let c = match coefficients {
                Some(c) => c.to_vec(),
                None => fit_for(s, p)?,
            };
            let t = c.len();
            let fv = move |n: usize, j: usize| np + 2 * (n * m + j);
            for (n, pose) in dr.iter().enumerate() {
                for j in 0..m {
                    let z = s.observations[n][j];
                    let f = pose
                        .compose(&Pose2 {
                            x: z.x,
                            y: z.y,
                            th: 0.0,
                        })
                        .p();
                    x.extend([f.x, f.y]);
                    let v = fv(n, j);
                    prob.add(
                        vec![3 * n, 3 * n + 1, 3 * n + 2, v, v + 1],
                        2,
                        move |v, out| {
                            obs_residual(&pose_of(v), &Vector2::new(v[3], v[4]), &z, so, out);
                        },
                    );
                }
            }
            let sf = p.ts_sigma_mm;
            let cv = x.len();
            let free = p.estimate_coefficients;
            // Estimated, the coefficients keep the form they were fitted in: the H periodic
            // parameters, or all t.
            let periodic = coefficients.is_none() && p.periodic && !t.is_multiple_of(2);
            let nc = if periodic { (t - 1) / 2 } else { t };
            if free {
                if periodic {
                    x.extend(periodic_parameters(s, t)?);
                } else {
                    x.extend(&c);
                }
            }
            for n in t..nsteps {
                for j in 0..m {
                    let mut vars = vec![fv(n, j), fv(n, j) + 1];
                    for i in 1..=t {
                        vars.extend([fv(n - i, j), fv(n - i, j) + 1]);
                    }
                    if free {
                        vars.extend(cv..cv + nc);
                    }
                    let c = c.clone();
                    prob.add(vars, 2, move |v, out| {
                        let from_u;
                        let coeff = if !free {
                            &c[..]
                        } else if periodic {
                            from_u = coefficients_of(&v[2 + 2 * t..]);
                            &from_u[..]
                        } else {
                            &v[2 + 2 * t..]
                        };
                        let (mut ex, mut ey) = (v[0], v[1]);
                        for (i, ci) in coeff.iter().enumerate() {
                            ex -= ci * v[2 + 2 * i];
                            ey -= ci * v[3 + 2 * i];
                        }
                        out[0] = ex / sf;
                        out[1] = ey / sf;
                    });
                }
            }
            prob.n = x.len();
            Ok((
                prob,
                x,
                Box::new(move |x: &[f64]| Estimate {
                    poses: (0..nsteps).map(|n| pose_of(&x[3 * n..])).collect(),
                    features: Some(
                        (0..nsteps)
                            .map(|n| {
                                (0..m)
                                    .map(|j| Vector2::new(x[fv(n, j)], x[fv(n, j) + 1]))
                                    .collect()
                            })
                            .collect(),
                    ),
                    info: Default::default(),
                }),
            ))
        }
    }
}

/// The time series' order for `s`: `p.order`, or 2H + 1 for the organ's H frequencies.
pub fn order_of(s: &Scene, p: &EstimatorParams) -> usize {
    if p.order > 0 {
        p.order
    } else {
        2 * s.params.organ.omegas().len() + 1
    }
}

/// The coefficients c_1..c_t of f^n = sum c_i f^{n-i}, fitted to the features seen during the
/// still period (the world frame is the start pose's, so those observations are world
/// positions), every feature and both coordinates sharing them. The regressors are noisy as
/// much as the targets, so the fit is total least squares (the right singular vector of
/// [f^{n-1} .. f^{n-t} | f^n] with the smallest singular value, as in linear prediction): plain
/// least squares shrinks the coefficients towards a smoother motion (heart, 0.3 mm noise: a sum
/// of |c_i| of 2.6 against the truth's 18.0). `ridge` > 0 instead takes ridge-regularised least
/// squares (relative to the regressors' scale).
pub fn fit_recurrence(s: &Scene, t: usize, ridge: f64) -> Result<Vec<f64>, String> {
    let sp = &s.params;
    if t == 0 || sp.static_steps <= t {
        return Err(format!(
            "the time series' order {t} needs more still steps than {} (`static_steps`)",
            sp.static_steps
        ));
    }
    let obs = &s.observations[..sp.static_steps];
    let rows = (sp.static_steps - t) * sp.features * 2;
    // Centred per feature and axis over the still period would remove the constant mode the
    // recurrence must keep (its root at 1), so the raw positions are used.
    let mut a = DMatrix::<f64>::zeros(rows, t + 1);
    let mut r = 0;
    for n in t..sp.static_steps {
        for (j, target) in obs[n].iter().enumerate() {
            for (axis, value) in target.iter().enumerate() {
                for i in 0..t {
                    a[(r, i)] = obs[n - 1 - i][j][axis];
                }
                a[(r, t)] = *value;
                r += 1;
            }
        }
    }
    let c: Vec<f64> = if ridge > 0.0 {
        let x = a.columns(0, t).into_owned();
        let y = a.column(t).into_owned();
        let mut ata = x.transpose() * &x;
        let scale = ata.diagonal().max().max(1e-300);
        for i in 0..t {
            ata[(i, i)] += ridge * scale;
        }
        ata.cholesky()
            .ok_or("the time series' fit is singular: lengthen the still period")?
            .solve(&(x.transpose() * y))
            .iter()
            .copied()
            .collect()
    } else {
        let svd = a.svd(false, true);
        let v_t = svd.v_t.ok_or("the time series' fit: no singular vectors")?;
        let k = svd
            .singular_values
            .iter()
            .enumerate()
            .min_by(|x, y| x.1.total_cmp(y.1))
            .map(|x| x.0)
            .ok_or("the time series' fit: no singular values")?;
        let v = v_t.row(k);
        if v[t].abs() < 1e-12 {
            return Err("the time series' fit is degenerate: lengthen the still period".into());
        }
        (0..t).map(|i| -v[i] / v[t]).collect()
    };
    if c.iter().any(|x| !x.is_finite()) {
        return Err("the time series' fit is not finite".into());
    }
    Ok(c)
}

/// The coefficients `p` asks for on `s`: [`fit_periodic`] for an odd order with `p.periodic`,
/// else [`fit_recurrence`].
pub fn fit_for(s: &Scene, p: &EstimatorParams) -> Result<Vec<f64>, String> {
    let t = order_of(s, p);
    if p.periodic && !t.is_multiple_of(2) {
        fit_periodic(s, t)
    } else {
        fit_recurrence(s, t, p.ridge)
    }
}

/// The coefficients of an order-t recurrence (t odd) for a periodic motion, fitted on the still
/// period: a sum of H = (t - 1) / 2 undamped harmonics plus a constant has the characteristic
/// polynomial (z - 1) q(z) with q palindromic (q(z) = prod_h (z^2 - 2 cos(w_h) z + 1)), so its
/// first differences g(n) = f(n) - f(n - 1) satisfy
/// g(n) + g(n - 2H) = sum_{k<H} u_k (g(n - k) + g(n - 2H + k)) + u_H g(n - H):
/// H unknowns, fitted by total least squares over every feature and axis, instead of t free
/// ones (better conditioned: the free fit of order 5 on the lung's 24 noisy still steps put its
/// last coefficient at 0.01 against the truth's 1).
pub fn fit_periodic(s: &Scene, t: usize) -> Result<Vec<f64>, String> {
    periodic_parameters(s, t).map(|u| coefficients_of(&u))
}

/// The H = (t - 1) / 2 parameters u of [`fit_periodic`], fitted on the still period.
pub fn periodic_parameters(s: &Scene, t: usize) -> Result<Vec<f64>, String> {
    let sp = &s.params;
    if t.is_multiple_of(2) {
        return Err(format!("the periodic fit needs an odd order, not {t}"));
    }
    let h = (t - 1) / 2;
    if h == 0 {
        return Ok(Vec::new());
    }
    if sp.static_steps < 2 * h + 3 {
        return Err(format!(
            "the time series' order {t} needs more still steps than {} (`static_steps`)",
            sp.static_steps
        ));
    }
    let obs = &s.observations[..sp.static_steps];
    let g = |n: usize, j: usize, axis: usize| obs[n][j][axis] - obs[n - 1][j][axis];
    let rows = (sp.static_steps - 2 * h - 1) * sp.features * 2;
    let mut a = DMatrix::<f64>::zeros(rows, h + 1);
    let mut r = 0;
    for n in 2 * h + 1..sp.static_steps {
        for j in 0..sp.features {
            for axis in 0..2 {
                for k in 1..h {
                    a[(r, k - 1)] = g(n - k, j, axis) + g(n - 2 * h + k, j, axis);
                }
                a[(r, h - 1)] = g(n - h, j, axis);
                a[(r, h)] = g(n, j, axis) + g(n - 2 * h, j, axis);
                r += 1;
            }
        }
    }
    let svd = a.svd(false, true);
    let v_t = svd.v_t.ok_or("the periodic fit: no singular vectors")?;
    let k = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))
        .map(|x| x.0)
        .ok_or("the periodic fit: no singular values")?;
    let v = v_t.row(k);
    if v[h].abs() < 1e-12 {
        return Err("the periodic fit is degenerate: lengthen the still period".into());
    }
    let u: Vec<f64> = (0..h).map(|i| -v[i] / v[h]).collect();
    if u.iter().any(|x| !x.is_finite()) {
        return Err("the periodic fit is not finite".into());
    }
    Ok(u)
}

/// The recurrence's coefficients c_1..c_{2H+1} of the periodic parameters u_1..u_H
/// ([`periodic_parameters`]): c_i = -p_i for p(z) = (z - 1) q(z), q palindromic with
/// q = 1, -u_1, ..., -u_H, ..., -u_1, 1.
pub fn coefficients_of(u: &[f64]) -> Vec<f64> {
    let h = u.len();
    let mut q = vec![0.0; 2 * h + 1];
    q[0] = 1.0;
    q[2 * h] = 1.0;
    for k in 1..=h {
        q[k] = -u[k - 1];
        q[2 * h - k] = -u[k - 1];
    }
    (1..=2 * h + 1)
        .map(|i| {
            let qi = if i <= 2 * h { q[i] } else { 0.0 };
            -(qi - q[i - 1])
        })
        .collect()
}

/// Runs `method` on `s`.
pub fn estimate(method: Method, s: &Scene, p: &EstimatorParams) -> Result<Estimate, String> {
    if method == Method::Odometry {
        return Ok(Estimate {
            poses: dead_reckoning(s),
            features: None,
            info: Default::default(),
        });
    }
    let (prob, mut x, read) = build(method, s, p, true)?;
    let info = prob.solve(&mut x, p.max_iterations, p.tol)?;
    let mut e = read(&x);
    e.info = info;
    Ok(e)
}

/// Errors of an estimate against the truth.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Errors {
    /// RMSE of the position over the moving steps, mm.
    pub position_rmse_mm: f64,
    /// RMSE of the heading over the moving steps, degrees.
    pub heading_rmse_deg: f64,
    /// RMSE of the feature positions over every step, mm (NaN for odometry).
    pub feature_rmse_mm: f64,
}

/// `e`'s errors on `s`.
pub fn errors(s: &Scene, e: &Estimate) -> Errors {
    let moving = s.params.static_steps..s.params.steps;
    let k = moving.len() as f64;
    let pos = moving
        .clone()
        .map(|n| (e.poses[n].p() - s.poses[n].p()).norm_squared())
        .sum::<f64>();
    let th = moving
        .map(|n| wrap(e.poses[n].th - s.poses[n].th).powi(2))
        .sum::<f64>();
    let feature_rmse_mm = e.features.as_ref().map_or(f64::NAN, |f| {
        let mut sum = 0.0;
        let mut count = 0.0;
        for (fe, ft) in f.iter().zip(&s.truth) {
            for (a, b) in fe.iter().zip(ft) {
                sum += (a - b).norm_squared();
                count += 1.0;
            }
        }
        (sum / count).sqrt()
    });
    Errors {
        position_rmse_mm: (pos / k).sqrt(),
        heading_rmse_deg: (th / k).sqrt().to_degrees(),
        feature_rmse_mm,
    }
}

/// The rank of a method's Fisher information without odometry.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct RankTest {
    /// The method.
    pub method: Method,
    /// Unknowns.
    pub unknowns: usize,
    /// Numerical rank of J^T J (eigenvalues above 1e-12 of the largest; the unobservable
    /// directions give about 1e-16).
    pub rank: usize,
    /// Unknowns less rank: the unobservable directions.
    pub deficiency: usize,
    /// The smallest eigenvalue kept over the largest.
    pub smallest_kept: f64,
    /// The largest eigenvalue dropped over the largest (0 when none is dropped).
    pub largest_dropped: f64,
}

/// The rank of `method`'s Fisher information on `s` without odometry, at the true poses with
/// the method's features or nodes at their initial values (the time series: the true features
/// and the motion's true coefficients, held: the information about the states under the model).
pub fn information_rank(
    method: Method,
    s: &Scene,
    p: &EstimatorParams,
) -> Result<RankTest, String> {
    // The information about the states (poses and features), the coefficients known.
    let p = &EstimatorParams {
        estimate_coefficients: false,
        ..p.clone()
    };
    let truth = s.true_recurrence();
    let (prob, mut x, _) = build_with(method, s, p, false, Some(&truth))?;
    for (n, q) in s.poses.iter().enumerate() {
        x[3 * n..3 * n + 3].copy_from_slice(&[q.x, q.y, q.th]);
    }
    if method == Method::TimeSeries {
        let np = 3 * s.params.steps;
        for (n, fs) in s.truth.iter().enumerate() {
            for (j, f) in fs.iter().enumerate() {
                let v = np + 2 * (n * s.params.features + j);
                x[v] = f.x;
                x[v + 1] = f.y;
            }
        }
    }
    let info = prob.information(&x);
    let eig = misslam_framework::nalgebra::SymmetricEigen::new(info);
    let max = eig.eigenvalues.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
    let tol = 1e-12 * max;
    let kept: Vec<f64> = eig
        .eigenvalues
        .iter()
        .copied()
        .filter(|&v| v > tol)
        .collect();
    let dropped = eig
        .eigenvalues
        .iter()
        .copied()
        .filter(|&v| v <= tol)
        .fold(0.0f64, |a, b| a.max(b.abs()));
    Ok(RankTest {
        method,
        unknowns: prob.n,
        rank: kept.len(),
        deficiency: prob.n - kept.len(),
        smallest_kept: kept.iter().copied().fold(f64::INFINITY, f64::min) / max,
        largest_dropped: dropped / max,
    })
}

/// Mean, standard deviation, smallest and largest of a figure over the runs.
#[derive(Clone, Copy, Debug, PartialEq, serde::Serialize)]
pub struct Stat {
    /// Mean.
    pub mean: f64,
    /// Standard deviation.
    pub std: f64,
    /// Smallest.
    pub min: f64,
    /// Largest.
    pub max: f64,
}

impl Stat {
    fn of(v: &[f64]) -> Stat {
        let n = v.len().max(1) as f64;
        let mean = v.iter().sum::<f64>() / n;
        let var = v.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / n;
        Stat {
            mean,
            std: var.sqrt(),
            min: v.iter().copied().fold(f64::INFINITY, f64::min),
            max: v.iter().copied().fold(f64::NEG_INFINITY, f64::max),
        }
    }
}

/// A method's figures over an organ's runs.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct MethodSummary {
    /// The method.
    pub method: Method,
    /// Position RMSE over the moving steps, mm.
    pub position_rmse_mm: Stat,
    /// Heading RMSE over the moving steps, degrees.
    pub heading_rmse_deg: Stat,
    /// Feature RMSE over every step, mm (NaN for odometry).
    pub feature_rmse_mm: Stat,
}

/// An organ's results.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct OrganStudy {
    /// The organ.
    pub organ: Organ,
    /// The scene's parameters (the seed of the first run; run r uses seed + r).
    pub scene: SceneParams,
    /// Monte Carlo runs.
    pub runs: usize,
    /// The time series' order, its coefficients fitted on the first run and the true ones.
    pub order: usize,
    /// Fitted on the first run.
    pub fitted_coefficients: Vec<f64>,
    /// Of the true motion (the order 2H + 1 recurrence).
    pub true_coefficients: Vec<f64>,
    /// Each method's figures.
    pub methods: Vec<MethodSummary>,
    /// The Fisher information's rank test of each SLAM method, on the first run's scene
    /// without odometry.
    pub rank: Vec<RankTest>,
}

/// Monte Carlo of every method on `organ`: `runs` scenes (seeds `scene.seed + r`), and the
/// rank test on a scene of `rank_steps` steps (half of them still) and the same features.
pub fn study_organ(
    scene: &SceneParams,
    p: &EstimatorParams,
    runs: usize,
    rank_steps: usize,
) -> Result<OrganStudy, String> {
    if runs == 0 {
        return Err("`runs` is 0: at least one Monte Carlo run".into());
    }
    let mut per: Vec<Vec<Errors>> = vec![Vec::new(); Method::ALL.len()];
    let mut fitted = Vec::new();
    let mut true_c = Vec::new();
    let mut order = 0;
    for r in 0..runs {
        let sp = SceneParams {
            seed: scene.seed + r as u64,
            ..scene.clone()
        };
        let s = Scene::simulate(&sp)?;
        if r == 0 {
            order = order_of(&s, p);
            fitted = fit_for(&s, p)?;
            true_c = s.true_recurrence();
        }
        for (k, m) in Method::ALL.iter().enumerate() {
            let e = estimate(*m, &s, p)?;
            per[k].push(errors(&s, &e));
        }
    }
    let methods = Method::ALL
        .iter()
        .zip(&per)
        .map(|(m, es)| MethodSummary {
            method: *m,
            position_rmse_mm: Stat::of(&es.iter().map(|e| e.position_rmse_mm).collect::<Vec<_>>()),
            heading_rmse_deg: Stat::of(&es.iter().map(|e| e.heading_rmse_deg).collect::<Vec<_>>()),
            feature_rmse_mm: Stat::of(&es.iter().map(|e| e.feature_rmse_mm).collect::<Vec<_>>()),
        })
        .collect();
    let rank_scene = Scene::simulate(&SceneParams {
        steps: rank_steps,
        static_steps: rank_steps / 2,
        ..scene.clone()
    })?;
    let rank = [Method::Static, Method::Ed, Method::Fem, Method::TimeSeries]
        .iter()
        .map(|m| information_rank(*m, &rank_scene, p))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(OrganStudy {
        organ: scene.organ,
        scene: scene.clone(),
        runs,
        order,
        fitted_coefficients: fitted,
        true_coefficients: true_c,
        methods,
        rank,
    })
}

/// The whole study: every organ asked for, with the estimators' parameters.
#[derive(Clone, Debug, PartialEq, serde::Serialize)]
pub struct Study {
    /// The estimators' parameters.
    pub estimator: EstimatorParams,
    /// Each organ's results.
    pub organs: Vec<OrganStudy>,
}

/// [`study_organ`] for each of `organs`, each scene built by `scene` from the organ.
pub fn run_study(
    organs: &[Organ],
    scene: impl Fn(Organ) -> SceneParams,
    p: &EstimatorParams,
    runs: usize,
    rank_steps: usize,
) -> Result<Study, String> {
    let organs = organs
        .iter()
        .map(|&o| study_organ(&scene(o), p, runs, rank_steps))
        .collect::<Result<Vec<_>, _>>()?;
    Ok(Study {
        estimator: p.clone(),
        organs,
    })
}

impl Study {
    /// The tables: per organ and method, mean ± standard deviation of the RMSEs, each method's
    /// position RMSE over the static map's, and the rank test.
    pub fn table(&self) -> String {
        use std::fmt::Write;
        let mut s = String::new();
        for o in &self.organs {
            let _ = writeln!(
                s,
                "{} ({} runs, {} steps of which {} still, {} features; time series of order {}):",
                o.organ.name(),
                o.runs,
                o.scene.steps,
                o.scene.static_steps,
                o.scene.features,
                o.order
            );
            let _ = writeln!(
                s,
                "  {:<12} {:>18} {:>10} {:>18} {:>18}",
                "method", "position RMSE mm", "/ static", "heading RMSE deg", "feature RMSE mm"
            );
            let base = o
                .methods
                .iter()
                .find(|m| m.method == Method::Static)
                .map_or(f64::NAN, |m| m.position_rmse_mm.mean);
            for m in &o.methods {
                let f = if m.feature_rmse_mm.mean.is_finite() {
                    format!(
                        "{:.3} ± {:.3}",
                        m.feature_rmse_mm.mean, m.feature_rmse_mm.std
                    )
                } else {
                    "-".into()
                };
                let _ = writeln!(
                    s,
                    "  {:<12} {:>18} {:>10.2} {:>18} {:>18}",
                    m.method.name(),
                    format!(
                        "{:.3} ± {:.3}",
                        m.position_rmse_mm.mean, m.position_rmse_mm.std
                    ),
                    m.position_rmse_mm.mean / base,
                    format!(
                        "{:.3} ± {:.3}",
                        m.heading_rmse_deg.mean, m.heading_rmse_deg.std
                    ),
                    f
                );
            }
            for r in &o.rank {
                let _ = writeln!(
                    s,
                    "  Fisher information without odometry, {}: rank {} of {} unknowns (deficiency {}; smallest eigenvalue kept {:.1e}, largest dropped {:.1e} of the largest)",
                    r.method.name(),
                    r.rank,
                    r.unknowns,
                    r.deficiency,
                    r.smallest_kept,
                    r.largest_dropped
                );
            }
        }
        s
    }
}

/// One run of every method on the scene of `scene` (its seed), with the estimates, for a
/// viewer: the scene and each method's estimate.
pub fn run_once(
    scene: &SceneParams,
    p: &EstimatorParams,
) -> Result<(Scene, Vec<(Method, Estimate)>), String> {
    let s = Scene::simulate(scene)?;
    let estimates = Method::ALL
        .iter()
        .map(|&m| estimate(m, &s, p).map(|e| (m, e)))
        .collect::<Result<Vec<_>, _>>()?;
    Ok((s, estimates))
}
