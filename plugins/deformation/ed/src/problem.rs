//! What a deformation solve is given (the model's visible points, the scan, the distance field, the
//! sparse correspondences, the pose prior) and the energy's weights and options.

use crate::field::DistanceField;
use crate::graph::Binding;
use misslam_framework::nalgebra::{Isometry3, Vector3};
use schemars::JsonSchema;
use serde::{Deserialize, Serialize};

/// Pinhole intrinsics of the scan (left camera), pixels.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Intrinsics {
    /// Focal length x.
    pub fx: f64,
    /// Focal length y.
    pub fy: f64,
    /// Principal point x.
    pub cx: f64,
    /// Principal point y.
    pub cy: f64,
    /// Width.
    pub width: u32,
    /// Height.
    pub height: u32,
}

impl Intrinsics {
    /// The pixel (row-major index) that camera-frame point `p` projects to, rounded to the
    /// nearest; none when it is behind the camera (or NaN) or outside the image.
    #[inline]
    pub fn pixel(&self, p: &Vector3<f64>) -> Option<usize> {
        if p.z.is_nan() || p.z <= 1e-6 {
            return None;
        }
        let (w, h) = (self.width as usize, self.height as usize);
        let u = (self.fx * p.x / p.z + self.cx).round();
        let v = (self.fy * p.y / p.z + self.cy).round();
        if !(u >= 0.0 && v >= 0.0 && (u as usize) < w && (v as usize) < h) {
            return None;
        }
        Some(v as usize * w + u as usize)
    }
}

/// The live observation for projective association: vertex and normal maps in the camera frame,
/// row-major, NaN where invalid.
#[derive(Clone, Copy, Debug)]
pub struct Scan<'a> {
    /// Camera model of the maps.
    pub intrinsics: Intrinsics,
    /// Gamma(u, v), mm.
    pub vertices: &'a [[f32; 3]],
    /// Unit normals H(u, v).
    pub normals: &'a [[f32; 3]],
}

/// The model points the data terms use (the visible set L), in the canonical frame.
#[derive(Clone, Copy, Debug)]
pub struct ModelPoints<'a> {
    /// Positions v_i.
    pub points: &'a [Vector3<f64>],
    /// Unit normals n_i (for the association's angle test).
    pub normals: &'a [Vector3<f64>],
    /// Each point's nodes and weights.
    pub bindings: &'a [Binding],
}

/// The visible set L gathered from a model's per-point arrays, in buffers a caller keeps across
/// frames.
#[derive(Clone, Debug, Default)]
pub struct ModelSubset {
    /// Positions of the gathered points.
    pub points: Vec<Vector3<f64>>,
    /// Their normals.
    pub normals: Vec<Vector3<f64>>,
    /// Their bindings.
    pub bindings: Vec<Binding>,
}

impl ModelSubset {
    /// Replaces the contents with the points at `indices`.
    pub fn gather(
        &mut self,
        indices: &[u32],
        points: &[Vector3<f64>],
        normals: &[Vector3<f64>],
        bindings: &[Binding],
    ) {
        self.points.clear();
        self.points
            .extend(indices.iter().map(|&i| points[i as usize]));
        self.normals.clear();
        self.normals
            .extend(indices.iter().map(|&i| normals[i as usize]));
        self.bindings.clear();
        self.bindings
            .extend(indices.iter().map(|&i| bindings[i as usize]));
    }

    /// The gathered points as the data terms see them.
    pub fn view(&self) -> ModelPoints<'_> {
        ModelPoints {
            points: &self.points,
            normals: &self.normals,
            bindings: &self.bindings,
        }
    }
}

impl ModelPoints<'_> {
    /// No points.
    pub const EMPTY: ModelPoints<'static> = ModelPoints {
        points: &[],
        normals: &[],
        bindings: &[],
    };
}

/// A sparse correspondence: a canonical model point (a keypoint of the model) should land on an
/// observed 3D point of the current frame (camera frame).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Correspondence {
    /// The model keypoint, canonical frame.
    pub point: Vector3<f64>,
    /// Its binding to the graph.
    pub binding: Binding,
    /// The observed position, camera frame, mm.
    pub target: Vector3<f64>,
    /// The observed surface's unit normal at `target` (camera frame), when known: the residual
    /// along it is weighted by `weights.corr_normal` (the data term already says where the
    /// surface is), the two directions along the surface fully.
    pub normal: Option<Vector3<f64>>,
}

/// One squared residual row of a point term: (direction, residual along it, weight factor).
pub type Row = (Vector3<f64>, f64, f64);

impl Correspondence {
    /// E_corr at the warped point `p` (camera frame): its three rows (x, y, z; or, with a
    /// normal, two directions along the surface and the normal, weighted by `normal_weight`)
    /// and the weighted residual norm sqrt(sum of weight * residual^2) the robust kernel takes.
    pub fn rows(&self, p: &Vector3<f64>, normal_weight: f64) -> ([Row; 3], f64) {
        let d = p - self.target;
        match self.normal {
            None => (
                [
                    (Vector3::x(), d.x, 1.0),
                    (Vector3::y(), d.y, 1.0),
                    (Vector3::z(), d.z, 1.0),
                ],
                d.norm(),
            ),
            Some(n) => {
                // A basis along the surface: the axis least aligned with n, made orthogonal.
                let a = if n.x.abs() < 0.6 {
                    Vector3::x()
                } else {
                    Vector3::y()
                };
                let t1 = (a - n * n.dot(&a)).normalize();
                let t2 = n.cross(&t1);
                let (r1, r2, rn) = (t1.dot(&d), t2.dot(&d), n.dot(&d));
                (
                    [(t1, r1, 1.0), (t2, r2, 1.0), (n, rn, normal_weight)],
                    (r1 * r1 + r2 * r2 + normal_weight * rn * rn).sqrt(),
                )
            }
        }
    }
}

/// Everything one solve sees.
#[derive(Clone, Copy, Debug)]
pub struct Problem<'a> {
    /// Model points for the data terms (projective and distance-field).
    pub model: ModelPoints<'a>,
    /// The scan for projective point-to-plane association (E_data, template-free).
    pub scan: Option<Scan<'a>>,
    /// The distance field for E_data of the template path (camera frame).
    pub field: Option<&'a DistanceField>,
    /// Sparse correspondences (E_corr).
    pub correspondences: &'a [Correspondence],
    /// The rigid tracker's pose R~_c, T~_c (`world_from_camera`), the prior of E_r and E_p, and the
    /// starting pose of the solve.
    pub pose_prior: Isometry3<f64>,
}

/// Weights of the energy terms (each a sum of squared residuals).
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Weights {
    /// w_rot: Sumner's rotation term ||A^T A - I||_F^2 per node.
    pub rot: f64,
    /// w_reg: regularisation, per edge and direction, mm^-2 scale.
    pub reg: f64,
    /// w_data: point-to-plane projective data term.
    pub data: f64,
    /// Extra point-to-point part of the projective data term, as a fraction of w_data (0 = pure
    /// point-to-plane, the default: the associated scan point is the one at the rounded pixel, up to
    /// half a pixel off along the surface, so a point-to-point part biases the fit by that much).
    pub point_to_point: f64,
    /// w_data of the distance-field term (template path).
    pub field: f64,
    /// w_corr: sparse 3D correspondences.
    pub corr: f64,
    /// Share of w_corr along the observed surface normal, for correspondences that carry one
    /// (1: the full 3D distance of method.md; 0: only where along the surface).
    pub corr_normal: f64,
    /// w_m: motion prior ||t_j - t_j^0||^2 on the translation of each solved node a model point
    /// binds, t_j^0 its value when the solve starts (the previous frame's), mm^-2. It holds what
    /// the data cannot see (a node sliding along the surface) where the previous frame left it.
    pub motion: f64,
    /// w_u: the same prior ||t_j - t_j^0||^2 on each solved node no data term binds (no model
    /// point, field sample or correspondence: the unseen part, and every node of the decoupled
    /// solve's level II), mm^-2. At 0 (the default, MIS-SLAM's behaviour) the unseen part follows
    /// the seen part as rigidly as E_rot and E_reg allow, however far from it; above 0 the seen
    /// part's motion fades into the unseen part over about the node spacing times
    /// sqrt(w_reg / w_u), and tissue far from any observation stays where it was. For organs
    /// held at their far side (the heart of `../shared/data/heart` moves 2.7 mm where the camera
    /// sees it and 0.5 mm behind); not for a whole organ shifting in view.
    pub unseen_motion: f64,
    /// w_rot of the solved nodes no data term binds (as for `unseen_motion`; every node of the
    /// decoupled solve's level II); unset, `rot`. Set high (1000) it holds the unseen part's nodes
    /// to rotations while the seen part keeps the affine freedom that fits the scan: the unseen
    /// tissue then follows the seen part as locally rigid instead of continuing its stretch. On
    /// the phantom organs' templates this lowers the never-seen part's error; on a heart whose
    /// back holds still while its front contracts it raises it (docs/template.md, session 42).
    pub rot_unseen: Option<f64>,
    /// w_reg of the edges with an end no data term binds; unset, `reg`. Lower than `reg`, the
    /// unseen part bends more freely from the seen one.
    pub reg_unseen: Option<f64>,
    /// w_r: rotation prior ||log(R~^T R)||^2 (rad^-2), when the pose is solved.
    pub pose_rot: f64,
    /// w_p: translation prior ||T - T~||^2 (mm^-2), when the pose is solved.
    pub pose_trans: f64,
}

impl Default for Weights {
    fn default() -> Self {
        Weights {
            rot: 1.0,
            reg: 10.0,
            data: 1.0,
            point_to_point: 0.0,
            field: 1.0,
            corr: 1.0,
            corr_normal: 1.0,
            motion: 0.0,
            unseen_motion: 0.0,
            rot_unseen: None,
            reg_unseen: None,
            pose_rot: 1e4,
            pose_trans: 10.0,
        }
    }
}

/// Robust kernel of the data terms.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Robust {
    /// Plain least squares.
    #[default]
    None,
    /// Huber: quadratic within the scale, linear beyond.
    Huber,
    /// Cauchy (Lorentzian): rho(r) = c^2 log(1 + r^2 / c^2).
    Cauchy,
}

impl Robust {
    /// IRLS weight and cost (in units of r^2) of a residual norm `r` at scale `c`.
    #[inline]
    pub fn weight_cost(self, r: f64, c: f64) -> (f64, f64) {
        match self {
            Robust::None => (1.0, r * r),
            Robust::Huber => {
                if r <= c {
                    (1.0, r * r)
                } else {
                    (c / r, c * (2.0 * r - c))
                }
            }
            Robust::Cauchy => {
                let q = r * r / (c * c);
                (1.0 / (1.0 + q), c * c * (1.0 + q).ln())
            }
        }
    }
}

/// The Jacobian of the distance-field row of E_data (residual D(v~_i), the field's trilinear
/// value at the warped point).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum FieldJacobian {
    /// The field's trilinear gradient, as written in method.md 5.2. Where the scan is noisy its
    /// level sets are bumpy, and the gradient's part along the surface pulls each vertex sideways
    /// towards the bumps: the template slides over the tissue.
    Gradient,
    /// The gradient's part along the warped model normal, n n^T grad D: the field says how far
    /// the surface is, not where on it the tissue went (a Gauss-Newton step that, like the
    /// point-to-plane row of back-projection, leaves the sliding to the regulariser and E_corr).
    /// The residual and the cost are the same. Phantom liver, ELAS depth, 40 frames: material
    /// drift 0.62 mm against 2.48 with `gradient`.
    #[default]
    Normal,
    /// The scan's own normal as the field stores it: the unit direction of the trilinear mean
    /// of each voxel's averaged pixel normals ([`crate::DistanceField::sample_normal`]; the field
    /// must be built with them, [`crate::DistanceField::from_maps_with_normals`]). Each voxel's
    /// value is a mean of n_i . (c - q_i) whose exact gradient is that mean normal, so this is
    /// the field's gradient without the bumps its finite differences take from neighbouring
    /// voxels averaging other pixels; like back-projection's point-to-plane row, the direction
    /// comes from the scan. Phantom liver, 8 seeds of 120 frames (session 38): whole template
    /// 0.2413 mm against `normal`'s 0.2442, back-projection 0.2406.
    FieldNormal,
}

/// Nonlinear least-squares method.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq, Serialize, Deserialize, JsonSchema)]
#[serde(rename_all = "snake_case")]
pub enum Method {
    /// Gauss-Newton: every step taken (a tiny ridge keeps unobserved components solvable).
    GaussNewton,
    /// Levenberg-Marquardt: H + lambda diag(H), steps accepted only when the cost falls.
    #[default]
    LevenbergMarquardt,
}

/// Options of one solve.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct SolverParams {
    /// Gauss-Newton or Levenberg-Marquardt.
    pub method: Method,
    /// Outer iterations (each re-associates the scan), 3 to 10 in the literature.
    pub max_iterations: usize,
    /// Starting LM damping lambda (relative to diag(H)).
    pub initial_lambda: f64,
    /// Stop when the cost falls by less than this fraction in an iteration.
    pub min_relative_decrease: f64,
    /// Stop when the largest parameter step is below this.
    pub min_step: f64,
    /// Solve the global scope pose (R_c, T_c) too, held near the tracker's by E_r and E_p (MIS-SLAM).
    pub optimize_pose: bool,
    /// Projective association: reject a scan point farther than this from the deformed model point, mm.
    /// Larger than the motion between two solves, smaller than the gap between folds of the tissue:
    /// a model point hidden behind a fold in front of it is otherwise pulled onto the fold. On the
    /// beating heart, 10 mm let a 2.7 mm jump end 2.1 mm off where seen (0.75 mm with 3).
    pub max_distance_mm: f64,
    /// Projective association: reject when the normals differ by more than this, degrees.
    pub max_normal_angle_deg: f64,
    /// Robust kernel of the data and correspondence terms.
    pub robust: Robust,
    /// Scale of the robust kernel, mm.
    pub robust_scale_mm: f64,
    /// Jacobian of the distance-field row (template path): `normal` or `gradient`.
    pub field_jacobian: FieldJacobian,
    /// Each numeric factorisation also serves the next this many iterations: they take their
    /// step from it (the Hessian and damping it was made with, the gradient and association of
    /// their own state: a modified Gauss-Newton step) and assemble only the gradient. A step the
    /// cost rejects is taken again from a fresh factorisation, so the cost still falls at every
    /// accepted iteration. 0: a factorisation every iteration.
    pub reuse_factorisation: usize,
    /// Term weights.
    pub weights: Weights,
}

impl Default for SolverParams {
    fn default() -> Self {
        SolverParams {
            method: Method::LevenbergMarquardt,
            max_iterations: 6,
            initial_lambda: 1e-4,
            min_relative_decrease: 1e-4,
            min_step: 1e-6,
            optimize_pose: false,
            max_distance_mm: 3.0,
            max_normal_angle_deg: 45.0,
            robust: Robust::None,
            robust_scale_mm: 2.0,
            field_jacobian: FieldJacobian::Normal,
            reuse_factorisation: 0,
            weights: Weights::default(),
        }
    }
}

impl SolverParams {
    /// Checks ranges, naming the field.
    pub fn validate(&self) -> Result<(), String> {
        let w = &self.weights;
        for (name, v) in [
            ("weights.rot", w.rot),
            ("weights.reg", w.reg),
            ("weights.data", w.data),
            ("weights.point_to_point", w.point_to_point),
            ("weights.field", w.field),
            ("weights.corr", w.corr),
            ("weights.corr_normal", w.corr_normal),
            ("weights.motion", w.motion),
            ("weights.unseen_motion", w.unseen_motion),
            ("weights.rot_unseen", w.rot_unseen.unwrap_or(0.0)),
            ("weights.reg_unseen", w.reg_unseen.unwrap_or(0.0)),
            ("weights.pose_rot", w.pose_rot),
            ("weights.pose_trans", w.pose_trans),
            ("initial_lambda", self.initial_lambda),
            ("min_relative_decrease", self.min_relative_decrease),
            ("min_step", self.min_step),
        ] {
            if !(v.is_finite() && v >= 0.0) {
                return Err(format!("{name} must be a finite number >= 0, got {v}"));
            }
        }
        for (name, v) in [
            ("max_distance_mm", self.max_distance_mm),
            ("robust_scale_mm", self.robust_scale_mm),
        ] {
            if !(v.is_finite() && v > 0.0) {
                return Err(format!("{name} must be > 0, got {v}"));
            }
        }
        if !(self.max_normal_angle_deg > 0.0 && self.max_normal_angle_deg <= 180.0) {
            return Err(format!(
                "max_normal_angle_deg must be in (0, 180], got {}",
                self.max_normal_angle_deg
            ));
        }
        if self.max_iterations == 0 {
            return Err("max_iterations must be at least 1".into());
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn correspondence_rows_split_the_residual_along_the_normal() {
        let mut c = Correspondence {
            point: Vector3::zeros(),
            binding: Binding::EMPTY,
            target: Vector3::new(1.0, 2.0, 60.0),
            normal: None,
        };
        let p = Vector3::new(1.3, 1.6, 60.5);
        let d = p - c.target;
        let (rows, norm) = c.rows(&p, 0.25);
        assert!(
            (norm - d.norm()).abs() < 1e-12,
            "no normal: the 3D distance"
        );
        assert_eq!(rows.map(|r| r.1), [d.x, d.y, d.z]);
        for n in [Vector3::z(), Vector3::new(0.9, 0.1, -0.2).normalize()] {
            c.normal = Some(n);
            let (rows, full) = c.rows(&p, 1.0);
            // An orthonormal basis: weight 1 along the normal is the 3D distance.
            assert!((full - d.norm()).abs() < 1e-12);
            assert!((rows[0].0.dot(&rows[1].0)).abs() < 1e-12);
            assert!((rows[0].0.dot(&n)).abs() < 1e-12 && (rows[1].0.dot(&n)).abs() < 1e-12);
            let (rows, along) = c.rows(&p, 0.0);
            let tangential = (d - n * n.dot(&d)).norm();
            assert!((along - tangential).abs() < 1e-12);
            assert_eq!(rows[2].2, 0.0);
            assert!((rows[2].1 - n.dot(&d)).abs() < 1e-12);
        }
    }
}
