//! The study: errors against the truth, the Fisher information's rank, the Monte Carlo over an
//! organ's runs and the tables.

use crate::scene::{wrap, Organ, Scene, SceneParams};
use crate::{build_with, estimate, fit_for, order_of, Estimate, EstimatorParams, Method};

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
