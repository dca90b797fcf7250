//! `tracking.stereo`: the scope's rigid pose per frame from stereo 3D keypoints (the role
//! ORB-SLAM plays in MIS-SLAM; method.md 2.3). Works with any feature node that outputs 3D
//! points (`features.orb`, `features.surf`).
//!
//! The library: [`pose`] (RANSAC over minimal 3-point absolute orientation, SE(3) refinement of
//! the stereo reprojection error) and [`tracker`] (guided and brute-force matching against the
//! reference keyframe, keyframe insertion, relocalisation).
#![deny(missing_docs)]

pub mod pose;
pub mod tracker;

use misslam_framework::{
    BuildContext, BuildError, Features, Flow, FrameInfo, Inputs, Match, Matches, Metrics, Node,
    NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Pose, Registry, StereoFrame,
    TrackingState, TypedPlugin,
};

pub use tracker::{Tracker, TrackerParams};

/// The node.
pub struct TrackingNode {
    tracker: Tracker,
}

/// `tracking.state` as a number for plots: 0 tracking, 1 lost, 2 relocalised.
pub fn state_code(s: TrackingState) -> f64 {
    match s {
        TrackingState::Tracking => 0.0,
        TrackingState::Lost => 1.0,
        TrackingState::Relocalised => 2.0,
    }
}

impl Node for TrackingNode {
    fn process(
        &mut self,
        _: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let features = inputs.get::<Features>("features")?;
        let pair = inputs.get::<StereoFrame>("stereo")?;
        let initial = inputs
            .opt::<Pose>("initial_pose")?
            .map(|p| p.world_from_camera);
        let c = &pair.calib;
        let cam = pose::StereoCamera {
            fx: c.fx,
            fy: c.fy,
            cx: c.cx,
            cy: c.cy,
            baseline: c.baseline_mm,
            doffs: c.doffs(),
        };
        let r = self
            .tracker
            .track(frame.index, features, &cam, (c.width, c.height), initial)
            .map_err(NodeError::msg)?;
        if let Some(reason) = &r.reason {
            tracing::warn!("frame {}: tracking lost: {reason}", frame.index);
        } else if r.state == TrackingState::Relocalised {
            tracing::info!(
                "frame {}: relocalised against the keyframe of frame {} ({} inliers)",
                frame.index,
                r.keyframe.unwrap_or(0),
                r.inliers
            );
        }
        let mut m = Matches::default();
        for c in &r.correspondences {
            m.pairs.push(Match {
                query: c.current,
                train: c.keyframe,
                distance: 0.0,
            });
            m.query_xy.push(c.current_xy);
            m.train_xy.push(c.keyframe_xy);
            m.query_points.push(c.camera);
            m.train_points.push(c.world);
        }
        let mut metrics = Metrics::default();
        for (k, v) in [
            ("state", state_code(r.state)),
            ("inliers", r.inliers as f64),
            ("matches", r.matches as f64),
            ("keyframes", self.tracker.keyframes().len() as f64),
            ("new_keyframe", r.new_keyframe as u8 as f64),
        ] {
            metrics.values.insert(format!("tracking.{k}"), v);
        }
        outputs.put(
            "pose",
            Pose {
                world_from_camera: r.pose,
                state: r.state,
            },
        )?;
        outputs.put("matches", m)?;
        outputs.put("metrics", metrics)?;
        Ok(Flow::Continue)
    }
}

/// Builds the node.
pub fn build(params: TrackerParams, _: &BuildContext) -> Result<TrackingNode, BuildError> {
    params.validate().map_err(|m| BuildError::Param {
        key: None,
        path: String::new(),
        message: m,
    })?;
    Ok(TrackingNode {
        tracker: Tracker::new(params),
    })
}

/// Registers `tracking.stereo`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "tracking.stereo",
        "rigid scope pose from stereo 3D keypoints: RANSAC 3-point, SE(3) refinement, keyframes, relocalisation",
        vec![
            PortSpec::new(
                "features",
                PortType::Features,
                "keypoints with descriptors and camera-frame 3D points (features.orb / features.surf on a stereo pair)",
            ),
            PortSpec::new("stereo", PortType::Stereo, "the pair (its calibration)"),
            PortSpec::optional(
                "initial_pose",
                PortType::Pose,
                "world_from_camera of the first frame (sets the world frame; identity if absent)",
            ),
        ],
        vec![
            PortSpec::new(
                "pose",
                PortType::Pose,
                "world_from_camera and the state (tracking, lost: last good pose, relocalised)",
            ),
            PortSpec::new(
                "matches",
                PortType::Matches,
                "inlier 3D correspondences: query = current keypoint (camera-frame point), train = keyframe keypoint (world point)",
            ),
            PortSpec::new(
                "metrics",
                PortType::Metrics,
                "tracking.state (0 tracking, 1 lost, 2 relocalised), inliers, matches, keyframes, new_keyframe",
            ),
        ],
        build,
    ))
}
