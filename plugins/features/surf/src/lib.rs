//! `features.surf`: SURF keypoints and 64-D descriptors (Bay et al., CVIU 2008; method.md 2.2),
//! or dense SURF on a grid, on the left image; with a stereo pair, matched along the rows of the
//! right image to give each keypoint a 3D position. The algorithm is the plain library [`surf`].
#![deny(missing_docs)]

pub mod sampler;
pub mod surf;

use misslam_features_matching::extractor::{self, Detector, FeatureNode, FeatureParams};
use misslam_framework::{
    BuildContext, BuildError, Descriptors, Keypoint, Registry, Sampler, TypedPlugin,
};

pub use surf::{DenseParams, SurfParams};

/// Parameters of `features.surf`: `detector` ([`SurfParams`]), `stereo`, `parallel`.
pub type Params = FeatureParams<SurfParams>;

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

    fn validate(params: &SurfParams) -> Result<(), String> {
        params.validate()
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

    fn sampler(&self) -> Option<Sampler> {
        let maps = self.scratch.sampler.clone()?;
        Some(Sampler(maps))
    }
}

/// The node.
pub type SurfNode = FeatureNode<Detect>;

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<SurfNode, BuildError> {
    FeatureNode::build(params)
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
