//! `depth.sgm`: semi-global matching (Hirschmueller, PAMI 2008) on rectified pairs, on the CPU.
//! The algorithm is the plain library [`sgm`]; the node converts the pair to gray, masks the
//! black border, and outputs disparity and depth (NaN where invalid).
#![deny(missing_docs)]

pub mod sgm;

use misslam_framework::{
    BuildContext, BuildError, DepthMap, DisparityMap, FloatMap, Flow, FrameInfo, Inputs, Node,
    NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Registry, StereoFrame,
    TypedPlugin,
};

/// Parameters of `depth.sgm`.
#[derive(Clone, Debug, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Number of disparities searched, starting at `min_disparity`.
    pub max_disparity: u32,
    /// Smallest disparity searched, px.
    pub min_disparity: i32,
    /// Census window width (odd).
    pub census_width: u32,
    /// Census window height (odd); width x height - 1 must not exceed 64.
    pub census_height: u32,
    /// Aggregation paths: 4 or 8.
    pub paths: u32,
    /// Penalty for a disparity change of one pixel between neighbours (census cost units, 0..63).
    pub p1: u16,
    /// Penalty for larger changes; must exceed `p1`.
    pub p2: u16,
    /// Divide P2 by the intensity step along each path (Hirschmueller's edge-aware P2), never below P1 + 1.
    pub p2_adaptive: bool,
    /// Uniqueness margin, %: the best aggregated cost must beat the second best (beyond +-1 px) by this much.
    pub uniqueness_pct: u32,
    /// Sub-pixel refinement by a parabola through the costs at d-1, d, d+1.
    pub subpixel: bool,
    /// Left-right consistency check (right disparities from the same aggregated cost).
    pub lr_check: bool,
    /// Largest left-right disagreement kept, px.
    pub lr_max_diff: f32,
    /// 3x3 median filter of the valid disparities.
    pub median: bool,
    /// Remove connected regions smaller than this many pixels (0: off).
    pub speckle_window: u32,
    /// Neighbours within this disparity difference belong to one region, px.
    pub speckle_range: f32,
}

impl Default for Params {
    fn default() -> Self {
        let s = sgm::SgmParams::default();
        Params {
            max_disparity: s.num_disparities,
            min_disparity: s.min_disparity,
            census_width: s.census_width,
            census_height: s.census_height,
            paths: s.paths,
            p1: s.p1,
            p2: s.p2,
            p2_adaptive: s.p2_adaptive,
            uniqueness_pct: s.uniqueness_pct,
            subpixel: s.subpixel,
            lr_check: s.lr_check,
            lr_max_diff: s.lr_max_diff,
            median: s.median,
            speckle_window: s.speckle_window,
            speckle_range: s.speckle_range,
        }
    }
}

impl Params {
    /// The library's parameters.
    pub fn sgm(&self) -> sgm::SgmParams {
        sgm::SgmParams {
            num_disparities: self.max_disparity,
            min_disparity: self.min_disparity,
            census_width: self.census_width,
            census_height: self.census_height,
            paths: self.paths,
            p1: self.p1,
            p2: self.p2,
            p2_adaptive: self.p2_adaptive,
            uniqueness_pct: self.uniqueness_pct,
            subpixel: self.subpixel,
            lr_check: self.lr_check,
            lr_max_diff: self.lr_max_diff,
            median: self.median,
            speckle_window: self.speckle_window,
            speckle_range: self.speckle_range,
        }
    }
}

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
        let calib = pair.calib;
        let depth = FloatMap {
            width: map.width,
            height: map.height,
            data: map
                .data
                .iter()
                .map(|&d| calib.depth_from_disparity(d))
                .collect(),
        };
        outputs.put("disparity", DisparityMap { map, calib })?;
        outputs.put("depth", DepthMap { map: depth, calib })?;
        Ok(Flow::Continue)
    }
}

/// Builds the node.
pub fn build(p: Params, _: &BuildContext) -> Result<SgmNode, BuildError> {
    let params = p.sgm();
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
