//! `eval.tracking`: the scope trajectory against ground truth. Keys (under `eval` in
//! `metrics.json`, computed over the run at the end; the per-frame raw position error goes out
//! on `metrics`):
//!
//! | key | meaning |
//! |---|---|
//! | `tracking.ate_mm` | absolute trajectory error: RMS of position errors after aligning the estimate to GT by the best rigid motion (Horn; `align = "none"` skips it), mm |
//! | `tracking.rpe_mm` | relative pose error over one frame: RMS of the translation error of frame-to-frame motion, mm |
//! | `tracking.rpe_deg` | the same for rotation, degrees |
//! | `tracking.lost_pct` | % of frames the tracker reported lost (excluded from the errors above) |
//!
//! | `tracking.point_err_mm` | with the tracker's `matches` and the GT depth connected: mean distance, over frames, between each tracked point's 3D position (camera frame) and the GT surface point at its keypoint (GT depth, bilinear, back-projected) |
#![deny(missing_docs)]

use misslam_framework::nalgebra::{Isometry3, Vector3};
use misslam_framework::{
    BuildContext, DepthMap, Flow, FrameInfo, Inputs, Matches, Metrics, Node, NodeContext,
    NodeError, NodeResult, Outputs, PortSpec, PortType, Pose, Registry, TrackingState, TypedPlugin,
};

/// How the estimate is aligned before the ATE.
#[derive(
    Clone, Copy, Debug, PartialEq, Eq, serde::Serialize, serde::Deserialize, schemars::JsonSchema,
)]
#[serde(rename_all = "snake_case")]
pub enum Align {
    /// The rigid motion that best maps the estimated positions onto GT (Horn / Kabsch).
    Rigid,
    /// None: both trajectories are already in the same world frame.
    None,
}

/// Parameters of `eval.tracking`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Alignment before the ATE: "rigid" or "none".
    pub align: Align,
    /// Prefix of the keys (`tracking` gives `tracking.ate_mm`).
    pub prefix: String,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            align: Align::Rigid,
            prefix: "tracking".into(),
        }
    }
}

/// Trajectory errors.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TrackingScores {
    /// Frames with a usable estimate.
    pub frames: usize,
    /// ATE, mm.
    pub ate_mm: f64,
    /// RPE translation, mm.
    pub rpe_mm: f64,
    /// RPE rotation, degrees.
    pub rpe_deg: f64,
    /// % of frames lost.
    pub lost_pct: f64,
}

pub use misslam_framework::geometry::align_rigid;

/// Scores an estimated trajectory against GT; `None` marks a frame without a usable estimate.
pub fn score(
    est: &[Option<Isometry3<f64>>],
    gt: &[Isometry3<f64>],
    align: Align,
) -> TrackingScores {
    let n = est.len().min(gt.len());
    let used: Vec<usize> = (0..n).filter(|&i| est[i].is_some()).collect();
    let lost_pct = if n == 0 {
        f64::NAN
    } else {
        100.0 * (n - used.len()) as f64 / n as f64
    };
    let e = |i: usize| est[i].unwrap_or_else(Isometry3::identity);
    let ps: Vec<Vector3<f64>> = used.iter().map(|&i| e(i).translation.vector).collect();
    let qs: Vec<Vector3<f64>> = used.iter().map(|&i| gt[i].translation.vector).collect();
    let m = match align {
        Align::Rigid => align_rigid(&ps, &qs),
        Align::None => Isometry3::identity(),
    };
    let ate = if used.is_empty() {
        f64::NAN
    } else {
        let ss: f64 = ps
            .iter()
            .zip(&qs)
            .map(|(p, q)| (m * nalgebra_point(p) - nalgebra_point(q)).norm_squared())
            .sum();
        (ss / used.len() as f64).sqrt()
    };
    // RPE over consecutive frames that both have an estimate.
    let (mut st, mut sr, mut k) = (0.0, 0.0, 0usize);
    for w in used.windows(2) {
        let (i, j) = (w[0], w[1]);
        if j != i + 1 {
            continue;
        }
        let de = e(i).inverse() * e(j);
        let dg = gt[i].inverse() * gt[j];
        let err = dg.inverse() * de;
        st += err.translation.vector.norm_squared();
        sr += err.rotation.angle().to_degrees().powi(2);
        k += 1;
    }
    let rms = |s: f64| {
        if k == 0 {
            f64::NAN
        } else {
            (s / k as f64).sqrt()
        }
    };
    TrackingScores {
        frames: used.len(),
        ate_mm: ate,
        rpe_mm: rms(st),
        rpe_deg: rms(sr),
        lost_pct,
    }
}

fn nalgebra_point(v: &Vector3<f64>) -> misslam_framework::nalgebra::Point3<f64> {
    misslam_framework::nalgebra::Point3::from(*v)
}

/// Mean distance (mm) between tracked points (camera frame, at pixel `xy`) and the GT surface
/// seen at the same pixels (GT depth, bilinear where all four neighbours are valid, lifted with
/// the calibration); `None` when no point has GT.
pub fn point_error(xy: &[[f32; 2]], points: &[[f32; 3]], depth_gt: &DepthMap) -> Option<f64> {
    let (w, h) = (depth_gt.map.width as usize, depth_gt.map.height as usize);
    let c = &depth_gt.calib;
    let (mut sum, mut n) = (0.0, 0usize);
    for (q, p) in xy.iter().zip(points) {
        if !p.iter().all(|v| v.is_finite()) {
            continue;
        }
        let (x, y) = (q[0] as f64, q[1] as f64);
        if !(x >= 0.0 && y >= 0.0) {
            continue;
        }
        let (x0, y0) = (x.floor() as usize, y.floor() as usize);
        if x0 + 1 >= w || y0 + 1 >= h {
            continue;
        }
        let (fx, fy) = (x - x0 as f64, y - y0 as f64);
        let d = |xx: usize, yy: usize| depth_gt.map.data[yy * w + xx] as f64;
        let z = (1.0 - fy) * ((1.0 - fx) * d(x0, y0) + fx * d(x0 + 1, y0))
            + fy * ((1.0 - fx) * d(x0, y0 + 1) + fx * d(x0 + 1, y0 + 1));
        if !z.is_finite() {
            continue;
        }
        let g = Vector3::new((x - c.cx) * z / c.fx, (y - c.cy) * z / c.fy, z);
        sum += (Vector3::new(p[0] as f64, p[1] as f64, p[2] as f64) - g).norm();
        n += 1;
    }
    (n > 0).then(|| sum / n as f64)
}

/// The node.
pub struct EvalTracking {
    params: Params,
    est: Vec<Option<Isometry3<f64>>>,
    gt: Vec<Isometry3<f64>>,
    point_errors: Vec<f64>,
}

impl Node for EvalTracking {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let est = inputs.get::<Pose>("pose")?;
        let gt = inputs.get::<Pose>("pose_gt")?;
        let usable = est.state != TrackingState::Lost
            && est
                .world_from_camera
                .translation
                .vector
                .iter()
                .all(|v| v.is_finite())
            && est
                .world_from_camera
                .rotation
                .coords
                .iter()
                .all(|v| v.is_finite());
        self.est.push(usable.then_some(est.world_from_camera));
        self.gt.push(gt.world_from_camera);
        let mut m = Metrics::default();
        let raw = if usable {
            (est.world_from_camera.translation.vector - gt.world_from_camera.translation.vector)
                .norm()
        } else {
            f64::NAN
        };
        m.values
            .insert(format!("{}.position_err_mm", self.params.prefix), raw);
        match (
            inputs.opt::<Matches>("matches")?,
            inputs.opt::<DepthMap>("depth_gt")?,
        ) {
            (Some(mt), Some(d)) if mt.query_points.len() == mt.query_xy.len() => {
                if let Some(e) = point_error(&mt.query_xy, &mt.query_points, d) {
                    self.point_errors.push(e);
                    m.values
                        .insert(format!("{}.point_err_mm", self.params.prefix), e);
                }
            }
            (Some(_), Some(_)) => {
                return Err(NodeError::msg(
                    "`matches` carry no 3D query points (connect a tracker's matches)",
                ))
            }
            (Some(_), None) | (None, Some(_)) => {
                return Err(NodeError::msg(
                    "connect both `matches` and `depth_gt` for tracking.point_err_mm, or neither",
                ))
            }
            (None, None) => {}
        }
        outputs.put("metrics", m)?;
        Ok(Flow::Continue)
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        if self.gt.is_empty() {
            return Ok(());
        }
        let s = score(&self.est, &self.gt, self.params.align);
        let p = &self.params.prefix;
        for (k, v) in [
            ("ate_mm", s.ate_mm),
            ("rpe_mm", s.rpe_mm),
            ("rpe_deg", s.rpe_deg),
            ("lost_pct", s.lost_pct),
        ] {
            if v.is_finite() {
                ctx.report_eval(&format!("{p}.{k}"), v);
            }
        }
        if !self.point_errors.is_empty() {
            let mean = self.point_errors.iter().sum::<f64>() / self.point_errors.len() as f64;
            ctx.report_eval(&format!("{p}.point_err_mm"), mean);
        }
        Ok(())
    }
}

/// Registers `eval.tracking`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "eval.tracking",
        "absolute and relative trajectory error of the scope pose (ATE, RPE) and lost frames",
        vec![
            PortSpec::new(
                "pose",
                PortType::Pose,
                "estimated world_from_camera with tracker state",
            ),
            PortSpec::new("pose_gt", PortType::Pose, "ground-truth world_from_camera"),
            PortSpec::optional(
                "matches",
                PortType::Matches,
                "the tracker's correspondences (query: current keypoint and camera-frame point)",
            ),
            PortSpec::optional(
                "depth_gt",
                PortType::Depth,
                "GT depth, for tracking.point_err_mm",
            ),
        ],
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "`position_err_mm` of the frame (before alignment)",
        )],
        |p: Params, _: &BuildContext| {
            Ok(EvalTracking {
                params: p,
                est: Vec::new(),
                gt: Vec::new(),
                point_errors: Vec::new(),
            })
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use misslam_framework::nalgebra::{Translation3, UnitQuaternion};
    use misslam_framework::{FloatMap, StereoCalib};

    #[test]
    fn point_error_is_exact_on_a_constructed_plane() {
        // GT: a fronto-parallel plane at 80 mm. Tracked points on it give 0; the same points
        // pushed 0.5 mm along z give exactly 0.5; points off the map or without 3D are skipped.
        let calib = StereoCalib {
            width: 64,
            height: 48,
            fx: 100.0,
            fy: 100.0,
            cx: 32.0,
            cy: 24.0,
            cx_right: 32.0,
            baseline_mm: 5.0,
        };
        let d = DepthMap {
            map: FloatMap {
                width: 64,
                height: 48,
                data: vec![80.0; 64 * 48],
            },
            calib,
        };
        let xy = [[10.25f32, 5.5], [40.0, 30.75], [100.0, 5.0], [3.0, 3.0]];
        let lift = |q: [f32; 2], z: f32| [(q[0] - 32.0) * z / 100.0, (q[1] - 24.0) * z / 100.0, z];
        let on = [
            lift(xy[0], 80.0),
            lift(xy[1], 80.0),
            [0.0, 0.0, 80.0],
            [f32::NAN; 3],
        ];
        assert!(point_error(&xy, &on, &d).unwrap() < 1e-4);
        let mut off = on;
        off[0][2] += 0.5;
        off[1][2] += 0.5;
        assert!((point_error(&xy, &off, &d).unwrap() - 0.5).abs() < 1e-4);
        assert!(point_error(&xy[2..], &on[2..], &d).is_none());
    }

    fn gt_trajectory(n: usize) -> Vec<Isometry3<f64>> {
        (0..n)
            .map(|i| {
                let t = i as f64 * 0.1;
                Isometry3::from_parts(
                    Translation3::new(10.0 * t.sin(), 4.0 * (0.6 * t).sin(), 2.0 * t),
                    UnitQuaternion::from_euler_angles(0.02 * t, 0.04 * t.sin(), 0.0),
                )
            })
            .collect()
    }

    #[test]
    fn a_rigidly_moved_trajectory_has_zero_ate_after_alignment() {
        let gt = gt_trajectory(50);
        let m = Isometry3::from_parts(
            Translation3::new(5.0, -3.0, 2.0),
            UnitQuaternion::from_euler_angles(0.3, -0.2, 0.5),
        );
        let est: Vec<Option<Isometry3<f64>>> = gt.iter().map(|g| Some(m * g)).collect();
        let s = score(&est, &gt, Align::Rigid);
        assert!(s.ate_mm < 1e-9, "{}", s.ate_mm);
        assert!(
            s.rpe_mm < 1e-9 && s.rpe_deg < 1e-6,
            "frame-to-frame motion is unchanged"
        );
        let raw = score(&est, &gt, Align::None);
        assert!(raw.ate_mm > 1.0, "without alignment the offset counts");
    }

    #[test]
    fn known_offsets_give_known_errors() {
        let gt = gt_trajectory(20);
        // Every estimate 3 mm off along x: unaligned ATE 3, RPE 0; lost frames excluded.
        let mut est: Vec<Option<Isometry3<f64>>> = gt
            .iter()
            .map(|g| Some(Translation3::new(3.0, 0.0, 0.0) * g))
            .collect();
        est[5] = None;
        est[6] = None;
        let s = score(&est, &gt, Align::None);
        assert!((s.ate_mm - 3.0).abs() < 1e-9);
        assert!(s.rpe_mm < 1e-9);
        assert_eq!(s.frames, 18);
        assert_eq!(s.lost_pct, 10.0);
        // One frame 4 mm off along z, others exact: ATE = sqrt(16 / 20) unaligned.
        let mut est: Vec<Option<Isometry3<f64>>> = gt.iter().map(|g| Some(*g)).collect();
        est[10] = Some(Translation3::new(0.0, 0.0, 4.0) * gt[10]);
        let s = score(&est, &gt, Align::None);
        assert!((s.ate_mm - (16.0f64 / 20.0).sqrt()).abs() < 1e-9);
        // RPE sees the jump in and out: two steps of 4 mm -> sqrt(2 * 16 / 19).
        assert!(
            (s.rpe_mm - (32.0f64 / 19.0).sqrt()).abs() < 1e-9,
            "{}",
            s.rpe_mm
        );
    }
}
