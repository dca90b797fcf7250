//! `depth.sgm`: semi-global matching (Hirschmueller, PAMI 2008) on rectified pairs, on the CPU.
//! The algorithm is the plain library [`sgm`]; the node converts the pair to gray, masks the
//! black border, and outputs disparity and depth (NaN where invalid).
#![deny(missing_docs)]

pub mod sgm;

use misslam_framework::{
    BuildContext, BuildError, DisparityMap, FloatMap, Flow, FrameInfo, Inputs, Node, NodeContext,
    NodeError, NodeResult, Outputs, PortSpec, PortType, Registry, StereoFrame, TypedPlugin,
};

/// Parameters of `depth.sgm`: those of the library.
pub use sgm::SgmParams as Params;

/// The node.
pub struct SgmNode {
    params: sgm::SgmParams,
    scratch: sgm::Scratch,
    gray_l: Vec<u8>,
    gray_r: Vec<u8>,
}

impl SgmNode {
    /// Disparity of a pair (px, NaN invalid).
    pub fn disparity(&mut self, pair: &StereoFrame) -> Result<FloatMap, String> {
        let (w, h) = (pair.left.width as usize, pair.left.height as usize);
        if (pair.right.width, pair.right.height) != (pair.left.width, pair.left.height) {
            return Err("left and right images differ in size".into());
        }
        pair.left.gray_into(&mut self.gray_l);
        pair.right.gray_into(&mut self.gray_r);
        let mask = pair.left_mask.as_ref().map(|m| m.data.as_slice());
        let data = sgm::sgm(
            &self.gray_l,
            &self.gray_r,
            w,
            h,
            mask,
            &self.params,
            &mut self.scratch,
        )?;
        Ok(FloatMap {
            width: w as u32,
            height: h as u32,
            data,
        })
    }
}

impl Node for SgmNode {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let pair = inputs.get::<StereoFrame>("stereo")?;
        let map = self.disparity(pair).map_err(NodeError::msg)?;
        let disparity = DisparityMap {
            map,
            calib: pair.calib,
        };
        outputs.put("depth", disparity.to_depth())?;
        outputs.put("disparity", disparity)?;
        Ok(Flow::Continue)
    }
}

/// Builds the node.
pub fn build(params: Params, _: &BuildContext) -> Result<SgmNode, BuildError> {
    params.validate().map_err(|m| BuildError::Param {
        key: None,
        path: String::new(),
        message: m,
    })?;
    Ok(SgmNode {
        params,
        scratch: sgm::Scratch::default(),
        gray_l: Vec::new(),
        gray_r: Vec::new(),
    })
}

/// Registers `depth.sgm`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "depth.sgm",
        "semi-global matching (census, 4/8 paths, sub-pixel, LR check, median, speckles) on the CPU",
        vec![PortSpec::new("stereo", PortType::Stereo, "rectified pair; its left mask is honoured")],
        vec![
            PortSpec::new("disparity", PortType::Disparity, "left disparity, px, NaN invalid"),
            PortSpec::new("depth", PortType::Depth, "left depth, mm, NaN invalid"),
        ],
        build,
    ))
}
