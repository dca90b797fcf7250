//! `features.surf`: SURF keypoints and 64-D descriptors (Bay et al., CVIU 2008; method.md 2.2),
//! or dense SURF on a grid, on the left image; with a stereo pair, matched along the rows of the
//! right image to give each keypoint a 3D position. The algorithm is the plain library [`surf`].
#![deny(missing_docs)]

pub mod surf;

use misslam_features_matching::extractor::{self, Detector, StereoExtractor};
use misslam_features_matching::stereo::StereoParams;
use misslam_framework::{
    BuildContext, BuildError, Descriptors, Features, Flow, FrameInfo, Inputs, Keypoint, Matches,
    Node, NodeContext, NodeResult, Outputs, Registry, StereoFrame, TypedPlugin,
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

/// SURF as a [`Detector`] for the shared feature-node machinery.
#[derive(Default)]
pub struct Detect {
    scratch: surf::SurfScratch,
}

impl Detector for Detect {
    type Params = SurfParams;
    type Descriptor = [f32; 64];

    fn detect(
        &mut self,
        gray: &[u8],
        width: usize,
        height: usize,
        params: &SurfParams,
        keypoints: &mut Vec<Keypoint>,
        descriptors: &mut Vec<[f32; 64]>,
    ) -> Result<(), String> {
        surf::extract(
            gray,
            width,
            height,
            params,
            &mut self.scratch,
            keypoints,
            descriptors,
        )
    }

    fn wrap(d: Vec<[f32; 64]>) -> Descriptors {
        Descriptors::Float64(d)
    }

    fn unwrap(d: Descriptors) -> Vec<[f32; 64]> {
        match d {
            Descriptors::Float64(d) => d,
            Descriptors::Binary256(_) => Vec::new(),
        }
    }
}

/// The node.
pub struct SurfNode {
    params: Params,
    views: StereoExtractor<Detect>,
}

impl SurfNode {
    /// Features of a stereo pair: left keypoints with 3D points (NaN without a stereo match),
    /// and the stereo matches (query = left, train = right).
    pub fn stereo_features(&mut self, pair: &StereoFrame) -> Result<(Features, Matches), String> {
        let p = &self.params;
        self.views
            .stereo_features(pair, &p.detector, &p.stereo, p.parallel)
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
        let p = &self.params;
        self.views
            .process(inputs, outputs, &p.detector, &p.stereo, p.parallel)
    }
}

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<SurfNode, BuildError> {
    params
        .detector
        .validate()
        .map_err(|m| BuildError::param("detector", m))?;
    params
        .stereo
        .validate()
        .map_err(|m| BuildError::param("stereo", m))?;
    Ok(SurfNode {
        params,
        views: StereoExtractor::default(),
    })
}

/// Registers `features.surf`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    let (inputs, outputs) = extractor::ports("64-float unit descriptors");
    registry.register(TypedPlugin::new(
        "features.surf",
        "SURF keypoints (box-filter Hessian scale space, Haar orientation, 64-D) or dense SURF; with a stereo pair, 3D keypoints by row matching",
        inputs,
        outputs,
        build,
    ))
}
