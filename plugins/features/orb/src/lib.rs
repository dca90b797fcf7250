//! `features.orb`: ORB keypoints and descriptors (Rublee et al., ICCV 2011; method.md 2.1) on the
//! left image, matched along the rows of the right image to give each keypoint a 3D position.
//!
//! The algorithm is the plain library [`extract`] (with [`fast`] and [`pyramid`]); stereo
//! matching and triangulation come from `misslam-features-matching`.
#![deny(missing_docs)]

pub mod extract;
pub mod fast;
pub mod pyramid;

use misslam_features_matching::stereo::{stereo_points, GrayView, StereoParams, StereoScratch};
use misslam_framework::{
    BuildContext, BuildError, Descriptors, Features, Flow, FrameInfo, Image, Inputs, Keypoint,
    Mask, Matches, Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Registry,
    StereoFrame, TypedPlugin,
};

pub use extract::{Distribution, OrbParams};

/// Parameters of `features.orb`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// The detector and descriptor.
    pub detector: OrbParams,
    /// Stereo matching of left keypoints against right keypoints (with a `stereo` input).
    pub stereo: StereoParams,
    /// Extract the left and right images on two threads.
    pub parallel: bool,
}

impl Default for Params {
    fn default() -> Self {
        Params {
            detector: OrbParams::default(),
            stereo: StereoParams::default(),
            parallel: true,
        }
    }
}

/// One image's keypoints and descriptors, with the buffers reused across frames.
#[derive(Default)]
pub struct Extractor {
    scratch: extract::OrbScratch,
    gray: Vec<u8>,
    /// Keypoints of the last image.
    pub keypoints: Vec<Keypoint>,
    /// Their descriptors.
    pub descriptors: Vec<[u64; 4]>,
}

impl Extractor {
    /// Extracts from an image, dropping keypoints on invalid pixels of `mask`.
    pub fn run(&mut self, img: &Image, mask: Option<&Mask>, p: &OrbParams) -> Result<(), String> {
        img.gray_into(&mut self.gray);
        let (w, h) = (img.width as usize, img.height as usize);
        extract::extract(
            &self.gray,
            w,
            h,
            p,
            &mut self.scratch,
            &mut self.keypoints,
            &mut self.descriptors,
        )?;
        let mask = mask.filter(|m| m.width == img.width && m.height == img.height);
        misslam_features_matching::retain_in_mask(&mut self.keypoints, &mut self.descriptors, mask);
        Ok(())
    }

    /// The gray image of the last run.
    pub fn gray(&self) -> &[u8] {
        &self.gray
    }
}

/// The node.
pub struct OrbNode {
    params: Params,
    left: Extractor,
    right: Extractor,
    stereo: StereoScratch,
}

impl OrbNode {
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
        let (rl, rr) = if p.parallel {
            rayon::join(
                || left.run(&pair.left, pair.left_mask.as_ref(), &p.detector),
                || right.run(&pair.right, pair.right_mask.as_ref(), &p.detector),
            )
        } else {
            (
                left.run(&pair.left, pair.left_mask.as_ref(), &p.detector),
                right.run(&pair.right, pair.right_mask.as_ref(), &p.detector),
            )
        };
        rl.map_err(|e| format!("left image: {e}"))?;
        rr.map_err(|e| format!("right image: {e}"))?;
        let (w, h) = (pair.left.width as usize, pair.left.height as usize);
        let ld = Descriptors::Binary256(std::mem::take(&mut self.left.descriptors));
        let rd = Descriptors::Binary256(std::mem::take(&mut self.right.descriptors));
        let (points, matches) = stereo_points(
            &self.left.keypoints,
            &ld,
            &self.right.keypoints,
            &rd,
            GrayView {
                width: w,
                height: h,
                data: self.left.gray(),
            },
            GrayView {
                width: w,
                height: h,
                data: self.right.gray(),
            },
            &pair.calib,
            &p.stereo,
            &mut self.stereo,
        );
        if let Descriptors::Binary256(d) = rd {
            self.right.descriptors = d;
        }
        let features = Features {
            keypoints: self.left.keypoints.clone(),
            descriptors: ld,
            points: Some(points),
        };
        Ok((features, matches))
    }
}

impl Node for OrbNode {
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
                    descriptors: Descriptors::Binary256(self.left.descriptors.clone()),
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
pub fn build(params: Params, _: &BuildContext) -> Result<OrbNode, BuildError> {
    params
        .detector
        .validate()
        .map_err(|m| param_err("detector", m))?;
    params
        .stereo
        .validate()
        .map_err(|m| param_err("stereo", m))?;
    Ok(OrbNode {
        params,
        left: Extractor::default(),
        right: Extractor::default(),
        stereo: StereoScratch::default(),
    })
}

/// Registers `features.orb`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "features.orb",
        "ORB keypoints (FAST-9 pyramid, Harris, quadtree, steered BRIEF); with a stereo pair, 3D keypoints by row matching",
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
                "left keypoints, 256-bit descriptors, camera-frame 3D points (mm, NaN unmatched)",
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
