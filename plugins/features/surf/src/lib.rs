//! `features.surf`: SURF keypoints and 64-D descriptors (Bay et al., CVIU 2008; method.md 2.2),
//! or dense SURF on a grid, on the left image; with a stereo pair, matched along the rows of the
//! right image to give each keypoint a 3D position. The algorithm is the plain library [`surf`].
#![deny(missing_docs)]

pub mod surf;

use misslam_features_matching::retain_in_mask;
use misslam_features_matching::stereo::{stereo_points, GrayView, StereoParams, StereoScratch};
use misslam_framework::{
    BuildContext, BuildError, Descriptors, Features, Flow, FrameInfo, Image, Inputs, Keypoint,
    Mask, Matches, Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Registry,
    StereoFrame, TypedPlugin,
};

pub use surf::{DenseParams, SurfParams};

/// Parameters of `features.surf`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The detector and descriptor (and dense SURF).
    pub detector: SurfParams,
    /// Stereo matching of left keypoints against right keypoints (with a `stereo` input).
    pub stereo: StereoParams,
    /// Extract the left and right images on two threads.
    pub parallel: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            detector: SurfParams::default(),
            stereo: StereoParams::default(),
            parallel: true,
        }
    }
}

/// One image's keypoints and descriptors, with buffers reused across frames.
#[derive(Default)]
pub struct Extractor {
    scratch: surf::SurfScratch,
    gray: Vec<u8>,
    /// Keypoints of the last image.
    pub keypoints: Vec<Keypoint>,
    /// Their descriptors.
    pub descriptors: Vec<[f32; 64]>,
}

impl Extractor {
    /// Extracts from an image, dropping keypoints on invalid pixels of `mask`.
    pub fn run(&mut self, img: &Image, mask: Option<&Mask>, p: &SurfParams) -> Result<(), String> {
        img.gray_into(&mut self.gray);
        surf::extract(
            &self.gray,
            img.width as usize,
            img.height as usize,
            p,
            &mut self.scratch,
            &mut self.keypoints,
            &mut self.descriptors,
        )?;
        let mask = mask.filter(|m| m.width == img.width && m.height == img.height);
        retain_in_mask(&mut self.keypoints, &mut self.descriptors, mask);
        Ok(())
    }
}

/// The node.
pub struct SurfNode {
    params: Params,
    left: Extractor,
    right: Extractor,
    stereo: StereoScratch,
}

impl SurfNode {
    /// Features of a stereo pair: left keypoints with 3D points (NaN without a stereo match),
    /// and the stereo matches (query = left, train = right).
    pub fn stereo_features(&mut self, pair: &StereoFrame) -> Result<(Features, Matches), String> {
        if (pair.left.width, pair.left.height) != (pair.right.width, pair.right.height) {
            return Err(format!(
                "left image is {}x{} but right is {}x{}",
                pair.left.width, pair.left.height, pair.right.width, pair.right.height
            ));
        }
        let p = &self.params;
        let (left, right) = (&mut self.left, &mut self.right);
        let mut run_l = || left.run(&pair.left, pair.left_mask.as_ref(), &p.detector);
        let mut run_r = || right.run(&pair.right, pair.right_mask.as_ref(), &p.detector);
        let (rl, rr) = if p.parallel {
            rayon::join(run_l, run_r)
        } else {
            (run_l(), run_r())
        };
        rl.map_err(|e| format!("left image: {e}"))?;
        rr.map_err(|e| format!("right image: {e}"))?;
        let (w, h) = (pair.left.width as usize, pair.left.height as usize);
        let ld = Descriptors::Float64(std::mem::take(&mut self.left.descriptors));
        let rd = Descriptors::Float64(std::mem::take(&mut self.right.descriptors));
        let (points, matches) = stereo_points(
            &self.left.keypoints,
            &ld,
            &self.right.keypoints,
            &rd,
            GrayView {
                width: w,
                height: h,
                data: &self.left.gray,
            },
            GrayView {
                width: w,
                height: h,
                data: &self.right.gray,
            },
            &pair.calib,
            &p.stereo,
            &mut self.stereo,
        );
        if let Descriptors::Float64(d) = rd {
            self.right.descriptors = d;
        }
        Ok((
            Features {
                keypoints: self.left.keypoints.clone(),
                descriptors: ld,
                points: Some(points),
            },
            matches,
        ))
    }
}

impl Node for SurfNode {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        if let Some(pair) = inputs.opt::<StereoFrame>("stereo")? {
            let (features, matches) = self.stereo_features(pair).map_err(NodeError::msg)?;
            outputs.put("features", features)?;
            outputs.put("stereo_matches", matches)?;
        } else if let Some(img) = inputs.opt::<Image>("image")? {
            self.left
                .run(img, None, &self.params.detector)
                .map_err(NodeError::msg)?;
            outputs.put(
                "features",
                Features {
                    keypoints: self.left.keypoints.clone(),
                    descriptors: Descriptors::Float64(self.left.descriptors.clone()),
                    points: None,
                },
            )?;
        } else {
            return Err(NodeError::msg(
                "neither `stereo` nor `image` received anything on this frame",
            ));
        }
        Ok(Flow::Continue)
    }
}

fn param_err(path: &str, message: String) -> BuildError {
    BuildError::Param {
        key: Some(path.split('.').next().unwrap_or(path).to_owned()),
        path: path.to_owned(),
        message,
    }
}

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<SurfNode, BuildError> {
    params
        .detector
        .validate()
        .map_err(|m| param_err("detector", m))?;
    params
        .stereo
        .validate()
        .map_err(|m| param_err("stereo", m))?;
    Ok(SurfNode {
        params,
        left: Extractor::default(),
        right: Extractor::default(),
        stereo: StereoScratch::default(),
    })
}

/// Registers `features.surf`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "features.surf",
        "SURF keypoints (box-filter Hessian scale space, Haar orientation, 64-D) or dense SURF; with a stereo pair, 3D keypoints by row matching",
        vec![
            PortSpec::optional(
                "stereo",
                PortType::Stereo,
                "rectified pair: left keypoints get 3D points from the right image",
            ),
            PortSpec::optional("image", PortType::Image, "a single image (no 3D points)"),
        ],
        vec![
            PortSpec::new(
                "features",
                PortType::Features,
                "left keypoints, 64-float unit descriptors, camera-frame 3D points (mm, NaN unmatched)",
            ),
            PortSpec::optional(
                "stereo_matches",
                PortType::Matches,
                "left-to-right matches (query = left), with the left 3D points",
            ),
        ],
        build,
    ))
}
