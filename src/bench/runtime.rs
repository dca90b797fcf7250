//! `misslam bench runtime-overhead`: the scheduler's own cost per node per frame, measured on
//! graphs of trivial nodes (a source and a chain or a fan of pass-through nodes that only clone
//! an `Arc`), so that what is measured is input gathering, timing, error handling and output
//! checks, not work. The budget is 50 microseconds per node per frame.

use std::path::Path;
use std::time::Instant;

use misslam_framework::graph;
use misslam_framework::{
    BuildContext, Flow, FrameInfo, Image, Inputs, Node, NodeContext, NodeResult, Outputs, PortSpec,
    PortType, Registry, RunOptions, Runtime, TypedPlugin,
};
use serde::Serialize;

#[derive(serde::Serialize, serde::Deserialize, schemars::JsonSchema, Default)]
#[serde(deny_unknown_fields)]
struct NoParams {}

struct Source {
    image: std::sync::Arc<Image>,
}

impl Node for Source {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        _: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        out.put_arc("image", self.image.clone())?;
        Ok(Flow::Continue)
    }
}

struct Pass;

impl Node for Pass {
    fn process(
        &mut self,
        _: &mut NodeContext,
        _: FrameInfo,
        inp: &Inputs,
        out: &mut Outputs,
    ) -> NodeResult<Flow> {
        let img = inp.get::<Image>("image")?;
        out.put_arc("image", img.clone())?;
        Ok(Flow::Continue)
    }
}

fn registry() -> Registry {
    let mut r = Registry::new();
    let image = std::sync::Arc::new(Image {
        width: 64,
        height: 48,
        channels: 1,
        data: vec![0; 64 * 48],
    });
    let _ = r.register(TypedPlugin::new(
        "bench.source",
        "a shared image every frame",
        vec![],
        vec![PortSpec::new("image", PortType::Image, "")],
        move |_: NoParams, _: &BuildContext| {
            Ok(Source {
                image: image.clone(),
            })
        },
    ));
    let _ = r.register(TypedPlugin::new(
        "bench.pass",
        "passes its input on",
        vec![PortSpec::new("image", PortType::Image, "")],
        vec![PortSpec::new("image", PortType::Image, "")],
        |_: NoParams, _: &BuildContext| Ok(Pass),
    ));
    r
}

/// One measured configuration.
#[derive(Debug, Serialize)]
pub struct OverheadRow {
    /// `chain` (each node feeds the next) or `fan` (every node reads the source: one level).
    pub shape: String,
    /// Pass-through nodes (the source not counted).
    pub nodes: usize,
    /// Frames run.
    pub frames: u64,
    /// Whether a level's nodes ran in parallel.
    pub parallel: bool,
    /// Frames in the graph at once (`graph.pipeline`; above 1, a thread per level).
    pub pipeline: u32,
    /// Wall time per frame, microseconds.
    pub frame_us: f64,
    /// Wall time per node per frame, microseconds (everything: the nodes do no work).
    pub per_node_us: f64,
    /// `per_node_us` / 50 us budget.
    pub budget_ratio: f64,
}

fn graph_text(shape: &str, nodes: usize, parallel: bool, pipeline: u32) -> String {
    let mut t = format!("[graph]\nname = \"overhead\"\nparallel = {parallel}\npipeline = {pipeline}\n\n[[node]]\nid = \"src\"\nplugin = \"bench.source\"\n");
    for i in 0..nodes {
        let from = if shape == "chain" && i > 0 {
            format!("n{}", i - 1)
        } else {
            "src".into()
        };
        t.push_str(&format!(
            "\n[[node]]\nid = \"n{i}\"\nplugin = \"bench.pass\"\ninputs = {{ image = \"{from}.image\" }}\n"
        ));
    }
    t
}

/// Runs every configuration and returns the rows.
pub fn runtime_overhead(
    nodes: usize,
    frames: u64,
    out_dir: &Path,
) -> Result<Vec<OverheadRow>, String> {
    let reg = registry();
    let mut rows = Vec::new();
    // The last row runs the chain as a pipeline: every node is a level of its own, with a thread
    // each, so it measures the hand-over of a frame from one thread to the next.
    for (shape, parallel, pipeline) in [
        ("chain", false, 1),
        ("fan", false, 1),
        ("fan", true, 1),
        ("chain", false, 4),
    ] {
        let text = graph_text(shape, nodes, parallel, pipeline);
        let g = graph::parse(Path::new("overhead.toml"), &text, &reg, &[])
            .map_err(|e| e.to_string())?;
        let rt = Runtime::build(g).map_err(|e| e.to_string())?;
        let t = Instant::now();
        let report = rt
            .run(RunOptions {
                out_dir: Some(out_dir.to_owned()),
                frames: Some(frames),
                ..Default::default()
            })
            .map_err(|e| e.to_string())?;
        if let Some(e) = report.error {
            return Err(e.to_string());
        }
        let frame_us = t.elapsed().as_secs_f64() * 1e6 / frames as f64;
        let per_node_us = frame_us / (nodes + 1) as f64;
        rows.push(OverheadRow {
            shape: shape.into(),
            nodes,
            frames,
            parallel,
            pipeline,
            frame_us,
            per_node_us,
            budget_ratio: per_node_us / 50.0,
        });
    }
    Ok(rows)
}
