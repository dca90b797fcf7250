//! `depth.sgm`: semi-global matching (Hirschmueller, PAMI 2008) on rectified pairs, on the CPU
//! ([`sgm::sgm`], SIMD) or the GPU ([`gpu::SgmGpu`], WGSL). The node converts the pair to gray,
//! honours the left mask, and outputs disparity and depth (NaN where invalid).
#![deny(missing_docs)]

mod aggregate;
#[cfg(target_arch = "x86_64")]
mod aggregate_avx2;
#[cfg(target_arch = "x86_64")]
mod avx512;
mod census;
mod filters;
pub mod gpu;
mod gpu_layout;
pub mod reference;
mod select;
pub mod sgm;
pub mod simd;
pub mod synthetic;

use misslam_framework::gpu::GpuContext;
use misslam_framework::{
    BuildContext, BuildError, DisparityMap, DisparityRangeWatch, FloatMap, Flow, FrameInfo, Inputs,
    Node, NodeContext, NodeError, NodeResult, Outputs, PortSpec, PortType, Registry, StereoFrame,
    TypedPlugin,
};
use std::sync::Arc;

/// Parameters of `depth.sgm`: those of the library.
pub use sgm::SgmParams as Params;

/// The node.
pub struct SgmNode {
    params: sgm::SgmParams,
    /// The GPU kernels with `device` = "gpu" (or "auto" with an adapter).
    gpu: Option<(Arc<GpuContext>, gpu::SgmGpu)>,
    scratch: sgm::Scratch,
    gray_l: Vec<u8>,
    gray_r: Vec<u8>,
    /// Frames whose scene outgrew the disparity range.
    range: DisparityRangeWatch,
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
        let data = match &mut self.gpu {
            Some((ctx, kernels)) => {
                let (d, t) =
                    kernels.run(ctx, &self.gray_l, &self.gray_r, w, h, mask, &self.params)?;
                tracing::debug!("depth.sgm on the GPU: {t:?}");
                d
            }
            None => sgm::sgm(
                &self.gray_l,
                &self.gray_r,
                w,
                h,
                mask,
                &self.params,
                &mut self.scratch,
            )?,
        };
        Ok(FloatMap {
            width: w as u32,
            height: h as u32,
            data,
        })
    }
}

impl Node for SgmNode {
    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        ctx.report_eval("depth.range_saturated_frames", self.range.frames as f64);
        Ok(())
    }

    fn process(
        &mut self,
        ctx: &mut NodeContext,
        frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let pair = inputs.get::<StereoFrame>("stereo")?;
        let map = self.disparity(pair).map_err(NodeError::msg)?;
        let top = self.params.min_disparity as f32 + self.params.max_disparity as f32 - 1.0;
        self.range
            .check(frame.index, &map, top, ctx.id, "max_disparity");
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
pub fn build(params: Params, ctx: &BuildContext) -> Result<SgmNode, BuildError> {
    params.validate().map_err(|m| BuildError::Param {
        key: None,
        path: String::new(),
        message: m,
    })?;
    let gpu = ctx
        .gpu
        .for_device(params.device, ctx.node_id)
        .map_err(|e| BuildError::param("device", e.to_string()))?
        .map(|c| {
            let k = gpu::SgmGpu::new(&c);
            (c, k)
        });
    if let Some((c, _)) = &gpu {
        gpu::check_exchange(&params, c).map_err(|m| BuildError::param("gpu_exchange", m))?;
    }
    Ok(SgmNode {
        gpu,
        params,
        scratch: sgm::Scratch::default(),
        gray_l: Vec::new(),
        gray_r: Vec::new(),
        range: DisparityRangeWatch::default(),
    })
}

/// Registers `depth.sgm`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "depth.sgm",
        "semi-global matching (census, 4/8 paths, sub-pixel, LR check, median, speckles) on the CPU (SIMD) or the GPU (WGSL)",
        vec![PortSpec::new("stereo", PortType::Stereo, "rectified pair; its left mask is honoured")],
        vec![
            PortSpec::new("disparity", PortType::Disparity, "left disparity, px, NaN invalid"),
            PortSpec::new("depth", PortType::Depth, "left depth, mm, NaN invalid"),
        ],
        build,
    ))
}
