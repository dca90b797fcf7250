//! Residuals of the regularisation and pose terms, and the pose retraction (see
//! [`crate::solver`]).

use crate::graph::{apply_node, EdGraph};
use misslam_framework::nalgebra::{Isometry3, Translation3, UnitQuaternion, Vector3};

/// The pose retraction the solver uses: world_from_camera * exp(xi), xi = (rho, omega).
pub fn pose_update(pose: &Isometry3<f64>, xi: &[f64]) -> Isometry3<f64> {
    let step = Isometry3::from_parts(
        Translation3::new(xi[0], xi[1], xi[2]),
        UnitQuaternion::from_scaled_axis(Vector3::new(xi[3], xi[4], xi[5])),
    );
    pose * step
}

/// Residuals and Jacobian of Sumner's rotation term for one node: 6 rows over the 12 unknowns.
/// Off-diagonal rows carry sqrt(2), so the sum of squares equals ||A^T A - I||_F^2.
pub fn rot_residuals(p: &[f64; 12]) -> ([f64; 6], [[f64; 12]; 6]) {
    let col = |i: usize| Vector3::new(p[i], p[4 + i], p[8 + i]);
    let c = [col(0), col(1), col(2)];
    let s2 = std::f64::consts::SQRT_2;
    let mut r = [0.0; 6];
    let mut j = [[0.0; 12]; 6];
    let put = |row: &mut [f64; 12], i: usize, v: Vector3<f64>, f: f64| {
        row[i] += f * v.x;
        row[4 + i] += f * v.y;
        row[8 + i] += f * v.z;
    };
    let pairs = [(0, 1), (0, 2), (1, 2)];
    for (q, &(a, b)) in pairs.iter().enumerate() {
        r[q] = s2 * c[a].dot(&c[b]);
        put(&mut j[q], a, c[b], s2);
        put(&mut j[q], b, c[a], s2);
    }
    for a in 0..3 {
        r[3 + a] = c[a].dot(&c[a]) - 1.0;
        put(&mut j[3 + a], a, c[a], 2.0);
    }
    (r, j)
}

/// The rotation-vector residual of E_r: log(R~^T R).
pub(crate) fn pose_rot_residual(prior: &Isometry3<f64>, pose: &Isometry3<f64>) -> Vector3<f64> {
    (prior.rotation.inverse() * pose.rotation).scaled_axis()
}

/// E_reg residual of directed edge (j, k).
pub fn reg_residual(graph: &EdGraph, j: u32, k: u32) -> Vector3<f64> {
    let g = graph.nodes();
    let (gj, gk) = (g[j as usize], g[k as usize]);
    let pk = &graph.warp[k as usize];
    apply_node(&graph.warp[j as usize], &gj, &gk) - gk - Vector3::new(pk[3], pk[7], pk[11])
}
