//! `features.orb`: ORB keypoints and descriptors (Rublee et al., ICCV 2011; method.md 2.1) on the
//! left image, matched along the rows of the right image to give each keypoint a 3D position.
//!
//! The algorithm is the plain library [`extract`] (with [`fast`], [`pyramid`] and `measure`); stereo
//! matching and triangulation come from `misslam-features-matching`.
#![deny(missing_docs)]

pub mod extract;
pub mod fast;
pub mod learn;
mod learned_pattern;
mod measure;
pub mod pyramid;

use misslam_features_matching::extractor::{self, Detector, FeatureNode, FeatureParams};
use misslam_framework::{BuildContext, BuildError, Descriptors, Keypoint, Registry, TypedPlugin};

pub use extract::{Distribution, OrbParams, PatternKind};

/// Parameters of `features.orb`: `detector` ([`OrbParams`]), `stereo`, `parallel`.
pub type Params = FeatureParams<OrbParams>;

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

    fn validate(params: &OrbParams) -> Result<(), String> {
        params.validate()
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
pub type OrbNode = FeatureNode<Detect>;

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<OrbNode, BuildError> {
    FeatureNode::build(params)
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

/// `n` bytes of uniform noise from a linear congruential generator started at `seed` (the
/// images of the unit tests).
#[cfg(test)]
pub(crate) fn noise_image(n: usize, seed: u32) -> Vec<u8> {
    let mut state = seed;
    (0..n)
        .map(|_| {
            state = state.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (state >> 24) as u8
        })
        .collect()
}
