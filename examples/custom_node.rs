//! A custom node in ten lines of logic: a plugin with typed parameters, registered beside the
//! built-in ones, wired in a graph written inline, run, and its evaluation figure read back.
//!
//! `cargo run --example custom_node`

use std::path::Path;

use misslam::framework::{
    graph, BuildContext, Flow, FrameInfo, Image, Inputs, Metrics, Node, NodeContext, NodeResult,
    Outputs, PortSpec, PortType, RunOptions, Runtime, TypedPlugin,
};

/// Parameters of `example.brightness` (docs come from these comments: `misslam plugins` shows them).
#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema)]
#[serde(deny_unknown_fields, default)]
struct BrightnessParams {
    /// Pixels at or below this value are not counted (the black border).
    floor: u8,
}

impl Default for BrightnessParams {
    fn default() -> Self {
        BrightnessParams { floor: 8 }
    }
}

/// Mean intensity of the image above `floor`, per frame and over the run.
struct Brightness {
    floor: u8,
    sum: f64,
    frames: u32,
}

impl Node for Brightness {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inputs: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let img = inputs.get::<Image>("image")?;
        let lit: Vec<f64> = img
            .data
            .iter()
            .filter(|&&v| v > self.floor)
            .map(|&v| v as f64)
            .collect();
        let mean = if lit.is_empty() {
            0.0
        } else {
            lit.iter().sum::<f64>() / lit.len() as f64
        };
        self.sum += mean;
        self.frames += 1;
        let mut m = Metrics::default();
        m.values.insert("brightness".into(), mean);
        outputs.put("metrics", m)?;
        Ok(Flow::Continue)
    }

    fn finish(&mut self, ctx: &mut NodeContext) -> NodeResult<()> {
        ctx.report_eval(
            "example.brightness_mean",
            self.sum / self.frames.max(1) as f64,
        );
        Ok(())
    }
}

/// A source of synthetic gray ramps, so the example needs no data.
#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
#[serde(deny_unknown_fields)]
struct RampParams {}

struct Ramp;

impl Node for Ramp {
    fn process(
        &mut self,
        _: &mut NodeContext,
        f: FrameInfo,
        _: &Inputs,
        outputs: &mut Outputs,
    ) -> NodeResult<Flow> {
        let data = (0..64 * 48)
            .map(|i| ((i % 64) * 4 + f.index as usize) as u8)
            .collect();
        outputs.put(
            "image",
            Image {
                width: 64,
                height: 48,
                channels: 1,
                data,
            },
        )?;
        Ok(Flow::Continue)
    }
}

const GRAPH: &str = r#"
[graph]
name = "custom_node"
frames = { count = 10 }

[[node]]
id = "ramp"
plugin = "example.ramp"

[[node]]
id = "bright"
plugin = "example.brightness"
inputs = { image = "ramp.image" }
params = { floor = 16 }
"#;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut registry = misslam::builtin_registry();
    registry.register(TypedPlugin::new(
        "example.ramp",
        "synthetic gray ramps",
        vec![],
        vec![PortSpec::new("image", PortType::Image, "64x48 ramp")],
        |_: RampParams, _: &BuildContext| Ok(Ramp),
    ))?;
    registry.register(TypedPlugin::new(
        "example.brightness",
        "mean intensity above a floor",
        vec![PortSpec::new("image", PortType::Image, "any image")],
        vec![PortSpec::new(
            "metrics",
            PortType::Metrics,
            "`brightness` per frame",
        )],
        |p: BrightnessParams, _: &BuildContext| {
            Ok(Brightness {
                floor: p.floor,
                sum: 0.0,
                frames: 0,
            })
        },
    ))?;
    print!(
        "{}",
        registry.describe("example.brightness").unwrap_or_default()
    );
    let g = graph::parse(Path::new("custom_node.toml"), GRAPH, &registry, &[])?;
    let out = std::env::temp_dir().join("misslam-example-custom-node");
    let report = Runtime::build(g)?.run(RunOptions {
        out_dir: Some(out),
        ..Default::default()
    })?;
    print!("{}", report.metrics.summary_table());
    Ok(())
}
