//! `image.gray`: RGB to BT.601 gray, on the CPU or on the GPU through WGSL
//! (`shaders/image/gray.wgsl`); the two are bit-exact.
#![deny(missing_docs)]

use std::sync::Arc;

use misslam_framework::gpu::GrayKernel;
use misslam_framework::{
    BuildContext, Device, Flow, FrameInfo, GpuContext, Image, Inputs, Node, NodeContext, NodeError,
    NodeResult, Outputs, PortSpec, PortType, Registry, TypedPlugin,
};

/// Parameters of `image.gray`.
#[derive(Clone, Debug, Default, serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
pub struct Params {
    /// Where to compute: "cpu", "gpu" (error without an adapter) or "auto" (GPU when present).
    pub device: Device,
}

/// The node.
pub struct GrayNode {
    gpu: Option<(Arc<GpuContext>, GrayKernel)>,
}

impl GrayNode {
    /// Converts one image (gray images pass through shared).
    pub fn convert(&self, img: &Arc<Image>) -> NodeResult<Arc<Image>> {
        if img.channels == 1 {
            return Ok(img.clone());
        }
        let data = match &self.gpu {
            Some((ctx, kernel)) => kernel.run(ctx, &img.data)?,
            None => {
                let mut out = Vec::new();
                img.gray_into(&mut out);
                out
            }
        };
        Ok(Arc::new(
            Image::new(img.width, img.height, 1, data).map_err(NodeError::msg)?,
        ))
    }
}

impl Node for GrayNode {
    fn process(
        &mut self,
        _ctx: &mut NodeContext,
        _frame: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let img = inputs.get::<Image>("image")?;
        outputs.put_arc("gray", self.convert(img)?)?;
        Ok(Flow::Continue)
    }
}

/// Builds the node directly (without a graph).
pub fn build(p: Params, ctx: &BuildContext) -> Result<GrayNode, misslam_framework::BuildError> {
    let gpu = ctx
        .gpu
        .for_device(p.device, ctx.node_id)
        .map_err(|e| misslam_framework::BuildError::Failed(e.to_string()))?;
    Ok(GrayNode {
        gpu: gpu.map(|c| {
            let k = GrayKernel::new(&c);
            (c, k)
        }),
    })
}

/// Registers `image.gray`.
pub fn register(registry: &mut Registry) -> Result<(), String> {
    registry.register(TypedPlugin::new(
        "image.gray",
        "RGB to BT.601 gray on the CPU or the GPU (bit-exact)",
        vec![PortSpec::new("image", PortType::Image, "RGB or gray image")],
        vec![PortSpec::new("gray", PortType::Image, "one-channel image")],
        build,
    ))
}
