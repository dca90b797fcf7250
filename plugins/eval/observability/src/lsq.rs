//! Sparse nonlinear least squares for the study: residual blocks over a few unknowns each,
//! Jacobians by central differences, Levenberg-Marquardt on the normal equations with faer's
//! sparse Cholesky, and the dense Fisher information for the rank test.

use std::collections::HashMap;

use faer::sparse::{SparseColMat, Triplet};
use faer::Side;
use misslam_framework::nalgebra::{DMatrix, SymmetricEigen};

/// A residual function: the values of a block's unknowns in, its residuals out.
pub type ResidualFn = Box<dyn Fn(&[f64], &mut [f64]) + Send + Sync>;

/// A residual block: `f(values of vars, out)` writes `dim` residuals, already whitened (divided
/// by their standard deviation, or scaled by the square root of their weight).
pub struct Block {
    /// The unknowns it reads, in the order `f` takes their values.
    pub vars: Vec<usize>,
    /// Residuals it writes.
    pub dim: usize,
    /// The residual function.
    pub f: ResidualFn,
}

/// A least-squares problem: unknowns and residual blocks.
#[derive(Default)]
pub struct Problem {
    /// Unknowns.
    pub n: usize,
    /// Blocks.
    pub blocks: Vec<Block>,
}

/// How a solve went.
#[derive(Clone, Copy, Debug, Default, PartialEq, serde::Serialize)]
pub struct SolveInfo {
    /// Accepted steps.
    pub iterations: usize,
    /// Cost (half the sum of squared whitened residuals) before and after.
    pub cost_before: f64,
    /// After.
    pub cost_after: f64,
}

impl Problem {
    /// Adds a block.
    pub fn add(
        &mut self,
        vars: Vec<usize>,
        dim: usize,
        f: impl Fn(&[f64], &mut [f64]) + Send + Sync + 'static,
    ) {
        self.blocks.push(Block {
            vars,
            dim,
            f: Box::new(f),
        });
    }

    fn gather(x: &[f64], vars: &[usize], out: &mut Vec<f64>) {
        out.clear();
        out.extend(vars.iter().map(|&v| x[v]));
    }

    /// Half the sum of squared residuals at `x`.
    pub fn cost(&self, x: &[f64]) -> f64 {
        let mut vals = Vec::new();
        let mut r = Vec::new();
        let mut total = 0.0;
        for b in &self.blocks {
            Self::gather(x, &b.vars, &mut vals);
            r.clear();
            r.resize(b.dim, 0.0);
            (b.f)(&vals, &mut r);
            total += r.iter().map(|v| v * v).sum::<f64>();
        }
        0.5 * total
    }

    /// Calls `each(vars, jacobian (dim x vars, row-major), residual)` for every block at `x`.
    fn linearise(&self, x: &[f64], mut each: impl FnMut(&[usize], &[f64], &[f64])) {
        let mut vals = Vec::new();
        let (mut r, mut rp, mut rm, mut jac) = (Vec::new(), Vec::new(), Vec::new(), Vec::new());
        for b in &self.blocks {
            Self::gather(x, &b.vars, &mut vals);
            let nv = vals.len();
            r.clear();
            r.resize(b.dim, 0.0);
            (b.f)(&vals, &mut r);
            jac.clear();
            jac.resize(b.dim * nv, 0.0);
            for k in 0..nv {
                let v0 = vals[k];
                let h = 1e-6 * v0.abs().max(1.0);
                rp.clear();
                rp.resize(b.dim, 0.0);
                rm.clear();
                rm.resize(b.dim, 0.0);
                vals[k] = v0 + h;
                (b.f)(&vals, &mut rp);
                vals[k] = v0 - h;
                (b.f)(&vals, &mut rm);
                vals[k] = v0;
                for i in 0..b.dim {
                    jac[i * nv + k] = (rp[i] - rm[i]) / (2.0 * h);
                }
            }
            each(&b.vars, &jac, &r);
        }
    }

    /// The normal equations at `x`: J^T J (lower triangle, by entry) and J^T r.
    fn normal_equations(&self, x: &[f64]) -> (HashMap<(usize, usize), f64>, Vec<f64>) {
        let mut h: HashMap<(usize, usize), f64> = HashMap::new();
        let mut g = vec![0.0; self.n];
        self.linearise(x, |vars, jac, r| {
            let nv = vars.len();
            let dim = r.len();
            for a in 0..nv {
                let mut ga = 0.0;
                for i in 0..dim {
                    ga += jac[i * nv + a] * r[i];
                }
                g[vars[a]] += ga;
                for b in 0..nv {
                    let (va, vb) = (vars[a], vars[b]);
                    if va < vb {
                        continue;
                    }
                    let mut s = 0.0;
                    for i in 0..dim {
                        s += jac[i * nv + a] * jac[i * nv + b];
                    }
                    if s != 0.0 {
                        *h.entry((va, vb)).or_insert(0.0) += s;
                    }
                }
            }
        });
        (h, g)
    }

    /// Levenberg-Marquardt from `x` (updated in place): steps of (J^T J + lambda I) dx = -J^T r
    /// by a sparse Cholesky, lambda divided by 3 after a step that lowers the cost and
    /// multiplied by 4 otherwise, until the cost falls by less than `tol` (relative) or
    /// `max_iterations` steps. The damping also keeps unobservable directions where they start.
    pub fn solve(
        &self,
        x: &mut [f64],
        max_iterations: usize,
        tol: f64,
    ) -> Result<SolveInfo, String> {
        let mut cost = self.cost(x);
        let mut info = SolveInfo {
            cost_before: cost,
            ..Default::default()
        };
        let mut lambda = 1e-4;
        let mut trial = x.to_vec();
        'outer: for _ in 0..max_iterations {
            let (h, g) = self.normal_equations(x);
            loop {
                // lambda I: Marquardt's scaling by the diagonal (tried) converged worse on the
                // stiff near-exact problems of the tests.
                let mut diag = vec![0.0; self.n];
                let mut trips: Vec<Triplet<usize, usize, f64>> = h
                    .iter()
                    .map(|(&(r, c), &v)| {
                        if r == c {
                            diag[r] = v;
                        }
                        Triplet::new(r, c, v + if r == c { lambda } else { 0.0 })
                    })
                    .collect();
                for (k, d) in diag.iter().enumerate() {
                    if *d == 0.0 {
                        trips.push(Triplet::new(k, k, lambda));
                    }
                }
                let a = SparseColMat::<usize, f64>::try_new_from_triplets(self.n, self.n, &trips)
                    .map_err(|e| format!("normal equations: {e:?}"))?;
                let llt = a.sp_cholesky(Side::Lower).map_err(|e| {
                    format!("the damped normal equations are not positive definite: {e:?}")
                })?;
                let mut rhs = faer::Mat::<f64>::from_fn(self.n, 1, |i, _| -g[i]);
                use faer::linalg::solvers::SolveCore;
                llt.solve_in_place_with_conj(faer::Conj::No, rhs.as_mut());
                for (k, t) in trial.iter_mut().enumerate() {
                    *t = x[k] + rhs[(k, 0)];
                }
                let c = self.cost(&trial);
                if c.is_finite() && c < cost {
                    x.copy_from_slice(&trial);
                    let drop = (cost - c) / cost.max(1e-300);
                    cost = c;
                    info.iterations += 1;
                    lambda = (lambda / 3.0).max(1e-12);
                    if drop < tol {
                        break 'outer;
                    }
                    break;
                }
                lambda *= 4.0;
                if lambda > 1e12 {
                    break 'outer;
                }
            }
        }
        info.cost_after = cost;
        Ok(info)
    }

    /// The Fisher information J^T J at `x` (whitened residuals), dense.
    pub fn information(&self, x: &[f64]) -> DMatrix<f64> {
        let mut m = DMatrix::zeros(self.n, self.n);
        self.linearise(x, |vars, jac, r| {
            let nv = vars.len();
            for a in 0..nv {
                for b in 0..nv {
                    let mut s = 0.0;
                    for i in 0..r.len() {
                        s += jac[i * nv + a] * jac[i * nv + b];
                    }
                    m[(vars[a], vars[b])] += s;
                }
            }
        });
        m
    }
}

/// Numerical rank of a symmetric positive semi-definite matrix: eigenvalues above
/// `rel_tol` times the largest.
pub fn rank(m: &DMatrix<f64>, rel_tol: f64) -> usize {
    if m.nrows() == 0 {
        return 0;
    }
    let eig = SymmetricEigen::new(m.clone());
    let max = eig.eigenvalues.iter().fold(0.0f64, |a, &b| a.max(b.abs()));
    eig.eigenvalues
        .iter()
        .filter(|&&v| v > rel_tol * max)
        .count()
}
