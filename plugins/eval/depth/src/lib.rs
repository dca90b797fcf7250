//! `eval.depth`: how good an estimated depth map is against ground truth, per frame and over
//! the run. Keys (in `metrics.json` under `eval`, and per frame on the `metrics` port):
//!
//! | key | meaning |
//! |---|---|
//! | `depth.bad1_pct`, `depth.bad2_pct` | % of evaluated GT pixels whose disparity error exceeds 1 / 2 px; a pixel without an estimate counts as bad |
//! | `depth.bad2_valid_pct` | the same over pixels that have an estimate only |
//! | `depth.mae_mm` | mean absolute depth error over pixels with an estimate, mm |
//! | `depth.bias_mm` | mean signed depth error (estimate minus GT) over the same pixels, mm: positive when the estimate lies behind the true surface |
//! | `depth.density_pct` | % of evaluated GT pixels that have an estimate |
//!
//! Evaluated pixels: GT depth finite and within `[min_depth_mm, max_depth_mm]`. Disparities of
//! both maps are computed with the GT calibration (`d = fx b / Z - doffs`), so depth from any
//! stereo method is scored on the same scale. Run summaries are means of the per-frame figures.
#![deny(missing_docs)]

use misslam_framework::metrics::FrameMeans;
use misslam_framework::{
    BuildContext, BuildError, DepthMap, Flow, FrameInfo, Inputs, Node, NodeContext, NodeError,
    NodeResult, Outputs, PortSpec, PortType, Registry, TypedPlugin,
};

/// Parameters of `eval.depth`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Nearest GT depth evaluated, mm.
    pub min_depth_mm: f32,
    /// Farthest GT depth evaluated, mm.
    pub max_depth_mm: f32,
    /// Prefix of the keys (`depth` gives `depth.mae_mm`); change it to score two estimates in one graph.
    pub prefix: String,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            min_depth_mm: 0.0,
            max_depth_mm: f32::MAX,
            prefix: "depth".into(),
        }
    }
}

/// Figures of one frame.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct DepthScores {
    /// Evaluated GT pixels.
    pub evaluated: usize,
    /// Of those, with an estimate.
    pub estimated: usize,
    /// % bad at 1 px, invalid counted as bad.
    pub bad1_pct: f64,
    /// % bad at 2 px, invalid counted as bad.
    pub bad2_pct: f64,
    /// % bad at 2 px over estimated pixels.
    pub bad2_valid_pct: f64,
    /// Mean absolute depth error over estimated pixels, mm.
    pub mae_mm: f64,
    /// Mean signed depth error (estimate minus GT) over estimated pixels, mm: a systematic
    /// offset of the method (a calibration's baseline or principal point off, a matcher's
    /// sub-pixel bias) shows here while `mae_mm` mixes it with the noise.
    pub bias_mm: f64,
    /// % of evaluated pixels with an estimate.
    pub density_pct: f64,
}

/// Scores `est` against `gt` (same size). Errors name what does not fit.
pub fn score(est: &DepthMap, gt: &DepthMap, p: &Params) -> Result<DepthScores, String> {
    if (est.map.width, est.map.height) != (gt.map.width, gt.map.height) {
        return Err(format!(
            "estimate is {}x{}, ground truth {}x{}",
            est.map.width, est.map.height, gt.map.width, gt.map.height
        ));
    }
    let c = &gt.calib;
    let (mut evaluated, mut estimated, mut bad1, mut bad2, mut bad2_valid) =
        (0usize, 0usize, 0usize, 0usize, 0usize);
    let (mut abs_sum, mut signed_sum) = (0.0f64, 0.0f64);
    for (&z, &g) in est.map.data.iter().zip(&gt.map.data) {
        if !(g.is_finite() && g >= p.min_depth_mm && g <= p.max_depth_mm) {
            continue;
        }
        evaluated += 1;
        if !(z.is_finite() && z > 0.0) {
            bad1 += 1;
            bad2 += 1;
            continue;
        }
        estimated += 1;
        abs_sum += (z as f64 - g as f64).abs();
        signed_sum += z as f64 - g as f64;
        let err = (c.disparity_from_depth(z) - c.disparity_from_depth(g)).abs();
        if err > 1.0 {
            bad1 += 1;
        }
        if err > 2.0 {
            bad2 += 1;
            bad2_valid += 1;
        }
    }
    // A mean over the pixels with an estimate (NaN without any).
    let per_estimated = |sum: f64| {
        if estimated == 0 {
            f64::NAN
        } else {
            sum / estimated as f64
        }
    };
    let pct = |n: usize, d: usize| {
        if d == 0 {
            f64::NAN
        } else {
            100.0 * n as f64 / d as f64
        }
    };
    Ok(DepthScores {
        evaluated,
        estimated,
        bad1_pct: pct(bad1, evaluated),
        bad2_pct: pct(bad2, evaluated),
        bad2_valid_pct: pct(bad2_valid, estimated),
        mae_mm: per_estimated(abs_sum),
        bias_mm: per_estimated(signed_sum),
        density_pct: pct(estimated, evaluated),
    })
}

/// The node: scores every frame, reports the means at the end.
pub struct EvalDepth {
    params: Params,
    means: FrameMeans,
}

impl EvalDepth {
    fn keys(&self, s: &DepthScores) -> [(String, f64); 6] {
        let k = |name: &str| format!("{}.{name}", self.params.prefix);
        [
            (k("bad1_pct"), s.bad1_pct),
            (k("bad2_pct"), s.bad2_pct),
            (k("bad2_valid_pct"), s.bad2_valid_pct),
            (k("mae_mm"), s.mae_mm),
            (k("bias_mm"), s.bias_mm),
            (k("density_pct"), s.density_pct),
        ]
    }
}

impl Node for EvalDepth {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let est = inputs.get::<DepthMap>("depth")?;
        let gt = inputs.get::<DepthMap>("depth_gt")?;
        let s = score(est, gt, &self.params).map_err(NodeError::msg)?;
        let m = self.means.add(self.keys(&s));
        outputs.put("metrics", m)?;
        Ok(Flow::Continue)
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        self.means.report(ctx);
        Ok(())
    }
}

/// Registers `eval.depth`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "eval.depth",
        "bad-1/bad-2 disparity rates, depth MAE and density against GT depth",
        vec![
            PortSpec::new("depth", PortType::Depth, "estimated depth, mm"),
            PortSpec::new(
                "depth_gt",
                PortType::Depth,
                "ground-truth depth, mm (its calibration is used)",
            ),
        ],
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "the frame's figures",
        )],
        |p: Params, _: &BuildContext| {
            if !(p.min_depth_mm >= 0.0 && p.max_depth_mm > p.min_depth_mm) {
                return Err(BuildError::Param {
                    key: Some("max_depth_mm".into()),
                    path: "max_depth_mm".into(),
                    message: format!("must exceed min_depth_mm ({})", p.min_depth_mm),
                });
            }
            if p.prefix.is_empty() {
                return Err(BuildError::Param {
                    key: Some("prefix".into()),
                    path: "prefix".into(),
                    message: "must not be empty".into(),
                });
            }
            Ok(EvalDepth {
                params: p,
                means: FrameMeans::default(),
            })
        },
    ))
}

#[cfg(test)]
mod tests {
    use super::*;
    use misslam_framework::{FloatMap, StereoCalib};

    fn calib() -> StereoCalib {
        // fx b = 700 * 5 = 3500: at 100 mm the disparity is 35 px; 1 px is about 2.9 mm there.
        StereoCalib {
            width: 4,
            height: 4,
            fx: 700.0,
            fy: 700.0,
            cx: 2.0,
            cy: 2.0,
            cx_right: 2.0,
            baseline_mm: 5.0,
        }
    }

    fn map(data: Vec<f32>) -> DepthMap {
        DepthMap {
            map: FloatMap {
                width: 4,
                height: 4,
                data,
            },
            calib: calib(),
        }
    }

    #[test]
    fn a_known_perturbation_gives_known_figures() {
        let gt = map(vec![100.0; 16]);
        // 4 exact, 4 off by +1 mm (0.34 px), 4 at 35/33.5 (1.5 px off), 2 at 3500/38 (3 px off), 2 missing.
        let mut est = vec![100.0f32; 4];
        est.extend([101.0; 4]);
        est.extend([3500.0 / 33.5; 4]);
        est.extend([3500.0 / 38.0; 2]);
        est.extend([f32::NAN; 2]);
        let s = score(&map(est.clone()), &gt, &Params::default()).unwrap();
        assert_eq!((s.evaluated, s.estimated), (16, 14));
        assert_eq!(
            s.bad1_pct,
            100.0 * 8.0 / 16.0,
            "4 at 1.5 px + 2 at 3 px + 2 missing"
        );
        assert_eq!(s.bad2_pct, 100.0 * 4.0 / 16.0, "2 at 3 px + 2 missing");
        assert_eq!(s.bad2_valid_pct, 100.0 * 2.0 / 14.0);
        assert_eq!(s.density_pct, 100.0 * 14.0 / 16.0);
        let want_mae =
            (4.0 * 1.0 + 4.0 * (3500.0f64 / 33.5 - 100.0) + 2.0 * (100.0 - 3500.0f64 / 38.0))
                / 14.0;
        assert!(
            (s.mae_mm - want_mae).abs() < 1e-4,
            "{} vs {want_mae}",
            s.mae_mm
        );
        // The signed mean: the far estimates (+1 mm, 1.5 px short) against the near ones.
        let want_bias = (4.0 * 1.0 + 4.0 * (3500.0f64 / 33.5 - 100.0)
            - 2.0 * (100.0 - 3500.0f64 / 38.0))
            / 14.0;
        assert!(
            (s.bias_mm - want_bias).abs() < 1e-4,
            "{} vs {want_bias}",
            s.bias_mm
        );
    }

    #[test]
    fn range_limits_and_gt_holes_exclude_pixels() {
        let mut g = vec![100.0f32; 16];
        g[0] = f32::NAN;
        g[1] = 200.0;
        let s = score(
            &map(vec![90.0; 16]),
            &map(g),
            &Params {
                max_depth_mm: 150.0,
                ..Params::default()
            },
        )
        .unwrap();
        assert_eq!(s.evaluated, 14);
        assert!((s.mae_mm - 10.0).abs() < 1e-6);
        // Every estimate 10 mm nearer than the GT: in front, a negative bias.
        assert!((s.bias_mm + 10.0).abs() < 1e-6);
        let e = score(
            &DepthMap {
                map: FloatMap {
                    width: 2,
                    height: 8,
                    data: vec![1.0; 16],
                },
                calib: calib(),
            },
            &map(vec![1.0; 16]),
            &Params::default(),
        )
        .unwrap_err();
        assert_eq!(e, "estimate is 2x8, ground truth 4x4");
    }

    #[test]
    fn perfect_estimate_scores_zero() {
        let gt = map((0..16).map(|i| 60.0 + i as f32).collect());
        let s = score(&gt, &gt, &Params::default()).unwrap();
        assert_eq!(
            (s.bad1_pct, s.bad2_pct, s.mae_mm, s.bias_mm, s.density_pct),
            (0.0, 0.0, 0.0, 0.0, 100.0)
        );
    }
}
