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

mod pipeline;

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
    #[error("{path}: {cause}")]
    Io {
        /// Path.
        path: PathBuf,
        /// Cause, in the message (not a `source`, so that an error chain prints it once).
        cause: std::io::Error,
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

pub(crate) struct Slot {
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
    last_ms: Option<f64>,
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
                last_ms: None,
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
        std::fs::create_dir_all(&out_dir).map_err(|cause| RunError::Io {
            path: out_dir.clone(),
            cause,
        })?;
        let mut recorder = opts.recorder.take();
        if let Some(r) = &mut recorder {
            r.set_log_every(self.graph.log_every);
            r.log_graph(&self.graph)?;
        }
        let limit = opts.frames.or(self.graph.frames.count);
        let graph_dir = self.graph.dir().to_owned();
        let seed = self.graph.seed;

        let mut counts = FrameCounts::default();
        let mut frame_ms = Vec::new();
        let mut interval_ms = Vec::new();
        let mut rerun_ms = Vec::new();
        let mut error: Option<RunError> = None;
        let pipelined = self.graph.pipeline > 1 && self.levels.len() > 1;
        let level_threads = self.graph.level_pool_threads(rayon::current_num_threads());
        let level_pools: Vec<usize> = if pipelined {
            self.levels
                .iter()
                .map(|l| self.graph.level_pool_threads_of(l.clone(), level_threads))
                .collect()
        } else {
            Vec::new()
        };
        let level_nice: Vec<u32> = if pipelined {
            self.levels
                .iter()
                .map(|l| self.graph.level_pool_nice_of(l.clone()))
                .collect()
        } else {
            Vec::new()
        };

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

        if error.is_none() {
            let env = Env {
                out_dir: &out_dir,
                graph_dir: &graph_dir,
                seed,
                gpu: &self.gpu,
                parallel: self.graph.parallel,
            };
            let mut collector = Collector {
                policy: self.graph.on_error,
                logged: self
                    .slots
                    .iter()
                    .map(|s| (s.id.clone(), s.out_specs.clone(), s.log))
                    .collect(),
                recorder: recorder.as_mut(),
                progress: opts.progress.as_mut(),
                limit,
                counts: &mut counts,
                frame_ms: &mut frame_ms,
                interval_ms: &mut interval_ms,
                rerun_ms: &mut rerun_ms,
                error: &mut error,
                last_done: None,
                ordinal: 0,
            };
            let frames = Frames {
                start: self.graph.frames.start,
                limit,
                outputs: self.slots.iter().map(|s| s.out_specs.len()).collect(),
            };
            if pipelined {
                let schedule = pipeline::Schedule {
                    levels: &self.levels,
                    frames: &frames,
                    in_flight: self.graph.pipeline,
                    level_threads: &level_pools,
                    level_nice: &level_nice,
                    policy: self.graph.on_error,
                };
                pipeline::run(&mut self.slots, &schedule, &env, &mut collector);
            } else {
                let mut ordinal = 0u64;
                while frames.limit.is_none_or(|n| ordinal < n) {
                    let mut state = frames.state(ordinal);
                    for level in &self.levels {
                        run_level(
                            &mut self.slots[level.clone()],
                            level.start,
                            &mut state,
                            &env,
                        );
                        if !matches!(state.outcome, FrameOutcome::Done) {
                            break;
                        }
                    }
                    if collector.take(state) {
                        break;
                    }
                    ordinal += 1;
                }
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

        if error.is_none() && counts.processed == 0 {
            let start = self.graph.frames.start;
            if counts.skipped > 0 {
                tracing::warn!(
                    "no frame was processed: {} skipped (see the warnings above)",
                    counts.skipped
                );
            } else {
                tracing::warn!(
                    "no frame was processed: the source gave none from frame {start} on (`graph.frames.start`; is it past the sequence's end?)"
                );
            }
        }
        let mut metrics = RunMetrics {
            graph: self.graph.name.clone(),
            graph_file: self.graph.file.display().to_string(),
            overrides: self.graph.overrides.clone(),
            frames: counts,
            wall_s: started.elapsed().as_secs_f64(),
            aborted: error.as_ref().map(|e| e.to_string()),
            pipeline: if pipelined { self.graph.pipeline } else { 1 },
            level_threads: if pipelined { level_threads } else { 0 },
            level_pools,
            level_nice,
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
            let params = spec
                .plugin
                .resolved_params(&spec.params)
                .unwrap_or_else(|| {
                    serde_json::to_value(&spec.params).unwrap_or(serde_json::Value::Null)
                });
            metrics.params.insert(slot.id.clone(), params);
        }
        metrics
            .timing_ms
            .insert("_frame".into(), TimingStats::from_samples(&frame_ms));
        metrics
            .timing_ms
            .insert("_interval".into(), TimingStats::from_samples(&interval_ms));
        if !rerun_ms.is_empty() {
            metrics
                .timing_ms
                .insert("_rerun".into(), TimingStats::from_samples(&rerun_ms));
        }
        let metrics_path = out_dir.join("metrics.json");
        let json = serde_json::to_string_pretty(&metrics).map_err(|e| RunError::Io {
            path: metrics_path.clone(),
            cause: std::io::Error::other(e),
        })?;
        std::fs::write(&metrics_path, json).map_err(|cause| RunError::Io {
            path: metrics_path.clone(),
            cause,
        })?;
        Ok(RunReport {
            metrics,
            metrics_path,
            error,
        })
    }
}

/// How a frame ended.
pub(crate) enum FrameOutcome {
    Done,
    EndOfStream,
    Failed { node: String, message: String },
}

/// What every node call of a run shares.
pub(crate) struct Env<'a> {
    out_dir: &'a Path,
    graph_dir: &'a Path,
    seed: u64,
    gpu: &'a GpuProvider,
    parallel: bool,
}

/// The frames a run asks for.
pub(crate) struct Frames {
    start: u64,
    /// At most this many frames.
    pub(crate) limit: Option<u64>,
    /// Output ports per node.
    outputs: Vec<usize>,
}

impl Frames {
    /// The empty state of the frame with this ordinal.
    pub(crate) fn state(&self, ordinal: u64) -> FrameState {
        FrameState {
            info: FrameInfo {
                index: self.start + ordinal,
                ordinal,
            },
            outputs: self.outputs.iter().map(|&n| vec![None; n]).collect(),
            times_ms: vec![None; self.outputs.len()],
            outcome: FrameOutcome::Done,
            started: Instant::now(),
        }
    }
}

/// One frame on its way through the levels: what each node produced for it, how long each took,
/// and how the frame ended.
pub(crate) struct FrameState {
    pub(crate) info: FrameInfo,
    /// Per node (graph order), its outputs on this frame.
    outputs: Vec<Vec<Option<Payload>>>,
    /// Per node, its `process` time on this frame.
    times_ms: Vec<Option<f64>>,
    pub(crate) outcome: FrameOutcome,
    started: Instant,
}

/// Runs the nodes of one level (`slots`, the first being node `offset` of the graph) on a frame:
/// inputs from the frame's outputs of earlier levels, outputs into the frame. The first node (in
/// graph order) that fails or ends the stream decides the frame's outcome; the level's other
/// nodes have run, as in one level of the serial schedule.
pub(crate) fn run_level(slots: &mut [Slot], offset: usize, state: &mut FrameState, env: &Env) {
    for slot in slots.iter_mut() {
        for (input, src) in slot.inputs.iter_mut().zip(&slot.sources) {
            *input = src.and_then(|s| state.outputs[s.node][s.port].clone());
        }
    }
    let frame = state.info;
    let run_one = |slot: &mut Slot| {
        let mut ctx = node_ctx(
            &slot.id,
            env.out_dir,
            env.graph_dir,
            env.seed,
            env.gpu,
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
        slot.last_ms = None;
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
            slot.last_ms = Some(ms);
        }
        slot.last = Some(result);
    };
    if env.parallel && slots.len() > 1 {
        slots.par_iter_mut().for_each(run_one);
    } else {
        slots.iter_mut().for_each(run_one);
    }
    for (i, slot) in slots.iter_mut().enumerate() {
        slot.inputs.iter_mut().for_each(|x| *x = None);
        std::mem::swap(&mut slot.outputs, &mut state.outputs[offset + i]);
        state.times_ms[offset + i] = slot.last_ms.take();
        let outcome = match slot.last.take() {
            Some(Ok(Flow::Continue)) | None => continue,
            Some(Ok(Flow::EndOfStream)) => FrameOutcome::EndOfStream,
            Some(Err(message)) => FrameOutcome::Failed {
                node: slot.id.clone(),
                message,
            },
        };
        if matches!(state.outcome, FrameOutcome::Done) {
            state.outcome = outcome;
        }
    }
}

/// Takes the frames in order as they complete: counts them, applies the error policy, records
/// them and reports progress.
pub(crate) struct Collector<'a> {
    policy: ErrorPolicy,
    /// Per node: id, output ports, whether its outputs are recorded.
    logged: Vec<(String, Vec<PortSpec>, bool)>,
    recorder: Option<&'a mut Recorder>,
    progress: Option<&'a mut ProgressFn>,
    limit: Option<u64>,
    counts: &'a mut FrameCounts,
    frame_ms: &'a mut Vec<f64>,
    interval_ms: &'a mut Vec<f64>,
    rerun_ms: &'a mut Vec<f64>,
    error: &'a mut Option<RunError>,
    /// When the last completed frame arrived.
    last_done: Option<Instant>,
    /// Frames taken.
    ordinal: u64,
}

impl Collector<'_> {
    /// Takes the next frame; true when the run must stop (end of the stream, an abort, a
    /// recording error).
    pub(crate) fn take(&mut self, state: FrameState) -> bool {
        let mut stop = false;
        match state.outcome {
            FrameOutcome::Done => {
                let now = Instant::now();
                self.frame_ms
                    .push((now - state.started).as_secs_f64() * 1e3);
                if let Some(t) = self.last_done {
                    self.interval_ms.push((now - t).as_secs_f64() * 1e3);
                }
                self.last_done = Some(now);
                self.counts.processed += 1;
                if let Some(r) = self.recorder.as_deref_mut() {
                    let t1 = Instant::now();
                    if let Err(e) = log_frame(r, &self.logged, &state) {
                        *self.error = Some(e.into());
                        stop = true;
                    }
                    self.rerun_ms.push(t1.elapsed().as_secs_f64() * 1e3);
                }
            }
            FrameOutcome::EndOfStream => return true,
            FrameOutcome::Failed { node, message } => match self.policy {
                ErrorPolicy::Abort => {
                    *self.error = Some(RunError::Frame {
                        frame: state.info.index,
                        node,
                        message,
                    });
                    return true;
                }
                ErrorPolicy::SkipFrame => {
                    tracing::warn!(
                        "frame {}: node `{node}`: {message}; frame skipped",
                        state.info.index
                    );
                    self.counts.skipped += 1;
                    self.counts.skipped_frames.push(SkippedFrame {
                        frame: state.info.index,
                        node,
                        error: message,
                    });
                }
            },
        }
        self.ordinal += 1;
        if let Some(p) = self.progress.as_deref_mut() {
            p(self.ordinal, self.limit);
        }
        stop
    }
}

fn log_frame(
    rec: &mut Recorder,
    logged: &[(String, Vec<PortSpec>, bool)],
    state: &FrameState,
) -> Result<(), RecorderError> {
    let input_time = state
        .outputs
        .iter()
        .flatten()
        .flatten()
        .find_map(|p| match p {
            Payload::Stereo(s) => Some(s.timestamp),
            _ => None,
        });
    rec.begin_frame(state.info.index, input_time);
    for ((id, out_specs, log), (outputs, ms)) in
        logged.iter().zip(state.outputs.iter().zip(&state.times_ms))
    {
        if let Some(ms) = ms {
            rec.log_timing(id, *ms)?;
        }
        if !log {
            continue;
        }
        for (spec, value) in out_specs.iter().zip(outputs) {
            if let Some(p) = value {
                rec.log_payload(&format!("{id}/{}", spec.name), p)?;
            }
        }
    }
    Ok(())
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
