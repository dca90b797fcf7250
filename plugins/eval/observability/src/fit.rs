//! The time series' coefficients: the order, and their fit on the still period (free, by total
//! or ridge least squares, or as a periodic motion).

use misslam_framework::nalgebra::DMatrix;

use crate::scene::Scene;
use crate::EstimatorParams;

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
        total_least_squares(a, "the time series' fit")?
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
    total_least_squares(a, "the periodic fit")
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

/// Total least squares of [X | y] (the last column the target): the right singular vector v of
/// the smallest singular value gives x = -v[..n] / v[n]. `what` names the fit in errors.
fn total_least_squares(a: DMatrix<f64>, what: &str) -> Result<Vec<f64>, String> {
    let n = a.ncols() - 1;
    let svd = a.svd(false, true);
    let v_t = svd
        .v_t
        .ok_or_else(|| format!("{what}: no singular vectors"))?;
    let k = svd
        .singular_values
        .iter()
        .enumerate()
        .min_by(|x, y| x.1.total_cmp(y.1))
        .map(|x| x.0)
        .ok_or_else(|| format!("{what}: no singular values"))?;
    let v = v_t.row(k);
    if v[n].abs() < 1e-12 {
        return Err(format!("{what} is degenerate: lengthen the still period"));
    }
    let x: Vec<f64> = (0..n).map(|i| -v[i] / v[n]).collect();
    if x.iter().any(|v| !v.is_finite()) {
        return Err(format!("{what} is not finite"));
    }
    Ok(x)
}
