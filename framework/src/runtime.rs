//! The scheduler: builds the nodes of a validated graph and runs them frame by frame.
//!
//! Per frame, nodes run level by level in dependency order; nodes of one level are independent
//! and run in parallel (rayon) when the graph allows it. Payloads move between nodes as `Arc`s.
//! Every node's wall time is collected. A node error or panic on a frame follows the graph's
//! policy (abort, or skip the frame); no panic escapes. `finish` runs on every node even after an
//! abort, and `metrics.json` is always written, so no measurement is lost.

use std::collections::BTreeMap;
use std::ops::Range;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::{Path, PathBuf};
use std::time::Instant;

use rayon::prelude::*;

use crate::gpu::GpuProvider;
use crate::graph::{ErrorPolicy, Graph, Source};
use crate::metrics::{FrameCounts, RunMetrics, SkippedFrame, TimingStats};
use crate::node::{Flow, FrameInfo, Inputs, Node, NodeContext, NodeResult, Outputs, PortSpec};
use crate::payload::Payload;
use crate::recorder::{Recorder, RecorderError};
use crate::registry::{BuildContext, BuildError};

/// Why a run could not start or had to stop.
#[derive(Debug, thiserror::Error)]
pub enum RunError {
    /// A node could not be built from its parameters.
    #[error("{file}: node `{node}` ({plugin}): {error}")]
    Build {
        /// Graph file.
        file: PathBuf,
        /// Node id.
        node: String,
        /// Plugin id.
        plugin: String,
        /// Cause.
        error: Box<BuildError>,
    },
    /// A node failed in `start` or `finish`.
    #[error("node `{node}` failed in {phase}: {message}")]
    Lifecycle {
        /// Node id.
        node: String,
        /// `start` or `finish`.
        phase: &'static str,
        /// Cause.
        message: String,
    },
    /// A node failed on a frame and the policy is `abort`.
    #[error("frame {frame}: node `{node}`: {message}")]
    Frame {
        /// Frame index.
        frame: u64,
        /// Node id.
        node: String,
        /// Cause.
        message: String,
    },
    /// The output folder or `metrics.json` could not be written.
    #[error("{path}: {source}")]
    Io {
        /// Path.
        path: PathBuf,
        /// Cause.
        source: std::io::Error,
    },
    /// The recording failed.
    #[error(transparent)]
    Recorder(#[from] RecorderError),
}

/// Called after each frame with (frames done, frames planned if known).
pub type ProgressFn = Box<dyn FnMut(u64, Option<u64>) + Send>;

/// Options of one run.
#[derive(Default)]
pub struct RunOptions {
    /// Output folder (the graph's `out` when `None`).
    pub out_dir: Option<PathBuf>,
    /// Frame count limit overriding the graph's `frames.count`.
    pub frames: Option<u64>,
    /// Recording, if any.
    pub recorder: Option<Recorder>,
    /// Called after each frame with (frames done, frames planned if known).
    pub progress: Option<ProgressFn>,
}

/// The result of a run: what it measured, and the error it stopped on (if any).
pub struct RunReport {
    /// Everything written to `metrics.json`.
    pub metrics: RunMetrics,
    /// Where `metrics.json` was written.
    pub metrics_path: PathBuf,
    /// The error that aborted the run, if any (metrics were written anyway).
    pub error: Option<RunError>,
}

struct Slot {
    id: String,
    node: Box<dyn Node>,
    in_specs: Vec<PortSpec>,
    out_specs: Vec<PortSpec>,
    sources: Vec<Option<Source>>,
    inputs: Vec<Option<Payload>>,
    outputs: Vec<Option<Payload>>,
    log: bool,
    times_ms: Vec<f64>,
    eval: BTreeMap<String, f64>,
    stages: BTreeMap<String, Vec<f64>>,
    last: Option<Result<Flow, String>>,
}

/// A graph with its nodes built, ready to run.
pub struct Runtime {
    graph: Graph,
    slots: Vec<Slot>,
    levels: Vec<Range<usize>>,
    gpu: GpuProvider,
}

impl Runtime {
    /// Builds every node of the graph (parameters parsed, files opened, devices requested).
    pub fn build(graph: Graph) -> Result<Self, RunError> {
        let gpu = GpuProvider::new();
        let mut slots = Vec::with_capacity(graph.nodes.len());
        for spec in &graph.nodes {
            let info = spec.plugin.info();
            let ctx = BuildContext {
                node_id: &spec.id,
                graph_dir: graph.dir(),
                seed: graph.seed,
                gpu: &gpu,
            };
            let built = catch_unwind(AssertUnwindSafe(|| spec.plugin.build(&spec.params, &ctx)))
                .unwrap_or_else(|p| {
                    Err(BuildError::Failed(format!(
                        "panicked: {}",
                        misslam_abi::panic_message(p.as_ref())
                    )))
                });
            let node = built.map_err(|error| RunError::Build {
                file: graph.file.clone(),
                node: spec.id.clone(),
                plugin: info.id.clone(),
                error: Box::new(error),
            })?;
            slots.push(Slot {
                id: spec.id.clone(),
                node,
                in_specs: info.inputs.clone(),
                out_specs: info.outputs.clone(),
                sources: spec.inputs.clone(),
                inputs: vec![None; info.inputs.len()],
                outputs: vec![None; info.outputs.len()],
                log: spec.log,
                times_ms: Vec::new(),
                eval: BTreeMap::new(),
                stages: BTreeMap::new(),
                last: None,
            });
        }
        // Nodes are sorted by level: each level is a contiguous range.
        let mut levels: Vec<Range<usize>> = Vec::new();
        for (i, spec) in graph.nodes.iter().enumerate() {
            match levels.last_mut() {
                Some(r) if graph.nodes[r.start].level == spec.level => r.end = i + 1,
                _ => levels.push(i..i + 1),
            }
        }
        Ok(Runtime {
            graph,
            slots,
            levels,
            gpu,
        })
    }

    /// The graph.
    pub fn graph(&self) -> &Graph {
        &self.graph
    }

    /// Runs the graph to the end of its input or frame range. Node errors under `abort`, start
    /// and finish failures are returned in [`RunReport::error`]; `Err` only when nothing could be
    /// written at all.
    pub fn run(mut self, mut opts: RunOptions) -> Result<RunReport, RunError> {
        let started = Instant::now();
        let out_dir = opts
            .out_dir
            .clone()
            .unwrap_or_else(|| self.graph.out.clone());
        std::fs::create_dir_all(&out_dir).map_err(|source| RunError::Io {
            path: out_dir.clone(),
            source,
        })?;
        let mut recorder = opts.recorder.take();
        if let Some(r) = &recorder {
            r.log_graph(&self.graph)?;
        }
        let limit = opts.frames.or(self.graph.frames.count);
        let graph_dir = self.graph.dir().to_owned();
        let seed = self.graph.seed;

        let mut counts = FrameCounts::default();
        let mut frame_ms = Vec::new();
        let mut rerun_ms = Vec::new();
        let mut error: Option<RunError> = None;

        // start
        for slot in &mut self.slots {
            let mut ctx = node_ctx(
                &slot.id,
                &out_dir,
                &graph_dir,
                seed,
                &self.gpu,
                &mut slot.eval,
                &mut slot.stages,
            );
            if let Err(message) = guarded(|| slot.node.start(&mut ctx)) {
                error = Some(RunError::Lifecycle {
                    node: slot.id.clone(),
                    phase: "start",
                    message,
                });
                break;
            }
        }

        let mut ordinal = 0u64;
        while error.is_none() && limit.is_none_or(|n| ordinal < n) {
            let frame = FrameInfo {
                index: self.graph.frames.start + ordinal,
                ordinal,
            };
            let t0 = Instant::now();
            match self.run_frame(frame, &out_dir, &graph_dir, seed) {
                FrameOutcome::Done => {
                    frame_ms.push(t0.elapsed().as_secs_f64() * 1e3);
                    counts.processed += 1;
                    if let Some(r) = recorder.as_mut() {
                        let t1 = Instant::now();
                        if let Err(e) = self.log_frame(r, frame.index) {
                            error = Some(e.into());
                        }
                        rerun_ms.push(t1.elapsed().as_secs_f64() * 1e3);
                    }
                }
                FrameOutcome::EndOfStream => break,
                FrameOutcome::Failed { node, message } => match self.graph.on_error {
                    ErrorPolicy::Abort => {
                        error = Some(RunError::Frame {
                            frame: frame.index,
                            node,
                            message,
                        });
                    }
                    ErrorPolicy::SkipFrame => {
                        tracing::warn!(
                            "frame {}: node `{node}`: {message}; frame skipped",
                            frame.index
                        );
                        counts.skipped += 1;
                        counts.skipped_frames.push(SkippedFrame {
                            frame: frame.index,
                            node,
                            error: message,
                        });
                    }
                },
            }
            for slot in &mut self.slots {
                slot.outputs.iter_mut().for_each(|o| *o = None);
                slot.inputs.iter_mut().for_each(|i| *i = None);
            }
            ordinal += 1;
            if let Some(p) = opts.progress.as_mut() {
                p(ordinal, limit);
            }
        }

        // finish: always, so exports and evaluation summaries are not lost.
        for slot in &mut self.slots {
            let mut ctx = node_ctx(
                &slot.id,
                &out_dir,
                &graph_dir,
                seed,
                &self.gpu,
                &mut slot.eval,
                &mut slot.stages,
            );
            if let Err(message) = guarded(|| slot.node.finish(&mut ctx)) {
                tracing::error!("node `{}` failed in finish: {message}", slot.id);
                if error.is_none() {
                    error = Some(RunError::Lifecycle {
                        node: slot.id.clone(),
                        phase: "finish",
                        message,
                    });
                }
            }
        }
        if let Some(r) = &recorder {
            if let Err(e) = r.flush() {
                tracing::error!("{e}");
                error.get_or_insert(e.into());
            }
        }

        let mut metrics = RunMetrics {
            graph: self.graph.name.clone(),
            graph_file: self.graph.file.display().to_string(),
            overrides: self.graph.overrides.clone(),
            frames: counts,
            wall_s: started.elapsed().as_secs_f64(),
            aborted: error.as_ref().map(|e| e.to_string()),
            ..Default::default()
        };
        for (slot, spec) in self.slots.iter().zip(&self.graph.nodes) {
            metrics
                .timing_ms
                .insert(slot.id.clone(), TimingStats::from_samples(&slot.times_ms));
            for (k, v) in &slot.eval {
                metrics.eval.insert(k.clone(), *v);
            }
            for (stage, samples) in &slot.stages {
                metrics.timing_ms.insert(
                    format!("{}.{stage}", slot.id),
                    TimingStats::from_samples(samples),
                );
            }
            let params = serde_json::to_value(&spec.params).unwrap_or(serde_json::Value::Null);
            metrics.params.insert(slot.id.clone(), params);
        }
        metrics
            .timing_ms
            .insert("_frame".into(), TimingStats::from_samples(&frame_ms));
        if !rerun_ms.is_empty() {
            metrics
                .timing_ms
                .insert("_rerun".into(), TimingStats::from_samples(&rerun_ms));
        }
        let metrics_path = out_dir.join("metrics.json");
        let json = serde_json::to_string_pretty(&metrics).map_err(|e| RunError::Io {
            path: metrics_path.clone(),
            source: std::io::Error::other(e),
        })?;
        std::fs::write(&metrics_path, json).map_err(|source| RunError::Io {
            path: metrics_path.clone(),
            source,
        })?;
        Ok(RunReport {
            metrics,
            metrics_path,
            error,
        })
    }

    fn run_frame(
        &mut self,
        frame: FrameInfo,
        out_dir: &Path,
        graph_dir: &Path,
        seed: u64,
    ) -> FrameOutcome {
        let parallel = self.graph.parallel;
        let gpu = &self.gpu;
        for level in self.levels.clone() {
            let (done, current) = self.slots.split_at_mut(level.start);
            let current = &mut current[..level.len()];
            for slot in current.iter_mut() {
                for (input, src) in slot.inputs.iter_mut().zip(&slot.sources) {
                    *input = src.and_then(|s| done[s.node].outputs[s.port].clone());
                }
            }
            let run_one = |slot: &mut Slot| {
                let mut ctx = node_ctx(
                    &slot.id,
                    out_dir,
                    graph_dir,
                    seed,
                    gpu,
                    &mut slot.eval,
                    &mut slot.stages,
                );
                let inputs = Inputs {
                    specs: &slot.in_specs,
                    values: &slot.inputs,
                };
                let mut outputs = Outputs {
                    specs: &slot.out_specs,
                    values: &mut slot.outputs,
                };
                let t = Instant::now();
                let node = &mut slot.node;
                let mut result = guarded(|| node.process(&mut ctx, frame, &inputs, &mut outputs));
                let ms = t.elapsed().as_secs_f64() * 1e3;
                if let Ok(Flow::Continue) = result {
                    if let Some(missing) = slot
                        .out_specs
                        .iter()
                        .zip(slot.outputs.iter())
                        .find(|(s, v)| !s.optional && v.is_none())
                    {
                        result = Err(format!("did not produce its output `{}`", missing.0.name));
                    }
                    slot.times_ms.push(ms);
                }
                slot.last = Some(result);
            };
            if parallel && current.len() > 1 {
                current.par_iter_mut().for_each(run_one);
            } else {
                current.iter_mut().for_each(run_one);
            }
            for slot in current.iter_mut() {
                match slot.last.take() {
                    Some(Ok(Flow::Continue)) | None => {}
                    Some(Ok(Flow::EndOfStream)) => return FrameOutcome::EndOfStream,
                    Some(Err(message)) => {
                        return FrameOutcome::Failed {
                            node: slot.id.clone(),
                            message,
                        }
                    }
                }
            }
        }
        FrameOutcome::Done
    }

    fn log_frame(&self, rec: &mut Recorder, frame: u64) -> Result<(), RecorderError> {
        let input_time = self
            .slots
            .iter()
            .flat_map(|s| s.outputs.iter().flatten())
            .find_map(|p| match p {
                Payload::Stereo(s) => Some(s.timestamp),
                _ => None,
            });
        rec.begin_frame(frame, input_time);
        for slot in &self.slots {
            if let Some(ms) = slot.times_ms.last() {
                rec.log_timing(&slot.id, *ms)?;
            }
            if !slot.log {
                continue;
            }
            for (spec, value) in slot.out_specs.iter().zip(&slot.outputs) {
                if let Some(p) = value {
                    rec.log_payload(&format!("{}/{}", slot.id, spec.name), p)?;
                }
            }
        }
        Ok(())
    }
}

enum FrameOutcome {
    Done,
    EndOfStream,
    Failed { node: String, message: String },
}

fn node_ctx<'a>(
    id: &'a str,
    out_dir: &'a Path,
    graph_dir: &'a Path,
    seed: u64,
    gpu: &'a GpuProvider,
    eval: &'a mut BTreeMap<String, f64>,
    stages: &'a mut BTreeMap<String, Vec<f64>>,
) -> NodeContext<'a> {
    NodeContext {
        id,
        out_dir,
        graph_dir,
        seed,
        gpu,
        eval,
        stages,
    }
}

/// Runs a node call, turning an error or a panic into a message.
fn guarded<T>(f: impl FnOnce() -> NodeResult<T>) -> Result<T, String> {
    match catch_unwind(AssertUnwindSafe(f)) {
        Ok(Ok(v)) => Ok(v),
        Ok(Err(e)) => Err(e.to_string()),
        Err(p) => Err(format!(
            "panicked: {}",
            misslam_abi::panic_message(p.as_ref())
        )),
    }
}
