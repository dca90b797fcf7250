//! Rigid alignment of a template to a distance field (the ICP of the template path, method.md 5.2):
//! Gauss-Newton on SE(3) over the point-to-surface distances the field gives, so no
//! correspondence search is needed. The field's gradient is the surface normal, which makes each
//! residual a point-to-plane term; Huber weights keep outliers (parts of the template the scan
//! does not see) from dragging the pose; a small damping keeps the directions a scan leaves
//! unconstrained (sliding along a plane) where they started.

use misslam_deformation_ed::DistanceField;
use misslam_framework::nalgebra::{
    Isometry3, Matrix6, Point3, Translation3, UnitQuaternion, Vector3, Vector6,
};

/// Options of [`align_to_field`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct AlignOptions {
    /// Gauss-Newton iterations at most.
    pub iterations: usize,
    /// Huber scale of the residuals, mm.
    pub huber_mm: f64,
    /// Damping added to the diagonal, relative to its mean.
    pub damping: f64,
    /// Stop when the step is below this (mm, and rad for the rotation).
    pub min_step: f64,
}

impl Default for AlignOptions {
    fn default() -> Self {
        AlignOptions {
            iterations: 30,
            huber_mm: 1.0,
            damping: 1e-6,
            min_step: 1e-7,
        }
    }
}

/// What the alignment did.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct AlignInfo {
    /// Iterations run.
    pub iterations: usize,
    /// Points inside the field at the start.
    pub points_before: usize,
    /// Points inside the field at the end.
    pub points_after: usize,
    /// RMS distance of those points at the start, mm.
    pub rms_before_mm: f64,
    /// RMS distance at the end, mm.
    pub rms_after_mm: f64,
}

fn rms(points: &[Vector3<f64>], field: &DistanceField, t: &Isometry3<f64>) -> (usize, f64) {
    let (mut n, mut s) = (0usize, 0.0);
    for p in points {
        if let Some((d, _)) = field.sample(&(t * Point3::from(*p)).coords) {
            n += 1;
            s += d * d;
        }
    }
    (n, if n > 0 { (s / n as f64).sqrt() } else { 0.0 })
}

/// The rigid motion `T` (in the field's frame) that brings `points` (the same frame) onto the
/// zero level of `field`: `T * p` lies on the surface. Fails with fewer than 6 points inside the
/// field or a non-finite step.
pub fn align_to_field(
    points: &[Vector3<f64>],
    field: &DistanceField,
    opts: &AlignOptions,
) -> Result<(Isometry3<f64>, AlignInfo), String> {
    let mut t = Isometry3::identity();
    let (points_before, rms_before_mm) = rms(points, field, &t);
    if points_before < 6 {
        return Err(format!(
            "only {points_before} template points lie within the distance field's truncation of the scan: \
             the given pose is too far off for ICP (raise align.truncation_mm or fix align.translation_mm / rotation_deg)"
        ));
    }
    let mut iterations = 0;
    for _ in 0..opts.iterations {
        let mut h = Matrix6::<f64>::zeros();
        let mut b = Vector6::<f64>::zeros();
        let mut used = 0usize;
        for p in points {
            let q = (t * Point3::from(*p)).coords;
            let Some((d, g)) = field.sample(&q) else {
                continue;
            };
            // Left perturbation: q' = q + rho + phi x q, so dq/dphi = -[q]x and
            // d(d)/d(rho, phi) = (g, q x g).
            let j = Vector6::new(g.x, g.y, g.z, 0.0, 0.0, 0.0)
                + Vector6::from_iterator(
                    [0.0, 0.0, 0.0]
                        .into_iter()
                        .chain(q.cross(&g).iter().copied()),
                );
            let w = if d.abs() <= opts.huber_mm {
                1.0
            } else {
                opts.huber_mm / d.abs()
            };
            h += w * j * j.transpose();
            b += w * d * j;
            used += 1;
        }
        if used < 6 {
            break;
        }
        let mean_diag = h.diagonal().mean().max(1e-12);
        for k in 0..6 {
            h[(k, k)] += opts.damping * mean_diag;
        }
        let Some(step) = h.cholesky().map(|c| -c.solve(&b)) else {
            break;
        };
        if !step.iter().all(|x| x.is_finite()) {
            return Err("the rigid alignment produced a non-finite step".into());
        }
        let dt = Isometry3::from_parts(
            Translation3::new(step[0], step[1], step[2]),
            UnitQuaternion::from_scaled_axis(Vector3::new(step[3], step[4], step[5])),
        );
        t = dt * t;
        iterations += 1;
        if step.amax() < opts.min_step {
            break;
        }
    }
    let (points_after, rms_after_mm) = rms(points, field, &t);
    Ok((
        t,
        AlignInfo {
            iterations,
            points_before,
            points_after,
            rms_before_mm,
            rms_after_mm,
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A bumpy surface z = f(x, y) sampled densely, with normals towards -z.
    fn surface(n: i32, step: f64) -> (Vec<[f32; 3]>, Vec<[f32; 3]>) {
        let f = |x: f64, y: f64| 60.0 + 4.0 * (x / 9.0).sin() * (y / 7.0).cos() + 0.02 * x * y;
        let mut pts = Vec::new();
        let mut nrm = Vec::new();
        for j in -n..=n {
            for i in -n..=n {
                let (x, y) = (i as f64 * step, j as f64 * step);
                let e = 1e-4;
                let fx = (f(x + e, y) - f(x - e, y)) / (2.0 * e);
                let fy = (f(x, y + e) - f(x, y - e)) / (2.0 * e);
                let nv = Vector3::new(fx, fy, -1.0).normalize();
                pts.push([x as f32, y as f32, f(x, y) as f32]);
                nrm.push([nv.x as f32, nv.y as f32, nv.z as f32]);
            }
        }
        (pts, nrm)
    }

    #[test]
    fn a_known_rigid_offset_of_a_curved_surface_is_recovered() {
        let (pts, nrm) = surface(60, 0.5);
        let field = DistanceField::from_scan(&pts, &nrm, 0.5, 6.0, 20_000_000).unwrap();
        // The template: the central part of the same surface, moved by a known motion.
        let truth = Isometry3::from_parts(
            Translation3::new(1.2, -0.8, 1.5),
            UnitQuaternion::from_euler_angles(0.03, -0.02, 0.04),
        );
        let moved = truth.inverse();
        let template: Vec<Vector3<f64>> = pts
            .iter()
            .filter(|p| p[0].abs() < 20.0 && p[1].abs() < 20.0)
            .step_by(3)
            .map(|p| (moved * Point3::new(p[0] as f64, p[1] as f64, p[2] as f64)).coords)
            .collect();
        let (t, info) = align_to_field(&template, &field, &AlignOptions::default()).unwrap();
        assert!(info.rms_before_mm > 0.5, "{info:?}");
        assert!(info.rms_after_mm < 0.01, "{info:?}");
        // Every template point is back where it came from.
        let worst = template
            .iter()
            .map(|p| ((t * Point3::from(*p)) - (truth * Point3::from(*p))).norm())
            .fold(0.0f64, f64::max);
        assert!(worst < 0.02, "worst point error {worst} mm, {info:?}");
    }

    #[test]
    fn a_template_outside_the_field_is_refused() {
        let (pts, nrm) = surface(10, 1.0);
        let field = DistanceField::from_scan(&pts, &nrm, 1.0, 3.0, 10_000_000).unwrap();
        let far: Vec<Vector3<f64>> = (0..50)
            .map(|i| Vector3::new(i as f64, 0.0, 200.0))
            .collect();
        let err = align_to_field(&far, &field, &AlignOptions::default()).unwrap_err();
        assert!(err.contains("truncation"), "{err}");
    }
}
