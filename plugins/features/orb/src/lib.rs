//! `features.orb`: ORB keypoints and descriptors (Rublee et al., ICCV 2011; method.md 2.1) on the
//! left image, matched along the rows of the right image to give each keypoint a 3D position.
//!
//! The algorithm is the plain library [`extract`] (with [`fast`] and [`pyramid`]); stereo
//! matching and triangulation come from `misslam-features-matching`.
#![deny(missing_docs)]

pub mod extract;
pub mod fast;
pub mod pyramid;

use misslam_features_matching::extractor::{self, Detector, StereoExtractor};
use misslam_features_matching::stereo::StereoParams;
use misslam_framework::{
    BuildContext, BuildError, Descriptors, Features, Flow, FrameInfo, Inputs, Keypoint, Matches,
    Node, NodeContext, NodeResult, Outputs, Registry, StereoFrame, TypedPlugin,
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

/// ORB as a [`Detector`] for the shared feature-node machinery.
#[derive(Default)]
pub struct Detect {
    scratch: extract::OrbScratch,
}

impl Detector for Detect {
    type Params = OrbParams;
    type Descriptor = [u64; 4];

    fn detect(
        &mut self,
        gray: &[u8],
        width: usize,
        height: usize,
        params: &OrbParams,
        keypoints: &mut Vec<Keypoint>,
        descriptors: &mut Vec<[u64; 4]>,
    ) -> Result<(), String> {
        extract::extract(
            gray,
            width,
            height,
            params,
            &mut self.scratch,
            keypoints,
            descriptors,
        )
    }

    fn wrap(d: Vec<[u64; 4]>) -> Descriptors {
        Descriptors::Binary256(d)
    }

    fn unwrap(d: Descriptors) -> Vec<[u64; 4]> {
        match d {
            Descriptors::Binary256(d) => d,
            Descriptors::Float64(_) => Vec::new(),
        }
    }
}

/// The node.
pub struct OrbNode {
    params: Params,
    views: StereoExtractor<Detect>,
}

impl OrbNode {
    /// Features of a stereo pair: left keypoints with 3D points (NaN without a stereo match),
    /// and the stereo matches (query = left, train = right).
    pub fn stereo_features(&mut self, pair: &StereoFrame) -> Result<(Features, Matches), String> {
        let p = &self.params;
        self.views
            .stereo_features(pair, &p.detector, &p.stereo, p.parallel)
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
        let p = &self.params;
        self.views
            .process(inputs, outputs, &p.detector, &p.stereo, p.parallel)
    }
}

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<OrbNode, BuildError> {
    params
        .detector
        .validate()
        .map_err(|m| BuildError::param("detector", m))?;
    params
        .stereo
        .validate()
        .map_err(|m| BuildError::param("stereo", m))?;
    Ok(OrbNode {
        params,
        views: StereoExtractor::default(),
    })
}

/// Registers `features.orb`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    let (inputs, outputs) = extractor::ports("256-bit descriptors");
    registry.register(TypedPlugin::new(
        "features.orb",
        "ORB keypoints (FAST-9 pyramid, Harris, quadtree, steered BRIEF); with a stereo pair, 3D keypoints by row matching",
        inputs,
        outputs,
        build,
    ))
}
