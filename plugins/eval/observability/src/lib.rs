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
//!   of the wall (co-rotational Euler-Bernoulli beams between neighbouring points, at rest in
//!   the first view), nothing tying the steps;
//! - [`Method::TimeSeries`]: a position per feature per step with E_f.
//!
//! [`run_study`] runs them by Monte Carlo (RMSE of position and heading against the truth) and
//! tests the rank of each one's Fisher information without odometry ([`information_rank`]).

pub mod fit;
pub mod lsq;
pub mod scene;
pub mod study;

pub use fit::*;
pub use study::*;

use misslam_framework::nalgebra::{Matrix2, Vector2};
use scene::{wrap, Pose2, Scene};

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
    /// SLAM with a finite-element model of the wall per step: a ring of co-rotational
    /// Euler-Bernoulli beam elements between neighbouring points (axial and bending energy, a
    /// rotation unknown per point), at rest in the first view, no temporal prior.
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
    /// FEM: axial stiffness EA of the beam elements (in the observations' weighting: twice an
    /// element's axial energy is EA / L (l - L)^2, L its rest length).
    pub fem_stiffness: f64,
    /// FEM: the wall's thickness h, mm, which sets the bending stiffness of its rectangular
    /// section, EI = EA h^2 / 12.
    pub fem_thickness_mm: f64,
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
            fem_thickness_mm: 8.0,
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
            ("fem_thickness_mm", self.fem_thickness_mm),
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

/// Adds a position per feature per step as unknowns (after the poses, already in `x`), each
/// started where its observation puts it from the dead-reckoned pose `dr`, with its
/// observation residual; returns where feature j of step n sits in `x`.
fn per_step_features(
    prob: &mut lsq::Problem,
    x: &mut Vec<f64>,
    s: &Scene,
    dr: &[Pose2],
    sigma: f64,
) -> impl Fn(usize, usize) -> usize + Copy {
    let (np, m) = (3 * s.params.steps, s.params.features);
    let fv = move |n: usize, j: usize| np + 2 * (n * m + j);
    for (n, pose) in dr.iter().enumerate() {
        for (j, z) in s.observations[n].iter().enumerate() {
            let z = *z;
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
                    obs_residual(&pose_of(v), &Vector2::new(v[3], v[4]), &z, sigma, out);
                },
            );
        }
    }
    fv
}

/// The residuals of a co-rotational Euler-Bernoulli beam element from `a` to `b` with nodal
/// rotations `ta`, `tb` (from the rest state), rest length and chord angle `rest`, and `scale`
/// (sqrt(EA / L), sqrt(EI / L)): the element's own end rotations are the nodes' less its chord's
/// turn, and the squares sum to twice its strain energy, EA / L (l - L)^2 + EI / L (4 ta^2 +
/// 4 ta tb + 4 tb^2) (the frame element's bending stiffness EI / L [4 2; 2 4]).
fn beam_residual(
    a: &Vector2<f64>,
    b: &Vector2<f64>,
    ta: f64,
    tb: f64,
    rest: (f64, f64),
    scale: (f64, f64),
    out: &mut [f64],
) {
    let d = b - a;
    let turn = wrap(d.y.atan2(d.x) - rest.1);
    let (ta, tb) = (wrap(ta - turn), wrap(tb - turn));
    out[0] = scale.0 * (d.norm() - rest.0);
    out[1] = scale.1 * (2.0 * ta + tb);
    out[2] = scale.1 * 3f64.sqrt() * tb;
}

/// The estimate of a problem built by [`per_step_features`]: the poses and the features.
fn read_per_step(x: &[f64], nsteps: usize, m: usize) -> Estimate {
    let np = 3 * nsteps;
    Estimate {
        poses: (0..nsteps).map(|n| pose_of(&x[3 * n..])).collect(),
        features: Some(
            (0..nsteps)
                .map(|n| {
                    (0..m)
                        .map(|j| {
                            let v = np + 2 * (n * m + j);
                            Vector2::new(x[v], x[v + 1])
                        })
                        .collect()
                })
                .collect(),
        ),
        info: Default::default(),
    }
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
            let fv = per_step_features(&mut prob, &mut x, s, &dr, so);
            // The wall as a ring of co-rotational Euler-Bernoulli beam elements between
            // neighbouring points: each point has a rotation unknown per step (after the
            // features), started at the mean turn of its two elements' chords.
            let tv0 = x.len();
            let tv = move |n: usize, j: usize| tv0 + n * m + j;
            let chord = |f: &[Vector2<f64>], j: usize| f[(j + 1) % m] - f[j];
            let rest: Vec<(f64, f64)> = (0..m)
                .map(|j| {
                    let d = chord(&first, j);
                    (d.norm().max(1e-9), d.y.atan2(d.x))
                })
                .collect();
            for n in 0..nsteps {
                let f: Vec<Vector2<f64>> = (0..m)
                    .map(|j| Vector2::new(x[fv(n, j)], x[fv(n, j) + 1]))
                    .collect();
                let turn = |j: usize| {
                    let d = chord(&f, j);
                    wrap(d.y.atan2(d.x) - rest[j].1)
                };
                for j in 0..m {
                    let (a, b) = (turn((j + m - 1) % m), turn(j));
                    x.push(wrap(a + 0.5 * wrap(b - a)));
                }
            }
            let ea = p.fem_stiffness;
            let ei = ea * p.fem_thickness_mm * p.fem_thickness_mm / 12.0;
            for n in 0..nsteps {
                for (j, &(len, angle)) in rest.iter().enumerate() {
                    let k = (j + 1) % m;
                    let (sa, sb) = ((ea / len).sqrt(), (ei / len).sqrt());
                    let (a, b) = (fv(n, j), fv(n, k));
                    let vars = vec![a, a + 1, b, b + 1, tv(n, j), tv(n, k)];
                    prob.add(vars, 3, move |v, out| {
                        let (a, b) = (Vector2::new(v[0], v[1]), Vector2::new(v[2], v[3]));
                        beam_residual(&a, &b, v[4], v[5], (len, angle), (sa, sb), out);
                    });
                }
            }
            prob.n = x.len();
            Ok((
                prob,
                x,
                Box::new(move |x: &[f64]| read_per_step(x, nsteps, m)),
            ))
        }
        Method::TimeSeries => {
            let c = match coefficients {
                Some(c) => c.to_vec(),
                None => fit_for(s, p)?,
            };
            let t = c.len();
            let fv = per_step_features(&mut prob, &mut x, s, &dr, so);
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
                Box::new(move |x: &[f64]| read_per_step(x, nsteps, m)),
            ))
        }
    }
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

#[cfg(test)]
mod tests {
    use super::*;

    fn energy2(a: Vector2<f64>, b: Vector2<f64>, ta: f64, tb: f64, rest: (f64, f64)) -> f64 {
        let (ea, ei) = (100.0, 50.0);
        let scale = ((ea / rest.0).sqrt(), (ei / rest.0).sqrt());
        let mut out = [0.0; 3];
        beam_residual(&a, &b, ta, tb, rest, scale, &mut out);
        out.iter().map(|r| r * r).sum()
    }

    #[test]
    fn a_beam_element_stores_the_textbook_energies_and_none_under_a_rigid_motion() {
        let (a, b) = (Vector2::new(1.0, 2.0), Vector2::new(11.0, 2.0));
        let rest = (10.0, 0.0);
        assert_eq!(energy2(a, b, 0.0, 0.0, rest), 0.0);
        // A rigid motion, the nodes turning with the element: no energy.
        let (r, t) = (scene::rot(0.7), Vector2::new(-3.0, 5.0));
        let e = energy2(r * a + t, r * b + t, 0.7, 0.7, rest);
        assert!(e < 1e-20, "{e}");
        // A stretch by 0.5: twice the energy is EA / L 0.5^2.
        let e = energy2(a, b + Vector2::new(0.5, 0.0), 0.0, 0.0, rest);
        assert!((e - 100.0 / 10.0 * 0.25).abs() < 1e-12, "{e}");
        // Bent into an arc of curvature k (its chord kept): the ends turn by -kL/2 and kL/2, and
        // twice the energy is EI k^2 L, the integral of EI k^2 along the element.
        let k = 0.01;
        let e = energy2(a, b, -k * 5.0, k * 5.0, rest);
        assert!((e - 50.0 * k * k * 10.0).abs() < 1e-12, "{e}");
        // A cantilever's end rotation without a turn of the chord is the stiffer one: 4 EI / L.
        let e = energy2(a, b, 0.0, 0.01, rest);
        assert!((e - 4.0 * 50.0 / 10.0 * 1e-4).abs() < 1e-12, "{e}");
    }
}
