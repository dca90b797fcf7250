//! What every feature node does around its detector: gray conversion with reused buffers, the
//! border mask, both views of a stereo pair (on two threads), stereo matching to 3D keypoints,
//! and the whole node ([`FeatureNode`], its [`FeatureParams`] and [`ports`]). A detector (ORB,
//! SURF) implements [`Detector`]; its crate only names the node and registers it.

use misslam_framework::{
    BuildError, Descriptors, Features, Flow, FrameInfo, Image, Inputs, Keypoint, Mask, Matches,
    Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Sampler, StereoFrame,
};

use crate::retain_in_mask;
use crate::stereo::{stereo_points, GrayView, StereoParams, StereoScratch};

/// A keypoint detector and descriptor on 8-bit gray images.
pub trait Detector: Default + Send {
    /// Its parameters.
    type Params: Default + Send + Sync;
    /// One descriptor.
    type Descriptor: Copy + Send;
    /// Detects on a `width` x `height` gray image into `keypoints` and `descriptors` (cleared
    /// first).
    fn detect(
        &mut self,
        gray: &[u8],
        width: usize,
        height: usize,
        params: &Self::Params,
        keypoints: &mut Vec<Keypoint>,
        descriptors: &mut Vec<Self::Descriptor>,
    ) -> Result<(), String>;
    /// Checks the parameters; the message names the field.
    fn validate(params: &Self::Params) -> Result<(), String>;
    /// The descriptors as the framework's payload.
    fn wrap(d: Vec<Self::Descriptor>) -> Descriptors;
    /// Back from the payload (empty for the other kind).
    fn unwrap(d: Descriptors) -> Vec<Self::Descriptor>;
    /// Descriptors at any pixel of the last image, where the detector gives them (dense grids).
    fn sampler(&self) -> Option<Sampler> {
        None
    }
}

/// One image's keypoints and descriptors, with the buffers reused across frames.
pub struct Extractor<D: Detector> {
    detector: D,
    gray: Vec<u8>,
    /// Keypoints of the last image.
    pub keypoints: Vec<Keypoint>,
    /// Their descriptors.
    pub descriptors: Vec<D::Descriptor>,
}

impl<D: Detector> Default for Extractor<D> {
    fn default() -> Self {
        Extractor {
            detector: D::default(),
            gray: Vec::new(),
            keypoints: Vec::new(),
            descriptors: Vec::new(),
        }
    }
}

impl<D: Detector> Extractor<D> {
    /// Extracts from an image, dropping keypoints on invalid pixels of `mask`.
    pub fn run(&mut self, img: &Image, mask: Option<&Mask>, p: &D::Params) -> Result<(), String> {
        img.gray_into(&mut self.gray);
        self.detector.detect(
            &self.gray,
            img.width as usize,
            img.height as usize,
            p,
            &mut self.keypoints,
            &mut self.descriptors,
        )?;
        let mask = mask.filter(|m| m.width == img.width && m.height == img.height);
        retain_in_mask(&mut self.keypoints, &mut self.descriptors, mask);
        Ok(())
    }

    /// The gray image of the last run.
    pub fn gray(&self) -> &[u8] {
        &self.gray
    }

    /// The detector's descriptors at any pixel of the last image, where it gives them.
    pub fn sampler(&self) -> Option<Sampler> {
        self.detector.sampler()
    }
}

/// Both views of a pair and the stereo matcher's buffers.
pub struct StereoExtractor<D: Detector> {
    /// The left view.
    pub left: Extractor<D>,
    /// The right view.
    pub right: Extractor<D>,
    stereo: StereoScratch,
}

impl<D: Detector> Default for StereoExtractor<D> {
    fn default() -> Self {
        StereoExtractor {
            left: Extractor::default(),
            right: Extractor::default(),
            stereo: StereoScratch::default(),
        }
    }
}

impl<D: Detector> StereoExtractor<D> {
    /// Features of a stereo pair: left keypoints with 3D points (NaN without a stereo match),
    /// and the stereo matches (query = left, train = right).
    pub fn stereo_features(
        &mut self,
        pair: &StereoFrame,
        detector: &D::Params,
        stereo: &StereoParams,
        parallel: bool,
    ) -> Result<(Features, Matches), String> {
        if (pair.left.width, pair.left.height) != (pair.right.width, pair.right.height) {
            return Err(format!(
                "left image is {}x{} but right is {}x{}",
                pair.left.width, pair.left.height, pair.right.width, pair.right.height
            ));
        }
        let (left, right) = (&mut self.left, &mut self.right);
        let mut run_l = || left.run(&pair.left, pair.left_mask.as_ref(), detector);
        let mut run_r = || right.run(&pair.right, pair.right_mask.as_ref(), detector);
        let (rl, rr) = if parallel {
            rayon::join(run_l, run_r)
        } else {
            (run_l(), run_r())
        };
        rl.map_err(|e| format!("left image: {e}"))?;
        rr.map_err(|e| format!("right image: {e}"))?;
        let (w, h) = (pair.left.width as usize, pair.left.height as usize);
        // The left descriptors go out with the features; the right ones come back for reuse.
        let ld = D::wrap(std::mem::take(&mut self.left.descriptors));
        let rd = D::wrap(std::mem::take(&mut self.right.descriptors));
        let view = |data| GrayView {
            width: w,
            height: h,
            data,
        };
        let (points, matches) = stereo_points(
            &self.left.keypoints,
            &ld,
            &self.right.keypoints,
            &rd,
            view(self.left.gray()),
            view(self.right.gray()),
            &pair.calib,
            stereo,
            &mut self.stereo,
        );
        self.right.descriptors = D::unwrap(rd);
        Ok((
            Features {
                keypoints: self.left.keypoints.clone(),
                descriptors: ld,
                points: Some(points),
                sampler: self.left.sampler(),
            },
            matches,
        ))
    }

    /// The body of a feature node: a stereo pair gives 3D keypoints and stereo matches, a single
    /// image gives keypoints only.
    pub fn process(
        &mut self,
        inputs: &Inputs,
        outputs: &mut Outputs,
        detector: &D::Params,
        stereo: &StereoParams,
        parallel: bool,
    ) -> NodeResult<Flow> {
        if let Some(pair) = inputs.opt::<StereoFrame>("stereo")? {
            let (features, matches) = self
                .stereo_features(pair, detector, stereo, parallel)
                .map_err(NodeError::msg)?;
            outputs.put("features", features)?;
            outputs.put("stereo_matches", matches)?;
        } else if let Some(img) = inputs.opt::<Image>("image")? {
            self.left.run(img, None, detector).map_err(NodeError::msg)?;
            outputs.put(
                "features",
                Features {
                    keypoints: self.left.keypoints.clone(),
                    descriptors: D::wrap(self.left.descriptors.clone()),
                    points: None,
                    sampler: self.left.sampler(),
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

/// The ports of a feature node; `descriptors` says what its descriptors are.
pub fn ports(descriptors: &str) -> (Vec<PortSpec>, Vec<PortSpec>) {
    (
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
                &format!(
                    "left keypoints, {descriptors}, camera-frame 3D points (mm, NaN unmatched)"
                ),
            ),
            PortSpec::optional(
                "stereo_matches",
                PortType::Matches,
                "left-to-right matches (query = left), with the left 3D points",
            ),
        ],
    )
}

/// Parameters of a feature node: its detector's, the stereo matcher's, and threading.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct FeatureParams<P: Default> {
    /// The detector and descriptor.
    pub detector: P,
    /// Stereo matching of left keypoints against right keypoints (with a `stereo` input).
    pub stereo: StereoParams,
    /// Extract the left and right images on two threads.
    pub parallel: bool,
}

impl<P: Default> Default for FeatureParams<P> {
    fn default() -> Self {
        FeatureParams {
            detector: P::default(),
            stereo: StereoParams::default(),
            parallel: true,
        }
    }
}

/// A feature node around a detector: `features.orb` and `features.surf` are this node.
pub struct FeatureNode<D: Detector> {
    params: FeatureParams<D::Params>,
    views: StereoExtractor<D>,
}

impl<D: Detector> FeatureNode<D> {
    /// Builds the node after checking both parameter groups.
    pub fn build(params: FeatureParams<D::Params>) -> Result<Self, BuildError> {
        D::validate(&params.detector).map_err(|m| BuildError::param("detector", m))?;
        params
            .stereo
            .validate()
            .map_err(|m| BuildError::param("stereo", m))?;
        Ok(FeatureNode {
            params,
            views: StereoExtractor::default(),
        })
    }

    /// Features of a stereo pair: left keypoints with 3D points (NaN without a stereo match),
    /// and the stereo matches (query = left, train = right).
    pub fn stereo_features(&mut self, pair: &StereoFrame) -> Result<(Features, Matches), String> {
        let p = &self.params;
        self.views
            .stereo_features(pair, &p.detector, &p.stereo, p.parallel)
    }
}

impl<D: Detector> Node for FeatureNode<D> {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let p = &self.params;
        self.views
            .process(inputs, outputs, &p.detector, &p.stereo, p.parallel)
    }
}
